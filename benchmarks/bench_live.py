"""Live streaming through `gesturedb serve`: step latency and real-time clients (run by hand, never by pytest).

Starts `gesturedb serve DB.h5` as its own process on a free port (the server and
the clients do not share an interpreter, as in use), then for each count of
clients streams the same speech from that many gesturedb.serve.client.LiveClient
threads at once, each in real time (chunks of --chunk-ms, starts staggered over
one chunk so that they do not move in lockstep), spread over --client-procs processes.

Step latency: every frames message says how many audio samples the server had
received when its frames became final (docs/live.md, the header's `samples`), i.e.
which audio message completed the steps in it; the latency of a step is the time
from sending that audio message to receiving the frames, so it counts the
server's queueing, the search, the assembly and both ways over the loopback. A
step is late when its latency is over --budget-ms. Prints, per count of clients, the
steps measured, p50 / p99 / max step latency, the late steps and the server process's CPU
time (all its threads) and the clients' per step measured, and the largest count with no late step.
"p99 streaming": p99 over the steps whose audio was sent before the first client of the count ended its
stream (and how many): the clients all stream the same speech, so with --stagger-ms their ends come within
one spread, which a server of independent speakers rarely sees. Each client's start message says its
speech's length (`total_samples`, what a client streaming a file does), so its last, shorter step is
pre-selected like the others; `--lengths untold` (a microphone's stream: the last step takes a pass over the
database when the end comes) or `told,untold` (both, alternating count by count). "server p50/p99": the
server's own share of the same steps (`GET /health?last=N`, `step_latency`: from the arrival of the audio
message that completed a step to the send of its frames, issue 39's definition), without the loopback and
the clients' own scheduling (the clients share this machine's cores).

Start-up (--startup): the time from `gesturedb.open(DB)` to the first search step, the
first frame and the second step (the first seam, which needs the database's typical
accelerations) of a `Stream`, and until its pose projection is ready (built in the
background while the first steps scan exactly), each in a fresh interpreter (imports not
counted; the file in the page cache, as for a server that starts on a database it has used),
speech pushed in --chunk-ms chunks as fast as the stream takes it (so the audio's own
latency, 1.7 s at 15 fps, is not in it). Measured with the per-frame arrays memory-mapped
and, alternating, read (GESTUREDB_MMAP=0, what `open` did before), on --chunked DB2.h5
(the same database with chunked per-frame arrays, as builds wrote them before: read), and
with gesturedb imported from --baseline-src DIR (a checkout's src/ before a change).
--paper OUT.h5 first writes a paper-scale database (616k frames) by tiling DB's
recordings (`--paper-frames`), and --paper-chunked OUT2.h5 the same with chunked arrays.

Usage:  python benchmarks/bench_live.py DB.h5 [--wav SPEECH.wav] [--seconds 10]
                                        [--clients 1,2,4,8,16,32,50] [--chunk-ms 40] [--budget-ms 100] [--stagger-ms MS]
                                        [--lengths told,untold]
        python benchmarks/bench_live.py DB.h5 --startup [--reps 5] [--chunked DB2.h5] [--baseline-src DIR]
        python benchmarks/bench_live.py out/scott.h5 --paper /tmp/paper.h5 --paper-chunked /tmp/paper_chunked.h5
"""
from __future__ import annotations

import argparse
import concurrent.futures
import json
import multiprocessing
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
#: the servers --modes compares
MODES = ("batch", "noahead", "alone", "workers", "workers-noahead", "base", "workers-base")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(db: str, port: int, batch: bool = True, workers: int = 1, ahead: bool = True,
                 src: str | None = None) -> subprocess.Popen:
    """``gesturedb serve`` in its own process (gesturedb imported from ``src`` when given: a baseline)."""
    env = None if src is None else dict(os.environ, PYTHONPATH=os.path.abspath(src))
    p = subprocess.Popen([sys.executable, "-m", "gesturedb.cli.main", "serve", db, "--port", str(port),
                          "--max-streams", "1000", "--workers", str(workers)] + ([] if batch else ["--no-batch"])
                         + ([] if ahead else ["--no-ahead"]),
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
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


def one_client(url: str, x: np.ndarray, chunk: int, offset_s: float, out: list, ends: list, errors: list,
               told: bool = True) -> None:
    from gesturedb.serve.client import LiveClient

    try:
        time.sleep(offset_s)
        sent = {}  # samples sent so far -> when the message that brought the count there left
        arrived = []  # (samples the server had, steps completed, time received)
        # told: the start message says the speech's length (a file; its last step is pre-selected too)
        with LiveClient(url, sample_rate=SR, total_samples=x.shape[0] if told else None) as live:
            t0 = time.monotonic()
            for a in range(0, x.shape[0], chunk):
                # wait for the next chunk's time by waiting for frames: each is stamped as it arrives
                while (left := t0 + a / SR - time.monotonic()) > 0:
                    for f in live.poll(left):
                        arrived.append((f.samples, len(f.steps), time.monotonic()))
                sent[min(a + chunk, x.shape[0])] = time.monotonic()
                live.send_audio(x[a:a + chunk])
            t_end_sent = time.monotonic()
            rest = live.end()
            t_end = time.monotonic()
            # frames that audio made final but that came only after the end (a server behind): counted,
            # stamped when end() returned (so their latency is if anything too small); the last steps
            # wait for finish(), not for audio (their stamp is every sample): not measured
            arrived += [(f.samples, len(f.steps), t_end) for f in rest if f.samples < x.shape[0]]
        # (when the step's last audio left, its latency): a step whose audio left before any stream of the
        # count ended is "while streaming"; the last ones wait on the ends of up to n streams at once
        for samples, n_steps, t_recv in arrived:
            out += [(sent[samples], t_recv - sent[samples])] * n_steps
        ends.append(t_end_sent)
    except Exception as exc:  # noqa: BLE001 - a benchmark reports, it does not stop at one client
        errors.append(f"{type(exc).__name__}: {exc}")


def run(url: str, x: np.ndarray, n: int, chunk_ms: float, seed: int | None = None,
        stagger_ms: float | None = None, told: bool = True) -> tuple[list, list]:
    """n clients as threads of this process, each starting at a random time within ``stagger_ms`` (default:
    one chunk); (per step (when its last audio left, its latency), in s of time.monotonic, which every process
    of the machine shares; when each client sent its end; errors)."""
    chunk = int(SR * chunk_ms / 1000)
    spread_s = (chunk_ms if stagger_ms is None else stagger_ms) / 1000
    lat, ends, errors = [], [], []
    rng = np.random.default_rng(n if seed is None else seed)
    threads = [threading.Thread(target=one_client,
                                args=(url, x, chunk, float(rng.uniform(0, spread_s)), lat, ends, errors, told))
               for _ in range(n)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    return lat, ends, errors


def run_procs(url: str, x: np.ndarray, n: int, chunk_ms: float, procs: int,
              stagger_ms: float | None = None, told: bool = True) -> tuple[list, list]:
    """n clients spread over ``procs`` processes (threads in each), so that the clients' own Python
    does not queue on one interpreter lock and count as the server's latency."""
    procs = max(1, min(procs, n))
    if procs == 1:
        return run(url, x, n, chunk_ms, stagger_ms=stagger_ms, told=told)
    sizes = [n // procs + (i < n % procs) for i in range(procs)]
    ctx = multiprocessing.get_context("fork")
    with concurrent.futures.ProcessPoolExecutor(procs, mp_context=ctx) as pool:
        parts = list(pool.map(run, [url] * procs, [x] * procs, sizes, [chunk_ms] * procs,
                              [1000 * n + i for i in range(procs)], [stagger_ms] * procs, [told] * procs))
    return ([v for lat, _, _ in parts for v in lat], [t for _, ends, _ in parts for t in ends],
            [e for _, _, err in parts for e in err])


#: the paper's database: 616k frames (11.4 hours at 15 fps)
PAPER_FRAMES = 616_000

STARTUP = r"""
import json, sys, time
import numpy as np
import librosa
import gesturedb
from gesturedb.io import read_audio
# the audio features' lazy imports and numba compilations, which a server has behind it
librosa.feature.mfcc(y=np.random.default_rng(0).standard_normal(16000).astype(np.float32), sr=16000)
from gesturedb.synth import Searcher
from gesturedb.synth.stream import Stream
x, _ = read_audio(sys.argv[2], sr=16000)
chunk = int(float(sys.argv[3]) * 16)
t0 = time.perf_counter()
db = gesturedb.open(sys.argv[1])
s = Stream(db, sample_rate=16000, searcher=Searcher(db, projection=sys.argv[4] == "1"))
t_open = time.perf_counter() - t0
step = frame = step2 = None
for a in range(0, x.shape[0], chunk):
    c = s.push(x[a:a + chunk])
    if step is None and s.n_steps > 0:
        step = time.perf_counter() - t0
    if frame is None and c.n_frames > 0:
        frame = time.perf_counter() - t0
    if s.n_steps > 1:  # the first seam: the seams' accelerations are needed from here on
        step2 = time.perf_counter() - t0
        break
s.searcher.pose_projection()  # waits for it where it is built in the background
print(json.dumps({"open": t_open, "step": step, "frame": frame, "step2": step2,
                  "projection": time.perf_counter() - t0}))
"""


def startup(db: str, wav: str, chunk_ms: float, mmap: bool, projection: bool = True, src: str | None = None) -> dict:
    """Seconds from open to the stream made, to its first step, its first frame, its second step and the
    pose projection ready, in a fresh process (``src``: import gesturedb from this folder instead)."""
    env = dict(os.environ, GESTUREDB_MMAP="1" if mmap else "0")
    if src:
        env["PYTHONPATH"] = os.path.abspath(src) + os.pathsep + env.get("PYTHONPATH", "")
    p = subprocess.run([sys.executable, "-c", STARTUP, db, wav, str(chunk_ms), "1" if projection else "0"], env=env,
                       capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"start-up run on {db} failed:\n{p.stderr}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def report_startup(args) -> None:
    runs = [(args.db, True, True, None, "mapped"), (args.db, False, True, None, "read (GESTUREDB_MMAP=0)")]
    if args.chunked:
        runs.append((args.chunked, True, True, None, "chunked file (read)"))
    # the pose projection filter (Searcher's default), built from every pose row
    runs += [(args.db, True, False, None, "mapped, no projection"), (args.db, False, False, None, "read, no projection")]
    if args.baseline_src:
        runs += [(args.db, True, True, args.baseline_src, "baseline src, mapped"),
                 (args.db, True, False, args.baseline_src, "baseline src, mapped, no proj.")]
    got: dict = {name: [] for *_, name in runs}
    for _ in range(args.reps):  # alternating, so that a change of load falls on every variant
        for db, m, proj, src, name in runs:
            got[name].append(startup(db, args.wav, args.chunk_ms, m, proj, src))
    keys = ("open", "step", "frame", "step2", "projection")
    print(f"start-up, median of {args.reps} (s): open + Stream / first step / first frame / second step / "
          "projection ready")
    for name, rs in got.items():
        med = {k: float(np.median([r[k] for r in rs])) for k in keys}
        print(f"  {name:<30} " + " / ".join(f"{med[k]:.3f}" for k in keys))


def paper_database(src: str, out: str, frames: int = PAPER_FRAMES, *, chunked: bool = False) -> None:
    """Write ``out``: the database ``src`` with its recordings repeated until it holds ``frames`` frames or
    more (names suffixed, every frame, segment, word and graph index shifted), per-frame arrays
    contiguous (as a build stores them) or ``chunked`` (as builds stored them before)."""
    import h5py

    from gesturedb.db import schema

    with h5py.File(src, "r") as a, h5py.File(out, "w", track_order=True) as b:
        F = int(a.attrs["n_frames"])
        R = a[schema.RECORDING_NAME].shape[0]
        W = a[schema.WORD_RECORDING].shape[0]
        C = a[schema.CLIP_START].shape[0]
        K = -(-frames // F)
        shift = {schema.RECORDING_START_FRAME: F, schema.CHUNK_START: F, schema.CLIP_START: F,
                 schema.CHUNK_RECORDING: R, schema.CLIP_RECORDING: R, schema.WORD_RECORDING: R,
                 schema.FRAME_RECORDING: R,
                 schema.CLIP_WORD_START: W, schema.CLIP_WORD_END: W}
        for k, v in a.attrs.items():
            b.attrs[k] = v
        b.attrs["n_frames"] = K * F

        def tiled(name, ds):
            if not isinstance(ds, h5py.Dataset):
                return
            x = ds[()]
            group = name.split("/")[0]
            if name in shift:
                y = np.concatenate([x + k * shift[name] for k in range(K)])
            elif name == schema.RECORDING_NAME:
                y = np.array([f"{n.decode() if isinstance(n, bytes) else n}~{k:04d}" for k in range(K) for n in x],
                             dtype=object)
            elif group in ("graph", "graph_lower") and name.endswith("indptr"):  # CSR over clips
                e = int(x[-1])
                y = np.concatenate([x[:-1] + k * e for k in range(K)] + [[K * e]]).astype(x.dtype)
            elif group in ("graph", "graph_lower") and name.endswith("indices"):
                y = np.concatenate([x + k * C for k in range(K)])
            elif group == schema.MASKS_GROUP:  # packed bits over frames, bit 0 first
                bits = ((x[:, None] >> np.arange(64, dtype=np.uint64)) & np.uint64(1)).reshape(-1)[:F]
                bits = np.concatenate([np.tile(bits, K), np.zeros(-(K * F) % 64, np.uint64)]).reshape(-1, 64)
                y = (bits << np.arange(64, dtype=np.uint64)).sum(axis=1, dtype=np.uint64)
            elif group in ("frames", "controls", "recordings", "chunks", "clips", "words", "graph", "graph_lower"):
                y = np.concatenate([x] * K)
            else:  # audio statistics, skeleton, style model
                y = x
            per_frame = name in schema.CONTIGUOUS_FIELDS or name.startswith(schema.CONTROLS_GROUP + "/")
            kw = {"chunks": (min(y.shape[0], max(1, (1 << 22) // max(1, y[:1].nbytes))),) + y.shape[1:]} \
                if chunked and per_frame else {}
            if y.dtype == object:
                kw["dtype"] = h5py.string_dtype()
            d = b.create_dataset(name, data=y, **kw)
            for k, v in ds.attrs.items():
                d.attrs.create(k, v, dtype=ds.attrs.get_id(k).dtype)

        a.visititems(tiled)
        for g in a:
            for k, v in a[g].attrs.items():
                b[g].attrs.create(k, v, dtype=a[g].attrs.get_id(k).dtype)
    print(f"wrote {out}: {K} copies of {F} frames = {K * F} frames, {os.path.getsize(out) / 1e9:.2f} GB"
          + (" (chunked)" if chunked else ""))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("db")
    ap.add_argument("--wav", default=DEFAULT_WAV)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--clients", default="1,2,4,8,16,32,50")
    ap.add_argument("--chunk-ms", type=float, default=40.0)
    ap.add_argument("--budget-ms", type=float, default=100.0)
    ap.add_argument("--stagger-ms", type=float, default=None,
                    help="clients start at random times within this many ms (default: one chunk, so that every "
                         "client's steps complete within one chunk of the others': the bursts a server must "
                         "absorb; a step's length, 533 ms at 15 fps, spreads them as independent speakers would)")
    ap.add_argument("--modes", default="batch,alone",
                    help="servers to compare, in this order: batch (steps of all streams searched in one call, "
                         "each pre-selected by pose while its speech arrives), noahead (batch with --no-ahead: "
                         "searched once the speech has come), alone (gesturedb serve --no-batch: each stream "
                         "searches its own), workers and workers-noahead (batch and noahead from --workers "
                         "processes), base and workers-base (the default server, one process or --workers, with "
                         "gesturedb imported from --baseline-src: the code before a change)")
    ap.add_argument("--lengths", default="told",
                    help="told: each client's start message says its speech's length (total_samples: a file; the "
                         "last step is pre-selected like the others); untold: it does not (a microphone); "
                         "told,untold: both, alternating count by count")
    ap.add_argument("--workers", type=int, default=2,
                    help="processes of the 'workers' mode's server (gesturedb serve --workers; batched in each)")
    ap.add_argument("--client-procs", type=int, default=4,
                    help="processes the clients are spread over (threads in each; default: %(default)s)")
    ap.add_argument("--give-up-ms", type=float, default=2000.0,
                    help="stop adding clients to a server once a count's p50 step latency is over this")
    ap.add_argument("--startup", action="store_true", help="measure the time from open to the first frame")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--chunked", help="--startup: also this database with chunked per-frame arrays")
    ap.add_argument("--baseline-src", help="--startup: also import gesturedb from this src/ folder (the code before a "
                                           "change), alternating with this one; the servers of --modes base, "
                                           "workers-base import it")
    ap.add_argument("--paper", help="write a paper-scale database here (DB's recordings repeated), then stop")
    ap.add_argument("--paper-chunked", help="also write it with chunked per-frame arrays here")
    ap.add_argument("--paper-frames", type=int, default=PAPER_FRAMES)
    args = ap.parse_args(argv)
    if args.paper or args.paper_chunked:
        for out, chunked in ((args.paper, False), (args.paper_chunked, True)):
            if out:
                paper_database(args.db, out, args.paper_frames, chunked=chunked)
        return 0
    if args.startup:
        report_startup(args)
        return 0

    from gesturedb.io import read_audio

    x, _ = read_audio(args.wav, sr=SR)
    x = x[: int(args.seconds * SR)]
    counts = [int(c) for c in args.clients.split(",")]
    modes = args.modes.split(",")
    lengths = [{"told": True, "untold": False}.get(v) for v in args.lengths.split(",")]
    if None in lengths:
        raise SystemExit(f"--lengths: expected told, untold or both; got {args.lengths!r}")
    for mode in modes:
        if mode not in MODES:
            raise SystemExit(f"--modes: expected some of {', '.join(MODES)}; got {mode!r}")
    print(f"{x.shape[0] / SR:.1f} s of speech per client in {args.chunk_ms:g} ms chunks; late = step latency over "
          f"{args.budget_ms:g} ms; {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at the start")
    # both servers up at once and the modes alternating count by count, so that a change of the
    # machine's load falls on both
    servers = {}
    try:
        for mode in dict.fromkeys(modes):  # one server per mode, however often --modes names it
            port = free_port()
            t = time.perf_counter()
            if "base" in mode and not args.baseline_src:
                raise SystemExit(f"--modes {mode}: needs --baseline-src")
            servers[mode] = (start_server(args.db, port, batch=mode != "alone", ahead="noahead" not in mode,
                                          workers=args.workers if mode.startswith("workers") else 1,
                                          src=args.baseline_src if "base" in mode else None), port)
            print(f"[{mode}] server up in {time.perf_counter() - t:.1f} s (warm-up included)")
        print(f"{'server':>6} {'clients':>8} {'steps':>7} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} {'late':>6} "
              f"{'batch':>6} {'search ms/step':>15} {'load':>5} {'ahead used ms/call':>14} {'cpu ms/step':>10} {'clients cpu':>10} "
              f"{'server p50/p99':>13} {'p99 streaming':>16}")
        runs = [(mode, told) for mode in modes for told in lengths]
        best = {r: 0 for r in runs}
        live = list(runs)
        for n in counts:
            for mode, told in list(live):
                ok, p50 = measure(args, x, n, mode, servers[mode][1], servers[mode][0].pid, told)
                if ok:
                    best[mode, told] = n
                if not p50 <= args.give_up_ms:
                    live.remove((mode, told))
    finally:
        for server, _ in servers.values():
            server.terminate()
            server.wait(30)
    for (mode, told), n in best.items():
        print(f"{_label(mode, told)}: real-time clients with no late step: {n}")
    return 0


def health(port: int, last: int | None = None) -> dict:
    q = "" if last is None else f"?last={int(last)}"
    return json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/health{q}", timeout=10).read())


def cpu_s(pid: int) -> float:
    """CPU seconds (user and system) the process ``pid`` has used so far (Linux: /proc)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def clients_cpu_s() -> float:
    """CPU seconds used by this process and its finished children: the clients (threads here or the processes
    of run_procs, waited for when it returns; the servers are children too, but still running)."""
    import resource

    return sum(r.ru_utime + r.ru_stime for r in map(resource.getrusage, (resource.RUSAGE_SELF,
                                                                         resource.RUSAGE_CHILDREN)))


def _label(mode: str, told: bool) -> str:
    return mode if told else f"{mode}/untold"


def measure(args, x: np.ndarray, n: int, mode: str, port: int, pid: int, told: bool = True) -> tuple[bool, float]:
    """n clients at once on the server at ``port`` (process ``pid``); prints a row; (no late step, p50 in ms)."""
    # a server of several processes answers /health from one of them: its batch counts are not the server's
    stats = not mode.startswith("workers")
    h0 = health(port)
    before = h0.get("batch") if stats else None
    timed0 = (h0.get("step_latency") or {}).get("steps")
    cpu0, ccpu0 = cpu_s(pid), clients_cpu_s()
    timed, ends, errors = run_procs(f"ws://127.0.0.1:{port}/stream", x, n, args.chunk_ms, args.client_procs,
                                    args.stagger_ms, told)
    lat = [v for _, v in timed]
    # while streaming: the steps whose audio left before the first stream of the count ended
    first_end = min(ends) if ends else np.inf
    steady = np.array([v for t, v in timed if t < first_end]) * 1000
    cpu, ccpu = cpu_s(pid) - cpu0, clients_cpu_s() - ccpu0
    h1 = health(port)
    after = h1.get("batch") if stats else None
    # the server's share (from the audio message that completed a step to the send of its frames), over this
    # count's steps (not with several processes: /health answers from one of them)
    server = "-"
    timed1 = (h1.get("step_latency") or {}).get("steps")
    if stats and timed0 is not None and timed1 is not None and timed1 > timed0:
        sl = health(port, last=timed1 - timed0)["step_latency"]
        server = f"{sl['p50_ms']:.1f}/{sl['p99_ms']:.1f}"
    ms = np.array(lat) * 1000
    streaming = f"{np.percentile(steady, 99):.1f} ({steady.size})" if steady.size else "-"
    late = int((ms > args.budget_ms).sum())
    p50, p99, mx = (np.percentile(ms, 50), np.percentile(ms, 99), ms.max()) if ms.size else (np.nan,) * 3
    batch = search = ahead = "-"
    if before is not None and after is not None and after["calls"] > before["calls"]:
        steps = after["steps"] - before["steps"]
        batch = f"{steps / (after['calls'] - before['calls']):.1f}"  # mean steps per search call
        search = f"{(after['busy_s'] - before['busy_s']) * 1000 / steps:.2f}"  # the search thread's time per step
    if before is not None and after is not None and "ahead" in after:
        a, b = after["ahead"], before["ahead"]
        used, calls = a["used"] - b["used"], a["calls"] - b["calls"]
        if calls:  # steps finished from their pre-selection, and the pre-selecting thread's ms per call
            ahead = f"{used}/{used + after['steps'] - before['steps']} {(a['busy_s'] - b['busy_s']) * 1000 / calls:.0f}"
    # the server's CPU per step, all its threads (one process: the workers' children are not in it)
    cpu_step = f"{cpu * 1000 / ms.size:.1f}" if stats and ms.size else "-"
    clients_step = f"{ccpu * 1000 / ms.size:.1f}" if ms.size else "-"
    print(f"{_label(mode, told):>6} {n:>8} {ms.size:>7} {p50:>8.1f} {p99:>8.1f} {mx:>8.1f} {late:>6} {batch:>6} {search:>15} "
          f"{os.getloadavg()[0]:>5.1f} {ahead:>14} {cpu_step:>10} {clients_step:>10} {server:>13} {streaming:>16}"
          + (f"  ({len(errors)} clients failed: {errors[0]})" if errors else ""), flush=True)
    return late == 0 and not errors and ms.size > 0, float(p50)


if __name__ == "__main__":
    sys.exit(main())
