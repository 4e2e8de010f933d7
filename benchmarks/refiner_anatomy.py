"""What a trained refiner's correction does to the motion: where speeds move, and which part of it does.

Run by hand (never collected by pytest); needs the refiner extra (torch):

    python benchmarks/refiner_anatomy.py REFINER.pt DB.h5 [--offset-checkpoint OUT.pt]

``DB.h5`` is the database the refiner was trained on (its training-data cache
``REFINER.pt.data.h5`` must be beside the checkpoint). On the validation windows and on the
training windows it prints, for the k-NN input, the refined output (the checkpoint's best
generator, or its last one with ``--last``) and the capture:

- joint speeds (upper body, root at the origin, m/s): mean and the 10/50/90/99 % quantiles;
- the speed ratio refined / input per joint (the lowest and highest) and per group
  (spine/neck/head, arms, fingers), against the capture's;
- the arms' velocity power in the stroke bands (the validator's definition);
- how the correction's power splits into bands, and how much of it is a posture offset: its
  mean over each window, and the mean over every window (one posture);
- the validation metrics (``gesturedb.refiner.validation``) of the refined output, of the input
  plus the correction's window means only (the posture part) and of the refined output minus them
  (the time-varying part).

``--offset-checkpoint OUT.pt`` writes a copy of the checkpoint whose best generator adds only
the mean correction over the training windows (its last layer's weights zero, its bias that
mean): ``gesturedb eval motion --refiner OUT.pt`` then measures the posture part alone.
Results of 2026-11-27: benchmarks/RESULTS.md, "Refiner".
"""
from __future__ import annotations

import argparse
import types

import numpy as np
import torch

import gesturedb
from gesturedb.measures import band_integrals, welch_psd
from gesturedb.refiner.data import WINDOW, cache_settings, load_cache
from gesturedb.refiner.train import _load_state, frozen_channels, make_generator, read_checkpoint
from gesturedb.refiner.validation import Validator, format_metrics

GROUPS = {"spine/neck/head": ("spine", "neck", "head", "jaw"), "arms": ("shoulder", "collar", "elbow", "wrist"),
          "fingers": ("thumb", "index", "middle", "ring", "pinky")}


def _windows(data, idx):
    """The training data seen through a Validator as if ``idx`` were its validation windows."""
    return types.SimpleNamespace(val_windows=idx, train_windows=np.array([], np.int64), joints=data.joints,
                                 window=data.window, starts=data.starts, audio=data.audio, fake=data.fake,
                                 real=data.real)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("db")
    ap.add_argument("--last", action="store_true", help="the last generator instead of the best")
    ap.add_argument("--offset-checkpoint", metavar="OUT.pt")
    args = ap.parse_args()
    torch.set_num_threads(1)
    with gesturedb.open(args.db) as db:
        ck = read_checkpoint(args.checkpoint, training=True)
        cfg = ck["config"]
        data = load_cache(args.checkpoint + ".data.h5", db, cache_settings(
            db, seed=cfg["seed"], window=WINDOW, stride=cfg["stride"], val_fraction=cfg["val_fraction"]))
        if data is None:
            raise SystemExit(f"{args.checkpoint}.data.h5: no training data for this database beside the checkpoint")
        joints = ck["joints"].numpy()
        G = make_generator(cfg, ck["features"], joints, 6 * len(joints), int(ck["features"]["audio_channels"]))
        which = "generator" if args.last or "best_generator" not in ck else "best_generator"
        _load_state(G, ck[which], args.checkpoint, which)
        G.eval()
        names = list(db.skeleton.names)
        for split, idx in (("validation", data.val_windows), ("training", data.train_windows)):
            v = Validator(db, _windows(data, idx))
            with torch.no_grad():
                out = G(torch.from_numpy(v.audio), torch.from_numpy(v.knn)).numpy()
            pos = {"input": v._positions(v.knn), "refined": v._positions(out), "capture": v._positions(v.real)}
            speed = {k: np.linalg.norm(np.diff(p, axis=1), axis=-1) * v.fps for k, p in pos.items()}
            print(f"== {split} windows: {len(idx)}")
            for k, s in speed.items():
                q = " ".join(f"{np.quantile(s, x):.3f}" for x in (0.1, 0.5, 0.9, 0.99))
                print(f"  {k:8s} speed mean {s.mean():.4f} m/s, quantiles 10/50/90/99 % {q}")
            ratio = speed["refined"].mean(axis=(0, 1)) / speed["input"].mean(axis=(0, 1))
            upper = [names[j] for j in v.upper]
            order = np.argsort(ratio)
            print("  speed refined / input, lowest: " + ", ".join(f"{upper[i]} {ratio[i]:.3f}" for i in order[:6]))
            print("  highest: " + ", ".join(f"{upper[i]} {ratio[i]:.3f}" for i in order[-6:]))
            for g, keys in GROUPS.items():
                sel = [i for i, n in enumerate(upper) if any(k in n.lower() for k in keys)
                       and (g == "fingers" or not any(f in n.lower() for f in GROUPS["fingers"]))]
                if sel:
                    base = speed["input"][..., sel].mean()
                    print(f"  {g} ({len(sel)} joints): refined / input {speed['refined'][..., sel].mean() / base:.3f}, "
                          f"capture / input {speed['capture'][..., sel].mean() / base:.3f}")
            for k, p in pos.items():
                f, psd, _ = welch_psd(np.diff(p[:, :, v.arms], axis=1) * v.fps, fps=v.fps, axis=1)
                bands = band_integrals(f, psd.sum(-1).mean(axis=(0, 2)), fps=v.fps)
                print(f"  arm band power {k:8s} " + " ".join(f"{b:.4f}" for b in bands.values()))
            c = out - v.knn
            spec = np.abs(np.fft.rfft(c, axis=-1)) ** 2
            fr = np.fft.rfftfreq(c.shape[-1], 1 / v.fps)
            share = " ".join(f"{spec[..., (fr >= a) & (fr < b)].sum() / spec.sum():.3f}"
                             for a, b in ((0, 0.5), (0.5, 2), (2, 4), (4, np.inf)))
            means = c.mean(-1, keepdims=True)
            posture = c.mean(axis=(0, 2))
            print(f"  correction RMS {np.sqrt((c ** 2).mean()):.4f}; power below 0.5 / 0.5-2 / 2-4 / 4+ Hz {share}; "
                  f"window means {(means ** 2).mean() / (c ** 2).mean():.3f} of it, one posture for every window "
                  f"{(posture ** 2).mean() / (c ** 2).mean():.3f} (RMS {np.sqrt((posture ** 2).mean()):.4f})")
            if split == "validation":
                vv = Validator(db, data)  # the real validator: against the database's own motion too
                for name, x in (("input", v.knn), ("refined", out), ("input + window means", v.knn + means),
                                ("refined - window means", out - means)):
                    print(f"  {name:24s} {format_metrics(vv.measure(x))}")
            else:
                mean_train = posture
        if args.offset_checkpoint:
            raw = torch.load(args.checkpoint, weights_only=True)
            g = dict(raw[which])
            keep = np.ones(len(mean_train), np.float32)
            keep[frozen_channels(ck["features"], joints)] = 0.0
            g["out.weight"] = torch.zeros_like(g["out.weight"])
            g["out.bias"] = torch.from_numpy((mean_train * keep).astype(np.float32))
            raw["best_generator"] = g
            torch.save(raw, args.offset_checkpoint)
            print(f"wrote {args.offset_checkpoint}: a generator that adds the training windows' mean correction")


if __name__ == "__main__":
    main()
