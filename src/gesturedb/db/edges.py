"""The motion graph's edges: exact transition costs and each clip's cheapest transitions.

The costs ``T(p, q) = |end_x[p] - start_x[q]|^2`` are over the clips' transition features
(:func:`gesturedb.db.graph.transition_features`), rounded to a power-of-two grid on which a
float64 product is exact (:func:`_on_grid`), so the costs, and the edges, are the same bits
whatever the BLAS kernel and the CPU.

Edges. ``p -> q`` exists where ``T(p, q) < delta_T``; ``delta_T`` defaults to the
``delta_quantile`` (10 %) quantile of all off-diagonal costs of the database (from a
fixed strided sample of at most 10^6 pairs), because the paper's ``delta_T = 8`` belongs to
its own units. Of those, every node keeps at most its ``max_out`` (32) cheapest, so the
search stays ``O(n K max_out)`` on large databases; and every node keeps its ``min_out``
(4) cheapest out-edges whatever ``delta_T``, so a small database never falls apart into
nodes without a way on. There are no self-edges: the graph itself never plays a clip twice in a
row (the back-to-back repeat rule), which also means the output never loops on one clip.

The search computes every cost a block of rows at a time (memory grows with K), and from
:data:`BOUND_MIN_K` clips on bounds them first from a few principal directions
(:class:`_ProjectedBounds`), computing exactly only the pairs that can still be an edge:
the same edges bit for bit. There the blocks also run on threads (:data:`EDGE_THREADS`), or,
given a Dask scheduler, as tasks on its workers.
"""
from __future__ import annotations

import contextlib
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from gesturedb.db.cluster import iter_on_cluster, optional_client, worker_threads
from gesturedb.errors import ParameterError
from gesturedb.threads import available_cpus

DELTA_QUANTILE = 0.10
MIN_OUT = 4
MAX_OUT = 32
#: principal directions of the bounded edge search (:class:`_ProjectedBounds`)
BOUND_DIMS = 32
#: clips from which ``edges_from_features`` bounds the costs instead of computing them all
BOUND_MIN_K = 4096
#: threads the edge search runs its blocks of rows on (at most the CPUs this process may use), from BOUND_MIN_K clips on
EDGE_THREADS = 8


def _on_grid(*xs: np.ndarray, compact: bool = False) -> tuple[list[np.ndarray], float]:
    """The arrays (n_i, D) in units of a power of two ``u``, rounded to integers, and ``u``.

    ``compact``: float32 arrays where they hold every integer exactly (``e <= 24``: D >= 3),
    rounded a chunk of rows at a time, so no float64 copy of the whole array is ever made.

    ``u`` is chosen from the largest magnitude over all of them (one unit, so that their norms
    and products add up exactly) so that every value is at most ``2^e`` units
    with ``4 D 4^e <= 2^53``: every product of two of them, every partial sum of D such
    products, and ``|a|^2 + |b|^2 - 2 a.b``, are integers below ``2^53``, so a float64
    matrix product computes them exactly in any order, with or without FMA. That makes the
    result independent of the BLAS kernel (and of the CPU that picks it). The rounding
    moves a value by at most ``u / 2``: ``2^-(e+1)`` of the largest magnitude (``e = 20``,
    5e-7, for the ~760 columns of BEAT2's transition features).
    """
    amax = max((float(np.abs(x).max()) for x in xs if x.size), default=0.0)
    u, dtype = _grid_unit(int(xs[0].shape[1]), amax, compact)
    if dtype == np.float64:
        return [np.rint(np.asarray(x, dtype=np.float64) / u) for x in xs], u
    out = []
    for x in xs:
        g = np.empty(x.shape, dtype=dtype)
        for s0 in range(0, x.shape[0], 8192):
            g[s0:s0 + 8192] = np.rint(np.asarray(x[s0:s0 + 8192], dtype=np.float64) / u)
        out.append(g)
    return out, u


def _grid_unit(D: int, amax: float, compact: bool = False) -> tuple[float, type]:
    """:func:`_on_grid`'s unit ``u`` for D columns whose largest magnitude is ``amax``, and the
    dtype of the rounded values (float32 with ``compact`` where it holds them exactly)."""
    if not np.isfinite(amax):
        raise ParameterError(f"features of an exact product (graph costs, style model): expected finite values, "
                             f"got {amax}")
    e = (51 - int(np.ceil(np.log2(max(D, 1))))) // 2
    dtype = np.float32 if compact and e <= 24 else np.float64
    if amax == 0.0:
        return 1.0, dtype
    _, ex = np.frexp(amax)  # amax < 2^ex
    return float(np.ldexp(1.0, int(ex) - e)), dtype


def transition_costs(end_x: np.ndarray, start_x: np.ndarray) -> np.ndarray:
    """Dense ``T[p, q] = |end_x[p] - start_x[q]|^2`` (K, K), float64, the same bits on every machine.

    One float64 matrix product (BLAS) over the features on :func:`_on_grid`'s grid, where
    it is exact; ``T >= 0`` holds exactly.
    """
    g = _GriddedCosts(end_x, start_x)
    return g.rows(0, g.K)


class _GriddedCosts:
    """Rows of ``|end_x[p] - start_x[q]|^2`` from the features on :func:`_on_grid`'s grid: any
    block of rows is exact, so it is the whole table's bit for bit.

    ``a``, ``b``: the grid's integers, in float32 when that holds them exactly (from 3 features
    on, see :func:`_on_grid`), else float64. Half the memory of float64 (the upper-body features
    of 1.2M clips are 3 GB each then), and half the bytes of the gathers that dominate
    :meth:`pairs`; every product and sum is still computed in float64.
    """

    def __init__(self, end_x: np.ndarray, start_x: np.ndarray):
        (a, b), u = _on_grid(np.asarray(end_x), np.asarray(start_x), compact=True)
        self._set(a, b, u)

    @classmethod
    def from_grid(cls, a: np.ndarray, b: np.ndarray, u: float) -> "_GriddedCosts":
        """From the grid's integers and its unit (features gridded elsewhere, a chunk at a time)."""
        g = cls.__new__(cls)
        g._set(a, b, u)
        return g

    def _set(self, a: np.ndarray, b: np.ndarray, u: float) -> None:
        self.K = a.shape[0]
        self.na = np.einsum("ij,ij->i", a, a, dtype=np.float64)
        self.nb = np.einsum("ij,ij->i", b, b, dtype=np.float64)
        self.uu = u * u
        self.a, self.b = a, b
        self._b64 = None  # b in float64 for the BLAS product of rows(), made on its first call

    def __getstate__(self):
        # the float64 copy of b is remade where it is needed (a Dask worker): not shipped
        return {**self.__dict__, "_b64": None}

    def rows(self, r0: int, r1: int) -> np.ndarray:
        if self._b64 is None:
            self._b64 = self.b.astype(np.float64)
        T = self.a[r0:r1].astype(np.float64) @ self._b64.T
        T *= -2.0
        T += self.na[r0:r1, None]
        T += self.nb[None, :]
        T *= self.uu
        return T

    def pairs(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """T[i, j] for index arrays, by elementwise products and sums (exact as well)."""
        out = np.empty(i.shape[0])
        for s0 in range(0, i.shape[0], 4096):
            ii, jj = i[s0:s0 + 4096], j[s0:s0 + 4096]
            # products and sums in float64, where every one is exact (einsum's order of
            # summation is not numpy's sum's; it does not matter)
            dot = np.einsum("ij,ij->i", self.a[ii], self.b[jj], dtype=np.float64)
            out[s0:s0 + 4096] = (self.na[ii] + self.nb[jj] - 2.0 * dot) * self.uu
        return out


def edges_from_costs(T: np.ndarray, *, delta_T: float | None = None, delta_quantile: float = DELTA_QUANTILE,
                     min_out: int = MIN_OUT, max_out: int = MAX_OUT):
    """CSR edges (no self-edges): each node's ``T < delta_T`` among its ``max_out`` cheapest, plus its ``min_out`` cheapest.

    ``T`` is modified (its diagonal set to +inf). Ties at the cut are broken by target index.
    ``delta_T`` None: the ``delta_quantile`` quantile of a strided sample of at most ~10^6
    off-diagonal costs.

    Returns
    -------
    indptr : int64 (K + 1,), indices : int64 (E,), cost : float64 (E,), delta_T : float
    """
    K = T.shape[0]
    np.fill_diagonal(T, np.inf)
    if delta_T is None:
        sample = T.reshape(-1)[_sample_pairs(K)]
        delta_T = _quantile(sample, delta_quantile)
    return _csr(K, [_block_csr(0, K, *_row_edges(T, 0, delta_T, min_out, max_out))]) + (float(delta_T),)


def edges_from_features(end_x: np.ndarray, start_x: np.ndarray, *, delta_T: float | None = None,
                        delta_quantile: float = DELTA_QUANTILE, min_out: int = MIN_OUT, max_out: int = MAX_OUT,
                        block_elems: int = 1 << 24, method: str = "auto", on_rows=None, scheduler=None):
    """``edges_from_costs(transition_costs(end_x, start_x), ...)`` without the K x K table.

    The costs are computed a block of rows at a time (about ``block_elems`` costs, 128 MB),
    each row's edges kept and the block dropped, so memory grows with K, not K^2 (the table of
    120,000 clips, about 100 hours, would be 115 GB). The sample for ``delta_T`` is the same
    pairs, computed first. The costs are exact on their grid (:func:`_on_grid`), so a block's
    values are those of the whole table bit for bit, and so are the edges.

    ``method``: ``"dense"`` computes every cost of a block (a product over all D features);
    ``"bounded"`` first bounds every cost from :data:`BOUND_DIMS` principal directions
    (:class:`_ProjectedBounds`) and computes exactly only the pairs that can still be among a
    row's ``max_out`` cheapest: the same edges bit for bit, for a float32 product over 34
    columns instead of D, and no selection over whole rows of exact costs (benchmarks/bench_graph.py,
    pose-like features: 2.4x faster at 20,000 clips of 644 features, 3.6x of 126, and the gap
    grows with K). Where the bounds keep too many columns to pay (features without
    low-dimensional structure, like i.i.d. noise), the blocks are computed densely from the first
    such block on. ``"auto"``: bounded from :data:`BOUND_MIN_K` clips on, when D > BOUND_DIMS + 2.

    ``on_rows(n)``, if given, is called after each block with its number of rows (a progress bar).

    ``scheduler`` (a ``distributed.Client``, ``"local:N"`` or ``"tcp://HOST:PORT"``): the blocks
    run as Dask tasks, a range of them each, with the features and bounds sent once to every
    worker; the same edges (``on_rows`` then hears of each task's rows).
    """
    return _edges(_GriddedCosts(end_x, start_x), delta_T=delta_T, delta_quantile=delta_quantile, min_out=min_out,
                  max_out=max_out, block_elems=block_elems, method=method, on_rows=on_rows, scheduler=scheduler)


def _edges(g: "_GriddedCosts", *, delta_T, delta_quantile: float = DELTA_QUANTILE, min_out: int = MIN_OUT,
           max_out: int = MAX_OUT, block_elems: int = 1 << 24, method: str = "auto", on_rows=None, scheduler=None):
    """edges_from_features over features already on their grid (the caller may drop its own copy).

    ``scheduler`` (a ``distributed.Client``, ``"local:N"`` or ``"tcp://HOST:PORT"``): the rows'
    blocks run as Dask tasks (:func:`_edges_on_cluster`) instead of on this machine's threads;
    the same edges.
    """
    if method not in ("auto", "dense", "bounded"):
        raise ParameterError(f"method: expected 'auto', 'dense' or 'bounded', got {method!r}")
    K = g.K
    if delta_T is None:
        i, j = np.divmod(_sample_pairs(K), K)
        sample = g.pairs(i, j)
        sample[i == j] = np.inf
        delta_T = _quantile(sample, delta_quantile)
    step = max(1, int(block_elems) // max(K, 1))
    k = min(int(max_out), K - 1)
    bounds = None
    if method == "bounded" or (method == "auto" and K >= BOUND_MIN_K and g.a.shape[1] > BOUND_DIMS + 2):
        bounds = _ProjectedBounds.fit(g, k)
    if scheduler is not None:
        parts = _edges_on_cluster(_Shared(g, bounds), step, delta_T, min_out, max_out, scheduler, on_rows)
    else:
        parts = _edges_here(_Shared(g, bounds), step, delta_T, min_out, max_out, on_rows)
    return _csr(K, parts) + (float(delta_T),)


class _Shared:
    """What every block of rows reads: the gridded features and their bounds (or None). One
    object, so that shipping it to a Dask worker sends ``g`` once (``bounds`` refers to it)."""

    def __init__(self, g: "_GriddedCosts", bounds: "_ProjectedBounds | None"):
        self.g, self.bounds = g, bounds

    def block(self, r0: int, r1: int, delta_T: float, min_out: int, max_out: int):
        """The edges of rows r0..r1 as :func:`_block_csr` pieces, bounded while the bounds pay,
        else dense."""
        b = self.bounds  # read once: another thread may drop it meanwhile
        if b is not None:
            got = b.edges(r0, r1, delta_T, min_out, max_out)
            if got is not None:
                return _block_csr(r0, r1, *got)
            self.bounds = None  # features without the structure bounds need: the rest densely too
        T = self.g.rows(r0, r1)
        d = np.arange(r0, r1)
        T[d - r0, d] = np.inf  # no self-edges
        return _block_csr(r0, r1, *_row_edges(T, r0, delta_T, min_out, max_out))


def _edges_here(shared: _Shared, step: int, delta_T: float, min_out: int, max_out: int, on_rows) -> list:
    """Every block's edges on this machine, in block order."""
    K = shared.g.K
    ranges = [(r0, min(K, r0 + step)) for r0 in range(0, K, step)]
    parts = []
    # blocks on threads when there are many (numpy releases the GIL in the passes over a
    # block, which run on one core each); the results are taken in order, so the edges do not
    # depend on the threads
    threads = min(available_cpus(), EDGE_THREADS) if K >= BOUND_MIN_K else 1

    def run(r: tuple[int, int]):
        return shared.block(*r, delta_T, min_out, max_out)

    with contextlib.ExitStack() as stack:
        results = map(run, ranges) if threads <= 1 else \
            stack.enter_context(ThreadPoolExecutor(max_workers=threads)).map(run, ranges)
        for (r0, r1), part in zip(ranges, results):
            parts.append(part)
            if on_rows is not None:
                on_rows(r1 - r0)
    return parts


#: Dask tasks per worker thread in :func:`_edges_on_cluster` (a few, so a slow worker is not
#: the last one everybody waits for)
TASKS_PER_THREAD = 4


def _range_task(shared: _Shared, rows: tuple):
    """A Dask task: the edges of rows r0..r1, a block of ``step`` rows at a time, concatenated
    (one :func:`_block_csr` piece); ``rows`` is ``(r0, r1, step, delta_T, min_out, max_out)``."""
    r0, r1, step, delta_T, min_out, max_out = rows
    parts = [shared.block(b0, min(r1, b0 + step), delta_T, min_out, max_out) for b0 in range(r0, r1, step)]
    return tuple(np.concatenate(x) for x in zip(*parts))


def _edges_on_cluster(shared: _Shared, step: int, delta_T: float, min_out: int, max_out: int, scheduler,
                      on_rows) -> list:
    """Every block's edges as Dask tasks: the features and bounds are sent once to every worker
    (:func:`gesturedb.db.cluster.iter_on_cluster`'s ``shared``), each task computes a range of
    whole blocks, and the ranges are put back in order. A block's edges do not depend on where
    it runs, so they are the local ones."""
    K = shared.g.K
    with optional_client(scheduler) as client:
        n_blocks = -(-K // step)
        per = step * max(1, -(-n_blocks // (TASKS_PER_THREAD * worker_threads(client))))
        ranges = [(r0, min(K, r0 + per), step, delta_T, min_out, max_out) for r0 in range(0, K, per)]
        parts = [None] * len(ranges)
        # never waits forever (see gesturedb.db.cluster.completed)
        for i, part in iter_on_cluster(_range_task, ranges, client, shared=shared,
                                       what="the motion graph's edge search"):
            parts[i] = part
            if on_rows is not None:
                on_rows(ranges[i][1] - ranges[i][0])
    return parts


class _ProjectedBounds:
    """Bounds of the exact costs from a few principal directions, and the exact edges through them.

    With ``U`` the ``J`` leading principal directions of the (gridded) features, ``z = U^T (x -
    mu)`` and ``r = |x - mu - U z|`` (what the directions leave out), the cost
    ``|a_p - b_q|^2`` lies in ``[L, L + 4 r_p r_q]`` with ``L = |z_p - z_q|^2 + (r_p - r_q)^2``
    (Pythagoras, and the triangle inequality on the residuals): one product over ``J + 2``
    columns instead of D. ``L`` of a whole block comes from that product, in float32, of
    ``-2 [z_p, r_p, 1]`` against ``[z_q, r_q, |z_q|^2 + r_q^2]``; both ends are widened by
    ``margin`` = 16 (J + 8) 2^-24 B^2, B = the largest |x_p - mu| + the largest |x_q - mu|: the
    magnitudes of a product's J + 2 terms add up to at most B^2, so its float32 value is within
    about (J + 4) 2^-24 B^2 of theirs, and the few sums after it add a few 2^-24 B^2 (float64
    rounding and ``U``'s departure from orthonormality are far smaller): the margin is over ten
    times that. Float32 halves the bytes of the block, which is what its passes are bound by.

    Per row: ``tau1`` = the k-th smallest upper bound over every ``stride``-th column, then the
    columns with ``L <= tau1``, ``tau2`` = the k-th smallest upper bound among those, the columns
    with ``L <= tau2``, and their exact costs. Every column left out has a cost above ``tau2``,
    which is at least the row's k-th smallest cost (k columns have costs below their upper
    bounds), so the k cheapest, ties at the cut included, are among the exact ones: the edges
    are the dense path's bit for bit. Which directions ``U`` are does not matter for that (any
    orthonormal ``U`` gives bounds), only for how many columns are kept: with BEAT2's 1,904
    frames (a recording and its mirror) as clips, 32 directions leave a median residual of 0.14
    of the upper body's 644 features, and 43 exact costs per row give the 32 edges (36 for the
    lower body's 126 features).
    """

    #: rows of the features (of both ends) the principal directions are estimated from
    PCA_ROWS = 100_000

    def __init__(self, g: "_GriddedCosts", k: int, P: np.ndarray, Q: np.ndarray, na: np.ndarray,
                 ra: np.ndarray, rb: np.ndarray, margin: float):
        self.g, self.k = g, k
        self.P, self.Q, self.na, self.ra, self.rb, self.margin = P, Q, na, ra, rb, margin
        K = g.K
        # tau1 from every stride-th column: about K / stride of them per row, then about
        # k * stride columns below it; stride ~ sqrt(K / k) balances the two
        self.stride = max(1, min(int(np.sqrt(K / max(k, 1))), (K - 2) // (2 * k + 2))) if k > 0 else 1

    @classmethod
    def fit(cls, g: "_GriddedCosts", k: int, J: int | None = None) -> "_ProjectedBounds":
        J = BOUND_DIMS if J is None else int(J)
        a, b = g.a, g.b
        K, D = a.shape
        J = max(0, min(J, D))
        sa = max(1, (2 * K) // cls.PCA_ROWS)
        # the sample's mean, then its scatter matrix, in float64 chunks of rows: a float64 copy
        # of the whole sample was 0.9 GB at 120k clips, half the graphs' peak memory there
        sample = (a[::sa], b[::sa])
        chunks = [(x, c0) for x in sample for c0 in range(0, x.shape[0], 8192)]
        mu = sum(x[c0:c0 + 8192].sum(0, dtype=np.float64) for x, c0 in chunks) / sum(x.shape[0] for x in sample)
        if J > 0 and K > 1:
            S = np.zeros((D, D))
            for x, c0 in chunks:
                d = x[c0:c0 + 8192] - mu
                S += d.T @ d
            _, V = np.linalg.eigh(S)
            U = np.ascontiguousarray(V[:, ::-1][:, :J])
        else:
            U = np.zeros((D, 0))

        def project(x):
            z, r, n2 = np.empty((K, U.shape[1])), np.empty(K), np.empty(K)
            for s0 in range(0, K, 8192):
                d = x[s0:s0 + 8192] - mu
                z[s0:s0 + 8192] = d @ U
                res = d - z[s0:s0 + 8192] @ U.T
                r[s0:s0 + 8192] = np.sqrt(np.einsum("ij,ij->i", res, res))
                n2[s0:s0 + 8192] = np.einsum("ij,ij->i", d, d)
            return z, r, n2

        za, ra, n2a = project(a)
        zb, rb, n2b = project(b)
        na = np.einsum("ij,ij->i", za, za) + ra * ra
        nb = np.einsum("ij,ij->i", zb, zb) + rb * rb
        f4 = np.float32
        P = np.concatenate([-2.0 * za, -2.0 * ra[:, None], np.ones((K, 1))], axis=1).astype(f4)
        Q = np.concatenate([zb, rb[:, None], nb[:, None]], axis=1).astype(f4)
        big = float(np.sqrt(max(n2a.max(initial=0.0), na.max(initial=0.0))) +
                    np.sqrt(max(n2b.max(initial=0.0), nb.max(initial=0.0))))
        return cls(g, k, P, Q, na.astype(f4), ra.astype(f4), rb.astype(f4), margin=16.0 * (J + 8) * 2.0 ** -24 * big * big)

    def edges(self, r0: int, r1: int, delta_T: float, min_out: int, max_out: int):
        """``_row_edges`` of rows r0..r1, or None when the bounds keep too many columns to pay
        (features without low-dimensional structure: the caller computes the block densely)."""
        K, k, n = self.g.K, self.k, r1 - r0
        if k <= 0 or K - 1 < 2 * k + 2:
            return None
        # G + na = L, the lower bound; the diagonal is no edge
        G = self.P[r0:r1] @ self.Q.T
        G[np.arange(n), np.arange(r0, r1)] = np.inf
        na, ra = self.na[r0:r1], self.ra[r0:r1]
        sub = G[:, ::self.stride] + na[:, None]
        sub += 4.0 * ra[:, None] * self.rb[None, ::self.stride]
        tau1 = np.partition(sub, k - 1, axis=1)[:, k - 1] + self.margin
        del sub
        # (a second margin on each threshold: the bounds' own roundings against tau's)
        rows, cols = np.divmod(np.flatnonzero(G <= (tau1 - na + 2.0 * self.margin)[:, None]), K)
        if rows.size > n * max(4 * k * self.stride, K // 8):
            return None
        lo = G[rows, cols] + na[rows]
        del G
        hi = lo + 4.0 * ra[rows] * self.rb[cols] + self.margin
        # tau2: the k-th smallest upper bound of each row's columns (rows come sorted), from
        # the rows padded with +inf to the longest
        first = np.searchsorted(rows, np.arange(n + 1))
        pad = np.full((n, int(np.diff(first).max())), np.inf, dtype=np.float32)
        pad[rows, np.arange(rows.size) - first[rows]] = hi
        tau2 = np.partition(pad, k - 1, axis=1)[:, k - 1]
        del pad
        keep = lo - 2.0 * self.margin <= tau2[rows]
        rows, cols = rows[keep], cols[keep]
        cost = self.g.pairs(rows + r0, cols)
        # the k cheapest of each row, ties to the smaller column (cols ascend within a row)
        o = np.lexsort((cols, cost, rows))
        rows, cols, cost = rows[o], cols[o], cost[o]
        rank = np.arange(rows.size) - np.searchsorted(rows, rows)
        keep = (rank < k) & ((cost < delta_T) | (rank < min(int(min_out), k))) & np.isfinite(cost)
        return rows[keep] + r0, cols[keep], cost[keep].astype(np.float64)


def _sample_pairs(K: int) -> np.ndarray:
    """Flat indices into a K x K table of the pairs delta_T's quantile is taken over (every step-th)."""
    step = max(1, (K * K) // 1_000_000)
    return np.arange(0, K * K, step, dtype=np.int64)


def _quantile(sample: np.ndarray, q: float) -> float:
    sample = sample[np.isfinite(sample)]
    return float(np.quantile(sample, q)) if sample.size else 0.0


def _row_edges(T: np.ndarray, r0: int, delta_T: float, min_out: int, max_out: int):
    """The edges of rows ``r0 ..`` of a cost table whose rows are ``T`` (n, K), diagonal +inf:
    (rows, cols, cost), each row's in order of cost."""
    n, K = T.shape
    k_max = min(int(max_out), K - 1)
    k_min = min(int(min_out), k_max)
    if k_max <= 0 or n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    # the k_max cheapest of every row, ties at the cut to the smaller target index (which of
    # several equal costs argpartition returns depends on its algorithm, and numpy picks
    # that by CPU; the k-th smallest value does not)
    kth = np.partition(T, k_max - 1, axis=1)[:, k_max - 1:k_max]
    below = T < kth
    at = T == kth
    need = k_max - below.sum(1, keepdims=True)  # how many of the tied costs each row takes
    take = below | (at & (np.cumsum(at, axis=1, dtype=np.int32) <= need))
    if not np.isfinite(kth).all():  # +inf (the diagonal) or nan: fill from the smallest indices
        fill = ~take & (np.cumsum(~take, axis=1, dtype=np.int32) <= k_max - take.sum(1, keepdims=True))
        take |= fill
    part = np.nonzero(take)[1].reshape(n, k_max)
    vals = np.take_along_axis(T, part, 1)
    o = np.lexsort((part, vals), axis=1)
    part, vals = np.take_along_axis(part, o, 1), np.take_along_axis(vals, o, 1)
    keep = (vals < delta_T) | (np.arange(k_max)[None, :] < k_min)
    keep &= np.isfinite(vals)
    return np.repeat(np.arange(r0, r0 + n), keep.sum(1)), part[keep], vals[keep].astype(np.float64)


def _block_csr(r0: int, r1: int, rows: np.ndarray, cols: np.ndarray, cost: np.ndarray):
    """The edges (rows, cols, cost) of rows r0..r1 as a piece of the CSR graph: (edges per row
    (r1 - r0,), targets increasing within each row, their costs), all int64 / float64.

    Ordered block by block, as the blocks come, so the whole graph never exists as (row, col,
    cost) triples plus their sorted copies: at 1.2M clips that was about 3 GB more at the end of
    each graph.
    """
    o = np.lexsort((cols, rows))
    counts = np.bincount(rows - r0, minlength=r1 - r0).astype(np.int64, copy=False)
    return counts, cols[o].astype(np.int64, copy=False), cost[o].astype(np.float64, copy=False)


def _csr(K: int, pieces: list) -> tuple:
    """indptr (K + 1,), indices, cost from the :func:`_block_csr` pieces of rows 0..K in order."""
    if not pieces:
        return np.zeros(K + 1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    counts, cols, cost = (np.concatenate(x) for x in zip(*pieces))
    indptr = np.zeros(K + 1, dtype=np.int64)
    np.cumsum(counts, out=indptr[1:])
    return indptr, cols, cost
