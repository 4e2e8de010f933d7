"""Metrics of the body's placement in the world: root motion, foot skating, heading.

The arm metrics of :mod:`gesturedb.eval.metrics` are root-relative; these are in
world space, where the seams between windows of different recordings show as a
sliding or teleporting body. Inputs are joint positions ``(F, J, 3)`` in metres,
y up, at ``fps`` frames per second.
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError

__all__ = ["root_speed", "max_root_step", "foot_skating", "heading_deg", "placement_metrics"]

#: A foot whose lowest point (ankle or toe) is within this height (m) of the floor is in contact.
SKATING_CONTACT_HEIGHT_M = 0.05


def _pos(positions) -> np.ndarray:
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] < 2:
        raise ParameterError(f"positions: expected (F >= 2, J, 3) metres; got shape {pos.shape}")
    return pos


def root_speed(positions, *, fps: float, root: int = 0) -> float:
    """Mean world-space speed (m/s) of the root joint (first differences times fps)."""
    pos = _pos(positions)
    return float(np.linalg.norm(np.diff(pos[:, root], axis=0), axis=-1).mean() * fps)


def max_root_step(positions, *, root: int = 0) -> float:
    """Largest distance (m) the root joint moves between two consecutive frames."""
    pos = _pos(positions)
    return float(np.linalg.norm(np.diff(pos[:, root], axis=0), axis=-1).max())


def foot_skating(positions, *, fps: float, feet, height_m: float = SKATING_CONTACT_HEIGHT_M) -> float:
    """Mean horizontal speed (m/s) of the feet while they touch the floor.

    A foot (``feet[i] = [ankle, toe]``) touches the floor in a step t -> t+1 when
    its lowest point is within ``height_m`` of the floor (the lowest foot point
    of the whole motion) in both frames; its speed is the ankle's horizontal
    displacement times fps. Contact is by height only, so a foot that slides
    fast still counts. NaN when no foot ever touches the floor.
    """
    pos = _pos(positions)
    feet = np.asarray(feet, dtype=np.int64).reshape(-1, 2)
    low = pos[:, feet, 1].min(axis=2)  # (F, n_feet)
    contact = low <= low.min() + height_m
    both = contact[1:] & contact[:-1]
    step = np.linalg.norm(np.diff(pos[:, feet[:, 0]][:, :, [0, 2]], axis=0), axis=-1) * fps
    return float(step[both].mean()) if both.any() else float("nan")


def heading_deg(positions, *, left_hip: int, right_hip: int) -> np.ndarray:
    """Heading (degrees, 0 = facing +z, positive towards +x) per frame, from the hips.

    The facing direction is perpendicular to the left-to-right hip line in the
    horizontal plane (y up): forward = up x (right - left)... oriented so that a
    body whose left hip is at +x faces +z.
    """
    pos = _pos(positions)
    across = pos[:, left_hip] - pos[:, right_hip]  # points to the body's left
    # facing = across x up rotated: for left = +x, forward = +z  ->  forward = (-across_z, across_x)... see test
    fx, fz = -across[:, 2], across[:, 0]
    return np.degrees(np.arctan2(fx, fz))


def placement_metrics(positions, *, fps: float, root: int, feet, hips=None) -> dict:
    """Root speed (m/s), largest root step (m), foot skating (m/s) and, with ``hips=(left, right)``,
    the largest absolute heading (degrees) and the heading over the last 10 % of frames."""
    out = {
        "root_speed_m_s": root_speed(positions, fps=fps, root=root),
        "max_root_step_m": max_root_step(positions, root=root),
        "foot_skating_m_s": foot_skating(positions, fps=fps, feet=feet) if len(feet) else float("nan"),
    }
    if hips is not None:
        h = heading_deg(positions, left_hip=hips[0], right_hip=hips[1])
        out["max_abs_heading_deg"] = float(np.abs(h).max())
        out["end_heading_deg"] = float(np.degrees(np.arctan2(np.sin(np.radians(h[-max(1, len(h) // 10):])).mean(),
                                                             np.cos(np.radians(h[-max(1, len(h) // 10):])).mean())))
    return out
