"""Benchmark of the rank-sum search at the paper's scale (run by hand, never by pytest).

Database: 9,624 segments x 64 frames = 615,936 frames, pose features of 150
values (schema 5: 8 feature joints and the 2 ankles at frames f-4 .. f+4; "--layout
centred" for the 120 values of schema 4, without the ankles; "--layout past" for the 96
values of schema 3, f .. f-6), audio features of 14 values, window N = 8 (the same sizes as Habibie
et al. 2022, Sec. 3.3), fixed seed. Pose data: by default ("--data motion")
synthetic motion with the structure of real pose features (see motion_pose:
smooth joints stacked over the layout's frames in a turning body frame); with
"--data random" i.i.d. Gaussian rows, which have no structure for the
PoseProjection filter to use (it then keeps most rows: the worst case).
Prints, in one run:

(a) latency of one step of the kernel (median of many), pose and audio pre-selection,
    pose pre-selection through a HalfPose (binary16 rows as a bounded filter,
    identical results, half the bytes) and through a PoseProjection (24 columns
    per frame as a bounded filter, identical results, a quarter of the bytes),
    and through the same projection in binary16 (an eighth of the bytes; what
    gesturedb's Searcher uses by default);
(b) the same step written in vectorised numpy (what a user would write) and
    a check that it picks the same window;
(c) the floors: the time to read the DP-wide pose matrix once at the memory
    bandwidth measured now (a streaming sum in C++ on 1 and 2 threads, and
    numpy's sum), and the 24-wide projection once (C++, 2 threads); and the
    floor of an exact step of this design, even one whose filter named every
    segment's candidate outright: the binary16 stream, one float32 audio
    window per segment read with the step's prefetching (and one pose row),
    and the ranker on a table of independent distances;
(d) the real-time factor of a 24 s synthesis at 15 fps (360 frames, 45 steps);
(e) the batched search with every segment's audio as a query (64 frames =
    8 steps each), against a loop of single searches timed on a subset and
    extrapolated (said so in the output), with a check that they agree; then
    the same batch with the PoseProjection (what the refiner's training data
    uses) in the same run, the ratio, and a check that all results are identical.

--masks DB.h5 measures only this, on a built database (its Searcher's segments and pose
projection, what the server searches): one step's pre-selection tables for --queries queries
(previous poses and audio windows at random frames), each with the bitset of one of C
controls (the database's saved masks; query i takes control i % C, the first none), through
tables.PreselectBatch (blocked, one thread): one call with a bitset per query, one call per
control (what gesturedb serve's StepBatch did before the kernel took a bitset per query), and,
for scale, one call with no bitset; interleaved, median ms per call. C = --controls (a list).

Usage:  python benchmarks/bench_search.py [--reps 41] [--loop-subset 24] [--skip-batch]
                                          [--batch-reps 1] [--data motion|random]
        python benchmarks/bench_search.py --masks DB.h5 [--queries 50] [--controls 1,2,4,8] [--reps 9]
The machine is shared: every timing is a median over interleaved repetitions,
and (e) also reports CPU time, which other processes do not inflate. The C++
floors of (c) are benchmark code (benchmarks/floors.cpp, not in gesturedb._core):
floors.py compiles them on the first run, a few seconds.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # floors.py, beside this file

from floors import load as load_floors  # noqa: E402
from gesturedb import _core, search  # noqa: E402

M, L, DA, N = 9624, 64, 14, 8
#: stacked frame offsets of each layout and whether it carries the ankles (gesturedb.features.pose:
#: schema 5 stance, schema 4 centred, schema 3 past)
LAYOUTS = {"stance": ((-4, -2, 0, 2, 4), True), "centred": ((-4, -2, 0, 2, 4), False), "past": ((0, -2, -4, -6), False)}
LAGS, STANCE = LAYOUTS["stance"]
DP = (24 + 6 * STANCE) * len(LAGS)
FPS, SECONDS = 15, 24


def _turned(p, c, sn):
    """(n, joints, 3) positions into each frame's body frame (cosine c, sine sn of its yaw, (n, 1)), (n, joints * 3)."""
    px, pz = p[..., 0], p[..., 2]
    return np.stack([c * px + sn * pz, p[..., 1], -sn * px + c * pz], axis=-1).reshape(len(p), -1)


def motion_pose(rng, F, n_rec=150):
    """(F, DP) pose features with the structure of real ones: 8 joints x 3
    coordinates moving smoothly (6 latent Gaussian-filtered signals, about
    5 frames of correlation like the wrists at 15 fps, mapped to the 24
    coordinates, plus 1 cm of jitter) and, with STANCE, two ankles about
    hip-width apart that shift by about 9 cm over seconds (BEAT2's spread),
    stacked at the frames f + LAGS clamped to the recording's ends, each in
    the current frame's slowly turning body frame (as gesturedb.features.pose
    does), over n_rec recordings."""
    from scipy.ndimage import gaussian_filter1d

    out = np.empty((F, DP), np.float32)
    bounds = np.linspace(0, F, n_rec + 1).astype(int)
    rest = rng.standard_normal(24) * 0.3  # one speaker: one rest pose
    arms = rng.standard_normal((6, 24)) * 0.08
    for a, b in zip(bounds[:-1], bounds[1:]):
        n = b - a
        # two arms: 6 latent degrees of freedom drive the 24 coordinates (joints
        # of one arm move together), plus a little independent jitter
        z = gaussian_filter1d(rng.standard_normal((n, 6)), 5.0, axis=0)
        x = (z / z.std(axis=0)) @ arms
        x += gaussian_filter1d(rng.standard_normal((n, 24)), 2.0, axis=0) * 0.01 + rest
        yaw = gaussian_filter1d(rng.standard_normal(n), 20.0) * 2.0
        c, sn = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        f = np.arange(n)
        if STANCE:  # drawn after the rest, so that the other layouts' data stay what they were
            # BEAT2's ankles in the body frame: mean (+-0.14, -0.84, 0) m, sd 9 cm across and forward, 3 cm up
            feet = (np.array([[0.136, -0.84, 0.0], [-0.136, -0.84, 0.0]])
                    + gaussian_filter1d(rng.standard_normal((n, 2, 3)), 20.0, axis=0) * [0.75, 0.28, 0.75])
        for k, lag in enumerate(LAGS):
            src = np.clip(f + lag, 0, n - 1)
            out[a:b, 24 * k:24 * (k + 1)] = _turned(x[src].reshape(n, 8, 3), c, sn)
            if STANCE:  # the ankles: a stance about hip-width apart, shifting slowly, after every lag's arms
                col = 24 * len(LAGS) + 6 * k
                out[a:b, col:col + 6] = _turned(feet[src], c, sn)
    return out


def make_db(seed=0, data="motion"):
    rng = np.random.default_rng(seed)
    F = M * L
    pose = (motion_pose(rng, F) if data == "motion"
            else rng.standard_normal((F, DP), dtype=np.float32))
    audio = rng.standard_normal((F, DA), dtype=np.float32)
    seg_start = np.arange(M, dtype=np.int64) * L
    seg_len = np.full(M, L, dtype=np.int64)
    return rng, pose, audio, seg_start, seg_len


def numpy_step(pose, audio, prev, q, preselect):
    """One spec step for equal 64-frame segments, vectorised as a user would."""
    n = q.shape[0]
    n_cand = L - n
    s = np.arange(1, n_cand + 1)
    if preselect == "pose":
        dp_all = ((pose - prev) ** 2).sum(axis=1).reshape(M, L)[:, :n_cand]  # entry frames s-1
        s_sel = np.argmin(dp_all, axis=1) + 1
        g = np.arange(M) * L + s_sel
        dp = dp_all[np.arange(M), s_sel - 1].astype(np.float64)
        win = audio[g[:, None] + np.arange(n)].reshape(M, n * DA).astype(np.float64)
        qf = q.ravel().astype(np.float64)
        da = 1.0 - win @ qf / np.sqrt((win * win).sum(1) * (qf @ qf))
    else:
        qf = q.ravel()
        wins = np.lib.stride_tricks.sliding_window_view(audio, (n, DA))[:, 0].reshape(-1, n * DA)
        qa = wins @ qf
        aa = np.einsum("ij,ij->i", wins, wins)
        da_all = 1.0 - qa / np.sqrt(aa * (qf @ qf))
        g_all = np.arange(M)[:, None] * L + s[None, :]
        da_c = da_all[g_all]
        s_sel = np.argmin(da_c, axis=1) + 1
        g = np.arange(M) * L + s_sel
        da = da_c[np.arange(M), s_sel - 1].astype(np.float64)
        dp = ((pose[g - 1] - prev) ** 2).sum(axis=1).astype(np.float64)
    m = np.arange(M)
    rp = np.empty(M, np.int64)
    rp[np.lexsort((m, dp))] = m
    ra = np.empty(M, np.int64)
    ra[np.lexsort((m, da))] = m
    best = np.lexsort((m, rp, rp + ra))[0]
    return int(best), int(s_sel[best])


def interleaved(fns, reps):
    """Median and min seconds of each callable, run round-robin."""
    times = {k: [] for k in fns}
    for _ in range(reps):
        for k, f in fns.items():
            t = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t)
    return {k: (float(np.median(v)), float(np.min(v))) for k, v in times.items()}


def cpu_seconds():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


MASKS = ("left_wrist_height_high", "hand_speed_high", "right_wrist_height_high", "hand_distance_low",
         "left_wrist_speed_high", "height_asymmetry_high", "right_wrist_forward_high")


def bench_masks(args) -> None:
    """--masks: a bitset per query in one call against a call per control (see the module notes)."""
    import gesturedb
    from gesturedb import tables
    from gesturedb.synth import Searcher

    db = gesturedb.open(args.masks)
    s = Searcher(db)
    t = time.perf_counter()
    proj = s.pose_projection()
    print(f"{args.masks}: {db.n_frames} frames, {s.seg_start.shape[0]} segments; pose projection "
          f"{time.perf_counter() - t:.1f} s; simd = {search.get_simd()}; load average {os.getloadavg()[0]:.1f}")
    P, A = db.pose_features, db.audio_features
    rng = np.random.default_rng(0)
    Q = args.queries
    F = db.n_frames
    prevs = np.ascontiguousarray(P[rng.integers(0, F, Q)])
    wins = np.ascontiguousarray(A[rng.integers(0, F - N, Q)[:, None] + np.arange(N)])
    batch = tables.PreselectBatch(P, A, s.seg_start, s.seg_len, pose_f16=s._half, pose_proj=proj)
    every = np.full((F + 63) // 64, np.uint64(0xFFFFFFFFFFFFFFFF))
    bits = [every] + [db.mask_datasets[name] if name in db.mask_datasets else None for name in MASKS]
    bits = [b if b is None else np.ascontiguousarray(b, dtype=np.uint64) for b in bits]
    print(f"{Q} queries, one step (N = {N}), blocked, 1 thread; ms per call (median of {args.reps}, interleaved); "
          "kept: the share of frames each control allows")
    for C in (int(c) for c in args.controls.split(",")):
        if C > len(bits) or any(b is None for b in bits[:C]):
            print(f"  {C} controls: the database lacks the saved masks {MASKS[:C - 1]}")
            continue
        which = np.arange(Q) % C
        per_query = np.ascontiguousarray(np.stack([bits[c] for c in which]))

        def one_call(per_query=per_query):
            return batch.tables(prevs, wins, allowed=per_query, threads=1, method="blocked")

        def per_control(C=C, which=which):
            out = [None] * Q
            for c in range(C):
                idx = np.flatnonzero(which == c)
                got = batch.tables(prevs[idx], wins[idx], allowed=None if c == 0 else bits[c], threads=1,
                                   method="blocked")
                for r, i in enumerate(idx):
                    out[i] = tuple(g[r] for g in got)
            return out

        a, b = one_call(), per_control()
        for i in range(Q):
            for x, y in zip((a[0][i], a[1][i], a[2][i]), b[i]):
                np.testing.assert_array_equal(x, y)
        got = interleaved({"one": one_call, "per": per_control,
                           "none": lambda: batch.tables(prevs, wins, threads=1, method="blocked")}, args.reps)
        kept = [float(np.unpackbits(bits[c].view(np.uint8)).mean()) for c in range(1, C)]
        print(f"  {C} controls (kept {', '.join(f'{k:.0%}' for k in kept) or '-'}): one call {got['one'][0] * 1e3:.1f}, "
              f"a call per control {got['per'][0] * 1e3:.1f}, no bitset {got['none'][0] * 1e3:.1f} "
              f"(the same tables)")
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--masks", metavar="DB", help="only the per-query bitsets on this database (see the notes)")
    ap.add_argument("--queries", type=int, default=50, help="--masks: queries in a call")
    ap.add_argument("--controls", default="1,2,4,8", help="--masks: numbers of controls among them")
    ap.add_argument("--reps", type=int, default=41, help="repetitions of each timed step")
    ap.add_argument("--loop-subset", type=int, default=24,
                    help="queries timed one by one to extrapolate the loop in (e)")
    ap.add_argument("--skip-batch", action="store_true", help="skip (e)")
    ap.add_argument("--batch-reps", type=int, default=1,
                    help="interleaved runs of the batch without and with the projection in (e) (median)")
    ap.add_argument("--data", choices=("motion", "random"), default="motion",
                    help="synthetic pose data: structured motion (default) or i.i.d. Gaussian")
    ap.add_argument("--layout", choices=tuple(LAYOUTS), default="stance",
                    help="pose features: stance (schema 5, 150 values, default), centred (schema 4, 120, no ankles) "
                         "or past (schema 3, 96)")
    args = ap.parse_args(argv)
    if args.masks:
        bench_masks(args)
        return 0
    global LAGS, STANCE, DP
    LAGS, STANCE = LAYOUTS[args.layout]
    DP = (24 + 6 * STANCE) * len(LAGS)

    threads = _core.default_threads()
    floors = load_floors()
    print(f"gesturedb search benchmark: {M} segments x {L} frames = {M * L} frames, "
          f"pose {DP}, audio {DA}, N = {N}; simd = {search.get_simd()} "
          f"(available {search.kernels()}), threads = {threads}, data = {args.data}")
    rng, pose, audio, st, ln = make_db(data=args.data)
    prev = pose[12345].copy()
    q = rng.standard_normal((N, DA), dtype=np.float32)
    t = time.perf_counter()
    half = search.HalfPose(pose)
    t_half = time.perf_counter() - t
    t = time.perf_counter()
    proj = search.PoseProjection(pose)
    t_proj = time.perf_counter() - t
    proj16 = search.PoseProjection(pose, half=True)
    print(f"pose matrix {pose.nbytes / 1e6:.0f} MB, audio matrix {audio.nbytes / 1e6:.0f} MB, "
          f"HalfPose {half.data.nbytes / 1e6:.0f} MB (built once in {t_half:.2f} s), "
          f"PoseProjection {proj.blocks.nbytes / 1e6:.0f} MB (built once in {t_proj:.2f} s; "
          f"median residual {np.median(proj.rows[:, -1]):.3f}), in binary16 {proj16.blocks.nbytes / 1e6:.0f} MB")

    # --- (a) + (c): kernel steps and the read floor, interleaved ----------------
    def step(pre, th=None, f16=None, pj=None):
        return lambda: search.rank_sum_step(pose, audio, st, ln, prev, q, preselect=pre, threads=th,
                                            pose_f16=f16, pose_proj=pj)

    # one window start per segment, as a step's pre-selection picks (s = 1 .. L - N), and a
    # pre-selection table of independent distances for the ranker
    win_starts = st + rng.integers(1, L - N + 1, M)
    table_dp = rng.random(M, dtype=np.float32)
    table_da = rng.random(M)
    flat24 = proj.blocks.reshape(-1)
    flat24h = proj16.blocks.view(np.float32).reshape(-1)  # the same bytes: only the read is timed
    fns = {
        "floor C++ 2 threads": lambda: floors.stream_sum_f32(pose, 2),
        "floor C++ 1 thread": lambda: floors.stream_sum_f32(pose, 1),
        "floor numpy sum": lambda: pose.sum(),
        "floor 24-wide 2 thr": lambda: floors.stream_sum_f32(flat24, 2),
        "floor 24 f16 2 thr": lambda: floors.stream_sum_f32(flat24h, 2),
        "step pose": step("pose"),
        "step pose 1 thread": step("pose", 1),
        "step pose HalfPose": step("pose", f16=half),
        "step pose Projection": step("pose", pj=proj),
        "step pose Proj 1 thr": step("pose", 1, pj=proj),
        "step pose Proj f16": step("pose", pj=proj16),
        "step pose Proj f16 1t": step("pose", 1, pj=proj16),
        "step audio": step("audio"),
        # what every exact step must read besides the stream, once a filter has named each
        # segment's pre-selected candidate: its audio window (and, to rank by pose, its row)
        "floor 1 window/seg": lambda: floors.gather_sum_f32(audio, win_starts, N, 2),
        "floor 1 pose row/seg": lambda: floors.gather_sum_f32(pose, win_starts - 1, 1, 2),
        "rank a table": lambda: _core.rank_table(st, table_dp, table_da, 1),
    }
    res = interleaved(fns, args.reps)
    print("\n(a)+(c) one step; median (min) over %d interleaved repetitions:" % args.reps)
    for k, (med, mn) in res.items():
        print(f"  {k:<22s} {1e3 * med:8.2f} ms  ({1e3 * mn:.2f})")
    floor = min(res["floor C++ 2 threads"][0], res["floor C++ 1 thread"][0], res["floor numpy sum"][0])
    floor1 = min(res["floor C++ 1 thread"][0], res["floor numpy sum"][0])
    print(f"  read floor (fastest full read of the pose matrix) {1e3 * floor:.2f} ms "
          f"= {pose.nbytes / floor / 1e9:.1f} GB/s")
    step_pose = res["step pose"][0]
    print(f"  step/floor: pose {step_pose / floor:.2f}, pose with HalfPose "
          f"{res['step pose HalfPose'][0] / floor:.2f}, audio {res['step audio'][0] / floor:.2f}; "
          f"single-thread pose step / single-thread floor {res['step pose 1 thread'][0] / floor1:.2f}")
    exact = search.rank_sum_step(pose, audio, st, ln, prev, q)

    def same_as_exact(**kw):
        return search.rank_sum_step(pose, audio, st, ln, prev, q, **kw) == exact

    print(f"  HalfPose step returns the same StepResult: {same_as_exact(pose_f16=half)}")
    step_proj = res["step pose Projection"][0]
    floor24 = res["floor 24-wide 2 thr"][0]
    print(f"  PoseProjection: step {1e3 * step_proj:.2f} ms = today's pose step / {step_pose / step_proj:.2f} "
          f"(1 thread: / {res['step pose 1 thread'][0] / res['step pose Proj 1 thr'][0]:.2f}); "
          f"step / 24-wide floor {step_proj / floor24:.2f}; {DP}-wide floor / 24-wide floor "
          f"{res['floor C++ 2 threads'][0] / floor24:.2f}")
    print(f"  PoseProjection step returns the same StepResult: {same_as_exact(pose_proj=proj)}")
    step16, floor16 = res["step pose Proj f16"][0], res["floor 24 f16 2 thr"][0]
    print(f"  PoseProjection in binary16 (Searcher's default): step {1e3 * step16:.2f} ms = today's pose step / "
          f"{step_pose / step16:.2f} (1 thread: / {res['step pose 1 thread'][0] / res['step pose Proj f16 1t'][0]:.2f}),"
          f" float32 projection step / {step_proj / step16:.2f}; step / its floor {step16 / floor16:.2f}")
    print(f"  binary16 PoseProjection step returns the same StepResult: {same_as_exact(pose_proj=proj16)}")
    window, row, rank = (res[k][0] for k in ("floor 1 window/seg", "floor 1 pose row/seg", "rank a table"))
    least = floor16 + window + rank
    print(f"  floor of an exact step of this design (each segment's candidate from the binary16 stream, its "
          f"float32 audio window, the ranker): stream {1e3 * floor16:.2f} + one audio window "
          f"per segment {1e3 * window:.2f} + rank {1e3 * rank:.2f} = {1e3 * least:.2f} ms; with one pose row "
          f"per segment ({1e3 * row:.2f}) {1e3 * (least + row):.2f} ms. The step is {step16 / least:.2f}x "
          f"the first; {-(-FPS * SECONDS // N)} steps at it would be {SECONDS / (-(-FPS * SECONDS // N) * least):.0f}x "
          f"real time (the goals: 1.5 ms, 500x)")
    print("  (a pose step reads the entry frames of every candidate, 56 of every 64 rows of the\n"
          "   pose matrix, and one audio window per segment; an audio step reads the audio matrix\n"
          "   and one pose row per segment)")

    # --- (b) numpy baseline -----------------------------------------------------
    # numpy allocates several temporaries of the pose matrix's size; whether the
    # allocator returns fresh (page-faulting) memory varies from run to run, so
    # its best of 5 is reported: the ratio is a lower bound
    print("\n(b) the same step in vectorised numpy (best of 5):")
    for pre in ("pose", "audio"):
        t_np = []
        for _ in range(5):
            t = time.perf_counter()
            m_np, s_np = numpy_step(pose, audio, prev, q, pre)
            t_np.append(time.perf_counter() - t)
        r = search.rank_sum_step(pose, audio, st, ln, prev, q, preselect=pre)
        same = (r.segment, r.start) == (m_np, s_np)
        t_step = res[f"step {pre}"][0]
        extra = (f"   numpy/PoseProjection step = {min(t_np) / step_proj:6.1f}x (binary16 "
                 f"{min(t_np) / step16:.1f}x)" if pre == "pose" else "")
        print(f"  numpy {pre:5s} {1e3 * min(t_np):8.1f} ms (median {1e3 * np.median(t_np):.1f})   "
              f"numpy/step = {min(t_np) / t_step:6.1f}x{extra}   same choice: {same}")

    # --- (d) real-time factor ---------------------------------------------------
    T = FPS * SECONDS
    query = rng.standard_normal((T, DA), dtype=np.float32)
    print(f"\n(d) {SECONDS} s at {FPS} fps = {T} frames, {-(-T // N)} steps of N = {N}:")
    for label, f16, pj in (("", None, None), (" with HalfPose", half, None),
                           (" with PoseProjection", None, proj),
                           (" with PoseProjection in binary16", None, proj16)):
        t_syn = []
        for _ in range(5):
            t = time.perf_counter()
            search.rank_sum_search(pose, audio, st, ln, query, prev, step=N, pose_f16=f16, pose_proj=pj)
            t_syn.append(time.perf_counter() - t)
        t_syn = float(np.median(t_syn))
        print(f"  search{label}: {1e3 * t_syn:.1f} ms, real-time factor {t_syn / SECONDS:.4f} "
              f"({SECONDS / t_syn:.0f}x faster than real time)")

    if args.skip_batch:
        return
    # --- (e) batched search over every segment's audio --------------------------
    queries = [audio[s:s + L] for s in st]
    init = pose[rng.integers(0, M * L, M)]
    sub = np.linspace(0, M - 1, args.loop_subset).astype(int)
    c0, t = cpu_seconds(), time.perf_counter()
    loop = [search.rank_sum_search(pose, audio, st, ln, queries[i], init[i], step=N) for i in sub]
    t_loop = (time.perf_counter() - t) / len(sub)
    cpu_loop = (cpu_seconds() - c0) / len(sub)
    print(f"\n(e) all {M} segments' audio as queries ({L} frames = {L // N} steps each), "
          f"pose pre-selection:")
    print(f"  loop of single searches: {1e3 * t_loop:.0f} ms per query, timed on {len(sub)} "
          f"queries and EXTRAPOLATED to {M}: {t_loop * M:.0f} s ({cpu_loop * M:.0f} CPU s)")
    # without and with the projection, interleaved (the machine is shared)
    runs = {"plain": [], "proj": []}
    for _ in range(args.batch_reps):
        for key, pj in (("plain", None), ("proj", proj)):
            c0, t = cpu_seconds(), time.perf_counter()
            res_b = search.rank_sum_search_batch(pose, audio, st, ln, queries, init, step=N, pose_proj=pj)
            runs[key].append((time.perf_counter() - t, cpu_seconds() - c0))
            if key == "plain":
                batch = res_b
            else:
                batch_p = res_b
    t_batch, cpu_batch = (float(np.median([r[i] for r in runs["plain"]])) for i in (0, 1))
    t_bp, cpu_bp = (float(np.median([r[i] for r in runs["proj"]])) for i in (0, 1))
    fields = ("segments", "starts", "frames", "pose_dist", "audio_dist", "pose_rank", "audio_rank",
              "n_candidates")
    same = all(all(np.array_equal(getattr(batch[i], f), getattr(r, f)) for f in fields)
               for i, r in zip(sub, loop))
    med = " (median of %d)" % args.batch_reps if args.batch_reps > 1 else ""
    print(f"  batched (measured on all {M}){med}: {t_batch:.1f} s wall, {cpu_batch:.1f} CPU s "
          f"({cpu_batch / max(t_batch, 1e-9):.2f} cores busy); loop/batch = {t_loop * M / t_batch:.1f}x; "
          f"same results on the timed subset: {same}")
    same_p = all(all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields)
                 for a, b in zip(batch, batch_p))
    print(f"  batched with PoseProjection{med}: {t_bp:.1f} s wall, {cpu_bp:.1f} CPU s; "
          f"without/with = {t_batch / t_bp:.2f}x (CPU {cpu_batch / max(cpu_bp, 1e-9):.2f}x); "
          f"identical to the batch without it on all {M} queries: {same_p}")
    c0, t = cpu_seconds(), time.perf_counter()
    batch_a = search.rank_sum_search_batch(pose, audio, st, ln, queries, init, step=N, preselect="audio")
    t_ba = time.perf_counter() - t
    cpu_ba = cpu_seconds() - c0
    one = search.rank_sum_search(pose, audio, st, ln, queries[sub[1]], init[sub[1]], step=N,
                                 preselect="audio")
    print(f"  batched, audio pre-selection: {t_ba:.1f} s wall, {cpu_ba:.1f} CPU s; "
          f"matches a single search: {np.array_equal(batch_a[sub[1]].frames, one.frames)}")


if __name__ == "__main__":
    main()
