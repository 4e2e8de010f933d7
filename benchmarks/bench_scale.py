"""Sharded pose step on a LocalCluster of 2 workers against one process (run by hand).

Database: synthetic structured motion (benchmarks/bench_search.py: motion_pose)
of --frames frames (default 5,000,000, about 93 hours at 15 fps) in 64-frame
segments, 96-wide pose and 14-wide audio features. Prints, in one run, the
median latency of one pose step
  - in this process through the PoseProjection filter in binary16 (2 threads and 1 thread),
  - through ShardedSearch: 2 shards on a LocalCluster of 2 single-threaded
    worker processes, each shard with its own PoseProjection, merged here from
    the shards' top lists (one round trip: a call to each shard's actor, merge),
  - the same shards merged from their whole tables, as ShardedSearch did
    before the top lists (2 table calls, rank every row, 1 row fetch),
and checks that all choose the same window. Memory per frame of each format
is printed too. Then a batch of --batch queries (the database's own segment
audio, 8 steps each, as the refiner's training data): rank_sum_search_batch in
this process (2 threads), ShardedSearch.search_batch (all queries step by step
together, blocked tables on each shard), and the same queries searched one
after another over the shards (what search_batch did before); same results.

Usage:  python benchmarks/bench_scale.py [--frames 5000000] [--reps 15] [--batch 64]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_search import DA, DP, interleaved, motion_pose  # noqa: E402
from gesturedb import search  # noqa: E402
from gesturedb.db.shards import ShardedSearch, top_rows  # noqa: E402

L, N = 64, 8


def scale_db(rng, frames: int):
    """The benchmark's database of about ``frames`` frames: synthetic motion (a recording per 4,000
    frames) and i.i.d. audio, in 64-frame segments: (pose, audio, seg_start, seg_len)."""
    M = frames // L
    F = M * L
    t = time.perf_counter()
    pose = motion_pose(rng, F, n_rec=max(1, F // 4000))
    audio = rng.standard_normal((F, DA), dtype=np.float32)
    st = np.arange(M, dtype=np.int64) * L
    ln = np.full(M, L, np.int64)
    print(f"{F} frames ({F / 15 / 3600:.0f} h at 15 fps), {M} segments; generated in {time.perf_counter() - t:.0f} s")
    return pose, audio, st, ln


def tables_step(sh, q, prev):
    """One pose step over ``sh``'s shards merged from their whole tables (the baseline): every
    shard's table to the client, ranked there, then a second call for the next pose."""
    m, start = sh._whole_tables(prev, q, "pose", None, None, 1)[:2]
    sh._row(m, int(sh.seg_start[m] + start) + q.shape[0] - 1)
    return m, start


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=5_000_000)
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--batch", type=int, default=64)
    args = ap.parse_args(argv)
    from distributed import Client

    from gesturedb.db.cluster import local_cluster

    rng = np.random.default_rng(0)
    pose, audio, st, ln = scale_db(rng, args.frames)
    F, M = pose.shape[0], st.shape[0]
    t = time.perf_counter()
    proj = search.PoseProjection(pose, half=True)  # as ShardedSearch and Searcher use it
    t_proj = time.perf_counter() - t
    print(f"memory per frame: pose {4 * DP} B, projection {proj.blocks.nbytes / F:.0f} B, audio {4 * DA} B; "
          f"PoseProjection built in {t_proj:.1f} s ({1e9 * t_proj / F:.0f} ns/frame)")
    prev = pose[12345].copy()
    q = rng.standard_normal((N, DA), dtype=np.float32)

    # as `synth --scheduler local:2` starts it
    with local_cluster(2, memory_limit=0) as cluster, Client(cluster) as client:
        t = time.perf_counter()
        sh = ShardedSearch(pose, audio, st, ln, client=client, parts=2, threads=1)
        client.gather(sh.shards)
        print(f"2 shards resident on 2 worker processes in {time.perf_counter() - t:.1f} s")
        fns = {
            "one process, 2 threads": lambda: search.rank_sum_step(pose, audio, st, ln, prev, q, pose_proj=proj),
            "one process, 1 thread": lambda: search.rank_sum_step(pose, audio, st, ln, prev, q, pose_proj=proj,
                                                                  threads=1),
            "2 shards on 2 workers": lambda: sh.search(q, prev, step=N),
            "2 shards, whole tables": lambda: tables_step(sh, q, prev),
        }
        res = interleaved(fns, args.reps)
        print(f"\none pose step, median (min) over {args.reps} interleaved repetitions:")
        for k, (med, mn) in res.items():
            print(f"  {k:<24s} {1e3 * med:8.1f} ms  ({1e3 * mn:.1f})")
        base = res["one process, 2 threads"][0]
        print(f"  sharded / one process (2 threads): {res['2 shards on 2 workers'][0] / base:.2f}; "
              f"per frame: {1e9 * base / F:.2f} ns (one process), "
              f"{1e9 * res['2 shards on 2 workers'][0] / F:.2f} ns (sharded)")
        a = search.rank_sum_step(pose, audio, st, ln, prev, q, pose_proj=proj)
        b = sh.search(q, prev, step=N)
        print(f"  sharded, top lists / whole tables: "
              f"{res['2 shards on 2 workers'][0] / res['2 shards, whole tables'][0]:.2f}; "
              f"steps the top lists (L = {top_rows(M)}) did not settle: {sh.unsettled} of {sh.steps}")
        same = (a.segment, a.start) == (int(b.segments[0]), int(b.starts[0])) == tables_step(sh, q, prev)
        print(f"  same choice: {same}")
        # a whole search (pose and audio ranks independent here: the lists' worst case)
        query = rng.standard_normal((24 * 15, DA), dtype=np.float32)
        sh.steps = sh.unsettled = 0
        whole = sh.search(query, prev, step=N)
        ref = search.rank_sum_search(pose, audio, st, ln, query, prev, step=N, pose_proj=proj)
        print(f"  24 s search over the shards: {sh.unsettled} of {sh.steps} steps not settled by the lists; "
              f"same windows as one process: {bool((whole.frames == ref.frames).all())}")

        B = args.batch
        idx = np.linspace(0, M - 1, B).astype(int)
        queries = [audio[st[i]:st[i] + L] for i in idx]
        init = pose[rng.integers(0, F, B)]
        ex = np.zeros((B, M), bool)
        ex[np.arange(B), idx] = True
        t = time.perf_counter()
        local = search.rank_sum_search_batch(pose, audio, st, ln, queries, init, step=N, exclude=ex, pose_proj=proj)
        t_local = time.perf_counter() - t
        sh.steps = sh.unsettled = 0
        t = time.perf_counter()
        together = sh.search_batch(queries, init, step=N, exclude=ex)
        t_together = time.perf_counter() - t
        unsettled, steps = sh.unsettled, sh.steps
        t = time.perf_counter()
        one_by_one = [sh.search(queries[i], init[i], step=N, exclude=ex[i]) for i in range(B)]
        t_one = time.perf_counter() - t
        same = all((a.frames == b.frames).all() and (a.frames == c.frames).all()
                   for a, b, c in zip(local, together, one_by_one))
        print(f"\nbatch of {B} queries x {L // N} steps (each segment's own audio, its segment excluded):")
        print(f"  one process, rank_sum_search_batch  {t_local:7.1f} s")
        print(f"  2 shards, search_batch (together)   {t_together:7.1f} s  ({t_together / t_local:.2f} x one process)")
        print(f"  2 shards, one query after another   {t_one:7.1f} s  ({t_one / t_together:.2f} x together)")
        print(f"  query steps of search_batch the top lists did not settle: {unsettled} of {steps}; "
              f"same results: {same}")
        sh.close()


if __name__ == "__main__":
    main()
