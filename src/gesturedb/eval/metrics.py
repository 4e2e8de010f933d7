"""Objective gesture metrics on joint positions.

Every function takes plain arrays: joint positions ``(F, J, 3)`` in metres
(y up) sampled at ``fps`` frames per second. Generated motion and ground truth
go through the same functions, so their numbers are comparable by construction.
Formulas, references and the choices made where the references disagree are in
``docs/metrics.md``.

Metrics
-------
average_acceleration, average_jerk
    GENEA numerical evaluation (Kucherenko et al. 2021): norm of the 2nd / 3rd
    finite difference times fps^k, averaged over frames, then joints.
speed_histogram, hellinger_distance, speed_hellinger
    GENEA "histogram of moving distance" of joint speeds and the Hellinger
    distance between the generated and the ground-truth histogram (the bins and
    the distance are :mod:`gesturedb.measures`', shared with the refiner's validation).
motion_beats, audio_beats, beat_align_score, beat_align
    BeatAlign (Liu et al. 2022, BEAT): Gaussian-weighted distance from motion
    beats (local minima of wrist speed) to audio beats (speech onsets).
l1_diversity
    Mean pairwise L1 distance between fixed-length windows of one motion.
seam_jerk
    Jerk at the frames where a database search switched windows versus
    inside the windows.
motion_report
    All of the above for generated motion and, when given, the ground truth.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.measures import SPEED_BIN_M_S, SPEED_MAX_M_S, hellinger_distance, speed_bins, speed_counts

__all__ = [
    "average_acceleration",
    "average_jerk",
    "joint_speeds",
    "speed_histogram",
    "hellinger_distance",
    "speed_hellinger",
    "motion_beats",
    "audio_beats",
    "beat_align_score",
    "beat_align",
    "l1_diversity",
    "seam_jerk",
    "find_wrists",
    "motion_report",
    "SMPLX_WRISTS",
    "DEFAULT_DIVERSITY_WINDOW_S",
]

#: Left and right wrist in the SMPL-X joint order (55 joints).
SMPLX_WRISTS = (20, 21)

#: 34 frames at 15 fps, the clip length of the TED/BEAT diversity evaluations.
DEFAULT_DIVERSITY_WINDOW_S = 34.0 / 15.0

# BEAT/EMAGE motion-beat detector: local minima over +-7 frames at 30 fps.
_BEAT_ORDER_S = 7.0 / 30.0
# EMAGE keeps only minima where the joint moves faster than 0.3 x its mean speed.
_BEAT_MIN_SPEED_RATIO = 0.3


# --------------------------------------------------------------------------- checks
def _positions(x: Any, name: str = "positions") -> np.ndarray:
    arr = np.asarray(x)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ParameterError(f"{name}: expected an array of shape (F, J, 3); got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ParameterError(f"{name}: expected real numbers; got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{name}: expected finite values; got NaN or inf")
    return arr


def _fps(fps: Any) -> float:
    try:
        value = float(fps)
    except (TypeError, ValueError):
        raise ParameterError(f"fps: expected a positive number; got {fps!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ParameterError(f"fps: expected a positive number; got {fps!r}")
    return value


def _joint_index(joints: Any, n_joints: int, name: str = "joints") -> np.ndarray:
    if joints is None:
        return np.arange(n_joints)
    idx = np.asarray(joints)
    if idx.ndim == 0:
        idx = idx.reshape(1)
    if idx.ndim != 1 or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer):
        raise ParameterError(f"{name}: expected a non-empty sequence of joint indices; got {joints!r}")
    if idx.min() < -n_joints or idx.max() >= n_joints:
        raise ParameterError(
            f"{name}: expected indices in [0, {n_joints}) for {n_joints} joints; got {idx.tolist()}"
        )
    return idx % n_joints


def _select(positions: Any, joints: Any, name: str = "positions") -> np.ndarray:
    pos = _positions(positions, name)
    return pos[:, _joint_index(joints, pos.shape[1])]


def _need_frames(pos: np.ndarray, n: int, what: str, name: str = "positions") -> None:
    if pos.shape[0] < n:
        raise ParameterError(f"{name}: {what} needs at least {n} frames; got {pos.shape[0]}")


# ------------------------------------------------------------------ GENEA: AA and AJ
def _finite_difference_norms(pos: np.ndarray, order: int, fps: float) -> np.ndarray:
    """Norm of the order-th forward difference times fps**order: (F - order, J)."""
    diff = np.diff(pos, n=order, axis=0)
    return np.linalg.norm(diff, axis=2) * fps**order


def average_acceleration(positions, *, fps, joints=None, per_joint=False):
    """Average acceleration magnitude (GENEA "AA").

    ``AA = mean_j mean_t || x[t+2, j] - 2 x[t+1, j] + x[t, j] || * fps**2``

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
        Frames per second.
    joints : sequence of int, optional
        Joint indices to evaluate (default: all).
    per_joint : bool
        Return the per-joint averages instead of their mean.

    Returns
    -------
    float or ndarray [shape=(len(joints),)], m/s^2
    """
    pos = _select(positions, joints)
    _need_frames(pos, 3, "acceleration")
    per = _finite_difference_norms(pos, 2, _fps(fps)).mean(axis=0)
    return per if per_joint else float(per.mean())


def average_jerk(positions, *, fps, joints=None, per_joint=False):
    """Average jerk magnitude (GENEA "AJ").

    ``AJ = mean_j mean_t || x[t+3] - 3 x[t+2] + 3 x[t+1] - x[t] || * fps**3``

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    joints : sequence of int, optional
    per_joint : bool
        Return the per-joint averages instead of their mean.

    Returns
    -------
    float or ndarray [shape=(len(joints),)], m/s^3
    """
    pos = _select(positions, joints)
    _need_frames(pos, 4, "jerk")
    per = _finite_difference_norms(pos, 3, _fps(fps)).mean(axis=0)
    return per if per_joint else float(per.mean())


# ------------------------------------------------------- GENEA: speed histograms (HMD)
def joint_speeds(positions, *, fps, joints=None):
    """Speed of each joint between adjacent frames.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    joints : sequence of int, optional

    Returns
    -------
    ndarray [shape=(F - 1, len(joints))], m/s
    """
    pos = _select(positions, joints)
    _need_frames(pos, 2, "speed")
    return _finite_difference_norms(pos, 1, _fps(fps))


def speed_histogram(positions, *, fps, joints=None, bin_width_m_s=SPEED_BIN_M_S, max_speed_m_s=SPEED_MAX_M_S):
    """Histogram of joint speeds pooled over the selected joints (GENEA HMD, "Total").

    Speeds at or above ``max_speed_m_s`` are counted in the last bin (GENEA
    dropped them silently; a fast synthesized motion must not look slow).

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    joints : sequence of int, optional
    bin_width_m_s : float
        Bin width in m/s (default 0.01 m/s = GENEA's 1 cm/s).
    max_speed_m_s : float
        Upper edge of the last bin in m/s.

    Returns
    -------
    counts : ndarray [shape=(n_bins,)], int64
        Number of (frame, joint) speed samples per bin, summed over joints.
    edges : ndarray [shape=(n_bins + 1,)], m/s
    """
    edges = speed_bins(float(bin_width_m_s), float(max_speed_m_s))
    return speed_counts(joint_speeds(positions, fps=fps, joints=joints), edges), edges


def speed_hellinger(generated, ground_truth, *, fps, joints=None, bin_width_m_s=SPEED_BIN_M_S,
                    max_speed_m_s=SPEED_MAX_M_S):
    """Hellinger distance between the speed histograms of two motions.

    Parameters
    ----------
    generated, ground_truth : ndarray [shape=(F, J, 3)], metres
        Same joints in the same order; frame counts may differ.
    fps : float
        Frame rate of both motions.
    joints, bin_width_m_s, max_speed_m_s
        As in :func:`speed_histogram`.

    Returns
    -------
    float in [0, 1]
    """
    gen = _positions(generated, "generated")
    gt = _positions(ground_truth, "ground_truth")
    if gen.shape[1] != gt.shape[1]:
        raise ParameterError(
            f"ground_truth: expected {gen.shape[1]} joints like the generated motion; got {gt.shape[1]}"
        )
    kw = dict(fps=fps, joints=joints, bin_width_m_s=bin_width_m_s, max_speed_m_s=max_speed_m_s)
    p, _ = speed_histogram(gen, **kw)
    q, _ = speed_histogram(gt, **kw)
    return hellinger_distance(p, q)


# ----------------------------------------------------------------- BEAT: BeatAlign
def motion_beats(positions, *, fps, joints, order_s=_BEAT_ORDER_S, min_speed_ratio=_BEAT_MIN_SPEED_RATIO):
    """Motion beats: local minima of joint speed, one list per joint.

    Speed uses central differences (first/last frame one-sided), so a beat at
    frame ``t`` is at time ``t / fps``. A frame is a beat when its speed is
    strictly below every other frame within ``order_s`` on both sides
    (``scipy.signal.argrelextrema(np.less, order)``) and above
    ``min_speed_ratio`` times the joint's mean speed over the clip, which
    drops the jitter minima of a hand at rest (EMAGE's threshold).

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    joints : sequence of int
        Joints whose speed defines beats (the wrists).
    order_s : float
        Half-width of the minimum's neighbourhood in seconds (default 7/30 s).
    min_speed_ratio : float
        Relative speed threshold; 0 keeps every local minimum.

    Returns
    -------
    list of ndarray [shape=(n_beats_j,)], seconds
        One array per joint in ``joints``.
    """
    from scipy.signal import argrelextrema

    fps = _fps(fps)
    pos = _select(positions, joints)
    _need_frames(pos, 3, "motion beats")
    if not (order_s > 0) or not (min_speed_ratio >= 0):
        raise ParameterError(
            f"motion beats: expected order_s > 0 and min_speed_ratio >= 0; got {order_s!r}, {min_speed_ratio!r}"
        )
    order = max(1, int(round(order_s * fps)))
    speed = np.linalg.norm(np.gradient(pos, 1.0 / fps, axis=0), axis=2)  # (F, J)
    beats = []
    for j in range(speed.shape[1]):
        (minima,) = argrelextrema(speed[:, j], np.less, order=order)
        keep = speed[minima, j] > min_speed_ratio * speed[:, j].mean()
        beats.append(minima[keep] / fps)
    return beats


def audio_beats(audio, *, sr, hop_length=512):
    """Audio beats: speech onsets from librosa's spectral-flux onset detector.

    ``librosa.onset.onset_detect(y, sr, hop_length, units="time")`` with
    librosa's default peak picking, as in BEAT/EMAGE's evaluation.

    Parameters
    ----------
    audio : ndarray [shape=(n_samples,)]
        Mono waveform.
    sr : int
        Sample rate in Hz.
    hop_length : int
        Onset envelope hop in samples (512 = 32 ms at 16 kHz).

    Returns
    -------
    ndarray [shape=(n_onsets,)], seconds
    """
    import librosa

    y = np.asarray(audio)
    if y.ndim != 1 or y.size == 0 or not np.issubdtype(y.dtype, np.floating):
        raise ParameterError(
            f"audio: expected a non-empty 1-D float waveform (mono); got dtype {y.dtype} shape {y.shape}"
        )
    if sr is None or not (float(sr) > 0):
        raise ParameterError(f"sr: expected the audio sample rate in Hz; got {sr!r}")
    onsets = librosa.onset.onset_detect(
        y=y.astype(np.float32, copy=False), sr=int(sr), hop_length=int(hop_length), units="time"
    )
    return np.asarray(onsets, dtype=np.float64)


def beat_align_score(motion_beats_s, audio_beats_s, *, sigma_s=0.3, direction="motion_to_audio"):
    """BeatAlign between two sets of beat times.

    ``direction="motion_to_audio"`` (the BEAT paper's equation)::

        BA = 1/|M| * sum_{m in M} exp(-min_{a in A} (m - a)^2 / (2 sigma^2))

    ``direction="audio_to_motion"`` swaps the roles of M and A (what BEAT's
    released ``GAHR(pose_beats, audio_beats)`` computes).

    Parameters
    ----------
    motion_beats_s, audio_beats_s : array_like [shape=(n,)], seconds
    sigma_s : float
        Tolerance in seconds (BEAT: 0.3).
    direction : {"motion_to_audio", "audio_to_motion"}

    Returns
    -------
    float in [0, 1], or NaN when the set being averaged over is empty
        (no beats to score). 0 when only the other set is empty.
    """
    m = np.asarray(motion_beats_s, dtype=np.float64).ravel()
    a = np.asarray(audio_beats_s, dtype=np.float64).ravel()
    if not (sigma_s > 0):
        raise ParameterError(f"sigma_s: expected a positive tolerance in seconds; got {sigma_s!r}")
    if direction == "motion_to_audio":
        src, ref = m, a
    elif direction == "audio_to_motion":
        src, ref = a, m
    else:
        raise ParameterError(
            f"direction: expected 'motion_to_audio' or 'audio_to_motion'; got {direction!r}"
        )
    if src.size == 0:
        return float("nan")
    if ref.size == 0:
        return 0.0
    ref = np.sort(ref)
    # Nearest reference beat by binary search instead of the O(n*m) double loop.
    k = np.searchsorted(ref, src)
    left = ref[np.clip(k - 1, 0, ref.size - 1)]
    right = ref[np.clip(k, 0, ref.size - 1)]
    d = np.minimum(np.abs(src - left), np.abs(src - right))
    return float(np.mean(np.exp(-(d**2) / (2.0 * sigma_s**2))))


def beat_align(
    positions,
    *,
    fps,
    joints,
    audio=None,
    sr=None,
    audio_beats_s=None,
    sigma_s=0.3,
    direction="motion_to_audio",
    order_s=_BEAT_ORDER_S,
    min_speed_ratio=_BEAT_MIN_SPEED_RATIO,
):
    """BeatAlign of a motion against speech, averaged over the beat joints.

    Motion beats come from :func:`motion_beats` on ``joints`` (the wrists);
    audio beats are ``audio_beats_s`` when given (e.g. word onsets), else the
    onsets :func:`audio_beats` detects in ``audio``. Audio beats after the end
    of the motion (``F / fps``) are ignored so a longer audio track does not
    count against the motion. The score is computed per joint and averaged
    over joints with at least one beat in the averaged-over set.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    joints : sequence of int
        Joints whose speed minima are motion beats.
    audio : ndarray [shape=(n_samples,)], optional
        Mono speech; needs ``sr``.
    sr : int, optional
    audio_beats_s : array_like, optional
        Audio beat times in seconds; overrides ``audio``.
    sigma_s, direction
        As in :func:`beat_align_score`.
    order_s, min_speed_ratio
        As in :func:`motion_beats`.

    Returns
    -------
    float in [0, 1], or NaN when no joint has a beat to score.
    """
    fps = _fps(fps)
    pos = _positions(positions)
    if audio_beats_s is None:
        if audio is None:
            raise ParameterError("beat_align: expected audio (with sr) or audio_beats_s; got neither")
        audio_beats_s = audio_beats(audio, sr=sr)
    a = np.asarray(audio_beats_s, dtype=np.float64).ravel()
    a = a[a <= pos.shape[0] / fps]
    per_joint = [
        beat_align_score(mb, a, sigma_s=sigma_s, direction=direction)
        for mb in motion_beats(pos, fps=fps, joints=joints, order_s=order_s, min_speed_ratio=min_speed_ratio)
    ]
    valid = [s for s in per_joint if not math.isnan(s)]
    return float(np.mean(valid)) if valid else float("nan")


# -------------------------------------------------------------------- L1 diversity
def l1_diversity(positions, *, fps, window_s=DEFAULT_DIVERSITY_WINDOW_S, joints=None):
    """Mean pairwise L1 distance between non-overlapping windows of one motion.

    The motion is cut into ``N = floor(F / W)`` windows of ``W = round(window_s
    * fps)`` frames (a shorter tail is dropped). For windows ``a`` and ``b``::

        d(a, b) = 1/(W |J|) * sum_t sum_j || a[t, j] - b[t, j] ||_1

    and the diversity is the mean of ``d`` over all ``N (N - 1) / 2`` pairs.
    Positions are used as given; pass root-relative positions to ignore
    where the speaker stands.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    window_s : float
        Window length in seconds (default 34/15 s, about 2.27 s).
    joints : sequence of int, optional

    Returns
    -------
    float, metres
    """
    fps = _fps(fps)
    pos = _select(positions, joints)
    if not (window_s > 0):
        raise ParameterError(f"window_s: expected a positive window length in seconds; got {window_s!r}")
    w = max(1, int(round(window_s * fps)))
    n = pos.shape[0] // w
    if n < 2:
        raise ParameterError(
            f"positions: L1 diversity needs at least 2 windows of {w} frames ({window_s:g} s); "
            f"got {pos.shape[0]} frames"
        )
    windows = pos[: n * w].reshape(n, w * pos.shape[1] * 3)
    total = 0.0
    # One row against the rest keeps memory at O(N * W * J) for long motions.
    for i in range(n - 1):
        total += float(np.abs(windows[i + 1 :] - windows[i]).sum())
    return total / (n * (n - 1) / 2) / (w * pos.shape[1])


# ---------------------------------------------------------------------- seam jerk
def seam_jerk(positions, *, fps, boundaries, joints=None):
    """Jerk at window seams versus inside windows.

    A boundary ``b`` is the first frame of a new window (the cut lies between
    frames ``b - 1`` and ``b``). The jerk stencil ``x[i..i+3]`` (``np.diff(n=3)``
    index ``i``) straddles that cut for ``i`` in ``b-3 .. b-1``; those stencils
    are "seam", all others "inside". Each stencil's jerk is averaged over the
    selected joints (as in :func:`average_jerk`).

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
    fps : float
    boundaries : sequence of int
        Frames in ``1 .. F-1`` where a new window starts.
    joints : sequence of int, optional

    Returns
    -------
    dict
        ``seam_jerk`` and ``inside_jerk`` (m/s^3), ``ratio`` =
        seam / inside (inf when inside is 0 and seam is not, NaN when both are 0),
        ``n_seam`` and ``n_inside`` (stencil counts).
    """
    fps = _fps(fps)
    pos = _select(positions, joints)
    _need_frames(pos, 4, "seam jerk")
    f = pos.shape[0]
    b = np.asarray(boundaries)
    if b.ndim != 1 or b.size == 0 or not np.issubdtype(b.dtype, np.integer):
        raise ParameterError(f"boundaries: expected a non-empty 1-D sequence of frame indices; got {boundaries!r}")
    if b.min() < 1 or b.max() > f - 1:
        raise ParameterError(
            f"boundaries: expected frames in [1, {f - 1}] for {f} frames; got min {b.min()}, max {b.max()}"
        )
    jerk = _finite_difference_norms(pos, 3, fps).mean(axis=1)  # (F - 3,)
    seam = np.zeros(jerk.shape[0], dtype=bool)
    for off in (1, 2, 3):
        i = b - off
        seam[i[(i >= 0) & (i < jerk.shape[0])]] = True
    if seam.all():
        raise ParameterError("boundaries: every jerk stencil touches a seam; nothing is left inside the windows")
    if not seam.any():
        raise ParameterError("boundaries: no jerk stencil touches a seam")
    s, ins = float(jerk[seam].mean()), float(jerk[~seam].mean())
    if ins > 0:
        ratio = s / ins
    else:
        ratio = float("inf") if s > 0 else float("nan")
    return {
        "seam_jerk": s,
        "inside_jerk": ins,
        "ratio": ratio,
        "n_seam": int(seam.sum()),
        "n_inside": int((~seam).sum()),
    }


# ---------------------------------------------------------------------- the report
_WRIST_KEYS = {
    "left": ("leftwrist", "lwrist", "lefthand", "lhand", "wristl", "handl"),
    "right": ("rightwrist", "rwrist", "righthand", "rhand", "wristr", "handr"),
}


def find_wrists(names: Sequence[str]) -> tuple[int, int]:
    """Indices of the left and right wrist in a list of joint names.

    Matches SMPL-X (``left_wrist``), BEAT/Mixamo-style BVH (``LeftHand``,
    ``mixamorig:RightHand``) and short forms (``LWrist``), ignoring case,
    separators and namespace prefixes; ``LeftHandThumb1`` does not match.

    Raises
    ------
    ParameterError
        When either wrist is missing.
    """
    keys = [n.rsplit(":", 1)[-1].lower().replace("_", "").replace("-", "").replace(" ", "") for n in names]
    found = []
    for side in ("left", "right"):
        hit = [i for i, k in enumerate(keys) if k in _WRIST_KEYS[side]]
        if not hit:
            raise ParameterError(
                f"names: expected a {side} wrist joint (e.g. '{side}_wrist' or '{side.capitalize()}Hand'); "
                f"got none among {len(names)} joints"
            )
        found.append(hit[0])
    return found[0], found[1]


def _motion_metrics(pos, *, fps, joints, beat_joints, abeats, sigma_s, boundaries, diversity_window_s):
    out: dict[str, Any] = {
        "n_frames": int(pos.shape[0]),
        "duration_s": pos.shape[0] / fps,
        "average_acceleration_m_s2": average_acceleration(pos, fps=fps, joints=joints),
        "average_jerk_m_s3": average_jerk(pos, fps=fps, joints=joints),
    }
    w = max(1, int(round(diversity_window_s * fps)))
    out["l1_diversity_m"] = (
        l1_diversity(pos, fps=fps, window_s=diversity_window_s, joints=joints)
        if pos.shape[0] >= 2 * w
        else float("nan")
    )
    if abeats is not None:
        out["beat_align"] = beat_align(pos, fps=fps, joints=beat_joints, audio_beats_s=abeats, sigma_s=sigma_s)
        out["beat_align_audio_to_motion"] = beat_align(
            pos, fps=fps, joints=beat_joints, audio_beats_s=abeats, sigma_s=sigma_s, direction="audio_to_motion"
        )
    if boundaries is not None:
        b = np.asarray(boundaries)
        b = b[(b >= 1) & (b <= pos.shape[0] - 1)]
        out["seam"] = (
            seam_jerk(pos, fps=fps, boundaries=b, joints=joints) if b.size else None
        )
    return out


def motion_report(
    positions,
    *,
    fps,
    audio=None,
    sr=None,
    ground_truth=None,
    boundaries=None,
    joints=None,
    beat_joints=None,
    names=None,
    audio_beats_s=None,
    beat_sigma_s=0.3,
    bin_width_m_s=0.01,
    max_speed_m_s=2.0,
    diversity_window_s=DEFAULT_DIVERSITY_WINDOW_S,
):
    """Every metric for a generated motion, and for the ground truth by the same code.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        Generated motion.
    fps : float
        Frame rate of both motions.
    audio : ndarray [shape=(n_samples,)], optional
        Mono speech that drives the motion (needs ``sr``); enables BeatAlign.
    sr : int, optional
    ground_truth : ndarray [shape=(F', J, 3)], optional
        Recorded motion for the same speech, same joints.
    boundaries : sequence of int, optional
        Frames where the synthesis switched database windows; enables the seam
        jerk. The ground truth is measured at the same frames as a control
        (it has no seams, so its ratio shows what "no seam" looks like).
    joints : sequence of int, optional
        Joints for jerk, acceleration, histograms, diversity and seams
        (e.g. arms and hands; default all).
    beat_joints : sequence of int, optional
        Joints whose speed minima are motion beats. Default: the wrists found
        in ``names``, else SMPL-X's (20, 21) when J == 55.
    names : list of str, optional
        Joint names, used to find the wrists.
    audio_beats_s : array_like, optional
        Audio beat times in seconds (e.g. word onsets); overrides onsets
        detected in ``audio``.
    beat_sigma_s : float
        BeatAlign tolerance in seconds (BEAT: 0.3).
    bin_width_m_s, max_speed_m_s
        Speed histogram bins (see :func:`speed_histogram`).
    diversity_window_s : float
        L1 diversity window (see :func:`l1_diversity`).

    Returns
    -------
    dict
        ``{"settings": {...}, "generated": {...}, "ground_truth": {...} or None,
        "comparison": {"speed_hellinger": float} or None}``; metric keys carry
        their units (``average_jerk_m_s3`` ...). BeatAlign is NaN when no motion
        beat was found; diversity is NaN when the motion is shorter than two windows.
    """
    fps = _fps(fps)
    gen = _positions(positions)
    n_joints = gen.shape[1]
    jidx = _joint_index(joints, n_joints)
    gt = None
    if ground_truth is not None:
        gt = _positions(ground_truth, "ground_truth")
        if gt.shape[1] != n_joints:
            raise ParameterError(
                f"ground_truth: expected {n_joints} joints like the generated motion; got {gt.shape[1]}"
            )

    abeats = None
    bjoints = None
    if audio_beats_s is not None or audio is not None:
        if audio_beats_s is not None:
            abeats = np.asarray(audio_beats_s, dtype=np.float64).ravel()
        else:
            abeats = audio_beats(audio, sr=sr)
        if beat_joints is not None:
            bjoints = _joint_index(beat_joints, n_joints, "beat_joints")
        elif names is not None:
            if len(names) != n_joints:
                raise ParameterError(f"names: expected {n_joints} joint names; got {len(names)}")
            bjoints = np.asarray(find_wrists(names))
        elif n_joints == 55:
            bjoints = np.asarray(SMPLX_WRISTS)
        else:
            raise ParameterError(
                f"beat_joints: BeatAlign needs the wrist joints; pass beat_joints or names for a "
                f"{n_joints}-joint skeleton"
            )

    kw = dict(
        fps=fps,
        joints=jidx,
        beat_joints=bjoints,
        abeats=abeats,
        sigma_s=float(beat_sigma_s),
        boundaries=boundaries,
        diversity_window_s=diversity_window_s,
    )
    report: dict[str, Any] = {
        "settings": {
            "fps": fps,
            "joints": jidx.tolist(),
            "beat_joints": None if bjoints is None else bjoints.tolist(),
            "n_audio_beats": None if abeats is None else int(abeats.size),
            "audio_beats_source": None
            if abeats is None
            else ("given" if audio_beats_s is not None else "librosa onsets"),
            "beat_sigma_s": float(beat_sigma_s),
            "beat_order_s": _BEAT_ORDER_S,
            "beat_min_speed_ratio": _BEAT_MIN_SPEED_RATIO,
            "speed_bin_width_m_s": float(bin_width_m_s),
            "max_speed_m_s": float(max_speed_m_s),
            "diversity_window_s": float(diversity_window_s),
            "n_boundaries": None if boundaries is None else int(np.asarray(boundaries).size),
        },
        "generated": _motion_metrics(gen, **kw),
        "ground_truth": None,
        "comparison": None,
    }
    if gt is not None:
        report["ground_truth"] = _motion_metrics(gt, **kw)
        report["comparison"] = {
            "speed_hellinger": speed_hellinger(
                gen, gt, fps=fps, joints=jidx, bin_width_m_s=bin_width_m_s, max_speed_m_s=max_speed_m_s
            )
        }
    return report
