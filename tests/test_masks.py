"""Control masks: bitset layout and algebra, the mask expression language, schedules.

Bitsets are checked bit by bit against the layout of ../shared/spec/search.md
(frame f is bit f & 63 of word f >> 6), expressions against plain numpy boolean
arithmetic in float64, schedules against an independent per-step coverage count.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from gesturedb import control as M
from gesturedb.errors import ParameterError

SIZES = [1, 5, 63, 64, 65, 127, 128, 129, 1000]
FEATURES = list(M.CONTROL_UNITS)


def random_controls(n_frames: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = {}
    for name in FEATURES:
        if name.endswith("_speed"):
            v = rng.gamma(2.0, 0.25, n_frames)  # m/s, mostly 0.1 .. 1.5
        elif name.endswith("_height"):
            v = rng.normal(1.1, 0.15, n_frames)  # m
        else:
            v = np.abs(rng.normal(0.0, 0.1, n_frames))
        out[name] = v.astype(np.float32)
    return out


def words_from_spec(bits: np.ndarray) -> np.ndarray:
    """Independent packing straight from the spec's wording, with Python ints."""
    F = bits.shape[0]
    words = [0] * ((F + 63) // 64)
    for f in np.flatnonzero(bits).tolist():
        words[f >> 6] |= 1 << (f & 63)
    return np.array(words, dtype=np.uint64)


def error_lines(excinfo) -> list[str]:
    return str(excinfo.value).split("\n")


# --------------------------------------------------------------------------------------
# bitsets
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("F", SIZES)
def test_pack_matches_spec_layout_and_roundtrips(F):
    rng = np.random.default_rng(F)
    bits = rng.random(F) < 0.3
    words = M.pack_bits(bits)
    assert words.dtype == np.uint64 and words.shape == (math.ceil(F / 64),)
    assert words.flags.c_contiguous
    np.testing.assert_array_equal(words, words_from_spec(bits))
    np.testing.assert_array_equal(M.unpack_bits(words, F), bits)
    assert M.count_bits(words) == int(bits.sum())
    if F % 64:
        assert int(words[-1]) >> (F % 64) == 0, "padding bits past F must be clear"


def test_pack_known_frames():
    bits = np.zeros(130, dtype=bool)
    bits[[0, 63, 64, 129]] = True
    words = M.pack_bits(bits)
    assert [int(w) for w in words] == [1 | (1 << 63), 1, 1 << 1]


def test_pack_zero_frames_and_rows():
    assert M.pack_bits(np.zeros(0, dtype=bool)).shape == (0,)
    assert M.n_words(0) == 0 and M.n_words(64) == 1 and M.n_words(65) == 2
    rng = np.random.default_rng(1)
    rows = rng.random((4, 70)) < 0.5
    packed = M.pack_bits(rows)
    assert packed.shape == (4, 2)
    for r in range(4):
        np.testing.assert_array_equal(packed[r], M.pack_bits(rows[r]))
    np.testing.assert_array_equal(M.unpack_bits(packed, 70), rows)
    np.testing.assert_array_equal(M.count_bits(packed), rows.sum(axis=1))


@pytest.mark.parametrize("F", SIZES)
def test_algebra_matches_numpy_bools(F):
    rng = np.random.default_rng(100 + F)
    a, b, c = (rng.random(F) < p for p in (0.5, 0.3, 0.8))
    A, B, C = (M.pack_bits(x) for x in (a, b, c))
    np.testing.assert_array_equal(M.unpack_bits(M.mask_and(A, B), F), a & b)
    np.testing.assert_array_equal(M.unpack_bits(M.mask_or(A, B), F), a | b)
    np.testing.assert_array_equal(M.unpack_bits(M.mask_and(A, B, C), F), a & b & c)
    np.testing.assert_array_equal(M.unpack_bits(M.mask_or(A, B, C), F), a | b | c)
    not_a = M.mask_not(A, F)
    np.testing.assert_array_equal(not_a, M.pack_bits(~a))  # padding cleared, bit for bit
    assert M.count_bits(not_a) == F - M.count_bits(A)
    np.testing.assert_array_equal(M.mask_not(not_a, F), A)
    assert M.count_bits(M.full_mask(F)) == F
    np.testing.assert_array_equal(M.full_mask(F), M.mask_not(M.empty_mask(F), F))
    assert M.count_bits(M.empty_mask(F)) == 0


def test_algebra_broadcasts_one_mask_over_steps():
    rng = np.random.default_rng(2)
    steps = rng.random((5, 200)) < 0.5
    one = rng.random(200) < 0.5
    out = M.mask_and(M.pack_bits(steps), M.pack_bits(one))
    np.testing.assert_array_equal(M.unpack_bits(out, 200), steps & one)
    np.testing.assert_array_equal(M.mask_not(M.pack_bits(steps), 200), M.pack_bits(~steps))


def test_step_bitsets_read_like_the_array_they_stand_for():
    rng = np.random.default_rng(9)
    F, S = 300, 40
    rows = np.stack([M.full_mask(F)] + [M.pack_bits(rng.random(F) < p) for p in (0.2, 0.5, 0.8)])
    a = M.StepBitsets(rows, rng.integers(0, 4, S))
    b = M.StepBitsets(rows[[0, 2]], rng.integers(0, 2, S))
    dense_a, dense_b = np.asarray(a), np.asarray(b)
    assert dense_a.shape == a.shape == (S, M.n_words(F)) and len(a) == S and a.dtype == np.uint64
    for i in (0, 7, S - 1, -1):
        np.testing.assert_array_equal(a[i], dense_a[i])
    np.testing.assert_array_equal(a[3:9], dense_a[3:9])
    both = a & b
    np.testing.assert_array_equal(np.asarray(both), dense_a & dense_b)
    # one row per distinct pair of rows, not per step
    assert both.rows.shape[0] == len(set(zip(a.of_step.tolist(), b.of_step.tolist())))
    with pytest.raises(ValueError):
        a[0][0] = 0  # a step's row is a view of the shared rows: read-only
    with pytest.raises(ParameterError, match=r"StepBitsets: of_step: expected \(S,\) indices into the 4 rows"):
        M.StepBitsets(rows, [0, 4])
    with pytest.raises(ParameterError, match=r"StepBitsets: rows: expected a uint64 bitset array"):
        M.StepBitsets(rows.astype(np.int64), [0])
    with pytest.raises(ParameterError, match=r"StepBitsets &: expected StepBitsets of shape \(40, 5\)"):
        a & M.StepBitsets(rows, [0])


def test_bitset_errors():
    with pytest.raises(ParameterError, match=r"pack_bits: expected a bool array .* got float64"):
        M.pack_bits(np.ones(10))
    with pytest.raises(ParameterError, match=r"expected 2 uint64 words for 65 frames; got 1"):
        M.unpack_bits(np.zeros(1, dtype=np.uint64), 65)
    with pytest.raises(ParameterError, match=r"mask_and: argument 2 has 3 words, argument 1 has 2"):
        M.mask_and(np.zeros(2, np.uint64), np.zeros(3, np.uint64))
    with pytest.raises(ParameterError, match=r"mask_or: argument 1: expected a uint64 bitset .* got int64"):
        M.mask_or(np.zeros(2, np.int64), np.zeros(2, np.uint64))
    with pytest.raises(ParameterError, match=r"mask_and: shapes \(2, 2\), \(3, 2\) do not broadcast"):
        M.mask_and(np.zeros((2, 2), np.uint64), np.zeros((3, 2), np.uint64))
    with pytest.raises(ParameterError, match=r"mask_not: words: expected 1 uint64 words for 10 frames; got 2"):
        M.mask_not(np.zeros(2, np.uint64), 10)
    with pytest.raises(ParameterError, match=r"n_frames: expected an integer >= 0; got -1"):
        M.full_mask(-1)


def test_validate_bitset():
    good = M.pack_bits(np.ones(70, dtype=bool))
    assert M.validate_bitset(good, 70) is good
    stray = good.copy()
    stray[-1] |= np.uint64(1 << 10)  # frame 74 of a 70-frame database
    with pytest.raises(ParameterError, match=r"allowed: bits set past the last frame 69"):
        M.validate_bitset(stray, 70)
    with pytest.raises(ParameterError, match=r"allowed: expected uint64 \(2,\) or \(steps, 2\) for 70 frames; got int64"):
        M.validate_bitset(good.astype(np.int64), 70)
    rows = np.stack([good] * 4)
    M.validate_bitset(rows, 70, n_steps=4)
    with pytest.raises(ParameterError, match=r"expected one bitset per search step, \(3, 2\); got \(4, 2\)"):
        M.validate_bitset(rows, 70, n_steps=3)
    with pytest.raises(ParameterError, match=r"expected a C-contiguous array"):
        M.validate_bitset(np.stack([good, good], axis=1).T, 70)  # a transposed view


def brute_candidate_counts(bits, seg_start, seg_len, n, exclude):
    counts = []
    for m, (st, ln) in enumerate(zip(seg_start, seg_len)):
        c = 0
        if not exclude[m]:
            for s in range(1, ln - n + 1):
                g = st + s
                c += bool(bits[g] and bits[g + n - 1])
        counts.append(c)
    return np.array(counts)


@pytest.mark.parametrize("seed", range(4))
def test_candidate_counts_match_the_spec_rule(seed):
    rng = np.random.default_rng(seed)
    F = int(rng.integers(50, 400))
    bits = rng.random(F) < 0.6
    M_ = int(rng.integers(1, 12))
    seg_start = rng.integers(0, F - 1, M_)
    seg_len = np.array([rng.integers(0, F - s + 1) for s in seg_start])
    exclude = rng.random(M_) < 0.2
    for n in (1, 3, 8, 9):
        got = M.candidate_counts(
            M.pack_bits(bits), n_frames=F, seg_start=seg_start, seg_len=seg_len, n=n, exclude=exclude
        )
        np.testing.assert_array_equal(got, brute_candidate_counts(bits, seg_start, seg_len, n, exclude))


def test_candidate_counts_errors():
    w = M.full_mask(100)
    with pytest.raises(ParameterError, match=r"segments must lie within the 100 database frames"):
        M.candidate_counts(w, n_frames=100, seg_start=np.array([90]), seg_len=np.array([20]), n=8)
    with pytest.raises(ParameterError, match=r"exclude: expected bool \(1,\); got int64 \(1,\)"):
        M.candidate_counts(
            w, n_frames=100, seg_start=np.array([0]), seg_len=np.array([64]), n=8, exclude=np.array([0])
        )


# --------------------------------------------------------------------------------------
# comparisons, percentiles, units
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("p", [0, 15, 50, 85, 97.5, 100])
def test_percentile_threshold_matches_numpy(p):
    v = random_controls(777, seed=3)["left_wrist_speed"]
    assert M.percentile_threshold(v, p) == np.percentile(v.astype(np.float64), p)


@pytest.mark.parametrize("op", ["<", "<=", ">", ">="])
@pytest.mark.parametrize("F", [1, 64, 65, 1000])
def test_percentile_comparison_matches_numpy(op, F):
    c = random_controls(F, seed=F)
    v = c["left_wrist_height"].astype(np.float64)
    thr = np.percentile(v, 85)
    expected = {"<": v < thr, "<=": v <= thr, ">": v > thr, ">=": v >= thr}[op]
    r = M.compile_mask(f"left_wrist_height {op} p85", controls=c)
    np.testing.assert_array_equal(r.bits(), expected)
    assert r.n_set == int(expected.sum()) and r.n_frames == F
    assert r.thresholds == {f"left_wrist_height {op} p85": thr}
    (cmp,) = r.comparisons
    assert cmp.percentile == 85 and cmp.unit == "m" and cmp.threshold == thr
    assert f"p85 = {thr:.4g} m" in r.describe()


def test_comparison_is_done_in_float64():
    # p50 of two adjacent float32 values lies between them; rounded to float32 it
    # would become 1.0 and '>= p50' would wrongly allow both frames.
    one = np.float32(1.0)
    v = np.array([one, np.nextafter(one, np.float32(2))], dtype=np.float32)
    r = M.compile_mask("x >= p50", controls={"x": v})
    assert r.bits().tolist() == [False, True]


def test_units_convert_to_the_feature_unit():
    c = random_controls(500, seed=4)
    h = c["left_wrist_height"].astype(np.float64)
    s = c["left_wrist_speed"].astype(np.float64)
    for expr, expected in [
        ("left_wrist_height > 110 cm", h > 1.10),
        ("left_wrist_height > 110cm", h > 1.10),
        ("left_wrist_height > 1100 mm", h > 1.10),
        ("left_wrist_height > 1.1 m", h > 1.10),
        ("left_wrist_height > 1.1", h > 1.10),
        ("left_wrist_speed < 40 cm/s", s < 0.4),
        ("left_wrist_speed < .4 m/s", s < 0.4),
        ("left_wrist_speed >= 4e-1", s >= 0.4),
        ("height_asymmetry > -5 cm", c["height_asymmetry"] > -0.05),
    ]:
        r = M.compile_mask(expr, controls=c)
        np.testing.assert_array_equal(r.bits(), expected, err_msg=expr)
    r = M.compile_mask("left_wrist_speed < 40 cm/s", controls=c)
    assert r.thresholds == {"left_wrist_speed < 40 cm/s": 0.4}
    # 35 cm is the double nearest 0.35, as if 0.35 had been typed (35 * 0.01 is not)
    assert M.compile_mask("mirror_distance <= 35 cm", controls=c).thresholds["mirror_distance <= 35 cm"] == 0.35
    exact = {k: np.zeros(3) for k in c}
    exact["mirror_distance"] = np.array([0.35, 0.36, 0.34])
    assert M.compile_mask("mirror_distance <= 35 cm", controls=exact).bits().tolist() == [True, False, True]
    assert str(r.comparisons[0]) == "left_wrist_speed < 40 cm/s (0.4 m/s)"


def test_unit_of_new_features_from_name_or_override():
    rng = np.random.default_rng(5)
    c = {"elbow_height": rng.random(50), "energy": rng.random(50), "foo": rng.random(50)}
    assert M.feature_unit("elbow_height") == "m"
    assert M.feature_unit("energy") is None
    np.testing.assert_array_equal(
        M.compile_mask("elbow_height < 50 cm", controls=c).bits(), c["elbow_height"] < 0.5
    )
    np.testing.assert_array_equal(
        M.compile_mask("foo < 50 cm", controls=c, units={"foo": "m"}).bits(), c["foo"] < 0.5
    )
    with pytest.raises(ParameterError, match=r"'energy' has no unit; write the value without 'cm'"):
        M.compile_mask("energy < 50 cm", controls=c)
    with pytest.raises(ParameterError, match=r"unit 'm/s' is a speed but 'elbow_height' is a length in m"):
        M.compile_mask("elbow_height < 2 m/s", controls=c)
    with pytest.raises(ParameterError, match=r"units\['foo'\]: expected one of m, cm"):
        M.compile_mask("foo < 1", controls=c, units={"foo": "inch"})


# --------------------------------------------------------------------------------------
# parser: precedence, parentheses, names
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def abc():
    rng = np.random.default_rng(6)
    F = 301
    bools = {k: rng.random(F) < 0.5 for k in "abc"}
    controls = random_controls(F, seed=6)
    named = {"a": M.pack_bits(bools["a"]), "b": bools["b"], "c": M.pack_bits(bools["c"])}
    return bools, controls, named


@pytest.mark.parametrize(
    "expr, canonical, reference",
    [
        ("a or b and not c", "(a or (b and (not c)))", lambda a, b, c: a | (b & ~c)),
        ("not a and b", "((not a) and b)", lambda a, b, c: ~a & b),
        ("not not a", "(not (not a))", lambda a, b, c: a),
        ("a and b or c", "((a and b) or c)", lambda a, b, c: (a & b) | c),
        ("(a or b) and not (c or a)", "((a or b) and (not (c or a)))", lambda a, b, c: (a | b) & ~(c | a)),
        ("a AND (b Or NOT c)", "(a and (b or (not c)))", lambda a, b, c: a & (b | ~c)),
        ("((a))", "a", lambda a, b, c: a),
    ],
)
def test_precedence_and_parentheses(abc, expr, canonical, reference):
    bools, controls, named = abc
    assert M.parse_mask_expression(expr).canonical == canonical
    r = M.compile_mask(expr, controls=controls, named=named)
    np.testing.assert_array_equal(r.bits(), reference(bools["a"], bools["b"], bools["c"]))


def test_mixed_comparisons_and_names_match_numpy(abc):
    bools, controls, named = abc
    h = controls["left_wrist_height"].astype(np.float64)
    s = controls["right_wrist_speed"].astype(np.float64)
    expected = (h > np.percentile(h, 70)) & ~bools["a"] | (s <= 0.3)
    r = M.compile_mask(
        "left_wrist_height > p70 and not a or right_wrist_speed <= 30 cm/s", controls=controls, named=named
    )
    np.testing.assert_array_equal(r.bits(), expected)
    assert set(r.thresholds) == {"left_wrist_height > p70", "right_wrist_speed <= 30 cm/s"}
    parsed = M.parse_mask_expression("left_wrist_height > p70 and not a or right_wrist_speed <= 30 cm/s")
    assert parsed.features == ("left_wrist_height", "right_wrist_speed") and parsed.names == ("a",)


def test_predefined_and_generated_names(abc):
    _, controls, _ = abc
    for name, expr in M.DEFAULT_NAMED.items():
        np.testing.assert_array_equal(
            M.compile_mask(name, controls=controls).words, M.compile_mask(expr, controls=controls).words
        )
    asym = controls["height_asymmetry"].astype(np.float64)
    np.testing.assert_array_equal(
        M.compile_mask("symmetric", controls=controls).bits(), asym < np.percentile(asym, 15)
    )
    np.testing.assert_array_equal(
        M.compile_mask("asymmetric", controls=controls).bits(), asym > np.percentile(asym, 85)
    )
    pre = M.percentile_masks(controls)
    assert set(pre) == {f"{f}_{lvl}" for f in controls for lvl in ("high", "low")}
    for f, v in controls.items():
        v = v.astype(np.float64)
        np.testing.assert_array_equal(pre[f"{f}_high"].bits(), v > np.percentile(v, 85))
        np.testing.assert_array_equal(pre[f"{f}_low"].bits(), v < np.percentile(v, 15))
        np.testing.assert_array_equal(
            M.compile_mask(f"{f}_high", controls=controls).words, pre[f"{f}_high"].words
        )
    # the paper's "high left wrist" is the generated mask under a friendlier name
    np.testing.assert_array_equal(pre["left_wrist_height_high"].words, M.compile_mask("left_wrist_high", controls=controls).words)
    # saved masks from the build can stand in for the expressions
    saved = {k: r.words for k, r in pre.items()}
    np.testing.assert_array_equal(
        M.compile_mask("left_wrist_speed_low and not mirror_distance_high", controls=controls, named=saved).words,
        M.compile_mask("left_wrist_speed < p15 and not mirror_distance > p85", controls=controls).words,
    )


def test_caller_names_extend_and_override(abc):
    bools, controls, named = abc
    v = controls["left_wrist_speed"].astype(np.float64)
    extra = {
        "calm": "left_wrist_speed < p30 and not a",
        "calm_or_b": "calm or b",
        "symmetric": "a",  # overrides the predefined one
        **named,
    }
    r = M.compile_mask("calm_or_b", controls=controls, named=extra)
    np.testing.assert_array_equal(r.bits(), ((v < np.percentile(v, 30)) & ~bools["a"]) | bools["b"])
    assert r.comparisons[0].source == "calm"
    assert "[in 'calm']" in r.describe()
    np.testing.assert_array_equal(M.compile_mask("symmetric", controls=controls, named=extra).bits(), bools["a"])
    defs = M.mask_definitions(controls, extra)
    assert defs["calm"] == extra["calm"] and defs["left_wrist_high"] == "left_wrist_height > p85"
    assert defs["mirror_distance_low"] == "mirror_distance < p15"


def test_result_never_aliases_saved_masks(abc):
    _, controls, named = abc
    before = named["a"].copy()
    r = M.compile_mask("a", controls=controls, named=named)
    r.words[:] = 0
    np.testing.assert_array_equal(named["a"], before)


def test_saved_masks_without_controls():
    F = 130
    a = np.zeros(F, bool)
    a[[0, 129]] = True
    r = M.compile_mask("not a", controls={}, named={"a": M.pack_bits(a)}, n_frames=F)
    np.testing.assert_array_equal(r.bits(), ~a)
    with pytest.raises(ParameterError, match=r"controls is empty and n_frames is not given"):
        M.compile_mask("a", controls={}, named={"a": M.pack_bits(a)})


def test_controls_and_masks_as_h5py_datasets_compile_like_arrays(tmp_path):
    """Database.control_datasets / mask_datasets: datasets are checked by shape and dtype
    and read when used; the bits are those of the arrays."""
    h5py = pytest.importorskip("h5py")
    F = 1000
    controls = random_controls(F, seed=3)
    saved = {"calm": M.compile_mask("left_wrist_speed < p40", controls=controls).words}
    with h5py.File(tmp_path / "c.h5", "w") as f:
        for k, v in controls.items():
            f[f"c/{k}"] = v
        f["m/calm"] = saved["calm"]
        f["bad/left_wrist_height"] = np.zeros((F, 2), np.float32)
    with h5py.File(tmp_path / "c.h5", "r") as f:
        lazy_c = {k: f[f"c/{k}"] for k in f["c"]}
        lazy_m = {"calm": f["m/calm"]}
        for expr in ("left_wrist_height > p85 and calm", "not symmetric or right_wrist_speed < 20 cm/s"):
            want = M.compile_mask(expr, controls=controls, named=saved)
            got = M.compile_mask(expr, controls=lazy_c, named=lazy_m)
            np.testing.assert_array_equal(got.words, want.words)
        with pytest.raises(ParameterError, match=r"controls\['left_wrist_height'\]: expected a 1-D array .*\(1000, 2\)"):
            M.compile_mask("symmetric", controls={"left_wrist_height": f["bad/left_wrist_height"]})


# --------------------------------------------------------------------------------------
# every error message
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "expr, message, column",
    [
        ("left_wrist_height > > 3", r"column 21: expected a number .* or a percentile .* after '>'; got '>'", 21),
        ("left_wrist_height >", r"after '>'; got the end of the expression", 20),
        ("(left_wrist_high or symmetric", r"expected '\)' to close the '\(' at column 1; got the end", 30),
        ("left_wrist_high)", r"unmatched '\)'", 16),
        ("left_wrist_high & symmetric", r"unexpected character '&' \(use 'and'\)", 17),
        ("left_wrist_height == 3", r"operator '==': equality is not supported", 19),
        ("left_wrist_height => 3", r"operator '=>': did you mean '>='\?", 19),
        ("left_wrist_height > 3 ft", r"unknown unit 'ft' after 3; expected one of m, cm, mm, m/s, cm/s, mm/s", 23),
        ("left_wrist_height > p150", r"percentile 'p150' is outside p0..p100", 21),
        ("left_wrist_height > -p85", r"a percentile takes no sign", 21),
        ("3 < left_wrist_height", r"got the number '3' \(the feature goes on the left\)", 1),
        ("p85", r"got the percentile 'p85' \(percentiles go on the right", 1),
        ("> 3", r"comparison '>' needs a control feature on its left", 1),
        ("left_wrist_high left_wrist_low", r"expected 'and', 'or' or the end of the expression; got 'left_wrist_low'", 17),
        ("symmetric and", r"expected a mask name, a comparison .* got the end of the expression", 14),
        ("symmetric and or asymmetric", r"got 'or'", 15),
        ("left_wrist_hieght > p85", r"unknown control feature 'left_wrist_hieght' \(did you mean 'left_wrist_height'", 1),
        ("symmetric and symetric", r"unknown mask name 'symetric' \(did you mean 'symmetric'", 15),
        ("left_wrist_height", r"'left_wrist_height' is a control feature, not a mask: compare it .* 'left_wrist_height > p85'", 1),
        ("not symmetric > 3", r"'symmetric' is a named mask, not a control feature", 5),
    ],
)
def test_expression_errors_point_at_the_column(abc, expr, message, column):
    _, controls, _ = abc
    with pytest.raises(ParameterError, match=message) as excinfo:
        M.compile_mask(expr, controls=controls)
    lines = error_lines(excinfo)
    assert f"column {column}:" in lines[0]
    assert lines[1] == "    " + expr
    assert lines[2] == "    " + " " * (column - 1) + "^"


def test_unknown_names_list_the_known_ones(abc):
    _, controls, _ = abc
    with pytest.raises(ParameterError, match=r"known features: hand_distance, hand_speed, height_asymmetry, left_hand_radius, left_wrist_forward, left_wrist_height"):
        M.compile_mask("nonsense > 3", controls=controls)
    with pytest.raises(ParameterError, match=r"known names: .*left_wrist_fast.*symmetric"):
        M.compile_mask("nonsense", controls=controls)


def test_other_errors(abc):
    _, controls, named = abc
    with pytest.raises(ParameterError, match=r"mask expression is empty"):
        M.compile_mask("   ", controls=controls)
    with pytest.raises(ParameterError, match=r"named mask 'calm' = 'left_wrist_sped < p30': .*unknown control feature 'left_wrist_sped'"):
        M.compile_mask("calm", controls=controls, named={"calm": "left_wrist_sped < p30"})
    with pytest.raises(ParameterError, match=r"named mask 'calm' = 'left_wrist_speed < < 3': .*column 20"):
        M.compile_mask("a or calm", controls=controls, named={"calm": "left_wrist_speed < < 3", **named})
    with pytest.raises(ParameterError, match=r"named mask 'x' refers to itself: x -> y -> x"):
        M.compile_mask("x", controls=controls, named={"x": "y and symmetric", "y": "not x"})
    with pytest.raises(ParameterError, match=r"named\['bad'\]: expected uint64 \(5,\) .* for 301 frames; got uint64 \(4,\)"):
        M.compile_mask("bad", controls=controls, named={"bad": np.zeros(4, np.uint64)})
    with pytest.raises(ParameterError, match=r"named\['bad'\]: expected a bool mask \(301,\); got \(300,\)"):
        M.compile_mask("bad", controls=controls, named={"bad": np.zeros(300, bool)})
    for bad_name in ("and", "p85", "two words"):
        with pytest.raises(ParameterError, match=r"named: "):
            M.compile_mask("symmetric", controls=controls, named={bad_name: "symmetric"})
    ragged = dict(controls, mirror_distance=np.zeros(300, np.float32))
    with pytest.raises(ParameterError, match=r"controls\['mirror_distance'\]: expected 301 frames like controls\['left_wrist_height'\]; got 300"):
        M.compile_mask("symmetric", controls=ragged)
    nan = dict(controls, left_wrist_speed=controls["left_wrist_speed"].copy())
    nan["left_wrist_speed"][[7, 9]] = np.nan
    with pytest.raises(ParameterError, match=r"controls\['left_wrist_speed'\]: expected finite values; got 2 NaN/inf \(first at frame 7\)"):
        M.compile_mask("left_wrist_slow", controls=nan)
    # the NaN does not matter to masks that do not read that feature
    M.compile_mask("left_wrist_high", controls=nan)
    with pytest.raises(ParameterError, match=r"controls\['left_wrist_height'\]: expected a 1-D array"):
        M.compile_mask("symmetric", controls=dict(controls, left_wrist_height=np.zeros((301, 2))))


# --------------------------------------------------------------------------------------
# nearest percentile that leaves candidates
# --------------------------------------------------------------------------------------


def brute_closest(values, op, p, within_bits, order):
    values = values.astype(np.float64)
    for q in order:
        thr = np.percentile(values, q)
        m = {"<": values < thr, "<=": values <= thr, ">": values > thr, ">=": values >= thr}[op]
        if np.any(m & within_bits):
            return q, thr, int((m & within_bits).sum())
    return None


@pytest.mark.parametrize("op", ["<", "<=", ">", ">="])
def test_closest_percentile_matches_a_linear_scan(op):
    rng = np.random.default_rng(7)
    v = rng.normal(size=2000).astype(np.float32)
    # the other terms of the expression only allow the middle of the distribution, so
    # "> p85" / "< p15" leave nothing and the answer sits where the band ends
    v64 = v.astype(np.float64)
    band = (v64 > np.percentile(v64, 34.5)) & (v64 < np.percentile(v64, 60.5))
    within = M.pack_bits(band)
    p = 85 if op.startswith(">") else 15
    got = M.closest_percentile_with_candidates(v, op, p, within=within)
    loosening = range(p - 1, -1, -1) if op.startswith(">") else range(p + 1, 101)
    q, thr, n = brute_closest(v, op, p, band, loosening)
    assert (got.percentile, got.threshold, got.n_set) == (q, thr, n)
    assert (q == 60) if op.startswith(">") else (q == 35)


def test_closest_percentile_edge_cases():
    v = np.arange(100, dtype=np.float32)
    hit = M.closest_percentile_with_candidates(v, ">", 50)
    assert hit.percentile == 50 and hit.threshold == 49.5 and hit.n_set == 50  # p itself is fine
    assert M.closest_percentile_with_candidates(v, ">", 50, within=M.empty_mask(100)) is None
    assert M.closest_percentile_with_candidates(v, ">", 100).percentile == 99
    # a non-integer p keeps its fraction (v > p_q keeps frame 90 iff 0.99 q < 90, q < 90.9)
    low = M.closest_percentile_with_candidates(v, ">", 97.5, within=M.pack_bits(np.arange(100) == 90))
    assert low.percentile == 90.5 and low.threshold == np.percentile(v.astype(np.float64), 90.5)
    # ... and the search ends exactly at the range limit (only p100 = 99 reaches frame 99)
    top = M.closest_percentile_with_candidates(v, "<=", 2.5, within=M.pack_bits(np.arange(100) == 99))
    assert (top.percentile, top.threshold, top.n_set) == (100.0, 99.0, 1)
    # accept decides what "candidates" means: here at least 10 frames (p90 = 89.1)
    ten = M.closest_percentile_with_candidates(v, ">", 95, accept=lambda w: M.count_bits(w) >= 10)
    assert ten.percentile == 90 and ten.n_set == 10
    with pytest.raises(ParameterError, match=r"op: expected one of <, <=, >, >=; got '=='"):
        M.closest_percentile_with_candidates(v, "==", 50)
    with pytest.raises(ParameterError, match=r"p: expected a number in \[0, 100\]; got 101"):
        M.closest_percentile_with_candidates(v, ">", 101)


def test_suggest_percentiles_moves_one_comparison_at_a_time():
    F = 3000
    c = random_controls(F, seed=8)
    # make the hands' heights anti-correlated with asymmetry, so "high and symmetric" is empty
    c["height_asymmetry"] = (c["left_wrist_height"] - 0.5).astype(np.float32)
    h = c["left_wrist_height"].astype(np.float64)
    a = c["height_asymmetry"].astype(np.float64)
    expr = "left_wrist_height > p85 and symmetric"
    assert M.compile_mask(expr, controls=c).n_set == 0
    out = M.suggest_percentiles(expr, controls=c)
    assert [r.comparison.text for r in out] == ["left_wrist_height > p85", "height_asymmetry < p15"]
    assert out[1].comparison.source == "symmetric"
    # brute force: move p of the first comparison outward until the AND is non-empty
    sym = a < np.percentile(a, 15)
    for q in range(84, -1, -1):
        if np.any((h > np.percentile(h, q)) & sym):
            break
    assert out[0].suggestion.percentile == q
    assert out[0].suggestion.n_set == int(((h > np.percentile(h, q)) & sym).sum())
    hi = h > np.percentile(h, 85)
    for q2 in range(16, 101):
        if np.any(hi & (a < np.percentile(a, q2))):
            break
    assert out[1].suggestion.percentile == q2
    assert "instead of 'left_wrist_height > p85'" in str(out[0])


# --------------------------------------------------------------------------------------
# schedules
# --------------------------------------------------------------------------------------


def test_parse_schedule_open_ends_and_order():
    items = M.parse_schedule(
        "24-: asymmetric; -12: left_wrist_height > p85;\n12-24: left_wrist_speed < p15 and symmetric;"
    )
    assert items == [
        (0.0, 12.0, "left_wrist_height > p85"),
        (12.0, 24.0, "left_wrist_speed < p15 and symmetric"),
        (24.0, None, "asymmetric"),
    ]
    assert items[1].start_s == 12.0 and items[2].end_s is None
    assert M.parse_schedule("-: symmetric") == [(0.0, None, "symmetric")]
    assert M.parse_schedule(" 1.5s - 3s : a ; 3-4.25:b") == [(1.5, 3.0, "a"), (3.0, 4.25, "b")]


@pytest.mark.parametrize(
    "text, message",
    [
        ("0-12 left_wrist_high", r"item 1 \('0-12 left_wrist_high'\): expected 'START-END: EXPRESSION'.*no ':' found"),
        ("0-12: a; 12-x: b", r"item 2 \('12-x: b'\): end 'x' is not a number of seconds"),
        ("abc-12: a", r"item 1 \('abc-12: a'\): start 'abc' is not a number of seconds"),
        ("12: a", r"item 1 \('12: a'\): range '12': expected START-END in seconds"),
        ("-3-5: a", r"range '-3-5': expected START-END"),
        ("0-5: a; 12-6: b", r"item 2 \('12-6: b'\): end 6 s is not after start 12 s"),
        ("5-5: a", r"end 5 s is not after start 5 s"),
        ("0-5:   ", r"item 1 \('0-5:'\): no mask expression after ':'"),
        ("0-12: a; 10-24: b", r"items 1 \('0-12: a'\) and 2 \('10-24: b'\) overlap from 10 s to 12 s"),
        ("30-: a; 24-: b", r"items 1 \('30-: a'\) and 2 \('24-: b'\) overlap from 30 s to the end"),
        ("0-12: a; 12-24: left_wrist_speed < < 3", r"item 2 .*: mask expression: column 20: expected a number"),
        (" ; ;", r"control schedule is empty"),
    ],
)
def test_schedule_errors_name_the_item(text, message):
    with pytest.raises(ParameterError, match=message):
        M.parse_schedule(text)


def test_schedule_tuples_are_validated():
    c = random_controls(200)
    out = M.schedule_bitsets([(None, 2.0, "symmetric"), (2.0, None, "asymmetric")], controls=c, n_out_frames=60)
    assert out.labels[0] == "symmetric" and out.labels[-1] == "asymmetric"
    with pytest.raises(ParameterError, match=r"item 1 \('-1-2: a'\): start_s: expected seconds >= 0 or None; got -1"):
        M.schedule_bitsets([(-1, 2, "a")], controls=c, n_out_frames=60)
    with pytest.raises(ParameterError, match=r"expected a string such as .* got int"):
        M.schedule_bitsets(3, controls=c, n_out_frames=60)


def coverage_owner(items, T, N, fps):
    """For each step, the item covering most of its time span (ties: the later item)."""
    owners = []
    for t in range(0, T, N):
        n = min(N, T - t)
        lo, hi = t / fps, (t + n) / fps
        best, best_len = None, 0.0
        for i, (s, e, _) in enumerate(items):
            e = math.inf if e is None else e
            cover = max(0.0, min(hi, e) - max(lo, s))
            if cover > 0 and cover >= best_len - 1e-12:
                best, best_len = i, cover
        # a step is constrained only when its ranges cover more than the gap does
        owners.append(best if best is not None and best_len > (hi - lo) / 2 - 1e-12 else None)
    return owners


@pytest.mark.parametrize("seed", range(6))
def test_each_step_follows_the_control_covering_most_of_it(seed):
    rng = np.random.default_rng(seed)
    c = random_controls(400, seed=seed)
    T = int(rng.integers(40, 300))
    N, fps = int(rng.choice([4, 8, 9])), float(rng.choice([15.0, 30.0, 12.5]))
    # boundaries off the step grid, the last one early enough to reach a step centre
    cuts = np.sort(rng.uniform(0, (T - N) / fps, 4))
    exprs = ["left_wrist_high", "symmetric", "right_wrist_slow and not asymmetric"]
    # adjacent ranges, then a gap before an open-ended one
    items = [(0.0, float(cuts[0]), exprs[0]), (float(cuts[0]), float(cuts[2]), exprs[1]), (float(cuts[3]), None, exprs[2])]
    # items longer than 1.5 steps always contain a step centre
    items = [it for it in items if it[1] is None or it[1] - it[0] > 1.5 * N / fps]
    out = M.schedule_bitsets(items, controls=c, n_out_frames=T, step=N, fps=fps)
    expected = coverage_owner(items, T, N, fps)
    assert None in out.labels and len(set(out.labels)) >= 3  # the seeds exercise gaps and switches
    assert out.labels == [None if o is None else items[o][2] for o in expected]
    F = 400
    for i, label in enumerate(out.labels):
        if label is None:
            np.testing.assert_array_equal(out.bitsets[i], M.full_mask(F))
        else:
            np.testing.assert_array_equal(out.bitsets[i], M.compile_mask(label, controls=c).words)
    M.validate_bitset(out.bitsets, F, n_steps=math.ceil(T / N))


def test_schedule_boundaries_inside_a_step():
    c = random_controls(500, seed=9)
    T, N, fps = 600, 8, 15.0  # steps of 0.533 s; step 22 spans 11.73-12.27 s, centre 12.0 s
    def labels(text):
        return M.schedule_bitsets(text, controls=c, n_out_frames=T, step=N, fps=fps).labels
    exact = labels("0-12: symmetric; 12-: asymmetric")
    assert exact[21] == "symmetric" and exact[22] == "asymmetric"  # boundary on the centre: later item
    assert labels("0-11.9: symmetric; 11.9-: asymmetric")[22] == "asymmetric"
    assert labels("0-12.1: symmetric; 12.1-: asymmetric")[22] == "symmetric"
    # a gap boundary inside a step: the step is constrained iff the range covers its centre
    gap = labels("0-4.1: symmetric; 6.1-: asymmetric")
    assert gap[7] == "symmetric"  # 3.73-4.27 s, centre 4.0 s: mostly inside 0-4.1
    assert gap[8:11] == [None, None, None]  # 4.27-5.87 s
    assert gap[11] == "asymmetric"  # 5.87-6.4 s, centre 6.13 s: mostly inside 6.1-
    # a range ending exactly on a centre leaves that step to the gap ([start, end))
    assert labels("0-4: symmetric")[6:8] == ["symmetric", None]
    # decimal seconds that land on a centre are not pushed off it by rounding (8.3*15 = 124.50000000000001)
    on_centre = M.schedule_bitsets("0-8.3: symmetric; 8.3-: asymmetric", controls=c, n_out_frames=300, step=3, fps=15.0)
    assert on_centre.labels[40] == "symmetric" and on_centre.labels[41] == "asymmetric"


def test_schedule_gaps_and_partial_last_step():
    c = random_controls(333, seed=10)
    out = M.schedule_bitsets("1-2: left_wrist_high; 4-: left_wrist_slow", controls=c, n_out_frames=100, step=8, fps=15.0)
    assert out.n_steps == 13 and out.step_len.tolist()[-1] == 4 and out.step_start.tolist()[-1] == 96
    # centres (frames) 8k + 4 = 4, 12, 20, 28, 36, 44, 52, 60, ..., 98; 1 s = 15, 2 s = 30, 4 s = 60
    assert out.labels[:2] == [None, None]
    assert out.labels[2:4] == ["left_wrist_high"] * 2
    assert out.labels[4:7] == [None] * 3
    assert out.labels[7:] == ["left_wrist_slow"] * 6
    assert M.count_bits(out.bitsets[0]) == 333
    assert M.count_bits(out.bitsets[2]) == out.masks["left_wrist_high"].n_set
    bits, labels = out
    assert bits is out.bitsets and labels is out.labels
    assert out.describe_step(8) == "step 8 (t=4.27 s), control 'left_wrist_slow'"
    with pytest.raises(ParameterError, match=r"describe_step: step index 13 is outside 0..12"):
        out.describe_step(13)
    assert out.describe_step(0) == "step 0 (t=0.00 s), no control"
    assert out.masks["left_wrist_high"].thresholds == {"left_wrist_height > p85": pytest.approx(
        np.percentile(c["left_wrist_height"].astype(np.float64), 85), abs=0)}


def test_describe_step_matches_the_brief_example():
    c = random_controls(200, seed=11)
    out = M.schedule_bitsets(
        "0-3.5: left_wrist_high; 3.5-: left_wrist_speed < p15 and symmetric", controls=c, n_out_frames=150
    )
    assert out.describe_step(7) == "step 7 (t=3.73 s), control 'left_wrist_speed < p15 and symmetric'"


def test_schedule_bitsets_errors():
    c = random_controls(200, seed=12)
    with pytest.raises(ParameterError, match=r"n_steps: expected ceil\(n_out_frames / step\) = ceil\(100 / 8\) = 13; got 12"):
        M.schedule_bitsets("0-: symmetric", controls=c, n_out_frames=100, n_steps=12)
    with pytest.raises(
        ParameterError,
        match=r"item 2 \('3-3.2: left_wrist_high'\): contains no search-step centre, so it would constrain "
        r"nothing: each search step of 8 frames \(0.533 s at 15 fps\).*nearest centres are 2.93 s \(step 5\) "
        r"and 3.47 s \(step 6\)",
    ):
        M.schedule_bitsets("0-3: symmetric; 3-3.2: left_wrist_high", controls=c, n_out_frames=300)
    with pytest.raises(ParameterError, match=r"item 1 \('24-: asymmetric'\): starts at 24 s, after the centre of the last search step \(19.9 s; the output is 20 s long\)"):
        M.schedule_bitsets("24-: asymmetric", controls=c, n_out_frames=300)
    with pytest.raises(ParameterError, match=r"item 2 \('12-: symetric'\): mask expression: column 1: unknown mask name 'symetric'"):
        M.schedule_bitsets("0-12: symmetric; 12-: symetric", controls=c, n_out_frames=300)
    with pytest.raises(ParameterError, match=r"fps: expected a frame rate > 0; got 0"):
        M.schedule_bitsets("0-: symmetric", controls=c, n_out_frames=300, fps=0)
    with pytest.raises(ParameterError, match=r"step: expected an integer >= 1; got 0"):
        M.schedule_bitsets("0-: symmetric", controls=c, n_out_frames=300, step=0)


# --------------------------------------------------------------------------------------
# real data: controls computed straight from the BEAT2 root trajectory
# --------------------------------------------------------------------------------------


def test_masks_on_real_motion(scott_dir):
    data = np.load(scott_dir / "2_scott_0_1_1.npz")
    fps = float(data["mocap_frame_rate"])
    trans = data["trans"].astype(np.float64)
    speed = np.linalg.norm(np.gradient(trans, 1.0 / fps, axis=0), axis=1)
    controls = {
        "pelvis_height": trans[:, 1].astype(np.float32),
        "pelvis_speed": speed.astype(np.float32),
    }
    F = trans.shape[0]
    assert M.feature_unit("pelvis_speed") == "m/s"
    high = M.compile_mask("pelvis_speed_high", controls=controls)
    v = controls["pelvis_speed"].astype(np.float64)
    assert np.unique(v).size == F  # distinct values: "> p85" keeps the frames ranked above 0.85 (F - 1)
    assert high.n_set == F - (math.floor(0.85 * (F - 1)) + 1)
    r = M.compile_mask("pelvis_speed < 2 cm/s or pelvis_height > p90 and not pelvis_speed_high", controls=controls)
    h = controls["pelvis_height"].astype(np.float64)
    expected = (v < 0.02) | ((h > np.percentile(h, 90)) & ~(v > np.percentile(v, 85)))
    np.testing.assert_array_equal(r.bits(), expected)
    sched = M.schedule_bitsets(
        "0-10: pelvis_speed_low; 10-: pelvis_speed_high", controls=controls, n_out_frames=20 * 15, fps=15.0
    )
    assert sched.bitsets.shape == (38, M.n_words(F))
    # step 18 spans 9.6-10.13 s, step 19 10.13-10.67 s
    assert sched.labels[18] == "pelvis_speed_low" and sched.labels[19] == "pelvis_speed_high"


def test_percentile_masks_of_many_features_each_match_their_own_percentiles():
    """One compiler serves every feature: a cached comparison must never leak to
    another feature's expression (ids of freed parse nodes are reused)."""
    import gc

    rng = np.random.default_rng(5)
    controls = {f"f{i:02d}": rng.standard_normal(1000).astype(np.float32) * (i + 1) for i in range(30)}
    for _ in range(3):
        gc.collect()
        masks = M.percentile_masks(controls)
        for name, x in controls.items():
            v = x.astype(np.float64)
            lo, hi = np.percentile(v, M.LOW_PERCENTILE), np.percentile(v, M.HIGH_PERCENTILE)
            np.testing.assert_array_equal(M.unpack_bits(masks[f"{name}_low"].words, 1000), v < lo, err_msg=name)
            np.testing.assert_array_equal(M.unpack_bits(masks[f"{name}_high"].words, 1000), v > hi, err_msg=name)
