"""Assembly: stretches of source motion ("pieces") -> one continuous output Motion.

Shared by both synthesis methods. The k-NN (:mod:`gesturedb.synth.matching`)
hands over one database frame per output frame (:func:`assemble_frames`); the
motion graph hands over time-warped clips. Both become a list of
:class:`Piece` and go through :func:`assemble_pieces`, so placement, seam blends
and smoothing are the same for every method.

Placement. Every piece keeps the placement of its own recording, normalised
once so that each recording's mean floor position is the origin and its mean
heading +z (chaining pieces onto each other's heading would integrate the
source's small turns into a slow spin).

Seams. After each piece boundary a short cross-fade (``blend_frames``, default
4) slerps (rotations) and lerps (root) from the previous piece's natural
continuation in its source into the new piece, with smoothstep weights, so
neither position nor velocity jumps at the seam. ``blend_frames=0``: pieces
back to back, as in the paper.

Smoothing. A Savitzky-Golay filter (window 7, order 2) over rotations and root,
as GestureMaster (Sec. 4.2) smooths its output.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from gesturedb import rotations as R
from gesturedb.motion import Motion

__all__ = ["Piece", "assemble_frames", "assemble_pieces", "continuation", "placed_frames", "savgol_smooth"]


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
        continued over this piece's first ``m`` frames in its own source; the
        seam cross-fade starts from it. ``None``: no cross-fade into this piece.
    """

    out_start: int
    rotations: np.ndarray
    root: np.ndarray
    lead_in: tuple[np.ndarray, np.ndarray] | None = None

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
        rec = db.frame_recording
        yaw = _yaw_of(np.asarray(db.local_rotations[:, 0], dtype=np.float64))
        root = np.asarray(db.root_positions, dtype=np.float64)
        n = len(db.recordings)
        mean_yaw = np.arctan2(np.bincount(rec, np.sin(yaw), n), np.bincount(rec, np.cos(yaw), n))
        centre = np.stack([np.bincount(rec, root[:, 0], n), np.zeros(n), np.bincount(rec, root[:, 2], n)], 1)
        centre /= np.maximum(np.bincount(rec, minlength=n), 1)[:, None]
        cached = _PLACEMENT[db] = (mean_yaw, centre)
    return cached


def placed_frames(db, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (n, J, 4) and root positions (n, 3) of database frames, normalised per recording."""
    frames = np.asarray(frames, dtype=np.int64)
    mean_yaw, centre = recording_placement(db)
    rec = db.frame_recording[frames]
    rot = np.asarray(db.local_rotations[frames], dtype=np.float64)
    root = np.asarray(db.root_positions[frames], dtype=np.float64)
    q = _yaw_quat(-mean_yaw[rec])
    root = R.apply(q, root - centre[rec])
    root[:, 1] = np.asarray(db.root_positions[frames, 1], dtype=np.float64)
    rot[:, 0] = R.multiply(q, rot[:, 0])
    return rot, root


def continuation(db, last_frame: int, n: int) -> np.ndarray:
    """Up to ``n`` database frames that follow ``last_frame`` in its own recording (fewer where it ends)."""
    cont = int(last_frame) + 1 + np.arange(n)
    ok = cont < db.n_frames
    ok[ok] &= db.frame_recording[cont[ok]] == db.frame_recording[int(last_frame)]
    return cont if ok.all() else cont[: int(np.argmin(ok))]


def assemble_pieces(skeleton, fps: float, pieces: list[Piece], *, n_frames: int | None = None,
                    blend_frames: int = 4, smooth: bool = True) -> Motion:
    """Lay pieces end to end, cross-fade each seam from the previous piece's continuation, smooth.

    Parameters
    ----------
    skeleton : gesturedb.motion.Skeleton
    fps : float
    pieces : list of Piece
        In output order; piece ``i`` covers output frames ``[out_start_i, out_start_{i+1})``
        (the last one up to ``n_frames``), and is cut to that span.
    n_frames : int, optional
        Output length (default: the end of the last piece).
    blend_frames : int
        Cross-fade length after each seam that has a ``lead_in`` (0: no cross-fade).
    smooth : bool
        Savitzky-Golay filter over the result.
    """
    if not pieces:
        raise ValueError("assemble_pieces: expected at least one piece")
    T = pieces[-1].out_start + pieces[-1].n_frames if n_frames is None else int(n_frames)
    J = pieces[0].rotations.shape[1]
    rot = np.empty((T, J, 4))
    root = np.empty((T, 3))
    ends = [p.out_start for p in pieces[1:]] + [T]
    for p, b in zip(pieces, ends):
        a = p.out_start
        if p.n_frames < b - a:
            raise ValueError(f"assemble_pieces: piece at frame {a} has {p.n_frames} frames, needs {b - a}")
        rot[a:b] = p.rotations[: b - a]
        root[a:b] = p.root[: b - a]
        if blend_frames > 0 and p.lead_in is not None and a > 0:
            c_rot, c_root = p.lead_in
            n_bl = min(blend_frames, b - a, c_rot.shape[0])
            if n_bl == 0:
                continue
            x = (np.arange(1, n_bl + 1) / (n_bl + 1))[:, None]
            w = x * x * (3 - 2 * x)
            rot[a:a + n_bl] = R.slerp(c_rot[:n_bl], rot[a:a + n_bl], w)
            root[a:a + n_bl] = (1 - w) * c_root[:n_bl] + w * root[a:a + n_bl]
    if smooth:
        rot, root = savgol_smooth(rot, root)
    return Motion(skeleton=skeleton, fps=fps, rotations=rot, root_positions=root)


def assemble_frames(db, source: np.ndarray, starts: np.ndarray, *, blend_frames: int = 4,
                    smooth: bool = True) -> Motion:
    """Copy chosen database frames into one :class:`Motion` (the k-NN path).

    Parameters
    ----------
    db : gesturedb.db.database.Database
    source : ndarray [shape=(T,)], int64
        Database frame for every output frame.
    starts : ndarray, int64
        Output frame where each window starts (the first is 0).
    blend_frames, smooth
        See :func:`assemble_pieces`.
    """
    source = np.asarray(source, dtype=np.int64)
    starts = [int(s) for s in starts]
    pieces = []
    for i, a in enumerate(starts):
        b = starts[i + 1] if i + 1 < len(starts) else source.shape[0]
        rot, root = placed_frames(db, source[a:b])
        lead_in = None
        if a > 0 and blend_frames > 0:
            cont = continuation(db, int(source[a - 1]), min(blend_frames, b - a))
            if cont.size:
                lead_in = placed_frames(db, cont)
        pieces.append(Piece(out_start=a, rotations=rot, root=root, lead_in=lead_in))
    return assemble_pieces(db.skeleton, db.fps, pieces, n_frames=source.shape[0],
                           blend_frames=blend_frames, smooth=smooth)


def savgol_smooth(rotations: np.ndarray, root: np.ndarray, *, window: int = 7, order: int = 2):
    """Savitzky-Golay smoothing of local rotations (T, J, 4) and root positions (T, 3) over time.

    Quaternions are first made continuous in time (q and -q are one rotation),
    filtered component-wise and renormalised: for the small angles between
    neighbouring frames this is close to filtering on the rotation manifold.
    Sequences shorter than the window are returned unchanged.
    """
    from scipy.signal import savgol_filter

    if rotations.shape[0] < window:
        return rotations, root
    q = savgol_filter(R.make_continuous(rotations, axis=0), window, order, axis=0)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q, savgol_filter(root, window, order, axis=0)
