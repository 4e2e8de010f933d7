"""glTF 2.0 binary (.glb): a skinned stick figure with one animation; rigs and motion back in.

Writing (`write_glb`)
    One node per joint (name, rest translation = `Skeleton.offsets`, rest
    rotation identity), a skin over all of them, and a mesh skinned to it (a
    thin box along every bone, rigidly bound to the bone's parent joint) so any
    viewer shows the figure, not only the bones. One animation with a LINEAR
    rotation channel per joint and a translation channel on the root, sampled at
    the motion's frames. glTF's world is the project's: y up, metres, the figure
    facing +z, +x its left; glTF quaternions are (x, y, z, w). Written with
    pygltflib to a temporary file and renamed. Blender, three.js, Unity and
    Unreal import it; speech travels beside it as a WAV of the same stem.

Reading (`read_gltf_rig`, `read_gltf`)
    Any file with a skin: the joints are the skin's, parents-first; rest poses
    with rotated bone axes and scaled parent nodes (an ``Armature`` at 0.01)
    are allowed. Joints are brought to the project's convention (rest pose =
    identity local rotations, offsets in metres) from their rest world
    transforms: the project-convention global rotation of a joint is its glTF
    world rotation times the inverse of its rest world rotation.

    The reader parses the container and JSON itself (`gesturedb.io.gltf_file`;
    pygltflib only writes) and checks every field before use: a broken or hostile file gives one
    `InputFileError` naming the file and the field (``accessors[3].count``).
    Node cycles are errors; buffers are read only from the GLB chunk, a data:
    URI or a regular file inside the glTF file's folder, never past byteLength;
    frames x nodes is capped at `MAX_JOINT_FRAMES`.
"""
from __future__ import annotations

import collections

import numpy as np

from gesturedb import rotations as rot
from gesturedb.errors import ParameterError
from gesturedb.io.atomic import atomic_open
from gesturedb.io.bvh import MAX_FPS, MIN_FPS
from gesturedb.io.gltf_file import Doc
from gesturedb.io.gltf_file import load as _load
from gesturedb.io.gltf_file import shown as _shown
from gesturedb.motion import Motion, Skeleton

__all__ = ["MAX_JOINT_FRAMES", "read_gltf", "read_gltf_rig", "write_glb"]

_FLOAT, _USHORT, _UINT = 5126, 5123, 5125
# half-thickness of the boxes drawn along the bones, as a fraction of the bone length (and at most this many metres)
_BOX_FRAC = 0.12
_BOX_MAX_M = 0.03


def _pygltflib():
    try:
        import pygltflib
    except ImportError as exc:  # pragma: no cover - an install problem, said plainly
        raise ParameterError("glTF needs the pygltflib package: pip install pygltflib") from exc
    return pygltflib


def _bone_boxes(rest: np.ndarray, segments):
    """Vertices (V, 3), joint index per vertex (V,), triangle indices (T*3,) of a box per segment."""
    verts, owner, tris = [], [], []
    for a_pos, b_pos, j in segments:
        d = b_pos - a_pos
        length = float(np.linalg.norm(d))
        if length < 1e-5:
            continue
        d = d / length
        # two unit vectors normal to the bone
        ref = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        u = np.cross(d, ref)
        u /= np.linalg.norm(u)
        v = np.cross(d, u)
        w = min(_BOX_FRAC * length, _BOX_MAX_M)
        base = len(verts)
        for end in (a_pos, b_pos):
            for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                verts.append(end + w * (su * u + sv * v))
                owner.append(j)
        # 6 faces of the box, outward winding
        for f in ((0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)):
            a, b, c, e = (base + i for i in f)
            tris += [a, c, b, a, e, c]
    return np.asarray(verts, np.float32).reshape(-1, 3), np.asarray(owner, np.uint16), np.asarray(tris, np.uint32)


def write_glb(path, motion: Motion, *, mesh: bool = True) -> None:
    """Write a `Motion` as a binary glTF 2.0 file (skin + one animation).

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.glb``; written to a temporary file in the same folder and
        renamed, so a failure never leaves half a file.
    motion : Motion
    mesh : bool
        Also write the box-per-bone mesh skinned to the joints (default), so
        viewers show a figure.

    Raises
    ------
    ParameterError
        Not a Motion, or pygltflib missing.
    InputFileError
        If the file cannot be written.
    """
    if not isinstance(motion, Motion):
        raise ParameterError(f"motion: expected a Motion; got {type(motion).__name__}")
    g = _pygltflib()
    sk = motion.skeleton
    n_j, n_f = sk.n_joints, motion.n_frames
    blob = bytearray()
    gl = g.GLTF2(asset=g.Asset(generator="gesturedb", version="2.0"))

    def add(arr: np.ndarray, comp: int, typ: str, *, target=None, minmax=False) -> int:
        data = np.ascontiguousarray(arr).tobytes()
        while len(blob) % 4:
            blob.append(0)
        gl.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob.extend(data)
        count = arr.shape[0]
        acc = g.Accessor(bufferView=len(gl.bufferViews) - 1, componentType=comp, count=count, type=typ)
        if minmax:
            flat = arr.reshape(count, -1)
            acc.min = [float(x) for x in flat.min(axis=0)]
            acc.max = [float(x) for x in flat.max(axis=0)]
        gl.accessors.append(acc)
        return len(gl.accessors) - 1

    children = [[] for _ in range(n_j)]
    for j in range(1, n_j):
        children[sk.parents[j]].append(j)
    for j in range(n_j):
        t = sk.offsets[j]  # the rig's rest pose, root included: a mesh bound to the rig binds to this
        gl.nodes.append(g.Node(name=sk.names[j], translation=[float(x) for x in t], rotation=[0.0, 0.0, 0.0, 1.0],
                               children=children[j] or None))

    rest = sk.rest_positions()
    # inverse bind matrices: the bind pose is the rig's rest pose; column-major
    ibm = np.tile(np.eye(4, dtype=np.float32), (n_j, 1, 1))
    ibm[:, :3, 3] = -rest
    ibm_acc = add(np.ascontiguousarray(ibm.transpose(0, 2, 1)).reshape(n_j, 16), _FLOAT, "MAT4")
    gl.skins.append(g.Skin(name="gesturedb", joints=list(range(n_j)), skeleton=0, inverseBindMatrices=ibm_acc))

    scene_nodes = [0]
    if mesh:
        segs = [(rest[sk.parents[j]], rest[j], int(sk.parents[j])) for j in range(1, n_j)]
        segs += [(rest[j], rest[j] + off, j) for j, off in sk.end_sites.items()]
        verts, owner, tris = _bone_boxes(rest, segs)
        joints4 = np.zeros((len(owner), 4), np.uint16)
        joints4[:, 0] = owner
        weights4 = np.zeros((len(owner), 4), np.float32)
        weights4[:, 0] = 1.0
        prim = g.Primitive(
            attributes=g.Attributes(POSITION=add(verts, _FLOAT, "VEC3", target=34962, minmax=True),
                                    JOINTS_0=add(joints4, _USHORT, "VEC4", target=34962),
                                    WEIGHTS_0=add(weights4, _FLOAT, "VEC4", target=34962)),
            indices=add(tris, _UINT, "SCALAR", target=34963), material=0)
        gl.materials.append(g.Material(name="figure", pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorFactor=[0.85, 0.55, 0.25, 1.0], metallicFactor=0.0, roughnessFactor=0.8)))
        gl.meshes.append(g.Mesh(name="figure", primitives=[prim]))
        gl.nodes.append(g.Node(name="figure", mesh=0, skin=0))
        scene_nodes.append(n_j)
    gl.scenes.append(g.Scene(name="gesturedb", nodes=scene_nodes))
    gl.scene = 0

    times = (np.arange(n_f) / motion.fps).astype(np.float32)
    t_acc = add(times, _FLOAT, "SCALAR", minmax=True)
    samplers, channels = [], []
    # glTF stores (x, y, z, w); one sampler per joint
    q = rot.make_continuous(motion.rotations, axis=0)[..., [1, 2, 3, 0]].astype(np.float32)
    for j in range(n_j):
        samplers.append(g.AnimationSampler(input=t_acc, output=add(q[:, j], _FLOAT, "VEC4"), interpolation="LINEAR"))
        channels.append(g.AnimationChannel(sampler=j, target=g.AnimationChannelTarget(node=j, path="rotation")))
    samplers.append(g.AnimationSampler(input=t_acc, output=add(motion.root_positions.astype(np.float32), _FLOAT,
                                                               "VEC3"), interpolation="LINEAR"))
    channels.append(g.AnimationChannel(sampler=n_j, target=g.AnimationChannelTarget(node=0, path="translation")))
    gl.animations.append(g.Animation(name="gesture", samplers=samplers, channels=channels))
    gl.buffers.append(g.Buffer(byteLength=len(blob)))
    gl.set_binary_blob(bytes(blob))

    data = b"".join(gl.save_to_bytes())
    with atomic_open(path, "wb") as f:
        f.write(data)


# --- reading -------------------------------------------------------------------------------------
#
# The container and JSON are parsed and checked in gesturedb.io.gltf_file; here the node tree must be
# a forest (one parent per node, no cycles) walked iteratively, and frames x nodes is capped
# (MAX_JOINT_FRAMES) with forward kinematics in blocks of frames, so memory stays proportional to
# the motion returned.

#: Frames x nodes (the joints and the nodes above them) a read may animate: about 120 bytes each
#: while reading (2 GB at this cap: 11 minutes at 120 fps of a 200-node rig).
MAX_JOINT_FRAMES = 1 << 24
# (frame, node) pairs composed at once: about 500 bytes each in flight (some 256 MB at most)
_FK_BLOCK = 1 << 19
_TRS = {"translation": 3, "rotation": 4, "scale": 3}


def _trs_matrix(t, q_xyzw, s) -> np.ndarray:
    """(..., 4, 4) matrices from translations (..., 3), glTF quaternions (..., 4) x,y,z,w, scales (..., 3)."""
    t, q, s = np.asarray(t, float), np.asarray(q_xyzw, float), np.asarray(s, float)
    shape = np.broadcast_shapes(t.shape[:-1], q.shape[:-1], s.shape[:-1])
    m = np.zeros(shape + (4, 4))
    m[..., :3, :3] = rot.to_matrix(rot.normalize(q[..., [3, 0, 1, 2]])) * s[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


class _Rig:
    """The node forest and the first skin, checked: joints parents-first and rest world matrices.

    Attributes
    ----------
    order : list of int
        Skin joints (node indices), parents first.
    joint_parent : dict
        Node index -> nearest ancestor that is a joint (None for the root joint).
    parent : list of int
        Parent node of every node (-1 for roots).
    needed : list of int
        The joints and every node above them, parents first: what forward kinematics walks.
    slot : dict
        Node index -> its position in ``needed``.
    rest_t, rest_q, rest_s : ndarray [shape=(N, 3), (N, 4), (N, 3)]
        Rest translation, rotation (x, y, z, w) and scale of each of ``needed``.
    fixed : dict
        Position in ``needed`` -> (4, 4) local matrix, for nodes given by ``matrix``.
    rest_world : ndarray [shape=(N, 4, 4)]
        Rest world matrix of each of ``needed``.
    """

    def __init__(self, doc: Doc):
        self.doc = doc
        nodes = doc.items("nodes")
        n = len(nodes)
        parent = [-1] * n
        children = []
        for i in range(n):
            where = f"nodes[{i}]"
            kids = doc.item("nodes", i).get("children", [])
            if not isinstance(kids, list):
                doc.fail(f"{where}.children", f"expected an array of node indices; got {_shown(kids)}")
            for k, c in enumerate(kids):
                if isinstance(c, bool) or not isinstance(c, int) or not 0 <= c < n:
                    doc.fail(f"{where}.children[{k}]", f"expected an index into nodes (0 to {n - 1}); got {_shown(c)}")
                if c == i:
                    doc.fail(f"{where}.children", f"node {i} is its own child (a cycle)")
                if parent[c] != -1:
                    doc.fail(f"{where}.children", f"node {c} is already a child of node {parent[c]} (a node has "
                                                  "at most one parent)")
                parent[c] = i
            children.append(kids)
        # parents-first order of the whole forest (iterative: a deep chain must not hit the recursion limit)
        forest, seen = [], [False] * n
        stack = [i for i in reversed(range(n)) if parent[i] == -1]
        while stack:
            i = stack.pop()
            seen[i] = True
            forest.append(i)
            stack += reversed(children[i])
        if len(forest) != n:
            # one parent per node: what no root reaches lies on a cycle (or under one); show it
            i = seen.index(False)
            chain, on = [], set()
            while i not in on:
                on.add(i)
                chain.append(i)
                i = parent[i]
            loop = chain[chain.index(i):][::-1]  # parent to child
            loop.append(loop[0])
            doc.fail(f"nodes[{loop[0]}].children", "the node hierarchy has a cycle: nodes "
                                                     + " -> ".join(map(str, loop[:12])) + (" ..." if len(loop) > 12 else ""))
        self.parent = parent

        skins = doc.items("skins")
        if not skins:
            doc.fail("skins", "expected a skin (the rig's joints); the file has none")
        skin = doc.item("skins", 0)
        joints = skin.get("joints")
        if not isinstance(joints, list) or not joints:
            doc.fail("skins[0].joints", f"expected a non-empty array of node indices; got {_shown(joints)}")
        for k, j in enumerate(joints):
            if isinstance(j, bool) or not isinstance(j, int) or not 0 <= j < n:
                doc.fail(f"skins[0].joints[{k}]", f"expected an index into nodes (0 to {n - 1}); got {_shown(j)}")
        jset = set(joints)
        if len(jset) != len(joints):
            doc.fail("skins[0].joints", "expected each node once; some repeat")
        jp = {}
        for i in forest:  # parents first: the nearest joint above i is known before i
            p = parent[i]
            jp[i] = None if p == -1 else (p if p in jset else jp[p])
        self.joint_parent = jp
        roots = [i for i in joints if jp[i] is None]
        if len(roots) != 1:
            names = ", ".join(self.name(i) for i in roots[:8]) + (", ..." if len(roots) > 8 else "")
            doc.fail("skins[0]", f"expected one root joint; got {len(roots)} ({names})")
        # a single root joint: every other joint's chain of joint parents ends there, so one hierarchy
        pos_in_skin = {j: k for k, j in enumerate(joints)}
        if joints[0] == roots[0] and all(pos_in_skin[jp[i]] < pos_in_skin[i] for i in joints[1:]):
            self.order = list(joints)  # already parents-first (our own files): keep the skin's joint order
        else:
            self.order = [i for i in forest if i in jset]  # depth-first from the root, children in file order
        mark = [False] * n
        for j in joints:
            while j != -1 and not mark[j]:
                mark[j] = True
                j = parent[j]
        self.needed = [i for i in forest if mark[i]]
        names = [self.name(i) for i in self.order]
        if len(set(names)) != len(names):
            dup = sorted(x for x, k in collections.Counter(names).items() if k > 1)  # not names.count: O(J^2)
            doc.fail("skins[0].joints", f"expected joints with unique names (nodes[i].name); repeated: "
                                        f"{_shown(', '.join(dup))}")
        self.slot = {i: k for k, i in enumerate(self.needed)}
        n_need = len(self.needed)
        self.rest_t, self.rest_q, self.rest_s = np.zeros((n_need, 3)), np.zeros((n_need, 4)), np.ones((n_need, 3))
        self.rest_q[:, 3] = 1.0
        self.fixed = {}
        for k, i in enumerate(self.needed):
            trs = self.trs(i)
            if isinstance(trs, np.ndarray):
                self.fixed[k] = trs
            else:
                self.rest_t[k], self.rest_q[k], self.rest_s[k] = trs
        # nodes by depth (parents first): a level's world matrices are one batched product with the level above
        up = np.array([-1 if parent[i] == -1 else self.slot[parent[i]] for i in self.needed], dtype=np.int64)
        depth = np.zeros(n_need, dtype=np.int64)
        for k in range(n_need):
            if up[k] >= 0:
                depth[k] = depth[up[k]] + 1
        by_depth = np.argsort(depth, kind="stable")
        cuts = np.flatnonzero(np.diff(depth[by_depth])) + 1
        self.levels = [(lv, up[lv]) for lv in np.split(by_depth, cuts)[1:]]
        self.rest_world = self.compose(self.local(self.rest_t, self.rest_q, self.rest_s))
        if not np.all(np.isfinite(self.rest_world)):
            k = int(np.argwhere(~np.isfinite(self.rest_world))[0, 0])
            doc.fail(f"nodes[{self.needed[k]}]", "its rest transform, composed with the nodes above it, is not finite")

    def local(self, t, q, s) -> np.ndarray:
        """Local matrices (..., N, 4, 4) of ``needed`` from TRS (..., N, 3/4/3); ``matrix`` nodes fixed."""
        m = _trs_matrix(t, q, s)
        for k, fixed in self.fixed.items():
            m[..., k, :, :] = fixed
        return m

    def compose(self, local: np.ndarray) -> np.ndarray:
        """World matrices (..., N, 4, 4) from local ones, level by level down the tree."""
        world = local.copy()
        for lv, up in self.levels:
            world[..., lv, :, :] = world[..., up, :, :] @ local[..., lv, :, :]
        return world

    def name(self, i: int) -> str:
        v = self.doc.item("nodes", i).get("name")
        if v is not None and not isinstance(v, str):
            self.doc.fail(f"nodes[{i}].name", f"expected a string; got {_shown(v)}")
        return v or f"joint{i}"

    def trs(self, i: int):
        """Node ``i``'s rest (translation, rotation x,y,z,w, scale), or its (4, 4) matrix if it has one."""
        doc, where = self.doc, f"nodes[{i}]"
        node = doc.item("nodes", i)
        if node.get("matrix") is not None:
            return doc.numbers(node, "matrix", where, 16, None).reshape(4, 4).T  # column-major
        t = doc.numbers(node, "translation", where, 3, [0.0, 0.0, 0.0])
        q = doc.numbers(node, "rotation", where, 4, [0.0, 0.0, 0.0, 1.0])
        s = doc.numbers(node, "scale", where, 3, [1.0, 1.0, 1.0])
        if not np.linalg.norm(q) > 1e-6:
            doc.fail(f"{where}.rotation", f"expected a unit quaternion; got {_shown(q.tolist())}")
        return t, q, s

    def skeleton(self):
        """The rig as a `Skeleton` (offsets from rest world positions) and the joints' rest world rotations."""
        order = self.order
        at = [self.slot[i] for i in order]
        pos = self.rest_world[at, :3, 3]
        idx = {n: k for k, n in enumerate(order)}
        parents = np.array([-1] + [idx[self.joint_parent[i]] for i in order[1:]], dtype=np.int64)
        offsets = pos.copy()
        offsets[1:] = pos[1:] - pos[parents[1:]]
        try:
            skel = Skeleton([self.name(i) for i in order], parents, offsets, ["ZXY"] * len(order))
        except ParameterError as exc:
            self.doc.fail("skins[0]", str(exc))
        rest_rot = _polar(self.rest_world[at, :3, :3])
        return skel, rest_rot


def _polar(m3: np.ndarray) -> np.ndarray:
    """Rotation part (..., 3, 3) of matrices that may carry scale."""
    u, _, vt = np.linalg.svd(m3)
    r = u @ vt
    flip = np.linalg.det(r) < 0
    if np.any(flip):
        u[flip, :, -1] *= -1
        r = u @ vt
    return r


def read_gltf_rig(path) -> Skeleton:
    """The rest skeleton of a glTF file's first skin, in the project's convention.

    Parameters
    ----------
    path : str or os.PathLike
        ``.glb`` or ``.gltf`` with at least one skin. Its buffers are not read.

    Returns
    -------
    Skeleton
        Skin joints parents-first, named after their nodes; offsets in metres
        from the rest world positions (rest rotations folded in, so the rest pose
        is all identity); channel order ``"ZXY"`` for BVH export.

    Raises
    ------
    InputFileError
        No skin, several root joints, a node cycle, or any field out of range
        or of the wrong kind (the message names it, as ``nodes[4].children``).
    """
    return _Rig(_load(path)).skeleton()[0]


def read_gltf(path, *, animation: int = 0) -> Motion:
    """Read the motion of a skinned glTF file.

    Parameters
    ----------
    path : str or os.PathLike
    animation : int
        Which animation (default the first).

    Returns
    -------
    Motion
        On `read_gltf_rig`'s skeleton, at the frame rate of the key times of
        the first channel that moves the rig (which must be evenly spaced);
        other channels are resampled at those times (LINEAR and CUBICSPLINE
        linearly through their values, STEP held; quaternions normalised).

    Raises
    ------
    InputFileError
        No skin, no such animation, uneven or non-finite key times, an accessor
        or buffer out of range, a buffer uri outside the file's folder, or more
        than `MAX_JOINT_FRAMES` frames x joints. The message names the field.
    ParameterError
        ``animation`` not an integer.
    """
    if isinstance(animation, bool) or not isinstance(animation, (int, np.integer)):
        raise ParameterError(f"animation: expected an integer index; got {_shown(animation)}")
    doc = _load(path)
    rig = _Rig(doc)
    skel, rest_rot = rig.skeleton()
    n_anim = len(doc.items("animations"))
    if not 0 <= animation < n_anim:
        doc.fail("animations", f"expected animation {animation}; the file has {n_anim}")
    aw = f"animations[{animation}]"
    anim = doc.item("animations", animation)
    channels, samplers = anim.get("channels"), anim.get("samplers")
    if not isinstance(channels, list) or not channels:
        doc.fail(f"{aw}.channels", f"expected a non-empty array; got {_shown(channels)}")
    if not isinstance(samplers, list) or not samplers:
        doc.fail(f"{aw}.samplers", f"expected a non-empty array; got {_shown(samplers)}")
    needed = set(rig.needed)
    used = []  # (channel where, node, path, sampler index) of the channels that move the rig
    for c, ch in enumerate(channels):
        cw = f"{aw}.channels[{c}]"
        if not isinstance(ch, dict):
            doc.fail(cw, f"expected an object; got {_shown(ch)}")
        target = ch.get("target")
        if not isinstance(target, dict):
            doc.fail(f"{cw}.target", f"expected an object; got {_shown(target)}")
        s = ch.get("sampler")
        if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < len(samplers):
            doc.fail(f"{cw}.sampler", f"expected an index into {aw}.samplers (0 to {len(samplers) - 1}); "
                                      f"got {_shown(s)}")
        tpath = doc.text(target, "path", f"{cw}.target")
        node = doc.index(target, "node", f"{cw}.target", "nodes", default=None)
        if node is not None and node in needed and tpath in _TRS:  # weights, extensions' paths: not ours
            used.append((cw, node, tpath, s))
    if not used:
        doc.fail(f"{aw}.channels", "no channel moves the skin's joints or the nodes above them")
    first_sampler = used[0][3]
    used = list({(u[1], u[2]): u for u in used}.values())  # one per (node, path): a later channel wins

    def keys(s):
        sw = f"{aw}.samplers[{s}]"
        smp = samplers[s]
        if not isinstance(smp, dict):
            doc.fail(sw, f"expected an object; got {_shown(smp)}")
        i = doc.index(smp, "input", sw, "accessors")
        t = doc.accessor(i, f"{sw}.input", types=("SCALAR",), comps=(5126,))[:, 0]
        if t.size > 1 and not np.all(np.diff(t) > 0):
            k = int(np.flatnonzero(~(np.diff(t) > 0))[0])
            doc.fail(f"{sw}.input", f"expected increasing key times; accessors[{i}] goes from {t[k]:.9g} to "
                                    f"{t[k + 1]:.9g} s at key {k + 1}")
        return sw, smp, t

    _, _, times = keys(first_sampler)
    if times.size > 1:
        dt = np.diff(times)
        if (dt.max() - dt.min()) > 1e-3 * dt.mean():
            doc.fail(f"{aw} key times", f"expected evenly spaced frames; got steps from {dt.min():.6g} to "
                                        f"{dt.max():.6g} s")
        fps = 1.0 / float(dt.mean())
        if not MIN_FPS * (1 - 1e-4) <= fps <= MAX_FPS * (1 + 1e-4):
            doc.fail(f"{aw} key times", f"expected {MIN_FPS:g} to {MAX_FPS:g} frames per second; got {fps:.6g}")
        if abs(fps - round(fps)) < 1e-4 * fps:  # float32 key times: 30.0000013 is 30
            fps = float(round(fps))
    else:
        fps = 30.0
    n_f = times.size
    if n_f * len(rig.needed) > MAX_JOINT_FRAMES:
        doc.fail(f"{aw} key times", f"{n_f} frames x {len(rig.needed)} nodes is more than this reader's limit of "
                                    f"{MAX_JOINT_FRAMES} frame-joints")
    anim_of = {}
    for _cw, node, tpath, s in used:
        sw, smp, tin = keys(s)
        interp = doc.text(smp, "interpolation", sw, choices=("LINEAR", "STEP", "CUBICSPLINE"), default="LINEAR")
        o = doc.index(smp, "output", sw, "accessors")
        rotation = tpath == "rotation"
        val = doc.accessor(o, f"{sw}.output", types=("VEC4",) if rotation else ("VEC3",), comps=(5126,),
                           normalized_ints=rotation)
        per_key = 3 if interp == "CUBICSPLINE" else 1
        if len(val) != per_key * len(tin):
            doc.fail(f"{sw}.output", f"expected {per_key * len(tin)} values ({interp}, {len(tin)} key times); "
                                     f"accessors[{o}].count is {len(val)}")
        if interp == "CUBICSPLINE":
            val = val[1::3]  # (in-tangent, value, out-tangent) per key: the values
        if rotation and not np.all(np.linalg.norm(val, axis=1) > 1e-6):
            doc.fail(f"{sw}.output", f"accessors[{o}] holds a zero-length rotation quaternion")
        if tin.size != n_f or not np.allclose(tin, times):
            if interp == "STEP":
                val = val[np.clip(np.searchsorted(tin, times, side="right") - 1, 0, len(tin) - 1)]
            else:
                val = np.stack([np.interp(times, tin, val[:, k]) for k in range(val.shape[1])], axis=1)
        if rotation:
            norm = np.linalg.norm(val, axis=1, keepdims=True)
            if not np.all(norm > 1e-6):  # neighbouring keys q and -q interpolate through zero
                doc.fail(f"{sw}.output", f"accessors[{o}]: resampled rotations pass through zero (neighbouring "
                                         "keys are opposite quaternions)")
            val = val / norm
        anim_of[(node, tpath)] = val

    # forward kinematics through every node above the joints, in blocks of frames
    # per path: the animated slots of rig.needed and their values (F, n, 3 or 4), stacked once
    animated = {}
    for tpath in _TRS:
        nodes = [i for (i, p) in anim_of if p == tpath]
        for i in nodes:
            if rig.slot[i] in rig.fixed:
                doc.fail(f"nodes[{i}].matrix", "an animated node must have translation/rotation/scale, not a matrix")
        if nodes:
            animated[tpath] = ([rig.slot[i] for i in nodes], np.stack([anim_of.pop((i, tpath)) for i in nodes], 1))
    rest_trs = dict(zip(_TRS, (rig.rest_t, rig.rest_q, rig.rest_s)))
    at = [rig.slot[i] for i in rig.order]
    rotations = np.empty((n_f, len(rig.order), 4))
    root_pos = np.empty((n_f, 3))
    block = max(1, _FK_BLOCK // len(rig.needed))
    inv_rest = np.swapaxes(rest_rot, -1, -2)[None]
    for a in range(0, n_f, block):
        b = min(n_f, a + block)
        trs = []
        for tpath in _TRS:
            v = np.repeat(rest_trs[tpath][None], b - a, axis=0)
            if tpath in animated:
                slots, vals = animated[tpath]
                v[:, slots] = vals[a:b]
            trs.append(v)
        w = rig.compose(rig.local(*trs))[:, at]  # (B, J, 4, 4)
        if not np.all(np.isfinite(w)):
            f, j = (int(x) for x in np.argwhere(~np.isfinite(w))[0, :2])
            doc.fail(aw, f"the world transform of nodes[{rig.order[j]}] at frame {a + f} is not finite")
        g_rot = _polar(w[..., :3, :3]) @ inv_rest  # ours: world rot @ rest^-1
        glob = rot.from_matrix(g_rot)
        local = np.empty_like(glob)
        local[:, 0] = glob[:, 0]
        local[:, 1:] = rot.multiply(rot.inverse(glob[:, skel.parents[1:]]), glob[:, 1:])
        rotations[a:b] = rot.normalize(local)
        root_pos[a:b] = w[:, 0, :3, 3]
    try:
        return Motion(skel, fps, rotations, root_pos)
    except ParameterError as exc:
        doc.fail(aw, str(exc))
