"""`gesturedb graph DB.h5`: add (or rebuild) the motion graphs of an existing database."""
from __future__ import annotations

from gesturedb.db.graph import add_graph


def add_parser(sub) -> None:
    p = sub.add_parser(
        "graph",
        help="add the GestureMaster motion graphs (upper and lower body) and style predictor to a database",
        description="Compute the clip-to-clip transition costs of the upper body and of the lower body, keep the "
        "edges under delta_T plus each clip's cheapest few, fit the style predictor, and store them in DB.h5 "
        "(a file of an older schema: `gesturedb upgrade` first).",
    )
    p.add_argument("db", metavar="DB.h5")
    p.add_argument("--delta", type=float, default=None, dest="delta_T",
                   help="upper-body edge threshold on T (default: the 10%% quantile of the database's costs)")
    p.add_argument("--delta-lower", type=float, default=None, dest="delta_T_lower",
                   help="lower-body edge threshold on T (default: the 10%% quantile of its costs)")
    p.add_argument("--min-out", type=int, default=4, help="cheapest out-edges every clip keeps (default: 4)")
    p.add_argument("--scheduler", default=None, metavar="local:N|tcp://HOST:PORT",
                   help="run the edge search's blocks of rows as Dask tasks (a LocalCluster of N workers or a "
                   "running scheduler); the same graphs")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run)


def run(args) -> int:
    s = add_graph(args.db, delta_T=args.delta_T, delta_T_lower=args.delta_T_lower, min_out=args.min_out,
                  progress=not args.quiet, scheduler=args.scheduler)
    print(f"{args.db}: motion graphs over {s['n_nodes']} clips: upper body {s['n_edges']} edges (delta_T "
          f"{s['delta_T']:.4g}), lower body {s['n_edges_lower']} edges (delta_T {s['delta_T_lower']:.4g}); "
          f"style predictor held-out RMS {s['heldout_rmse']:.3f} vs {s['mean_rmse']:.3f} for the mean (in target std)")
    return 0
