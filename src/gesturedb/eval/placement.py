"""Metrics of the body's placement in the world: root motion, foot skating, heading.

The arm metrics of :mod:`gesturedb.eval.metrics` are root-relative; these are in
world space, where the seams between windows of different recordings show as a
sliding or teleporting body. Inputs are joint positions ``(F, J, 3)`` in metres,
y up, at ``fps`` frames per second.
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.io.joints import body_keys
from gesturedb.io.joints import group_joints as _group_joints
from gesturedb.roles import JOINT_GROUPS

__all__ = ["JOINT_GROUPS", "root_speed", "max_root_step", "foot_skating", "heading_deg", "placement_metrics",
           "group_joints", "root_relative", "mean_jerk", "world_metrics"]

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


def group_joints(names) -> dict[str, np.ndarray]:
    """Joint indices of every group of :data:`gesturedb.roles.JOINT_GROUPS` that the skeleton has (int64 arrays)."""
    return _group_joints(names, JOINT_GROUPS)


def root_relative(positions, *, root: int = 0) -> np.ndarray:
    """Positions with the root's horizontal position removed from every joint (its height kept)."""
    pos = _pos(positions)
    return pos - pos[:, root:root + 1] * np.array([1.0, 0.0, 1.0])


def mean_jerk(positions, *, fps: float, joints) -> float:
    """GENEA average jerk (m/s^3): mean over joints and frames of ``|third forward difference| * fps^3``."""
    pos = _pos(positions)[:, np.asarray(joints, dtype=np.int64)]
    if pos.shape[0] < 4:
        return float("nan")
    return float(np.linalg.norm(np.diff(pos, n=3, axis=0), axis=-1).mean() * fps ** 3)


def world_metrics(positions, *, fps: float, names) -> dict:
    """Everything ``gesturedb eval motion`` shows about the body in the world, one flat dict.

    ``pelvis_speed_m_s`` and ``foot_speed_m_s`` (mean world speeds of the root and
    the ankles), ``max_root_step_m``, ``foot_skating_m_s``, ``max_abs_heading_deg``
    and, per group ``g`` of :data:`JOINT_GROUPS`, ``jerk_world_<g>_m_s3`` and
    ``jerk_rel_<g>_m_s3`` (root-relative: the root's horizontal position removed).
    Missing body parts give NaN.
    """

    pos = _pos(positions)
    keys = {k: j for j, k in body_keys(names).items()}
    root = keys.get("hips", 0)
    feet = [[keys[f"{s}_foot"], keys.get(f"{s}_toe", keys[f"{s}_foot"])] for s in ("left", "right")
            if f"{s}_foot" in keys]
    out = {
        "pelvis_speed_m_s": root_speed(pos, fps=fps, root=root),
        "foot_speed_m_s": (float(np.mean([root_speed(pos, fps=fps, root=f[0]) for f in feet])) if feet
                           else float("nan")),
        "max_root_step_m": max_root_step(pos, root=root),
        "foot_skating_m_s": foot_skating(pos, fps=fps, feet=feet) if feet else float("nan"),
        "max_abs_heading_deg": float("nan"),
    }
    if "left_upleg" in keys and "right_upleg" in keys:
        h = heading_deg(pos, left_hip=keys["left_upleg"], right_hip=keys["right_upleg"])
        out["max_abs_heading_deg"] = float(np.abs(h).max())
    rel = root_relative(pos, root=root)
    groups = group_joints(names)
    for g in JOINT_GROUPS:
        js = groups.get(g)
        out[f"jerk_world_{g}_m_s3"] = mean_jerk(pos, fps=fps, joints=js) if js is not None else float("nan")
        out[f"jerk_rel_{g}_m_s3"] = mean_jerk(rel, fps=fps, joints=js) if js is not None else float("nan")
    return out
