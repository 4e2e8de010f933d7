"""``gesturedb serve --workers N``: one server in N processes, each serving its share of the clients.

A stream's apply step (the window, the seams, the feet) is Python and holds the interpreter's
lock, about 10 ms a step at paper scale; one process applies one step at a time whatever the
CPUs. With N processes, N steps are applied at once. The processes are forked after the app
is made and warmed (the database open, its pose projection and the stream's set-up built), so
they start at once and share all of that: the per-frame arrays are memory maps of the same
file (one copy in the page cache) and the rest is shared copy-on-write.

Each process listens on its own socket bound to the same address with ``SO_REUSEPORT``, so the
kernel spreads the connections over the processes (by a hash of each connection's addresses).
What a process knows is its own: ``/health``'s ``streams`` and ``batch`` count its streams, and
``--max-streams`` bounds each process. Steps are batched within a process, so with many
workers a batch is smaller (each pays the search's pass over the database): more workers than
CPUs only adds passes. The default is one worker; ``auto`` takes the CPUs this process may use
(:func:`gesturedb.threads.available_cpus`: affinity and cgroup quota).

Stopping: SIGINT or SIGTERM to the first process stops it and then the others; each other
process also stops when the first one dies (``PR_SET_PDEATHSIG``), so none outlives it.
"""
from __future__ import annotations

import ctypes
import gc
import logging
import os
import signal
import socket

from gesturedb.errors import ParameterError
from gesturedb.threads import available_cpus

log = logging.getLogger("gesturedb.serve")

__all__ = ["resolve_workers", "listen", "serve"]

#: Linux prctl option: the signal a process gets when its parent dies
_PR_SET_PDEATHSIG = 1


def resolve_workers(workers) -> int:
    """``workers`` as a count: an int >= 1, or ``"auto"`` for :func:`gesturedb.threads.available_cpus`."""
    if workers == "auto":
        return available_cpus()
    try:
        n = int(workers)
    except (TypeError, ValueError):
        n = 0
    if isinstance(workers, bool) or n < 1 or str(workers).strip() != str(n):
        raise ParameterError(f"workers: expected a count >= 1 or 'auto'; got {workers!r}")
    return n


def listen(host: str, port: int, *, reuse_port: bool) -> socket.socket:
    """A listening TCP socket on ``(host, port)``; ``reuse_port``: others may bind the same (SO_REUSEPORT)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if reuse_port:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind((host, port))
        sock.listen(2048)
        sock.set_inheritable(True)
    except OSError:
        sock.close()
        raise
    return sock


def _die_with_parent() -> None:
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass  # not Linux: the first process still stops the others when it stops cleanly


def serve(app, host: str, port: int, workers: int, **uvicorn_kwargs) -> None:
    """Serve ``app`` on ``(host, port)`` from ``workers`` processes (this one and ``workers - 1`` forks);
    returns when this process's server stops, after stopping the others."""
    import uvicorn

    if workers < 1:
        raise ParameterError(f"workers: expected >= 1; got {workers}")
    if workers > 1 and not hasattr(socket, "SO_REUSEPORT"):
        raise ParameterError("workers: more than one needs SO_REUSEPORT (Linux, macOS, the BSDs)")
    try:
        first = listen(host, port, reuse_port=workers > 1)
    except OSError as exc:
        raise ParameterError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    port = first.getsockname()[1]  # port 0: the one the system chose, which the others bind too
    # what the app has made so far (the modules, the database, the warm-up: about 170,000 objects) lasts as
    # long as the server: out of the collector's reach, a full collection (it comes once enough objects have
    # outlived the younger ones': sessions that start and end, uploads) takes under a millisecond instead of
    # the 75-80 ms that every stream would wait for, and forked workers do not copy those pages by touching them
    gc.collect()
    gc.freeze()
    children = []
    for i in range(1, workers):
        pid = os.fork()
        if pid == 0:  # a worker: its own socket on the same address, its own event loop
            code = 0
            try:
                first.close()
                _die_with_parent()
                sock = listen(host, port, reuse_port=True)
                uvicorn.Server(uvicorn.Config(app, **uvicorn_kwargs)).run(sockets=[sock])
            except BaseException:  # noqa: BLE001 - a forked child must never return into the parent's code
                log.exception("worker %d failed", i)
                code = 1
            finally:
                os._exit(code)
        children.append(pid)
    try:
        uvicorn.Server(uvicorn.Config(app, **uvicorn_kwargs)).run(sockets=[first])
    finally:
        for pid in children:
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for pid in children:
            try:
                os.waitpid(pid, 0)
            except ChildProcessError:
                pass
        first.close()
