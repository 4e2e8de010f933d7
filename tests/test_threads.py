"""The default thread count: the CPUs this process may use (affinity mask, cgroup quota), the same in C++ and Python."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

from gesturedb import _core
from gesturedb.threads import available_cpus, cgroup_cpu_limit

needs_affinity = pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="no CPU affinity mask on this OS")


def _under_taskset(cpus: list[int]) -> list[int]:
    """(_core.default_threads(), available_cpus()) in a fresh interpreter pinned to ``cpus``."""
    taskset = shutil.which("taskset")
    if taskset is None:
        pytest.skip("taskset (util-linux) is not installed")
    code = ("from gesturedb import _core; from gesturedb.threads import available_cpus; "
            "print(_core.default_threads(), available_cpus())")
    res = subprocess.run([taskset, "-c", ",".join(map(str, cpus)), sys.executable, "-c", code],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    return [int(w) for w in res.stdout.split()]


@needs_affinity
def test_one_cpu_under_taskset_gives_one_thread_in_cpp_and_python():
    # the first CPU this process may use, not CPU 0: a container's CPU set need not hold 0
    cpu = min(os.sched_getaffinity(0))
    assert _under_taskset([cpu]) == [1, 1]


@needs_affinity
def test_two_cpus_under_taskset_give_two_threads_unless_a_quota_says_fewer():
    mine = sorted(os.sched_getaffinity(0))
    if len(mine) < 2:
        pytest.skip("this process may use one CPU only")
    want = min(2, cgroup_cpu_limit() or 2)
    assert _under_taskset(mine[:2]) == [want, want]


@needs_affinity
def test_cpp_and_python_agree_on_this_machine():
    n = available_cpus()
    assert _core.default_threads() == n
    quota = cgroup_cpu_limit()
    assert n == min(len(os.sched_getaffinity(0)), quota or n)


def _v2(root, text):
    (root / "cpu.max").write_text(text)


def _v1(root, quota, period="100000"):
    (root / "cpu").mkdir()
    (root / "cpu" / "cpu.cfs_quota_us").write_text(quota + "\n")
    (root / "cpu" / "cpu.cfs_period_us").write_text(period + "\n")


@pytest.mark.parametrize("files, want", [
    ({"v2": "150000 100000\n"}, 2),       # 1.5 CPUs: two threads may each run half the time
    ({"v2": "max 100000\n"}, None),
    ({"v2": "200000 100000\n"}, 2),
    ({"v2": "50000 100000\n"}, 1),        # under one CPU still gives one thread
    ({"v2": "400000 100000"}, 4),         # no trailing newline
    ({"v2": "max 100000", "v1": ("100000",)}, None),   # v2 is read first: its "max" wins
    ({"v1": ("-1",)}, None),
    ({"v1": ("250000",)}, 3),
    ({"v1": ("300000", "50000")}, 6),
    ({"v2": "100000\n", "v1": ("300000",)}, 3),         # a v2 file with one word is not read
    ({"v2": "abc 100000\n"}, None),
    ({"v2": "0 100000\n"}, None),
    ({"v2": "150000 0\n"}, None),
    ({"v2": "1.5 1\n"}, None),
    ({"v1": ("200000", "")}, None),
    ({}, None),
])
def test_cgroup_quota_from_fake_files_in_cpp_and_python(tmp_path, files, want):
    if "v2" in files:
        _v2(tmp_path, files["v2"])
    if "v1" in files:
        _v1(tmp_path, *files["v1"])
    assert cgroup_cpu_limit(tmp_path) == want
    assert _core.cgroup_cpu_limit(str(tmp_path)) == (want or 0)  # C++ says 0 for no quota


@needs_affinity
def test_a_quota_bounds_the_affinity_mask(tmp_path):
    _v2(tmp_path, "100000 100000\n")
    assert available_cpus(tmp_path) == 1
    _v2(tmp_path, "max 100000\n")
    assert available_cpus(tmp_path) == len(os.sched_getaffinity(0))
    _v2(tmp_path, f"{100000 * (len(os.sched_getaffinity(0)) + 5)} 100000\n")  # more than the mask: the mask
    assert available_cpus(tmp_path) == len(os.sched_getaffinity(0))
