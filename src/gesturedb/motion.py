"""Skeletons and motion: forward kinematics, resampling, left/right mirroring.

World axes are y up, metres, seconds; +x is the speaker's left when the speaker
faces +z. Rotations are local unit quaternions ``(w, x, y, z)`` (see
`gesturedb.rotations`): joint ``j`` is placed at
``p[parent] + R_world[parent] @ offsets[j]`` and turns by
``R_world[j] = R_world[parent] @ R_local[j]``.

Frame ``i`` of a `Motion` is at time ``i / fps`` seconds; a clip of ``n``
frames spans ``(n - 1) / fps`` seconds and is said to last ``n / fps``.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from gesturedb import rotations as rot
from gesturedb.errors import ParameterError

__all__ = ["Motion", "Skeleton", "forward_kinematics", "mirror_permutation", "resampled_length"]

# Quaternions further than this from unit norm are rejected rather than silently
# renormalised: they come from a bug (an unnormalised blend), not from rounding.
_UNIT_TOL = 1e-3

@dataclass(eq=False)
class Skeleton:
    """A joint hierarchy with rest offsets.

    Parameters
    ----------
    names : list of str [length J]
        Unique joint names; ``names[0]`` is the root.
    parents : ndarray [shape=(J,)], int64
        Parent index of each joint, -1 for the root; every parent index is
        smaller than its child's, so a single forward pass visits parents first.
    offsets : ndarray [shape=(J, 3)], metres
        Rest offset of each joint from its parent (for the root: its rest
        position).
    channel_orders : list of str [length J]
        Euler order of each joint's rotation channels as written in BVH, e.g.
        ``"ZXY"``; ``""`` for a joint without rotation channels.
    end_sites : dict of int to ndarray [shape=(3,)], metres
        Joint index -> BVH End Site offset from that joint.
    length_unit_m : float
        Metres per length unit of the file the skeleton came from (0.01 for a
        BVH in centimetres), so a writer can write back in the same units.
        Offsets are always stored in metres.
    """

    names: list
    parents: np.ndarray
    offsets: np.ndarray
    channel_orders: list
    end_sites: dict = field(default_factory=dict)
    length_unit_m: float = 1.0

    def __post_init__(self):
        self.names = [str(n) for n in self.names]
        n = len(self.names)
        if n == 0:
            raise ParameterError("Skeleton.names: expected at least one joint; got none")
        if len(set(self.names)) != n:
            dup = sorted({x for x in self.names if self.names.count(x) > 1})
            raise ParameterError(f"Skeleton.names: expected unique joint names; repeated: {', '.join(dup)}")
        parents = np.asarray(self.parents)
        if parents.shape != (n,) or not np.issubdtype(parents.dtype, np.integer):
            raise ParameterError(f"Skeleton.parents: expected int array of shape ({n},); "
                                 f"got {parents.dtype} {parents.shape}")
        self.parents = parents.astype(np.int64)
        if self.parents[0] != -1:
            raise ParameterError(f"Skeleton.parents: joint 0 ({self.names[0]}) must be the root (-1); "
                                 f"got {self.parents[0]}")
        idx = np.arange(n)
        bad = np.flatnonzero((self.parents[1:] < 0) | (self.parents[1:] >= idx[1:])) + 1
        if bad.size:
            j = int(bad[0])
            raise ParameterError(f"Skeleton.parents: joint {j} ({self.names[j]}) has parent {self.parents[j]}; "
                                 "expected an index in [0, j) (one root, parents before children)")
        offsets = np.asarray(self.offsets, dtype=np.float64)
        if offsets.shape != (n, 3):
            raise ParameterError(f"Skeleton.offsets: expected shape ({n}, 3); got {offsets.shape}")
        if not np.all(np.isfinite(offsets)):
            j = int(np.argwhere(~np.isfinite(offsets))[0, 0])
            raise ParameterError(f"Skeleton.offsets: joint {self.names[j]} has a non-finite offset {offsets[j]}")
        self.offsets = offsets
        if len(self.channel_orders) != n:
            raise ParameterError(f"Skeleton.channel_orders: expected {n} orders; got {len(self.channel_orders)}")
        self.channel_orders = ["" if o == "" else rot.check_order(o) for o in self.channel_orders]
        ends = {}
        for j, off in dict(self.end_sites).items():
            if not (isinstance(j, (int, np.integer)) and 0 <= j < n):
                raise ParameterError(f"Skeleton.end_sites: expected joint indices in [0, {n}); got {j!r}")
            off = np.asarray(off, dtype=np.float64)
            if off.shape != (3,) or not np.all(np.isfinite(off)):
                raise ParameterError(f"Skeleton.end_sites[{j}] ({self.names[j]}): expected 3 finite numbers; "
                                     f"got {off!r}")
            ends[int(j)] = off
        self.end_sites = ends
        unit = float(self.length_unit_m)
        if not (math.isfinite(unit) and unit > 0):
            raise ParameterError(f"Skeleton.length_unit_m: expected a positive number; got {self.length_unit_m!r}")
        self.length_unit_m = unit

    @property
    def n_joints(self) -> int:
        """Number of joints J."""
        return len(self.names)

    def index(self, name: str) -> int:
        """Index of the joint called ``name`` (exact match).

        Raises
        ------
        ParameterError
            If there is no such joint; the message lists the joints.
        """
        try:
            return self.names.index(name)
        except ValueError:
            raise ParameterError(f"joint {name!r} not in the skeleton; joints: {', '.join(self.names)}") from None

    def children(self, j: int) -> list[int]:
        """Indices of the direct children of joint ``j``, in index order."""
        return [int(c) for c in np.flatnonzero(self.parents == j)]

    def rest_positions(self) -> np.ndarray:
        """World joint positions in the rest pose (all rotations identity).

        Returns
        -------
        ndarray [shape=(J, 3)], metres
            The root sits at ``offsets[0]``.
        """
        pos = np.empty_like(self.offsets)
        pos[0] = self.offsets[0]
        for j in range(1, self.n_joints):
            pos[j] = pos[self.parents[j]] + self.offsets[j]
        return pos

    def rest_height(self) -> float:
        """Vertical extent of the rest joints (max - min of y), metres."""
        y = self.rest_positions()[:, 1]
        return float(y.max() - y.min())

    def scale(self) -> float:
        """A size for tolerances: the largest extent of the rest joints along any axis, metres."""
        p = self.rest_positions()
        return float(np.max(p.max(axis=0) - p.min(axis=0)))

    def same_as(self, other: "Skeleton", *, atol_m: float = 1e-9) -> bool:
        """True when ``other`` has the same names, parents and offsets (within ``atol_m``)."""
        return (
            self.names == other.names
            and np.array_equal(self.parents, other.parents)
            and np.allclose(self.offsets, other.offsets, rtol=0.0, atol=atol_m)
        )

    def mirror_permutation(self) -> np.ndarray:
        """Left/right joint pairing; see `mirror_permutation`."""
        return mirror_permutation(self.names)

    def mirrored(self) -> "Skeleton":
        """The skeleton reflected across the x = 0 plane with left/right joints swapped.

        Joint ``j`` of the result gets the reflected offset of its counterpart
        ``P[j]``. A left/right symmetric skeleton is its own mirror image, and
        ``self`` is returned unchanged.

        Raises
        ------
        ParameterError
            If swapping names does not map the hierarchy onto itself.
        """
        perm = self.mirror_permutation()
        # the counterpart of a joint's parent must be the parent of its counterpart
        par = self.parents
        consistent = perm[0] == 0 and np.array_equal(par[perm[1:]], perm[par[1:]])
        if not consistent:
            raise ParameterError("Skeleton.mirrored: swapping left/right joint names does not map the hierarchy "
                                 "onto itself; the skeleton cannot be mirrored by name")
        flip = np.array([-1.0, 1.0, 1.0])
        offsets = self.offsets[perm] * flip
        # The root's offset moves no joint of a Motion (root_positions replace it), so it
        # is kept: a skeleton whose only asymmetry is where its root rests stays the same.
        offsets[0] = self.offsets[0]
        ends = {}
        for j in range(self.n_joints):
            if int(perm[j]) in self.end_sites:
                ends[j] = self.end_sites[int(perm[j])] * flip
        same = (np.allclose(offsets, self.offsets, rtol=0.0, atol=1e-9)
                and ends.keys() == self.end_sites.keys()
                and all(np.allclose(ends[j], self.end_sites[j], rtol=0.0, atol=1e-9) for j in ends))
        if same:
            return self
        return Skeleton(list(self.names), self.parents.copy(), offsets, list(self.channel_orders), ends,
                        self.length_unit_m)


# Side markers. "Left"/"Right" count at a word start (start, separator, digit) or at a
# camel-case boundary ("HandLeft"), and must not run on into lower case, so "Bright" or
# "Leftover" are not sides; single letters L/R likewise ("L_Hand", "b_l_wrist",
# "LHipJoint", "HandR"). A name is paired only if its swapped name exists, so a stray
# match (the R of "ROOT") pairs with nothing.
_SIDE_PATTERNS = [
    re.compile(r"(?:(?<![A-Za-z])(?:left|right|Left|Right|LEFT|RIGHT)|(?<=[a-z])(?:Left|Right|LEFT|RIGHT))"
               r"(?![a-z])"),
    re.compile(r"(?:(?<![A-Za-z])[lrLR]|(?<=[a-z])[LR])(?![a-z])"),
]
_SWAP = {"left": "right", "right": "left", "l": "r", "r": "l"}


def _swap_side(m: re.Match) -> str:
    side = m.group(0)
    word = _SWAP[side.lower()]
    if side.isupper() and len(side) > 1:
        return word.upper()
    return word[:1].upper() + word[1:] if side[:1].isupper() else word


def _counterpart(name: str) -> str:
    for pat in _SIDE_PATTERNS:
        if pat.search(name):
            return pat.sub(_swap_side, name)
    return name


def mirror_permutation(names) -> np.ndarray:
    """Pair left and right joints by name.

    Recognises ``Left``/``Right`` as a word (``LeftHand``, ``left_wrist``,
    ``mixamorig:RightArm``, ``HandLeft``) and ``L``/``R`` as a token
    (``L_Hand``, ``b_l_wrist``, ``Hand.R``, ``LHipJoint``).

    Parameters
    ----------
    names : sequence of str [length J]

    Returns
    -------
    ndarray [shape=(J,)], int64
        ``P[j]`` is the index of the counterpart of joint ``j`` (``j`` itself
        for midline joints and for side joints without a counterpart); ``P`` is
        an involution, ``P[P] == arange(J)``.
    """
    names = list(names)
    where = {n: i for i, n in enumerate(names)}
    perm = np.arange(len(names), dtype=np.int64)
    for i, n in enumerate(names):
        k = where.get(_counterpart(n))
        if k is not None and k != i and where.get(_counterpart(names[k])) == i:
            perm[i] = k
    return perm


def resampled_length(n_frames: int, fps_src: float, fps: float) -> int:
    """Number of frames a clip has after resampling; the one rule every module uses.

    Output frame ``i`` is at ``i / fps`` seconds and the last one is the last
    that is not after the last source frame:
    ``floor((n_frames - 1) * fps / fps_src) + 1``. The span is kept and nothing
    is extrapolated; e.g. 1906 frames at 30 fps (63.5 s) give 953 frames at
    15 fps and 1271 at 20 fps.

    Parameters
    ----------
    n_frames : int
        Source frame count, >= 1.
    fps_src, fps : float
        Source and target frame rates, Hz.

    Returns
    -------
    int
    """
    if n_frames < 1:
        raise ParameterError(f"n_frames: expected >= 1; got {n_frames}")
    # the 1e-9 keeps an exact ratio such as 1905 * 15 / 30 = 952.5 or 952.99999999 from flooring one short
    return int(math.floor((n_frames - 1) * fps / fps_src + 1e-9)) + 1


def _renormalised(q: np.ndarray, norm: np.ndarray) -> np.ndarray:
    """``q`` (..., 4) with the quaternions whose ``norm`` (...) rounding moved off 1 renormalised: unit
    input (a slice, a mirror of a mirror) keeps its exact bits and is not copied."""
    drift = np.abs(norm - 1.0) > 1e-12
    return np.where(drift[..., None], q / norm[..., None], q) if drift.any() else q


def forward_kinematics(skeleton: Skeleton, rotations: np.ndarray, root: np.ndarray, *, want_rotations: bool = True):
    """:meth:`Motion.forward_kinematics` of the arrays a Motion would hold, without making one.

    rotations (F, J, 4) and root (F, 3) m in; positions (F, J, 3) m and global rotations (F, J, 4) out (None
    without ``want_rotations``). The same bits as a Motion's: the rotations are renormalised as a Motion
    renormalises them. The assembly's feet take the kinematics of every piece of a live step, where making
    (and checking) a Motion cost more than the kinematics."""
    q = np.asarray(rotations, dtype=np.float64)
    return _unit_forward_kinematics(skeleton, _renormalised(q, rot._norm4(q)[..., 0]), root, want_rotations)


def _unit_forward_kinematics(skeleton: Skeleton, q: np.ndarray, root: np.ndarray, want_rotations: bool):
    """:func:`forward_kinematics` of rotations renormalised already (a Motion's own)."""
    # local on purpose, as in gesturedb.search: the compiled core is no stage of the layers
    import gesturedb._core as _core

    # quaternions to matrices, the chain and back in C++ (csrc/fk.cpp), frame by frame: the numpy
    # loop over joints cost a live step 1.3 ms per 8-frame piece in call overhead, and numpy's
    # to_matrix and from_matrix about 1 ms more; the conversions are numpy's to the bit
    # (tests/test_motion.py checks both against numpy)
    return _core.forward_kinematics_quat(np.ascontiguousarray(q, dtype=np.float64),
                                         np.ascontiguousarray(root, dtype=np.float64),
                                         np.ascontiguousarray(skeleton.parents, dtype=np.int64),
                                         np.ascontiguousarray(skeleton.offsets, dtype=np.float64), want_rotations)


@dataclass(eq=False)
class Motion:
    """Motion of a skeleton: local joint rotations and the root trajectory.

    Parameters
    ----------
    skeleton : Skeleton
    fps : float
        Frames per second; frame ``i`` is at ``i / fps`` s.
    rotations : ndarray [shape=(F, J, 4)]
        Local unit quaternions (w, x, y, z). Renormalised on construction;
        quaternions off unit norm by more than 1e-3 are an error. Float64
        input that needs no change is kept, not copied.
    root_positions : ndarray [shape=(F, 3)], metres
        World position of joint 0.

    Raises
    ------
    ParameterError
        On wrong shapes, non-finite values (naming the joint and frame) or a
        non-positive frame rate.
    """

    skeleton: Skeleton
    fps: float
    rotations: np.ndarray
    root_positions: np.ndarray

    def __post_init__(self):
        if not isinstance(self.skeleton, Skeleton):
            raise ParameterError(f"Motion.skeleton: expected a Skeleton; got {type(self.skeleton).__name__}")
        fps = float(self.fps)
        if not (math.isfinite(fps) and fps > 0):
            raise ParameterError(f"Motion.fps: expected a positive frame rate; got {self.fps!r}")
        self.fps = fps
        names = self.skeleton.names
        j = len(names)
        q = np.asarray(self.rotations, dtype=np.float64)
        if q.ndim != 3 or q.shape[1:] != (j, 4) or q.shape[0] < 1:
            raise ParameterError(f"Motion.rotations: expected shape (F >= 1, {j}, 4); got {q.shape}")
        root = np.asarray(self.root_positions, dtype=np.float64)
        if root.shape != (q.shape[0], 3):
            raise ParameterError(f"Motion.root_positions: expected shape ({q.shape[0]}, 3); got {root.shape}")
        # checks over the flat arrays first, the per-element search only on failure: reductions over
        # a last axis of 4 cost numpy 5x more, and every synthesis and refinement makes Motions
        if not np.isfinite(q).all():
            f, jj = np.argwhere(~np.isfinite(q).all(axis=-1))[0]
            raise ParameterError(f"Motion.rotations: joint {names[jj]} at frame {f} is not finite: {q[f, jj]}")
        if not np.isfinite(root).all():
            f = int(np.flatnonzero(~np.isfinite(root).all(axis=-1))[0])
            raise ParameterError(f"Motion.root_positions: joint {names[0]} at frame {f} is not finite: {root[f]}")
        norm = rot._norm4(q)[..., 0]  # np.linalg.norm(q, axis=-1), bit for bit
        off = np.abs(norm - 1.0) > _UNIT_TOL
        if off.any():
            f, jj = np.argwhere(off)[0]
            raise ParameterError(f"Motion.rotations: joint {names[jj]} at frame {f} is not a unit quaternion "
                                 f"(norm {norm[f, jj]:.6g})")
        self.rotations = _renormalised(q, norm)
        self.root_positions = root

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return self.rotations.shape[0]

    @property
    def duration_s(self) -> float:
        """``n_frames / fps``, seconds."""
        return self.n_frames / self.fps

    def __len__(self) -> int:
        return self.n_frames

    def _fk(self, want_rotations: bool):
        # the rotations were renormalised when the Motion was made: not a second pass over them
        return _unit_forward_kinematics(self.skeleton, self.rotations, self.root_positions, want_rotations)

    def forward_kinematics(self) -> tuple[np.ndarray, np.ndarray]:
        """World positions and rotations of every joint in every frame.

        In C++ (csrc/fk.cpp), frame by frame: any split of the frames gives the same bits.

        Returns
        -------
        positions : ndarray [shape=(F, J, 3)], metres
        global_rotations : ndarray [shape=(F, J, 4)]
            World (not local) unit quaternions, ``w >= 0``.
        """
        return self._fk(True)

    @property
    def positions(self) -> np.ndarray:
        """World joint positions, ``(F, J, 3)`` metres (forward kinematics).

        Computed on every access: keep the result rather than asking twice.
        """
        return self._fk(False)[0]

    def end_site_positions(self) -> dict[int, np.ndarray]:
        """World positions of the End Sites.

        Returns
        -------
        dict of int to ndarray [shape=(F, 3)], metres
            Joint index -> position of its End Site.
        """
        if not self.skeleton.end_sites:
            return {}
        pos, grot = self.forward_kinematics()
        return {j: pos[:, j] + rot.apply(grot[:, j], off) for j, off in self.skeleton.end_sites.items()}

    def __getitem__(self, item) -> "Motion":
        """Frames ``a:b`` (or ``a:b:step``, which divides ``fps`` by ``step``).

        The arrays of the result are numpy views of this motion's arrays.
        """
        if not isinstance(item, slice):
            raise ParameterError(f"Motion[...]: expected a slice of frames such as m[10:50]; got {item!r}")
        start, stop, step = item.indices(self.n_frames)
        if step < 1:
            raise ParameterError(f"Motion[...]: expected a positive step; got {item.step}")
        if len(range(start, stop, step)) == 0:
            raise ParameterError(f"Motion[{item.start}:{item.stop}]: empty slice of a {self.n_frames}-frame motion")
        return Motion(self.skeleton, self.fps / step, self.rotations[item], self.root_positions[item])

    def copy(self) -> "Motion":
        """A motion with its own copies of the arrays (the skeleton is shared)."""
        return Motion(self.skeleton, self.fps, self.rotations.copy(), self.root_positions.copy())

    def resample(self, fps: float) -> "Motion":
        """The same motion at another frame rate.

        Rotations are interpolated with slerp, the root linearly. Output frame
        ``i`` is at ``i / fps`` s; the frame count is
        `resampled_length` ``(n_frames, self.fps, fps)``, so the result never
        extends past the last source frame.

        Parameters
        ----------
        fps : float
            Target frame rate, Hz.

        Returns
        -------
        Motion
        """
        fps = float(fps)
        if not (math.isfinite(fps) and fps > 0):
            raise ParameterError(f"fps: expected a positive frame rate; got {fps!r}")
        n_src = self.n_frames
        n_out = resampled_length(n_src, self.fps, fps)
        if n_src == 1 or fps == self.fps:
            return Motion(self.skeleton, fps, self.rotations[:n_out].copy(), self.root_positions[:n_out].copy())
        u = np.arange(n_out) * (self.fps / fps)
        i0 = np.minimum(np.floor(u + 1e-9).astype(np.int64), n_src - 2)
        t = np.clip(u - i0, 0.0, 1.0)
        rots = rot.slerp(self.rotations[i0], self.rotations[i0 + 1], t[:, None])
        root = self.root_positions[i0] * (1.0 - t[:, None]) + self.root_positions[i0 + 1] * t[:, None]
        return Motion(self.skeleton, fps, rots, root)

    def mirror(self) -> "Motion":
        """Reflect the motion across the x = 0 plane and swap left/right joints.

        +x is the speaker's left, so the result is the same performance by a
        mirror-image speaker. Joint ``j`` takes the reflected local rotation of
        its counterpart ``P[j]`` (`mirror_permutation`): a quaternion
        ``(w, x, y, z)`` becomes ``(w, x, -y, -z)``, the reflection ``M R M`` with
        ``M = diag(-1, 1, 1)``. The root's x is negated. Joint offsets are reflected
        the same way (`Skeleton.mirrored`), so the mirrored positions are exactly
        the reflected, swapped positions; for a symmetric skeleton the skeleton is
        unchanged. Mirroring twice gives the original.

        Returns
        -------
        Motion
        """
        skel = self.skeleton.mirrored()
        perm = self.skeleton.mirror_permutation()
        q = self.rotations[:, perm] * np.array([1.0, 1.0, -1.0, -1.0])
        root = self.root_positions * np.array([-1.0, 1.0, 1.0])
        return Motion(skel, self.fps, q, root)
