"""The pose filters' data: narrower copies of a pose matrix that bound distances exactly.

:class:`HalfPose` (binary16 rows, ``pose_f16=``) and :class:`PoseProjection`
(24 projected columns, ``pose_proj=``; ``Searcher``'s default). Used by
:mod:`gesturedb.search`, which re-exports both; kept apart from the search module
so each stays readable. Depends on numpy only.
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError

__all__ = ["HalfPose", "PoseProjection"]


def _describe(a) -> str:
    # as gesturedb.search describes arrays in its messages
    if not isinstance(a, np.ndarray):
        return type(a).__name__
    layout = "" if a.flags.c_contiguous else " non-contiguous"
    return f"{a.dtype}{layout} {a.shape}"


class HalfPose:
    """Half-precision copy of a pose matrix: pose steps read half the bytes.

    A pose pre-selection streams every candidate's entry pose at every step,
    so it is bound by memory bandwidth. With a ``HalfPose`` it streams these
    binary16 rows instead (2 bytes per value), bounds how far each row's
    float32 distance can be from its half-precision distance (round-to-nearest
    error of binary16, plus float32 rounding), and reads in float32 only the
    rows that may still be a segment's minimum -- usually one per segment.
    Results are identical with and without it (it is only a filter); rows
    with values beyond the binary16 range (|x| > 65504) or non-finite values
    make their segment fall back to the exact scan.

    Build it once per database and pass it as ``pose_f16=`` to the searches,
    together with the very array it was made from. It is a snapshot: modify
    ``pose`` in place and it must be rebuilt.

    Parameters
    ----------
    pose : ndarray [shape=(F, Dp)], float32, C-contiguous
        The database's pose features.

    Attributes
    ----------
    pose : ndarray
        The source array (kept to check that searches use the same one).
    data : ndarray [shape=(F, Dp)], float16
        ``pose`` rounded to binary16 (half the memory of ``pose``).
    """

    def __init__(self, pose):
        if not (isinstance(pose, np.ndarray) and pose.dtype == np.float32 and pose.ndim == 2
                and pose.flags.c_contiguous):
            raise ParameterError(f"pose: expected float32 C-contiguous (F, Dp); got {_describe(pose)}")
        self.pose = pose
        with np.errstate(over="ignore"):  # beyond +-65504 becomes inf: those segments scan exactly
            self.data = np.ascontiguousarray(pose.astype(np.float16))

    def __repr__(self) -> str:
        return f"HalfPose({self.data.shape[0]} frames x {self.data.shape[1]}, {self.data.nbytes / 1e6:.0f} MB)"


class PoseProjection:
    """A narrow projection of a pose matrix: pose steps read J instead of Dp floats per frame.

    Row ``f`` holds ``z_f = (U^T (P[f] - mean), r_f)``: the coordinates of the
    frame's pose in the ``J - 1`` leading principal directions ``U`` of the
    database and ``r_f``, the length of what those directions leave out.
    For a previous pose ``x`` with ``z_x`` alike, the squared distance
    ``|P[f] - x|^2`` lies in ``[|z_f - z_x|^2, |z_f - z_x|^2 + 4 r_f r_x]``
    (Pythagoras on the projection, the triangle inequality on the rest). A pose
    step streams these rows, widens both bounds by a rigorous float32 error
    budget, keeps the candidates whose lower bound can still reach the smallest
    upper bound of their segment (about 2 of 56 on the real database) and
    computes only those exactly on ``pose``. Results are identical with and
    without it; non-finite values make their segment fall back to the exact scan.

    Pose features stack a frame's feature joints (and ankles) over 5 frames
    centred on it, all in the current frame's body frame, so most of each row
    is nearly, but not exactly, a copy of its neighbours' rows: 24 principal
    directions keep most of it (median ``r_f`` 0.09 of typical distances of 1-2
    on the real database with the schema-3 feature).

    Build it once per database (one pass over ``pose`` and a (Dp, Dp)
    eigendecomposition) and pass it as ``pose_proj=`` together with the very
    array it was made from. It is a snapshot: rebuild it after changing ``pose``.

    Parameters
    ----------
    pose : ndarray [shape=(F, Dp)], float32, C-contiguous
        The database's pose features.
    n_columns : int in [2, Dp + 1], keyword-only
        ``J``: columns per frame, ``J - 1`` principal directions plus the
        residual length (default ``min(24, Dp + 1)``: 96 bytes per frame, a
        quarter of 96 floats).
    half : bool, keyword-only
        Store the rows in IEEE binary16 (rounded to nearest from the float64
        projection): 48 bytes per frame at J = 24, half the stream of a pose
        step. The bound then also covers that rounding (about 2^-11 of
        ``max_norm`` per frame), so a step keeps a few more candidates for the
        exact check; results are the same.

    Attributes
    ----------
    pose : ndarray
        The source array (kept to check that searches use the same one).
    blocks : ndarray [shape=(ceil(F / 16), J, 16)], float32 (float16 with ``half``)
        ``z_f`` of frame ``f`` at ``blocks[f // 16, :, f % 16]`` (padding frames 0).
    rows : ndarray [shape=(F, J)], float32
        The same values row by row (as float32 also with ``half``).
    basis : ndarray [shape=(Dp, J - 1)], float64, orthonormal columns
    mean : ndarray [shape=(Dp,)], float64
    max_norm : float
        An upper bound of ``|P[f] - mean|`` over the frames.
    keep_fraction : float
        Estimated fraction of candidates a step keeps for the exact check
        (``Searcher`` uses the projection only when it is below 0.25).
    """

    def __init__(self, pose, *, n_columns: int | None = None, half: bool = False):
        if not (isinstance(pose, np.ndarray) and pose.dtype == np.float32 and pose.ndim == 2
                and pose.flags.c_contiguous):
            raise ParameterError(f"pose: expected float32 C-contiguous (F, Dp); got {_describe(pose)}")
        F, Dp = pose.shape
        if n_columns is None:
            n_columns = min(24, Dp + 1)
        if isinstance(n_columns, (bool, np.bool_)) or not isinstance(n_columns, (int, np.integer)) \
                or not 2 <= n_columns <= Dp + 1:
            raise ParameterError(f"n_columns: expected an int in [2, {Dp + 1}]; got {n_columns!r}")
        self.pose = pose
        k = int(n_columns) - 1
        block = 65536
        mean = np.zeros(Dp)
        for a in range(0, F, block):
            mean += pose[a:a + block].sum(axis=0, dtype=np.float64)
        mean /= max(F, 1)
        finite = bool(np.isfinite(mean).all())
        if not finite:
            mean = np.zeros(Dp)
        cov = np.zeros((Dp, Dp))
        for a in range(0, F, block):
            d = pose[a:a + block] - mean
            if not finite:
                d = np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)
            cov += d.T @ d
        _, vecs = np.linalg.eigh(cov)
        self.basis = np.ascontiguousarray(vecs[:, ::-1][:, :k])
        self.mean = mean
        # binary16 is rounded once, from float64 (the kernel's bound assumes at
        # most 2^-11 (1 + 2^-10) relative per value)
        rows = np.zeros((-(-F // 16) * 16, k + 1), dtype=np.float16 if half else np.float32)
        max_norm = 0.0
        with np.errstate(invalid="ignore", over="ignore"):
            for a in range(0, F, block):
                d = pose[a:a + block] - mean  # float64
                c = d @ self.basis
                r = np.sqrt(((d - c @ self.basis.T) ** 2).sum(axis=1))
                rows[a:a + len(c), :k] = c
                rows[a:a + len(c), k] = r
                n = np.sqrt((d * d).sum(axis=1))
                if n.size:
                    # NaN rows are caught per segment by the kernel; they set no bound
                    max_norm = max(max_norm, float(np.nanmax(n, initial=0.0)))
        self.max_norm = max_norm * (1.0 + 1e-9) if np.isfinite(max_norm) else np.inf
        # 16 frames per block, column by column: the kernel computes 16 frames'
        # distances as one vector per column (no horizontal sums)
        self.blocks = np.ascontiguousarray(rows.reshape(-1, 16, k + 1).transpose(0, 2, 1))
        self.half = bool(half)
        self._F = F
        self.keep_fraction = self._estimate_keep_fraction()

    def _estimate_keep_fraction(self, *, n_runs: int = 64, run: int = 56, seed: int = 0) -> float:
        """Fraction of candidates the filter keeps, estimated on runs of ``run``
        consecutive frames against other frames of the database (float64, no
        error budget: close to what the kernel keeps). About 0.03-0.04 on real
        pose features; near 1 on unstructured data, where the filter only adds work."""
        F = self._F
        if F < 2 * run:
            return 0.0
        rng = np.random.default_rng(seed)
        z = self.rows.astype(np.float64)
        if not np.isfinite(z).all():
            return 1.0
        kept = 0
        for _ in range(n_runs):
            a = int(rng.integers(0, F - run))
            zx = z[int(rng.integers(0, F))]
            lo = ((z[a:a + run] - zx) ** 2).sum(axis=1)
            hi = lo + 4.0 * z[a:a + run, -1] * zx[-1]
            kept += int((lo <= hi.min()).sum())
        return kept / (n_runs * run)

    @property
    def rows(self) -> np.ndarray:
        """ndarray [shape=(F, J)], float32: ``z_f`` row by row (a copy of ``blocks``)."""
        return self.blocks.transpose(0, 2, 1).reshape(-1, self.blocks.shape[1])[:self._F].astype(np.float32)

    def __repr__(self) -> str:
        return (f"PoseProjection({self._F} frames x {self.blocks.shape[1]}{', binary16' if self.half else ''}, "
                f"{self.blocks.nbytes / 1e6:.0f} MB)")
