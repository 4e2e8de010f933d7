"""Local worker processes (the build's ``-j``, the refiner's training-data assembly).

Each worker runs one BLAS/OpenMP thread and dies with the process that started it.
"""
from __future__ import annotations

import os

__all__ = ["exit_with_parent", "single_threaded_worker"]


def single_threaded_worker(parent_pid: int | None = None) -> None:
    """Worker-process initializer: one BLAS/OpenMP thread per process.

    Parallelism comes from the processes; letting each one's BLAS also use
    every core oversubscribes the machine (measured: each worker ran 2x slower
    and two workers gained nothing).
    """
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    exit_with_parent(parent_pid)


def exit_with_parent(parent: int | None = None) -> None:
    """Make this worker die when the process that started it dies (even by SIGKILL), not linger for minutes.

    Linux: prctl(PR_SET_PDEATHSIG, SIGKILL). Elsewhere (or if prctl is unavailable) a
    daemon thread polls the parent pid once a second.
    """
    import signal
    import sys
    import threading

    # the pid is taken in the parent before the fork: read here, a parent killed during the fork
    # would already have been replaced by the reaper and the check below would pass
    parent = os.getppid() if parent is None else parent
    if os.getppid() != parent:
        os._exit(1)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            PR_SET_PDEATHSIG = 1
            if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
                if os.getppid() != parent:  # the parent died before prctl took effect
                    os._exit(1)
                return
        except (OSError, AttributeError):
            pass

    def watch():
        import time

        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="gesturedb-parent-watch", daemon=True).start()
