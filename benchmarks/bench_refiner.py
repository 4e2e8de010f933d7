"""Refiner speed on this CPU: training iterations per second, and what refining adds to a synthesis.

Run by hand (never collected by pytest); needs the refiner extra (torch):

    python benchmarks/bench_refiner.py [--threads 2] [--repeat 3]

Builds the mirrored BEAT2 database in a temporary folder, makes the training
windows twice, then prints (medians over --repeat, all measured in this run):

- the training data: made in this process and held in memory, against
  assembled on --workers processes and written to the memory-mapped cache
  (identical data, checked here), and the bytes per window each keeps in memory;

- training: seconds per iteration (5 critic updates + 1 generator update,
  batch 32, width 64, the default recipe: critic augmentation, jitter term) and
  iterations per second, on the data in memory and on the cached data (batches
  read through the memory map), on every device present (the CPU, and CUDA when
  torch sees a GPU), and one validation pass (the held-back windows refined and
  measured, every --val-every iterations of a run);
- a 60 s synthesis (four input clips joined, trimmed to 60 s): the k-NN
  synthesis alone, the refinement of its result alone, and the ratio
  refinement / synthesis (the goal: refining adds less than 10%). Refining runs
  as synth runs it (REFINE_THREADS torch threads, whatever --threads says) and,
  interleaved with it, on torch's default thread count (what it ran on before);
  synthesis and refining take turns, round after round, and the share is the
  median of the rounds' shares (each round's parts see about the same load).
The refiner is untrained here: its cost does not depend on its weights.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("GESTUREDB_DATA", ROOT.parent / "shared" / "data"))


def median_time(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=5, help="training iterations per timing")
    ap.add_argument("--workers", type=int, default=2, help="processes assembling the cached training data")
    args = ap.parse_args()

    import torch

    import gesturedb
    from gesturedb.features.audio import audio_deltas
    from gesturedb.io.audio import read_audio
    from gesturedb.refiner.data import database_identity, feature_identity, make_training_data
    from gesturedb.refiner.train import REFINE_THREADS, Refiner, TrainConfig, Trainer
    from gesturedb.refiner.validation import Validator
    from gesturedb.synth import Searcher

    default_threads = torch.get_num_threads()  # torch's own choice: the machine's cores
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        db = gesturedb.build([DATA / "beat2-scott"], os.path.join(tmp, "scott.h5"), mirror=True)
        t = time.perf_counter()
        split = TrainConfig.val_fraction
        data = make_training_data(db, val_fraction=split)
        t_data = time.perf_counter() - t
        t = time.perf_counter()
        cached = make_training_data(db, workers=args.workers, cache=os.path.join(tmp, "r.pt.data.h5"),
                                    val_fraction=split)
        t_cached = time.perf_counter() - t
        every = np.arange(data.n_windows)
        assert np.array_equal(cached.fake(every), data.fake(every)), "the cached fakes differ"
        W = data.n_windows
        per_window_before = (data.channels * 2 + data.audio_channels) * data.window * 4  # audio, real, fake per window
        resident = (cached.frame_real.nbytes + cached.frame_audio.nbytes) / W
        s_train = {}
        devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
        runs = [("memory", data, "cpu")] + [("cache", cached, dev) for dev in devices]
        for name, d, dev in runs:
            tr = Trainer(d, TrainConfig(), database_identity(db), feature_identity(db), device=dev)
            tr.step()  # warm-up

            def steps(tr=tr, dev=dev):
                for _ in range(args.iterations):
                    tr.step()
                if dev == "cuda":
                    torch.cuda.synchronize()
            s_train[(name, dev)] = median_time(steps, args.repeat) / args.iterations
        tr.validator = Validator(db, cached)
        s_val = median_time(tr.validate, args.repeat)

        rate = db.sample_rate
        clips = sorted((DATA / "beat2-scott" / "inputs").glob("*.wav"))
        y = np.concatenate([read_audio(c, sr=rate)[0] for c in clips])[: 60 * rate]
        searcher = Searcher(db)
        refiner = Refiner(tr.G.cpu(), data.joints, feature_identity(db))  # applied on the CPU, as synth does
        before = Refiner(tr.G, data.joints, feature_identity(db), threads=default_threads)
        res = searcher.synthesize(y, sr=rate)
        query = searcher.query_features(y, rate)
        audio = np.concatenate([query, audio_deltas(query)], axis=1)
        # synthesis and both ways of refining in turn, round after round, so that all three see the
        # same load (a shared machine's moves within seconds); the share is the median of the
        # rounds' shares
        times = {"synth": [], "refine": [], "before": []}
        for _ in range(max(args.repeat, 5)):
            for key, fn in (("synth", lambda: searcher.synthesize(y, sr=rate)),
                            ("refine", lambda: refiner.refine(res.motion, audio)),
                            ("before", lambda: before.refine(res.motion, audio))):
                t = time.perf_counter()
                fn()
                times[key].append(time.perf_counter() - t)
        s_synth, s_refine, s_before = (statistics.median(times[k]) for k in ("synth", "refine", "before"))
        share = statistics.median(r / s for r, s in zip(times["refine"], times["synth"]))
        share_before = statistics.median(r / s for r, s in zip(times["before"], times["synth"]))

    print(f"torch {torch.__version__}, {args.threads} threads; database {db.n_frames} frames; "
          f"{W} training windows of {data.channels} channels")
    print(f"training data: {t_data:.1f} s in this process, {t_cached:.1f} s on {args.workers} processes into the "
          f"cache ({t_data / t_cached:.2f}x; identical fakes); in memory per window: {per_window_before / 1e3:.0f} kB "
          f"stored per window before, {resident / 1e3:.1f} kB now (per-frame arrays / windows; the "
          f"{data.channels * data.window * 4 / 1e3:.0f} kB fake stays in the file)")
    for (name, dev), s_it in s_train.items():
        print(f"training on the data in {name}, {dev}: {s_it * 1000:.0f} ms per iteration = {1 / s_it:.2f} "
              f"iterations/s")
    print(f"one validation pass ({cached.val_windows.size} windows, on {devices[-1]}): {s_val * 1000:.0f} ms")
    print(f"60 s synthesis ({len(times['synth'])} rounds, medians): k-NN {s_synth * 1000:.0f} ms, refining it "
          f"{s_refine * 1000:.0f} ms on {REFINE_THREADS} torch thread(s): {100 * share:.1f}% of the synthesis (goal "
          f"< 10%); on torch's default {default_threads} threads {s_before * 1000:.0f} ms: {100 * share_before:.1f}%")
    return 0


if __name__ == "__main__":
    sys.exit(main())
