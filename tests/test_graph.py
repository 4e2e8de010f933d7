"""The motion graph (gesturedb.db.graph) and graph synthesis (gesturedb.synth.graph) on toy and real data."""
from __future__ import annotations

import json
import re
import shutil

import h5py
import numpy as np
import pytest

import gesturedb
from gesturedb import rotations as R
from gesturedb.db import edges as E
from gesturedb.db import graph as G
from gesturedb.db import schema
from gesturedb.errors import SchemaError, SearchError
from gesturedb.synth.graph import MAX_SPEED, GraphSynthesizer, voiced_segments
from gesturedb.synth.viterbi import check_csr

INPUTS = ["2_scott_0_2_2", "2_scott_0_3_3", "2_scott_0_4_4", "2_scott_0_5_5"]


def _direct_cost(pos, rot, root, fa, fb, l1, l2, joints=None, part="whole"):
    """T between frame lists fa (end of p) and fb (start of q) by explicit loops (the oracle).

    part "whole"/"lower": positions in the heading frame; "upper": in the pelvis frame (the root's
    whole rotation removed); "lower" adds the pelvis tilt (root rotation without heading).
    """
    joints = np.arange(pos.shape[1]) if joints is None else np.asarray(joints)
    tp = tr = 0.0
    for a, b in zip(fa, fb):
        local, quats = [], []
        for f in (a, b):
            fwd = R.apply(rot[f, 0], np.array([0.0, 0.0, 1.0]))
            yaw = np.arctan2(fwd[0], fwd[2])
            c, s = np.cos(yaw), np.sin(yaw)
            m = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])  # rotation about y by -yaw
            if part == "upper":
                m = R.to_matrix(rot[f, 0]).T  # world -> pelvis frame
            local.append((pos[f, joints] - root[f]) @ m.T)
            q = [rot[f, j] for j in joints if j != 0]
            if part == "lower":
                q.append(R.multiply(np.array([np.cos(-yaw / 2), 0, np.sin(-yaw / 2), 0]), rot[f, 0]))
            q = np.array(q)
            quats.append(q * np.sign(q[:, :1] + 1e-300))  # w >= 0 hemisphere
        tp += float(np.sum((local[0] - local[1]) ** 2))
        tr += float(np.sum(1 - np.sum(quats[0] * quats[1], -1)))
    return l1 * tp + l2 * tr


@pytest.mark.parametrize("part,joints", [("whole", None), ("upper", [2, 3, 4]), ("lower", [0, 1])])
def test_transition_costs_match_direct_loops(part, joints):
    rng = np.random.default_rng(0)
    F, J, K, m = 40, 5, 6, 2
    pos = rng.normal(size=(F, J, 3))
    root = rng.normal(size=(F, 3))
    rot = R.normalize(rng.normal(size=(F, J, 4)))
    ends = rng.integers(0, F, (K, m))
    starts = rng.integers(0, F, (K, m))
    kw = dict(l1=0.7, l2=0.3, joints=joints, part=part)
    ex = G.transition_features(pos, rot, root, ends, **kw)
    sx = G.transition_features(pos, rot, root, starts, **kw)
    T = E.transition_costs(ex, sx)
    assert T.dtype == np.float64 and T.shape == (K, K)
    for p in range(K):
        for q in range(K):
            # exact on a grid of ~2^-21 of the largest feature: within 1e-5 of the float64 loops
            want = _direct_cost(pos, rot, root, ends[p], starts[q], 0.7, 0.3, joints, part)
            assert T[p, q] == pytest.approx(want, rel=1e-5, abs=1e-5)


@pytest.mark.parametrize("D,scale", [(762, 1.0), (5, 1e-3), (3000, 40.0), (3, 7.0), (2, 1.0)])
def test_transition_costs_are_exact_integers_on_their_grid(D, scale):
    """The float64 BLAS product computes |a - b|^2 of the gridded features exactly: the same as
    int64 arithmetic on the grid's integers, for every pair (so no kernel, blocking or FMA can
    change a bit), and within the grid's rounding of the float64 distance."""
    rng = np.random.default_rng(D)
    a = rng.normal(size=(23, D)) * scale
    b = rng.normal(size=(31, D)) * scale
    b[0] = a[0]  # an exact zero
    T = E.transition_costs(a, b)
    (qa, qb), u = E._on_grid(a, b)
    ia, ib = qa.astype(np.int64), qb.astype(np.int64)
    e = (51 - int(np.ceil(np.log2(D)))) // 2  # 4 D 4^e <= 2^53
    assert max(np.abs(ia).max(), np.abs(ib).max()) <= 2 ** e and np.array_equal(ia, qa) and np.array_equal(ib, qb)
    # the compact grid the costs use: the same integers, in float32 where that holds them (D >= 3)
    (ca, cb), uc = E._on_grid(a, b, compact=True)
    assert uc == u and ca.dtype == cb.dtype == (np.float32 if D >= 3 else np.float64)
    assert np.array_equal(ca, qa) and np.array_equal(cb, qb)
    exact = ((ia[:, None, :] - ib[None, :, :]) ** 2).sum(-1)  # int64: no overflow below 2^63
    assert exact.max() < 2 ** 53
    np.testing.assert_array_equal(T, exact.astype(np.float64) * (u * u))
    assert T[0, 0] == 0.0 and (T >= 0).all()
    direct = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    # each value moved by at most u/2, so each difference by at most u: |T - direct| <= 2 u |a - b|_1 + D u^2
    bound = 2 * u * np.abs(a[:, None, :] - b[None, :, :]).sum(-1) + D * u * u
    assert (np.abs(T - direct) <= bound * (1 + 1e-9) + 1e-12 * direct).all()


def test_graph_features_in_chunks_equal_the_whole_arrays(scott_db_path):
    """The build grids the transition features a chunk of clips at a time (two passes, reading only
    each chunk's frames): the same integers and unit as the whole arrays on one grid."""
    with h5py.File(scott_db_path, "r") as h5:
        start, length = h5["clips/start"][()], h5["clips/length"][()]
        last = start[:, None] + np.array([[-2, -1]]) + length[:, None]
        first = start[:, None] + np.array([[0, 1]])
        upper, lower = G.body_parts(schema.read(h5, "skeleton/names"), schema.read(h5, "skeleton/parents"))
        parts = [("upper", upper), ("lower", lower)]
        pos, rot, root = (h5[f"frames/{k}"][()] for k in ("joint_positions", "local_rotations", "root_positions"))
        for chunk in (1, 7, 10 ** 6):
            for (p, j), g in zip(parts, G._gridded_features(h5, last, first, parts, l1=0.7, l2=0.3, chunk=chunk)):
                want = E._GriddedCosts(G.transition_features(pos, rot, root, last, joints=j, part=p),
                                       G.transition_features(pos, rot, root, first, joints=j, part=p))
                assert g.uu == want.uu and g.a.dtype == want.a.dtype == np.float32
                assert np.array_equal(g.a, want.a) and np.array_equal(g.b, want.b)
                assert np.array_equal(g.na, want.na) and np.array_equal(g.nb, want.nb)


def test_csr_made_block_by_block_is_the_whole_sort(rng=np.random.default_rng(5)):
    """_block_csr orders each block's edges as it comes; put together they are the CSR of all
    the (row, target, cost) triples sorted at once (edges of a row in any order, empty rows
    and empty blocks included)."""
    for K in (1, 7, 300):
        rows, cols, cost = [], [], []
        for r in range(K):
            n = int(rng.integers(0, 6)) if r % 5 else 0
            rows += [r] * n
            cols += list(rng.choice(K, size=min(n, K), replace=False))
            cost += list(rng.random(min(n, K)))
        rows, cols, cost = np.array(rows, np.int64), np.array(cols, np.int64), np.array(cost)
        o = np.lexsort((cols, rows))
        want_ptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=K))])
        for step in (1, 3, K):
            pieces = []
            for r0 in range(0, K, step):
                r1 = min(K, r0 + step)
                sel = rng.permutation(np.flatnonzero((rows >= r0) & (rows < r1)))  # any order within a block
                pieces.append(E._block_csr(r0, r1, rows[sel], cols[sel].astype(np.int32), cost[sel]))
            indptr, indices, c = E._csr(K, pieces)
            check_csr(indptr, indices, c, K)
            np.testing.assert_array_equal(indptr, want_ptr)
            np.testing.assert_array_equal(indices, cols[o])
            np.testing.assert_array_equal(c, cost[o])


def test_the_second_body_part_is_gridded_after_the_first_is_done(scott_db_path, monkeypatch):
    """write_graph holds one body part's grid at a time: the lower body's is made (its rounding
    pass) only when the upper body's graph is written and its grid dropped."""
    import weakref

    events, live = [], []
    tf, we = G.transition_features, G._write_edges
    monkeypatch.setattr(G, "transition_features", lambda *a, **k: events.append(("features", k["part"])) or tf(*a, **k))

    def write_edges(h5, group, part, joints, g, *a, **k):
        live.append(weakref.ref(g))
        events.append(("edges", part, sum(r() is not None for r in live)))
        return we(h5, group, part, joints, g, *a, **k)

    monkeypatch.setattr(G, "_write_edges", write_edges)
    with h5py.File(scott_db_path, "r") as src, h5py.File("mem.h5", "w", driver="core", backing_store=False) as h5:
        for name in ("frames", "clips", "skeleton", "recordings"):
            src.copy(name, h5)
        G.write_graph(h5)
    # pass 1: both parts' magnitudes; then the upper part's rounding, its edges, the lower's
    # rounding, its edges, with one grid alive at each
    n = [e for e in events if e[0] == "features"]
    half = len(n) // 2
    assert {p for _, p in n[:half]} == {"upper", "lower"}
    i_up, i_low = events.index(("edges", "upper", 1)), events.index(("edges", "lower", 1))
    assert {e for e in events[half:i_up]} == {("features", "upper")}
    assert {e for e in events[i_up + 1:i_low]} == {("features", "lower")}


def test_each_body_graph_sees_only_its_own_joints(scott_db):
    """Changing the arms leaves the lower-body costs alone, changing the legs the upper-body ones."""
    upper, lower = G.body_parts(scott_db.skeleton.names, scott_db.skeleton.parents)
    names = scott_db.skeleton.names
    assert names[0] == "pelvis" and {names[j] for j in lower} == {
        "pelvis", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_foot",
        "right_foot"}
    assert len(upper) + len(lower) == len(names) and not set(upper) & set(lower)
    from gesturedb.motion import Motion

    frames = np.arange(40).reshape(20, 2)
    motion = scott_db.motion(scott_db.recordings[0].name, 0.0, 4.0)
    rng = np.random.default_rng(5)

    def costs(rotations, part, joints):
        m = Motion(skeleton=motion.skeleton, fps=motion.fps, rotations=rotations, root_positions=motion.root_positions)
        x = G.transition_features(m.positions, m.rotations, m.root_positions, frames, joints=joints, part=part)
        return E.transition_costs(x[::2], x[1::2])

    base = np.asarray(motion.rotations, dtype=np.float64)
    for changed, same_part, same_joints, other_part, other_joints in (
            (upper[upper != 3], "lower", lower, "upper", upper),  # arms etc. (spine1 kept: it is a child of the root)
            (lower[lower != 0], "upper", upper, "lower", lower)):  # legs
        rot = base.copy()
        rot[:, changed] = R.normalize(rot[:, changed] + 0.3 * rng.normal(size=rot[:, changed].shape))
        np.testing.assert_allclose(costs(rot, same_part, same_joints), costs(base, same_part, same_joints),
                                   rtol=1e-5, atol=1e-6)
        assert not np.allclose(costs(rot, other_part, other_joints), costs(base, other_part, other_joints))


@pytest.mark.parametrize("K,max_out,ties", [(30, 32, False), (60, 8, False), (40, 8, True), (9, 8, True)])
def test_edges_threshold_plus_cheapest(K, max_out, ties):
    """The rule taken literally from a stable sort: ties (a few distinct costs, most rows tied
    at the cut) go to the smaller target index."""
    rng = np.random.default_rng(1)
    T = rng.integers(0, 4, (K, K)).astype(np.float64) if ties else rng.random((K, K)) * 10
    indptr, indices, cost, dT = E.edges_from_costs(T.copy(), delta_quantile=0.1, min_out=3, max_out=max_out)
    check_csr(indptr, indices, cost, K)
    dense = np.zeros((K, K), bool)
    src = np.repeat(np.arange(K), np.diff(indptr))
    dense[src, indices] = True
    assert not dense.diagonal().any()
    off = ~np.eye(K, dtype=bool)
    assert dT == pytest.approx(np.quantile(T[off], 0.1))
    for p in range(K):  # oracle: sort the row, take the rule literally
        order = [q for q in np.argsort(T[p], kind="stable") if q != p][: min(max_out, K - 1)]
        want = {q for r, q in enumerate(order) if r < 3 or T[p, q] < dT}
        assert set(np.flatnonzero(dense[p])) == want
    np.testing.assert_array_equal(cost, T[src, indices])


@pytest.mark.parametrize("K,D,ties,delta_T", [(40, 30, False, None), (300, 762, False, None), (1500, 12, False, None),
                                               (120, 6, True, None), (9, 5, False, 50.0), (2, 4, False, None),
                                               (1, 4, False, None)])
def test_edges_from_features_in_blocks_equal_the_whole_table(K, D, ties, delta_T):
    """The build's blocked path (no K x K table) gives the dense path's edges, costs and
    delta_T bit for bit, whatever the block: exact costs make a block's values the table's.
    (K = 1500: the delta_T sample is every 2nd pair.)"""
    rng = np.random.default_rng(K)
    if ties:  # few distinct costs: most rows tied at the cut
        a, b = (rng.integers(0, 2, (K, D)).astype(np.float64) for _ in range(2))
    else:
        a, b = rng.normal(size=(K, D)), rng.normal(size=(K, D))
    want = E.edges_from_costs(E.transition_costs(a, b), delta_T=delta_T, min_out=3, max_out=8)
    for block in (1, 37, 1 << 24):
        got = E.edges_from_features(a, b, delta_T=delta_T, min_out=3, max_out=8, block_elems=block)
        for x, y in zip(want[:3], got[:3]):
            assert x.dtype == y.dtype and np.array_equal(x, y)
        assert got[3] == want[3]


def _low_rank(rng, K, D, latent=10, dup=0):
    """(K, D) end and start features with a few dominant directions (as real poses have), and
    ``dup`` start rows copied from others (exact ties in every row that reaches them)."""
    h = rng.normal(size=(2 * K, latent)) * 0.6 ** np.arange(latent)
    x = np.tanh(h @ rng.normal(size=(latent, D)) / 3) + 0.01 * rng.normal(size=(2 * K, D))
    a, b = x[:K], x[K:]
    if dup:
        b[rng.choice(K, dup, replace=False)] = b[rng.choice(K, dup, replace=False)]
    return a, b


def _count_dense_blocks(monkeypatch):
    calls = []
    dense = E._row_edges
    monkeypatch.setattr(E, "_row_edges", lambda T, *a: calls.append(T.shape[0]) or dense(T, *a))
    return calls


@pytest.mark.parametrize("K,D,dup,delta_T,block", [(400, 120, 0, None, 1 << 24), (900, 300, 40, None, 1 << 14),
                                                    (250, 64, 25, 2.0, 1000), (200, 40, 0, None, 1 << 24)])
def test_bounded_edges_equal_the_dense_ones(K, D, dup, delta_T, block, monkeypatch):
    """The projection bounds pick exactly the dense path's edges (ties at the cut from duplicated
    starts included), and they really did the work: no block fell back to the dense costs."""
    a, b = _low_rank(np.random.default_rng(K), K, D, dup=dup)
    want = E.edges_from_features(a, b, delta_T=delta_T, min_out=3, max_out=8, method="dense", block_elems=block)
    calls = _count_dense_blocks(monkeypatch)
    got = E.edges_from_features(a, b, delta_T=delta_T, min_out=3, max_out=8, method="bounded", block_elems=block)
    assert calls == []
    for x, y in zip(want[:3], got[:3]):
        assert x.dtype == y.dtype and np.array_equal(x, y)
    assert got[3] == want[3]
    if dup:  # the duplicated starts did tie at some row's cut
        T = E.transition_costs(a, b)
        np.fill_diagonal(T, np.inf)
        kth = np.sort(T, axis=1)[:, 7]
        assert ((T == kth[:, None]).sum(1) > 1).any()


@pytest.mark.parametrize("K", [1, 2, 9, 17, 300, 1000])
def test_bounded_edges_fall_back_where_bounds_cannot_pay(K, monkeypatch):
    """Too few clips for the sampled threshold, or features without structure (i.i.d. noise keeps
    every column): those blocks are computed densely, with the same edges."""
    rng = np.random.default_rng(K)
    a, b = rng.normal(size=(K, 200)), rng.normal(size=(K, 200))
    want = E.edges_from_features(a, b, min_out=3, max_out=8, method="dense")
    calls = _count_dense_blocks(monkeypatch)
    got = E.edges_from_features(a, b, min_out=3, max_out=8, method="bounded")
    assert sum(calls) == K
    for x, y in zip(want[:3], got[:3]):
        assert np.array_equal(x, y)


def test_auto_bounds_from_bound_min_k_clips(monkeypatch):
    """method="auto" is what the build uses: bounded from BOUND_MIN_K clips on (and only when the
    features are wider than the projection), dense below."""
    a, b = _low_rank(np.random.default_rng(7), 300, 120)
    calls = _count_dense_blocks(monkeypatch)
    E.edges_from_features(a, b, max_out=8)
    assert sum(calls) == 300
    monkeypatch.setattr(E, "BOUND_MIN_K", 300)
    calls.clear()
    E.edges_from_features(a, b, max_out=8)
    assert calls == []
    E.edges_from_features(a[:, :E.BOUND_DIMS + 2], b[:, :E.BOUND_DIMS + 2], max_out=8)
    assert sum(calls) == 300


def test_edge_search_reports_its_rows(monkeypatch):
    """on_rows (the build's progress bar over the clips) hears of every row once, in both paths."""
    a, b = _low_rank(np.random.default_rng(8), 500, 100)
    for method in ("dense", "bounded"):
        rows = []
        E.edges_from_features(a, b, max_out=8, method=method, block_elems=500 * 64, on_rows=rows.append)
        assert rows == [64] * 7 + [52]


@pytest.mark.parametrize("method", ["dense", "bounded"])
def test_edge_blocks_on_threads_equal_one_thread(method, monkeypatch):
    """From BOUND_MIN_K clips on the blocks of rows run on threads; the edges, and the rows
    reported to a progress bar, are those of one thread."""
    a, b = _low_rank(np.random.default_rng(9), 700, 90, dup=30)
    monkeypatch.setattr(E, "BOUND_MIN_K", 100)
    out = {}
    for threads in (1, 4):
        monkeypatch.setattr(E, "EDGE_THREADS", threads)
        rows = []
        out[threads] = E.edges_from_features(a, b, max_out=8, method=method, block_elems=700 * 50, on_rows=rows.append)
        assert rows == [50] * 14
    for x, y in zip(out[1], out[4]):
        assert np.array_equal(x, y)


def test_projected_bounds_hold_on_every_pair():
    """L <= T <= L + 4 r_p r_q (with the margin) for every pair, T exact; and the margin is small
    against the costs that decide edges."""
    a, b = _low_rank(np.random.default_rng(3), 300, 150)
    g = E._GriddedCosts(a, b)
    B = E._ProjectedBounds.fit(g, 8, J=6)
    T = g.rows(0, g.K) / g.uu
    L = B.P @ B.Q.T + B.na[:, None]
    U = L + 4.0 * B.ra[:, None] * B.rb[None, :]
    assert (L - B.margin <= T).all() and (T <= U + B.margin).all()
    np.fill_diagonal(T, np.inf)
    assert B.margin < 0.01 * np.median(np.sort(T, axis=1)[:, 7])  # against the 8th cheapest of a row
    assert np.median(U - L) < 0.5 * np.median(T)  # and they bound something


def test_bounded_edges_of_real_frames(scott_db, monkeypatch):
    """Every frame of the real recording as a clip (951 ends against 951 starts, 46 upper-body
    joints, 644 features): the bounded edges are the dense ones, no block fell back, and fewer
    than 3 exact costs were computed per edge."""
    upper, _ = G.body_parts(scott_db.skeleton.names, scott_db.skeleton.parents)
    pos, rot, root = scott_db.joint_positions, scott_db.local_rotations, scott_db.root_positions
    f = np.arange(1, pos.shape[0] - 1)
    ex = G.transition_features(pos, rot, root, np.stack([f - 1, f], 1), joints=upper, part="upper")
    sx = G.transition_features(pos, rot, root, np.stack([f, f + 1], 1), joints=upper, part="upper")
    want = E.edges_from_features(ex, sx, method="dense")
    calls = _count_dense_blocks(monkeypatch)
    n_pairs = []
    pairs = E._GriddedCosts.pairs
    monkeypatch.setattr(E._GriddedCosts, "pairs", lambda self, i, j: n_pairs.append(i.size) or pairs(self, i, j))
    got = E.edges_from_features(ex, sx, method="bounded")
    assert calls == []
    for x, y in zip(want[:3], got[:3]):
        assert np.array_equal(x, y)
    assert sum(n_pairs[1:]) < 3 * 32 * len(f)  # [0] is the delta_T sample


def test_style_model_beats_the_mean_on_learnable_data():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(200, 5))
    Y = X @ rng.normal(size=(5, 3)) + 0.1 * rng.normal(size=(200, 3))
    m = G.fit_style_model(X, Y)
    assert m["heldout_rmse"] < 0.3 * m["mean_rmse"]
    np.testing.assert_allclose(G.predict_style(m, X), Y, atol=0.5)
    # a clip and its mirrored copy are held out together
    mg = G.fit_style_model(X, Y, groups=np.arange(200) // 2)
    assert mg["n_heldout"] == 2 * (100 // 5)
    assert m["alpha"] <= 1.0 and mg["alpha"] <= 1.0  # cross-validation keeps the fit where it predicts


def test_style_model_falls_back_to_the_mean_where_audio_does_not_predict_style():
    """Pure noise inputs and few clips (as on one short recording): the cross-validated strength is
    strong, the predictions stay close to the training mean, and the held-out error is about that
    of the mean (a fixed weak ridge does worse than the mean here)."""
    rng = np.random.default_rng(5)
    X, Y = rng.normal(size=(30, 29)), rng.normal(size=(30, 3))
    groups = np.arange(30) // 2
    m = G.fit_style_model(X, Y, groups=groups)
    assert m["alpha"] >= 100
    assert np.all(G.predict_style(m, X).std(0) < 0.4 * Y.std(0))  # close to the mean everywhere
    assert m["heldout_rmse"] <= 1.05 * m["mean_rmse"]
    weak = G.fit_style_model(X, Y, groups=groups, alpha=0.1)
    assert weak["alpha"] == 0.1 and weak["heldout_rmse"] > 1.1 * weak["mean_rmse"]


@pytest.mark.parametrize("n_groups", [12, 400])
def test_style_model_cross_validation_folds_and_solves(n_groups, monkeypatch):
    """Leave-one-group-out up to CV_FOLDS groups, CV_FOLDS folds beyond (the cost of the fit
    stays linear in the clips); each strength solves all folds in one batched Cholesky whose
    solutions are those of the folds one by one (bit for bit) and of numpy's solver (closely)."""
    rng = np.random.default_rng(n_groups)
    X = rng.normal(size=(2 * n_groups, 6))
    Y = X[:, :3] @ rng.normal(size=(3, 3)) + 0.3 * rng.normal(size=(2 * n_groups, 3))
    calls = []
    solve = G._cholesky_solve

    def recording(A, B):
        out = solve(A, B)
        calls.append(A.shape[:-2])
        if A.ndim == 3:
            for i in range(A.shape[0]):
                assert np.array_equal(out[i], solve(A[i], B[i]))
                np.testing.assert_allclose(out[i], np.linalg.solve(A[i], B[i]), rtol=1e-9, atol=1e-12)
        return out

    monkeypatch.setattr(G, "_cholesky_solve", recording)
    m = G.fit_style_model(X, Y, groups=np.arange(2 * n_groups) // 2)
    held = n_groups // 5  # every 5th group is held out of the estimate's fit
    want = min(n_groups - held, G.CV_FOLDS), min(n_groups, G.CV_FOLDS)
    batched = [c for c in calls if c]
    assert batched == [(want[0],)] * len(G.RIDGE_ALPHAS) + [(want[1],)] * len(G.RIDGE_ALPHAS)
    assert m["heldout_rmse"] < 0.5 * m["mean_rmse"]


def test_voiced_segments_find_bursts():
    sr = 16000
    t = np.arange(int(3.0 * sr)) / sr
    x = 1e-4 * np.random.default_rng(3).normal(size=t.shape)
    truth = [(0.2, 0.6), (1.1, 1.5), (2.2, 2.9)]
    for a, b in truth:
        sel = (t >= a) & (t < b)
        x[sel] += 0.3 * np.sin(2 * np.pi * 220 * t[sel])
    s, e = voiced_segments(x, sr, method="energy")
    assert len(s) == 3
    np.testing.assert_allclose(s, [a for a, _ in truth], atol=0.02)
    np.testing.assert_allclose(e, [b for _, b in truth], atol=0.02)


def test_real_graph_is_stored_and_consistent(scott_db_path):
    with h5py.File(scott_db_path, "r") as h5:
        K = h5["clips/start"].shape[0]
        st, ln = h5["clips/start"][()], h5["clips/length"][()]
        pos, rot, root = (h5[f"frames/{k}"][()].astype(np.float64) for k in ("joint_positions", "local_rotations",
                                                                              "root_positions"))
        upper, lower = G.body_parts(schema.read(h5, "skeleton/names"), schema.read(h5, "skeleton/parents"))
        for group, part, joints in (("graph", "upper", upper), ("graph_lower", "lower", lower)):
            indptr, indices, cost = (schema.read(h5, f"{group}/{k}") for k in ("indptr", "indices", "cost"))
            check_csr(indptr, indices, cost, K)
            assert np.all(np.diff(indptr) >= min(G.MIN_OUT, K - 1))
            attrs = dict(h5[group].attrs)
            assert attrs["l1"] == 0.7 and attrs["l2"] == 0.3 and attrs["body"] == part
            # every edge recomputed from the frames by the direct loop
            m = int(attrs["transition_frames"])
            for p in range(K):
                for e in range(indptr[p], indptr[p + 1]):
                    q = int(indices[e])
                    want = _direct_cost(pos, rot, root, st[p] + ln[p] - m + np.arange(m), st[q] + np.arange(m),
                                        0.7, 0.3, joints, part)
                    # float32 matmul: absolute error ~1e-7 of the squared feature norms (~100)
                    assert cost[e] == pytest.approx(want, rel=1e-4, abs=1e-4), (group, p, q)
        sm = dict(h5["style_model"].attrs)
        assert np.isfinite(sm["heldout_rmse"]) or K < 7


@pytest.mark.parametrize("version", [1, 2, 3, 4])
def test_old_file_is_a_clear_error_and_upgrade_brings_it_to_what_a_build_writes(scott_db_path, tmp_path, capsys,
                                                                                 version):
    from gesturedb.cli.main import main

    old = tmp_path / "old.h5"
    shutil.copy(scott_db_path, old)
    with h5py.File(old, "r+") as h5:
        want = {f"{g}/{k}": h5[f"{g}/{k}"][()] for g in ("graph", "graph_lower") for k in ("indptr", "indices", "cost")}
        want["frames/pose_features"] = h5["frames/pose_features"][()]
        want_config = json.loads(h5.attrs["config"])
        want_timescale = float(h5.attrs["motion_timescale_s"])
        del h5.attrs["motion_timescale_s"]  # an old file has none
        if version < 3:
            del h5["graph_lower"]
        if version == 1:
            del h5["graph"], h5["style_model"]
        # what version 3 stored: the past only (frames f, f-2, f-4, f-6, 96 values); version 4: centred, no
        # ankles (120 values)
        del h5["frames/pose_features"]
        h5["frames/pose_features"] = np.zeros((want["frames/pose_features"].shape[0], 96 if version < 4 else 120),
                                              np.float32)
        if version < 4:
            h5.attrs["config"] = json.dumps({**want_config, "pose_window": 4, "pose_stride": 2})
        h5.attrs["schema_version"] = version
    now = schema.SCHEMA_VERSION
    with pytest.raises(SchemaError, match=rf"old.h5: schema_version: expected {now}, got {version} "
                                          rf"\({re.escape(schema.UPGRADABLE_VERSIONS[version])}\).*gesturedb upgrade"):
        gesturedb.open(old)
    with pytest.raises(SchemaError, match="gesturedb upgrade"):
        G.add_graph(old)  # the graph alone would leave the pose features as they were
    assert main(["upgrade", str(old)] + (["-q"] if version == 2 else [])) == 0
    out = capsys.readouterr().out
    assert f"schema version {version} -> {now}" in out and "pose features" in out and "stance" in out
    assert ("motion graphs" in out) == (version < 3)
    with gesturedb.open(old) as db, h5py.File(old, "r") as h5:
        for k, v in want.items():
            np.testing.assert_array_equal(h5[k][()], v)  # the same features and graphs as the build made
        assert json.loads(h5.attrs["config"]) == want_config
        assert db.motion_timescale_s == want_timescale  # the stride chosen as a build chooses it
        GraphSynthesizer(db)
    assert main(["upgrade", str(old)]) == 0
    assert "nothing to do" in capsys.readouterr().out


@pytest.fixture(scope="module")
def mirrored_db(scott_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("gdb") / "scott_m.h5"
    gesturedb.build([scott_dir], out, mirror=True).close()
    return out


def _check_result(res, db, n_expected, synth):
    T = res.n_frames
    assert T == n_expected and res.motion.rotations.shape[0] == T
    np.testing.assert_allclose(np.linalg.norm(res.motion.rotations, axis=-1), 1, atol=1e-6)
    steps = res.steps
    assert steps[0]["out_start"] == 0 and steps[-1]["out_end"] == T
    assert all(a["out_end"] == b["out_start"] for a, b in zip(steps[:-1], steps[1:]))
    nodes = [s["node"] for s in steps]
    assert all(a != b for a, b in zip(nodes[:-1], nodes[1:])), "back-to-back repeat"
    assert all(1 / MAX_SPEED - 1e-9 <= s["speed"] <= MAX_SPEED + 1e-9 for s in steps)
    # the path's cost, recomputed from the provenance, is the search's cost
    o = res.options
    total = o["w_data"] * sum(s["data_cost"] for s in steps) + o["w_trans"] * sum(
        s["transition_cost"] for s in steps[1:])
    assert total == pytest.approx(o["total_cost"], rel=1e-9)
    for s in steps:
        assert s["data_cost"] == pytest.approx(o["l5"] * s["style_cost"] + o["l6"] * s["rhythm_cost"]
                                               + o["l_dur"] * s["duration_cost"] + 1000.0 * s["unfit"])
        rec = db.recording(s["recording"])
        assert 0 <= s["source_start_s"] < s["source_end_s"] <= rec.n_frames / db.fps + 1e-6


@pytest.mark.slow
def test_graph_synthesis_on_all_inputs(mirrored_db, scott_dir):
    from gesturedb.features.audio import n_frames_for_duration
    from gesturedb.io.audio import read_audio

    with gesturedb.open(mirrored_db) as db:
        synth = GraphSynthesizer(db)
        assert any(r.mirrored for r in db.recordings) and len(synth.start) == len(db.clips)
        for stem in INPUTS:
            wav = scott_dir / "inputs" / f"{stem}.wav"
            x, sr = read_audio(wav, sr=16000)
            n = n_frames_for_duration(x.shape[0] / sr, db.fps)
            tg = scott_dir / "inputs" / f"{stem}.TextGrid"
            for tr in ([tg, None] if tg.exists() else [None]):
                res = synth.synthesize(wav, transcript=tr)
                _check_result(res, db, n, synth)
                assert len(res.steps) >= 3


def test_cli_graph_synth_and_missing_graph(mirrored_db, scott_dir, tmp_path, capsys):
    from gesturedb.cli.main import main

    wav = scott_dir / "inputs" / "2_scott_0_2_2.wav"
    out = tmp_path / "g.bvh"
    assert main(["synth", str(mirrored_db), "--method", "graph", "--audio", str(wav), "-o", str(out),
                 "--npz", str(tmp_path / "g.npz")]) == 0
    prov = json.loads((tmp_path / "g.provenance.json").read_text())
    assert prov["options"]["method"] == "graph" and prov["steps"][0]["node"] >= 0
    assert prov["options"]["vad"] == "silero" and prov["options"]["transcript"] is False
    assert prov["options"]["rhythm"] == "chance"
    pos = np.load(tmp_path / "g.npz")["positions"]
    assert pos.shape[0] == prov["n_frames"] and np.isfinite(pos).all()
    # the input clips follow the detector asked for: the energy detector cuts where it hears pauses
    from gesturedb.features.pauses import voiced_segments
    from gesturedb.io.audio import read_audio

    assert main(["synth", str(mirrored_db), "--method", "graph", "--audio", str(wav), "-o", str(tmp_path / "e.bvh"),
                 "--vad", "energy", "--gap", "0.4", "--rhythm", "hamming"]) == 0
    pe = json.loads((tmp_path / "e.provenance.json").read_text())
    assert pe["options"]["vad"] == "energy" and pe["options"]["rhythm"] == "hamming"
    x, sr = read_audio(wav, sr=16000)
    s, e = voiced_segments(x, sr, method="energy")
    gap = s[1:] - e[:-1] > 0.4
    cuts = {int(round((a + b) / 2 * 15.0)) for a, b in zip(e[:-1][gap], s[1:][gap])}
    starts = {step["out_start"] for step in pe["steps"]}
    assert len(cuts) >= 2 and cuts <= starts  # every pause it hears cuts (long clips may be split further)
    capsys.readouterr()
    with pytest.raises(SystemExit) as ex:
        main(["synth", str(mirrored_db), "--method", "graph", "--audio", str(wav), "-o", str(tmp_path / "b.bvh"),
              "--vad", "webrtc"])
    assert ex.value.code == 2 and "--vad: invalid choice: 'webrtc'" in capsys.readouterr().err
    assert main(["synth", str(mirrored_db), "--audio", str(wav), "-o", str(tmp_path / "k.bvh"), "--rhythm", "hamming"]) == 2
    assert "--rhythm works with --method graph only" in capsys.readouterr().err
    nog = tmp_path / "nog.h5"
    assert main(["build", str(scott_dir), "-o", str(nog), "--no-graph", "-q"]) == 0
    capsys.readouterr()
    assert main(["synth", str(nog), "--method", "graph", "--audio", str(wav), "-o", str(tmp_path / "x.bvh")]) == 2
    err = capsys.readouterr().err
    assert "no motion graph" in err and "gesturedb graph" in err and not (tmp_path / "x.bvh").exists()


def test_graph_control_schedule_restricts_nodes(mirrored_db, scott_dir):
    """A node is allowed for a target clip when >= half its frames are in the mask at the clip's middle."""
    wav = scott_dir / "inputs" / "2_scott_0_2_2.wav"
    with gesturedb.open(mirrored_db) as db:
        synth = GraphSynthesizer(db)
        res = synth.synthesize(wav, control="0-30: left_wrist_height > p50")
        h = db.controls["left_wrist_height"]
        thr = np.percentile(h, 50)
        for s in res.steps:
            mid_s = (s["out_start"] + s["out_end"]) / 2 / db.fps
            a, n = synth.start[s["node"]], synth.length[s["node"]]
            frac = float(np.mean(h[a:a + n] > thr))
            if mid_s < 30:
                assert s["control"] is not None and frac >= 0.5 - 1.0 / n
            else:
                assert s["control"] is None
        assert any(s["control"] for s in res.steps)
        # excluding the only recording (its mirror goes with it) leaves no node: a named error
        orig = [r.name for r in db.recordings if not r.mirrored][0]
        with pytest.raises(SearchError, match="target clip 0 has no allowed node"):
            synth.synthesize(wav, exclude=[orig])


def test_rhythm_agreement_reproduces_the_database_signatures(scott_db):
    """eval.rhythm on a recording's own motion and words = the build's stored signatures (independent path)."""
    from gesturedb.eval.common import feature_joint_indices
    from gesturedb.eval.rhythm import rhythm_hamming
    from gesturedb.features.rhythm import hamming

    rec = scott_db.recordings[0]
    a, b = rec.start_frame, rec.start_frame + rec.n_frames
    words = scott_db.words
    sel = np.asarray(words.recording) == rec.index
    got = rhythm_hamming(np.asarray(scott_db.joint_positions[a:b], dtype=np.float64),
                         word_start_s=np.asarray(words.start_s)[sel], word_end_s=np.asarray(words.end_s)[sel],
                         fps=scott_db.fps, joints=feature_joint_indices(scott_db), gap_s=scott_db.config["gap_s"])
    c = scott_db.clips
    mine = np.asarray(c.recording) == rec.index
    want = float(np.mean(hamming(c.rhythm_audio[mine], c.rhythm_motion[mine])))
    assert got == pytest.approx(want)


def test_suggest_gap_gives_clips_of_a_few_seconds():
    rng = np.random.default_rng(4)
    pauses = rng.exponential(0.15, 400)
    gap = G.suggest_gap_s(pauses, 120.0, n_sequences=1)
    n_cuts = int(np.sum(pauses > gap))
    assert 0.1 <= gap <= 0.4
    assert n_cuts == round(120 / 3) - 1 or gap in (0.1, 0.4)
    assert G.suggest_gap_s(pauses, 2.0) == 0.4  # shorter than one clip: no cut needed
    assert G.suggest_gap_s(np.full(5, 0.05), 120.0) == 0.1  # too few pauses: the lower bound


def test_build_gap_auto_and_input_gap_auto(scott_dir, tmp_path):
    out = tmp_path / "auto.h5"
    with gesturedb.build([scott_dir], out, gap_s="auto") as db:
        gap = db.config["gap_s"]
        assert isinstance(gap, float) and 0.1 <= gap <= 0.4
        mean_clip_s = np.mean(db.clips.length) / db.fps
        assert mean_clip_s < 8.0  # the 0.4 s default gives ~13 s clips on this speaker
        res = GraphSynthesizer(db).synthesize(scott_dir / "inputs" / "2_scott_0_3_3.wav",
                                              transcript=scott_dir / "inputs" / "2_scott_0_3_3.TextGrid",
                                              gap_s="auto")
        assert 0.1 <= res.options["gap_s"] <= 0.4 and len(res.steps) >= 10


def test_build_without_transcript_cuts_at_voiced_pauses(scott_dir, tmp_path):
    """A recording without a transcript is cut at the pauses the energy detector finds (not one clip)."""
    from gesturedb.features.pauses import voiced_segments
    from gesturedb.io.audio import read_audio

    for ext in ("npz", "wav"):
        (tmp_path / f"2_scott_0_1_1.{ext}").symlink_to(scott_dir / f"2_scott_0_1_1.{ext}")
    with gesturedb.build([tmp_path], tmp_path / "nt.h5", gap_s=0.3) as db:
        words = db.words
        assert len(words) > 10 and set(words.text) == {""}
        x, sr = read_audio(scott_dir / "2_scott_0_1_1.wav", sr=int(db.config["sample_rate"]))
        vs, _ = voiced_segments(x, sr)
        np.testing.assert_allclose(np.asarray(words.start_s), vs[vs < db.n_frames / db.fps])
        assert len(db.clips) > 1
        GraphSynthesizer(db).synthesize(scott_dir / "inputs" / "2_scott_0_2_2.wav")


def test_graph_keyword_clips_take_phrases_with_the_speakers_own_keyword(mirrored_db, scott_dir, tmp_path):
    """Where the input says 'time', the clip is filled by a node that overlaps one of the speaker's
    own 'time's wherever the graph's edges allow; every other clip is unconstrained."""
    from gesturedb.db.keywords import add_keyword

    db_path = tmp_path / "kw.h5"
    shutil.copy(mirrored_db, db_path)
    add_keyword(db_path, "time")
    wav = scott_dir / "inputs" / "2_scott_0_2_2.wav"
    tg = scott_dir / "inputs" / "2_scott_0_2_2.TextGrid"
    with gesturedb.open(db_path) as db:
        synth = GraphSynthesizer(db)
        on = np.unpackbits(db.h5["subdatabases/time/mask"][()].view(np.uint8), bitorder="little")[:db.n_frames]
        for gap in (None, "auto"):
            res = synth.synthesize(wav, transcript=tg, gap_s=gap)
            words = gesturedb.io.read_transcript(tg)
            said = [float(s) for s, w in zip(words.start_s, words.text) if w.lower() == "time"]
            n_kw = 0
            for s in res.steps:
                a_s, b_s = s["out_start"] / db.fps, s["out_end"] / db.fps
                overlap = on[synth.start[s["node"]]:synth.start[s["node"]] + synth.length[s["node"]]].sum()
                if s["keyword"] is None:
                    assert not any(a_s <= t < b_s for t in said), (gap, s)  # no 'time' starts in it
                    continue
                assert s["keyword"].startswith("time")
                if s["keyword"] == "time":
                    n_kw += 1
                    assert overlap > 0, (gap, s)
                else:
                    assert s["keyword"] == "time (no node)" and overlap == 0
            assert n_kw >= 1, gap
            # without keywords nothing is labelled, and the choice differs
            res0 = synth.synthesize(wav, transcript=tg, gap_s=gap, keywords=False)
            assert all(s["keyword"] is None for s in res0.steps)
            if gap == "auto":
                assert [s["node"] for s in res0.steps] != [s["node"] for s in res.steps]


def test_upper_body_follows_one_path_and_root_and_legs_the_other(mirrored_db, scott_dir):
    """Split synthesis (Sec. 4.1-4.2): upper-body joints from the upper path's clips, the pelvis from the lower path's."""
    wav = scott_dir / "inputs" / "2_scott_0_3_3.wav"
    with gesturedb.open(mirrored_db) as db:
        synth = GraphSynthesizer(db)
        res = synth.synthesize(wav, seam_decay_s=0, smooth=False)
        upper, _lower = np.asarray(synth.upper_joints), synth.lower_joints
        rot = res.motion.rotations
        up_nodes = [s["node"] for s in res.steps]
        low_nodes = [s["lower"]["node"] for s in res.steps]
        assert up_nodes != low_nodes  # two searches, two paths (transitions alone pick other clips here)
        tilt = lambda q: R.multiply(G._yaw_inverse(q), q)  # noqa: E731  the pelvis without its heading
        for s in res.steps:
            a = s["out_start"]  # the clip's first frame is its node's first frame exactly (no blend, no smoothing)
            src_up = np.asarray(db.local_rotations[synth.start[s["node"]]], dtype=np.float64)
            src_low = np.asarray(db.local_rotations[synth.start[s["lower"]["node"]]], dtype=np.float64)
            # an upper joint hanging from the pelvis keeps its world rotation less the heading (the spine's
            # own orientation, G.join_upper_body); every other upper joint its local rotation
            hung = np.array([db.skeleton.parents[j] == 0 for j in upper])
            np.testing.assert_allclose(np.abs(np.sum(rot[a, upper[~hung]] * src_up[upper[~hung]], -1)), 1.0, atol=1e-6)
            for j in np.asarray(upper)[hung]:
                w_out, w_src = R.multiply(rot[a, 0], rot[a, j]), R.multiply(src_up[0], src_up[j])
                assert abs(abs(float(np.dot(tilt(w_out), tilt(w_src)))) - 1.0) < 1e-6
            assert abs(abs(float(np.dot(tilt(rot[a, 0]), tilt(src_low[0])))) - 1.0) < 1e-6
            # the lower body is not time-warped: frame a + k is its node's frame start + k (root height)
            assert s["lower"]["speed"] == 1.0
            k = np.arange(s["out_end"] - a)
            np.testing.assert_allclose(res.motion.root_positions[a + k, 1],
                                       db.root_positions[synth.start[s["lower"]["node"]] + k, 1], atol=1e-6)
        # the lower path's cost, recomputed from the provenance (transitions and duration fit only)
        o = res.options
        low = [s["lower"] for s in res.steps]
        total = o["w_data"] * sum(x["data_cost"] for x in low) + o["w_trans"] * sum(x["transition_cost"] for x in low[1:])
        assert total == pytest.approx(o["total_cost_lower"], rel=1e-9)
        assert all(x["data_cost"] == pytest.approx(o["l_dur"] * (abs(np.log(
            synth.length[x["node"]] / (s["out_end"] - s["out_start"]))) + synth.stepping[x["node"]]), abs=1e-9)
            for x, s in zip(low, res.steps))
        assert (synth.stepping >= 0).all() and (synth.stepping == 0).mean() >= 0.5  # the calmer half costs nothing


@pytest.mark.parametrize("method", ["dense", "bounded"])
def test_edge_blocks_on_dask_equal_the_local_ones(method, dask_client, monkeypatch):
    """The blocks of rows as Dask tasks (2 workers, a range of blocks each, finishing in any
    order): the local edges, every row reported once."""
    a, b = _low_rank(np.random.default_rng(10), 700, 90, dup=30)
    want = E.edges_from_features(a, b, max_out=8, method=method, block_elems=700 * 50)
    rows = []
    got = E.edges_from_features(a, b, max_out=8, method=method, block_elems=700 * 50, on_rows=rows.append,
                                scheduler=dask_client)
    # 14 blocks of 50 rows, 8 tasks wanted for 2 worker threads: 7 tasks of 2 blocks
    assert sorted(rows) == [100] * 7
    for x, y in zip(want, got):
        assert np.array_equal(x, y)


def test_edge_blocks_on_dask_fall_back_like_the_local_ones(dask_client):
    """Features without structure: the tasks' blocks go dense as the local ones do, same edges."""
    rng = np.random.default_rng(11)
    a, b = rng.normal(size=(300, 200)), rng.normal(size=(300, 200))
    want = E.edges_from_features(a, b, min_out=3, max_out=8, method="dense")
    got = E.edges_from_features(a, b, min_out=3, max_out=8, method="bounded", block_elems=300 * 20,
                                scheduler=dask_client)
    for x, y in zip(want, got):
        assert np.array_equal(x, y)


def test_cli_graph_on_a_local_cluster_rebuilds_the_same_graphs(scott_db_path, tmp_path, capsys):
    """`gesturedb graph DB --scheduler local:2`: worker processes (the features and bounds are
    pickled to them), started and stopped by the command; the graphs are the build's."""
    from gesturedb.cli.main import main

    db = tmp_path / "db.h5"
    shutil.copy(scott_db_path, db)
    with h5py.File(db, "r+") as h5:
        for grp in ("graph", "graph_lower", "style_model"):
            del h5[grp]
    assert main(["graph", str(db), "--scheduler", "local:2", "-q"]) == 0
    assert "motion graphs over" in capsys.readouterr().out
    with h5py.File(scott_db_path, "r") as a, h5py.File(db, "r") as b:
        for grp in ("graph", "graph_lower"):
            for k in ("indptr", "indices", "cost"):
                assert a[f"{grp}/{k}"][()].tobytes() == b[f"{grp}/{k}"][()].tobytes(), f"{grp}/{k}"
            assert dict(a[grp].attrs) == dict(b[grp].attrs)
    assert main(["graph", str(db), "--scheduler", "udp://x", "-q"]) == 2
    assert "scheduler: expected 'local:N' or 'tcp://HOST:PORT'; got 'udp://x'" in capsys.readouterr().err


def test_add_graph_checks_the_scheduler_before_copying_the_database(scott_db_path, tmp_path, monkeypatch):
    """A wrong scheduler fails before storage.edit copies the file (minutes for a large one)."""
    from gesturedb.db import storage
    from gesturedb.errors import ParameterError

    copies = []
    monkeypatch.setattr(storage, "edit", lambda *a, **k: copies.append(a) or pytest.fail("copied"))
    with pytest.raises(ParameterError, match="scheduler: expected 'local:N' or 'tcp://HOST:PORT'; got 'udp://x'"):
        G.add_graph(scott_db_path, scheduler="udp://x")
    assert copies == []


@pytest.mark.parametrize("n,speed", [(60, 1.25), (75, 0.8), (40, 1.0), (9, 0.8)])
def test_a_fitted_clip_keeps_its_own_pace_and_its_rhythm(n, speed):
    """fit_times: every output frame plays a source frame at the clip's own pace (rate 1) except at cuts,
    which skip (clip longer than its input clip) or repeat (shorter) frames just before the hands' rests,
    so that each rest plays where the uniform warp would put it; the clip's first and last frames are its
    own (its word gaps and the graph's transition costs stay where they are)."""
    from gesturedb.features.rhythm import speed_minima
    from gesturedb.synth.graph import fit_times

    fps = 15.0
    k = int(round((n - 1) * (speed - 1)))
    m = n + max(k, 0)
    hand = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(m) / 15.0)  # a beat a second, the hands at rest between
    t, cuts = fit_times(hand, n, speed, fps=fps)
    assert t.shape == (n,) and t[0] == 0
    steps = np.diff(t)
    if k == 0:
        assert cuts == [] and np.all(steps == 1)
        return
    if n < 15:  # no room for a cut: the uniform warp
        assert cuts == []
        np.testing.assert_allclose(t, np.arange(n) * speed)
        return
    assert cuts and t[-1] == (n - 1) + k
    jumps = np.flatnonzero(steps != 1) + 1
    assert jumps.tolist() == cuts and all(3 <= c <= n - 3 for c in cuts)
    assert np.all(np.isin(np.arange(n + k), t) | (k > 0))  # a shorter clip plays every frame of its own
    for p in speed_minima(hand[:n + k], fps=fps)[:-1]:  # every rest but the last cut's plays at p / speed
        where = np.flatnonzero(t == p)
        assert where.size and abs(where[-1] - p / speed) <= 1, (p, where, p / speed)


def test_graph_clips_play_at_their_own_pace_and_keep_the_strokes(mirrored_db, scott_dir):
    """On a real input the upper body plays whole source frames one after another except at seams (the
    clips' boundaries and the cuts that fit them), so the arms keep the database's band power: the BEAT2
    input 2_2, whose clips are mostly longer than its phrases, had 1.8x / 2.6x the database's arm power at
    2-4 / 4-7 Hz when the clips were played faster (0.97/1.11/1.17 now, seam/inside jerk 0.88)."""
    from gesturedb.eval import strokes as ST
    from gesturedb.eval.metrics import seam_jerk

    wav = scott_dir / "inputs" / "2_scott_0_2_2.wav"
    with gesturedb.open(mirrored_db) as db:
        res = GraphSynthesizer(db).synthesize(wav, transcript=wav.with_suffix(".TextGrid"))
        src = np.asarray(res.source_frames)
        jumps = np.flatnonzero(np.diff(src) != 1) + 1
        assert set(jumps.tolist()) <= set(np.asarray(res.boundaries).tolist())
        clip_starts = {s["out_start"] for s in res.steps[1:]}
        assert set(res.boundaries.tolist()) > clip_starts  # some clips were fitted by a cut
        arms = ST.band_groups(db.joint_names)["arms"]
        recs = [np.asarray(db.joint_positions[r.start_frame:r.start_frame + r.n_frames], dtype=np.float64)
                for r in db.recordings]
        ref = ST.pooled_band_power(recs, fps=db.fps, joints=arms)
        ratios = ST.band_ratios(ST.band_power(res.positions, fps=db.fps, joints=arms), ref)
        assert all(0.67 <= v <= 1.5 for v in ratios.values()), ratios
        assert seam_jerk(res.positions, fps=db.fps, boundaries=res.boundaries, joints=arms)["ratio"] < 1.1
