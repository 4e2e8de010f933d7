"""Pauses and word-like onsets from speech audio alone, for recordings and inputs without a transcript.

A simple energy detector (documented below) rather than a trained voice-activity model: it
needs no extra package, and the input side only needs the pauses (> ``gap_s``) and onsets
of voiced stretches. Used by the graph synthesis (:mod:`gesturedb.synth.graph`) and by
the build for recordings without a transcript, so both split speech the same way.
"""
from __future__ import annotations

import numpy as np

__all__ = ["voiced_segments"]


def voiced_segments(samples: np.ndarray, sr: int, *, hop_s: float = 0.01, min_silence_s: float = 0.08):
    """Word-like voiced stretches of speech from its energy (no transcript needed).

    Parameters
    ----------
    samples : ndarray [shape=(n,)], mono
    sr : int, Hz

    Returns
    -------
    start_s, end_s : ndarray [shape=(W,)], seconds
        Voiced runs (RMS in dB above 35 % of the way from its 10th to 95th percentile),
        merged across silences shorter than ``min_silence_s``.
    """
    x = np.asarray(samples, dtype=np.float64)
    hop = max(1, int(round(hop_s * sr)))
    n = x.shape[0] // hop
    if n == 0:
        return np.zeros(0), np.zeros(0)
    rms = np.sqrt((x[: n * hop].reshape(n, hop) ** 2).mean(1) + 1e-12)
    db = 20 * np.log10(rms)
    lo, hi = np.percentile(db, 10), np.percentile(db, 95)
    voiced = db > lo + 0.35 * (hi - lo)
    edges = np.diff(np.concatenate([[0], voiced.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if starts.size == 0:
        return np.zeros(0), np.zeros(0)
    keep = np.concatenate([[True], (starts[1:] - ends[:-1]) * hop_s >= min_silence_s])
    s = starts[keep]
    e = np.maximum.reduceat(ends, np.flatnonzero(keep))
    return s * hop_s, e * hop_s
