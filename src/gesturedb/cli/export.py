"""`gesturedb export DB.h5 --recording NAME --start S --end E -o out.bvh|out.glb [--target-skeleton RIG]`"""
from __future__ import annotations

import gesturedb
from gesturedb.io import check_motion_output, write_motion
from gesturedb.io.outputs import check_outputs


def add_parser(sub) -> None:
    p = sub.add_parser("export", help="write a stretch of a recording in the database to BVH or glTF")
    p.add_argument("db", metavar="DB.h5")
    p.add_argument("--recording", required=True, help="recording name (see `gesturedb info`)")
    p.add_argument("--start", type=float, default=None, help="start time, s (default: 0)")
    p.add_argument("--end", type=float, default=None, help="end time, s (default: the end)")
    p.add_argument("-o", "--output", required=True, metavar="OUT.bvh|OUT.glb")
    from gesturedb.cli.retarget import add_target_options

    add_target_options(p)
    p.set_defaults(run=run)


def run(args) -> int:
    from gesturedb.cli.retarget import apply_target

    check_motion_output(args.output)
    check_outputs({"-o": args.output}, [args.db, args.target_skeleton])
    with gesturedb.open(args.db) as db:
        motion = db.motion(args.recording, args.start, args.end)
    motion = apply_target(args, motion)
    write_motion(args.output, motion)
    print(f"wrote {args.output}: {motion.rotations.shape[0]} frames at {motion.fps:g} fps")
    return 0
