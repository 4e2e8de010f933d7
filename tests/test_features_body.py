"""Body frame and speeds: gesturedb.features.body."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.features.body import body_frame, gaussian_smooth, point_speeds, to_body_frame

try:  # tests/ is on sys.path when it is not a package, the repo root when it is
    from test_features_synth import SMPLX_JOINTS, gesturing, rest_positions, rigid, yaw_matrix
except ModuleNotFoundError:  # pragma: no cover
    from tests.test_features_synth import SMPLX_JOINTS, gesturing, rest_positions, rigid, yaw_matrix

J = SMPLX_JOINTS


def test_rest_pose_is_the_world_frame():
    pos = np.repeat(rest_positions()[None], 5, axis=0)
    origin, rot = body_frame(pos, joints=J)
    np.testing.assert_allclose(origin, pos[:, 0])
    np.testing.assert_allclose(rot, np.broadcast_to(np.eye(3), (5, 3, 3)), atol=1e-12)


@pytest.mark.parametrize("angle", [0.3, np.pi / 2, -2.0, np.pi])
def test_yaw_and_translation_give_the_rotated_frame(angle):
    pos = gesturing(60)
    shift = np.array([1.5, 0.2, -3.0])
    moved = rigid(pos, angle, shift)
    origin, rot = body_frame(moved, joints=J)
    np.testing.assert_allclose(origin, pos[:, 0] @ yaw_matrix(angle).T + shift, atol=1e-12)
    np.testing.assert_allclose(rot, np.broadcast_to(yaw_matrix(angle), rot.shape), atol=1e-12)
    # the forward axis is where +z went
    np.testing.assert_allclose(rot[:, :, 2], np.broadcast_to([np.sin(angle), 0, np.cos(angle)], (60, 3)), atol=1e-12)
    local = to_body_frame(moved, origin, rot)
    o0, r0 = body_frame(pos, joints=J)
    np.testing.assert_allclose(local, to_body_frame(pos, o0, r0), atol=1e-12)


def test_rotations_are_proper_yaw_rotations_and_invertible():
    rng = np.random.default_rng(3)
    pos = rigid(gesturing(100), rng.uniform(-np.pi, np.pi, 100), rng.normal(size=(100, 3)))
    pos = pos + rng.normal(scale=0.02, size=pos.shape)  # hips/shoulders no longer exactly level
    origin, rot = body_frame(pos, joints=J)
    np.testing.assert_allclose(np.einsum("fji,fjk->fik", rot, rot), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    np.testing.assert_allclose(rot[:, :, 1], np.broadcast_to([0, 1, 0], (100, 3)), atol=1e-12)
    local = to_body_frame(pos, origin, rot)
    back = origin[:, None, :] + np.einsum("fij,fkj->fki", rot, local)
    np.testing.assert_allclose(back, pos, atol=1e-12)


def test_facing_is_perpendicular_to_hips_plus_shoulders():
    # hips turned +40 deg, shoulders -10 deg: the summed left-right axis (both
    # vectors have different lengths) decides, not either one alone.
    pos = rest_positions()[None].copy()
    for side, s in (("left", 1), ("right", -1)):
        pos[0, J[f"{side}_hip"], [0, 2]] = s * 0.09 * np.array([np.cos(0.7), -np.sin(0.7)])
        pos[0, J[f"{side}_shoulder"], [0, 2]] = s * 0.18 * np.array([np.cos(-0.2), -np.sin(-0.2)])
    across = (pos[0, J["left_hip"]] - pos[0, J["right_hip"]]) + (pos[0, J["left_shoulder"]] - pos[0, J["right_shoulder"]])
    _, rot = body_frame(pos, joints=J, smooth_frames=0)
    fwd = rot[0, :, 2]
    assert abs(fwd @ across) < 1e-12
    assert abs(fwd[1]) < 1e-12
    assert np.cross(across, [0, 1, 0]) @ fwd > 0  # forward, not backward


def test_degenerate_frames_take_the_nearest_valid_facing():
    pos = rigid(gesturing(20), np.linspace(0, 1.0, 20), 0.0)
    bad = [0, 1, 9, 10, 19]
    for f in bad:  # hips and shoulders collapse onto the pelvis
        pos[f, [J["left_hip"], J["right_hip"], J["left_shoulder"], J["right_shoulder"]]] = pos[f, 0]
    pos[9, J["left_hip"]] += [0, 0.3, 0]  # only a vertical left-right axis: still unusable
    _, rot = body_frame(pos, joints=J, smooth_frames=0)
    _, good = body_frame(rigid(gesturing(20), np.linspace(0, 1.0, 20), 0.0), joints=J, smooth_frames=0)
    expect = {0: 2, 1: 2, 9: 8, 10: 11, 19: 18}  # nearest usable frame, earlier on ties
    for f, src in expect.items():
        np.testing.assert_allclose(rot[f], good[src], atol=1e-12)
    assert np.isfinite(rot).all()


def test_all_degenerate_faces_plus_z():
    pos = np.zeros((4, 55, 3))
    origin, rot = body_frame(pos, joints=J)
    np.testing.assert_allclose(rot, np.broadcast_to(np.eye(3), (4, 3, 3)))
    np.testing.assert_allclose(origin, 0.0)


def _yaw_angles(rot):
    return np.arctan2(rot[:, 0, 2], rot[:, 2, 2])


def test_smoothing_removes_jitter_but_follows_a_steady_turn():
    rng = np.random.default_rng(7)
    n = 300
    turn = np.linspace(0.0, 1.5, n)  # a steady turn of 86 degrees over 10 s
    pos = rigid(gesturing(n), turn, 0.0)
    noisy = pos.copy()
    for r in ("left_hip", "right_hip", "left_shoulder", "right_shoulder"):
        noisy[:, J[r]] += rng.normal(scale=0.01, size=(n, 3))
    raw = _yaw_angles(body_frame(noisy, joints=J, smooth_frames=0)[1])
    smooth = _yaw_angles(body_frame(noisy, joints=J)[1])
    err_raw = np.std(raw - turn)
    err_smooth = np.std(smooth - turn)
    assert err_smooth < 0.6 * err_raw
    # without noise the smoothed frame follows the turn (no lag for a symmetric kernel)
    clean = _yaw_angles(body_frame(pos, joints=J)[1])
    np.testing.assert_allclose(clean[10:-10], turn[10:-10], atol=1e-9)


def test_smoothing_commutes_with_a_constant_yaw():
    rng = np.random.default_rng(1)
    pos = gesturing(80) + rng.normal(scale=0.01, size=(80, 55, 3))
    a = body_frame(pos, joints=J)[1]
    b = body_frame(rigid(pos, 2.2, [0.5, 0, 0.5]), joints=J)[1]
    np.testing.assert_allclose(b, yaw_matrix(2.2) @ a, atol=1e-12)


def test_to_body_frame_broadcasts_over_extra_axes():
    pos = rigid(gesturing(10), 0.8, [1, 0, 2])
    origin, rot = body_frame(pos, joints=J)
    many = to_body_frame(pos, origin, rot)
    one = to_body_frame(pos[:, 20], origin, rot)
    np.testing.assert_allclose(many[:, 20], one)
    two = to_body_frame(pos[:, None, [20, 21]], origin, rot)
    np.testing.assert_allclose(two[:, 0], many[:, [20, 21]])


def test_point_speed_of_constant_velocity_is_exact():
    fps = 30.0
    t = np.arange(50) / fps
    direction = np.array([0.6, 0.0, 0.8])
    x = t[:, None] * direction + [0.1, 1.0, 0.2]  # 1 m/s
    np.testing.assert_allclose(point_speeds(x, fps=fps), 1.0, atol=1e-9)
    np.testing.assert_allclose(point_speeds(x, fps=fps, smooth_s=0), 1.0, atol=1e-9)
    np.testing.assert_allclose(point_speeds(2.5 * x[:, None, :], fps=fps)[:, 0], 2.5, atol=1e-9)


def test_point_speed_on_a_circle_matches_the_analytic_speed():
    fps, radius, omega = 60.0, 0.3, 2 * np.pi * 0.5  # 0.94 m/s
    t = np.arange(600) / fps
    x = np.stack([radius * np.cos(omega * t), np.zeros_like(t), radius * np.sin(omega * t)], axis=1)
    sp = point_speeds(x, fps=fps)
    # Gaussian smoothing (sigma 0.05 s) shrinks a circle by exp(-(omega sigma)^2 / 2),
    # the central difference scales the speed by sin(omega / fps) / (omega / fps).
    h = omega / fps
    expect = radius * omega * np.exp(-0.5 * (omega * 0.05) ** 2) * np.sin(h) / h
    np.testing.assert_allclose(sp[30:-30], expect, rtol=1e-4)
    np.testing.assert_allclose(point_speeds(x, fps=fps, smooth_s=0)[30:-30], radius * omega * np.sin(h) / h, rtol=1e-9)
    assert point_speeds(x[:1], fps=fps).tolist() == [0.0]


def test_gaussian_smooth_keeps_lines_and_constants():
    x = np.linspace(-1, 3, 40)[:, None] * [1.0, -2.0]
    np.testing.assert_allclose(gaussian_smooth(x, sigma=3.0, mode="odd"), x, atol=1e-12)
    c = np.full((12, 2), 4.0)
    np.testing.assert_allclose(gaussian_smooth(c, sigma=5.0, mode="edge"), c, atol=1e-12)
    # the kernel reaches far past both ends of a short signal
    np.testing.assert_allclose(gaussian_smooth(x[:3], sigma=4.0, mode="odd"), x[:3], atol=1e-12)


def test_bad_inputs_are_named():
    pos = gesturing(5)
    with pytest.raises(ParameterError, match=r"positions: expected shape \(F, J, 3\)"):
        body_frame(pos[:, :, :2], joints=J)
    with pytest.raises(ParameterError, match="missing role.*'left_hip'"):
        body_frame(pos, joints={k: v for k, v in J.items() if k != "left_hip"})
    with pytest.raises(ParameterError, match=r"joints\['root'\]: expected an index in \[0, 55\); got 60"):
        body_frame(pos, joints={**J, "root": 60})
    bad = pos.copy()
    bad[3, 7, 1] = np.nan
    with pytest.raises(ParameterError, match="NaN/inf in 1 frame.*frame 3"):
        body_frame(bad, joints=J)
    with pytest.raises(ParameterError, match="smooth_frames: expected a number >= 0"):
        body_frame(pos, joints=J, smooth_frames=-1)
    with pytest.raises(ParameterError, match="fps: expected a positive"):
        point_speeds(pos, fps=0)
    with pytest.raises(ParameterError, match=r"origin: expected shape \(5, 3\)"):
        to_body_frame(pos, np.zeros((4, 3)), np.zeros((5, 3, 3)))
