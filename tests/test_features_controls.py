"""Control signals: gesturedb.features.controls."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.features.body import body_frame, to_body_frame
from gesturedb.features.controls import CONTROL_DOCS, CONTROL_NAMES, CONTROL_UNITS, control_features

try:
    from test_features_synth import PELVIS_Y, SMPLX_JOINTS, gesturing, rest_positions, rigid
except ModuleNotFoundError:  # pragma: no cover
    from tests.test_features_synth import PELVIS_Y, SMPLX_JOINTS, gesturing, rest_positions, rigid

J = SMPLX_JOINTS
REQUIRED = {
    "left_wrist_height", "right_wrist_height", "left_wrist_speed", "right_wrist_speed",
    "left_hand_radius", "right_hand_radius", "height_asymmetry", "mirror_distance",
}


def test_names_units_and_docs():
    assert REQUIRED <= set(CONTROL_NAMES)
    assert set(CONTROL_UNITS) == set(CONTROL_DOCS) == set(CONTROL_NAMES)
    assert all(CONTROL_UNITS[n] in ("m", "m/s") for n in CONTROL_NAMES)
    assert all(CONTROL_UNITS[n] == "m/s" for n in CONTROL_NAMES if n.endswith("speed"))
    assert all(CONTROL_DOCS[n] and "\n" not in CONTROL_DOCS[n] for n in CONTROL_NAMES)
    out = control_features(gesturing(30), joints=J, fps=30)
    assert list(out) == list(CONTROL_NAMES)
    for v in out.values():
        assert v.shape == (30,) and v.dtype == np.float32 and v.flags.c_contiguous


def test_symmetric_rest_pose():
    pos = np.repeat(rest_positions()[None], 10, axis=0)
    out = control_features(pos, joints=J, fps=30)
    np.testing.assert_allclose(out["left_wrist_height"], 1.02 - PELVIS_Y, atol=1e-6)
    np.testing.assert_allclose(out["right_wrist_height"], 1.02 - PELVIS_Y, atol=1e-6)
    np.testing.assert_allclose(out["left_hand_radius"], np.hypot(0.20, 0.28), atol=1e-6)
    np.testing.assert_allclose(out["left_wrist_forward"], 0.28, atol=1e-6)
    np.testing.assert_allclose(out["hand_distance"], 0.40, atol=1e-6)
    for name in ("height_asymmetry", "mirror_distance", "left_wrist_speed", "hand_speed"):
        np.testing.assert_allclose(out[name], 0.0, atol=1e-6)


def test_hand_made_motion():
    fps = 30.0
    n = 45
    t = np.arange(n) / fps
    pos = np.repeat(rest_positions()[None], n, axis=0)
    pos[:, J["left_wrist"]] += t[:, None] * [0.0, 1.0, 0.0]  # left wrist rises at 1 m/s
    out = control_features(pos, joints=J, fps=fps)
    np.testing.assert_allclose(out["left_wrist_speed"], 1.0, atol=1e-6)
    np.testing.assert_allclose(out["right_wrist_speed"], 0.0, atol=1e-6)
    np.testing.assert_allclose(out["hand_speed"], 1.0, atol=1e-6)
    np.testing.assert_allclose(out["left_wrist_height"], 1.02 - PELVIS_Y + t, atol=1e-6)
    np.testing.assert_allclose(out["height_asymmetry"], t, atol=1e-6)
    # mirrored right wrist = (0.20, 1.02, 0.28): only the height differs
    np.testing.assert_allclose(out["mirror_distance"], t, atol=1e-6)
    np.testing.assert_allclose(out["left_hand_radius"], np.hypot(0.20, 0.28), atol=1e-6)


def test_mirror_distance_ignores_mirror_symmetric_gestures_only():
    pos = gesturing(60, seed=4)
    # make the right arm the exact mirror image of the left one
    for a, b in (("left_wrist", "right_wrist"), ("left_elbow", "right_elbow")):
        pos[:, J[b]] = pos[:, J[a]] * [-1, 1, 1]
    out = control_features(pos, joints=J, fps=30)
    np.testing.assert_allclose(out["mirror_distance"], 0.0, atol=1e-6)
    np.testing.assert_allclose(out["height_asymmetry"], 0.0, atol=1e-6)
    np.testing.assert_allclose(out["left_wrist_speed"], out["right_wrist_speed"], atol=1e-6)
    # moving both wrists the same way (not mirrored) sideways breaks the symmetry
    pos[:, J["right_wrist"]] += [0.1, 0, 0]
    pos[:, J["left_wrist"]] += [0.1, 0, 0]
    assert (control_features(pos, joints=J, fps=30)["mirror_distance"] > 0.19).all()


@pytest.mark.parametrize("angle", [0.9, -np.pi / 2, np.pi])
def test_yaw_and_translation_leave_controls_unchanged(angle):
    pos = gesturing(100, seed=2)
    a = control_features(pos, joints=J, fps=30)
    b = control_features(rigid(pos, angle, [2.0, -0.5, 3.0]), joints=J, fps=30)
    for name in CONTROL_NAMES:
        np.testing.assert_allclose(b[name], a[name], atol=2e-6, err_msg=name)


def test_real_wrists_are_plausible(scott_dir):
    from gesturedb.io.smplx import read_smplx

    motion = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    pos, fps = motion.positions, motion.fps
    out = control_features(pos, joints=J, fps=fps)
    origin, rot = body_frame(pos, joints=J)
    local = to_body_frame(pos, origin, rot)
    hip_y = local[:, [J["left_hip"], J["right_hip"]], 1].mean(axis=1)
    shoulder_y = local[:, [J["left_shoulder"], J["right_shoulder"]], 1].mean(axis=1)
    for side in ("left", "right"):
        h = out[f"{side}_wrist_height"]
        # mostly between (a hand-width below) the hips and the shoulders
        assert np.mean((h > hip_y - 0.05) & (h < shoulder_y)) > 0.85, side
        assert np.mean(out[f"{side}_wrist_forward"] > 0) > 0.75, side  # in front of the body
        assert 0.3 <= np.median(out[f"{side}_wrist_speed"]) <= 1.0, side
        assert 0.15 < np.median(out[f"{side}_hand_radius"]) < 0.6, side
    assert np.percentile(out["hand_speed"], 99) < 3.0
    assert 0.0 < np.median(out["height_asymmetry"]) < 0.3


def test_bad_arguments():
    pos = gesturing(5)
    with pytest.raises(ParameterError, match="missing role.*'left_shoulder'"):
        control_features(pos, joints={k: v for k, v in J.items() if k != "left_shoulder"}, fps=30)
    with pytest.raises(ParameterError, match="fps: expected a positive number"):
        control_features(pos, joints=J, fps=-30)
    with pytest.raises(ParameterError, match="smooth_s: expected a number >= 0"):
        control_features(pos, joints=J, fps=30, smooth_s=float("nan"))
