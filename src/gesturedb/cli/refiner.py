"""`gesturedb refiner train|apply`: the cGAN refiner (needs the `refiner` extra: PyTorch CPU)."""
from __future__ import annotations

import sys
import warnings

import gesturedb
from gesturedb.cli._args import int_range
from gesturedb.db.cluster import check_scheduler, optional_client
from gesturedb.errors import GestureDBWarning, InputFileError, ParameterError
from gesturedb.features.audio import audio_deltas
from gesturedb.io import read_motion, write_motion
from gesturedb.io.audio import read_audio
from gesturedb.io.outputs import check_outputs
from gesturedb.motion import Motion
from gesturedb.refiner.data import STRIDE  # no torch: the data module is plain numpy
from gesturedb.threads import available_cpus


def add_parser(sub) -> None:
    p = sub.add_parser("refiner", help="train a cGAN refiner on a database, or refine existing motion",
                       description="The refiner of Habibie et al. 2022 (Sec. 3.2) smooths and resynchronises "
                       "k-NN output. Needs PyTorch: pip install 'gesturedb[refiner]'.")
    ops = p.add_subparsers(dest="op", metavar="OP", required=True)
    t = ops.add_parser("train", help="train on a database's own audio and its k-NN synthesis")
    t.add_argument("db", metavar="DB.h5")
    t.add_argument("-o", "--output", required=True, metavar="REFINER.pt")
    t.add_argument("--iterations", type=int, default=2000, help="generator updates in all (default: 2000)")
    t.add_argument("--batch", type=int, default=32)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--stride", type=int, default=STRIDE, metavar="FRAMES",
                   help="frames between training windows (default: %(default)s, the paper's); a larger stride "
                   "searches and caches fewer windows, for large databases")
    t.add_argument("--threads", type=int, default=None,
                   help=f"torch threads while training (default: the CPUs this process may use, {available_cpus()})")
    t.add_argument("--checkpoint-every", type=float, default=120.0, metavar="SECONDS")
    t.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="where to train: auto = a CUDA GPU when torch sees one, else the CPU (default: auto); a "
                   "run resumes on any device, and the checkpoint applies on the CPU")
    t.add_argument("--val-fraction", type=float, default=0.25, metavar="F",
                   help="hold back the last F of every recording (and of its mirror) for validation; 0: none "
                   "(default: %(default)s)")
    t.add_argument("--val-every", type=int, default=100, metavar="N",
                   help="validate every N iterations and keep the best generator (default: %(default)s)")
    again = t.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true", help="continue from the checkpoint at --output")
    again.add_argument("--overwrite", action="store_true",
                       help="start afresh over an existing --output (without --resume or --overwrite an existing "
                       "file is refused)")
    t.add_argument("--scheduler", default=None, metavar="local:N|tcp://HOST:PORT",
                   help="run the training windows' self-search over --parts shards on Dask workers, and their "
                   "assembly on the same workers (same data)")
    t.add_argument("--parts", type=int_range(1, 256), default=2, help="shards with --scheduler (default: %(default)s)")
    t.add_argument("-j", "--workers", type=int_range(1, 256), default=min(2, available_cpus()),
                   help="local processes assembling the training windows without --scheduler (default: %(default)s)")
    a = ops.add_parser("apply", help="refine motion that already exists (BVH on the database's skeleton); "
                       "warns when the refiner's validation does not say it beat the unrefined motion")
    a.add_argument("refiner", metavar="REFINER.pt")
    a.add_argument("--db", required=True, metavar="DB.h5")
    a.add_argument("--audio", required=True, metavar="SPEECH.wav")
    a.add_argument("--input", required=True, metavar="KNN.bvh")
    a.add_argument("-o", "--output", required=True, metavar="REFINED.bvh")
    p.set_defaults(run=run)


def verdict_screen(tr) -> str:
    """The end of a training run on one screen: the validation rows, unrefined and best, and the verdict."""
    from gesturedb.refiner.validation import describe_worse, format_metrics

    v = tr.validator
    if v is None:
        return "no validation (--val-fraction 0): nothing says whether this refiner improves on its input"
    best = tr.best
    rows = [f"validation: {v.n} held-back windows, {len(tr.train_idx)} training; score = |log jerk ratio| + "
            "mean |log band ratio| + H(speed), ratios to the capture, lower is better; vs DB: against the "
            "database's own motion",
            f"  unrefined (identity)     {format_metrics(v.identity)}"]
    if best is not None:
        if best["iteration"] > 0:
            rows.append(f"  best, iteration {best['iteration']:<8} {format_metrics(best['metrics'])}")
        if tr.trained_best is not None and tr.trained_best["iteration"] != best["iteration"]:
            t = tr.trained_best
            rows.append(f"  best trained, it. {t['iteration']:<6} {format_metrics(t['metrics'])}  (not kept)")
    verdict = tr.verdict()
    if verdict is None:
        rows.append("verdict: no iteration validated yet")
    elif verdict.get("identity_kept"):
        t = verdict.get("trained") or {}
        rows.append("verdict: NOT better than the unrefined motion on validation: no trained generator kept every "
                    f"guard with a score {100 * verdict['margin']:.0f}% lower"
                    + (f" (the closest, iteration {t['iteration']}: score {100 * t['improvement']:+.1f}%"
                       + (f", worse on {describe_worse(t['worse'])}" if t.get("worse") else "") + ")" if t else "")
                    + "; the checkpoint keeps the identity (refining with it changes nothing), and synth "
                    "--refiner refuses it unless --force")
    elif verdict.get("worse"):
        rows.append(f"verdict: NOT better than the unrefined motion on validation: score {100 * verdict['improvement']:.1f}% "
                    f"lower (iteration {verdict['best_iteration']}) but worse on {describe_worse(verdict['worse'])}; "
                    "synth --refiner refuses this checkpoint unless --force")
    elif verdict["beats_identity"]:
        rows.append(f"verdict: BETTER than the unrefined motion on validation, score {100 * verdict['improvement']:.1f}% "
                    f"lower (iteration {verdict['best_iteration']}, kept in the checkpoint)")
    else:
        rows.append(f"verdict: NOT better than the unrefined motion on validation (best score "
                    f"{100 * verdict['improvement']:+.1f}% vs the {100 * verdict['margin']:.0f}% needed); synth "
                    "--refiner refuses this checkpoint unless --force")
    return "\n".join(rows)


def _positive(name, v):
    if v is not None and v < 1:
        raise ParameterError(f"--{name}: expected a positive integer, got {v}")


def run(args) -> int:
    from gesturedb.refiner import require_torch

    require_torch()  # before anything else: says how to install torch when it is missing
    if args.op == "train":
        # the training-window cache is written beside the checkpoint
        check_outputs({"-o": args.output, "-o (cache)": args.output + ".data.h5"}, [args.db])
        from gesturedb.refiner.train import TrainConfig, check_output, train

        check_output(args.output, resume=args.resume, overwrite=args.overwrite)  # before a cluster is started

        for name in ("iterations", "batch", "stride", "threads", "parts", "workers", "val_every"):
            _positive(name.replace("_", "-"), getattr(args, name))
        if args.scheduler:
            check_scheduler(args.scheduler)  # before the database is opened or anything is searched
        if not 0 <= args.val_fraction <= 0.9:
            raise ParameterError(f"--val-fraction: expected a fraction from 0 to 0.9, got {args.val_fraction}")
        cfg = TrainConfig(iterations=args.iterations, batch=args.batch, seed=args.seed, stride=args.stride,
                          checkpoint_every_s=args.checkpoint_every, val_fraction=args.val_fraction,
                          val_every=args.val_every)

        with gesturedb.open(args.db) as db, optional_client(args.scheduler or None) as client:
            tr = train(db, args.output, config=cfg, resume=args.resume, overwrite=args.overwrite, progress=True,
                       log=lambda m: print(m, file=sys.stderr), scheduler=client, parts=args.parts,
                       workers=args.workers, threads=args.threads, device=args.device)
        last = tr.history[-1] if tr.history else {}
        ran = tr.iteration - tr.resumed_from  # a resume up to where the checkpoint already is trains nothing
        print(f"trained {ran} iterations" + (f" ({tr.iteration} in all)" if tr.resumed_from else "")
              + f" -> {args.output}"
              + (f" (critic {last['critic']:.3f}, L1 {last['l1']:.4f})" if last else ""))
        print(verdict_screen(tr))
        return 0
    import numpy as np

    from gesturedb.refiner import load_refiner
    from gesturedb.synth import Searcher

    check_outputs({"-o": args.output}, [args.refiner, args.db, args.audio, args.input])
    with gesturedb.open(args.db) as db:
        refiner = load_refiner(args.refiner, db)
        kind, message = refiner.assess()
        if kind != "better":  # applied as asked (a file named on purpose, often to compare), but not silently
            warnings.warn(f"{message}; applied as asked (synth --refiner refuses it without --force)",
                          GestureDBWarning, stacklevel=1)
        motion = read_motion(args.input)
        names, want = list(motion.skeleton.names), list(db.skeleton.names)
        if sorted(names) != sorted(want):
            missing = sorted(set(want) - set(names))[:5]
            raise InputFileError(args.input, f"skeleton: expected the database's {len(want)} joints, got "
                                             f"{len(names)} (missing e.g. {', '.join(missing) or 'none'})")
        if names != want:  # a BVH lists joints depth first: put them back in the database's order
            order = [names.index(n) for n in want]
            motion = Motion(skeleton=db.skeleton, fps=motion.fps, rotations=motion.rotations[:, order],
                            root_positions=motion.root_positions)
        if abs(motion.fps - db.fps) > 1e-6:
            motion = motion.resample(db.fps)
        samples, sr = read_audio(args.audio, sr=db.sample_rate)
        query = Searcher(db).query_features(samples, sr)
        T = min(query.shape[0], motion.n_frames)
        if abs(query.shape[0] - motion.n_frames) > db.fps:
            raise InputFileError(args.input, f"length: expected about {query.shape[0]} frames for {args.audio}, "
                                             f"got {motion.n_frames}")
        motion = motion[:T]
        out = refiner.refine(motion, np.concatenate([query[:T], audio_deltas(query[:T])], axis=1))
    write_motion(args.output, out)
    print(f"refined {T} frames -> {args.output}")
    return 0
