"""Unit quaternions, vectorised over any leading shape.

Every quaternion array is ``(..., 4)`` float64 in **w, x, y, z** order. Products
follow the Hamilton convention and act on column vectors, so
``multiply(a, b)`` is the rotation "first ``b``, then ``a``" and
``to_matrix(multiply(a, b)) == to_matrix(a) @ to_matrix(b)``.

Euler angles follow BVH: an order such as ``"ZXY"`` lists the rotation channels
as they appear in the file, angles ``(..., 3)`` in degrees in that same order,
and the rotation is ``R = Rz(a0) @ Rx(a1) @ Ry(a2)`` applied to column vectors
(intrinsic rotations in the listed order; scipy spells this
``Rotation.from_euler("ZXY", a, degrees=True)`` with upper-case letters).
Only the six Tait-Bryan orders (each axis once) exist in BVH.
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError

__all__ = [
    "EULER_ORDERS",
    "angle_between",
    "apply",
    "check_order",
    "from_axis_angle",
    "from_euler",
    "from_matrix",
    "identity",
    "inverse",
    "make_continuous",
    "multiply",
    "normalize",
    "slerp",
    "to_axis_angle",
    "to_euler",
    "to_matrix",
]

EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
_AXIS = {"X": 0, "Y": 1, "Z": 2}


def _quat(q, name: str = "q") -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.ndim == 0 or q.shape[-1] != 4:
        raise ParameterError(f"{name}: expected quaternions of shape (..., 4) (w, x, y, z); got shape {q.shape}")
    return q


def _vec3(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    if v.ndim == 0 or v.shape[-1] != 3:
        raise ParameterError(f"{name}: expected vectors of shape (..., 3); got shape {v.shape}")
    return v


def check_order(order: str) -> str:
    """Return a BVH Euler order in upper case, or raise `ParameterError`.

    Parameters
    ----------
    order : str
        Three distinct axis letters, e.g. ``"ZXY"`` or ``"xyz"``.

    Returns
    -------
    str
        The order in upper case, one of `EULER_ORDERS`.
    """
    up = order.upper() if isinstance(order, str) else None
    if up not in EULER_ORDERS:
        raise ParameterError(f"Euler order: expected one of {', '.join(EULER_ORDERS)}; got {order!r}")
    return up


def identity(shape=()) -> np.ndarray:
    """Identity quaternions.

    Parameters
    ----------
    shape : int or tuple of int
        Leading shape.

    Returns
    -------
    ndarray [shape=(*shape, 4)]
        ``(1, 0, 0, 0)`` everywhere.
    """
    shape = (shape,) if np.isscalar(shape) else tuple(shape)
    q = np.zeros(shape + (4,), dtype=np.float64)
    q[..., 0] = 1.0
    return q


def normalize(q) -> np.ndarray:
    """Scale quaternions to unit norm.

    Parameters
    ----------
    q : array_like [shape=(..., 4)]

    Returns
    -------
    ndarray [shape=(..., 4)]

    Raises
    ------
    ParameterError
        If a quaternion has (near) zero norm, which has no direction to keep.
    """
    q = _quat(q)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~(n > 1e-12)):
        bad = np.argwhere(~(n[..., 0] > 1e-12))[0]
        raise ParameterError(f"q: cannot normalise a zero or non-finite quaternion at index {tuple(bad.tolist())}")
    return q / n


def multiply(a, b) -> np.ndarray:
    """Hamilton product ``a * b`` (rotate by ``b`` first, then by ``a``).

    Parameters
    ----------
    a, b : array_like [shape=(..., 4)]
        Broadcastable quaternion arrays.

    Returns
    -------
    ndarray [shape=(..., 4)]
    """
    a = _quat(a, "a")
    b = _quat(b, "b")
    # components by indexing and the result written in place: np.moveaxis and np.stack cost more
    # than the arithmetic on the small arrays of a live step (the same operations, the same bits)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    out = np.empty(a.shape if a.shape == b.shape else np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = aw * bw - ax * bx - ay * by - az * bz
    out[..., 1] = aw * bx + ax * bw + ay * bz - az * by
    out[..., 2] = aw * by - ax * bz + ay * bw + az * bx
    out[..., 3] = aw * bz + ax * by - ay * bx + az * bw
    return out


def inverse(q) -> np.ndarray:
    """Inverse rotation (the conjugate divided by the squared norm).

    Parameters
    ----------
    q : array_like [shape=(..., 4)]

    Returns
    -------
    ndarray [shape=(..., 4)]
    """
    q = _quat(q)
    conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    return conj / np.sum(q * q, axis=-1, keepdims=True)


def apply(q, v) -> np.ndarray:
    """Rotate vectors by unit quaternions.

    Parameters
    ----------
    q : array_like [shape=(..., 4)]
        Unit quaternions.
    v : array_like [shape=(..., 3)]
        Vectors, broadcastable against ``q[..., :3]``.

    Returns
    -------
    ndarray [shape=(..., 3)]
        ``to_matrix(q) @ v``.
    """
    q = _quat(q)
    v = _vec3(v, "v")
    w = q[..., :1]
    u = q[..., 1:]
    # v + 2w (u x v) + 2 u x (u x v): two cross products instead of a 3x3 matrix per element
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def _cross(a, b):
    """``np.cross`` over the last axis (length 3) without its axis bookkeeping, which cost the synthesis
    more than the arithmetic on its many small arrays (0.03 ms per call, 1600 calls a minute of output)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(a.shape if a.shape == b.shape else np.broadcast_shapes(a.shape, b.shape),
                   dtype=np.result_type(a, b))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def from_axis_angle(rotvec) -> np.ndarray:
    """Quaternions from rotation vectors (axis times angle).

    Parameters
    ----------
    rotvec : array_like [shape=(..., 3)], radians
        Unit axis scaled by the rotation angle, as in SMPL-X ``poses``.

    Returns
    -------
    ndarray [shape=(..., 4)]
        Unit quaternions with ``w >= 0`` for angles up to pi.
    """
    rotvec = _vec3(rotvec, "rotvec")
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half) / angle written with np.sinc stays exact as the angle goes to 0
    scale = 0.5 * np.sinc(half / np.pi)
    return np.concatenate([np.cos(half), rotvec * scale], axis=-1)


def to_axis_angle(q) -> np.ndarray:
    """Rotation vectors (axis times angle, angle in [0, pi]) from quaternions.

    Parameters
    ----------
    q : array_like [shape=(..., 4)]
        Unit quaternions.

    Returns
    -------
    ndarray [shape=(..., 3)], radians
    """
    q = _quat(q)
    # q and -q are the same rotation; w >= 0 picks the angle in [0, pi]
    q = np.where(q[..., :1] < 0.0, -q, q)
    w = q[..., :1]
    u = q[..., 1:]
    s = np.linalg.norm(u, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, w)
    small = s < 1e-12
    # angle / s -> 2 / w as s -> 0 (w is then ~1)
    factor = np.where(small, 2.0 / np.where(small, w, 1.0), angle / np.where(small, 1.0, s))
    return u * factor


def to_matrix(q) -> np.ndarray:
    """Rotation matrices acting on column vectors.

    Parameters
    ----------
    q : array_like [shape=(..., 4)]
        Quaternions; normalised first, so slightly off-unit input is fine.

    Returns
    -------
    ndarray [shape=(..., 3, 3)]
    """
    q = _quat(q)
    q = q / _norm4(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    m = np.stack(
        [
            1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
        ],
        axis=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def from_matrix(m) -> np.ndarray:
    """Quaternions from rotation matrices (Shepperd's method).

    Parameters
    ----------
    m : array_like [shape=(..., 3, 3)]
        Proper rotation matrices acting on column vectors.

    Returns
    -------
    ndarray [shape=(..., 4)]
        Unit quaternions with ``w >= 0``.
    """
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-2:] != (3, 3):
        raise ParameterError(f"m: expected rotation matrices of shape (..., 3, 3); got shape {m.shape}")
    shape = m.shape[:-2]
    # the nine entries as flat arrays: gathering one branch's elements from them is cheaper than
    # gathering 3x3 blocks (from_matrix was half the refiner's cost on a minute of output)
    a = m.reshape(-1, 9).T
    m00, m11, m22 = a[0], a[4], a[8]
    # Each branch divides by the largest of |w|, |x|, |y|, |z|; picking the largest
    # diagonal term per element keeps the division well conditioned everywhere.
    case = np.argmax(np.stack([m00 + m11 + m22, m00, m11, m22], axis=-1), axis=-1)
    q = np.empty((a.shape[1], 4))
    for c in range(4):
        idx = np.flatnonzero(case == c)
        if idx.size == 0:
            continue
        if idx.size == case.size:
            a00, a01, a02, a10, a11, a12, a20, a21, a22 = a
        else:
            a00, a01, a02, a10, a11, a12, a20, a21, a22 = a[:, idx]
        if c == 0:
            t = np.sqrt(np.maximum(1 + a00 + a11 + a22, 0.0))
            v = (0.5 * t, (a21 - a12) / (2 * t), (a02 - a20) / (2 * t), (a10 - a01) / (2 * t))
        elif c == 1:
            t = np.sqrt(np.maximum(1 + a00 - a11 - a22, 0.0))
            v = ((a21 - a12) / (2 * t), 0.5 * t, (a01 + a10) / (2 * t), (a02 + a20) / (2 * t))
        elif c == 2:
            t = np.sqrt(np.maximum(1 - a00 + a11 - a22, 0.0))
            v = ((a02 - a20) / (2 * t), (a01 + a10) / (2 * t), 0.5 * t, (a12 + a21) / (2 * t))
        else:
            t = np.sqrt(np.maximum(1 - a00 - a11 + a22, 0.0))
            v = ((a10 - a01) / (2 * t), (a02 + a20) / (2 * t), (a12 + a21) / (2 * t), 0.5 * t)
        for k in range(4):
            q[idx, k] = v[k]
    q = q.reshape(shape + (4,))
    q = q / _norm4(q)
    return np.where(q[..., :1] < 0.0, -q, q)


def norm3(v) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1, keepdims=True)`` of vectors (..., 3), bit for bit (numpy sums a last axis
    this short in order), without numpy's reduction machinery: a live step takes a dozen such norms of a few
    rotation vectors each, where the call cost ten times the arithmetic."""
    v = np.asarray(v, dtype=np.float64)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.sqrt(x * x + y * y + z * z)[..., None]


def _norm4(q):
    """``np.linalg.norm(q, axis=-1, keepdims=True)`` for (..., 4), bit for bit (the same sum order), without
    numpy's slow reduction over a short last axis."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.sqrt(w * w + x * x + y * y + z * z)[..., None]


def _axis_quat(axis: int, angle_rad: np.ndarray) -> np.ndarray:
    q = np.zeros(angle_rad.shape + (4,), dtype=np.float64)
    q[..., 0] = np.cos(0.5 * angle_rad)
    q[..., 1 + axis] = np.sin(0.5 * angle_rad)
    return q


def from_euler(angles_deg, order: str) -> np.ndarray:
    """Quaternions from BVH Euler angles.

    Parameters
    ----------
    angles_deg : array_like [shape=(..., 3)], degrees
        Angles in the order the channels are listed.
    order : str
        One of `EULER_ORDERS`, e.g. ``"ZXY"`` for channels
        ``Zrotation Xrotation Yrotation``: ``R = Rz(a0) @ Rx(a1) @ Ry(a2)``.

    Returns
    -------
    ndarray [shape=(..., 4)]
    """
    order = check_order(order)
    a = np.deg2rad(_vec3(angles_deg, "angles_deg"))
    q = _axis_quat(_AXIS[order[0]], a[..., 0])
    q = multiply(q, _axis_quat(_AXIS[order[1]], a[..., 1]))
    return multiply(q, _axis_quat(_AXIS[order[2]], a[..., 2]))


def to_euler(q, order: str) -> np.ndarray:
    """BVH Euler angles from quaternions.

    Parameters
    ----------
    q : array_like [shape=(..., 4)]
        Unit quaternions.
    order : str
        One of `EULER_ORDERS`; see `from_euler`.

    Returns
    -------
    ndarray [shape=(..., 3)], degrees
        First and last angle in (-180, 180], middle angle in [-90, 90], so that
        ``from_euler(to_euler(q, o), o)`` is ``q`` up to sign. In gimbal lock
        (middle angle at +-90) the last angle is set to 0.
    """
    order = check_order(order)
    i, j, k = (_AXIS[c] for c in order)
    # +1 for the cyclic orders XYZ, YZX, ZXY; -1 for the others
    s = 1.0 if (j - i) % 3 == 1 else -1.0
    m = to_matrix(q)
    # For R = Ri(a) Rj(b) Rk(c): R[i,k] = s sin b, R[j,k] = -s sin a cos b,
    # R[k,k] = cos a cos b, R[i,j] = -s cos b sin c, R[i,i] = cos b cos c.
    cos_b = np.hypot(m[..., i, i], m[..., i, j])
    b = np.arctan2(s * m[..., i, k], cos_b)
    a = np.arctan2(-s * m[..., j, k], m[..., k, k])
    c = np.arctan2(-s * m[..., i, j], m[..., i, i])
    # Gimbal lock: only a -/+ c is defined; with c = 0, column j of R is Ri(a) e_j.
    lock = cos_b < 1e-7
    if np.any(lock):
        a_lock = np.arctan2(s * m[..., k, j], m[..., j, j])
        a = np.where(lock, a_lock, a)
        c = np.where(lock, 0.0, c)
    return np.rad2deg(np.stack([a, b, c], axis=-1))


def slerp(q0, q1, t) -> np.ndarray:
    """Spherical linear interpolation along the shorter arc.

    Parameters
    ----------
    q0, q1 : array_like [shape=(..., 4)]
        Unit quaternions at ``t = 0`` and ``t = 1``.
    t : float or array_like [shape=(...)]
        Interpolation parameter, broadcastable against the leading shape.

    Returns
    -------
    ndarray [shape=(..., 4)]
        Unit quaternions.
    """
    q0 = _quat(q0, "q0")
    q1 = _quat(q1, "q1")
    t = np.asarray(t, dtype=np.float64)[..., None]
    d = np.sum(q0 * q1, axis=-1, keepdims=True)
    # q and -q are one rotation: flipping q1 onto q0's hemisphere takes the short way
    q1 = np.where(d < 0.0, -q1, q1)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def make_continuous(q, axis: int = 0) -> np.ndarray:
    """Flip signs so neighbouring quaternions along ``axis`` lie in one hemisphere.

    ``q`` and ``-q`` are the same rotation; filters, blends and finite
    differences along time need consecutive samples with a non-negative dot
    product.

    Parameters
    ----------
    q : array_like [shape=(..., 4)]
        Quaternions, e.g. ``(F, J, 4)`` with time on ``axis=0``.
    axis : int
        The time axis (not the last one).

    Returns
    -------
    ndarray, same shape as ``q``
        The first sample is unchanged.
    """
    q = _quat(q)
    axis = axis % q.ndim
    if axis == q.ndim - 1:
        raise ParameterError("make_continuous: axis must not be the quaternion axis (-1)")
    qm = np.moveaxis(q, axis, 0)
    if qm.shape[0] < 2:
        return q.copy()
    d = np.sum(qm[1:] * qm[:-1], axis=-1)
    flips = np.where(d < 0.0, -1.0, 1.0)
    sign = np.concatenate([np.ones_like(flips[:1]), np.cumprod(flips, axis=0)], axis=0)
    return np.moveaxis(qm * sign[..., None], 0, axis)


def angle_between(a, b) -> np.ndarray:
    """Angle of the rotation taking ``b`` to ``a``.

    Parameters
    ----------
    a, b : array_like [shape=(..., 4)]
        Unit quaternions.

    Returns
    -------
    ndarray [shape=(...)], radians in [0, pi]
        0 for the same rotation, whatever the signs of ``a`` and ``b``.
    """
    a = _quat(a, "a")
    b = _quat(b, "b")
    # atan2 of the relative rotation stays accurate near 0, where arccos(dot) does not
    r = multiply(inverse(b), a)
    return 2.0 * np.arctan2(np.linalg.norm(r[..., 1:], axis=-1), np.abs(r[..., 0]))
