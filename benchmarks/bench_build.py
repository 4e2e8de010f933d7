"""Build throughput on the real data: seconds of recording processed per second.

Run by hand (never collected by pytest):

    python benchmarks/bench_build.py [--copies 8] [--repeat 3]

The BEAT2 recording (63.5 s) is linked under several stems into a temporary
folder so the build sees a multi-recording corpus. Printed, all measured in this
run (medians over --repeat):

- the time to only read the inputs (motion + FK, audio, transcript): the floor
  any build pays, and the baseline the other figures are divided by;
- per-stage times of one recording (read, resample, features, ...);
- whole builds with 1 and 2 worker processes, with and without mirroring,
  as recording-seconds per wall-second and as a ratio to the read floor.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("GESTUREDB_DATA", ROOT.parent / "shared" / "data"))
STEM = "2_scott_0_1_1"


def median_time(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def make_corpus(folder: Path, copies: int) -> list[Path]:
    src = DATA / "beat2-scott"
    for i in range(copies):
        for ext in (".npz", ".wav", ".TextGrid"):
            os.symlink(src / f"{STEM}{ext}", folder / f"rec{i:02d}{ext}")
    return [folder]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--copies", type=int, default=8, help="recordings in the corpus (default: 8)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    import gesturedb
    from gesturedb.db.build import BuildConfig, RecordingSource, _auto_gap, _features_for, process_recording
    from gesturedb.io import read_audio, read_motion, read_transcript

    base = DATA / "beat2-scott" / STEM
    src = RecordingSource(STEM, f"{base}.npz", f"{base}.wav", f"{base}.TextGrid")
    cfg = BuildConfig()
    # process_recording takes a resolved gap, as gesturedb.build passes it (the default "auto" is
    # resolved once from every transcript before the recordings are processed)
    cfg = dataclasses.replace(cfg, gap_s=_auto_gap([src])[0])
    rec_s = 1906 / 30.0
    process_recording(src, cfg)  # warm-up: librosa/numba imports and caches

    def read_only():
        m = read_motion(src.motion)
        m.positions  # noqa: B018 - forward kinematics is part of reading motion
        read_audio(src.audio, sr=cfg.sample_rate)
        read_transcript(src.transcript)

    t_read = median_time(read_only, args.repeat)
    print(f"machine: {os.cpu_count()} cores; recording {rec_s:.1f} s; corpus {args.copies} recordings "
          f"({args.copies * rec_s / 60:.1f} min)")
    print(f"\nbaseline: read inputs (motion + FK, audio, transcript) of one recording: {t_read * 1e3:8.1f} ms "
          f"= {rec_s / t_read:8.0f} recording-s/s")

    # stage breakdown of one recording
    m = read_motion(src.motion)
    x, sr = read_audio(src.audio, sr=cfg.sample_rate)
    w = read_transcript(src.transcript)
    t_res = median_time(lambda: m.resample(cfg.fps), args.repeat)
    m15 = m.resample(cfg.fps)
    from gesturedb.features.audio import audio_features

    t_audio = median_time(lambda: audio_features(x, sr, fps=cfg.fps, n_frames=m15.n_frames), args.repeat)
    a15 = audio_features(x, sr, fps=cfg.fps, n_frames=m15.n_frames).astype(np.float64)
    t_feat = median_time(lambda: _features_for(m15, a15, w, cfg, src, mirrored=False, source_fps=30.0), args.repeat)
    t_proc = median_time(lambda: process_recording(src, cfg), args.repeat)
    print("\nstages of one recording (median):")
    for name, t in [("read", t_read), ("resample to 15 fps", t_res), ("audio features (MFCC)", t_audio),
                    ("motion features+segments+signatures", t_feat),
                    ("process_recording (all)", t_proc)]:
        print(f"  {name:<36} {t * 1e3:8.1f} ms   {t / t_read:6.2f} x read")

    print("\nwhole builds (median; HDF5 write included):")
    print(f"  {'config':<28} {'wall s':>8} {'rec-s/s':>9} {'x read floor':>13}")
    with tempfile.TemporaryDirectory() as tmp:
        corpus = Path(tmp) / "corpus"
        corpus.mkdir()
        inputs = make_corpus(corpus, args.copies)
        total_s = args.copies * rec_s
        floor = args.copies * t_read
        for workers in (1, 2):
            for mirror in (False, True):
                out = Path(tmp) / "db.h5"
                t = median_time(lambda out=out, workers=workers, mirror=mirror:
                                gesturedb.build(inputs, out, workers=workers, mirror=mirror).close(),
                                args.repeat)
                label = f"workers={workers}{' mirror' if mirror else ''}"
                print(f"  {label:<28} {t:8.2f} {total_s / t:9.0f} {t / floor:13.2f}")
        size = os.path.getsize(Path(tmp) / "db.h5")
        print(f"\ndatabase size (mirrored, {args.copies} recordings): {size / 1e6:.1f} MB "
              f"({size / (2 * args.copies * rec_s * 15) / 1e3:.2f} kB per frame)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
