"""Files that appear whole or not at all: the one atomic writer of gesturedb.

Every file gesturedb writes goes through :func:`replacing`: the bytes go to a
temporary sibling ``.<name>.<pid>.<random>.tmp`` that is renamed over the target
only when the writing block ends without an exception, so a full disk, Ctrl-C,
SIGTERM or a crash never leaves half a file where the user's previous one was.
The sibling lives in the same folder, so the rename is atomic; it is removed on
any failure (SIGTERM is turned into the same interruption as Ctrl-C).

:func:`atomic_open` is :func:`replacing` for text and binary outputs (BVH, glTF,
npz, provenance JSON, evaluation reports); the database writer
(:mod:`gesturedb.db.storage`) adds its lock and its HDF5 handling around
:func:`replacing`.

Kills: a process killed with SIGKILL cannot remove its own temporary file; its
name carries the pid, and :func:`remove_stale_temporaries` (called by the next
database writer of the same path, holding its lock) removes those whose process
is no longer alive.
"""
from __future__ import annotations

import contextlib
import errno
import glob
import os
import re
import shutil
import signal
import tempfile
import threading
from typing import IO, Iterator

from gesturedb.errors import GestureDBError, InputFileError


def _tmp_prefix(path: str) -> str:
    return "." + os.path.basename(path) + "."


def is_temporary_of(name: str | os.PathLike, path: str | os.PathLike) -> bool:
    """Whether ``name`` is a temporary file of ``path`` (made by :func:`replacing`, any process)."""
    name, path = os.path.abspath(os.fsdecode(name)), os.path.abspath(os.fspath(path))
    return (os.path.dirname(name) == os.path.dirname(path) and os.path.basename(name).startswith(_tmp_prefix(path))
            and name.endswith(".tmp"))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[str]:
    """Remove temporary files of ``path`` left by dead processes (call with the path's lock held).

    Returns the files removed.
    """
    path = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(path)
    pat = re.compile(re.escape(_tmp_prefix(path)) + r"(\d+)\.[^.]+\.tmp$")
    removed = []
    for f in glob.glob(os.path.join(glob.escape(folder), glob.escape(_tmp_prefix(path)) + "*.tmp")):
        m = pat.match(os.path.basename(f))
        if m and int(m.group(1)) != os.getpid() and not _pid_alive(int(m.group(1))):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(f)
                removed.append(f)
    return removed


def _remove_own_temporaries(path: str) -> None:
    """Remove every temporary file of ``path`` made by this process (also one whose name a signal lost)."""
    path = os.path.abspath(path)
    pattern = os.path.join(glob.escape(os.path.dirname(path)), glob.escape(f"{_tmp_prefix(path)}{os.getpid()}.") + "*.tmp")
    for f in glob.glob(pattern):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(f)


def os_error(path: str, exc: OSError) -> GestureDBError:
    """One line for an OSError while writing ``path``; ENOSPC and EDQUOT say so in plain words."""
    if exc.errno == errno.ENOSPC or "No space left" in str(exc):
        return InputFileError(path, "no space left on device while writing it; the previous file (if any) is "
                              "unchanged")
    if exc.errno == errno.EDQUOT:
        return InputFileError(path, "disk quota exceeded while writing it; the previous file (if any) is unchanged")
    return InputFileError(path, f"cannot write: {exc.strerror or exc}")


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Turn SIGTERM into KeyboardInterrupt in the main thread, so cleanup runs as for Ctrl-C.

    Yields a list that records the signals received: a KeyboardInterrupt raised inside a
    finalizer (h5py closing objects) is swallowed by Python, so writers check the list
    once more before their rename.
    """
    got: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield got
        return

    def handler(signum, frame):
        got.append(signum)
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        old = signal.signal(signal.SIGTERM, handler)
    except (ValueError, OSError):  # not settable here (embedded interpreter): nothing to restore
        yield got
        return
    try:
        yield got
    finally:
        signal.signal(signal.SIGTERM, old)


def _reraise_interrupt(signals: list[int], exc: BaseException) -> None:
    """After a SIGTERM, whatever failed failed because of it: raise it as the interrupt.

    The handler's KeyboardInterrupt can surface as another error: raised inside
    an h5py type-conversion callback it comes out as ``TypeError: Operation not
    defined for data type class`` (seen in CI), which would exit 1 with a
    misleading message instead of 130.
    """
    if signals and not isinstance(exc, KeyboardInterrupt):
        raise KeyboardInterrupt(f"signal {signals[0]}") from exc


@contextlib.contextmanager
def replacing(path: str | os.PathLike, *, mode_of: str | os.PathLike | None = None) -> Iterator[str]:
    """A temporary sibling of ``path`` to write, renamed over ``path`` when the block succeeds.

    Parameters
    ----------
    path : str or os.PathLike
        The file to create or replace.
    mode_of : str or os.PathLike, optional
        A file whose permissions the new file takes (an edit keeps the database's own); by
        default those a plain ``open()`` gives (0666 less the umask).

    Yields
    ------
    str
        The temporary file (created empty, 0600 until the rename). On any exception in the
        block (KeyboardInterrupt and SIGTERM included) it is removed, ``path`` is left as it
        was, and the exception propagates (after a SIGTERM, as KeyboardInterrupt).

    Raises
    ------
    InputFileError
        The temporary file cannot be created (the message names ``path`` and the reason).
    """
    path = os.fspath(path)
    with sigterm_as_interrupt() as signals:
        try:
            tmp = _new_temporary(path)
            yield tmp
            if signals:  # a KeyboardInterrupt that a finalizer swallowed
                raise KeyboardInterrupt("SIGTERM")
            if mode_of is not None:
                shutil.copymode(mode_of, tmp)
            else:  # mkstemp made it 0600: give it the mode a plain open() would
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(tmp, 0o666 & ~umask)
            os.replace(tmp, path)
        except BaseException as exc:
            # by pattern, not by name: a SIGTERM inside mkstemp leaves a file whose name we never got
            _remove_own_temporaries(path)
            _reraise_interrupt(signals, exc)
            raise


def _new_temporary(path: str) -> str:
    """An empty file beside ``path``, named so that :func:`remove_stale_temporaries` knows
    whose it is (this process's id); an :class:`InputFileError` naming ``path`` if it cannot be made."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{_tmp_prefix(path)}{os.getpid()}.", suffix=".tmp",
                                   dir=os.path.dirname(os.path.abspath(path)))
    except OSError as exc:
        raise os_error(path, exc) from None
    os.close(fd)
    return tmp


@contextlib.contextmanager
def scratch(path: str | os.PathLike) -> Iterator[str]:
    """An intermediate file beside ``path``, removed when the block ends, whatever happens.

    Named as :func:`replacing` names its temporaries, so a process killed with SIGKILL
    leaves one that :func:`remove_stale_temporaries` removes, and a failed :func:`replacing`
    block around it removes it too.
    """
    path = os.fspath(path)
    tmp = _new_temporary(path)
    try:
        yield tmp
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """Open ``path`` for writing through a temporary sibling renamed on success (:func:`replacing`).

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
    try:
        with replacing(path) as tmp, open(tmp, mode, **kwargs) as f:
            yield f
    except OSError as exc:
        raise InputFileError(path, f"cannot write: {exc.strerror or exc}") from None


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_open`)."""
    with atomic_open(path, "w") as f:
        f.write(text)
