"""Dask processes started from the command line for the tests, as one starts them on machines
set up by hand: each in a session (process group) of its own, killed with it."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

DASK = os.path.join(os.path.dirname(sys.executable), "dask")
QUIET = dict(stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def start_scheduler(folder, host: str) -> tuple[subprocess.Popen, str]:
    """A `dask scheduler` on ``host`` (any free port) run in ``folder``: (process, its address)."""
    info = folder / "scheduler.json"
    proc = subprocess.Popen([DASK, "scheduler", "--host", host, "--port", "0", "--no-dashboard",
                             "--scheduler-file", str(info)], cwd=folder, **QUIET)
    for _ in range(600):
        if info.exists() and info.stat().st_size:
            break
        time.sleep(0.1)
    return proc, json.loads(info.read_text())["address"]


def worker_command(address: str, *options: str) -> list[str]:
    """The command line of a one-thread `dask worker` of the scheduler at ``address``."""
    return [DASK, "worker", address, "--nthreads", "1", "--no-dashboard", *options]


def kill_groups(procs) -> None:
    """SIGKILL each process's group (a worker's nanny and its worker process; a polite shutdown
    took 8 s per set), last started first, and reap them."""
    for p in procs[::-1]:
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    for p in procs:
        p.wait(timeout=60)
