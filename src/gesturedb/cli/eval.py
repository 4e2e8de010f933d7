"""`gesturedb eval controls|motion`: Table 2 of Habibie et al. 2022 and the objective metrics report.

    gesturedb eval controls DB.h5 --audio SPEECH.wav [--json out.json] [--md out.md] [--plot out.png] [--strict]
    gesturedb eval motion --data-dir DIR --holdout-start 48 --holdout-end 63.5 -o report/
    gesturedb eval motion DB.h5 --audio a.wav [--audio b.wav ...] -o report/
"""
from __future__ import annotations

import os
import sys

import gesturedb
from gesturedb.cli._args import add_init_argument, float_range
from gesturedb.errors import ParameterError
from gesturedb.eval.common import SYSTEM_LABELS, SYSTEMS, eval_options
from gesturedb.io.outputs import check_outputs
from gesturedb.synth.seams import SEAM_DECAY_S


def _search_options(p, *, preselect: bool) -> None:
    g = p.add_argument_group("search settings (the same for every synthesis)")
    g.add_argument("--k", type=int, default=1, help="take the k-th best candidate (default: 1)")
    if preselect:
        g.add_argument("--preselect", choices=("pose", "audio"), default="pose")
    add_init_argument(g)
    g.add_argument("--seed", type=int, default=0, help="seed of --init random and of the random baseline")
    g.add_argument("--step", type=int, default=None,
                   help="frames per search step N (default: 8/15 s in frames, 8 at 15 fps)")
    g.add_argument("--seam-decay", type=float_range(0, 60), default=SEAM_DECAY_S, dest="seam_decay_s", metavar="S",
                   help="seconds over which a seam's offset decays, 0 = windows back to back (default: %(default).3g)")
    g.add_argument("--segments", choices=("chunks", "clips"), default="chunks")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "eval",
        help="evaluate controlled synthesis (Table 2) and objective motion metrics with baselines",
        description="Evaluate a database: `eval controls` reproduces Table 2 of Habibie et al. 2022; "
        "`eval motion` compares the rank-sum search with baselines (and the ground truth of a held-out stretch) "
        "by objective metrics and writes an HTML report.",
    )
    esub = p.add_subparsers(dest="eval_command", metavar="WHAT", required=True)

    c = esub.add_parser(
        "controls",
        help="controlled vs unconstrained synthesis for wrist high/low, fast/slow, (a)symmetric",
        description="Synthesize the speech once without control and once per control (left wrist height above "
        "p85 / below p15, left wrist speed above p85 / below p15, height asymmetry above p85 / below p15), "
        "recompute the controlled variable on the output, and check that each control moved it past the "
        "unconstrained mean in the requested direction without freezing it.",
    )
    c.add_argument("db", metavar="DB.h5")
    c.add_argument("--audio", required=True, metavar="SPEECH.wav")
    c.add_argument("--json", default=None, metavar="OUT.json", help="write the table as JSON")
    c.add_argument("--md", default=None, metavar="OUT.md", help="write the table as Markdown")
    c.add_argument("--plot", default=None, metavar="OUT.png", help="plot controlled vs unconstrained over time")
    c.add_argument("--strict", action="store_true", help="exit 1 when any control fails a check or finds no candidate")
    c.add_argument("--min-std-ratio", type=float, default=0.3,
                   help="no-freeze check: controlled std >= this x the reference std (default: %(default)s)")
    c.add_argument("--freeze-reference", choices=("allowed", "unconstrained"), default="allowed",
                   help="reference std of the no-freeze check: the database frames the mask allows (default) "
                   "or the unconstrained synthesis")
    c.add_argument("--exclude", default=None, help="comma-separated recordings to leave out of the search")
    _search_options(c, preselect=True)
    c.set_defaults(run=run_controls)

    m = esub.add_parser(
        "motion",
        help="objective metrics of the search and baselines, with an HTML report",
        description="Either hold out a stretch of a recording (--data-dir, --holdout-start, --holdout-end): build a "
        "database from the rest and compare every system with the held-out motion capture; or take a database "
        "and new speech (DB.h5 --audio ...) and compute the metrics that need no ground truth. Systems: "
        + "; ".join(SYSTEM_LABELS[s] for s in SYSTEMS[1:]) + ".",
    )
    m.add_argument("db", nargs="?", default=None, metavar="DB.h5", help="database to search (not with --data-dir)")
    m.add_argument("--audio", action="append", default=[], metavar="SPEECH.wav",
                   help="speech without motion (repeatable); a transcript with the same stem beside it is used "
                   "for subtitles")
    m.add_argument("--data-dir", action="append", default=[], metavar="DIR",
                   help="recordings for a held-out evaluation (repeatable)")
    m.add_argument("--recording", default=None, help="stem of the recording to hold a stretch out of (default: first)")
    m.add_argument("--holdout-start", type=float, default=None, metavar="S", help="held-out stretch start, s")
    m.add_argument("--holdout-end", type=float, default=None, metavar="S", help="held-out stretch end, s")
    m.add_argument("--no-mirror", action="store_true", help="no mirrored copies in the training database")
    m.add_argument("--train-db", default=None, metavar="DB.h5",
                   help="keep the training database here (default: OUT/train.h5)")
    m.add_argument("-o", "--output", required=True, metavar="DIR", help="report folder")
    m.add_argument("--systems", default=None,
                   help=f"comma-separated subset of {','.join(SYSTEMS[1:])}")
    m.add_argument("--controls", action="store_true", help="also run `eval controls` and add it to the report")
    m.add_argument("--no-render", action="store_true", help="no contact sheets or video")
    m.add_argument("--video", choices=("mp4", "gif", "none"), default="mp4",
                   help="side-by-side video of the first input (default: mp4 with the speech)")
    m.add_argument("--video-seconds", type=float, default=None, metavar="S", help="render only the first S seconds")
    m.add_argument("--keywords", action="store_true", help="let the rank-sum search use keyword sub-databases")
    m.add_argument("--refiner", default=None, metavar="REFINER.pt",
                   help="add the system 'rank-sum + refiner' (gesturedb refiner train)")
    m.add_argument("--starts", type=int, default=0, metavar="N",
                   help="also run the rank-sum search from N random starting poses (seeds 0..N-1, as Habibie et al. "
                   "evaluate) and report mean, sd, min and max of its metrics: one start is one path through the "
                   "database (default: 0, only --init)")
    m.add_argument("-q", "--quiet", action="store_true", help="do not print the tables")
    _search_options(m, preselect=False)
    m.set_defaults(run=run_motion)


def _search_kwargs(args, **more) -> dict:
    """``segments`` and the shared search options (:class:`gesturedb.synth.options.SearchOptions`)."""
    options = eval_options(k=args.k, init=args.init, seed=args.seed, step=args.step,
                           seam_decay_s=args.seam_decay_s, **more)
    return dict(segments=args.segments, options=options)


def run_controls(args) -> int:
    from gesturedb.eval.evaluate import evaluate_controls
    from gesturedb.eval.report import write_controls_report

    check_outputs({"--json": args.json, "--md": args.md, "--plot": args.plot}, [args.db, args.audio])
    with gesturedb.open(args.db) as db:
        rep = evaluate_controls(
            db, args.audio, min_std_ratio=args.min_std_ratio, freeze_reference=args.freeze_reference,
            **_search_kwargs(args, preselect=args.preselect,
                             exclude=args.exclude.split(",") if args.exclude else None),
        )
    print(rep.to_text())
    written = write_controls_report(rep, json_path=args.json, md_path=args.md, plot_path=args.plot)
    if written:
        print("wrote " + ", ".join(map(str, written)))
    return 1 if args.strict and not rep.passed else 0


def _beside(audio: str) -> str | None:
    stem = os.path.splitext(audio)[0]
    for ext in (".TextGrid", ".textgrid", ".tsv", ".json"):
        if os.path.isfile(stem + ext):
            return stem + ext
    return None


def run_motion(args) -> int:
    from gesturedb.eval.evaluate import evaluate_holdout, evaluate_inputs

    systems = None
    if args.systems:
        systems = [s.strip() for s in args.systems.split(",") if s.strip()]
        bad = [s for s in systems if s not in SYSTEMS[1:]]
        if bad:
            raise ParameterError(f"--systems: expected names from {','.join(SYSTEMS[1:])}, got {','.join(bad)}")
    refiner = None
    if args.refiner:
        from gesturedb.refiner import load_refiner

        refiner = load_refiner(args.refiner)  # checked against the database when it is used
    holdout = args.data_dir or args.holdout_start is not None or args.holdout_end is not None
    if holdout:
        if args.db or args.audio:
            raise ParameterError("eval motion: give either --data-dir with --holdout-start/--holdout-end "
                                 "or DB.h5 with --audio, not both")
        if not args.data_dir or args.holdout_start is None or args.holdout_end is None:
            raise ParameterError("eval motion: a held-out evaluation needs --data-dir, --holdout-start and --holdout-end")
        os.makedirs(args.output, exist_ok=True)
        ev = evaluate_holdout(
            args.data_dir, args.holdout_start, args.holdout_end, recording=args.recording,
            db_path=args.train_db or os.path.join(args.output, "train.h5"), mirror=not args.no_mirror,
            systems=["ground_truth"] + (systems or list(SYSTEMS[1:])), controls=args.controls,
            refiner=refiner, starts=args.starts, **_search_kwargs(args, keywords=args.keywords),
        )
    else:
        if not args.db or not args.audio:
            raise ParameterError("eval motion: expected DB.h5 and at least one --audio (or a held-out evaluation "
                                 "with --data-dir, --holdout-start and --holdout-end)")

        with gesturedb.open(args.db) as db:
            ev = evaluate_inputs(
                db, args.audio, transcripts=[_beside(a) for a in args.audio], systems=systems or list(SYSTEMS[1:]),
                controls=args.controls, refiner=refiner, starts=args.starts,
                **_search_kwargs(args, keywords=args.keywords),
            )
    written = ev.write(args.output, render=not args.no_render, video=None if args.video == "none" else args.video,
                       video_seconds=args.video_seconds)
    if not args.quiet:
        print(ev.to_text())
    print(f"wrote {len(written)} files to {args.output}: open {written[-1]}", file=sys.stderr)
    return 0
