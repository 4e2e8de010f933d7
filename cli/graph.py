"""`gesturedb graph DB.h5`: add (or rebuild) the motion graph of an existing database."""
from __future__ import annotations


def add_parser(sub) -> None:
    p = sub.add_parser(
        "graph",
        help="add the GestureMaster motion graph and style predictor to a database",
        description="Compute the clip-to-clip transition costs, keep the edges under delta_T plus each clip's "
        "cheapest few, fit the style predictor, and store them in DB.h5 (a version-1 file is upgraded).",
    )
    p.add_argument("db", metavar="DB.h5")
    p.add_argument("--delta", type=float, default=None, dest="delta_T",
                   help="edge threshold on T (default: the 10%% quantile of the database's costs)")
    p.add_argument("--min-out", type=int, default=4, help="cheapest out-edges every clip keeps (default: 4)")
    p.set_defaults(run=run)


def run(args) -> int:
    from gesturedb.db.graph import add_graph

    s = add_graph(args.db, delta_T=args.delta_T, min_out=args.min_out)
    print(f"{args.db}: motion graph with {s['n_nodes']} clips, {s['n_edges']} edges (delta_T {s['delta_T']:.4g}); "
          f"style predictor held-out RMS {s['heldout_rmse']:.3f} vs {s['mean_rmse']:.3f} for the mean (in target std)")
    return 0
