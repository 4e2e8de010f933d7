"""glTF 2.0 (.glb): written with pygltflib, checked by forward kinematics from the file alone."""
from __future__ import annotations

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation

import rigs
from gesturedb.errors import InputFileError
from gesturedb.io import read_motion, write_motion
from gesturedb.io.gltf import read_gltf, read_gltf_rig, write_glb
from gesturedb.retarget import load_rig, retarget


@pytest.fixture(scope="module")
def source(scott_dir):
    return read_motion(scott_dir / "2_scott_0_1_1.npz")[300:600]


def _accessor(gl, blob, i):
    """An accessor's floats, read with nothing but the file's own layout."""
    acc = gl.accessors[i]
    bv = gl.bufferViews[acc.bufferView]
    n = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    assert acc.componentType == pygltflib.FLOAT and not bv.byteStride
    start = bv.byteOffset + (acc.byteOffset or 0)
    return np.frombuffer(blob, np.float32, acc.count * n, start).reshape(acc.count, n).astype(np.float64)


def fk_from_file(path):
    """Joint world positions (F, J, 3) and names, from the .glb alone (pygltflib + scipy, none of our code)."""
    gl = pygltflib.GLTF2().load(str(path))
    blob = gl.binary_blob()
    joints = gl.skins[0].joints
    anim = gl.animations[0]
    times = _accessor(gl, blob, anim.samplers[0].input)[:, 0]
    n_f = len(times)
    trs = {}
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        assert s.interpolation == "LINEAR" and np.array_equal(_accessor(gl, blob, s.input)[:, 0], times)
        trs[(ch.target.node, ch.target.path)] = _accessor(gl, blob, s.output)
    parent = {c: i for i, nd in enumerate(gl.nodes) for c in (nd.children or [])}
    world = {}

    def w(i):
        if i not in world:
            nd = gl.nodes[i]
            t = trs.get((i, "translation"), np.tile(nd.translation or [0, 0, 0], (n_f, 1)))
            q = trs.get((i, "rotation"), np.tile(nd.rotation or [0, 0, 0, 1], (n_f, 1)))
            m = np.zeros((n_f, 4, 4))
            m[:, :3, :3] = Rotation.from_quat(q).as_matrix()  # scipy is (x, y, z, w), as glTF
            m[:, :3, 3] = t
            m[:, 3, 3] = 1
            world[i] = m if i not in parent else w(parent[i]) @ m
        return world[i]

    pos = np.stack([w(j)[:, :3, 3] for j in joints], axis=1)
    return pos, [gl.nodes[j].name for j in joints], times, gl


def test_glb_forward_kinematics_from_the_file_matches(source, tmp_path):
    out = tmp_path / "scott.glb"
    write_glb(out, source)
    pos, names, times, gl = fk_from_file(out)
    assert names == source.skeleton.names
    np.testing.assert_allclose(times, np.arange(source.n_frames) / source.fps, atol=1e-6)
    err = np.abs(pos - source.positions).max()
    print(f"glb FK vs ours: max {err:.2e} m")
    assert err < 1e-4
    # one rotation channel per joint and the root translation
    paths = sorted((c.target.node, c.target.path) for c in gl.animations[0].channels)
    assert paths == sorted([(j, "rotation") for j in range(len(names))] + [(0, "translation")])
    # the skinned mesh is bound at the rest pose: inverse bind matrices undo the rest joint placements
    ibm = _accessor(gl, gl.binary_blob(), gl.skins[0].inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    rest = source.skeleton.rest_positions()
    np.testing.assert_allclose(ibm[:, :3, 3], -rest, atol=1e-5)
    assert gl.meshes and gl.nodes[gl.scenes[0].nodes[1]].skin == 0

    # our reader gives the same motion back
    back = read_gltf(out)
    assert back.fps == source.fps and back.skeleton.names == names
    np.testing.assert_allclose(back.positions, source.positions, atol=1e-4)


def test_retargeted_glb_and_a_rig_with_rotated_bone_axes(source, tmp_path):
    rig_bvh = tmp_path / "mixamo.bvh"
    rig_bvh.write_text(rigs.mixamo_rig())
    res = retarget(source, load_rig(rig_bvh))
    out = tmp_path / "mixamo.glb"
    write_motion(out, res.motion)
    pos, names, _, _ = fk_from_file(out)
    assert names == res.motion.skeleton.names
    assert np.abs(pos - res.motion.positions).max() < 1e-4

    # the same rig as a glTF skin whose bones have their own axes (random rest rotations) under an
    # "Armature" node scaled to centimetres, as exporters write them: same rest joints in metres
    gl = pygltflib.GLTF2().load(str(out))
    rng = np.random.default_rng(0)
    sk = res.motion.skeleton
    rest_world = sk.rest_positions() / 0.01  # in the armature's centimetres
    rest_world[:] -= rest_world[0] - sk.offsets[0] / 0.01
    world_rot = Rotation.random(sk.n_joints, random_state=rng)
    for j in range(sk.n_joints):
        p = sk.parents[j]
        if p < 0:
            t, r = rest_world[j], world_rot[j]
        else:
            t = world_rot[p].inv().apply(rest_world[j] - rest_world[p])
            r = world_rot[p].inv() * world_rot[j]
        gl.nodes[j].translation = [float(x) for x in t]
        gl.nodes[j].rotation = [float(x) for x in r.as_quat()]
    gl.nodes.append(pygltflib.Node(name="Armature", scale=[0.01, 0.01, 0.01], children=[0]))
    gl.scenes[0].nodes = [len(gl.nodes) - 1]
    # the animation in those bone frames: world rotation = our global rotation @ the bone's rest rotation
    _, glob = res.motion.forward_kinematics()
    g_w = [Rotation.from_quat(glob[:, j][:, [1, 2, 3, 0]]) * world_rot[j] for j in range(sk.n_joints)]
    blob = bytearray(gl.binary_blob())
    anim = gl.animations[0]
    for ch in anim.channels:
        j = ch.target.node
        if ch.target.path == "rotation":
            local = g_w[j] if sk.parents[j] < 0 else g_w[sk.parents[j]].inv() * g_w[j]
            val = local.as_quat().astype(np.float32)
        else:
            val = (res.motion.root_positions / 0.01).astype(np.float32)
        acc = gl.accessors[anim.samplers[ch.sampler].output]
        start = gl.bufferViews[acc.bufferView].byteOffset
        blob[start:start + val.nbytes] = val.tobytes()
    gl.set_binary_blob(bytes(blob))
    odd = tmp_path / "odd_axes.glb"
    gl.save_binary(str(odd))
    # read back as motion in the project's convention: the same joint positions
    moved = read_gltf(odd)
    np.testing.assert_allclose(moved.positions, res.motion.positions, atol=1e-5)
    # and the same local rotations (up to the sign of the quaternion)
    dot = np.abs((moved.rotations * res.motion.rotations).sum(-1))
    assert dot.min() > 1 - 1e-9
    rig = read_gltf_rig(odd)
    assert rig.names == sk.names
    np.testing.assert_allclose(rig.rest_positions() - rig.offsets[0], sk.rest_positions() - sk.offsets[0],
                               atol=1e-5)
    # and the motion retargeted onto it is the one retargeted onto the BVH form of the rig
    again = retarget(source, load_rig(odd)).motion
    np.testing.assert_allclose(again.positions - again.positions[:, :1],
                               res.motion.positions - res.motion.positions[:, :1], atol=1e-5)


def test_gltf_errors(tmp_path, source):
    gl = pygltflib.GLTF2(nodes=[pygltflib.Node(name="a")], scenes=[pygltflib.Scene(nodes=[0])])
    gl.save_binary(str(tmp_path / "noskin.glb"))
    with pytest.raises(InputFileError, match="noskin.glb.*skins: expected a skin"):
        read_gltf_rig(tmp_path / "noskin.glb")
    (tmp_path / "junk.glb").write_bytes(b"not a gltf")
    with pytest.raises(InputFileError, match="junk.glb"):
        read_gltf(tmp_path / "junk.glb")
    with pytest.raises(InputFileError, match=r"x\.fbx.*expected \.bvh or \.glb"):
        write_motion(tmp_path / "x.fbx", source)
    assert not list(tmp_path.glob("x.fbx*"))


# --- hostile files (issue 41): one-line errors naming the file and the field, bounded time and memory ---

import json  # noqa: E402
import os  # noqa: E402
import struct  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

from gesturedb.errors import GestureDBError  # noqa: E402
from gesturedb.motion import Motion, Skeleton  # noqa: E402


def tiny_motion(n_frames=4):
    """Three joints in a chain, a few frames of turning: small enough to edit by hand."""
    sk = Skeleton(["Hips", "Spine", "Head"], [-1, 0, 1], [[0, 1, 0], [0, 0.3, 0], [0, 0.3, 0]], ["ZXY"] * 3)
    ang = np.linspace(0, 0.5, n_frames)
    q = np.zeros((n_frames, 3, 4))
    q[..., 0] = np.cos(ang / 2)[:, None]
    q[..., 2] = np.sin(ang / 2)[:, None]
    root = np.stack([ang, np.ones(n_frames), np.zeros(n_frames)], axis=1)
    return Motion(sk, 30.0, q, root)


def split_glb(data: bytes):
    """A .glb's JSON (as a dict) and BIN chunk."""
    (jlen,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20:20 + jlen])
    (blen,) = struct.unpack_from("<I", data, 20 + jlen)
    return doc, bytearray(data[28 + jlen:28 + jlen + blen])


def make_glb(doc, blob) -> bytes:
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    blob = bytes(blob) + b"\0" * (-len(blob) % 4)
    body = struct.pack("<I4s", len(j), b"JSON") + j + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


@pytest.fixture()
def tiny(tmp_path):
    """(json dict, BIN bytes, motion) of a small .glb written by write_glb."""
    m = tiny_motion()
    write_glb(tmp_path / "tiny.glb", m, mesh=False)
    doc, blob = split_glb((tmp_path / "tiny.glb").read_bytes())
    return doc, blob, m


def _times_accessor(doc):
    return doc["animations"][0]["samplers"][0]["input"]


def _one_line(exc_info, name):
    msg = str(exc_info.value)
    assert "\n" not in msg and msg.startswith(str(name)), msg
    return msg


def test_own_glb_json_and_external_buffers_read_the_same(tiny, tmp_path):
    """The split and rebuilt .glb, a .gltf with a data: URI and one with a .bin beside it all read alike."""
    doc, blob, m = tiny
    (tmp_path / "re.glb").write_bytes(make_glb(doc, blob))
    ref = read_gltf(tmp_path / "re.glb")
    np.testing.assert_allclose(ref.positions, m.positions, atol=1e-6)
    d = json.loads(json.dumps(doc))
    import base64

    d["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode()
    (tmp_path / "inline.gltf").write_text(json.dumps(d))
    d["buffers"][0]["uri"] = "tiny%20data.bin"
    (tmp_path / "tiny data.bin").write_bytes(bytes(blob))
    (tmp_path / "beside.gltf").write_text(json.dumps(d))
    for name in ("inline.gltf", "beside.gltf"):
        np.testing.assert_array_equal(read_gltf(tmp_path / name).rotations, ref.rotations)
    assert read_gltf_rig(tmp_path / "beside.gltf").names == ["Hips", "Spine", "Head"]


# case 9: node cycles, two parents, deep chains

def test_node_cycles_are_one_line_errors(tiny, tmp_path):
    doc, blob, _ = tiny
    own = json.loads(json.dumps(doc))
    own["nodes"][1]["children"] = [2, 1]
    (tmp_path / "own.glb").write_bytes(make_glb(own, blob))
    for reader in (read_gltf, read_gltf_rig):
        with pytest.raises(InputFileError, match=r"own\.glb: nodes\[1\]\.children: node 1 is its own child") as e:
            reader(tmp_path / "own.glb")
        _one_line(e, tmp_path / "own.glb")
    loop = json.loads(json.dumps(doc))
    loop["nodes"][0]["children"] = []
    loop["nodes"][2]["children"] = [1]  # 1 -> 2 -> 1, out of reach of any root
    (tmp_path / "loop.glb").write_bytes(make_glb(loop, blob))
    with pytest.raises(InputFileError, match=r"loop\.glb: nodes\[\d\]\.children: the node hierarchy has a cycle: "
                                             r"nodes (1 -> 2 -> 1|2 -> 1 -> 2)"):
        read_gltf(tmp_path / "loop.glb")
    two = json.loads(json.dumps(doc))
    two["nodes"][0]["children"] = [1, 2]  # 2 is also 1's child
    (tmp_path / "two.glb").write_bytes(make_glb(two, blob))
    with pytest.raises(InputFileError, match=r"two\.glb: nodes\[1\]\.children: node 2 is already a child of node 0"):
        read_gltf_rig(tmp_path / "two.glb")


def test_a_deep_node_chain_reads_without_recursion(tiny, tmp_path):
    """5,000 plain nodes above the rig: the walks are iterative (no RecursionError) and quick."""
    import time

    doc, blob, m = tiny
    n0 = len(doc["nodes"])
    depth = 5000
    doc["nodes"] += [{"name": f"group{k}", "children": [n0 + k + 1 if k + 1 < depth else 0]} for k in range(depth)]
    doc["scenes"][0]["nodes"] = [n0]
    (tmp_path / "deep.glb").write_bytes(make_glb(doc, blob))
    t0 = time.perf_counter()
    back = read_gltf(tmp_path / "deep.glb")
    assert time.perf_counter() - t0 < 30
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6)


def _cli(*argv, timeout=120):
    """`gesturedb ...` in a child process with a time limit and a 4 GB address-space limit."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))

    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "gesturedb.cli", *map(str, argv)], capture_output=True, text=True,
                          timeout=timeout, preexec_fn=limit, env=env)


def test_cli_on_a_self_child_node_ends_at_once_with_one_line(tiny, tmp_path, scott_dir):
    """Used to grow memory by ~16 MB/s for ever: now exit 2 and one line within the time limit, as input or rig."""
    doc, blob, _ = tiny
    doc["nodes"][1]["children"] = [2, 1]
    bad = tmp_path / "cycle.glb"
    bad.write_bytes(make_glb(doc, blob))
    rig = tmp_path / "mixamo.bvh"
    rig.write_text(rigs.mixamo_rig())
    out = tmp_path / "out.bvh"
    for argv in (("retarget", bad, "--to", rig, "-o", out),
                 ("retarget", scott_dir / "2_scott_0_1_1.npz", "--to", bad, "-o", out)):
        proc = _cli(*argv)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.count("\n") == 1, proc.stderr
        assert proc.stderr.startswith(f"gesturedb retarget: error: {bad}: nodes[1].children: node 1 is its own child")
        assert not out.exists()


def test_synth_reads_the_target_rig_before_the_database(tiny, tmp_path, scott_dir, capsys):
    """synth --target-skeleton: a broken rig is found before any synthesis, not after minutes of it."""
    from gesturedb.cli.main import main

    doc, blob, _ = tiny
    doc["nodes"][1]["children"] = [2, 1]
    bad = tmp_path / "cycle.glb"
    bad.write_bytes(make_glb(doc, blob))
    db = tmp_path / "no.h5"
    db.write_bytes(b"")  # never opened: the rig fails first
    out = tmp_path / "s.bvh"
    code = main(["synth", str(db), "--audio", str(scott_dir / "inputs/2_scott_0_3_3.wav"),
                 "--target-skeleton", str(bad), "-o", str(out)])
    _, err = capsys.readouterr()
    assert code == 2 and err.count("\n") == 1, err
    assert f"{bad}: nodes[1].children: node 1 is its own child" in err and not out.exists()
