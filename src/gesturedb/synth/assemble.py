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
from gesturedb.motion import Motion, forward_kinematics
from gesturedb.search import _core  # the compiled core, or its build hint where it is missing
from gesturedb.synth.contacts import FootPlanter, foot_contacts, foot_joints
from gesturedb.synth.seams import (
    LEAD_FRAMES,
    SEAM_DECAY_S,
    adaptive_decays,
    check_decay_s,
    continuous_rotation_vectors,
    decay_frames,
    extend_constant_velocity,
    rotation_offsets,
    seam_derivatives,
)

__all__ = ["Piece", "PieceAssembler", "SEAM_DECAY_S", "SMOOTH_WINDOW_S", "assemble_frames", "assemble_pieces",
           "continuation", "continuations", "floor_height", "foot_contacts", "foot_joints", "placed_frames",
           "savgol_smooth"]

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
    # R.apply(q, (0, 0, 1)) written out for that vector, every product and sum of it kept in its order (the
    # zeros too: they decide the sign of a zero), so the same bits without its broadcasting and checks,
    # which cost more than the arithmetic on a live step's few frames (called five times a step)
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    t0 = 2.0 * (y * 1.0 - z * 0.0)
    t1 = 2.0 * (z * 0.0 - x * 1.0)
    t2 = 2.0 * (x * 0.0 - y * 0.0)
    fx = 0.0 + w * t0 + (y * t2 - z * t1)
    fz = 1.0 + w * t2 + (x * t1 - y * t0)
    return np.arctan2(fx, fz)


def _yaw_quat(angle: np.ndarray | float) -> np.ndarray:
    a = np.asarray(angle, dtype=np.float64) / 2
    out = np.zeros(a.shape + (4,))
    out[..., 0] = np.cos(a)
    out[..., 2] = np.sin(a)
    return out


# One placement per recording of an open database, computed when a piece first needs it (a first
# frame then reads its own recording's roots, not those of the 648 recordings of a paper-scale file).
_PLACEMENT: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def recording_placement(db, recordings=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-recording yaw (rad) and horizontal centre (m) that put each recording at the origin facing +z.

    Parameters
    ----------
    recordings : array-like of int, optional
        Only these recording indices (in this order); default every recording.

    Returns
    -------
    mean_yaw : ndarray [shape=(R,)], radians
        Circular mean of the root heading.
    centre : ndarray [shape=(R, 3)], metres
        Mean floor position (y = 0).
    """
    cached = _PLACEMENT.setdefault(db, {})  # recording index -> (yaw, centre)
    want = [r.index for r in db.recordings] if recordings is None else [int(r) for r in np.asarray(recordings).ravel()]
    todo = sorted({r for r in want if r not in cached})
    if todo:
        # one recording at a time, the root joint only (Database.rows): a client of a
        # sharded database never holds its rotations. bincount sums in frame order,
        # so the sums are those of one bincount over all frames, bit for bit.
        sums = np.zeros((len(todo), 4))  # sin yaw, cos yaw, root x, root z
        for i, ri in enumerate(todo):
            r = db.recordings[ri]
            frames = np.arange(r.start_frame, r.stop_frame)
            yaw = _yaw_of(np.asarray(db.rows("local_rotations", frames, column=0), dtype=np.float64))
            root = np.asarray(db.rows("root_positions", frames), dtype=np.float64)
            at = np.zeros(frames.size, dtype=np.intp)
            for j, w in enumerate((np.sin(yaw), np.cos(yaw), root[:, 0], root[:, 2])):
                sums[i, j] = np.bincount(at, w, 1)[0]
        mean_yaw = np.arctan2(sums[:, 0], sums[:, 1])
        centre = np.stack([sums[:, 2], np.zeros(len(todo)), sums[:, 3]], 1)
        centre /= np.maximum(np.array([db.recordings[ri].n_frames for ri in todo], dtype=np.int64), 1)[:, None]
        for i, ri in enumerate(todo):
            cached[ri] = (mean_yaw[i], centre[i])
    return (np.array([cached[r][0] for r in want], dtype=np.float64).reshape(len(want)),
            np.array([cached[r][1] for r in want], dtype=np.float64).reshape(len(want), 3))


def placed_frames(db, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (n, J, 4) and root positions (n, 3) of database frames, normalised per recording."""
    frames = np.asarray(frames, dtype=np.int64)
    rec = db.rows("frame_recording", frames)
    if rec.size and (rec == rec[0]).all():  # a window: one recording (np.unique's answer, at a third of its cost)
        recs, rec = rec[:1], np.zeros(rec.size, dtype=np.intp)
    else:
        recs, rec = np.unique(rec, return_inverse=True)  # only the recordings of these frames are placed
    mean_yaw, centre = recording_placement(db, recs)
    rot = np.asarray(db.rows("local_rotations", frames), dtype=np.float64)
    root0 = np.asarray(db.rows("root_positions", frames), dtype=np.float64)
    # the turn and the root's rotation in C++ (csrc/assembly.cpp): rotations.multiply and rotations.apply's
    # operations, the same bits, without a dozen numpy calls on a live step's few frames
    return _core().place_frames(_yaw_quat(-mean_yaw[rec]), np.ascontiguousarray(rot), root0,
                              np.ascontiguousarray(centre[rec]), None, False)


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
    # in C++ (csrc/assembly.cpp): rot[:, 0] = R.multiply(q, rot[:, 0]) and, with d = root - src with its y
    # zeroed, R.apply(q, d) + dst with the y of root, their operations in their order: the same bits
    return _core().place_frames(_yaw_quat(theta)[None], np.ascontiguousarray(rot, dtype=np.float64),
                              np.ascontiguousarray(root, dtype=np.float64),
                              np.ascontiguousarray(src, dtype=np.float64).reshape(1, 3),
                              np.ascontiguousarray(dst, dtype=np.float64), True)


class _Pull:
    """Leaky integration of the root's turning and horizontal velocity towards +z and the origin,
    a block of frames at a time (causal: a frame's pull depends only on the frames before it)."""

    def __init__(self, fps: float):
        self.kh = 1.0 / (HEADING_PULL_S * fps)
        self.kp = 1.0 / (POSITION_PULL_S * fps)
        self.last = None  # (yaw, root (x, z), pulled heading, pulled (x, z)) of the last frame

    def run(self, rot: np.ndarray, root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = root.shape[0]
        if T == 0:
            return rot, root
        yaw = _yaw_of(rot[:, 0])
        xz = root[:, [0, 2]]
        if self.last is None:
            h_prev, y_prev = yaw[0], xz[0]
            dyaw, dx, first = _wrap(np.diff(yaw)), np.diff(xz, axis=0), 1
        else:
            yaw0, xz0, h_prev, y_prev = self.last
            dyaw = _wrap(np.diff(np.concatenate([[yaw0], yaw])))
            dx, first = np.diff(np.concatenate([xz0[None], xz]), axis=0), 0
        # the loop over frames in C++ (csrc/assembly.cpp, the same operations: tests/test_placement.py checks it
        # against this loop in numpy to the bit), where it cost a live step about ten numpy calls a frame
        h, y = _core().pull_root(np.ascontiguousarray(yaw, dtype=np.float64), np.ascontiguousarray(dyaw),
                               np.ascontiguousarray(dx, dtype=np.float64), first, self.kh, self.kp, float(h_prev),
                               float(y_prev[0]), float(y_prev[1]))
        self.last = (yaw[-1], xz[-1], h[-1], y[-1])
        delta = h - yaw
        rot = rot.copy()
        rot[:, 0] = R.multiply(_yaw_quat(delta), rot[:, 0])
        root = root.copy()
        root[:, 0], root[:, 2] = y[:, 0], y[:, 1]
        return rot, root


def _pull(rot, root, fps):
    """Leaky integration of the root's turning and horizontal velocity towards +z and the origin."""
    return _Pull(fps).run(rot, root)


def assemble_pieces(skeleton, fps: float, pieces: list[Piece], *, n_frames: int | None = None,
                    seam_decay_s: float = SEAM_DECAY_S, smooth: bool = False, placement: str = "continue",
                    lock_feet: bool = True, seam_accel: tuple | None = None, floor_y: float | None = None) -> Motion:
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
    floor_y : float, optional
        Floor height (m) for the foot contacts (:func:`floor_height` of the database); None:
        the lowest foot point of all pieces (known only once every piece is in).

    The pieces go through a :class:`PieceAssembler` (``batch=True``): placement and seams piece
    by piece as a live synthesis places them, the kinematics of all frames at once.
    """
    if not pieces:
        raise ValueError("assemble_pieces: expected at least one piece")
    T = pieces[-1].out_start + pieces[-1].n_frames if n_frames is None else int(n_frames)
    asm = PieceAssembler(skeleton, fps, seam_decay_s=seam_decay_s, smooth=smooth, placement=placement,
                         lock_feet=lock_feet, seam_accel=seam_accel, floor_y=floor_y, batch=True)
    ends = [p.out_start for p in pieces[1:]] + [T]
    blocks = [asm.add(p, end=b) for p, b in zip(pieces, ends)] + [asm.finish()]
    rot = np.concatenate([r for r, _ in blocks])
    root = np.concatenate([x for _, x in blocks])
    return Motion(skeleton=skeleton, fps=fps, rotations=rot, root_positions=root)


class PieceAssembler:
    """:func:`assemble_pieces` one piece at a time: each :meth:`add` returns the output frames that
    no later piece can change, :meth:`finish` the rest.

    Placement and seams are causal (a piece's frames are set when it comes; a seam's offset changes
    only the frames after it), the pulls too; the feet are planted :attr:`lag` frames behind
    (:class:`gesturedb.synth.contacts.FootPlanter`). Whatever the pieces' timing, the frames are the
    same bits as one :func:`assemble_pieces` call over the same pieces (that call is this class with
    ``batch=True``, which runs the kinematics once over all frames at :meth:`finish`: every decision is
    taken frame by frame in the same order, and forward and inverse kinematics, the pulls and the
    contacts are per-frame numpy operations, which give the same bits in blocks of any size;
    ``tests/test_stream.py`` checks both on the real inputs). With ``floor_y=None`` (the floor of all
    pieces) or ``smooth=True`` nothing is final before :meth:`finish` either.
    """

    def __init__(self, skeleton, fps: float, *, seam_decay_s: float = SEAM_DECAY_S, smooth: bool = False,
                 placement: str = "continue", lock_feet: bool = True, seam_accel: tuple | None = None,
                 floor_y: float | None = None, batch: bool = False):
        if placement not in ("continue", "source"):
            raise ValueError(f"assemble_pieces: placement: expected 'continue' or 'source'; got {placement!r}")
        self.skeleton, self.fps = skeleton, float(fps)
        self.decay_s = check_decay_s(seam_decay_s)
        self.n_decay = decay_frames(self.decay_s, fps)
        self.smooth, self.seam_accel, self.floor_y = bool(smooth), seam_accel, floor_y
        self.cont = placement == "continue"
        self.feet = foot_joints(skeleton) if self.cont and lock_feet else np.zeros((0, 2), dtype=np.int64)
        J = len(skeleton.names)
        # the placed output (before the pulls and the feet) from frame _base on: every frame when
        # deferred to finish(), else the last two (a seam without lead-in extrapolates them)
        self._rot, self._root = np.zeros((0, J, 4)), np.zeros((0, 3))
        self._contacts = np.zeros((0, 2), dtype=bool)
        self._base = 0
        self._src_pos = []  # floor_y=None: (a, b, rotations, root, given contacts) of every piece, for finish()
        self._tf_prev = None
        self._active = None  # the _Offset being decayed
        self._deferred = batch or self.smooth or (self.feet.shape[0] > 0 and floor_y is None)
        self._pull = _Pull(fps) if self.cont else None
        self._planter = (FootPlanter(skeleton, fps, floor_y=floor_y) if self.feet.shape[0] and not self._deferred
                         else None)
        self._pulled_root = np.zeros((0, 3))  # pulled root of the frames the planter holds back
        self.n_placed = 0
        self.n_out = 0
        self._finished = False

    @property
    def lag(self) -> int:
        """Frames an output frame may wait after its piece came (0 without planted feet)."""
        return 0 if self._planter is None else self._planter.lag

    def add(self, p: Piece, *, end: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Place piece ``p`` over output frames ``[p.out_start, end)`` (default: its own length; it must
        start where the last one ended); return the rotations ``(k, J, 4)`` and root ``(k, 3)`` of the
        frames that became final (output frames ``n_out - k .. n_out - 1``)."""
        a = p.out_start
        b = a + p.n_frames if end is None else int(end)
        if p.n_frames < b - a:
            raise ValueError(f"assemble_pieces: piece at frame {a} has {p.n_frames} frames, needs {b - a}")
        if b <= a:
            return self._empty()
        if a != self.n_placed:
            raise ValueError(f"assemble_pieces: piece at frame {a}, expected one at frame {self.n_placed}")
        fps = self.fps
        # the piece's first LEAD_FRAMES frames (where it is shorter, its own continuation is unknown:
        # it is extended at its last velocity) define the offset at its seam
        m = min(p.n_frames, max(b - a, LEAD_FRAMES))
        p_rot = np.asarray(p.rotations[:m], dtype=np.float64)
        p_root = np.asarray(p.root[:m], dtype=np.float64)
        lead = p.lead_in if (p.lead_in is not None and a > 0) else None
        if lead is not None and lead[0].shape[0] == 0:
            lead = None
        o = self._base  # rot[i] is output frame o + i
        rot = np.concatenate([self._rot, np.empty((b - a,) + self._rot.shape[1:])])
        root = np.concatenate([self._root, np.empty((b - a, 3))])
        contacts = np.zeros((b - a, 2), dtype=bool)
        if self.cont:
            tf_prev = self._tf_prev
            if tf_prev is None or a == 0:
                tf = (0.0, np.zeros(3), np.zeros(3))
            else:
                if lead is not None:
                    l_rot, l_root = _place(np.asarray(lead[0][:1], dtype=np.float64),
                                           np.asarray(lead[1][:1], dtype=np.float64), tf_prev)
                    target, target_yaw = l_root[0], float(_yaw_of(l_rot[0, 0]))
                else:
                    target = 2 * root[a - o - 1] - root[a - o - 2] if a >= 2 else root[a - o - 1]
                    target_yaw = float(_yaw_of(rot[a - o - 1, 0]))
                tf = (target_yaw - float(_yaw_of(p_rot[0, 0])), p_root[0], target)
            if self.feet.shape[0]:
                given = p.contacts
                if self._deferred:
                    self._src_pos.append((a, b, p_rot[: b - a], p_root[: b - a], given))
                elif given is not None:
                    contacts[:] = np.asarray(given[: b - a], dtype=bool)
                else:
                    # contacts need only heights and speeds, which placement keeps: the piece's own poses
                    pos, _ = forward_kinematics(self.skeleton, p_rot[: b - a], p_root[: b - a], want_rotations=False)
                    contacts[:] = foot_contacts(pos, fps=fps, feet=self.feet, floor_y=self.floor_y)
            if lead is not None:
                lead = _place(np.asarray(lead[0], dtype=np.float64), np.asarray(lead[1], dtype=np.float64), tf_prev)
            p_rot, p_root = _place(p_rot, p_root, tf)
            self._tf_prev = tf
        elif lead is not None:
            lead = (np.asarray(lead[0], dtype=np.float64), np.asarray(lead[1], dtype=np.float64))
        if self.n_decay > 0 and a > 0 and (lead is not None or a >= 2):
            # _seam_offset reads at most the two output frames before the seam, which are kept
            self._active = _seam_offset(rot, root, a, lead, p_rot, p_root, self._active, fps=fps,
                                        decay_s=self.decay_s, accel=self.seam_accel, base=o)
        rot[a - o:] = p_rot[: b - a]
        root[a - o:] = p_root[: b - a]
        active = self._active
        if active is not None and active.seam + active.n_frames > a:
            k = np.arange(a, min(b, active.seam + active.n_frames))
            rot[k - o], root[k - o] = active.apply(rot[k - o], root[k - o], (k - active.seam) / fps)
        self.n_placed = b
        if self._deferred:
            self._rot, self._root = rot, root
            self._contacts = np.concatenate([self._contacts, contacts])
            return self._empty()
        out = self._emit(rot[a - o:], root[a - o:], contacts, final=False)
        keep = min(2, rot.shape[0])
        self._rot, self._root, self._base = rot[-keep:], root[-keep:], b - keep
        return out

    def _empty(self):
        return np.zeros((0,) + self._rot.shape[1:]), np.zeros((0, 3))

    def _emit(self, rot, root, contacts, *, final: bool):
        """Pull the next placed frames, plant the feet; the frames now final."""
        if self._pull is not None:
            rot, root = self._pull.run(rot, root)
        if self._planter is None:
            self.n_out += rot.shape[0]
            return rot, root
        self._pulled_root = np.concatenate([self._pulled_root, root])
        out = self._planter.push(rot, root, contacts, final=final)
        k = out.shape[0]
        done_root, self._pulled_root = self._pulled_root[:k], self._pulled_root[k:]
        self.n_out += k
        return out, done_root

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """The frames still held back (all of them with ``floor_y=None`` or ``smooth=True``)."""
        if self._finished:
            raise ValueError("PieceAssembler.finish: already finished")
        self._finished = True
        if not self._deferred:
            if self._planter is None:
                return self._empty()
            e_rot, e_root = self._empty()
            return self._emit(e_rot, e_root, np.zeros((0, 2), dtype=bool), final=True)
        rot, root, fps = self._rot, self._root, self.fps
        floor_y = self.floor_y
        if self._src_pos:
            # the pieces' own (unplaced) poses, by one forward kinematics over all of them (as add's, per piece)
            pos, _ = forward_kinematics(self.skeleton, np.concatenate([q[2] for q in self._src_pos]),
                                        np.concatenate([q[3] for q in self._src_pos]), want_rotations=False)
            cuts = np.cumsum([q[1] - q[0] for q in self._src_pos])[:-1]
            pieces_pos = np.split(pos, cuts)
            if floor_y is None:
                floor_y = min(float(pp[:, self.feet, 1].min()) for pp in pieces_pos if pp.shape[0])
            for (a, b, _, _, given), pp in zip(self._src_pos, pieces_pos):
                self._contacts[a:b] = (np.asarray(given[: b - a], dtype=bool) if given is not None
                                       else foot_contacts(pp, fps=fps, feet=self.feet, floor_y=floor_y))
        if self.smooth:
            rot, root = savgol_smooth(rot, root, fps=fps)
        if self.cont:
            rot, root = self._pull.run(rot, root)
            if self.feet.shape[0]:
                rot = FootPlanter(self.skeleton, fps, floor_y=floor_y).push(rot, root, self._contacts, final=True)
        self.n_out = rot.shape[0]
        return rot, root


def _seam_offset(rot, root, a, lead, p_rot, p_root, active, *, fps, decay_s, accel=None, base=0) -> "_Offset":
    """The offset that the seam at output frame ``a`` starts (``rot[i]``, ``root[i]``: output frame ``base + i``).

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
            i = a - base
            seq_rot, seq_root = np.concatenate([rot[i - 1:i], l_rot]), np.concatenate([root[i - 1:i], l_root])
            e_rot, e_root = extend_constant_velocity(seq_rot, seq_root, n - got)
            old_rot, old_root = np.concatenate([l_rot, e_rot]), np.concatenate([l_root, e_root])
    else:  # no continuation at all: the output (offset included) goes on at its last velocity
        i = a - base
        old_rot, old_root = extend_constant_velocity(rot[i - 2:i], root[i - 2:i], n)
    new_rot, new_root = p_rot[:n], p_root[:n]
    if new_rot.shape[0] < n:
        if new_rot.shape[0] < 2:
            new_rot, new_root = np.concatenate([new_rot, new_rot]), np.concatenate([new_root, new_root])
        e_rot, e_root = extend_constant_velocity(new_rot, new_root, n - new_rot.shape[0])
        new_rot, new_root = np.concatenate([new_rot, e_rot])[:n], np.concatenate([new_root, e_root])[:n]
    # in C++ (csrc/assembly.cpp): the arithmetic below in numpy (_seam_arithmetic_numpy, the reference
    # tests/test_placement.py holds it to) ran some forty small array operations per seam
    r_der, p_der, dr, dp = _core().seam_offset(
        *(np.ascontiguousarray(x, dtype=np.float64) for x in (old_rot, new_rot, old_root, new_root)), float(fps),
        None if accel is None else np.ascontiguousarray(accel[0], dtype=np.float64),
        0.0 if accel is None else float(accel[1]), float(decay_s), MAX_DECAY_FACTOR * decay_s)
    n = decay_frames(float(np.max(dr)), fps)
    return _Offset(a, tuple(r_der), tuple(p_der), dr, dp, max(n, decay_frames(float(dp), fps)))


def _seam_arithmetic_numpy(old_rot, new_rot, old_root, new_root, *, fps, decay_s, accel=None):
    """What :func:`_seam_offset` computes in C++, in numpy: ``(r_der, p_der, dr, dp)``, the joints' and the
    root's ``(x0, v0, a0)`` ((J, 3) each, (3,) each) and their decays ((J,) s, a float)."""
    # rotation vectors wrap at pi: each sample on the branch nearest the one before, so that the
    # differences are the motion's
    d_rot = continuous_rotation_vectors(rotation_offsets(old_rot, new_rot))
    r_der, p_der = seam_derivatives(d_rot, fps), seam_derivatives(old_root - new_root, fps)
    if accel is None:
        return r_der, p_der, np.full(old_rot.shape[1], float(decay_s)), float(decay_s)
    # no longer than a few times the base decay: a seam between opposite poses still ends
    dr = np.minimum(adaptive_decays(r_der[0], r_der[1], accel[0], decay_s), MAX_DECAY_FACTOR * decay_s)
    dp = float(np.minimum(adaptive_decays(p_der[0], p_der[1], accel[1], decay_s), MAX_DECAY_FACTOR * decay_s)[0])
    return r_der, p_der, dr[:, 0], dp


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
        # in C++ (csrc/seams.cpp), per frame, so a stream's and the offline synthesis's frames stay the same
        # bits: the rotations as seams.apply_quintic_rotation_offsets, the root as root + seams.quintic_offsets
        # (the same operations). Called without that function's checks: the offsets come from _core.seam_offset
        # as contiguous float64 of the right shapes, and the core checks them again
        t = np.ascontiguousarray(t, dtype=np.float64)
        return (_core().apply_quintic_rotation_offsets(*self.rot, self.decay_rot, t,
                                                     np.ascontiguousarray(rot, dtype=np.float64)),
                _core().add_quintic_offsets(*self.root, self.decay_root, t,
                                          np.ascontiguousarray(root, dtype=np.float64)))


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


def window_piece(db, frames: np.ndarray, out_start: int, *, prev_frame: int | None, seam_decay_s: float) -> Piece:
    """The :class:`Piece` of one window of database frames (the k-NN's).

    Parameters
    ----------
    frames : ndarray [shape=(n,)], int64
        Database frame of each output frame of the window.
    out_start : int
        Its first output frame.
    prev_frame : int or None
        The previous window's last database frame: the piece's lead-in is how that window goes
        on in its recording (read when ``seam_decay_s > 0``).

    A window shorter than the seam's stencil (:data:`LEAD_FRAMES`) reads its own recording's
    next frames too (the output ends or the next seam comes first).
    """
    return window_pieces(db, [(frames, out_start, prev_frame)], seam_decay_s=seam_decay_s)[0]


def window_pieces(db, windows, *, seam_decay_s: float) -> list[Piece]:
    """:func:`window_piece` of many windows ``(frames, out_start, prev_frame)`` with one read of the
    database: a database that is not loaded (Database.rows) costs one read per run of frames, not
    several per piece. The same pieces as one window at a time (placement is per frame)."""
    windows = [(np.asarray(f, dtype=np.int64), int(a), p) for f, a, p in windows]
    heads = [(i, p, LEAD_FRAMES) for i, (f, a, p) in enumerate(windows)
             if p is not None and a > 0 and seam_decay_s > 0]
    tails = [(i, int(f[-1]), LEAD_FRAMES - f.shape[0]) for i, (f, a, p) in enumerate(windows)
             if 0 < f.shape[0] < LEAD_FRAMES]
    asked = heads + tails
    got = continuations(db, [x[1] for x in asked], [x[2] for x in asked]) if asked else []
    cont = {i: c for (i, _, _), c in zip(heads, got[:len(heads)])}
    tail = {i: c for (i, _, _), c in zip(tails, got[len(heads):])}
    none = np.zeros(0, np.int64)
    parts = [(f, cont.get(i, none), tail.get(i, none)) for i, (f, _, _) in enumerate(windows)]
    rot_all, root_all = placed_frames(db, np.concatenate([x for part in parts for x in part]))
    out, at = [], 0
    for (f, c, t), (_, a, _) in zip(parts, windows):
        n, c1, t1 = f.shape[0], f.shape[0] + c.shape[0], f.shape[0] + c.shape[0] + t.shape[0]
        rot, root = rot_all[at:at + t1], root_all[at:at + t1]
        at += t1
        out.append(Piece(out_start=a, rotations=np.concatenate([rot[:n], rot[c1:]]),
                         root=np.concatenate([root[:n], root[c1:]]),
                         lead_in=(rot[n:c1], root[n:c1]) if c.shape[0] else None))
    return out


# One floor height per open database (reads a bounded sample of frames once).
_FLOOR: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def floor_height(db) -> float:
    """The floor of the database's motion (m): the lowest ankle or toe over up to
    :data:`ACCEL_SAMPLE_FRAMES` frames spread over the database (all of a small one).

    Foot contacts are measured against it, so that a piece's contacts are known when the
    piece comes (the lowest foot of all pieces, the floor before, is known only at the end).
    """
    cached = _FLOOR.get(db)
    if cached is None:
        feet = np.unique(foot_joints(db.skeleton).ravel())
        if feet.size == 0 or db.n_frames == 0:
            cached = 0.0
        else:
            frames = np.arange(db.n_frames)
            if db.n_frames > ACCEL_SAMPLE_FRAMES:
                frames = np.unique(np.linspace(0, db.n_frames - 1, ACCEL_SAMPLE_FRAMES).astype(np.int64))
            cached = min(float(np.asarray(db.rows("joint_positions", frames, column=int(j)))[:, 1].min())
                         for j in feet)
        _FLOOR[db] = cached
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
        See :func:`assemble_pieces`; contacts are measured against :func:`floor_height`.
    """
    source = np.asarray(source, dtype=np.int64)
    starts = [int(s) for s in starts]
    ends = starts[1:] + [source.shape[0]]
    decay_s = check_decay_s(seam_decay_s)
    pieces = window_pieces(db, [(source[a:b], a, int(source[a - 1]) if a > 0 else None)
                                for a, b in zip(starts, ends)], seam_decay_s=decay_s)
    return assemble_pieces(db.skeleton, db.fps, pieces, n_frames=source.shape[0],
                           seam_decay_s=decay_s, smooth=smooth, placement=placement, lock_feet=lock_feet,
                           seam_accel=typical_accelerations(db) if decay_s > 0 else None, floor_y=floor_height(db))


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
