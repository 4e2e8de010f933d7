"""Dask across two hosts, emulated on this one machine with Linux namespaces.

Host A runs the scheduler, one `dask worker` and the client (pytest). Host B is a `dask worker`
in a network namespace of its own, with its own address reached over a veth pair (as a second
machine on a LAN), and a mount namespace of its own: an empty private /tmp, so none of the
files this session writes (databases, shard files, pair lists) is visible there, and its own
copy of the real recordings at the same path (as a folder copied to it), and its own copy of
gesturedb, laid out as pip installs it. What the two share is the kernel and the virtualenv's
other packages.

This is what the hand-started workers of `test_build_cluster.py` cannot show: a worker that
does not see the client's files. Each test runs a command the way a user would on two
machines, first without the files on host B (a one-line error naming the file and host B's
worker), then with them copied there (the result of one machine, exactly).

Setting the namespaces up needs root and the `ip`, `unshare` and `nsenter` tools; without them
the tests are skipped with a warning that says so, never silently.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

import gesturedb
from daskprocs import QUIET, kill_groups, remove_veth, start_scheduler, veth_pair, worker_command
from gesturedb.cli.main import main

STEM = "2_scott_0_1_1"

# Host B: its own /dev/shm, where it keeps its copy of the recordings (bound over the data
# folder, at the same path) and its own gesturedb (installed as pip lays it out, first on its
# PYTHONPATH); then its own /tmp, over everything this session wrote; then the dask worker
# command given after the two folders, listening on its own address. The copies are read
# before /tmp is covered.
_HOST_B = r"""
set -e
data=$1; site=$2; shift 2
mount -t tmpfs gesturedb-host-b /dev/shm
cp -a "$data" /dev/shm/data
cp -a "$site" /dev/shm/site
mount --bind /dev/shm/data "$data"
mount -t tmpfs gesturedb-host-b-tmp /tmp
cd /
export PYTHONPATH=/dev/shm/site
exec "$@"
"""


def _installed_copy(dest) -> None:
    """gesturedb (the package this process imported, with its extension) as pip installs it,
    gesturedb.cli inside it, in ``dest``."""
    skip = shutil.ignore_patterns("__pycache__")
    shutil.copytree(os.path.dirname(gesturedb.__file__), dest / "gesturedb", ignore=skip)


def _run(*cmd, **kw):
    return subprocess.run(cmd, check=True, capture_output=True, text=True, **kw)


def _namespaces_missing() -> str | None:
    if sys.platform != "linux" or os.geteuid() != 0:
        return "needs root on Linux"
    missing = [t for t in ("ip", "unshare", "nsenter", "tar") if shutil.which(t) is None]
    if missing:
        return f"{', '.join(missing)} not installed"
    try:
        _run("unshare", "--net", "--mount", "true")
    except subprocess.CalledProcessError as exc:
        return f"unshare --net --mount failed: {exc.stderr.strip()}"
    return None


class TwoHosts:
    """The running set: ``address`` of the scheduler, ``watch`` (a Client), host B's address."""

    def __init__(self, address, watch, b_address, b_pid):
        self.address, self.watch, self.b_address, self._b_pid = address, watch, b_address, b_pid

    def copy_to_b(self, folder) -> None:
        """Copy ``folder`` to the same path on host B (tar through its mount namespace)."""
        folder = os.fspath(folder)
        pack = subprocess.Popen(["tar", "-C", folder, "-cf", "-", "."], stdout=subprocess.PIPE)
        subprocess.run(["nsenter", "-t", str(self._b_pid), "-m", "--", "sh", "-c",
                        'mkdir -p "$1" && tar -C "$1" -xf -', "sh", folder], stdin=pack.stdout, check=True)
        pack.stdout.close()
        assert pack.wait() == 0

    def tasks_by_host(self, stream, prefix: str) -> dict:
        """How many tasks whose key starts with ``prefix`` ran on each host ("a", "b")."""
        hosts = {}
        for t in stream.data:
            if t["key"].startswith(prefix):
                h = "b" if t["worker"].startswith(f"tcp://{self.b_address}:") else "a"
                hosts[h] = hosts.get(h, 0) + 1
        return hosts


@pytest.fixture(scope="module")
def two_hosts(tmp_path_factory, scott_dir):
    distributed = pytest.importorskip("distributed")
    missing = _namespaces_missing()
    if missing:
        warnings.warn(f"two-host Dask tests NOT run: {missing}")
        pytest.skip(missing)
    pid = os.getpid()
    ns, veth_a, veth_b = f"gdb{pid}", f"gdb{pid}a", f"gdb{pid}b"
    # a /24 of its own per test process, so two test runs on one machine do not collide
    net = f"10.{100 + pid % 100}.{(pid // 100) % 250}"
    a_addr, b_addr = f"{net}.1", f"{net}.2"
    procs = []
    elsewhere = tmp_path_factory.mktemp("host-a-cwd")
    site = tmp_path_factory.mktemp("host-b-site")
    _installed_copy(site)
    b_log = tmp_path_factory.mktemp("host-b-log") / "worker.log"
    try:
        try:
            veth_pair(ns, veth_a, veth_b, a_addr, b_addr)
        except subprocess.CalledProcessError as exc:  # e.g. a container without veth devices
            reason = f"{' '.join(exc.cmd)} failed: {exc.stderr.strip()}"
            warnings.warn(f"two-host Dask tests NOT run: {reason}")
            pytest.skip(reason)
        scheduler, address = start_scheduler(elsewhere, a_addr)
        procs.append(scheduler)
        procs.append(subprocess.Popen(worker_command(address, "--host", a_addr, "--name", "host-a"), cwd=elsewhere,
                                      **QUIET))
        with open(b_log, "w") as log:
            b = subprocess.Popen(["ip", "netns", "exec", ns, "unshare", "--mount", "--propagation", "private",
                                  "bash", "-c", _HOST_B, "host-b", str(scott_dir.resolve()), str(site),
                                  *worker_command(address, "--host", b_addr, "--name", "host-b")],
                                 stdout=subprocess.DEVNULL, stderr=log, start_new_session=True)
        procs.append(b)
        with distributed.Client(address, timeout="60s") as watch:
            for _ in range(1800):
                if len(watch.scheduler_info()["workers"]) >= 2:
                    break
                if b.poll() is not None:  # host B could not be set up here (its mounts, say)
                    reason = f"host B's worker exited ({b.returncode}): {b_log.read_text().strip()[-500:]}"
                    warnings.warn(f"two-host Dask tests NOT run: {reason}")
                    pytest.skip(reason)
                time.sleep(0.1)
            watch.wait_for_workers(2, timeout=60)
            b_worker = next(w for w in watch.scheduler_info()["workers"] if w.startswith(f"tcp://{b_addr}:"))
            # host B runs its own copy of gesturedb: the code check must take it as the same code
            assert watch.run(lambda: gesturedb.__file__, workers=[b_worker]) == {
                b_worker: "/dev/shm/site/gesturedb/__init__.py"}
            yield TwoHosts(address, watch, b_addr, b.pid)
    finally:
        kill_groups(procs)
        remove_veth(ns, veth_a)


@pytest.fixture(scope="module")
def pairs(scott_dir, tmp_path_factory):
    """A pair list (on host A only) of the real take under 4 names, by absolute paths: the
    recordings are at those paths on both hosts."""
    src = scott_dir.resolve() / STEM
    path = tmp_path_factory.mktemp("pairs") / "pairs.csv"
    rows = [f"{src}.npz,{src}.wav,{src}.TextGrid,scott,take_{n}" for n in "abcd"]
    path.write_text("motion,audio,transcript,speaker,name\n" + "\n".join(rows) + "\n")
    return path


@pytest.fixture(scope="module")
def local_db(pairs, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "takes.h5"
    assert main(["build", "--pairs", str(pairs), "-o", str(out), "-q"]) == 0
    return out


def test_build_on_two_hosts_is_the_local_database(two_hosts, pairs, local_db, tmp_path):
    """Recordings processed on both hosts (B reads its own copy of them) and the motion graphs'
    edges on both: the database the local build writes, dataset by dataset."""
    import distributed

    from dbcontent import differing

    out = tmp_path / "takes.h5"
    with distributed.get_task_stream(two_hosts.watch) as stream:
        assert main(["build", "--pairs", str(pairs), "-o", str(out), "--scheduler", two_hosts.address, "-q"]) == 0
    assert differing(local_db, out) == []
    assert two_hosts.tasks_by_host(stream, "_process_on_worker").keys() == {"a", "b"}, stream.data


def test_synth_over_shards_needs_them_on_both_hosts(two_hosts, local_db, scott_dir, tmp_path, capsys):
    """Shard files on host A only: a one-line error naming host B's worker and the file it lacks,
    exit 2, nothing written. Copied to B: the BVH of the unsharded database, byte for byte, each
    host having read one shard file."""
    import distributed

    from gesturedb.db.shardfiles import shard_database

    folder = tmp_path / "shards"
    folder.mkdir()
    shutil.copyfile(local_db, folder / "takes.h5")
    rep = shard_database(str(folder / "takes.h5"), 2)
    speech = str(scott_dir / "inputs/2_scott_0_3_3.wav")
    local, remote = tmp_path / "local.bvh", tmp_path / "remote.bvh"
    assert main(["synth", str(local_db), "--audio", speech, "-o", str(local)]) == 0
    capsys.readouterr()
    assert main(["synth", rep.index, "--audio", speech, "-o", str(remote), "--scheduler", two_hosts.address]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"on Dask worker tcp://{two_hosts.b_address}:" in err, err
    assert ".2-of-2.h5 is missing" in err or ".1-of-2.h5 is missing" in err, err
    assert not remote.exists()

    two_hosts.copy_to_b(folder)
    with distributed.get_task_stream(two_hosts.watch) as stream:
        assert main(["synth", rep.index, "--audio", speech, "-o", str(remote), "--scheduler", two_hosts.address]) == 0
    assert remote.read_bytes() == local.read_bytes()
    assert two_hosts.tasks_by_host(stream, "_load_shard") == {"a": 1, "b": 1}, stream.data


def test_refiner_training_data_needs_the_database_on_both_hosts(two_hosts, scott_db_path, tmp_path, capsys):
    """`gesturedb refiner train --scheduler` with the database on host A only: a one-line error
    naming the database and host B's worker (not the cache file being written), exit 2, no
    cache left. Copied to B: the training data made in this process."""
    import distributed

    from gesturedb.refiner import data as D

    folder = tmp_path / "db"
    folder.mkdir()
    db_path = folder / "scott.h5"
    shutil.copyfile(scott_db_path, db_path)
    out = tmp_path / "r.pt"
    capsys.readouterr()
    assert main(["refiner", "train", str(db_path), "-o", str(out), "--iterations", "1", "--stride", "10",
                 "--scheduler", two_hosts.address]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress line
    assert err.startswith("gesturedb refiner: error: "), err
    assert f"{db_path}: not found on Dask worker tcp://{two_hosts.b_address}:" in err and "r.pt" not in err, err
    assert [n for n in os.listdir(tmp_path) if n != "db" and not n.endswith(".lock")] == []

    two_hosts.copy_to_b(folder)
    with gesturedb.open(db_path) as db:
        here = D.make_training_data(db, seed=2, stride=10)
        with distributed.Client(two_hosts.address) as client, \
                distributed.get_task_stream(two_hosts.watch) as stream:
            there = D.make_training_data(db, seed=2, stride=10, scheduler=client)
    idx = np.arange(here.n_windows)
    for name in ("frame_audio", "frame_real", "starts", "ks", "joints"):
        np.testing.assert_array_equal(getattr(there, name), getattr(here, name), err_msg=name)
    for name in ("audio", "real", "fake"):
        np.testing.assert_array_equal(getattr(there, name)(idx), getattr(here, name)(idx), err_msg=name)
    assert two_hosts.tasks_by_host(stream, "_assemble_task").keys() == {"a", "b"}, stream.data



def test_a_host_with_another_kernel_gives_the_same_synthesis(two_hosts, scott_dir, tmp_path):
    """Host B switched to the scalar kernel (as on a CPU without AVX2), host A on its widest: the
    sharded synthesis of a mirrored database is the single machine's, byte for byte. Before the
    kernels shared one summation order it differed in 7 of 8 runs (the exact audio tie between a
    recording and its mirror broke by the worker that held each shard)."""
    from gesturedb import search

    if search.get_simd() == "scalar":
        pytest.skip("this CPU has only the scalar kernel: nothing to mix")
    db = tmp_path / "mirrored.h5"
    gesturedb.build([scott_dir], db, mirror=True).close()
    b = next(w for w in two_hosts.watch.scheduler_info()["workers"] if w.startswith(f"tcp://{two_hosts.b_address}:"))
    [before] = two_hosts.watch.run(search.get_simd, workers=[b]).values()
    two_hosts.watch.run(search.set_simd, "scalar", workers=[b])
    try:
        for name in ("2_scott_0_2_2", "2_scott_0_3_3"):
            speech = str(scott_dir / f"inputs/{name}.wav")
            local, remote = tmp_path / f"{name}.local.bvh", tmp_path / f"{name}.remote.bvh"
            assert main(["synth", str(db), "--audio", speech, "-o", str(local)]) == 0
            assert main(["synth", str(db), "--audio", speech, "-o", str(remote), "--scheduler", two_hosts.address,
                         "--parts", "2"]) == 0
            assert remote.read_bytes() == local.read_bytes(), name
        kernels = two_hosts.watch.run(search.get_simd)
        assert kernels.pop(b) == "scalar" and list(kernels.values()) == [search.get_simd()], kernels
    finally:
        two_hosts.watch.run(search.set_simd, before, workers=[b])
