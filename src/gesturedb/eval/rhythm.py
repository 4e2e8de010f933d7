"""Rhythm agreement (GestureMaster Sec. 3.2 as a metric): does the output move to the speech's rhythm?

Per input clip (the speech split at pauses > ``gap_s``, from the transcript or, without one,
from :func:`gesturedb.synth.graph.voiced_segments`), the Hamming distance between the
speech's rhythm signature (word onsets over 32 bins) and the output motion's (hand-speed
minima over the same 32 bins); the metric is the mean over clips (0 = every bin agrees,
32 = none). Every system is measured on the same clips, the random baseline included.
"""
from __future__ import annotations

import numpy as np

from gesturedb.features.pauses import DEFAULT_VAD, voiced_segments
from gesturedb.features.rhythm import audio_rhythm, hamming, hand_speed, motion_rhythm
from gesturedb.features.segments import word_gap_clips
from gesturedb.io.transcripts import Words, read_transcript


def input_words(samples: np.ndarray, sr: int, transcript=None, *, vad: str = DEFAULT_VAD) -> tuple[np.ndarray, np.ndarray]:
    """Word start and end times (s) from a transcript (path or Words) or, without one, voiced stretches
    found by :func:`gesturedb.features.pauses.voiced_segments` (detector ``vad``)."""
    if transcript is not None:
        w = transcript if isinstance(transcript, Words) else read_transcript(transcript)
        return np.asarray(w.start_s, dtype=np.float64), np.asarray(w.end_s, dtype=np.float64)
    return voiced_segments(samples, sr, method=vad)


def rhythm_hamming(positions: np.ndarray, *, word_start_s, word_end_s, fps: float, joints, gap_s: float = 0.4) -> float:
    """Mean Hamming distance (bits of 32) between speech and motion rhythm signatures over the input clips.

    Parameters
    ----------
    positions : ndarray [shape=(T, J, 3)], metres
    word_start_s, word_end_s : ndarray [shape=(W,)], seconds
    joints : mapping role -> joint index (wrists and body-frame roles)
    """

    T = positions.shape[0]
    order = np.argsort(word_start_s, kind="stable")
    ws, we = np.asarray(word_start_s)[order], np.asarray(word_end_s)[order]
    clips = word_gap_clips(ws, we, n_frames=T, fps=fps, gap_s=gap_s)
    ok = clips.length > 0
    st, ln = clips.start[ok], clips.length[ok]
    ra = np.atleast_1d(audio_rhythm(ws, start_s=st / fps, end_s=(st + ln) / fps))
    speed = hand_speed(positions, joints=joints, fps=fps)
    rm = np.atleast_1d(motion_rhythm(speed, start=st, length=ln, fps=fps))
    return float(np.mean(hamming(ra, rm)))
