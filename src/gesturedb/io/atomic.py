"""Output files that appear whole or not at all.

Every file gesturedb writes beside a database (BVH, glTF, npz, provenance JSON,
evaluation reports) goes through :func:`atomic_open`: the bytes go to a sibling
temporary file that is renamed over the target only after the last write
succeeded, so a full disk, Ctrl-C or a crash never leaves half a file where the
user's previous output was. (The database itself has its own locked writer,
``gesturedb/db/storage.py``, because it also edits files in place.)
"""
from __future__ import annotations

import contextlib
import os
import uuid
from typing import IO, Iterator

from gesturedb.errors import InputFileError


def temporary_name(path: str | os.PathLike) -> str:
    """A sibling of ``path`` no other process picks: ``<path>.tmp-<pid>-<random>``.

    A sibling (not the system's temporary folder) so the final rename stays on one
    file system and is atomic.
    """
    return f"{os.fspath(path)}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """Open ``path`` for writing through a temporary sibling renamed on success.

    Parameters
    ----------
    path : str or os.PathLike
        The file to (re)place.
    mode : {"w", "wb"}
        Text or binary; any other keyword (``encoding``, ``newline``) goes to ``open``.

    Yields
    ------
    file object
        Write to it inside the ``with`` block; the target is replaced when the block
        ends without an exception, and untouched (the temporary removed) otherwise.

    Raises
    ------
    InputFileError
        The file cannot be written (the message names it and the system's reason).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open: expected mode 'w' or 'wb', got {mode!r}")
    if mode == "w":
        kwargs.setdefault("encoding", "utf-8")
    path = os.fspath(path)
    tmp = temporary_name(path)
    try:
        # "x" (not mkstemp) so the file gets the usual umask permissions, like a plain open()
        with open(tmp, mode.replace("w", "x"), **kwargs) as f:
            yield f
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise InputFileError(path, f"cannot write: {exc.strerror or exc}") from None
        raise


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_open`)."""
    with atomic_open(path, "w") as f:
        f.write(text)
