"""Measurement primitives shared by evaluation and the refiner's validation.

``gesturedb.eval`` (the tables of ``gesturedb eval``) and ``gesturedb.refiner.validation``
(the score that decides whether a refiner beat its input) measure motion the same way,
and must: a refiner chosen on one definition of band power and judged on another would
be chosen for the wrong thing. The refiner sits below ``eval`` in the layers
(docs/ARCHITECTURE.md), so the definitions they share live here, below both. Plain
numpy on arrays (scipy for Welch's method); every caller keeps its own checks of shapes
and its own reductions over joints and windows.

:data:`BANDS_HZ`, :data:`WELCH_SEGMENT_S`, :func:`band_key`
    The frequency bands of the stroke tables and the Welch segment they are measured with.
:func:`welch_psd`
    Welch power spectral density of velocities along their time axis.
:func:`band_integrals`
    A PSD integrated over each band (NaN for a band past the Nyquist frequency).
:func:`speed_bins`, :func:`speed_counts`
    The joint-speed histogram of GENEA's "histogram of moving distance" (1 cm/s bins up
    to 2 m/s, the last bin holding everything faster).
:func:`hellinger_distance`
    The distance between two such histograms.
:func:`frechet_distance`
    The Fréchet distance between Gaussians fitted to two samples of codes (FGD*).

Definitions and references: ``docs/metrics.md``.
"""
from __future__ import annotations

import math
import warnings
from typing import Sequence

import numpy as np
from scipy import linalg

from gesturedb.errors import ParameterError

__all__ = ["BANDS_HZ", "WELCH_SEGMENT_S", "SPEED_BIN_M_S", "SPEED_MAX_M_S", "band_key", "welch_psd",
           "band_integrals", "speed_bins", "speed_counts", "hellinger_distance", "frechet_distance",
           "FGD_STRIDE", "motion_windows"]

#: Frequency bands (Hz): slow movement and sway, gesture phrases, beat strokes.
BANDS_HZ: tuple[tuple[float, float], ...] = ((0.5, 2.0), (2.0, 4.0), (4.0, 7.0))
#: Welch segment length (s): 0.25 Hz resolution, several segments in a 15 s stretch.
WELCH_SEGMENT_S = 4.0
#: The speed histogram's bin width and the upper edge of its last bin (m/s): GENEA's 1 cm/s up to 2 m/s.
SPEED_BIN_M_S = 0.01
SPEED_MAX_M_S = 2.0


def band_key(band: Sequence[float]) -> str:
    """``"0.5-2"`` for (0.5, 2.0): the name of a band in tables and JSON."""
    return "-".join(f"{x:g}" for x in band)


def welch_psd(velocity: np.ndarray, *, fps: float, axis: int = 0,
              segment_s: float = WELCH_SEGMENT_S) -> tuple[np.ndarray, np.ndarray, int]:
    """Welch PSD of velocities along their time axis: segments of ``segment_s`` (at most the
    whole length), half overlapping, Hann window, each segment's mean removed.

    Parameters
    ----------
    velocity : ndarray [shape=(..., n, ...)], m/s
        ``n`` samples along ``axis`` (at least 2).
    fps : float
        Samples per second.
    axis : int
        The time axis.
    segment_s : float
        Segment length (s).

    Returns
    -------
    freqs : ndarray [shape=(K,)], Hz
    psd : ndarray, (m/s)^2 / Hz
        ``velocity``'s shape with ``axis`` replaced by the K frequencies (sum or average the
        other axes as the caller needs).
    n_segments : int
        Segments averaged (a weight when pooling PSDs of several recordings).
    """
    from scipy.signal import welch

    n = velocity.shape[axis]
    nper = min(int(round(segment_s * fps)), n)
    f, p = welch(velocity, fs=fps, nperseg=nper, noverlap=nper // 2, detrend="constant", axis=axis)
    return f, p, 1 + (n - nper) // (nper - nper // 2)


def band_integrals(freqs: np.ndarray, psd: np.ndarray, *, fps: float, bands=BANDS_HZ) -> dict[str, float]:
    """``psd`` (K,) summed over the frequency bins in ``[lo, hi)`` of each band, times the bin width.

    Returns
    -------
    dict band name (:func:`band_key`) -> power, NaN for a band reaching past ``fps / 2``
    (what this frame rate cannot carry).
    """
    df = freqs[1] - freqs[0] if freqs.size > 1 else 0.0
    out = {}
    for lo, hi in bands:
        if hi > fps / 2 + 1e-9:
            out[band_key((lo, hi))] = float("nan")
            continue
        sel = (freqs >= lo - 1e-9) & (freqs < hi - 1e-9)
        out[band_key((lo, hi))] = float(psd[sel].sum() * df)
    return out


def speed_bins(bin_width_m_s: float = SPEED_BIN_M_S, max_speed_m_s: float = SPEED_MAX_M_S) -> np.ndarray:
    """Edges (m/s) of the speed histogram: ``0, w, 2w, ...`` up to ``max_speed_m_s`` (rounded up to a bin)."""
    if not (bin_width_m_s > 0 and max_speed_m_s > bin_width_m_s):
        raise ParameterError(
            "bins: expected 0 < bin_width_m_s < max_speed_m_s; "
            f"got bin_width_m_s={bin_width_m_s!r}, max_speed_m_s={max_speed_m_s!r}"
        )
    n_bins = int(math.ceil(max_speed_m_s / bin_width_m_s - 1e-9))
    return np.arange(n_bins + 1) * bin_width_m_s


def speed_counts(speeds: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(n_bins,) int64: how many of ``speeds`` (any shape, m/s) fall in each bin of ``edges``.

    Speeds at or above the last edge count in the last bin (GENEA dropped them silently;
    a fast synthesized motion must not look slow)."""
    # np.histogram's last bin is closed on the right
    counts, _ = np.histogram(np.minimum(np.ravel(speeds), edges[-1]), bins=edges)
    return counts.astype(np.int64)


def hellinger_distance(p, q):
    """Hellinger distance between two histograms.

    ``H(p, q) = sqrt(1 - sum_i sqrt(p_i q_i))`` after normalising each to sum 1
    (GENEA's formula), evaluated as the equal ``sqrt(sum_i (sqrt(p_i) - sqrt(q_i))^2 / 2)``,
    which is exactly 0 for identical histograms instead of ``sqrt(rounding error)``.
    0 for identical distributions, 1 for disjoint supports.

    Parameters
    ----------
    p, q : array_like [shape=(n_bins,)]
        Non-negative counts or weights over the same bins.

    Returns
    -------
    float in [0, 1]
    """
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    if p.ndim != 1 or p.shape != q.shape:
        raise ParameterError(
            f"histograms: expected two 1-D arrays of the same length; got shapes {p.shape} and {q.shape}"
        )
    for name, h in (("p", p), ("q", q)):
        if not np.all(np.isfinite(h)) or np.any(h < 0) or h.sum() <= 0:
            raise ParameterError(f"histogram {name}: expected finite non-negative weights with a positive sum")
    h2 = 0.5 * np.sum((np.sqrt(p / p.sum()) - np.sqrt(q / q.sum())) ** 2)
    return float(min(1.0, math.sqrt(h2)))


def frechet_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to two samples of codes (n, L) and (m, L).

    ``|mu_a - mu_b|^2 + tr(C_a + C_b - 2 (C_a C_b)^(1/2))`` with the sample covariances;
    the tiny imaginary part ``sqrtm`` can return from rounding is dropped, and a result
    below 0 from rounding is 0. FGD* of :mod:`gesturedb.eval.fgd` and the refiner's
    validation (:mod:`gesturedb.refiner.validation`) both measure with it.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1] or a.shape[0] < 2 or b.shape[0] < 2:
        raise ParameterError(f"codes: expected two arrays (n >= 2, L) with the same L, got {a.shape} and {b.shape}")
    mu = a.mean(0) - b.mean(0)
    ca, cb = np.atleast_2d(np.cov(a, rowvar=False)), np.atleast_2d(np.cov(b, rowvar=False))
    # without disp= (deprecated in SciPy 1.17, gone in 1.18): the matrix only, in every version we allow.
    # A still system has a singular covariance; SciPy warns, and the root is still right to rounding.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", linalg.LinAlgWarning)
        root = linalg.sqrtm(ca @ cb)
    d = float(mu @ mu + np.trace(ca) + np.trace(cb) - 2 * np.trace(np.real(root)))
    return max(d, 0.0)


#: frames between the starts of FGD*'s windows (:func:`motion_windows`)
FGD_STRIDE = 4


def motion_windows(positions: np.ndarray, *, joints, window: int, fps: float, stride: int = FGD_STRIDE) -> np.ndarray:
    """Windows (n, window, 6 len(joints)) float32 of positions (T, J, 3) in metres and their
    velocities in m/s (backward differences, the first frame's repeated), starts 0, stride, ...;
    (0, window, D) when T < window. What FGD* encodes (:mod:`gesturedb.eval.fgd`, and the
    refiner's validation, which may not import eval)."""
    pos = np.asarray(positions, dtype=np.float64)[:, np.asarray(joints)]
    T = pos.shape[0]
    vel = np.diff(pos, axis=0, prepend=pos[:1]) * fps
    if T > 1:
        vel[0] = vel[1]
    flat = np.concatenate([pos.reshape(T, -1), vel.reshape(T, -1)], axis=1).astype(np.float32)
    starts = np.arange(0, T - window + 1, stride)
    if starts.size == 0:
        return np.zeros((0, window, flat.shape[1]), dtype=np.float32)
    return np.stack([flat[s:s + window] for s in starts])
