"""Arrays from user ``.npz`` files, with their memory bounded before numpy allocates it.

``np.load`` trusts a file: an ``.npy`` header may declare a (10**12, 165) array in a
1 KB file, a deflate bomb of 3.9 MB inflates to 4 GB (and the zip's own size fields
can say anything), and a file that is no zip at all is reported as "pickled data".
`read_npz` reads only the arrays it is asked for and bounds what each may inflate to:
an entry's stored (compressed) bytes are what the file really holds, so an array
larger than `MAX_NPZ_INFLATE_RATIO` times them (beyond a free `MAX_NPZ_FREE_BYTES`)
is refused before anything is allocated, whatever the zip's size fields say; then
exactly the declared bytes are inflated, in slices, straight into the array.
"""
from __future__ import annotations

import lzma
import math
import os
import tokenize
import zipfile
import zlib
from typing import NamedTuple

import numpy as np
import numpy.lib.format as npy_format

from gesturedb.errors import InputFileError, ParameterError, echo, echo_list
from gesturedb.io.atomic import atomic_open

__all__ = ["JOINT_POSITION_FIELDS", "MAX_NPZ_FREE_BYTES", "MAX_NPZ_INFLATE_RATIO", "JointPositions", "npz_keys",
           "read_joint_positions", "read_npz", "write_joint_positions"]

#: an entry may inflate to this many bytes whatever its compression ratio (54 minutes of
#: SMPL-X poses at 30 fps in float32); a larger one must compress no better than
#: `MAX_NPZ_INFLATE_RATIO`, so a small file never becomes gigabytes of arrays
MAX_NPZ_FREE_BYTES = 64 * 2**20
#: beyond `MAX_NPZ_FREE_BYTES`, inflated bytes per stored byte an entry may reach. Motion
#: capture compresses 1.1-3x; deflate's own limit is about 1032x, which only a bomb (or
#: an array of one repeated value) approaches
MAX_NPZ_INFLATE_RATIO = 64

_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header; an empty archive's end record
_NPY_MAGIC = b"\x93NUMPY"

#: What zipfile and numpy raise on a damaged archive or .npy entry (each found by
#: tests/fuzz/fuzz_npz.py): zlib.error, a corrupt deflate stream; NotImplementedError, a zip
#: compression or "version needed" this Python cannot read; RuntimeError, an encrypted entry;
#: EOFError, a truncated entry; tokenize.TokenError and SyntaxError, a damaged header dict
#: (numpy 2.4 parses it with Python's tokenizer and literal_eval); lzma.LZMAError, an entry
#: marked LZMA-compressed whose properties are damaged (bz2's errors are OSErrors).
NPZ_ERRORS = (OSError, ValueError, zipfile.BadZipFile, zlib.error, lzma.LZMAError, NotImplementedError,
              RuntimeError, EOFError, tokenize.TokenError, SyntaxError)


def _entry_limit(info: zipfile.ZipInfo) -> int:
    """Most bytes an entry may inflate to: what it stores times the ratio, at least the free amount."""
    return max(MAX_NPZ_FREE_BYTES, MAX_NPZ_INFLATE_RATIO * info.compress_size)


def _kind_of(path) -> str:
    """"npz", "npy", or raise InputFileError naming what the file is instead."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise InputFileError(path, f"cannot read as .npz: {exc.strerror or exc}") from None
    if head.startswith(_ZIP_MAGIC):
        return "npz"
    if head.startswith(_NPY_MAGIC):
        return "npy"
    if not head:
        raise InputFileError(path, "expected an .npz archive (a zip of .npy arrays); got an empty file")
    raise InputFileError(path, f"expected an .npz archive (a zip of .npy arrays, starting with 'PK'); "
                               f"got a file starting with {echo(head)}: not a zip archive")


def _open_zip(path) -> zipfile.ZipFile:
    if _kind_of(path) == "npy":
        raise InputFileError(path, "expected an .npz archive of named arrays; got a single .npy array")
    try:
        return zipfile.ZipFile(path)
    except NPZ_ERRORS as exc:
        raise InputFileError(path, f"cannot read as .npz: {' '.join(str(exc).split())}") from None


def _keys(zf: zipfile.ZipFile) -> list[str]:
    return [n[:-4] for n in zf.namelist() if n.endswith(".npy")]


def npz_keys(path) -> list[str]:
    """Names of the arrays in an ``.npz`` file, without reading any.

    Raises
    ------
    InputFileError
        Not a zip archive (the message says what the file starts with), or a damaged one.
    """
    with _open_zip(path) as zf:
        return _keys(zf)


def _read_entry(path, zf: zipfile.ZipFile, key: str) -> np.ndarray:
    info = zf.getinfo(key + ".npy")
    limit = _entry_limit(info)
    with zf.open(info) as f:
        version = npy_format.read_magic(f)
        reader = {(1, 0): npy_format.read_array_header_1_0, (2, 0): npy_format.read_array_header_2_0}.get(version)
        if reader is None:
            raise InputFileError(path, f"{key}: unsupported .npy format version {version}")
        shape, fortran, dtype = reader(f)
        if dtype.hasobject:
            raise InputFileError(path, f"{key}: expected numbers; got an array of Python objects (pickled data, "
                                       "which is never loaded)")
        count = math.prod(int(d) for d in shape)
        declared = count * dtype.itemsize
        # refused before anything is allocated: the declared size must fit what the entry says
        # it holds and what its stored bytes may inflate to
        room = min(info.file_size, limit)
        if declared > room:
            raise InputFileError(path, f"{key}: header declares {dtype} {echo(tuple(shape))} ({declared} bytes), but "
                                       f"the archive entry may hold at most {room} bytes (stored {info.compress_size}, "
                                       f"MAX_NPZ_INFLATE_RATIO = {MAX_NPZ_INFLATE_RATIO}); a damaged file or a "
                                       "deflate bomb")
        arr = np.empty(count, dtype=dtype)
        into = memoryview(arr.view(np.uint8).reshape(-1)) if declared else memoryview(b"")
        pos = 0
        while pos < declared:  # in slices, straight into the array: no second copy of the bytes
            data = f.read(min(_READ_SLICE, declared - pos))
            if not data:
                raise InputFileError(path, f"{key}: {pos} of the {declared} declared bytes (the entry is truncated)")
            into[pos:pos + len(data)] = data
            pos += len(data)
        return arr.reshape(shape[::-1]).transpose() if fortran else arr.reshape(shape)


_READ_SLICE = 1 << 20


def read_npz(path, keys, *, optional=()) -> dict[str, np.ndarray]:
    """Read named arrays from an ``.npz`` file with bounded memory.

    Parameters
    ----------
    path : str or os.PathLike
    keys : sequence of str
        Arrays that must be there.
    optional : sequence of str
        Arrays read when present.

    Returns
    -------
    dict of str to ndarray
        The arrays found (read-only views of their bytes).

    Raises
    ------
    InputFileError
        Not a zip archive, a damaged archive or entry, a missing key (the message lists
        the keys there are), an array of objects, or an entry whose declared or inflated
        size exceeds its bounds (`MAX_NPZ_FREE_BYTES`, `MAX_NPZ_INFLATE_RATIO`).
    """
    path = os.fspath(path)
    with _open_zip(path) as zf:
        have = _keys(zf)
        missing = [k for k in keys if k not in have]
        if missing:
            raise InputFileError(path, f"{missing[0]}: missing; the file has keys {echo_list(sorted(have)) or 'none'}")
        out = {}
        for key in list(keys) + [k for k in optional if k in have and k not in keys]:
            try:
                out[key] = _read_entry(path, zf, key)
            except InputFileError:
                raise
            except NPZ_ERRORS as exc:
                raise InputFileError(path, f"{key}: unreadable ({echo(' '.join(str(exc).split()), 200)[1:-1]})") \
                    from None
        return out


# --- joint positions: ``gesturedb synth --npz`` writes them, ``gesturedb render`` reads them ----------

#: The fields of a joint-position npz that must be there; ``names`` (J,) is optional.
JOINT_POSITION_FIELDS = ("positions", "parents", "fps")


class JointPositions(NamedTuple):
    """A joint-position npz: world positions of every joint with the hierarchy to draw them.

    positions : ndarray [shape=(T, J, 3)], float64, metres
    parents : ndarray [shape=(J,)], int64, -1 for the root
    fps : float
    names : list of str [length J] or None
    """

    positions: np.ndarray
    parents: np.ndarray
    fps: float
    names: list | None


def write_joint_positions(path, positions, *, parents, fps: float, names=None) -> None:
    """Write joint positions to a compressed ``.npz``, atomically (`read_joint_positions` reads it).

    Parameters
    ----------
    path : str or os.PathLike
    positions : array_like [shape=(T, J, 3)], metres
        Stored as float32 (0.1 mm at 10 m).
    parents : array_like [shape=(J,)], int, -1 for the root
    fps : float
    names : sequence of str [length J], optional

    Raises
    ------
    ParameterError
        Shapes that do not agree, or a frame rate that is not positive.
    InputFileError
        The file cannot be written (a previous file stays as it was).
    """
    pos = np.asarray(positions, dtype=np.float32)
    par = np.asarray(parents, dtype=np.int64)
    if pos.ndim != 3 or pos.shape[2] != 3 or par.shape != (pos.shape[1],):
        raise ParameterError(f"positions, parents: expected (T, J, 3) and (J,); got {pos.shape} and {par.shape}")
    if not (float(fps) > 0 and math.isfinite(float(fps))):
        raise ParameterError(f"fps: expected a positive frame rate; got {fps!r}")
    fields = dict(positions=pos, fps=np.float64(fps), parents=par)
    if names is not None:
        names = [str(n) for n in names]
        if len(names) != pos.shape[1]:
            raise ParameterError(f"names: expected one per joint ({pos.shape[1]}); got {len(names)}")
        fields["names"] = np.asarray(names)
    with atomic_open(path, "wb") as f:
        np.savez_compressed(f, **fields)


def read_joint_positions(path) -> JointPositions:
    """Read a joint-position npz (`write_joint_positions`, ``gesturedb synth --npz``), memory bounded.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    JointPositions

    Raises
    ------
    InputFileError
        Not an npz, a missing field of `JOINT_POSITION_FIELDS` (the message lists those
        missing), shapes that do not agree, a frame rate that is not positive, or a
        damaged array.
    """
    keys = set(npz_keys(path))
    missing = [k for k in JOINT_POSITION_FIELDS if k not in keys]
    if missing:
        raise InputFileError(path, f"joint-position npz: expected fields {', '.join(JOINT_POSITION_FIELDS)}; "
                                   f"missing {', '.join(missing)}")
    z = read_npz(path, JOINT_POSITION_FIELDS, optional=("names",))
    try:
        pos = np.asarray(z["positions"], dtype=np.float64)
        par = np.asarray(z["parents"]).astype(np.int64)
        fps = float(z["fps"])
        names = [str(n) for n in z["names"]] if "names" in z else None
    except (TypeError, ValueError) as exc:  # a string as fps, an array of several frame rates...
        raise InputFileError(path, f"joint-position npz: not readable ({' '.join(str(exc).split())})") from None
    if pos.ndim != 3 or pos.shape[2] != 3 or par.shape != (pos.shape[1],):
        raise InputFileError(path, f"positions: expected (T, J, 3) with parents (J,); got {pos.shape} and {par.shape}")
    if not (fps > 0):
        raise InputFileError(path, f"fps: expected a positive frame rate; got {fps}")
    if names is not None and len(names) != pos.shape[1]:
        raise InputFileError(path, f"names: expected one per joint ({pos.shape[1]}); got {len(names)}")
    return JointPositions(pos, par, fps, names)
