"""Skeleton / Motion: FK against an independent scipy implementation, resampling, mirroring, slicing."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gesturedb import rotations as rt
from gesturedb.errors import ParameterError
from gesturedb.io.bvh import read_bvh
from gesturedb.io.smplx import read_smplx
from gesturedb.motion import Motion, Skeleton, mirror_permutation, resampled_length

RNG = np.random.default_rng(99)


def _fk_scipy(skel, rotations, root):
    """Forward kinematics with scipy Rotation objects, written independently of Motion."""
    n_f, n_j = rotations.shape[:2]
    world = [None] * n_j
    pos = np.zeros((n_f, n_j, 3))
    for j in range(n_j):
        r = Rotation.from_quat(np.roll(rotations[:, j], -1, axis=-1))
        p = skel.parents[j]
        if p < 0:
            world[j], pos[:, j] = r, root
        else:
            world[j] = world[p] * r
            pos[:, j] = pos[:, p] + world[p].apply(skel.offsets[j])
    return pos


def _random_skeleton(n_j=12):
    parents = np.array([-1] + [int(RNG.integers(0, j)) for j in range(1, n_j)])
    return Skeleton([f"j{j}" for j in range(n_j)], parents, RNG.normal(scale=0.2, size=(n_j, 3)),
                    ["ZXY"] * n_j)


def _random_motion(skel, n_f=40, fps=30.0):
    q = np.roll(Rotation.random(n_f * skel.n_joints, random_state=int(RNG.integers(1 << 31))).as_quat(), 1, -1)
    return Motion(skel, fps, q.reshape(n_f, skel.n_joints, 4), RNG.normal(size=(n_f, 3)))


def _symmetric_skeleton():
    names = ["Hips", "Spine", "Head", "LeftShoulder", "LeftArm", "LeftHand", "RightShoulder", "RightArm",
             "RightHand", "LeftUpLeg", "LeftFoot", "RightUpLeg", "RightFoot"]
    par = {"Hips": None, "Spine": "Hips", "Head": "Spine", "LeftShoulder": "Spine", "LeftArm": "LeftShoulder",
           "LeftHand": "LeftArm", "RightShoulder": "Spine", "RightArm": "RightShoulder", "RightHand": "RightArm",
           "LeftUpLeg": "Hips", "LeftFoot": "LeftUpLeg", "RightUpLeg": "Hips", "RightFoot": "RightUpLeg"}
    left = {"LeftShoulder": (0.05, 0.3, -0.02), "LeftArm": (0.12, 0.01, 0.0), "LeftHand": (0.5, 0.0, 0.03),
            "LeftUpLeg": (0.09, -0.05, 0.0), "LeftFoot": (0.01, -0.8, 0.05)}
    mid = {"Hips": (0.0, 0.95, 0.0), "Spine": (0.0, 0.2, 0.01), "Head": (0.0, 0.35, 0.02)}
    offsets = []
    for n in names:
        if n in mid:
            offsets.append(mid[n])
        elif n in left:
            offsets.append(left[n])
        else:
            x, y, z = left[n.replace("Right", "Left")]
            offsets.append((-x, y, z))
    parents = [-1 if par[n] is None else names.index(par[n]) for n in names]
    ends = {2: np.array([0, 0.1, 0]), 5: np.array([0.08, 0, 0]), 8: np.array([-0.08, 0, 0])}
    return Skeleton(names, np.array(parents), np.array(offsets), ["ZXY"] * len(names), ends)


# --- forward kinematics ------------------------------------------------------------------

def test_fk_matches_independent_scipy_fk_on_random_trees():
    skel = _random_skeleton(15)
    m = _random_motion(skel)
    np.testing.assert_allclose(m.positions, _fk_scipy(skel, m.rotations, m.root_positions), atol=1e-12)
    pos, grot = m.forward_kinematics()
    np.testing.assert_array_equal(pos, m.positions)
    # world rotation of a child = world rotation of its parent times its local rotation
    j = 5
    p = skel.parents[j]
    assert np.max(rt.angle_between(grot[:, j], rt.multiply(grot[:, p], m.rotations[:, j]))) < 1e-12


@pytest.mark.parametrize("n_f", [1, 3, 8, 17])
def test_fk_of_any_split_of_the_frames_is_the_same_bits(n_f):
    """The C++ chain (csrc/fk.cpp) takes every frame on its own: a stream's 8-frame pieces get the bits
    of one pass over the whole clip, and the scipy oracle's values."""
    skel = _random_skeleton(9)
    m = _random_motion(skel, n_f=n_f)
    pos, grot = m.forward_kinematics()
    assert pos.shape == (n_f, 9, 3) and grot.shape == (n_f, 9, 4)
    np.testing.assert_allclose(pos, _fk_scipy(skel, m.rotations, m.root_positions), atol=1e-12)
    for cut in sorted({0, n_f // 3, n_f}):
        parts = [m.rotations[:cut], m.rotations[cut:]]
        roots = [m.root_positions[:cut], m.root_positions[cut:]]
        got = [Motion(skel, m.fps, q, r).forward_kinematics() for q, r in zip(parts, roots) if q.shape[0]]
        if got:
            assert np.array_equal(np.concatenate([g[0] for g in got]), pos)
            assert np.array_equal(np.concatenate([g[1] for g in got]), grot)


def test_fk_core_refuses_bad_shapes_and_parents_after_children():
    from gesturedb import _core

    mats, root = np.tile(np.eye(3), (2, 3, 1, 1)), np.zeros((2, 3))
    offsets = np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"parents\[2\]: expected 0 <= parent < 2 \(parents first\); got 2"):
        _core.forward_kinematics(mats, root, np.array([-1, 0, 2]), offsets, False)
    with pytest.raises(ValueError, match=r"root: expected \(2, 3\); got \(1, 3\)"):
        _core.forward_kinematics(mats, root[:1], np.array([-1, 0, 1]), offsets, False)
    pos, worlds = _core.forward_kinematics(mats, root, np.array([-1, 0, 1]), offsets, False)
    assert worlds is None and pos.shape == (2, 3, 3)


def _fk_numpy_conversions(m):
    """Motion.forward_kinematics as it was before the quaternions went to C++: numpy's to_matrix, the
    matrix chain (_core.forward_kinematics) and numpy's from_matrix."""
    from gesturedb import _core

    sk = m.skeleton
    pos, worlds = _core.forward_kinematics(np.ascontiguousarray(rt.to_matrix(m.rotations)), m.root_positions,
                                           np.ascontiguousarray(sk.parents, dtype=np.int64),
                                           np.ascontiguousarray(sk.offsets, dtype=np.float64), True)
    return pos, rt.from_matrix(worlds)


def test_fk_from_quaternions_is_numpys_conversions_to_the_bit(scott_dir):
    """csrc/fk.cpp converts quaternions to matrices and back operation for operation as
    rotations.to_matrix and from_matrix do: the same bits, on random trees (every branch of
    Shepperd's method) and on real motion, and quaternions slightly off unit."""
    skel = _random_skeleton(15)
    m = _random_motion(skel, n_f=300)
    off = Motion(skel, m.fps, m.rotations * (1 + 1e-13 * RNG.normal(size=m.rotations.shape[:-1] + (1,))),
                 m.root_positions)
    real = read_smplx(scott_dir / "2_scott_0_1_1.npz")[:400]
    for mo in (m, off, real):
        pos, grot = mo.forward_kinematics()
        want_pos, want_grot = _fk_numpy_conversions(mo)
        assert np.array_equal(pos, want_pos) and np.array_equal(grot, want_grot)
        assert np.array_equal(mo.positions, want_pos)
    # every branch of from_matrix was taken (the largest of the trace and the diagonal)
    w = rt.to_matrix(m.forward_kinematics()[1]).reshape(-1, 9)
    assert set(np.argmax(np.stack([w[:, 0] + w[:, 4] + w[:, 8], w[:, 0], w[:, 4], w[:, 8]], -1), -1)) == {0, 1, 2, 3}


def test_fk_quat_core_refuses_bad_shapes():
    from gesturedb import _core

    q, root, offsets = np.tile([1.0, 0, 0, 0], (2, 3, 1)), np.zeros((2, 3)), np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"quats: expected \(F, J >= 1, 4\); got \(2, 3, 3\)"):
        _core.forward_kinematics_quat(np.zeros((2, 3, 3)), root, np.array([-1, 0, 1]), offsets, False)
    with pytest.raises(ValueError, match=r"parents\[2\]: expected 0 <= parent < 2 \(parents first\); got 2"):
        _core.forward_kinematics_quat(q, root, np.array([-1, 0, 2]), offsets, False)
    pos, grot = _core.forward_kinematics_quat(q, root, np.array([-1, 0, 1]), offsets, False)
    assert grot is None and pos.shape == (2, 3, 3)


def test_fk_on_real_smplx_motion_matches_scipy(scott_dir):
    m = read_smplx(scott_dir / "2_scott_0_1_1.npz")[:1100]
    np.testing.assert_allclose(m.positions, _fk_scipy(m.skeleton, m.rotations, m.root_positions), atol=1e-12)
    pos, grot = m.forward_kinematics()
    ref = Rotation.from_quat(np.roll(m.rotations[:, 0], -1, -1))
    for j in (3, 6, 9, 12):  # spine chain: world rotation is the product of the locals
        ref = ref * Rotation.from_quat(np.roll(m.rotations[:, j], -1, -1))
    assert np.max(rt.angle_between(grot[:, 12], np.roll(ref.as_quat(), 1, -1))) < 1e-10


def test_rest_pose_gives_rest_positions_and_end_sites():
    skel = _symmetric_skeleton()
    m = Motion(skel, 30, rt.identity((3, skel.n_joints)), np.repeat(skel.offsets[:1], 3, axis=0))
    np.testing.assert_allclose(m.positions[1], skel.rest_positions(), atol=1e-15)
    ends = m.end_site_positions()
    np.testing.assert_allclose(ends[5][0], skel.rest_positions()[5] + [0.08, 0, 0], atol=1e-15)
    # turn the whole body 90 degrees about y: the left hand (+x) swings to -z
    q = np.repeat(rt.identity((1, skel.n_joints)), 1, axis=0)
    q[0, 0] = rt.from_axis_angle([0.0, np.pi / 2, 0.0])
    turned = Motion(skel, 30, q, skel.offsets[:1])
    hand = turned.positions[0, 5] - turned.positions[0, 0]
    rest_hand = skel.rest_positions()[5] - skel.offsets[0]
    np.testing.assert_allclose(hand, [rest_hand[2], rest_hand[1], -rest_hand[0]], atol=1e-12)


# --- validation --------------------------------------------------------------------------

def test_skeleton_validation_messages():
    with pytest.raises(ParameterError, match="repeated: a"):
        Skeleton(["a", "a"], np.array([-1, 0]), np.zeros((2, 3)), ["XYZ", "XYZ"])
    with pytest.raises(ParameterError, match=r"joint 1 \(b\) has parent 2"):
        Skeleton(["a", "b", "c"], np.array([-1, 2, 0]), np.zeros((3, 3)), ["XYZ"] * 3)
    with pytest.raises(ParameterError, match=r"offsets: expected shape \(2, 3\)"):
        Skeleton(["a", "b"], np.array([-1, 0]), np.zeros((3, 3)), ["XYZ"] * 2)
    with pytest.raises(ParameterError, match="Euler order"):
        Skeleton(["a", "b"], np.array([-1, 0]), np.zeros((2, 3)), ["XYZ", "XXY"])
    with pytest.raises(ParameterError, match="joint b has a non-finite offset"):
        Skeleton(["a", "b"], np.array([-1, 0]), np.array([[0, 0, 0], [0, np.nan, 0]]), ["XYZ"] * 2)


def test_motion_validation_names_joint_and_frame():
    skel = _symmetric_skeleton()
    q = rt.identity((5, skel.n_joints))
    q[3, 4, 2] = np.nan
    with pytest.raises(ParameterError, match="joint LeftArm at frame 3 is not finite"):
        Motion(skel, 30, q, np.zeros((5, 3)))
    root = np.zeros((5, 3))
    root[2, 1] = np.inf
    with pytest.raises(ParameterError, match="root_positions: joint Hips at frame 2 is not finite"):
        Motion(skel, 30, rt.identity((5, skel.n_joints)), root)
    q = rt.identity((5, skel.n_joints))
    q[1, 7] *= 1.5
    with pytest.raises(ParameterError, match="joint RightArm at frame 1 is not a unit quaternion"):
        Motion(skel, 30, q, np.zeros((5, 3)))
    with pytest.raises(ParameterError, match=r"rotations: expected shape \(F >= 1, 13, 4\); got \(5, 12, 4\)"):
        Motion(skel, 30, rt.identity((5, 12)), np.zeros((5, 3)))
    with pytest.raises(ParameterError, match="fps: expected a positive frame rate"):
        Motion(skel, 0, rt.identity((5, skel.n_joints)), np.zeros((5, 3)))


# --- slicing -----------------------------------------------------------------------------

def test_slicing_selects_frames():
    m = _random_motion(_random_skeleton(), n_f=50)
    s = m[10:30]
    assert s.n_frames == 20 and s.fps == m.fps
    np.testing.assert_allclose(s.positions, m.positions[10:30], atol=1e-14)
    half = m[::2]
    assert half.fps == m.fps / 2 and half.n_frames == 25
    np.testing.assert_allclose(half.positions, m.positions[::2], atol=1e-14)
    assert m[-5:].n_frames == 5
    with pytest.raises(ParameterError, match="empty slice"):
        m[30:10]
    with pytest.raises(ParameterError, match="expected a slice"):
        m[3]


# --- resampling --------------------------------------------------------------------------

def test_resampled_length_rule():
    assert resampled_length(1906, 30, 15) == 953  # 63.5 s at 15 fps
    assert resampled_length(1906, 30, 20) == 1271
    assert resampled_length(1906, 30, 30) == 1906
    assert resampled_length(10, 30, 60) == 19
    assert resampled_length(1, 30, 15) == 1
    for _ in range(500):
        n = int(RNG.integers(1, 5000))
        src, dst = float(RNG.choice([24, 25, 30, 50, 60, 120, 29.97])), float(RNG.choice([10, 15, 20, 30, 60]))
        k = resampled_length(n, src, dst)
        span = (n - 1) / src
        # the last output frame is inside the source span and one more would not be
        assert (k - 1) / dst <= span + 1e-9 < k / dst


def test_resample_interpolates_rotations_and_root():
    skel = _random_skeleton(4)
    n_f, fps = 61, 30.0
    t = np.arange(n_f) / fps
    axis = np.array([0.3, 0.5, -0.8]) / np.linalg.norm([0.3, 0.5, -0.8])
    speed = 2.0  # rad/s: 0.067 rad per frame, slerp is then exact for a fixed axis
    q = rt.from_axis_angle((speed * t)[:, None, None] * axis * np.ones((1, 4, 1)))
    root = np.stack([t, 2 * t, -t], axis=1)
    m = Motion(skel, fps, q, root)
    r = m.resample(24.0)
    assert r.fps == 24.0 and r.n_frames == resampled_length(n_f, fps, 24.0) == 49
    tr = np.arange(r.n_frames) / 24.0
    want = rt.from_axis_angle((speed * tr)[:, None, None] * axis * np.ones((1, 4, 1)))
    assert np.max(rt.angle_between(r.rotations, want)) < 1e-9
    np.testing.assert_allclose(r.root_positions, np.stack([tr, 2 * tr, -tr], axis=1), atol=1e-12)


def test_resample_keeps_frames_at_shared_times():
    m = _random_motion(_random_skeleton(6), n_f=31)
    down = m.resample(15.0)
    assert down.n_frames == 16
    assert np.max(rt.angle_between(down.rotations, m.rotations[::2])) < 1e-12
    np.testing.assert_allclose(down.root_positions, m.root_positions[::2], atol=1e-12)
    up = m.resample(60.0)
    assert up.n_frames == 61
    assert np.max(rt.angle_between(up.rotations[::2], m.rotations)) < 1e-7
    np.testing.assert_allclose(up.root_positions[::2], m.root_positions, atol=1e-12)
    with pytest.raises(ParameterError, match="fps: expected a positive frame rate"):
        m.resample(-1)


def test_resample_real_clip_to_15fps(scott_dir):
    m = read_smplx(scott_dir / "2_scott_0_1_1.npz")
    r = m.resample(15)
    assert r.n_frames == 953
    np.testing.assert_allclose(r.positions, m.positions[::2], atol=1e-9)


# --- mirroring ---------------------------------------------------------------------------

@pytest.mark.parametrize("names, pairs", [
    (["Hips", "LeftHand", "RightHand", "Spine"], {1: 2}),
    (["pelvis", "left_wrist", "right_wrist", "left_index1", "right_index1"], {1: 2, 3: 4}),
    (["b_root", "b_l_wrist", "b_r_wrist", "b_spine0"], {1: 2}),
    (["mixamorig:Hips", "mixamorig:LeftHand", "mixamorig:RightHand"], {1: 2}),
    (["Root", "L_Hand", "R_Hand", "Hand.L", "Hand.R", "LHipJoint", "RHipJoint"], {1: 2, 3: 4, 5: 6}),
    (["ROOT", "Bright", "Bleft", "LeftOnly"], {}),
])
def test_mirror_permutation_pairs_names(names, pairs):
    perm = mirror_permutation(names)
    want = np.arange(len(names))
    for a, b in pairs.items():
        want[a], want[b] = b, a
    np.testing.assert_array_equal(perm, want)
    np.testing.assert_array_equal(perm[perm], np.arange(len(names)))


def _reflected(pos, perm):
    return pos[:, perm] * np.array([-1.0, 1.0, 1.0])


def test_mirror_reflects_positions_exactly_and_is_an_involution():
    skel = _symmetric_skeleton()
    m = _random_motion(skel, n_f=20)
    mm = m.mirror()
    assert mm.skeleton is skel  # symmetric skeleton: unchanged
    perm = skel.mirror_permutation()
    np.testing.assert_allclose(mm.positions, _reflected(m.positions, perm), atol=1e-12)
    back = mm.mirror()
    np.testing.assert_array_equal(back.rotations, m.rotations)
    np.testing.assert_array_equal(back.root_positions, m.root_positions)
    ends, mends = m.end_site_positions(), mm.end_site_positions()
    np.testing.assert_allclose(mends[8], ends[5] * [-1, 1, 1], atol=1e-12)


def test_mirror_of_an_asymmetric_skeleton_mirrors_the_skeleton():
    skel = _symmetric_skeleton()
    offsets = skel.offsets.copy()
    offsets[5] *= 1.2  # a longer left forearm
    lop = Skeleton(skel.names, skel.parents, offsets, skel.channel_orders, skel.end_sites)
    m = _random_motion(lop, n_f=10)
    mm = m.mirror()
    assert mm.skeleton is not lop
    np.testing.assert_allclose(mm.skeleton.offsets[8], offsets[5] * [-1, 1, 1])
    np.testing.assert_allclose(mm.positions, _reflected(m.positions, lop.mirror_permutation()), atol=1e-12)
    assert mm.mirror().skeleton.same_as(lop)
    np.testing.assert_allclose(mm.mirror().positions, m.positions, atol=1e-12)


def test_mirror_real_smplx_and_foreign_bvh(scott_dir, data_dir):
    for m in (read_smplx(scott_dir / "2_scott_0_1_1.npz")[:300],
              read_bvh(data_dir / "bvh-foreign" / "AV_8Walk_Meredith_HVHA_Rep1.bvh")[:300]):
        mm = m.mirror()
        assert mm.skeleton is m.skeleton  # both skeletons are left/right symmetric
        perm = m.skeleton.mirror_permutation()
        assert (perm != np.arange(m.skeleton.n_joints)).sum() >= 8
        np.testing.assert_allclose(mm.positions, _reflected(m.positions, perm), atol=1e-9)
        np.testing.assert_allclose(mm.mirror().rotations, m.rotations, atol=0)


def test_mirror_refuses_an_inconsistent_hierarchy():
    # LeftHand hangs off Spine, RightHand off RightArm: swapping names breaks the tree
    names = ["Hips", "Spine", "RightArm", "LeftArm", "LeftHand", "RightHand"]
    skel = Skeleton(names, np.array([-1, 0, 1, 1, 1, 2]), np.zeros((6, 3)), ["XYZ"] * 6)
    with pytest.raises(ParameterError, match="cannot be mirrored"):
        Motion(skel, 30, rt.identity((2, 6)), np.zeros((2, 3))).mirror()
