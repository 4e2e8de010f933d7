"""SMPL-X motion in BEAT2 / AMASS npz files, on the project's own rest skeleton.

A file holds ``poses (F, 165)``: 55 joints x axis-angle (radians), the local
rotation of each joint in SMPL-X joint order (joint 0, the pelvis, is the
global orientation); ``trans (F, 3)``: the SMPL-X translation in metres; and
``mocap_frame_rate`` (AMASS spells it ``mocap_framerate``).

The approximation
    The official SMPL-X body model, whose rest joint positions come from a
    licence-restricted template mesh and shape blend shapes (``betas``), is
    not available. `smplx_skeleton` is instead a fixed, left/right symmetric
    skeleton with the SMPL-X topology and joint order and plausible adult
    bone lengths (stature about 1.7 m), laid out like the SMPL-X T-pose:
    y up, facing +z, +x the speaker's left, arms along +-x, palms down,
    fingers straight, pelvis at ``(0, -0.35, 0)`` so that the usual
    ``trans[:, 1]`` of about 1.29 m puts the pelvis about 0.94 m above the
    floor. ``betas`` and ``expressions`` are ignored and the hand pose is
    applied to the flat hand. Joint positions therefore differ from the true
    SMPL-X ones by centimetres; the features built on them are relative
    (velocities, positions in a body frame), so this matters little.

Export
    Every joint gets Euler channel order ``"ZXY"`` (`CHANNEL_ORDER`), whose
    middle axis (x) is the twist axis of the arms in the T-pose, which moves
    little, so BVH exports stay far from gimbal lock.
"""
from __future__ import annotations

import lzma
import math
import tokenize
import zipfile
import zlib

import numpy as np

from gesturedb import rotations as rot
from gesturedb.errors import InputFileError
from gesturedb.motion import Motion, Skeleton

__all__ = ["CHANNEL_ORDER", "SMPLX_JOINT_NAMES", "SMPLX_PARENTS", "read_smplx", "smplx_skeleton"]

CHANNEL_ORDER = "ZXY"

SMPLX_JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw", "left_eye", "right_eye",
    "left_index1", "left_index2", "left_index3", "left_middle1", "left_middle2", "left_middle3",
    "left_pinky1", "left_pinky2", "left_pinky3", "left_ring1", "left_ring2", "left_ring3",
    "left_thumb1", "left_thumb2", "left_thumb3",
    "right_index1", "right_index2", "right_index3", "right_middle1", "right_middle2", "right_middle3",
    "right_pinky1", "right_pinky2", "right_pinky3", "right_ring1", "right_ring2", "right_ring3",
    "right_thumb1", "right_thumb2", "right_thumb3",
)

SMPLX_PARENTS = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
)

# Offsets from the SMPL-X parent (SMPLX_PARENTS) in metres for the midline and the LEFT side (+x); the right
# side is the x-reflection, which keeps the skeleton exactly symmetric so mirroring a
# motion leaves the skeleton unchanged. Proportions follow an adult of about 1.7 m.
_MIDLINE = {
    "pelvis": (0.0, -0.35, 0.0),
    "spine1": (0.0, 0.11, -0.02),
    "spine2": (0.0, 0.135, 0.0),
    "spine3": (0.0, 0.055, 0.025),
    "neck": (0.0, 0.215, -0.035),
    "head": (0.0, 0.07, 0.045),
    "jaw": (0.0, -0.02, 0.04),
}
_LEFT = {
    "hip": (0.07, -0.09, -0.005),
    "knee": (0.035, -0.375, -0.005),
    "ankle": (-0.01, -0.40, -0.04),
    "foot": (0.025, -0.055, 0.115),
    "collar": (0.075, 0.12, -0.03),
    "shoulder": (0.095, 0.025, -0.01),
    "elbow": (0.26, -0.01, -0.02),
    "wrist": (0.255, 0.01, 0.0),
    "eye": (0.032, 0.055, 0.085),
    # fingers straight along +x, palm down; metacarpo-phalangeal joints spread over the palm
    "index1": (0.090, -0.005, 0.025),
    "index2": (0.037, 0.0, 0.0),
    "index3": (0.023, 0.0, 0.0),
    "middle1": (0.095, -0.003, 0.004),
    "middle2": (0.040, 0.0, 0.0),
    "middle3": (0.026, 0.0, 0.0),
    "pinky1": (0.080, -0.010, -0.035),
    "pinky2": (0.027, 0.0, 0.0),
    "pinky3": (0.018, 0.0, 0.0),
    "ring1": (0.089, -0.007, -0.016),
    "ring2": (0.036, 0.0, 0.0),
    "ring3": (0.024, 0.0, 0.0),
    "thumb1": (0.025, -0.015, 0.030),
    "thumb2": (0.030, -0.004, 0.020),
    "thumb3": (0.026, -0.002, 0.012),
}
# End Sites: the top of the head, the chin, the front of the eyes, the toe tips, the fingertips
_END_SITES = {
    "head": (0.0, 0.13, 0.0),
    "jaw": (0.0, -0.03, 0.06),
    "left_eye": (0.0, 0.0, 0.02),
    "left_foot": (0.0, -0.03, 0.06),
    "left_index3": (0.022, 0.0, 0.0),
    "left_middle3": (0.024, 0.0, 0.0),
    "left_pinky3": (0.019, 0.0, 0.0),
    "left_ring3": (0.023, 0.0, 0.0),
    "left_thumb3": (0.022, -0.001, 0.006),
}

_N_JOINTS = len(SMPLX_JOINT_NAMES)
_FPS_KEYS = ("mocap_frame_rate", "mocap_framerate", "fps")


def _offset(name: str) -> tuple:
    if name in _MIDLINE:
        return _MIDLINE[name]
    side, part = name.split("_", 1)
    off = _LEFT[part]
    return off if side == "left" else (-off[0], off[1], off[2])


def smplx_skeleton() -> Skeleton:
    """The project's SMPL-X-topology rest skeleton (see the module notes).

    Returns
    -------
    Skeleton
        55 joints in SMPL-X order, offsets in metres (T-pose, y up, facing
        +z, +x the speaker's left), channel order `CHANNEL_ORDER` for every
        joint, End Sites on the head, jaw, eyes, feet and fingertips.
    """
    offsets = np.array([_offset(n) for n in SMPLX_JOINT_NAMES], dtype=np.float64)
    ends = {}
    for name, (x, y, z) in _END_SITES.items():
        ends[SMPLX_JOINT_NAMES.index(name)] = np.array([x, y, z])
        if name.startswith("left_"):
            ends[SMPLX_JOINT_NAMES.index("right_" + name[5:])] = np.array([-x, y, z])
    return Skeleton(list(SMPLX_JOINT_NAMES), np.array(SMPLX_PARENTS, dtype=np.int64), offsets,
                    [CHANNEL_ORDER] * _N_JOINTS, ends, 1.0)


def _check_declared_size(path, data, key) -> None:
    """Refuse an array whose header declares more bytes than its archive entry can hold, before allocating.

    numpy allocates the declared shape first and reads after; a 1 KB file can declare
    a (10**12, 165) array. Deflate expands at most ~1032:1, so the declared size must
    fit the entry's uncompressed size and its compressed size times 1100.
    """
    import numpy.lib.format as fmt

    name = key + ".npy"
    if getattr(data, "zip", None) is None or name not in data.zip.namelist():
        return
    info = data.zip.getinfo(name)
    with data.zip.open(name) as f:
        version = fmt.read_magic(f)
        reader = {(1, 0): fmt.read_array_header_1_0, (2, 0): fmt.read_array_header_2_0}.get(version)
        if reader is None:
            raise InputFileError(path, f"{key}: unsupported .npy format version {version}")
        shape, _fortran, dtype = reader(f)
    n = 1
    for d in shape:
        n *= int(d)
    declared = n * dtype.itemsize
    limit = min(info.file_size, 1100 * info.compress_size + 4096)
    if declared > limit:
        raise InputFileError(path, f"{key}: header declares {dtype} {tuple(shape)} ({declared} bytes), but the "
                                   f"archive entry holds at most {limit} bytes; damaged or hostile file")


#: What numpy raises on a damaged .npz or .npy (each found by tests/fuzz/fuzz_npz.py): zlib.error, a corrupt
#: deflate stream; NotImplementedError, a zip compression or "version needed" this Python cannot read;
#: RuntimeError, an encrypted entry; EOFError, a truncated entry; tokenize.TokenError and SyntaxError,
#: a damaged header dict (numpy 2.4 parses it with Python's tokenizer and literal_eval); lzma.LZMAError, an
#: entry marked LZMA-compressed (zip method 14) whose properties are damaged (bz2's errors are OSErrors).
_NPZ_ERRORS = (OSError, ValueError, zipfile.BadZipFile, zlib.error, lzma.LZMAError, NotImplementedError,
               RuntimeError, EOFError, tokenize.TokenError, SyntaxError)


def _array(path, data, key, shape_desc):
    if key not in data.files:
        raise InputFileError(path, f"{key}: missing (expected {shape_desc}); the file has keys "
                                   f"{', '.join(sorted(data.files)) or 'none'}")
    try:
        _check_declared_size(path, data, key)
        return np.asarray(data[key])
    except _NPZ_ERRORS as exc:
        raise InputFileError(path, f"{key}: unreadable ({exc})") from None


def read_smplx(path) -> Motion:
    """Read BEAT2 / AMASS SMPL-X motion onto `smplx_skeleton`.

    Parameters
    ----------
    path : str or os.PathLike
        ``.npz`` with ``poses (F, 165)`` axis-angle radians, ``trans (F, 3)``
        metres and ``mocap_frame_rate`` (or ``mocap_framerate``) in Hz.

    Returns
    -------
    Motion
        ``rotations (F, 55, 4)`` local quaternions in SMPL-X joint order;
        ``root_positions = trans + (0, -0.35, 0)``, the pelvis in metres.

    Raises
    ------
    InputFileError
        Unreadable file; a missing key, wrong shape or non-finite value (the
        message names the key, and the frame and joint for non-finite values).
    """
    try:
        data = np.load(path, allow_pickle=False)
    except _NPZ_ERRORS as exc:
        raise InputFileError(path, f"cannot read as .npz: {exc}") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise InputFileError(path, "expected an .npz archive with poses, trans and mocap_frame_rate; "
                                   "got a single .npy array")
    with data:
        poses = _array(path, data, "poses", f"(F, {3 * _N_JOINTS}) axis-angle")
        trans = _array(path, data, "trans", "(F, 3) metres")
        fps_key = next((k for k in _FPS_KEYS if k in data.files), None)
        if fps_key is None:
            raise InputFileError(path, f"mocap_frame_rate: missing (expected the frame rate in Hz); the file has "
                                       f"keys {', '.join(sorted(data.files))}")
        fps_arr = _array(path, data, fps_key, "a frame rate")
    if poses.ndim != 2 or poses.shape[1] != 3 * _N_JOINTS or poses.shape[0] < 1 \
            or not np.issubdtype(poses.dtype, np.number):
        raise InputFileError(path, f"poses: expected shape (F, {3 * _N_JOINTS}) (55 SMPL-X joints x axis-angle), "
                                   f"got {poses.dtype} {poses.shape}")
    n_f = poses.shape[0]
    if trans.shape != (n_f, 3) or not np.issubdtype(trans.dtype, np.number):
        raise InputFileError(path, f"trans: expected shape ({n_f}, 3) to match poses, got {trans.dtype} {trans.shape}")
    try:
        fps = float(np.asarray(fps_arr).reshape(-1)[0]) if np.asarray(fps_arr).size == 1 else float("nan")
    except (TypeError, ValueError):
        fps = float("nan")
    if not (math.isfinite(fps) and fps > 0):
        raise InputFileError(path, f"{fps_key}: expected one positive frame rate in Hz, got {fps_arr!r}")

    aa = poses.astype(np.float64).reshape(n_f, _N_JOINTS, 3)
    bad = ~np.isfinite(aa).all(axis=-1)
    if bad.any():
        f, j = (int(v) for v in np.argwhere(bad)[0])
        raise InputFileError(path, f"poses: frame {f}, joint {j} ({SMPLX_JOINT_NAMES[j]}) is not finite: {aa[f, j]}")
    trans = trans.astype(np.float64)
    bad = ~np.isfinite(trans).all(axis=-1)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise InputFileError(path, f"trans: frame {f} is not finite: {trans[f]}")

    skel = smplx_skeleton()
    return Motion(skel, fps, rot.from_axis_angle(aa), trans + skel.offsets[0])

