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
    (lambda a: a.update(mocap_frame_rate=np.array(0.0)), r"mocap_frame_rate: expected one frame rate of 1 to 1000 Hz"),
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
    with pytest.raises(InputFileError, match=r"expected an .npz archive \(a zip of .npy arrays, starting with 'PK'\); "
                                             r"got a file starting with b'not a zi': not a zip archive$"):
        read_smplx(garbage)
    npy = tmp_path / "array.npz"
    with open(npy, "wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(InputFileError, match="got a single .npy array"):
        read_smplx(npy)
    with pytest.raises(InputFileError, match="cannot read as .npz"):
        read_smplx(tmp_path / "missing.npz")


# --- issue 41: what a non-npz file is, deflate bombs, frame rates BVH can carry ------------------------------

def _bomb(path, frames, *, trans_frames=None):
    """A deflated .npz whose poses are `frames` x 165 float32 zeros: about 1000x smaller than it inflates."""
    import io
    import zipfile

    import numpy.lib.format as fmt

    hdr = io.BytesIO()
    fmt.write_array_header_1_0(hdr, {"descr": "<f4", "fortran_order": False, "shape": (frames, 165)})
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        with z.open("poses.npy", "w", force_zip64=True) as f:
            f.write(hdr.getvalue())
            left, zero = frames * 165 * 4, bytes(1 << 22)
            while left > 0:
                f.write(zero[:min(left, len(zero))])
                left -= len(zero)
        for name, arr in (("trans", np.zeros((trans_frames or frames, 3))), ("mocap_frame_rate", np.array(30.0))):
            b = io.BytesIO()
            np.save(b, arr)
            z.writestr(name + ".npy", b.getvalue())
    return path


def test_a_deflate_bomb_is_refused_before_it_inflates(tmp_path):
    """A real bomb (3.9 MB inflating to 4 GB) reached 3.85 GB RSS (23 GB on the way to rotations); the
    inflated size is now bounded by the bytes the entry really stores, before anything is allocated.
    This one: 160k frames (106 MB of zeros) in about 0.1 MB."""
    import tracemalloc

    p = _bomb(tmp_path / "bomb.npz", 160_000)
    assert p.stat().st_size < 1_000_000
    tracemalloc.start()
    try:
        with pytest.raises(InputFileError, match=r"bomb.npz: poses: header declares float32 \(160000, 165\) "
                                                 r"\(105600000 bytes\), but the archive entry may hold at most "
                                                 r"67108864 bytes \(stored \d+, MAX_NPZ_INFLATE_RATIO = 64\); "
                                                 r"a damaged file or a deflate bomb$"):
            read_smplx(p)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8e6, peak


def test_compressed_files_within_the_bounds_read(tmp_path, good_arrays):
    p = tmp_path / "compressed.npz"
    big = {"poses": np.random.default_rng(1).normal(scale=0.3, size=(6000, 165)),  # 7.9 MB, ~1.1x compressible
           "trans": np.zeros((6000, 3)), "mocap_frame_rate": np.array(30.0)}
    np.savez_compressed(p, **big)
    np.testing.assert_array_equal(read_smplx(p).rotations, read_smplx(_write(tmp_path, "stored.npz", **big)).rotations)
    # highly compressible but small (a rest pose): under MAX_NPZ_FREE_BYTES whatever the ratio
    assert read_smplx(_bomb(tmp_path / "rest.npz", 20_000)).n_frames == 20_000
    # Fortran-ordered arrays come back in their logical layout
    arrays = dict(good_arrays, poses=np.asfortranarray(good_arrays["poses"]))
    back = read_smplx(_write(tmp_path, "fortran.npz", **arrays))
    np.testing.assert_array_equal(back.rotations, read_smplx(_write(tmp_path, "c.npz", **good_arrays)).rotations)


@pytest.mark.parametrize("data, message", [
    (bytes(range(256)) * 40, r"expected an \.npz archive \(a zip of \.npy arrays, starting with 'PK'\); got a file "
                             r"starting with b'\\x00\\x01\\x02\\x03\\x04\\x05\\x06\\x07': not a zip archive$"),
    (b"", r"expected an \.npz archive \(a zip of \.npy arrays\); got an empty file$"),
    (b"PK\x03\x04" + bytes(200), r"cannot read as \.npz: "),
])
def test_a_file_that_is_no_npz_is_called_what_it_is(tmp_path, data, message):
    """Random bytes used to be reported as 'Cannot load file containing pickled data'."""
    p = tmp_path / "random.npz"
    p.write_bytes(data)
    with pytest.raises(InputFileError, match=message) as err:
        read_smplx(p)
    assert str(err.value).startswith(f"{p}: ") and "pickled" not in str(err.value) and "\n" not in str(err.value)


def test_object_arrays_are_never_unpickled(tmp_path, good_arrays):
    p = tmp_path / "objects.npz"
    np.savez(p, poses=np.array([{"a": 1}] * 165, dtype=object).reshape(1, 165), trans=np.zeros((1, 3)),
             mocap_frame_rate=np.array(30))
    with pytest.raises(InputFileError, match=r"poses: expected numbers; got an array of Python objects"):
        read_smplx(p)


@pytest.mark.parametrize("fps", [1e9, 1e-9, 1000.5])
def test_frame_rates_bvh_cannot_carry_are_refused(tmp_path, good_arrays, fps):
    """Motion read at 1e9 fps was retargeted and written to a BVH read_bvh refuses."""
    p = _write(tmp_path, **dict(good_arrays, mocap_frame_rate=np.array(fps)))
    with pytest.raises(InputFileError, match=r"mocap_frame_rate: expected one frame rate of 1 to 1000 Hz, got "):
        read_smplx(p)
