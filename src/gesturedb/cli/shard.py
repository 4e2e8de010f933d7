"""`gesturedb shard DB.h5 --parts N [-o INDEX.h5]`: split a database into shard files and an index file."""
from __future__ import annotations

from gesturedb.cli._args import int_range


def add_parser(sub) -> None:
    p = sub.add_parser(
        "shard",
        help="split a database into N shard files of whole recordings and an index file",
        description="Write N shard files holding the per-frame arrays of contiguous runs of whole recordings, and "
        "an index file (an ordinary database whose per-frame arrays are HDF5 virtual datasets over the shards). "
        "Every command accepts the index in place of the database; `synth --scheduler` loads each shard file on a "
        "worker. Keep the shard files beside the index (move them together).",
    )
    p.add_argument("db", metavar="DB.h5")
    p.add_argument("--parts", type=int_range(1, 65536), required=True,
                   help="number of shard files (at most the number of recordings)")
    p.add_argument("-o", "--output", metavar="INDEX.h5", default=None,
                   help="the index file (default: DB.index.h5 beside DB.h5; DB.h5 itself replaces it by an index)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=run)


def run(args) -> int:
    from gesturedb.db.shardfiles import describe, shard_database

    report = shard_database(args.db, args.parts, index=args.output, progress=not args.no_progress)
    print(describe(report))
    return 0
