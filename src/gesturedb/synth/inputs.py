"""What every synthesis method does with its input, in one place.

The k-NN search (:mod:`gesturedb.synth.matching`), the motion graph
(:mod:`gesturedb.synth.graph`), the evaluation's baselines and the live stream
all start the same way: speech as mono samples at the database's analysis rate
(:func:`speech_samples`), no shorter than :data:`MIN_SPEECH_S` (:func:`check_speech`),
turned into audio features standardised like the database's (:func:`query_features`);
the transcript read and checked against the speech (:func:`read_words`); the
recordings left out (:func:`excluded`); the control schedule and keyword
sub-databases as one allowed bitset per step (:func:`step_masks`).
"""
from __future__ import annotations

import os

import numpy as np

from gesturedb.control import schedule_bitsets
from gesturedb.db import keywords as kw
from gesturedb.errors import ParameterError
from gesturedb.features.audio import audio_features, n_frames_for_duration
from gesturedb.io.audio import read_audio
from gesturedb.io.transcripts import Words, check_words_fit, read_transcript
from gesturedb.synth.options import STEP_S, default_step

__all__ = ["MIN_SPEECH_S", "min_speech_frames", "speech_samples", "check_speech", "check_frames",
           "query_features", "read_words", "excluded", "step_masks"]

#: The shortest speech any synthesis method takes: one k-NN search step (8 frames at 15 fps,
#: 0.53 s). The graph's shortest input clip is as long (:data:`gesturedb.synth.graph.MIN_CLIP`),
#: and less speech holds no gesture.
MIN_SPEECH_S = STEP_S


def min_speech_frames(fps: float) -> int:
    """:data:`MIN_SPEECH_S` in frames at ``fps`` (one default search step)."""
    return default_step(fps)


def speech_samples(db, audio, sr: int | None = None, *, resample: bool = False):
    """Speech as mono float32 samples: ``(samples, sr, path or None)``.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    audio : path or ndarray [shape=(n,)]
        A WAV file (read and resampled to the database's analysis rate) or mono
        samples whose rate ``sr`` must then be given.
    sr : int, optional
    resample : bool
        Resample given samples to the analysis rate too (the feature extractor takes
        any rate; the evaluation's metrics want one).
    """
    rate = db.sample_rate  # the rate the database's audio features were computed at
    if isinstance(audio, (str, os.PathLike)):
        path = os.fspath(audio)
        samples, sr = read_audio(path, sr=rate)
        return samples, sr, path
    if sr is None:
        raise ParameterError("sr: expected the sample rate of the samples given as audio, got None")
    y = np.asarray(audio, dtype=np.float32)
    if y.ndim != 1 or y.size == 0:
        raise ParameterError(f"audio: expected mono samples (n,), got shape {y.shape}")
    if resample and int(sr) != rate:
        import soxr  # only for samples at another rate

        return soxr.resample(y, int(sr), rate).astype(np.float32), rate, None
    return y, sr, None


def check_speech(n_samples: int, sr: int, fps: float, *, audio: str | None = None) -> int:
    """The speech's length in output frames, at least :data:`MIN_SPEECH_S`; ParameterError otherwise."""
    return check_frames(n_frames_for_duration(n_samples / sr, fps), fps, audio=audio)


def check_frames(T: int, fps: float, *, audio: str | None = None) -> int:
    """``T`` output frames of speech, at least :data:`MIN_SPEECH_S`; ParameterError otherwise."""
    need = min_speech_frames(fps)
    if T < need:
        raise ParameterError(
            f"audio: expected at least one search step ({need} frames = {need / fps:.2f} s), "
            f"got {T} frames ({T / fps:.2f} s){' in ' + audio if audio else ''}: every synthesis method "
            f"needs {MIN_SPEECH_S:.2f} s of speech")
    return T


def query_features(db, samples: np.ndarray, sr: int) -> np.ndarray:
    """Audio features of new speech, standardised like the database's.

    Returns
    -------
    ndarray [shape=(T, Da)], float32, T = the speech duration in database frames.
    """
    T = n_frames_for_duration(samples.shape[0] / sr, db.fps)
    if T < 1:
        raise ParameterError(f"audio: expected at least one frame ({1 / db.fps:.3f} s) of speech, "
                             f"got {samples.shape[0] / sr:.3f} s")
    n_mfcc = int(db.config.get("n_mfcc", 13))
    raw = audio_features(samples, sr, fps=db.fps, n_frames=T, n_mfcc=n_mfcc).astype(np.float64)
    return ((raw - db.audio_mean) / db.audio_std).astype(np.float32)


def read_words(transcript, duration_s: float, *, audio: str | None = None) -> Words | None:
    """The transcript (a path, :class:`Words` or None) read, and checked to fit ``duration_s`` of speech.

    A given file is always read and checked, even when no keyword sub-database will use it.
    """
    if transcript is None:
        return None
    words = transcript if isinstance(transcript, Words) else read_transcript(transcript)
    check_words_fit(words, duration_s, audio=audio)
    return words


def excluded(db, seg_recording: np.ndarray, names=None, speaker: str | None = None) -> np.ndarray | None:
    """bool per segment: True for the segments a synthesis leaves out, or None for none.

    Parameters
    ----------
    seg_recording : ndarray [shape=(M,)], int
        Recording index of each segment (chunks, clips or graph nodes).
    names : sequence of str, optional
        Recordings to leave out (e.g. a query's own); a mirrored copy is the same
        performance and goes with its recording.
    speaker : str, optional
        Leave out every recording of another speaker.
    """
    out = None
    seg_recording = np.asarray(seg_recording)
    if names:
        idx = {db.recording(n).index for n in names}
        stems = {db.recordings[i].name.removesuffix("~mirror") for i in idx}
        idx |= {r.index for r in db.recordings if r.name.removesuffix("~mirror") in stems}
        out = np.isin(seg_recording, sorted(idx))
    if speaker is not None:
        others = ~np.isin(seg_recording, [r.index for r in db.speaker_recordings(speaker)])
        out = others if out is None else (out | others)
    return out


def step_masks(db, control, transcript, keywords, *, n_steps: int, step: int, T: int):
    """Per-step allowed bitsets and keyword bitsets (:class:`gesturedb.control.StepBitsets`) and the
    (control, keyword) label of each step; Nones when unconstrained.

    Parameters
    ----------
    control : str, list or None
        A schedule or one bare mask expression (for the whole synthesis).
    transcript : Words or None
    keywords : bool or list of str
    n_steps, step, T : int
        Steps of ``step`` output frames over ``T`` frames (``step=1``: one row per frame).
    """
    hooks = []
    keyword_bits = None
    if control:
        # one bare expression applies to the whole synthesis
        sched = [(0.0, None, control)] if isinstance(control, str) and ":" not in control else control
        res = schedule_bitsets(
            sched, controls=db.control_datasets, named=db.mask_datasets, n_steps=n_steps, step=step,
            fps=db.fps, n_out_frames=T, n_frames=db.n_frames,
        )
        hooks.append(("control", res.steps, res.labels))
    if keywords and transcript is not None:
        res = kw.keyword_step_masks(db, transcript, n_steps=n_steps, step=step, n_out_frames=T,
                                    only=None if keywords is True else list(keywords), compact=True)
        if res is not None:
            hooks.append(("keyword", *res))
            keyword_bits = res[0]
    if not hooks:
        return None, None, None
    # StepBitsets: each distinct row once, not steps x F / 8 bytes
    allowed = None
    labels = [[None, None] for _ in range(n_steps)]
    for kind, bits, lab in hooks:
        allowed = bits if allowed is None else allowed & bits
        for i in range(n_steps):
            if lab[i] is not None:
                labels[i][0 if kind == "control" else 1] = lab[i]
    labels = [tuple(x) if any(v is not None for v in x) else None for x in labels]
    return allowed, labels, keyword_bits
