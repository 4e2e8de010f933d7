"""Pose features for the motion-matching search (Habibie et al. 2022, Sec. 3.1).

The pose feature of a frame describes where the hands and arms are and where
they came from: the 8 feature joints (wrists, elbows, index- and little-finger
roots of both hands) in the body frame of that frame, stacked over a short past
window. The search compares it by squared Euclidean distance with the feature of
the last output frame, so everything is in metres and no joint is weighted.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.features.body import (
    BODY_ROLES,
    FACING_SMOOTH_FRAMES,
    body_frame,
    check_joints,
    check_positions,
)
from gesturedb.roles import FEATURE_ROLES

__all__ = ["FEATURE_ROLES", "pose_features", "pose_feature_size"]


# Frames per block: bounds the float64 temporaries to a few tens of MB however
# long the recording is.
_BLOCK = 32768


def pose_feature_size(*, window: int = 4) -> int:
    """Length of one pose feature vector: ``len(FEATURE_ROLES) * 3 * window``."""
    return len(FEATURE_ROLES) * 3 * _check_window(window)


def pose_features(
    positions: np.ndarray,
    *,
    joints: Mapping[str, int],
    window: int = 4,
    stride: int = 2,
    smooth_frames: float = FACING_SMOOTH_FRAMES,
) -> np.ndarray:
    """Pose feature of every frame of one recording.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        World joint positions of one recording, y up.
    joints : mapping of str to int, keyword-only
        Joint index of every role in :data:`FEATURE_ROLES` and in
        :data:`gesturedb.features.body.BODY_ROLES`.
    window : int >= 1, keyword-only
        Number of frames stacked (current frame and its past).
    stride : int >= 1, keyword-only
        Frames between stacked frames.
    smooth_frames : float >= 0, keyword-only
        Facing smoothing of the body frame, see
        :func:`gesturedb.features.body.body_frame`.

    Returns
    -------
    ndarray [shape=(F, 8 * 3 * window)], float32, C-contiguous, metres
        Row ``f`` holds, for lag ``k = 0 .. window-1`` (outer), joint ``j`` in
        :data:`FEATURE_ROLES` order (middle) and axis x, y, z (inner), the
        position of joint ``j`` at frame ``max(f - k * stride, 0)`` expressed in
        the body frame of frame ``f`` (x = speaker's left, y = up from the root,
        z = forward). Column ``(k * 8 + j) * 3 + axis``. With the defaults:
        frames f, f-2, f-4, f-6 and 96 values; frames before the start of the
        recording are clamped to frame 0.

    Notes
    -----
    Because every stacked frame is expressed in the *current* body frame, the
    feature is unchanged by a translation or a rotation about the vertical axis
    of the whole recording, while it still records how the hands moved relative
    to where the body is now.
    """
    positions = check_positions(positions)
    window = _check_window(window)
    if isinstance(stride, (bool, np.bool_)) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ParameterError(f"stride: expected an int >= 1 (frames); got {stride!r}")
    n_frames, n_joints, _ = positions.shape
    idx = check_joints(joints, FEATURE_ROLES + BODY_ROLES, n_joints=n_joints)
    origin, rotation = body_frame(positions, joints=idx, smooth_frames=smooth_frames)

    feat_joints = np.array([idx[r] for r in FEATURE_ROLES], dtype=np.int64)
    pts = positions[:, feat_joints, :]  # (F, 8, 3)
    lags = np.arange(window, dtype=np.int64) * int(stride)
    out = np.empty((n_frames, window * len(FEATURE_ROLES) * 3), dtype=np.float32)
    for a in range(0, n_frames, _BLOCK):
        b = min(a + _BLOCK, n_frames)
        f = np.arange(a, b, dtype=np.int64)
        src = np.maximum(f[:, None] - lags[None, :], 0)  # (B, window)
        d = (pts[src] - origin[a:b, None, None, :]).reshape(b - a, -1, 3)  # (B, window * 8, 3)
        # row vector times R applies R transposed: local_c = sum_k d_k R[k, c]
        out[a:b] = np.matmul(d, rotation[a:b]).reshape(b - a, -1)
    return out


def _check_window(window) -> int:
    if isinstance(window, (bool, np.bool_)) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ParameterError(f"window: expected an int >= 1 (frames); got {window!r}")
    return int(window)
