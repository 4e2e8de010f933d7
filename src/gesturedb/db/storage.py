"""Atomic, locked storage: every database file is written to a temporary file beside it and renamed.

The one place that creates or replaces database files. A failed or interrupted
build or edit leaves the previous file exactly as it was and no half-written
file behind: the temporary file lives in the same folder, so the rename is
atomic, and it is removed on any failure (including KeyboardInterrupt and
SIGTERM, which is turned into the same interruption).

Concurrency: every write (a build to a path, an edit of a database) holds an
exclusive lock on ``.<name>.lock`` beside the database for its whole
read-modify-rename, so two concurrent ``masks add`` both survive. An edit that
decides from the file's contents (is this mask name taken? which occurrences
does this keyword have?) reads them while holding the same lock
(:func:`locked` is re-entrant, so ``with locked(p): read...; with edit(p): ...``
is one transaction): a concurrent edit is then refused, or applied on top of
the other, exactly as when the two run one after the other. Readers take no
lock: they open either the old or the new file, never a half-written one.

Links: a database reached through a symbolic link is edited where it lives:
the lock, the temporary file and the rename are those of the real file, so the
link stays a link and every name of the file shares one lock.

Space: an edit writes a compact copy (every object copied into a fresh file,
:func:`compact_copy`), so the space of replaced or deleted objects never piles
up from edit to edit, at about the cost of the byte copy it replaces.

Kills: temporary files are named ``.<name>.<pid>.<random>.tmp``. A process
killed with SIGKILL cannot remove its own; the next writer of the same path
(holding the lock) removes those whose pid is no longer alive.
"""
from __future__ import annotations

import contextlib
import errno
import glob
import io
import os
import re
import shutil
import signal
import tempfile
import threading
from typing import Callable

from gesturedb.db import schema
from gesturedb.errors import GestureDBError, InputFileError, ParameterError

#: seconds a writer waits for another writer of the same database before giving up
LOCK_TIMEOUT_S = 600.0


def real_path(path: str | os.PathLike) -> str:
    """The file a database path names, symbolic links resolved (edits replace that file, not the link)."""
    return os.path.realpath(os.fspath(path))


def lock_path(path: str | os.PathLike) -> str:
    """The lock file of a database: ``.<name>.lock`` beside the real file (links resolved)."""
    path = real_path(path)
    return os.path.join(os.path.dirname(path), "." + os.path.basename(path) + ".lock")


#: (lock file, process, thread) -> how many nested :func:`locked` blocks of this thread hold it (the
#: process too: a child forked inside a locked block inherits this dict, not the lock)
_held: dict[tuple[str, int, int], int] = {}


@contextlib.contextmanager
def locked(path: str | os.PathLike, *, timeout_s: float | None = None):
    """Hold the exclusive write lock of database ``path`` (other writers wait; readers do not).

    Re-entrant within a thread: an edit's checks and its :func:`edit` share one hold,
    so nothing can change the file between what the checks read and what is written.
    """
    import filelock

    lp = lock_path(path)
    key = (lp, os.getpid(), threading.get_ident())
    if key in _held:
        _held[key] += 1
        try:
            yield
        finally:
            _held[key] -= 1
        return
    lock = filelock.FileLock(lp, timeout=LOCK_TIMEOUT_S if timeout_s is None else timeout_s)
    try:
        lock.acquire()
    except filelock.Timeout:
        raise InputFileError(path, f"another gesturedb process is writing this database (lock {lp} held "
                             f"for more than {lock.timeout:g} s)") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot create the lock file {lp}: {exc.strerror or exc}") from None
    _held[key] = 1
    try:
        yield
    finally:
        del _held[key]
        lock.release()


def _tmp_prefix(path: str) -> str:
    return "." + os.path.basename(path) + "."


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[str]:
    """Remove temporary files of ``path`` left by dead processes (call with the lock held).

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


def _mkstemp(path: str) -> str:
    folder = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{_tmp_prefix(path)}{os.getpid()}.", suffix=".tmp", dir=folder)
    except OSError as exc:
        raise _os_error(path, exc) from None
    os.close(fd)
    return tmp


def _os_error(path: str, exc: OSError) -> GestureDBError:
    """One line for an OSError while writing ``path``; ENOSPC says so in plain words."""
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


def _is_disk_error(exc: BaseException) -> OSError | None:
    """The OSError behind ``exc`` if it is a disk-full/quota error (h5py wraps them in OSError text)."""
    e = exc
    while e is not None:
        if isinstance(e, OSError) and (e.errno in (errno.ENOSPC, errno.EDQUOT) or "No space left" in str(e)):
            return e
        e = e.__cause__ or e.__context__
    return None


class _GuardedFile(io.RawIOBase):
    """A temporary HDF5 file as h5py's ``fileobj`` driver sees it: a write the disk refuses
    (full, quota, I/O error) is recorded, never reported to HDF5.

    HDF5 does not survive a failed write inside a close: with its own driver a full disk
    failed a dataset's close in a finalizer (``Exception ignored in ObjectID.__dealloc__``),
    HDF5 freed memory twice, and the build printed its one-line error, h5py tracebacks, then
    died of a segfault (exit 139). Here, once the disk has refused a write, that write and every
    later one go to pages held in memory instead, so HDF5 reads back what it wrote and closes
    every handle normally; the writer then raises the recorded error (:func:`check_writes` at
    its checkpoints, at the latest when the file is closed) and the file is deleted. The memory
    held is what HDF5 writes between the failure and the next checkpoint.
    """

    PAGE = 1 << 16

    def __init__(self, path: str):
        self.path = path
        self._fd = os.open(path, os.O_RDWR)
        self._pos = 0
        self._size = os.fstat(self._fd).st_size
        self.error: OSError | None = None
        self._pages: dict[int, bytearray] = {}  # page number -> content, once a write failed
        # the name h5py gives HDF5 (and h5.filename returns): repr(self) made ASCII
        self.key = path.encode("ascii", "replace").decode()
        _GUARDED[self.key] = self

    def __repr__(self) -> str:  # h5py takes it as the file's name (h5.filename, HDF5's messages)
        return self.path

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, pos: int, whence: int = 0) -> int:
        self._pos = pos if whence == 0 else self._pos + pos if whence == 1 else self._size + pos
        return self._pos

    def tell(self) -> int:
        return self._pos

    def _disk(self, pos: int, n: int) -> bytes:
        n = max(0, min(n, self._size - pos))
        data = os.pread(self._fd, n, pos) if n else b""
        return data + bytes(n - len(data))

    def _page(self, k: int) -> bytearray:
        page = self._pages.get(k)
        if page is None:
            page = self._pages[k] = bytearray(self._disk(k * self.PAGE, self.PAGE).ljust(self.PAGE, b"\0"))
        return page

    def readinto(self, b) -> int:
        out = memoryview(b).cast("B")
        pos, n = self._pos, len(out)
        if not self._pages:
            data = self._disk(pos, n)
            out[:len(data)] = data
            out[len(data):] = bytes(n - len(data))
        else:
            done = 0
            while done < n:
                k, off = divmod(pos + done, self.PAGE)
                m = min(n - done, self.PAGE - off)
                page = self._pages.get(k)
                piece = page[off:off + m] if page is not None else self._disk(pos + done, m)
                out[done:done + m] = bytes(piece).ljust(m, b"\0")
                done += m
        self._pos += n
        return n

    def write(self, b) -> int:
        data = memoryview(b).cast("B")
        pos, n = self._pos, len(data)
        if self.error is None:
            try:
                done = 0
                while done < n:
                    done += os.pwrite(self._fd, data[done:], pos + done)
            except OSError as exc:
                self.error = exc
        if self.error is not None:
            done = 0
            while done < n:
                k, off = divmod(pos + done, self.PAGE)
                m = min(n - done, self.PAGE - off)
                self._page(k)[off:off + m] = data[done:done + m]
                done += m
        self._pos += n
        self._size = max(self._size, pos + n)
        return n

    def truncate(self, size: int | None = None) -> int:
        size = self._pos if size is None else size
        if self.error is None:
            try:
                os.ftruncate(self._fd, size)
            except OSError as exc:
                self.error = exc
        for k in [k for k in self._pages if (k + 1) * self.PAGE > size]:
            if k * self.PAGE >= size:
                del self._pages[k]
            else:
                self._pages[k][size - k * self.PAGE:] = bytes((k + 1) * self.PAGE - size)
        self._size = size
        return size

    def flush(self) -> None:
        pass  # every write is an unbuffered pwrite

    def close(self) -> None:
        if not self.closed:
            _GUARDED.pop(self.key, None)
            self._pages.clear()
            os.close(self._fd)
        super().close()

    def close_h5(self, h5, *, check: bool = True) -> None:
        """Close ``h5`` (every handle of it), then raise the write that failed, if one did."""
        try:
            h5.close()
        finally:
            if h5.id.valid:  # a close that failed half-way (say, interrupted): once more
                with contextlib.suppress(Exception):
                    h5.close()
        if check:
            self.check()

    def check(self) -> None:
        if self.error is not None:
            raise self.error


#: the guarded temporary files being written, by name (``h5.filename``), for :func:`check_writes`
_GUARDED: dict[str, _GuardedFile] = {}


def check_writes(h5) -> None:
    """Raise the OSError of a write to ``h5`` that the disk refused (see :class:`_GuardedFile`).

    Writers call it at checkpoints (a build: after each recording and each stage), so that
    a full disk stops them there, with what HDF5 wrote since held in memory; nothing for a
    file not written by :func:`write_atomically`."""
    guard = _GUARDED.get(h5.filename)
    if guard is not None:
        guard.check()


def write_atomically(out_path: str | os.PathLike, fill: Callable) -> None:
    """Create an HDF5 file by writing a temporary file beside ``out_path`` and renaming it.

    The temporary file is in the same folder so the rename is atomic; it is
    removed on any failure (including KeyboardInterrupt and SIGTERM), so a
    failed build leaves nothing behind and an existing database untouched. The
    write lock of ``out_path`` is held throughout.
    """
    import h5py

    out_path = os.fspath(out_path)
    folder = os.path.dirname(os.path.abspath(out_path))
    if not os.path.isdir(folder):
        raise ParameterError(f"output: folder {folder} does not exist")
    if os.path.isdir(out_path):
        raise ParameterError(f"output: {out_path} is a folder; expected a file name such as DB.h5")
    with sigterm_as_interrupt() as signals, locked(out_path):
        remove_stale_temporaries(out_path)
        tmp = None
        try:
            tmp = _mkstemp(out_path)
            with _GuardedFile(tmp) as guard:
                h5 = h5py.File(guard, "w", track_order=True)
                try:
                    fill(h5)
                except BaseException as exc:
                    # a refused write is the cause of what failed after it; an interruption stays one
                    guard.close_h5(h5, check=isinstance(exc, Exception))
                    raise
                guard.close_h5(h5)
            if signals:
                raise KeyboardInterrupt("SIGTERM")
            # mkstemp makes the file 0600; give it the mode a plain open() would
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
            os.replace(tmp, out_path)
        except BaseException as exc:
            # by pattern, not by name: a SIGTERM inside mkstemp leaves a file whose name we never got
            _remove_own_temporaries(out_path)
            _reraise_interrupt(signals, exc)
            disk = _is_disk_error(exc)
            if disk is not None:
                raise _os_error(out_path, disk) from None
            if isinstance(exc, OSError) and type(exc).__module__.split(".")[0] in ("distributed", "tornado"):
                raise  # a lost Dask connection (CommClosedError), not this file: "cannot write" misled
            if isinstance(exc, OSError) and not isinstance(exc, GestureDBError):
                other = _other_file(exc, (out_path, tmp))
                if other is not None:
                    # an input that ``fill`` read (on a Dask worker, say) is not the output
                    raise InputFileError(other, f"{exc.strerror or exc} (while writing {out_path}, which is left "
                                                f"as it was)") from None
                raise _os_error(out_path, exc) from None
            raise


def _other_file(exc: OSError, own) -> str | None:
    """The file an OSError names when it is none of ``own`` (the output and its temporary)."""
    name = exc.filename
    if name is None or isinstance(name, int):
        return None
    name = os.fsdecode(name)
    return None if any(p is not None and os.path.abspath(name) == os.path.abspath(p) for p in own) else name


def compact_copy(src_path: str, dst) -> None:
    """Copy the HDF5 file ``src_path`` into ``dst`` object by object (a fresh, compact file).

    HDF5 does not give back the space of a deleted or replaced object once the file
    is closed: a byte copy carries every earlier edit's dead space into the next
    one. Copying each top-level object (``H5Ocopy``: datasets with their layout,
    filters and attributes, virtual datasets as virtual) and the root attributes
    into a new file leaves it behind.

    Parameters
    ----------
    src_path : str
    dst : str or h5py.File
        A path (created with creation order tracked, as :func:`write_atomically`
        makes files), or an empty file open for writing.
    """
    import h5py

    if isinstance(dst, (str, os.PathLike)):
        with h5py.File(dst, "w", track_order=True) as h5:
            compact_copy(src_path, h5)
        return
    with h5py.File(src_path, "r") as src:
        for k, v in src.attrs.items():
            dst.attrs[k] = v
        for name in src:
            link = src.get(name, getlink=True)
            if isinstance(link, (h5py.SoftLink, h5py.ExternalLink)):
                dst[name] = link  # a link stays a link (H5Ocopy would copy what it points at)
            else:
                src.copy(src[name], dst, name)


@contextlib.contextmanager
def edit(path: str | os.PathLike, *, upgrade: bool = False):
    """Yield a writable :class:`h5py.File` on a compact copy of ``path``; replace ``path`` on success.

    The database's write lock is held from before the copy until after the
    rename, so concurrent edits serialise instead of losing each other; callers
    that decide what to write from the file's contents read them inside
    ``with locked(path):`` around this (see the module notes). A symbolic link
    is followed: the real file is replaced and the link kept.
    ``upgrade=True`` also opens a file of :data:`schema.UPGRADABLE_VERSIONS` (the caller brings it to the current version).

    Examples
    --------
    >>> with edit("scott.h5") as h5:                      # doctest: +SKIP
    ...     h5["masks"].create_dataset("calm", data=bits)
    """
    import h5py

    shown = os.fspath(path)
    if not os.path.isfile(shown):
        raise InputFileError(shown, "no such file")
    path = real_path(shown)
    with sigterm_as_interrupt() as signals, locked(path):
        remove_stale_temporaries(path)
        try:
            tmp = _mkstemp(path)
            with h5py.File(path, "r") as h5:  # before the copy: a file of another version is refused as it is
                schema.check_version(h5, shown, upgradable=upgrade)
            # the copy and the edit are one session of HDF5 on a guarded file (see _GuardedFile):
            # a full disk is one error, not a failed close inside HDF5
            with _GuardedFile(tmp) as guard:
                h5 = h5py.File(guard, "w", track_order=True)
                try:
                    try:
                        compact_copy(path, h5)
                        guard.check()
                    except OSError as exc:
                        raise _os_error(shown, _is_disk_error(exc) or exc) from None
                    yield h5
                except BaseException as exc:
                    guard.close_h5(h5, check=isinstance(exc, Exception))
                    raise
                guard.close_h5(h5)
            shutil.copymode(path, tmp)  # mkstemp made it 0600: keep the database's own permissions
            if signals:
                raise KeyboardInterrupt("SIGTERM")
            os.replace(tmp, path)
        except BaseException as exc:
            _remove_own_temporaries(path)
            _reraise_interrupt(signals, exc)
            disk = _is_disk_error(exc)
            if disk is not None and not isinstance(exc, GestureDBError):
                raise _os_error(shown, disk) from None
            raise
