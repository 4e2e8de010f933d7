"""Rhythm signatures (GestureMaster, Zhou et al. 2022, Sec. 3.2).

A clip's rhythm signature is a 32-bit pattern over 32 evenly spaced bins of the
clip: for speech a bit is set when a word starts in the bin, for motion when the
hand speed has a local minimum there (a pause, sharp turn or stroke end). Speech
and motion clips are compared by the Hamming distance of their signatures.

Bit order: bin 0 (the start of the clip) is the least significant bit, so bit
``i`` is ``(signature >> i) & 1``. Signatures are ``numpy.uint32``; with
``bits < 32`` only the low ``bits`` bits are used.
"""
from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.features.body import (
    BODY_ROLES,
    SPEED_SMOOTH_S,
    body_frame,
    check_fps,
    check_joints,
    check_positions,
    point_speeds,
    to_body_frame,
)
from gesturedb.roles import WRIST_ROLES

__all__ = [
    "MINIMUM_PROMINENCE",
    "MINIMUM_WINDOW_S",
    "audio_rhythm",
    "hand_speed",
    "speed_minima",
    "motion_rhythm",
    "hamming",
    "hamming_beyond_chance",
]

#: Default prominence (m/s) a speed minimum needs to count as a beat: the speed
#: must rise at least this much on both sides before it falls below the minimum
#: again. Marker and solver noise makes wiggles of a few mm/s even after smoothing;
#: real pauses and turns of a gesturing hand dip by tenths of a m/s.
MINIMUM_PROMINENCE: float = 0.05
#: Default width (seconds) of the window in which the prominence is measured, so a
#: short pause inside a long slow stretch still counts.
MINIMUM_WINDOW_S: float = 1.0


def _check_bits(bits) -> int:
    if isinstance(bits, (bool, np.bool_)) or not isinstance(bits, (int, np.integer)) or not 1 <= bits <= 32:
        raise ParameterError(f"bits: expected an int in [1, 32]; got {bits!r}")
    return int(bits)


def _or_reduce(n_clips: int, clip_of: np.ndarray, bin_of: np.ndarray) -> np.ndarray:
    sig = np.zeros(n_clips, dtype=np.uint32)
    np.bitwise_or.at(sig, clip_of, np.left_shift(np.uint32(1), bin_of.astype(np.uint32)))
    return sig


def _pairs(sorted_events: np.ndarray, lo_val: np.ndarray, hi_val: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(clip, event index) for every event with lo_val[c] <= event < hi_val[c]."""
    lo = np.searchsorted(sorted_events, lo_val, side="left")
    hi = np.searchsorted(sorted_events, hi_val, side="left")
    counts = np.maximum(hi - lo, 0)
    clip_of = np.repeat(np.arange(len(lo), dtype=np.int64), counts)
    offset = np.arange(counts.sum(), dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
    return clip_of, lo[clip_of] + offset


def audio_rhythm(word_onsets_s, *, start_s, end_s, bits: int = 32):
    """Rhythm signature of speech: which bins of a clip contain a word onset.

    Parameters
    ----------
    word_onsets_s : ndarray [shape=(W,)], seconds
        Start time of every word (any order); onsets outside the clip are ignored.
    start_s, end_s : float or ndarray [shape=(C,)], seconds, keyword-only
        Clip span ``[start_s, end_s)``, ``end_s > start_s``. Arrays give one
        signature per clip.
    bits : int in [1, 32], keyword-only
        Number of bins.

    Returns
    -------
    numpy.uint32 or ndarray [shape=(C,)], uint32
        Bit ``i`` (bin 0 = least significant bit) is set iff an onset ``t``
        satisfies ``floor((t - start_s) / (end_s - start_s) * bits) == i``. An
        onset within 1e-9 bin widths below a bin edge counts in the later bin,
        so that onsets placed exactly on an edge in frame units (``m / fps``)
        give the same bit as :func:`motion_rhythm` computes exactly in integers.
    """
    bits = _check_bits(bits)
    onsets = np.asarray(word_onsets_s, dtype=np.float64)
    if onsets.ndim != 1:
        raise ParameterError(f"word_onsets_s: expected a 1-D array of seconds; got shape {onsets.shape}")
    if not np.isfinite(onsets).all():
        raise ParameterError("word_onsets_s: expected finite times in seconds; got NaN/inf")
    s = np.asarray(start_s, dtype=np.float64)
    e = np.asarray(end_s, dtype=np.float64)
    scalar = s.ndim == 0 and e.ndim == 0
    s, e = np.broadcast_arrays(np.atleast_1d(s), np.atleast_1d(e))
    if s.ndim != 1:
        raise ParameterError(f"start_s, end_s: expected scalars or 1-D arrays; got shapes {s.shape}")
    ok = np.isfinite(s) & np.isfinite(e) & (e > s)
    if not ok.all():
        bad = int(np.flatnonzero(~ok)[0])
        raise ParameterError(
            f"start_s, end_s: expected finite clip spans with end_s > start_s; "
            f"got clip {bad}: {float(s[bad])} s to {float(e[bad])} s"
        )
    onsets = np.sort(onsets)
    clip_of, ev = _pairs(onsets, s, e)
    pos = (onsets[ev] - s[clip_of]) / (e[clip_of] - s[clip_of]) * bits
    bin_of = np.clip(np.floor(pos + 1e-9), 0, bits - 1).astype(np.int64)
    sig = _or_reduce(len(s), clip_of, bin_of)
    return sig[0] if scalar else sig


def hand_speed(
    positions: np.ndarray,
    *,
    joints: Mapping[str, int],
    fps: float,
    smooth_s: float = SPEED_SMOOTH_S,
) -> np.ndarray:
    """Speed of the faster wrist in every frame of one recording.

    Parameters
    ----------
    positions : ndarray [shape=(F, J, 3)], metres
        World joint positions of one recording (speeds are never taken across
        recordings: call once per recording).
    joints : mapping of str to int, keyword-only
        Roles ``left_wrist``, ``right_wrist`` and the body-frame roles.
    fps : float > 0, keyword-only
        Frames per second.
    smooth_s : float >= 0, keyword-only
        Gaussian sigma on positions before differentiating, seconds; see
        :func:`gesturedb.features.body.point_speeds`.

    Returns
    -------
    ndarray [shape=(F,)], float64, metres per second
        ``max(|v_left_wrist|, |v_right_wrist|)`` with velocities of the wrist
        positions in the body frame (so walking or turning does not count as
        gesturing).
    """
    positions = check_positions(positions)
    idx = check_joints(joints, WRIST_ROLES + BODY_ROLES, n_joints=positions.shape[1])
    origin, rotation = body_frame(positions, joints=idx, fps=fps)
    wrists = to_body_frame(positions[:, [idx[r] for r in WRIST_ROLES]], origin, rotation)
    return point_speeds(wrists, fps=fps, smooth_s=smooth_s).max(axis=1)


def speed_minima(
    speed: np.ndarray,
    *,
    fps: float,
    prominence: float = MINIMUM_PROMINENCE,
    window_s: float = MINIMUM_WINDOW_S,
) -> np.ndarray:
    """Frames where the speed curve has a prominent local minimum.

    Parameters
    ----------
    speed : ndarray [shape=(F,)], metres per second
        Speed curve of one recording, e.g. :func:`hand_speed`.
    fps : float > 0, keyword-only
        Frames per second.
    prominence : float >= 0, keyword-only
        Minimum topographic prominence of the dip, m/s: from the minimum, the
        speed must rise by at least this much on each side before it drops below
        the minimum's value again (or the window or the recording ends); the
        smaller of the two rises is the prominence. 0 accepts every strict local
        minimum.
    window_s : float > 0, keyword-only
        The rises are searched within ``window_s / 2`` on each side.

    Returns
    -------
    ndarray [shape=(M,)], int64, frames, ascending
        Interior frames only (the first and last frame are never minima); on a
        flat bottom the middle frame.
    """
    from scipy.signal import find_peaks  # scipy ships with librosa

    fps = check_fps(fps)
    x = np.asarray(speed, dtype=np.float64)
    if x.ndim != 1:
        raise ParameterError(f"speed: expected shape (F,) in m/s; got {x.shape}")
    if not np.isfinite(x).all():
        raise ParameterError("speed: expected finite values; got NaN/inf")
    try:
        prom = float(prominence)
        win = float(window_s)
    except (TypeError, ValueError):
        raise ParameterError(f"prominence, window_s: expected numbers; got {prominence!r}, {window_s!r}") from None
    if not (math.isfinite(prom) and prom >= 0):
        raise ParameterError(f"prominence: expected m/s >= 0; got {prominence!r}")
    if not (math.isfinite(win) and win > 0):
        raise ParameterError(f"window_s: expected seconds > 0; got {window_s!r}")
    if len(x) < 3:
        return np.zeros(0, dtype=np.int64)
    wlen = max(3, 2 * int(round(win * fps / 2.0)) + 1)
    # Prominence 0 still has to be passed so that scipy evaluates it; a dip with
    # exactly zero prominence is impossible for a strict minimum.
    peaks, _ = find_peaks(-x, prominence=prom if prom > 0 else 1e-300, wlen=wlen)
    return peaks.astype(np.int64)


def motion_rhythm(
    speed: np.ndarray,
    *,
    start,
    length,
    fps: float,
    bits: int = 32,
    prominence: float = MINIMUM_PROMINENCE,
    window_s: float = MINIMUM_WINDOW_S,
):
    """Rhythm signature of motion: which bins of a clip contain a speed minimum.

    Parameters
    ----------
    speed : ndarray [shape=(F,)], metres per second
        Speed curve of the whole recording (:func:`hand_speed`); minima are found
        on the whole curve so a minimum right at a clip edge is still seen.
    start, length : int or ndarray [shape=(C,)], frames, keyword-only
        Clip ``[start, start + length)`` within the recording, ``length >= 1``.
        Arrays give one signature per clip.
    fps : float > 0, keyword-only
        Frames per second.
    bits : int in [1, 32], keyword-only
        Number of bins.
    prominence, window_s : float, keyword-only
        See :func:`speed_minima`.

    Returns
    -------
    numpy.uint32 or ndarray [shape=(C,)], uint32
        Bit ``i`` (bin 0 = least significant bit) is set iff a minimum frame
        ``m`` of the clip has ``(m - start) * bits // length == i``. This is the
        bin of the time ``m / fps`` in the clip span ``[start / fps, (start +
        length) / fps)``, as in :func:`audio_rhythm`.
    """
    bits = _check_bits(bits)
    x = np.asarray(speed, dtype=np.float64)
    if x.ndim != 1:
        raise ParameterError(f"speed: expected shape (F,) in m/s; got {x.shape}")
    st = np.asarray(start)
    ln = np.asarray(length)
    scalar = st.ndim == 0 and ln.ndim == 0
    st, ln = np.broadcast_arrays(np.atleast_1d(st), np.atleast_1d(ln))
    if st.ndim != 1 or not (np.issubdtype(st.dtype, np.integer) and np.issubdtype(ln.dtype, np.integer)):
        raise ParameterError(
            f"start, length: expected ints or 1-D int arrays of frames; got {st.dtype} {st.shape}, {ln.dtype} {ln.shape}"
        )
    st = st.astype(np.int64)
    ln = ln.astype(np.int64)
    bad = (st < 0) | (ln < 1) | (st + ln > len(x))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ParameterError(
            f"start, length: expected clips with length >= 1 inside the {len(x)} frames of speed; "
            f"got clip {k}: start {st[k]}, length {ln[k]}"
        )
    minima = speed_minima(x, fps=fps, prominence=prominence, window_s=window_s)
    clip_of, ev = _pairs(minima, st, st + ln)
    bin_of = (minima[ev] - st[clip_of]) * bits // ln[clip_of]
    sig = _or_reduce(len(st), clip_of, bin_of)
    return sig[0] if scalar else sig


def _as_signatures(name: str, a) -> np.ndarray:
    arr = np.asarray(a)
    if arr.dtype == np.uint32:
        return arr
    if not np.issubdtype(arr.dtype, np.integer):
        raise ParameterError(f"{name}: expected uint32 signatures; got dtype {arr.dtype}")
    if arr.size and (arr.min() < 0 or arr.max() > 0xFFFFFFFF):
        raise ParameterError(
            f"{name}: expected signatures in [0, 2**32); got values in [{arr.min()}, {arr.max()}]"
        )
    return arr.astype(np.uint32)


def hamming(a, b) -> np.ndarray:
    """Number of differing bits between rhythm signatures.

    Parameters
    ----------
    a, b : int or array of uint32 (any integer dtype with values in [0, 2**32))
        Broadcast against each other, e.g. ``a[:, None]`` and ``b[None, :]`` for
        all pairs.

    Returns
    -------
    ndarray of the broadcast shape, int64
        Popcount of ``a ^ b``, 0 to 32 (0-d for scalars).
    """
    x = np.bitwise_xor(_as_signatures("a", a), _as_signatures("b", b))
    return _popcount32(x)


def hamming_beyond_chance(a, b, *, bits: int = 32) -> np.ndarray:
    """Hamming distance between rhythm signatures with the part their numbers of set bits explain taken out.

    ``H(a, b) - E[H | n_a, n_b] + E[H | n_a, n_a]``, where ``E[H | n_a, n_b] = n_a + n_b - 2 n_a n_b / bits``
    is the Hamming distance expected between signatures of ``n_a`` and ``n_b`` set bits placed at random.
    Why: the plain Hamming distance of a sparse speech signature (a 3 s clip sets about 8 of 32 bins)
    grows with every set bit of the other signature that misses, so among candidates that agree with the
    speech no better than chance it prefers those with the fewest bits: motion with few speed minima,
    the calm clips (on a 1.25x faster BEAT2 speaker the motion graph chose clips of 5.7 bits where the
    clips of fitting length had 8.6). This measure rewards only agreement beyond chance. It is the
    Hamming distance whenever ``n_b = n_a``, 0 iff ``a == b``, and never negative.

    Parameters
    ----------
    a, b : int or array of uint32
        Signatures of ``bits`` bins, broadcast against each other; ``a`` is the reference (the speech).
    bits : int in [1, 32], keyword-only
        Bins per signature.

    Returns
    -------
    ndarray of the broadcast shape, float64
    """
    bits = _check_bits(bits)
    a, b = _as_signatures("a", a), _as_signatures("b", b)
    na, nb = _popcount32(a).astype(np.float64), _popcount32(b).astype(np.float64)
    h = _popcount32(np.bitwise_xor(a, b)).astype(np.float64)
    # H - (na + nb - 2 na nb / bits) + (2 na - 2 na^2 / bits), grouped so that b = a gives 0 exactly
    return np.maximum(h + (na - nb) * (1.0 - 2.0 * na / bits), 0.0)


def _popcount32(x: np.ndarray) -> np.ndarray:
    if hasattr(np, "bitwise_count"):  # numpy >= 2.0
        return np.bitwise_count(x).astype(np.int64)
    # SWAR popcount for older numpy (setup.py allows numpy >= 1.24)
    x = np.asarray(x, dtype=np.uint32)
    x = x - ((x >> np.uint32(1)) & np.uint32(0x55555555))
    x = (x & np.uint32(0x33333333)) + ((x >> np.uint32(2)) & np.uint32(0x33333333))
    x = (x + (x >> np.uint32(4))) & np.uint32(0x0F0F0F0F)
    return ((x * np.uint32(0x01010101)) >> np.uint32(24)).astype(np.int64)
