"""Rhythm signatures: gesturedb.features.rhythm."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.features.rhythm import (
    audio_rhythm,
    hamming,
    hamming_beyond_chance,
    hand_speed,
    motion_rhythm,
    speed_minima,
)
from gesturedb.features.segments import fixed_chunks

try:
    from test_features_synth import SMPLX_JOINTS, gesturing, rest_positions, rigid
except ModuleNotFoundError:  # pragma: no cover
    from tests.test_features_synth import SMPLX_JOINTS, gesturing, rest_positions, rigid

J = SMPLX_JOINTS


def _bits(sig) -> list[int]:
    return [i for i in range(32) if (int(sig) >> i) & 1]


def test_word_onset_at_a_known_time_sets_a_known_bit():
    # clip 10 s .. 12 s, 32 bins of 62.5 ms: 10.5 s is bin 8
    sig = audio_rhythm([10.5], start_s=10.0, end_s=12.0)
    assert isinstance(sig, np.uint32) and sig == 1 << 8
    assert audio_rhythm([10.0], start_s=10.0, end_s=12.0) == 1  # bin 0 is the least significant bit
    assert audio_rhythm([11.99], start_s=10.0, end_s=12.0) == 1 << 31
    assert audio_rhythm([12.0, 9.99, 30.0], start_s=10.0, end_s=12.0) == 0  # outside [start, end)
    assert audio_rhythm([], start_s=0.0, end_s=1.0) == 0
    assert _bits(audio_rhythm([10.5, 10.51, 11.0, 10.0625], start_s=10.0, end_s=12.0)) == [1, 8, 16]
    assert audio_rhythm([0.5], start_s=0.0, end_s=1.0, bits=4) == 1 << 2


def test_audio_rhythm_vectorised_equals_one_by_one():
    rng = np.random.default_rng(0)
    onsets = np.sort(rng.uniform(0, 60, 180))
    starts = rng.uniform(-1, 58, 50)
    ends = starts + rng.uniform(0.3, 8, 50)
    many = audio_rhythm(onsets[::-1], start_s=starts, end_s=ends)  # order of onsets does not matter
    assert many.dtype == np.uint32 and many.shape == (50,)
    for c in range(50):
        expect = 0
        for t in onsets:
            if starts[c] <= t < ends[c]:
                expect |= 1 << int((t - starts[c]) / (ends[c] - starts[c]) * 32)
        assert many[c] == expect == audio_rhythm(onsets, start_s=starts[c], end_s=ends[c])


def _v_speed(minima, n, noise=0.0, seed=0):
    """0.05 m/s at each minimum frame, rising 0.1 m/s per frame, capped at 0.85 m/s."""
    f = np.arange(n)
    dist = np.min(np.abs(f[:, None] - np.asarray(minima)[None, :]), axis=1)
    s = 0.05 + np.minimum(0.8, 0.1 * dist)
    return s + noise * np.random.default_rng(seed).uniform(-1, 1, n)


def test_speed_minima_at_known_times_set_known_bits():
    minima = [90, 100, 110, 131, 163, 175]
    speed = _v_speed(minima, 260, noise=0.003)
    np.testing.assert_array_equal(speed_minima(speed, fps=30), minima)
    sig = motion_rhythm(speed, start=100, length=64, fps=30)
    # bins of 2 frames from frame 100: 100 -> 0, 110 -> 5, 131 -> 15, 163 -> 31
    assert isinstance(sig, np.uint32) and _bits(sig) == [0, 5, 15, 31]
    # 13 bins of 20 frames: 90 -> 4, 100 and 110 -> 5, 131 -> 6, 163 -> 8, 175 -> 8
    assert _bits(motion_rhythm(speed, start=0, length=260, fps=30, bits=13)) == [4, 5, 6, 8]


def test_noise_alone_sets_no_bit():
    rng = np.random.default_rng(2)
    speed = 0.4 + 0.01 * rng.normal(size=600)  # a hand moving steadily, 1 cm/s noise
    assert motion_rhythm(speed, start=0, length=600, fps=30) == 0
    # without a prominence threshold the noise sets almost every bit
    assert bin(int(motion_rhythm(speed, start=0, length=600, fps=30, prominence=0))).count("1") > 28


def test_prominence_is_measured_within_the_window():
    speed = _v_speed([50], 101)
    speed[80:] = 0.85 - 0.002 * np.arange(21)  # a slow drift down: no second minimum
    assert speed_minima(speed, fps=30).tolist() == [50]
    # dips of 0.06 m/s every 20 frames, 10 minima inside
    shallow = 0.5 + 0.03 * np.cos(np.arange(200) * 2 * np.pi / 20)
    np.testing.assert_array_equal(speed_minima(shallow, fps=30, prominence=0.05), np.arange(10, 200, 20))
    assert len(speed_minima(shallow, fps=30, prominence=0.07)) == 0
    # a window of +-4 frames sees only 0.021 m/s of the rise
    assert len(speed_minima(shallow, fps=30, prominence=0.05, window_s=0.3)) == 0
    assert len(speed_minima(shallow, fps=30, prominence=0.02, window_s=0.3)) == 10


def test_motion_and_audio_signatures_agree_on_the_same_times():
    rng = np.random.default_rng(4)
    minima = np.sort(rng.choice(np.arange(5, 995, 8), size=60, replace=False))
    speed = _v_speed(minima, 1000)
    starts, lengths = fixed_chunks(1000, length=64)
    fps = 30.0
    motion = motion_rhythm(speed, start=starts, length=lengths, fps=fps)
    audio = audio_rhythm(minima / fps, start_s=starts / fps, end_s=(starts + lengths) / fps)
    np.testing.assert_array_equal(motion, audio)
    assert (hamming(motion, audio) == 0).all()


def test_hand_speed_of_known_wrist_motion():
    fps = 30.0
    n = 60
    t = np.arange(n) / fps
    pos = np.repeat(rest_positions()[None], n, axis=0)
    pos[:, J["left_wrist"]] += t[:, None] * [1.0, 0.0, 0.0]  # 1 m/s
    pos[:, J["right_wrist"]] += t[:, None] * [0.0, 0.3, 0.4]  # 0.5 m/s
    np.testing.assert_allclose(hand_speed(pos, joints=J, fps=fps), 1.0, atol=1e-9)
    pos[30:, J["left_wrist"]] = pos[30, J["left_wrist"]]  # left stops half-way: the max switches
    sp = hand_speed(pos, joints=J, fps=fps, smooth_s=0)
    np.testing.assert_allclose(sp[:29], 1.0, atol=1e-9)
    np.testing.assert_allclose(sp[32:], 0.5, atol=1e-9)
    # turning and walking with the arms fixed to the body is not hand motion (away from the ends, where
    # the facing smoothing, sigma 2/15 s = 4 frames here, sees a turn that stops: 2.5 sigma)
    still = np.repeat(rest_positions()[None], n, axis=0)
    moving = rigid(still, np.linspace(0, 1, n), np.arange(n)[:, None] / fps * [0.5, 0, 0.5])
    np.testing.assert_allclose(hand_speed(moving, joints=J, fps=fps)[10:-10], 0.0, atol=0.02)


def test_popcount_fallback_for_old_numpy_matches(monkeypatch):
    from gesturedb.features.rhythm import _popcount32

    rng = np.random.default_rng(9)
    x = np.concatenate([[0, 1, 0xFFFFFFFF, 0x80000000], rng.integers(0, 2**32, 500, dtype=np.uint64)]).astype(np.uint32)
    expect = [bin(int(v)).count("1") for v in x]
    np.testing.assert_array_equal(_popcount32(x), expect)
    monkeypatch.delattr(np, "bitwise_count", raising=False)  # numpy < 2.0
    np.testing.assert_array_equal(_popcount32(x), expect)


def test_hamming_counts_differing_bits():
    assert hamming(0, 0) == 0
    assert hamming(0b1011, 0b0001) == 2
    assert hamming(0xFFFFFFFF, 0) == 32
    rng = np.random.default_rng(1)
    a = rng.integers(0, 2**32, size=40, dtype=np.uint64).astype(np.uint32)
    b = rng.integers(0, 2**32, size=30, dtype=np.uint64).astype(np.uint32)
    d = hamming(a[:, None], b[None, :])
    assert d.shape == (40, 30) and d.dtype == np.int64
    for i in range(40):
        for j in range(30):
            assert d[i, j] == bin(int(a[i]) ^ int(b[j])).count("1")



def _random_signatures(rng, n_bits: int, size: int, bits: int = 32) -> np.ndarray:
    """``size`` signatures of exactly ``n_bits`` set bits out of ``bits``, placed at random."""
    out = np.zeros(size, dtype=np.uint32)
    for i in range(size):
        for b in rng.choice(bits, size=n_bits, replace=False):
            out[i] |= np.uint32(1) << np.uint32(b)
    return out


def test_hamming_beyond_chance_does_not_reward_sparse_signatures():
    """Against a sparse speech signature (8 of 32 bits) the plain Hamming distance of a clip whose bits fall at
    random grows with its number of bits, so the emptier (calmer) clip wins; beyond chance, clips of any
    number of random bits score the same on average, and only agreement beyond chance scores lower."""
    rng = np.random.default_rng(7)
    a = _random_signatures(rng, 8, 1)[0]
    plain, beyond = {}, {}
    for nb in (0, 4, 8, 16, 24):
        b = _random_signatures(rng, nb, 4000)
        plain[nb], beyond[nb] = hamming(a, b).mean(), hamming_beyond_chance(a, b).mean()
    assert plain[0] < plain[4] < plain[8] < plain[16] < plain[24]  # the bias: 8, 11, 14, 20, 26
    expected = 2 * 8 * (1 - 8 / 32)  # E[H] between two random signatures of 8 bits
    for nb, v in beyond.items():
        assert abs(v - expected) < 0.15, (nb, beyond)
    # a clip that shares the speech's bits beats every random one, whatever its number of bits
    assert hamming_beyond_chance(a, a) == 0 and hamming_beyond_chance(a, a | np.uint32(0xFF00FF00)) < expected - 1


def test_hamming_beyond_chance_is_hamming_for_equal_bit_counts():
    rng = np.random.default_rng(3)
    for n in (0, 1, 8, 31, 32):
        a, b = _random_signatures(rng, n, 200), _random_signatures(rng, n, 200)
        np.testing.assert_array_equal(hamming_beyond_chance(a, b), hamming(a, b).astype(np.float64))
    a = rng.integers(0, 2**32, size=50, dtype=np.uint64).astype(np.uint32)
    b = rng.integers(0, 2**32, size=60, dtype=np.uint64).astype(np.uint32)
    d = hamming_beyond_chance(a[:, None], b[None, :])
    assert d.shape == (50, 60) and d.dtype == np.float64 and (d >= 0).all()
    assert (d[np.equal.outer(a, b)] == 0).all()
    # the chance depends on the bins: every bin set is what any clip matches by chance when there are 8
    assert hamming_beyond_chance(0xFF, 0x0F, bits=8) == 0 and hamming_beyond_chance(0xFF, 0x0F) == 6.0
    with pytest.raises(ParameterError, match=r"bits: expected an int in \[1, 32\]; got 0"):
        hamming_beyond_chance(1, 1, bits=0)

def test_real_motion_has_a_plausible_rhythm(scott_dir):
    from gesturedb.io.smplx import read_smplx

    motion = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    pos, fps = motion.positions, motion.fps
    speed = hand_speed(pos, joints=J, fps=fps)
    assert speed.shape == (len(pos),)
    assert 0.3 <= np.median(speed) <= 1.0
    assert np.percentile(speed, 99) < 3.0
    per_second = len(speed_minima(speed, fps=fps)) / (len(pos) / fps)
    assert 0.5 < per_second < 4.0  # pauses and turns, not every frame of noise
    starts, lengths = fixed_chunks(len(pos), length=64)
    sigs = motion_rhythm(speed, start=starts, length=lengths, fps=fps)
    counts = hamming(sigs, 0)
    assert 1.0 < counts.mean() < 10.0
    assert (counts < 32).all()


def test_bad_arguments():
    with pytest.raises(ParameterError, match=r"bits: expected an int in \[1, 32\]; got 33"):
        audio_rhythm([1.0], start_s=0.0, end_s=2.0, bits=33)
    with pytest.raises(ParameterError, match="end_s > start_s; got clip 1"):
        audio_rhythm([1.0], start_s=[0.0, 2.0], end_s=[1.0, 2.0])
    with pytest.raises(ParameterError, match="inside the 100 frames of speed; got clip 0: start 90, length 20"):
        motion_rhythm(np.zeros(100), start=90, length=20, fps=30)
    with pytest.raises(ParameterError, match="start, length: expected ints"):
        motion_rhythm(np.zeros(100), start=1.5, length=20, fps=30)
    with pytest.raises(ParameterError, match=r"a: expected signatures in \[0, 2\*\*32\)"):
        hamming(-1, 0)
    with pytest.raises(ParameterError, match="b: expected uint32 signatures; got dtype float64"):
        hamming(1, 2.0)
    with pytest.raises(ParameterError, match="prominence: expected m/s >= 0"):
        speed_minima(np.zeros(10), fps=30, prominence=-1)
    with pytest.raises(ParameterError, match="missing role.*'right_wrist'"):
        hand_speed(gesturing(5), joints={k: v for k, v in J.items() if k != "right_wrist"}, fps=30)
