"""Foot contacts and a two-bone leg IK that keeps planted feet in place.

Used by :func:`gesturedb.synth.assemble.assemble_pieces`: contacts are detected on
each source piece (so a mirrored recording or a time-warped clip is treated like
any other), and after placement the ankles of planted feet are held where the
contact began by rotating hip and knee (analytic two-bone IK); the ankle keeps
its world orientation so the sole stays flat. The root is not moved.
"""
from __future__ import annotations

import numpy as np

from gesturedb import rotations as R
from gesturedb.motion import Motion

__all__ = ["CONTACT_HEIGHT_M", "CONTACT_SPEED_M_S", "foot_contacts", "foot_joints", "leg_joints",
           "plant_feet", "pin_root", "two_bone_ik"]

#: A foot's lowest point within this height (m) of the floor can be planted.
CONTACT_HEIGHT_M = 0.05
#: ... and its ankle moves horizontally slower than this (m/s).
CONTACT_SPEED_M_S = 0.3
#: Frames over which a released foot returns from its anchor to where the motion puts it.
RELEASE_FRAMES = 6
#: A contact whose anchor drifts further than this (m, horizontally) from the foot is re-anchored.
MAX_ANCHOR_DRIFT_M = 0.3


def foot_joints(skeleton) -> np.ndarray:
    """Ankle and toe joints of each side, ``[[left_ankle, left_toe], [right_ankle, right_toe]]`` (2, 2) int64.

    Found by body part (:func:`gesturedb.io.joints.body_keys`); a side without a toe
    uses its ankle twice. Empty (0, 2) when the skeleton has no feet.
    """
    from gesturedb.io.joints import body_keys

    keys = {k: j for j, k in body_keys(skeleton.names).items()}
    out = []
    for side in ("left", "right"):
        ankle = keys.get(f"{side}_foot")
        if ankle is None:
            return np.zeros((0, 2), dtype=np.int64)
        out.append([ankle, keys.get(f"{side}_toe", ankle)])
    return np.asarray(out, dtype=np.int64)


def foot_contacts(positions: np.ndarray, *, fps: float, feet: np.ndarray, floor_y: float | None = None,
                  height_m: float = CONTACT_HEIGHT_M, speed_m_s: float = CONTACT_SPEED_M_S) -> np.ndarray:
    """Planted feet: lowest foot point near the floor and ankle slow horizontally.

    Parameters
    ----------
    positions : ndarray [shape=(T, J, 3)], metres, y up
    fps : float
    feet : ndarray [shape=(2, 2)], int
        :func:`foot_joints`.
    floor_y : float, optional
        Floor height (m); default the lowest foot point of ``positions``.
    height_m, speed_m_s : float
        Thresholds.

    Returns
    -------
    ndarray [shape=(T, 2)], bool
        Left, right planted. The horizontal speed of frame t is the mean of its
        backward and forward differences (one-sided at the ends).
    """
    T = positions.shape[0]
    if feet.shape[0] == 0 or T == 0:
        return np.zeros((T, 2), dtype=bool)
    low = positions[:, feet, 1].min(axis=2)  # (T, 2)
    if floor_y is None:
        floor_y = float(low.min())
    ankle = positions[:, feet[:, 0]][:, :, [0, 2]]  # (T, 2, 2)
    if T > 1:
        d = np.linalg.norm(np.diff(ankle, axis=0), axis=-1) * fps  # (T-1, 2)
        speed = np.empty((T, 2))
        speed[0], speed[-1] = d[0], d[-1]
        speed[1:-1] = 0.5 * (d[1:] + d[:-1])
    else:
        speed = np.zeros((T, 2))
    return (low <= floor_y + height_m) & (speed < speed_m_s)


def pin_root(skeleton, fps: float, rotations: np.ndarray, root: np.ndarray, contacts: np.ndarray, *,
             leak_s: float = 6.0, max_step_m_s: float = 0.15) -> np.ndarray:
    """Move the root horizontally so that planted ankles do not slide.

    Parameters
    ----------
    skeleton : gesturedb.motion.Skeleton
    fps : float
    rotations : ndarray [shape=(T, J, 4)]
    root : ndarray [shape=(T, 3)], metres
    contacts : ndarray [shape=(T, 2)], bool
        Left, right planted.
    leak_s : float
        Time constant (s) with which the accumulated correction decays back to
        zero (so the speaker does not wander; the decay is a slow, even slide of
        at most ``correction / (leak_s * fps)`` per frame).
    max_step_m_s : float
        Largest correction speed (m/s): a faster slide (a seam) is left to the leg IK
        of :func:`plant_feet` rather than turned into a jump of the whole body.

    Returns
    -------
    ndarray [shape=(T, 3)], metres
        Root with a horizontal correction ``c[t] = (1 - k) c[t-1] - d[t]`` where
        ``d[t]`` is the mean horizontal step of the planted ankles (planted in both
        t-1 and t) and 0 when no foot is planted: a step of a planted foot becomes
        a step of the body the other way, as when the capture stands on that foot.
    """
    feet = foot_joints(skeleton)
    T = root.shape[0]
    if feet.shape[0] == 0 or T < 2 or not contacts.any():
        return root
    pos = Motion(skeleton=skeleton, fps=fps, rotations=rotations, root_positions=root).positions
    ank = pos[:, feet[:, 0]][:, :, [0, 2]]  # (T, 2, 2)
    step = np.diff(ank, axis=0)  # (T-1, 2, 2)
    both = (contacts[1:] & contacts[:-1]).astype(np.float64)  # (T-1, 2)
    n = both.sum(axis=1)
    d = (step * both[..., None]).sum(axis=1) / np.maximum(n, 1)[:, None]
    mag = np.linalg.norm(d, axis=-1, keepdims=True)
    lim = max_step_m_s / fps
    d = d * np.minimum(1.0, lim / np.maximum(mag, 1e-12))
    k = 1.0 / (leak_s * fps)
    c = np.zeros((T, 2))
    for t in range(1, T):
        c[t] = (1 - k) * c[t - 1] - d[t - 1]
    out = root.copy()
    out[:, 0] += c[:, 0]
    out[:, 2] += c[:, 1]
    return out


def leg_joints(skeleton) -> np.ndarray:
    """``[[hip, knee, ankle], ...]`` for the left and right leg (2, 3) int64; (0, 3) without legs."""
    from gesturedb.io.joints import body_keys

    keys = {k: j for j, k in body_keys(skeleton.names).items()}
    out = []
    for side in ("left", "right"):
        js = [keys.get(f"{side}_{p}") for p in ("upleg", "leg", "foot")]
        if None in js:
            return np.zeros((0, 3), dtype=np.int64)
        out.append(js)
    return np.asarray(out, dtype=np.int64)


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _angle(u, v):
    return np.arccos(np.clip((_unit(u) * _unit(v)).sum(-1), -1.0, 1.0))


def _axis_angle(axis, angle):
    return R.from_axis_angle(_unit(axis) * angle[..., None])


def two_bone_ik(rotations: np.ndarray, global_rot: np.ndarray, positions: np.ndarray, *, hip: int, knee: int,
                ankle: int, target: np.ndarray) -> np.ndarray:
    """Analytic two-bone IK: new local rotations of hip and knee that put the ankle at ``target``.

    Parameters
    ----------
    rotations : ndarray [shape=(n, J, 4)]
        Local rotations (modified copy returned).
    global_rot, positions : ndarray [shape=(n, J, 4)], [shape=(n, J, 3)] metres
        Forward kinematics of ``rotations``.
    hip, knee, ankle : int
    target : ndarray [shape=(n, 3)], metres
        Unreachable targets are approached as far as the leg reaches.

    Returns
    -------
    ndarray [shape=(n, J, 4)]
        Local rotations; the ankle's local rotation is changed so that its world
        rotation stays what it was.
    """
    a, b, c = positions[:, hip], positions[:, knee], positions[:, ankle]
    l_ab = np.linalg.norm(b - a, axis=-1)
    l_cb = np.linalg.norm(b - c, axis=-1)
    l_at = np.clip(np.linalg.norm(target - a, axis=-1), 1e-4, l_ab + l_cb - 1e-4)
    ac_ab_0 = _angle(c - a, b - a)
    ba_bc_0 = _angle(a - b, c - b)
    ac_at_0 = _angle(c - a, target - a)
    ac_ab_1 = np.arccos(np.clip((l_cb ** 2 - l_ab ** 2 - l_at ** 2) / (-2 * l_ab * l_at), -1, 1))
    ba_bc_1 = np.arccos(np.clip((l_at ** 2 - l_ab ** 2 - l_cb ** 2) / (-2 * l_ab * l_cb), -1, 1))
    axis0 = np.cross(c - a, b - a)
    # a straight leg has no bend plane: bend about the hip's own x axis (knees bend forward)
    straight = np.linalg.norm(axis0, axis=-1) < 1e-8
    if straight.any():
        axis0[straight] = R.apply(global_rot[straight, hip], np.broadcast_to([1.0, 0, 0], (int(straight.sum()), 3)))
    axis1 = np.cross(c - a, target - a)
    ok1 = np.linalg.norm(axis1, axis=-1) > 1e-10
    axis1[~ok1] = axis0[~ok1]
    ac_at_0 = np.where(ok1, ac_at_0, 0.0)
    inv_a, inv_b = R.inverse(global_rot[:, hip]), R.inverse(global_rot[:, knee])
    r0 = _axis_angle(R.apply(inv_a, axis0), ac_ab_1 - ac_ab_0)
    r2 = _axis_angle(R.apply(inv_a, axis1), ac_at_0)
    r1 = _axis_angle(R.apply(inv_b, axis0), ba_bc_1 - ba_bc_0)
    out = rotations.copy()
    # in world terms: bend in the leg's own plane first (r0), then swing the ankle onto the target (r2)
    out[:, hip] = R.multiply(rotations[:, hip], R.multiply(r2, r0))
    out[:, knee] = R.multiply(rotations[:, knee], r1)
    # the knee's new world rotation = parent(hip) world * new hip local * new knee local
    hip_parent = R.multiply(global_rot[:, hip], R.inverse(rotations[:, hip]))
    knee_world = R.multiply(R.multiply(hip_parent, out[:, hip]), out[:, knee])
    out[:, ankle] = R.multiply(R.inverse(knee_world), global_rot[:, ankle])
    return out


def plant_feet(skeleton, fps: float, rotations: np.ndarray, root: np.ndarray, contacts: np.ndarray) -> np.ndarray:
    """Hold each planted ankle where its contact began (horizontally), by leg IK.

    Parameters
    ----------
    skeleton : gesturedb.motion.Skeleton
    fps : float
    rotations : ndarray [shape=(T, J, 4)]
    root : ndarray [shape=(T, 3)], metres
    contacts : ndarray [shape=(T, 2)], bool
        Left, right planted.

    Returns
    -------
    ndarray [shape=(T, J, 4)]
        Local rotations with the legs adjusted; the root and every other joint unchanged.
        After a contact the ankle returns to the motion's own path over
        ``RELEASE_FRAMES`` frames; a contact whose anchor is more than
        ``MAX_ANCHOR_DRIFT_M`` from the motion's ankle is re-anchored there.
    """
    legs = leg_joints(skeleton)
    T = rotations.shape[0]
    if legs.shape[0] == 0 or T == 0 or not contacts.any():
        return rotations
    pos, grot = Motion(skeleton=skeleton, fps=fps, rotations=rotations, root_positions=root).forward_kinematics()
    out = rotations
    for side in range(2):
        hip, knee, ankle = (int(j) for j in legs[side])
        free = pos[:, ankle]
        target = free.copy()
        weight = np.zeros(T)
        anchor = None
        since_release = RELEASE_FRAMES + 1
        for t in range(T):
            if contacts[t, side]:
                if anchor is None or np.linalg.norm((free[t] - anchor)[[0, 2]]) > MAX_ANCHOR_DRIFT_M:
                    anchor = free[t].copy()
                target[t, [0, 2]] = anchor[[0, 2]]
                weight[t] = 1.0
                since_release = 0
            elif anchor is not None:
                since_release += 1
                w = 1.0 - since_release / (RELEASE_FRAMES + 1)
                if w > 0:
                    target[t, [0, 2]] = w * anchor[[0, 2]] + (1 - w) * free[t, [0, 2]]
                    weight[t] = 1.0
                else:
                    anchor = None
        sel = np.flatnonzero(weight > 0)
        if sel.size == 0:
            continue
        new = two_bone_ik(out[sel], grot[sel], pos[sel], hip=hip, knee=knee, ankle=ankle, target=target[sel])
        out = out.copy()
        out[sel] = new
        # the other leg's chain does not depend on this one: positions of the other side stay valid
    return out
