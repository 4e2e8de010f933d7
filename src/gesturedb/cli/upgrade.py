"""`gesturedb upgrade DB.h5`: bring a database of an older schema up to date."""
from __future__ import annotations

from gesturedb.db.upgrade import upgrade


def add_parser(sub) -> None:
    p = sub.add_parser(
        "upgrade",
        help="bring a database written by an older gesturedb up to the current schema",
        description="Recompute, from what the file keeps (joint positions, clips, words), what the current schema "
        "has and the file's version lacks: the pose features centred on each frame (before version 4), the "
        "motion graphs (before version 3). The file is replaced only when the upgrade succeeds.",
    )
    p.add_argument("db", metavar="DB.h5")
    p.add_argument("--scheduler", default=None, metavar="local:N|tcp://HOST:PORT",
                   help="run a motion-graph edge search as Dask tasks (only when the graphs are recomputed)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run)


def run(args) -> int:
    s = upgrade(args.db, progress=not args.quiet, scheduler=args.scheduler)
    if not s["done"]:
        print(f"{args.db}: already schema version {s['to']}; nothing to do")
    else:
        print(f"{args.db}: schema version {s['from']} -> {s['to']}: recomputed " + "; ".join(s["done"]))
    return 0
