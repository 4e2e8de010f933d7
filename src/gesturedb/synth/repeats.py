"""Repeated database windows: the k-NN synthesis' repetition guard and the repeat statistics.

Left to itself the rank-sum search returns to the same few windows: on the
mirrored BEAT2 database with ``left_wrist_speed > p85`` 117 steps came from 29
windows, one of them 15 times. The guard takes every window used within the
last ``guard_s`` seconds of output out of the step's allowed set: it clears the
frames of those windows in the step's bitset. A candidate is allowed only when
its first and last frames are set (``../shared/spec/search.md``), so with
windows of one length exactly the windows that overlap a recent one drop out,
while the window that continues a recent one (its first frame right after)
stays allowed. The kernel and its contract are unchanged: the guard is one more
bitset ANDed into each step's, so the steps must run one at a time (the mask of
step i depends on the windows of steps before it). A step the guard would
leave without a candidate runs without it (counted as *relaxed*).

A window *repeats* when it overlaps a window of an earlier step (at any time
before, not only within the guard): the statistics below count those, for the
provenance and for ``gesturedb eval motion``.
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError, SearchError

#: seconds of output within which a database window is not played again (0: off)
DEFAULT_REPEAT_GUARD_S = 4.0


def check_guard_s(value) -> float:
    """``repeat_guard_s`` as a float >= 0 (seconds); ParameterError otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not (np.isfinite(value) and value >= 0):
        raise ParameterError(f"repeat_guard_s: expected a number of seconds >= 0 (0 = off), got {value!r}")
    return float(value)


def clear_frames(words: np.ndarray, frames: list[tuple[int, int]]) -> np.ndarray:
    """A copy of a packed bitset with the frames ``[a, b)`` of every range cleared.

    Parameters
    ----------
    words : ndarray [shape=(W,)], uint64
        Bit ``f & 63`` of word ``f >> 6`` is frame ``f``.
    frames : list of (int, int)
        Frame ranges ``[a, b)``.

    Returns
    -------
    ndarray [shape=(W,)], uint64
    """
    out = np.array(words, dtype=np.uint64, copy=True)
    n = out.shape[0] * 64
    for a, b in frames:
        a, b = max(int(a), 0), min(int(b), n)
        while a < b:
            w, lo = a >> 6, a & 63
            hi = min(64, lo + (b - a))  # bits [lo, hi) of word w
            width = hi - lo
            bits = np.uint64(0xFFFFFFFFFFFFFFFF) if width == 64 else np.uint64(((1 << width) - 1) << lo)
            out[w] &= ~bits
            a += width
    return out


def guarded_search(search, *, query: np.ndarray, init_pose: np.ndarray, pose_row, step: int,
                   allowed: np.ndarray | None, full: np.ndarray, guard_frames: int, no_candidate):
    """The rank-sum search one step at a time, with recently used windows taken out of each step's allowed set.

    Parameters
    ----------
    search : callable ``(query (n, Da), prev (Dp,), allowed (1, W) uint64) -> SearchResult``
        One step of the search (the kernel, or the sharded search) on an ``n``-frame query.
    query : ndarray [shape=(T, Da)], float32
    init_pose : ndarray [shape=(Dp,)], float32
    pose_row : callable ``(frame) -> ndarray [shape=(Dp,)]``
        The database's pose feature of a frame (the next step's previous pose is the
        last copied frame): ``pose.__getitem__``, or ``Database.rows`` for a client
        that does not hold the pose features.
    step : int
        N, frames per step.
    allowed : ndarray [shape=(S, W)], uint64, or None
        The steps' own allowed sets (controls, keywords); None: every frame.
    full : ndarray [shape=(W,)], uint64
        Every frame of the database set.
    guard_frames : int
        A window placed fewer than this many output frames before the step's start is taken out.
    no_candidate : callable ``(i, t, n, row) -> SearchError``
        The error for a step that has no candidate even without the guard.

    Returns
    -------
    dict
        ``segments, starts, frames, lengths, out_frames, pose_rank, audio_rank,
        n_candidates`` (int64 (S,)), ``pose_dist, audio_dist`` (float64 (S,)) as in
        :class:`gesturedb.search.SearchResult`, and ``relaxed``: bool (S,), True
        where the guard would have left no candidate and the step ran without it.
    """
    T = query.shape[0]
    S = -(-T // step)
    ints = ("segments", "starts", "frames", "lengths", "out_frames", "pose_rank", "audio_rank", "n_candidates")
    out = {f: np.zeros(S, np.int64) for f in ints}
    out["pose_dist"] = np.zeros(S)
    out["audio_dist"] = np.zeros(S)
    out["relaxed"] = np.zeros(S, dtype=bool)
    prev = np.ascontiguousarray(init_pose, dtype=np.float32)
    used: list[tuple[int, int, int]] = []  # (output frame, first database frame, length) of every step so far
    for i in range(S):
        t = i * step
        n = min(step, T - t)
        row = full if allowed is None else allowed[i]
        recent = [(g, g + m) for (t0, g, m) in used if t - t0 < guard_frames]
        q = query[t:t + n]
        res = None
        if recent:
            try:
                res = search(q, prev, clear_frames(row, recent)[None, :])
            except SearchError:
                out["relaxed"][i] = True
        if res is None:
            try:
                res = search(q, prev, np.ascontiguousarray(row)[None, :])
            except SearchError:
                raise no_candidate(i, t, n, row) from None
        for f in ints:
            out[f][i] = int(getattr(res, f)[0])
        out["out_frames"][i] = t
        out["pose_dist"][i] = float(res.pose_dist[0])
        out["audio_dist"][i] = float(res.audio_dist[0])
        g = int(res.frames[0])
        used.append((t, g, n))
        prev = np.ascontiguousarray(pose_row(g + n - 1), dtype=np.float32)
    return out


def repeat_of(frames, lengths) -> list[int | None]:
    """For every window, the latest earlier window it overlaps (None if none).

    Parameters
    ----------
    frames, lengths : sequence of int [length S]
        First database frame and length of each step's window, in output order.

    Returns
    -------
    list of (int or None) [length S]
    """
    frames = np.asarray(frames, dtype=np.int64)
    lengths = np.asarray(lengths, dtype=np.int64)
    out: list[int | None] = []
    for i in range(frames.shape[0]):
        a, b = frames[i], frames[i] + lengths[i]
        hit = np.flatnonzero((frames[:i] < b) & (frames[:i] + lengths[:i] > a))
        out.append(int(hit[-1]) if hit.size else None)
    return out


class Overlaps:
    """:func:`repeat_of` one window at a time, as a live stream adds its windows: the windows' database
    frames are kept in an array that doubles when full (rebuilt from a list at each step, they cost a
    step more the longer the stream: about 0.1 ms after ten minutes)."""

    def __init__(self):
        self._spans = np.zeros((64, 2), dtype=np.int64)  # rows < n: each window's database frames [a, b)
        self.n = 0

    def add(self, frame: int, length: int) -> int | None:
        """Add a window; the latest earlier window it overlaps (None if none), as :func:`repeat_of`."""
        a, b = int(frame), int(frame) + int(length)
        before = self._spans[:self.n]
        hit = np.flatnonzero((before[:, 0] < b) & (before[:, 1] > a))
        if self.n == self._spans.shape[0]:
            self._spans = np.concatenate([self._spans, np.zeros_like(self._spans)])
        self._spans[self.n] = (a, b)
        self.n += 1
        return int(hit[-1]) if hit.size else None


def repeat_stats(frames, lengths, *, out_frames=None, fps: float | None = None) -> dict:
    """How often a synthesis plays the same database windows.

    Parameters
    ----------
    frames, lengths : sequence of int [length S]
        First database frame and length of each step's window, in output order.
    out_frames : sequence of int [length S], optional
        Output frame of each window; with ``fps`` gives the shortest time between two plays.
    fps : float, optional

    Returns
    -------
    dict
        ``steps``; ``repeats``: windows that overlap an earlier window;
        ``distinct``: ``steps - repeats``; ``max_plays``: the most windows that
        overlap one window (itself included; 1 = nothing repeats);
        ``min_gap_s``: the shortest output time from a window to a later one that
        overlaps it (None without repeats or without ``out_frames``/``fps``).
    """
    frames = np.asarray(frames, dtype=np.int64)
    lengths = np.asarray(lengths, dtype=np.int64)
    S = int(frames.shape[0])
    rep = repeat_of(frames, lengths)
    ends = frames + lengths
    plays = [int(((frames < ends[i]) & (ends > frames[i])).sum()) for i in range(S)]
    gap = None
    if out_frames is not None and fps and S:
        t = np.asarray(out_frames, dtype=np.int64)
        gaps = [int(t[i] - t[j]) for i, j in enumerate(rep) if j is not None]
        gap = round(min(gaps) / float(fps), 4) if gaps else None
    n_rep = sum(j is not None for j in rep)
    return {"steps": S, "repeats": n_rep, "distinct": S - n_rep, "max_plays": max(plays, default=0),
            "min_gap_s": gap}


def windows_of(source_frames: np.ndarray, boundaries: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The windows of a synthesis from its frame map: ``(frames, lengths, out_frames)``, int64 (S,).

    Parameters
    ----------
    source_frames : ndarray [shape=(T,)], int64
        Database frame copied to each output frame.
    boundaries : ndarray, int64
        Output frames where a new window starts (after the first).
    """
    src = np.asarray(source_frames, dtype=np.int64)
    T = src.shape[0]
    b = np.asarray(boundaries, dtype=np.int64)
    starts = np.concatenate([[0], b[(b > 0) & (b < T)]]).astype(np.int64)
    lengths = np.diff(np.concatenate([starts, [T]]))
    return src[starts], lengths, starts
