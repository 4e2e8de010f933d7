"""Atomic, locked storage: every database file is written to a temporary file beside it and renamed.

The one place that creates or replaces database files. A failed or interrupted
build or edit leaves the previous file exactly as it was and no half-written
file behind: the temporary file and its rename are those of every output of
gesturedb (:func:`gesturedb.io.atomic.replacing`, which also turns SIGTERM into
the same interruption as Ctrl-C); this module adds the lock, the HDF5 file on
top of it and the edit of an existing file.

Concurrency: every write (a build to a path, an edit of a database) holds an
exclusive lock on ``.<name>.lock`` beside the database for its whole
read-modify-rename, so two concurrent ``masks add`` both survive. The lock file
exists only while a writer holds it (it is removed on release, see
:func:`_acquire`), so nothing is left beside the database. An edit that decides
from the file's contents (is this mask name taken? which occurrences does this
keyword have?) reads them while holding the same lock (:func:`locked` is
re-entrant, so ``with locked(p): read...; with edit(p): ...`` is one
transaction): a concurrent edit is then refused, or applied on top of the
other, exactly as when the two run one after the other. Readers take no lock:
they open either the old or the new file, never a half-written one.

Links: a database reached through a symbolic link is edited where it lives:
the lock, the temporary file and the rename are those of the real file, so the
link stays a link and every name of the file shares one lock.

Space: an edit writes a compact copy (every object copied into a fresh file,
:func:`compact_copy`), so the space of replaced or deleted objects never piles
up from edit to edit, at about the cost of the byte copy it replaces.

Kills: a process killed with SIGKILL cannot remove its temporary file; the next
writer of the same path (holding the lock) removes those whose process is no
longer alive (:func:`gesturedb.io.atomic.remove_stale_temporaries`).
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import io
import os
import threading
import time
from typing import Callable

import numpy as np

from gesturedb.db import schema
from gesturedb.errors import GestureDBError, InputFileError, ParameterError
from gesturedb.io.atomic import is_temporary_of, os_error, remove_stale_temporaries, replacing, scratch

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
    The lock file exists only while it is held (see :func:`_acquire`): nothing is left
    beside the database.
    """
    lp = lock_path(path)
    key = (lp, os.getpid(), threading.get_ident())
    if key in _held:
        _held[key] += 1
        try:
            yield
        finally:
            _held[key] -= 1
        return
    timeout_s = LOCK_TIMEOUT_S if timeout_s is None else float(timeout_s)
    fd = _acquire(path, lp, timeout_s)
    _held[key] = 1
    try:
        yield
    finally:
        del _held[key]
        # unlinked while still held, then closed: a writer waiting on this file wakes up, sees that
        # it is no longer the file at ``lp`` and locks a fresh one (see _acquire)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(lp)
        os.close(fd)


#: seconds between two tries of a held lock
_LOCK_POLL_S = 0.05


def _acquire(path, lp: str, timeout_s: float) -> int:
    """Lock the file ``lp`` (``flock``, exclusive), creating it; the open descriptor that holds it.

    A lock file removed on release could be locked by a waiter after its removal (the waiter
    opened it before): a hold counts only if the file locked is still the one at ``lp`` (same
    device and inode), otherwise the descriptor is closed and the lock tried again on the new file.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            try:
                fd = os.open(lp, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
            except PermissionError:  # another user's lock file: a read-only descriptor locks as well
                fd = os.open(lp, os.O_RDONLY | os.O_CLOEXEC)
        except FileNotFoundError:  # removed between the two opens: try again
            continue
        except OSError as exc:
            raise InputFileError(path, f"cannot create the lock file {lp}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            if time.monotonic() >= deadline:
                raise InputFileError(path, f"another gesturedb process is writing this database (lock {lp} held "
                                           f"for more than {timeout_s:g} s)") from None
            time.sleep(_LOCK_POLL_S)
            continue
        except OSError as exc:
            os.close(fd)
            raise InputFileError(path, f"cannot lock the lock file {lp}: {exc.strerror or exc}") from None
        held = os.fstat(fd)
        try:
            now = os.stat(lp)
        except FileNotFoundError:
            now = None
        if now is not None and (now.st_dev, now.st_ino) == (held.st_dev, held.st_ino):
            return fd
        os.close(fd)  # the previous holder removed it after this open: lock the new one


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


def write_atomically(out_path: str | os.PathLike, fill: Callable, *, compact: bool = False) -> None:
    """Create an HDF5 file by writing a temporary file beside ``out_path`` and renaming it.

    The temporary file is in the same folder so the rename is atomic; it is
    removed on any failure (including KeyboardInterrupt and SIGTERM), so a
    failed build leaves nothing behind and an existing database untouched
    (:func:`gesturedb.io.atomic.replacing`). The write lock of ``out_path`` is
    held throughout.

    ``compact=True``: ``fill`` writes an intermediate file beside ``out_path``, which is
    then copied into the temporary file with :func:`compact_copy` (the per-frame arrays
    stored contiguous, so that readers memory-map them) and removed. For a build, whose
    per-frame arrays grow chunk by chunk as the recordings arrive: it costs a copy of the
    file, as an edit does, and twice its size on the disk while it runs.
    """
    out_path = os.fspath(out_path)
    folder = os.path.dirname(os.path.abspath(out_path))
    if not os.path.isdir(folder):
        raise ParameterError(f"output: folder {folder} does not exist")
    if os.path.isdir(out_path):
        raise ParameterError(f"output: {out_path} is a folder; expected a file name such as DB.h5")
    with locked(out_path):
        remove_stale_temporaries(out_path)
        try:
            with replacing(out_path) as tmp, contextlib.ExitStack() as stack:
                first = stack.enter_context(scratch(out_path)) if compact else tmp
                _fill_guarded(first, fill)
                if compact:
                    _fill_guarded(tmp, lambda h5: compact_copy(first, h5, contiguous=schema.CONTIGUOUS_FIELDS))
        except Exception as exc:
            if isinstance(exc, GestureDBError):
                raise
            disk = _is_disk_error(exc)
            if disk is not None:
                raise os_error(out_path, disk) from None
            if isinstance(exc, OSError) and type(exc).__module__.split(".")[0] in ("distributed", "tornado"):
                raise  # a lost Dask connection (CommClosedError), not this file: "cannot write" misled
            if isinstance(exc, OSError):
                other = _other_file(exc, out_path)
                if other is not None:
                    # an input that ``fill`` read (on a Dask worker, say) is not the output
                    raise InputFileError(other, f"{exc.strerror or exc} (while writing {out_path}, which is left "
                                                f"as it was)") from None
                raise os_error(out_path, exc) from None
            raise


def _fill_guarded(path: str, fill: Callable) -> None:
    """Create the HDF5 file ``path`` (creation order tracked) through a :class:`_GuardedFile` and ``fill`` it."""
    import h5py

    with _GuardedFile(path) as guard:
        h5 = h5py.File(guard, "w", track_order=True)
        try:
            fill(h5)
        except BaseException as exc:
            # a refused write is the cause of what failed after it; an interruption stays one
            guard.close_h5(h5, check=isinstance(exc, Exception))
            raise
        guard.close_h5(h5)


def _other_file(exc: OSError, out_path: str) -> str | None:
    """The file an OSError names when it is neither ``out_path`` nor one of its temporaries."""
    name = exc.filename
    if name is None or isinstance(name, int):
        return None
    name = os.fsdecode(name)
    return None if os.path.abspath(name) == os.path.abspath(out_path) or is_temporary_of(name, out_path) else name


def compact_copy(src_path: str, dst, *, contiguous=()) -> None:
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
    contiguous : collection of str
        Dataset paths (``schema.CONTIGUOUS_FIELDS``) stored contiguous in the copy when they
        are chunked without filters (a build's growable per-frame arrays, a file written
        before): the same values and attributes, laid out so that a reader can memory-map
        them. Virtual datasets (an index file's) and filtered ones are copied as they are.
    """
    import h5py

    if isinstance(dst, (str, os.PathLike)):
        with h5py.File(dst, "w", track_order=True) as h5:
            compact_copy(src_path, h5, contiguous=contiguous)
        return
    groups = {p.split("/")[0] for p in contiguous if "/" in p}
    with h5py.File(src_path, "r") as src:
        for k, v in src.attrs.items():
            dst.attrs[k] = v
        for name in src:
            link = src.get(name, getlink=True)
            if isinstance(link, (h5py.SoftLink, h5py.ExternalLink)):
                dst[name] = link  # a link stays a link (H5Ocopy would copy what it points at)
            elif name in groups and isinstance(src[name], h5py.Group) and any(
                    _to_contiguous(src[f"{name}/{m}"]) for m in src[name] if f"{name}/{m}" in contiguous):
                _copy_group(src[name], dst, name, contiguous)
            else:
                src.copy(src[name], dst, name)


def _to_contiguous(ds) -> bool:
    """Whether ``ds`` is a dataset :func:`compact_copy` rewrites contiguous: chunked, unfiltered, in its file."""
    import h5py

    return (isinstance(ds, h5py.Dataset) and ds.chunks is not None and not ds.is_virtual and not ds.external
            and ds.id.get_create_plist().get_nfilters() == 0)


#: bytes of rows copied at a time into a contiguous dataset (bounds the memory of a copy)
COPY_BYTES = 1 << 26


def _copy_group(group, dst, name: str, contiguous) -> None:
    """Copy the top-level ``group`` as ``dst[name]``, its members of ``contiguous`` stored contiguous."""
    import h5py

    # the group's own creation properties (link order tracking), as H5Ocopy keeps them
    h5py.h5g.create(dst.id, name.encode(), gcpl=group.id.get_create_plist())
    out = dst[name]
    _copy_attrs(group, out)
    for m in group:
        link = group.get(m, getlink=True)
        ds = group[m] if not isinstance(link, (h5py.SoftLink, h5py.ExternalLink)) else None
        if ds is None:
            out[m] = link
        elif f"{name}/{m}" in contiguous and _to_contiguous(ds):
            new = out.create_dataset(m, shape=ds.shape, dtype=ds.dtype)
            _copy_attrs(ds, new)
            row_bytes = max(1, ds.dtype.itemsize * int(np.prod(ds.shape[1:], dtype=np.int64)))
            step = max(1, COPY_BYTES // row_bytes)
            for a in range(0, ds.shape[0], step):
                new[a:a + step] = ds[a:a + step]
        else:
            group.copy(ds, out, m)


def _copy_attrs(src, dst) -> None:
    """Every attribute of ``src`` onto ``dst`` with its stored type (a fixed-length string stays one)."""
    for k in src.attrs:
        dst.attrs.create(k, src.attrs[k], dtype=src.attrs.get_id(k).dtype)


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
    with locked(path):
        remove_stale_temporaries(path)
        try:
            # the database's own permissions, not mkstemp's 0600
            with replacing(path, mode_of=path) as tmp:
                with h5py.File(path, "r") as h5:  # before the copy: a file of another version is refused as it is
                    schema.check_version(h5, shown, upgradable=upgrade)
                # the copy and the edit are one session of HDF5 on a guarded file (see _GuardedFile):
                # a full disk is one error, not a failed close inside HDF5
                with _GuardedFile(tmp) as guard:
                    h5 = h5py.File(guard, "w", track_order=True)
                    try:
                        try:
                            # per-frame arrays stored contiguous: a file written before gets them on its next edit
                            compact_copy(path, h5, contiguous=schema.CONTIGUOUS_FIELDS)
                            guard.check()
                        except OSError as exc:
                            raise os_error(shown, _is_disk_error(exc) or exc) from None
                        yield h5
                    except BaseException as exc:
                        guard.close_h5(h5, check=isinstance(exc, Exception))
                        raise
                    guard.close_h5(h5)
        except Exception as exc:
            disk = _is_disk_error(exc)
            if disk is not None and not isinstance(exc, GestureDBError):
                raise os_error(shown, disk) from None
            raise
