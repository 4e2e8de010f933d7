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

import math

import numpy as np

from gesturedb import rotations as rot
from gesturedb.errors import InputFileError, echo, echo_list
from gesturedb.io.bvh import MAX_FPS, MIN_FPS
from gesturedb.io.npz import npz_keys, read_npz
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
        Unreadable file (not a zip archive, damaged, an array larger than its entry
        can hold or inflating past `gesturedb.io.npz.MAX_NPZ_INFLATE_RATIO`); a
        missing key, wrong shape or non-finite value (the message names the key, and
        the frame and joint for non-finite values); a frame rate outside the 1-1000 Hz
        BVH files can carry.
    """
    have = npz_keys(path)
    for key, desc in (("poses", f"(F, {3 * _N_JOINTS}) axis-angle"), ("trans", "(F, 3) metres")):
        if key not in have:
            raise InputFileError(path, f"{key}: missing (expected {desc}); the file has keys "
                                       f"{echo_list(sorted(have)) or 'none'}")
    # memory bounded before allocation: declared and inflated sizes (gesturedb.io.npz)
    arrays = read_npz(path, ("poses", "trans"))
    fps_key = next((k for k in _FPS_KEYS if k in have), None)
    if fps_key is None:
        raise InputFileError(path, f"mocap_frame_rate: missing (expected the frame rate in Hz); the file has "
                                   f"keys {echo_list(sorted(have)) or 'none'}")
    poses, trans, fps_arr = arrays["poses"], arrays["trans"], read_npz(path, (fps_key,))[fps_key]
    if poses.ndim != 2 or poses.shape[1] != 3 * _N_JOINTS or poses.shape[0] < 1 \
            or not np.issubdtype(poses.dtype, np.number):
        raise InputFileError(path, f"poses: expected shape (F, {3 * _N_JOINTS}) (55 SMPL-X joints x axis-angle), "
                                   f"got {poses.dtype} {echo(poses.shape)}")
    n_f = poses.shape[0]
    if trans.shape != (n_f, 3) or not np.issubdtype(trans.dtype, np.number):
        raise InputFileError(path, f"trans: expected shape ({n_f}, 3) to match poses, got {trans.dtype} "
                                   f"{echo(trans.shape)}")
    try:
        fps = float(np.asarray(fps_arr).reshape(-1)[0]) if np.asarray(fps_arr).size == 1 else float("nan")
    except (TypeError, ValueError):
        fps = float("nan")
    if not (math.isfinite(fps) and MIN_FPS <= fps <= MAX_FPS):
        # the range read_bvh accepts: motion at 1e9 fps could be read, retargeted and written
        # to a BVH our own reader refuses
        raise InputFileError(path, f"{fps_key}: expected one frame rate of {MIN_FPS:g} to {MAX_FPS:g} Hz, "
                                   f"got {echo(fps_arr)}")

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

