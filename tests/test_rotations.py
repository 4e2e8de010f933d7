"""Quaternion ops against scipy.spatial.transform.Rotation as an independent reference."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gesturedb import rotations as rt
from gesturedb.errors import ParameterError

RNG = np.random.default_rng(1234)


def _wxyz(r: Rotation) -> np.ndarray:
    return np.roll(r.as_quat(), 1, axis=-1)  # scipy is x, y, z, w


def _xyzw(q: np.ndarray) -> np.ndarray:
    return np.roll(q, -1, axis=-1)


def _same_rotation(a, b, tol=1e-12):
    """Largest angle between two quaternion arrays, which may differ in sign."""
    return float(np.max(rt.angle_between(a, b))) <= tol


def _random_quats(n):
    return _wxyz(Rotation.random(n, random_state=RNG.integers(1 << 31)))


@pytest.mark.parametrize("order", rt.EULER_ORDERS)
def test_from_euler_matches_scipy_intrinsic(order):
    angles = RNG.uniform(-180, 180, (2000, 3))
    q = rt.from_euler(angles, order)
    ref = _wxyz(Rotation.from_euler(order, angles, degrees=True))  # upper case = intrinsic
    assert _same_rotation(q, ref, 1e-12)
    # BVH meaning: channels "Z X Y" give R = Rz @ Rx @ Ry on column vectors
    mats = [Rotation.from_euler(ax.lower(), angles[:, k:k + 1], degrees=True).as_matrix() for k, ax in enumerate(order)]
    np.testing.assert_allclose(rt.to_matrix(q), mats[0] @ mats[1] @ mats[2], atol=1e-12)


@pytest.mark.parametrize("order", rt.EULER_ORDERS)
def test_to_euler_matches_scipy_and_round_trips(order):
    q = _random_quats(2000)
    e = rt.to_euler(q, order)
    ref = Rotation.from_quat(_xyzw(q)).as_euler(order, degrees=True)
    # same conventions as scipy: outer angles in (-180, 180], middle in [-90, 90]
    np.testing.assert_allclose(e, ref, atol=1e-7)
    assert np.all(np.abs(e[:, 1]) <= 90.0)
    assert _same_rotation(rt.from_euler(e, order), q, 1e-12)


@pytest.mark.parametrize("order", rt.EULER_ORDERS)
def test_to_euler_gimbal_lock_still_round_trips(order):
    angles = RNG.uniform(-180, 180, (500, 3))
    angles[:, 1] = RNG.choice([-90.0, 90.0], 500)
    angles[:10, 1] += RNG.uniform(-1e-7, 1e-7, 10)  # just off the lock
    q = rt.from_euler(angles, order)
    e = rt.to_euler(q, order)
    assert np.all(np.isfinite(e))
    assert _same_rotation(rt.from_euler(e, order), q, 1e-7)


def test_euler_order_is_validated():
    with pytest.raises(ParameterError, match="Euler order: expected one of XYZ.*got 'XZX'"):
        rt.from_euler(np.zeros(3), "XZX")
    with pytest.raises(ParameterError, match="got 'XY'"):
        rt.to_euler(rt.identity(), "XY")
    assert rt.check_order("zxy") == "ZXY"


def test_multiply_inverse_apply_match_matrices():
    a, b = _random_quats(1000), _random_quats(1000)
    ab = rt.multiply(a, b)
    np.testing.assert_allclose(rt.to_matrix(ab), rt.to_matrix(a) @ rt.to_matrix(b), atol=1e-12)
    assert _same_rotation(ab, _wxyz(Rotation.from_quat(_xyzw(a)) * Rotation.from_quat(_xyzw(b))))
    assert _same_rotation(rt.multiply(a, rt.inverse(a)), rt.identity(1000))
    v = RNG.normal(size=(1000, 3))
    np.testing.assert_allclose(rt.apply(a, v), Rotation.from_quat(_xyzw(a)).apply(v), atol=1e-12)
    # broadcasting: one rotation, many vectors
    np.testing.assert_allclose(rt.apply(a[0], v), v @ rt.to_matrix(a[0]).T, atol=1e-12)


def test_inverse_of_non_unit_quaternion():
    q = _random_quats(10) * 3.0
    np.testing.assert_allclose(rt.multiply(q, rt.inverse(q)), rt.identity(10), atol=1e-12)


def test_axis_angle_matches_scipy_including_tiny_and_half_turns():
    rv = Rotation.random(1000, random_state=7).as_rotvec()
    rv[:5] *= 1e-14 / np.linalg.norm(rv[:5], axis=1, keepdims=True)  # tiny angles
    rv[5:10] *= np.pi / np.linalg.norm(rv[5:10], axis=1, keepdims=True)  # exactly pi
    rv[10] = 0.0
    q = rt.from_axis_angle(rv)
    assert _same_rotation(q, _wxyz(Rotation.from_rotvec(rv)))
    back = rt.to_axis_angle(q)
    np.testing.assert_allclose(back[10:], rv[10:], atol=1e-12)
    np.testing.assert_allclose(back[:5], rv[:5], rtol=1e-9, atol=0)
    # a half turn about a and about -a are the same rotation
    assert _same_rotation(rt.from_axis_angle(back[5:10]), q[5:10])
    # angle > pi comes back as the equivalent angle in [0, pi]
    big = np.array([[0.0, 0.0, 1.5 * np.pi]])
    np.testing.assert_allclose(rt.to_axis_angle(rt.from_axis_angle(big)), [[0.0, 0.0, -0.5 * np.pi]], atol=1e-12)


def test_matrix_round_trip_covers_every_branch():
    q = _random_quats(2000)
    # half turns about x, y, z and an axis in the xy plane exercise the non-w branches
    extra = rt.from_axis_angle(np.pi * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.6, 0.8, 0]]))
    q = np.concatenate([q, extra, rt.identity(1)])
    m = Rotation.from_quat(_xyzw(q)).as_matrix()
    np.testing.assert_allclose(rt.to_matrix(q), m, atol=1e-12)
    back = rt.from_matrix(m)
    assert _same_rotation(back, q)
    assert np.all(back[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-15)


def test_slerp_matches_scipy_and_takes_the_short_way():
    q0, q1 = _random_quats(200), _random_quats(200)
    t = np.linspace(0, 1, 11)
    for k in range(5):
        ref = _wxyz(Slerp([0, 1], Rotation.from_quat(_xyzw(np.stack([q0[k], q1[k]]))))(t))
        got = rt.slerp(q0[k], q1[k], t)
        assert _same_rotation(got, ref, 1e-12)
        # -q1 is the same rotation: same path
        assert _same_rotation(rt.slerp(q0[k], -q1[k], t), ref, 1e-12)
    # constant angular speed along the path
    tt = RNG.uniform(0, 1, 200)
    mid = rt.slerp(q0, q1, tt)
    np.testing.assert_allclose(rt.angle_between(q0, mid), tt * rt.angle_between(q0, q1), atol=1e-9)
    # identical endpoints (sin(theta) = 0) stay put without NaN
    same = rt.slerp(q0, q0, tt)
    assert _same_rotation(same, q0)


def test_make_continuous_removes_sign_flips_only():
    # a smooth rotation sequence with random sign flips on top
    angles = np.linspace(0, 6 * np.pi, 300)
    q = rt.from_axis_angle(np.stack([angles * 0.3, angles, 0 * angles], axis=1))
    flipped = q * RNG.choice([-1.0, 1.0], (300, 1))
    cont = rt.make_continuous(flipped[:, None, :], axis=0)[:, 0]
    assert _same_rotation(cont, q)
    assert np.all(np.sum(cont[1:] * cont[:-1], axis=-1) >= 0)
    np.testing.assert_array_equal(cont[0], flipped[0])
    with pytest.raises(ParameterError, match="axis must not be"):
        rt.make_continuous(q, axis=-1)


def test_shapes_are_checked():
    with pytest.raises(ParameterError, match=r"expected quaternions of shape \(\.\.\., 4\).*got shape \(5, 3\)"):
        rt.multiply(np.zeros((5, 3)), rt.identity(5))
    with pytest.raises(ParameterError, match=r"rotvec: expected vectors of shape \(\.\.\., 3\)"):
        rt.from_axis_angle(np.zeros((2, 4)))
    with pytest.raises(ParameterError, match="zero or non-finite quaternion at index"):
        rt.normalize(np.zeros((2, 4)))
    with pytest.raises(ParameterError, match=r"\(\.\.\., 3, 3\)"):
        rt.from_matrix(np.eye(4))
