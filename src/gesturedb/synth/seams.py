"""Seams treated where they are: inertialization of the offset between two pieces of motion.

At a seam the output switches from one stretch of source motion to another. The old
stretch would have gone on (its ``lead_in``: its own recording's next frames); the new
one starts elsewhere. Instead of cross-fading the two, or low-passing the whole output,
the difference between them at the seam (an offset) is added to the new stretch and
decays to zero (inertialization, as games switch animations: Bollo, "Inertialization:
High-Performance Animation Transitions in Gears of War", GDC 2018; Holden's
Motion-Matching ``inertialize_*``):

    output(a + t) = new(a + t) + offset(t),   offset(t) = 0 for t >= decay_s

The offset at the seam and its first two time derivatives are those of the old motion's
natural continuation minus the new motion over the seam's first three frames, so the
output's position, velocity and acceleration run on from the old motion across the
seam. A quintic then takes the offset, its velocity and acceleration to zero at
``decay_s`` (Bollo's polynomial, with the acceleration matched instead of chosen), so
every frame ``decay_s`` or more after a seam is the new piece's frame exactly, and no
frequency of the source is filtered anywhere.

Rotations: the offset of a joint is the rotation vector of ``old * new^-1`` (applied on
the left, in the parent's frame); positions (the root) offset by subtraction.
A second seam inside a decay folds the remaining offset into the new one (the output
is continuous there too), so only one offset is active at a time.
"""
from __future__ import annotations

import math

import numpy as np

from gesturedb import rotations as R
from gesturedb.errors import ParameterError

__all__ = ["SEAM_DECAY_S", "LEAD_FRAMES", "quintic_offsets", "adaptive_decays", "seam_derivatives", "decay_frames",
           "check_decay_s", "extend_constant_velocity", "rotation_offsets", "continuous_rotation_vectors",
           "apply_rotation_offsets", "apply_quintic_rotation_offsets"]

#: Time (s) the offset at a seam takes to reach zero: one search step of the paper
#: (N = 8 frames at 15 fps), the time until the k-NN's next seam. Measured on the
#: held-out BEAT2 stretch (arm velocity power against the database's own at 0.5-2 /
#: 2-4 / 4-7 Hz): 0.2 s 0.93/3.2/24, 0.4 s 0.91/1.9/2.1, 0.53 s 0.84/1.1/1.2,
#: 0.8 s 0.63/0.55/1.05: a shorter decay puts the seam's correction into the stroke
#: band, a longer one damps the gestures themselves. Seconds, so a 30 fps database
#: decays over as much time as a 15 fps one.
SEAM_DECAY_S = 8.0 / 15.0
#: Frames of the old motion's continuation that define the offset's value, velocity
#: and acceleration at the seam (three samples: a second-order one-sided stencil).
LEAD_FRAMES = 3


def check_decay_s(decay_s) -> float:
    """``decay_s`` as a float >= 0 (0: no seam treatment, pieces back to back as in the paper)."""
    if isinstance(decay_s, (bool, np.bool_)) or not isinstance(decay_s, (int, float, np.integer, np.floating)):
        raise ParameterError(f"seam_decay_s: expected a number of seconds >= 0; got {decay_s!r}")
    v = float(decay_s)
    if not math.isfinite(v) or v < 0 or v > 60:
        raise ParameterError(f"seam_decay_s: expected a number of seconds from 0 to 60; got {decay_s!r}")
    return v


def decay_frames(decay_s: float, fps: float) -> int:
    """Frames after a seam that carry an offset: those with ``k / fps < decay_s``."""
    return int(math.ceil(decay_s * fps - 1e-9))


def quintic_offsets(x0: np.ndarray, v0: np.ndarray, a0: np.ndarray, decay_s: float, t: np.ndarray) -> np.ndarray:
    """The quintic from ``(x0, v0, a0)`` at ``t = 0`` to zero value, velocity and acceleration at ``decay_s``.

    Parameters
    ----------
    x0, v0, a0 : ndarray [shape=(...)]
        Offset, its velocity (per s) and acceleration (per s^2) at the seam.
    decay_s : float > 0, or ndarray broadcastable to ``x0``
        One decay for all, or one per value (per joint).
    t : ndarray [shape=(n,)], seconds
        Times after the seam.

    Returns
    -------
    ndarray [shape=(n, ...)]
        Exactly 0 where ``t >= decay_s``.
    """
    x0, v0, a0 = (np.asarray(v, dtype=np.float64) for v in (x0, v0, a0))
    D = np.asarray(decay_s, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape((-1,) + (1,) * x0.ndim)
    A = -(a0 * D * D + 6 * v0 * D + 12 * x0) / (2 * D ** 5)
    B = (3 * a0 * D * D + 16 * v0 * D + 30 * x0) / (2 * D ** 4)
    C = -(3 * a0 * D * D + 12 * v0 * D + 20 * x0) / (2 * D ** 3)
    out = ((((A * t + B) * t + C) * t + 0.5 * a0) * t + v0) * t + x0
    return np.where(t < D, out, 0.0)


def adaptive_decays(x0: np.ndarray, v0: np.ndarray, accel_ref: np.ndarray, decay_s: float) -> np.ndarray:
    """Per-value decay (s): at least ``decay_s``, longer where removing the offset faster would
    accelerate the motion more than its own typical acceleration ``accel_ref``.

    The quintic that takes an offset ``x0`` (velocity ``v0``) to rest over ``D`` peaks at about
    ``5.8 |x0| / D^2`` and ``1.9 |v0| / D`` of added acceleration (exactly, for each alone with
    no initial acceleration: 10 / sqrt(3) and 15 / 8). ``D`` is the shortest decay that keeps both
    within ``accel_ref``, so a seam between two very different windows is spread over as long as
    the speaker would take to make that change, and a small one stays short.

    x0, v0 : ndarray [shape=(..., 3)]
        Rotation vectors or positions: their norms (the offset's size, not its components) decide.
    accel_ref : ndarray broadcastable to the norms, same unit per s^2
    """
    x, v = R.norm3(x0), R.norm3(v0)
    a = np.maximum(np.asarray(accel_ref, dtype=np.float64), 1e-12)[..., None]
    d = np.maximum.reduce([np.full_like(x, float(decay_s)), np.sqrt(10 / np.sqrt(3) * x / a), 15 / 8 * v / a])
    return d


def seam_derivatives(d: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Value, velocity and acceleration at the first of three samples ``d[0], d[1], d[2]`` (frames apart).

    Second-order one-sided differences: exact for a quadratic.
    """
    d0, d1, d2 = d[0], d[1], d[2]
    v0 = (-3 * d0 + 4 * d1 - d2) * (fps / 2)
    a0 = (d0 - 2 * d1 + d2) * fps * fps
    return d0, v0, a0


def extend_constant_velocity(rot: np.ndarray, root: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Extend a sequence (at least 2 frames) by ``n`` frames at its last frame's velocity.

    Used where an old piece has no continuation of its own (its recording ends at the
    seam): the old motion is then taken to go on as it was moving.

    rot : ndarray [shape=(m, J, 4)], root : ndarray [shape=(m, 3)]
    Returns the ``n`` new frames: ``(n, J, 4)``, ``(n, 3)``.
    """
    step_q = R.multiply(rot[-1], R.inverse(rot[-2]))  # (J, 4): the last frame's rotation per frame
    step_v = R.to_axis_angle(step_q)
    k = np.arange(1, n + 1, dtype=np.float64)[:, None, None]
    q = R.multiply(R.from_axis_angle(step_v[None] * k), np.broadcast_to(rot[-1], (n,) + rot.shape[1:]))
    p = root[-1] + (root[-1] - root[-2]) * k[:, :, 0]
    return q, p


def rotation_offsets(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of ``old * new^-1``: what takes the new rotation onto the old one."""
    return R.to_axis_angle(R.multiply(old, R.inverse(new)))


def continuous_rotation_vectors(d: np.ndarray) -> np.ndarray:
    """Rotation vectors ``d`` (n, ..., 3) of a sequence, each on the branch nearest the one before it.

    A rotation of angle ``a`` about ``u`` is also the rotation vector ``(a - 2 pi) u``; ``to_axis_angle``
    always gives the first (angle in [0, pi]), so a sequence that passes through pi jumps by about
    2 pi there. Sample ``k`` takes whichever of its two vectors is nearer sample ``k - 1``, so the
    differences that give a seam's velocity and acceleration are those of the motion, not of the
    branch. (Before 2026-11-28 a sample was moved to the other branch when it pointed against the
    *first* one and turned more than pi / 2: a sequence turning fast away from a small first offset,
    0.47, 1.26 and 2.26 rad, had its last sample moved to -4.0 rad, a velocity of 64 rad/s instead of
    23, and the decaying offset spun the elbow by up to 179 degrees a frame for two seconds.)
    """
    d = np.array(d, dtype=np.float64)
    for k in range(1, d.shape[0]):
        ang = R.norm3(d[k])
        other = d[k] - 2 * np.pi * d[k] / np.maximum(ang, 1e-12)
        nearer = R.norm3(other - d[k - 1]) < R.norm3(d[k] - d[k - 1])
        d[k] = np.where(nearer, other, d[k])
    return d


def apply_rotation_offsets(offsets: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``exp(offsets) * q`` (offsets (..., 3) rad, q (..., 4))."""
    return R.multiply(R.from_axis_angle(offsets), q)


def apply_quintic_rotation_offsets(x0: np.ndarray, v0: np.ndarray, a0: np.ndarray, decay_s, t: np.ndarray,
                                   q: np.ndarray) -> np.ndarray:
    """``apply_rotation_offsets(quintic_offsets(x0, v0, a0, decay_s, t), q)``: a seam's offset on every joint.

    Parameters
    ----------
    x0, v0, a0 : ndarray [shape=(J, 3)]
        Each joint's rotation-vector offset (rad), its velocity (rad/s) and acceleration (rad/s^2)
        at the seam.
    decay_s : float > 0, or ndarray [shape=(J,) or (J, 1)], seconds
        One decay for all joints, or one per joint.
    t : ndarray [shape=(n,)], seconds
        Times after the seam.
    q : ndarray [shape=(n, J, 4)]
        Local rotations.

    Returns
    -------
    ndarray [shape=(n, J, 4)]
        Equal to the numpy composition to rounding (tests/test_placement.py), and per frame: the same
        bits whatever the frames' split into calls (a live stream's and the offline synthesis's).
    """
    # in C++ (csrc/seams.cpp): the numpy composition ran some thirty small array operations per call,
    # twice a live step (about 1 ms of its apply in interpreter overhead)
    import gesturedb._core as _core

    q = np.ascontiguousarray(q, dtype=np.float64)
    if q.ndim != 3 or q.shape[2] != 4:
        raise ParameterError(f"q: expected (n, J, 4) quaternions; got shape {q.shape}")
    n, J = q.shape[:2]
    x0, v0, a0 = (np.ascontiguousarray(v, dtype=np.float64) for v in (x0, v0, a0))
    for name, v in (("x0", x0), ("v0", v0), ("a0", a0)):
        if v.shape != (J, 3):
            raise ParameterError(f"{name}: expected ({J}, 3); got {v.shape}")
    D = np.asarray(decay_s, dtype=np.float64)
    if D.shape not in ((), (J,), (J, 1)):
        raise ParameterError(f"decay_s: expected a number, ({J},) or ({J}, 1); got shape {D.shape}")
    D = np.ascontiguousarray(np.broadcast_to(D.reshape(-1), (J,)))  # one decay a joint
    t = np.ascontiguousarray(t, dtype=np.float64).reshape(-1)
    if t.shape[0] != n:
        raise ParameterError(f"t: expected ({n},) times, one per frame of q; got {t.shape}")
    return _core.apply_quintic_rotation_offsets(x0, v0, a0, D, t, q)
