"""`gesturedb build INPUT... -o DB.h5`"""
from __future__ import annotations

import sys

from gesturedb.cli._args import float_range, int_range
from gesturedb.db.build import build, pair_inputs, read_pairing_file
from gesturedb.db.cluster import check_scheduler
from gesturedb.errors import ParameterError
from gesturedb.features.pauses import DEFAULT_VAD, VAD_METHODS
from gesturedb.features.pose import POSE_WINDOW
from gesturedb.io.bvh import parse_length_unit
from gesturedb.io.joints import read_joint_map
from gesturedb.threads import available_cpus


def add_parser(sub) -> None:
    p = sub.add_parser(
        "build",
        help="build a gesture database from recordings",
        description="Pair motion (.bvh/.npz), speech (.wav/.flac) and transcripts (.TextGrid/.tsv/.json) by file stem "
        "and build a gesture database (HDF5).",
    )
    p.add_argument("inputs", nargs="*", metavar="INPUT", help="files or folders (paired by file stem)")
    p.add_argument("--pairs", default=None, metavar="PAIRS.csv",
                   help="a CSV file listing recordings: header motion,audio[,transcript,speaker,name]; "
                   "paths relative to the file")
    p.add_argument("-o", "--output", required=True, metavar="DB.h5")
    p.add_argument("-j", "--workers", type=int_range(1, 256), default=min(2, available_cpus()), help="processes (default: %(default)s)")
    p.add_argument("--scheduler", default=None, metavar="local:N|tcp://HOST:PORT",
                   help="process recordings and the motion graphs' edge search as Dask tasks (a LocalCluster of N "
                   "workers or a running scheduler); this process still writes the file")
    p.add_argument("-r", "--recursive", action="store_true", help="also take files in sub-folders")
    p.add_argument("--fps", type=float_range(1, 1000), default=15.0, help="database frame rate (default: %(default)s)")
    p.add_argument("--chunk-frames", type=int, default=None,
                   help="fixed chunk length, frames (default: 64/15 s in frames: 64 at 15 fps, 128 at 30 fps)")
    p.add_argument("--gap", type=_gap, default="auto", dest="gap_s",
                   help="word gap that splits clips, s, or 'auto' (clips of about 3 s from the speakers' own pauses; "
                   "default: %(default)s)")
    p.add_argument("--vad", choices=VAD_METHODS, default=DEFAULT_VAD,
                   help="recordings without a transcript: how pauses are found in the speech (default: %(default)s)")
    p.add_argument("--pose-window", type=int, default=POSE_WINDOW,
                   help="pose feature frames on each side of a frame, itself included (default: %(default)s)")
    p.add_argument("--pose-stride", type=int, default=None,
                   help="frames between the pose feature's frames (default: chosen from the recordings' own motion "
                        "timescale: 2 at 15 fps and 4 at 30 fps for the BEAT2 speaker, fewer for a faster one)")
    p.add_argument("--mirror", action="store_true", help="add left/right mirrored copies")
    p.add_argument("--speaker", default=None,
                   help="speaker name of every recording (default: a --pairs speaker column, BEAT's "
                   "<id>_<name>_... file names, else the folder name)")
    p.add_argument("--length-unit", default=None, metavar="cm|m|mm|inch|METRES",
                   help="length unit of the BVH files (default: guessed from the skeleton's height, "
                   "said in the report)")
    p.add_argument("--joint-map", default=None, metavar="JSON",
                   help='role -> joint name override, e.g. \'{"left_index1": "LeftHandThumb1"}\' or a .json file')
    p.add_argument("--max-mismatch", type=float, default=1.0, dest="max_mismatch_s",
                   help="largest audio/motion duration difference, s (default: %(default)s)")
    p.add_argument("--no-graph", action="store_true", help="skip the motion graph (add it later with `gesturedb graph`)")
    p.add_argument("-q", "--quiet", action="store_true", help="no pairing report or progress bar")
    p.set_defaults(run=run)


def _gap(text):
    return text if text == "auto" else float(text)


def _joint_map(text):
    return read_joint_map(text)


def run(args) -> int:
    if not args.inputs and not args.pairs:
        raise ParameterError("inputs: expected files or folders, or --pairs PAIRS.csv; got neither")
    if args.scheduler is not None:
        check_scheduler(args.scheduler)  # before the inputs are read (local:100000 started without limit)
    unit = None if args.length_unit is None else parse_length_unit(args.length_unit)
    listed = read_pairing_file(args.pairs) if args.pairs else []
    pairing = pair_inputs(args.inputs, recursive=args.recursive)
    pairing.recordings = sorted(pairing.recordings + listed, key=lambda r: r.name)
    # without recordings the build's error carries this report: print it once
    if not args.quiet and pairing.recordings:
        print(pairing.summary(), file=sys.stderr)
    db = build(
        list(args.inputs) + listed, args.output, workers=args.workers, recursive=args.recursive,
        progress=not args.quiet, length_unit_m=unit,
        scheduler=args.scheduler,
        fps=args.fps, chunk_frames=args.chunk_frames, gap_s=args.gap_s, pose_window=args.pose_window,
        pose_stride=args.pose_stride, mirror=args.mirror, speaker=args.speaker,
        joint_map=_joint_map(args.joint_map), max_mismatch_s=args.max_mismatch_s, graph=not args.no_graph, vad=args.vad,
    )
    if not args.quiet:
        for line in db.pairing.notes:
            print(line, file=sys.stderr)
    with db:
        print(f"wrote {args.output}: {len(db.recordings)} recording(s), {db.n_frames} frames "
              f"({db.n_frames / db.fps:.1f} s at {db.fps:g} fps), {len(db.chunks)} chunks, {len(db.clips)} clips")
    return 0
