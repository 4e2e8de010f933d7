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


# -- the same conversions on torch tensors, for refining ---------------------------
# Refining a minute of output converts 50k rotations each way; numpy's float64
# pipeline above (matrices, then Shepperd's branches by gathers) took 9 of the
# refiner's 16 ms, more than the generator itself. These do the same arithmetic
# component-wise on (Jm, T) float32 planes laid out as the generator reads and
# writes them (channels first), so nothing is transposed or gathered. Float32 is
# the generator's own precision; they agree with the numpy functions to ~1e-6
# (tested). Training keeps to_channels (its windows are made once); from_channels is
# the tests' oracle for from_channels_torch.

def to_channels_torch(rotations: np.ndarray, joints: np.ndarray):
    """Local rotations (T, J, 4) -> the generator's input, a (1, 6 * Jm, T) float32 tensor.

    Same channels as :func:`to_channels` (transposed), in float32.
    """
    import torch

    q = torch.from_numpy(np.ascontiguousarray(np.asarray(rotations)[:, joints].transpose(2, 1, 0), dtype=np.float32))
    q = q / torch.sqrt((q * q).sum(0))  # (4, Jm, T), normalised as R.to_matrix does
    w, x, y, z = q
    out = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y),   # column 0
                       2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)],  # column 1
                      dim=1)  # (Jm, 6, T)
    return out.reshape(1, -1, q.shape[-1])


def from_channels_torch(channels, base_rotations: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """The generator's output (6 * Jm, T) tensor -> local rotations (T, J, 4) float64.

    As :func:`from_channels` (Gram-Schmidt, Shepperd's method, ``w >= 0`` then the
    base's hemisphere), in float32; every branch of Shepperd's method is computed
    for every element and the well-conditioned one selected (four cheap planes
    instead of gathers).
    """
    import torch

    T = base_rotations.shape[0]
    if tuple(channels.shape) != (6 * len(joints), T):
        raise ParameterError(f"channels: expected ({6 * len(joints)}, {T}); got {tuple(channels.shape)}")
    # six contiguous (Jm, T) planes first: the generator's output is a cropped view, and
    # arithmetic on strided planes runs several times slower
    a0, a1, a2, b0, b1, b2 = channels.reshape(len(joints), 6, T).transpose(0, 1).contiguous()
    n = torch.clamp(torch.sqrt(a0 * a0 + a1 * a1 + a2 * a2), min=1e-12)
    a0, a1, a2 = a0 / n, a1 / n, a2 / n
    d = a0 * b0 + a1 * b1 + a2 * b2
    b0, b1, b2 = b0 - d * a0, b1 - d * a1, b2 - d * a2
    n = torch.clamp(torch.sqrt(b0 * b0 + b1 * b1 + b2 * b2), min=1e-12)
    b0, b1, b2 = b0 / n, b1 / n, b2 / n
    c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    # matrix m[row][col]: column 0 = a, column 1 = b, column 2 = c
    m00, m10, m20, m01, m11, m21, m02, m12, m22 = a0, a1, a2, b0, b1, b2, c0, c1, c2
    # Shepperd's case per element (numpy's argmax over [trace, m00, m11, m22], first on ties)
    # as four 0/1 planes: selecting by multiply-add is several times faster than torch.where
    # or argmax across a stacked axis at this size
    tr = m00 + m11 + m22
    e0 = tr >= torch.maximum(torch.maximum(m00, m11), m22)
    e1 = ~e0 & (m00 >= torch.maximum(m11, m22))
    e2 = ~e0 & ~e1 & (m11 >= m22)
    e3 = ~(e0 | e1 | e2)
    e0, e1, e2, e3 = (e.to(m00.dtype) for e in (e0, e1, e2, e3))
    t = 1 + e0 * tr + e1 * (m00 - m11 - m22) + e2 * (m11 - m00 - m22) + e3 * (m22 - m00 - m11)
    t = torch.sqrt(torch.clamp(t, min=0.0))
    s = 0.5 / torch.clamp(t, min=1e-12)
    h = 0.5 * t
    d21, d02, d10 = m21 - m12, m02 - m20, m10 - m01
    p01, p02, p12 = m01 + m10, m02 + m20, m12 + m21
    w = e0 * h + (e1 * d21 + e2 * d02 + e3 * d10) * s
    x = e1 * h + (e0 * d21 + e2 * p01 + e3 * p02) * s
    y = e2 * h + (e0 * d02 + e1 * p01 + e3 * p12) * s
    z = e3 * h + (e0 * d10 + e1 * p02 + e2 * p12) * s
    out = np.array(base_rotations, dtype=np.float64, copy=True)
    bw, bx, by, bz = torch.from_numpy(np.ascontiguousarray(out[:, joints].transpose(2, 1, 0), dtype=np.float32))
    # unit length, then the base's hemisphere (so nothing flips sign in time): one factor
    n = torch.sqrt(w * w + x * x + y * y + z * z)
    far = (w * bw + x * bx + y * by + z * bz < 0).to(n.dtype)
    n = n - 2 * far * n
    q = torch.stack([w / n, x / n, y / n, z / n], dim=-1)  # (Jm, T, 4)
    out[:, joints] = q.permute(1, 0, 2).double().numpy()
    return out
