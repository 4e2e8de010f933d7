"""Live streaming through `gesturedb serve`: step latency and real-time clients (run by hand, never by pytest).

Starts `gesturedb serve DB.h5` as its own process on a free port (the server and
the clients do not share an interpreter, as in use), then for each count of
clients streams the same speech from that many gesturedb.serve.client.LiveClient
threads at once, each in real time (chunks of --chunk-ms, starts staggered over
one chunk so that they do not move in lockstep).

Step latency: every frames message says how many audio samples the server had
received when its frames became final (docs/live.md, the header's `samples`), i.e.
which audio message completed the steps in it; the latency of a step is the time
from sending that audio message to receiving the frames, so it counts the
server's queueing, the search, the assembly and both ways over the loopback. A
step is late when its latency is over --budget-ms. Prints, per count of clients, the
steps measured, p50 / p99 / max step latency and the late steps, and the largest
count with no late step.

Usage:  python benchmarks/bench_live.py DB.h5 [--wav SPEECH.wav] [--seconds 10]
                                        [--clients 1,2,4,8,16,32,50] [--chunk-ms 40] [--budget-ms 100]
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_WAV = os.path.join(HERE, "..", "..", "shared", "data", "beat2-scott", "2_scott_0_1_1.wav")
SR = 16000


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(db: str, port: int) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-m", "gesturedb.cli.main", "serve", db, "--port", str(port),
                          "--max-streams", "1000"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t = time.monotonic()
    while time.monotonic() - t < 300:
        try:
            h = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=1).read())
            if not h["stream"]:
                raise SystemExit(f"the server cannot stream: {h['stream_error']}")
            return p
        except OSError:
            if p.poll() is not None:
                raise SystemExit(f"gesturedb serve exited: {p.stdout.read()}") from None
            time.sleep(0.2)
    p.kill()
    raise SystemExit("gesturedb serve did not answer within 300 s")


def one_client(url: str, x: np.ndarray, chunk: int, offset_s: float, out: list, errors: list) -> None:
    from gesturedb.serve.client import LiveClient

    try:
        time.sleep(offset_s)
        sent = {}  # samples sent so far -> when the message that brought the count there left
        arrived = []  # (samples the server had, steps completed, time received)
        with LiveClient(url, sample_rate=SR) as live:
            t0 = time.monotonic()
            for a in range(0, x.shape[0], chunk):
                # wait for the next chunk's time by waiting for frames: each is stamped as it arrives
                while (left := t0 + a / SR - time.monotonic()) > 0:
                    for f in live.poll(left):
                        arrived.append((f.samples, len(f.steps), time.monotonic()))
                sent[min(a + chunk, x.shape[0])] = time.monotonic()
                live.send_audio(x[a:a + chunk])
            live.end()  # the last steps wait for finish(), not for audio: not measured
        for samples, n_steps, t_recv in arrived:
            out += [t_recv - sent[samples]] * n_steps
    except Exception as exc:  # noqa: BLE001 - a benchmark reports, it does not stop at one client
        errors.append(f"{type(exc).__name__}: {exc}")


def run(url: str, x: np.ndarray, n: int, chunk_ms: float) -> tuple[list, list]:
    chunk = int(SR * chunk_ms / 1000)
    lat, errors = [], []
    rng = np.random.default_rng(n)
    threads = [threading.Thread(target=one_client,
                                args=(url, x, chunk, float(rng.uniform(0, chunk_ms / 1000)), lat, errors))
               for _ in range(n)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    return lat, errors


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("db")
    ap.add_argument("--wav", default=DEFAULT_WAV)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--clients", default="1,2,4,8,16,32,50")
    ap.add_argument("--chunk-ms", type=float, default=40.0)
    ap.add_argument("--budget-ms", type=float, default=100.0)
    args = ap.parse_args(argv)

    from gesturedb.io import read_audio

    x, _ = read_audio(args.wav, sr=SR)
    x = x[: int(args.seconds * SR)]
    port = free_port()
    t = time.perf_counter()
    server = start_server(args.db, port)
    print(f"server up in {time.perf_counter() - t:.1f} s (warm-up included); {x.shape[0] / SR:.1f} s of speech "
          f"per client in {args.chunk_ms:g} ms chunks; late = step latency over {args.budget_ms:g} ms")
    print(f"{'clients':>8} {'steps':>7} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} {'late':>6}")
    best = 0
    try:
        for n in [int(c) for c in args.clients.split(",")]:
            lat, errors = run(f"ws://127.0.0.1:{port}/stream", x, n, args.chunk_ms)
            ms = np.array(lat) * 1000
            late = int((ms > args.budget_ms).sum())
            p50, p99, mx = (np.percentile(ms, 50), np.percentile(ms, 99), ms.max()) if ms.size else (np.nan,) * 3
            print(f"{n:>8} {ms.size:>7} {p50:>8.1f} {p99:>8.1f} {mx:>8.1f} {late:>6}"
                  + (f"  ({len(errors)} clients failed: {errors[0]})" if errors else ""), flush=True)
            if late == 0 and not errors:
                best = n
    finally:
        server.terminate()
        server.wait(30)
    print(f"real-time clients with no late step: {best}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
