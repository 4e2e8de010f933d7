"""Audio features for the motion-matching search (Habibie et al. 2022, Sec. 3.1).

13 MFCCs and the log mean energy, computed on short analysis frames (25 ms
window, 10 ms hop) and averaged over every motion frame, so that database and
query features come from the same extractor at the motion frame rate.

Time alignment: motion frame ``i`` covers the interval ``[i / fps, (i + 1) /
fps)`` of the audio. An analysis frame belongs to the motion frame that contains
its centre. :func:`n_frames_for_duration` uses the same convention.
"""
from __future__ import annotations

import math

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.features.body import check_fps

__all__ = [
    "AUDIO_HOP_S",
    "AUDIO_WINDOW_S",
    "N_MELS",
    "MAX_PAD_S",
    "audio_features",
    "audio_deltas",
    "n_frames_for_duration",
]

#: Hop between analysis frames, seconds.
AUDIO_HOP_S: float = 0.010
#: Length of an analysis frame, seconds.
AUDIO_WINDOW_S: float = 0.025
#: Number of mel bands the MFCCs are computed from.
N_MELS: int = 40
#: Upper edge of the mel filter bank (Hz), capped at the Nyquist frequency. Fixed
#: rather than sr / 2 so that the same speech at 16 kHz and at 48 kHz gives
#: comparable features.
FMAX_HZ: float = 8000.0
#: Lower edge of the mel filter bank (Hz).
FMIN_HZ: float = 20.0
#: Default limit on how much shorter than the motion the audio may be.
MAX_PAD_S: float = 1.0

# Energy floor (mean squared amplitude) and power floor of the mel spectrogram:
# silence gets a finite feature (log(1e-10) = -23.0) instead of -inf.
_FLOOR = 1e-10

# log(2) split so that e * _LN2_HI is exact for |e| < 2^11 (the low 11 bits of its mantissa are 0)
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
# 2 atanh(s) = 2 (s + s^3/3 + s^5/5 + ...): terms up to s^25 reach 2^-53 for |s| <= 0.1716
_ATANH = tuple(1.0 / (2 * k + 1) for k in range(1, 13))
_LOG_CHUNK = 8192  # values per pass of _log


def _log(x: np.ndarray) -> np.ndarray:
    """Natural logarithm of positive finite float64 values, within about 2 ulp, the same bits on
    every machine.

    numpy's ``log`` and ``log10`` pick an implementation by CPU (its AVX-512 ones round
    differently from its AVX2 ones), so a recording's audio features depended on the machine
    that built them: between the two, 80 % of BEAT2's audio feature values differed, by up to
    3e-6, and a Dask build on a cluster mixing them depended on which worker took which
    recording. This uses only ``frexp`` (exact) and IEEE additions, multiplications and one
    division, which every machine rounds alike.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size > _LOG_CHUNK:
        # a chunk's thirty temporaries stay in the cache and are reused; over a whole mel
        # spectrogram each would be fresh memory to fault in (3.5x slower)
        flat = x.reshape(-1)
        out = np.empty_like(flat)
        for i in range(0, flat.size, _LOG_CHUNK):
            out[i:i + _LOG_CHUNK] = _log(flat[i:i + _LOG_CHUNK])
        return out.reshape(x.shape)
    m, e = np.frexp(x)  # x = m 2^e, m in [0.5, 1)
    low = m < 0.7071067811865476
    m = np.where(low, m * 2.0, m)  # now in [sqrt(1/2), sqrt(2)); exact
    e = (e - low).astype(np.float64)
    s = (m - 1.0) / (m + 1.0)  # m - 1 is exact (Sterbenz)
    z = s * s
    p = np.full_like(z, _ATANH[-1])
    for c in _ATANH[-2::-1]:
        p = p * z + c
    return e * _LN2_HI + ((2.0 * s) * (z * p) + (e * _LN2_LO + 2.0 * s))


def n_frames_for_duration(duration_s: float, fps: float) -> int:
    """Number of motion frames that spans a duration.

    Parameters
    ----------
    duration_s : float >= 0
        Duration, seconds (e.g. ``len(samples) / sr`` of a query's audio).
    fps : float > 0
        Motion frame rate, frames per second.

    Returns
    -------
    int
        ``round(duration_s * fps)`` (halves round up): the frame count whose span
        ``n / fps`` is closest to the duration, so synthesized motion is as long
        as the audio to within half a frame. :func:`audio_features` pads the at
        most half a frame of missing audio with silence.
    """
    fps = check_fps(fps)
    try:
        d = float(duration_s)
    except (TypeError, ValueError):
        raise ParameterError(f"duration_s: expected a duration >= 0 in seconds; got {duration_s!r}") from None
    if not (math.isfinite(d) and d >= 0):
        raise ParameterError(f"duration_s: expected a duration >= 0 in seconds; got {duration_s!r}")
    # The small slack absorbs float error in products such as 2.0 s * 29.97 fps.
    return int(math.floor(d * fps + 0.5 + 1e-9))


def audio_features(
    samples: np.ndarray,
    sr: int,
    *,
    fps: float,
    n_frames: int,
    n_mfcc: int = 13,
    max_pad_s: float = MAX_PAD_S,
) -> np.ndarray:
    """MFCCs and log mean energy per motion frame.

    Parameters
    ----------
    samples : ndarray [shape=(n_samples,)], float, amplitude in [-1, 1]
        Mono speech (see :mod:`gesturedb.io.audio` to read and mix down any WAV).
    sr : int > 0
        Sample rate, Hz.
    fps : float > 0, keyword-only
        Motion frame rate, frames per second.
    n_frames : int >= 0, keyword-only
        Number of motion frames to produce. Audio beyond ``n_frames / fps``
        seconds is ignored; audio shorter than that is padded with silence.
    n_mfcc : int in [1, 40], keyword-only
        Number of MFCCs.
    max_pad_s : float >= 0, keyword-only
        Largest shortfall of the audio (seconds) that is padded with silence; a
        larger one is almost certainly a wrong audio/motion pairing and raises.

    Returns
    -------
    ndarray [shape=(n_frames, n_mfcc + 1)], float32
        Columns ``0 .. n_mfcc-1``: MFCCs (DCT-II, orthonormal, of the log mel
        power in dB over :data:`N_MELS` Slaney mel bands from 20 Hz to
        ``min(8000, sr/2)`` Hz). Column ``n_mfcc``: natural log of the mean squared
        amplitude over the 25 ms window (floored at 1e-10). Each row is the mean
        of the analysis frames (25 ms Hann window, 10 ms hop, frame ``j`` centred
        at ``j * hop`` seconds) whose centre lies in ``[i / fps, (i + 1) / fps)``;
        when fps exceeds 100 some motion frames contain no centre and take the
        analysis frame nearest to their middle.

    Raises
    ------
    ParameterError
        Bad shapes or values, or audio shorter than ``n_frames / fps`` by
        ``max_pad_s`` seconds or more.

    Notes
    -----
    The log mel power has no ``top_db`` clipping: clipping relative to the loudest
    frame would make every feature depend on the whole file, so a query and the
    database recording of the same speech would differ. Every feature here
    depends only on audio within 12.5 ms of its analysis frames.
    """
    import librosa  # heavy import, only needed here

    y = np.asarray(samples)
    if y.ndim != 1:
        raise ParameterError(
            f"samples: expected mono audio of shape (n_samples,); got shape {y.shape} "
            "(mix down with gesturedb.io.audio)"
        )
    if not np.issubdtype(y.dtype, np.floating):
        raise ParameterError(f"samples: expected float amplitudes in [-1, 1]; got dtype {y.dtype}")
    if isinstance(sr, (bool, np.bool_)) or not isinstance(sr, (int, np.integer)) or sr <= 0:
        raise ParameterError(f"sr: expected a positive int sample rate in Hz; got {sr!r}")
    sr = int(sr)
    fps = check_fps(fps)
    if isinstance(n_frames, (bool, np.bool_)) or not isinstance(n_frames, (int, np.integer)) or n_frames < 0:
        raise ParameterError(f"n_frames: expected an int >= 0; got {n_frames!r}")
    n_frames = int(n_frames)
    if isinstance(n_mfcc, (bool, np.bool_)) or not isinstance(n_mfcc, (int, np.integer)) or not 1 <= n_mfcc <= N_MELS:
        raise ParameterError(f"n_mfcc: expected an int in [1, {N_MELS}]; got {n_mfcc!r}")
    n_mfcc = int(n_mfcc)
    try:
        max_pad_s = float(max_pad_s)
    except (TypeError, ValueError):
        raise ParameterError(f"max_pad_s: expected seconds >= 0; got {max_pad_s!r}") from None
    if not (math.isfinite(max_pad_s) and max_pad_s >= 0):
        raise ParameterError(f"max_pad_s: expected seconds >= 0; got {max_pad_s!r}")
    if not np.isfinite(y).all():
        raise ParameterError(f"samples: expected finite values; got NaN/inf at sample {int(np.flatnonzero(~np.isfinite(y))[0])}")

    n_out = n_mfcc + 1
    if n_frames == 0:
        return np.zeros((0, n_out), dtype=np.float32)

    need_s = n_frames / fps
    have_s = len(y) / sr
    if need_s - have_s >= max_pad_s:
        raise ParameterError(
            f"samples: audio lasts {have_s:.3f} s but n_frames={n_frames} at {fps:g} fps needs "
            f"{need_s:.3f} s; only shortfalls under max_pad_s={max_pad_s:g} s are padded with silence"
        )

    hop = max(1, int(round(AUDIO_HOP_S * sr)))
    win = max(1, int(round(AUDIO_WINDOW_S * sr)))
    n_fft = 1 << (win - 1).bit_length()
    # Analysis frames whose centre lies before need_s; keep real audio (or
    # silence padding) under the last window's right half as well.
    n_fine = int(math.ceil(need_s * sr / hop - 1e-9))
    n_fine = max(n_fine, 1)
    n_samples = (n_fine - 1) * hop + 1
    total = n_samples + n_fft // 2
    y = y.astype(np.float32, copy=False)
    if len(y) >= total:
        y = y[:total]
    else:
        y = np.concatenate([y, np.zeros(total - len(y), dtype=np.float32)])

    fmax = min(FMAX_HZ, sr / 2.0)
    fmin = min(FMIN_HZ, fmax / 2.0)
    spec = librosa.stft(y, n_fft=n_fft, hop_length=hop, win_length=win, window="hann", center=True,
                        pad_mode="constant")
    # |z|^2 as re^2 + im^2: numpy's abs of a complex number (a hypot) rounds differently with
    # and without AVX2, elementwise products and sums do not
    power = spec.real * spec.real + spec.imag * spec.imag
    basis = librosa.filters.mel(sr=sr, n_fft=n_fft, n_mels=N_MELS, fmin=fmin, fmax=fmax)
    # librosa.feature.melspectrogram, but the projection without BLAS (optimize=False: numpy's own
    # loop): OpenBLAS rounds it differently with other thread counts, and BLAS thread limits are
    # per process while builds run recordings in threads (Dask) or processes; a database must not
    # depend on how it was built (a 1-worker and a 2-worker build differed by 3e-5 here)
    mel = np.einsum("mf,ft->mt", basis, power, optimize=False)
    # librosa.power_to_db(mel, ref=1.0, amin=_FLOOR, top_db=None), with a logarithm that does not
    # depend on the CPU (see _log), rounded to float32 once
    log_mel = (_log(np.maximum(mel, _FLOOR)) * (10.0 / math.log(10.0))).astype(np.float32)
    mfcc = librosa.feature.mfcc(S=log_mel, n_mfcc=n_mfcc, dct_type=2, norm="ortho")  # (n_mfcc, n_fine')

    # Rectangular 25 ms energy centred at each analysis frame, on the same
    # zero padding librosa applies with center=True.
    padded = np.pad(y.astype(np.float64), (n_fft // 2, n_fft // 2))
    starts = np.arange(mfcc.shape[1], dtype=np.int64) * hop + (n_fft - win) // 2
    csum = np.concatenate([[0.0], np.cumsum(padded * padded)])
    energy = (csum[starts + win] - csum[starts]) / win
    log_energy = _log(np.maximum(energy, _FLOOR))

    fine = np.concatenate([mfcc.T.astype(np.float64), log_energy[:, None]], axis=1)[:n_fine]
    centres_s = np.arange(len(fine), dtype=np.float64) * hop / sr
    owner = np.floor(centres_s * fps + 1e-9).astype(np.int64)
    keep = owner < n_frames
    fine, owner = fine[keep], owner[keep]

    counts = np.bincount(owner, minlength=n_frames).astype(np.float64)
    sums = np.zeros((n_frames, n_out))
    for c in range(n_out):
        sums[:, c] = np.bincount(owner, weights=fine[:, c], minlength=n_frames)
    out = np.empty((n_frames, n_out))
    has = counts > 0
    out[has] = sums[has] / counts[has, None]
    if not has.all():
        empty = np.flatnonzero(~has)
        mid_s = (empty + 0.5) / fps
        nearest = np.clip(np.rint(mid_s * sr / hop).astype(np.int64), 0, len(centres_s) - 1)
        out[empty] = np.concatenate([mfcc.T, log_energy[:, None]], axis=1)[nearest]
    return np.ascontiguousarray(out, dtype=np.float32)


def audio_deltas(features: np.ndarray) -> np.ndarray:
    """First time derivative of per-frame audio features.

    Parameters
    ----------
    features : ndarray [shape=(n_frames, D)]
        Output of :func:`audio_features`.

    Returns
    -------
    ndarray [shape=(n_frames, D)], float32
        ``numpy.gradient`` along frames: central differences ``(x[i+1] - x[i-1]) /
        2`` inside, one-sided differences at the first and last frame, zeros for a
        single frame. Units: feature units per motion frame. Unlike a
        Savitzky-Golay delta it works for any length, so a short query gets the
        same deltas as the same frames inside a database recording (except at
        its ends).
    """
    x = np.asarray(features)
    if x.ndim != 2:
        raise ParameterError(f"features: expected shape (n_frames, D); got {x.shape}")
    x = x.astype(np.float64)
    if len(x) < 2:
        return np.zeros(x.shape, dtype=np.float32)
    return np.ascontiguousarray(np.gradient(x, axis=0), dtype=np.float32)
