"""The repetition guard's effect on repeats and on the motion metrics (real data).

    python benchmarks/bench_repeats.py [--data ../shared/data] [--guards 0,2,4,8]

For each guard (seconds, 0 = off) and each setting, synthesizes with the k-NN search
and measures the output with the evaluation's own code (gesturedb.eval.evaluate.system_metrics,
the upper-body joints, root removed), averaged over the inputs:

- held-out: database 0-48 s of the BEAT2 take plus its mirror, speech 48-63.5 s, against the
  capture (H vs GT);
- new speech: the mirrored database, the four held-out speech files (274 s), no control and
  with ``left_wrist_speed > p85`` (the control under which one window came back 15 times).

Columns: repeats (windows overlapping an earlier one), max plays of one window, the shortest
time between two plays, relaxed steps, jerk, H(speed) vs the database / ground truth,
BeatAlign, seam/inside jerk, the rhythm Hamming distance, and the time per synthesis.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--guards", default="0,2,4,8")
    args = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import numpy as np

    import gesturedb
    from gesturedb.db.build import pair_inputs
    from gesturedb.eval.common import feature_joint_indices, upper_body_joints
    from gesturedb.eval.evaluate import SystemOutput, database_reference, holdout_split, system_metrics
    from gesturedb.eval.rhythm import input_words, rhythm_hamming
    from gesturedb.io import read_transcript
    from gesturedb.io.audio import read_audio
    from gesturedb.synth import Searcher

    guards = [float(g) for g in args.guards.split(",")]
    scott = Path(args.data) / "beat2-scott"
    tmp = Path(tempfile.mkdtemp())
    full = gesturedb.build([scott], tmp / "m.h5", mirror=True)
    src = pair_inputs([scott]).recordings[0]
    held = gesturedb.build(holdout_split(src, 48.0, 63.5, 63.5), tmp / "h.h5", mirror=True)

    def measure(db, inputs, control=None):
        fj = feature_joint_indices(db)
        root = fj["root"]
        joints = upper_body_joints(db.skeleton.parents, root=root, hips=[fj["left_hip"], fj["right_hip"]])
        ref = database_reference(db, joints=joints, root=root)
        s = Searcher(db)
        rows = {g: [] for g in guards}
        for samples, sr, words, gt in inputs:
            for g in guards:
                t0 = time.perf_counter()
                res = s.synthesize(samples, sr=sr, control=control, repeat_guard_s=g)
                dt = time.perf_counter() - t0
                outs = {"k": SystemOutput("k", res.positions, res.boundaries, res.source_frames)}
                if gt is not None:
                    n = min(len(gt), res.n_frames)
                    outs = {"ground_truth": SystemOutput("ground_truth", gt[:n], np.zeros(0, np.int64)),
                            "k": SystemOutput("k", res.positions[:n], res.boundaries[res.boundaries < n],
                                              res.source_frames[:n])}
                r, _ = system_metrics(outs, fps=db.fps, samples=samples, sr=sr, joints=joints, root=root,
                                      names=db.joint_names, reference_counts=ref["speed_counts"])
                row = r["k"]
                ws, we = input_words(samples, sr, words)
                row["rhythm"] = rhythm_hamming(outs["k"].positions, word_start_s=ws, word_end_s=we, fps=db.fps,
                                               joints=feature_joint_indices(db), gap_s=float(db.config["gap_s"]))
                row.update(min_gap=res.repeats["min_gap_s"] or float("nan"), relaxed=res.repeats["guard_relaxed"],
                           steps=res.repeats["steps"], ms=1000 * dt)
                rows[g].append(row)
        return {g: {k: float(np.nanmean([r[k] for r in v])) for k in v[0] if isinstance(v[0][k], (int, float))}
                for g, v in rows.items()}

    def table(title, res, gt):
        print(f"\n{title}\n")
        hv = "H(speed) vs GT" if gt else "H(speed) vs DB"
        print(f"| guard s | steps | repeats | max plays | min gap s | relaxed | jerk m/s³ | {hv} | BeatAlign | "
              "seam/inside | rhythm Ham | ms |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for g, r in res.items():
            h = r["speed_hellinger_gt"] if gt else r["speed_hellinger_db"]
            print(f"| {g:g} | {r['steps']:.0f} | {r['repeats']:.1f} | {r['max_plays']:.1f} | {r['min_gap']:.2f} | "
                  f"{r['relaxed']:.1f} | {r['average_jerk_m_s3']:.1f} | {h:.3f} | {r['beat_align']:.3f} | "
                  f"{r['seam_ratio']:.2f} | {r['rhythm']:.2f} | {r['ms']:.0f} |")

    # held-out stretch with its capture
    y, sr = read_audio(scott / "2_scott_0_1_1.wav", sr=16000)
    a, b = int(48.0 * sr), int(63.5 * sr)
    words = read_transcript(scott / "2_scott_0_1_1.TextGrid")
    keep = (words.start_s >= 48.0) & (words.start_s < 63.5)
    w = words[keep]
    w = type(w)(start_s=w.start_s - 48.0, end_s=np.minimum(w.end_s, 63.5) - 48.0, text=w.text)
    gt = full.joint_positions[int(48.0 * full.fps):full.recordings[0].stop_frame]
    table("held-out 48-63.5 s (database 0-48 s + mirror), against the capture",
          measure(held, [(y[a:b], sr, w, np.asarray(gt, dtype=np.float64))]), True)

    inputs = []
    for wav in sorted((scott / "inputs").glob("*.wav")):
        s_, r_ = read_audio(wav, sr=16000)
        tg = wav.with_suffix(".TextGrid")
        inputs.append((s_, r_, read_transcript(tg) if tg.exists() else None, None))
    table("4 new speech inputs (274 s), mirrored database, no control", measure(full, inputs), False)
    table("4 new speech inputs, mirrored database, control left_wrist_speed > p85",
          measure(full, inputs, control="left_wrist_speed > p85"), False)
    full.close()
    held.close()


if __name__ == "__main__":
    main()
