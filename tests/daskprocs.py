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


def veth_pair(ns: str, veth_a: str, veth_b: str, a_addr: str, b_addr: str) -> None:
    """A network namespace ``ns`` (a second host) reached from this one over a veth pair:
    ``a_addr`` here on ``veth_a``, ``b_addr`` there on ``veth_b``, one /24. Needs root; raises
    ``subprocess.CalledProcessError`` (its stderr says why) where the machine cannot."""
    def run(*cmd):
        subprocess.run(cmd, check=True, capture_output=True, text=True)

    run("ip", "netns", "add", ns)
    run("ip", "link", "add", veth_a, "type", "veth", "peer", "name", veth_b)
    run("ip", "link", "set", veth_b, "netns", ns)
    run("ip", "addr", "add", f"{a_addr}/24", "dev", veth_a)
    run("ip", "link", "set", veth_a, "up")
    for cmd in (["ip", "addr", "add", f"{b_addr}/24", "dev", veth_b], ["ip", "link", "set", veth_b, "up"],
                ["ip", "link", "set", "lo", "up"]):
        run("ip", "netns", "exec", ns, *cmd)


def remove_veth(ns: str, veth_a: str) -> None:
    """Undo :func:`veth_pair` (whatever part of it was made)."""
    subprocess.run(["ip", "netns", "del", ns], capture_output=True)  # takes its end of the pair along
    subprocess.run(["ip", "link", "del", veth_a], capture_output=True)


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
