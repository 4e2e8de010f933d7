"""Where a live step's time goes, in one process without the network (run by hand, never by pytest).

N streams over one Searcher are fed the same speech (each from another offset) in 40 ms pieces,
in lockstep; every ready step is searched twice, alone (``Stream.search_step``, what a server
without batching runs) and in one call for all streams (``StepBatch.search``, what
``gesturedb serve`` runs), checked to agree, and applied (``Stream.complete_step``). Prints the
milliseconds per step of: the audio features fed per 40 ms piece and fed once per step (what
the server does: it holds a step's audio until the step can be complete), the step's
preparation, the search alone, the search batched, the apply (window, seams, feet) and the
frames message (``pack_frames`` with its provenance JSON). And the pose pre-selection ahead of
the speech (what ``gesturedb serve`` does by default): after each round's apply every stream's
coming step is pre-selected in one call (``StepBatch.speculate``, off the latency path), and
once its speech has come finished (``StepBatch.finish``: the audio distances and the ranks, on
the path), checked to agree with the batched search.

``--controls C``: stream j steers with the saved mask ``CONTROLS[j % C]`` (C = 1: none), and
the batched search is timed twice, alternating: one call for every stream (each step with its
control's bitset: the kernel's per-query bitsets) and one call per control (what StepBatch did
before the kernel took a bitset per query: a pass over the database per control).

``--long MIN``: instead, one stream fed MIN minutes of the speech (tiled) in one-step pieces, searched
alone; prints the median milliseconds of a piece's feed, search and apply in the first minute and in
the last one (a stream's step should cost no more after twenty minutes than after one).

``--pause S[,S...]``: instead, one stream fed a step's speech at a time, each piece after a pause of S
seconds (sleeping), and again back to back (the baseline, in the same run): the median milliseconds of a
piece's feed and of its apply, and their ratio to the baseline. A server with one client runs a step every
0.53 s; on a machine where code that has not run for a while runs slower at first, its steps pay that.

Usage:  python benchmarks/bench_live_steps.py DB.h5 [--streams 50] [--seconds 12] [--threads 1] [--controls 1]
        python benchmarks/bench_live_steps.py DB.h5 --long 12
        python benchmarks/bench_live_steps.py DB.h5 --pause 0.02,0.2,0.5
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_WAV = os.path.join(HERE, "..", "..", "shared", "data", "beat2-scott", "2_scott_0_1_1.wav")
#: the controls of --controls (saved masks every built database has), the first one none
CONTROLS = (None, "left_wrist_height_high", "hand_speed_high", "right_wrist_height_high", "hand_distance_low",
            "left_wrist_speed_high", "height_asymmetry_high", "right_wrist_forward_high")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("db")
    ap.add_argument("--wav", default=DEFAULT_WAV)
    ap.add_argument("--streams", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--threads", type=int, default=1, help="threads of the batched search (the server: 1); the search alone takes every CPU, as a stream does")
    ap.add_argument("--controls", type=int, default=1, help=f"streams steer with this many different controls "
                                                            f"(1 to {len(CONTROLS)}; 1: none)")
    ap.add_argument("--long", type=float, default=None, metavar="MIN",
                    help="one stream fed MIN minutes of speech: its step's cost at the start and at the end")
    ap.add_argument("--pause", default=None, metavar="S[,S...]",
                    help="one stream fed a step at a time after each of these pauses (s), against none")
    args = ap.parse_args(argv)
    if not 1 <= args.controls <= len(CONTROLS):
        ap.error(f"--controls: expected 1 to {len(CONTROLS)}")
    try:
        pauses = None if args.pause is None else [float(v) for v in args.pause.split(",")]
    except ValueError:
        ap.error(f"--pause: expected seconds separated by commas; got {args.pause!r}")
    if pauses is not None and not all(0 < v <= 10 for v in pauses):
        ap.error(f"--pause: expected seconds in (0, 10]; got {args.pause!r}")

    import gesturedb
    from gesturedb.io import read_audio
    from gesturedb.serve import protocol as P
    from gesturedb.synth import Searcher, SearchOptions
    from gesturedb.synth.stepbatch import StepBatch

    x, sr = read_audio(args.wav, sr=16000)
    db = gesturedb.open(args.db)
    searcher = Searcher(db)
    if args.long is not None:
        return long_stream(searcher, x, sr, args.long)
    if pauses is not None:
        return paused_stream(searcher, x, sr, pauses)
    t = time.perf_counter()
    searcher.pose_projection()
    print(f"{db.n_frames} frames; pose projection {time.perf_counter() - t:.1f} s; {args.streams} streams, "
          f"{args.seconds:g} s each; load average {os.getloadavg()[0]:.1f}")
    Q, piece = args.streams, 640
    n = int(args.seconds * sr)
    starts = np.random.default_rng(0).integers(0, max(1, x.shape[0] - n), Q)
    def opts(j):
        return SearchOptions(seed=j, control=CONTROLS[j % args.controls])

    pieces = [searcher.stream(opts(j), sample_rate=sr) for j in range(Q)]  # fed in 40 ms pieces
    steps = [searcher.stream(opts(j), sample_rate=sr) for j in range(Q)]  # fed once per step
    batch = StepBatch(searcher, threads=args.threads)
    t_piece = t_step = t_prep = t_alone = t_batch = t_per_control = t_apply = t_pack = 0.0
    t_ahead = t_finish = t_upcoming = 0.0
    n_finished = n_ahead_calls = 0
    ahead = {}  # stream index -> (its coming step, its pre-selected table)
    n_steps = n_calls = 0
    fed = [0] * Q
    for a in range(0, n, piece):
        for j in range(Q):
            y = x[starts[j] + a: starts[j] + min(a + piece, n)]
            t0 = time.perf_counter()
            pieces[j].feed(y)
            t_piece += time.perf_counter() - t0
        ready = []
        for j, s in enumerate(steps):
            if a + piece < s.samples_before_step():
                continue
            t0 = time.perf_counter()
            s.feed(x[starts[j] + fed[j]: starts[j] + min(a + piece, n)])
            t_step += time.perf_counter() - t0
            fed[j] = min(a + piece, n)
            t0 = time.perf_counter()
            sq = s.next_step()
            t_prep += time.perf_counter() - t0
            if sq is not None:
                ready.append((j, sq))
        if not ready:
            continue
        t0 = time.perf_counter()
        alone = [steps[j].search_step(sq) for j, sq in ready]
        t_alone += time.perf_counter() - t0
        def per_control(ready):
            out = {}
            for c in range(args.controls):
                part = [(j, sq) for j, sq in ready if j % args.controls == c]
                out.update(zip([j for j, _ in part], batch.search([sq for _, sq in part]) if part else []))
            return [out[j] for j, _ in ready]

        for first in ((0, 1) if n_calls % 2 else (1, 0)) if args.controls > 1 else (0,):
            t0 = time.perf_counter()
            if first == 0:
                got = batch.search([sq for _, sq in ready])
                t_batch += time.perf_counter() - t0
            else:
                split = per_control(ready)
                t_per_control += time.perf_counter() - t0
        if args.controls > 1:
            for g, h in zip(got, split):
                assert int(g[0].frames[0]) == int(h[0].frames[0]), "one call and one per control differ"
        n_calls += 1
        for (j, sq), g in zip(ready, got):
            up, table = ahead.pop(j, (None, None))  # (empty where the code has no pre-selection: a baseline)
            if table is not None and up.same_but_audio(sq):
                t0 = time.perf_counter()
                f = batch.finish(sq, table)
                t_finish += time.perf_counter() - t0
                n_finished += 1
                assert int(f[0].frames[0]) == int(g[0].frames[0]) and f[1] == g[1], "ahead and batched differ"
        for (j, sq), g, o in zip(ready, got, alone):
            assert int(g[0].frames[0]) == int(o[0].frames[0]) and g[1] == o[1], "batched and alone differ"
            t0 = time.perf_counter()
            steps[j].complete_step(sq, *g)
            c = steps[j].take_chunk()
            t_apply += time.perf_counter() - t0
            t0 = time.perf_counter()
            P.pack_frames(c.start, np.asarray(c.motion.root_positions, np.float32),
                          np.asarray(c.motion.rotations, np.float32), c.steps, samples=fed[j])
            t_pack += time.perf_counter() - t0
            n_steps += 1
        if not hasattr(batch, "speculate"):  # gesturedb from before the pre-selection ahead (a baseline)
            continue
        t0 = time.perf_counter()
        ups = [(j, steps[j].upcoming_step()) for j, _ in ready]
        t_upcoming += time.perf_counter() - t0
        t0 = time.perf_counter()
        tabs = batch.speculate([up for _, up in ups])
        t_ahead += time.perf_counter() - t0
        n_ahead_calls += 1
        ahead.update({j: (up, tab) for (j, up), tab in zip(ups, tabs)})
    ms = 1000.0 / max(n_steps, 1)
    print(f"steps {n_steps} in {n_calls} calls (mean batch {n_steps / max(n_calls, 1):.1f}); ms per step:")
    for name, v in (("features, fed in 40 ms pieces", t_piece), ("features, fed once per step", t_step),
                    ("prepare", t_prep), ("search alone", t_alone), ("search batched", t_batch),
                    *((("search batched, a call per control", t_per_control),) if args.controls > 1 else ()),
                    ("apply (window, seams, feet)", t_apply), ("frames message", t_pack),
                    ("coming step prepared (ahead)", t_upcoming), ("pre-selected ahead, batched", t_ahead)):
        print(f"  {name:<32} {v * ms:8.2f}")
    print(f"  {'finished from the pre-selection':<32} {t_finish * 1000 / max(n_finished, 1):8.2f}  "
          f"({n_finished} steps; pre-selection {t_ahead * 1000 / max(n_ahead_calls, 1):.1f} ms per call)")
    print(f"load average {os.getloadavg()[0]:.1f} at the end")
    return 0


def _one_stream(searcher, x, sr: int, seconds: float):
    """A stream, the samples of one of its steps, and ``x`` tiled to ``seconds``."""
    from gesturedb.synth import SearchOptions

    st = searcher.stream(SearchOptions(seed=1), sample_rate=sr)
    n = int(seconds * sr)
    return st, int(round(st.step / st.fps * sr)), np.tile(x, int(np.ceil(n / x.shape[0])))[:n]


def _fed_piece(st, piece) -> tuple[float, float, float]:
    """Feed ``piece``, search and apply every step it made ready: seconds of (the feed, the applies, all)."""
    t0 = time.perf_counter()
    st.feed(piece)
    t1 = time.perf_counter()
    t_apply = 0.0
    while (sq := st.next_step()) is not None:
        got = st.search_step(sq)
        t2 = time.perf_counter()
        st.complete_step(sq, *got)
        t_apply += time.perf_counter() - t2
    st.take_chunk()
    return t1 - t0, t_apply, time.perf_counter() - t0


def long_stream(searcher, x, sr: int, minutes: float) -> int:
    """One stream fed ``minutes`` of ``x`` tiled, a step's samples at a time: ms per piece, start and end."""
    st, piece, x = _one_stream(searcher, x, sr, minutes * 60)
    ms = np.array([_fed_piece(st, x[a:a + piece])[2] for a in range(0, x.shape[0], piece)]) * 1000
    per_min = int(60 * sr / piece)
    print(f"{len(ms)} pieces of {piece} samples; median ms per piece (feed, search, apply): "
          f"first minute {np.median(ms[:per_min]):.2f}, last minute {np.median(ms[-per_min:]):.2f}")
    return 0


def paused_stream(searcher, x, sr: int, pauses: list, pieces: int = 24, skip: int = 4) -> int:
    """One stream per pause fed ``pieces`` steps of ``x``, each after that pause (and one without, the baseline,
    first): the median ms of a piece's feed and of its apply (the first ``skip`` pieces left out)."""
    base = None
    for pause in [0.0] + list(pauses):
        st, piece, xs = _one_stream(searcher, x, sr, pieces * 0.6)
        feed, apply = [], []
        for k in range(pieces):
            if pause:
                time.sleep(pause)
            t_feed, t_apply, _ = _fed_piece(st, xs[k * piece:(k + 1) * piece])
            if k >= skip:
                feed.append(t_feed)
                apply.append(t_apply)
        f, ap_ = 1000 * float(np.median(feed)), 1000 * float(np.median(apply))
        base = base or (f, ap_)
        print(f"pause {pause:5.3f} s: median ms a step, feed {f:6.2f} ({f / base[0]:5.1f}x), "
              f"apply {ap_:6.2f} ({ap_ / base[1]:5.1f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
