"""The search steps of many live streams in one call (issue 39: many real-time streams on one server).

A :class:`gesturedb.synth.matching.Stream` runs a step in three parts: prepare
(:meth:`~gesturedb.synth.matching.Stream.next_step`: the step's audio rows, previous pose and
allowed bitsets), search and apply (:meth:`~gesturedb.synth.matching.Stream.complete_step`).
:class:`StepBatch` is the search part for the steps of many streams at once: one pass of the
blocked kernel over the database serves every step of a batch (each candidate row read once
per block of steps instead of once per step), and each step gets exactly the window its stream
would have chosen alone.

How a batch stays exact. Each stream's step has its own bitset: its control, and the repeat
guard, which clears the frames of the stream's recent windows (:mod:`gesturedb.synth.repeats`).
Pre-selection (spec steps 1-3) is per segment and a segment reads only the bits of its own
frames, so

1. the steps of one window length and pre-selection mode are one call of
   :meth:`gesturedb.tables.PreselectBatch.tables`, each step with its control's bitset (the
   kernel takes one per query: per segment, the steps whose controls allow the same candidates
   share a pass of the blocked filter, and the database is read once for all of them), each
   excluding the few segments its recent windows touch: every other segment sees the same bits
   with or without the guard;
2. each step's touched segments are pre-selected alone under its guarded bitset
   (:func:`gesturedb.tables.preselect_table` with every other segment excluded) and put
   into its table;
3. the table is ranked by the kernel's own ranker (:func:`gesturedb.tables.rank_table`, as the
   shards merge theirs).

A step that the guard leaves without a candidate, a stream searching over a Dask cluster,
and a batch call that fails for any reason take the stream's own search
(:meth:`~gesturedb.synth.matching.Stream.search_step`): one stream's failure is its own.
"""
from __future__ import annotations

import threading
from collections.abc import Callable, Sequence

import numpy as np

from gesturedb import tables
from gesturedb.errors import ParameterError
from gesturedb.search import SearchResult

__all__ = ["StepBatch"]


class StepBatch:
    """Search prepared steps (:class:`gesturedb.synth.matching.StepQuery`) of many streams at once.

    Parameters
    ----------
    searcher : gesturedb.synth.Searcher
        The searcher the streams share (their database, segments and pose projection);
        steps of streams over another searcher are searched by their own stream.
    method : {"auto", "blocked", "per_query"}
        The kernel's strategy for the shared pre-selection (results are identical;
        ``"auto"`` blocks from :func:`gesturedb.search.blocked_min_queries` steps on: 3 a thread).
    threads : int, optional
        Worker threads of the kernel (default: the CPUs this process may use).

    Calls from several threads are safe; a server calls it from one, a batch at a time.
    """

    def __init__(self, searcher, *, method: str = "auto", threads: int | None = None):
        if method not in tables.METHODS:
            raise ParameterError(f"method: expected one of {', '.join(tables.METHODS)}; got {method!r}")
        self.searcher = searcher
        self.method, self.threads = method, threads
        self._batches: dict[str, tables.PreselectBatch] = {}
        self._lock = threading.Lock()
        start, length = searcher.seg_start, searcher.seg_len
        self._sorted = bool(np.all(start[1:] >= start[:-1]))
        self._max_len = int(length.max(initial=0))
        #: steps searched in batches, steps searched alone (a fallback), batch calls made
        self.n_batched = self.n_alone = self.n_calls = 0

    # -- the search -----------------------------------------------------------------
    def search(self, steps: Sequence) -> list:
        """Search every step of ``steps`` (StepQuery of any streams, at most one per stream).

        Returns
        -------
        list
            Per step, in order: ``(res, relaxed)`` as its stream's
            :meth:`~gesturedb.synth.matching.Stream.search_step` returns them (a one-step
            :class:`gesturedb.search.SearchResult` and whether the repeat guard was relaxed),
            or the exception that call raises (a :class:`gesturedb.errors.SearchError` when the
            step has no candidate): bit for bit what each stream gets alone, whatever the other
            steps of the call are.
        """
        out: list = [None] * len(steps)
        groups: dict[tuple, list[int]] = {}
        for j, sq in enumerate(steps):
            if self._batchable(sq):
                groups.setdefault((sq.stream.options.preselect, sq.n), []).append(j)
        for (preselect, _), idx in groups.items():
            try:
                got = self._search_group([steps[j] for j in idx], preselect)
            except Exception:  # noqa: BLE001 - whatever one step brought, each step is searched alone below
                continue  # (with its own outcome, its own error), so that no stream fails for another
            for j, r in zip(idx, got):
                out[j] = r
        for j, sq in enumerate(steps):
            if out[j] is None:
                out[j] = self._alone(sq)
        return out

    def _batchable(self, sq) -> bool:
        # a Dask searcher searches its shards; another searcher has other segments
        return sq.stream.searcher is self.searcher and self.searcher._client is None

    def _alone(self, sq):
        self.n_alone += 1
        try:
            return sq.stream.search_step(sq)
        except Exception as exc:  # noqa: BLE001 - returned to its own stream, which raises it
            return exc

    def _preselect_batch(self, preselect: str) -> tables.PreselectBatch:
        with self._lock:
            if preselect not in self._batches:
                s, db = self.searcher, self.searcher.db
                self._batches[preselect] = tables.PreselectBatch(
                    db.pose_features, db.audio_features, s.seg_start, s.seg_len, preselect=preselect,
                    pose_f16=s._half, pose_proj=s.pose_projection() if preselect == "pose" else None)
            return self._batches[preselect]

    def _search_group(self, group: list, preselect: str) -> list:
        """Steps of one pre-selection mode and length, each under its control's bitset: ``(res, False)``
        per step, or None where the guard leaves no candidate (that step then runs alone)."""
        windows = np.stack([sq.query for sq in group]).astype(np.float32, copy=False)
        out = []
        for sq, (st, dp, da) in zip(group, self._tables(group, preselect, windows)):
            out.append(self._ranked(sq, st, dp, da))
        return out

    def _tables(self, group: list, preselect: str, windows: np.ndarray, *, other: bool = True) -> list:
        """Each step's pre-selection table ``(starts, pose_dist, audio_dist)``, (M,) each, under its guarded
        bitset: one batch call for all, then the segments its recent windows touch, each step alone.
        ``other=False``: without the other distance (0; :func:`gesturedb.tables.preselect_table`)."""
        s, db = self.searcher, self.searcher.db
        M = s.seg_start.shape[0]
        touched = [self._touched(sq.recent) for sq in group]
        exclude = np.zeros((len(group), M), dtype=bool)
        for r, (sq, tm) in enumerate(zip(group, touched)):
            if sq.stream._excl is not None:
                exclude[r] = sq.stream._excl
            exclude[r, tm] = True
        prevs = np.stack([sq.prev for sq in group]).astype(np.float32, copy=False)
        rows = {None if sq.row is None else sq.row.tobytes() for sq in group}
        if len(rows) == 1:  # one control (or none) for all: one bitset
            allowed = group[0].row
        else:  # one per step (every frame where a step has none); equal rows share the filter's passes
            allowed = np.stack([sq.allowed for sq in group])
        starts, pose_d, audio_d = self._preselect_batch(preselect).tables(
            prevs, windows, allowed=allowed, exclude=exclude, threads=self.threads, method=self.method, other=other)
        self.n_calls += 1
        proj = s.pose_projection() if preselect == "pose" else None
        out = []
        for r, (sq, tm) in enumerate(zip(group, touched)):
            st, dp, da = starts[r], pose_d[r], audio_d[r]
            if tm.size:
                # the touched segments under the step's guarded bitset, each alone
                only = np.ones(M, dtype=bool)
                only[tm] = False
                if sq.stream._excl is not None:
                    only |= sq.stream._excl
                s1, dp1, da1 = tables.preselect_table(
                    db.pose_features, db.audio_features, s.seg_start, s.seg_len, sq.prev, windows[r],
                    preselect=preselect, allowed=sq.guarded, exclude=only, threads=self.threads,
                    pose_f16=s._half, pose_proj=proj, other=other)
                st[tm], dp[tm], da[tm] = s1[tm], dp1[tm], da1[tm]
            out.append((st, dp, da))
        return out

    def _ranked(self, sq, st, dp, da):
        """``(res, False)`` of step ``sq`` ranked over its table, or None when the table has no candidate."""
        got = tables.rank_table(st, dp, da, k=sq.stream.options.k)
        if got is None:
            return None
        m, rp, ra, K = got
        start = int(st[m])

        def one(v, dtype=np.int64):
            return np.array([v], dtype=dtype)

        seg_start = self.searcher.seg_start
        res = SearchResult(segments=one(m), starts=one(start), frames=one(int(seg_start[m]) + start),
                           lengths=one(sq.n), out_frames=one(0), pose_dist=one(float(dp[m]), np.float64),
                           audio_dist=one(float(da[m]), np.float64), pose_rank=one(rp), audio_rank=one(ra),
                           n_candidates=one(K), n_frames=sq.n)
        self.n_batched += 1
        return res, False

    # -- pose pre-selection ahead of the audio ------------------------------------------
    def speculate(self, steps: Sequence, *, ready: Callable[[int, tuple], None] | None = None) -> list:
        """Pre-select the coming steps of streams before their audio has come.

        With pre-selection ``"pose"`` a step's table, but for its audio distances, depends on its
        previous pose, its bitsets and its length only (spec steps 1-3): all known once the step
        before it is applied. ``steps`` are such steps (:meth:`gesturedb.synth.matching.Stream.upcoming_step`,
        ``query`` empty); all are pre-selected in one call of the blocked kernel. ``ready(j, table)``, when
        given, is called (from this thread) with each step's table as soon as it is complete, in the order
        of ``steps`` within a window length: a server hands it over at once, since that step's speech may
        have come while the others' windows are gathered.

        Returns
        -------
        list
            Per step: ``(starts, pose_dist, windows)``, (M,) int64, (M,) float32 and (M, n, Da) float32
            (each candidate's audio window, :func:`gesturedb.tables.gather_windows`: about 4 MB at paper
            scale), the table that :meth:`finish` completes once the step's audio is there; or None where
            the step cannot be finished so (its stream searches another way, its guard leaves no
            candidate, or the call failed): that step is searched as usual.
        """
        out: list = [None] * len(steps)
        groups: dict[int, list[int]] = {}
        for j, sq in enumerate(steps):
            if self._batchable(sq) and sq.stream.options.preselect == "pose":
                groups.setdefault(sq.n, []).append(j)
        s, db = self.searcher, self.searcher.db
        Da = db.audio_features.shape[1]
        for n, idx in groups.items():
            group = [steps[j] for j in idx]
            # any window gives the same starts and pose distances; its audio distances, which finish computes
            # once the audio has come, are left out (a third of the call at paper scale)
            windows = np.zeros((len(group), n, Da), dtype=np.float32)
            try:
                got = self._tables(group, "pose", windows, other=False)
            except Exception:  # noqa: BLE001 - those steps are searched as usual, each with its own outcome
                continue
            for j, (st, dp, _) in zip(idx, got):
                if not (st >= 0).any():  # the guard is relaxed: the usual search handles it
                    continue
                try:
                    # the candidates' windows lie scattered over the audio matrix (4 MB of 35 at paper
                    # scale): read them now, off the path, so that finish reads one contiguous block
                    win = tables.gather_windows(db.pose_features, db.audio_features, s.seg_start, s.seg_len,
                                                st, n)
                except Exception:  # noqa: BLE001 - that step is searched as usual
                    continue
                out[j] = (st, dp, win)
                if ready is not None:
                    ready(j, out[j])
        return out

    def finish(self, sq, table) -> tuple:
        """``(res, relaxed)`` of step ``sq`` (its audio now there) from its speculative ``table`` (one of
        :meth:`speculate`'s, for a step with the same inputs but the audio): the audio distances of the
        pre-selected candidates and the ranks, bit for bit what :meth:`search` gives."""
        st, dp, win = table
        da = tables.window_distances(win, st, np.ascontiguousarray(sq.query, dtype=np.float32))
        return self._ranked(sq, st, dp, da)

    def _touched(self, recent: list) -> np.ndarray:
        """Segments (indices) that read a bit of the frame ranges ``recent`` (``[a, b)`` each): segment m
        reads the bits of frames ``[seg_start + 1, seg_start + seg_len - 1]`` (first and last frames of its
        candidate windows). Taking one too many would only cost time; none is missed."""
        if not recent:
            return np.zeros(0, dtype=np.int64)
        start, length = self.searcher.seg_start, self.searcher.seg_len
        hits = []
        for a, b in recent:
            lo, hi = 0, start.shape[0]
            if self._sorted:  # only segments starting within a longest segment before the range can reach it
                lo = int(np.searchsorted(start, a - self._max_len, side="left"))
                hi = int(np.searchsorted(start, b, side="left"))
            m = np.arange(lo, hi)
            first, last = start[lo:hi] + 1, start[lo:hi] + length[lo:hi] - 1
            hits.append(m[(first < b) & (last >= a)])
        return np.unique(np.concatenate(hits))
