"""Style signatures (GestureMaster, Zhou et al. 2022, Sec. 3.3).

Following StyleGestures (Alexanderson et al. 2020), the style of a clip is
summarised by three numbers: how fast, how wide and how high the hands move.
All three are measured on the wrists in the body frame and averaged over both
wrists and all frames of the clip.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.features.body import (
    BODY_ROLES,
    SPEED_SMOOTH_S,
    body_frame,
    check_joints,
    check_positions,
    point_speeds,
    to_body_frame,
)
from gesturedb.roles import WRIST_ROLES

__all__ = ["STYLE_NAMES", "STYLE_UNITS", "style_signature", "style_signatures"]

#: Names of the three components, in order.
STYLE_NAMES: tuple[str, str, str] = ("speed", "radius", "height")
#: Units of the three components.
STYLE_UNITS: tuple[str, str, str] = ("m/s", "m", "m")


def style_signatures(
    positions: np.ndarray,
    *,
    joints: Mapping[str, int],
    fps: float,
    starts,
    lengths,
    smooth_s: float = SPEED_SMOOTH_S,
) -> np.ndarray:
    """Style signature of many clips of one recording.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        World joint positions of one recording. Speeds are computed on the whole
        recording, so frames at a clip's edges use their real neighbours.
    joints : mapping of str to int, keyword-only
        Roles ``left_wrist``, ``right_wrist`` and the body-frame roles.
    fps : float > 0, keyword-only
        Frames per second.
    starts, lengths : array of int [shape=(C,)], frames, keyword-only
        Clips ``[starts[c], starts[c] + lengths[c])`` inside the recording,
        ``lengths >= 1``.
    smooth_s : float >= 0, keyword-only
        Speed smoothing, see :func:`gesturedb.features.body.point_speeds`.

    Returns
    -------
    ndarray [shape=(C, 3)], float32
        Per clip, averaged over its frames and over both wrists, in the body
        frame: ``speed`` (m/s), ``radius`` (horizontal distance of the wrist from
        the vertical axis through the root, m) and ``height`` (wrist height above
        the root, m; negative below it).
    """
    positions = check_positions(positions)
    idx = check_joints(joints, WRIST_ROLES + BODY_ROLES, n_joints=positions.shape[1])
    n = len(positions)
    st = np.atleast_1d(np.asarray(starts))
    ln = np.atleast_1d(np.asarray(lengths))
    if st.ndim != 1 or ln.shape != st.shape:
        raise ParameterError(f"starts, lengths: expected two 1-D int arrays of equal length; got {st.shape} and {ln.shape}")
    if st.size == 0:
        return np.zeros((0, 3), dtype=np.float32)
    if not (np.issubdtype(st.dtype, np.integer) and np.issubdtype(ln.dtype, np.integer)):
        raise ParameterError(f"starts, lengths: expected int frames; got dtypes {st.dtype} and {ln.dtype}")
    st = st.astype(np.int64)
    ln = ln.astype(np.int64)
    bad = (st < 0) | (ln < 1) | (st + ln > n)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ParameterError(
            f"starts, lengths: expected clips with length >= 1 inside the {n} frames of positions; "
            f"got clip {k}: start {st[k]}, length {ln[k]}"
        )

    origin, rotation = body_frame(positions, joints=idx, fps=fps)
    wrists = to_body_frame(positions[:, [idx[r] for r in WRIST_ROLES]], origin, rotation)  # (F, 2, 3)
    per_frame = np.stack(
        [
            point_speeds(wrists, fps=fps, smooth_s=smooth_s).mean(axis=1),
            np.hypot(wrists[..., 0], wrists[..., 2]).mean(axis=1),
            wrists[..., 1].mean(axis=1),
        ],
        axis=1,
    )  # (F, 3)
    csum = np.concatenate([np.zeros((1, 3)), np.cumsum(per_frame, axis=0)])
    means = (csum[st + ln] - csum[st]) / ln[:, None]
    return np.ascontiguousarray(means, dtype=np.float32)


def style_signature(
    positions: np.ndarray,
    *,
    joints: Mapping[str, int],
    fps: float,
    start: int,
    length: int,
    smooth_s: float = SPEED_SMOOTH_S,
) -> np.ndarray:
    """Style signature of one clip: mean wrist speed, radius and height.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        World joint positions of the whole recording the clip belongs to.
    joints : mapping of str to int, keyword-only
        Roles ``left_wrist``, ``right_wrist`` and the body-frame roles.
    fps : float > 0, keyword-only
        Frames per second.
    start, length : int, frames, keyword-only
        The clip ``[start, start + length)``.
    smooth_s : float >= 0, keyword-only
        Speed smoothing, see :func:`gesturedb.features.body.point_speeds`.

    Returns
    -------
    ndarray [shape=(3,)], float32
        ``speed`` (m/s), ``radius`` (m), ``height`` (m); see
        :func:`style_signatures`.
    """
    for name, v in (("start", start), ("length", length)):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise ParameterError(f"{name}: expected an int number of frames; got {v!r}")
    return style_signatures(
        positions, joints=joints, fps=fps, starts=[int(start)], lengths=[int(length)], smooth_s=smooth_s
    )[0]
