"""BVH reader/writer: a foreign file against an independent reference, write-then-read, bad input."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gesturedb import rotations as rt
from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io import read_motion
from gesturedb.io.bvh import read_bvh, write_bvh
from gesturedb.io.smplx import read_smplx
from gesturedb.motion import Motion, Skeleton

RNG = np.random.default_rng(5)


@pytest.fixture(scope="module")
def foreign_path(data_dir):
    return data_dir / "bvh-foreign" / "AV_8Walk_Meredith_HVHA_Rep1.bvh"


def _reference_positions(path, frames):
    """World positions (file units) of the given frames, by a deliberately simple parser + scipy."""
    lines = path.read_text().splitlines()
    stack, joints = [], []  # joints: (name, parent, offset, channels)
    pending = None
    for i, line in enumerate(lines):
        tok = line.split()
        if not tok:
            continue
        if tok[0] in ("ROOT", "JOINT"):
            pending = (tok[1], stack[-1] if stack else -1)
        elif tok[0] == "End":
            pending = ("<end>", stack[-1])
        elif tok[0] == "{":
            joints.append([pending[0], pending[1], None, []])
            stack.append(len(joints) - 1)
        elif tok[0] == "}":
            stack.pop()
        elif tok[0] == "OFFSET":
            joints[stack[-1]][2] = np.array(tok[1:4], float)
        elif tok[0] == "CHANNELS":
            joints[stack[-1]][3] = tok[2:]
        elif tok[0] == "MOTION":
            data = np.array([lines[i + 3 + f].split() for f in frames], float)
            break
    out = {}
    for k in range(len(frames)):
        col, world, pos = 0, {}, {}
        for j, (name, parent, offset, chans) in enumerate(joints):
            r = Rotation.identity()
            t = offset
            for c in chans:
                v = data[k, col]
                col += 1
                if c.endswith("rotation"):
                    r = r * Rotation.from_euler(c[0].lower(), v, degrees=True)
                elif c == "Xposition":
                    t = np.array([v, data[k, col], data[k, col + 1]])
            if parent < 0:
                world[j], pos[j] = r, t
            else:
                world[j] = world[parent] * r
                pos[j] = pos[parent] + world[parent].apply(offset)
            if name != "<end>":
                out.setdefault(name, []).append(pos[j])
    return {n: np.array(v) for n, v in out.items()}


def test_foreign_bvh_reads_like_the_file_says(foreign_path):
    m = read_bvh(foreign_path)
    sk = m.skeleton
    assert m.n_frames == 1064 and m.fps == 120.0
    assert sk.n_joints == 23 and sk.names[:3] == ["Hips", "Spine", "Head"]
    assert sk.channel_orders == ["XYZ"] * 23
    # 60.6 units from toe to head End Site: 0.61 m in centimetres, 1.54 m in inches (guess_length_unit)
    assert sk.length_unit_m == 0.0254
    assert len(sk.end_sites) == 7
    np.testing.assert_allclose(sk.offsets[sk.index("LeftArm")], [0.073084 * 2.54, 0, 0])
    np.testing.assert_allclose(m.root_positions[0], np.array([-0.065115, 0.355548, -1.630160]) * 2.54)
    frames = [0, 517, 1063]
    ref = _reference_positions(foreign_path, frames)
    pos = m.positions
    for name, p in ref.items():
        np.testing.assert_allclose(pos[frames, sk.index(name)], p * 0.0254, atol=1e-9, err_msg=name)


def test_length_unit_can_be_given(foreign_path):
    inch = read_bvh(foreign_path)
    cm = read_bvh(foreign_path, length_unit_m=0.01)
    assert cm.skeleton.length_unit_m == 0.01
    np.testing.assert_allclose(inch.positions[:50], cm.positions[:50] * 2.54, atol=1e-12)
    with pytest.raises(ParameterError, match="length_unit_m: expected a positive number"):
        read_bvh(foreign_path, length_unit_m=0)


def _positions_by_name(m):
    pos = m.positions
    return {n: pos[:, j] for j, n in enumerate(m.skeleton.names)}


def test_foreign_write_then_read(foreign_path, tmp_path):
    m = read_bvh(foreign_path)
    out = tmp_path / "copy.bvh"
    write_bvh(out, m)
    back = read_bvh(out)
    assert back.skeleton.names == m.skeleton.names and back.fps == m.fps
    assert back.skeleton.length_unit_m == 0.0254
    assert "OFFSET 7.308400 0.000000 0.000000" in out.read_text()  # written back in the file's unit
    tol = 1e-4 * m.skeleton.scale()
    np.testing.assert_allclose(back.positions, m.positions, atol=tol)
    # the same motion written in metres reads back (unit inferred as metres) to the same positions
    write_bvh(tmp_path / "metres.bvh", m, length_unit_m=1.0)
    metres = read_bvh(tmp_path / "metres.bvh")
    assert metres.skeleton.length_unit_m == 1.0
    np.testing.assert_allclose(metres.positions, m.positions, atol=tol)


def test_smplx_write_then_read(scott_dir, tmp_path):
    m = read_smplx(scott_dir / "2_scott_0_1_1.npz")[:400]
    out = tmp_path / "scott.bvh"
    write_bvh(out, m)
    back = read_motion(out)
    assert sorted(back.skeleton.names) == sorted(m.skeleton.names)
    assert back.skeleton.names[:4] == ["pelvis", "left_hip", "left_knee", "left_ankle"]  # depth first
    assert back.skeleton.length_unit_m == 1.0 and back.fps == 30.0
    assert set(back.skeleton.channel_orders) == {"ZXY"}
    tol = 1e-4 * m.skeleton.scale()
    a, b = _positions_by_name(m), _positions_by_name(back)
    worst = max(np.abs(a[n] - b[n]).max() for n in a)
    assert worst < tol
    ends_a, ends_b = m.end_site_positions(), back.end_site_positions()
    for j, p in ends_a.items():
        np.testing.assert_allclose(ends_b[back.skeleton.index(m.skeleton.names[j])], p, atol=tol)


def test_every_channel_order_round_trips(tmp_path):
    n_j = 18
    parents = np.array([-1] + [int(RNG.integers(0, j)) for j in range(1, n_j)])
    orders = [str(o) for o in RNG.choice(rt.EULER_ORDERS, n_j)]
    skel = Skeleton([f"joint{j}" for j in range(n_j)], parents, RNG.normal(scale=0.2, size=(n_j, 3)), orders,
                    {n_j - 1: np.array([0.0, 0.1, 0.0])})
    q = np.roll(Rotation.random(30 * n_j, random_state=3).as_quat(), 1, -1).reshape(30, n_j, 4)
    # include gimbal-locked rotations (middle angle exactly +-90)
    for j, o in enumerate(orders):
        q[0, j] = rt.from_euler([40.0, 90.0, -25.0], o)
        q[1, j] = rt.from_euler([-130.0, -90.0, 60.0], o)
    m = Motion(skel, 29.97, q, RNG.normal(size=(30, 3)))
    write_bvh(tmp_path / "orders.bvh", m)
    back = read_bvh(tmp_path / "orders.bvh", length_unit_m=1.0)
    idx = [back.skeleton.index(n) for n in skel.names]  # the file lists joints depth first
    assert [back.skeleton.channel_orders[i] for i in idx] == orders
    assert abs(back.fps - 29.97) < 1e-6  # not snapped to 30
    np.testing.assert_allclose(back.positions[:, idx], m.positions, atol=1e-4 * skel.scale())
    assert np.max(rt.angle_between(back.rotations[:, idx], m.rotations)) < 1e-6


MIXED = """HIERARCHY
ROOT Base
{
  OFFSET 0.0 0.0 0.0
  CHANNELS 6 Zrotation Xrotation Yrotation Xposition Yposition Zposition
  JOINT Torso {
    OFFSET 0.0 0.5 0.0
    CHANNELS 6 Xposition Yposition Zposition Yrotation Zrotation Xrotation
    JOINT Still
    {
      OFFSET 0.2 0.0 0.0
      CHANNELS 0
      JOINT Tip
      {
        OFFSET 0.3 0.0 0.0
        CHANNELS 3 Xrotation Zrotation Yrotation
        End Site
        {
          OFFSET 0.1 0.0 0.0
        }
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
10 20 30 1 2 3 0.0 0.5 0.0 5 -15 25 -40 10 70
0 0 0 0 0 0 0.0 0.5 0.0 0 0 0 0 0 0
"""


def test_mixed_channel_layouts(tmp_path):
    path = tmp_path / "mixed.bvh"
    path.write_text(MIXED)
    m = read_bvh(path)
    assert m.fps == 30.0 and m.skeleton.length_unit_m == 1.0
    assert m.skeleton.channel_orders == ["ZXY", "YZX", "", "XZY"]
    np.testing.assert_allclose(m.root_positions, [[1, 2, 3], [0, 0, 0]])
    r0 = Rotation.from_euler("ZXY", [10, 20, 30], degrees=True)
    r1 = r0 * Rotation.from_euler("YZX", [5, -15, 25], degrees=True)
    r3 = r1 * Rotation.from_euler("XZY", [-40, 10, 70], degrees=True)
    still = np.array([1, 2, 3]) + r0.apply([0, 0.5, 0]) + r1.apply([0.2, 0, 0])
    np.testing.assert_allclose(m.positions[0, 2], still, atol=1e-12)
    np.testing.assert_allclose(m.end_site_positions()[3][0], still + r1.apply([0.3, 0, 0]) + r3.apply([0.1, 0, 0]),
                               atol=1e-12)
    write_bvh(tmp_path / "again.bvh", m)
    text = (tmp_path / "again.bvh").read_text()
    assert "CHANNELS 0" in text and "CHANNELS 3 Xrotation Zrotation Yrotation" in text
    np.testing.assert_allclose(read_bvh(tmp_path / "again.bvh").positions, m.positions, atol=1e-6)


def test_moving_non_root_position_channels_warn(tmp_path):
    text = MIXED.replace("0 0 0 0 0 0 0.0 0.5 0.0", "0 0 0 0 0 0 0.0 0.7 0.0")
    (tmp_path / "moving.bvh").write_text(text)
    with pytest.warns(UserWarning, match="joint Torso has position channels that move"):
        m = read_bvh(tmp_path / "moving.bvh")
    np.testing.assert_allclose(m.skeleton.offsets[1], [0, 0.6, 0])
    (tmp_path / "steady.bvh").write_text(MIXED)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # constant position channels are just the offset: no warning
        read_bvh(tmp_path / "steady.bvh")


def test_three_channel_root_stays_at_its_offset(tmp_path):
    text = MIXED.replace("CHANNELS 6 Zrotation Xrotation Yrotation Xposition Yposition Zposition",
                         "CHANNELS 3 Zrotation Xrotation Yrotation").replace("OFFSET 0.0 0.0 0.0", "OFFSET 0.0 1.0 0.0")
    text = re.sub(r"^(\S+ \S+ \S+) \S+ \S+ \S+ ", r"\1 ", text, flags=re.M)  # drop the 3 root position values
    (tmp_path / "root3.bvh").write_text(text)
    m = read_bvh(tmp_path / "root3.bvh")
    np.testing.assert_allclose(m.root_positions, [[0, 1, 0], [0, 1, 0]])


# --- bad input ---------------------------------------------------------------------------

def _small(tmp_path, text, name="bad.bvh"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.fixture
def small_text(tmp_path, foreign_path):
    """The foreign file cut to 10 frames: 72 channels per frame line, frame lines start at line 148."""
    lines = foreign_path.read_text().splitlines()
    m = lines.index("MOTION")
    return "\n".join(lines[:m] + ["MOTION", "Frames: 10", "Frame Time: 0.008333"] + lines[m + 3:m + 13]) + "\n"


def test_small_text_fixture_is_valid(tmp_path, small_text):
    m = read_bvh(_small(tmp_path, small_text))
    assert m.n_frames == 10


@pytest.mark.parametrize("mutate, message", [
    (lambda t: "\n".join(t.splitlines()[:-3]) + "\n",
     r"Frames: 10 declared but the file has 7 frame lines \(fewer\) \(the file is truncated\)"),
    (lambda t: t.rstrip("\n")[:-40] + "\n", r"line 157 \(frame 9\): expected 72 values \(from CHANNELS\), got \d+"),
    (lambda t: "\n".join(ln if i != 150 else ln + " 1.0" for i, ln in enumerate(t.splitlines())) + "\n",
     r"line 151 \(frame 3\): expected 72 values \(from CHANNELS\), got 73"),
    (lambda t: re.sub(r"(?m)^(-?[\d.]+ )", "", t),  # every frame line one value short
     r"line 148 \(frame 0\): expected 72 values \(from CHANNELS\), got 71"),
    (lambda t: "\n".join(ln if i != 149 else ln.replace(" ", " abc ", 1) for i, ln in enumerate(t.splitlines())),
     r"line 150 \(frame 2\): expected 72 values \(from CHANNELS\), got 73"),
    (lambda t: "\n".join(ln if i != 152 else " ".join(ln.split()[:4] + ["x1.5"] + ln.split()[5:])
                         for i, ln in enumerate(t.splitlines())),
     r"line 153 \(frame 5\), value 5 \(Hips Yrotation\): expected a number, got 'x1.5'"),
    (lambda t: "\n".join(ln if i != 155 else " ".join(ln.split()[:10] + ["nan"] + ln.split()[11:])
                         for i, ln in enumerate(t.splitlines())),
     r"line 156 \(frame 8\), value 11 \(Head Yrotation\): expected a finite number, got nan"),
    (lambda t: t.replace("MOTION", "MOTON"), "no MOTION section"),
    (lambda t: t.replace("Frame Time: 0.008333", ""), r"line \d+: expected 'Frame Time: <number>'"),
    (lambda t: t.replace("Frame Time: 0.008333", "Frame Time: 0"), "Frame Time: expected a positive number"),
    (lambda t: t.replace("Frames: 10", "Frames: ten"), "Frames: expected a positive integer, got 'ten'"),
    (lambda t: t.replace("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 3 Xrotation Yrotation Wrotation", 1),
     "Spine CHANNELS: expected X/Y/Z position/rotation channels, got 'Wrotation'"),
    (lambda t: t.replace("OFFSET 0.0000 8.4730 0.0000", "OFFSET 0.0000 8.47a 0.0000"),
     r"line 8: Spine OFFSET: expected a number, got '8.47a'"),
    (lambda t: t.replace("JOINT Head", "JOINT Spine"), "JOINT Spine: the name is used twice"),
    (lambda t: t.split("MOTION")[0][:600], "no MOTION section"),
])
def test_bad_files_name_line_and_field(tmp_path, small_text, mutate, message):
    p = _small(tmp_path, mutate(small_text))
    with pytest.raises(InputFileError) as err:
        read_bvh(p)
    assert str(err.value).startswith(str(p) + ": ")
    assert re.search(message, str(err.value)), str(err.value)


def test_truncated_hierarchy_and_missing_file(tmp_path, small_text):
    cut = small_text[:small_text.index("JOINT LeftUpLeg")] + "MOTION\nFrames: 1\nFrame Time: 0.1\n0\n"
    with pytest.raises(InputFileError, match="HIERARCHY ends early"):
        read_bvh(_small(tmp_path, cut))
    with pytest.raises(InputFileError, match="cannot read"):
        read_bvh(tmp_path / "nope.bvh")
    with pytest.raises(InputFileError, match="unknown motion extension '.txt'"):
        read_motion(tmp_path / "motion.txt")


def test_writer_leaves_no_partial_file(tmp_path, foreign_path):
    m = read_bvh(foreign_path)[:5]
    with pytest.raises(InputFileError, match="cannot write"):
        write_bvh(tmp_path / "no-such-dir" / "x.bvh", m)
    with pytest.raises(ParameterError, match="expected a Motion"):
        write_bvh(tmp_path / "x.bvh", m.rotations)
    assert list(tmp_path.iterdir()) == []


# --- issue 41: BOM, bounded messages, joint and channel limits, linear parsing, writable frame rates --------

def test_a_byte_order_mark_is_accepted(tmp_path, small_text):
    """Some exporters and Windows editors start the file with a UTF-8 BOM: it is not part of HIERARCHY."""
    plain = read_bvh(_small(tmp_path, small_text, "plain.bvh"))
    p = tmp_path / "bom.bvh"
    p.write_bytes(b"\xef\xbb\xbf" + small_text.encode())
    m = read_bvh(p)
    assert m.skeleton.names == plain.skeleton.names
    np.testing.assert_array_equal(m.rotations, plain.rotations)


def _one_line(err, path, longest=300):
    msg = str(err.value)
    assert msg.startswith(f"{path}: ") and "\n" not in msg and len(msg) < longest + len(str(path)), msg[:400]
    return msg


def test_a_huge_channel_count_is_refused_at_the_count(tmp_path):
    """A joint declaring 10^7 channels (a 100 MB line) used to take 48 s and 2.2 GB to print a 100 MB
    message; the count is refused before its names are read, and the message is one short line."""
    p = tmp_path / "channels.bvh"
    p.write_text("HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 0\nCHANNELS 10000000 " + "Xrotation " * 200_000
                 + "\n}\nMOTION\nFrames: 1\nFrame Time: 0.03\n0\n")
    with pytest.raises(InputFileError, match=r"line 5: Hips CHANNELS: expected 0 to 6 channels, got 10000000$") as err:
        read_bvh(p)
    _one_line(err, p)
    p.write_text("HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 0\nCHANNELS " + "9" * 100_000 + "\n}\nMOTION\n")
    with pytest.raises(InputFileError, match=r"Hips CHANNELS: expected 0 to 6 channels, got 9{80}\.\.\. "
                                             r"\(100000 characters\)$") as err:
        read_bvh(p)
    _one_line(err, p)


@pytest.mark.parametrize("token, message", [
    # a joint name of 10^6 characters, used twice
    (lambda t, big: t.replace("JOINT Spine", "JOINT " + big, 1).replace("JOINT Head", "JOINT " + big, 1),
     r"JOINT x{80}\.\.\. \(1000000 characters\): the name is used twice$"),
    (lambda t, big: t.replace("OFFSET 0.0000 8.4730 0.0000", "OFFSET 0.0000 " + big + " 0.0000", 1),
     r"Spine OFFSET: expected a number, got 'x{80}'\.\.\. \(1000000 characters\)$"),
    (lambda t, big: t.replace("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 3 Xrotation Yrotation " + big, 1),
     r"Spine CHANNELS: expected X/Y/Z position/rotation channels, got 'x{80}'\.\.\. \(1000000 characters\)$"),
    (lambda t, big: t.replace("Frames: 10", "Frames: " + big),
     r"Frames: expected a positive integer, got 'x{80}'\.\.\. \(1000000 characters\)$"),
    (lambda t, big: "\n".join(ln if i != 152 else " ".join(ln.split()[:4] + [big] + ln.split()[5:])
                              for i, ln in enumerate(t.splitlines())),
     r"value 5 \(Hips Yrotation\): expected a number, got 'x{40}'\.\.\. \(1000000 characters\)$"),
])
def test_huge_tokens_are_echoed_short(tmp_path, small_text, token, message):
    p = _small(tmp_path, token(small_text, "x" * 1_000_000))
    with pytest.raises(InputFileError) as err:
        read_bvh(p)
    assert re.search(message, _one_line(err, p)), str(err.value)[:400]


def _wide_bvh(path, n_joints):
    """A hierarchy of ``n_joints`` joints in chains of 50 under one root (a face or hand rig writ large)."""
    out = ["HIERARCHY", "ROOT Hips", "{", "OFFSET 0 0 0",
           "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    k = 1
    while k < n_joints:
        depth = min(50, n_joints - k)
        for d in range(depth):
            out += [f"JOINT j{k + d}", "{", "OFFSET 0 1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
        out += ["End Site", "{", "OFFSET 0 1 0", "}"] + ["}"] * depth
        k += depth
    frame = " ".join(["0"] * (6 + 3 * (n_joints - 1)))
    path.write_text("\n".join(out + ["}", "MOTION", "Frames: 2", "Frame Time: 0.033333", frame, frame]) + "\n")
    return path


def test_parsing_is_linear_in_joints_and_joints_are_limited(tmp_path):
    """10k joints took 1.9-6 s and 100k past 240 s (a scan of all joints per joint); now the time grows
    with the joints, and more than MAX_BVH_JOINTS are refused at the first joint too many."""
    import time

    from gesturedb.io.bvh import MAX_BVH_JOINTS

    def best(path):
        times = []
        for _ in range(2):
            t0 = time.perf_counter()
            m = read_bvh(path)
            times.append(time.perf_counter() - t0)
        return m, min(times)

    small, t_small = best(_wide_bvh(tmp_path / "2k.bvh", 2_000))
    big, t_big = best(_wide_bvh(tmp_path / "10k.bvh", MAX_BVH_JOINTS))
    assert small.skeleton.n_joints == 2_000 and big.skeleton.n_joints == MAX_BVH_JOINTS
    # 5x the joints: about 5x the time when linear, 25x when quadratic (the old parser: 13x for 4x)
    assert t_big < 4.0 and t_big < 10 * max(t_small, 0.02), (t_small, t_big)
    p = _wide_bvh(tmp_path / "too-many.bvh", MAX_BVH_JOINTS + 1)
    with pytest.raises(InputFileError, match=rf"line \d+: JOINT: expected at most {MAX_BVH_JOINTS} joints "
                                             r"\(MAX_BVH_JOINTS\); the hierarchy has more") as err:
        read_bvh(p)
    _one_line(err, p)


@pytest.mark.parametrize("fps", [1e9, 1e-9, 1000.5, 0.5])
def test_write_refuses_frame_rates_the_reader_refuses(tmp_path, foreign_path, fps):
    m = read_bvh(foreign_path)[:4]
    bad = Motion(m.skeleton, fps, m.rotations, m.root_positions)
    with pytest.raises(ParameterError, match=rf"motion.fps: expected 1 to 1000 frames per second for BVH "
                                             rf"\(read_bvh's range\); got {re.escape(f'{fps:g}')}$"):
        write_bvh(tmp_path / "x.bvh", bad)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fps", [1.0, 1000.0, 29.97])
def test_frame_rates_at_the_limits_round_trip(tmp_path, foreign_path, fps):
    m = read_bvh(foreign_path)[:4]
    write_bvh(tmp_path / "x.bvh", Motion(m.skeleton, fps, m.rotations, m.root_positions))
    assert read_bvh(tmp_path / "x.bvh").fps == pytest.approx(fps, rel=1e-9)
