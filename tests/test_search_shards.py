"""Sharded search on a LocalCluster: exactly the single-machine results."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb import search, tables
from gesturedb.control import StepBitsets
from gesturedb.db.shards import ShardedSearch
from gesturedb.errors import ParameterError
from test_search import assert_same_search, continuous_db, exact_db, pack_bits


def test_rank_table_merges_shard_tables_exactly():
    """Ranks over concatenated per-shard tables equal the kernel's step on the whole database."""
    rng = np.random.default_rng(11)
    P, A, st, ln = exact_db(rng, Dp=5)
    q = rng.integers(-2, 3, size=(8, A.shape[1])).astype(np.float32)
    for prev in (P[3], P[40], P[100]):
        for k in (1, 2, 5, 1000):
            s, dp, da = tables.preselect_table(P, A, st, ln, prev, q)
            want = search.rank_sum_step(P, A, st, ln, prev, q, k=k)
            m, rp, ra, K = tables.rank_table(s, dp, da, k=k)
            assert (m, s[m], rp, ra, K) == (want.segment, want.start, want.pose_rank, want.audio_rank,
                                            want.n_candidates)
            assert float(dp[m]) == want.pose_dist and float(da[m]) == want.audio_dist


def _numpy_rank(s, dp, da, k):
    """Spec steps 4-5 written independently in numpy (lexsort: last key primary, ties by m)."""
    m = np.flatnonzero(s >= 0)
    if m.size == 0:
        return None
    K = m.size
    rp = np.empty(K, np.int64)
    rp[np.lexsort((m, dp[m].astype(np.float64) + 0.0))] = np.arange(K)
    ra = np.empty(K, np.int64)
    ra[np.lexsort((m, da[m] + 0.0))] = np.arange(K)
    c = np.lexsort((m, rp, rp + ra))[min(k, K) - 1]
    return int(m[c]), int(rp[c]), int(ra[c]), K


@pytest.mark.parametrize("M", [1, 7, 300, 5000])
def test_rank_table_matches_numpy_with_ties_and_gaps(M):
    rng = np.random.default_rng(M)
    for trial in range(20):
        s = np.where(rng.random(M) < 0.8, rng.integers(1, 50, M), -1).astype(np.int64)
        dp = rng.integers(0, 4 if trial % 2 else 1000, M).astype(np.float32)  # many exact ties
        da = rng.integers(0, 5, M) / 4.0 if trial % 3 else rng.random(M)
        dp[rng.random(M) < 0.05] = -0.0
        for k in (1, 2, 17, M + 3):
            assert tables.rank_table(s, dp, da, k=k) == _numpy_rank(s, dp, da, k), (trial, k)
    assert tables.rank_table(np.full(3, -1), np.zeros(3, np.float32), np.zeros(3), k=1) is None


@pytest.mark.parametrize("M", [1, 6, 300, 5000])
def test_top_lists_are_the_rankers_order(M):
    """The kernel's top lists are the first rows by (distance, row), -0 equal to +0 and NaN
    last (numpy oracle: the keys the merge uses), rows without a candidate left out, -1
    past them; one table or several at once."""
    from gesturedb.db.shards import _order_keys

    rng = np.random.default_rng(40 + M)
    Q = 7
    s = np.where(rng.random((Q, M)) < 0.8, rng.integers(1, 50, (Q, M)), -1).astype(np.int64)
    dp = rng.integers(0, 4, (Q, M)).astype(np.float32)  # many ties
    dp[1] = rng.random(M)
    dp[rng.random((Q, M)) < 0.05] = -0.0
    dp[rng.random((Q, M)) < 0.02] = np.nan
    da = rng.integers(0, 6, (Q, M)) / 4.0
    da[rng.random((Q, M)) < 0.02] = np.nan
    s[2] = -1  # a table without candidates
    for n in (1, 3, 256, M + 5):
        K, bp, ba = tables.top_lists(s, dp, da, n)
        assert bp.shape == ba.shape == (Q, n) and bp.dtype == np.int32
        for q in range(Q):
            valid = np.flatnonzero(s[q] >= 0)
            assert K[q] == valid.size
            for got, x in ((bp[q], dp[q]), (ba[q], da[q])):
                want = valid[np.lexsort((valid, _order_keys(x[valid])))][:n]
                np.testing.assert_array_equal(got[:want.size], want)
                assert (got[want.size:] == -1).all()
        one = tables.top_lists(s[1], dp[1], da[1], n)
        assert one[0] == K[1]
        np.testing.assert_array_equal(one[1], bp[1])
        np.testing.assert_array_equal(one[2], ba[1])
    with pytest.raises(ParameterError, match="top_lists: expected three"):
        tables.top_lists(s, dp[:, :-1] if M > 1 else dp[:1], da, 4)
    with pytest.raises(ParameterError, match="n"):
        tables.top_lists(s, dp, da, 0)


@pytest.mark.parametrize("parts", [2, 3])
def test_sharded_search_random_data(dask_client, parts):
    rng = np.random.default_rng(12 + parts)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=40)
    F, M = P.shape[0], st.shape[0]
    q = rng.standard_normal((50, A.shape[1])).astype(np.float32)
    sh = ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=parts)
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


def test_steps_call_each_shard_directly(dask_client):
    """Steps go to the shards' actors, straight to their workers: once the shards are set up, a
    search runs no Dask task (a task's round trip passes the scheduler's batched streams: 13 ms
    for two trivial tasks on the 2-core test machine, against 2.6 ms for two actor calls), the
    fallback to whole tables and its row fetch included; each actor lives on its shard's worker."""
    import distributed

    rng = np.random.default_rng(31)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=40)
    q = rng.standard_normal((50, A.shape[1])).astype(np.float32)
    sh = ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=2, top_rows=2)  # lists too short to settle all
    try:
        sh.search(q[:8], P[5])
        with distributed.get_task_stream(dask_client) as stream:
            one = sh.search(q, P[5], k=2)
            many = sh.search_batch([q, q[10:]], np.stack([P[5], P[7]]))
        assert stream.data == []
        assert 0 < sh.unsettled < sh.steps
        assert_same_search(one, search.rank_sum_search(P, A, st, ln, q, P[5], k=2))
        for a, b in zip(many, search.rank_sum_search_batch(P, A, st, ln, [q, q[10:]], np.stack([P[5], P[7]]))):
            assert_same_search(a, b)
        who = dask_client.who_has(sh.shards + sh._actor_futures)
        held = [who[f.key] for f in sh.shards]
        assert [who[f.key] for f in sh._actor_futures] == held and len({w for ws in held for w in ws}) == 2
    finally:
        sh.close()


def test_a_shard_takes_its_workers_threads():
    """Without ``threads`` a shard's kernel calls take as many threads as its worker has (an
    actor's calls run one at a time, so a batch's chunks no longer spread over the worker's
    threads as tasks did); the results are the same with any count."""
    import distributed

    rng = np.random.default_rng(33)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=40)
    qs = [rng.standard_normal((30, A.shape[1])).astype(np.float32) for _ in range(3)]
    init = P[[3, 9, 27]]
    ref = search.rank_sum_search_batch(P, A, st, ln, qs, init)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=3, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        for threads, used in ((None, 3), (1, 1), (2, 2)):
            sh = ShardedSearch(P, A, st, ln, scheduler=client, parts=2, threads=threads)
            try:
                for a, b in zip(sh.search_batch(qs, init), ref):
                    assert_same_search(a, b)
                assert_same_search(sh.search(qs[0], init[0]), ref[0])
                assert [a.nthreads for a in sh._actors] == [3, 3] and (sh.threads or 3) == used
            finally:
                sh.close()
        for bad in (0, 1.5, True):
            with pytest.raises(ParameterError, match="threads: expected None or an int >= 1"):
                ShardedSearch(P, A, st, ln, scheduler=client, parts=2, threads=bad)


def test_shards_with_equal_segment_arrays_keep_their_own_data():
    """Equal 64-frame segments cut in 2 give both shards the same local segment arrays. Scattered
    under keys made from their content, the second shard's copy shared the first's key, and the
    first shard's release could take it: 1 of 10 constructions lost its actor's dependency (2 of
    2 on the mirrored database of test_two_hosts). Each scatter now has a key of its own."""
    from distributed import Client

    from gesturedb.db.cluster import local_cluster

    rng = np.random.default_rng(35)
    M = 40
    P = rng.standard_normal((64 * M, 24), dtype=np.float32)
    A = rng.standard_normal((64 * M, 14), dtype=np.float32)
    st, ln = np.arange(M, dtype=np.int64) * 64, np.full(M, 64, np.int64)
    q = rng.standard_normal((24, 14), dtype=np.float32)
    ref = search.rank_sum_search(P, A, st, ln, q, P[1])
    with local_cluster(2, memory_limit=0) as cluster, Client(cluster) as client:
        for _ in range(30):
            sh = ShardedSearch(P, A, st, ln, scheduler=client, parts=2)
            try:
                assert_same_search(sh.search(q, P[1]), ref)
            finally:
                sh.close()


def test_a_lost_worker_gives_its_shards_to_the_others():
    """A worker process killed between steps (its nanny starts a new one at another address): the
    next step sets its shard up again on the workers there are and the search goes on, exactly
    as one process searches; the shard is no longer on the dead worker."""
    import os
    import signal

    from distributed import Client

    from gesturedb.db.cluster import local_cluster

    rng = np.random.default_rng(32)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=40)
    q = rng.standard_normal((24, A.shape[1])).astype(np.float32)
    ref = search.rank_sum_search(P, A, st, ln, q, P[5])
    with local_cluster(2, memory_limit=0) as cluster, Client(cluster) as client:
        sh = ShardedSearch(P, A, st, ln, scheduler=client, parts=2)
        assert_same_search(sh.search(q, P[5]), ref)
        dead = client.who_has(sh.shards[1])[sh.shards[1].key][0]
        os.kill(client.run(os.getpid, workers=[dead])[dead], signal.SIGKILL)
        assert_same_search(sh.search(q, P[5]), ref)
        where = client.who_has(sh.shards)
        assert dead not in {w for f in sh.shards for w in where[f.key]}
        assert_same_search(sh.search_batch([q, q[4:]], np.stack([P[5], P[8]]))[1],
                           search.rank_sum_search(P, A, st, ln, q[4:], P[8]))


def test_no_worker_left_is_a_one_line_error():
    """Every worker gone: a SearchError naming the shard, not Dask's error from an actor call."""
    import time

    import distributed

    from gesturedb.errors import SearchError

    rng = np.random.default_rng(34)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=20)
    q = rng.standard_normal((16, A.shape[1])).astype(np.float32)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        sh = ShardedSearch(P, A, st, ln, scheduler=client, parts=2)
        sh.search(q, P[1])
        cluster.scale(0)
        for _ in range(300):
            if not client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.workers)):
                break
            time.sleep(0.1)
        with pytest.raises(SearchError, match=r"^shard [12] of 2: its Dask worker was lost during the search .*"
                                              r"no other worker could take the shard"):
            sh.search(q, P[1])


@pytest.mark.parametrize("parts", [2, 3])
def test_sharded_search_real_database(dask_client, scott_db, parts):
    P = np.ascontiguousarray(scott_db.pose_features[:], dtype=np.float32)
    A = np.ascontiguousarray(scott_db.audio_features[:], dtype=np.float32)
    st = np.ascontiguousarray(scott_db.h5["chunks/start"][:], dtype=np.int64)
    ln = np.ascontiguousarray(scott_db.h5["chunks/length"][:], dtype=np.int64)
    rng = np.random.default_rng(20)
    q = rng.standard_normal((120, A.shape[1])).astype(np.float32)
    sh = ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=parts)
    try:
        for kw in (dict(), dict(k=2)):
            assert_same_search(sh.search(q, P[10], **kw), search.rank_sum_search(P, A, st, ln, q, P[10], **kw))
    finally:
        sh.close()


def test_synthesis_over_shards_is_identical(dask_client, scott_db, scott_dir):
    from gesturedb.synth import Searcher

    speech = scott_dir / "inputs/2_scott_0_2_2.wav"
    a = Searcher(scott_db).synthesize(speech, k=2, smooth=False)
    for parts in (2, 3):
        b = Searcher(scott_db, client=dask_client, parts=parts).synthesize(speech, k=2, smooth=False)
        assert a.steps == b.steps
        np.testing.assert_array_equal(a.positions, b.positions)


def test_cli_synth_with_a_scheduler(scott_db_path, scott_dir, tmp_path):
    from gesturedb.cli.main import main

    speech = scott_dir / "inputs/2_scott_0_2_2.wav"
    out_a, out_b = tmp_path / "a.bvh", tmp_path / "b.bvh"
    assert main(["synth", str(scott_db_path), "--audio", str(speech), "-o", str(out_a)]) == 0
    assert main(["synth", str(scott_db_path), "--audio", str(speech), "-o", str(out_b),
                 "--scheduler", "local:1", "--parts", "3"]) == 0
    assert out_a.read_bytes() == out_b.read_bytes()


def _split_replies(s, dp, da, cuts, top):
    """What the shards of a table cut at ``cuts`` would send (next poses: the segment index)."""
    from gesturedb.db.shards import _top_lists

    replies = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        [lists] = _top_lists(s[None, a:b], dp[None, a:b], da[None, a:b], top)
        replies.append(lists + ((lists[5] + a).astype(np.float32)[:, None],))
    return replies, list(zip(cuts[:-1], cuts[1:]))


@pytest.mark.parametrize("M", [5, 300, 4000])
def test_top_list_merge_is_exact_or_says_unsettled(M):
    """The shards' top lists settle a step exactly as ranking every row does (numpy
    oracle), with ties, -0, NaN and segments without a candidate; when they cannot
    (small L, or k beyond the lists) the merge says so instead of guessing."""
    from gesturedb.db.shards import _merge_tops, _order_keys

    x = np.array([-0.0, 0.0, -1.5, 2.0, np.nan, np.inf, -np.inf], np.float32)
    assert (np.argsort(_order_keys(x), kind="stable") == [6, 2, 0, 1, 3, 5, 4]).all()
    assert _order_keys(x)[0] == _order_keys(x)[1]
    rng = np.random.default_rng(M)
    outcomes = {"settled": 0, "complete": 0, "unsettled": 0}
    for trial in range(40):
        s = np.where(rng.random(M) < 0.85, rng.integers(1, 50, M), -1).astype(np.int64)
        dp = (rng.integers(0, 5, M) if trial % 2 else rng.random(M)).astype(np.float32)  # ties
        da = rng.integers(0, 7, M) / 4.0 if trial % 3 == 0 else rng.random(M)
        if trial % 4 == 1:  # agreeing ranks, as real pose and audio partly are
            da = dp.astype(np.float64) + 0.3 * rng.random(M)
        dp[rng.random(M) < 0.03] = -0.0
        dp[rng.random(M) < 0.01] = np.nan
        da[rng.random(M) < 0.01] = np.nan
        parts = 1 + trial % 4
        cuts = sorted({0, M, *rng.integers(0, M, parts - 1).tolist()})
        for top in (1, 3, 16, 256, M):
            for k in (1, 2, 5, M + 2):
                replies, ranges = _split_replies(s, dp, da, np.array(cuts), top)
                got = _merge_tops(replies, ranges, top, k)
                want = _numpy_rank(s, dp, da, k)
                if got is None:
                    outcomes["unsettled"] += 1
                    continue
                if want is None:
                    assert got[0] == -1
                    continue
                m, start, rp, ra, K, pdist, adist, nxt = got
                assert (m, rp, ra, K) == want, (trial, top, k)
                assert start == s[m] and nxt[0] == m
                np.testing.assert_equal([pdist, adist], [dp[m], da[m]])
                outcomes["complete" if all(r[0] <= top for r in replies) else "settled"] += 1
    # every path ran (a test that cannot fall back or settle proves nothing)
    assert outcomes["settled"] > 0 or M <= 16 * 4, outcomes
    assert outcomes["complete"] > 0 and (outcomes["unsettled"] > 0 or M <= 5), outcomes


def test_top_rows_grows_with_the_database():
    from gesturedb.db.shards import top_rows

    assert top_rows(100) == 256 and top_rows(78_000) == 1118 and top_rows(78_000, k=4) == 2235
    assert top_rows(844_000) > top_rows(84_000) > 256


@pytest.mark.parametrize("top", [1, 4, None])
def test_sharded_search_top_lists_settle_or_fall_back_exactly(dask_client, top):
    """Whether the shards' top lists settle a step or it falls back to whole tables,
    the search is the single-machine one; with L = 1 or 4 both paths run."""
    rng = np.random.default_rng(31)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=60)
    q = rng.standard_normal((80, A.shape[1])).astype(np.float32)
    sh = ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=3, top_rows=top)
    try:
        for kw in (dict(), dict(k=2), dict(preselect="audio")):
            assert_same_search(sh.search(q, P[7], **kw), search.rank_sum_search(P, A, st, ln, q, P[7], **kw),
                               str(kw))
        assert sh.steps == 30
        if top == 4:
            assert 0 < sh.unsettled < sh.steps, (sh.unsettled, sh.steps)
        if top is None:
            assert sh.unsettled == 0  # 60 segments: every shard sends all its rows
    finally:
        sh.close()
    with pytest.raises(Exception, match="top_rows"):
        ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=2, top_rows=0)


@pytest.mark.parametrize("isa", search.kernels())
@pytest.mark.parametrize("method", ["blocked", "per_query"])
def test_preselect_table_batch_rows_are_the_single_tables(isa, method):
    """Each row of the batched table is preselect_table's for that query alone: ties,
    empty segments, a shared mask, per-query exclusion, pose and audio pre-selection,
    with and without the projection filter, windows shorter than N."""
    rng = np.random.default_rng(41)
    P, A, st, ln = exact_db(rng, Dp=24, Da=3, n_segments=60)
    F, M = P.shape[0], st.shape[0]
    Q = 37  # more than 16 (blocked) and not a multiple of the 64-lane panel
    prevs = P[rng.integers(0, F, Q)]
    allowed = pack_bits(rng.random(F) < 0.6)
    exclude = rng.random((Q, M)) < 0.2
    proj = search.PoseProjection(P)
    with search.simd(isa):
        for n in (8, 3):
            wins = rng.integers(-2, 3, size=(Q, n, A.shape[1])).astype(np.float32)
            for kw in (dict(), dict(preselect="audio"), dict(allowed=allowed, exclude=exclude),
                       dict(pose_proj=proj, allowed=allowed)):
                s, dp, da = tables.preselect_table_batch(P, A, st, ln, prevs, wins, method=method, **kw)
                assert s.shape == dp.shape == da.shape == (Q, M)
                for i in range(Q):
                    one = dict(kw)
                    if "exclude" in one:
                        one["exclude"] = exclude[i]
                    want = tables.preselect_table(P, A, st, ln, prevs[i], wins[i], **one)
                    for got, w in zip((s[i], dp[i], da[i]), want):
                        np.testing.assert_array_equal(got, w, err_msg=f"{isa} {method} n={n} {kw.keys()} q{i}")
                # without the other distance (other=False, a pose pre-selection ahead of its audio): the same
                # starts and pre-selection distances, the other distance 0, alone and batched
                pose = kw.get("preselect", "pose") == "pose"
                s0, dp0, da0 = tables.preselect_table_batch(P, A, st, ln, prevs, wins, method=method, other=False,
                                                            **kw)
                one = {k: (v[0] if k == "exclude" else v) for k, v in kw.items()}
                alone = tables.preselect_table(P, A, st, ln, prevs[0], wins[0], other=False, **one)
                for got in ((s0, dp0, da0), tuple(x[None] for x in alone)):
                    rows = slice(None) if got[0].shape[0] == Q else slice(0, 1)
                    np.testing.assert_array_equal(got[0], s[rows])
                    np.testing.assert_array_equal(got[1 if pose else 2], (dp if pose else da)[rows])
                    assert not got[2 if pose else 1].any(), f"{isa} {method} n={n} {kw.keys()}"
    with pytest.raises(Exception, match="query_windows"):
        tables.preselect_table_batch(P, A, st, ln, prevs, np.zeros((Q + 1, 8, A.shape[1]), np.float32))


def test_preselect_batch_keeps_its_set_up_and_gives_the_same_tables_every_call():
    """A PreselectBatch called step after step (several window lengths, masks, exclusion,
    from two threads at once) returns exactly the one-off tables, building the blocked
    set-up once per window length; a shard keeps one and still pickles."""
    import pickle
    from concurrent.futures import ThreadPoolExecutor

    from gesturedb.db.shards import _Shard

    rng = np.random.default_rng(47)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=50)
    F, M = P.shape[0], st.shape[0]
    proj = search.PoseProjection(P, half=True)
    pb = tables.PreselectBatch(P, A, st, ln, pose_proj=proj)
    assert pb.n_setups == 0
    calls = []
    for n in (8, 8, 5, 8, 5):
        Q = 20
        prevs = P[rng.integers(0, F, Q)]
        wins = A[rng.integers(0, F - n, Q)[:, None] + np.arange(n)]
        kw = dict(allowed=pack_bits(rng.random(F) < 0.7), exclude=rng.random((Q, M)) < 0.1)
        calls.append((prevs, wins, kw))
    with ThreadPoolExecutor(2) as ex:
        got = list(ex.map(lambda c: pb.tables(c[0], c[1], method="blocked", **c[2]), calls))
    assert pb.n_setups == 2  # windows of 8 and of 5 frames
    for (prevs, wins, kw), g in zip(calls, got):
        want = tables.preselect_table_batch(P, A, st, ln, prevs, wins, method="per_query", pose_proj=proj, **kw)
        for a, b in zip(g, want):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(Exception, match=r"prev_poses: expected \(Q, 24\)"):
        pb.tables(np.zeros((3, 23), np.float32), np.zeros((3, 8, A.shape[1]), np.float32))
    with pytest.raises(Exception, match="method"):
        pb.tables(calls[0][0], calls[0][1], method="fast")

    shard = _Shard(P, A, st, ln, projection=True)
    assert shard.batch("pose") is shard.batch("pose")
    moved = pickle.loads(pickle.dumps(shard))
    prevs, wins, kw = calls[0]
    for a, b in zip(moved.batch("pose").tables(prevs, wins, **kw), shard.batch("pose").tables(prevs, wins, **kw)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("top", [4, None])
def test_sharded_batch_advances_all_queries_together_exactly(dask_client, top):
    """20 queries of different lengths (partial last windows grouped by length), per-query
    k and exclusion, a shared mask: the blocked per-step tables on each shard, merged
    from top lists (or whole tables when L = 4 does not settle), give exactly
    rank_sum_search_batch's results, in one round trip per step for the whole batch."""
    rng = np.random.default_rng(43)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=70)
    F, M = P.shape[0], st.shape[0]
    Q = 20
    qs = [rng.standard_normal((int(rng.integers(9, 60)), A.shape[1])).astype(np.float32) for _ in range(Q)]
    init = P[rng.integers(0, F, Q)]
    ks = rng.integers(1, 4, Q)
    ex = rng.random((Q, M)) < 0.15
    allowed = pack_bits(rng.random(F) < 0.7)
    sh = ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=3, top_rows=top)
    try:
        for kw in (dict(k=ks, exclude=ex), dict(preselect="audio", allowed=allowed)):
            got = sh.search_batch(qs, init, **kw)
            want = search.rank_sum_search_batch(P, A, st, ln, qs, init, **kw)
            for i, (a, b) in enumerate(zip(got, want)):
                assert_same_search(a, b, f"query {i} {sorted(kw)}")
        if top == 4:
            assert 0 < sh.unsettled < sh.steps
    finally:
        sh.close()


def test_sharded_batch_on_the_real_database_and_its_errors(dask_client, scott_db):
    P = np.ascontiguousarray(scott_db.pose_features[:], dtype=np.float32)
    A = np.ascontiguousarray(scott_db.audio_features[:], dtype=np.float32)
    st = np.ascontiguousarray(scott_db.h5["chunks/start"][:], dtype=np.int64)
    ln = np.ascontiguousarray(scott_db.h5["chunks/length"][:], dtype=np.int64)
    M = st.shape[0]
    # every chunk's own audio as a query, its own chunk excluded (the refiner's training data)
    qs = [A[s:s + 64] for s in st]
    init = P[st]
    ex = np.eye(M, dtype=bool)
    sh = ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=2)
    try:
        for a, b in zip(sh.search_batch(qs, init, exclude=ex),
                        search.rank_sum_search_batch(P, A, st, ln, qs, init, exclude=ex)):
            assert_same_search(a, b)
        # queries 3 and 5 have every segment excluded: the first is named, as the kernel batch does
        bad = ex.copy()
        bad[[3, 5]] = True
        with pytest.raises(search.SearchError) as got:
            sh.search_batch(qs[:8], init[:8], exclude=bad[:8])
        with pytest.raises(search.SearchError) as want:
            search.rank_sum_search_batch(P, A, st, ln, qs[:8], init[:8], exclude=bad[:8])
        assert str(got.value) == str(want.value) and got.value.query == 3
    finally:
        sh.close()


def test_sharded_search_with_rows_sent_sparse(dask_client, monkeypatch):
    """Allowed rows reach the shards as words, or as the few words that differ from a
    full row (the repeat guard's cleared windows) or from an empty one (a keyword
    sub-database), for the whole query or one per step: the same results."""
    from gesturedb.db import shards

    kinds = []
    real = shards._encode_row
    monkeypatch.setattr(shards, "_encode_row", lambda *a: kinds.append(real(*a)[0]) or real(*a))
    rng = np.random.default_rng(21)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=400)
    F = P.shape[0]
    q = rng.standard_normal((50, A.shape[1])).astype(np.float32)
    nearly_full = np.ones(F, bool)
    nearly_empty = np.zeros(F, bool)
    for a in rng.integers(0, F - 200, 2):
        nearly_full[a:a + 8] = False
        nearly_empty[a:a + 200] = True
    per_step = np.stack([pack_bits(rng.random(F) < 0.5 if i % 3 else nearly_full) for i in range(-(-50 // 8))])
    sh = ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=3)
    try:
        for kw in (dict(allowed=pack_bits(nearly_full)), dict(allowed=pack_bits(nearly_empty), k=2),
                   dict(allowed=per_step, preselect="audio")):
            assert_same_search(sh.search(q, P[5], **kw), search.rank_sum_search(P, A, st, ln, q, P[5], **kw),
                               str(kw))
        # the per-step rows as a synthesis holds them: each distinct row once
        compact = StepBitsets(np.stack([pack_bits(nearly_full), per_step[1]]), np.arange(per_step.shape[0]) % 2)
        assert_same_search(sh.search(q, P[5], allowed=compact),
                           search.rank_sum_search(P, A, st, ln, q, P[5], allowed=np.asarray(compact)))
    finally:
        sh.close()
    assert {"set", "clear", "words"} <= set(kinds)


def test_allowed_rows_go_to_the_shards_packed_and_sparse_when_they_can():
    """A shard's row is its own frames' bits (slice_bits), as words or, when few words differ
    from all set or all clear, as those words alone; decoding gives the words back."""
    from gesturedb.control import full_mask, slice_bits, unpack_bits
    from gesturedb.db.shards import _decode_row, _encode_row

    rng = np.random.default_rng(3)
    F = 100_003
    full = np.ones(F, bool)
    full[[5, 64, 65, 70_000]] = False
    empty = ~full
    for bits, kind in ((full, "set"), (empty, "clear"), (rng.random(F) < 0.5, "words")):
        words = pack_bits(bits)
        for f0, f1 in ((0, F), (37, 64_001), (64_001, F), (10, 10)):
            row = _encode_row(slice_bits(words, f0, f1), f1 - f0)
            assert row[0] == (kind if f1 - f0 > 1000 else row[0])
            got = _decode_row(row)
            np.testing.assert_array_equal(got, pack_bits(bits[f0:f1]))
            np.testing.assert_array_equal(unpack_bits(got, f1 - f0), bits[f0:f1])
            if row[0] != "words":
                assert sum(x.nbytes for x in row[2:]) < 64
    assert np.array_equal(_decode_row(_encode_row(full_mask(F), F)), full_mask(F))


def test_allowed_of_the_wrong_width_is_refused(dask_client):
    from gesturedb.errors import ParameterError

    rng = np.random.default_rng(4)
    P, A, st, ln = continuous_db(rng, Dp=24, n_segments=10)
    sh = ShardedSearch(P, A, st, ln, scheduler=dask_client, parts=2)
    try:
        with pytest.raises(ParameterError, match=r"allowed: expected packed bitsets of \d+ words .*got shape \(3,\)"):
            sh.search(rng.standard_normal((16, A.shape[1])).astype(np.float32), P[0],
                      allowed=np.zeros(3, np.uint64))
    finally:
        sh.close()



def test_tables_have_the_same_bits_on_every_isa(scott_db):
    """The shards of one search may run on CPUs of different generations: each row of a shard's
    table is the same bits whichever kernel made it (kernels.h's one summation order), so the
    merged ranks are one machine's. Before, the ISAs' distances differed in their last bits, and
    the exact audio tie between a recording and its mirror broke by the worker holding each."""
    P, A = scott_db.pose_features, scott_db.audio_features
    st, ln = np.asarray(scott_db.chunks.start), np.asarray(scott_db.chunks.length)
    rng = np.random.default_rng(9)
    ts = rng.integers(0, P.shape[0] - 8, 5)
    prevs, wins = P[ts], np.stack([A[t:t + 8] for t in ts])
    proj = search.PoseProjection(P, half=True)
    for pre in ("pose", "audio"):
        got = {}
        for isa in search.kernels():
            with search.simd(isa):
                one = [tables.preselect_table(P, A, st, ln, P[t], A[t:t + 8], preselect=pre) for t in ts]
                filtered = [tables.preselect_table(P, A, st, ln, P[t], A[t:t + 8], preselect=pre, pose_proj=proj)
                            for t in ts]
                got[isa] = [np.stack(x) for x in zip(*one)], [np.stack(x) for x in zip(*filtered)], [
                    tables.preselect_table_batch(P, A, st, ln, prevs, wins, preselect=pre, method=m)
                    for m in ("blocked", "per_query")]
        for isa in got:
            for a, b in zip(got[isa][0] + got[isa][1] + [x for t in got[isa][2] for x in t],
                            got["scalar"][0] * 4):
                np.testing.assert_array_equal(a, b, err_msg=f"{isa} {pre}")
