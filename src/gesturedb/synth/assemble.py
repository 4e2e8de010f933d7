"""Assembly: stretches of source motion ("pieces") -> one continuous output Motion.

Shared by both synthesis methods. The k-NN (:mod:`gesturedb.synth.matching`)
hands over one database frame per output frame (:func:`assemble_frames`); the
motion graph hands over time-warped clips. Both become a list of
:class:`Piece` and go through :func:`assemble_pieces`, so placement, seam
treatment and feet are the same for every method.

Placement (``placement="continue"``, the default). The first piece keeps its
own placement (recordings are normalised so that their mean floor position is
the origin and their mean heading +z). Every later piece is rotated about +y
and translated so that its first root position and heading continue the
output's current root (the previous piece's ``lead_in`` where there is one,
else a linear extrapolation of the last two output frames): a piece contributes
only its own displacement and turning relative to its start, never the absolute
place of its recording, so a seam between windows from different places does
not teleport the body. Two gentle pulls keep a long output near the origin and
facing forward: the heading decays towards +z with time constant
``HEADING_PULL_S`` and the horizontal root position towards the origin with
``POSITION_PULL_S`` (a leaky integration of the root's own velocity and turning,
so neither jumps). ``placement="source"``: the old behaviour, every piece where
its recording was.

Foot contacts (:mod:`gesturedb.synth.contacts`). A foot (ankle + toe) is planted
in a source frame when its lowest point is within ``CONTACT_HEIGHT_M`` of the
floor (the lowest foot point of all pieces) and its ankle moves horizontally
slower than ``CONTACT_SPEED_M_S`` (or, nearly still, within ``RESTING_HEIGHT_M``:
a foot on its heel or toe); contacts are computed on every piece's own
forward kinematics, so mirrored recordings and time-warped clips are handled
the same way (or given as ``Piece.contacts``). After the seams, any smoothing and the
pulls, a two-bone leg IK (hip, knee) holds each planted ankle where its contact
began, and the ankle keeps its world orientation; when the motion carries a
planted foot more than ``MAX_ANCHOR_DRIFT_M`` away, the foot takes a short
lifted step there. The root is not moved, so the cross-fade's slide is absorbed
by the legs instead of the feet (moving the root against the slip, which an
earlier version did, doubled the root's jerk and raised the pelvis speed by a
quarter on the four BEAT2 inputs).

Seams (:mod:`gesturedb.synth.seams`). At each piece boundary the difference between
the previous piece's natural continuation in its own recording (``Piece.lead_in``)
and the new piece, with its velocity and acceleration, is added to the new piece
and decays to zero over ``seam_decay_s`` (inertialization): position, velocity and
acceleration run on across the seam, and every frame ``seam_decay_s`` or more after
a seam is the placed source frame exactly. Nothing is low-passed, so the strokes
of the source motion are kept. ``seam_decay_s=0``: pieces back to back, as in the
paper. An earlier version cross-faded 4 frames and ran a Savitzky-Golay filter
(7 frames) over everything: at 15 fps that filter's zeros sit near 4 and 6 Hz and
it removed most beat strokes (``docs/metrics.md``, band power).

Smoothing (``smooth=True``, off by default). A Savitzky-Golay filter whose window
is defined in seconds (:data:`SMOOTH_WINDOW_S`, GestureMaster's 7 frames at 30 fps).
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from gesturedb import rotations as R
from gesturedb.motion import Motion
from gesturedb.synth.contacts import foot_contacts, foot_joints, plant_feet
from gesturedb.synth.seams import (
    LEAD_FRAMES, SEAM_DECAY_S, adaptive_decays, apply_rotation_offsets, check_decay_s, decay_frames, extend_constant_velocity,
    quintic_offsets, rotation_offsets, seam_derivatives,
)

__all__ = ["Piece", "SEAM_DECAY_S", "SMOOTH_WINDOW_S", "assemble_frames", "assemble_pieces", "continuation",
           "continuations", "foot_contacts", "foot_joints", "placed_frames", "savgol_smooth"]

#: Time constant (s) of the pull of the heading towards +z.
HEADING_PULL_S = 2.0
#: Time constant (s) of the pull of the horizontal root position towards the origin.
POSITION_PULL_S = 6.0



@dataclass
class Piece:
    """One stretch of output motion taken from the source.

    Attributes
    ----------
    out_start : int
        Output frame where the piece starts.
    rotations : ndarray [shape=(n, J, 4)], float64
        Local joint rotations (w, x, y, z), root rotation in the recording's normalised placement.
    root : ndarray [shape=(n, 3)], float64, metres
        Root positions in the recording's normalised placement.
    lead_in : tuple of ndarray or None
        ``(rotations (m, J, 4), root (m, 3))``: how the *previous* piece would have
        continued over this piece's first ``m`` frames in its own source (``m`` up to
        :data:`gesturedb.synth.seams.LEAD_FRAMES`); the seam's offset is measured
        against it. ``None``: the output is taken to go on at its last velocity.
        Expressed in the same coordinates as the previous piece.
    contacts : ndarray [shape=(n, 2)], bool, optional
        Left and right foot planted in each frame; ``None``: detected from the
        piece's own forward kinematics (:func:`foot_contacts`).
    """

    out_start: int
    rotations: np.ndarray
    root: np.ndarray
    lead_in: tuple[np.ndarray, np.ndarray] | None = None
    contacts: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.rotations.shape[0])


def _yaw_of(q: np.ndarray) -> np.ndarray:
    """Heading angle (rad, about +y) of the root's forward axis (+z) under rotations q (..., 4)."""
    fwd = R.apply(q, np.broadcast_to(np.array([0.0, 0.0, 1.0]), q.shape[:-1] + (3,)))
    return np.arctan2(fwd[..., 0], fwd[..., 2])


def _yaw_quat(angle: np.ndarray | float) -> np.ndarray:
    a = np.asarray(angle, dtype=np.float64) / 2
    return np.stack([np.cos(a), np.zeros_like(a), np.sin(a), np.zeros_like(a)], axis=-1)


# One placement per open database: computing it reads every frame's root once.
_PLACEMENT: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def recording_placement(db) -> tuple[np.ndarray, np.ndarray]:
    """Per-recording yaw (rad) and horizontal centre (m) that put each recording at the origin facing +z.

    Returns
    -------
    mean_yaw : ndarray [shape=(R,)], radians
        Circular mean of the root heading.
    centre : ndarray [shape=(R, 3)], metres
        Mean floor position (y = 0).
    """
    cached = _PLACEMENT.get(db)
    if cached is None:
        # one recording at a time, the root joint only (Database.rows): a client of a
        # sharded database never holds its rotations. bincount sums in frame order,
        # so the sums are those of one bincount over all frames, bit for bit.
        n = len(db.recordings)
        sums = np.zeros((n, 4))  # sin yaw, cos yaw, root x, root z
        for r in db.recordings:
            frames = np.arange(r.start_frame, r.stop_frame)
            yaw = _yaw_of(np.asarray(db.rows("local_rotations", frames, column=0), dtype=np.float64))
            root = np.asarray(db.rows("root_positions", frames), dtype=np.float64)
            at = np.zeros(frames.size, dtype=np.intp)
            for j, w in enumerate((np.sin(yaw), np.cos(yaw), root[:, 0], root[:, 2])):
                sums[r.index, j] = np.bincount(at, w, 1)[0]
        mean_yaw = np.arctan2(sums[:, 0], sums[:, 1])
        centre = np.stack([sums[:, 2], np.zeros(n), sums[:, 3]], 1)
        centre /= np.maximum(np.array([r.n_frames for r in db.recordings], dtype=np.int64), 1)[:, None]
        cached = _PLACEMENT[db] = (mean_yaw, centre)
    return cached


def placed_frames(db, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (n, J, 4) and root positions (n, 3) of database frames, normalised per recording."""
    frames = np.asarray(frames, dtype=np.int64)
    mean_yaw, centre = recording_placement(db)
    rec = db.rows("frame_recording", frames)
    rot = np.asarray(db.rows("local_rotations", frames), dtype=np.float64)
    root0 = np.asarray(db.rows("root_positions", frames), dtype=np.float64)
    q = _yaw_quat(-mean_yaw[rec])
    root = R.apply(q, root0 - centre[rec])
    root[:, 1] = root0[:, 1]
    rot[:, 0] = R.multiply(q, rot[:, 0])
    return rot, root


def continuation(db, last_frame: int, n: int) -> np.ndarray:
    """Up to ``n`` database frames that follow ``last_frame`` in its own recording (fewer where it ends)."""
    return continuations(db, [last_frame], [n])[0]


def continuations(db, last_frames, ns) -> list[np.ndarray]:
    """:func:`continuation` of many frames, with one read of the recordings of the frames involved.

    last_frames, ns : sequences of int [length K]
    Returns a list of K int64 arrays.
    """
    lasts = np.asarray(last_frames, dtype=np.int64).reshape(-1)
    cands = [int(f) + 1 + np.arange(max(int(n), 0), dtype=np.int64) for f, n in zip(lasts, ns)]
    cands = [c[c < db.n_frames] for c in cands]
    rec = db.rows("frame_recording", np.concatenate([lasts] + cands))
    out, at = [], lasts.size
    for i, c in enumerate(cands):
        same = rec[at:at + c.size] == rec[i]
        at += c.size
        out.append(c if same.all() else c[: int(np.argmin(same))])
    return out


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _place(rot: np.ndarray, root: np.ndarray, tf) -> tuple[np.ndarray, np.ndarray]:
    """Apply a placement ``(yaw rad, source origin (3,), output origin (3,))`` to rotations and root."""
    theta, src, dst = tf
    q = _yaw_quat(theta)
    rot = rot.copy()
    rot[:, 0] = R.multiply(np.broadcast_to(q, rot[:, 0].shape), rot[:, 0])
    d = root - src
    d[:, 1] = 0.0
    out = R.apply(np.broadcast_to(q, d.shape[:-1] + (4,)), d) + dst
    out[:, 1] = root[:, 1]
    return rot, out


def _pull(rot, root, fps):
    """Leaky integration of the root's turning and horizontal velocity towards +z and the origin."""
    T = root.shape[0]
    yaw = _yaw_of(rot[:, 0])
    kh = 1.0 / (HEADING_PULL_S * fps)
    kp = 1.0 / (POSITION_PULL_S * fps)
    h = np.empty(T)
    y = np.empty((T, 2))
    h[0] = yaw[0]
    y[0] = root[0, [0, 2]]
    dyaw = _wrap(np.diff(yaw))
    dx = np.diff(root[:, [0, 2]], axis=0)
    for t in range(1, T):
        h[t] = h[t - 1] + dyaw[t - 1] - kh * _wrap(h[t - 1])
        delta = h[t] - yaw[t]
        c, s = np.cos(delta), np.sin(delta)
        # rotation about +y by delta maps (x, z) -> (x cos + z sin, -x sin + z cos)
        v = np.array([c * dx[t - 1, 0] + s * dx[t - 1, 1], -s * dx[t - 1, 0] + c * dx[t - 1, 1]])
        y[t] = y[t - 1] + v - kp * y[t - 1]
    delta = h - yaw
    rot = rot.copy()
    rot[:, 0] = R.multiply(_yaw_quat(delta), rot[:, 0])
    root = root.copy()
    root[:, 0], root[:, 2] = y[:, 0], y[:, 1]
    return rot, root


def assemble_pieces(skeleton, fps: float, pieces: list[Piece], *, n_frames: int | None = None,
                    seam_decay_s: float = SEAM_DECAY_S, smooth: bool = False, placement: str = "continue",
                    lock_feet: bool = True, seam_accel: tuple | None = None) -> Motion:
    """Place pieces one after the other and inertialize each seam (:mod:`gesturedb.synth.seams`).

    Parameters
    ----------
    skeleton : gesturedb.motion.Skeleton
    fps : float
    pieces : list of Piece
        In output order; piece ``i`` covers output frames ``[out_start_i, out_start_{i+1})``
        (the last one up to ``n_frames``), and is cut to that span.
    n_frames : int, optional
        Output length (default: the end of the last piece).
    seam_decay_s : float >= 0
        Seconds over which the offset at a seam decays to zero; frames further from
        the last seam are the placed piece's frames exactly. 0: no seam treatment
        (pieces back to back, as in the paper).
    smooth : bool
        Savitzky-Golay filter over the result (:func:`savgol_smooth`; its window is
        defined in seconds). Off by default: it removes the beat strokes.
    placement : {"continue", "source"}
        ``"continue"``: each piece continues the output's root position and heading,
        with the pulls to the origin and +z; ``"source"``: each piece where its
        recording was (the behaviour before the placement issue). See the module docstring.
    lock_feet : bool
        Keep planted feet in place with leg IK (only with ``"continue"``).
    seam_accel : (ndarray [shape=(J,)] rad/s^2, float m/s^2), optional
        The source motion's typical angular acceleration per joint and the root's linear
        acceleration (:func:`typical_accelerations`): a seam's offset on a joint then decays
        over at least ``seam_decay_s`` and long enough not to accelerate that joint more than
        this (:func:`gesturedb.synth.seams.adaptive_decays`). None: ``seam_decay_s`` for all.
    """
    if not pieces:
        raise ValueError("assemble_pieces: expected at least one piece")
    if placement not in ("continue", "source"):
        raise ValueError(f"assemble_pieces: placement: expected 'continue' or 'source'; got {placement!r}")
    decay_s = check_decay_s(seam_decay_s)
    n_decay = decay_frames(decay_s, fps)
    T = pieces[-1].out_start + pieces[-1].n_frames if n_frames is None else int(n_frames)
    J = pieces[0].rotations.shape[1]
    rot = np.empty((T, J, 4))
    root = np.empty((T, 3))
    ends = [p.out_start for p in pieces[1:]] + [T]
    cont = placement == "continue"
    feet = foot_joints(skeleton) if cont and lock_feet else np.zeros((0, 2), dtype=np.int64)
    contacts = np.zeros((T, 2), dtype=bool)
    src_pos = []
    tf_prev = None
    active = None  # the _Offset being decayed
    for i, (p, b) in enumerate(zip(pieces, ends)):
        a = p.out_start
        if p.n_frames < b - a:
            raise ValueError(f"assemble_pieces: piece at frame {a} has {p.n_frames} frames, needs {b - a}")
        if b <= a:
            continue
        # the piece's first LEAD_FRAMES frames (where it is shorter, its own continuation is unknown:
        # it is extended at its last velocity) define the offset at its seam
        m = min(p.n_frames, max(b - a, LEAD_FRAMES))
        p_rot = np.asarray(p.rotations[:m], dtype=np.float64)
        p_root = np.asarray(p.root[:m], dtype=np.float64)
        lead = p.lead_in if (p.lead_in is not None and a > 0) else None
        if lead is not None and lead[0].shape[0] == 0:
            lead = None
        if cont:
            if tf_prev is None or a == 0:
                tf = (0.0, np.zeros(3), np.zeros(3))
            else:
                if lead is not None:
                    l_rot, l_root = _place(np.asarray(lead[0][:1], dtype=np.float64),
                                           np.asarray(lead[1][:1], dtype=np.float64), tf_prev)
                    target, target_yaw = l_root[0], float(_yaw_of(l_rot[0, 0]))
                else:
                    target = 2 * root[a - 1] - root[a - 2] if a >= 2 else root[a - 1]
                    target_yaw = float(_yaw_of(rot[a - 1, 0]))
                tf = (target_yaw - float(_yaw_of(p_rot[0, 0])), p_root[0], target)
            if feet.shape[0]:
                src_pos.append((a, b, p_rot[: b - a], p_root[: b - a], p.contacts))
            if lead is not None:
                lead = _place(np.asarray(lead[0], dtype=np.float64), np.asarray(lead[1], dtype=np.float64), tf_prev)
            p_rot, p_root = _place(p_rot, p_root, tf)
            tf_prev = tf
        elif lead is not None:
            lead = (np.asarray(lead[0], dtype=np.float64), np.asarray(lead[1], dtype=np.float64))
        if n_decay > 0 and a > 0 and (lead is not None or a >= 2):
            active = _seam_offset(rot, root, a, lead, p_rot, p_root, active, fps=fps, decay_s=decay_s,
                                  accel=seam_accel)
        rot[a:b] = p_rot[: b - a]
        root[a:b] = p_root[: b - a]
        if active is not None and active.seam + active.n_frames > a:
            k = np.arange(a, min(b, active.seam + active.n_frames))
            rot[k], root[k] = active.apply(rot[k], root[k], (k - active.seam) / fps)
    if src_pos:
        # the pieces' own (unplaced) poses, by one forward kinematics over all of them (one call per piece
        # was a fifth of a k-NN synthesis); contacts need only heights and speeds, which placement keeps
        pos = Motion(skeleton=skeleton, fps=fps, rotations=np.concatenate([q[2] for q in src_pos]),
                     root_positions=np.concatenate([q[3] for q in src_pos])).positions
        cuts = np.cumsum([q[1] - q[0] for q in src_pos])[:-1]
        pieces_pos = np.split(pos, cuts)
        floor_y = min(float(pp[:, feet, 1].min()) for pp in pieces_pos if pp.shape[0])
        for (a, b, _, _, given), pp in zip(src_pos, pieces_pos):
            contacts[a:b] = (np.asarray(given[: b - a], dtype=bool) if given is not None
                             else foot_contacts(pp, fps=fps, feet=feet, floor_y=floor_y))
    if smooth:
        rot, root = savgol_smooth(rot, root, fps=fps)
    if cont:
        rot, root = _pull(rot, root, fps)
        if feet.shape[0]:
            rot = plant_feet(skeleton, fps, rot, root, contacts)
    return Motion(skeleton=skeleton, fps=fps, rotations=rot, root_positions=root)


def _seam_offset(rot, root, a, lead, p_rot, p_root, active, *, fps, decay_s, accel=None) -> "_Offset":
    """The offset that the seam at output frame ``a`` starts.

    The old motion over frames ``a .. a+2`` is its own continuation (``lead``, placed in output
    coordinates), extended at its last velocity where it has fewer frames (from the output's
    last two frames where it has none), plus the offset still active from an earlier seam;
    the new motion is the placed piece's first frames.
    """
    n = LEAD_FRAMES
    if lead is not None:
        got = min(lead[0].shape[0], n)
        l_rot, l_root = lead[0][:got], lead[1][:got]
        if active is not None:
            # an offset still decaying from an earlier seam goes on under the old motion: the output ran with it
            l_rot, l_root = active.apply(l_rot, l_root, (a + np.arange(got) - active.seam) / fps)
        if got >= n:
            old_rot, old_root = l_rot, l_root
        else:  # the old recording ends within the stencil: on at its last velocity (the output's last frame first)
            seq_rot, seq_root = np.concatenate([rot[a - 1:a], l_rot]), np.concatenate([root[a - 1:a], l_root])
            e_rot, e_root = extend_constant_velocity(seq_rot, seq_root, n - got)
            old_rot, old_root = np.concatenate([l_rot, e_rot]), np.concatenate([l_root, e_root])
    else:  # no continuation at all: the output (offset included) goes on at its last velocity
        old_rot, old_root = extend_constant_velocity(rot[a - 2:a], root[a - 2:a], n)
    new_rot, new_root = p_rot[:n], p_root[:n]
    if new_rot.shape[0] < n:
        if new_rot.shape[0] < 2:
            new_rot, new_root = np.concatenate([new_rot, new_rot]), np.concatenate([new_root, new_root])
        e_rot, e_root = extend_constant_velocity(new_rot, new_root, n - new_rot.shape[0])
        new_rot, new_root = np.concatenate([new_rot, e_rot])[:n], np.concatenate([new_root, e_root])[:n]
    d_rot = rotation_offsets(old_rot, new_rot)
    # rotation vectors wrap at pi: keep the three samples on one branch so their differences are small
    ang = np.linalg.norm(d_rot, axis=-1, keepdims=True)
    flip = ((d_rot * d_rot[:1]).sum(-1, keepdims=True) < 0) & (ang > np.pi / 2)
    d_rot = np.where(flip, d_rot - 2 * np.pi * d_rot / np.maximum(ang, 1e-12), d_rot)
    r_der, p_der = seam_derivatives(d_rot, fps), seam_derivatives(old_root - new_root, fps)
    if accel is None:
        dr, dp = decay_s, decay_s
    else:
        # no longer than a few times the base decay: a seam between opposite poses still ends
        dr = np.minimum(adaptive_decays(r_der[0], r_der[1], accel[0], decay_s), MAX_DECAY_FACTOR * decay_s)
        dp = float(np.minimum(adaptive_decays(p_der[0], p_der[1], accel[1], decay_s), MAX_DECAY_FACTOR * decay_s)[0])
    n = decay_frames(float(np.max(dr)), fps)
    return _Offset(a, r_der, p_der, dr, dp, max(n, decay_frames(float(dp), fps)))


class _Offset(NamedTuple):
    """The offset a seam started: ``(x0, v0, a0)`` of the joints' rotation vectors (J, 3) and of the
    root position (3,), their decays (s; per joint (J, 1) or one), and the frames it lasts."""

    seam: int
    rot: tuple
    root: tuple
    decay_rot: np.ndarray | float
    decay_root: float
    n_frames: int

    def apply(self, rot: np.ndarray, root: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (n, J, 4) and root (n, 3) with the offset at times ``t`` (s after the seam) added."""
        return (apply_rotation_offsets(quintic_offsets(*self.rot, self.decay_rot, t), rot),
                root + quintic_offsets(*self.root, self.decay_root, t))


#: The longest decay of an adaptive seam, in base decays (``seam_decay_s``).
MAX_DECAY_FACTOR = 3.0


# One acceleration reference per open database (reads a bounded sample of frames once).
_ACCEL: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
#: Frames read for :func:`typical_accelerations` (contiguous runs spread over the database).
ACCEL_SAMPLE_FRAMES = 1 << 15


def typical_accelerations(db) -> tuple[np.ndarray, float]:
    """RMS angular acceleration of every joint's local rotation (J,) rad/s^2 and of the root position (m/s^2).

    Measured on the database's own motion (mirrored copies included), within recordings, from
    up to :data:`ACCEL_SAMPLE_FRAMES` frames in runs of one chunk spread evenly over the database.
    """
    cached = _ACCEL.get(db)
    if cached is not None:
        return cached
    run = 64
    n_runs = max(1, min(db.n_frames // run, ACCEL_SAMPLE_FRAMES // run))
    starts = np.linspace(0, max(db.n_frames - run, 0), n_runs).astype(np.int64)
    frames = (starts[:, None] + np.arange(min(run, db.n_frames))[None]).ravel()
    rec = np.asarray(db.rows("frame_recording", frames)).reshape(n_runs, -1)
    q = np.asarray(db.rows("local_rotations", frames), dtype=np.float64).reshape(n_runs, rec.shape[1], -1, 4)
    p = np.asarray(db.rows("root_positions", frames), dtype=np.float64).reshape(n_runs, rec.shape[1], 3)
    fps = db.fps
    w = R.to_axis_angle(R.multiply(q[:, 1:], R.inverse(q[:, :-1]))) * fps  # (runs, n-1, J, 3) rad/s
    acc_w = np.linalg.norm(np.diff(w, axis=1), axis=-1) * fps  # (runs, n-2, J)
    acc_p = np.linalg.norm(np.diff(p, n=2, axis=1), axis=-1) * fps * fps  # (runs, n-2)
    ok = (rec[:, 2:] == rec[:, :-2])  # the three frames of a stencil in one recording
    if not ok.any():
        cached = (np.full(q.shape[2], np.inf), float("inf"))
    else:
        cached = (np.sqrt((acc_w[ok] ** 2).mean(axis=0)), float(np.sqrt((acc_p[ok] ** 2).mean())))
    _ACCEL[db] = cached
    return cached


def assemble_frames(db, source: np.ndarray, starts: np.ndarray, *, seam_decay_s: float = SEAM_DECAY_S,
                    smooth: bool = False, placement: str = "continue", lock_feet: bool = True) -> Motion:
    """Copy chosen database frames into one :class:`Motion` (the k-NN path).

    Parameters
    ----------
    db : gesturedb.db.database.Database
    source : ndarray [shape=(T,)], int64
        Database frame for every output frame.
    starts : ndarray, int64
        Output frame where each window starts (the first is 0).
    seam_decay_s, smooth, placement, lock_feet
        See :func:`assemble_pieces`.
    """
    source = np.asarray(source, dtype=np.int64)
    starts = [int(s) for s in starts]
    ends = starts[1:] + [source.shape[0]]
    decay_s = check_decay_s(seam_decay_s)
    # every frame the pieces and their lead-ins use, read at once: a database
    # that is not loaded (Database.rows) costs one read per run of frames, not
    # several per piece. A piece shorter than the seam's stencil reads its own
    # recording's next frames too (the output ends or the next seam comes first).
    seams = [i for i, a in enumerate(starts) if a > 0 and decay_s > 0]
    conts = [np.zeros(0, np.int64)] * len(starts)
    for i, c in zip(seams, continuations(db, [source[starts[i] - 1] for i in seams], [LEAD_FRAMES] * len(seams))):
        conts[i] = c
    tails = [np.zeros(0, np.int64)] * len(starts)
    short = [i for i, (a, b) in enumerate(zip(starts, ends)) if 0 < b - a < LEAD_FRAMES]
    for i, c in zip(short, continuations(db, [source[ends[i] - 1] for i in short],
                                         [LEAD_FRAMES - (ends[i] - starts[i]) for i in short])):
        tails[i] = c
    used = np.concatenate([source] + conts + tails)
    rot_all, root_all = placed_frames(db, used)
    # where each piece's lead-in and tail sit in the one read
    cont_at = source.size + np.cumsum([0] + [c.size for c in conts])
    tail_at = cont_at[-1] + np.cumsum([0] + [t.size for t in tails])
    out = []
    for i, (a, b) in enumerate(zip(starts, ends)):
        c0, c1, t0, t1 = cont_at[i], cont_at[i + 1], tail_at[i], tail_at[i + 1]
        out.append(Piece(out_start=a, rotations=np.concatenate([rot_all[a:b], rot_all[t0:t1]]),
                         root=np.concatenate([root_all[a:b], root_all[t0:t1]]),
                         lead_in=(rot_all[c0:c1], root_all[c0:c1]) if c1 > c0 else None))
    return assemble_pieces(db.skeleton, db.fps, out, n_frames=source.shape[0],
                           seam_decay_s=decay_s, smooth=smooth, placement=placement, lock_feet=lock_feet,
                           seam_accel=typical_accelerations(db) if decay_s > 0 else None)


#: Savitzky-Golay window (s) of the optional smoothing: GestureMaster's 7 frames at its 30 fps (Sec. 4.2).
SMOOTH_WINDOW_S = 7.0 / 30.0


def savgol_smooth(rotations: np.ndarray, root: np.ndarray, *, fps: float, window_s: float = SMOOTH_WINDOW_S,
                  order: int = 2):
    """Savitzky-Golay smoothing of local rotations (T, J, 4) and root positions (T, 3) over time.

    The window is ``window_s`` seconds rounded to an odd number of frames at ``fps``
    (5 frames at 15 fps, 7 at 30 fps for the default): the same filter in time at any
    frame rate. Quaternions are first made continuous in time (q and -q are one
    rotation), filtered component-wise and renormalised: for the small angles between
    neighbouring frames this is close to filtering on the rotation manifold. Sequences
    shorter than the window, or windows too short for ``order``, are returned unchanged.
    """
    from scipy.signal import savgol_filter

    window = int(round(window_s * fps)) | 1
    if rotations.shape[0] < window or window <= order:
        return rotations, root
    q = savgol_filter(R.make_continuous(rotations, axis=0), window, order, axis=0)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q, savgol_filter(root, window, order, axis=0)
