"""Pose features for the motion-matching search (Habibie et al. 2022, Sec. 3.1).

The pose feature of a frame describes where the hands and arms are, where they came from
and where they are going: the 8 feature joints (wrists, elbows, index- and little-finger
roots of both hands) in the body frame of that frame, stacked over a short window centred
on it (frames ``f - 2s, f - s, f, f + s, f + 2s`` with the defaults, ``s`` = 2/15 s for the
BEAT2 speaker: see "The stride" below), and
the same of the two ankles (the stance), where the rig has legs. The
search compares the feature of a candidate window's entry frame, whose future half is the
candidate's own first frames, with the feature of the last output frame, whose future half
is how its source recording went on: a close match is a window that starts where the
previous one was going, which is the offset that the seam treatment then removes
(:mod:`gesturedb.synth.seams`). The paper's features likewise "encode information about
the relevant future frames". Squared Euclidean distance, so everything is in metres and no
joint is weighted.

Why not the past alone (the schema-3 feature: frames f, f-2, f-4, f-6): matching a fast
movement's past favours windows whose entry is near still (a still candidate is closer to a
fast query than a fast candidate moving another way), so the k-NN chained calmer windows
than the database's average (0.75-0.89x its arm velocity power on the four BEAT2 inputs)
while its seams added the energy back at 4-7 Hz. With the centred window the windows it
chooses carry about the database's own power and the seams' offsets are smaller
(``docs/evaluation.md``, "Strokes").

Why the ankles (schema 5; the paper's feature has the upper body only): nothing else keeps a
window's stance near the output's. Each window is placed so that its root continues the
output's, so it brings its own feet relative to its root; a planted foot that the next window
puts a few centimetres elsewhere drifts from where the motion wants it, seam after seam, until
it takes a step the source never took. With the ankles in the feature (the same stacked
frames, in metres, unweighted like the rest) the search prefers windows whose feet stand and
move as the output's do: on the held-out BEAT2 stretch the mean foot speed went from 1.50x
the capture's to 0.78x (seed 0; 1.12x -> 0.67x over four starts), the pelvis from 1.40x to
0.90x (``docs/evaluation.md``, "Feet").

The stride in the speaker's own time (2026-11-28): a build spaces the stacked frames
:data:`POSE_STRIDE_PER_TIMESCALE` of the motion's timescale apart (:func:`motion_timescale`, the
lag at which the hands' and arms' velocity decorrelates to one half), which is the paper's 2/15 s
for the BEAT2 speaker at 15 and 30 fps. With a fixed 2/15 s a speaker whose strokes are faster is
matched over more of each movement, and a lively entry frame is then far from most previous poses:
the rank sum chained calm windows (the speaker 1.25x faster at 30 fps kept 0.83x the database's
2-4 Hz arm power, strokes 2x larger and 1.25x faster at 15 fps 0.77x, with 3 and 6 of 72 band
values below the goal; in its own time 0.93x and 0.86x, none below; ``docs/evaluation.md``).
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.features.body import (
    BODY_ROLES,
    FACING_SMOOTH_S,
    SPEED_SMOOTH_S,
    body_frame,
    check_fps,
    check_joints,
    check_positions,
    gaussian_smooth,
    to_body_frame,
)
from gesturedb.roles import FEATURE_ROLES

__all__ = ["FEATURE_ROLES", "POSE_STRIDE_PER_TIMESCALE", "POSE_STRIDE_S", "POSE_WINDOW", "TIMESCALE_MAX_S",
           "default_pose_stride", "motion_timescale", "pose_features", "pose_feature_size", "timescale_pose_stride",
           "velocity_lag_products"]

#: Time between stacked frames, s, where the motion's timescale is unknown: every second frame of the
#: paper's 15 fps database.
POSE_STRIDE_S = 2 / 15
#: Time between stacked frames as a fraction of the motion's own timescale (:func:`motion_timescale`):
#: the paper's 2/15 s at the BEAT2 speaker's 0.165 s, so that a speaker who moves faster (or slower) is
#: matched over the same part of a movement, not over the same number of milliseconds.
POSE_STRIDE_PER_TIMESCALE = 0.81
#: Longest lag of the velocity autocorrelation (s): a motion whose velocity stays correlated for longer
#: has this timescale.
TIMESCALE_MAX_S = 1.0
#: Stacked frames on each side of the current one, the current one included (5 frames in all).
POSE_WINDOW = 3

# Frames per block: bounds the float64 temporaries to a few tens of MB however
# long the recording is.
_BLOCK = 32768


def default_pose_stride(fps: float) -> int:
    """Frames between stacked frames at ``fps``: :data:`POSE_STRIDE_S` rounded, at least 1
    (2 at 15 fps, 4 at 30 fps)."""
    return max(1, int(round(check_fps(fps) * POSE_STRIDE_S)))


def velocity_lag_products(
    positions: np.ndarray,
    *,
    joints: Mapping[str, int],
    fps: float,
    facing_smooth_s: float = FACING_SMOOTH_S,
) -> np.ndarray:
    """Sums of the feature joints' velocity dot products at lags 0 .. L over one recording.

    The velocity is that of the :data:`FEATURE_ROLES` joints (hands and arms) in the body frame
    (:func:`gesturedb.features.body.body_frame`), in m/s, between adjacent frames, after a Gaussian
    of :data:`gesturedb.features.body.SPEED_SMOOTH_S` (as every speed of the features). Sums of
    recordings add up, so a build accumulates them a recording at a time and
    :func:`motion_timescale` reads the whole database's timescale from the total.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        World joint positions of one recording, y up.
    joints : mapping of str to int, keyword-only
        Joint index of every role in :data:`FEATURE_ROLES` and in :data:`BODY_ROLES`.
    fps : float, keyword-only
        Frame rate (Hz).

    Returns
    -------
    ndarray [shape=(L + 1,)], float64, m²/s²
        Entry ``k`` is the sum over frames ``t`` and joints of ``v(t) . v(t + k)``, with
        ``L = ceil(TIMESCALE_MAX_S * fps)``; zeros where the recording is too short.
    """
    positions = check_positions(positions)
    fps = check_fps(fps)
    idx = check_joints(joints, FEATURE_ROLES + BODY_ROLES, n_joints=positions.shape[1])
    max_lag = int(np.ceil(TIMESCALE_MAX_S * fps))
    out = np.zeros(max_lag + 1)
    if positions.shape[0] < 2:
        return out
    origin, rotation = body_frame(positions, joints=idx, smooth_frames=facing_smooth_s * fps)
    local = to_body_frame(positions[:, [idx[r] for r in FEATURE_ROLES], :], origin, rotation)
    # smoothed as for every speed (SPEED_SMOOTH_S): the capture's frame-to-frame jitter decorrelates the
    # velocity within a frame, and 5 mm of it at 30 fps would read as a timescale of 0.03 s
    local = gaussian_smooth(local, sigma=SPEED_SMOOTH_S * fps, mode="odd")
    v = (np.diff(local, axis=0) * fps).reshape(positions.shape[0] - 1, -1)
    for k in range(min(max_lag + 1, v.shape[0])):
        out[k] = np.einsum("ij,ij->", v[:v.shape[0] - k], v[k:])
    return out


def motion_timescale(lag_products: np.ndarray, fps: float) -> float | None:
    """The motion's timescale (s): the lag at which the velocity's autocorrelation falls to one half.

    Linear between frames. From the sums of :func:`velocity_lag_products` (of one recording or of
    many, added up). About 0.165 s for the BEAT2 speaker at any frame rate, 0.137 s for the same
    recording played 1.25x faster; a pure sinusoid of frequency ``f`` gives ``1 / (6 f)``. None where
    the motion does not move (no velocity); :data:`TIMESCALE_MAX_S` where its autocorrelation stays
    above one half that long.
    """
    fps = check_fps(fps)
    sums = np.asarray(lag_products, dtype=np.float64).reshape(-1)
    if sums.size < 2 or not np.isfinite(sums).all() or not sums[0] > 0:
        return None
    ac = sums / sums[0]
    below = np.flatnonzero(ac < 0.5)
    if below.size == 0:
        return float(TIMESCALE_MAX_S)
    k = int(below[0])
    lag = k - 1 + (ac[k - 1] - 0.5) / (ac[k - 1] - ac[k])
    return float(min(lag / fps, TIMESCALE_MAX_S))


def timescale_pose_stride(timescale_s: float | None, fps: float) -> int:
    """Frames between stacked frames for a motion of this timescale: :data:`POSE_STRIDE_PER_TIMESCALE`
    of it, rounded, at least 1 (2 at 15 fps and 4 at 30 fps for the BEAT2 speaker, 3 at 30 fps when
    it moves 1.25x faster); :func:`default_pose_stride` where the timescale is unknown (None)."""
    if timescale_s is None:
        return default_pose_stride(fps)
    if not (np.isfinite(timescale_s) and timescale_s > 0):
        raise ParameterError(f"timescale_s: expected a positive number of seconds or None; got {timescale_s!r}")
    return max(1, int(round(check_fps(fps) * POSE_STRIDE_PER_TIMESCALE * timescale_s)))


def pose_feature_size(*, window: int = POSE_WINDOW, stance: bool = False) -> int:
    """Length of one pose feature vector: ``(len(FEATURE_ROLES) + 2 * stance) * 3 * (2 * window - 1)``
    (120 with the defaults; 150 with the ankles, what a build stores for a rig with legs)."""
    return (len(FEATURE_ROLES) + 2 * bool(stance)) * 3 * (2 * _check_window(window) - 1)


def pose_features(
    positions: np.ndarray,
    *,
    joints: Mapping[str, int],
    fps: float,
    window: int = POSE_WINDOW,
    stride: int | None = None,
    stance=(),
    facing_smooth_s: float = FACING_SMOOTH_S,
) -> np.ndarray:
    """Pose feature of every frame of one recording.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        World joint positions of one recording, y up.
    joints : mapping of str to int, keyword-only
        Joint index of every role in :data:`FEATURE_ROLES` and in
        :data:`gesturedb.features.body.BODY_ROLES`.
    fps : float, keyword-only
        Frame rate (Hz): sets the default stride and the facing smoothing, both in seconds.
    window : int >= 1, keyword-only
        Frames stacked on each side, the current one included: ``2 * window - 1`` in all.
    stride : int >= 1 or None, keyword-only
        Frames between stacked frames; None: :func:`default_pose_stride` of ``fps``.
    stance : sequence of int, keyword-only
        The left and the right ankle (:func:`gesturedb.io.joints.ankle_joints`), stacked after
        the feature joints; empty (the default): no stance columns (a rig without legs).
    facing_smooth_s : float >= 0, keyword-only
        Gaussian sigma (s) of the body frame's facing smoothing
        (:func:`gesturedb.features.body.body_frame`); 0 disables it.

    Returns
    -------
    ndarray [shape=(F, (8 + len(stance)) * 3 * (2 * window - 1))], float32, C-contiguous, metres
        Row ``f`` holds, for lag ``k = -(window-1) .. window-1`` (outer, past first), joint
        ``j`` in :data:`FEATURE_ROLES` order (middle) and axis x, y, z (inner), the position
        of joint ``j`` at frame ``f + k * stride`` (clamped to the recording's first and last
        frame) expressed in the body frame of frame ``f`` (x = speaker's left, y = up from the
        root, z = forward). Column ``((k + window - 1) * 8 + j) * 3 + axis``. With the
        defaults at 15 fps: frames f-4, f-2, f, f+2, f+4 and 120 values. Then the ankles the
        same way (lag outer, left before right, axis inner): column
        ``120 + ((k + window - 1) * 2 + a) * 3 + axis``, 150 values in all.

    Notes
    -----
    Because every stacked frame is expressed in the *current* body frame, the
    feature is unchanged by a translation or a rotation about the vertical axis
    of the whole recording, while it still records how the hands move relative
    to where the body is now.
    """
    positions = check_positions(positions)
    fps = check_fps(fps)
    window = _check_window(window)
    stride = default_pose_stride(fps) if stride is None else stride
    if isinstance(stride, (bool, np.bool_)) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ParameterError(f"stride: expected an int >= 1 (frames); got {stride!r}")
    n_frames, n_joints, _ = positions.shape
    idx = check_joints(joints, FEATURE_ROLES + BODY_ROLES, n_joints=n_joints)
    origin, rotation = body_frame(positions, joints=idx, smooth_frames=facing_smooth_s * fps)

    stance = _check_stance(stance, n_joints)
    lags = np.arange(-(window - 1), window, dtype=np.int64) * int(stride)
    groups = [np.array([idx[r] for r in FEATURE_ROLES], dtype=np.int64)] + ([stance] if stance.size else [])
    pts = [positions[:, g, :] for g in groups]  # (F, |g|, 3) each: the feature joints, then the ankles
    widths = [lags.size * g.size * 3 for g in groups]
    out = np.empty((n_frames, sum(widths)), dtype=np.float32)
    for a in range(0, n_frames, _BLOCK):
        b = min(a + _BLOCK, n_frames)
        f = np.arange(a, b, dtype=np.int64)
        src = np.clip(f[:, None] + lags[None, :], 0, n_frames - 1)  # (B, 2 * window - 1)
        col = 0
        for p, width in zip(pts, widths):
            d = (p[src] - origin[a:b, None, None, :]).reshape(b - a, -1, 3)  # (B, lags * |g|, 3)
            # row vector times R applies R transposed: local_c = sum_k d_k R[k, c]
            out[a:b, col:col + width] = np.matmul(d, rotation[a:b]).reshape(b - a, -1)
            col += width
    return out


def _check_stance(stance, n_joints: int) -> np.ndarray:
    arr = np.asarray(stance if stance is not None else (), dtype=np.int64).reshape(-1)
    if arr.size not in (0, 2) or np.any((arr < 0) | (arr >= n_joints)):
        raise ParameterError(f"stance: expected the two ankles' joint indices in [0, {n_joints}) or none; "
                             f"got {stance!r}")
    return arr


def _check_window(window) -> int:
    if isinstance(window, (bool, np.bool_)) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ParameterError(f"window: expected an int >= 1 (frames); got {window!r}")
    return int(window)
