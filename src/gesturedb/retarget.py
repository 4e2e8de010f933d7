"""Retarget motion onto another rig: other names, bone lengths, rest pose and bone axes.

The method
    Joints are paired by body part (`gesturedb.io.joints.body_keys`: SMPL-X,
    GENEA / TWH, ZEGGS, Mixamo, Unreal, generic BVH names), or by an explicit
    ``{target joint: source joint}`` mapping that overrides the names. Local
    Euler angles are meaningless across rigs whose rest poses differ (T-pose vs
    A-pose) or whose bones point along other axes, so what is transferred is each
    paired joint's **global** rotation relative to the rest pose of its own rig:

        G_target[t](frame) = G_source[s](frame) @ C[t]

    where ``C[t]`` is the rest-pose correction that turns the target's rest bone
    directions (from ``t`` to its nearest paired descendants) onto the source's
    (from ``s`` to theirs): the least rotation for one descendant (a limb
    segment), the best-fitting rotation (Kabsch) for several (the hips, a hand
    with fingers). A joint with no paired descendant (a hand without fingers, the
    head) takes the correction of its nearest paired ancestor. So every paired
    bone points in the same world direction as in the source, whatever the bone
    lengths. Target joints without a source keep their rest (identity) local
    rotation; source joints without a target are dropped.

    The hips trajectory is scaled by the ratio of the rigs' hip heights (rest
    height of the hips above the lowest joint), so a longer-legged character's
    feet neither sink nor float more than the source's. The world is the
    project's: y up, metres, facing +z.

    rig = load_rig("mixamo_character.bvh")        # or a .glb / .gltf skin
    res = retarget(motion, rig)                   # -> RetargetResult
    res.motion, res.mapped, res.unmapped_target, res.unmapped_source
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from gesturedb import rotations as rot
from gesturedb.errors import InputFileError, ParameterError, echo, echo_list
from gesturedb.io.bvh import MAX_FPS, MIN_FPS, read_bvh
from gesturedb.io.gltf import read_gltf_rig
from gesturedb.io.joints import MESSAGE_JOINTS, body_keys
from gesturedb.motion import Motion, Skeleton
from gesturedb.roles import RETARGET_REQUIRED

__all__ = ["RIG_EXTENSIONS", "RetargetResult", "load_rig", "match_joints", "retarget"]

RIG_EXTENSIONS = (".bvh", ".glb", ".gltf")


def load_rig(path) -> Skeleton:
    """The hierarchy and rest pose of a target rig.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.bvh`` (its HIERARCHY; any MOTION in it is ignored) or a glTF 2.0
        file with a skin (``.glb`` / ``.gltf``; see `gesturedb.io.gltf.read_gltf_rig`).

    Returns
    -------
    Skeleton
        Offsets in metres, rest pose = all local rotations identity.

    Raises
    ------
    InputFileError
        Unknown extension or any reader's error.
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext == ".bvh":
        return read_bvh(path).skeleton
    if ext in (".glb", ".gltf"):
        return read_gltf_rig(path)
    raise InputFileError(path, f"target rig: unknown extension {ext or '(none)'!r}; expected "
                               f"{', '.join(RIG_EXTENSIONS)}")


def match_joints(source: Skeleton, target: Skeleton, mapping=None) -> dict[int, int]:
    """Pair target joints with source joints.

    Parameters
    ----------
    source, target : Skeleton
    mapping : dict of str to str, optional
        ``{target joint name: source joint name}``; overrides the pairing by
        name for those target joints (a value of ``None`` or ``""`` leaves the
        target joint unpaired).

    Returns
    -------
    dict of int to int
        Target joint index -> source joint index, one-to-one.

    Raises
    ------
    ParameterError
        A mapping that names a joint neither rig has.
    """
    mapping = dict(mapping or {})
    for t, s in mapping.items():
        if t not in target.names:
            raise ParameterError(f"mapping: target joint {echo(t)} not in the target rig; joints: "
                                 f"{echo_list(target.names, MESSAGE_JOINTS)}")
        if s and s not in source.names:
            raise ParameterError(f"mapping[{echo(t)}]: source joint {echo(s)} not in the source skeleton; joints: "
                                 f"{echo_list(source.names, MESSAGE_JOINTS)}")
    src_by_key = {k: j for j, k in body_keys(source.names).items()}
    pairs: dict[int, int] = {}
    for t, key in body_keys(target.names).items():
        if target.names[t] in mapping:
            continue
        if key.startswith("spine"):
            continue  # spine chains differ in length: paired below
        if key in src_by_key:
            pairs[t] = src_by_key[key]
    # spine chains: ends to ends, the joints between by their place along the chain
    s_sp = sorted((int(k[5:]), j) for k, j in src_by_key.items() if k.startswith("spine"))
    t_sp = sorted((int(k[5:]), j) for j, k in body_keys(target.names).items() if k.startswith("spine"))
    t_sp = [(i, j) for i, j in t_sp if target.names[j] not in mapping]
    if s_sp and t_sp:
        n_s, n_t = len(s_sp), len(t_sp)
        for i, (_, t) in enumerate(t_sp):
            pos = (n_s - 1) if n_t == 1 else round(i * (n_s - 1) / (n_t - 1))
            pairs[t] = s_sp[pos][1]
    for t, s in mapping.items():
        if s:
            pairs[target.names.index(t)] = source.names.index(s)
    # one-to-one: a source joint claimed twice goes to the target joint nearest the root
    seen: dict[int, int] = {}
    for t in sorted(pairs):
        s = pairs[t]
        if s in seen and target.names[t] not in mapping:
            continue
        seen[s] = t
    return {t: s for s, t in seen.items()}


@dataclass
class RetargetResult:
    """What `retarget` made and how.

    Attributes
    ----------
    motion : Motion
        On the target skeleton, at the source frame rate.
    mapped : list of (str, str)
        (target joint, source joint) pairs, in target joint order.
    unmapped_target : list of str
        Target joints that kept their rest rotation.
    unmapped_source : list of str
        Source joints whose motion was dropped.
    scale : float
        Hip-height ratio target / source applied to the hips trajectory.
    """

    motion: Motion
    mapped: list = field(default_factory=list)
    unmapped_target: list = field(default_factory=list)
    unmapped_source: list = field(default_factory=list)
    scale: float = 1.0

    def report(self) -> str:
        """A few lines for people: which joints were paired and which not."""
        pairs = ", ".join(f"{t}<-{s}" for t, s in self.mapped)
        return (f"mapped {len(self.mapped)} joints: {pairs}\n"
                f"target joints kept at rest ({len(self.unmapped_target)}): "
                f"{', '.join(self.unmapped_target) or 'none'}\n"
                f"source joints dropped ({len(self.unmapped_source)}): {', '.join(self.unmapped_source) or 'none'}\n"
                f"hips trajectory scaled by {self.scale:.4f} (hip-height ratio)")


def _least_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unit quaternion of the least rotation taking direction ``a`` (3,) onto ``b`` (3,)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-9:
        # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        return rot.from_axis_angle(axis / np.linalg.norm(axis) * np.pi)
    q = np.concatenate([[1.0 + c], np.cross(a, b)])
    return q / np.linalg.norm(q)


def _fit_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation quaternion R minimising sum |R a_i - b_i|^2 over unit rows a, b (n, 3), n >= 2 (Kabsch)."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    u, s, vt = np.linalg.svd(b.T @ a)
    if s[1] < 1e-6:  # all collinear: only a direction is known
        return _least_rotation(a.sum(axis=0), b.sum(axis=0))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    m = u @ np.diag([1.0, 1.0, d]) @ vt
    return rot.from_matrix(m)


def _nearest_paired_ancestor(skel: Skeleton, j: int, paired) -> int:
    p = int(skel.parents[j])
    while p >= 0 and p not in paired:
        p = int(skel.parents[p])
    return p


def _hip_height(skel: Skeleton, hips: int) -> float:
    rest = skel.rest_positions()
    return float(rest[hips, 1] - rest[:, 1].min())


def retarget(motion: Motion, target: Skeleton, *, mapping=None) -> RetargetResult:
    """Move ``motion`` onto the ``target`` skeleton (see the module notes).

    Parameters
    ----------
    motion : Motion
        Source motion, any skeleton whose joints `match_joints` can pair.
    target : Skeleton
        Target rig; its rest pose is all local rotations identity (as
        `load_rig` returns it).
    mapping : dict of str to str, optional
        ``{target joint name: source joint name}`` overrides.

    Returns
    -------
    RetargetResult

    Raises
    ------
    ParameterError
        If the arms (upper arm, forearm, hand on both sides) cannot be paired:
        the message says which parts each rig lacks; a frame rate outside
        `gesturedb.io.bvh.MIN_FPS` to `MAX_FPS` (1-1000, what `read_bvh` accepts).
    """
    if not isinstance(motion, Motion):
        raise ParameterError(f"motion: expected a Motion; got {type(motion).__name__}")
    if not isinstance(target, Skeleton):
        raise ParameterError(f"target: expected a Skeleton; got {type(target).__name__}")
    if not MIN_FPS <= motion.fps <= MAX_FPS:
        # the output is BVH or glTF: never make a file read_bvh would refuse (1e9 or 1e-9 fps)
        raise ParameterError(f"motion.fps: expected {MIN_FPS:g} to {MAX_FPS:g} frames per second (what a BVH "
                             f"file carries); got {motion.fps:g}")
    src = motion.skeleton
    pairs = match_joints(src, target, mapping)
    t_keys = body_keys(target.names)
    s_keys = body_keys(src.names)
    # a part counts as paired when either side of a pair has it (a mapping may pair an odd name)
    paired_keys = {t_keys.get(t) for t in pairs} | {s_keys.get(s) for s in pairs.values()}
    missing = [k for k in RETARGET_REQUIRED if k not in paired_keys]
    if missing:
        no_t = [k for k in missing if k not in t_keys.values()]
        no_s = [k for k in missing if k not in s_keys.values()]
        raise ParameterError(
            f"retarget: no arms found to pair: {', '.join(missing)} unpaired (target rig lacks "
            f"{', '.join(no_t) or 'none'}; source lacks {', '.join(no_s) or 'none'}); target joints: "
            f"{echo_list(target.names, MESSAGE_JOINTS)}. Pass mapping={{target_joint: source_joint}} (--map T=S) "
            "to pair them")

    rest_s = src.rest_positions()
    rest_t = target.rest_positions()
    n_t = target.n_joints
    # rest-pose correction C[t]: target rest bone directions -> source rest bone directions
    corr = {}
    for t in range(n_t):  # parents first, so an ancestor's correction is known
        if t not in pairs:
            continue
        s = pairs[t]
        kids = [u for u in pairs if u != t and _nearest_paired_ancestor(target, u, pairs) == t]
        va, vb = [], []
        for u in kids:
            a = rest_t[u] - rest_t[t]
            b = rest_s[pairs[u]] - rest_s[s]
            if np.linalg.norm(a) > 1e-6 and np.linalg.norm(b) > 1e-6:
                va.append(a)
                vb.append(b)
        if len(va) == 1:
            corr[t] = _least_rotation(va[0], vb[0])
        elif va:
            corr[t] = _fit_rotation(np.array(va), np.array(vb))
        else:
            anc = _nearest_paired_ancestor(target, t, pairs)
            corr[t] = corr[anc] if anc >= 0 else rot.identity()

    s_pos, s_glob = motion.forward_kinematics()
    n_f = motion.n_frames
    glob = np.empty((n_f, n_t, 4))
    for t in range(n_t):
        if t in pairs:
            glob[:, t] = rot.multiply(s_glob[:, pairs[t]], corr[t])
        elif t == 0:
            glob[:, t] = rot.identity()
        else:
            glob[:, t] = glob[:, target.parents[t]]  # rest local rotation: identity
    local = np.empty_like(glob)
    local[:, 0] = glob[:, 0]
    par = target.parents[1:]
    local[:, 1:] = rot.multiply(rot.inverse(glob[:, par]), glob[:, 1:])
    local = rot.make_continuous(rot.normalize(local), axis=0)

    # hips trajectory, scaled by the hip-height ratio; the root is placed so the hips land there
    t_hips = next(j for j, k in t_keys.items() if k == "hips")
    s_hips = pairs.get(t_hips, next((j for j, k in s_keys.items() if k == "hips"), 0))
    h_s, h_t = _hip_height(src, s_hips), _hip_height(target, t_hips)
    if h_s > 1e-6 and h_t > 1e-6:
        scale = h_t / h_s
    else:  # a rig without legs: the overall heights
        hs, ht = src.rest_height(), target.rest_height()
        scale = ht / hs if hs > 1e-6 and ht > 1e-6 else 1.0
    hips_world = s_pos[:, s_hips] * scale
    if t_hips == 0:
        root = hips_world
    else:
        # root -> hips through the rotating chain above the hips
        chain = []
        j = t_hips
        while j != 0:
            chain.append(j)
            j = int(target.parents[j])
        offset = np.zeros((n_f, 3))
        for j in chain:
            offset += rot.apply(glob[:, target.parents[j]], target.offsets[j])
        root = hips_world - offset

    out = Motion(target, motion.fps, local, root)
    mapped = [(target.names[t], src.names[s]) for t, s in sorted(pairs.items())]
    used = set(pairs.values())
    return RetargetResult(
        motion=out,
        mapped=mapped,
        unmapped_target=[n for t, n in enumerate(target.names) if t not in pairs],
        unmapped_source=[n for s, n in enumerate(src.names) if s not in used],
        scale=float(scale),
    )
