"""The speaker's body frame: origin at the root joint, yaw-only rotation.

Every per-frame feature (pose, controls, style, rhythm) is measured in this frame
so that it does not change when the speaker stands somewhere else in the capture
volume or turns to face another direction.

Axes of the body frame (the columns of ``rotation``): x = the speaker's left,
y = world up, z = the speaker's forward (facing) direction. In the rest pose
(``+x`` the speaker's left, ``+z`` forward, ``y`` up) the body frame coincides
with the world axes. The frame turns only about the vertical axis: a lean or a
bow does not tilt it, so heights in the body frame stay heights above the root.

The helpers at the bottom (argument checks, Gaussian smoothing, speeds) are
shared by the other feature modules.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.roles import BODY_ROLES

__all__ = [
    "BODY_ROLES",
    "FACING_SMOOTH_FRAMES",
    "FACING_SMOOTH_S",
    "SPEED_SMOOTH_S",
    "body_frame",
    "to_body_frame",
    "point_speeds",
]

#: Default Gaussian sigma (frames) of the facing-direction smoothing in :func:`body_frame`.
FACING_SMOOTH_FRAMES: float = 2.0
#: The same sigma in seconds, what :func:`body_frame` uses given the frame rate (``FACING_SMOOTH_S * fps``
#: frames: 2.0 exactly at the paper's 15 fps, 4.0 at 30 fps).
FACING_SMOOTH_S: float = 2.0 / 15.0

#: Default Gaussian sigma (seconds) applied to positions before differentiating them
#: into speeds (:func:`point_speeds`): 1.5 frames at 30 fps.
SPEED_SMOOTH_S: float = 0.05

# Below this horizontal length (metres) the left-right axis of a frame gives no
# usable facing direction (hips and shoulders collapsed, or the axis vertical).
_DEGENERATE_M = 1e-6


def body_frame(
    positions: np.ndarray,
    *,
    joints: Mapping[str, int],
    fps: float | None = None,
    smooth_frames: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Origin and yaw rotation of the speaker's body frame in every frame.

    The left-right axis of a frame is ``(left_hip - right_hip) + (left_shoulder -
    right_shoulder)``; hips and shoulders are summed so that a twist of the upper
    body moves the frame half-way. The facing direction is the horizontal
    direction perpendicular to that axis and to world up, oriented so that it is
    ``+z`` when the left-right axis is ``+x`` (the rest pose).

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        World joint positions, y up.
    joints : mapping of str to int
        Joint index of each role in :data:`BODY_ROLES` (other keys are ignored).
    fps : float > 0 or None, keyword-only
        Frame rate (Hz): the default smoothing is then :data:`FACING_SMOOTH_S` in frames, the
        same time at any rate (2 frames at 15 fps); without it, :data:`FACING_SMOOTH_FRAMES`.
    smooth_frames : float >= 0 or None, keyword-only
        Gaussian sigma, in frames, applied to the unit facing vectors before they
        are renormalised, so that marker noise on the hips and shoulders does not
        make the whole frame (and with it every hand feature) jitter. The default
        of 2/15 s removes frame-to-frame noise but follows any real turn of the body
        within a few frames. Smoothing is linear, so a constant rotation of the whole
        recording about the vertical axis commutes with it exactly. 0 disables it.

    Returns
    -------
    origin : ndarray [shape=(F, 3)], float64, metres
        World position of the ``root`` joint.
    rotation : ndarray [shape=(F, 3, 3)], float64
        Columns are the body axes (left, up, forward) in world coordinates, so
        ``world = origin + rotation @ local`` and ``local = rotation.T @ (world -
        origin)``. Always a proper rotation about world y.

    Notes
    -----
    Degenerate frames, where the horizontal part of the left-right axis is
    shorter than 1e-6 m, take the facing direction of the nearest usable frame
    (the earlier one on a tie). If no frame of the recording is usable the body
    frame faces ``+z``. Where smoothing averages opposite directions to (almost)
    nothing, the unsmoothed direction of that frame is kept.
    """
    positions = check_positions(positions)
    idx = check_joints(joints, BODY_ROLES, n_joints=positions.shape[1])
    if smooth_frames is None:
        smooth_frames = FACING_SMOOTH_FRAMES if fps is None else FACING_SMOOTH_S * check_fps(fps)
    smooth_frames = _check_nonnegative("smooth_frames", smooth_frames)

    origin = positions[:, idx["root"], :].copy()
    across = (positions[:, idx["left_hip"]] - positions[:, idx["right_hip"]]) + (
        positions[:, idx["left_shoulder"]] - positions[:, idx["right_shoulder"]]
    )
    # forward = across x up, restricted to the horizontal plane: (-a_z, 0, a_x).
    fwd = np.stack([-across[:, 2], across[:, 0]], axis=1)  # (F, 2): world x and z components
    norm = np.hypot(fwd[:, 0], fwd[:, 1])
    valid = norm > _DEGENERATE_M
    fwd = np.divide(fwd, norm[:, None], out=np.zeros_like(fwd), where=valid[:, None])
    fwd = _fill_from_nearest(fwd, valid, default=np.array([0.0, 1.0]))

    if smooth_frames > 0 and len(fwd) > 1:
        sm = gaussian_smooth(fwd, sigma=smooth_frames, mode="edge")
        sm_norm = np.hypot(sm[:, 0], sm[:, 1])
        ok = sm_norm > 1e-3
        fwd = np.where(ok[:, None], sm / np.where(ok, sm_norm, 1.0)[:, None], fwd)

    fx, fz = fwd[:, 0], fwd[:, 1]
    rotation = np.zeros((len(fwd), 3, 3))
    # left axis = up x forward = (f_z, 0, -f_x); up = (0, 1, 0); forward = (f_x, 0, f_z)
    rotation[:, 0, 0] = fz
    rotation[:, 2, 0] = -fx
    rotation[:, 1, 1] = 1.0
    rotation[:, 0, 2] = fx
    rotation[:, 2, 2] = fz
    return origin, rotation


def to_body_frame(points: np.ndarray, origin: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Express world points in the body frame of their own frame.

    Parameters
    ----------
    points : ndarray [shape=(F, ..., 3)], metres
        World points; frame ``f`` of ``points`` is expressed in body frame ``f``.
    origin : ndarray [shape=(F, 3)], metres
        From :func:`body_frame`.
    rotation : ndarray [shape=(F, 3, 3)]
        From :func:`body_frame`.

    Returns
    -------
    ndarray [shape=(F, ..., 3)], float64, metres
        ``rotation[f].T @ (points[f, ...] - origin[f])``: x = left, y = up (above
        the root), z = forward.
    """
    points = np.asarray(points, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    rotation = np.asarray(rotation, dtype=np.float64)
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ParameterError(f"points: expected shape (F, ..., 3); got {points.shape}")
    n = points.shape[0]
    if origin.shape != (n, 3):
        raise ParameterError(f"origin: expected shape ({n}, 3) to match points; got {origin.shape}")
    if rotation.shape != (n, 3, 3):
        raise ParameterError(f"rotation: expected shape ({n}, 3, 3) to match points; got {rotation.shape}")
    extra = points.ndim - 2
    o = origin.reshape((n,) + (1,) * extra + (3,))
    r = rotation.reshape((n,) + (1,) * extra + (3, 3))
    # local_c = sum_k R[k, c] * d_k  (R transposed applied to d)
    return np.einsum("...kc,...k->...c", r, points - o)


def point_speeds(local_points: np.ndarray, *, fps: float, smooth_s: float = SPEED_SMOOTH_S) -> np.ndarray:
    """Speed of points over time, lightly smoothed.

    Parameters
    ----------
    local_points : ndarray [shape=(F, ..., 3)], metres
        Positions of one recording (usually already in the body frame).
    fps : float > 0, keyword-only
        Frame rate, frames per second.
    smooth_s : float >= 0, keyword-only
        Gaussian sigma, seconds, applied to the positions before differentiating
        (0 disables). The signal is extended by point reflection at both ends, so
        a straight line at constant velocity stays exactly straight and its speed
        is exact up to the first and last frame.

    Returns
    -------
    ndarray [shape=(F, ...)], float64, metres per second
        Norm of the central-difference velocity (one-sided at the first and last
        frame). A single frame has speed 0.
    """
    fps = check_fps(fps)
    smooth_s = _check_nonnegative("smooth_s", smooth_s)
    x = np.asarray(local_points, dtype=np.float64)
    if x.ndim < 2 or x.shape[-1] != 3:
        raise ParameterError(f"local_points: expected shape (F, ..., 3); got {x.shape}")
    if len(x) < 2:
        return np.zeros(x.shape[:-1])
    if smooth_s > 0:
        x = gaussian_smooth(x, sigma=smooth_s * fps, mode="odd")
    vel = np.gradient(x, axis=0) * fps
    return np.sqrt(np.sum(vel * vel, axis=-1))


# --------------------------------------------------------------------------
# Shared helpers of the feature modules.


def check_positions(positions, name: str = "positions") -> np.ndarray:
    """Validate world positions and return them as float64 ``(F, J, 3)``."""
    arr = np.asarray(positions)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ParameterError(f"{name}: expected shape (F, J, 3) in metres; got {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ParameterError(f"{name}: expected a float array; got dtype {arr.dtype}")
    arr = np.asarray(arr, dtype=np.float64)
    if arr.shape[0] == 0:
        raise ParameterError(f"{name}: expected at least one frame; got shape {arr.shape}")
    finite = np.isfinite(arr).all(axis=(1, 2))
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise ParameterError(
            f"{name}: expected finite values; got NaN/inf in {len(bad)} frame(s), first at frame {bad[0]}"
        )
    return arr


def check_joints(joints: Mapping[str, int], roles: Sequence[str], *, n_joints: int) -> dict[str, int]:
    """Validate a role -> joint-index mapping for the given roles."""
    if not isinstance(joints, Mapping):
        raise ParameterError(f"joints: expected a dict of role -> joint index; got {type(joints).__name__}")
    missing = [r for r in roles if r not in joints]
    if missing:
        raise ParameterError(
            f"joints: missing role(s) {', '.join(repr(m) for m in missing)}; "
            f"expected keys {list(roles)}; got {sorted(joints)}"
        )
    out: dict[str, int] = {}
    for r in roles:
        v = joints[r]
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise ParameterError(f"joints[{r!r}]: expected an int joint index; got {v!r}")
        if not 0 <= int(v) < n_joints:
            raise ParameterError(f"joints[{r!r}]: expected an index in [0, {n_joints}); got {int(v)}")
        out[r] = int(v)
    return out


def check_fps(fps) -> float:
    """Validate a frame rate (frames per second)."""
    try:
        value = float(fps)
    except (TypeError, ValueError):
        raise ParameterError(f"fps: expected a positive number of frames per second; got {fps!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise ParameterError(f"fps: expected a positive number of frames per second; got {fps!r}")
    return value


def _check_nonnegative(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name}: expected a number >= 0; got {value!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise ParameterError(f"{name}: expected a number >= 0; got {value!r}")
    return v


def gaussian_smooth(x: np.ndarray, *, sigma: float, mode: str) -> np.ndarray:
    """Gaussian smoothing along axis 0 (kernel truncated at 4 sigma).

    Parameters
    ----------
    x : ndarray [shape=(F, ...)]
    sigma : float
        Standard deviation in samples; <= 0 returns a copy.
    mode : {"edge", "odd"}
        How the signal continues past both ends: ``"edge"`` repeats the end
        value; ``"odd"`` reflects through the end point (``2 x[0] - x[k]``), which
        keeps linear trends unchanged.

    Returns
    -------
    ndarray, float64, same shape as ``x``.
    """
    x = np.asarray(x, dtype=np.float64)
    if sigma <= 0 or len(x) < 2:
        return x.copy()
    radius = max(1, int(math.ceil(4.0 * sigma)))
    t = np.arange(-radius, radius + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (t / sigma) ** 2)
    kernel /= kernel.sum()
    pad = [(radius, radius)] + [(0, 0)] * (x.ndim - 1)
    if mode == "edge":
        xp = np.pad(x, pad, mode="edge")
    elif mode == "odd":
        xp = np.pad(x, pad, mode="reflect", reflect_type="odd")
    else:  # pragma: no cover - internal misuse
        raise ParameterError(f"mode: expected 'edge' or 'odd'; got {mode!r}")
    out = np.zeros_like(x)
    n = len(x)
    # A loop over the (short) kernel keeps memory at one copy of x, instead of
    # a (F, kernel) sliding-window product for every channel.
    for k, w in enumerate(kernel):
        out += w * xp[k : k + n]
    return out


def _fill_from_nearest(values: np.ndarray, valid: np.ndarray, *, default: np.ndarray) -> np.ndarray:
    """Replace rows where ``valid`` is False by the nearest valid row (earlier on ties)."""
    if valid.all():
        return values
    good = np.flatnonzero(valid)
    out = values.copy()
    if len(good) == 0:
        out[:] = default
        return out
    bad = np.flatnonzero(~valid)
    pos = np.searchsorted(good, bad)  # first valid index > bad
    left = good[np.clip(pos - 1, 0, len(good) - 1)]
    right = good[np.clip(pos, 0, len(good) - 1)]
    use_left = (pos > 0) & ((pos == len(good)) | (bad - left <= right - bad))
    out[bad] = values[np.where(use_left, left, right)]
    return out
