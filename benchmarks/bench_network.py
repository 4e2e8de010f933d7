"""What the network costs a sharded step, with one shard on a second host (run by hand, as root).

The second host is emulated as `tests/test_two_hosts.py` does it: a `dask worker` in a Linux
network namespace of its own, reached over a veth pair, so every byte between it and the
client or the scheduler crosses a real TCP connection between two network stacks. This
machine's kernel has no `netem`, so two things stand in for a slower network:
  - bandwidth: a token bucket (`tc qdisc ... tbf`) on both ends of the veth pair;
  - latency: a forwarder process on host A that holds every chunk it carries for a given
    one-way delay, both ways; the second host's worker is reached through it (its
    `--contact-address`) and reaches its scheduler through another.

Database: synthetic structured motion (bench_search.motion_pose) of --frames frames in 64-frame
segments, pose 96 and audio 14 wide, cut in 2 shards (ShardedSearch, binary16 projection, top
lists). Three Dask sets run side by side, each a scheduler and 2 single-threaded workers holding
the 2 shards: both workers on host A; one on A and one on B; one on A and one on B behind the
forwarder. Prints, in one run:
  - the bytes one step sends over the link to host B (the veth's counters
    around --count steps, less what the same time idle sends);
  - the median (min) latency of one pose step on each set, interleaved: both on A; A and B;
    A and B at 1 Gbit/s and 100 Mbit/s; A and B through the forwarder at round trips of 0,
    1 and 5 ms; with the extra time each adds over both on A;
  - a 24 s search (45 steps) on the first two sets and the forwarder at 1 ms, and a check
    that every set chooses the windows one process does;
  - a batch of --batch queries x 8 steps (the refiner's self-search) on both shards on A, and on
    A and B unlimited, at 1 Gbit/s and at 100 Mbit/s, with the bytes it moved over the link.

Usage:  sudo python benchmarks/bench_network.py [--frames 2500000] [--reps 21] [--count 40] [--batch 256]
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE), str(HERE.parent / "tests")]

from bench_scale import scale_db  # noqa: E402
from bench_search import DA, DP  # noqa: E402
from daskprocs import QUIET, kill_groups, remove_veth, start_scheduler, veth_pair, worker_command  # noqa: E402
from gesturedb import search  # noqa: E402
from gesturedb.db.shards import ShardedSearch, top_rows  # noqa: E402

N = 8


def _pump(src: socket.socket, dst: socket.socket, delay) -> None:
    """Carry bytes from ``src`` to ``dst``, each chunk ``delay.value`` seconds after it came."""
    q: deque = deque()
    cv = threading.Condition()

    def read():
        while True:
            try:
                data = src.recv(1 << 16)
            except OSError:
                data = b""
            with cv:
                q.append((time.perf_counter() + delay.value, data))
                cv.notify()
            if not data:
                return

    threading.Thread(target=read, daemon=True).start()
    while True:
        with cv:
            while not q:
                cv.wait()
            due, data = q.popleft()
        wait = due - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        try:
            if not data:
                dst.shutdown(socket.SHUT_WR)
                return
            dst.sendall(data)
        except OSError:
            return


def _forward(listener: socket.socket, target: tuple, delay) -> None:
    """Accept on ``listener``; connect each to ``target``; pump both ways with ``delay``."""
    while True:
        a, _ = listener.accept()
        b = socket.create_connection(target)
        for s in (a, b):
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        threading.Thread(target=_pump, args=(a, b, delay), daemon=True).start()
        threading.Thread(target=_pump, args=(b, a, delay), daemon=True).start()


class DelayLink:
    """A TCP forwarder in a process of its own (the client's GIL stays out of it), listening on
    ``host`` (any free port) for ``target``; ``delay`` (seconds, one way) can change at any time."""

    def __init__(self, host: str, target: tuple, delay):
        ls = socket.socket()
        ls.bind((host, 0))
        ls.listen(64)
        self.port = ls.getsockname()[1]
        self.proc = mp.get_context("fork").Process(target=_forward, args=(ls, target, delay), daemon=True)
        self.proc.start()
        ls.close()


def _counters(dev: str) -> np.ndarray:
    base = Path("/sys/class/net") / dev / "statistics"
    return np.array([int((base / n).read_text()) for n in ("rx_bytes", "tx_bytes")])


def _tc(veth_a: str, veth_b: str, ns: str, rate: str | None) -> None:
    """A token bucket of ``rate`` on both ends of the veth pair (None: none). Its burst is about 10
    Ethernet frames: with a larger one a step's reply (tens of kB) passes whole at the veth's speed."""
    for pre, d in (([], veth_a), (["ip", "netns", "exec", ns], veth_b)):
        if rate is None:
            subprocess.run([*pre, "tc", "qdisc", "del", "dev", d, "root"], capture_output=True)
        else:
            subprocess.run([*pre, "tc", "qdisc", "replace", "dev", d, "root", "tbf", "rate", rate,
                            "burst", "16kb", "latency", "50ms"], check=True, capture_output=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2_500_000)
    ap.add_argument("--reps", type=int, default=21)
    ap.add_argument("--count", type=int, default=40, help="steps counted on the link")
    ap.add_argument("--batch", type=int, default=256, help="queries of the batch")
    args = ap.parse_args(argv)
    if os.geteuid() != 0:
        sys.exit("bench_network: needs root (a network namespace and a veth pair)")
    import distributed

    pid = os.getpid()
    ns, veth_a, veth_b = f"gdbn{pid}", f"gdbn{pid}a", f"gdbn{pid}b"
    net = f"10.{100 + pid % 100}.{(pid // 100) % 250}"
    a_addr, b_addr = f"{net}.1", f"{net}.2"
    delay = mp.get_context("fork").Value("d", 0.0, lock=False)
    procs, clients = [], []
    folder = Path(tempfile.mkdtemp(prefix="bench-network-"))
    try:
        veth_pair(ns, veth_a, veth_b, a_addr, b_addr)
        # one process per worker, no nanny: the nanny's MALLOC_TRIM_THRESHOLD_ (see
        # gesturedb.db.cluster.local_cluster) would make these workers unlike synth's
        opts = ("--no-nanny",)
        sets = {}
        for name in ("forwarded", "one host", "two hosts"):  # forks before any client starts threads
            (folder / name).mkdir()
            sched, address = start_scheduler(folder / name, a_addr)
            procs.append(sched)
            procs.append(subprocess.Popen(worker_command(address, "--host", a_addr, *opts), cwd=folder, **QUIET))
            if name == "one host":
                procs.append(subprocess.Popen(worker_command(address, "--host", a_addr, *opts), cwd=folder, **QUIET))
            elif name == "two hosts":
                procs.append(subprocess.Popen(["ip", "netns", "exec", ns, *worker_command(address, "--host", b_addr,
                                                                                           *opts)], cwd=folder, **QUIET))
            else:
                port = 40000 + pid % 20000  # host B's own namespace: nothing else listens there
                to_b = DelayLink(a_addr, (b_addr, port), delay)
                host, sport = address.removeprefix("tcp://").rsplit(":", 1)
                to_sched = DelayLink(a_addr, (host, int(sport)), delay)
                procs += [to_b.proc, to_sched.proc]
                procs.append(subprocess.Popen(
                    ["ip", "netns", "exec", ns, *worker_command(f"tcp://{a_addr}:{to_sched.port}",
                                                                "--listen-address", f"tcp://{b_addr}:{port}",
                                                                "--contact-address", f"tcp://{a_addr}:{to_b.port}",
                                                                *opts)], cwd=folder, **QUIET))
            client = distributed.Client(address, timeout="60s")
            clients.append(client)
            client.wait_for_workers(2, timeout=120)
            sets[name] = client

        rng = np.random.default_rng(0)
        pose, audio, st, ln = scale_db(rng, args.frames)
        M = st.shape[0]
        print(f"pose {DP} and audio {DA} wide; L = {top_rows(M)} rows per list")
        shs = {}
        for name, client in sets.items():
            t = time.perf_counter()
            shs[name] = ShardedSearch(pose, audio, st, ln, client=client, parts=2, threads=1)
            client.gather(shs[name].shards)
            where = sorted(w.split("//")[1].rsplit(":", 1)[0] for w in client.scheduler_info()["workers"])
            print(f"  {name}: 2 shards resident on workers at {', '.join(where)} in {time.perf_counter() - t:.1f} s")
        prev = pose[12345].copy()
        q = rng.standard_normal((N, DA), dtype=np.float32)
        proj = search.PoseProjection(pose, half=True)
        ref = search.rank_sum_step(pose, audio, st, ln, prev, q, pose_proj=proj)

        # what a step sends over the link: the veth's counters around steps of the two-host set,
        # less the same time idle (heartbeats)
        two = shs["two hosts"]
        two.search(q, prev, step=N)
        c0, t0 = _counters(veth_a), time.perf_counter()
        for _ in range(args.count):
            two.search(q, prev, step=N)
        busy, dt = _counters(veth_a) - c0, time.perf_counter() - t0
        c0 = _counters(veth_a)
        time.sleep(dt)
        idle = _counters(veth_a) - c0
        per = (busy - idle) / args.count
        print(f"\nover the link to host B, per step ({args.count} steps, idle time subtracted): "
              f"{per[1] / 1e3:.1f} kB to B, {per[0] / 1e3:.1f} kB from B")

        def on(name, rate=None, rtt=0.0):
            sh = shs[name]

            def setup():
                _tc(veth_a, veth_b, ns, rate)
                delay.value = rtt / 2
            return setup, lambda: sh.search(q, prev, step=N)

        fns = {
            "both shards on host A": on("one host"),
            "A and B": on("two hosts"),
            "A and B, 1 Gbit/s": on("two hosts", "1gbit"),
            "A and B, 100 Mbit/s": on("two hosts", "100mbit"),
            "A and B forwarded, RTT 0": on("forwarded"),
            "A and B forwarded, RTT 1 ms": on("forwarded", rtt=1e-3),
            "A and B forwarded, RTT 5 ms": on("forwarded", rtt=5e-3),
        }
        times = {k: [] for k in fns}
        same = True
        for _ in range(args.reps):
            for k, (setup, step) in fns.items():
                setup()
                t = time.perf_counter()
                r = step()
                times[k].append(time.perf_counter() - t)
                same &= (int(r.segments[0]), int(r.starts[0])) == (ref.segment, ref.start)
        _tc(veth_a, veth_b, ns, None)
        delay.value = 0.0
        base = float(np.median(times["both shards on host A"]))
        print(f"\none pose step, median (min) over {args.reps} interleaved repetitions:")
        for k, v in times.items():
            med = float(np.median(v))
            extra = "" if k.startswith("both") else f"   {1e3 * (med - base):+6.2f} ms"
            print(f"  {k:<30s} {1e3 * med:7.2f} ms  ({1e3 * min(v):.2f}){extra}")
        print(f"  every step chose the window one process chooses: {same}")

        query = rng.standard_normal((24 * 15, DA), dtype=np.float32)
        whole = search.rank_sum_search(pose, audio, st, ln, query, prev, step=N, pose_proj=proj)
        print("\na 24 s search (45 steps):")
        for name, rtt in (("one host", 0.0), ("two hosts", 0.0), ("forwarded", 1e-3)):
            delay.value = rtt / 2
            sh = shs[name]
            sh.steps = sh.unsettled = 0
            t = time.perf_counter()
            res = sh.search(query, prev, step=N)
            dt = time.perf_counter() - t
            print(f"  {name + (', RTT 1 ms' if rtt else ''):<22s} {1e3 * dt:7.1f} ms; same windows as one process: "
                  f"{bool((res.frames == whole.frames).all())}; steps not settled by the lists: {sh.unsettled}")
        delay.value = 0.0

        # a batch (the refiner's self-search: each query a segment's own audio, that segment
        # excluded): every query's lists cross the link at every step
        B = args.batch
        idx = np.linspace(0, M - 1, B).astype(int)
        queries = [audio[st[i]:st[i] + ln[i]] for i in idx]
        init = pose[rng.integers(0, pose.shape[0], B)]
        ex = np.zeros((B, M), bool)
        ex[np.arange(B), idx] = True
        local = search.rank_sum_search_batch(pose, audio, st, ln, queries, init, step=N, exclude=ex, pose_proj=proj)
        print(f"\na batch of {B} queries x 8 steps:")
        for name, rate in (("one host", None), ("two hosts", None), ("two hosts", "1gbit"), ("two hosts", "100mbit")):
            _tc(veth_a, veth_b, ns, rate)
            c0, t = _counters(veth_a), time.perf_counter()
            got = shs[name].search_batch(queries, init, step=N, exclude=ex)
            dt, moved = time.perf_counter() - t, _counters(veth_a) - c0
            same = all((a.frames == b.frames).all() for a, b in zip(got, local))
            link = "" if name == "one host" else (f"; over the link {moved[1] / 1e6:.2f} MB to B, {moved[0] / 1e6:.2f} MB "
                                                  f"from B ({moved[0] / (8 * B) / 1e3:.1f} kB per query and step)")
            print(f"  {name + (f', {rate}' if rate else ''):<22s} {dt:6.2f} s{link}; same as one process: {same}")
        _tc(veth_a, veth_b, ns, None)
        for sh in shs.values():
            sh.close()
    finally:
        for c in clients:
            c.close()
        kill_groups([p for p in procs if isinstance(p, subprocess.Popen)])
        for p in procs:
            if not isinstance(p, subprocess.Popen):
                p.kill()
        remove_veth(ns, veth_a)


if __name__ == "__main__":
    main()
