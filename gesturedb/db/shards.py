"""Rank-sum search over a database split into shards resident on Dask workers.

Pre-selection (spec steps 1-3) is per segment, so a shard computes the rows of
its own segments exactly as one database would
(:func:`gesturedb.search.preselect_table`); ranking (steps 4-5) needs every
row, so the client concatenates the shards' tables in global segment order and
ranks them (:func:`gesturedb.search.rank_table`). Every step therefore chooses
exactly what :func:`gesturedb.search.rank_sum_search` chooses on the whole
database (same instruction set). Per step the network carries the previous
pose and the query window out, and M rows of 20 bytes plus one pose row back.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gesturedb import search
from gesturedb.errors import ParameterError

__all__ = ["ShardedSearch"]


class _Shard:
    """One shard on its worker: a slice of frames, its segments, and the projection filter."""

    def __init__(self, pose, audio, seg_start, seg_len, projection):
        self.pose = np.ascontiguousarray(pose, dtype=np.float32)
        self.audio = np.ascontiguousarray(audio, dtype=np.float32)
        self.seg_start = np.ascontiguousarray(seg_start, dtype=np.int64)
        self.seg_len = np.ascontiguousarray(seg_len, dtype=np.int64)
        self.proj = search.PoseProjection(self.pose, half=True) if projection else None


def _make_shard(pose, audio, seg_start, seg_len, projection):
    return _Shard(pose, audio, seg_start, seg_len, projection)


def _load_shard(path, seg_start, seg_len, projection):
    """On the worker: read a shard file's features (``gesturedb shard``) and keep them resident."""
    import h5py

    with h5py.File(path, "r") as h5:
        pose, audio = h5["frames/pose_features"][()], h5["frames/audio_features"][()]
    return _Shard(pose, audio, seg_start, seg_len, projection)


def _shard_table(shard, prev, q, preselect, allowed_bits, exclude, threads):
    allowed = None if allowed_bits is None else _pack(allowed_bits)
    return search.preselect_table(shard.pose, shard.audio, shard.seg_start, shard.seg_len, prev, q,
                                  preselect=preselect, allowed=allowed, exclude=exclude, threads=threads,
                                  pose_proj=shard.proj if preselect == "pose" else None)


def _shard_row(shard, f):
    return shard.pose[f].copy()


def _pack(bits: np.ndarray) -> np.ndarray:
    """bool (F,) -> packed uint64 words (bit f & 63 of word f >> 6)."""
    n = -(-bits.shape[0] // 64) * 64
    b = np.zeros(n, bool)
    b[:bits.shape[0]] = bits
    return np.packbits(b, bitorder="little").view(np.uint64).copy()


def _unpack(words: np.ndarray, F: int) -> np.ndarray:
    return np.unpackbits(np.ascontiguousarray(words).view(np.uint8), bitorder="little")[:F].astype(bool)


class ShardedSearch:
    """A database's search data split by segments into ``parts`` shards on a Dask cluster.

    Parameters
    ----------
    pose, audio, seg_start, seg_len
        The whole database, as for :func:`gesturedb.search.rank_sum_search`
        (read once here to cut the shards; each shard then lives on one worker).
    client : distributed.Client
    parts : int >= 1
        Number of shards: contiguous runs of segments of about equal frame counts.
    projection : bool
        Each shard builds its :class:`gesturedb.search.PoseProjection` (same results).
    threads : int
        Kernel threads per shard step (1: parallelism comes from the workers).
    """

    def __init__(self, pose, audio, seg_start, seg_len, *, client, parts: int = 2,
                 projection: bool = True, threads: int = 1):
        seg_start = np.ascontiguousarray(seg_start, dtype=np.int64)
        seg_len = np.ascontiguousarray(seg_len, dtype=np.int64)
        M = seg_start.shape[0]
        if isinstance(parts, bool) or not isinstance(parts, (int, np.integer)) or not 1 <= parts <= max(M, 1):
            raise ParameterError(f"parts: expected an int in [1, {M}] (segments); got {parts!r}")
        self.client = client
        self.F, self.Dp, self.Da = pose.shape[0], pose.shape[1], audio.shape[1]
        self.seg_start, self.seg_len = seg_start, seg_len
        self.threads = int(threads)
        # cut between segments so that every shard has about F / parts frames of segments
        cum = np.cumsum(seg_len)
        cuts = [0] + [int(np.searchsorted(cum, cum[-1] * i / parts, side="left")) + 1 for i in range(1, parts)] + [M]
        cuts = np.maximum.accumulate(np.minimum(cuts, M))
        self.seg_ranges = [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
        workers = sorted(client.scheduler_info()["workers"])
        self.frame_ranges, self.shards = [], []
        for i, (a, b) in enumerate(self.seg_ranges):
            f0 = int(seg_start[a:b].min())
            f1 = int((seg_start[a:b] + seg_len[a:b]).max())
            self.frame_ranges.append((f0, f1))
            w = [workers[i % len(workers)]] if workers else None
            args = [client.scatter(x, workers=w) for x in
                    (pose[f0:f1], audio[f0:f1], seg_start[a:b] - f0, seg_len[a:b])]
            self.shards.append(client.submit(_make_shard, *args, projection, workers=w, pure=False))

    @classmethod
    def from_shard_files(cls, entries, seg_start, seg_len, *, n_frames: int, Dp: int, Da: int, client,
                         projection: bool = True, threads: int = 1) -> "ShardedSearch":
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
        self.client = client
        self.F, self.Dp, self.Da = int(n_frames), int(Dp), int(Da)
        self.seg_start, self.seg_len = seg_start, seg_len
        self.threads = int(threads)
        workers = sorted(client.scheduler_info()["workers"])
        self.seg_ranges, self.frame_ranges, self.shards = [], [], []
        for i, e in enumerate(entries):
            a, b = (int(v) for v in np.searchsorted(owner, [i, i + 1], side="left"))
            if b == a:
                continue  # a shard without segments of this kind takes no part in the search
            f0 = int(e["frames"][0])
            self.seg_ranges.append((a, b))
            self.frame_ranges.append((f0, int(e["frames"][1])))
            w = [workers[len(self.shards) % len(workers)]] if workers else None
            self.shards.append(client.submit(_load_shard, e["file"], seg_start[a:b] - f0, seg_len[a:b], projection,
                                             workers=w, pure=False))
        return self

    def search(self, query_audio, init_pose, *, step=8, k=1, preselect="pose", allowed=None,
               exclude=None) -> search.SearchResult:
        """Exactly :func:`gesturedb.search.rank_sum_search` on the whole database."""
        q = np.ascontiguousarray(query_audio, dtype=np.float32)
        if q.ndim != 2 or q.shape[1] != self.Da or q.shape[0] < 1:
            raise ParameterError(f"query_audio: expected (T >= 1, {self.Da}); got {q.shape}")
        prev = np.ascontiguousarray(init_pose, dtype=np.float32)
        if prev.shape != (self.Dp,):
            raise ParameterError(f"init_pose: expected ({self.Dp},); got {prev.shape}")
        N = int(step)
        T = q.shape[0]
        S = -(-T // N)
        rows = None
        if allowed is not None:
            allowed = np.asarray(allowed, dtype=np.uint64)
            rows = [_unpack(allowed[i] if allowed.ndim == 2 else allowed, self.F) for i in
                    range(S if allowed.ndim == 2 else 1)]
        exclude = None if exclude is None else np.asarray(exclude, dtype=bool)
        out = {f: np.zeros(S, np.int64) for f in ("segments", "starts", "frames", "lengths", "out_frames",
                                                  "pose_rank", "audio_rank", "n_candidates")}
        out["pose_dist"] = np.zeros(S)
        out["audio_dist"] = np.zeros(S)
        for i in range(S):
            t = i * N
            n = min(N, T - t)
            bits = None if rows is None else rows[i if len(rows) > 1 else 0]
            futs = []
            for sh, (a, b), (f0, f1) in zip(self.shards, self.seg_ranges, self.frame_ranges):
                futs.append(self.client.submit(
                    _shard_table, sh, prev, q[t:t + n], preselect, None if bits is None else bits[f0:f1],
                    None if exclude is None else exclude[a:b], self.threads, pure=False))
            tables = self.client.gather(futs)
            s = np.concatenate([x[0] for x in tables])
            dp = np.concatenate([x[1] for x in tables])
            da = np.concatenate([x[2] for x in tables])
            r = search.rank_table(s, dp, da, k=k)
            if r is None:
                row = None if allowed is None else (allowed[i] if allowed.ndim == 2 else allowed)
                raise search._no_candidate_error(i, t, n, self.seg_len, exclude, row)
            m, rp, ra, K = r
            g = int(self.seg_start[m] + s[m])
            for f, v in (("segments", m), ("starts", s[m]), ("frames", g), ("lengths", n), ("out_frames", t),
                         ("pose_rank", rp), ("audio_rank", ra), ("n_candidates", K),
                         ("pose_dist", float(dp[m])), ("audio_dist", float(da[m]))):
                out[f][i] = v
            j = next(j for j, (a, b) in enumerate(self.seg_ranges) if a <= m < b)
            # the next window continues from the last frame this one copies
            prev = self.client.submit(_shard_row, self.shards[j], g + n - 1 - self.frame_ranges[j][0],
                                      pure=False).result()
        return search.SearchResult(n_frames=T, **out)

    def search_batch(self, queries: Sequence, init_poses, *, step=8, k=1, preselect="pose",
                     allowed=None, exclude=None) -> list[search.SearchResult]:
        """Exactly :func:`gesturedb.search.rank_sum_search_batch` on the whole database
        (``k`` and ``exclude`` may be per query, as there)."""
        Q = len(queries)
        ks = np.broadcast_to(np.asarray(k), (Q,))
        ex = None if exclude is None else np.asarray(exclude, dtype=bool)
        return [self.search(queries[i], init_poses[i], step=step, k=int(ks[i]), preselect=preselect,
                            allowed=allowed,
                            exclude=None if ex is None else (ex[i] if ex.ndim == 2 else ex))
                for i in range(Q)]

    def close(self) -> None:
        """Release the shards on the workers."""
        self.client.cancel(self.shards)
        self.shards = []
