"""Motion <-> the refiner's gesture channels.

Parent-relative (local) joint rotations, as Habibie et al. found more stable
than positions, in the continuous 6D form of Zhou et al. 2019 (the first two
columns of the rotation matrix): no sign ambiguity as with quaternions, no
wrap-around as with Euler angles. Only the *moving* joints are represented
(joints whose rotation varies anywhere in the database; a fixed joint such as
an eye or a joint the capture never moved would be wasted channels), and the
root is not: its position and rotation (where the speaker stands and faces)
stay those of the k-NN output, since placement is the assembly's job, not the
refiner's. The refined motion therefore exports to BVH on the database's own
skeleton unchanged.

Shapes: ``rotations (T, J, 4)`` unit quaternions w, x, y, z; channels
``(T, 6 * len(joints))`` float, ordered joint by joint, matrix column 0 then 1.
"""
from __future__ import annotations

import numpy as np

from gesturedb import rotations as R
from gesturedb.errors import ParameterError


def moving_joints(local_rotations: np.ndarray, *, tol_rad: float = 1e-3) -> np.ndarray:
    """Indices of the non-root joints whose rotation varies by more than ``tol_rad`` over the frames.

    Parameters
    ----------
    local_rotations : ndarray [shape=(F, J, 4)]

    Returns
    -------
    ndarray [shape=(Jm,)], int64, ascending, never containing the root (0).
    """
    q = np.asarray(local_rotations, dtype=np.float64)
    if q.ndim != 3 or q.shape[-1] != 4:
        raise ParameterError(f"local_rotations: expected (F, J, 4); got {q.shape}")
    # angle between every frame and the first frame, per joint: |<q0, qf>| = cos(angle / 2)
    dots = np.abs(np.einsum("fjc,jc->fj", q, q[0]))
    angle = 2 * np.arccos(np.clip(dots, 0.0, 1.0)).max(axis=0)
    idx = np.flatnonzero(angle > tol_rad)
    return idx[idx != 0].astype(np.int64)


def to_channels(rotations: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Local rotations (T, J, 4) -> 6D channels (T, 6 * len(joints)), float64."""
    m = R.to_matrix(np.asarray(rotations, dtype=np.float64)[:, joints])  # (T, Jm, 3, 3)
    six = np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)  # (T, Jm, 6)
    return six.reshape(six.shape[0], -1)


def from_channels(channels: np.ndarray, base_rotations: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """6D channels -> local rotations: ``base_rotations`` with the represented joints replaced.

    Any 6 numbers give a rotation: the two 3-vectors are orthonormalised
    (Gram-Schmidt), the third column is their cross product.

    Parameters
    ----------
    channels : ndarray [shape=(T, 6 * Jm)]
    base_rotations : ndarray [shape=(T, J, 4)]
        Rotations of the joints not represented (the root, fixed joints).
    joints : ndarray [shape=(Jm,)]
    """
    x = np.asarray(channels, dtype=np.float64)
    T = base_rotations.shape[0]
    if x.shape != (T, 6 * len(joints)):
        raise ParameterError(f"channels: expected ({T}, {6 * len(joints)}); got {x.shape}")
    # component-wise arithmetic on (T, Jm) planes: numpy's reductions over a last axis of length 3
    # (norm, sum) cost 6x more, and this runs on every refined synthesis
    a = np.moveaxis(x.reshape(T, len(joints), 6), -1, 0)  # (6, T, Jm)
    a, b = a[:3], a[3:]
    c0 = a / np.maximum(np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]), 1e-12)
    b = b - (c0[0] * b[0] + c0[1] * b[1] + c0[2] * b[2]) * c0
    c1 = b / np.maximum(np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]), 1e-12)
    c2 = np.stack([c0[1] * c1[2] - c0[2] * c1[1], c0[2] * c1[0] - c0[0] * c1[2], c0[0] * c1[1] - c0[1] * c1[0]])
    m = np.moveaxis(np.stack([c0, c1, c2], axis=-1), 0, -2)  # (T, Jm, 3 rows, 3 columns)
    out = np.array(base_rotations, dtype=np.float64, copy=True)
    q = R.from_matrix(m)
    # keep each joint's quaternion on the same hemisphere as the base, so nothing flips sign in time
    q *= np.where(np.einsum("...i,...i->...", q, out[:, joints])[..., None] < 0, -1.0, 1.0)
    out[:, joints] = q
    return out
