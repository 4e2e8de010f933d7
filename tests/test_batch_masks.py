"""A batch of pre-selection tables with a bitset per query (issue 39: clients with different
controls searched in one pass): each row is exactly the query's table alone, on every ISA,
and the choice ranked from it is the float64 oracle's."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb import _core, search, tables
from gesturedb.errors import ParameterError, SearchError
from test_search import assert_same_search, exact_db, oracle_step, pack_bits
from test_search_proj import stacked_recordings

ISAS = search.kernels()


def _masks(rng, st, ln, F):
    """Bitsets as clients bring them: every frame; controls that hold over whole stretches (so
    that two of them often agree on a segment); one of those with a few recent windows cleared
    (the repeat guard); a sparse random one; and every frame again as a separate array."""
    def stretches(p):
        keep = np.zeros(F, bool)
        for a, n in zip(st, ln):
            if rng.random() < p:
                keep[a:a + n] = True
        return keep

    ctrl = stretches(0.6)
    guarded = ctrl.copy()
    for a in rng.integers(0, F - 10, 3):
        guarded[a:a + 8] = False
    rows = [np.ones(F, bool), ctrl, stretches(0.5) | ctrl, guarded, rng.random(F) < 0.5, np.ones(F, bool)]
    return np.stack([pack_bits(r) for r in rows])


def _per_query(rng, masks, Q):
    which = rng.integers(0, masks.shape[0], Q)
    return which, np.ascontiguousarray(masks[which])


@pytest.mark.parametrize("method", ["blocked", "per_query"])
@pytest.mark.parametrize("data", ["exact", "stacked"])
def test_rows_are_each_querys_table_alone_on_every_isa(method, data):
    """70 queries (two 64-lane panels) with six bitsets among them, with per-query exclusion,
    pose and audio pre-selection, with the projection filter, windows of N and shorter."""
    rng = np.random.default_rng(53)
    if data == "exact":
        P, A, st, ln = exact_db(rng, Dp=12, Da=3, n_segments=60)
    else:
        P, A, st, ln = stacked_recordings(rng, n_rec=14)
    F, M, Q = P.shape[0], st.shape[0], 70
    masks = _masks(rng, st, ln, F)
    which, allowed = _per_query(rng, masks, Q)
    prevs = P[rng.integers(0, F, Q)]
    exclude = rng.random((Q, M)) < 0.2
    proj = search.PoseProjection(P)
    variants = [dict(), dict(preselect="audio"), dict(exclude=exclude), dict(pose_proj=proj, exclude=exclude)]
    scalar = {}
    for isa in ISAS:
        with search.simd(isa):
            for n in (4, 3):
                wins = (rng if isa == ISAS[0] else np.random.default_rng(n)).standard_normal(
                    (Q, n, A.shape[1])).astype(np.float32)
                if data == "exact":
                    wins = np.round(wins).astype(np.float32)
                wins = scalar.setdefault(("wins", n), wins)
                for v, kw in enumerate(variants):
                    got = tables.preselect_table_batch(P, A, st, ln, prevs, wins, allowed=allowed, method=method,
                                                       **kw)
                    for i in range(Q):
                        one = dict(kw, allowed=allowed[i])
                        if "exclude" in one:
                            one["exclude"] = exclude[i]
                        want = tables.preselect_table(P, A, st, ln, prevs[i], wins[i], **one)
                        for g, w in zip(got, want):
                            np.testing.assert_array_equal(g[i], w, err_msg=f"{isa} {method} n={n} v{v} q{i}")
                    if data == "exact":  # integer data: every ISA's sums are exact, so the bits agree too
                        for g, w in zip(got, scalar.setdefault((n, v), got)):
                            np.testing.assert_array_equal(g, w, err_msg=f"{isa} vs {ISAS[0]} n={n} v{v}")


def test_scalar_rows_rank_to_the_float64_oracle():
    """The scalar kernel's batched rows, ranked, choose what spec steps 1-5 in float64 choose for
    each query under its own bitset (exact data: no near ties)."""
    rng = np.random.default_rng(59)
    P, A, st, ln = exact_db(rng, Dp=6, Da=3, n_segments=50)
    F, M, Q = P.shape[0], st.shape[0], 40
    masks = _masks(rng, st, ln, F)
    which, allowed = _per_query(rng, masks, Q)
    prevs = P[rng.integers(0, F, Q)]
    wins = rng.integers(-2, 3, size=(Q, 8, A.shape[1])).astype(np.float32)
    exclude = rng.random((Q, M)) < 0.1
    with search.simd("scalar"):
        s, dp, da = tables.preselect_table_batch(P, A, st, ln, prevs, wins, allowed=allowed, exclude=exclude,
                                                 method="blocked")
    checked = 0
    for i in range(Q):
        want, near = oracle_step(P, A, st, ln, prevs[i], wins[i], allowed=allowed[i], exclude=exclude[i])
        got = tables.rank_table(s[i], dp[i], da[i], k=1)
        if want is None:
            assert got is None, i
            continue
        if near:
            continue
        m, rp, ra, K = got
        assert (m, int(s[i, m]), rp, ra, K) == (want["segment"], want["start"], want["pose_rank"],
                                                want["audio_rank"], want["n_candidates"]), i
        checked += 1
    assert checked > Q // 2


def test_per_query_bitsets_are_validated():
    rng = np.random.default_rng(61)
    P, A, st, ln = exact_db(rng)
    F, Q = P.shape[0], 3
    W = (F + 63) // 64
    prevs, wins = P[:Q], np.zeros((Q, 8, A.shape[1]), np.float32)
    batch = tables.PreselectBatch(P, A, st, ln)
    with pytest.raises(ParameterError, match=rf"allowed: expected one bitset \({W},\) for all queries or "
                                              rf"\({Q}, {W}\) one per query \(F = {F} frames\); got shape \(4, {W}\)"):
        batch.tables(prevs, wins, allowed=np.zeros((Q + 1, W), np.uint64))
    with pytest.raises(ParameterError, match="allowed: expected uint64"):
        batch.tables(prevs, wins, allowed=np.zeros((Q, W), np.int64))
    # no frame allowed for one query: its row has no candidate, the others are untouched
    allowed = np.stack([pack_bits(np.ones(F, bool)), np.zeros(W, np.uint64), pack_bits(np.ones(F, bool))])
    s, _, _ = batch.tables(prevs, wins, allowed=allowed, method="blocked")
    assert (s[1] == -1).all() and (s[0] >= 0).any()
    np.testing.assert_array_equal(s[0], batch.tables(prevs, wins)[0][0])


@pytest.mark.parametrize("method", ["blocked", "per_query"])
def test_whole_searches_with_a_bitset_per_query_are_each_search_alone(method):
    """rank_sum_search_batch(query_allowed=...): 70 queries of different lengths (partial last
    windows), per-query k and exclusion, the projection filter; every ISA."""
    rng = np.random.default_rng(67)
    P, A, st, ln = stacked_recordings(rng, n_rec=14)
    F, M, Q = P.shape[0], st.shape[0], 70
    which, allowed = _per_query(rng, _masks(rng, st, ln, F), Q)
    queries = [rng.standard_normal((int(rng.choice([24, 21, 40])), A.shape[1])).astype(np.float32) for _ in range(Q)]
    init = P[rng.integers(0, F, Q)]
    ks = rng.integers(1, 5, Q)
    exclude = rng.random((Q, M)) < 0.2
    proj = search.PoseProjection(P)
    for isa in ISAS:
        with search.simd(isa):
            for kw in (dict(), dict(pose_proj=proj, exclude=exclude), dict(preselect="audio")):
                got = search.rank_sum_search_batch(P, A, st, ln, queries, init, step=4, k=ks, query_allowed=allowed,
                                                   method=method, **kw)
                for i in range(Q):
                    one = dict(kw, allowed=allowed[i])
                    if "exclude" in one:
                        one["exclude"] = exclude[i]
                    want = search.rank_sum_search(P, A, st, ln, queries[i], init[i], step=4, k=int(ks[i]), **one)
                    assert_same_search(got[i], want, f"{isa} {method} {sorted(kw)} query {i}")


def test_whole_search_bitsets_are_validated_and_failures_named():
    rng = np.random.default_rng(71)
    P, A, st, ln = exact_db(rng)
    F, Q = P.shape[0], 3
    W = (F + 63) // 64
    queries = [np.ones((16, A.shape[1]), np.float32)] * Q
    every = pack_bits(np.ones(F, bool))
    with pytest.raises(ParameterError, match="allowed, query_allowed: expected one of them"):
        search.rank_sum_search_batch(P, A, st, ln, queries, P[:Q], allowed=every,
                                     query_allowed=np.stack([every] * Q))
    with pytest.raises(ParameterError, match=rf"query_allowed: expected uint64 bitsets \({Q}, {W}\) \(one per query"):
        search.rank_sum_search_batch(P, A, st, ln, queries, P[:Q], query_allowed=np.stack([every] * (Q + 1)))
    none = np.stack([every, np.zeros(W, np.uint64), every])
    with pytest.raises(SearchError, match="query 1"):
        search.rank_sum_search_batch(P, A, st, ln, queries, P[:Q], query_allowed=none)


@pytest.mark.parametrize("Q", [1, 7, 8, 9, 16, 17, 33, 63, 64, 65])
def test_every_panel_width_gives_each_querys_table_alone(Q):
    """The blocked filter's panel is as wide as the call's queries need (8, 16, 32 or panels of 64
    lanes): each width, with its padding lanes, with a bitset per query or one for all and with
    exclusions, pose (plain and projection, float32 and binary16) and audio pre-selection, gives
    every row as the query's table alone, on every ISA."""
    rng = np.random.default_rng(73 + Q)
    P, A, st, ln = stacked_recordings(rng, n_rec=14)
    F, M = P.shape[0], st.shape[0]
    _, allowed = _per_query(rng, _masks(rng, st, ln, F), Q)
    prevs = P[rng.integers(0, F, Q)]
    wins = rng.standard_normal((Q, 4, A.shape[1])).astype(np.float32)
    exclude = rng.random((Q, M)) < 0.2
    variants = [dict(), dict(allowed=allowed[0]), dict(preselect="audio", allowed=allowed),
                dict(pose_proj=search.PoseProjection(P), allowed=allowed, exclude=exclude),
                dict(pose_proj=search.PoseProjection(P, half=True), exclude=exclude)]
    for isa in ISAS:
        with search.simd(isa):
            for v, kw in enumerate(variants):
                got = tables.preselect_table_batch(P, A, st, ln, prevs, wins, method="blocked", **kw)
                for i in range(Q):
                    one = dict(kw)
                    if isinstance(one.get("allowed"), np.ndarray) and one["allowed"].ndim == 2:
                        one["allowed"] = allowed[i]
                    if "exclude" in one:
                        one["exclude"] = exclude[i]
                    want = tables.preselect_table(P, A, st, ln, prevs[i], wins[i], **one)
                    for g, w in zip(got, want):
                        np.testing.assert_array_equal(g[i], w, err_msg=f"{isa} Q={Q} v{v} q{i}")


def test_whole_searches_narrow_their_panel_as_queries_end():
    """A whole blocked search whose queries end at different steps: its panel narrows step by
    step (65 lanes, then 40, 20, 9, 3, 1: every width) and each query is still its search alone."""
    rng = np.random.default_rng(79)
    P, A, st, ln = stacked_recordings(rng, n_rec=14)
    F, M = P.shape[0], st.shape[0]
    lengths = [24] * 1 + [20] * 8 + [16] * 11 + [12] * 20 + [8] * 25 + [4] * 1
    Q = len(lengths)
    queries = [rng.standard_normal((n, A.shape[1])).astype(np.float32) for n in lengths]
    init = P[rng.integers(0, F, Q)]
    exclude = rng.random((Q, M)) < 0.2
    proj = search.PoseProjection(P)
    for isa in ISAS:
        with search.simd(isa):
            for kw in (dict(), dict(pose_proj=proj, exclude=exclude), dict(preselect="audio")):
                got = search.rank_sum_search_batch(P, A, st, ln, queries, init, step=4, method="blocked", **kw)
                for i in range(Q):
                    one = dict(kw)
                    if "exclude" in one:
                        one["exclude"] = exclude[i]
                    want = search.rank_sum_search(P, A, st, ln, queries[i], init[i], step=4, **one)
                    assert_same_search(got[i], want, f"{isa} {sorted(kw)} query {i}")


def test_auto_takes_the_blocked_path_from_three_queries_a_thread():
    """The threshold of method="auto" counts queries per thread (a block per thread)."""
    assert [search.blocked_min_queries(t) for t in (1, 2, 4)] == [3, 5, 9]
    assert search.blocked_min_queries() == search.blocked_min_queries(_core.default_threads())
