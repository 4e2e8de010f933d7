"""Pre-selection tables: a rank-sum step in the form that merges across shards.

Spec steps 1-3 are per segment: for every segment the pre-selected candidate
(its start ``s``), its pose distance and its audio distance. Ranks (steps 4-5)
computed by :func:`rank_table` over several shards' tables, concatenated in
global segment order, are exactly the ranks of one database holding them all
(:mod:`gesturedb.db.shards` merges them, mostly from short top lists).

- :func:`preselect_table`: one query's table (the single-step kernel).
- :class:`PreselectBatch`: many queries' tables step after step on one
  database, the blocked kernel's per-frame set-up kept between calls (what a
  shard keeps on its worker).
- :func:`preselect_table_batch`: one such call without keeping anything.
- :func:`audio_distances`: the audio distances of a table's pre-selected candidates for a
  query window (a table pre-selected by pose before the step's audio came, finished);
  :func:`gather_windows` copies those candidates' windows out ahead of the audio and
  :func:`window_distances` gives the same distances from that contiguous copy.
- :func:`rank_table`: the kernel's ranker over a table.
- :func:`top_lists`: the first rows of tables by each distance, as the ranker
  orders them (what a shard sends instead of its table).

Arguments are validated here with the same messages as :mod:`gesturedb.search`.
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.search import (
    _allowed,
    _check_database,
    _core,
    _exclude,
    _float_array,
    _pose_f16,
    _pose_proj,
    _pose_vector,
    _positive_int,
    _preselect,
    _query,
    _threads,
)

__all__ = ["preselect_table", "PreselectBatch", "preselect_table_batch", "audio_distances", "gather_windows",
           "window_distances", "rank_table", "top_lists"]

METHODS = ("auto", "blocked", "per_query")


def preselect_table(pose, audio, seg_start, seg_len, prev_pose, query_audio, *, preselect="pose",
                    allowed=None, exclude=None, threads=None, pose_f16=None, pose_proj=None, other=True):
    """Spec steps 1-3 of one step: the pre-selected candidate of every segment.

    Parameters are those of :func:`gesturedb.search.rank_sum_step` (without ``k``), and

    other : bool
        False: the pre-selected candidates' other distance (the audio distance with
        ``preselect="pose"``) is left out, 0 in the table; the starts and the pre-selection
        distances are the same. A pose pre-selection made before its audio has come
        (:meth:`gesturedb.synth.stepbatch.StepBatch.speculate`) is finished with
        :func:`audio_distances`: its stand-in window's distances cost a third of the call.

    Returns
    -------
    starts : ndarray [shape=(M,)], int64
        Pre-selected ``s`` of each segment, -1 when it has no allowed candidate.
    pose_dist : ndarray [shape=(M,)], float32
        Its pose distance (0 where ``starts`` is -1), as the ranking compares it.
    audio_dist : ndarray [shape=(M,)], float64
        Its audio distance (0 where ``starts`` is -1).
    """
    seg_start, seg_len = _check_database(pose, audio, seg_start, seg_len)
    prev = _pose_vector(prev_pose, pose.shape[1], "prev_pose")
    q = _query(query_audio, audio.shape[1], "query_audio")
    preselect = _preselect(preselect)
    allowed = _allowed(allowed, pose.shape[0])
    exclude = _exclude(exclude, seg_start.shape[0])
    return _core().preselect(pose, audio, seg_start, seg_len, prev, q, preselect, allowed, exclude,
                             _threads(threads), _pose_f16(pose_f16, pose), _pose_proj(pose_proj, pose), bool(other))


class PreselectBatch:
    """:func:`preselect_table` of one step for many queries at once, call after call.

    Row i of :meth:`tables` equals ``preselect_table(..., prev_poses[i],
    query_windows[i], ...)`` exactly. With ``method="blocked"`` (the default from
    :func:`gesturedb.search.blocked_min_queries` queries on AVX2 / AVX-512: 3 a
    thread) blocks of queries share each candidate
    row, as in :func:`gesturedb.search.rank_sum_search_batch`. That method needs
    a pass over the database first (the audio windows' norms and the projection
    rows: about 0.4 s at 2.5M frames); this object builds it on the first call
    for each window length and keeps it, so a search that pre-selects step
    after step (a shard on its worker) pays it once. It holds references to
    the arrays (they must not change while it lives) and about 100 bytes per
    frame with a projection. Calls from several threads are safe.

    Parameters
    ----------
    pose, audio, seg_start, seg_len
        The database, as in :func:`gesturedb.search.rank_sum_step`.
    preselect, pose_f16, pose_proj
        As in :func:`gesturedb.search.rank_sum_step`.
    """

    def __init__(self, pose, audio, seg_start, seg_len, *, preselect="pose", pose_f16=None, pose_proj=None):
        seg_start, seg_len = _check_database(pose, audio, seg_start, seg_len)
        self.preselect = _preselect(preselect)
        self._shape = (pose.shape[0], pose.shape[1], audio.shape[1], seg_start.shape[0])
        self._plan = _core().BatchPlan(pose, audio, seg_start, seg_len, self.preselect,
                                       _pose_f16(pose_f16, pose), _pose_proj(pose_proj, pose))

    @property
    def n_setups(self) -> int:
        """Window lengths whose blocked set-up is kept (0 before the first blocked call)."""
        return self._plan.n_setups

    def tables(self, prev_poses, query_windows, *, allowed=None, exclude=None, threads=None, method="auto",
               other=True):
        """One step's tables for Q queries.

        Parameters
        ----------
        prev_poses : ndarray [shape=(Q, Dp)], float32
            Each query's previous pose.
        query_windows : ndarray [shape=(Q, n, Da)], float32
            Each query's audio window (all of the same length n).
        allowed : ndarray, uint64, optional
            One packed bitset over the frames ``(ceil(F/64),)`` for all queries, or
            ``(Q, ceil(F/64))``: each query's own (clients with different controls in one
            call). Queries with equal rows share the blocked filter's passes; per segment,
            queries whose bitsets allow the same candidates of it share one.
        exclude : ndarray, bool, optional
            ``(M,)`` for all queries or ``(Q, M)`` per query.
        threads : int, optional
        method : {"auto", "blocked", "per_query"}
            Evaluation strategy (results are identical).
        other : bool
            False: the other distance is left out (0), as in :func:`preselect_table`.

        Returns
        -------
        starts, pose_dist, audio_dist : ndarray [shape=(Q, M)]
            int64, float32, float64; as :func:`preselect_table` per row.
        """
        F, Dp, Da, M = self._shape
        prev = _float_array(prev_poses, "prev_poses", f"(Q, {Dp})", 2)
        if prev.shape[1:] != (Dp,):
            raise ParameterError(f"prev_poses: expected (Q, {Dp}); got {prev.shape}")
        Q = prev.shape[0]
        q = _float_array(query_windows, "query_windows", f"({Q}, n, {Da})", 3)
        if q.shape[0] != Q or q.shape[1] < 1 or q.shape[2] != Da:
            raise ParameterError(f"query_windows: expected ({Q}, n >= 1, {Da}); got {q.shape}")
        W = (F + 63) // 64
        if isinstance(allowed, np.ndarray) and allowed.ndim == 2 and allowed.dtype == np.uint64:
            if allowed.shape != (Q, W):
                raise ParameterError(f"allowed: expected one bitset ({W},) for all queries or ({Q}, {W}) one per "
                                     f"query (F = {F} frames); got shape {allowed.shape}")
            allowed = np.ascontiguousarray(allowed)
        else:
            allowed = _allowed(allowed, F)
        exclude = _exclude(exclude, M, Q)
        if method not in METHODS:
            raise ParameterError(f"method: expected 'auto', 'blocked' or 'per_query'; got {method!r}")
        return self._plan.tables(prev, q, allowed, exclude, _threads(threads), method, bool(other))


def preselect_table_batch(pose, audio, seg_start, seg_len, prev_poses, query_windows, *, preselect="pose",
                          allowed=None, exclude=None, threads=None, method="auto", pose_f16=None,
                          pose_proj=None, other=True):
    """One call of :meth:`PreselectBatch.tables` (nothing kept): (starts, pose_dist,
    audio_dist), each (Q, M), row i exactly :func:`preselect_table`'s for query i."""
    batch = PreselectBatch(pose, audio, seg_start, seg_len, preselect=preselect, pose_f16=pose_f16,
                           pose_proj=pose_proj)
    return batch.tables(prev_poses, query_windows, allowed=allowed, exclude=exclude, threads=threads,
                        method=method, other=other)


def audio_distances(pose, audio, seg_start, seg_len, starts, query_audio):
    """The audio distance (spec step 2) of each segment's given candidate for one query window.

    With pre-selection ``"pose"`` a table's starts and pose distances depend on the previous
    pose and the bitsets only; a step can pre-select before its audio has come and finish with
    this when it has. The values are those of :func:`preselect_table` (the kernel's own
    arithmetic, bit for bit), so the ranks and their ties are the same.

    Parameters
    ----------
    pose, audio, seg_start, seg_len
        The database, as in :func:`gesturedb.search.rank_sum_step`.
    starts : ndarray [shape=(M,)], int64
        Each segment's candidate ``s`` (``1 <= s <= seg_len - n``), -1 for none.
    query_audio : ndarray [shape=(n, Da)], float32
        The step's audio window.

    Returns
    -------
    audio_dist : ndarray [shape=(M,)], float64
        ``1 - <q, a> / (|q| |a|)`` of each candidate's window (1 when a norm is 0), 0 where
        ``starts`` is -1.
    """
    seg_start, seg_len = _check_database(pose, audio, seg_start, seg_len)
    q = _query(query_audio, audio.shape[1], "query_audio")
    s = _starts(starts, seg_start.shape)
    return _core().audio_distances(pose, audio, seg_start, seg_len, s, q)


def gather_windows(pose, audio, seg_start, seg_len, starts, n):
    """Each segment's candidate audio window, copied into one contiguous block.

    A step pre-selected by pose before its audio came gathers its candidates' windows then
    (they lie scattered over the whole audio matrix, a cache and TLB miss each), so that
    finishing it once the audio has come (:func:`window_distances`) reads one block.

    Parameters
    ----------
    pose, audio, seg_start, seg_len
        The database, as in :func:`gesturedb.search.rank_sum_step`.
    starts : ndarray [shape=(M,)], int64
        Each segment's candidate ``s`` (``1 <= s <= seg_len - n``), -1 for none.
    n : int >= 1
        Window length, frames.

    Returns
    -------
    windows : ndarray [shape=(M, n, Da)], float32
        Row ``m``: audio frames ``seg_start[m] + starts[m]`` onwards; zeros where ``starts`` is -1.
    """
    seg_start, seg_len = _check_database(pose, audio, seg_start, seg_len)
    n = _positive_int(n, "n")
    s = _starts(starts, seg_start.shape)
    return _core().gather_windows(pose, audio, seg_start, seg_len, s, n)


def window_distances(windows, starts, query_audio):
    """:func:`audio_distances` over windows gathered by :func:`gather_windows`, bit for bit.

    Parameters
    ----------
    windows : ndarray [shape=(M, n, Da)], float32
        As :func:`gather_windows` returns them.
    starts : ndarray [shape=(M,)], int64
        The starts they were gathered for (-1: none).
    query_audio : ndarray [shape=(n, Da)], float32
        The step's audio window.

    Returns
    -------
    audio_dist : ndarray [shape=(M,)], float64
        As :func:`audio_distances`: 0 where ``starts`` is -1.
    """
    w = np.asarray(windows)
    if w.dtype != np.float32 or w.ndim != 3 or not w.flags.c_contiguous:
        raise ParameterError(f"windows: expected float32 C-contiguous (M, n, Da); got {w.dtype} {w.shape}")
    s = _starts(starts, w.shape[:1])
    q = _query(query_audio, w.shape[2], "query_audio")
    if q.shape[0] != w.shape[1]:
        raise ParameterError(f"query_audio: expected {w.shape[1]} frames as the windows; got {q.shape[0]}")
    return _core().window_distances(w, s, q)


def _starts(starts, shape) -> np.ndarray:
    s = np.asarray(starts)
    if s.dtype != np.int64 or s.shape != tuple(shape):
        raise ParameterError(f"starts: expected int64 {tuple(shape)}; got {s.dtype} {s.shape}")
    return np.ascontiguousarray(s)


def rank_table(starts, pose_dist, audio_dist, *, k=1):
    """Spec steps 4-5 over a pre-selection table (one database's or several shards' concatenated).

    Parameters
    ----------
    starts, pose_dist, audio_dist : ndarray [shape=(M,)]
        As returned by :func:`preselect_table`; row ``m`` is segment ``m``.
    k : int
        The k-th best (1-based); the last one if fewer remain.

    Returns
    -------
    tuple (segment, pose_rank, audio_rank, n_candidates) of int, or None when no segment remains.
    """
    k = _positive_int(k, "k")
    s = np.ascontiguousarray(starts, dtype=np.int64)
    dp = np.ascontiguousarray(pose_dist, dtype=np.float32)
    da = np.ascontiguousarray(audio_dist, dtype=np.float64)
    if s.ndim != 1 or dp.shape != s.shape or da.shape != s.shape:
        raise ParameterError(f"rank_table: expected three (M,) arrays; got {s.shape}, {dp.shape}, {da.shape}")
    # the kernel's own ranker (radix sort, top-list shortcut): the same ranks as a step
    m, rp, ra, K = _core().rank_table(s, dp, da, k)
    return None if m < 0 else (int(m), int(rp), int(ra), int(K))


def top_lists(starts, pose_dist, audio_dist, n):
    """The first ``n`` rows of each table by pose distance and by audio distance.

    Rows are ordered as the ranker ranks them: by distance (-0 equal to +0, every
    NaN last and equal to the others), ties by row index; rows without a
    candidate (start -1) are left out. Position ``r`` of a list is that row's
    rank within its table. A shard sends these lists instead of its table.

    Parameters
    ----------
    starts, pose_dist, audio_dist : ndarray [shape=(M,) or (Q, M)]
        Tables as returned by :func:`preselect_table` (one) or
        :meth:`PreselectBatch.tables` (Q), int64 / float32 / float64.
    n : int >= 1
        List length.

    Returns
    -------
    n_candidates : ndarray [shape=() or (Q,)], int64
        Rows with a candidate.
    by_pose, by_audio : ndarray [shape=(n,) or (Q, n)], int32
        Row indices, first first; -1 past ``n_candidates``.
    """
    n = _positive_int(n, "n")
    s = np.ascontiguousarray(starts, dtype=np.int64)
    dp = np.ascontiguousarray(pose_dist, dtype=np.float32)
    da = np.ascontiguousarray(audio_dist, dtype=np.float64)
    if s.ndim not in (1, 2) or dp.shape != s.shape or da.shape != s.shape:
        raise ParameterError(f"top_lists: expected three (M,) or (Q, M) arrays; got {s.shape}, {dp.shape}, "
                             f"{da.shape}")
    K, bp, ba = _core().table_top_lists(s.reshape(-1, s.shape[-1]), dp.reshape(-1, s.shape[-1]),
                                        da.reshape(-1, s.shape[-1]), n)
    return (K[0], bp[0], ba[0]) if s.ndim == 1 else (K, bp, ba)
