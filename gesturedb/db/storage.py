"""Atomic storage: every database file is written to a temporary file beside it and renamed.

The one place that creates or replaces database files. A failed or interrupted
build or edit leaves the previous file exactly as it was and no half-written
file behind: the temporary file lives in the same folder, so the rename is
atomic, and it is removed on any failure (including KeyboardInterrupt).
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from typing import Callable

from gesturedb.db import schema
from gesturedb.errors import InputFileError, ParameterError


def write_atomically(out_path: str | os.PathLike, fill: Callable) -> None:
    """Create an HDF5 file by writing a temporary file beside ``out_path`` and renaming it.

    The temporary file is in the same folder so the rename is atomic; it is
    removed on any failure (including KeyboardInterrupt), so a failed build
    leaves nothing behind and an existing database untouched.
    """
    import h5py

    out_path = os.fspath(out_path)
    folder = os.path.dirname(os.path.abspath(out_path))
    if not os.path.isdir(folder):
        raise ParameterError(f"output: folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(out_path) + ".", suffix=".tmp", dir=folder)
    os.close(fd)
    try:
        with h5py.File(tmp, "w", track_order=True) as h5:
            fill(h5)
        # mkstemp makes the file 0600; give it the mode a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, out_path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


@contextlib.contextmanager
def edit(path: str | os.PathLike, *, upgrade: bool = False):
    """Yield a writable :class:`h5py.File` on a copy of ``path``; replace ``path`` on success.

    ``upgrade=True`` also opens a version-1 file (the caller brings it to the current version).

    Examples
    --------
    >>> with edit("scott.h5") as h5:                      # doctest: +SKIP
    ...     h5["masks"].create_dataset("calm", data=bits)
    """
    import h5py

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputFileError(path, "no such file")
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp", dir=folder)
    os.close(fd)
    try:
        shutil.copyfile(path, tmp)
        shutil.copymode(path, tmp)  # mkstemp made it 0600: keep the database's own permissions
        with h5py.File(tmp, "r+") as h5:
            schema.check_version(h5, path, upgradable=upgrade)
            yield h5
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
