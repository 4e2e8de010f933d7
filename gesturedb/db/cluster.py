"""Dask for the build and the search: tasks on a cluster, the client the only writer.

``scheduler`` is ``"local:N"`` (a :class:`distributed.LocalCluster` of N
single-threaded worker processes, started and shut down here: :func:`local_cluster`),
``"tcp://HOST:PORT"`` (an existing scheduler), or a ``distributed.Client``
the caller owns. Workers only compute: in a build each returns the
:class:`gesturedb.db.build.RecordingData` of one recording, then the edges of a
range of the motion graphs' rows, to the client, which writes the HDF5 file
through :mod:`gesturedb.db.storage` as a local build does. A failed task raises
on the client before anything is written.
"""
from __future__ import annotations

import contextlib
import re
from collections.abc import Callable, Iterator, Sequence

from gesturedb.errors import ParameterError

__all__ = ["dask_client", "iter_on_cluster", "local_cluster", "optional_client", "worker_address"]

_LOCAL = re.compile(r"^local:(\d+)$")


@contextlib.contextmanager
def dask_client(scheduler) -> Iterator[object]:
    """A ``distributed.Client`` for ``scheduler``; clusters started here are shut down on exit."""
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - an install without the dependency
        raise ParameterError(
            "scheduler: expected dask[distributed] to be installed (pip install 'dask[distributed]')") from None
    if isinstance(scheduler, Client):
        yield scheduler
        return
    if not isinstance(scheduler, str):
        raise ParameterError(f"scheduler: expected 'local:N', 'tcp://HOST:PORT' or a distributed.Client; got {scheduler!r}")
    m = _LOCAL.match(scheduler)
    if m:
        n = int(m.group(1))
        if n < 1:
            raise ParameterError(f"scheduler: expected local:N with N >= 1 workers; got {scheduler!r}")
        with local_cluster(n) as cluster, Client(cluster) as client:
            yield client
        return
    if not scheduler.startswith("tcp://"):
        raise ParameterError(f"scheduler: expected 'local:N' or 'tcp://HOST:PORT'; got {scheduler!r}")
    try:
        client = Client(scheduler, timeout="10s")
    except OSError as exc:
        raise ParameterError(f"scheduler: expected a reachable Dask scheduler at {scheduler}; got {exc}") from None
    with client:
        yield client


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


def iter_on_cluster(fn: Callable, items: Sequence, scheduler) -> Iterator[tuple[int, object]]:
    """``(i, fn(items[i]))`` as each Dask task finishes, for callers that store each
    result as it comes rather than holding them all (the build's recordings, the refiner's
    training windows).

    The first failed task's exception is raised after the others were cancelled.
    """
    from distributed import as_completed

    with dask_client(scheduler) as client:
        # pure=False: every item is computed even if two compare equal
        futures = client.map(fn, list(items), pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in as_completed(futures):
                yield index[fut.key], fut.result()  # re-raises the task's exception
                fut.release()
        except BaseException:
            client.cancel(futures)
            raise


def worker_address() -> str:
    """The address of the Dask worker running the calling task, for messages about what that
    worker sees (its own files, on its own machine); ``"(not a worker)"`` outside one."""
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):  # ValueError: no worker runs this code
        return "(not a worker)"
