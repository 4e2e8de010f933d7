"""SMPL-X npz reader on the real BEAT2 clip, the rest skeleton, and malformed files."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gesturedb import rotations as rt
from gesturedb.errors import InputFileError
from gesturedb.io import read_motion
from gesturedb.io.smplx import SMPLX_JOINT_NAMES, SMPLX_PARENTS, read_smplx, smplx_skeleton


@pytest.fixture(scope="module")
def scott(scott_dir):
    path = scott_dir / "2_scott_0_1_1.npz"
    return path, read_smplx(path), np.load(path)


def test_reads_poses_trans_and_rate(scott):
    path, m, raw = scott
    assert m.n_frames == 1906 and m.fps == 30.0 and m.skeleton.n_joints == 55
    ref = Rotation.from_rotvec(raw["poses"].astype(np.float64).reshape(-1, 3)).as_quat()
    assert np.max(rt.angle_between(m.rotations.reshape(-1, 4), np.roll(ref, 1, -1))) < 1e-12
    np.testing.assert_allclose(m.root_positions, raw["trans"] + [0.0, -0.35, 0.0], atol=1e-12)
    assert read_motion(path).n_frames == 1906


def test_rest_skeleton_is_smplx_shaped_and_symmetric():
    sk = smplx_skeleton()
    assert sk.names == list(SMPLX_JOINT_NAMES) and sk.parents.tolist() == list(SMPLX_PARENTS)
    # standard tree: spine chain, arms, fingers off the wrists
    par = dict(zip(SMPLX_JOINT_NAMES, SMPLX_PARENTS))
    assert [SMPLX_JOINT_NAMES[par[n]] for n in ("spine1", "spine2", "spine3", "neck", "head")] == \
        ["pelvis", "spine1", "spine2", "spine3", "neck"]
    assert SMPLX_JOINT_NAMES[par["left_index1"]] == "left_wrist"
    assert SMPLX_JOINT_NAMES[par["right_thumb1"]] == "right_wrist"
    assert sk.mirrored() is sk
    rest = sk.rest_positions()
    ix = sk.index
    np.testing.assert_allclose(rest[0], [0, -0.35, 0])
    # plausible adult proportions, metres
    bone = lambda a, b: np.linalg.norm(rest[ix(a)] - rest[ix(b)])  # noqa: E731
    assert 0.24 < bone("left_shoulder", "left_elbow") < 0.32
    assert 0.22 < bone("left_elbow", "left_wrist") < 0.30
    assert 0.36 < bone("left_hip", "left_knee") < 0.46
    assert 0.34 < bone("left_knee", "left_ankle") < 0.45
    stature = rest[ix("head"), 1] + sk.end_sites[ix("head")][1] - rest[ix("left_foot"), 1] + 0.05
    assert 1.6 < stature < 1.85
    # T-pose: left arm along +x, fingers beyond the wrist, facing +z (toes forward)
    assert rest[ix("left_wrist"), 0] > rest[ix("left_elbow"), 0] > rest[ix("left_shoulder"), 0] > 0.1
    assert rest[ix("left_index1"), 0] > rest[ix("left_wrist"), 0] + 0.05
    assert rest[ix("left_foot"), 2] > rest[ix("left_ankle"), 2]
    assert set(sk.channel_orders) == {"ZXY"}


def test_pelvis_and_feet_heights(scott):
    _, m, _ = scott
    pos = m.positions
    ix = m.skeleton.index
    assert 0.85 < np.median(pos[:, ix("pelvis"), 1]) < 1.05
    feet = pos[:, [ix("left_foot"), ix("right_foot")], 1]
    assert -0.05 < np.percentile(feet, 5) and np.percentile(feet, 50) < 0.15  # standing on the floor


def test_wrists_move_like_a_speaker(scott):
    """Most of the clip: wrists between hip and chest height, in front of the body, at 0.3-1 m/s."""
    _, m, _ = scott
    pos = m.positions
    ix = m.skeleton.index
    # facing direction from hips and shoulders (never assumed): forward = left x up
    left = (pos[:, ix("left_hip")] - pos[:, ix("right_hip")]) + \
        (pos[:, ix("left_shoulder")] - pos[:, ix("right_shoulder")])
    left[:, 1] = 0.0
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    forward = np.cross(left, [0.0, 1.0, 0.0])
    hip_y = pos[:, [ix("left_hip"), ix("right_hip")], 1].mean(axis=1)
    chest_y = pos[:, ix("spine3"), 1]
    for side in ("left", "right"):
        w = pos[:, ix(f"{side}_wrist")]
        between = (w[:, 1] > hip_y) & (w[:, 1] < chest_y)
        front = np.sum((w - pos[:, ix("pelvis")]) * forward, axis=1) > 0.0
        speed = np.linalg.norm(np.diff(w, axis=0), axis=1) * m.fps
        assert between.mean() > 0.6, (side, between.mean())
        assert front.mean() > 0.75, (side, front.mean())
        assert 0.3 < speed.mean() < 1.0, (side, speed.mean())


def _write(tmp_path, name="bad.npz", **arrays):
    p = tmp_path / name
    np.savez(p, **arrays)
    return p


@pytest.fixture
def good_arrays():
    rng = np.random.default_rng(0)
    return {"poses": rng.normal(scale=0.2, size=(12, 165)).astype(np.float32),
            "trans": np.tile([0.0, 1.29, 0.0], (12, 1)), "mocap_frame_rate": np.array(30)}


def test_small_file_and_amass_rate_key(tmp_path, good_arrays):
    m = read_smplx(_write(tmp_path, "ok.npz", **good_arrays))
    assert m.n_frames == 12
    arrays = dict(good_arrays)
    arrays["mocap_framerate"] = arrays.pop("mocap_frame_rate") * 2.0
    assert read_smplx(_write(tmp_path, "amass.npz", **arrays)).fps == 60.0


@pytest.mark.parametrize("change, message", [
    (lambda a: a.pop("poses"),
     r"poses: missing \(expected \(F, 165\) axis-angle\); the file has keys mocap_frame_rate, trans"),
    (lambda a: a.pop("trans"), r"trans: missing"),
    (lambda a: a.pop("mocap_frame_rate"), r"mocap_frame_rate: missing"),
    (lambda a: a.update(poses=a["poses"][:, :156]), r"poses: expected shape \(F, 165\).*got float32 \(12, 156\)"),
    (lambda a: a.update(trans=a["trans"][:10]),
     r"trans: expected shape \(12, 3\) to match poses, got float64 \(10, 3\)"),
    (lambda a: a["poses"].__setitem__((7, 61), np.nan), r"poses: frame 7, joint 20 \(left_wrist\) is not finite"),
    (lambda a: a["trans"].__setitem__((3, 1), np.inf), r"trans: frame 3 is not finite"),
    (lambda a: a.update(mocap_frame_rate=np.array(0.0)), r"mocap_frame_rate: expected one positive frame rate"),
])
def test_malformed_files_name_the_key(tmp_path, good_arrays, change, message):
    change(good_arrays)
    p = _write(tmp_path, **good_arrays)
    with pytest.raises(InputFileError, match=message) as err:
        read_smplx(p)
    assert str(err.value).startswith(str(p))


def test_unreadable_files(tmp_path):
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip archive at all")
    with pytest.raises(InputFileError, match="cannot read as .npz"):
        read_smplx(garbage)
    npy = tmp_path / "array.npz"
    with open(npy, "wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(InputFileError, match="got a single .npy array"):
        read_smplx(npy)
    with pytest.raises(InputFileError, match="cannot read as .npz"):
        read_smplx(tmp_path / "missing.npz")
