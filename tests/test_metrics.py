"""Objective gesture metrics: hand-made signals with known values, and the real clip."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.eval import metrics as M

FPS = 30.0


def _motion(f, fn_list):
    """(F, J, 3) positions with joint j's x(t) = fn_list[j](t); y, z fixed."""
    t = np.arange(f) / FPS
    pos = np.zeros((f, len(fn_list), 3))
    for j, fn in enumerate(fn_list):
        pos[:, j, 0] = fn(t)
        pos[:, j, 1] = 1.0 + 0.1 * j
    return pos


def _genea_loops(pos, order, fps):
    """GENEA's reference loops (calk_jerk_or_acceleration.py), on (F, J*3) data."""
    data = pos.reshape(pos.shape[0], -1)
    d = np.diff(data, n=order, axis=0)
    n_joints = data.shape[1] // 3
    norms = np.zeros((d.shape[0], n_joints))
    for i in range(d.shape[0]):
        for j in range(n_joints):
            norms[i, j] = np.linalg.norm(d[i, 3 * j : 3 * j + 3])
    return norms.mean(axis=0) * fps**order


# ---------------------------------------------------------------- AA / AJ
def test_constant_velocity_has_zero_acceleration_and_jerk():
    pos = _motion(60, [lambda t: 0.7 * t - 0.2, lambda t: -1.3 * t])
    pos[:, :, 2] = np.arange(60)[:, None] * 0.01  # also moving along z
    assert M.average_acceleration(pos, fps=FPS) == pytest.approx(0.0, abs=1e-9)
    assert M.average_jerk(pos, fps=FPS) == pytest.approx(0.0, abs=1e-7)


def test_constant_acceleration_gives_that_acceleration_and_zero_jerk():
    a = 2.5  # m/s^2 along x; the other joint 4 m/s^2 along a diagonal
    pos = _motion(90, [lambda t: 0.5 * a * t**2 + 0.3 * t, lambda t: 0 * t])
    diag = np.array([1.0, 2.0, 2.0]) / 3.0
    t = np.arange(90) / FPS
    pos[:, 1] = 0.5 * 4.0 * t[:, None] ** 2 * diag
    per = M.average_acceleration(pos, fps=FPS, per_joint=True)
    np.testing.assert_allclose(per, [a, 4.0], rtol=1e-6)
    assert M.average_acceleration(pos, fps=FPS) == pytest.approx((a + 4.0) / 2, rel=1e-6)
    assert M.average_jerk(pos, fps=FPS) == pytest.approx(0.0, abs=1e-5)


def test_cubic_has_the_known_jerk_at_any_frame_rate():
    c = 0.8  # x = c t^3 -> jerk 6c, exact for third differences
    for fps in (25.0, 30.0, 120.0):
        t = np.arange(int(3 * fps)) / fps
        pos = np.zeros((t.size, 1, 3))
        pos[:, 0, 0] = c * t**3
        assert M.average_jerk(pos, fps=fps) == pytest.approx(6 * c, rel=1e-6)
        # acceleration 6 c t averaged over the centre of each 2nd-difference stencil
        expected_aa = np.mean(6 * c * (t[1:-1]))
        assert M.average_acceleration(pos, fps=fps) == pytest.approx(expected_aa, rel=1e-6)


def test_jerk_and_acceleration_match_genea_reference_loops():
    rng = np.random.default_rng(1)
    pos = np.cumsum(rng.normal(0, 0.01, (50, 5, 3)), axis=0)
    np.testing.assert_allclose(M.average_jerk(pos, fps=FPS, per_joint=True), _genea_loops(pos, 3, FPS), rtol=1e-12)
    np.testing.assert_allclose(
        M.average_acceleration(pos, fps=FPS, per_joint=True), _genea_loops(pos, 2, FPS), rtol=1e-12
    )
    sub = M.average_jerk(pos, fps=FPS, joints=[3, 1], per_joint=True)
    np.testing.assert_allclose(sub, _genea_loops(pos[:, [3, 1]], 3, FPS), rtol=1e-12)


def test_bad_inputs_are_named():
    with pytest.raises(ParameterError, match=r"positions: expected an array of shape \(F, J, 3\); got shape \(10, 3\)"):
        M.average_jerk(np.zeros((10, 3)), fps=FPS)
    with pytest.raises(ParameterError, match="fps: expected a positive number; got 0"):
        M.average_jerk(np.zeros((10, 2, 3)), fps=0)
    with pytest.raises(ParameterError, match="jerk needs at least 4 frames; got 3"):
        M.average_jerk(np.zeros((3, 2, 3)), fps=FPS)
    with pytest.raises(ParameterError, match=r"joints: expected indices in \[0, 2\)"):
        M.average_jerk(np.zeros((10, 2, 3)), fps=FPS, joints=[0, 5])
    bad = np.zeros((10, 2, 3))
    bad[4, 1, 2] = np.nan
    with pytest.raises(ParameterError, match="finite"):
        M.average_acceleration(bad, fps=FPS)


# ------------------------------------------------------------ Hellinger
def test_hellinger_identical_disjoint_and_hand_value():
    p = np.array([3.0, 1.0, 0.0, 6.0])
    assert M.hellinger_distance(p, p) == 0.0
    assert M.hellinger_distance(p, 5 * p) == pytest.approx(0.0, abs=1e-12)  # normalised first
    assert M.hellinger_distance([1, 1, 0, 0], [0, 0, 2, 5]) == 1.0
    assert M.hellinger_distance([1, 0], [1, 1]) == pytest.approx(math.sqrt(1 - math.sqrt(0.5)), rel=1e-12)
    with pytest.raises(ParameterError, match="same length"):
        M.hellinger_distance([1, 2], [1, 2, 3])
    with pytest.raises(ParameterError, match="histogram q: expected finite non-negative weights"):
        M.hellinger_distance([1, 2], [0, 0])


def test_speed_histogram_counts_every_sample_in_its_bin():
    # joint 0 moves at 0.105 m/s, joint 1 at 0.505 m/s (bin centres), joint 2 at 3 m/s (beyond the range)
    pos = _motion(31, [lambda t: 0.105 * t, lambda t: 0.505 * t, lambda t: 3.0 * t])
    counts, edges = M.speed_histogram(pos, fps=FPS, bin_width_m_s=0.01, max_speed_m_s=2.0)
    assert edges.shape == (201,) and edges[-1] == pytest.approx(2.0)
    assert counts.sum() == 3 * 30  # nothing dropped: the 3 m/s samples land in the last bin
    assert counts[10] == 30 and counts[50] == 30 and counts[-1] == 30


def test_speed_hellinger_same_motion_zero_static_vs_moving_one():
    rng = np.random.default_rng(2)
    moving = np.cumsum(rng.normal(0, 0.01, (200, 4, 3)), axis=0)
    assert M.speed_hellinger(moving, moving, fps=FPS) == pytest.approx(0.0, abs=1e-12)
    # played backwards, or translated, a motion has the same speeds
    assert M.speed_hellinger(moving[::-1] + 0.3, moving, fps=FPS) == pytest.approx(0.0, abs=1e-7)
    # a slower copy does not
    assert M.speed_hellinger(0.5 * moving, moving, fps=FPS) > 0.2
    static = np.repeat(moving[:1], 100, axis=0)
    fast = moving * 0 + np.arange(200)[:, None, None] * np.array([0.05, 0, 0])  # 1.5 m/s
    assert M.speed_hellinger(static, fast, fps=FPS) == 1.0


# ------------------------------------------------------------ BeatAlign
def test_beat_align_score_exact_far_and_hand_computed():
    beats = [1.0, 2.0, 3.0]
    assert M.beat_align_score(beats, beats) == 1.0
    assert M.beat_align_score(beats, [20.0, 40.0]) == pytest.approx(0.0, abs=1e-100)
    # motion -> audio: distances 0.1, 0.0, 0.3 with sigma 0.3
    hand = (math.exp(-0.01 / 0.18) + 1.0 + math.exp(-0.09 / 0.18)) / 3
    assert M.beat_align_score(beats, [0.2, 1.1, 2.0, 3.3], sigma_s=0.3) == pytest.approx(hand, rel=1e-12)
    # the two directions differ: one motion beat on the first of two audio beats
    assert M.beat_align_score([1.0], [1.0, 5.0]) == 1.0
    assert M.beat_align_score([1.0], [1.0, 5.0], direction="audio_to_motion") == pytest.approx(0.5, rel=1e-12)
    assert math.isnan(M.beat_align_score([], [1.0]))
    assert M.beat_align_score([1.0], []) == 0.0
    with pytest.raises(ParameterError, match="direction: expected"):
        M.beat_align_score(beats, beats, direction="both")


def test_beat_align_score_matches_brute_force():
    rng = np.random.default_rng(3)
    m = rng.uniform(0, 30, 40)
    a = rng.uniform(0, 30, 70)
    brute = np.mean([math.exp(-min(abs(x - y) for y in a) ** 2 / (2 * 0.3**2)) for x in m])
    assert M.beat_align_score(m, a) == pytest.approx(brute, rel=1e-12)


def _wrist_with_beats(seconds=10.0):
    """Wrist speed 1.5 + cos(2 pi t): minima (0.5 m/s) at t = 0.5, 1.5, ... (exact frames)."""
    f = int(seconds * FPS)
    return _motion(f, [lambda t: 1.5 * t + np.sin(2 * np.pi * t) / (2 * np.pi)])


def test_motion_beats_found_at_the_speed_minima():
    pos = _wrist_with_beats()
    (beats,) = M.motion_beats(pos, fps=FPS, joints=[0])
    np.testing.assert_allclose(beats, np.arange(0.5, 10.0, 1.0), atol=1e-12)
    # the speed threshold drops minima of a joint at rest
    assert M.motion_beats(pos, fps=FPS, joints=[0], min_speed_ratio=0.5)[0].size == 0


def test_beat_align_on_motion_exact_and_shifted():
    pos = _wrist_with_beats()
    on = np.arange(0.5, 10.0, 1.0)
    assert M.beat_align(pos, fps=FPS, joints=[0], audio_beats_s=on) == 1.0
    # every motion beat is 0.5 s from the nearest audio beat
    shifted = M.beat_align(pos, fps=FPS, joints=[0], audio_beats_s=np.arange(0.0, 11.0, 1.0))
    assert shifted == pytest.approx(math.exp(-0.25 / 0.18), rel=1e-12)
    # audio beats after the end of the motion are ignored
    late = np.concatenate([on, [12.0, 13.0]])
    assert M.beat_align(pos, fps=FPS, joints=[0], audio_beats_s=late, direction="audio_to_motion") == 1.0
    with pytest.raises(ParameterError, match="expected audio \\(with sr\\) or audio_beats_s"):
        M.beat_align(pos, fps=FPS, joints=[0])


def test_audio_beats_find_clicks():
    sr = 16000
    y = np.zeros(sr * 5, dtype=np.float32)
    clicks = np.array([0.5, 1.25, 2.0, 3.1, 4.0])
    burst = np.random.default_rng(4).normal(0, 0.5, 400).astype(np.float32) * np.hanning(400).astype(np.float32)
    for c in clicks:
        i = int(c * sr)
        y[i : i + 400] += burst
    onsets = M.audio_beats(y, sr=sr)
    # every click is found within about one 32 ms hop, and nothing is found away from a click
    # (librosa may mark a burst twice, one hop apart)
    assert np.all(np.min(np.abs(onsets[None, :] - clicks[:, None]), axis=1) < 0.04)
    assert np.all(np.min(np.abs(onsets[:, None] - clicks[None, :]), axis=1) < 0.08)
    assert M.audio_beats(np.zeros(sr, dtype=np.float32), sr=sr).size == 0
    with pytest.raises(ParameterError, match="audio: expected a non-empty 1-D float waveform"):
        M.audio_beats(np.zeros((10, 2), dtype=np.float32), sr=sr)


# ------------------------------------------------------------ L1 diversity
def test_l1_diversity_identical_windows_zero_and_known_offsets():
    w = int(round(M.DEFAULT_DIVERSITY_WINDOW_S * FPS))
    assert w == 68
    rng = np.random.default_rng(5)
    one = rng.normal(0, 0.1, (w, 3, 3))
    assert M.l1_diversity(np.concatenate([one] * 4), fps=FPS) == 0.0
    # three windows offset by 0, 0.2 and -0.1 m along x: pairs 0.2, 0.1, 0.3 -> mean 0.2
    offs = [0.0, 0.2, -0.1]
    pos = np.concatenate([one + np.array([d, 0, 0]) for d in offs] + [one[:10]])  # tail dropped
    assert M.l1_diversity(pos, fps=FPS) == pytest.approx(0.2, rel=1e-12)


def test_l1_diversity_matches_pairwise_brute_force():
    rng = np.random.default_rng(6)
    pos = rng.normal(0, 0.2, (125, 4, 3))
    win = 25
    wins = [pos[k * win : (k + 1) * win, [0, 2]] for k in range(5)]
    pairs = [np.abs(a - b).sum() / (win * 2) for i, a in enumerate(wins) for b in wins[i + 1 :]]
    got = M.l1_diversity(pos, fps=FPS, window_s=win / FPS, joints=[0, 2])
    assert got == pytest.approx(np.mean(pairs), rel=1e-12)
    with pytest.raises(ParameterError, match="needs at least 2 windows of 25 frames"):
        M.l1_diversity(pos[:40], fps=FPS, window_s=win / FPS)


# ------------------------------------------------------------ seam jerk
def test_seam_jerk_cubic_is_one_and_sinusoid_close_to_one():
    cubic = _motion(200, [lambda t: 0.3 * t**3, lambda t: -t**3])
    b = np.arange(8, 200, 8)
    s = M.seam_jerk(cubic, fps=FPS, boundaries=b)
    assert s["ratio"] == pytest.approx(1.0, rel=1e-6)
    assert s["n_seam"] == 3 * b.size and s["n_seam"] + s["n_inside"] == 197
    smooth = _motion(300, [lambda t: 0.2 * np.sin(2 * np.pi * 0.7 * t), lambda t: 0.1 * np.cos(2 * np.pi * 1.3 * t)])
    r = M.seam_jerk(smooth, fps=FPS, boundaries=np.arange(8, 300, 8))["ratio"]
    assert 0.9 < r < 1.1


def test_seam_jerk_large_for_a_step_discontinuity():
    # smooth motion with a 2 cm jump at every window start, as a bad stitch would give
    pos = _motion(240, [lambda t: 0.2 * np.sin(2 * np.pi * 0.5 * t)])
    b = np.arange(8, 240, 8)
    pos[:, 0, 0] += 0.02 * np.searchsorted(b, np.arange(240), side="right")
    s = M.seam_jerk(pos, fps=FPS, boundaries=b)
    assert s["ratio"] > 50
    with pytest.raises(ParameterError, match=r"boundaries: expected frames in \[1, 239\]"):
        M.seam_jerk(pos, fps=FPS, boundaries=[0, 8])


# ------------------------------------------------------------ report
def test_find_wrists_across_naming_schemes():
    assert M.find_wrists(["pelvis", "left_wrist", "x", "right_wrist"]) == (1, 3)
    assert M.find_wrists(["Hips", "mixamorig:RightHand", "LeftHandThumb1", "LeftHand"]) == (3, 1)
    with pytest.raises(ParameterError, match="names: expected a right wrist joint"):
        M.find_wrists(["LeftHand", "RightHandThumb1"])


def test_motion_report_uses_the_same_code_for_ground_truth():
    rng = np.random.default_rng(7)
    gt = np.cumsum(rng.normal(0, 0.005, (300, 55, 3)), axis=0)
    gen = gt[::-1].copy()
    beats = np.arange(0.5, 10.0, 0.7)
    rep = M.motion_report(gen, fps=FPS, ground_truth=gt, audio_beats_s=beats, boundaries=np.arange(8, 300, 8), joints=[16, 18, 20])
    g, t = rep["generated"], rep["ground_truth"]
    assert set(g) == set(t)
    assert t["average_jerk_m_s3"] == M.average_jerk(gt, fps=FPS, joints=[16, 18, 20])
    assert g["average_acceleration_m_s2"] == M.average_acceleration(gen, fps=FPS, joints=[16, 18, 20])
    assert t["beat_align"] == M.beat_align(gt, fps=FPS, joints=list(M.SMPLX_WRISTS), audio_beats_s=beats)
    assert t["seam"] == M.seam_jerk(gt, fps=FPS, boundaries=np.arange(8, 300, 8), joints=[16, 18, 20])
    assert rep["comparison"]["speed_hellinger"] == M.speed_hellinger(gen, gt, fps=FPS, joints=[16, 18, 20])
    assert rep["settings"]["beat_joints"] == [20, 21]
    # the reversed motion has the same speeds, so the same histogram
    assert rep["comparison"]["speed_hellinger"] == pytest.approx(0.0, abs=1e-12)
    solo = M.motion_report(gen, fps=FPS)
    assert solo["ground_truth"] is None and "beat_align" not in solo["generated"]
    with pytest.raises(ParameterError, match="beat_joints: BeatAlign needs the wrist joints"):
        M.motion_report(gen[:, :20], fps=FPS, audio_beats_s=beats)
    with pytest.raises(ParameterError, match="ground_truth: expected 55 joints"):
        M.motion_report(gen, fps=FPS, ground_truth=gt[:, :20])


# ------------------------------------------------------------ real data
@pytest.fixture(scope="module")
def scott(scott_dir):
    import soundfile as sf

    from gesturedb.io.smplx import read_smplx

    motion = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    audio, sr = sf.read(scott_dir / "2_scott_0_1_1.wav", dtype="float32")
    return motion, audio, sr


def test_real_ground_truth_numbers_are_plausible(scott):
    motion, audio, sr = scott
    pos, fps = motion.positions, motion.fps
    arms = [motion.skeleton.index(n) for n in ("left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist")]
    half = pos.shape[0] // 2
    # a stitched version: 8-frame windows from random places, as a bad search would give
    rng = np.random.default_rng(8)
    starts = rng.integers(0, pos.shape[0] - 8, pos.shape[0] // 8)
    stitched = pos[np.concatenate([np.arange(s, s + 8) for s in starts])]
    b = np.arange(8, stitched.shape[0], 8)
    rep = M.motion_report(
        stitched, fps=fps, audio=audio, sr=sr, ground_truth=pos, boundaries=b, joints=arms, names=motion.skeleton.names
    )
    gt = rep["ground_truth"]
    # Conversational arm motion: accelerations of a few m/s^2 and jerks of tens of m/s^3
    # (GENEA-style finite differences at 30 fps; mocap noise raises jerk, not by decades).
    assert 0.5 < gt["average_acceleration_m_s2"] < 20
    assert 5 < gt["average_jerk_m_s3"] < 500
    assert 0.0 < gt["beat_align"] <= 1.0 and 0.0 < gt["beat_align_audio_to_motion"] <= 1.0
    assert 0.05 < gt["l1_diversity_m"] < 2.0
    # recorded motion has no seams: its jerk is the same at the "boundaries" as elsewhere
    assert 0.8 < gt["seam"]["ratio"] < 1.25
    assert rep["generated"]["seam"]["ratio"] > 10
    # speed distributions: the two halves of one take are close, a frozen pose is not
    first, second = pos[:half], pos[half:]
    assert M.speed_hellinger(first, second, fps=fps, joints=arms) < 0.25
    frozen = np.repeat(pos[:1], 200, axis=0)
    assert M.speed_hellinger(frozen, pos, fps=fps, joints=arms) > 0.9
    # the data README: wrists move at about 0.3 to 1 m/s
    wrists = list(rep["settings"]["beat_joints"])
    assert 0.3 < M.joint_speeds(pos, fps=fps, joints=wrists).mean() < 1.0
    # speech has several onsets per second
    assert 1.0 < rep["settings"]["n_audio_beats"] / (audio.size / sr) < 10.0
