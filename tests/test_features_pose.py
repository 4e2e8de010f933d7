"""Pose features: gesturedb.features.pose."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.features.pose import (
    FEATURE_ROLES,
    POSE_STRIDE_S,
    TIMESCALE_MAX_S,
    default_pose_stride,
    motion_timescale,
    pose_feature_size,
    pose_features,
    timescale_pose_stride,
    velocity_lag_products,
)

try:
    from test_features_synth import SMPLX_JOINTS, gesturing, rigid, yaw_matrix
except ModuleNotFoundError:  # pragma: no cover
    from tests.test_features_synth import SMPLX_JOINTS, gesturing, rigid, yaw_matrix

J = SMPLX_JOINTS
#: SMPL-X's left and right ankle (gesturing() moves every joint)
ANKLES = (7, 8)


def _reference(pos, window, stride, stance=()):
    """Frame-by-frame loop with the facing angle from atan2 (no smoothing)."""
    n = len(pos)
    lags = range(-(window - 1), window)
    out = np.zeros((n, len(lags), 8, 3))
    ankles = np.zeros((n, len(lags), len(stance), 3))
    for f in range(n):
        a = (pos[f, J["left_hip"]] - pos[f, J["right_hip"]]) + (pos[f, J["left_shoulder"]] - pos[f, J["right_shoulder"]])
        rot = yaw_matrix(np.arctan2(-a[2], a[0]))  # the rest axis +x maps to (cos, 0, -sin)
        for i, k in enumerate(lags):
            s = min(max(f + k * stride, 0), n - 1)
            for j, role in enumerate(FEATURE_ROLES):
                out[f, i, j] = rot.T @ (pos[s, J[role]] - pos[f, J["root"]])
            for j, joint in enumerate(stance):
                ankles[f, i, j] = rot.T @ (pos[s, joint] - pos[f, J["root"]])
    return np.concatenate([out.reshape(n, -1), ankles.reshape(n, -1)], axis=1)


def test_layout_dtype_and_default_size():
    pos = gesturing(40)
    feat = pose_features(pos, joints=J, fps=15)
    assert feat.shape == (40, 120) == (40, pose_feature_size())
    assert feat.dtype == np.float32 and feat.flags.c_contiguous
    assert FEATURE_ROLES == (
        "left_wrist", "right_wrist", "left_elbow", "right_elbow",
        "left_index1", "right_index1", "left_pinky1", "right_pinky1",
    )
    assert pose_features(pos, joints=J, fps=15, window=1).shape == (40, 24)
    assert pose_feature_size(window=4) == 168
    # the stance: the two ankles after the 8 feature joints, what a build stores for a rig with legs
    with_stance = pose_features(pos, joints=J, fps=15, stance=ANKLES)
    assert with_stance.shape == (40, 150) == (40, pose_feature_size(stance=True))
    np.testing.assert_array_equal(with_stance[:, :120], feat)  # the feature joints' columns are untouched
    for bad in ([7], [7, 8, 9], [7, len(pos[0])], [-1, 8]):
        with pytest.raises(ParameterError, match=r"^stance: expected the two ankles' joint indices"):
            pose_features(pos, joints=J, fps=15, stance=bad)


def test_the_ankles_are_found_in_every_rig_with_legs_and_only_there():
    from gesturedb.io.joints import ankle_joints

    names = ["pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
             "right_ankle", "spine3", "left_foot", "right_foot"]
    assert ankle_joints(names).tolist() == [7, 8]  # SMPL-X: "foot" are the toes there
    bvh = ["Hips", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase", "RightUpLeg", "RightLeg", "RightFoot", "Spine"]
    assert ankle_joints(bvh).tolist() == [3, 7]
    assert ankle_joints(["Hips", "Spine", "Neck", "Head", "LeftArm", "RightArm"]).size == 0  # no legs: no stance
    assert ankle_joints(bvh[:5] + ["Spine"]).size == 0  # one leg is no stance either


def test_default_stride_is_the_same_time_at_any_frame_rate():
    assert [default_pose_stride(f) for f in (15, 30, 60, 7.5, 4)] == [2, 4, 8, 1, 1]
    assert POSE_STRIDE_S == pytest.approx(2 / 15)
    # the same movement sampled at 30 fps and at 15 fps: the same features at the same instants
    pos30 = gesturing(80, fps=30.0)
    f30 = pose_features(pos30, joints=J, fps=30)
    f15 = pose_features(pos30[::2], joints=J, fps=15)
    inner = np.arange(4, 36)  # away from the clamped ends
    np.testing.assert_allclose(f30[2 * inner], f15[inner], atol=1e-6)


@pytest.mark.parametrize("window,stride", [(3, 2), (4, 2), (1, 1), (3, 5)])
def test_matches_a_frame_by_frame_loop_while_walking_and_turning(window, stride):
    rng = np.random.default_rng(window * 10 + stride)
    n = 50
    angles = np.cumsum(rng.normal(scale=0.05, size=n))
    walk = np.cumsum(rng.normal(scale=0.02, size=(n, 3)), axis=0)
    pos = rigid(gesturing(n, seed=stride), angles, walk)
    got = pose_features(pos, joints=J, fps=15, window=window, stride=stride, facing_smooth_s=0)
    np.testing.assert_allclose(got, _reference(pos, window, stride), atol=2e-6)
    got = pose_features(pos, joints=J, fps=15, window=window, stride=stride, stance=ANKLES, facing_smooth_s=0)
    np.testing.assert_allclose(got, _reference(pos, window, stride, ANKLES), atol=2e-6)


def test_stacked_frames_are_past_and_future_clamped_at_both_ends():
    pos = gesturing(30)  # the body frame never moves, so lag k of frame f is lag 0 of frame f + 2k
    feat = pose_features(pos, joints=J, fps=15).reshape(30, 5, 24)
    for f in range(30):
        for i, k in enumerate(range(-2, 3)):
            np.testing.assert_array_equal(feat[f, i], feat[min(max(f + 2 * k, 0), 29), 2])
    wrist = pos[:, J["left_wrist"]] - pos[:, J["root"]]
    np.testing.assert_allclose(feat[:, 2, 0:3], wrist, atol=1e-6)  # rest body frame = world axes
    np.testing.assert_allclose(feat[:, 2, 3:6], pos[:, J["right_wrist"]] - pos[:, J["root"]], atol=1e-6)


@pytest.mark.parametrize("angle", [0.4, -1.7, np.pi])
def test_yaw_and_translation_leave_the_features_unchanged(angle):
    rng = np.random.default_rng(5)
    pos = gesturing(90) + rng.normal(scale=0.005, size=(90, 55, 3))  # noisy hips: smoothing active
    ref = pose_features(pos, joints=J, fps=15)
    np.testing.assert_allclose(pose_features(rigid(pos, angle, [3.0, -0.1, 7.0]), joints=J, fps=15), ref, atol=2e-5)
    np.testing.assert_allclose(pose_features(pos + [10.0, 0.0, -4.0], joints=J, fps=15), ref, atol=2e-5)


def test_past_and_future_frames_are_expressed_in_the_current_body_frame():
    # the whole speaker walks forward at 1 m/s: the past wrist positions lie behind the
    # current root by 1 m/s * lag, the future ones ahead of it
    fps = 30.0
    pos = gesturing(40, fps=fps)
    static = pose_features(pos, joints=J, fps=fps).reshape(40, 5, 8, 3)
    walking = rigid(pos, 0.0, np.arange(40)[:, None] / fps * [0, 0, 1.0])
    moved = pose_features(walking, joints=J, fps=fps).reshape(40, 5, 8, 3)
    f = np.arange(40)
    for i, k in enumerate(range(-2, 3)):
        lag_s = (np.clip(f + 4 * k, 0, 39) - f) / fps  # stride 4 at 30 fps
        np.testing.assert_allclose(moved[:, i, :, 2], static[:, i, :, 2] + lag_s[:, None], atol=1e-5)
        np.testing.assert_allclose(moved[:, i, :, :2], static[:, i, :, :2], atol=1e-5)


def test_large_recordings_are_processed_in_blocks_identically(monkeypatch):
    import gesturedb.features.pose as pose_mod

    pos = rigid(gesturing(100), np.linspace(0, 2, 100), 0.0)
    whole = pose_features(pos, joints=J, fps=15)
    monkeypatch.setattr(pose_mod, "_BLOCK", 7)
    np.testing.assert_array_equal(pose_features(pos, joints=J, fps=15), whole)


def test_bad_arguments():
    pos = gesturing(5)
    with pytest.raises(ParameterError, match="window: expected an int >= 1"):
        pose_features(pos, joints=J, fps=15, window=0)
    with pytest.raises(ParameterError, match="stride: expected an int >= 1"):
        pose_features(pos, joints=J, fps=15, stride=1.5)
    with pytest.raises(ParameterError, match="fps: expected a positive number"):
        pose_features(pos, joints=J, fps=0)
    with pytest.raises(ParameterError, match="missing role.*'right_pinky1'"):
        pose_features(pos, joints={k: v for k, v in J.items() if k != "right_pinky1"}, fps=15)
    with pytest.raises(ParameterError, match=r"positions: expected shape \(F, J, 3\)"):
        pose_features(pos[0], joints=J, fps=15)


def test_real_motion(scott_dir):
    from gesturedb.features.controls import control_features
    from gesturedb.io.smplx import read_smplx

    motion = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    pos = motion.positions
    feat = pose_features(pos, joints=J, fps=motion.fps)
    assert feat.shape == (len(pos), 120) and np.isfinite(feat).all()
    assert np.abs(feat).max() < 1.5  # every feature joint within arm's reach of the root
    # the same speaker elsewhere in the room, facing elsewhere
    moved = rigid(pos, 2.0, [-1.0, 0.0, 2.5])
    np.testing.assert_allclose(pose_features(moved, joints=J, fps=motion.fps), feat, atol=2e-5)
    # lag 0 (the middle block), left and right wrist y: the wrist heights of the controls
    # (an independent path, with the same facing smoothing in seconds)
    ctrl = control_features(pos, joints=J, fps=motion.fps)
    np.testing.assert_allclose(feat[:, 48 + 1], ctrl["left_wrist_height"], atol=1e-6)
    np.testing.assert_allclose(feat[:, 48 + 4], ctrl["right_wrist_height"], atol=1e-6)
    # hands move: the past and future blocks differ from the current one
    assert np.abs(feat[:, :24] - feat[:, 48:72]).mean() > 0.01
    assert np.abs(feat[:, 96:] - feat[:, 48:72]).mean() > 0.01


def _swinging(freq_hz, fps, seconds=20.0, amplitude_m=0.1):
    """A standing speaker whose feature joints all swing left and right at ``freq_hz``."""
    pos = gesturing(int(seconds * fps), fps=fps)
    pos[:] = pos[:1]  # still, then only the swing
    swing = amplitude_m * np.sin(2 * np.pi * freq_hz * np.arange(len(pos)) / fps)
    for role in FEATURE_ROLES:
        pos[:, J[role], 0] += swing
    return pos


@pytest.mark.parametrize("fps", [15.0, 30.0, 60.0])
@pytest.mark.parametrize("freq", [0.8, 1.5])
def test_the_timescale_of_a_swing_is_a_sixth_of_its_period(fps, freq):
    """A sinusoid's velocity autocorrelation is cos(2 pi f lag): one half at lag 1 / (6 f), at any frame
    rate (linear between frames: within 5 % of it down to 10 frames a period), wherever the speaker
    stands and faces."""
    pos = _swinging(freq, fps)
    lags = velocity_lag_products(pos, joints=J, fps=fps)
    assert lags.shape == (int(np.ceil(TIMESCALE_MAX_S * fps)) + 1,) and lags.dtype == np.float64
    assert motion_timescale(lags, fps) == pytest.approx(1 / (6 * freq), rel=0.05)
    moved = rigid(pos, 2.0, [-1.0, 0.0, 2.5])
    np.testing.assert_allclose(velocity_lag_products(moved, joints=J, fps=fps), lags, rtol=1e-9, atol=1e-9)
    # recordings add up: two halves give the whole but for the products across the cut
    half = len(pos) // 2
    parts = velocity_lag_products(pos[:half], joints=J, fps=fps) + velocity_lag_products(pos[half:], joints=J, fps=fps)
    assert motion_timescale(parts, fps) == pytest.approx(motion_timescale(lags, fps), rel=0.02)


def test_the_stride_follows_the_timescale():
    # the BEAT2 speaker's 0.165 s gives the paper's 2/15 s at 15 and 30 fps; 1.25x faster, 3 frames at 30 fps
    assert [timescale_pose_stride(0.165, f) for f in (15, 30, 60)] == [2, 4, 8]
    assert timescale_pose_stride(0.137, 30) == 3
    assert timescale_pose_stride(0.097, 15) == 1 and timescale_pose_stride(0.001, 60) == 1  # at least 1
    assert timescale_pose_stride(None, 30) == default_pose_stride(30) == 4  # unknown: 2/15 s
    with pytest.raises(ParameterError, match=r"^timescale_s: expected a positive number of seconds or None"):
        timescale_pose_stride(-0.1, 15)
    # a still speaker has no timescale; one who drifts slowly has the longest measured
    still = gesturing(60, fps=15.0)
    still[:] = still[:1]
    assert motion_timescale(velocity_lag_products(still, joints=J, fps=15.0), 15.0) is None
    assert motion_timescale(velocity_lag_products(_swinging(0.05, 15.0), joints=J, fps=15.0), 15.0) == TIMESCALE_MAX_S
    assert motion_timescale(velocity_lag_products(still[:1], joints=J, fps=15.0), 15.0) is None  # one frame


def test_the_real_speakers_timescale_at_two_frame_rates_and_through_jitter(scott_dir):
    """The BEAT2 speaker at the capture's 30 fps and every second frame (15 fps): the same timescale in
    seconds (within 3 %), so the same stride in seconds; told that the frames come 1.25x faster, shorter
    (the smoothing in seconds keeps it from 1/1.25 exactly), 3 frames at 30 fps. Jitter of a few
    millimetres per frame, another capture pipeline's, leaves it within 3 % and the stride as it was
    (unsmoothed, 5 mm at 30 fps read as 0.03 s)."""
    from gesturedb.io.smplx import read_smplx

    motion = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    assert motion.fps == 30
    pos = motion.positions
    t30 = motion_timescale(velocity_lag_products(pos, joints=J, fps=30.0), 30.0)
    t15 = motion_timescale(velocity_lag_products(pos[::2], joints=J, fps=15.0), 15.0)
    assert 0.15 < t30 < 0.18 and t15 == pytest.approx(t30, rel=0.03)
    assert (timescale_pose_stride(t30, 30.0), timescale_pose_stride(t15, 15.0)) == (4, 2)
    faster = motion_timescale(velocity_lag_products(pos, joints=J, fps=37.5), 37.5)
    assert 0.78 < faster / t30 < 0.86 and timescale_pose_stride(faster, 30.0) == 3
    rng = np.random.default_rng(0)
    for fps, clean, p in ((30.0, t30, pos), (15.0, t15, pos[::2])):
        noisy = p + rng.normal(0.0, 0.005, p.shape)
        got = motion_timescale(velocity_lag_products(noisy, joints=J, fps=fps), fps)
        assert got == pytest.approx(clean, rel=0.03) and timescale_pose_stride(got, fps) == round(fps * 2 / 15)
