"""SIMD distance kernels against the scalar oracle, and the oracle against float64 numpy.

Sizes are the awkward ones {1, 3, 7, 8, 9, 15, 16, 17, 31, 33, 64, 96, 100}:
every combination of full vectors and tails for 8 and 16 lanes.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

try:
    from gesturedb import _core
except ImportError:  # pragma: no cover
    pytest.skip("gesturedb._core is not built", allow_module_level=True)

ROOT = Path(__file__).resolve().parents[1]
SIZES = [1, 3, 7, 8, 9, 15, 16, 17, 31, 33, 64, 96, 100]
ISAS = _core.kernels()
SIMD = [i for i in ISAS if i != "scalar"]


def rows_and_vec(rng, n_rows, dim):
    rows = rng.standard_normal((n_rows, dim)).astype(np.float32)
    v = rng.standard_normal(dim).astype(np.float32)
    return rows, v


def windows(a, n):
    """(W, n * Da) float64 copies of every n-frame window of a (F, Da)."""
    return np.lib.stride_tricks.sliding_window_view(a, (n, a.shape[1]))[:, 0].reshape(
        a.shape[0] - n + 1, -1).astype(np.float64)


def test_scalar_always_available_and_dispatch_default():
    assert ISAS[0] == "scalar"
    assert _core.get_simd() in ISAS


@pytest.mark.parametrize("dim", SIZES)
def test_l2sq_scalar_vs_float64(dim):
    rng = np.random.default_rng(dim)
    rows, v = rows_and_vec(rng, 37, dim)
    want = ((rows.astype(np.float64) - v.astype(np.float64)) ** 2).sum(axis=1)
    got = _core.l2sq_rows_f32(rows, v, "scalar")
    assert got.dtype == np.float32
    # float32 throughout, in the order of kernels.h: the difference and each FMA round once
    # (3u per term at most), then at most dim / 16 + 5 additions per lane and tree
    np.testing.assert_allclose(got, want, rtol=(dim + 8) * 2.0 ** -24, atol=0)


def _awkward_rows(rng, n_rows, dim):
    """Rows of mixed scales, with cancellation (rows near v), zeros, duplicates, inf and NaN."""
    rows, v = rows_and_vec(rng, n_rows, dim)
    rows *= np.float32(10.0) ** rng.integers(-6, 6, size=(n_rows, 1)).astype(np.float32)
    rows[1] = v + np.float32(1e-4) * rng.standard_normal(dim).astype(np.float32)
    rows[2] = v
    rows[3] = 0.0
    rows[4, 0] = np.inf
    rows[5, -1] = np.nan
    rows[6] = rows[7]
    return rows, v


@pytest.mark.parametrize("isa", SIMD)
@pytest.mark.parametrize("dim", SIZES)
def test_l2sq_same_bits_on_every_isa(isa, dim):
    """kernels.h's one summation order: every ISA gives the scalar path's bits (a search is then
    the same on any CPU, and shards on mixed CPUs rank like one table)."""
    rng = np.random.default_rng(100 + dim)
    for _ in range(5):
        rows, v = _awkward_rows(rng, 41, dim)
        np.testing.assert_array_equal(_core.l2sq_rows_f32(rows, v, isa), _core.l2sq_rows_f32(rows, v, "scalar"))


@pytest.mark.parametrize("isa", ISAS)
def test_l2sq_exact_on_integers(isa):
    """Integer features: every float32 partial sum is exact, so all ISAs agree bit for bit."""
    rng = np.random.default_rng(5)
    for dim in SIZES:
        rows = rng.integers(-8, 9, size=(19, dim)).astype(np.float32)
        v = rng.integers(-8, 9, size=dim).astype(np.float32)
        want = ((rows.astype(np.int64) - v.astype(np.int64)) ** 2).sum(axis=1)
        np.testing.assert_array_equal(_core.l2sq_rows_f32(rows, v, isa), want.astype(np.float32))


@pytest.mark.parametrize("isa", ISAS)
def test_l2sq_depends_only_on_row_values(isa):
    """Determinism contract: a row gets the same bits wherever it sits and however many rows go along."""
    rng = np.random.default_rng(6)
    for dim in SIZES:
        rows, v = rows_and_vec(rng, 50, dim)
        rows[31] = rows[4]
        full = _core.l2sq_rows_f32(rows, v, isa)
        assert full[31] == full[4]
        for lo in (0, 3, 4):
            part = _core.l2sq_rows_f32(np.ascontiguousarray(rows[lo:lo + 5]), v, isa)
            np.testing.assert_array_equal(part, full[lo:lo + 5])


@pytest.mark.parametrize("da", SIZES)
def test_cosdots_scalar_vs_float64(da):
    rng = np.random.default_rng(200 + da)
    a = rng.standard_normal((40, da)).astype(np.float32)
    for n in (1, 3, 8):
        q = rng.standard_normal((n, da)).astype(np.float32)
        qa, aa = _core.cosdots_f32(a, q, "scalar")
        w = windows(a, n)
        # float32 FMAs in the order of kernels.h: dot products can cancel, so the error is
        # bounded by the sum of |terms|
        scale = np.abs(w) @ np.abs(q.astype(np.float64).ravel())
        assert np.all(np.abs(qa - w @ q.astype(np.float64).ravel()) <= (n * da + 4) * 2.0 ** -24 * scale)
        np.testing.assert_allclose(aa, (w * w).sum(axis=1), rtol=(n * da + 4) * 2.0 ** -24, atol=0)


@pytest.mark.parametrize("isa", SIMD)
@pytest.mark.parametrize("da", SIZES)
def test_cosdots_same_bits_on_every_isa(isa, da):
    rng = np.random.default_rng(300 + da)
    a = rng.standard_normal((45, da)).astype(np.float32)
    a *= np.float32(10.0) ** rng.integers(-6, 6, size=(45, 1)).astype(np.float32)
    a[7] = 0.0
    a[9, 0] = np.inf
    a[11, -1] = np.nan
    for n in (1, 2, 3, 8):
        q = rng.standard_normal((n, da)).astype(np.float32)
        for got, want in zip(_core.cosdots_f32(a, q, isa), _core.cosdots_f32(a, q, "scalar")):
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("isa", ISAS)
def test_cosdots_depends_only_on_window_values(isa):
    rng = np.random.default_rng(7)
    a = rng.standard_normal((60, 14)).astype(np.float32)
    a[40:48] = a[3:11]  # the window at 40 duplicates the one at 3
    q = rng.standard_normal((8, 14)).astype(np.float32)
    qa, aa = _core.cosdots_f32(a, q, isa)
    assert qa[40] == qa[3] and aa[40] == aa[3]
    qa2, aa2 = _core.cosdots_f32(np.ascontiguousarray(a[3:20]), q, isa)
    np.testing.assert_array_equal(qa2, qa[3:13])
    np.testing.assert_array_equal(aa2, aa[3:13])


def test_kernel_rejects_bad_input():
    rows = np.ones((4, 5), np.float32)
    with pytest.raises(TypeError):
        _core.l2sq_rows_f32(rows.astype(np.float64), np.ones(5, np.float32), "scalar")
    with pytest.raises(ValueError, match="v: expected 5 values; got 4"):
        _core.l2sq_rows_f32(rows, np.ones(4, np.float32), "scalar")
    with pytest.raises(ValueError, match="simd: expected one of"):
        _core.l2sq_rows_f32(rows, np.ones(5, np.float32), "neon")


@pytest.fixture(scope="module")
def floors():
    # the benchmark's read floors are benchmark code, not in _core: benchmarks/floors.py
    # compiles benchmarks/floors.cpp on first use (a few seconds) and loads it with ctypes
    spec = importlib.util.spec_from_file_location("bench_floors", ROOT / "benchmarks" / "floors.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.load()


def test_stream_sum_matches_numpy(floors):
    a = np.random.default_rng(8).standard_normal((1000, 333)).astype(np.float32)
    np.testing.assert_allclose(floors.stream_sum_f32(a, 2), a.astype(np.float64).sum(), rtol=1e-5, atol=1e-2)


def test_gather_sum_matches_numpy_and_refuses_rows_outside(floors):
    rng = np.random.default_rng(9)
    a = rng.standard_normal((3000, 14)).astype(np.float32)
    starts = rng.integers(0, 3000 - 8, 1500).astype(np.int64)  # several chunks of 512, repeats
    want = sum(a[s:s + 8].astype(np.float64).sum() for s in starts)
    for threads in (1, 2):
        np.testing.assert_allclose(floors.gather_sum_f32(a, starts, 8, threads), want, rtol=1e-5, atol=1e-2)
    assert floors.gather_sum_f32(a, starts[:0], 8) == 0.0
    with pytest.raises(ValueError, match="2993 \\+ 8 reaches outside the 3000 rows"):
        floors.gather_sum_f32(a, np.array([5, 2993], np.int64), 8)


def test_the_floors_are_not_in_core():
    # benchmark code stays with the benchmarks (STYLE.md): the shipped extension does not carry it
    assert not hasattr(_core, "stream_sum_f32") and not hasattr(_core, "gather_sum_f32")


@pytest.mark.parametrize("isa", ISAS)
def test_env_override_selects_isa(isa):
    import os
    import subprocess
    import sys

    env = dict(os.environ, GESTUREDB_SIMD=isa)
    out = subprocess.run([sys.executable, "-c", "from gesturedb import _core; print(_core.get_simd())"],
                         env=env, capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == isa


def test_env_override_rejects_unknown_isa():
    import os
    import subprocess
    import sys

    env = dict(os.environ, GESTUREDB_SIMD="sse9")
    out = subprocess.run([sys.executable, "-c", "from gesturedb import _core"], env=env, cwd=ROOT,
                         capture_output=True, text=True)
    assert out.returncode != 0
    assert "GESTUREDB_SIMD: expected one of scalar" in out.stderr and "got 'sse9'" in out.stderr


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("dim", SIZES)
def test_l2sq_f16_vs_float64(isa, dim):
    """The half-precision filter kernel: binary16 rows converted exactly, float32 sums."""
    rng = np.random.default_rng(400 + dim)
    h = (rng.standard_normal((23, dim)) * 3).astype(np.float16)
    h[0, 0] = np.float16(6e-8)   # a subnormal half
    h[1, :] = np.float16(60000)  # near the top of the range
    v = rng.standard_normal(dim).astype(np.float32)
    want = ((h.astype(np.float64) - v.astype(np.float64)) ** 2).sum(axis=1)
    got = _core.l2sq_rows_f16(h.view(np.uint16), v, isa)
    np.testing.assert_allclose(got, want, rtol=(dim + 4) * 2.0 ** -23, atol=0)


def test_l2sq_f16_non_finite():
    h = np.array([[np.inf, 1.0], [np.nan, 0.0], [1.0, 2.0]], np.float16)
    v = np.zeros(2, np.float32)
    for isa in ISAS:
        got = _core.l2sq_rows_f16(h.view(np.uint16), v, isa)
        assert got[0] == np.inf and np.isnan(got[1]) and got[2] == 5.0


# --- frames in blocks of 16 (the pose projection filter) ---------------------

def _blocks(rows):
    """(F, dim) rows -> (ceil(F/16), dim, 16) blocks, padding frames zero."""
    F, dim = rows.shape
    pad = np.zeros((-(-F // 16) * 16, dim), np.float32)
    pad[:F] = rows
    return np.ascontiguousarray(pad.reshape(-1, 16, dim).transpose(0, 2, 1))


@pytest.mark.parametrize("dim", SIZES)
def test_l2sq_blocks_scalar_vs_float64(dim):
    rng = np.random.default_rng(300 + dim)
    rows, v = rows_and_vec(rng, 53, dim)
    want = ((rows.astype(np.float64) - v.astype(np.float64)) ** 2).sum(axis=1)
    got, umin = _core.l2sq_blocks_f32(_blocks(rows), 0, 53, v, "scalar")
    np.testing.assert_allclose(got, want, rtol=2 ** -23, atol=0)
    assert umin == np.inf  # no bound asked for


@pytest.mark.parametrize("isa", SIMD)
@pytest.mark.parametrize("dim", SIZES)
def test_l2sq_blocks_simd_vs_scalar_on_awkward_ranges(isa, dim):
    rng = np.random.default_rng(400 + dim)
    rows, v = rows_and_vec(rng, 70, dim)
    b = _blocks(rows)
    up = (1.5, 0.75, 0.125)
    for f0, f1 in [(0, 70), (0, 1), (3, 10), (15, 17), (16, 32), (5, 69), (31, 33), (64, 70), (20, 20)]:
        ref, _ = _core.l2sq_blocks_f32(b, f0, f1, v, "scalar")
        got, umin = _core.l2sq_blocks_f32(b, f0, f1, v, isa, up)
        assert got.shape == (f1 - f0,)
        np.testing.assert_allclose(got, ref, rtol=(dim + 4) * 2.0 ** -24, atol=0)
        # the fused upper bound: the minimum over exactly the frames in range
        # (a frame outside it, however close, must not count), to the bound's
        # own rounding (3 float32 operations)
        ub = up[0] * ref.astype(np.float64) + up[1] * rows[f0:f1, -1].astype(np.float64) + up[2]
        want = ub.min() if f1 > f0 else np.inf
        assert umin == pytest.approx(want, rel=(dim + 8) * 2.0 ** -24)


@pytest.mark.parametrize("isa", ISAS)
def test_l2sq_blocks_bound_ignores_nan_and_frames_out_of_range(isa):
    rng = np.random.default_rng(7)
    rows, v = rows_and_vec(rng, 48, 24)
    rows[17] = v  # the nearest frame by far, but outside [18, 40)
    rows[20, 3] = np.nan  # a NaN never lowers the bound ...
    b = _blocks(rows)
    d, umin = _core.l2sq_blocks_f32(b, 18, 40, v, isa, (1.0, 0.0, 0.0))
    assert np.isnan(d[2])  # ... and shows in the distances, for the caller's finiteness test
    assert umin == pytest.approx(np.nanmin(d), rel=1e-6)
    d, umin = _core.l2sq_blocks_f32(b, 20, 21, v, isa, (1.0, 0.0, 0.0))
    assert np.isnan(d[0]) and umin == np.inf


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("dim", [2, 7, 24, 33])
def test_l2sq_blocks_f16_vs_float64_of_the_half_values(isa, dim):
    """binary16 blocks: every ISA converts exactly, then sums like the float32 kernel."""
    rng = np.random.default_rng(500 + dim)
    rows, v = rows_and_vec(rng, 70, dim)
    rows[5, 0] = 3e-6  # a subnormal half
    h = rows.astype(np.float16)
    b = _blocks(h.astype(np.float32)).astype(np.float16).view(np.uint16)
    up = (1.5, 0.75, 0.125)
    for f0, f1 in [(0, 70), (3, 10), (15, 17), (31, 33), (5, 69), (20, 20)]:
        want = ((h[f0:f1].astype(np.float64) - v.astype(np.float64)) ** 2).sum(axis=1)
        got, umin = _core.l2sq_blocks_f16(b, f0, f1, v, isa, up)
        np.testing.assert_allclose(got, want, rtol=(dim + 4) * 2.0 ** -24, atol=1e-30)
        ub = up[0] * want + up[1] * h[f0:f1, -1].astype(np.float64) + up[2]
        assert umin == pytest.approx(ub.min() if f1 > f0 else np.inf, rel=(dim + 8) * 2.0 ** -24)
        ref32, _ = _core.l2sq_blocks_f32(_blocks(h.astype(np.float32)), f0, f1, v, isa)
        np.testing.assert_array_equal(got, ref32)  # same sums as float32 blocks of the same values


def test_l2sq_blocks_rejects_bad_shapes():
    b = np.zeros((2, 3, 16), np.float32)
    with pytest.raises(ValueError, match=r"blocks: expected \(n_blocks, dim, 16\)"):
        _core.l2sq_blocks_f32(np.zeros((2, 3, 8), np.float32), 0, 4, np.zeros(3, np.float32), "scalar")
    with pytest.raises(ValueError, match=r"\[f0, f1\): expected inside \[0, 32\)"):
        _core.l2sq_blocks_f32(b, 0, 33, np.zeros(3, np.float32), "scalar")


# --- blocked batch: exact pairs and the projection filter --------------------

@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("dim", SIZES)
def test_l2sq_pairs_bit_identical_to_single_rows(isa, dim):
    """The batch decides on these values: they must be the single path's, bit for bit."""
    rng = np.random.default_rng(500 + dim)
    rows, _ = rows_and_vec(rng, 29, dim)
    vs = rng.standard_normal((11, dim)).astype(np.float32)
    for n in (1, 15, 16, 17, 40):  # groups of 16 and tails
        ri = rng.integers(0, 29, n).astype(np.int64)
        vi = rng.integers(0, 11, n).astype(np.int64)
        got = _core.l2sq_pairs_f32(rows, vs, ri, vi, isa)
        want = np.array([_core.l2sq_rows_f32(rows[r:r + 1], vs[v], isa)[0] for r, v in zip(ri, vi)])
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("n", [1, 2, 3, 8])
@pytest.mark.parametrize("da", [1, 3, 7, 14, 16, 17])
def test_cosdots_pairs_bit_identical_to_cosdots(isa, n, da):
    rng = np.random.default_rng(600 + 31 * n + da)
    audio = rng.standard_normal((40, da)).astype(np.float32)
    qs = rng.standard_normal((5, n * da)).astype(np.float32)
    starts = rng.integers(0, 40 - n + 1, 23).astype(np.int64)
    qi = rng.integers(0, 5, 23).astype(np.int64)
    got = _core.cosdots_pairs_f32(audio, starts, qs, qi, isa)
    for i, (g, q) in enumerate(zip(starts, qi)):
        qa, _ = _core.cosdots_f32(audio[g:g + n], qs[q].reshape(n, da), isa)
        assert got[i] == qa[0]


def _proj_case(rng, n_rows, J, n_lanes):
    z = rng.standard_normal((n_rows, J)).astype(np.float32)
    x = rng.standard_normal((n_lanes, J)).astype(np.float32)
    nrow = (z.astype(np.float64) ** 2).sum(1).astype(np.float32)
    nrow[3::7] = np.inf  # rows that must not count (the caller keeps at least one that does)
    rres = np.abs(z[:, -1])
    lanes = np.empty((6, n_lanes), np.float32)
    lanes[0] = (x.astype(np.float64) ** 2).sum(1)
    lanes[1] = 1.0 + rng.random(n_lanes) * 1e-3  # aup
    lanes[2] = rng.random(n_lanes)                # bup
    lanes[3] = rng.random(n_lanes) * 1e-2         # cup
    lanes[4] = 1.0 - rng.random(n_lanes) * 1e-3  # alo
    lanes[5] = rng.random(n_lanes) * 1e-2         # clo
    return z, nrow, rres, x, lanes


@pytest.mark.parametrize("J", [2, 3, 8, 17, 24, 33])
@pytest.mark.parametrize("n_rows", [1, 5, 6, 7, 13, 56])
def test_projfilter_scalar_vs_float64(J, n_rows):
    rng = np.random.default_rng(700 + J * 101 + n_rows)
    z, nrow, rres, x, lanes = _proj_case(rng, n_rows, J, 70)
    dh, umin, keep = _core.projfilter_f32(z, nrow, rres, x, lanes, "scalar")
    assert dh.shape == (n_rows, 128) and keep.shape == (n_rows, 2)
    d64 = ((z.astype(np.float64)[:, None, :] - x.astype(np.float64)[None]) ** 2).sum(-1)
    ok = np.isfinite(nrow)
    scale = (np.linalg.norm(z, axis=1)[:, None] + np.linalg.norm(x, axis=1)[None]) ** 2
    np.testing.assert_array_less(np.abs(dh[ok, :70] - d64[ok]), 4 * (J + 8) * 2.0 ** -24 * scale[ok] + 1e-30)
    assert np.all(np.isinf(dh[~ok, :70]))
    ub = lanes[1] * d64 + (lanes[2] * rres[:, None] + lanes[3])
    if ok.any():
        # dh is within the cancellation bound of the distance, the bound's own arithmetic within 1e-6
        atol = 1.01 * 4 * (J + 8) * 2.0 ** -24 * scale[ok].max(0)
        np.testing.assert_array_less(np.abs(umin[:70] - ub[ok].min(0)), atol + 1e-6 * np.abs(ub[ok].min(0)))
    else:
        assert np.all(np.isinf(umin[:70]))
    bits = (keep[:, :, None] >> np.arange(64, dtype=np.uint64)) & np.uint64(1)
    kept = bits.reshape(n_rows, 128)[:, :70].astype(bool)
    assert not kept[~ok].any()
    # the row that gives the smallest upper bound is always kept
    if ok.any():
        lb = lanes[4] * dh[:, :70] - lanes[5]
        np.testing.assert_array_equal(kept, lb <= umin[:70])


@pytest.mark.parametrize("isa", SIMD)
@pytest.mark.parametrize("J", [2, 3, 8, 17, 24, 33])
@pytest.mark.parametrize("n_rows", [1, 5, 6, 7, 13, 56])
def test_projfilter_simd_vs_scalar(isa, J, n_rows):
    rng = np.random.default_rng(800 + J * 101 + n_rows)
    z, nrow, rres, x, lanes = _proj_case(rng, n_rows, J, 130)
    ref = _core.projfilter_f32(z, nrow, rres, x, lanes, "scalar")
    got = _core.projfilter_f32(z, nrow, rres, x, lanes, isa)
    ok = np.isfinite(nrow)
    scale = (np.linalg.norm(z, axis=1)[:, None] + np.linalg.norm(x, axis=1)[None]) ** 2
    tol = 4 * (J + 8) * 2.0 ** -24 * scale
    np.testing.assert_array_less(np.abs(got[0][ok, :130] - ref[0][ok, :130]), tol[ok] + 1e-30)
    assert np.all(np.isinf(got[0][~ok, :130]))
    atol = 1.01 * 2 * tol[ok].max(0) if ok.any() else 0.0
    np.testing.assert_array_less(np.abs(got[1][:130] - ref[1][:130]), atol + 1e-6 * np.abs(ref[1][:130]) + 1e-30)
    # keep bits: the same rule on the kernel's own values
    bits = (got[2][:, :, None] >> np.arange(64, dtype=np.uint64)) & np.uint64(1)
    kept = bits.reshape(n_rows, -1)[:, :130].astype(bool)
    lb = lanes[4] * got[0][:, :130] - lanes[5]
    near = np.abs(lb - got[1][:130]) <= 1e-5 * np.abs(got[1][:130])
    np.testing.assert_array_equal(kept[~near], (lb <= got[1][:130])[~near])


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("n_lanes", [1, 7, 8, 9, 15, 16, 17, 31, 33, 63, 64, 65])
def test_projfilter_every_panel_width(isa, n_lanes):
    """A panel as narrow as the lanes need (8, 16, 32, then panels of 64): each ISA's distances
    stay within the bound of the float64 ones, its bound and keep bits follow the same rule."""
    rng = np.random.default_rng(900 + n_lanes)
    J, n_rows = 24, 13
    z, nrow, rres, x, lanes = _proj_case(rng, n_rows, J, n_lanes)
    dh, umin, keep = _core.projfilter_f32(z, nrow, rres, x, lanes, isa)
    qp = {1: 8, 7: 8, 8: 8, 9: 16, 15: 16, 16: 16, 17: 32, 31: 32, 33: 64, 63: 64, 64: 64, 65: 128}[n_lanes]
    assert dh.shape == (n_rows, qp) and umin.shape == (qp,) and keep.shape == (n_rows, (qp + 63) // 64)
    d64 = ((z.astype(np.float64)[:, None, :] - x.astype(np.float64)[None]) ** 2).sum(-1)
    ok = np.isfinite(nrow)
    scale = (np.linalg.norm(z, axis=1)[:, None] + np.linalg.norm(x, axis=1)[None]) ** 2
    np.testing.assert_array_less(np.abs(dh[ok, :n_lanes] - d64[ok]), 4 * (J + 8) * 2.0 ** -24 * scale[ok] + 1e-30)
    assert np.all(np.isinf(dh[~ok, :n_lanes]))
    ub = lanes[1] * d64 + (lanes[2] * rres[:, None] + lanes[3])
    atol = 1.01 * 4 * (J + 8) * 2.0 ** -24 * scale[ok].max(0)
    np.testing.assert_array_less(np.abs(umin[:n_lanes] - ub[ok].min(0)), atol + 1e-6 * np.abs(ub[ok].min(0)))
    bits = (keep[:, :, None] >> np.arange(64, dtype=np.uint64)) & np.uint64(1)
    kept = bits.reshape(n_rows, -1)[:, :n_lanes].astype(bool)
    lb = lanes[4] * dh[:, :n_lanes] - lanes[5]
    near = np.abs(lb - umin[:n_lanes]) <= 1e-5 * np.abs(umin[:n_lanes])
    np.testing.assert_array_equal(kept[~near], (lb <= umin[:n_lanes])[~near])
    assert not kept[~ok].any()
    # padding lanes (zero x, aup = alo = 1) never set a bit beyond the panel's lanes
    assert not bits.reshape(n_rows, -1)[:, qp:].any()
