"""Formats in and out: motion (BVH, SMPL-X npz, glTF), speech audio, word transcripts, joint names.

    motion = read_motion("2_scott_0_1_1.npz")      # or a .bvh / .glb
    write_motion("out.glb", motion)                # or a .bvh
    samples, sr = read_audio("2_scott_0_1_1.wav")  # mono float32 at 16 kHz
    words = read_transcript("2_scott_0_1_1.TextGrid")
"""
from __future__ import annotations

import os

from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io.audio import read_audio
from gesturedb.io.bvh import read_bvh, write_bvh
from gesturedb.io.gltf import read_gltf, write_glb
from gesturedb.io.joints import BODY_ROLES, FEATURE_ROLES, find_joints
from gesturedb.io.smplx import read_smplx, smplx_skeleton
from gesturedb.io.transcripts import Words, read_transcript

__all__ = [
    "BODY_ROLES",
    "FEATURE_ROLES",
    "MOTION_EXTENSIONS",
    "MOTION_OUT_EXTENSIONS",
    "check_motion_output",
    "Words",
    "find_joints",
    "read_audio",
    "read_bvh",
    "read_motion",
    "read_smplx",
    "read_transcript",
    "smplx_skeleton",
    "write_bvh",
    "write_motion",
]

MOTION_EXTENSIONS = (".bvh", ".npz", ".glb", ".gltf")
MOTION_OUT_EXTENSIONS = (".bvh", ".glb")


def read_motion(path, *, length_unit_m: float | None = None):
    """Read motion, choosing the reader by extension.

    Parameters
    ----------
    path : str or os.PathLike
        ``.bvh`` -> `read_bvh`, ``.npz`` -> `read_smplx`, ``.glb``/``.gltf`` ->
        `gesturedb.io.gltf.read_gltf` (case-insensitive).
    length_unit_m : float or None
        Metres per BVH length unit (``None``: inferred, see `read_bvh`).
        SMPL-X files are in metres; only ``None`` or 1.0 is accepted for them.

    Returns
    -------
    gesturedb.motion.Motion

    Raises
    ------
    InputFileError
        Unknown extension or any reader's error.
    ParameterError
        A ``length_unit_m`` other than 1.0 for an ``.npz`` file.
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext == ".bvh":
        return read_bvh(path, length_unit_m=length_unit_m)
    if ext == ".npz":
        if length_unit_m not in (None, 1.0):
            raise ParameterError(f"length_unit_m: SMPL-X .npz files are in metres; got {length_unit_m} for {path}")
        return read_smplx(path)
    if ext in (".glb", ".gltf"):
        if length_unit_m not in (None, 1.0):
            raise ParameterError(f"length_unit_m: glTF files are in metres; got {length_unit_m} for {path}")

        return read_gltf(path)
    raise InputFileError(path, f"unknown motion extension {ext or '(none)'!r}; expected "
                               f"{' or '.join(MOTION_EXTENSIONS)}")


def check_motion_output(path) -> str:
    """The lower-case extension of a motion output path, checked before any work is done.

    Raises
    ------
    InputFileError
        An extension other than ``.bvh`` or ``.glb``.
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in MOTION_OUT_EXTENSIONS:
        raise InputFileError(path, f"output: unknown motion extension {ext or '(none)'!r}; expected "
                                   f"{' or '.join(MOTION_OUT_EXTENSIONS)}")
    return ext


def write_motion(path, motion) -> None:
    """Write motion, choosing the writer by extension: ``.bvh`` -> `write_bvh`,
    ``.glb`` -> `gesturedb.io.gltf.write_glb` (skin, box-per-bone mesh, animation).

    Raises
    ------
    InputFileError
        Unknown extension or the file cannot be written.
    """
    if check_motion_output(path) == ".glb":
        write_glb(path, motion)
    else:
        write_bvh(path, motion)
