"""Speech audio: any WAV (or other libsndfile format) to mono float32 at the analysis rate.

soundfile reads what Python's ``wave`` cannot, notably 32-bit float WAV (format
tag 3, as in BEAT2) and 24-bit PCM; channels are averaged to mono and soxr
(high quality) resamples to the requested rate.
"""
from __future__ import annotations

import os

import numpy as np
import soundfile as sf
import soxr

from gesturedb.errors import InputFileError, ParameterError

__all__ = ["read_audio", "audio_duration", "MAX_AUDIO_PEAK"]

_SLICE = 1 << 18  # samples checked and mixed down at a time

#: largest |sample| accepted. Full scale is 1; float WAVs may overshoot a little, but a peak
#: far outside [-1, 1] (1e30) makes the MFCC statistics of the whole database overflow to NaN
MAX_AUDIO_PEAK = 16.0


def audio_duration(path) -> float:
    """Duration of an audio file in seconds, from its header (no samples decoded).

    The build's automatic gap needs every recording's length before any is processed: on
    the client, one after another, where decoding took 9 ms of a 63 s recording. The samples
    themselves are checked when the recording is read (:func:`read_audio`).

    Raises
    ------
    InputFileError
        Missing file, or a header libsndfile cannot read.
    """
    info = _libsndfile(path, sf.info)
    return float(info.frames) / float(info.samplerate)


def _libsndfile(path, call):
    """``call(path)`` (a soundfile function), a missing file or libsndfile's failure turned into
    the one-line InputFileError both readers give."""
    if not os.path.isfile(path):
        raise InputFileError(path, "no such file")
    try:
        return call(os.fspath(path))
    except (sf.LibsndfileError, RuntimeError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"cannot read as audio: {exc}") from None


def read_audio(path, *, sr: int | None = 16000) -> tuple[np.ndarray, int]:
    """Read speech as mono float32 samples.

    Parameters
    ----------
    path : str or os.PathLike
        WAV (PCM 16/24/32-bit, 32/64-bit float) or any format libsndfile reads.
    sr : int or None
        Output sample rate in Hz (a whole-number float such as 16000.0 is
        accepted); ``None`` keeps the file's rate.

    Returns
    -------
    samples : ndarray [shape=(n,)], float32
        Mono (the mean of the channels), full scale +-1 for PCM.
    sr : int
        Sample rate of ``samples``, Hz.

    Raises
    ------
    InputFileError
        Missing or unreadable file, no samples, or non-finite samples (the
        message gives the first bad sample and its time). Silence is fine.
    ParameterError
        If ``sr`` is not a positive integer.
    """
    if sr is not None:
        integral = isinstance(sr, (int, np.integer)) or \
            (isinstance(sr, (float, np.floating)) and float(sr).is_integer())
        if isinstance(sr, bool) or not integral or sr <= 0:
            raise ParameterError(f"sr: expected a positive integer sample rate in Hz or None; got {sr!r}")
        sr = int(sr)
    data, sr_file = _libsndfile(path, lambda p: sf.read(p, dtype="float32", always_2d=True))
    if data.shape[0] == 0:
        raise InputFileError(path, f"no audio samples (0 frames, {data.shape[1]} channel(s) at {sr_file} Hz)")
    # checked and mixed down in slices: whole-file temporaries (a NaN mask, |x|, the channel mean)
    # were 2-3 times the samples, 1 GB more for 2 hours of speech
    n_ch = data.shape[1]
    mono = data[:, 0] if n_ch == 1 else np.empty(data.shape[0], dtype=np.float32)
    peak, at = -1.0, None
    for a in range(0, data.shape[0], _SLICE):
        part = data[a:a + _SLICE]
        bad = ~np.isfinite(part)
        if bad.any():
            i, c = (int(v) for v in np.argwhere(bad)[0])
            i += a
            raise InputFileError(path, f"sample {i} (t = {i / sr_file:.3f} s, channel {c}) is not finite: "
                                       f"{data[i, c]}")
        mag = np.abs(part)
        k = int(mag.argmax())
        if float(mag.flat[k]) > peak:
            peak, at = float(mag.flat[k]), (a + k // n_ch, k % n_ch)
        if n_ch > 1:
            mono[a:a + _SLICE] = part.mean(axis=1, dtype=np.float32)
    if peak > MAX_AUDIO_PEAK:
        i, c = at
        raise InputFileError(path, f"peak {peak:.6g} at sample {i} (t = {i / sr_file:.3f} s, channel {c}): expected "
                                   f"samples within +-{MAX_AUDIO_PEAK:g} (full scale is +-1); not speech audio")
    del data  # a multi-channel file's samples are no longer needed once mixed down
    if sr is None or sr == sr_file:
        return np.ascontiguousarray(mono, dtype=np.float32), int(sr_file)
    out = soxr.resample(mono, sr_file, sr, quality="HQ")
    return np.ascontiguousarray(out, dtype=np.float32), sr
