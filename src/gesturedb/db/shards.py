"""Rank-sum search over a database split into shards resident on Dask workers.

Pre-selection (spec steps 1-3) is per segment, so a shard computes the rows of
its own segments exactly as one database would
(:func:`gesturedb.tables.preselect_table`). Ranking (steps 4-5) would need
every row, but the winner can be settled from short lists: a segment outside
the first L rows by pose distance has ``rp >= L``, one outside the first L by
audio distance ``ra >= L``, so any segment with ``R < L`` is in both lists, and
the global first L by either distance are among the shards' own first L. Each
shard therefore sends only its first L rows by each distance, each with the
distance it is ranked by, and the start and next pose of the few rows that can
be the choice (see :func:`_top_lists`); the client merges them, and when
the k-th best of the segments in both global lists has ``R < L`` that is
exactly the step's choice. Otherwise (rare: L grows with the square root of
the segment count, see :func:`top_rows`) the step falls back to the shards'
whole tables, ranked by :func:`gesturedb.tables.rank_table`. Every step
chooses exactly what :func:`gesturedb.search.rank_sum_search` chooses on the
whole database (same instruction set). Per settled step the network carries
the previous pose and the query window out and L rows of 8 bytes, L of 12 and
a few pose rows back, in one round trip, instead of M rows of 20 bytes and a
second round trip for the next pose.
"""
from __future__ import annotations

import contextlib
from collections.abc import Sequence

import numpy as np

from gesturedb import search, tables
from gesturedb.control.bitsets import StepBitsets, full_mask, n_words, slice_bits
from gesturedb.db import cluster, schema
from gesturedb.db.cluster import worker_address
from gesturedb.errors import ParameterError, SchemaError, SearchError

__all__ = ["ShardedSearch", "top_rows"]


class _Shard:
    """One shard on its worker: a slice of frames, its segments, and the projection filter."""

    def __init__(self, pose, audio, seg_start, seg_len, projection):
        self.pose = np.ascontiguousarray(pose, dtype=np.float32)
        self.audio = np.ascontiguousarray(audio, dtype=np.float32)
        self.seg_start = np.ascontiguousarray(seg_start, dtype=np.int64)
        self.seg_len = np.ascontiguousarray(seg_len, dtype=np.int64)
        self.proj = search.PoseProjection(self.pose, half=True) if projection else None
        self._batches = {}

    def batch(self, preselect: str) -> tables.PreselectBatch:
        """The shard's :class:`gesturedb.tables.PreselectBatch` for this mode, made on
        first use and kept: its set-up is a pass over the shard (about 0.4 s at
        2.5M frames) that every later step of every batch search reuses."""
        b = self._batches.get(preselect)
        if b is None:
            b = self._batches[preselect] = tables.PreselectBatch(
                self.pose, self.audio, self.seg_start, self.seg_len, preselect=preselect,
                pose_proj=self.proj if preselect == "pose" else None)
        return b

    def __getstate__(self):
        # should Dask move a shard, the kept set-up (a kernel object, not picklable)
        # is rebuilt where it lands
        state = self.__dict__.copy()
        state["_batches"] = {}
        return state


def _make_shard(pose, audio, seg_start, seg_len, projection):
    return _Shard(pose, audio, seg_start, seg_len, projection)


def _load_shard(path, expected, n_frames, Dp, Da, seg_start, seg_len, projection):
    """On the worker: read a shard file's features (``gesturedb shard``) and keep them resident.

    The worker checks the file itself (``expected``: :func:`gesturedb.db.schema.shard_expected`;
    n_frames rows of Dp pose and Da audio values): the client checked its own view of the
    folder when it opened the index, but a worker on another machine reads its own copy, and
    a stale one would search other frames without a word.
    """
    import h5py

    shapes = {schema.POSE_FEATURES: (n_frames, Dp), schema.AUDIO_FEATURES: (n_frames, Da)}
    problem = schema.shard_file_problem(path, expected, shapes)
    if problem is not None:
        raise SchemaError(path, f"on Dask worker {worker_address()}: {problem}. Every worker must see the "
                                f"index's shard files at the same paths as the client (a shared or copied folder)")
    with h5py.File(path, "r") as h5:
        pose, audio = h5[schema.POSE_FEATURES][()], h5[schema.AUDIO_FEATURES][()]
    return _Shard(pose, audio, seg_start, seg_len, projection)


def _shard_table(shard, prev, q, preselect, allowed_row, exclude, threads):
    allowed = None if allowed_row is None else _decode_row(allowed_row)
    return tables.preselect_table(shard.pose, shard.audio, shard.seg_start, shard.seg_len, prev, q,
                                  preselect=preselect, allowed=allowed, exclude=exclude, threads=threads,
                                  pose_proj=shard.proj if preselect == "pose" else None)


def _order_keys(x: np.ndarray) -> np.ndarray:
    """Unsigned keys that order as the ranking compares (the kernel's ``order_key``):
    -0 equals +0, every NaN sorts last and equal to the others."""
    x = x + x.dtype.type(0)  # -0 -> +0
    u = x.view(np.uint32 if x.dtype == np.float32 else np.uint64)
    top = u.dtype.type(1) << u.dtype.type(8 * u.itemsize - 1)
    k = np.where((u & top) != 0, ~u, u | top)
    k[np.isnan(x)] = np.iinfo(u.dtype).max
    return k


def _top_lists(s, dp, da, top: int) -> list:
    """Tables' first ``top`` rows by each distance, as a shard sends them, one per table.

    ``s``, ``dp``, ``da``: (Q, M) tables. Each item is (K, pose_rows, pose_dist,
    audio_rows, audio_dist, keep, keep_start): K the segments with a candidate; each
    list's rows (int32, in rank order: :func:`gesturedb.tables.top_lists`) with only the
    distance it is ranked by; ``keep`` (int32, ascending) the rows that can be the step's
    choice, with their starts. A segment chosen from the lists has a rank sum R below
    ``top`` over all shards, so also over its own shard's rows (a rank there counts fewer
    rows): ``keep`` is the rows in both lists with a local rank sum below ``top``, or every
    row when the shard has at most ``top`` (the client then ranks them all). 8 + 12 bytes a
    list row where whole table rows were 28, and starts and next poses for a few rows
    instead of every row in both lists.
    """
    Ks, bps, bas = tables.top_lists(s, dp, da, top)
    rank = np.full(s.shape[1], top, np.int64)  # a row's local pose rank; `top` outside the pose list
    out = []
    for i in range(s.shape[0]):
        K = int(Ks[i])
        bp, ba = bps[i, :min(K, top)], bas[i, :min(K, top)]
        if K <= top:
            keep = np.flatnonzero(s[i] >= 0).astype(np.int32)
        else:
            rank[bp] = np.arange(bp.size)
            keep = np.sort(ba[rank[ba] + np.arange(ba.size) < top])  # in both lists, R below `top`
            rank[bp] = top
        out.append((K, bp, dp[i, bp], ba, da[i, ba], keep, s[i, keep].astype(np.int32)))
    return out


def _shard_top_batch(shard, prevs, wins, preselect, allowed_row, exclude, threads, top):
    """On the worker: for each query of one step (previous poses (Q, Dp), windows
    (Q, n, Da)), :func:`_top_lists` of the shard's table and the pose each of its kept
    rows would continue from, (len(keep), Dp). The tables come from one
    blocked kernel call of the shard's kept :class:`gesturedb.tables.PreselectBatch`."""
    if prevs.shape[0] == 1:  # one query: the single step, whose threads share its segments
        s, dp, da = (x[None] for x in _shard_table(shard, prevs[0], wins[0], preselect, allowed_row,
                                                     None if exclude is None else exclude.reshape(-1), threads))
    else:
        allowed = None if allowed_row is None else _decode_row(allowed_row)
        s, dp, da = shard.batch(preselect).tables(prevs, wins, allowed=allowed, exclude=exclude, threads=threads)
    return [lists + (shard.pose[shard.seg_start[lists[5]] + lists[6] + wins.shape[1] - 1],)
            for lists in _top_lists(s, dp, da, top)]


def top_rows(n_segments: int, k: int = 1) -> int:
    """Rows per distance each shard sends (L): ``max(256, ceil(4 sqrt(k M)))``.

    With pose and audio ranks independent and uniform, about ``r^2 / 2M``
    segments have ``R <= r``, so the k-th smallest R is near ``sqrt(2 k M)``;
    at ``L = 4 sqrt(k M)`` about 8k segments are expected below L and a step
    is rarely left unsettled (ranks that agree, as real pose and audio partly
    do, settle sooner). 256 is the kernel ranker's own top-list length.
    """
    return int(max(256, np.ceil(4.0 * np.sqrt(float(k) * float(max(n_segments, 1))))))


def _merge_tops(replies, seg_ranges, top: int, k: int):
    """The step's choice from the shards' lists (:func:`_top_lists` plus next poses), or None
    when they do not settle it.

    Returns (m, start, pose_rank, audio_rank, K, pose_dist, audio_dist, next_pose),
    m = -1 when no segment has a candidate.
    """
    K = sum(int(r[0]) for r in replies)
    if K == 0:
        return (-1,) + (0,) * 7
    pm = np.concatenate([r[1].astype(np.int64) + a for r, (a, _) in zip(replies, seg_ranges)])
    dp = np.concatenate([r[2] for r in replies])
    am = np.concatenate([r[3].astype(np.int64) + a for r, (a, _) in zip(replies, seg_ranges)])
    da = np.concatenate([r[4] for r in replies])
    if all(int(r[0]) <= top for r in replies):
        # every shard sent all its rows: rank them as they are (in segment order)
        op, oa = np.argsort(pm, kind="stable"), np.argsort(am, kind="stable")
        m = pm[op]
        c, rp, ra, _ = tables.rank_table(np.zeros(m.size, np.int64), dp[op], da[oa], k=k)
        seg, pdist, adist = int(m[c]), float(dp[op][c]), float(da[oa][c])
    else:
        if k >= K:
            return None  # "the last" of fewer than k: needs every row's rank
        # the global first `top` by each distance are among the shards' first `top`
        p_order = np.lexsort((pm, _order_keys(dp)))[:top]
        a_order = np.lexsort((am, _order_keys(da)))[:top]
        both, ip, ia = np.intersect1d(pm[p_order], am[a_order], assume_unique=True, return_indices=True)
        if both.size < k:
            return None
        R = ip + ia
        c = np.lexsort((ip, R))[k - 1]  # (R, rp) orders them; rp is unique
        # every segment outside both lists has R >= top
        if R[c] >= top:
            return None
        seg, rp, ra = int(both[c]), int(ip[c]), int(ia[c])
        pdist, adist = float(dp[p_order[ip[c]]]), float(da[a_order[ia[c]]])
    j = next(j for j, (a, b) in enumerate(seg_ranges) if a <= seg < b)
    keep = replies[j][5]
    i = int(np.searchsorted(keep, seg - seg_ranges[j][0]))
    # its local rank sum is at most its global one: its shard kept it (see _top_lists)
    assert i < keep.size and keep[i] == seg - seg_ranges[j][0], (seg, j)
    return seg, int(replies[j][6][i]), rp, ra, K, pdist, adist, replies[j][7][i]


def _shard_row(shard, f):
    return shard.pose[f].copy()


class _ShardActor:
    """What a step calls on a shard, run on the shard's worker as a Dask actor.

    A task goes from the client to the scheduler to the worker and back through Dask's
    batched streams, which hold each message up to their send interval (10 ms on the
    client's): a round trip of two trivial tasks took 13 ms on the 2-core test machine
    (median of 50), two actor calls 2.6 ms. An actor call goes straight from the client to
    the worker holding the shard (the scheduler only placed it there).
    """

    nthreads: int = 1  # the worker's threads, set there (declared here for the client's proxy)

    def __init__(self, shard: _Shard):
        self.shard = shard
        # an actor's calls run one at a time on a thread of its own, not on the worker's
        # threads as tasks do: the kernel takes the worker's threads instead
        self.nthreads = cluster.this_worker_threads()

    def top_batch(self, prevs, wins, preselect, allowed_row, exclude, threads, top):
        return _shard_top_batch(self.shard, prevs, wins, preselect, allowed_row, exclude,
                                threads or self.nthreads, top)

    def table(self, prev, q, preselect, allowed_row, exclude, threads):
        return _shard_table(self.shard, prev, q, preselect, allowed_row, exclude, threads or self.nthreads)

    def row(self, f):
        return _shard_row(self.shard, f)


def _encode_row(words: np.ndarray, n_frames: int) -> tuple:
    """A shard's allowed row for the wire: its packed words, or, when fewer than
    one word in 8 differs from all set (the repeat guard clears a few recent
    windows of an otherwise full row) or from all clear (a keyword
    sub-database), only the positions and values of the words that do."""
    for kind, base in (("set", full_mask(n_frames)), ("clear", None)):
        idx = np.flatnonzero(words != (0 if base is None else base))
        if 8 * idx.size < words.size:
            return kind, n_frames, idx.astype(np.int32), words[idx]
    return "words", n_frames, words


def _decode_row(row: tuple) -> np.ndarray:
    kind, n_frames = row[0], row[1]
    if kind == "words":
        return row[2]
    out = full_mask(n_frames) if kind == "set" else np.zeros(n_words(n_frames), np.uint64)
    out[row[2]] = row[3]
    return out


class ShardedSearch:
    """A database's search data split by segments into ``parts`` shards on a Dask cluster.

    Parameters
    ----------
    pose, audio, seg_start, seg_len
        The whole database, as for :func:`gesturedb.search.rank_sum_search`
        (cut here into shards, each sent to one worker; kept by reference, not
        copied, to send a shard again should its worker be lost).
    scheduler : distributed.Client or str
        The Dask cluster: a client the caller owns, or ``"local:N"`` / ``"tcp://HOST:PORT"``
        (connected, or started, here and let go by :meth:`close`), as everywhere in gesturedb
        (:mod:`gesturedb.db.cluster`).
    parts : int >= 1
        Number of shards: contiguous runs of segments of about equal frame counts.
    projection : bool
        Each shard builds its :class:`gesturedb.search.PoseProjection` (same results).
    threads : int or None
        Kernel threads per call on a shard; None: as many as its worker has (``dask worker
        --nthreads 8`` gives its shard 8; each worker of a ``local:N`` cluster has one). A
        shard's calls run one after another on its actor's thread, so these threads are
        what a batch's chunks of queries share.
    top_rows : int or None
        Rows per distance each shard sends per step (L); None: :func:`top_rows`
        of the segment count and k. Any L >= 1 gives the same results; a small
        one makes more steps fall back to whole tables.

    Attributes
    ----------
    steps, unsettled : int
        Steps searched so far, and those the top lists did not settle.
    """

    def __init__(self, pose, audio, seg_start, seg_len, *, scheduler, parts: int = 2,
                 projection: bool = True, threads: int | None = None, top_rows: int | None = None):
        seg_start = np.ascontiguousarray(seg_start, dtype=np.int64)
        seg_len = np.ascontiguousarray(seg_len, dtype=np.int64)
        M = seg_start.shape[0]
        if isinstance(parts, bool) or not isinstance(parts, (int, np.integer)) or not 1 <= parts <= max(M, 1):
            raise ParameterError(f"parts: expected an int in [1, {M}] (segments); got {parts!r}")
        self.F, self.Dp, self.Da = pose.shape[0], pose.shape[1], audio.shape[1]
        self.seg_start, self.seg_len = seg_start, seg_len
        self._set_options(threads, top_rows)
        # cut between segments so that every shard has about F / parts frames of segments
        cum = np.cumsum(seg_len)
        cuts = [0] + [int(np.searchsorted(cum, cum[-1] * i / parts, side="left")) + 1 for i in range(1, parts)] + [M]
        cuts = np.maximum.accumulate(np.minimum(cuts, M))
        self.seg_ranges = [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
        self.frame_ranges, self._recipes = [], []
        for a, b in self.seg_ranges:
            f0 = int(seg_start[a:b].min())
            f1 = int((seg_start[a:b] + seg_len[a:b]).max())
            self.frame_ranges.append((f0, f1))
            # the caller's arrays, not copies: sliced (and sent) again if the shard's worker is lost
            self._recipes.append(("arrays", (pose, audio, f0, f1, seg_start[a:b] - f0, seg_len[a:b], projection)))
        self._start(scheduler)

    def _start(self, scheduler) -> None:
        """Connect to (or start) the cluster and place every shard on it."""
        self._cluster = contextlib.ExitStack()
        try:
            self.client = self._cluster.enter_context(cluster.dask_client(scheduler))
            self._place_all()
        except BaseException:
            self._cluster.close()
            raise

    @classmethod
    def from_shard_files(cls, entries, seg_start, seg_len, *, n_frames: int, Dp: int, Da: int, scheduler,
                         projection: bool = True, threads: int | None = None,
                         top_rows: int | None = None) -> "ShardedSearch":
        """One shard per shard file of an index (``gesturedb shard``), each read by its worker.

        The client never holds the feature matrices: each worker opens its shard file,
        so the files must be reachable at the same paths from the workers (a shared or
        copied folder).

        Parameters
        ----------
        entries : list of dict
            :attr:`gesturedb.db.database.Database.shard_entries` (``file``, ``frames``).
        seg_start, seg_len : ndarray of int64, shape (M,)
            Segments in frame order; each must lie inside one shard (true of every
            segment kind: shards hold whole recordings).
        n_frames, Dp, Da : int
            The database's frame count and feature sizes.
        """
        seg_start = np.ascontiguousarray(seg_start, dtype=np.int64)
        seg_len = np.ascontiguousarray(seg_len, dtype=np.int64)
        f0s = np.array([e["frames"][0] for e in entries], dtype=np.int64)
        f1s = np.array([e["frames"][1] for e in entries], dtype=np.int64)
        owner = np.searchsorted(f0s, seg_start, side="right") - 1
        bad = np.flatnonzero((owner < 0) | (seg_start + seg_len > f1s[np.maximum(owner, 0)]))
        if bad.size:
            m = int(bad[0])
            raise ParameterError(f"segment {m} (frames {seg_start[m]}..{seg_start[m] + seg_len[m]}): expected it "
                                 f"inside one shard file, but it crosses a shard boundary")
        if (np.diff(owner) < 0).any():
            raise ParameterError("seg_start: expected segments in frame order for a sharded search")
        self = cls.__new__(cls)
        self.F, self.Dp, self.Da = int(n_frames), int(Dp), int(Da)
        self.seg_start, self.seg_len = seg_start, seg_len
        self._set_options(threads, top_rows)
        self.seg_ranges, self.frame_ranges, self._recipes = [], [], []
        for i, e in enumerate(entries):
            a, b = (int(v) for v in np.searchsorted(owner, [i, i + 1], side="left"))
            if b == a:
                continue  # a shard without segments of this kind takes no part in the search
            f0 = int(e["frames"][0])
            self.seg_ranges.append((a, b))
            self.frame_ranges.append((f0, int(e["frames"][1])))
            self._recipes.append(("file", (e["file"], schema.shard_expected(entries, i), int(e["frames"][1]) - f0,
                                           self.Dp, self.Da, seg_start[a:b] - f0, seg_len[a:b], projection)))
        self._start(scheduler)
        return self

    def _place_all(self) -> None:
        """Every shard on a worker, in turn by address (as many shards per worker as it takes)."""
        workers = cluster.worker_addresses(self.client)
        n = len(self._recipes)
        self.shards, self._actor_futures, self._workers = [None] * n, [None] * n, [None] * n
        for j in range(n):
            self._place(j, workers[j % len(workers)] if workers else None)

    def _place(self, j: int, worker) -> None:
        """Set shard ``j`` up on ``worker`` (an address; None: where Dask likes) from its recipe,
        and its actor beside it, holding the shard without a copy. Both are resolved at the
        first call, so that a shard's own error (a stale file, say) is raised there."""
        kind, args = self._recipes[j]
        if kind == "arrays":
            pose, audio, f0, f1, st, ln, projection = args
            # the frames and segments are sent to the worker, each as an object of its own
            self.shards[j] = cluster.place(self.client, _make_shard, projection, worker=worker,
                                           send=(pose[f0:f1], audio[f0:f1], st, ln))
        else:
            self.shards[j] = cluster.place(self.client, _load_shard, *args, worker=worker)
        self._actor_futures[j] = cluster.place_actor(self.client, _ShardActor, self.shards[j], worker=worker)
        self._workers[j] = worker
        self._actors = None

    def _wait(self, j: int, f):
        """The result of call ``f`` to shard ``j``. OSError when the worker did not answer, or has
        left the cluster: asked every second while waiting, since a call to a lost actor whose
        shard Dask cannot set up again (no worker left) would wait for it forever."""
        while True:
            try:
                return f.result(timeout=1.0)
            except TimeoutError:
                if self._workers[j] is not None and self._workers[j] not in self._live_workers():
                    raise OSError(f"worker {self._workers[j]} left the cluster") from None

    def _live_workers(self) -> set:
        """The scheduler's workers now (the client's own view lags behind by seconds)."""
        return cluster.live_workers(self.client)

    def _replace_lost(self, j: int, timeout: float = 30.0) -> bool:
        """After a call to shard ``j`` failed for want of its worker: once the scheduler has
        dropped that worker, set every shard it held up again on the workers left (the one
        with the fewest shards first). False if the worker is still listed after ``timeout``
        seconds or none is left."""
        import time

        deadline = time.monotonic() + timeout
        alive = self._live_workers()
        while self._workers[j] in alive:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.1)
            alive = self._live_workers()
        if not alive:
            return False
        for i, w in enumerate(self._workers):
            if w is not None and w not in alive:
                load = {a: sum(x == a for x in self._workers) for a in alive}
                self._place(i, min(sorted(alive), key=load.__getitem__))
        return True

    def _on_shards(self, calls: list) -> list:
        """Run ``calls``, (shard index, method of :class:`_ShardActor`, args) each, on the shards'
        actors at once; their results in order.

        A worker lost since the shards were set up (its machine restarted, say) took its shards
        and actors with it. They are then set up again on the workers left (a shard file read
        again there, or the shard's frames sent again from this process) and the calls run
        once more; if that cannot be done, or fails too, a one-line error names the shard.
        """
        for attempt in (0, 1):
            if self._actors is None:
                self._actors = [f.result() for f in self._actor_futures]
            futs, out = [], []
            j = 0
            try:
                for j, name, args in calls:
                    futs.append(getattr(self._actors[j], name)(*args))  # raises once Dask knows the worker is gone
                for (j, _, _), f in zip(calls, futs):
                    out.append(self._wait(j, f))
                return out
            except (RuntimeError, OSError) as exc:
                if isinstance(exc, RuntimeError) and self._actor_futures[j].status == "finished":
                    raise  # the method's own error
                if attempt == 0 and self._replace_lost(j):
                    continue
                raise SearchError(f"shard {j + 1} of {len(self.shards)}: its Dask worker was lost during the search "
                                  f"({exc}), and no other worker could take the shard") from exc
        raise AssertionError("unreachable")

    @classmethod
    def for_database(cls, db, seg_start, seg_len, *, scheduler, parts: int = 2, **kw) -> "ShardedSearch":
        """The shards of an open database: an index file (``gesturedb shard``) is searched
        over its own shard files, each read by a worker (:meth:`from_shard_files`);
        a single file is cut into ``parts`` shards sent from this process.

        Parameters
        ----------
        db : gesturedb.db.database.Database
        seg_start, seg_len : ndarray of int64, shape (M,)
            The segments searched (e.g. ``db.chunks``' starts and lengths).
        scheduler, parts, **kw
            As for the constructor.
        """
        if db.shard_entries:
            return cls.from_shard_files(db.shard_entries, seg_start, seg_len, n_frames=db.n_frames,
                                        Dp=db.frame_shape("pose_features")[1],
                                        Da=db.frame_shape("audio_features")[1], scheduler=scheduler, **kw)
        return cls(db.pose_features, db.audio_features, seg_start, seg_len, scheduler=scheduler, parts=parts, **kw)

    def _set_options(self, threads, top) -> None:
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, (int, np.integer))
                                    or threads < 1):
            raise ParameterError(f"threads: expected None or an int >= 1; got {threads!r}")
        self.threads = None if threads is None else int(threads)
        if top is not None and (isinstance(top, bool) or not isinstance(top, (int, np.integer)) or top < 1):
            raise ParameterError(f"top_rows: expected None or an int >= 1; got {top!r}")
        self.top_rows = None if top is None else int(top)
        self.steps = self.unsettled = 0

    def search(self, query_audio, init_pose, *, step=8, k=1, preselect="pose", allowed=None,
               exclude=None) -> search.SearchResult:
        """Exactly :func:`gesturedb.search.rank_sum_search` on the whole database."""
        q = np.ascontiguousarray(query_audio, dtype=np.float32)
        if q.ndim != 2 or q.shape[1] != self.Da or q.shape[0] < 1:
            raise ParameterError(f"query_audio: expected (T >= 1, {self.Da}); got {q.shape}")
        prev = np.ascontiguousarray(init_pose, dtype=np.float32)
        if prev.shape != (self.Dp,):
            raise ParameterError(f"init_pose: expected ({self.Dp},); got {prev.shape}")
        return self._search_many([q], prev[None], np.array([int(k)]), int(step), preselect, allowed,
                                 None if exclude is None else np.asarray(exclude, dtype=bool), batch=False)[0]

    def search_batch(self, queries: Sequence, init_poses, *, step=8, k=1, preselect="pose",
                     allowed=None, exclude=None) -> list[search.SearchResult]:
        """Exactly :func:`gesturedb.search.rank_sum_search_batch` on the whole database
        (``k`` and ``exclude`` may be per query, as there).

        All queries advance step by step together: per step each shard pre-selects
        for chunks of queries in one blocked kernel call and sends each query's top
        lists, so a step costs one round trip for the whole batch, not one per query.
        """
        Q = len(queries)
        if Q == 0:
            return []
        ks = np.broadcast_to(np.asarray(k), (Q,)).astype(np.int64)
        if ks.min() < 1:
            raise ParameterError(f"k: expected >= 1; got {int(ks.min())}")
        qs = []
        for i, q in enumerate(queries):
            q = np.ascontiguousarray(q, dtype=np.float32)
            if q.ndim != 2 or q.shape[1] != self.Da or q.shape[0] < 1:
                raise ParameterError(f"queries[{i}]: expected (T >= 1, {self.Da}); got {q.shape}")
            qs.append(q)
        init = np.ascontiguousarray(init_poses, dtype=np.float32)
        if init.shape != (Q, self.Dp):
            raise ParameterError(f"init_poses: expected ({Q}, {self.Dp}); got {init.shape}")
        return self._search_many(qs, init, ks, int(step), preselect, allowed,
                                 None if exclude is None else np.asarray(exclude, dtype=bool), batch=True)

    def _search_many(self, qs, init, ks, N, preselect, allowed, ex, *, batch):
        """Searches advancing step by step together; errors name the query when ``batch``."""
        Q = len(qs)
        prev = list(init)
        S = np.array([-(-q.shape[0] // N) for q in qs])
        rows = None
        if allowed is not None:
            if not isinstance(allowed, StepBitsets):  # which reads like (S, W) without building it
                allowed = np.asarray(allowed, dtype=np.uint64)
            if allowed.ndim not in (1, 2) or allowed.shape[-1] != n_words(self.F):
                raise ParameterError(f"allowed: expected packed bitsets of {n_words(self.F)} words ({self.F} frames), "
                                     f"(W,) or one row per step (S, W); got shape {allowed.shape}")
            if allowed.ndim == 2 and len(set(S.tolist())) > 1:
                raise ParameterError("allowed: a per-step schedule needs every query to have the same number of "
                                     f"steps; got {S.min()} to {S.max()} steps")
            rows = [allowed[i] if allowed.ndim == 2 else allowed for i in
                    range(int(S.max()) if allowed.ndim == 2 else 1)]
        out = [{f: np.zeros(S[i], np.int64) for f in ("segments", "starts", "frames", "lengths", "out_frames",
                                                      "pose_rank", "audio_rank", "n_candidates")}
               | {"pose_dist": np.zeros(S[i]), "audio_dist": np.zeros(S[i])} for i in range(Q)]
        top = self.top_rows if self.top_rows is not None else top_rows(self.seg_start.shape[0], int(ks.max()))
        failed: dict[int, tuple[int, int, int]] = {}
        for st in range(int(S.max())):
            t = st * N
            bits = None if rows is None else rows[st if len(rows) > 1 else 0]
            # each shard gets its own frames' bits, packed (sparse when nearly all set or clear)
            shard_rows = None if bits is None else [_encode_row(slice_bits(bits, f0, f1), f1 - f0)
                                                    for f0, f1 in self.frame_ranges]
            live = [i for i in range(Q) if st < S[i] and i not in failed]
            groups: dict[int, list[int]] = {}
            for i in live:  # windows of equal length share a kernel call (the last may be shorter)
                groups.setdefault(min(N, qs[i].shape[0] - t), []).append(i)
            calls, owners = [], []
            for n, idx in groups.items():
                for j, (a, b) in enumerate(self.seg_ranges):
                    # about 64 MB of tables per call on the worker
                    chunk = int(np.clip((64 << 20) // (20 * max(b - a, 1)), 16, 256))
                    for c0 in range(0, len(idx), chunk):
                        ids = idx[c0:c0 + chunk]
                        e = None if ex is None else (ex[ids][:, a:b] if ex.ndim == 2 else ex[a:b])
                        calls.append((j, "top_batch", (
                            np.stack([prev[i] for i in ids]), np.stack([qs[i][t:t + n] for i in ids]), preselect,
                            None if shard_rows is None else shard_rows[j], e, self.threads, top)))
                        owners.append(ids)
            replies: dict[int, list] = {i: [] for i in live}
            # calls are made shard by shard within each group: replies stay in shard order
            for ids, res in zip(owners, self._on_shards(calls)):
                for i, r in zip(ids, res):
                    replies[i].append(r)
            for i in live:
                n = min(N, qs[i].shape[0] - t)
                got = _merge_tops(replies[i], self.seg_ranges, top, int(ks[i]))
                self.steps += 1
                e = None if ex is None else (ex[i] if ex.ndim == 2 else ex)
                if got is None:
                    self.unsettled += 1
                    got = self._whole_tables(prev[i], qs[i][t:t + n], preselect, shard_rows, e, int(ks[i]))
                m, start, rp, ra, K, pose_dist, audio_dist, nxt = got
                if m < 0:
                    failed[i] = (st, t, n)
                    continue
                g = int(self.seg_start[m] + start)
                for f, v in (("segments", m), ("starts", start), ("frames", g), ("lengths", n),
                             ("out_frames", t), ("pose_rank", rp), ("audio_rank", ra), ("n_candidates", K),
                             ("pose_dist", pose_dist), ("audio_dist", audio_dist)):
                    out[i][f][st] = v
                prev[i] = nxt if nxt is not None else self._row(m, g + n - 1)
        if failed:
            i = min(failed)
            st, t, n = failed[i]
            row = None if allowed is None else (allowed[st] if allowed.ndim == 2 else allowed)
            err = search._no_candidate_error(st, t, n, self.seg_len,
                                             None if ex is None else (ex[i] if ex.ndim == 2 else ex), row,
                                             query=i if batch else None)
            if len(failed) > 1:
                err.args = (err.args[0] + f" ({len(failed)} of {Q} queries failed)",)
            raise err
        return [search.SearchResult(n_frames=qs[i].shape[0], **out[i]) for i in range(Q)]

    def _whole_tables(self, prev, q, preselect, shard_rows, exclude, k):
        """A step ranked over every shard's whole table (when the top lists do not settle it)."""
        parts = self._on_shards([
            (j, "table", (prev, q, preselect, None if shard_rows is None else shard_rows[j],
                          None if exclude is None else exclude[a:b], self.threads))
            for j, (a, b) in enumerate(self.seg_ranges)])
        s = np.concatenate([x[0] for x in parts])
        dp = np.concatenate([x[1] for x in parts])
        da = np.concatenate([x[2] for x in parts])
        r = tables.rank_table(s, dp, da, k=k)
        if r is None:
            return (-1,) + (0,) * 7
        return r[0], int(s[r[0]]), r[1], r[2], r[3], float(dp[r[0]]), float(da[r[0]]), None

    def _row(self, m, g):
        """Pose row ``g`` (a global frame of segment m) from the shard holding it."""
        j = next(j for j, (a, b) in enumerate(self.seg_ranges) if a <= m < b)
        return self._on_shards([(j, "row", (g - self.frame_ranges[j][0],))])[0]

    def close(self) -> None:
        """Release the shards on the workers."""
        try:
            cluster.cancel(self.client, self._actor_futures + self.shards)
        finally:
            self.shards, self._actor_futures, self._workers, self._actors = [], [], [], None
            self._cluster.close()
