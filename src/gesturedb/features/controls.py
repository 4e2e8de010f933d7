"""Per-frame control signals (Habibie et al. 2022, Sec. 3.1 and 4.1).

Controls restrict the search to database frames whose signal passes a threshold
("left wrist higher than 0.2 m", "slow hands", "symmetric hands"). Each signal is
a float32 curve over the frames of one recording, measured on the wrists in the
body frame (x = speaker's left, y = up from the root, z = forward; see
:mod:`gesturedb.features.body`), so it means the same wherever the speaker
stands and whichever way they face.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

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

__all__ = ["CONTROL_NAMES", "CONTROL_UNITS", "CONTROL_DOCS", "control_features"]

#: Unit of every control signal.
CONTROL_UNITS: dict[str, str] = {
    "left_wrist_height": "m",
    "right_wrist_height": "m",
    "left_wrist_speed": "m/s",
    "right_wrist_speed": "m/s",
    "left_hand_radius": "m",
    "right_hand_radius": "m",
    "left_wrist_forward": "m",
    "right_wrist_forward": "m",
    "height_asymmetry": "m",
    "mirror_distance": "m",
    "hand_speed": "m/s",
    "hand_distance": "m",
}

#: One-line description of every control signal.
CONTROL_DOCS: dict[str, str] = {
    "left_wrist_height": "height of the left wrist above the root joint (negative below it)",
    "right_wrist_height": "height of the right wrist above the root joint (negative below it)",
    "left_wrist_speed": "speed of the left wrist relative to the body frame, lightly smoothed",
    "right_wrist_speed": "speed of the right wrist relative to the body frame, lightly smoothed",
    "left_hand_radius": "horizontal distance of the left wrist from the vertical axis through the root",
    "right_hand_radius": "horizontal distance of the right wrist from the vertical axis through the root",
    "left_wrist_forward": "distance of the left wrist in front of the root along the facing direction",
    "right_wrist_forward": "distance of the right wrist in front of the root along the facing direction",
    "height_asymmetry": "absolute difference of the left and right wrist heights",
    "mirror_distance": "distance between the left wrist and the right wrist mirrored left-right in the body frame",
    "hand_speed": "speed of the faster wrist (the curve of the rhythm signatures)",
    "hand_distance": "distance between the two wrists",
}

#: Names of the control signals, in a fixed order.
CONTROL_NAMES: tuple[str, ...] = tuple(CONTROL_UNITS)


def control_features(
    positions: np.ndarray,
    *,
    joints: Mapping[str, int],
    fps: float,
    smooth_s: float = SPEED_SMOOTH_S,
) -> dict[str, np.ndarray]:
    """Every control signal of one recording.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        World joint positions of one recording, y up. Call once per recording:
        speeds never span two recordings.
    joints : mapping of str to int, keyword-only
        Roles ``left_wrist``, ``right_wrist`` and the body-frame roles ``root``,
        ``left_hip``, ``right_hip``, ``left_shoulder``, ``right_shoulder``.
    fps : float > 0, keyword-only
        Frames per second.
    smooth_s : float >= 0, keyword-only
        Gaussian sigma (seconds) on the wrist positions before differentiating
        into speeds; see :func:`gesturedb.features.body.point_speeds`.

    Returns
    -------
    dict of str to ndarray [shape=(F,)], float32
        One entry per name in :data:`CONTROL_NAMES`; units in
        :data:`CONTROL_UNITS`, meanings in :data:`CONTROL_DOCS`.
    """
    positions = check_positions(positions)
    idx = check_joints(joints, WRIST_ROLES + BODY_ROLES, n_joints=positions.shape[1])
    origin, rotation = body_frame(positions, joints=idx, fps=fps)
    wrists = to_body_frame(positions[:, [idx[r] for r in WRIST_ROLES]], origin, rotation)  # (F, 2, 3)
    left, right = wrists[:, 0], wrists[:, 1]
    speeds = point_speeds(wrists, fps=fps, smooth_s=smooth_s)  # (F, 2)
    mirrored_right = right * np.array([-1.0, 1.0, 1.0])
    out = {
        "left_wrist_height": left[:, 1],
        "right_wrist_height": right[:, 1],
        "left_wrist_speed": speeds[:, 0],
        "right_wrist_speed": speeds[:, 1],
        "left_hand_radius": np.hypot(left[:, 0], left[:, 2]),
        "right_hand_radius": np.hypot(right[:, 0], right[:, 2]),
        "left_wrist_forward": left[:, 2],
        "right_wrist_forward": right[:, 2],
        "height_asymmetry": np.abs(left[:, 1] - right[:, 1]),
        "mirror_distance": np.linalg.norm(left - mirrored_right, axis=1),
        "hand_speed": speeds.max(axis=1),
        "hand_distance": np.linalg.norm(left - right, axis=1),
    }
    return {name: np.ascontiguousarray(out[name], dtype=np.float32) for name in CONTROL_NAMES}
