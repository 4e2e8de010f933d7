"""Style signatures: gesturedb.features.style."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.features.controls import control_features
from gesturedb.features.style import STYLE_NAMES, STYLE_UNITS, style_signature, style_signatures

try:
    from test_features_synth import PELVIS_Y, SMPLX_JOINTS, gesturing, rest_positions, rigid
except ModuleNotFoundError:  # pragma: no cover
    from tests.test_features_synth import PELVIS_Y, SMPLX_JOINTS, gesturing, rest_positions, rigid

J = SMPLX_JOINTS


def test_static_pose_has_exact_radius_and_height_and_no_speed():
    pos = np.repeat(rest_positions()[None], 20, axis=0)
    sig = style_signature(pos, joints=J, fps=30, start=3, length=10)
    assert sig.shape == (3,) and sig.dtype == np.float32
    # rest wrists at (+-0.20, 1.02, 0.28): radius hypot(0.2, 0.28), height 1.02 - pelvis
    np.testing.assert_allclose(sig, [0.0, np.hypot(0.20, 0.28), 1.02 - PELVIS_Y], atol=1e-6)
    assert STYLE_NAMES == ("speed", "radius", "height") and STYLE_UNITS == ("m/s", "m", "m")


def test_speed_is_the_mean_over_both_wrists():
    fps = 30.0
    n = 40
    t = np.arange(n) / fps
    pos = np.repeat(rest_positions()[None], n, axis=0)
    pos[:, J["left_wrist"]] += t[:, None] * [0.0, 0.0, 1.0]  # 1 m/s forward
    pos[:, J["right_wrist"]] += t[:, None] * [0.0, 0.6, 0.0]  # 0.6 m/s up
    sig = style_signature(pos, joints=J, fps=fps, start=0, length=n)
    assert sig[0] == pytest.approx(0.8, abs=1e-6)
    # mean height: both wrists start at 1.02 - pelvis, the right one rises 0.6 m/s * mean(t)
    assert sig[2] == pytest.approx(1.02 - PELVIS_Y + 0.5 * 0.6 * t.mean(), abs=1e-6)


def test_many_clips_equal_one_by_one_and_the_control_means():
    rng = np.random.default_rng(0)
    pos = rigid(gesturing(300, seed=3), np.linspace(0, 1, 300), [0.3, 0, 0.1])
    starts = rng.integers(0, 250, 25)
    lengths = rng.integers(1, 50, 25)
    many = style_signatures(pos, joints=J, fps=30, starts=starts, lengths=lengths)
    assert many.shape == (25, 3) and many.dtype == np.float32
    ctrl = control_features(pos, joints=J, fps=30)
    for c, (s, n) in enumerate(zip(starts, lengths)):
        np.testing.assert_allclose(many[c], style_signature(pos, joints=J, fps=30, start=int(s), length=int(n)), rtol=1e-6)
        sl = slice(s, s + n)
        expect = [
            np.mean((ctrl["left_wrist_speed"][sl] + ctrl["right_wrist_speed"][sl]) / 2),
            np.mean((ctrl["left_hand_radius"][sl] + ctrl["right_hand_radius"][sl]) / 2),
            np.mean((ctrl["left_wrist_height"][sl] + ctrl["right_wrist_height"][sl]) / 2),
        ]
        np.testing.assert_allclose(many[c], expect, rtol=1e-5, atol=1e-6)
    assert style_signatures(pos, joints=J, fps=30, starts=[], lengths=[]).shape == (0, 3)


def test_yaw_and_translation_do_not_change_the_style():
    pos = gesturing(120)
    a = style_signatures(pos, joints=J, fps=30, starts=[0, 40], lengths=[60, 80])
    b = style_signatures(rigid(pos, -2.5, [4.0, 0.3, 1.0]), joints=J, fps=30, starts=[0, 40], lengths=[60, 80])
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_real_clips_have_a_plausible_style(scott_dir):
    from gesturedb.io.smplx import read_smplx

    motion = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    n = len(motion.positions)
    starts = np.arange(0, n - 90, 90)
    sig = style_signatures(motion.positions, joints=J, fps=motion.fps, starts=starts, lengths=np.full(len(starts), 90))
    speed, radius, height = sig.T
    assert 0.2 < np.median(speed) < 1.2 and (speed < 3.0).all()
    assert 0.15 < np.median(radius) < 0.6
    assert -0.2 < np.median(height) < 0.45  # between the hips and the shoulders
    assert sig.std(axis=0).min() > 0.005  # clips differ in style


def test_bad_clips():
    pos = gesturing(50)
    with pytest.raises(ParameterError, match="inside the 50 frames of positions; got clip 1: start 45, length 10"):
        style_signatures(pos, joints=J, fps=30, starts=[0, 45], lengths=[10, 10])
    with pytest.raises(ParameterError, match="got clip 0: start 0, length 0"):
        style_signature(pos, joints=J, fps=30, start=0, length=0)
    with pytest.raises(ParameterError, match="start: expected an int number of frames"):
        style_signature(pos, joints=J, fps=30, start=1.0, length=5)
    with pytest.raises(ParameterError, match="equal length"):
        style_signatures(pos, joints=J, fps=30, starts=[0, 1], lengths=[5])
