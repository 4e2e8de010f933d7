"""The search core against an independent float64 numpy implementation of the spec.

`oracle_step` below is written from ../shared/spec/search.md alone, in float64,
with numpy's lexsort for the rank rules; it shares no code with the kernel.

Two kinds of data:
- *exact* data (small integers): every float32 sum in the kernel is exact, so
  the kernel must agree with the oracle bit for bit on every candidate, and the
  data is full of exact ties (duplicated frames and windows, integer distances)
  that exercise every tie rule;
- *continuous* data (random normals, and the real BEAT2 recording): float32 and
  float64 may legitimately disagree only where two values are equal to within
  float32 rounding, so the oracle reports such near-ties and the comparison is
  exact everywhere else.
Every test runs on every instruction set this CPU supports.
"""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError, SearchError

search = pytest.importorskip("gesturedb.search")
try:
    from gesturedb import _core  # noqa: F401
except ImportError:  # pragma: no cover
    pytest.skip("gesturedb._core is not built", allow_module_level=True)

ISAS = search.kernels()
PRESELECTS = ["pose", "audio"]


@pytest.fixture(params=ISAS)
def isa(request):
    with search.simd(request.param):
        yield request.param


# ---------------------------------------------------------------------------
# independent float64 reference


def pack_bits(mask: np.ndarray) -> np.ndarray:
    """bool (F,) -> uint64 words, bit f & 63 of word f >> 6."""
    F = mask.shape[0]
    words = (F + 63) // 64
    padded = np.zeros(words * 64, dtype=bool)
    padded[:F] = mask
    return np.packbits(padded, bitorder="little").view("<u8").astype(np.uint64)


def bit_set(words: np.ndarray, f: np.ndarray) -> np.ndarray:
    return ((words[f >> 6] >> (f & 63).astype(np.uint64)) & np.uint64(1)).astype(bool)


def oracle_step(P, A, seg_start, seg_len, prev, q, *, k=1, preselect="pose", allowed=None,
                exclude=None):
    """Spec steps 1-5 in float64. Returns (choice dict or None, near_tie flag).

    near_tie is True when some decision of this step (a pre-selection or the
    order of two pre-selected segments) compares two different values closer
    than float32 rounding could separate.
    """
    P = P.astype(np.float64)
    A = A.astype(np.float64)
    prev = np.asarray(prev, dtype=np.float64)
    n = q.shape[0]
    qf = q.astype(np.float64).ravel()
    qq = float(qf @ qf)
    rows = []
    near = False
    for m in range(seg_start.shape[0]):
        if exclude is not None and exclude[m]:
            continue
        s = np.arange(1, seg_len[m] - n + 1)
        g = seg_start[m] + s
        if allowed is not None and s.size:
            ok = bit_set(allowed, g) & bit_set(allowed, g + n - 1)
            s, g = s[ok], g[ok]
        if s.size == 0:
            continue
        dp = ((P[g - 1] - prev) ** 2).sum(axis=1)
        win = A[g[:, None] + np.arange(n)].reshape(g.size, n * A.shape[1])
        qa = win @ qf
        aa = (win * win).sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            da = np.where((qq == 0) | (aa == 0), 1.0, 1.0 - qa / np.sqrt(qq * aa))
        key = dp if preselect == "pose" else da
        j = int(np.argmin(key))  # first minimum: ties go to the smallest s
        near |= _near_tie(key, key[j], preselect == "pose")
        rows.append((m, int(s[j]), int(g[j]), dp[j], da[j]))
    if not rows:
        return None, near
    ms = np.array([r[0] for r in rows])
    dps = np.array([r[3] for r in rows])
    das = np.array([r[4] for r in rows])
    for vals, rel in ((dps, True), (das, False)):
        srt = np.sort(vals)
        near |= bool(np.any(_close(srt[1:], srt[:-1], rel) & (srt[1:] != srt[:-1])))
    K = len(rows)
    rp = np.empty(K, dtype=np.int64)
    rp[np.lexsort((ms, dps))] = np.arange(K)
    ra = np.empty(K, dtype=np.int64)
    ra[np.lexsort((ms, das))] = np.arange(K)
    R = rp + ra
    c = np.lexsort((ms, rp, R))[min(k, K) - 1]
    m, s, g, dp, da = rows[c]
    return dict(segment=m, start=s, frame=g, length=n, pose_dist=dp, audio_dist=da,
                pose_rank=int(rp[c]), audio_rank=int(ra[c]), n_candidates=K), near


def _close(a, b, rel):
    # float32 SIMD sums of at most ~100 terms in 16 lanes carry well under 1e-6
    # relative error on dp (a sum of positive terms) and under 1e-6 absolute on
    # the cosine; 5e-6 leaves a margin without hiding real disagreements
    if rel:
        return np.abs(a - b) <= 5e-6 * np.maximum(np.abs(a), np.abs(b)) + 1e-12
    return np.abs(a - b) <= 5e-6


def _near_tie(key, best, rel):
    others = key[key != best]
    return bool(others.size and np.any(_close(others, best, rel)))


def check_step(got, want, *, exact):
    """Compare a kernel StepResult-like mapping with the oracle's choice."""
    for f in ("segment", "start", "frame", "length", "pose_rank", "audio_rank", "n_candidates"):
        assert got[f] == want[f], (f, got, want)
    if exact:
        assert got["pose_dist"] == want["pose_dist"], (got, want)
        assert got["audio_dist"] == want["audio_dist"], (got, want)
    else:
        np.testing.assert_allclose(got["pose_dist"], want["pose_dist"], rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(got["audio_dist"], want["audio_dist"], rtol=0, atol=2e-5)


def as_dict(r):
    return {f: getattr(r, f) for f in ("segment", "start", "frame", "length", "pose_dist",
                                        "audio_dist", "pose_rank", "audio_rank", "n_candidates")}


def check_search(res, P, A, seg_start, seg_len, query, init, *, step=8, k=1, preselect="pose",
                 allowed=None, exclude=None, exact=True):
    """Compare a whole SearchResult with the oracle, step by step.

    Each oracle step starts from the previous pose the spec prescribes for the
    kernel's previous choice, so one legitimate near-tie difference cannot
    cascade; returns the number of steps with near-ties (not compared exactly).
    """
    T = query.shape[0]
    S = -(-T // step)
    assert len(res) == S
    prev = np.asarray(init, dtype=np.float32)
    n_near = 0
    for i in range(S):
        t = i * step
        n = min(step, T - t)
        row = allowed if allowed is None or allowed.ndim == 1 else allowed[i]
        want, near = oracle_step(P, A, seg_start, seg_len, prev, query[t:t + n], k=k,
                                 preselect=preselect, allowed=row, exclude=exclude)
        assert want is not None
        got = as_dict(res.step(i))
        assert res.out_frames[i] == t
        if exact or not near:
            check_step(got, want, exact=exact)
        else:
            n_near += 1
            _check_valid_choice(got, P, A, seg_start, seg_len, prev, query[t:t + n], row, exclude)
        prev = P[res.frames[i] + res.lengths[i] - 1]
    fm = res.frame_map()
    assert fm.shape == (T,)
    np.testing.assert_array_equal(fm[res.out_frames], res.frames)
    return n_near


def _check_valid_choice(got, P, A, seg_start, seg_len, prev, q, allowed, exclude):
    """Where the oracle saw a near-tie: the choice is still a legal candidate
    and its reported distances are right."""
    m, s, g, n = got["segment"], got["start"], got["frame"], got["length"]
    assert 1 <= s <= seg_len[m] - n and g == seg_start[m] + s
    assert exclude is None or not exclude[m]
    if allowed is not None:
        assert bit_set(allowed, np.array([g]))[0] and bit_set(allowed, np.array([g + n - 1]))[0]
    dp = ((P[g - 1].astype(np.float64) - prev) ** 2).sum()
    np.testing.assert_allclose(got["pose_dist"], dp, rtol=1e-5, atol=1e-9)


# ---------------------------------------------------------------------------
# databases


def exact_db(rng, *, Dp=5, Da=3, n_segments=40, window=8):
    """Small-integer features on uneven segments, with deliberate exact ties.

    Segment lengths include 0, 1, window and window + 1 (no candidate, or just
    one), segments are separated by frames that belong to none, and blocks of
    frames are copied between segments so that whole windows are duplicated
    (ties across segments) and frames repeat inside a segment (ties within).
    """
    lens = rng.integers(window + 2, 90, size=n_segments)
    lens[:6] = [0, 1, window - 1, window, window + 1, window + 2]
    rng.shuffle(lens)
    gaps = rng.integers(0, 3, size=n_segments)  # frames that belong to no segment
    seg_start = np.concatenate([[gaps[0]], gaps[0] + np.cumsum(lens[:-1] + gaps[1:])])
    F = int(seg_start[-1] + lens[-1] + 2)
    P = rng.integers(-2, 3, size=(F, Dp)).astype(np.float32)
    A = rng.integers(-2, 3, size=(F, Da)).astype(np.float32)
    # duplicated blocks: windows and entry frames repeated in other segments
    for _ in range(12):
        src = int(rng.integers(0, F - 30))
        dst = int(rng.integers(0, F - 30))
        ln = int(rng.integers(2, 30))
        P[dst:dst + ln] = P[src:src + ln]
        A[dst:dst + ln] = A[src:src + ln]
    # a run of silent frames: windows with |a| = 0 (da = 1 by definition)
    z = int(rng.integers(0, F - 20))
    A[z:z + 20] = 0.0
    return P, A, seg_start.astype(np.int64), lens.astype(np.int64)


def continuous_db(rng, *, Dp=24, Da=14, n_segments=50, seg=64):
    lens = rng.integers(10, seg + 1, size=n_segments).astype(np.int64)
    seg_start = np.concatenate([[0], np.cumsum(lens)[:-1]]).astype(np.int64)
    F = int(lens.sum())
    P = rng.standard_normal((F, Dp)).astype(np.float32)
    A = rng.standard_normal((F, Da)).astype(np.float32)
    return P, A, seg_start, lens


# ---------------------------------------------------------------------------
# single steps


@pytest.mark.parametrize("preselect", ["pose", "audio"])
@pytest.mark.parametrize("dims", [(5, 3), (1, 1), (17, 14), (33, 7)])
def test_step_exact_matches_oracle(isa, preselect, dims):
    rng = np.random.default_rng([dims[0], dims[1], PRESELECTS.index(preselect)])
    P, A, st, ln = exact_db(rng, Dp=dims[0], Da=dims[1])
    F, M = P.shape[0], st.shape[0]
    for trial in range(12):
        n = int(rng.integers(1, 10))
        k = int(rng.choice([1, 2, 5, 1000]))
        prev = P[int(rng.integers(0, F))] if trial % 2 else rng.integers(-2, 3, dims[0]).astype(np.float32)
        if trial % 3 == 0:  # the query repeats a database window: da = 0, duplicated elsewhere
            g = int(rng.integers(0, F - n))
            q = A[g:g + n].copy()
        else:
            q = rng.integers(-2, 3, size=(n, dims[1])).astype(np.float32)
        if trial == 5:
            q[:] = 0.0  # |q| = 0: every candidate has da = 1
        allowed = pack_bits(rng.random(F) < 0.7) if trial % 4 == 1 else None
        exclude = rng.random(M) < 0.3 if trial % 4 == 2 else None
        got = search.rank_sum_step(P, A, st, ln, prev, q, k=k, preselect=preselect,
                                   allowed=allowed, exclude=exclude)
        want, _ = oracle_step(P, A, st, ln, prev, q, k=k, preselect=preselect, allowed=allowed,
                              exclude=exclude)
        check_step(as_dict(got), want, exact=True)
        assert got.rank == got.pose_rank + got.audio_rank


def test_exact_db_really_has_ties():
    """Guard on the test data itself: the tie rules are only tested if ties occur."""
    rng = np.random.default_rng(7)
    P, A, st, ln = exact_db(rng)
    d = ((P - P[100]) ** 2).sum(axis=1)
    # equal entry distances within segments, at the segment minimum
    n_tied_minima = 0
    for m in range(st.shape[0]):
        seg_d = d[st[m]:st[m] + ln[m] - 8]
        if seg_d.size:
            n_tied_minima += int((seg_d == seg_d.min()).sum() > 1)
    assert n_tied_minima >= 5
    # whole 8-frame audio windows that occur more than once
    win = np.lib.stride_tricks.sliding_window_view(A, (8, A.shape[1]))[:, 0].reshape(-1, 8 * A.shape[1])
    assert np.unique(win, axis=0).shape[0] < win.shape[0] - 20


@pytest.mark.parametrize("preselect", ["pose", "audio"])
def test_step_continuous_matches_oracle(isa, preselect):
    rng = np.random.default_rng(11 if preselect == "pose" else 12)
    P, A, st, ln = continuous_db(rng)
    n_near = 0
    for trial in range(10):
        n = 8 if trial < 8 else int(rng.integers(1, 8))
        prev = P[int(rng.integers(0, P.shape[0]))]
        q = rng.standard_normal((n, A.shape[1])).astype(np.float32)
        got = search.rank_sum_step(P, A, st, ln, prev, q, k=1 + trial % 3, preselect=preselect)
        want, near = oracle_step(P, A, st, ln, prev, q, k=1 + trial % 3, preselect=preselect)
        if near:
            n_near += 1
            continue
        check_step(as_dict(got), want, exact=False)
    assert n_near <= 3  # most steps must be compared exactly


def test_step_prefers_smallest_s_and_segment_on_ties(isa):
    """Hand-built ties: identical segments and identical frames inside a segment."""
    Dp, Da, L = 4, 2, 20
    base_p = np.zeros((L, Dp), np.float32)
    base_a = np.ones((L, Da), np.float32)
    base_p[3] = base_p[9] = 1.0  # two entry frames at the same distance (s = 4 and 10)
    P = np.concatenate([base_p, base_p, base_p])
    A = np.concatenate([base_a, base_a, base_a])
    st = np.array([0, L, 2 * L], np.int64)
    ln = np.array([L, L, L], np.int64)
    prev = np.ones(Dp, np.float32)
    q = np.ones((4, Da), np.float32)
    r = search.rank_sum_step(P, A, st, ln, prev, q)
    # every segment pre-selects s = 4 (entry frame 3, dp = 0); ranks tie, so m = 0 wins
    assert (r.segment, r.start, r.frame, r.pose_dist, r.pose_rank, r.audio_rank) == (0, 4, 4, 0.0, 0, 0)
    r3 = search.rank_sum_step(P, A, st, ln, prev, q, k=3)
    assert (r3.segment, r3.start, r3.pose_rank, r3.audio_rank, r3.rank) == (2, 4, 2, 2, 4)
    # k beyond the number of segments: the last one
    r9 = search.rank_sum_step(P, A, st, ln, prev, q, k=9)
    assert (r9.segment, r9.n_candidates) == (2, 3)


def test_rank_sum_orders_by_R_then_pose_rank_then_segment(isa):
    """Three segments with one candidate each (windows of n = 1); rp and ra designed by hand.

    dp: seg0 = 4, seg1 = 1, seg2 = 0  -> rp = (2, 1, 0)
    da: seg0 = 0, seg1 = ~0.2, seg2 = 1 (|a| = 0) -> ra = (0, 1, 2)
    R = (2, 2, 2): all equal, so the smallest rp wins: seg2 first, then seg1, seg0.
    """
    Dp = 1
    P = np.array([[2.0], [0.0], [1.0], [0.0], [0.0], [0.0]], np.float32)
    A = np.array([[0, 0], [1, 0], [0, 0], [1.0, 0.5], [0, 0], [0, 0]], np.float32)
    st = np.array([0, 2, 4], np.int64)
    ln = np.array([2, 2, 2], np.int64)
    prev = np.zeros(Dp, np.float32)
    q = np.array([[1.0, 0.0]], np.float32)
    picks = [search.rank_sum_step(P, A, st, ln, prev, q, k=k) for k in (1, 2, 3)]
    assert [p.segment for p in picks] == [2, 1, 0]
    assert [(p.pose_rank, p.audio_rank) for p in picks] == [(0, 2), (1, 1), (2, 0)]
    assert picks[0].audio_dist == 1.0  # zero-norm audio window
    np.testing.assert_allclose(picks[1].audio_dist, 1 - 1 / np.sqrt(1.25), rtol=1e-7)


def test_ranking_with_many_segments_matches_oracle(isa):
    """More than 512 segments: the ranker settles small k from the top-256
    lists by dp and by da and falls back to ranking everything otherwise
    (large k, or k beyond the number of segments). Both against the oracle,
    on integer data full of tied ranks."""
    rng = np.random.default_rng(71)
    M, L = 1300, 12
    st = np.arange(M, dtype=np.int64) * L
    ln = np.full(M, L, np.int64)
    ln[::97] = 3  # a few segments too short for a window
    F = M * L
    P = rng.integers(-3, 4, size=(F, 4)).astype(np.float32)
    A = rng.integers(-3, 4, size=(F, 2)).astype(np.float32)
    P[5 * L:9 * L] = P[100 * L:104 * L]  # duplicated segments: tied distances
    A[5 * L:9 * L] = A[100 * L:104 * L]
    for _trial, k in enumerate([1, 2, 15, 400, 1300, 5000]):
        prev = P[int(rng.integers(0, F))]
        q = rng.integers(-3, 4, size=(4, 2)).astype(np.float32)
        for preselect in ("pose", "audio"):
            got = search.rank_sum_step(P, A, st, ln, prev, q, k=k, preselect=preselect)
            want, _ = oracle_step(P, A, st, ln, prev, q, k=k, preselect=preselect)
            check_step(as_dict(got), want, exact=True)


# ---------------------------------------------------------------------------
# whole searches


@pytest.mark.parametrize("preselect", ["pose", "audio"])
def test_search_exact_matches_oracle(isa, preselect):
    rng = np.random.default_rng(21 if preselect == "pose" else 22)
    P, A, st, ln = exact_db(rng, Dp=7, Da=3)
    F, M = P.shape[0], st.shape[0]
    T = 61  # 8 steps, the last one partial (n = 5)
    q = rng.integers(-2, 3, size=(T, 3)).astype(np.float32)
    q[16:24] = A[200:208]  # a query window that exists in the database
    init = P[int(rng.integers(0, F))]
    # one mask for all steps
    allowed = pack_bits(rng.random(F) < 0.8)
    exclude = np.zeros(M, bool)
    exclude[rng.choice(M, 8, replace=False)] = True
    for kw in (dict(), dict(allowed=allowed), dict(exclude=exclude), dict(k=3, allowed=allowed, exclude=exclude)):
        res = search.rank_sum_search(P, A, st, ln, q, init, step=8, preselect=preselect, **kw)
        assert res.lengths[-1] == 5 and res.n_frames == T
        check_search(res, P, A, st, ln, q, init, step=8, preselect=preselect, **kw)


def test_search_per_step_schedule(isa):
    rng = np.random.default_rng(31)
    P, A, st, ln = exact_db(rng)
    F = P.shape[0]
    T, N = 45, 6
    S = -(-T // N)
    q = rng.integers(-2, 3, size=(T, A.shape[1])).astype(np.float32)
    # a control schedule: alternate between two halves of the database
    first_half = np.arange(F) < F // 2
    sched = np.stack([pack_bits(first_half if i % 2 == 0 else ~first_half) for i in range(S)])
    res = search.rank_sum_search(P, A, st, ln, q, P[0], step=N, allowed=sched)
    check_search(res, P, A, st, ln, q, P[0], step=N, allowed=sched)
    in_first = res.frames < F // 2
    assert np.all(in_first[::2]) and not np.any(in_first[1::2])


def test_search_continuous_matches_oracle(isa):
    rng = np.random.default_rng(41)
    P, A, st, ln = continuous_db(rng)
    q = rng.standard_normal((100, A.shape[1])).astype(np.float32)
    for preselect in ("pose", "audio"):
        res = search.rank_sum_search(P, A, st, ln, q, P[5], k=2, preselect=preselect)
        assert check_search(res, P, A, st, ln, q, P[5], k=2, preselect=preselect, exact=False) <= 4


def test_step_window_continues_from_last_copied_frame(isa):
    """prev = P[g + n - 1]: with a database made of one smooth trajectory the
    pose term makes the search continue the clip it copied."""
    F, Da = 400, 2
    tt = np.arange(F, dtype=np.float32)
    P = np.stack([tt, np.sin(tt), np.cos(tt)], axis=1).astype(np.float32)
    A = np.ones((F, Da), np.float32)  # all audio equal: only the pose decides
    st = np.array([0], np.int64)
    ln = np.array([F], np.int64)
    res = search.rank_sum_search(P, A, st, ln, np.ones((40, Da), np.float32), P[99], step=8)
    np.testing.assert_array_equal(res.frames, 100 + 8 * np.arange(5))
    np.testing.assert_array_equal(res.pose_dist, np.zeros(5))
    np.testing.assert_array_equal(res.frame_map(), np.arange(100, 140))


@pytest.mark.slow
def test_search_real_data_matches_oracle(scott_dir):
    """Whole searches on features computed from the real BEAT2 recording."""
    librosa = pytest.importorskip("librosa")
    sf = pytest.importorskip("soundfile")
    clip = np.load(scott_dir / "2_scott_0_1_1.npz")
    poses = clip["poses"].astype(np.float32)  # (F, 165) axis-angle, 30 fps
    # wrists, elbows and both hands' finger roots (the paper's pose feature joints)
    joints = [18, 19, 20, 21, 25, 31, 40, 46]
    pose = np.ascontiguousarray(poses[:, np.ravel([[3 * j, 3 * j + 1, 3 * j + 2] for j in joints])])

    def mfcc(path, n_frames=None):
        y, sr = sf.read(str(path), dtype="float32")
        if y.ndim > 1:
            y = y.mean(axis=1)
        hop = sr // 30
        m = librosa.feature.mfcc(y=y, sr=sr, n_mfcc=13, hop_length=hop, n_fft=1024)
        e = np.log(librosa.feature.rms(y=y, hop_length=hop, frame_length=1024) + 1e-6)
        f = np.concatenate([m, e]).T.astype(np.float32)
        return np.ascontiguousarray(f[:n_frames] if n_frames else f)

    F = pose.shape[0]
    audio = mfcc(scott_dir / "2_scott_0_1_1.wav", F)
    assert audio.shape[0] == F
    # standardise with the database statistics, as a feature pipeline would:
    # raw c0 is in the hundreds and would make every cosine nearly 1
    mu, sd = audio.mean(axis=0), audio.std(axis=0)
    audio = np.ascontiguousarray((audio - mu) / sd, dtype=np.float32)
    st = np.arange(0, F, 64, dtype=np.int64)
    ln = np.minimum(64, F - st).astype(np.int64)
    query_path = sorted((scott_dir / "inputs").glob("2_scott_0_2_*.wav"))[0]
    q = np.ascontiguousarray((mfcc(query_path)[:600] - mu) / sd, dtype=np.float32)
    n_near = 0
    for isa in ISAS:
        with search.simd(isa):
            for preselect, k in (("pose", 1), ("audio", 4)):
                res = search.rank_sum_search(pose, audio, st, ln, q, pose[0], k=k, preselect=preselect)
                n_near += check_search(res, pose, audio, st, ln, q, pose[0], k=k,
                                       preselect=preselect, exact=False)
    assert n_near <= 0.1 * len(ISAS) * 2 * 75  # most steps compared exactly


# ---------------------------------------------------------------------------
# batch


FIELDS = ("segments", "starts", "frames", "lengths", "out_frames", "pose_dist", "audio_dist",
          "pose_rank", "audio_rank", "n_candidates")


def assert_same_search(a, b, what=""):
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f"{what} {f}")


@pytest.mark.parametrize("method", ["blocked", "per_query"])
@pytest.mark.parametrize("preselect", ["pose", "audio"])
def test_batch_equals_one_by_one(isa, preselect, method):
    rng = np.random.default_rng(51)
    P, A, st, ln = continuous_db(rng, n_segments=40)
    M = st.shape[0]
    lens = [64, 64, 30, 1, 17, 64, 9, 64]
    queries = [rng.standard_normal((T, A.shape[1])).astype(np.float32) for T in lens]
    init = P[rng.integers(0, P.shape[0], len(queries))]
    ks = np.array([1, 2, 15, 1, 3, 1, 1, 7])
    # each query excludes "its own" segment, as when the queries are the database's audio
    exclude = np.zeros((len(queries), M), bool)
    exclude[np.arange(len(queries)), np.arange(len(queries))] = True
    allowed = pack_bits(rng.random(P.shape[0]) < 0.9)
    batch = search.rank_sum_search_batch(P, A, st, ln, queries, init, k=ks, preselect=preselect,
                                         allowed=allowed, exclude=exclude, method=method)
    assert len(batch) == len(queries)
    for i, q in enumerate(queries):
        one = search.rank_sum_search(P, A, st, ln, q, init[i], k=int(ks[i]), preselect=preselect,
                                     allowed=allowed, exclude=exclude[i])
        assert_same_search(batch[i], one, f"query {i}")
        assert not np.any(batch[i].segments == i)


@pytest.mark.parametrize("preselect", ["pose", "audio"])
def test_blocked_batch_exact_ties_and_long_segments(isa, preselect):
    """The blocked filter must keep every tied candidate so the exact tie rules
    still decide: integer data full of ties, 70 queries (two 64-lane words),
    segments longer than one 128-row tile, per-query k, partial last windows."""
    rng = np.random.default_rng(61)
    P, A, st, ln = exact_db(rng, Dp=9, Da=3, n_segments=30)
    # two long segments: candidates span several dot-product tiles
    ln = ln.copy()
    F = P.shape[0]
    st = np.concatenate([st, [0, 100]]).astype(np.int64)
    ln = np.concatenate([ln, [F, 300]]).astype(np.int64)
    Q = 70
    queries = []
    for i in range(Q):
        T = int(rng.choice([16, 24, 21, 5]))
        q = rng.integers(-2, 3, size=(T, 3)).astype(np.float32)
        if i % 5 == 0:
            g = int(rng.integers(0, F - T))
            q = A[g:g + T].copy()  # exact database audio: da = 0 ties
        if i % 7 == 0:
            q[:8] = 0.0  # a silent window: |q| = 0
        queries.append(q)
    init = P[rng.integers(0, F, Q)]
    ks = rng.integers(1, 6, Q)
    exclude = rng.random((Q, st.shape[0])) < 0.2
    allowed = pack_bits(rng.random(F) < 0.85)
    kw = dict(k=ks, preselect=preselect, allowed=allowed, exclude=exclude)
    blocked = search.rank_sum_search_batch(P, A, st, ln, queries, init, method="blocked", threads=1, **kw)
    per_query = search.rank_sum_search_batch(P, A, st, ln, queries, init, method="per_query", **kw)
    for i in range(Q):
        assert_same_search(blocked[i], per_query[i], f"query {i}")
    for i in (0, 7, 13):  # and a few against the float64 oracle
        check_search(blocked[i], P, A, st, ln, queries[i], init[i], k=int(ks[i]), preselect=preselect,
                     allowed=allowed, exclude=exclude[i])


@pytest.mark.parametrize("preselect", ["pose", "audio"])
def test_blocked_batch_non_finite_and_huge_values(isa, preselect):
    """Where the approximate distances overflow or are NaN the bound says
    nothing: those lanes must fall back to the exact scan and still match."""
    rng = np.random.default_rng(62)
    P, A, st, ln = continuous_db(rng, n_segments=30)
    P[st[3] + 5] = np.nan           # one NaN entry frame
    P[st[4]:st[4] + ln[4]] *= 3e19  # |P|^2 overflows float32 in the blocked form
    A[st[5] + 2:st[5] + 30] = 0.0   # silent windows (|a| = 0)
    A[st[6] + 7] = np.inf
    queries = [rng.standard_normal((40, A.shape[1])).astype(np.float32) for _ in range(20)]
    queries[3][:] = 0.0
    init = P[rng.integers(0, P.shape[0], 20)]
    init[2] = P[st[4] + 3]  # start near the huge segment
    with np.errstate(all="ignore"):
        blocked = search.rank_sum_search_batch(P, A, st, ln, queries, init, preselect=preselect,
                                               method="blocked")
        per_query = search.rank_sum_search_batch(P, A, st, ln, queries, init, preselect=preselect,
                                                 method="per_query")
    for i in range(20):
        assert_same_search(blocked[i], per_query[i], f"query {i}")
    # the NaN frame never wins against real distances
    assert not np.any(np.concatenate([b.frames for b in blocked]) - 1 == st[3] + 5)


def test_batch_shared_schedule_and_threads(isa):
    rng = np.random.default_rng(52)
    P, A, st, ln = exact_db(rng)
    F = P.shape[0]
    queries = [rng.integers(-2, 3, size=(24, A.shape[1])).astype(np.float32) for _ in range(5)]
    init = P[:5]
    sched = np.stack([pack_bits(rng.random(F) < 0.6) for _ in range(3)])
    b1 = search.rank_sum_search_batch(P, A, st, ln, queries, init, allowed=sched, threads=1,
                                      method="blocked")
    b2 = search.rank_sum_search_batch(P, A, st, ln, queries, init, allowed=sched, threads=2,
                                      method="blocked")
    for i, q in enumerate(queries):
        check_search(b1[i], P, A, st, ln, q, init[i], allowed=sched)
        assert_same_search(b1[i], b2[i])
    assert search.rank_sum_search_batch(P, A, st, ln, [], np.zeros((0, P.shape[1]), np.float32)) == []


def test_threads_do_not_change_results(isa):
    rng = np.random.default_rng(53)
    # large enough that the step really splits segments across threads
    P, A, st, ln = continuous_db(rng, Dp=96, n_segments=600)
    q = rng.standard_normal((40, A.shape[1])).astype(np.float32)
    for preselect in ("pose", "audio"):
        r1 = search.rank_sum_search(P, A, st, ln, q, P[0], preselect=preselect, threads=1)
        r2 = search.rank_sum_search(P, A, st, ln, q, P[0], preselect=preselect, threads=2)
        np.testing.assert_array_equal(r1.frames, r2.frames)
        np.testing.assert_array_equal(r1.pose_dist, r2.pose_dist)


# ---------------------------------------------------------------------------
# half-precision pose filter: a filter only, so results must not change


def _with_and_without_half(P, A, st, ln, q, init, **kw):
    half = search.HalfPose(P)
    a = search.rank_sum_search(P, A, st, ln, q, init, **kw)
    b = search.rank_sum_search(P, A, st, ln, q, init, pose_f16=half, **kw)
    assert_same_search(a, b)
    return a


def test_half_pose_identical_on_random_and_exact_data(isa):
    rng = np.random.default_rng(81)
    P, A, st, ln = continuous_db(rng, Dp=33)
    q = rng.standard_normal((70, A.shape[1])).astype(np.float32)
    F, M = P.shape[0], st.shape[0]
    allowed = pack_bits(rng.random(F) < 0.7)
    exclude = rng.random(M) < 0.2
    for kw in (dict(), dict(k=3), dict(allowed=allowed, exclude=exclude), dict(preselect="audio")):
        _with_and_without_half(P, A, st, ln, q, P[3], **kw)
    # integers are exact in binary16: every tie of the exact data survives the filter
    P2, A2, st2, ln2 = exact_db(rng, Dp=7)
    q2 = rng.integers(-2, 3, size=(53, A2.shape[1])).astype(np.float32)
    res = _with_and_without_half(P2, A2, st2, ln2, q2, P2[9], step=6)
    check_search(res, P2, A2, st2, ln2, q2, P2[9], step=6)


def test_half_pose_cannot_separate_candidates(isa):
    """Entry poses that differ far below binary16 resolution: the filter must
    keep all of them and let the float32 distances decide, like the oracle."""
    rng = np.random.default_rng(82)
    M, L, Dp = 30, 40, 12
    base = rng.standard_normal((M, 1, Dp)).astype(np.float32) * 4
    P = (base + rng.standard_normal((M, L, Dp)).astype(np.float32) * 1e-4).reshape(M * L, Dp)
    P = np.ascontiguousarray(P, dtype=np.float32)
    A = rng.standard_normal((M * L, 3)).astype(np.float32)
    st = np.arange(M, dtype=np.int64) * L
    ln = np.full(M, L, np.int64)
    assert len(np.unique(P.astype(np.float16), axis=0)) < P.shape[0] // 2  # halves collide
    q = rng.standard_normal((40, 3)).astype(np.float32)
    for k in (1, 4):
        _with_and_without_half(P, A, st, ln, q, P[5], k=k)
    # inside segment 0 the entry poses differ only below binary16 resolution;
    # the float32 distances must still pre-select entry frame 5 (dp = 0), s = 6
    only0 = np.ones(M, bool)
    only0[0] = False
    one = search.rank_sum_step(P, A, st, ln, P[5], q[:8], exclude=only0, pose_f16=search.HalfPose(P))
    assert (one.segment, one.start, one.pose_dist) == (0, 6, 0.0)
    assert np.unique(P[:L - 8].astype(np.float16), axis=0).shape[0] < L - 8


def test_half_pose_out_of_range_and_non_finite_rows(isa):
    """Values beyond +-65504 overflow in binary16 and NaN rows say nothing:
    their segments fall back to the exact scan."""
    rng = np.random.default_rng(83)
    P, A, st, ln = continuous_db(rng, Dp=16)
    P[st[2]:st[2] + ln[2]] *= 1e5       # whole segment beyond the half range
    P[st[3] + 4, 0] = 7e4               # one overflowing value
    P[st[4] + 2] = np.nan               # a NaN entry pose
    P[st[5]:st[5] + ln[5]] *= 1e-7      # deep in the subnormal range of binary16
    q = rng.standard_normal((60, A.shape[1])).astype(np.float32)
    for init in (P[st[2] + 1], P[st[5] + 3], P[0]):
        _with_and_without_half(P, A, st, ln, q, init)
    batch = search.rank_sum_search_batch(P, A, st, ln, [q, q[:21]], np.stack([P[0], P[st[5]]]),
                                         method="per_query", pose_f16=search.HalfPose(P))
    assert_same_search(batch[0], search.rank_sum_search(P, A, st, ln, q, P[0]))


def test_half_pose_validation():
    P, A, st, ln = small_db()
    q = np.ones((8, 4), np.float32)
    other = search.HalfPose(P.copy())
    with pytest.raises(ParameterError, match="pose_f16: expected a HalfPose made from this pose array"):
        search.rank_sum_step(P, A, st, ln, P[0], q, pose_f16=other)
    with pytest.raises(ParameterError, match=r"pose_f16: expected gesturedb.search.HalfPose\(pose\); got float16"):
        search.rank_sum_search(P, A, st, ln, q, P[0], pose_f16=P.astype(np.float16))
    with pytest.raises(ParameterError, match=r"pose: expected float32 C-contiguous \(F, Dp\); got float64"):
        search.HalfPose(P.astype(np.float64))


# ---------------------------------------------------------------------------
# failures and validation


def small_db():
    rng = np.random.default_rng(0)
    P = rng.standard_normal((200, 6)).astype(np.float32)
    A = rng.standard_normal((200, 4)).astype(np.float32)
    st = np.array([0, 64, 128], np.int64)
    ln = np.array([64, 64, 72], np.int64)
    return P, A, st, ln


def test_no_candidate_raises_search_error_with_step_and_t():
    P, A, st, ln = small_db()
    F = P.shape[0]
    q = np.ones((40, 4), np.float32)
    ok = pack_bits(np.ones(F, bool))
    none = pack_bits(np.zeros(F, bool))
    sched = np.stack([ok, ok, none, ok, ok])
    with pytest.raises(SearchError, match=r"step 2 \(output frame t=16\)") as exc:
        search.rank_sum_search(P, A, st, ln, q, P[0], allowed=sched)
    assert exc.value.step == 2 and exc.value.t == 16
    with pytest.raises(SearchError, match="3 are excluded") as exc:
        search.rank_sum_search(P, A, st, ln, q, P[0], exclude=np.ones(3, bool))
    assert exc.value.step == 0 and exc.value.t == 0
    with pytest.raises(SearchError, match="too short"):
        search.rank_sum_step(P, A, st, np.array([3, 3, 3]), P[0], q[:8])
    # batch: the first failing query is named
    ex = np.zeros((3, 3), bool)
    ex[1] = True
    with pytest.raises(SearchError, match=r"query 1, step 0") as exc:
        search.rank_sum_search_batch(P, A, st, ln, [q, q, q], P[:3], exclude=ex)
    assert exc.value.query == 1


def test_database_validation_messages():
    P, A, st, ln = small_db()
    q = np.ones((8, 4), np.float32)
    with pytest.raises(ParameterError, match=r"pose: expected float32 C-contiguous \(F, Dp\); got float64 \(200, 6\)"):
        search.rank_sum_step(P.astype(np.float64), A, st, ln, P[0], q)
    with pytest.raises(ParameterError, match=r"pose: expected float32 C-contiguous .* got float32 non-contiguous"):
        search.rank_sum_step(np.asfortranarray(P), A, st, ln, P[0], q)
    with pytest.raises(ParameterError, match=r"audio: expected float32 C-contiguous \(F, Da\); got float32 \(200,\)"):
        search.rank_sum_step(P, A[:, 0].copy(), st, ln, P[0], q)
    with pytest.raises(ParameterError, match=r"audio: expected 200 rows .* got 199 rows"):
        search.rank_sum_step(P, A[:199].copy(), st, ln, P[0], q)
    with pytest.raises(ParameterError, match=r"segment 2: frames \[128, 201\) reach beyond the database \(F = 200"):
        search.rank_sum_step(P, A, st, np.array([64, 64, 73]), P[0], q)
    with pytest.raises(ParameterError, match=r"seg_len: expected >= 0; got -1 at segment 1"):
        search.rank_sum_step(P, A, st, np.array([64, -1, 64]), P[0], q)
    with pytest.raises(ParameterError, match=r"seg_start: expected >= 0; got -5 at segment 0"):
        search.rank_sum_step(P, A, np.array([-5, 64, 128]), ln, P[0], q)
    with pytest.raises(ParameterError, match=r"seg_len: expected 3 entries like seg_start; got 2"):
        search.rank_sum_step(P, A, st, ln[:2], P[0], q)
    with pytest.raises(ParameterError, match=r"seg_start: expected 1-d integer array \(M,\); got float64"):
        search.rank_sum_step(P, A, st.astype(float), ln, P[0], q)
    with pytest.raises(ParameterError, match="at least one segment"):
        search.rank_sum_step(P, A, st[:0], ln[:0], P[0], q)


def test_query_and_option_validation_messages():
    P, A, st, ln = small_db()
    q = np.ones((8, 4), np.float32)
    step = search.rank_sum_step
    with pytest.raises(ParameterError, match=r"query_audio: expected 4 audio features per frame like the database; got shape \(8, 5\)"):
        step(P, A, st, ln, P[0], np.ones((8, 5)))
    with pytest.raises(ParameterError, match=r"query_audio: expected at least one frame \(T >= 1\)"):
        step(P, A, st, ln, P[0], np.ones((0, 4)))
    with pytest.raises(ParameterError, match=r"query_audio: expected finite values; got nan at index \(2, 1\)"):
        qn = q.copy()
        qn[2, 1] = np.nan
        step(P, A, st, ln, P[0], qn)
    with pytest.raises(ParameterError, match=r"prev_pose: expected 6 pose features like the database; got shape \(5,\)"):
        step(P, A, st, ln, P[0, :5], q)
    with pytest.raises(ParameterError, match=r"k: expected an integer >= 1; got 0"):
        step(P, A, st, ln, P[0], q, k=0)
    with pytest.raises(ParameterError, match=r"k: expected an integer >= 1; got 1.5"):
        step(P, A, st, ln, P[0], q, k=1.5)
    with pytest.raises(ParameterError, match=r"preselect: expected 'pose' or 'audio'; got 'both'"):
        step(P, A, st, ln, P[0], q, preselect="both")
    with pytest.raises(ParameterError, match=r"allowed: expected uint64 bitset \(4,\) .* got int64"):
        step(P, A, st, ln, P[0], q, allowed=np.zeros(4, np.int64))
    with pytest.raises(ParameterError, match=r"allowed: expected uint64 bitset \(4,\) for F = 200 frames; got shape \(3,\)"):
        step(P, A, st, ln, P[0], q, allowed=np.zeros(3, np.uint64))
    with pytest.raises(ParameterError, match=r"exclude: expected bool array \(3,\); got shape \(4,\)"):
        step(P, A, st, ln, P[0], q, exclude=np.zeros(4, bool))
    with pytest.raises(ParameterError, match=r"exclude: expected bool array \(3,\); got int64"):
        step(P, A, st, ln, P[0], q, exclude=np.zeros(3, np.int64))
    srch = search.rank_sum_search
    with pytest.raises(ParameterError, match=r"step: expected an integer >= 1; got 0"):
        srch(P, A, st, ln, q, P[0], step=0)
    with pytest.raises(ParameterError, match=r"init_pose: expected 6 pose features"):
        srch(P, A, st, ln, q, P[0, :2], step=4)
    with pytest.raises(ParameterError, match=r"allowed: expected 2 rows \(one bitset per step\); got 3 rows"):
        srch(P, A, st, ln, q, P[0], step=4, allowed=np.zeros((3, 4), np.uint64))
    with pytest.raises(ParameterError, match=r"allowed: expected 4 uint64 words per bitset"):
        srch(P, A, st, ln, q, P[0], step=4, allowed=np.zeros((2, 5), np.uint64))
    batch = search.rank_sum_search_batch
    with pytest.raises(ParameterError, match=r"init_poses: expected \(2, 6\) \(one pose per query\); got \(3, 6\)"):
        batch(P, A, st, ln, [q, q], P[:3])
    with pytest.raises(ParameterError, match=r"queries\[1\]: expected 4 audio features"):
        batch(P, A, st, ln, [q, q[:, :3]], P[:2])
    with pytest.raises(ParameterError, match=r"k: expected >= 1; got 0 for query 1"):
        batch(P, A, st, ln, [q, q], P[:2], k=[1, 0])
    with pytest.raises(ParameterError, match=r"exclude: expected bool array \(3,\) or \(2, 3\); got shape \(3, 3\)"):
        batch(P, A, st, ln, [q, q], P[:2], exclude=np.zeros((3, 3), bool))
    with pytest.raises(ParameterError, match="same number of steps"):
        batch(P, A, st, ln, [q, q[:4]], P[:2], step=4, allowed=np.zeros((2, 4), np.uint64))
    with pytest.raises(ParameterError, match=r"queries: expected a list"):
        batch(P, A, st, ln, np.ones((2, 8, 4), np.float32), P[:2])


def test_core_refuses_silent_conversion():
    """The bindings' backstop: no cast or copy of the database arrays."""
    P, A, st, ln = small_db()
    q = np.ones((8, 4), np.float32)
    with pytest.raises(TypeError):
        _core.step(P.astype(np.float64), A, st, ln, P[0], q, 1, "pose", None, None)
    with pytest.raises(ValueError, match="segment 2"):
        _core.step(P, A, st, np.array([64, 64, 100]), P[0], q, 1, "pose", None, None)


def test_simd_switching():
    assert "scalar" in ISAS
    before = search.get_simd()
    with search.simd("scalar"):
        assert search.get_simd() == "scalar"
    assert search.get_simd() == before
    with pytest.raises(ParameterError, match=r"simd: expected one of .*; got 'sse9'"):
        search.set_simd("sse9")
