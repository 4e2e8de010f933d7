"""The projection filter of pose pre-selection (gesturedb.search.PoseProjection).

It is only a filter: every search must give exactly what the plain path gives
(same segments, starts, distances, ranks) on every instruction set, and what
the float64 oracle of ../shared/spec/search.md gives.
"""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb import search
from gesturedb.errors import ParameterError
from test_search import (
    ISAS,
    assert_same_search,
    check_search,
    continuous_db,
    exact_db,
    pack_bits,
)


@pytest.fixture(params=ISAS)
def isa(request):
    with search.simd(request.param):
        yield request.param


@pytest.fixture(params=[False, True], ids=["f32", "f16"])
def half(request):
    """float32 or binary16 projection rows: the same results either way."""
    return request.param


def _both(P, A, st, ln, q, init, proj=None, half=False, **kw):
    proj = proj if proj is not None else search.PoseProjection(P, half=half)
    a = search.rank_sum_search(P, A, st, ln, q, init, **kw)
    b = search.rank_sum_search(P, A, st, ln, q, init, pose_proj=proj, **kw)
    assert_same_search(a, b)
    return b


def _real_arrays(db):
    """The search's arrays of a gesturedb database: pose, audio, chunk starts and lengths."""
    return (np.ascontiguousarray(db.pose_features[:], dtype=np.float32),
            np.ascontiguousarray(db.audio_features[:], dtype=np.float32),
            np.ascontiguousarray(db.h5["chunks/start"][:], dtype=np.int64),
            np.ascontiguousarray(db.h5["chunks/length"][:], dtype=np.int64))


def stacked_recordings(rng, *, n_rec=12, Da=6, lag=2, window=4):
    """Smooth random 'joint' trajectories (8 joints x 3) stacked like pose
    features: frame f holds frames f, f-2, f-4, f-6 of its recording, clamped
    to the recording's first frame, in a slowly turning body frame; recordings
    cut into 64-frame segments (the last one shorter)."""
    P_parts, st, ln = [], [], []
    start = 0
    for _ in range(n_rec):
        F = int(rng.integers(20, 300))
        x = np.cumsum(rng.standard_normal((F, 24)) * 0.03, axis=0) + rng.standard_normal(24)
        yaw = np.cumsum(rng.standard_normal(F) * 0.01)
        f = np.arange(F)
        rows = []
        for k in range(window):
            src = np.maximum(f - k * lag, 0)
            p = x[src].reshape(F, 8, 3).copy()
            c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]  # the current frame's facing
            p[..., 0], p[..., 2] = c * p[..., 0] + s * p[..., 2], -s * p[..., 0] + c * p[..., 2]
            rows.append(p.reshape(F, 24))
        P_parts.append(np.concatenate(rows, axis=1))
        for a in range(0, F, 64):
            st.append(start + a)
            ln.append(min(64, F - a))
        start += F
    P = np.ascontiguousarray(np.concatenate(P_parts), dtype=np.float32)
    A = rng.standard_normal((P.shape[0], Da)).astype(np.float32)
    return P, A, np.array(st, np.int64), np.array(ln, np.int64)


def test_projection_rows_bound_the_distance():
    """The bounds the kernel relies on, in float64: |z_f - z_x|^2 <= d <= ... + 4 r_f r_x."""
    rng = np.random.default_rng(1)
    P, _, _, _ = stacked_recordings(rng, n_rec=4)
    pp = search.PoseProjection(P)
    np.testing.assert_allclose(pp.basis.T @ pp.basis, np.eye(pp.basis.shape[1]), atol=1e-12)
    x = P[7].astype(np.float64)
    dx = x - pp.mean
    zx = np.append(dx @ pp.basis, np.linalg.norm(dx - pp.basis @ (pp.basis.T @ dx)))
    d = ((P.astype(np.float64) - x) ** 2).sum(1)
    lo = ((pp.rows.astype(np.float64) - zx) ** 2).sum(1)
    hi = lo + 4 * pp.rows[:, -1] * zx[-1]
    assert np.all(lo <= d * (1 + 1e-5) + 1e-9) and np.all(d <= hi * (1 + 1e-5) + 1e-9)
    assert np.all(np.linalg.norm(P - pp.mean, axis=1) <= pp.max_norm)


def test_half_rows_are_the_rounding_of_the_float64_projection():
    """What the kernel's bound for binary16 rows assumes: each stored value is
    within 2^-11 of its float64 projection relative to itself (2^-25 absolute
    among subnormals), so a row within 2^-11 max_norm + sqrt(J) 2^-25."""
    rng = np.random.default_rng(11)
    P, _, _, _ = stacked_recordings(rng, n_rec=4)
    p16 = search.PoseProjection(P, half=True)
    p32 = search.PoseProjection(P)
    assert p16.blocks.dtype == np.float16 and p16.blocks.nbytes * 2 == p32.blocks.nbytes
    d = P.astype(np.float64) - p16.mean
    z = np.column_stack([d @ p16.basis, np.linalg.norm(d - (d @ p16.basis) @ p16.basis.T, axis=1)])
    err = np.abs(p16.rows.astype(np.float64) - z)
    assert np.all(err <= 2.0 ** -11 * np.abs(z) * (1 + 2.0 ** -10) + 2.0 ** -25)
    J = z.shape[1]
    assert np.linalg.norm(err, axis=1).max() <= 2.0 ** -11 * p16.max_norm + np.sqrt(J) * 2.0 ** -25
    np.testing.assert_array_equal(p16.rows, z.astype(np.float16).astype(np.float32))


def test_stacked_recordings_with_clamped_starts_and_heavy_masks(isa, half):
    rng = np.random.default_rng(2)
    P, A, st, ln = stacked_recordings(rng)
    proj = search.PoseProjection(P, half=half)
    q = rng.standard_normal((90, A.shape[1])).astype(np.float32)
    F, M = P.shape[0], st.shape[0]
    # recording starts: the first rows repeat the clamped frame 0 in every part
    heavy = pack_bits(rng.random(F) < 0.15)
    exclude = rng.random(M) < 0.4
    sched = np.stack([pack_bits(rng.random(F) < 0.3) for _ in range(-(-90 // 8))])
    for init in (P[0], P[st[3]], P[F - 1]):
        for kw in (dict(), dict(k=4), dict(allowed=heavy, exclude=exclude), dict(allowed=sched),
                   dict(step=5, k=2)):
            res = _both(P, A, st, ln, q, init, proj=proj, **kw)
            check_search(res, P, A, st, ln, q, init, exact=False, **kw)


def test_long_segments_cross_the_keep_collections_blocks(isa, half):
    """Segments of hundreds of candidates (the filter collects kept candidates 256 at
    a time, 8 flags per load): few or most kept (24 or 2 columns), runs of allowed
    frames starting and ending anywhere."""
    rng = np.random.default_rng(8)
    P, A, _, _ = stacked_recordings(rng, n_rec=10)
    F = P.shape[0]
    st = np.array([0, F // 3 - 11, 2 * F // 3 + 5], dtype=np.int64)
    ln = np.diff(np.r_[st, F]).astype(np.int64)
    assert ln.min() > 300
    q = rng.standard_normal((40, A.shape[1])).astype(np.float32)
    runs = np.zeros(F, bool)
    for a in rng.integers(0, F - 1, 12):
        runs[a:a + int(rng.integers(1, 400))] = True
    for n_columns in (24, 2):
        proj = search.PoseProjection(P, n_columns=n_columns, half=half)
        for kw in (dict(), dict(allowed=pack_bits(runs)), dict(allowed=pack_bits(rng.random(F) < 0.9), k=2)):
            res = _both(P, A, st, ln, q, P[st[1] + 7], proj=proj, **kw)
            check_search(res, P, A, st, ln, q, P[st[1] + 7], exact=False, **kw)


def test_random_unstructured_and_exact_ties(isa, half):
    """No structure to project (iid rows) and integer data full of exact ties:
    the filter keeps what it must and the tie rules still hold."""
    rng = np.random.default_rng(3)
    P, A, st, ln = continuous_db(rng, Dp=33)
    q = rng.standard_normal((70, A.shape[1])).astype(np.float32)
    for n_columns in (2, 5, 24, 34):
        _both(P, A, st, ln, q, P[3], proj=search.PoseProjection(P, n_columns=n_columns, half=half), k=2)
    P2, A2, st2, ln2 = exact_db(rng, Dp=7)
    q2 = rng.integers(-2, 3, size=(53, A2.shape[1])).astype(np.float32)
    for n_columns in (2, 4, 8):
        res = _both(P2, A2, st2, ln2, q2, P2[9], proj=search.PoseProjection(P2, n_columns=n_columns, half=half), step=6)
        check_search(res, P2, A2, st2, ln2, q2, P2[9], step=6)


def test_near_identical_candidates_and_non_finite_rows(isa, half):
    rng = np.random.default_rng(4)
    M, L, Dp = 30, 40, 12
    base = rng.standard_normal((M, 1, Dp)).astype(np.float32) * 4
    P = np.ascontiguousarray((base + rng.standard_normal((M, L, Dp)).astype(np.float32) * 1e-6)
                             .reshape(M * L, Dp), dtype=np.float32)
    A = rng.standard_normal((M * L, 3)).astype(np.float32)
    st = np.arange(M, dtype=np.int64) * L
    ln = np.full(M, L, np.int64)
    q = rng.standard_normal((40, 3)).astype(np.float32)
    for k in (1, 4):
        _both(P, A, st, ln, q, P[5], k=k, half=half)
    P[st[4] + 2] = np.nan
    P[st[6] + 1, 3] = 1e30
    _both(P, A, st, ln, q, P[0], half=half)
    P[st[7] + 3, 0] = np.inf  # no bound at all: the exact scan everywhere
    proj = search.PoseProjection(P, half=half)
    assert not np.isfinite(proj.max_norm)
    _both(P, A, st, ln, q, P[0], proj=proj)
    batch = search.rank_sum_search_batch(P, A, st, ln, [q, q[:21]], np.stack([P[0], P[st[5]]]),
                                         method="per_query", pose_proj=proj)
    assert_same_search(batch[0], search.rank_sum_search(P, A, st, ln, q, P[0]))


def test_real_database_with_masks(scott_db, half):
    P, A, st, ln = _real_arrays(scott_db)
    proj = search.PoseProjection(P, half=half)
    rng = np.random.default_rng(5)
    q = rng.standard_normal((300, A.shape[1])).astype(np.float32)
    F = P.shape[0]
    allowed = pack_bits(rng.random(F) < 0.25)
    for isa in ISAS:
        with search.simd(isa):
            for kw in (dict(), dict(k=3), dict(allowed=allowed)):
                res = _both(P, A, st, ln, q, P[10], proj=proj, **kw)
                check_search(res, P, A, st, ln, q, P[10], exact=False, **kw)


def test_projection_validation():
    rng = np.random.default_rng(6)
    P, A, st, ln = continuous_db(rng, Dp=8, n_segments=5)
    q = np.ones((8, A.shape[1]), np.float32)
    with pytest.raises(ParameterError, match="pose_proj: expected a PoseProjection made from this pose array"):
        search.rank_sum_search(P, A, st, ln, q, P[0], pose_proj=search.PoseProjection(P.copy()))
    with pytest.raises(ParameterError, match=r"pose_proj: expected gesturedb.search.PoseProjection\(pose\)"):
        search.rank_sum_step(P, A, st, ln, P[0], q, pose_proj=P)
    with pytest.raises(ParameterError, match=r"n_columns: expected an int in \[2, 9\]; got 10"):
        search.PoseProjection(P, n_columns=10)
    with pytest.raises(ParameterError, match="pose: expected float32 C-contiguous"):
        search.PoseProjection(P.astype(np.float64))


def test_searcher_uses_the_projection_by_default_with_identical_output(scott_db, scott_dir):
    from gesturedb.synth import Searcher

    speech = scott_dir / "inputs/2_scott_0_2_2.wav"
    fast = Searcher(scott_db)
    plain = Searcher(scott_db, projection=False)
    assert isinstance(fast.pose_projection(), search.PoseProjection)
    assert fast.pose_projection().half  # binary16 rows by default
    assert plain.pose_projection() is None
    for k in (1, 3):
        a = fast.synthesize(speech, k=k, smooth=False)
        b = plain.synthesize(speech, k=k, smooth=False)
        assert a.steps == b.steps
        np.testing.assert_array_equal(a.positions, b.positions)


def test_keep_fraction_separates_motion_from_unstructured_rows(scott_db):
    """Real pose features keep a few candidates per segment; i.i.d. rows keep most."""
    real = search.PoseProjection(np.ascontiguousarray(scott_db.pose_features[:], dtype=np.float32))
    assert real.keep_fraction < 0.1
    rng = np.random.default_rng(7)
    noise = search.PoseProjection(rng.standard_normal((4000, 96)).astype(np.float32))
    assert noise.keep_fraction > 0.5
    P, _, _, _ = stacked_recordings(rng)
    assert search.PoseProjection(P).keep_fraction < 0.25


# ---------------------------------------------------------------------------
# the blocked batch through the projection: the same results as without it and
# as each query alone


def _batch_three_ways(P, A, st, ln, queries, init, proj, **kw):
    """Blocked with and without the projection, and per query alone (no projection)."""
    with_proj = search.rank_sum_search_batch(P, A, st, ln, queries, init, method="blocked",
                                             pose_proj=proj, **kw)
    plain = search.rank_sum_search_batch(P, A, st, ln, queries, init, method="blocked", **kw)
    k = kw.pop("k", 1)
    exclude = kw.pop("exclude", None)
    for i, q in enumerate(queries):
        ki = int(k[i]) if np.ndim(k) else k
        ex = None if exclude is None else (exclude[i] if exclude.ndim == 2 else exclude)
        one = search.rank_sum_search(P, A, st, ln, q, init[i], k=ki, exclude=ex, **kw)
        assert_same_search(with_proj[i], one, f"query {i} (projection)")
        assert_same_search(plain[i], one, f"query {i} (plain)")
    return with_proj


@pytest.mark.parametrize("preselect", ["pose", "audio"])
def test_blocked_batch_with_projection_masks_and_exclusions(isa, preselect, half):
    """70 queries (two panels of 64 lanes), partial last windows, per-query k,
    per-query exclusion rows, a heavy shared mask and a per-step schedule."""
    rng = np.random.default_rng(21)
    P, A, st, ln = stacked_recordings(rng, n_rec=14)
    proj = search.PoseProjection(P, half=half)
    F, M, Q = P.shape[0], st.shape[0], 70
    queries = [rng.standard_normal((int(rng.choice([24, 21, 40])), A.shape[1])).astype(np.float32)
               for _ in range(Q)]
    init = P[rng.integers(0, F, Q)]
    init[0] = P[0]  # a clamped recording start
    ks = rng.integers(1, 6, Q)
    exclude = rng.random((Q, M)) < 0.3
    kw = dict(k=ks, preselect=preselect, exclude=exclude)
    _batch_three_ways(P, A, st, ln, queries, init, proj, **kw)
    _batch_three_ways(P, A, st, ln, queries, init, proj, allowed=pack_bits(rng.random(F) < 0.15), **kw)
    same_len = [q[:24] for q in queries]
    sched = np.stack([pack_bits(rng.random(F) < 0.3) for _ in range(3)])
    _batch_three_ways(P, A, st, ln, same_len, init, proj, allowed=sched, **kw)


def test_blocked_batch_with_projection_ties_and_non_finite(isa, half):
    """Integer data full of exact ties; NaN and huge rows (their segments are
    scanned exactly); a huge initial pose (that lane scans everything exactly)."""
    rng = np.random.default_rng(22)
    P, A, st, ln = exact_db(rng, Dp=9, Da=3, n_segments=30)
    Q = 20
    queries = [rng.integers(-2, 3, size=(24, 3)).astype(np.float32) for _ in range(Q)]
    init = P[rng.integers(0, P.shape[0], Q)]
    for n_columns in (2, 5, 10):
        _batch_three_ways(P, A, st, ln, queries, init, search.PoseProjection(P, n_columns=n_columns, half=half),
                          k=rng.integers(1, 4, Q))
    P2, A2, st2, ln2 = continuous_db(rng, Dp=20, n_segments=30)
    P2[st2[3] + 2] = np.nan
    P2[st2[5]:st2[5] + 4] *= 3e18  # |z|^2 beyond the filter's range
    queries2 = [rng.standard_normal((32, A2.shape[1])).astype(np.float32) for _ in range(Q)]
    init2 = P2[rng.integers(0, P2.shape[0], Q)]
    init2[4] = P2[st2[5] + 2]  # a huge previous pose: that lane scans everything exactly
    init2[6] = P2[st2[5] + 1]  # start next to the huge rows
    with np.errstate(all="ignore"):
        proj = search.PoseProjection(P2, half=half)
        _batch_three_ways(P2, A2, st2, ln2, queries2, init2, proj)


def test_blocked_batch_with_projection_on_the_real_database(scott_db, half):
    """The refiner's self-search on the real recording: every chunk's audio as a
    query, excluding its own neighbourhood, k from 1 to 15, with and without a mask."""
    P, A, st, ln = _real_arrays(scott_db)
    proj = search.PoseProjection(P, half=half)
    rng = np.random.default_rng(23)
    M = st.shape[0]
    idx = rng.choice(M, size=min(M, 48), replace=False)
    queries = [A[st[m]:st[m] + 64] for m in idx if ln[m] >= 64][:40]
    idx = [m for m in idx if ln[m] >= 64][:40]
    Q = len(queries)
    init = P[rng.integers(0, P.shape[0], Q)]
    exclude = np.zeros((Q, M), bool)
    for i, m in enumerate(idx):
        exclude[i, max(0, m - 1):m + 2] = True
    ks = rng.integers(1, 16, Q)
    for isa in ISAS:
        with search.simd(isa):
            _batch_three_ways(P, A, st, ln, queries, init, proj, k=ks, exclude=exclude)
            _batch_three_ways(P, A, st, ln, queries, init, proj, k=ks, exclude=exclude,
                              allowed=pack_bits(rng.random(P.shape[0]) < 0.25))
            _batch_three_ways(P, A, st, ln, queries, init, proj, k=ks, exclude=exclude, preselect="audio")
