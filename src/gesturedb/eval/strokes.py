"""Stroke metrics: how much fast motion a synthesis keeps, per joint group and frequency band.

A beat gesture is a stroke of a few hundred milliseconds; its energy sits at 2-7 Hz
in the velocity of the elbows and wrists. A global low-pass (a Savitzky-Golay filter
too long for the frame rate) removes it while leaving the slow movement, and a seam
adds energy at the rate windows are switched. Average jerk cannot tell the two
apart (it weights 7 Hz 16x more than 2 Hz and mixes both); band power can.

:func:`band_power`
    Welch power spectral density of root-relative joint velocity, integrated over
    each band of :data:`BANDS_HZ`, averaged over a group's joints (m^2/s^2).
:func:`band_groups`
    The groups: ``arms`` (elbows and wrists, the joints whose positions carry a
    stroke), ``hands`` (finger joints), ``head`` (neck and head).
:func:`stroke_strength`
    95th percentile of root-relative wrist speed (m/s): how fast the strongest
    strokes are.
:func:`band_ratios`
    Band power of a motion divided by a reference's (the database's own motion,
    or the ground truth).

The bands, the Welch estimate and the band integrals are :mod:`gesturedb.measures`', the
definitions the refiner's validation measures with too. Every length is in seconds, so a 30 fps database is measured like a 15 fps one
(the bands must lie below the Nyquist frequency: a band reaching past it is NaN).
Definitions: ``docs/metrics.md``.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.eval.metrics import find_wrists
from gesturedb.eval.placement import root_relative
from gesturedb.io.joints import group_joints
from gesturedb.measures import BANDS_HZ, WELCH_SEGMENT_S, band_integrals, band_key, welch_psd
from gesturedb.roles import STROKE_JOINT_GROUPS

__all__ = ["BANDS_HZ", "WELCH_SEGMENT_S", "STROKE_PERCENTILE", "band_groups", "band_psd", "band_power",
           "band_ratios", "stroke_strength", "band_key", "pooled_band_power", "stroke_metrics", "database_strokes",
           "STROKE_GROUPS", "STROKE_COLUMNS", "STROKE_GT_COLUMNS", "group_band_power"]

#: Percentile of wrist speed reported as stroke strength.
STROKE_PERCENTILE = 95.0

#: Joint groups of the stroke tables, in table order (:data:`gesturedb.roles.STROKE_JOINT_GROUPS`).
STROKE_GROUPS = tuple(STROKE_JOINT_GROUPS)


#: (key, header, format) of ``gesturedb eval motion``'s stroke table against the database's own motion
#: (``_db``), with the wrist p95, and of the table against the ground truth (``_gt``).
STROKE_COLUMNS = tuple(
    (f"band_{g}_{band_key(b)}_db", f"{g} {band_key(b)}", ".2f") for g in STROKE_GROUPS for b in BANDS_HZ
) + (("wrist_p95_m_s", "wrist p95 m/s", ".2f"),)
STROKE_GT_COLUMNS = tuple(
    (f"band_{g}_{band_key(b)}_gt", f"{g} {band_key(b)}", ".2f") for g in STROKE_GROUPS for b in BANDS_HZ
)

def band_groups(names: Sequence[str]) -> dict[str, np.ndarray]:
    """Joint indices (int64) of each band group the skeleton has: ``arms``, ``hands``, ``head``
    (:data:`gesturedb.roles.STROKE_JOINT_GROUPS`)."""
    return group_joints(list(names), STROKE_JOINT_GROUPS)


def _check(positions, fps) -> tuple[np.ndarray, float]:
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[-1] != 3:
        raise ParameterError(f"positions: expected an array (frames, joints, 3); got shape {pos.shape}")
    fps = float(fps)
    if not np.isfinite(fps) or fps <= 0:
        raise ParameterError(f"fps: expected a positive frame rate; got {fps!r}")
    return pos, fps


def band_psd(positions, *, fps: float, joints, root: int = 0,
             segment_s: float = WELCH_SEGMENT_S) -> tuple[np.ndarray, np.ndarray, int]:
    """Welch PSD of root-relative velocity, summed over x, y, z and averaged over ``joints``.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    joints : sequence of int
    root : int
        Joint whose horizontal position is removed from every joint in every frame.
    segment_s : float
        Welch segment length (s); shorter motions use one segment of their own length.

    Returns
    -------
    freqs : ndarray [shape=(K,)], Hz
    psd : ndarray [shape=(K,)], (m/s)^2 / Hz
    n_segments : int
        Welch segments averaged (weight when pooling several recordings).
    """
    pos, fps = _check(positions, fps)
    joints = np.asarray(joints, dtype=np.int64)
    vel = np.diff(root_relative(pos, root=root)[:, joints], axis=0) * fps  # (F-1, j, 3)
    if vel.shape[0] < 4:
        raise ParameterError(f"positions: expected at least 5 frames for a band power; got {pos.shape[0]}")
    f, p, n_seg = welch_psd(vel, fps=fps, axis=0, segment_s=segment_s)
    return f, p.sum(axis=-1).mean(axis=-1), n_seg


def band_power(positions, *, fps: float, joints, root: int = 0, bands=BANDS_HZ,
               segment_s: float = WELCH_SEGMENT_S) -> dict[str, float]:
    """Power (m^2/s^2) of root-relative joint velocity in each band, averaged over ``joints``.

    The Welch PSD of :func:`band_psd` summed over the frequency bins in ``[lo, hi)``
    times the bin width. A sinusoid of amplitude ``A`` m and frequency ``f`` Hz in one
    coordinate has velocity power ``(2 pi f A)^2 / 2 * sinc(f / fps)^2`` in the band that holds ``f``
    (the sinc is the gain of the first difference that makes the velocity).

    Returns
    -------
    dict band name (:func:`band_key`) -> power, NaN for a band past the Nyquist frequency.
    """
    f, p, _ = band_psd(positions, fps=fps, joints=joints, root=root, segment_s=segment_s)
    return band_integrals(f, p, fps=float(fps), bands=bands)


def pooled_band_power(recordings: Sequence[np.ndarray], *, fps: float, joints, root: int = 0, bands=BANDS_HZ,
                      segment_s: float = WELCH_SEGMENT_S) -> dict[str, float]:
    """:func:`band_power` of several recordings (e.g. a database's), their PSDs averaged by Welch segments.

    Recordings shorter than one segment are left out unless all are.
    """
    fps = float(fps)
    nper = int(round(segment_s * fps))
    recs = [r for r in recordings if r.shape[0] > nper] or list(recordings)
    if not recs:
        raise ParameterError("recordings: expected at least one recording")
    acc, tot, f = None, 0, None
    for r in recs:
        f, p, n = band_psd(r, fps=fps, joints=joints, root=root, segment_s=segment_s)
        if acc is not None and p.shape != acc.shape:
            continue  # a shorter recording's coarser spectrum: pooled only with its own kind
        acc = p * n if acc is None else acc + p * n
        tot += n
    return band_integrals(f, acc / tot, fps=fps, bands=bands)


def band_ratios(power: dict[str, float], reference: dict[str, float]) -> dict[str, float]:
    """``power[band] / reference[band]`` for every band (NaN where the reference is 0 or missing)."""
    out = {}
    for k, v in power.items():
        r = reference.get(k, float("nan"))
        out[k] = float(v / r) if r and np.isfinite(r) and r > 0 else float("nan")
    return out


def stroke_strength(positions, *, fps: float, wrists, root: int = 0, percentile: float = STROKE_PERCENTILE) -> float:
    """The ``percentile`` (95th) of root-relative wrist speed over frames and both wrists (m/s)."""
    pos, fps = _check(positions, fps)
    w = np.asarray(wrists, dtype=np.int64)
    if pos.shape[0] < 2:
        return float("nan")
    v = np.linalg.norm(np.diff(root_relative(pos, root=root)[:, w], axis=0), axis=-1) * fps
    return float(np.percentile(v, percentile))


def _wrists(names) -> list[int]:
    return list(find_wrists(list(names)))


def stroke_metrics(positions, *, fps: float, names: Sequence[str], root: int, reference: dict,
                   truth: dict | None = None) -> dict:
    """One motion's stroke numbers, flat, for the evaluation tables.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    names : sequence of str
        Joint names (groups and wrists are found by body part).
    root : int
    reference : dict group -> dict band -> power
        The database's own band power (:func:`database_strokes`).
    truth : dict group -> dict band -> power, optional
        The ground truth's band power (:func:`group_band_power` of it, computed once for all systems).

    Returns
    -------
    dict
        ``band_<group>_<band>_db`` (ratio to ``reference``), ``band_<group>_<band>_gt``
        (ratio to ``truth``, NaN without one), ``band_<group>_<band>_m2_s2``
        (the power itself) and ``wrist_p95_m_s`` (:func:`stroke_strength`).
    """
    out = {}
    for g, bp in group_band_power(positions, fps=fps, names=names, root=root).items():
        for k, v in band_ratios(bp, reference[g]).items():
            out[f"band_{g}_{k}_db"] = v
        for k, v in (band_ratios(bp, truth[g]) if truth is not None else {k: float("nan") for k in bp}).items():
            out[f"band_{g}_{k}_gt"] = v
        for k, v in bp.items():
            out[f"band_{g}_{k}_m2_s2"] = v
    out["wrist_p95_m_s"] = stroke_strength(positions, fps=fps, wrists=_wrists(names), root=root)
    return out


def group_band_power(positions, *, fps: float, names: Sequence[str], root: int) -> dict:
    """:func:`band_power` of every group of :func:`band_groups`: group -> band -> power (m^2/s^2)."""
    return {g: band_power(positions, fps=fps, joints=js, root=root) for g, js in band_groups(names).items()}


def database_strokes(recordings: Sequence[np.ndarray], *, fps: float, names: Sequence[str],
                     root: int) -> tuple[dict, float]:
    """The database's own band power per group (:func:`pooled_band_power`) and its wrist p95 (m/s).

    ``recordings``: joint positions (F_r, J, 3) of each recording, measured apart (no seam between them).
    """
    bands = {g: pooled_band_power(recordings, fps=fps, joints=js, root=root) for g, js in band_groups(names).items()}
    w = _wrists(names)
    speeds = np.concatenate([
        np.linalg.norm(np.diff(root_relative(np.asarray(p, dtype=np.float64), root=root)[:, w], axis=0), axis=-1).ravel()
        * fps for p in recordings if p.shape[0] > 1])
    return bands, float(np.percentile(speeds, STROKE_PERCENTILE)) if speeds.size else float("nan")
