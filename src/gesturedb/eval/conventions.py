"""Metrics in the conventions of published evaluations, so numbers can sit beside their tables.

:mod:`gesturedb.eval.metrics` makes its own choices where the references
disagree (``docs/metrics.md``). This module gives the other readings under
their own names; the formulas are the same, only the conventions differ:

genea_histogram, genea_hellinger
    GENEA's histograms (``calc_histogram.py``): speeds (or accelerations) in
    **cm/s** (cm/s²) at the data's own frame rate (GENEA's script hard-codes
    30 fps), 1 cm/s bins from 0 to ``max_cm_s``, values beyond the last edge
    **dropped** (``np.histogram``), one histogram per joint summed over joints.
beat_align_headline
    BeatAlign in the BEAT/EMAGE code's reading: for every **audio** beat the
    nearest motion beat (``direction="audio_to_motion"``), with motion beats the
    speed minima above ``0.3 x`` a **reference** mean speed (the database's, as
    EMAGE normalises by its training set's) rather than each clip's own.
"""
from __future__ import annotations

import math

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.eval import metrics as M

__all__ = ["GENEA_SPEED_MAX_CM_S", "GENEA_ACCEL_MAX_CM_S2", "CONVENTION_COLUMNS", "genea_histogram",
           "genea_hellinger", "reference_mean_speed", "beat_align_headline", "database_mean_speed",
           "database_genea_counts", "convention_metrics"]

#: Last speed bin edge of the GENEA histograms (cm/s): values beyond are dropped.
GENEA_SPEED_MAX_CM_S = 50.0
#: Last acceleration bin edge (cm/s^2) of our GENEA-style acceleration histogram.
GENEA_ACCEL_MAX_CM_S2 = 1000.0


def _values_cm(positions, *, fps: float, joints, kind: str) -> np.ndarray:
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise ParameterError(f"positions: expected (F, J, 3) metres; got shape {pos.shape}")
    if joints is not None:
        pos = pos[:, np.asarray(joints, dtype=np.int64)]
    order = {"speed": 1, "acceleration": 2}.get(kind)
    if order is None:
        raise ParameterError(f"kind: expected 'speed' or 'acceleration'; got {kind!r}")
    if pos.shape[0] <= order:
        raise ParameterError(f"positions: expected more than {order} frames for {kind}; got {pos.shape[0]}")
    # forward differences as GENEA's scripts (np.diff), metres -> centimetres
    return np.linalg.norm(np.diff(pos, n=order, axis=0), axis=-1) * float(fps) ** order * 100.0


def genea_histogram(positions, *, fps: float, joints=None, kind: str = "speed", bin_width: float = 1.0,
                    max_value: float | None = None):
    """GENEA-convention histogram of joint speeds (cm/s) or accelerations (cm/s²), summed over joints.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
        The data's own frame rate.
    joints : sequence of int, optional
    kind : {"speed", "acceleration"}
    bin_width : float
        cm/s (or cm/s²); GENEA: 1.
    max_value : float, optional
        Last bin edge; default ``GENEA_SPEED_MAX_CM_S`` or ``GENEA_ACCEL_MAX_CM_S2``.

    Returns
    -------
    counts : ndarray [shape=(n_bins,)], int64
        Values at or beyond ``max_value`` are not counted (GENEA's convention).
    edges : ndarray [shape=(n_bins + 1,)]
    """
    if max_value is None:
        max_value = GENEA_SPEED_MAX_CM_S if kind == "speed" else GENEA_ACCEL_MAX_CM_S2
    if not (bin_width > 0 and max_value > bin_width):
        raise ParameterError(f"bins: expected 0 < bin_width < max_value; got {bin_width!r}, {max_value!r}")
    v = _values_cm(positions, fps=fps, joints=joints, kind=kind)
    edges = np.arange(int(math.ceil(max_value / bin_width - 1e-9)) + 1) * float(bin_width)
    # np.histogram closes its last bin on the right; GENEA's edges are half-open throughout
    counts, _ = np.histogram(v[v < edges[-1]], bins=edges)
    return counts.astype(np.int64), edges


def genea_hellinger(generated, ground_truth, *, fps: float, joints=None, kind: str = "speed",
                    bin_width: float = 1.0, max_value: float | None = None) -> float:
    """Hellinger distance between GENEA-convention histograms of two motions (see :func:`genea_histogram`).

    NaN when either histogram is empty (every value beyond the last edge).
    """
    kw = dict(fps=fps, joints=joints, kind=kind, bin_width=bin_width, max_value=max_value)
    p, _ = genea_histogram(generated, **kw)
    q, _ = genea_histogram(ground_truth, **kw)
    if p.sum() == 0 or q.sum() == 0:
        return float("nan")
    return M.hellinger_distance(p, q)


def reference_mean_speed(positions, *, fps: float, joints) -> np.ndarray:
    """Mean speed (m/s) per joint by central differences, as :func:`gesturedb.eval.metrics.motion_beats` measures it.

    Returns ndarray [shape=(len(joints),)]: pass the database's to :func:`beat_align_headline`.
    """
    pos = np.asarray(positions, dtype=np.float64)[:, np.asarray(joints, dtype=np.int64)]
    return np.linalg.norm(np.gradient(pos, 1.0 / float(fps), axis=0), axis=2).mean(axis=0)


def beat_align_headline(positions, *, fps: float, joints, audio_beats_s, reference_speed_m_s,
                        sigma_s: float = 0.3, min_speed_ratio: float = 0.3) -> float:
    """BeatAlign, audio -> motion, with the motion-beat threshold from a reference mean speed.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    joints : sequence of int
        Beat joints (the upper body, or the wrists).
    audio_beats_s : array_like, seconds
    reference_speed_m_s : float or ndarray [shape=(len(joints),)]
        Mean speed of each beat joint over the database (:func:`reference_mean_speed`).
        A motion beat is a speed minimum faster than ``min_speed_ratio`` times it.
    sigma_s : float

    Returns
    -------
    float in [0, 1] (mean over joints), NaN when no joint has a beat to score.
    """
    joints = np.asarray(joints, dtype=np.int64)
    ref = np.broadcast_to(np.asarray(reference_speed_m_s, dtype=np.float64), joints.shape)
    pos = np.asarray(positions, dtype=np.float64)
    a = np.asarray(audio_beats_s, dtype=np.float64).ravel()
    a = a[a <= pos.shape[0] / float(fps)]
    own = reference_mean_speed(pos, fps=fps, joints=joints)
    scores = []
    for j, r, m in zip(joints, ref, own):
        # motion_beats thresholds at ratio x the clip's own mean: rescale the ratio so the
        # threshold becomes ratio x the reference mean instead
        ratio = min_speed_ratio * r / m if m > 0 else math.inf
        if not math.isfinite(ratio):
            continue
        (mb,) = M.motion_beats(pos, fps=fps, joints=[int(j)], min_speed_ratio=ratio)
        s = M.beat_align_score(mb, a, sigma_s=sigma_s, direction="audio_to_motion")
        if not math.isnan(s):
            scores.append(s)
    return float(np.mean(scores)) if scores else float("nan")


#: (key, header, format) of the published-conventions table of ``gesturedb eval motion``.
CONVENTION_COLUMNS = (
    ("genea_hellinger_speed_gt", "H speed GENEA vs GT", ".3f"),
    ("genea_hellinger_accel_gt", "H accel GENEA vs GT", ".3f"),
    ("genea_hellinger_speed_db", "H speed GENEA vs DB", ".3f"),
    ("beat_align_headline", "BeatAlign a->m (DB thr)", ".3f"),
)


def database_mean_speed(db, *, joints, root: int) -> np.ndarray:
    """Mean speed (m/s) of each joint over the database's recordings (root's horizontal position removed),
    frame-weighted; the reference of :func:`beat_align_headline`."""
    total = np.zeros(len(joints))
    n = 0
    for rec in db.recordings:
        if rec.n_frames < 3:
            continue
        pos = np.array(db.joint_positions[rec.start_frame:rec.start_frame + rec.n_frames], dtype=np.float64)
        pos[:, :, [0, 2]] -= pos[:, root:root + 1, [0, 2]]
        total += reference_mean_speed(pos, fps=db.fps, joints=joints) * rec.n_frames
        n += rec.n_frames
    return total / max(n, 1)


def convention_metrics(positions: dict, *, fps: float, joints, audio_beats_s, reference_speed_m_s,
                       database_counts=None) -> dict:
    """Rows of :data:`CONVENTION_COLUMNS` for every system.

    Parameters
    ----------
    positions : dict name -> ndarray [shape=(F, J, 3)], metres
        Root-relative positions (``"ground_truth"`` among them enables the "vs GT" columns).
    joints : sequence of int
        Joints of the histograms and the beats (the upper body).
    database_counts : ndarray, optional
        :func:`genea_histogram` of the database, for the "vs DB" column.
    """
    gt = positions.get("ground_truth")
    rows = {}
    for name, pos in positions.items():
        row = {k: float("nan") for k, _, _ in CONVENTION_COLUMNS}
        if gt is not None:
            row["genea_hellinger_speed_gt"] = genea_hellinger(pos, gt, fps=fps, joints=joints)
            row["genea_hellinger_accel_gt"] = genea_hellinger(pos, gt, fps=fps, joints=joints, kind="acceleration")
        if database_counts is not None:
            c, _ = genea_histogram(pos, fps=fps, joints=joints)
            if c.sum() and np.sum(database_counts):
                row["genea_hellinger_speed_db"] = M.hellinger_distance(c, database_counts)
        row["beat_align_headline"] = beat_align_headline(pos, fps=fps, joints=joints, audio_beats_s=audio_beats_s,
                                                         reference_speed_m_s=reference_speed_m_s)
        rows[name] = row
    return rows


def database_genea_counts(db, *, joints, root: int) -> np.ndarray:
    """:func:`genea_histogram` (speed) summed over the database's recordings."""
    counts = None
    for rec in db.recordings:
        if rec.n_frames < 2:
            continue
        pos = np.array(db.joint_positions[rec.start_frame:rec.start_frame + rec.n_frames], dtype=np.float64)
        pos[:, :, [0, 2]] -= pos[:, root:root + 1, [0, 2]]
        c, _ = genea_histogram(pos, fps=db.fps, joints=joints)
        counts = c if counts is None else counts + c
    return counts
