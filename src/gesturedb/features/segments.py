"""Segmenting a recording into database segments.

Two schemes, both covering the recording completely and without overlap:

* :func:`fixed_chunks`: equal chunks (Habibie et al. 2022 use T_match = 64
  frames).
* :func:`word_gap_clips`: clips split at pauses between words longer than
  ``gap_s`` (GestureMaster, Zhou et al. 2022, Sec. 3.1: 0.4 s).

Frame ``i`` covers ``[i / fps, (i + 1) / fps)`` seconds, as in
:mod:`gesturedb.features.audio`.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.features.body import check_fps

__all__ = ["CHUNK_S", "Clips", "default_chunk_frames", "fixed_chunks", "word_gap_clips"]

#: Length of the fixed chunks, s: the paper's T_match = 64 frames at its 15 fps.
CHUNK_S = 64 / 15


def default_chunk_frames(fps: float) -> int:
    """:data:`CHUNK_S` in frames at ``fps``, rounded (64 at 15 fps, 128 at 30 fps)."""
    return max(1, int(round(float(fps) * CHUNK_S)))


class Clips(NamedTuple):
    """Word-gap clips of one recording (all arrays int64, shape (C,)).

    Attributes
    ----------
    start : ndarray [shape=(C,)], int64, frames
        First frame of each clip.
    length : ndarray [shape=(C,)], int64, frames
        Number of frames; ``start[k + 1] == start[k] + length[k]``.
    word_start, word_end : ndarray [shape=(C,)], int64
        Clip ``k`` holds words ``word_start[k] <= w < word_end[k]`` (indices into
        the word arrays given); ``word_end[k] == word_start[k + 1]``.
    """

    start: np.ndarray
    length: np.ndarray
    word_start: np.ndarray
    word_end: np.ndarray


def _check_count(name: str, value, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ParameterError(f"{name}: expected an int >= {minimum}; got {value!r}")
    return int(value)


def fixed_chunks(n_frames: int, *, length: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Split ``n_frames`` frames into consecutive chunks of ``length`` frames.

    Parameters
    ----------
    n_frames : int >= 0
        Frames in the recording.
    length : int >= 1, keyword-only
        Chunk length, frames.

    Returns
    -------
    start : ndarray [shape=(C,)], int64, frames
    length : ndarray [shape=(C,)], int64, frames
        ``C = ceil(n_frames / length)``. The last chunk is kept even when it is
        shorter than ``length`` so that every frame belongs to a segment (a chunk
        shorter than the search window simply yields no search candidates).
    """
    n_frames = _check_count("n_frames", n_frames, 0)
    length = _check_count("length", length, 1)
    start = np.arange(0, n_frames, length, dtype=np.int64)
    lengths = np.minimum(start + length, n_frames) - start
    return start, lengths.astype(np.int64)


def word_gap_clips(
    word_start_s: np.ndarray,
    word_end_s: np.ndarray,
    *,
    n_frames: int,
    fps: float,
    gap_s: float = 0.4,
) -> Clips:
    """Split a recording into clips at long pauses between words.

    Parameters
    ----------
    word_start_s, word_end_s : ndarray [shape=(W,)], seconds
        Word timings, sorted by start time (``word_end_s >= word_start_s``).
    n_frames : int >= 0, keyword-only
        Frames in the recording.
    fps : float > 0, keyword-only
        Frame rate, frames per second.
    gap_s : float > 0, keyword-only
        A pause longer than this splits the recording (GestureMaster: 0.4 s).

    Returns
    -------
    Clips
        Clips tiling ``[0, n_frames)`` in order. The pause between word ``w`` and
        ``w + 1`` is ``word_start_s[w + 1] - max(word_end_s[:w + 1])`` (the running
        maximum tolerates overlapping words). Each pause longer than ``gap_s``
        puts a clip boundary at frame ``round(mid * fps)``, ``mid`` the middle of
        the pause, so the silence is shared between the two clips. Leading and
        trailing silence belong to the first and last clip. No words give one
        clip; ``n_frames == 0`` gives none.

    Notes
    -----
    Boundaries that would fall outside ``(0, n_frames)`` or not after the
    previous boundary (only possible when words lie past the end of the motion)
    are dropped, so such words join the last clip.
    """
    n_frames = _check_count("n_frames", n_frames, 0)
    fps = check_fps(fps)
    try:
        gap = float(gap_s)
    except (TypeError, ValueError):
        raise ParameterError(f"gap_s: expected seconds > 0; got {gap_s!r}") from None
    if not (math.isfinite(gap) and gap > 0):
        raise ParameterError(f"gap_s: expected seconds > 0; got {gap_s!r}")
    ws = np.asarray(word_start_s, dtype=np.float64)
    we = np.asarray(word_end_s, dtype=np.float64)
    if ws.ndim != 1 or we.shape != ws.shape:
        raise ParameterError(
            f"word_start_s, word_end_s: expected two 1-D arrays of equal length; got {ws.shape} and {we.shape}"
        )
    if not (np.isfinite(ws).all() and np.isfinite(we).all()):
        raise ParameterError("word_start_s, word_end_s: expected finite times in seconds; got NaN/inf")
    if len(ws) > 1 and np.any(np.diff(ws) < 0):
        w = int(np.flatnonzero(np.diff(ws) < 0)[0])
        raise ParameterError(
            f"word_start_s: expected times sorted ascending; got {ws[w]:.3f} s then {ws[w + 1]:.3f} s at word {w + 1}"
        )
    if np.any(we < ws):
        w = int(np.flatnonzero(we < ws)[0])
        raise ParameterError(f"word_end_s: expected end >= start; got word {w}: {ws[w]:.3f} s to {we[w]:.3f} s")

    empty = np.zeros(0, dtype=np.int64)
    if n_frames == 0:
        return Clips(empty, empty.copy(), empty.copy(), empty.copy())
    n_words = len(ws)

    bounds_f: list[int] = []
    bounds_w: list[int] = []
    if n_words > 1:
        prev_end = np.maximum.accumulate(we)[:-1]
        pause = ws[1:] - prev_end
        split = np.flatnonzero(pause > gap)  # split between word k and k + 1
        mids = 0.5 * (prev_end[split] + ws[split + 1])
        frames = np.floor(mids * fps + 0.5).astype(np.int64)
        last = 0
        for k, fr in zip(split.tolist(), frames.tolist()):
            if last < fr < n_frames:
                bounds_f.append(fr)
                bounds_w.append(k + 1)
                last = fr
    starts = np.array([0] + bounds_f, dtype=np.int64)
    ends = np.array(bounds_f + [n_frames], dtype=np.int64)
    w0 = np.array([0] + bounds_w, dtype=np.int64)
    w1 = np.array(bounds_w + [n_words], dtype=np.int64)
    return Clips(starts, ends - starts, w0, w1)
