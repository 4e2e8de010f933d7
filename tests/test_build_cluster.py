"""Building on Dask: the same database as a local build, the client the only writer."""
from __future__ import annotations

import dataclasses
import os
import re

import pytest

import gesturedb
from gesturedb.errors import GestureDBError, ParameterError

try:  # tests/ is on sys.path when it is not a package, the repo root when it is
    from dbcontent import differing
except ModuleNotFoundError:  # pragma: no cover
    from tests.dbcontent import differing

STEM = "2_scott_0_1_1"


def _two_recordings(scott_dir, tmp_path):
    """Two recordings (links to the real one under two stems), so the cluster has two tasks."""
    src = tmp_path / "in"
    src.mkdir()
    for stem in ("a_scott", "b_scott"):
        for ext in (".npz", ".wav", ".TextGrid"):
            os.symlink(scott_dir / f"{STEM}{ext}", src / f"{stem}{ext}")
    return src


def test_cluster_build_is_identical_to_local_build(scott_dir, tmp_path, dask_client):
    src = _two_recordings(scott_dir, tmp_path)
    local = tmp_path / "local.h5"
    dist = tmp_path / "dask.h5"
    gesturedb.build([src], local, workers=2).close()
    with gesturedb.build([src], dist, scheduler=dask_client) as db:
        assert [r.name for r in db.recordings] == ["a_scott", "b_scott"]
    assert differing(local, dist) == []


def test_cli_build_with_relative_paths_on_workers_started_by_hand(scott_dir, tmp_path, monkeypatch,
                                                                  hand_started_workers):
    """`gesturedb build in -o db.h5 --scheduler tcp://HOST:PORT` from the input's folder, with
    workers running in a folder of their own: they get absolute paths (a relative one failed to
    open there), and the database stores the paths as given, as a local build does."""
    from gesturedb.cli.main import main

    address, _ = hand_started_workers
    _two_recordings(scott_dir, tmp_path)
    monkeypatch.chdir(tmp_path)
    assert main(["build", "in", "-o", "local.h5", "--no-graph", "-q"]) == 0
    assert main(["build", "in", "-o", "dask.h5", "--no-graph", "-q", "--scheduler", address]) == 0
    assert differing(tmp_path / "local.h5", tmp_path / "dask.h5") == []
    with gesturedb.open(tmp_path / "dask.h5") as db:
        assert db.h5["recordings/motion_path"].asstr()[0] == os.path.join("in", "a_scott.npz")


def test_a_file_the_worker_cannot_see_is_named_with_the_worker(scott_dir, tmp_path):
    from gesturedb.db.build import BuildConfig, RecordingSource, _process_on_worker
    from gesturedb.errors import InputFileError

    src = _two_recordings(scott_dir, tmp_path)
    ok = RecordingSource("a_scott", str(src / "a_scott.npz"), str(src / "a_scott.wav"), str(src / "a_scott.TextGrid"))
    assert _process_on_worker((ok, BuildConfig(gap_s=0.4), None))[0].n_frames > 0
    for field in ("motion", "audio", "transcript"):
        bad = dataclasses.replace(ok, **{field: str(tmp_path / f"elsewhere.{field}")})
        with pytest.raises(InputFileError) as err:
            _process_on_worker((bad, BuildConfig(gap_s=0.4), None))
        assert str(err.value) == (f"{tmp_path}/elsewhere.{field}: not found on Dask worker (not a worker): every "
                                  f"worker must see the input files at the same paths as the client (a shared or "
                                  f"copied folder)")


def test_failed_task_leaves_nothing_behind(scott_dir, tmp_path, dask_client):
    src = _two_recordings(scott_dir, tmp_path)
    os.remove(src / "b_scott.wav")
    (src / "b_scott.wav").write_bytes(b"RIFF\x00\x00\x00\x00WAVEjunk")  # unreadable audio
    out = tmp_path / "db.h5"
    out.write_bytes(b"previous")
    with pytest.raises(GestureDBError, match="b_scott.wav"):
        gesturedb.build([src], out, scheduler=dask_client)
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["db.h5", "in"]


def test_failed_graph_task_leaves_nothing_behind(scott_dir, tmp_path, dask_client, monkeypatch):
    """A motion-graph task that fails on a worker (this cluster's workers are threads of this
    process, so the patch reaches them): the build raises it, and the file is as before."""
    from gesturedb.db import edges as E

    def broken(self, r0, r1, *a):
        raise MemoryError(f"rows {r0}-{r1}")

    monkeypatch.setattr(E._Shared, "block", broken)
    out = tmp_path / "db.h5"
    out.write_bytes(b"previous")
    with pytest.raises(MemoryError, match="rows 0-"):
        gesturedb.build([scott_dir], out, scheduler=dask_client)
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["db.h5"]


def test_scheduler_validation(scott_dir, tmp_path):
    for bad, msg in (("local:0", "expected local:N with N from 1 to 256 workers; got 'local:0'"),
                     ("local:100000", "expected local:N with N from 1 to 256 workers; got 'local:100000'"),
                     ("http://x:1", "expected 'local:N' or 'tcp://HOST:PORT'"),
                     (3, "expected 'local:N', 'tcp://HOST:PORT' or a distributed.Client")):
        with pytest.raises(ParameterError, match=msg):
            gesturedb.build([scott_dir], tmp_path / "x.h5", scheduler=bad)
    assert not (tmp_path / "x.h5").exists()


def test_cli_build_with_a_local_cluster(scott_dir, tmp_path, capsys):
    """`gesturedb build --scheduler local:1`: a LocalCluster of worker processes, started and stopped."""
    from gesturedb.cli.main import main

    out = tmp_path / "cli.h5"
    assert main(["build", str(scott_dir), "-o", str(out), "--scheduler", "local:1", "-q"]) == 0
    ref = tmp_path / "ref.h5"
    gesturedb.build([scott_dir], ref).close()
    assert differing(ref, out) == []
    assert main(["build", str(scott_dir), "-o", str(tmp_path / "bad.h5"), "--scheduler", "udp://x"]) == 2
    assert "scheduler: expected 'local:N' or 'tcp://HOST:PORT'; got 'udp://x'" in capsys.readouterr().err
    assert not (tmp_path / "bad.h5").exists()


def test_cluster_of_mixed_cpus_builds_the_local_database(scott_dir, tmp_path):
    """Two worker processes, one running numpy's AVX-512 code and one its AVX2 code (emulated with
    NPY_DISABLE_CPU_FEATURES, which numpy reads when it is imported: the worker processes are
    started with it), build the database a local build gives, dataset by dataset; before the
    audio features used their own logarithm, 80 % of their values depended on the worker."""
    import platform
    import subprocess
    import sys

    distributed = pytest.importorskip("distributed")
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("the emulated CPUs are x86 ones")
    src = _two_recordings(scott_dir, tmp_path)
    local = tmp_path / "local.h5"
    gesturedb.build([src], local, workers=1).close()
    dask = os.path.join(os.path.dirname(sys.executable), "dask")
    with distributed.LocalCluster(n_workers=0, processes=False, protocol="tcp", host="127.0.0.1",
                                  dashboard_address=":0") as cluster, \
            distributed.Client(cluster) as client:
        procs = []
        try:
            for disable in ("", "X86_V4"):
                env = {k: v for k, v in os.environ.items() if k != "NPY_DISABLE_CPU_FEATURES"}
                if disable:
                    env["NPY_DISABLE_CPU_FEATURES"] = disable
                procs.append(subprocess.Popen([dask, "worker", cluster.scheduler_address, "--nthreads", "1",
                                               "--no-nanny", "--no-dashboard"], env=env,
                                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            client.wait_for_workers(2, timeout=180)

            def log_target():
                from numpy.lib.introspect import opt_func_info
                return opt_func_info(func_name="^log$", signature="float64")["log"]["dd"]["current"]

            targets = sorted(client.run(log_target).values())
            if targets[0] == targets[1]:
                pytest.skip(f"this CPU has no AVX-512 code in numpy to switch off: {targets}")
            dist = tmp_path / "dask.h5"
            with distributed.get_task_stream(client) as stream:
                gesturedb.build([src], dist, scheduler=client).close()
            # one recording on each kind of worker (two one-thread workers, two tasks at once)
            assert len({t["worker"] for t in stream.data}) == 2, stream.data
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                p.wait(timeout=60)
    assert differing(local, dist) == []


def test_local_cluster_workers_keep_glibc_malloc_defaults(monkeypatch):
    """Dask gives its workers MALLOC_TRIM_THRESHOLD_=65536, which made the graph blocks 1.7x
    slower (a fresh mmap per temporary); the LocalClusters gesturedb starts leave it unset."""
    from gesturedb.db.cluster import dask_client

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    with dask_client("local:1") as client:
        env = client.run(lambda: {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "OPENBLAS_NUM_THREADS")})
    assert [v for v in env.values()] == [{"MALLOC_TRIM_THRESHOLD_": None, "OPENBLAS_NUM_THREADS": "1"}]


def test_workers_running_other_gesturedb_code_are_refused(scott_dir, tmp_path, dask_client, monkeypatch):
    """A worker set up by hand with another installation (emulated: its code_identity differs, or
    it cannot run the check) is refused before any task, with a one-line reason; nothing written.
    Before, an older worker failed inside Dask with a traceback, and a changed one built other
    features without a word."""
    from gesturedb.db import cluster

    real = cluster._source_hash  # what code_identity returns (not patched below)
    assert cluster.code_identity() == real() and len(real()) == 16
    assert dask_client.run(cluster.code_identity) == {a: real() for a in dask_client.scheduler_info()["workers"]}
    src = _two_recordings(scott_dir, tmp_path)

    def on(kind, value):  # client.run and run_on_scheduler give the Worker or Scheduler as dask_worker
        return lambda dask_worker=None: value() if type(dask_worker).__name__ == kind else real()

    def on_workers(value):
        return on("Worker", value)

    def on_scheduler(value):
        return on("Scheduler", value)

    def older():
        raise AttributeError("module 'gesturedb.db.cluster' has no attribute 'code_identity'")

    for where, fake, msg in (
            (on_workers, lambda: "0123456789abcdef",
             r"got other code on 2 of 2 worker\(s\) and the scheduler, first \S+ \(code 0123456789abcdef\)\. Install the same gesturedb"),
            (on_scheduler, lambda: "0123456789abcdef",
             r"got other code on 1 of 2 worker\(s\) and the scheduler, first \S+ \(the scheduler\) \(code 0123456789abcdef\)"),
            (on_workers, older, r"a worker could not check its own \(AttributeError: module")):
        monkeypatch.setattr(cluster, "code_identity", where(fake))
        with pytest.raises(ParameterError, match=rf"^scheduler: expected every worker to run this gesturedb "
                                                 rf"\(code {real()}\); {msg}"):
            gesturedb.build([src], tmp_path / "db.h5", scheduler=dask_client)
        assert not (tmp_path / "db.h5").exists()


def test_code_identity_is_the_same_for_a_checkout_and_an_installed_copy(tmp_path):
    """A copy laid out as pip installs it, imported in another process, has this checkout's code
    identity (an editable install and a wheel of the same commit must agree, or a client in a
    checkout refuses workers that pip-installed it). A changed CLI file changes it."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from gesturedb.db import cluster

    root = Path(__file__).resolve().parents[1]
    site = tmp_path / "site"
    skip = shutil.ignore_patterns("__pycache__")
    shutil.copytree(root / "src" / "gesturedb", site / "gesturedb", ignore=skip)
    probe = ("import sys; sys.path.insert(0, sys.argv[1]); import gesturedb; "
             "from gesturedb.db import cluster; print(gesturedb.__file__, cluster.code_identity())")
    out = subprocess.run([sys.executable, "-c", probe, str(site)], cwd=tmp_path, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == [str(site / "gesturedb" / "__init__.py"), cluster.code_identity()]
    main_py = site / "gesturedb" / "cli" / "main.py"
    main_py.write_text(main_py.read_text() + "\n# changed\n")
    assert cluster.tree_hash(str(site / "gesturedb")) != cluster.code_identity()


# ---------------------------------------------------------------- a cluster failing under a build (issue 41, case 11)

_BUILD_WITH_TIMEOUT = """\
import sys
from gesturedb.db import cluster
cluster.NO_WORKER_TIMEOUT_S = float(sys.argv[1])
from gesturedb.cli.main import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("kill", ["the-only-worker", "the-scheduler"])
def test_a_cluster_lost_mid_build_is_one_line_in_bounded_time(kill, scott_dir, scott_db_path, tmp_path):
    """`gesturedb build --scheduler tcp://...` while its one worker (with its nanny) or its
    scheduler is killed (SIGKILL) as the recordings are processed: before, the build hung with
    no message and a temporary file (worker), or ended in a FutureCancelledError traceback
    (scheduler). Now exit 2, one line naming the scheduler, the old database byte for byte, no
    temporary file, within a bounded time (no worker for 3 s here, 30 s by default)."""
    import signal
    import subprocess
    import sys
    import time

    from daskprocs import QUIET, kill_groups, start_scheduler, worker_command

    pytest.importorskip("distributed")
    src = _two_recordings(scott_dir, tmp_path)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "db.h5"
    old = scott_db_path.read_bytes()
    out.write_bytes(old)
    elsewhere = tmp_path / "cluster"
    elsewhere.mkdir()
    scheduler, address = start_scheduler(elsewhere, "127.0.0.1")
    procs = [scheduler]
    try:
        procs.append(subprocess.Popen(worker_command(address), cwd=elsewhere, **QUIET))
        import distributed

        with distributed.Client(address, timeout="60s") as watch:
            watch.wait_for_workers(1, timeout=180)
        build = subprocess.Popen([sys.executable, "-c", _BUILD_WITH_TIMEOUT, "3", "build", str(src), "-o", str(out),
                                  "-q", "--no-graph", "--scheduler", address],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                 env=dict(os.environ, OMP_NUM_THREADS="1"))
        try:
            deadline = time.monotonic() + 180
            while not [p for p in out_dir.iterdir() if p.name.endswith(".tmp")] and time.monotonic() < deadline:
                assert build.poll() is None, build.communicate()
                time.sleep(0.02)
            time.sleep(0.5)  # the tasks are on the worker
            victim = procs[1] if kill == "the-only-worker" else procs[0]
            os.killpg(victim.pid, signal.SIGKILL)
            killed = time.monotonic()
            _, err = build.communicate(timeout=120)
        finally:
            if build.poll() is None:
                build.kill()
                build.communicate()
    finally:
        kill_groups(procs)
    assert build.returncode == 2, err[-3000:]
    assert time.monotonic() - killed < 60, "stopped long after the cluster was lost"
    assert "Traceback" not in err, err[-3000:]
    want = ("no Dask worker for 3 s while 2 task\\(s\\) of the build's recordings waited \\(every worker was lost, "
            "or none joined\\); stopped" if kill == "the-only-worker" else
            "lost the connection to the Dask scheduler while the build's recordings ran( \\(.*\\))?; stopped")
    assert re.fullmatch(rf"gesturedb build: error: scheduler {address}: {want}\n", err), err[-3000:]
    assert out.read_bytes() == old
    assert sorted(p.name for p in out_dir.iterdir()) == ["db.h5"]


def test_a_lost_connection_while_writing_is_the_clusters_failure_not_the_file(tmp_path, dask_client):
    """Dask's CommClosedError is an OSError: inside the write it became "cannot write DB.h5:
    Stream is closed". It is now one line about the cluster, and the file is as it was."""
    from distributed.comm.core import CommClosedError

    from gesturedb.db.cluster import ClusterError
    from gesturedb.db.cluster import dask_client as open_client
    from gesturedb.db.storage import write_atomically

    out = tmp_path / "db.h5"
    out.write_bytes(b"previous")

    def fill(h5):
        h5["x"] = [1, 2, 3]
        raise CommClosedError("in <TCP (closed) ConnectionPool.scatter local=tcp://127.0.0.1:1>: Stream is closed")

    with pytest.raises(ClusterError, match=r"^scheduler \S+: the Dask cluster failed under the work \(CommClosedError: "
                                           r"in <TCP \(closed\) ConnectionPool\.scatter .*Stream is closed\); stopped$"):
        with open_client(dask_client):
            write_atomically(out, fill)
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["db.h5"]


def test_a_task_that_kills_its_worker_is_one_line():
    """A task whose worker process dies under it, each time it runs (here: once allowed), was
    Dask's KilledWorker traceback; now one ClusterError line naming the scheduler and the tasks."""
    import dask

    from gesturedb.db.cluster import ClusterError, iter_on_cluster

    pytest.importorskip("distributed")
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with pytest.raises(ClusterError, match=r"^scheduler tcp://\S+: a task of the doomed tasks was running on every "
                                               r"worker that died \(KilledWorker: .*\); stopped$"):
            list(iter_on_cluster(lambda i: os._exit(1), [1], "local:1", what="the doomed tasks"))
