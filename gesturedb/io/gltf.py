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
"""
from __future__ import annotations

import os

import numpy as np

from gesturedb import rotations as rot
from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io.atomic import atomic_open
from gesturedb.motion import Motion, Skeleton

__all__ = ["read_gltf", "read_gltf_rig", "write_glb"]

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

_COMP = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def _load(path):
    g = _pygltflib()
    try:
        gl = g.GLTF2().load(os.fspath(path))
    except Exception as exc:  # pygltflib raises assorted errors on a broken file
        raise InputFileError(path, f"not a readable glTF 2.0 file: {exc}") from None
    if gl is None:
        raise InputFileError(path, "not a readable glTF 2.0 file")
    blob = gl.binary_blob()
    buffers = []
    for i, b in enumerate(gl.buffers):
        if b.uri is None:
            if blob is None:
                raise InputFileError(path, f"buffers[{i}]: no uri and no binary chunk")
            buffers.append(blob)
        elif b.uri.startswith("data:"):
            buffers.append(gl.decode_data_uri(b.uri))
        else:
            with open(os.path.join(os.path.dirname(os.fspath(path)), b.uri), "rb") as f:
                buffers.append(f.read())
    return gl, buffers


def _accessor(gl, buffers, i) -> np.ndarray:
    acc = gl.accessors[i]
    n = _NCOMP[acc.type]
    dt = np.dtype(_COMP[acc.componentType])
    out = np.zeros((acc.count, n), dt)
    if acc.bufferView is not None:
        bv = gl.bufferViews[acc.bufferView]
        start = (bv.byteOffset or 0) + (acc.byteOffset or 0)
        stride = bv.byteStride or n * dt.itemsize
        raw = np.frombuffer(buffers[bv.buffer], np.uint8, count=stride * (acc.count - 1) + n * dt.itemsize,
                            offset=start)
        idx = np.arange(acc.count)[:, None] * stride + np.arange(n * dt.itemsize)[None, :]
        out = raw[idx].copy().view(dt).reshape(acc.count, n)
    if acc.normalized and dt.kind in "iu":
        out = out.astype(np.float64) / np.iinfo(dt).max
    return out.astype(np.float64) if dt == np.float32 or acc.normalized else out


def _trs_matrix(t, q_xyzw, s) -> np.ndarray:
    """(..., 4, 4) matrices from translations (..., 3), glTF quaternions (..., 4) x,y,z,w, scales (..., 3)."""
    t, q, s = np.asarray(t, float), np.asarray(q_xyzw, float), np.asarray(s, float)
    shape = np.broadcast_shapes(t.shape[:-1], q.shape[:-1], s.shape[:-1])
    m = np.zeros(shape + (4, 4))
    m[..., :3, :3] = rot.to_matrix(rot.normalize(q[..., [3, 0, 1, 2]])) * s[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def _rest_local(node) -> np.ndarray:
    if node.matrix is not None and len(node.matrix) == 16:
        return np.asarray(node.matrix, float).reshape(4, 4).T  # column-major
    return _trs_matrix(node.translation or [0, 0, 0], node.rotation or [0, 0, 0, 1], node.scale or [1, 1, 1])


def _rig(path, gl):
    """Skin joints parents-first, their parents, the node chain above each, and rest world matrices."""
    if not gl.skins:
        raise InputFileError(path, "skins: expected a skin (the rig's joints); the file has none")
    joints = list(gl.skins[0].joints)
    parent_node = {}
    for i, node in enumerate(gl.nodes):
        for c in node.children or []:
            parent_node[c] = i
    # rest world matrix of every node (through non-joint ancestors too: an Armature node's scale or turn)
    world = {}

    def world_of(i):
        if i not in world:
            p = parent_node.get(i)
            loc = _rest_local(gl.nodes[i])
            world[i] = loc if p is None else world_of(p) @ loc
        return world[i]

    jset = set(joints)

    def joint_parent(i):
        p = parent_node.get(i)
        while p is not None and p not in jset:
            p = parent_node.get(p)
        return p

    def depth(i):
        d, p = 0, parent_node.get(i)
        while p is not None:
            d, p = d + 1, parent_node.get(p)
        return d

    roots = [i for i in joints if joint_parent(i) is None]
    if len(roots) != 1:
        raise InputFileError(path, f"skins[0]: expected one root joint; got {len(roots)} "
                                   f"({', '.join(gl.nodes[i].name or str(i) for i in roots)})")
    # parents first: depth-first order from the root, children in file order
    order, stack = [], [roots[0]]
    while stack:
        i = stack.pop()
        order.append(i)
        stack += [c for c in reversed(gl.nodes[i].children or []) if c in jset]
    if len(order) != len(joints):
        raise InputFileError(path, "skins[0]: its joints are not one connected hierarchy")
    pos_in_skin = {n: k for k, n in enumerate(joints)}
    if joints[0] == roots[0] and all(pos_in_skin[joint_parent(i)] < pos_in_skin[i] for i in joints[1:]):
        order = joints  # already parents-first (our own files): keep the skin's joint order
    for i in order:
        world_of(i)
    return order, joint_parent, world, parent_node


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
        ``.glb`` or ``.gltf`` with at least one skin.

    Returns
    -------
    Skeleton
        Skin joints parents-first, named after their nodes; offsets in metres
        from the rest world positions (rest rotations folded in, so the rest pose
        is all identity); channel order ``"ZXY"`` for BVH export.

    Raises
    ------
    InputFileError
        No skin, several root joints, or an unreadable file.
    """
    gl, _ = _load(path)
    return _rig_skeleton(path, gl)[0]


def _rig_skeleton(path, gl):
    order, joint_parent, world, _ = _rig(path, gl)
    pos = np.array([world[i][:3, 3] for i in order])
    idx = {n: k for k, n in enumerate(order)}
    parents = np.array([-1] + [idx[joint_parent(i)] for i in order[1:]], dtype=np.int64)
    offsets = pos.copy()
    offsets[1:] = pos[1:] - pos[parents[1:]]
    names = [gl.nodes[i].name or f"joint{i}" for i in order]
    skel = Skeleton(names, parents, offsets, ["ZXY"] * len(order))
    rest_rot = _polar(np.array([world[i][:3, :3] for i in order]))
    return skel, order, rest_rot


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
        On `read_gltf_rig`'s skeleton, at the frame rate of the first channel's
        key times (which must be evenly spaced); other channels are
        interpolated at those times (linear; quaternions normalised).

    Raises
    ------
    InputFileError
        No skin, no such animation, uneven key times.
    """
    gl, buffers = _load(path)
    skel, order, rest_rot = _rig_skeleton(path, gl)
    if not (0 <= animation < len(gl.animations)):
        raise InputFileError(path, f"animations: expected animation {animation}; the file has {len(gl.animations)}")
    anim = gl.animations[animation]
    if not anim.channels:
        raise InputFileError(path, f"animations[{animation}]: no channels")
    times = _accessor(gl, buffers, anim.samplers[anim.channels[0].sampler].input)[:, 0]
    if times.size < 1:
        raise InputFileError(path, f"animations[{animation}]: no key times")
    if times.size > 1:
        dt = np.diff(times)
        if dt.min() <= 0 or (dt.max() - dt.min()) > 1e-3 * dt.mean():
            raise InputFileError(path, f"animations[{animation}] key times: expected evenly spaced frames; got "
                                       f"steps from {dt.min():.6g} to {dt.max():.6g} s")
        fps = 1.0 / float(dt.mean())
        if abs(fps - round(fps)) < 1e-4 * fps:  # float32 key times: 30.0000013 is 30
            fps = float(round(fps))
    else:
        fps = 30.0
    n_f = times.size
    anim_of = {}
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        tin = _accessor(gl, buffers, s.input)[:, 0]
        val = _accessor(gl, buffers, s.output)
        if s.interpolation == "CUBICSPLINE":
            val = val.reshape(len(tin), 3, -1)[:, 1]
        if tin.size != n_f or not np.allclose(tin, times):
            val = np.stack([np.interp(times, tin, val[:, k]) for k in range(val.shape[1])], axis=1)
        if ch.target.path == "rotation":
            val = val / np.linalg.norm(val, axis=1, keepdims=True)
        anim_of[(ch.target.node, ch.target.path)] = val

    _, _, _, parent_node = _rig(path, gl)
    worlds = {}

    def world_of(i):
        if i not in worlds:
            node = gl.nodes[i]
            if (node.matrix is not None and len(node.matrix) == 16
                    and not any((i, p) in anim_of for p in ("translation", "rotation", "scale"))):
                loc = np.broadcast_to(_rest_local(node), (n_f, 4, 4))
            else:
                t = anim_of.get((i, "translation"), np.asarray(node.translation or [0, 0, 0], float))
                q = anim_of.get((i, "rotation"), np.asarray(node.rotation or [0, 0, 0, 1], float))
                s = anim_of.get((i, "scale"), np.asarray(node.scale or [1, 1, 1], float))
                loc = _trs_matrix(np.broadcast_to(t, (n_f, 3)), np.broadcast_to(q, (n_f, 4)),
                                  np.broadcast_to(s, (n_f, 3)))
            p = parent_node.get(i)
            worlds[i] = loc if p is None else world_of(p) @ loc
        return worlds[i]

    w = np.stack([world_of(i) for i in order], axis=1)  # (F, J, 4, 4)
    g_rot = _polar(w[..., :3, :3]) @ np.swapaxes(rest_rot, -1, -2)[None]  # ours: world rot @ rest^-1
    glob = rot.from_matrix(g_rot)
    local = np.empty_like(glob)
    local[:, 0] = glob[:, 0]
    local[:, 1:] = rot.multiply(rot.inverse(glob[:, skel.parents[1:]]), glob[:, 1:])
    return Motion(skel, fps, rot.normalize(local), w[:, 0, :3, 3])
