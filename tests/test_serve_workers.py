"""gesturedb serve --workers: one address served by several processes, each with its share of the clients."""
from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")

from gesturedb.errors import ParameterError  # noqa: E402
from gesturedb.serve import workers as W  # noqa: E402
from gesturedb.serve.client import LiveClient  # noqa: E402
from gesturedb.threads import available_cpus  # noqa: E402

SR = 16000


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _health(port: int) -> dict:
    return json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=5).read())


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"  # a zombie has stopped
    except FileNotFoundError:
        return False


def test_worker_counts():
    assert W.resolve_workers("auto") == available_cpus()
    assert W.resolve_workers("3") == 3 and W.resolve_workers(1) == 1
    for bad in ("0", "-1", "two", "1.5", None, True):
        with pytest.raises(ParameterError, match="workers: expected a count >= 1 or 'auto'"):
            W.resolve_workers(bad)


def test_address_in_use_is_a_clear_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        with pytest.raises(ParameterError, match=rf"cannot listen on 127.0.0.1:{port}: Address already in use"):
            W.serve(None, "127.0.0.1", port, 1)


def test_two_workers_share_the_clients_and_stop_together(scott_db_path, scott_dir):
    """Connections spread over both processes; four clients at once all stream; SIGTERM to the first
    process stops both."""
    from gesturedb.io import read_audio

    x, _ = read_audio(scott_dir / "2_scott_0_1_1.wav", sr=SR)
    port = _free_port()
    p = subprocess.Popen([sys.executable, "-m", "gesturedb.cli.main", "serve", str(scott_db_path), "--port", str(port),
                          "--workers", "2"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for _ in range(600):
            try:
                _health(port)
                break
            except OSError:
                assert p.poll() is None, p.stdout.read()
                time.sleep(0.1)
        else:
            raise AssertionError("gesturedb serve --workers 2 did not answer")
        pids = {_health(port)["pid"] for _ in range(40)}  # a new connection each: the kernel spreads them
        assert len(pids) == 2 and p.pid in pids, pids
        got, errors = {}, []

        def run(i):
            try:
                with LiveClient(f"ws://127.0.0.1:{port}/stream", sample_rate=SR) as live:
                    frames = []
                    for a in range(0, 3 * SR, SR // 10):
                        live.send_audio(x[i * SR + a:i * SR + a + SR // 10])
                        frames += live.poll()
                    frames += live.end()
                got[i] = sum(len(f) for f in frames)
            except Exception as exc:  # noqa: BLE001 - reported below
                errors.append(exc)

        threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
        [t.start() for t in threads]
        [t.join(120) for t in threads]
        assert not errors and sorted(got) == [0, 1, 2, 3] and all(n == 45 for n in got.values()), (got, errors)
    finally:
        p.send_signal(signal.SIGTERM)
        out = p.communicate(timeout=30)[0]
    assert "2 worker processes" in out
    others = pids - {p.pid}
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in others) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in others), "a worker outlived the server"
