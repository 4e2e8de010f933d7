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
import re  # noqa: E402
import struct  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

from gesturedb.errors import ParameterError  # noqa: E402
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


# case 10: a buffer uri names a data: URI or a regular file inside the glTF file's folder, byteLength long

def _gltf_with_uri(tiny, folder, uri, name="x.gltf", byte_length=None):
    doc, blob, _ = tiny
    d = json.loads(json.dumps(doc))
    d["buffers"][0]["uri"] = uri
    if byte_length is not None:
        d["buffers"][0]["byteLength"] = byte_length
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(json.dumps(d))
    return folder / name


@pytest.mark.parametrize("uri, error", [
    ("/dev/zero", r"buffers\[0\]\.uri: expected a path relative to the glTF file's folder; got '/dev/zero'"),
    ("../../etc/passwd", r"buffers\[0\]\.uri: '\.\./\.\./etc/passwd' leads outside the glTF file's folder"),
    ("..%2F..%2Fetc%2Fpasswd", r"buffers\[0\]\.uri: '\.\.%2F\.\.%2Fetc%2Fpasswd' leads outside"),
    ("file:///etc/passwd", r"buffers\[0\]\.uri: expected a data: URI or a path relative to the glTF file; "
                           r"got 'file:///etc/passwd'"),
    ("https://example.com/a.bin", r"buffers\[0\]\.uri: expected a data: URI or a path relative"),
    ("missing.bin", r"buffers\[0\]\.uri: 'missing\.bin': no such file"),
    ("", r"buffers\[0\]\.uri: '': expected a regular file; got a folder"),
    ("sub", r"buffers\[0\]\.uri: 'sub': expected a regular file; got a folder"),
    ("data:application/octet-stream;base64,@@@@", r"buffers\[0\]\.uri: bad base64 in the data: URI"),
    ("data:application/octet-stream,AAAA", r"buffers\[0\]\.uri: expected a base64 data: URI"),
    ("data:application/octet-stream;base64,AAAA", r"buffers\[0\]\.byteLength: expected the 3 bytes the data: "
                                                  r"URI holds; got \d+"),
])
def test_buffer_uris_outside_the_folder_or_not_files_are_refused(tiny, tmp_path, uri, error):
    folder = tmp_path / "a" / "b"
    (folder / "sub").mkdir(parents=True)
    path = _gltf_with_uri(tiny, folder, uri)
    with pytest.raises(InputFileError, match=error) as e:
        read_gltf(path)
    _one_line(e, path)


def test_buffer_files_must_be_regular_and_byte_length_long(tiny, tmp_path):
    doc, blob, _ = tiny
    # a link inside the folder to a device or to a file outside it: refused where it leads
    os.symlink("/dev/zero", tmp_path / "zero.bin")
    with pytest.raises(InputFileError, match=r"buffers\[0\]\.uri: 'zero\.bin' leads outside the glTF file's folder"):
        read_gltf(_gltf_with_uri(tiny, tmp_path, "zero.bin"))
    # a pipe inside the folder: refused without waiting for a writer
    os.mkfifo(tmp_path / "pipe.bin")
    with pytest.raises(InputFileError, match=r"buffers\[0\]\.uri: 'pipe\.bin': expected a regular file; got a "
                                             r"device, pipe or socket"):
        read_gltf(_gltf_with_uri(tiny, tmp_path, "pipe.bin"))
    # a file longer or shorter than byteLength: refused, nothing read past byteLength
    (tmp_path / "long.bin").write_bytes(bytes(blob) + b"\0" * 100)
    with pytest.raises(InputFileError, match=rf"buffers\[0\]\.byteLength: expected the {len(blob) + 100} bytes of "
                                             rf"'long\.bin'; got {len(blob)}"):
        read_gltf(_gltf_with_uri(tiny, tmp_path, "long.bin"))
    (tmp_path / "short.bin").write_bytes(bytes(blob[:-8]))
    with pytest.raises(InputFileError, match=r"buffers\[0\]\.byteLength: expected the \d+ bytes of 'short\.bin'"):
        read_gltf(_gltf_with_uri(tiny, tmp_path, "short.bin"))
    # a subfolder is inside the folder: allowed
    (tmp_path / "bins").mkdir()
    (tmp_path / "bins" / "ok.bin").write_bytes(bytes(blob))
    assert read_gltf(_gltf_with_uri(tiny, tmp_path, "bins/ok.bin")).n_frames == 4
    # the rig needs no buffers: a missing .bin does not stop read_gltf_rig (load_rig, --to)
    assert read_gltf_rig(_gltf_with_uri(tiny, tmp_path, "gone.bin")).n_joints == 3
    # the input itself must be a regular file
    with pytest.raises(InputFileError, match=r"pipe\.bin: expected a regular file"):
        read_gltf(tmp_path / "pipe.bin")


# case 12: hostile files: truncated, out-of-range indices, bad types and sizes, NaN key times

def _edit_acc(doc, k, **kw):
    doc["accessors"][k].update(kw)


def _nan_times(doc, blob):
    acc = doc["accessors"][_times_accessor(doc)]
    start = doc["bufferViews"][acc["bufferView"]]["byteOffset"] + acc.get("byteOffset", 0)
    blob[start + 4:start + 8] = struct.pack("<f", float("nan"))


def _view_of(doc, k):
    return doc["bufferViews"][doc["accessors"][k]["bufferView"]]


HOSTILE = {
    # name: (edit of (doc, blob) -> None, regex naming the field)
    "bad_byte_offset": (lambda d, b: _view_of(d, _times_accessor(d)).update(byteOffset=10 ** 6),
                        r"bufferViews\[\d+\]\.byteOffset: bytes 1000000 to \d+ lie past the end of buffers\[0\]"),
    "negative_byte_offset": (lambda d, b: _edit_acc(d, _times_accessor(d), byteOffset=-4),
                             r"accessors\[\d+\]\.byteOffset: expected an integer >= 0; got -4"),
    "buffer_view_range": (lambda d, b: _edit_acc(d, _times_accessor(d), bufferView=99),
                          r"accessors\[\d+\]\.bufferView: expected an index into bufferViews \(0 to \d+\); got 99"),
    "buffer_range": (lambda d, b: _view_of(d, _times_accessor(d)).update(buffer=3),
                     r"bufferViews\[\d+\]\.buffer: expected an index into buffers \(0 to 0\); got 3"),
    "sampler_range": (lambda d, b: d["animations"][0]["channels"][0].update(sampler=500),
                      r"animations\[0\]\.channels\[0\]\.sampler: expected an index into animations\[0\]\.samplers"),
    "accessor_range": (lambda d, b: d["animations"][0]["samplers"][0].update(input=77),
                       r"animations\[0\]\.samplers\[0\]\.input: expected an index into accessors"),
    "joint_range": (lambda d, b: d["skins"][0]["joints"].__setitem__(1, 40),
                    r"skins\[0\]\.joints\[1\]: expected an index into nodes \(0 to 2\); got 40"),
    "node_range": (lambda d, b: d["animations"][0]["channels"][1]["target"].update(node=-1),
                   r"animations\[0\]\.channels\[1\]\.target\.node: expected an index into nodes"),
    "child_range": (lambda d, b: d["nodes"][0].update(children=[1, 9]),
                    r"nodes\[0\]\.children\[1\]: expected an index into nodes \(0 to 2\); got 9"),
    "component_type": (lambda d, b: _edit_acc(d, _times_accessor(d), componentType=5130),
                       r"accessors\[\d+\]\.componentType: expected one of 5120, 5121, 5122, 5123, 5125, 5126; "
                       r"got 5130"),
    "wrong_type_for_times": (lambda d, b: _edit_acc(d, _times_accessor(d), type="VEC3"),
                             r"animations\[0\]\.samplers\[0\]\.input: expected an accessor of SCALAR of FLOAT; "
                             r"accessors\[\d+\] is VEC3 of FLOAT"),
    "stride_past_buffer": (lambda d, b: _view_of(d, _times_accessor(d)).update(byteStride=252),
                           r"accessors\[\d+\]\.count: 4 elements of 4 bytes \(stride 252\) from byteOffset 0 need "
                           r"760 bytes; bufferViews\[\d+\]\.byteLength is 16"),
    "stride_too_small": (lambda d, b: _view_of(d, d["animations"][0]["samplers"][0]["output"]).update(byteStride=8),
                         r"bufferViews\[\d+\]\.byteStride: expected at least the 16 bytes of one element"),
    "count_past_buffer": (lambda d, b: _edit_acc(d, _times_accessor(d), count=10 ** 12),
                          r"accessors\[\d+\]\.count: 1000000000000 elements of 4 bytes .* need \d+ bytes"),
    "negative_count": (lambda d, b: _edit_acc(d, _times_accessor(d), count=-3),
                       r"accessors\[\d+\]\.count: expected an integer >= 1; got -3"),
    "count_not_integer": (lambda d, b: _edit_acc(d, _times_accessor(d), count="4"),
                          r"accessors\[\d+\]\.count: expected an integer >= 1; got '4'"),
    "nan_key_times": (_nan_times, r"animations\[0\]\.samplers\[0\]\.input: accessors\[\d+\] element 1 is not "
                                  r"finite: \[nan\]"),
    "cubicspline_size": (lambda d, b: d["animations"][0]["samplers"][0].update(interpolation="CUBICSPLINE"),
                         r"animations\[0\]\.samplers\[0\]\.output: expected 12 values \(CUBICSPLINE, 4 key times\); "
                         r"accessors\[\d+\]\.count is 4"),
    "interpolation": (lambda d, b: d["animations"][0]["samplers"][0].update(interpolation="SMOOTH"),
                      r"animations\[0\]\.samplers\[0\]\.interpolation: expected one of LINEAR, STEP, CUBICSPLINE; "
                      r"got 'SMOOTH'"),
    "sparse": (lambda d, b: _edit_acc(d, _times_accessor(d), sparse={"count": 1}),
               r"accessors\[\d+\]\.sparse: sparse accessors are not supported"),
    "zero_rotation": (lambda d, b: d["nodes"][1].update(rotation=[0, 0, 0, 0]),
                      r"nodes\[1\]\.rotation: expected a unit quaternion; got \[0\.0, 0\.0, 0\.0, 0\.0\]"),
    "nan_translation": (lambda d, b: d["nodes"][2].update(translation=[0, float("nan"), 0]),
                        r"nodes\[2\]\.translation: expected 3 finite numbers"),
    "duplicate_names": (lambda d, b: d["nodes"][2].update(name="Spine"),
                        r"skins\[0\]\.joints: expected joints with unique names \(nodes\[i\]\.name\); repeated: "
                        r"'Spine'"),
    "two_roots": (lambda d, b: d["nodes"][1].update(children=[]),
                  r"skins\[0\]: expected one root joint; got 2 \(Hips, Head\)"),
    "buffer_byte_length": (lambda d, b: d["buffers"][0].update(byteLength=10 ** 9),
                           r"buffers\[0\]\.byteLength: expected at most the \d+ bytes of the GLB BIN chunk; "
                           r"got 1000000000"),
    "no_animation": (lambda d, b: d.pop("animations"), r"animations: expected animation 0; the file has 0"),
    "asset_version": (lambda d, b: d["asset"].update(version="1.0"), r"asset\.version: expected '2\.0'"),
    "nodes_not_array": (lambda d, b: d.update(nodes={"0": {}}), r"nodes: expected an array; got \{'0': \{\}\}"),
}


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_hostile_glb_gives_one_line_naming_the_field(tiny, tmp_path, name):
    doc, blob, _ = tiny
    edit, error = HOSTILE[name]
    edit(doc, blob)
    path = tmp_path / f"{name}.glb"
    path.write_bytes(make_glb(doc, blob))
    with pytest.raises(InputFileError, match=error) as e:
        read_gltf(path)
    _one_line(e, path)


def test_truncated_and_malformed_containers(tiny, tmp_path):
    doc, blob, _ = tiny
    good = make_glb(doc, blob)
    cases = {
        "cut.glb": (good[:len(good) // 2], r"GLB header length: says \d+ bytes; the file has \d+ \(truncated\)"),
        "cut_header.glb": (good[:9], r"GLB header: expected 12 bytes; the file has 9"),
        "v1.glb": (good[:4] + struct.pack("<I", 1) + good[8:], r"GLB header version: expected 2; got 1"),
        # the header's length fixed up to the cut: the chunk itself runs past the end
        "cut_chunk.glb": (good[:4] + struct.pack("<II", 2, 40) + good[12:40],
                          r"GLB chunk 0 length: \d+ bytes from byte 20 run past the end of the file \(40 bytes"),
        "bin_first.glb": (good[:16] + b"BIN\0" + good[20:], r"GLB chunk 0 type: expected JSON"),
        "not_json.glb": (good[:20] + b"X" + good[21:], r"JSON: Expecting value at line 1 column 1"),
        "junk.gltf": (b"\xff\xfe not text", r"JSON: not UTF-8 text"),
        "deep.gltf": (b"[" * 100_000 + b"]" * 100_000, r"JSON: nested too deeply"),
        "list.gltf": (b"[1, 2]", r"JSON: expected an object at the top; got list"),
        "bigint.gltf": (b'{"asset": {"version": "2.0"}, "nodes": ' + b"9" * 5000 + b"}", r"JSON: "),
    }
    for name, (data, error) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputFileError, match=error) as e:
            read_gltf(tmp_path / name)
        _one_line(e, tmp_path / name)


def test_rotations_stored_as_normalized_shorts_and_step_keys_read(tiny, tmp_path):
    """What the checks allow still reads: normalized SHORT rotations (as glTF permits) and STEP samplers."""
    doc, blob, m = tiny
    s = doc["animations"][0]["samplers"][1]
    acc = doc["accessors"][s["output"]]
    view = doc["bufferViews"][acc["bufferView"]]
    q = np.frombuffer(bytes(blob), np.float32, 16, view["byteOffset"]).reshape(4, 4)
    shorts = np.round(q * 32767).astype("<i2").tobytes()
    start = len(blob) + (-len(blob) % 4)
    blob += b"\0" * (start - len(blob)) + shorts
    doc["bufferViews"].append({"buffer": 0, "byteOffset": start, "byteLength": len(shorts)})
    doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5122, "normalized": True,
                             "count": 4, "type": "VEC4"})
    s["output"] = len(doc["accessors"]) - 1
    doc["buffers"][0]["byteLength"] = len(blob)
    (tmp_path / "shorts.glb").write_bytes(make_glb(doc, blob))
    np.testing.assert_allclose(read_gltf(tmp_path / "shorts.glb").positions, m.positions, atol=1e-4)
    # without normalized: refused, naming what came
    doc["accessors"][-1]["normalized"] = False
    (tmp_path / "raw_shorts.glb").write_bytes(make_glb(doc, blob))
    with pytest.raises(InputFileError, match=r"samplers\[1\]\.output: expected an accessor of VEC4 of FLOAT \(or "
                                             r"normalized integers\); accessors\[\d+\] is VEC4 of SHORT"):
        read_gltf(tmp_path / "raw_shorts.glb")


def test_read_gltf_animation_argument(tiny, tmp_path):
    doc, blob, _ = tiny
    (tmp_path / "t.glb").write_bytes(make_glb(doc, blob))
    with pytest.raises(ParameterError, match=r"animation: expected an integer index; got '0'"):
        read_gltf(tmp_path / "t.glb", animation="0")
    with pytest.raises(InputFileError, match=r"t\.glb: animations: expected animation 3; the file has 1"):
        read_gltf(tmp_path / "t.glb", animation=3)


def test_cli_retarget_with_hostile_glb_exits_2_with_one_line(tiny, tmp_path, capsys):
    from gesturedb.cli.main import main

    doc, blob, _ = tiny
    _edit_acc(doc, _times_accessor(doc), count=-3)
    bad = tmp_path / "neg.glb"
    bad.write_bytes(make_glb(doc, blob))
    rig = tmp_path / "mixamo.bvh"
    rig.write_text(rigs.mixamo_rig())
    out = tmp_path / "o.glb"
    assert main(["retarget", str(bad), "--to", str(rig), "-o", str(out)]) == 2
    _, err = capsys.readouterr()
    assert err.count("\n") == 1 and not out.exists(), err
    assert re.match(rf"gesturedb retarget: error: {re.escape(str(bad))}: accessors\[\d+\]\.count: expected an "
                    r"integer >= 1; got -3$", err.strip()), err


def test_frame_rate_and_size_limits(tiny, tmp_path, monkeypatch):
    doc, blob, _ = tiny
    acc = doc["accessors"][_times_accessor(doc)]
    start = doc["bufferViews"][acc["bufferView"]]["byteOffset"]
    slow = bytearray(blob)
    slow[start:start + 16] = np.array([0, 10, 20, 30], "<f4").tobytes()  # 0.1 fps
    (tmp_path / "slow.glb").write_bytes(make_glb(doc, slow))
    with pytest.raises(InputFileError, match=r"slow\.glb: animations\[0\] key times: expected 1 to 1000 frames per "
                                             r"second; got 0\.1$"):
        read_gltf(tmp_path / "slow.glb")
    # frames x nodes is capped before anything the size of the motion is allocated
    import gesturedb.io.gltf as gltf

    (tmp_path / "t.glb").write_bytes(make_glb(doc, blob))
    monkeypatch.setattr(gltf, "MAX_JOINT_FRAMES", 11)
    with pytest.raises(InputFileError, match=r"t\.glb: animations\[0\] key times: 4 frames x 3 nodes is more than "
                                             r"this reader's limit of 11 frame-joints"):
        read_gltf(tmp_path / "t.glb")
    monkeypatch.setattr(gltf, "MAX_JOINT_FRAMES", 12)
    assert read_gltf(tmp_path / "t.glb").n_frames == 4


def test_a_large_skin_with_repeated_names_fails_fast(tiny, tmp_path):
    """60,000 joints named alike: an error in about a second, not a quadratic search for the repeats."""
    import time

    doc, blob, _ = tiny
    n0, n = len(doc["nodes"]), 60_000
    doc["nodes"][2]["children"] = list(range(n0, n0 + n))
    doc["nodes"] += [{"name": "same"} for _ in range(n)]
    doc["skins"][0]["joints"] += list(range(n0, n0 + n))
    (tmp_path / "many.glb").write_bytes(make_glb(doc, blob))
    t0 = time.perf_counter()
    with pytest.raises(InputFileError, match=r"many\.glb: skins\[0\]\.joints: expected joints with unique names "
                                             r"\(nodes\[i\]\.name\); repeated: 'same'"):
        read_gltf_rig(tmp_path / "many.glb")
    assert time.perf_counter() - t0 < 30
