"""Shared fixtures: the real data lives outside the repository, in ../shared/data."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Commands the tests start (gesturedb, lint-imports) come from the environment running the tests
# (scripts/test.sh's .venv, or whichever python runs pytest), not from whatever is first on the PATH.
_BIN = os.path.dirname(sys.executable)
if os.environ.get("PATH", "").split(os.pathsep)[:1] != [_BIN]:
    os.environ["PATH"] = _BIN + os.pathsep + os.environ.get("PATH", "")


def _data_dir() -> Path:
    env = os.environ.get("GESTUREDB_DATA")
    return Path(env) if env else (ROOT.parent / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    d = _data_dir()
    if not d.is_dir():
        pytest.fail(f"real data not found at {d}: set GESTUREDB_DATA")
    return d


@pytest.fixture(scope="session")
def scott_dir(data_dir) -> Path:
    return data_dir / "beat2-scott"


@pytest.fixture(scope="session")
def scott_db_path(scott_dir, tmp_path_factory) -> Path:
    """A database built once per test session from the real BEAT2 recording (no mirroring)."""
    import gesturedb

    out = tmp_path_factory.mktemp("db") / "scott.h5"
    gesturedb.build([scott_dir], out).close()
    return out


@pytest.fixture()
def scott_db(scott_db_path):
    import gesturedb

    with gesturedb.open(scott_db_path) as db:
        yield db


@pytest.fixture(scope="session")
def dask_client():
    """A LocalCluster of 2 single-threaded workers for the whole session
    (in-process threads: starts in about a second and shuts down cleanly)."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        yield client


@pytest.fixture(scope="module")
def hand_started_workers(tmp_path_factory):
    """A `dask scheduler` and two `dask worker` processes started from the command line, in a
    folder of their own and a session of their own, as on machines one sets up by hand: yields
    (scheduler address, a Client that only watches). Their working folder is not the tests', so
    a relative path sent to them fails. One set per test module: none of it runs in pytest's
    process, and none outlives the tests that use it."""
    import subprocess

    from daskprocs import QUIET, kill_groups, start_scheduler, worker_command

    distributed = pytest.importorskip("distributed")
    elsewhere = tmp_path_factory.mktemp("worker-cwd")
    scheduler, address = start_scheduler(elsewhere, "127.0.0.1")
    procs = [scheduler]
    try:
        procs += [subprocess.Popen(worker_command(address), cwd=elsewhere, **QUIET) for _ in range(2)]
        with distributed.Client(address, timeout="60s") as watch:
            watch.wait_for_workers(2, timeout=180)
            yield address, watch
    finally:
        kill_groups(procs)
