"""Pose features: gesturedb.features.pose."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.features.pose import FEATURE_ROLES, pose_feature_size, pose_features

try:
    from test_features_synth import SMPLX_JOINTS, gesturing, rigid, yaw_matrix
except ModuleNotFoundError:  # pragma: no cover
    from tests.test_features_synth import SMPLX_JOINTS, gesturing, rigid, yaw_matrix

J = SMPLX_JOINTS


def _reference(pos, window, stride):
    """Frame-by-frame loop with the facing angle from atan2 (no smoothing)."""
    n = len(pos)
    out = np.zeros((n, window, 8, 3))
    for f in range(n):
        a = (pos[f, J["left_hip"]] - pos[f, J["right_hip"]]) + (pos[f, J["left_shoulder"]] - pos[f, J["right_shoulder"]])
        rot = yaw_matrix(np.arctan2(-a[2], a[0]))  # the rest axis +x maps to (cos, 0, -sin)
        for k in range(window):
            s = max(f - k * stride, 0)
            for j, role in enumerate(FEATURE_ROLES):
                out[f, k, j] = rot.T @ (pos[s, J[role]] - pos[f, J["root"]])
    return out.reshape(n, -1)


def test_layout_dtype_and_default_size():
    pos = gesturing(40)
    feat = pose_features(pos, joints=J)
    assert feat.shape == (40, 96) == (40, pose_feature_size())
    assert feat.dtype == np.float32 and feat.flags.c_contiguous
    assert FEATURE_ROLES == (
        "left_wrist", "right_wrist", "left_elbow", "right_elbow",
        "left_index1", "right_index1", "left_pinky1", "right_pinky1",
    )
    assert pose_features(pos, joints=J, window=1).shape == (40, 24)
    assert pose_feature_size(window=3) == 72


@pytest.mark.parametrize("window,stride", [(4, 2), (1, 1), (3, 5)])
def test_matches_a_frame_by_frame_loop_while_walking_and_turning(window, stride):
    rng = np.random.default_rng(window * 10 + stride)
    n = 50
    angles = np.cumsum(rng.normal(scale=0.05, size=n))
    walk = np.cumsum(rng.normal(scale=0.02, size=(n, 3)), axis=0)
    pos = rigid(gesturing(n, seed=stride), angles, walk)
    got = pose_features(pos, joints=J, window=window, stride=stride, smooth_frames=0)
    np.testing.assert_allclose(got, _reference(pos, window, stride), atol=2e-6)


def test_stacked_frames_are_the_past_clamped_at_the_start():
    pos = gesturing(30)  # the body frame never moves, so lag k of frame f is lag 0 of frame f - 2k
    feat = pose_features(pos, joints=J).reshape(30, 4, 24)
    for f in range(30):
        for k in range(4):
            np.testing.assert_array_equal(feat[f, k], feat[max(f - 2 * k, 0), 0])
    wrist = pos[:, J["left_wrist"]] - pos[:, J["root"]]
    np.testing.assert_allclose(feat[:, 0, 0:3], wrist, atol=1e-6)  # rest body frame = world axes
    np.testing.assert_allclose(feat[:, 0, 3:6], pos[:, J["right_wrist"]] - pos[:, J["root"]], atol=1e-6)


@pytest.mark.parametrize("angle", [0.4, -1.7, np.pi])
def test_yaw_and_translation_leave_the_features_unchanged(angle):
    rng = np.random.default_rng(5)
    pos = gesturing(90) + rng.normal(scale=0.005, size=(90, 55, 3))  # noisy hips: smoothing active
    ref = pose_features(pos, joints=J)
    np.testing.assert_allclose(pose_features(rigid(pos, angle, [3.0, -0.1, 7.0]), joints=J), ref, atol=2e-5)
    np.testing.assert_allclose(pose_features(pos + [10.0, 0.0, -4.0], joints=J), ref, atol=2e-5)


def test_past_frames_are_expressed_in_the_current_body_frame():
    # the whole speaker walks forward at 1 m/s: the past wrist positions lie behind
    # the current root by 1 m/s * lag
    fps = 30.0
    pos = gesturing(40, fps=fps)
    static = pose_features(pos, joints=J).reshape(40, 4, 8, 3)
    walking = rigid(pos, 0.0, np.arange(40)[:, None] / fps * [0, 0, 1.0])
    moved = pose_features(walking, joints=J).reshape(40, 4, 8, 3)
    for k in range(4):
        lag_s = np.minimum(np.arange(40), 2 * k) / fps
        np.testing.assert_allclose(moved[:, k, :, 2], static[:, k, :, 2] - lag_s[:, None], atol=1e-5)
        np.testing.assert_allclose(moved[:, k, :, :2], static[:, k, :, :2], atol=1e-5)


def test_large_recordings_are_processed_in_blocks_identically(monkeypatch):
    import gesturedb.features.pose as pose_mod

    pos = rigid(gesturing(100), np.linspace(0, 2, 100), 0.0)
    whole = pose_features(pos, joints=J)
    monkeypatch.setattr(pose_mod, "_BLOCK", 7)
    np.testing.assert_array_equal(pose_features(pos, joints=J), whole)


def test_bad_arguments():
    pos = gesturing(5)
    with pytest.raises(ParameterError, match="window: expected an int >= 1"):
        pose_features(pos, joints=J, window=0)
    with pytest.raises(ParameterError, match="stride: expected an int >= 1"):
        pose_features(pos, joints=J, stride=1.5)
    with pytest.raises(ParameterError, match="missing role.*'right_pinky1'"):
        pose_features(pos, joints={k: v for k, v in J.items() if k != "right_pinky1"})
    with pytest.raises(ParameterError, match=r"positions: expected shape \(F, J, 3\)"):
        pose_features(pos[0], joints=J)


def test_real_motion(scott_dir):
    from gesturedb.features.controls import control_features
    from gesturedb.io.smplx import read_smplx

    motion = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    pos = motion.positions
    feat = pose_features(pos, joints=J)
    assert feat.shape == (len(pos), 96) and np.isfinite(feat).all()
    assert np.abs(feat).max() < 1.5  # every feature joint within arm's reach of the root
    # the same speaker elsewhere in the room, facing elsewhere
    moved = rigid(pos, 2.0, [-1.0, 0.0, 2.5])
    np.testing.assert_allclose(pose_features(moved, joints=J), feat, atol=2e-5)
    # lag 0, left and right wrist y: the wrist heights of the controls (independent path)
    ctrl = control_features(pos, joints=J, fps=motion.fps)
    np.testing.assert_allclose(feat[:, 1], ctrl["left_wrist_height"], atol=1e-6)
    np.testing.assert_allclose(feat[:, 4], ctrl["right_wrist_height"], atol=1e-6)
    # hands move: the lagged blocks differ from the current one
    assert np.abs(feat[:, 72:] - feat[:, :24]).mean() > 0.01
