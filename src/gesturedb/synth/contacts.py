"""Foot contacts and a two-bone leg IK that keeps planted feet in place.

Used by :func:`gesturedb.synth.assemble.assemble_pieces`: contacts are detected on
each source piece (so a mirrored recording or a time-warped clip is treated like
any other), and after placement the ankles of planted feet are held where the
contact began (at one height through the contact) by rotating hip and knee (analytic
two-bone IK); a lifted foot glides straight to where it comes down. The ankle keeps its
world orientation so the sole stays flat. The root is not moved.
"""
from __future__ import annotations

import math

import numpy as np

from gesturedb import rotations as R
from gesturedb.errors import ParameterError
from gesturedb.io.joints import ankle_joints, body_keys
from gesturedb.motion import forward_kinematics

__all__ = ["CONTACT_HEIGHT_M", "CONTACT_SPEED_M_S", "MAX_FILL_GAP_S", "FootPlanter", "fill_non_steps", "foot_contacts",
           "foot_joints", "leg_joints", "plant_feet", "smoothstep", "two_bone_ik"]

#: A foot's lowest point within this height (m) of the floor can be planted.
CONTACT_HEIGHT_M = 0.05
#: ... and its ankle moves horizontally slower than this (m/s).
CONTACT_SPEED_M_S = 0.3
#: Least frames of a lifted foot's glide from its anchor to where it comes down; its height returns to the
#: motion's over half of them.
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

    The ankles are :func:`gesturedb.io.joints.ankle_joints`' (those whose stance the pose
    features carry), the toes found by body part (:func:`gesturedb.io.joints.body_keys`); a side
    without a toe uses its ankle twice. Empty (0, 2) when the skeleton has no feet.
    """
    ankles = ankle_joints(skeleton.names)
    if ankles.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    keys = {k: j for j, k in body_keys(skeleton.names).items()}
    toes = [keys.get(f"{side}_toe", int(a)) for side, a in zip(("left", "right"), ankles)]
    return np.stack([ankles, np.asarray(toes, dtype=np.int64)], axis=1)


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
    # the arithmetic in C++ (csrc/ik.cpp, per frame, so blocks of any size give the same bits): this numpy
    # version (_two_bone_ik_numpy, the reference tests/test_placement.py compares it with) ran some eighty
    # small array operations per call, about 2.7 ms of a live step's apply in interpreter overhead
    import gesturedb._core as _core

    rot, grot, pos, tgt = (np.ascontiguousarray(x, dtype=np.float64) for x in (rotations, global_rot, positions, target))
    n = rot.shape[0]
    if rot.ndim != 3 or rot.shape[2] != 4:
        raise ParameterError(f"two_bone_ik: rotations: expected (n, J, 4); got {rot.shape}")
    J = rot.shape[1]
    for name, x, want in (("global_rot", grot, (n, J, 4)), ("positions", pos, (n, J, 3)), ("target", tgt, (n, 3))):
        if x.shape != want:
            raise ParameterError(f"two_bone_ik: {name}: expected {want}; got {x.shape}")
    for name, j in (("hip", hip), ("knee", knee), ("ankle", ankle)):
        if not 0 <= int(j) < J:
            raise ParameterError(f"two_bone_ik: {name}: expected a joint in [0, {J}); got {j}")
    return _core.two_bone_ik(rot, grot, pos, tgt, int(hip), int(knee), int(ankle))


def _two_bone_ik_numpy(rotations: np.ndarray, global_rot: np.ndarray, positions: np.ndarray, *, hip: int, knee: int,
                       ankle: int, target: np.ndarray) -> np.ndarray:
    """:func:`two_bone_ik` in numpy: the reference the C++ version is tested against (same arguments)."""
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


def _planar_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Horizontal (x, z) distance of two points (3,): ``np.linalg.norm((a - b)[[0, 2]])`` bit for bit (its
    own ``dot`` and a correctly rounded square root), without the wrapper's checks, taken per frame and
    side in a live step's foot planting."""
    d = (a - b)[[0, 2]]
    return math.sqrt(d.dot(d))


def smoothstep(x):
    """``3x^2 - 2x^3`` on [0, 1] (clipped): zero slope at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


#: The longest gap between two contacts (s) that :func:`fill_non_steps` may fill: a flicker of contact
#: detection, a heel lifting. Longer gaps are steps whatever the foot does, so whether a frame is planted
#: is known this long after it (a live stream's feet lag by this plus a step).
MAX_FILL_GAP_S = 0.4


class _Fill:
    """:func:`fill_non_steps` one frame at a time: ``planted[:n_done]`` is final once the frames after it
    have come (a gap is decided at its end or when it is longer than ``max_gap`` frames)."""

    def __init__(self, min_step_m: float, max_gap: int | None):
        self.min_step_m, self.max_gap = min_step_m, max_gap
        self.anchor = None
        self.n_done = 0

    def run(self, planted: np.ndarray, free: np.ndarray, out: np.ndarray, *, final: bool, base: int = 0) -> None:
        """Decide frames from ``n_done`` on, writing ``out`` (filled contacts) in place; ``planted``,
        ``free`` and ``out`` hold frames ``base ..`` of every frame so far (``T`` = the end)."""
        T = base + planted.shape[0]
        t = self.n_done
        while t < T:
            if planted[t - base]:
                if self.anchor is None:
                    self.anchor = free[t - base]
                out[t - base] = True
                t += 1
                continue
            g0, e = t, t
            cap = T if self.max_gap is None else min(T, g0 + self.max_gap + 1)
            while e < cap and not planted[e - base]:
                e += 1
            if e < T and planted[e - base]:  # the gap ended at e
                fill = (self.anchor is not None
                        and _planar_distance(free[e - base], self.anchor) < self.min_step_m)
                out[g0 - base:e - base] = fill
                if not fill:
                    self.anchor = None
            elif e < T or final:  # longer than max_gap, or the motion ends in it: not filled
                out[g0 - base:e - base] = False
                self.anchor = None
            else:  # undecided until more frames come
                break
            t = e
        self.n_done = t


def fill_non_steps(planted: np.ndarray, free: np.ndarray, min_step_m: float, max_gap: int | None = None) -> np.ndarray:
    """Contacts (T,) bool with every gap that is not a step filled.

    A gap between two contacts is a step when the foot comes down at least ``min_step_m``
    (horizontally) from where its previous contact began, the place a planted foot is held;
    a shorter gap (contact detection flickering while the foot rests, a heel lifting, the
    body shifting its weight) keeps the foot planted where it was, instead of easing it to
    where the motion puts it and planting it again there. A gap longer than ``max_gap``
    frames (None: no limit) is a step.

    planted : ndarray [shape=(T,)], bool
    free : ndarray [shape=(T, 3)], metres: the ankle where the motion puts it
    """
    out = np.zeros(planted.shape[0], dtype=bool)
    _Fill(min_step_m, max_gap).run(np.asarray(planted, dtype=bool), free, out, final=True)
    return out


class _Targets:
    """:func:`_ankle_targets` one frame at a time: a step and a lift read the contacts up to ``step_frames``
    ahead, so ``target[:n_done]`` is final at most ``step_frames`` frames after the contacts are."""

    def __init__(self, *, max_drift_m: float, step_frames: int, release_frames: int, step_height_m: float):
        self.max_drift_m, self.step_frames = max_drift_m, step_frames
        self.release_frames, self.step_height_m = release_frames, step_height_m
        self.anchor = None
        self.since_release = release_frames + 1
        #: a lifted foot's glide (:meth:`_lift`): (its first frame, its last frame, where it goes (3,), whether it
        #: lands there); None while planted or once the glide is over
        self.glide = None
        self.settle_until = 0  # frames before it: the planted ankle settles down with the motion
        self.n_done = 0

    def run(self, free: np.ndarray, planted: np.ndarray, target: np.ndarray, weight: np.ndarray, *,
            final: bool, base: int = 0) -> None:
        """Targets and weights from ``n_done`` up to the frames ``planted`` decides (its end), written in
        place; the arrays hold frames ``base ..`` (``base < n_done`` once a frame is done: a re-plant reads
        the target before it); ``free``, ``target`` and ``weight`` are at least as long as ``planted``,
        and ``target`` starts as a copy of ``free``. ``final``: ``planted`` covers the whole motion."""
        T = base + planted.shape[0]
        t = self.n_done
        while t < T:
            i = t - base
            if self.glide is None and self.anchor is not None and not planted[i] and self.since_release == 0:
                if not self._lift(i, t, free, planted, final=final):
                    break  # where the foot comes down is not known yet: the state stays as it was before frame t
            if self.glide is not None:
                self._glide(i, t, free, target, weight)
            elif planted[i]:
                anchor = self.anchor
                if anchor is None:
                    anchor = free[i].copy()
                    self.settle_until = t + self.release_frames
                elif self.since_release > 0:
                    # planted again after a step that ended in the air: the new contact starts where the ankle
                    # is now (going back to the old anchor would be a jump)
                    anchor = target[i - 1].copy()
                if _planar_distance(free[i], anchor) > self.max_drift_m:
                    # a step: from the anchor to where the motion has the foot at the step's end
                    if not final and t + self.step_frames >= T:
                        break  # its end has not come yet: the state stays as it was before frame t
                    end = min(t + self.step_frames, T - 1) - base
                    n = end - i + 1
                    u = np.arange(1, n + 1) / n
                    w = smoothstep(u)[:, None]
                    target[i:end + 1] = (1 - w) * anchor + w * free[end]
                    target[i:end + 1, 1] += self.step_height_m * np.sin(np.pi * u)
                    weight[i:end + 1] = True
                    self.anchor = free[end].copy()
                    self.since_release = 0 if planted[end] else 1
                    t = end + base + 1
                    continue
                if t < self.settle_until:
                    # a contact begins as the foot comes down, often on its toe or heel with the ankle still high:
                    # over its first release of frames the ankle settles with the motion (held at the contact's
                    # first height, a foot stood 6 cm up for seconds); then it keeps that height, and a seam's offset
                    # that moves the root up or down bends the knee instead of moving the foot (the floor bounds
                    # it). Following the motion down all through the contact (until the strokes issue) ratcheted
                    # planted ankles down and the floor pushed them up again: 0.029-0.032 m/s of vertical motion
                    # held out, where the capture's planted ankles have 0.014-0.022
                    anchor[1] = min(anchor[1], free[i, 1])
                self.anchor = anchor
                target[i] = anchor
                weight[i] = True
                self.since_release = 0
            else:  # in the air after a step that ended there: the motion's own path
                self.anchor = None
            t += 1
        self.n_done = t

    def _lift(self, i: int, t: int, free: np.ndarray, planted: np.ndarray, *, final: bool) -> bool:
        """The planted foot lifts at frame ``t`` (row ``i``): plan its glide from the anchor straight to where it
        comes down, the next contact if one comes within ``step_frames``, else onto the motion's path
        ``step_frames`` on. False when the contacts that decide it are not known yet.

        Gliding straight instead of easing back to the motion's path and following it: that path sweeps with
        every seam's offset on the legs (held out, seed 0, the feet moved 1.66x the capture's, 1.54x
        gliding). The capture's gaps between contacts last 0.4-1.6 s, about half within ``step_frames``;
        waiting for the longer ones would delay a live stream's frames by as much. A glide takes at least
        ``release_frames``: a contact that comes a frame after the lift, further than a foot's length away,
        would otherwise be a jump (0.31 m in a frame on a BEAT2 input)."""
        n = planted.shape[0]  # rows whose contacts are decided
        ahead = np.flatnonzero(planted[i + 1:min(i + 1 + self.step_frames, n)])
        if ahead.size:
            land = i + 1 + int(ahead[0])
            last = max(land - 1, i + self.release_frames - 1)
        else:
            if i + self.step_frames >= n and not final:
                return False
            land = last = min(i + self.step_frames - 1, n - 1)
        # no faster than a step: a foot far from its anchor (the motion swept it 0.64 m away on a BEAT2 input)
        # takes longer; the frames after ``land`` are not read, so this waits for nothing
        dist = _planar_distance(free[land], self.anchor)
        last = max(last, i + int(np.ceil(dist * self.step_frames / self.max_drift_m)) - 1)
        self.glide = (t, last + (t - i), free[land].copy(), bool(ahead.size))
        return True

    def _glide(self, i: int, t: int, free: np.ndarray, target: np.ndarray, weight: np.ndarray) -> None:
        """Frame ``t`` (row ``i``) of the glide :meth:`_lift` planned."""
        g0, g1, land, lands = self.glide
        self.since_release += 1
        w = smoothstep((t - g0 + 1) / (g1 - g0 + 1))
        to = land if lands else free[i]  # a foot still in the air eases back onto the motion's path
        target[i, [0, 2]] = (1 - w) * self.anchor[[0, 2]] + w * to[[0, 2]]
        # the height returns to the motion's over half the release: a foot that leaves the floor rises before it
        # slides (eased over the whole release, the feet slid low over the floor: skating 0.037-0.054 m/s on the
        # BEAT2 inputs against 0.028-0.048 this way, 0.027-0.046 before the hold) ...
        wy = 1.0 - smoothstep(self.since_release / (self.release_frames / 2 + 1))
        # and at least a step's arc, lower for a shorter way: a foot the motion barely lifts slid low over the
        # floor (skating 0.056-0.063 m/s on the inputs without the arc, 0.020-0.037 with it). The motion's own
        # lift shows in the middle only: the glide ends at the height where the foot lands (ending where the
        # motion had the foot just before, still coming down, held a foot 6 cm up for seconds)
        u = (t - g0 + 1) / (g1 - g0 + 1)
        lift = self.step_height_m * min(1.0, _planar_distance(to, self.anchor) / self.max_drift_m)
        arc = (1 - w) * self.anchor[1] + w * to[1] + lift * np.sin(np.pi * u)
        motion = wy * self.anchor[1] + (1 - wy) * free[i, 1]
        target[i, 1] = arc + max(0.0, motion - arc) * np.sin(np.pi * u)
        weight[i] = True
        if t == g1:  # over: the foot stands where it landed (and lifts again from there), or is released
            self.glide = None
            if lands:  # a landing is a contact's start: it settles as the motion comes down
                self.anchor, self.since_release, self.settle_until = target[i].copy(), 0, t + 1 + self.release_frames
            else:
                self.anchor = None


def _ankle_targets(free: np.ndarray, planted: np.ndarray, *, max_drift_m: float = MAX_ANCHOR_DRIFT_M,
                   step_frames: int = STEP_FRAMES, release_frames: int = RELEASE_FRAMES,
                   step_height_m: float = STEP_HEIGHT_M) -> tuple[np.ndarray, np.ndarray]:
    """Where one ankle should be (T, 3) and whether the IK applies (T,) bool, for :func:`plant_feet`.

    ``free`` is the ankle where the motion puts it, ``planted`` its contacts. A planted
    ankle is held where its contact began, settling down with the motion over the
    contact's first ``release_frames`` and at one height from then on (a seam's offset that
    moves the root up or down bends the knee instead). A step goes from there to
    where the motion has the foot at its end, lifted on the way. A lifted foot glides
    straight from its anchor to where it comes down (:meth:`_Targets._lift`). The
    defaults are the 15 fps values; :func:`plant_feet` derives them from the frame rate
    and the rig.
    """
    target = np.array(free, dtype=np.float64, copy=True)
    weight = np.zeros(free.shape[0], dtype=bool)
    _Targets(max_drift_m=max_drift_m, step_frames=step_frames, release_frames=release_frames,
             step_height_m=step_height_m).run(free, planted, target, weight, final=True)
    return target, weight


class FootPlanter:
    """:func:`plant_feet` over motion that arrives a block at a time (a live synthesis).

    :meth:`push` takes the next frames (local rotations, root, contacts) and returns the
    frames that no later frame can change any more, with the legs adjusted: whether a
    frame is planted is known :data:`MAX_FILL_GAP_S` after it, and a step needs the
    motion up to its end, so frames come out :attr:`lag` frames behind (all of them at
    ``final=True``). Pushing the same frames in blocks of any size gives the same bits as
    pushing them at once: every decision is taken frame by frame in order, the forward
    and inverse kinematics are per frame.
    """

    def __init__(self, skeleton, fps: float, *, max_gap_s: float = MAX_FILL_GAP_S, floor_y: float | None = None):
        self.skeleton, self.fps = skeleton, float(fps)
        #: no foot goes under this height (m): where the motion would put the lowest of its ankle and toe
        #: lower (the root of a seam's offset still low from a crouch, over a standing window), the ankle
        #: is raised by the leg IK (the knee bends) until it is on it; None: no floor
        self.floor_y = None if floor_y is None else float(floor_y)
        self.legs, self.feet = leg_joints(skeleton), foot_joints(skeleton)
        # frames from seconds, distances from the rig: the same behaviour at any frame rate and body size
        self.steps = dict(step_frames=max(2, int(round(STEP_S * fps))), release_frames=max(1, int(round(RELEASE_S * fps))))
        self.max_gap = max(1, int(round(max_gap_s * fps)))
        #: frames a pushed frame may wait before it is final
        self.lag = self.max_gap + 1 + self.steps["step_frames"]
        J = len(skeleton.names)
        self._rot = np.zeros((0, J, 4))
        self._contacts = np.zeros((0, 2), dtype=bool)
        self._base = 0  # the arrays below hold frames _base ..
        self._pos, self._grot = np.zeros((0, J, 3)), np.zeros((0, J, 4))
        self._sides = None  # per leg: (fill, targets, filled, target, weight), made at the first frame
        self.n_out = 0  # frames returned so far

    def _first_frame(self) -> None:
        pos = self._pos
        self._sides = []
        for side in range(self.legs.shape[0]):
            hip, knee, ankle = (int(j) for j in self.legs[side])
            leg_m = float(np.linalg.norm(pos[0, knee] - pos[0, hip]) + np.linalg.norm(pos[0, ankle] - pos[0, knee]))
            # a step moves a foot by at least its own length (ankle to toe on this rig)
            foot_len = (float(np.linalg.norm(pos[0, self.feet[side, 1]] - pos[0, self.feet[side, 0]]))
                        if self.feet.shape[0] and self.feet[side, 1] != self.feet[side, 0] else 0.0)
            fill = _Fill(foot_len, self.max_gap) if foot_len > 0 else None
            targets = _Targets(max_drift_m=STEP_DRIFT_LEG_FRACTION * leg_m, step_height_m=STEP_HEIGHT_LEG_FRACTION * leg_m,
                               **self.steps)
            self._sides.append([fill, targets, np.zeros(0, bool), np.zeros((0, 3)), np.zeros(0, bool)])

    def push(self, rotations: np.ndarray, root: np.ndarray, contacts: np.ndarray, *, final: bool = False) -> np.ndarray:
        """Add frames ``(n, J, 4)``, ``(n, 3)``, contacts ``(n, 2)`` bool; return the local rotations
        ``(k, J, 4)`` of the frames that became final (frames ``n_out - k .. n_out - 1``)."""
        n = rotations.shape[0]
        if n:
            pos, grot = forward_kinematics(self.skeleton, rotations, root)
            self._rot = np.concatenate([self._rot, rotations])
            self._contacts = np.concatenate([self._contacts, np.asarray(contacts, dtype=bool)])
            self._pos, self._grot = np.concatenate([self._pos, pos]), np.concatenate([self._grot, grot])
        base = self._base  # the arrays hold frames base ..
        T = base + self._rot.shape[0]
        done = T
        if self.legs.shape[0] and T:
            if self._sides is None:
                self._first_frame()
            for side, st in enumerate(self._sides):
                fill, targets = st[0], st[1]
                free = self._pos[:, int(self.legs[side, 2])]
                grow = T - base - st[2].shape[0]
                st[2] = np.concatenate([st[2], np.zeros(grow, bool)])
                st[3] = np.concatenate([st[3], free[free.shape[0] - grow:]])
                st[4] = np.concatenate([st[4], np.zeros(grow, bool)])
                if fill is not None:
                    fill.run(self._contacts[:, side], free, st[2], final=final, base=base)
                    decided = fill.n_done
                else:
                    st[2][:] = self._contacts[:, side]
                    decided = T
                targets.run(free, st[2][:decided - base], st[3], st[4], final=final, base=base)
                done = min(done, targets.n_done)
        if final:
            done = T
        a, b = self.n_out - base, done - base
        out = np.array(self._rot[a:b], copy=True)
        if self._sides is not None:
            for side, st in enumerate(self._sides):
                target, weight = st[3][a:b], st[4][a:b]
                if self.floor_y is not None and self.feet.shape[0]:
                    target, weight = self._above_floor(side, target, weight, a, b)
                sel = np.flatnonzero(weight)
                if sel.size == 0:
                    continue
                hip, knee, ankle = (int(j) for j in self.legs[side])
                # the other leg's chain does not depend on this one: positions of the other side stay valid
                out[sel] = two_bone_ik(out[sel], self._grot[a + sel], self._pos[a + sel], hip=hip, knee=knee,
                                       ankle=ankle, target=target[sel])
        self.n_out = done
        self._trim()
        return out

    def _above_floor(self, side: int, target: np.ndarray, weight: np.ndarray, a: int, b: int):
        """``target`` (n, 3) and ``weight`` (n,) of frames ``a .. b`` (array rows) with every ankle raised
        where its foot's lowest point would be under :attr:`floor_y` (the ankle keeps its world orientation
        in the IK, so the toe rises with it). Per frame: the same bits whatever the blocks."""
        ankle, toe = (int(j) for j in self.feet[side])
        ay, ty = self._pos[a:b, ankle, 1], self._pos[a:b, toe, 1]
        y = np.where(weight, target[:, 1], ay)  # where the ankle goes: the target where the IK applies
        low = np.minimum(y, ty + (y - ay))
        under = low < self.floor_y
        if not under.any():
            return target, weight
        target, weight = target.copy(), weight | under
        target[under, 1] = y[under] + (self.floor_y - low[under])
        return target, weight

    def _trim(self) -> None:
        """Drop the frames nothing reads again (a live stream's memory stays bounded): those returned and
        decided, less the one a re-plant reads."""
        keep = self.n_out
        if self._sides is not None:
            for fill, targets, *_ in self._sides:
                keep = min(keep, targets.n_done - 1, fill.n_done - 1 if fill is not None else keep)
        drop = keep - self._base
        if drop <= 0:
            return
        self._rot, self._contacts = self._rot[drop:], self._contacts[drop:]
        self._pos, self._grot = self._pos[drop:], self._grot[drop:]
        if self._sides is not None:
            for st in self._sides:
                st[2], st[3], st[4] = st[2][drop:], st[3][drop:], st[4][drop:]
        self._base = keep


def plant_feet(skeleton, fps: float, rotations: np.ndarray, root: np.ndarray, contacts: np.ndarray) -> np.ndarray:
    """Hold each planted ankle where its contact began, by leg IK (:func:`_ankle_targets`).

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
        A gap of up to :data:`MAX_FILL_GAP_S` between two contacts that is not a step keeps
        the foot planted (:func:`fill_non_steps`). After a contact the ankle glides (smoothstep)
        straight to where its next contact begins, if that comes within ``STEP_FRAMES``,
        else onto the motion's own path, over at least ``RELEASE_FRAMES``. When the motion
        carries a planted foot more than ``MAX_ANCHOR_DRIFT_M`` from its anchor (the body
        moved over it, or a seam changed the stance), the foot steps: over
        ``STEP_FRAMES`` frames the ankle follows a smoothstep from the anchor to
        where the motion puts it at the end of the step, lifted by up to
        ``STEP_HEIGHT_M``, and is planted again there (before, it was re-anchored
        in one frame: a jump of up to 0.3 m). :class:`FootPlanter` does the same a block
        of frames at a time.
    """
    if leg_joints(skeleton).shape[0] == 0 or rotations.shape[0] == 0 or not np.asarray(contacts).any():
        return rotations
    return FootPlanter(skeleton, fps).push(np.asarray(rotations), np.asarray(root), contacts, final=True)
