"""Motion graph at the paper's scale: 6,000 clips of 1-10 s (synthetic arrays), 60 s of speech.

    python benchmarks/bench_graph.py [--clips 6000] [--threads 2] [--edges-clips 20000] [--skip-dense]
                                     [--scheduler local:2|tcp://HOST:PORT]

Measures, in one run:
- graph build: the upper-body and the lower-body graph (Sec. 4.1; 46 and 9 of the 55
  joints, as BEAT2's SMPL-X split): transition features + the K x K cost table by BLAS +
  the edge rule, each; against a row-by-row numpy baseline (one clip against all others per iteration, the
  shape a "loop over clip pairs" takes once its inner loop is vectorised) timed on a
  sample of rows and scaled to all K rows;
- synthesis of 60 s (20 target clips of 3 s): data term, both searches (upper body:
  data and transitions; lower body: duration fit and transitions) and both time-warped
  assemblies through assemble_pieces, joined; against the same recurrence written as a plain
  Python loop over every node's in-edges (timed on one step, scaled to all steps);
- the build's edge search over --edges-clips clips with the structure of real poses: dense
  against bounded (the projection bounds of gesturedb.db.graph), with a check that the edges
  are identical; with --scheduler, the bounded search also as Dask tasks (the cluster started
  before the clock, the features' scatter to every worker timed), against the local threads.
"""
from __future__ import annotations

import argparse
import os
import time


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clips", type=int, default=6000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--joints", type=int, default=55)
    ap.add_argument("--edges-clips", type=int, default=20000,
                    help="also time the edge search over this many structured clips, dense against bounded (0: skip)")
    ap.add_argument("--skip-dense", action="store_true", help="time only the bounded edge search at --edges-clips")
    ap.add_argument("--scheduler", default=None, help="also run the bounded edge search on this Dask scheduler")
    args = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", str(args.threads))
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import numpy as np

    from gesturedb import rotations as R
    from gesturedb.db import edges as E
    from gesturedb.db import graph as G
    from gesturedb.motion import Skeleton
    from gesturedb.synth.assemble import Piece, assemble_pieces
    from gesturedb.synth.graph import viterbi

    rng = np.random.default_rng(0)
    K, J, m, fps = args.clips, args.joints, G.TRANSITION_FRAMES, 15.0
    lengths = rng.integers(int(1 * fps), int(10 * fps) + 1, K)
    # only the transition frames of each clip matter for the graph: 2 m frames per clip
    n_tf = 2 * m * K
    pos = rng.normal(scale=0.3, size=(n_tf, J, 3))
    root = rng.normal(scale=0.1, size=(n_tf, 3))
    rot = R.normalize(rng.normal(size=(n_tf, J, 4)) * [4, 1, 1, 1])
    ends = np.arange(K * m).reshape(K, m)
    starts = K * m + ends

    upper, lower = np.arange(9, J), np.arange(9)  # root + 8 leg joints, as SMPL-X
    t0 = time.perf_counter()
    exl = G.transition_features(pos, rot, root, ends, joints=lower, part="lower")
    sxl = G.transition_features(pos, rot, root, starts, joints=lower, part="lower")
    low_graph = E.edges_from_costs(E.transition_costs(exl, sxl))[:3]
    ex = G.transition_features(pos, rot, root, ends, joints=upper, part="upper")
    sx = G.transition_features(pos, rot, root, starts, joints=upper, part="upper")
    T = E.transition_costs(ex, sx)
    indptr, indices, cost, dT = E.edges_from_costs(T)
    t_build = time.perf_counter() - t0

    rows = 200
    t0 = time.perf_counter()
    base = np.empty((rows, K))
    for p in range(rows):
        base[p] = ((ex[p] - sx) ** 2).sum(1)
    t_base = (time.perf_counter() - t0) * K / rows * 2  # two graphs (the lower one's rows are shorter: generous)
    base[np.arange(rows), np.arange(rows)] = np.inf  # edges_from_costs set the diagonal to +inf
    assert np.allclose(base, T[:rows], rtol=1e-4, atol=1e-4)

    # -- synthesis of 60 s: 20 target clips of 3 s -------------------------------------
    n = 20
    target = np.full(n, int(3 * fps))
    style = rng.random((K, 3))
    style_in = rng.random((n, 3))
    rhythm = rng.integers(0, 2 ** 32, K, dtype=np.uint64).astype(np.uint32)
    rhythm_in = rng.integers(0, 2 ** 32, n, dtype=np.uint64).astype(np.uint32)
    from gesturedb.features.rhythm import hamming

    J_out = J
    sk = Skeleton(names=[f"j{i}" for i in range(J_out)], parents=np.arange(-1, J_out - 1),
                  offsets=np.tile([0.0, 0.1, 0.0], (J_out, 1)), channel_orders=["ZXY"] * J_out, end_sites={})
    src_rot = R.normalize(rng.normal(size=(int(11 * fps) + 2, J_out, 4)))
    src_root = rng.normal(size=(src_rot.shape[0], 3))

    def synth():
        g_z = np.linalg.norm(style_in[:, None] - style[None], axis=-1)
        g_r = hamming(rhythm_in[:, None], rhythm[None]).astype(np.float64)
        ratio = lengths[None] / target[:, None]
        unary = 1.0 * g_z + 0.1 * g_r + 0.5 * np.abs(np.log(ratio))
        path, c = viterbi(unary, indptr, indices, cost, w_data=1.0, w_trans=3.0)
        path_low, _ = viterbi(0.5 * np.abs(np.log(ratio)), *low_graph, w_data=1.0, w_trans=3.0)
        motions = []
        for p in (path, path_low):
            pieces, a = [], 0
            for i, d in enumerate(p):
                speed = float(np.clip(ratio[i, d], 0.8, 1.25))
                t = np.arange(target[i]) * speed
                f0 = np.floor(t).astype(int)
                w = (t - f0)[:, None]
                r = R.slerp(src_rot[f0], src_rot[f0 + 1], np.broadcast_to(w, (len(t), J_out)))
                pieces.append(Piece(out_start=a, rotations=r, root=(1 - w) * src_root[f0] + w * src_root[f0 + 1],
                                    lead_in=(src_rot[:4], src_root[:4]) if a else None))
                a += int(target[i])
            motions.append(assemble_pieces(sk, fps, pieces, n_frames=a))
        rot_out = motions[1].rotations.copy()
        rot_out[:, upper] = motions[0].rotations[:, upper]
        return path, unary, rot_out

    synth()  # warm-up (imports)
    reps = 5
    t0 = time.perf_counter()
    for _ in range(reps):
        path, unary, motion = synth()
    t_synth = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    path_v, _ = viterbi(unary, indptr, indices, cost, w_data=1.0, w_trans=3.0)
    t_vit = time.perf_counter() - t0

    # baseline: the same recurrence as a plain Python loop over every node's in-edges,
    # timed on one step and scaled to the n - 1 steps (checked against viterbi on 2 clips)
    src = np.repeat(np.arange(K), np.diff(indptr))
    order = np.lexsort((src, indices))
    in_ptr = np.concatenate([[0], np.cumsum(np.bincount(indices, minlength=K))])
    s_src, s_cost = src[order].tolist(), (3.0 * cost[order]).tolist()
    acc0 = unary[0].tolist()
    t0 = time.perf_counter()
    acc1, back1 = [], []
    for q in range(K):
        best, arg = float("inf"), -1
        for e in range(in_ptr[q], in_ptr[q + 1]):
            c = acc0[s_src[e]] + s_cost[e]
            if c < best:
                best, arg = c, s_src[e]
        acc1.append(best + unary[1, q])
        back1.append(arg)
    t_dense = (time.perf_counter() - t0) * (n - 1)
    d = int(np.argmin(acc1))
    p2, _ = viterbi(unary[:2], indptr, indices, cost, w_data=1.0, w_trans=3.0)
    assert [back1[d], d] == p2.tolist(), "loop baseline disagrees"

    E = indices.shape[0]
    print(f"clips K = {K} ({lengths.sum() / fps / 3600:.1f} h of motion), joints {J}, edges E = {E} "
          f"({E / K:.1f} per clip, delta_T = {dT:.3g}) in the upper-body graph, BLAS threads {args.threads}")
    print(f"graph build (both): {t_build:7.3f} s   (row-by-row numpy baseline {t_base:7.3f} s, "
          f"{t_base / t_build:5.1f}x)  goal < 10 s")
    print(f"60 s synthesis:  {t_synth * 1e3:7.1f} ms  (search {t_vit * 1e3:.1f} ms; Python-loop "
          f"baseline {t_dense * 1e3:.0f} ms, {t_dense / t_vit:.0f}x slower)  goal < 100 ms")
    print(f"output frames {motion.shape[0]}; lower-body graph {low_graph[1].shape[0]} edges")
    if args.edges_clips:
        edges_at_scale(args.edges_clips, dense=not args.skip_dense, scheduler=args.scheduler)


def edges_at_scale(K: int, D: int = 644, dense: bool = True, scheduler=None) -> None:
    """The build's edge search (edges_from_features) over K clips, dense against bounded.

    The random clips above have no structure, which no bound can use (every column is kept:
    the bounded path falls back to the dense one there). Real clip boundaries are poses: on
    BEAT2's 1,904 frames, 8 / 16 / 32 principal directions hold 95 / 98 / 99.4 % of the
    upper-body features' variance. These synthetic features have that shape (95 / 98 / 99 %: a
    24-dimensional latent pose with a decaying spectrum through a tanh, plus 2 % noise), D = 644
    as BEAT2's upper body over 2 transition frames.
    """
    import numpy as np

    from gesturedb.db import edges as E

    rng = np.random.default_rng(1)
    h = rng.normal(size=(2 * K, 24)) * 0.8 ** np.arange(24)
    x = np.tanh(h @ rng.normal(size=(24, D)) / 3) + 0.02 * rng.normal(size=(2 * K, D))
    a, b = x[:K], x[K:]
    del x
    xs = np.concatenate([a[::max(1, K // 20000)], b[::max(1, K // 20000)]])
    w = np.linalg.eigvalsh(np.cov(xs.T))[::-1]
    print(f"\nedges of {K} clips x {D} features (synthetic poses: variance in 8 / 16 / 32 directions "
          f"{w[:8].sum() / w.sum():.3f} / {w[:16].sum() / w.sum():.3f} / {w[:32].sum() / w.sum():.3f})")
    n_pairs = []
    pairs = E._GriddedCosts.pairs
    E._GriddedCosts.pairs = lambda self, i, j: n_pairs.append(i.size) or pairs(self, i, j)
    t0 = time.perf_counter()
    got = E.edges_from_features(a, b, method="bounded")
    t_b = time.perf_counter() - t0
    E._GriddedCosts.pairs = pairs
    print(f"  bounded ({E.BOUND_DIMS} directions): {t_b:7.1f} s, exact costs {sum(n_pairs[1:]) / K:.1f} per "
          f"clip for {got[1].shape[0] / K:.1f} edges per clip")
    if scheduler is not None:
        from gesturedb.db.cluster import dask_client

        with dask_client(scheduler) as client:
            n = sum(client.nthreads().values())
            t0 = time.perf_counter()
            on = E.edges_from_features(a, b, method="bounded", scheduler=client)
            t_c = time.perf_counter() - t0
        same = all(np.array_equal(u, v) for u, v in zip(on, got))
        print(f"  bounded on Dask ({n} worker threads): {t_c:7.1f} s; local threads / Dask = {t_b / t_c:.2f}x; "
              f"identical edges: {same}")
    if dense:
        t0 = time.perf_counter()
        want = E.edges_from_features(a, b, method="dense")
        t_d = time.perf_counter() - t0
        same = all(np.array_equal(u, v) for u, v in zip(want[:3], got[:3])) and want[3] == got[3]
        print(f"  dense: {t_d:7.1f} s; dense / bounded = {t_d / t_b:.1f}x; identical edges: {same}")


if __name__ == "__main__":
    main()
