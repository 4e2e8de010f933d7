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

__all__ = ["CONTACT_HEIGHT_M", "CONTACT_SPEED_M_S", "fill_non_steps", "foot_contacts", "foot_joints", "leg_joints",
           "plant_feet", "smoothstep", "two_bone_ik"]

#: A foot's lowest point within this height (m) of the floor can be planted.
CONTACT_HEIGHT_M = 0.05
#: ... and its ankle moves horizontally slower than this (m/s).
CONTACT_SPEED_M_S = 0.3
#: Frames over which a released foot returns from its anchor to where the motion puts it.
RELEASE_FRAMES = 6
#: A foot that is nearly still (ankle slower than this, m/s) is planted up to ``RESTING_HEIGHT_M`` above the
#: floor: a foot resting on its heel or toe has its lowest joint a few centimetres higher than one flat on the
#: floor, and left unplanted it slides with every seam blend around it.
RESTING_SPEED_M_S = 0.1
RESTING_HEIGHT_M = 0.10
#: A planted foot whose anchor is further than this (m, horizontally) from where the motion puts the foot
#: takes a step: the leg would otherwise stretch straight (and its knee snap) to hold it.
MAX_ANCHOR_DRIFT_M = 0.2
#: Frames of such a step, and how high (m) the ankle lifts at its middle: a short arc, not a slide.
STEP_FRAMES = 10
STEP_HEIGHT_M = 0.05
#: What :func:`plant_feet` uses, by frame rate and rig: a release and a step in seconds (the frames
#: above at 15 fps); the drift that makes a planted foot step as a fraction of the leg's length (hip to
#: knee to ankle): about half a short step's length. At 0.2 m (0.22 legs, the value until the strokes
#: issue) the anchored feet stepped every few seconds as the root's path wandered from the stance,
#: and the mean foot speed was 1.3-1.4x the capture's on the BEAT2 inputs; at 0.35 legs 1.0-1.1x.
RELEASE_S = RELEASE_FRAMES / 15.0
STEP_S = STEP_FRAMES / 15.0
STEP_DRIFT_LEG_FRACTION = 0.35
STEP_HEIGHT_LEG_FRACTION = 0.055


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
    return (((low <= floor_y + height_m) & (speed < speed_m_s))
            | ((low <= floor_y + RESTING_HEIGHT_M) & (speed < RESTING_SPEED_M_S)))


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


def smoothstep(x):
    """``3x^2 - 2x^3`` on [0, 1] (clipped): zero slope at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _ankle_targets(free: np.ndarray, planted: np.ndarray, *, max_drift_m: float = MAX_ANCHOR_DRIFT_M,
                   step_frames: int = STEP_FRAMES, release_frames: int = RELEASE_FRAMES,
                   step_height_m: float = STEP_HEIGHT_M) -> tuple[np.ndarray, np.ndarray]:
    """Where one ankle should be (T, 3) and whether the IK applies (T,) bool, for :func:`plant_feet`.

    ``free`` is the ankle where the motion puts it, ``planted`` its contacts. Horizontal
    targets only, except during a step, which also lifts the ankle. The defaults are the
    15 fps values; :func:`plant_feet` derives them from the frame rate and the rig.
    """
    T = free.shape[0]
    target = free.copy()
    weight = np.zeros(T, dtype=bool)
    anchor = None
    since_release = release_frames + 1
    t = 0
    while t < T:
        if planted[t]:
            if anchor is None:
                anchor = free[t].copy()
            elif since_release > 0:
                # planted again while easing back from the last anchor: the new contact starts where the
                # ankle is now (going back to the old anchor would be a jump)
                anchor = target[t - 1].copy()
            if np.linalg.norm((free[t] - anchor)[[0, 2]]) > max_drift_m:
                # a step: from the anchor to where the motion has the foot at the step's end
                end = min(t + step_frames, T - 1)
                n = end - t + 1
                u = np.arange(1, n + 1) / n
                w = smoothstep(u)[:, None]
                target[t:end + 1, [0, 2]] = (1 - w) * anchor[[0, 2]] + w * free[end, [0, 2]]
                target[t:end + 1, 1] = free[t:end + 1, 1] + step_height_m * np.sin(np.pi * u)
                weight[t:end + 1] = True
                anchor = free[end].copy()
                since_release = 0 if planted[end] else 1
                t = end + 1
                continue
            target[t, [0, 2]] = anchor[[0, 2]]
            weight[t] = True
            since_release = 0
        elif anchor is not None:
            since_release += 1
            w = 1.0 - smoothstep(since_release / (release_frames + 1))
            if since_release <= release_frames:
                target[t, [0, 2]] = w * anchor[[0, 2]] + (1 - w) * free[t, [0, 2]]
                weight[t] = True
            else:
                anchor = None
        t += 1
    return target, weight


def fill_non_steps(planted: np.ndarray, free: np.ndarray, min_step_m: float) -> np.ndarray:
    """Contacts (T,) bool with every gap that is not a step filled.

    A gap between two contacts is a step when the foot comes down at least ``min_step_m``
    (horizontally) from where its previous contact began, the place a planted foot is held;
    a shorter gap (contact detection flickering while the foot rests, a heel lifting, the
    body shifting its weight) keeps the foot planted where it was, instead of easing it to
    where the motion puts it and planting it again there.

    planted : ndarray [shape=(T,)], bool
    free : ndarray [shape=(T, 3)], metres: the ankle where the motion puts it
    """
    out = planted.copy()
    T = planted.shape[0]
    t = 0
    anchor = None
    while t < T:
        if out[t]:
            if anchor is None:
                anchor = free[t]
            t += 1
            continue
        g0 = t
        while t < T and not out[t]:
            t += 1
        if anchor is not None and t < T and np.linalg.norm((free[t] - anchor)[[0, 2]]) < min_step_m:
            out[g0:t] = True  # not a step: the foot stays where it is
        else:
            anchor = None
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
        ``RELEASE_FRAMES`` frames (smoothstep). When the motion carries a planted
        foot more than ``MAX_ANCHOR_DRIFT_M`` from its anchor (the body moved
        over it, or a seam changed the stance), the foot steps: over
        ``STEP_FRAMES`` frames the ankle follows a smoothstep from the anchor to
        where the motion puts it at the end of the step, lifted by up to
        ``STEP_HEIGHT_M``, and is planted again there (before, it was re-anchored
        in one frame: a jump of up to 0.3 m).
    """
    legs = leg_joints(skeleton)
    T = rotations.shape[0]
    if legs.shape[0] == 0 or T == 0 or not contacts.any():
        return rotations
    pos, grot = Motion(skeleton=skeleton, fps=fps, rotations=rotations, root_positions=root).forward_kinematics()
    out = rotations
    feet = foot_joints(skeleton)
    # frames from seconds, distances from the rig: the same behaviour at any frame rate and body size
    steps = dict(step_frames=max(2, int(round(STEP_S * fps))), release_frames=max(1, int(round(RELEASE_S * fps))))
    for side in range(2):
        hip, knee, ankle = (int(j) for j in legs[side])
        leg_m = float(np.linalg.norm(pos[0, knee] - pos[0, hip]) + np.linalg.norm(pos[0, ankle] - pos[0, knee]))
        steps.update(max_drift_m=STEP_DRIFT_LEG_FRACTION * leg_m, step_height_m=STEP_HEIGHT_LEG_FRACTION * leg_m)
        # a step moves a foot by at least its own length (ankle to toe on this rig)
        foot_len = (float(np.linalg.norm(pos[0, feet[side, 1]] - pos[0, feet[side, 0]]))
                    if feet.shape[0] and feet[side, 1] != feet[side, 0] else 0.0)
        planted = fill_non_steps(contacts[:, side], pos[:, ankle], foot_len) if foot_len > 0 else contacts[:, side]
        target, weight = _ankle_targets(pos[:, ankle], planted, **steps)
        sel = np.flatnonzero(weight > 0)
        if sel.size == 0:
            continue
        new = two_bone_ik(out[sel], grot[sel], pos[sel], hip=hip, knee=knee, ankle=ankle, target=target[sel])
        out = out.copy()
        out[sel] = new
        # the other leg's chain does not depend on this one: positions of the other side stay valid
    return out
