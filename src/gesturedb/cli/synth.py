"""`gesturedb synth DB.h5 --audio speech.wav [--transcript words.TextGrid] -o out.bvh`"""
from __future__ import annotations

import os

import gesturedb
from gesturedb.cli._args import add_init_argument, float_range, int_range
from gesturedb.db.cluster import optional_client
from gesturedb.errors import GestureDBWarning, ParameterError
from gesturedb.features.pauses import DEFAULT_VAD, VAD_METHODS
from gesturedb.io import check_motion_output, read_transcript, write_motion
from gesturedb.io.npz import write_joint_positions
from gesturedb.io.outputs import check_outputs
from gesturedb.synth import methods
from gesturedb.synth.seams import SEAM_DECAY_S


def add_parser(sub) -> None:
    p = sub.add_parser(
        "synth",
        help="synthesize gestures for speech by searching a database",
        description="Rank-sum motion matching (Habibie et al. 2022): every STEP frames pick the database window "
        "whose entry pose matches the previous output pose and whose audio matches the speech.",
    )
    p.add_argument("db", metavar="DB.h5")
    p.add_argument("--audio", required=True, metavar="SPEECH.wav")
    p.add_argument("--transcript", default=None, metavar="WORDS", help="TextGrid/TSV/JSON word timings (for keywords)")
    p.add_argument("--accept-transcript-mismatch", action="store_true",
                   help="use --transcript even where it does not fit the audio (words starting after the audio's "
                   "end, or a TextGrid made for speech of another length): a warning instead of an error")
    p.add_argument("-o", "--output", required=True, metavar="OUT.bvh|OUT.glb")
    p.add_argument("--npz", default=None, metavar="OUT.npz", help="also write joint positions (T, J, 3) in metres")
    p.add_argument("--provenance", default=None, metavar="OUT.json",
                   help="where every step came from (default: OUT.provenance.json)")
    p.add_argument("--method", choices=methods.names(), default=methods.names()[0],
                   help="; ".join(f"{m.name}: {m.summary}" for m in methods.all_methods())
                   + " (default: %(default)s)")
    p.add_argument("--gap", type=lambda t: t if t == "auto" else float(t), default=None, dest="gap_s",
                   help="--method graph: input pause that splits clips, s, or 'auto' (default: the database's)")
    p.add_argument("--vad", choices=VAD_METHODS, default=DEFAULT_VAD,
                   help="--method graph without --transcript: how pauses are found in the speech "
                   "(default: %(default)s; see gesturedb.features.pauses)")
    p.add_argument("--rhythm", choices=("chance", "hamming"), default=None,
                   help="--method graph: the rhythm term, agreement beyond chance or the paper's plain Hamming "
                   "distance, which prefers calm clips (default: chance; docs/motion-graph.md)")
    p.add_argument("--k", type=int_range(1, 10**6), default=1, help="take the k-th best candidate (default: 1)")
    p.add_argument("--preselect", choices=("pose", "audio"), default="pose")
    add_init_argument(p)
    p.add_argument("--seed", type=int_range(0, 2**63 - 1), default=0, help="seed for --init random")
    p.add_argument("--step", type=int_range(1, 10**5), default=None,
                   help="frames per search step N (default: 8/15 s in frames, 8 at 15 fps)")
    p.add_argument("--seam-decay", type=float_range(0, 60), default=SEAM_DECAY_S, dest="seam_decay_s", metavar="S",
                   help="seconds over which the offset at a seam decays to zero (inertialization); 0 = windows "
                   "back to back as in the paper (default: %(default).3g)")
    p.add_argument("--smooth", action="store_true",
                   help="Savitzky-Golay smoothing of the result (GestureMaster's window, 0.23 s); off by default: "
                   "it removes beat strokes")
    p.add_argument("--segments", choices=("chunks", "clips"), default="chunks")
    p.add_argument("--control", default=None,
                   help='control schedule, e.g. "0-12: left_wrist_height > p85; 12-: left_wrist_speed < p15"')
    p.add_argument("--no-keywords", action="store_true", help="ignore keyword sub-databases")
    p.add_argument("--keywords", default=None, help="comma-separated keywords to use (default: all)")
    p.add_argument("--exclude", default=None, help="comma-separated recordings to leave out of the search")
    p.add_argument("--speaker", default=None, help="search only this speaker's recordings (gesturedb info lists them)")
    p.add_argument("--repeat-guard", type=float_range(0, 1e6), default=None, metavar="SECONDS", dest="repeat_guard_s",
                   help="k-NN: do not play a database window again within this many seconds (default: 4; 0 = off)")
    p.add_argument("--export-fps", type=float_range(1, 1000), default=None, help="resample the BVH/npz to this frame rate")
    p.add_argument("--scheduler", default=None, metavar="local:N|tcp://HOST:PORT",
                   help="search over --parts shards on Dask workers (same output)")
    p.add_argument("--parts", type=int_range(1, 4096), default=2, help="shards with --scheduler (default: %(default)s)")
    p.add_argument("--render", default=None, metavar="OUT.mp4", help="also render the result (mp4/gif/png)")
    p.add_argument("--refiner", default=None, metavar="REFINER.pt",
                   help="refine the result with a trained refiner (gesturedb refiner train)")
    p.add_argument("--force", action="store_true",
                   help="with --refiner: use a refiner whose validation does not say it beat the unrefined "
                        "motion (it lost, or its checkpoint has no verdict or one recorded before the guards)")
    from gesturedb.cli.retarget import add_target_options

    add_target_options(p)
    p.set_defaults(run=run)


def run(args) -> int:
    from gesturedb.cli.retarget import apply_target, load_target

    check_motion_output(args.output)
    prov = args.provenance or os.path.splitext(args.output)[0] + ".provenance.json"
    speech = os.path.splitext(args.output)[0] + ".wav" if args.output.lower().endswith(".glb") else None
    check_outputs({"-o": args.output, "--provenance": prov, "--npz": args.npz, "--render": args.render,
                   "speech beside the .glb": speech},
                  [args.db, args.audio, args.transcript, getattr(args, "target_skeleton", None)])
    load_target(args)  # a broken rig fails now, not after the synthesis
    if args.transcript and args.accept_transcript_mismatch:
        args.transcript = read_transcript(args.transcript, accept_mismatch=True)

    keywords = False if args.no_keywords else (args.keywords.split(",") if args.keywords else True)
    method = methods.get(args.method)
    options = method_options(method, args, keywords=keywords)  # a flag the method cannot use fails now

    with gesturedb.open(args.db) as db, optional_client(args.scheduler or None) as client:
        refiner = None
        if args.refiner:
            from gesturedb.refiner import load_refiner

            refiner = load_refiner(args.refiner, db)
            check_verdict(refiner, force=args.force)
        settings = dict(segments=args.segments, scheduler=client, parts=args.parts)
        synth = method.open(db, **{k: v for k, v in settings.items() if k in method.settings})
        res = synth.synthesize(args.audio, transcript=args.transcript, options=options,
                               **({"refiner": refiner} if refiner is not None else {}))
    motion = res.motion if args.export_fps is None else res.motion.resample(args.export_fps)
    motion = apply_target(args, motion)
    write_motion(args.output, motion)
    res.write_provenance(prov)
    written = [args.output, prov]
    from gesturedb.cli.retarget import speech_beside

    written += [w for w in [speech_beside(args.output, args.audio)] if w]
    if args.npz:
        write_joint_positions(args.npz, motion.positions, parents=motion.skeleton.parents, fps=motion.fps,
                              names=motion.skeleton.names)
        written.append(args.npz)
    if args.render:
        from gesturedb.render import render_file

        render_file(args.render, [(res.positions, res.motion.skeleton.parents, "synthesized")],
                    fps=res.fps, audio=args.audio)
        written.append(args.render)
    n_ctl = sum(1 for s in res.steps if s["control"])
    n_kw = sum(1 for s in res.steps if s["keyword"])
    rep = res.repeats
    again = "" if rep is None else (f"; {rep['distinct']} distinct windows, {rep['repeats']} repeats (a window "
                                    f"at most {rep['max_plays']} times, {guard_summary(rep)})")
    print(f"synthesized {res.n_frames} frames ({res.n_frames / res.fps:.2f} s at {res.fps:g} fps) in "
          f"{len(res.steps)} steps ({n_ctl} controlled, {n_kw} keyword{again}); wrote {', '.join(written)}")
    return 0


#: The option flags that a method without the option refuses (their default, None, means "not given").
_METHOD_FLAGS = {"step": "--step", "repeat_guard_s": "--repeat-guard", "gap_s": "--gap", "rhythm": "--rhythm"}


def method_options(method, args, *, keywords):
    """The method's options object from the command line; a flag the method cannot use is an error."""

    given = dict(seam_decay_s=args.seam_decay_s, smooth=args.smooth, control=args.control, keywords=keywords,
                 exclude=args.exclude.split(",") if args.exclude else None, speaker=args.speaker,
                 k=args.k, preselect=args.preselect, init=args.init, seed=args.seed, step=args.step,
                 repeat_guard_s=args.repeat_guard_s, gap_s=args.gap_s, vad=args.vad, rhythm=args.rhythm)

    def unusable(m) -> list[str]:
        """The flags given that method ``m`` has no use for."""
        fields = set(m.options.field_names())
        out = [flag for name, flag in _METHOD_FLAGS.items() if given[name] is not None and name not in fields]
        out += ["--refiner"] if args.refiner and not m.refines else []
        return out + (["--scheduler"] if args.scheduler and "scheduler" not in m.settings else [])

    unused = unusable(method)
    if unused:
        able = [m.name for m in methods.all_methods() if m is not method and not unusable(m)]
        raise ParameterError(f"--method {method.name}: {', '.join(unused)} {'work' if len(unused) > 1 else 'works'} "
                             + (f"with --method {' or '.join(able)} only" if able else "with no single method"))
    fields = set(method.options.field_names())
    return method.options(**{k: v for k, v in given.items() if k in fields and v is not None})


def check_verdict(refiner, *, force: bool) -> None:
    """Refuse a refiner whose validation does not say it beat the identity (it lost, or it has no
    verdict, or one recorded before the verdict's guards), unless ``force``, which uses it with a warning.

    A missing or partial verdict is refused like a losing one: the 1,652-iteration run of issue 40
    recorded "better" before the guards existed and measures worse against the database's motion, so
    a verdict that cannot be checked is no endorsement."""
    import warnings

    kind, message = refiner.assess()
    if kind == "better":
        return
    if not force:
        raise ParameterError(f"--refiner {message}; --force uses it anyway")
    warnings.warn(message + "; used because of --force", GestureDBWarning, stacklevel=2)


def guard_summary(rep: dict) -> str:
    """The repeat guard as it ran: its span, and on how many steps it was relaxed (the search ran without it)."""
    if not rep.get("guard_s"):
        return "repeat guard off"
    n = int(rep.get("guard_relaxed", 0))
    relaxed = f", relaxed on {n} of {rep['steps']} steps where it left no candidate" if n else ""
    return f"repeat guard {rep['guard_s']:g} s{relaxed}"
