"""How many threads or worker processes to use when not told: the CPUs this process may run on.

``os.cpu_count()`` counts the machine's CPUs. A process started under ``taskset``, in a batch
scheduler's CPU set or in a container with a CPU quota may use fewer, and a pool sized by the
machine then runs several threads per CPU, each slowing the others. :func:`available_cpus` is
the count every default in gesturedb uses (the build's and the refiner's ``-j``, the refiner's
torch threads, the motion graph's edge threads); the C++ kernel's
``gesturedb._core.default_threads()`` applies the same rule (csrc/threads.cpp, which reads the
quota once per process: it runs on every search), and the tests check that the two agree.
"""
from __future__ import annotations

import os
import re

__all__ = ["CGROUP_ROOT", "available_cpus", "cgroup_cpu_limit"]

#: where the cgroup file system is mounted; in a container the cgroup namespace shows the
#: container's own cgroup here, so the quota read is the one that applies to this process
CGROUP_ROOT = "/sys/fs/cgroup"


def available_cpus(cgroup_root: str | os.PathLike = CGROUP_ROOT) -> int:
    """CPUs this process may use: those in its affinity mask, bounded by the cgroup CPU quota.

    Parameters
    ----------
    cgroup_root : path
        Where the cgroup file system is mounted (tests point it at fake files).

    Returns
    -------
    n : int, at least 1
        ``len(os.sched_getaffinity(0))`` (``os.cpu_count()`` where there is no affinity mask),
        no more than :func:`cgroup_cpu_limit` when there is a quota.
    """
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux: the machine's count is all that is known
        n = os.cpu_count() or 1
    quota = cgroup_cpu_limit(cgroup_root)
    if quota is not None:
        n = min(n, quota)
    return max(n, 1)


def cgroup_cpu_limit(root: str | os.PathLike = CGROUP_ROOT) -> int | None:
    """The CPU quota of the cgroup mounted at ``root`` in whole CPUs, rounded up; None when there is none.

    cgroup v2's ``cpu.max`` ("max 100000": no quota; "150000 100000": 1.5 CPUs, so 2) is read
    first, then cgroup v1's ``cpu/cpu.cfs_quota_us`` and ``cpu/cpu.cfs_period_us`` (a quota of
    -1: none). Missing or unreadable files, or numbers that do not parse, mean no quota.
    A quota of 1.5 periods still lets two threads run: rounding up keeps the second one rather
    than leaving half a CPU unused.
    """
    v2 = _tokens(os.path.join(root, "cpu.max"), 2)
    if v2 is not None:
        return None if v2[0] == b"max" else _quota_cpus(*v2)
    quota = _tokens(os.path.join(root, "cpu", "cpu.cfs_quota_us"), 1)
    period = _tokens(os.path.join(root, "cpu", "cpu.cfs_period_us"), 1)
    if quota is None or period is None:
        return None
    return _quota_cpus(quota[0], period[0])


def _tokens(path: str, n: int) -> list[bytes] | None:
    """The first ``n`` whitespace-separated words of a file, or None when it cannot be read or has fewer."""
    try:
        with open(path, "rb") as f:
            words = f.read(4096).split()
    except OSError:
        return None
    return words[:n] if len(words) >= n else None


def _quota_cpus(quota: bytes, period: bytes) -> int | None:
    # the same checks as csrc/threads.cpp, so Python and C++ agree on any file
    if not (re.fullmatch(rb"[0-9]{1,18}", quota) and re.fullmatch(rb"[0-9]{1,18}", period)):
        return None
    q, p = int(quota), int(period)
    if q <= 0 or p <= 0:
        return None
    return min(-(-q // p), 1 << 20)
