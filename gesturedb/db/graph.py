"""The motion graph over the database's word-gap clips (GestureMaster, Sec. 4.1) and the style predictor.

Built at ``gesturedb build`` (default) or added to an existing file by ``gesturedb graph DB.h5``;
stored under ``graph/`` and ``style_model/`` (see :mod:`gesturedb.db.schema`). It lives in the
database layer because the build writes it; the search over it is :mod:`gesturedb.synth.graph`.

Transition cost (Eq. 1), ``T(p, q) = l1 * T_p + l2 * T_r`` over ``m = transition_frames``
frames, the last ``m`` frames of ``p`` against the first ``m`` of ``q``:

- ``T_p``: summed *squared* distance (m^2) of all joints in the body frame (root position
  subtracted, root heading removed), so where the speaker stood or faced does not matter.
- ``T_r``: summed ``1 - <q_a, q_b>`` over the local rotations of every non-root joint, each
  quaternion first put on the ``w >= 0`` hemisphere (q and -q are one rotation); for unit
  quaternions that is ``|q_a - q_b|^2 / 2`` (1 - cos of half the angle). A local joint
  rotation near 180 degrees (w ~ 0) could land on either hemisphere; gestures do not bend
  joints that far.
- Both are squared Euclidean distances, so with ``x = [sqrt(l1) p, sqrt(l2 / 2) q]`` the
  whole K x K table is ``|x_a|^2 + |x_b|^2 - 2 x_a . x_b``: one float64 matrix product
  (BLAS) over ``x`` rounded to a power-of-two grid fine enough that every product and
  partial sum is an exact float64 (:func:`transition_costs`). The table is then the same
  bits whatever the BLAS kernel and the CPU: with a float32 product the costs moved by
  2e-5 between OpenBLAS's AVX2 and AVX-512 kernels, and with them the graph search's path
  (the held-out jerk 26.3 on one machine, 25.5 on another).

Edges. ``p -> q`` exists where ``T(p, q) < delta_T``; ``delta_T`` defaults to the
``delta_quantile`` (10 %) quantile of all off-diagonal costs of the database (from a
fixed strided sample of at most 10^6 pairs), because the paper's ``delta_T = 8`` belongs to
its own units. Of those, every node keeps at most its ``max_out`` (32) cheapest, so the
search stays ``O(n K max_out)`` on large databases; and every node keeps its ``min_out``
(4) cheapest out-edges whatever ``delta_T``, so a small database never falls apart into
nodes without a way on. There are no self-edges: the graph itself never plays a clip twice in a
row (the back-to-back repeat rule), which also means the output never loops on one clip.

Style predictor (Sec. 3.3 uses StyleGestures; here a ridge regression): the clip's mean
and standard deviation of the standardised audio features (2 x Da) plus its word rate
-> the clip's style signature (speed m/s, radius m, height m). Fitted on the database's
clips when the graph is built; the held-out error (every 5th clip held out, RMS per
output standardised by the target std) is stored beside the error of predicting the mean.
Its normal equations, their solution and its predictions avoid BLAS and LAPACK too (an
exact Gram matrix, a Cholesky solve and products in numpy's own reductions), so the
stored model and the predicted styles are also the same bits on every machine.
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError

L1 = 0.7
L2 = 0.3
TRANSITION_FRAMES = 2
DELTA_QUANTILE = 0.10
MIN_OUT = 4
MAX_OUT = 32
#: principal directions of the bounded edge search (:class:`_ProjectedBounds`)
BOUND_DIMS = 32
#: clips from which ``edges_from_features`` bounds the costs instead of computing them all
BOUND_MIN_K = 4096
#: ridge strengths the style predictor chooses from by cross-validation (fit_style_model)
RIDGE_ALPHAS = (0.1, 1.0, 10.0, 100.0, 1e3, 1e4, 1e6)
#: cross-validation folds of the style predictor: leave-one-group-out up to this many groups,
#: beyond it this many folds of groups (each fold refits on all other clips: leave-one-out over
#: the ~60,000 groups of 100 hours would take hours)
CV_FOLDS = 20


def _yaw_inverse(root_q: np.ndarray) -> np.ndarray:
    """Quaternions (n, 4) removing the heading (rotation about +y) of root rotations (n, 4)."""
    from gesturedb import rotations as R

    fwd = R.apply(root_q, np.broadcast_to(np.array([0.0, 0.0, 1.0]), root_q.shape[:-1] + (3,)))
    a = -np.arctan2(fwd[..., 0], fwd[..., 2]) / 2
    return np.stack([np.cos(a), np.zeros_like(a), np.sin(a), np.zeros_like(a)], axis=-1)


def body_parts(names, parents) -> tuple[np.ndarray, np.ndarray]:
    """Joint indices of the upper body and the lower body (Sec. 4.1: one graph for each).

    Lower body: the root (joint 0: its rotation and position, i.e. where the speaker stands
    and how the pelvis tilts) and both legs (:func:`gesturedb.io.joints.leg_joints`); upper
    body: everything else (spine, arms, hands, head). Both int64, ascending, disjoint, covering
    all joints. A rig without recognisable hips has a lower body of the root alone.
    """
    from gesturedb.io.joints import leg_joints

    J = len(names)
    lower = np.union1d([0], leg_joints(names, parents)).astype(np.int64)
    upper = np.setdiff1d(np.arange(J), lower).astype(np.int64)
    return upper, lower


def transition_features(positions, rotations, root, frames, *, l1: float = L1, l2: float = L2,
                        joints=None, part: str = "whole") -> np.ndarray:
    """Weighted body-frame features of the given frames: ``T = |x_end(p) - x_start(q)|^2``.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres, world
    rotations : ndarray [shape=(F, J, 4)], local quaternions (w, x, y, z)
    root : ndarray [shape=(F, 3)], metres
    frames : ndarray [shape=(K, m)], int
        Frames of each clip's transition window.
    joints : int array, optional
        The joints whose positions and local rotations count (default: all; the root's own
        local rotation never counts as a joint rotation).
    part : {"whole", "upper", "lower"}
        The frame the positions are measured in, and the root's share:

        - ``"whole"``/``"lower"``: root position subtracted, root heading removed (where the
          speaker stood or faced does not matter); ``"lower"`` adds the root's rotation without
          its heading (the pelvis' tilt) as one more rotation term.
        - ``"upper"``: root position subtracted and the root's *whole* rotation removed: the
          upper body is played on another clip's pelvis in split synthesis, so only its own
          chain above the pelvis may decide its transitions.

    Returns
    -------
    ndarray [shape=(K, m * (Jp * 3 + Jr * 4))], float64
        ``sqrt(l1)`` x the joint positions, then ``sqrt(l2 / 2)`` x the local quaternions
        (and the tilt) on the ``w >= 0`` hemisphere.
    """
    from gesturedb import rotations as R

    if part not in ("whole", "upper", "lower"):
        raise ParameterError(f"part: expected 'whole', 'upper' or 'lower', got {part!r}")
    K, m = frames.shape
    f = frames.reshape(-1)
    J = positions.shape[1]
    joints = np.arange(J) if joints is None else np.asarray(joints, dtype=np.int64)
    p = np.asarray(positions[f][:, joints], dtype=np.float64) - np.asarray(root[f], dtype=np.float64)[:, None, :]
    q = np.asarray(rotations[f], dtype=np.float64)
    yinv = _yaw_inverse(q[:, 0])
    frame_inv = R.inverse(q[:, 0]) if part == "upper" else yinv
    p = R.apply(np.repeat(frame_inv[:, None, :], p.shape[1], axis=1), p)
    qq = q[:, joints[joints != 0], :]
    if part == "lower":
        qq = np.concatenate([qq, R.multiply(yinv, q[:, 0])[:, None, :]], axis=1)
    qq = qq * np.where(qq[..., :1] < 0, -1.0, 1.0)
    x = np.concatenate([np.sqrt(l1) * p.reshape(len(f), -1), np.sqrt(l2 / 2) * qq.reshape(len(f), -1)], axis=1)
    return x.reshape(K, -1)


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

    def __init__(self, end_x: np.ndarray, start_x: np.ndarray, *, u: float | None = None):
        """From the features (the grid is made here), or with ``u`` from the grid's integers themselves."""
        if u is None:
            (a, b), u = _on_grid(np.asarray(end_x), np.asarray(start_x), compact=True)
        else:
            a, b = end_x, start_x
        self.K = a.shape[0]
        self.na = np.einsum("ij,ij->i", a, a, dtype=np.float64)
        self.nb = np.einsum("ij,ij->i", b, b, dtype=np.float64)
        self.uu = u * u
        self.a, self.b = a, b
        self._b64 = None  # b in float64 for the BLAS product of rows(), made on its first call

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
    rows, cols, cost = _row_edges(T, 0, delta_T, min_out, max_out)
    return _csr(K, rows, cols, cost) + (float(delta_T),)


def edges_from_features(end_x: np.ndarray, start_x: np.ndarray, *, delta_T: float | None = None,
                        delta_quantile: float = DELTA_QUANTILE, min_out: int = MIN_OUT, max_out: int = MAX_OUT,
                        block_elems: int = 1 << 24, method: str = "auto", on_rows=None):
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
    """
    return _edges(_GriddedCosts(end_x, start_x), delta_T=delta_T, delta_quantile=delta_quantile, min_out=min_out,
                  max_out=max_out, block_elems=block_elems, method=method, on_rows=on_rows)


def _edges(g: "_GriddedCosts", *, delta_T, delta_quantile: float, min_out: int, max_out: int, block_elems: int,
           method: str, on_rows):
    """edges_from_features over features already on their grid (the caller may drop its own copy)."""
    if method not in ("auto", "dense", "bounded"):
        raise ParameterError(f"method: expected 'auto', 'dense' or 'bounded', got {method!r}")
    K = g.K

    def costs(r0: int, r1: int) -> np.ndarray:  # rows r0..r1 of transition_costs, diagonal +inf
        T = g.rows(r0, r1)
        d = np.arange(r0, r1)
        T[d - r0, d] = np.inf
        return T

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

    def block(r0: int, r1: int):
        nonlocal bounds
        if bounds is not None:
            got = bounds.edges(r0, r1, delta_T, min_out, max_out)
            if got is not None:
                return got
            bounds = None  # features without the structure bounds need: the rest densely too
        return _row_edges(costs(r0, r1), r0, delta_T, min_out, max_out)

    parts = []
    for r0 in range(0, K, step):
        parts.append(block(r0, min(K, r0 + step)))
        if on_rows is not None:
            on_rows(min(K, r0 + step) - r0)
    rows, cols, cost = (np.concatenate(x) for x in zip(*parts)) if parts else _row_edges(np.zeros((0, 0)), 0, 0, 0, 0)
    return _csr(K, rows, cols, cost) + (float(delta_T),)


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
        rows = np.concatenate([a[::sa], b[::sa]]).astype(np.float64)
        mu = rows.mean(0)
        if J > 0 and K > 1:
            rows -= mu
            _, V = np.linalg.eigh(rows.T @ rows)
            U = np.ascontiguousarray(V[:, ::-1][:, :J])
        else:
            U = np.zeros((D, 0))
        del rows

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


def _csr(K: int, rows: np.ndarray, cols: np.ndarray, cost: np.ndarray):
    """indptr, indices, cost with targets increasing within a row."""
    o = np.lexsort((cols, rows))
    rows, cols, cost = rows[o], cols[o], cost[o]
    indptr = np.zeros(K + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=K), out=indptr[1:])
    return indptr, cols.astype(np.int64), cost


def suggest_gap_s(pauses_s, total_s: float, *, n_sequences: int = 1, target_clip_s: float = 3.0,
                  lo_s: float = 0.1, hi_s: float = 0.4) -> float:
    """The word gap (s) that cuts speech into clips of about ``target_clip_s`` (Sec. 3.1: a few seconds).

    Parameters
    ----------
    pauses_s : ndarray [shape=(P,)], seconds
        Pauses between consecutive words of all sequences.
    total_s : float
        Total duration of the sequences.
    n_sequences : int
        Recordings (each already starts a clip).

    Returns
    -------
    float
        Midway between the ``n``-th and ``n+1``-th longest pauses, ``n = round(total_s /
        target_clip_s) - n_sequences`` cuts, clamped to ``[lo_s, hi_s]`` (the paper's 0.4 s
        is the upper end: a longer gap only gives fewer, longer clips).
    """
    p = np.sort(np.asarray(pauses_s, dtype=np.float64))[::-1]
    n = int(round(float(total_s) / float(target_clip_s))) - int(n_sequences)
    if n <= 0 or p.size == 0:
        return float(hi_s)
    if n >= p.size:
        return float(lo_s)
    return float(np.clip((p[n - 1] + p[n]) / 2, lo_s, hi_s))


def clip_audio_inputs(audio_features: np.ndarray, starts, lengths, n_words) -> np.ndarray:
    """Style-predictor inputs per clip: mean and std of standardised audio features, word rate.

    Parameters
    ----------
    audio_features : ndarray [shape=(F, Da)], standardised
    starts, lengths : int arrays (K,), frames
    n_words : ndarray (K,), words per clip; divided by the clip length in frames (words/frame)

    Returns
    -------
    ndarray [shape=(K, 2 Da + 1)], float64
    """
    a = np.asarray(audio_features, dtype=np.float64)
    out = np.empty((len(starts), 2 * a.shape[1] + 1))
    for k, (s, n) in enumerate(zip(starts, lengths)):
        seg = a[int(s): int(s) + int(n)]
        out[k, : a.shape[1]] = seg.mean(0)
        out[k, a.shape[1]: 2 * a.shape[1]] = seg.std(0)
        out[k, -1] = float(n_words[k]) / max(int(n), 1)
    return out


def fit_style_model(X: np.ndarray, Y: np.ndarray, *, alpha: float | None = None, groups=None) -> dict:
    """Ridge regression ``Y ~ X`` on standardised inputs, its strength chosen by cross-validation;
    held-out error vs the mean predictor.

    ``groups`` (K,) int: clips of one group are held out together (a clip and its mirrored
    copy share audio and nearly share style: splitting them would leak). Every 5th group
    (by order of first appearance) is held out; default: every clip its own group.

    ``alpha`` None (default): the ridge strength from :data:`RIDGE_ALPHAS` chosen by
    leave-one-group-out error (:data:`CV_FOLDS` folds of groups when there are more groups) on
    the clips it is fitted on, the strongest within one standard
    error of the best (for the held-out estimate, on the training groups only, so the held-out
    clips choose nothing). The largest strength is
    practically the mean predictor, so where audio does not predict style on a database (a
    single short recording), the fit falls back to the mean rather than doing worse than it.

    Returns a dict with ``coef (P, S)``, ``intercept (S,)``, ``x_mean (P,)``, ``x_std (P,)``,
    ``alpha``, ``heldout_rmse`` and ``mean_rmse`` (RMS over held-out clips and the S outputs,
    each output divided by its standard deviation), ``n_heldout``.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)

    def normal_equations(Xt, Yt):
        """Z^T Z (P, P) and Z^T (Y - ym) (P, S) of the standardised inputs, exactly (on a grid,
        see _on_grid), so that no BLAS kernel decides the bits; and ym, mu, sd."""
        mu, sd = Xt.mean(0), np.maximum(Xt.std(0), 1e-9)
        Z = (Xt - mu) / sd
        ym = Yt.mean(0)
        (Zg,), uz = _on_grid(Z.T)
        (Rg,), ur = _on_grid((Yt - ym).T)  # its own unit: the targets are far smaller than Z
        return (Zg @ Zg.T) * (uz * uz), (Zg @ Rg.T) * (uz * ur), ym, mu, sd

    def fit(Xt, Yt, a):
        G, R, ym, mu, sd = normal_equations(Xt, Yt)
        return _cholesky_solve(G + a * np.eye(G.shape[0]), R), ym, mu, sd

    def predict(m, Xq):
        coef, ym, mu, sd = m
        return _product((Xq - mu) / sd, coef) + ym

    ysd = np.maximum(Y.std(0), 1e-9)

    def choose(Xt, Yt, gt):
        if alpha is not None:
            return float(alpha)
        ug, gi = np.unique(gt, return_inverse=True)
        if ug.size < 3:  # too few groups to cross-validate: the strongest shrinkage
            return float(RIDGE_ALPHAS[-1])
        n_folds = min(ug.size, CV_FOLDS)
        fold = gi % n_folds  # up to CV_FOLDS groups: each group its own fold
        # each fold's normal equations once, the folds' systems of one strength solved together
        folds = [normal_equations(Xt[fold != f], Yt[fold != f]) for f in range(n_folds)]
        G = np.stack([f[0] for f in folds])
        R = np.stack([f[1] for f in folds])
        err = np.empty((len(RIDGE_ALPHAS), n_folds))  # (alphas, folds)
        for i, a in enumerate(RIDGE_ALPHAS):
            coefs = _cholesky_solve(G + a * np.eye(G.shape[1]), R)
            for f in range(n_folds):
                m = (coefs[f],) + folds[f][2:]
                err[i, f] = (((predict(m, Xt[fold == f]) - Yt[fold == f]) / ysd) ** 2).mean()
        mean, se = err.mean(1), err.std(1) / np.sqrt(n_folds)
        best = int(np.argmin(mean))
        # the one-standard-error rule (glmnet's lambda.1se): the strongest shrinkage within one
        # standard error of the best, so that a few clips that happen to fit do not buy a
        # predictor the held-out clips find worse than the mean
        return float(RIDGE_ALPHAS[int(np.flatnonzero(mean <= mean[best] + se[best]).max())])

    K = X.shape[0]
    groups = np.arange(K) if groups is None else np.asarray(groups)
    _, first, inv = np.unique(groups, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))  # group number in order of first appearance
    held = rank[inv] % 5 == 4
    if held.sum() >= 1 and (~held).sum() >= 2:
        m = fit(X[~held], Y[~held], choose(X[~held], Y[~held], inv[~held]))
        err = ((predict(m, X[held]) - Y[held]) / ysd) ** 2
        base = ((Y[~held].mean(0) - Y[held]) / ysd) ** 2
        heldout, mean_err = float(np.sqrt(err.mean())), float(np.sqrt(base.mean()))
    else:
        heldout = mean_err = float("nan")
    a = choose(X, Y, inv)
    coef, ym, mu, sd = fit(X, Y, a)
    return dict(coef=coef, intercept=ym, x_mean=mu, x_std=sd, alpha=a, heldout_rmse=heldout, mean_rmse=mean_err,
                n_heldout=int(held.sum()))


def predict_style(model: dict, X: np.ndarray) -> np.ndarray:
    """Style signatures (n, S) predicted from inputs (n, P) by a model from :func:`fit_style_model`."""
    return _product((np.asarray(X, dtype=np.float64) - model["x_mean"]) / model["x_std"], model["coef"]) \
        + model["intercept"]


def _product(Z: np.ndarray, W: np.ndarray) -> np.ndarray:
    """``Z @ W`` (n, P) x (P, S) -> (n, S) as numpy's own elementwise products and sum (no BLAS:
    the same bits on every machine). For the style model's few inputs and outputs."""
    return (Z[:, :, None] * W[None, :, :]).sum(axis=1)


def _cholesky_solve(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A^-1 B`` for symmetric positive definite ``A`` (..., P, P) and ``B`` (..., P, S), float64,
    by a Cholesky factorisation written in numpy's elementwise operations and sums (LAPACK's
    results depend on the BLAS kernel under it; these do not). Leading axes are a batch of
    independent systems, each solved with the same operations as alone. P is small (the style
    inputs)."""
    P = A.shape[-1]
    L = np.zeros_like(A)
    for j in range(P):
        d = A[..., j, j] - (L[..., j, :j] * L[..., j, :j]).sum(axis=-1)
        if not (d > 0.0).all():
            raise ParameterError(f"style model: expected a positive definite system, got pivot {d.min()!r} at {j}")
        L[..., j, j] = np.sqrt(d)
        L[..., j + 1:, j] = (A[..., j + 1:, j] - (L[..., j + 1:, :j] * L[..., j, None, :j]).sum(axis=-1)) \
            / L[..., j, j, None]
    Y = np.zeros(np.broadcast_shapes(A.shape[:-2], B.shape[:-2]) + B.shape[-2:])
    for i in range(P):  # L y = B
        Y[..., i, :] = (B[..., i, :] - (L[..., i, :i, None] * Y[..., :i, :]).sum(axis=-2)) / L[..., i, i, None]
    X = np.zeros_like(Y)
    for i in range(P - 1, -1, -1):  # L^T x = y
        X[..., i, :] = (Y[..., i, :] - (L[..., i + 1:, i, None] * X[..., i + 1:, :]).sum(axis=-2)) \
            / L[..., i, i, None]
    return X


def write_graph(h5, *, l1: float = L1, l2: float = L2, transition_frames: int = TRANSITION_FRAMES,
                delta_T: float | None = None, delta_T_lower: float | None = None, delta_quantile: float = DELTA_QUANTILE, min_out: int = MIN_OUT,
                max_out: int = MAX_OUT, progress: bool = False) -> dict:
    """Compute the motion graphs (upper and lower body) and the style model of an open, writable database file.

    ``delta_T`` is the upper-body graph's edge threshold, ``delta_T_lower`` the lower-body one's
    (their costs are over different joints; default for each: its ``delta_quantile`` quantile).
    ``progress``: a progress bar over both graphs' clips on stderr (minutes at 100 hours).

    Called by the build (inside :func:`gesturedb.db.storage.write_atomically`) and by
    :func:`add_graph` (inside :func:`gesturedb.db.storage.edit`). Returns a summary dict.
    """
    from gesturedb.db import schema

    if not isinstance(transition_frames, (int, np.integer)) or transition_frames < 1:
        raise ParameterError(f"transition_frames: expected a positive integer, got {transition_frames!r}")
    for name, v in (("l1", l1), ("l2", l2)):
        if not np.isfinite(v) or v < 0:
            raise ParameterError(f"{name}: expected a finite weight >= 0, got {v!r}")
    r = lambda p: schema.read(h5, p)  # noqa: E731
    start, length = r("clips/start"), r("clips/length")
    K = start.shape[0]
    m = int(transition_frames)
    off = np.arange(m)
    # clips shorter than m frames repeat their edge frames
    last = start[:, None] + np.maximum(length[:, None] - m + off, 0).clip(max=length[:, None] - 1)
    first = start[:, None] + np.minimum(off, length[:, None] - 1)
    upper, lower = body_parts(schema.read(h5, "skeleton/names"), schema.read(h5, "skeleton/parents"))
    parts = (("graph", "upper", upper, delta_T), ("graph_lower", "lower", lower, delta_T_lower))
    grids = _gridded_features(h5, last, first, [(part, joints) for _, part, joints, _ in parts], l1=l1, l2=l2)
    dims = {"K": K}
    summary = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=2 * K, unit="clip", desc="motion graphs", disable=None)
    try:
        for (group, part, joints, dt), g in zip(parts, grids):
            summary[part] = _write_edges(h5, group, part, joints, g, dims, l1=l1, l2=l2, m=m, delta_T=dt,
                                         delta_quantile=delta_quantile, min_out=min_out, max_out=max_out,
                                         on_rows=bar.update if bar is not None else None)
    finally:
        if bar is not None:
            bar.close()
    del grids

    n_words = r("clips/word_end") - r("clips/word_start")
    X = clip_audio_inputs(h5["frames/audio_features"][()], start, length, n_words)
    # a clip and its mirrored copy (same recording name but '~mirror', same offset) form one group
    names = [nm.removesuffix("~mirror") for nm in r("recordings/name")]
    rec = r("clips/recording")
    rstart = r("recordings/start_frame")
    keys = [(names[int(c)], int(s0 - rstart[int(c)])) for c, s0 in zip(rec, start)]
    uniq = {k: i for i, k in enumerate(dict.fromkeys(keys))}
    model = fit_style_model(X, r("clips/style").astype(np.float64), groups=np.array([uniq[k] for k in keys]))
    for k in ("coef", "intercept", "x_mean", "x_std"):
        schema.write(h5, f"style_model/{k}", model[k], dims)
    sm = h5["style_model"]
    for k in ("heldout_rmse", "mean_rmse", "n_heldout"):
        sm.attrs[k] = model[k]
    sm.attrs["alpha"] = model["alpha"]
    return dict(n_nodes=K, n_edges=summary["upper"]["n_edges"], delta_T=summary["upper"]["delta_T"],
                n_edges_lower=summary["lower"]["n_edges"], delta_T_lower=summary["lower"]["delta_T"],
                heldout_rmse=model["heldout_rmse"], mean_rmse=model["mean_rmse"])


#: clips whose transition features are computed at once when the graphs are built
FEATURE_CHUNK = 16384


def _gridded_features(h5, last: np.ndarray, first: np.ndarray, parts, *, l1: float, l2: float,
                      chunk: int = FEATURE_CHUNK) -> list[_GriddedCosts]:
    """Per (part, joints): the transition features of every clip's ``last`` and ``first`` frames
    ((K, m) frame indices), on their grid.

    Computed a chunk of clips at a time, reading only the chunk's frames, and twice: the grid's
    unit needs the largest magnitude first. So the memory is the grids' float32 integers, not
    the features' float64 nor every transition frame's joints (at 1.2M clips, 1,000 hours,
    about 7 GB instead of about 26 GB); the values are those of the whole arrays at once.
    """
    pos, rot, root = h5["frames/joint_positions"], h5["frames/local_rotations"], h5["frames/root_positions"]
    K = last.shape[0]

    def features():  # (s0, [(end_x, start_x) per part]) per chunk
        for s0 in range(0, max(K, 1), chunk):
            lc, fc = last[s0:s0 + chunk], first[s0:s0 + chunk]
            need = np.unique(np.concatenate([lc.ravel(), fc.ravel()]))
            pa, ra, oa = pos[need], rot[need], root[need]
            li, fi = np.searchsorted(need, lc), np.searchsorted(need, fc)
            yield s0, [(transition_features(pa, ra, oa, li, l1=l1, l2=l2, joints=j, part=p),
                        transition_features(pa, ra, oa, fi, l1=l1, l2=l2, joints=j, part=p)) for p, j in parts]

    amax = [0.0] * len(parts)
    D = [0] * len(parts)
    for _, xs in features():
        for i, (ex, sx) in enumerate(xs):
            D[i] = ex.shape[1]
            amax[i] = max([amax[i]] + [float(np.abs(x).max()) for x in (ex, sx) if x.size])
    units = [_grid_unit(D[i], amax[i], compact=True) for i in range(len(parts))]
    grids = [(np.empty((K, D[i]), dtype), np.empty((K, D[i]), dtype)) for i, (_, dtype) in enumerate(units)]
    for s0, xs in features():
        for (ex, sx), (u, _), (ga, gb) in zip(xs, units, grids):
            ga[s0:s0 + ex.shape[0]] = np.rint(ex / u)
            gb[s0:s0 + sx.shape[0]] = np.rint(sx / u)
    return [_GriddedCosts(ga, gb, u=u) for (ga, gb), (u, _) in zip(grids, units)]


def _write_edges(h5, group: str, part: str, joints, g: _GriddedCosts, dims: dict, *, l1: float,
                 l2: float, m: int, delta_T, delta_quantile: float, min_out: int, max_out: int, on_rows) -> dict:
    """One body part's graph from its gridded transition features, written under ``group``."""
    from gesturedb.db import schema

    indptr, indices, cost, dT = _edges(g, delta_T=delta_T, delta_quantile=delta_quantile, min_out=min_out,
                                       max_out=max_out, block_elems=1 << 24, method="auto", on_rows=on_rows)
    schema.write(h5, f"{group}/indptr", indptr, dims)
    schema.write(h5, f"{group}/indices", indices, dims)
    schema.write(h5, f"{group}/cost", cost, dims)
    g = h5[group]
    for k, v in dict(body=part, n_joints=len(joints), l1=float(l1), l2=float(l2), transition_frames=m, delta_T=dT,
                     delta_quantile=float(delta_quantile), min_out=int(min_out), max_out=int(max_out)).items():
        g.attrs[k] = v
    return dict(n_edges=int(indices.shape[0]), delta_T=dT)


def add_graph(path, **options) -> dict:
    """Add (or replace) the motion graphs of an existing database file, upgrading a version-1 or -2 file.

    Written through :func:`gesturedb.db.storage.edit` (temporary copy + rename).
    """
    from gesturedb.db import schema, storage

    with storage.edit(path, upgrade=True) as h5:
        for grp in ("graph", "graph_lower", "style_model"):
            if grp in h5:
                del h5[grp]
        summary = write_graph(h5, **options)
        h5.attrs["schema_version"] = schema.SCHEMA_VERSION
    return summary
