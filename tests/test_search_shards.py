"""Sharded search on a LocalCluster: exactly the single-machine results."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb import search
from gesturedb.db.shards import ShardedSearch
from test_search import assert_same_search, continuous_db, exact_db, pack_bits


def test_rank_table_merges_shard_tables_exactly():
    """Ranks over concatenated per-shard tables equal the kernel's step on the whole database."""
    rng = np.random.default_rng(11)
    P, A, st, ln = exact_db(rng, Dp=5)
    q = rng.integers(-2, 3, size=(8, A.shape[1])).astype(np.float32)
    for prev in (P[3], P[40], P[100]):
        for k in (1, 2, 5, 1000):
            s, dp, da = search.preselect_table(P, A, st, ln, prev, q)
            want = search.rank_sum_step(P, A, st, ln, prev, q, k=k)
            m, rp, ra, K = search.rank_table(s, dp, da, k=k)
            assert (m, s[m], rp, ra, K) == (want.segment, want.start, want.pose_rank, want.audio_rank,
                                            want.n_candidates)
            assert float(dp[m]) == want.pose_dist and float(da[m]) == want.audio_dist


@pytest.mark.parametrize("parts", [2, 3])
def test_sharded_search_random_data(dask_client, parts):
    rng = np.random.default_rng(12 + parts)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=40)
    F, M = P.shape[0], st.shape[0]
    q = rng.standard_normal((50, A.shape[1])).astype(np.float32)
    sh = ShardedSearch(P, A, st, ln, client=dask_client, parts=parts)
    try:
        assert len(sh.shards) == parts
        allowed = pack_bits(rng.random(F) < 0.3)
        exclude = rng.random(M) < 0.3
        for kw in (dict(), dict(k=3), dict(preselect="audio", k=2), dict(allowed=allowed, exclude=exclude)):
            assert_same_search(sh.search(q, P[5], **kw), search.rank_sum_search(P, A, st, ln, q, P[5], **kw),
                               str(kw))
        qs = [q[:20], q[5:40]]
        init = np.stack([P[0], P[9]])
        for a, b in zip(sh.search_batch(qs, init, k=[1, 2]),
                        search.rank_sum_search_batch(P, A, st, ln, qs, init, k=np.array([1, 2]))):
            assert_same_search(a, b)
    finally:
        sh.close()


@pytest.mark.parametrize("parts", [2, 3])
def test_sharded_search_real_database(dask_client, scott_db, parts):
    P = np.ascontiguousarray(scott_db.pose_features[:], dtype=np.float32)
    A = np.ascontiguousarray(scott_db.audio_features[:], dtype=np.float32)
    st = np.ascontiguousarray(scott_db.h5["chunks/start"][:], dtype=np.int64)
    ln = np.ascontiguousarray(scott_db.h5["chunks/length"][:], dtype=np.int64)
    rng = np.random.default_rng(20)
    q = rng.standard_normal((120, A.shape[1])).astype(np.float32)
    sh = ShardedSearch(P, A, st, ln, client=dask_client, parts=parts)
    try:
        for kw in (dict(), dict(k=2)):
            assert_same_search(sh.search(q, P[10], **kw), search.rank_sum_search(P, A, st, ln, q, P[10], **kw))
    finally:
        sh.close()
