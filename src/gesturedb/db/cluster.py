"""Dask for the build and the search: tasks on a cluster, the client the only writer.

The one module of gesturedb that uses Dask (``tests/test_architecture.py`` keeps it so):
the build's recordings, the motion graphs' edge blocks and the refiner's windows run
through :func:`iter_on_cluster`; the sharded search (:mod:`gesturedb.db.shards`) places
its shards and their actors through :func:`place` and :func:`place_actor`. Every caller
names the cluster the same way, ``scheduler``: ``"local:N"`` (a :class:`distributed.LocalCluster` of N
single-threaded worker processes, started and shut down here: :func:`local_cluster`),
``"tcp://HOST:PORT"`` (an existing scheduler), or a ``distributed.Client``
the caller owns. Workers only compute: in a build each returns the
:class:`gesturedb.db.build.RecordingData` of one recording, then the edges of a
range of the motion graphs' rows, to the client, which writes the HDF5 file
through :mod:`gesturedb.db.storage` as a local build does. A failed task raises
on the client before anything is written.

Nothing waits forever and nothing surfaces as Dask's own traceback: :func:`completed` (the
one wait loop of every caller) gives up after :data:`NO_WORKER_TIMEOUT_S` seconds without a
single worker (a lost worker's tasks otherwise wait for a new one forever), and a lost
scheduler, a task that killed its workers or any other Dask failure becomes one
:class:`~gesturedb.errors.GestureDBError` line naming the scheduler (:func:`dask_client`).
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import re
from collections.abc import Callable, Iterator, Sequence

from gesturedb.errors import GestureDBError, InputFileError, ParameterError

__all__ = ["cancel", "check_on_worker", "check_scheduler", "check_workers_code", "code_identity", "completed",
           "dask_client", "iter_on_cluster", "live_workers", "local_cluster", "optional_client", "place", "place_actor",
           "this_worker_threads", "worker_address", "worker_addresses", "worker_threads"]

_LOCAL = re.compile(r"^local:(\d+)$")
#: the most worker processes ``local:N`` starts on this machine (as ``build -j``)
MAX_LOCAL_WORKERS = 256
#: the default of :func:`iter_on_cluster`'s ``shared``: no object shared by the tasks
_NOTHING = object()
#: seconds the tasks may wait without any worker before the work stops with an error (a worker
#: that its nanny restarts is back within seconds; a lost one's tasks would wait forever)
NO_WORKER_TIMEOUT_S = 30.0


class ClusterError(GestureDBError):
    """The Dask cluster failed under the work: scheduler lost, no worker left, a task killed its workers."""


def _address(client) -> str:
    return str(getattr(getattr(client, "scheduler", None), "address", None) or "(unknown address)")


def _first_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return f"{type(exc).__name__}: {lines[0][:200]}" if lines else type(exc).__name__


def _from_dask(exc: BaseException) -> bool:
    """Raised by Dask itself (a lost connection, a cancelled future), not by a task's own code."""
    from concurrent.futures import CancelledError

    return isinstance(exc, CancelledError) or type(exc).__module__.split(".")[0] in ("distributed", "tornado")


def completed(client, futures, *, what: str = "the tasks") -> Iterator[object]:
    """Each of ``futures`` as it finishes (``distributed.as_completed``), without waiting forever.

    Raises :class:`ClusterError` (one line naming the scheduler and ``what``) when the
    scheduler has had no worker for :data:`NO_WORKER_TIMEOUT_S` seconds, when the connection
    to the scheduler is lost (its futures are then cancelled), or when a task killed every
    worker that ran it (``KilledWorker``). A task's own exception is left to ``fut.result()``.
    """
    import time

    from distributed import as_completed

    ac = as_completed(futures)
    alone_since = None
    next_check = time.monotonic() + 1.0
    while not ac.is_empty():
        if ac.has_ready():
            fut = next(ac)
            if fut.status == "cancelled":
                raise ClusterError(f"scheduler {_address(client)}: lost the connection to the Dask scheduler while "
                                   f"{what} ran; stopped")
            if fut.status == "error":
                exc = fut.exception()
                if type(exc).__name__ == "KilledWorker":
                    raise ClusterError(f"scheduler {_address(client)}: a task of {what} was running on every worker "
                                       f"that died ({_first_line(exc)}); stopped")
            yield fut
            continue
        now = time.monotonic()
        if now >= next_check:
            next_check = now + 1.0
            try:
                n = len(client.scheduler_info(n_workers=-1)["workers"])
            except Exception as exc:  # noqa: BLE001 - the scheduler is gone or unreachable
                raise ClusterError(f"scheduler {_address(client)}: lost the connection to the Dask scheduler while "
                                   f"{what} ran ({_first_line(exc)}); stopped") from None
            alone_since = None if n else (alone_since or now)
            if alone_since is not None and now - alone_since > NO_WORKER_TIMEOUT_S:
                raise ClusterError(f"scheduler {_address(client)}: no Dask worker for {NO_WORKER_TIMEOUT_S:g} s while "
                                   f"{ac.count()} task(s) of {what} waited (every worker was lost, or none joined); "
                                   f"stopped")
        with ac.thread_condition:
            ac.thread_condition.wait(timeout=0.1)


@contextlib.contextmanager
def dask_client(scheduler) -> Iterator[object]:
    """A ``distributed.Client`` for ``scheduler``; clusters started here are shut down on exit."""
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - an install without the dependency
        raise ParameterError(
            "scheduler: expected dask[distributed] to be installed (pip install 'dask[distributed]')") from None
    if isinstance(scheduler, Client):
        with _one_line_failures(scheduler):
            check_workers_code(scheduler)
            yield scheduler
        return
    n = check_scheduler(scheduler)
    if n is not None:
        with local_cluster(n) as cluster, Client(cluster) as client, _one_line_failures(client):
            yield client
        return
    try:
        client = Client(scheduler, timeout="10s")
    except OSError as exc:
        raise ParameterError(f"scheduler: expected a reachable Dask scheduler at {scheduler}; got {exc}") from None
    with _quiet_close(client), _one_line_failures(client):
        check_workers_code(client)
        yield client


def check_scheduler(scheduler) -> int | None:
    """Check a ``--scheduler`` text before any work: the N of ``"local:N"`` (1 to
    :data:`MAX_LOCAL_WORKERS`), or None for ``"tcp://HOST:PORT"``; anything else is a
    :class:`ParameterError`."""
    if not isinstance(scheduler, str):
        raise ParameterError(f"scheduler: expected 'local:N', 'tcp://HOST:PORT' or a distributed.Client; got {scheduler!r}")
    m = _LOCAL.match(scheduler)
    if m:
        n = int(m.group(1)) if len(m.group(1)) < 10 else MAX_LOCAL_WORKERS + 1
        if not 1 <= n <= MAX_LOCAL_WORKERS:
            raise ParameterError(f"scheduler: expected local:N with N from 1 to {MAX_LOCAL_WORKERS} workers; got "
                                 f"{scheduler[:40]!r}")
        return n
    if not scheduler.startswith("tcp://"):
        raise ParameterError(f"scheduler: expected 'local:N' or 'tcp://HOST:PORT'; got {scheduler[:80]!r}")
    return None


@contextlib.contextmanager
def _one_line_failures(client) -> Iterator[None]:
    """Dask's own exceptions escaping the work (a lost connection while sending data, a cancelled
    future, ``KilledWorker``) as one :class:`ClusterError` line naming the scheduler."""
    try:
        yield
    except Exception as exc:
        if isinstance(exc, GestureDBError) or not _from_dask(exc):
            raise
        raise ClusterError(f"scheduler {_address(client)}: the Dask cluster failed under the work "
                           f"({_first_line(exc)}); stopped") from None


@contextlib.contextmanager
def _quiet_close(client) -> Iterator[None]:
    """Close ``client`` on exit; once its scheduler is gone, without Dask's log of the failed
    reconnection (tracebacks after a one-line error, or after work that was already done)."""
    import logging

    try:
        yield
    finally:
        quiet = client.status not in ("running", "newly-created")
        loggers = [logging.getLogger(n) for n in ("distributed.client", "distributed.batched", "distributed.core")]
        levels = [lg.level for lg in loggers]
        if quiet:
            for lg in loggers:
                lg.setLevel(logging.CRITICAL)
        try:
            client.close(timeout=10)
        except Exception:  # noqa: BLE001 - the scheduler is gone: nothing left to close there
            pass
        finally:
            for lg, lv in zip(loggers, levels):
                lg.setLevel(lv)


@contextlib.contextmanager
def optional_client(scheduler) -> Iterator[object]:
    """:func:`dask_client` for ``scheduler``, or None when it is None (no Dask: the caller runs
    locally). For callers that take an optional ``--scheduler`` and open it once for all their
    tasks."""
    if scheduler is None:
        yield None
        return
    with dask_client(scheduler) as client:
        yield client


@contextlib.contextmanager
def local_cluster(n_workers: int, **kwargs) -> Iterator[object]:
    """A ``distributed.LocalCluster`` of ``n_workers`` single-threaded worker processes (``kwargs``:
    more LocalCluster options), shut down on exit.

    Dask starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which also turns off glibc's
    adaptive mmap threshold: every temporary array over 128 kB is then a fresh mmap, and the
    motion graphs' blocks ran 1.7x slower (5.3 s against 3.1 s for 20,000 clips on one thread,
    same result). The workers started here keep glibc's defaults.
    """
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}), \
            LocalCluster(n_workers=n_workers, **{"threads_per_worker": 1, "processes": True,
                                                 "dashboard_address": None, **kwargs}) as cluster:
        yield cluster


def iter_on_cluster(fn: Callable, items: Sequence, scheduler, *, what: str = "the tasks",
                    shared: object = _NOTHING) -> Iterator[tuple[int, object]]:
    """``(i, fn(items[i]))`` as each Dask task finishes, for callers that store each
    result as it comes rather than holding them all (the build's recordings, the refiner's
    training windows, the motion graphs' blocks of rows).

    ``shared``: an object every task needs (the motion graphs' features), sent once to
    every worker (``scatter``, broadcast) instead of with each task; the tasks are then
    ``fn(shared, items[i])``.

    The first failed task's exception is raised after the others were cancelled; a cluster
    that fails under the tasks is a :class:`ClusterError` (see :func:`completed`, where
    ``what`` names the tasks).
    """
    with dask_client(scheduler) as client:
        data = None if shared is _NOTHING else client.scatter([shared], broadcast=True, hash=False)[0]
        # pure=False: every item is computed even if two compare equal
        futures = (client.map(fn, list(items), pure=False) if data is None
                   else [client.submit(fn, data, item, pure=False) for item in items])
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in completed(client, futures, what=what):
                yield index[fut.key], fut.result()  # re-raises the task's exception
                fut.release()
        except BaseException:
            with contextlib.suppress(Exception):  # a lost scheduler has nothing left to cancel
                client.cancel(futures)
            raise
        finally:
            if data is not None:
                with contextlib.suppress(Exception):
                    client.cancel([data])


def worker_threads(scheduler) -> int:
    """The threads of all the workers of ``scheduler`` (a client, ``"local:N"`` or an address) now."""
    with dask_client(scheduler) as client:
        return max(1, sum(client.nthreads().values()))


# -- objects kept on chosen workers (the sharded search: gesturedb.db.shards) ------------------

def worker_addresses(client) -> list[str]:
    """The addresses of the workers the client knows of, sorted."""
    return sorted(client.scheduler_info()["workers"])


def live_workers(client) -> set[str]:
    """The scheduler's workers now (the client's own view lags behind by seconds)."""
    return set(client.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.workers)))


def place(client, fn: Callable, *args, worker: str | None = None, send: Sequence = ()):
    """A future of ``fn(*send, *args)`` computed on ``worker`` (an address; None: where Dask likes)
    and kept there. The arrays of ``send`` go to that worker first, each under a key of its own
    (two equal arrays are two objects: a key made from the content made the second copy the
    first's, which the first one's release could take away)."""
    w = None if worker is None else [worker]
    sent = [client.scatter(x, workers=w, hash=False) for x in send]
    return client.submit(fn, *sent, *args, workers=w, pure=False)


def place_actor(client, cls: type, *args, worker: str | None = None):
    """A future of a Dask actor ``cls(*args)`` on ``worker``: its methods are called straight from the
    client to that worker (no round trip through the scheduler), one call at a time."""
    return client.submit(cls, *args, actor=True, pure=False, workers=None if worker is None else [worker])


def cancel(client, futures: Sequence) -> None:
    """Release ``futures`` (and what they hold on the workers)."""
    client.cancel(list(futures))


def this_worker_threads() -> int:
    """The threads of the Dask worker running the caller (an actor's constructor, a task)."""
    from distributed import get_worker

    return get_worker().state.nthreads


def worker_address() -> str:
    """The address of the Dask worker running the calling task, for messages about what that
    worker sees (its own files, on its own machine); ``"(not a worker)"`` outside one."""
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):  # ValueError: no worker runs this code
        return "(not a worker)"


def check_on_worker(path: str, what: str) -> None:
    """Raise :class:`InputFileError` unless ``path`` is a file on the machine of the Dask worker
    running the calling task; ``what`` names the files that must be shared (e.g. "the input
    files")."""
    if not os.path.isfile(path):
        raise InputFileError(path, f"not found on Dask worker {worker_address()}: every worker must see {what} "
                                   f"at the same paths as the client (a shared or copied folder)")


def code_identity() -> str:
    """A short hash of this process's gesturedb Python sources (their paths and bytes; about
    3 ms, once per process). Two installations with the same hash run the same code.

    A plain function (the cache is :func:`_source_hash`'s): it is what the workers and the
    scheduler are asked to run, by name."""
    return _source_hash()


@functools.lru_cache(maxsize=1)
def _source_hash() -> str:
    return tree_hash(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def tree_hash(package: str) -> str:
    """The hash of :func:`code_identity` over the ``.py`` files under the folder ``package``
    (gesturedb, its CLI included), each file by its path inside the package: an editable
    install and a wheel of the same sources hash alike."""
    h = hashlib.sha256()
    for folder, dirs, files in os.walk(package):
        dirs.sort()
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            h.update(os.path.relpath(path, package).encode())
            with open(path, "rb") as f:
                h.update(f.read())
    return h.hexdigest()[:16]


def check_workers_code(client) -> None:
    """Raise :class:`ParameterError` unless every worker of ``client``, and its scheduler, run the
    gesturedb code this process runs (:func:`code_identity`).

    Workers set up by hand on other machines may carry another installation: an older one fails
    on a task with a traceback from inside Dask, a changed one computes other features without a
    word, and the database would then depend on which worker took which recording. Workers that
    join later are not checked. (The LocalClusters started here run this installation.)
    """
    mine = code_identity()
    try:
        theirs = client.run(code_identity)
        # the scheduler unpickles the tasks too: an older gesturedb there failed every build
        theirs[f"{client.scheduler.address} (the scheduler)"] = client.run_on_scheduler(code_identity)
    except Exception as exc:  # noqa: BLE001 - e.g. a worker without gesturedb, or an older one
        raise ParameterError(f"scheduler: expected every worker to run this gesturedb (code {mine}); a worker "
                             f"could not check its own ({type(exc).__name__}: {exc})") from None
    other = sorted(a for a, h in theirs.items() if h != mine)
    if other:
        raise ParameterError(f"scheduler: expected every worker to run this gesturedb (code {mine}); got other "
                             f"code on {len(other)} of {len(theirs) - 1} worker(s) and the scheduler, first "
                             f"{other[0]} (code {theirs[other[0]]}). Install the same gesturedb on every worker: "
                             f"results would otherwise depend on which worker ran a task")
