"""Rhythm agreement (GestureMaster Sec. 3.2 as a metric): does the output move to the speech's rhythm?

Per input clip (the speech split at pauses > ``gap_s``, from the transcript or, without one,
from :func:`gesturedb.synth.graph.voiced_segments`), the speech's rhythm signature (word onsets
over 32 bins) is compared with the output motion's (hand-speed minima over the same 32 bins) in
two ways, each averaged over the clips: the paper's Hamming distance (0 = every bin agrees,
32 = none) and the Hamming distance beyond chance
(:func:`gesturedb.features.rhythm.hamming_beyond_chance`, the motion graph's own rhythm term),
which takes out what the two numbers of set bits explain, so that a motion is not scored better
for having fewer speed minima. Every system is measured on the same clips, the random baseline
included.
"""
from __future__ import annotations

import numpy as np

from gesturedb.features.pauses import DEFAULT_VAD, voiced_segments
from gesturedb.features.rhythm import audio_rhythm, hamming, hamming_beyond_chance, hand_speed, motion_rhythm
from gesturedb.features.segments import word_gap_clips
from gesturedb.io.transcripts import Words, read_transcript


def input_words(samples: np.ndarray, sr: int, transcript=None, *, vad: str = DEFAULT_VAD) -> tuple[np.ndarray, np.ndarray]:
    """Word start and end times (s) from a transcript (path or Words) or, without one, voiced stretches
    found by :func:`gesturedb.features.pauses.voiced_segments` (detector ``vad``)."""
    if transcript is not None:
        w = transcript if isinstance(transcript, Words) else read_transcript(transcript)
        return np.asarray(w.start_s, dtype=np.float64), np.asarray(w.end_s, dtype=np.float64)
    return voiced_segments(samples, sr, method=vad)


def rhythm_signatures(positions: np.ndarray, *, word_start_s, word_end_s, fps: float, joints,
                      gap_s: float = 0.4) -> tuple[np.ndarray, np.ndarray]:
    """Speech and motion rhythm signatures of every input clip (the words split at pauses > ``gap_s``).

    Parameters
    ----------
    positions : ndarray [shape=(T, J, 3)], metres
    word_start_s, word_end_s : ndarray [shape=(W,)], seconds
    joints : mapping role -> joint index (wrists and body-frame roles)

    Returns
    -------
    speech, motion : ndarray [shape=(C,)], uint32
        Clip ``c``'s word-onset bits and hand-speed-minimum bits (bin 0 the least significant bit).
    """

    T = positions.shape[0]
    order = np.argsort(word_start_s, kind="stable")
    ws, we = np.asarray(word_start_s)[order], np.asarray(word_end_s)[order]
    clips = word_gap_clips(ws, we, n_frames=T, fps=fps, gap_s=gap_s)
    ok = clips.length > 0
    st, ln = clips.start[ok], clips.length[ok]
    speech = np.atleast_1d(audio_rhythm(ws, start_s=st / fps, end_s=(st + ln) / fps))
    speed = hand_speed(positions, joints=joints, fps=fps)
    return speech, np.atleast_1d(motion_rhythm(speed, start=st, length=ln, fps=fps))


def rhythm_agreement(positions: np.ndarray, *, word_start_s, word_end_s, fps: float, joints,
                     gap_s: float = 0.4) -> dict[str, float]:
    """``rhythm_hamming`` (the paper's distance) and ``rhythm_beyond_chance``, each the mean over the clips
    of :func:`rhythm_signatures` (bits of 32, lower = better agreement; arguments as there)."""

    speech, motion = rhythm_signatures(positions, word_start_s=word_start_s, word_end_s=word_end_s, fps=fps,
                                       joints=joints, gap_s=gap_s)
    return {"rhythm_hamming": float(np.mean(hamming(speech, motion))),
            "rhythm_beyond_chance": float(np.mean(hamming_beyond_chance(speech, motion)))}


def rhythm_hamming(positions: np.ndarray, *, word_start_s, word_end_s, fps: float, joints, gap_s: float = 0.4) -> float:
    """Mean Hamming distance (bits of 32) between speech and motion rhythm signatures over the input clips.

    Parameters
    ----------
    positions : ndarray [shape=(T, J, 3)], metres
    word_start_s, word_end_s : ndarray [shape=(W,)], seconds
    joints : mapping role -> joint index (wrists and body-frame roles)
    """

    speech, motion = rhythm_signatures(positions, word_start_s=word_start_s, word_end_s=word_end_s, fps=fps,
                                       joints=joints, gap_s=gap_s)
    return float(np.mean(hamming(speech, motion)))
