"""Baselines for the objective evaluation: database windows chosen by one cue or none.

Every baseline makes the same kind of choice as the rank-sum search of
:mod:`gesturedb.search` (``../shared/spec/search.md``): every ``step`` output
frames one window of ``n = min(step, T - t)`` database frames, taken from a
candidate ``(m, s)`` with ``1 <= s <= seg_len[m] - n`` (so the entry frame
``g - 1`` lies in the same segment), optionally leaving out excluded segments.
Only the rule that picks the candidate differs:

``random_windows``
    Uniformly at random among all candidates, with a seed: real motion with
    mismatched audio (the "mismatched audio-gesture" condition of Habibie et
    al. 2022, Table 3).
``pose_only_windows``
    The candidate whose entry pose ``P[g - 1]`` is nearest (squared Euclidean)
    to the previous output pose, ignoring audio. Because the continuation of
    the previous window has distance 0, this mostly plays the database back
    and jumps only where a segment ends: smooth, but unrelated to the speech.
``audio_only_windows``
    The candidate whose audio window ``A[g : g + n]`` is nearest by cosine
    distance to the speech window ``Q[t : t + n]``, ignoring pose: speech-driven,
    with unconstrained jumps at every seam.

Each returns a :class:`WindowChoice` (the chosen first frames per step and the
database frame of every output frame); the evaluation turns it into motion with
:meth:`gesturedb.synth.matching.Searcher.assemble`, the same root placement and
cross-fade the real search gets, so the systems differ only in what they choose.

Distances use the search's definitions and are computed in float64; ties go to
the candidate that comes first in (segment, offset) order, as in the search's
pre-selection. Distances within ``TIE_TOLERANCE`` of the minimum count as ties:
a mirrored copy has exactly the audio of its original, but matrix products
round the two copies' dot products differently in the last bits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gesturedb.errors import ParameterError, SearchError
from gesturedb.search import window_frame_map

__all__ = [
    "WindowChoice",
    "candidate_windows",
    "step_layout",
    "random_windows",
    "pose_only_windows",
    "audio_only_windows",
]

#: Distances this close to the step's minimum are ties (float64 rounding of the products).
TIE_TOLERANCE = 1e-10

# Rows of database features converted to float64 at a time: bounds the
# temporary memory on large databases (65536 x 96 x 8 bytes = 50 MB).
_BLOCK = 65536


@dataclass(frozen=True, eq=False)
class WindowChoice:
    """The windows a baseline chose: one per search step.

    Attributes
    ----------
    name : str
        Which baseline made the choice.
    frames : ndarray [shape=(S,)], int64
        Global database frame ``g`` of the first frame of each step's window.
    lengths : ndarray [shape=(S,)], int64
        Window length ``n`` of each step.
    out_frames : ndarray [shape=(S,)], int64
        Output frame ``t`` where each window is placed (``0, step, 2 step, ...``).
    distance : ndarray [shape=(S,)], float64
        The criterion of the chosen window: squared pose distance (pose-only),
        cosine distance (audio-only), NaN (random).
    n_candidates : ndarray [shape=(S,)], int64
        Candidate windows each step chose from.
    n_frames : int
        Number of output frames ``T``.
    """

    name: str
    frames: np.ndarray
    lengths: np.ndarray
    out_frames: np.ndarray
    distance: np.ndarray
    n_candidates: np.ndarray
    n_frames: int

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    @property
    def source_frames(self) -> np.ndarray:
        """ndarray [shape=(T,)], int64: database frame copied to each output frame."""

        return window_frame_map(self.frames, self.out_frames, self.lengths, self.n_frames)

    @property
    def boundaries(self) -> np.ndarray:
        """ndarray [shape=(S - 1,)], int64: output frames where a new window starts."""
        return self.out_frames[1:].copy()


# --------------------------------------------------------------------------- checks
def _segments(seg_start, seg_len, exclude):
    s = np.asarray(seg_start)
    L = np.asarray(seg_len)
    if s.ndim != 1 or s.shape != L.shape or s.dtype.kind not in "iu" or L.dtype.kind not in "iu":
        raise ParameterError(
            f"seg_start, seg_len: expected two integer arrays of shape (M,); got {s.dtype} {s.shape} and {L.dtype} {L.shape}"
        )
    if s.size and (s.min() < 0 or L.min() < 0):
        raise ParameterError("seg_start, seg_len: expected non-negative frame indices and lengths")
    if exclude is not None:
        exclude = np.asarray(exclude)
        if exclude.dtype != np.bool_ or exclude.shape != s.shape:
            raise ParameterError(f"exclude: expected bool {s.shape} (one per segment); got {exclude.dtype} {exclude.shape}")
    return s.astype(np.int64), L.astype(np.int64), exclude


def _count(value, what: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ParameterError(f"{what}: expected an integer >= {minimum}; got {value!r}")
    return int(value)


def candidate_windows(seg_start, seg_len, n: int, *, exclude=None) -> np.ndarray:
    """First frames of every candidate window of length ``n`` (search spec, step 1).

    Parameters
    ----------
    seg_start, seg_len : ndarray [shape=(M,)], int
        Segment ``m`` covers frames ``[seg_start[m], seg_start[m] + seg_len[m])``.
    n : int
        Window length.
    exclude : ndarray [shape=(M,)], bool, optional
        Segments to leave out.

    Returns
    -------
    ndarray [shape=(G,)], int64
        ``g = seg_start[m] + s`` for every ``m`` (not excluded) and
        ``1 <= s <= seg_len[m] - n``, in (m, s) order.
    """
    s0, L, exclude = _segments(seg_start, seg_len, exclude)
    n = _count(n, "n", 1)
    per = np.maximum(L - n, 0)
    if exclude is not None:
        per = np.where(exclude, 0, per)
    total = int(per.sum())
    # offsets 1..per[m] for every segment, without a Python loop over segments
    first = np.repeat(np.cumsum(per) - per, per)
    s = np.arange(total, dtype=np.int64) - first + 1
    return np.repeat(s0, per) + s


def step_layout(n_frames: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Output frame and window length of every search step.

    Returns
    -------
    out_frames, lengths : ndarray [shape=(ceil(T / step),)], int64
        ``t = 0, step, 2 step, ...`` and ``n = min(step, T - t)``.
    """
    T = _count(n_frames, "n_frames", 1)
    step = _count(step, "step", 1)
    t = np.arange(0, T, step, dtype=np.int64)
    return t, np.minimum(step, T - t)


def _candidates_by_length(seg_start, seg_len, lengths, exclude, name):
    cands = {}
    for n in np.unique(lengths):
        c = candidate_windows(seg_start, seg_len, int(n), exclude=exclude)
        if c.size == 0:
            raise SearchError(
                f"{name}: no database window of {int(n)} frames (plus its entry frame) in any "
                f"{'non-excluded ' if exclude is not None else ''}segment"
            )
        cands[int(n)] = c
    return cands


def _first_min(d: np.ndarray):
    """Index of the first entry within TIE_TOLERANCE of the minimum, along the last axis."""
    near = d <= d.min(axis=-1, keepdims=True) + TIE_TOLERANCE
    j = np.argmax(near, axis=-1)
    return int(j) if np.ndim(j) == 0 else j


def _check_reach(cands: dict, n_rows: int, what: str) -> None:
    for n, c in cands.items():
        if int(c.max()) + n > n_rows:
            raise ParameterError(f"seg_start, seg_len: segments reach past the {n_rows} frames of {what}")


# --------------------------------------------------------------------------- random
def random_windows(seg_start, seg_len, *, n_frames: int, step: int = 8, seed: int | None = 0,
                   exclude=None) -> WindowChoice:
    """Database windows drawn uniformly at random (seeded): mismatched audio.

    Parameters
    ----------
    seg_start, seg_len : ndarray [shape=(M,)], int
    n_frames : int
        Output length ``T`` in database frames.
    step : int
        Frames per step ``N``.
    seed : int or None
        Seed of :func:`numpy.random.default_rng`; the same seed gives the same windows.
    exclude : ndarray [shape=(M,)], bool, optional

    Returns
    -------
    WindowChoice
    """
    t, lengths = step_layout(n_frames, step)
    cands = _candidates_by_length(seg_start, seg_len, lengths, exclude, "random_windows")
    rng = np.random.default_rng(seed)
    frames = np.empty_like(t)
    n_cand = np.empty_like(t)
    for n, c in cands.items():
        sel = lengths == n
        frames[sel] = c[rng.integers(c.size, size=int(sel.sum()))]
        n_cand[sel] = c.size
    return WindowChoice("random", frames, lengths, t, np.full(t.shape, np.nan), n_cand, int(n_frames))


# ------------------------------------------------------------------------ pose-only
def _sq_dist_rows(X: np.ndarray, rows: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``||X[rows[i]] - y||^2`` in float64, converting at most ``_BLOCK`` rows at a time."""
    out = np.empty(rows.shape[0], dtype=np.float64)
    for a in range(0, rows.shape[0], _BLOCK):
        d = X[rows[a:a + _BLOCK]].astype(np.float64) - y
        out[a:a + _BLOCK] = np.einsum("ij,ij->i", d, d)
    return out


def pose_only_windows(pose, seg_start, seg_len, init_pose, *, n_frames: int, step: int = 8,
                      exclude=None) -> WindowChoice:
    """Each step: the window whose entry pose is nearest to the previous pose (audio ignored).

    Parameters
    ----------
    pose : ndarray [shape=(F, Dp)], float
        Database pose features.
    seg_start, seg_len : ndarray [shape=(M,)], int
    init_pose : ndarray [shape=(Dp,)]
        Previous pose of the first step (e.g. the database mean pose).
    n_frames, step, exclude
        As in :func:`random_windows`.

    Returns
    -------
    WindowChoice
        ``distance`` is ``||P[g - 1] - prev||^2`` of the chosen window;
        ``prev`` becomes ``P[g + n - 1]`` after each step.
    """
    P = np.asarray(pose)
    if P.ndim != 2 or not np.issubdtype(P.dtype, np.floating):
        raise ParameterError(f"pose: expected a float array (F, Dp); got {P.dtype} {P.shape}")
    prev = np.asarray(init_pose, dtype=np.float64)
    if prev.shape != (P.shape[1],):
        raise ParameterError(f"init_pose: expected shape ({P.shape[1]},) like the pose features; got {prev.shape}")
    t, lengths = step_layout(n_frames, step)
    cands = _candidates_by_length(seg_start, seg_len, lengths, exclude, "pose_only_windows")
    _check_reach(cands, P.shape[0], "pose")
    frames = np.empty_like(t)
    dist = np.empty(t.shape, dtype=np.float64)
    n_cand = np.empty_like(t)
    for i, n in enumerate(lengths):
        c = cands[int(n)]
        d = _sq_dist_rows(P, c - 1, prev)
        j = _first_min(d)
        g = int(c[j])
        frames[i], dist[i], n_cand[i] = g, d[j], c.size
        prev = P[g + int(n) - 1].astype(np.float64)
    return WindowChoice("pose_only", frames, lengths, t, dist, n_cand, int(n_frames))


# ----------------------------------------------------------------------- audio-only
def _window_sums(rows: np.ndarray, n: int) -> np.ndarray:
    """``sum(rows[g : g + n])`` for every g (float64 prefix sums)."""
    c = np.concatenate([[0.0], np.cumsum(rows, dtype=np.float64)])
    return c[n:] - c[:-n]


def audio_only_windows(audio, seg_start, seg_len, query, *, step: int = 8, exclude=None) -> WindowChoice:
    """Each step: the window whose audio is nearest by cosine to the speech (pose ignored).

    Steps are independent, so all steps of one window length are scored in one
    pass: ``dot[s, c] = sum_i <Q[t_s + i], A[g_c + i]>``, accumulated over the
    window offsets ``i`` as ``n`` matrix products.

    Parameters
    ----------
    audio : ndarray [shape=(F, Da)], float
        Database audio features.
    seg_start, seg_len : ndarray [shape=(M,)], int
    query : ndarray [shape=(T, Da)], float
        Audio features of the speech, standardised like the database's.
    step, exclude
        As in :func:`random_windows`.

    Returns
    -------
    WindowChoice
        ``distance`` is ``1 - cos`` of the chosen window (1 when either norm is 0).
    """
    A = np.asarray(audio)
    Q = np.asarray(query, dtype=np.float64)
    if A.ndim != 2 or not np.issubdtype(A.dtype, np.floating):
        raise ParameterError(f"audio: expected a float array (F, Da); got {A.dtype} {A.shape}")
    if Q.ndim != 2 or Q.shape[1] != A.shape[1] or Q.shape[0] < 1:
        raise ParameterError(f"query: expected (T, {A.shape[1]}) audio features with T >= 1; got {Q.shape}")
    T = Q.shape[0]
    t, lengths = step_layout(T, step)
    cands = _candidates_by_length(seg_start, seg_len, lengths, exclude, "audio_only_windows")
    _check_reach(cands, A.shape[0], "audio")
    a_sq = _sq_dist_rows(A, np.arange(A.shape[0]), np.zeros(A.shape[1]))
    q_sq = np.einsum("ij,ij->i", Q, Q)
    frames = np.empty_like(t)
    dist = np.empty(t.shape, dtype=np.float64)
    n_cand = np.empty_like(t)
    for n, c in cands.items():
        sel = np.flatnonzero(lengths == n)
        ts = t[sel]
        qn = np.sqrt(_window_sums(q_sq, n)[ts])  # (S_n,)
        an_all = np.sqrt(_window_sums(a_sq, n))
        best = np.full(sel.size, np.inf)
        arg = np.zeros(sel.size, dtype=np.int64)
        for a in range(0, c.size, _BLOCK):
            cb = c[a:a + _BLOCK]
            dot = np.zeros((sel.size, cb.size))
            for i in range(n):
                dot += Q[ts + i] @ A[cb + i].astype(np.float64).T
            denom = qn[:, None] * an_all[cb][None, :]
            with np.errstate(divide="ignore", invalid="ignore"):
                d = np.where(denom > 0, 1.0 - dot / np.where(denom > 0, denom, 1.0), 1.0)
            j = _first_min(d)
            dj = d[np.arange(sel.size), j]
            better = dj < best - TIE_TOLERANCE  # an earlier block keeps its tie
            best[better] = dj[better]
            arg[better] = a + j[better]
        frames[sel] = c[arg]
        dist[sel] = best
        n_cand[sel] = c.size
    return WindowChoice("audio_only", frames, lengths, t, dist, n_cand, int(T))
