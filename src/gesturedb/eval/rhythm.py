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

The same hand-speed minima also show whether the motion pauses at its window seams rather than
with the speech (:func:`seam_minima`).
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.features.pauses import DEFAULT_VAD, voiced_segments
from gesturedb.features.rhythm import (
    audio_rhythm,
    hamming,
    hamming_beyond_chance,
    hand_speed,
    motion_rhythm,
    speed_minima,
)
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
    """Mean Hamming distance (bits of 32) between speech and motion rhythm signatures over the input clips:
    :func:`rhythm_agreement`'s ``rhythm_hamming`` (arguments as there)."""
    return rhythm_agreement(positions, word_start_s=word_start_s, word_end_s=word_end_s, fps=fps, joints=joints,
                            gap_s=gap_s)["rhythm_hamming"]


#: Seconds on each side of a window's cut that count as "at the seam" for :func:`seam_minima`: one frame
#: at the paper's 15 fps (frames ``b - 1`` and ``b``), two at 30 fps: a quarter of a 0.53 s step either way.
SEAM_MINIMA_S = 1.0 / 15.0


def seam_minima(positions: np.ndarray, *, fps: float, joints, boundaries) -> dict[str, float]:
    """How much more often the hands pause at window seams than inside the windows.

    The hand-speed minima are those of the rhythm signatures (:func:`gesturedb.features.rhythm.speed_minima`
    of :func:`~gesturedb.features.rhythm.hand_speed`). A frame is at a seam when it lies within
    :data:`SEAM_MINIMA_S` of a cut (``b`` in ``boundaries`` is a window's first frame; the cut lies between
    ``b - 1`` and ``b``). The ratio is 1 when the minima ignore the seams, as the ground truth's do at the
    synthesis's boundaries; above 1 the output slows down at the step's rate, whatever the speech does.

    Parameters
    ----------
    positions : ndarray [shape=(T, J, 3)], metres
    fps : float
    joints : mapping role -> joint index (wrists and body-frame roles)
    boundaries : sequence of int
        Frames in ``1 .. T-1`` where a new window starts.

    Returns
    -------
    dict
        ``seam_rate`` and ``inside_rate`` (minima per frame at and away from the seams) and ``ratio``
        (their quotient; NaN without minima inside the windows).
    """
    T = positions.shape[0]
    b = np.asarray(boundaries)
    if b.ndim != 1 or b.size == 0 or not np.issubdtype(b.dtype, np.integer) or b.min() < 1 or b.max() > T - 1:
        raise ParameterError(f"boundaries: expected frame indices in [1, {T - 1}] for {T} frames; got {boundaries!r}")
    half = SEAM_MINIMA_S * float(fps)
    # each frame's distance from the nearest cut, in frames (the cut of boundary b lies at b - 0.5): the cuts
    # on either side of it, by a sorted search (a frames x boundaries matrix is gigabytes for an hour of speech)
    frames, cut = np.arange(T), np.sort(b).astype(np.float64) - 0.5
    i = np.searchsorted(cut, frames)
    near = np.minimum(np.abs(frames - cut[np.maximum(i - 1, 0)]), np.abs(frames - cut[np.minimum(i, cut.size - 1)]))
    at_seam = near <= half + 1e-9
    mins = speed_minima(hand_speed(positions, joints=joints, fps=fps), fps=fps)
    hit = np.zeros(T, dtype=bool)
    hit[mins] = True
    seam_rate = float(hit[at_seam].mean()) if at_seam.any() else float("nan")
    inside_rate = float(hit[~at_seam].mean()) if (~at_seam).any() else float("nan")
    ratio = seam_rate / inside_rate if inside_rate > 0 else float("nan")
    return {"seam_rate": seam_rate, "inside_rate": inside_rate, "ratio": ratio}
