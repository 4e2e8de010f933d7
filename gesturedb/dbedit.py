"""Atomic edits of an existing database (saved masks, control features, keyword sub-databases).

The file is copied to a temporary file beside it, the copy is edited, and the
copy is renamed over the original only when the edit succeeded: an error or an
interruption leaves the database exactly as it was.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile

from gesturedb import schema
from gesturedb.errors import InputFileError


@contextlib.contextmanager
def edit(path: str | os.PathLike):
    """Yield a writable :class:`h5py.File` on a copy of ``path``; replace ``path`` on success.

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
            schema.check_version(h5, path)
            yield h5
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
