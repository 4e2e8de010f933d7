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
  partial sum is an exact float64 (:func:`gesturedb.db.edges.transition_costs`). The table is then the same
  bits whatever the BLAS kernel and the CPU: with a float32 product the costs moved by
  2e-5 between OpenBLAS's AVX2 and AVX-512 kernels, and with them the graph search's path
  (the held-out jerk 26.3 on one machine, 25.5 on another).

Edges: :mod:`gesturedb.db.edges` (each clip's cheapest transitions under ``delta_T``, from
exact costs, bounded where the database is large).

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

import contextlib
from collections.abc import Iterator

import numpy as np

from gesturedb import rotations as R
from gesturedb.db import schema, storage, store
from gesturedb.db.cluster import optional_client
from gesturedb.db.edges import DELTA_QUANTILE, MAX_OUT, MIN_OUT, _edges, _grid_unit, _GriddedCosts, _on_grid
from gesturedb.errors import ParameterError
from gesturedb.io.joints import leg_joints

L1 = 0.7
L2 = 0.3
#: frames of each clip's transition window, in frames at any rate, not seconds: at 30 fps, 4 frames
#: (2/15 s, the 15 fps window's time) took the graph's arms to 1.4-2.2x the database's 4-7 Hz power
#: on the four BEAT2 inputs, where 2 keep 0.97-1.07 (``docs/evaluation.md``, "Motion graph")
TRANSITION_FRAMES = 2
#: ridge strengths the style predictor chooses from by cross-validation (fit_style_model)
RIDGE_ALPHAS = (0.1, 1.0, 10.0, 100.0, 1e3, 1e4, 1e6)
#: cross-validation folds of the style predictor: leave-one-group-out up to this many groups,
#: beyond it this many folds of groups (each fold refits on all other clips: leave-one-out over
#: the ~60,000 groups of 100 hours would take hours)
CV_FOLDS = 20


def _yaw_inverse(root_q: np.ndarray) -> np.ndarray:
    """Quaternions (n, 4) removing the heading (rotation about +y) of root rotations (n, 4)."""

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
                max_out: int = MAX_OUT, progress: bool = False, scheduler=None) -> dict:
    """Compute the motion graphs (upper and lower body) and the style model of an open, writable database file.

    ``delta_T`` is the upper-body graph's edge threshold, ``delta_T_lower`` the lower-body one's
    (their costs are over different joints; default for each: its ``delta_quantile`` quantile).
    ``progress``: a progress bar over both graphs' clips on stderr (minutes at 100 hours).
    ``scheduler`` (``"local:N"``, ``"tcp://HOST:PORT"`` or a ``distributed.Client``): the edge
    search's blocks of rows run as Dask tasks (hours at 1,000 hours on one machine); the
    same graphs.

    Called by the build (inside :func:`gesturedb.db.storage.write_atomically`) and by
    :func:`add_graph` (inside :func:`gesturedb.db.storage.edit`). Returns a summary dict.
    """
    if not isinstance(transition_frames, (int, np.integer)) or transition_frames < 1:
        raise ParameterError(f"transition_frames: expected a positive integer, got {transition_frames!r}")
    for name, v in (("l1", l1), ("l2", l2)):
        if not np.isfinite(v) or v < 0:
            raise ParameterError(f"{name}: expected a finite weight >= 0, got {v!r}")
    r = lambda p: schema.read(h5, p)  # noqa: E731
    start, length = r(schema.CLIP_START), r(schema.CLIP_LENGTH)
    K = start.shape[0]
    m = int(transition_frames)
    off = np.arange(m)
    # clips shorter than m frames repeat their edge frames
    last = start[:, None] + np.maximum(length[:, None] - m + off, 0).clip(max=length[:, None] - 1)
    first = start[:, None] + np.minimum(off, length[:, None] - 1)
    upper, lower = body_parts(schema.read(h5, schema.SKELETON_NAMES), schema.read(h5, schema.SKELETON_PARENTS))
    parts = ((schema.GRAPH_UPPER, "upper", upper, delta_T), (schema.GRAPH_LOWER, "lower", lower, delta_T_lower))
    # made one at a time, each dropped after its graph: one body part's grid in memory at a time
    grids = _gridded_features(h5, last, first, [(part, joints) for _, part, joints, _ in parts], l1=l1, l2=l2)
    dims = {"K": K}
    summary = {}
    with contextlib.ExitStack() as stack:
        scheduler = stack.enter_context(optional_client(scheduler))  # one cluster for both graphs
        bar = None
        if progress:
            from tqdm import tqdm

            bar = stack.enter_context(tqdm(total=2 * K, unit="clip", desc="motion graphs", disable=None))
        for (group, part, joints, dt), g in zip(parts, grids):
            summary[part] = _write_edges(h5, group, part, joints, g, dims, l1=l1, l2=l2, m=m, delta_T=dt,
                                         delta_quantile=delta_quantile, min_out=min_out, max_out=max_out,
                                         on_rows=bar.update if bar is not None else None, scheduler=scheduler)
            del g  # before the next part's grid is made

    n_words = r(schema.CLIP_WORD_END) - r(schema.CLIP_WORD_START)
    X = clip_audio_inputs(store.array(h5, schema.AUDIO_FEATURES)[()], start, length, n_words)
    # a clip and its mirrored copy (same recording name but '~mirror', same offset) form one group
    names = [nm.removesuffix("~mirror") for nm in r(schema.RECORDING_NAME)]
    rec = r(schema.CLIP_RECORDING)
    rstart = r(schema.RECORDING_START_FRAME)
    keys = [(names[int(c)], int(s0 - rstart[int(c)])) for c, s0 in zip(rec, start)]
    uniq = {k: i for i, k in enumerate(dict.fromkeys(keys))}
    model = fit_style_model(X, r(schema.CLIP_STYLE).astype(np.float64), groups=np.array([uniq[k] for k in keys]))
    for k, path in schema.STYLE_MODEL_FIELDS.items():
        schema.write(h5, path, model[k], dims)
    store.set_attrs(h5, schema.STYLE_MODEL, {k: model[k] for k in ("heldout_rmse", "mean_rmse", "n_heldout", "alpha")})
    return dict(n_nodes=K, n_edges=summary["upper"]["n_edges"], delta_T=summary["upper"]["delta_T"],
                n_edges_lower=summary["lower"]["n_edges"], delta_T_lower=summary["lower"]["delta_T"],
                heldout_rmse=model["heldout_rmse"], mean_rmse=model["mean_rmse"])


#: clips whose transition features are computed at once when the graphs are built
FEATURE_CHUNK = 4096


def _gridded_features(h5, last: np.ndarray, first: np.ndarray, parts, *, l1: float, l2: float,
                      chunk: int = FEATURE_CHUNK) -> Iterator[_GriddedCosts]:
    """Per (part, joints), in turn: the transition features of every clip's ``last`` and ``first``
    frames ((K, m) frame indices), on their grid.

    Computed a chunk of clips at a time, reading only the chunk's frames: one pass for every
    part's largest magnitude (the grid's unit), then one per part, made when the caller asks
    for it. So the memory is one part's grid of float32 integers at a time, not the features'
    float64 nor every transition frame's joints (at 120k clips the graphs peak at 1.2 GB, 1.8
    with both grids held at once and 3.7 with every frame's features; about 8 GB at 1.2M clips,
    1,000 hours); the values are those of the whole arrays at once. A caller that drops each
    grid before asking for the next holds one at a time (the lower body's is 1 kB per clip).
    """
    pos, rot, root = (store.array(h5, p) for p in (schema.JOINT_POSITIONS, schema.LOCAL_ROTATIONS, schema.ROOT_POSITIONS))
    K = last.shape[0]

    def features(which):  # (s0, [(end_x, start_x) per part in which]) per chunk
        for s0 in range(0, max(K, 1), chunk):
            lc, fc = last[s0:s0 + chunk], first[s0:s0 + chunk]
            need = np.unique(np.concatenate([lc.ravel(), fc.ravel()]))
            pa, ra, oa = pos[need], rot[need], root[need]
            li, fi = np.searchsorted(need, lc), np.searchsorted(need, fc)
            yield s0, [(transition_features(pa, ra, oa, li, l1=l1, l2=l2, joints=j, part=p),
                        transition_features(pa, ra, oa, fi, l1=l1, l2=l2, joints=j, part=p)) for p, j in which]

    amax = [0.0] * len(parts)
    D = [0] * len(parts)
    for _, xs in features(parts):
        for i, (ex, sx) in enumerate(xs):
            D[i] = ex.shape[1]
            amax[i] = max([amax[i]] + [float(np.abs(x).max()) for x in (ex, sx) if x.size])
    for i, part in enumerate(parts):
        u, dtype = _grid_unit(D[i], amax[i], compact=True)
        ga, gb = np.empty((K, D[i]), dtype), np.empty((K, D[i]), dtype)
        for s0, [(ex, sx)] in features([part]):
            ga[s0:s0 + ex.shape[0]] = np.rint(ex / u)
            gb[s0:s0 + sx.shape[0]] = np.rint(sx / u)
        yield _GriddedCosts.from_grid(ga, gb, u)
        del ga, gb


def _write_edges(h5, group: str, part: str, joints, g: _GriddedCosts, dims: dict, *, l1: float,
                 l2: float, m: int, delta_T, delta_quantile: float, min_out: int, max_out: int, on_rows,
                 scheduler=None) -> dict:
    """One body part's graph from its gridded transition features, written under ``group``."""
    indptr, indices, cost, dT = _edges(g, delta_T=delta_T, delta_quantile=delta_quantile, min_out=min_out,
                                       max_out=max_out, on_rows=on_rows, scheduler=scheduler)
    for path, arr in zip(schema.GRAPHS[group], (indptr, indices, cost)):
        schema.write(h5, path, arr, dims)
    store.set_attrs(h5, group, dict(body=part, n_joints=len(joints), l1=float(l1), l2=float(l2), transition_frames=m,
                                    delta_T=dT, delta_quantile=float(delta_quantile), min_out=int(min_out),
                                    max_out=int(max_out)))
    return dict(n_edges=int(indices.shape[0]), delta_T=dT)


def add_graph(path, **options) -> dict:
    """Add (or replace) the motion graphs of an existing database file (an older version:
    :func:`gesturedb.db.upgrade.upgrade`).

    Written through :func:`gesturedb.db.storage.edit` (temporary copy + rename). ``options``:
    those of :func:`write_graph` (``scheduler`` included).
    """
    # connect (or start the cluster) before the database is copied: a wrong address fails at
    # once instead of after copying a large file
    with optional_client(options.pop("scheduler", None)) as client:
        with storage.edit(path) as h5:
            for grp in (*schema.GRAPHS, schema.STYLE_MODEL):
                store.delete(h5, grp)
            summary = write_graph(h5, scheduler=client, **options)
    return summary
