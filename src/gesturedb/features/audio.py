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
from gesturedb.features.body import _check_nonnegative, check_fps

__all__ = [
    "AUDIO_HOP_S",
    "AudioFeatureStream",
    "FEATURE_BLOCK_FRAMES",
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
    if x.ndim == 0:  # frexp would give scalars, which the in-place steps below cannot write
        return _log(x.reshape(1))[0]
    if x.size > _LOG_CHUNK:
        # a chunk's thirty temporaries stay in the cache and are reused; over a whole mel
        # spectrogram each would be fresh memory to fault in (3.5x slower)
        flat = x.reshape(-1)
        out = np.empty_like(flat)
        for i in range(0, flat.size, _LOG_CHUNK):
            out[i:i + _LOG_CHUNK] = _log(flat[i:i + _LOG_CHUNK])
        return out.reshape(x.shape)
    # The same operations in the same order as the formula at the end, but in place: a live step's
    # 2,200 values spent a third of the time allocating temporaries (0.061 -> 0.041 ms)
    m, e = np.frexp(x)  # x = m 2^e, m in [0.5, 1)
    low = m < 0.7071067811865476
    np.multiply(m, 2.0, out=m, where=low)  # now in [sqrt(1/2), sqrt(2)); exact
    e = e.astype(np.float64)
    e -= low
    s = m - 1.0  # exact (Sterbenz)
    m += 1.0
    s /= m  # s = (m - 1) / (m + 1)
    z = s * s
    p = z * _ATANH[-1]  # Horner's scheme from p = _ATANH[-1]: p = p * z + c for the others
    p += _ATANH[-2]
    for c in _ATANH[-3::-1]:
        p *= z
        p += c
    z *= p
    s += s  # 2 s, exact
    z *= s
    p = e * _LN2_LO
    p += s
    z += p
    e *= _LN2_HI
    e += z
    return e  # e * _LN2_HI + ((2.0 * s) * (z * p) + (e * _LN2_LO + 2.0 * s))


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


def _check_int(name, value, lo, hi=None, what=None):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < lo \
            or (hi is not None and value > hi):
        raise ParameterError(f"{name}: expected {what}; got {value!r}")
    return int(value)


def _check_samples(y, first: int = 0) -> np.ndarray:
    """Mono float samples, finite; ``first`` is the index of ``y[0]`` in the whole speech (for messages)."""
    y = np.asarray(y)
    if y.ndim != 1:
        raise ParameterError(
            f"samples: expected mono audio of shape (n_samples,); got shape {y.shape} "
            "(mix down with gesturedb.io.audio)"
        )
    if not np.issubdtype(y.dtype, np.floating):
        raise ParameterError(f"samples: expected float amplitudes in [-1, 1]; got dtype {y.dtype}")
    # in slices: a whole-file isfinite mask is a byte per sample (115 MB for 2 h at 16 kHz)
    for a in range(0, len(y), _CHECK_SLICE):
        part = y[a:a + _CHECK_SLICE]
        if not np.isfinite(part).all():
            bad = a + int(np.flatnonzero(~np.isfinite(part))[0])
            raise ParameterError(f"samples: expected finite values; got NaN/inf at sample {first + bad}")
    return y


_CHECK_SLICE = 1 << 20
#: Analysis frames (10 ms each) computed per block: the STFT and mel temporaries of one block
#: take about 30 MB, whatever the length of the speech.
FEATURE_BLOCK_FRAMES: int = 2048


class AudioFeatureStream:
    """:func:`audio_features` computed block by block, as samples arrive.

    Memory is bounded by the block (:data:`FEATURE_BLOCK_FRAMES` analysis frames, about
    20 s of speech) instead of growing with the speech; the features are the same bits as
    :func:`audio_features` gives for the whole speech (which uses this class): every
    analysis frame depends only on the audio within 12.5 ms of its centre, and the only
    quantity carried from block to block, the running sum of squares behind the energy
    column, is carried exactly as the one-pass sum adds it.

    Parameters
    ----------
    sr : int > 0
        Sample rate of the samples pushed, Hz.
    fps : float > 0, keyword-only
        Motion frame rate, frames per second.
    n_mfcc : int in [1, 40], keyword-only
    n_frames : int >= 0 or None, keyword-only
        Motion frames wanted, when known in advance: samples beyond ``n_frames / fps``
        seconds are then ignored and the result equals ``audio_features(all samples,
        n_frames=n_frames)`` exactly. ``None`` (live speech): frames are returned as soon
        as their audio has arrived and :meth:`finish` decides the count.
    block_frames : int >= 1, keyword-only
        Analysis frames per block (tests use small ones; the results do not depend on it).

    Examples
    --------
    >>> stream = AudioFeatureStream(16000, fps=30)
    >>> rows = [stream.push(chunk) for chunk in chunks]   # (k, 14) float32 each, k >= 0
    >>> rows.append(stream.finish())                      # the last frames, silence-padded
    >>> features = np.concatenate(rows)
    """

    def __init__(self, sr: int, *, fps: float, n_mfcc: int = 13, n_frames: int | None = None,
                 block_frames: int = FEATURE_BLOCK_FRAMES):
        import librosa  # heavy import, only needed here

        self.sr = _check_int("sr", sr, 1, what="a positive int sample rate in Hz")
        self.fps = check_fps(fps)
        self.n_mfcc = _check_int("n_mfcc", n_mfcc, 1, N_MELS, what=f"an int in [1, {N_MELS}]")
        self.n_frames = None if n_frames is None else \
            _check_int("n_frames", n_frames, 0, what="an int >= 0 or None")
        self._block = _check_int("block_frames", block_frames, 1, what="an int >= 1")
        sr = self.sr
        self._hop = max(1, int(round(AUDIO_HOP_S * sr)))
        self._win = max(1, int(round(AUDIO_WINDOW_S * sr)))
        self._n_fft = 1 << (self._win - 1).bit_length()
        self._half = self._n_fft // 2
        fmax = min(FMAX_HZ, sr / 2.0)
        fmin = min(FMIN_HZ, fmax / 2.0)
        self._basis = librosa.filters.mel(sr=sr, n_fft=self._n_fft, n_mels=N_MELS, fmin=fmin, fmax=fmax)
        # librosa.stft's window, made once, 1-D: it multiplies rows of transposed frames (see _stft)
        self._fft_window = librosa.util.pad_center(librosa.filters.get_window("hann", self._win, fftbins=True),
                                                   size=self._n_fft)
        self._fft, self._max_mem_block = librosa.get_fftlib(), librosa.util.MAX_MEM_BLOCK
        # analysis frames kept: those whose centre lies before n_frames / fps
        self._n_fine = None if self.n_frames is None else self._fine_count(self.n_frames)
        # samples from absolute index _buf_at (negative: the zero padding before the speech, as
        # librosa's center=True puts it), and the sum of squares of all samples before them
        self._buf = np.zeros(self._half, dtype=np.float32)
        self._buf_at = -self._half
        self._csum = 0.0
        self._j = 0  # next analysis frame to compute
        self._rows = np.zeros((0, self.n_mfcc + 1))  # computed analysis frames from _rows_at on
        self._own = np.zeros(0, dtype=np.int64)  # the motion frame each of them belongs to
        self._rows_at = 0
        self._i = 0  # next motion frame to return
        self._pushed = 0
        self._finished = False

    # -- the analysis-frame <-> motion-frame map, the same float operations as one pass over the file
    def _fine_count(self, n_frames: int) -> int:
        need_s = n_frames / self.fps
        return max(int(math.ceil(need_s * self.sr / self._hop - 1e-9)), 1)

    def _owners(self, j0: int, j1: int) -> np.ndarray:
        centres_s = np.arange(j0, j1, dtype=np.float64) * self._hop / self.sr
        return np.floor(centres_s * self.fps + 1e-9).astype(np.int64)

    def _owner(self, j: int) -> int:
        """``_owners(j, j + 1)[0]`` in Python floats, the same IEEE operations in the same order, without
        numpy's overhead on one value (called at every emit)."""
        return math.floor(float(j) * self._hop / self.sr * self.fps + 1e-9)

    def _nearest(self, i0: int, i1: int) -> np.ndarray:
        """The analysis frame each of motion frames ``i0 .. i1 - 1`` takes if it has none of its own
        (fps above 100): the one nearest its middle."""
        mid_s = (np.arange(i0, i1, dtype=np.int64) + 0.5) / self.fps
        j = np.rint(mid_s * self.sr / self._hop).astype(np.int64)
        return np.clip(j, 0, None if self._n_fine is None else self._n_fine - 1)

    def _nearest_one(self, i: int) -> int:
        """``_nearest(i, i + 1)[0]`` in Python floats (``round`` rounds halves to even as ``np.rint``)."""
        j = max(round((i + 0.5) / self.fps * self.sr / self._hop), 0)
        return j if self._n_fine is None else min(j, self._n_fine - 1)

    # -- analysis frames
    def _compute(self, j1: int) -> None:
        """Analysis frames ``_j .. j1 - 1`` from the buffer, in blocks."""
        hop, n_fft, win, n_mfcc = self._hop, self._n_fft, self._win, self.n_mfcc
        while self._j < j1:
            j0 = self._j
            jb = min(j1, j0 + self._block)
            nf = jb - j0
            # the buffer starts at the first sample of frame j0's window (see the end of the loop)
            seg = self._buf[:(nf - 1) * hop + n_fft]
            spec = self._stft(seg)
            # |z|^2 as re^2 + im^2: numpy's abs of a complex number (a hypot) rounds differently with
            # and without AVX2, elementwise products and sums do not
            power = spec.real * spec.real + spec.imag * spec.imag
            # librosa.feature.melspectrogram, but the projection without BLAS (optimize=False: numpy's
            # own loop): OpenBLAS rounds it differently with other thread counts, and BLAS thread limits
            # are per process while builds run recordings in threads (Dask) or processes; a database
            # must not depend on how it was built (a 1-worker and a 2-worker build differed by 3e-5)
            mel = np.einsum("mf,ft->mt", self._basis, power, optimize=False)

            # Rectangular 25 ms energy centred at each analysis frame, from a running sum of squares
            # carried across blocks exactly as one cumulative sum over the file adds it. In place and
            # by slices rather than concatenations and index arrays (0.03 -> 0.01 ms a live step)
            csum = np.empty(len(seg) + 1)
            csum[0] = self._csum
            np.multiply(seg, seg, out=csum[1:], dtype=np.float64)  # in float64, as seg64 * seg64
            np.cumsum(csum, out=csum)
            first = (n_fft - win) // 2
            stop = first + (nf - 1) * hop + 1

            # The logarithms of the mel power (librosa.power_to_db(mel, ref=1.0, amin=_FLOOR,
            # top_db=None), with a logarithm that does not depend on the CPU, see _log) and of the
            # energy in one call: elementwise, so the same bits as two, for half the calls' overhead
            n_mel = mel.size
            logs = np.empty(n_mel + nf)
            np.maximum(mel, _FLOOR, out=logs[:n_mel].reshape(mel.shape))  # in float32 (mel's), as before
            np.subtract(csum[first + win:stop + win:hop], csum[first:stop:hop], out=logs[n_mel:])
            logs[n_mel:] /= win
            np.maximum(logs[n_mel:], _FLOOR, out=logs[n_mel:])
            logs = _log(logs)
            # power_to_db's dB, rounded to float32 once
            log_mel = (logs[:n_mel].reshape(mel.shape) * (10.0 / math.log(10.0))).astype(np.float32)
            # librosa.feature.mfcc(S=log_mel, n_mfcc, dct_type=2, norm="ortho") is this call and a slice;
            # called directly it skips librosa's wrapper (2 us a live step)
            mfcc = self._fft.dct(log_mel, axis=-2, type=2, norm="ortho")[:n_mfcc]

            # appended to the rows kept in one copy instead of two concatenations
            k = len(self._rows)
            rows = np.empty((k + nf, n_mfcc + 1))
            rows[:k] = self._rows
            rows[k:, :n_mfcc] = mfcc.T
            rows[k:, n_mfcc] = logs[n_mel:]
            self._rows = rows
            self._own = np.concatenate([self._own, self._owners(j0, jb)])
            # the next block's first window starts nf hops later: drop the samples before it
            shift = nf * hop
            self._csum = float(csum[shift])
            self._buf = self._buf[shift:]
            self._buf_at += shift
            self._j = jb

    def _stft(self, seg: np.ndarray) -> np.ndarray:
        """``librosa.stft(seg, n_fft, hop_length, win_length, window="hann", center=False)``, the same bits.

        seg : ndarray [shape=(n,)], float32, n >= n_fft; returns ndarray [shape=(n_fft // 2 + 1, frames)],
        complex64, Fortran order as librosa's. librosa's own steps (the window, the frames as a strided
        view, the FFT in blocks of ``librosa.util.MAX_MEM_BLOCK`` bytes of frames, into complex64), without
        remaking the window and checking the input at every call: a live step's features spent about a
        third of their time there.
        """
        n_fft, hop, size = self._n_fft, self._hop, seg.itemsize
        n = (len(seg) - n_fft) // hop + 1
        # librosa.util.frame, transposed: row t is seg[t * hop : t * hop + n_fft]. A plain strided view
        # (sliding_window_view cost 10 us a call), and the FFT along rows: pocketfft copies each frame
        # to its own buffer and transforms it alike along either axis, the same bits, but the window
        # product, the FFT's copies and the cast to complex64 then run over contiguous memory instead
        # of transposing (0.126 -> 0.091 ms a live step). spec.T is librosa's Fortran-order matrix.
        frames = np.ndarray((n, n_fft), seg.dtype, seg, 0, (hop * size, size))
        spec = np.empty((n, 1 + n_fft // 2), dtype=np.complex64)
        cols = max(int(self._max_mem_block // (n_fft * size)), 1)
        for a in range(0, n, cols):
            b = min(a + cols, n)
            spec[a:b] = self._fft.rfft(frames[a:b] * self._fft_window, axis=-1)
        return spec.T

    def _available(self) -> int:
        """Analysis frames the buffer holds all the samples of (capped at the frames kept)."""
        end = self._buf_at + len(self._buf)  # absolute index after the last sample
        n = (end - (self._n_fft - self._half)) // self._hop + 1
        n = max(n, self._j)
        return n if self._n_fine is None else min(n, self._n_fine)

    # -- motion frames
    def _emit(self) -> np.ndarray:
        """The motion frames whose analysis frames are all computed, in order."""
        n_out = self.n_mfcc + 1
        lo, i0 = self._rows_at, self._i
        done = self._n_fine is not None and self._j >= self._n_fine
        # frames before the owner of the next analysis frame have all theirs (owners never decrease)
        i1 = self.n_frames if done else self._owner(self._j)
        if self.n_frames is not None:
            i1 = min(i1, self.n_frames)
        if i1 <= i0:
            return np.zeros((0, n_out), dtype=np.float32)
        n = i1 - i0
        # owners never decrease, so the rows of frames i0 .. i1 - 1 are a slice t0:t1 (cheaper to find
        # than by masks and index arrays)
        own = self._own
        t0, t1 = (int(t) for t in own.searchsorted((i0, i1)))
        if self._n_fine is not None:
            t1 = min(t1, max(t0, self._n_fine - lo))  # live speech: frames past the end finish() set
        owner = own[t0:t1] - i0
        counts = np.bincount(owner, minlength=n).astype(np.float64)
        has = counts > 0
        if not has.all():
            # a frame without analysis frames of its own waits for the one nearest its middle
            empty = np.flatnonzero(~has)
            late = empty[self._nearest(i0 + empty[0], i0 + empty[-1] + 1)[empty - empty[0]] >= self._j]
            if len(late):
                n = int(late[0])
                if n == 0:
                    return np.zeros((0, n_out), dtype=np.float32)
                i1 = i0 + n
                t1 = t0 + int(owner.searchsorted(n))
                owner, counts, has = owner[:t1 - t0], counts[:n], has[:n]
        # All columns' sums in one bincount over (frame, column) cells instead of one per column: each
        # cell still adds its rows in order to 0.0, the same bits (0.04 -> 0.01 ms a live step)
        cells = (owner[:, None] * n_out + np.arange(n_out)).ravel()
        sums = np.bincount(cells, weights=self._rows[t0:t1].ravel(), minlength=n * n_out).reshape(n, n_out)
        if has.all():
            out = sums / counts[:, None]
        else:
            out = np.empty((n, n_out))
            out[has] = sums[has] / counts[has, None]
            empty = np.flatnonzero(~has)
            out[empty] = self._rows[self._nearest(i0, i1)[empty] - lo]
        self._i = i1
        # keep the rows later motion frames may still need: their own, or the one nearest them
        later = int(own.searchsorted(i1))
        keep = min(lo + later if later < len(own) else self._j, self._nearest_one(i1))
        if keep > lo:
            self._rows, self._own = self._rows[keep - lo:], own[keep - lo:]
            self._rows_at = keep
        return np.ascontiguousarray(out, dtype=np.float32)

    def push(self, samples) -> np.ndarray:
        """Add the next samples; returns the motion frames they complete.

        Parameters
        ----------
        samples : ndarray [shape=(n,)], float, amplitude in [-1, 1]

        Returns
        -------
        ndarray [shape=(k, n_mfcc + 1)], float32
            Motion frames ``self.n_returned - k .. self.n_returned - 1``; ``k`` may be 0.

        Raises
        ------
        ParameterError
            Samples that are not mono floats or not finite (the message gives the sample's
            index in the whole speech), or a push after :meth:`finish`.
        """
        if self._finished:
            raise ParameterError("AudioFeatureStream.push: the stream is finished; start a new one")
        y = _check_samples(samples, self._pushed)
        self._pushed += len(y)
        if self._n_fine is not None:
            # samples past the last kept analysis frame's window are never read
            end = (self._n_fine - 1) * self._hop + self._n_fft - self._half
            y = y[:max(0, end - (self._buf_at + len(self._buf)))]
        # a block's worth of samples at a time, so a long push costs no more memory than a short one
        step = self._block * self._hop
        out = []
        for a in range(0, len(y), step):
            self._buf = np.concatenate([self._buf, y[a:a + step].astype(np.float32, copy=False)])
            out.append(self._advance())
        if not out:
            out.append(self._advance())
        return out[0] if len(out) == 1 else np.concatenate(out)

    def _advance(self) -> np.ndarray:
        """Compute the analysis frames the buffer allows, block by block; return the motion frames done."""
        out = []
        n = self._available()
        while self._j < n:
            self._compute(min(n, self._j + self._block))
            out.append(self._emit())
        if not out:
            out.append(self._emit())
        return out[0] if len(out) == 1 else np.concatenate(out)

    def finish(self, n_frames: int | None = None, *, max_pad_s: float = MAX_PAD_S) -> np.ndarray:
        """The remaining motion frames, the audio padded with silence as :func:`audio_features` pads it.

        Parameters
        ----------
        n_frames : int >= 0 or None
            Total motion frames; ``None``: the ``n_frames`` given to the constructor, else
            ``n_frames_for_duration(samples pushed / sr, fps)``. Frames already returned
            count.
        max_pad_s : float >= 0, keyword-only
            As in :func:`audio_features`.

        Returns
        -------
        ndarray [shape=(n_frames - n_returned, n_mfcc + 1)], float32

        Raises
        ------
        ParameterError
            Fewer ``n_frames`` than already returned, a frame count other than the
            constructor's, or audio short of ``n_frames / fps`` by ``max_pad_s`` or more.
        """
        if self._finished:
            raise ParameterError("AudioFeatureStream.finish: the stream is already finished")
        if n_frames is None:
            n_frames = self.n_frames if self.n_frames is not None else \
                n_frames_for_duration(self._pushed / self.sr, self.fps)
        n_frames = _check_int("n_frames", n_frames, 0, what="an int >= 0")
        if self.n_frames is not None and n_frames != self.n_frames:
            raise ParameterError(f"n_frames: expected {self.n_frames} (as the stream was made); got {n_frames}")
        if n_frames < self._i:
            raise ParameterError(f"n_frames: expected at least the {self._i} frames already returned; "
                                 f"got {n_frames}")
        max_pad_s = _check_nonnegative("max_pad_s", max_pad_s)
        _check_shortfall(self._pushed / self.sr, n_frames, self.fps, max_pad_s)
        self._finished = True
        if n_frames == self._i:
            return np.zeros((0, self.n_mfcc + 1), dtype=np.float32)
        self.n_frames = n_frames
        self._n_fine = self._fine_count(n_frames)
        end = (self._n_fine - 1) * self._hop + self._n_fft - self._half
        short = end - (self._buf_at + len(self._buf))
        if short > 0:
            self._buf = np.concatenate([self._buf, np.zeros(short, dtype=np.float32)])
        return self._advance()

    @property
    def n_returned(self) -> int:
        """Motion frames returned so far."""
        return self._i


def _check_shortfall(have_s: float, n_frames: int, fps: float, max_pad_s: float) -> None:
    need_s = n_frames / fps
    if n_frames and need_s - have_s >= max_pad_s:
        raise ParameterError(
            f"samples: audio lasts {have_s:.3f} s but n_frames={n_frames} at {fps:g} fps needs "
            f"{need_s:.3f} s; only shortfalls under max_pad_s={max_pad_s:g} s are padded with silence"
        )


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
    depends only on audio within 12.5 ms of its analysis frames, which is what lets
    :class:`AudioFeatureStream` compute them in blocks of bounded memory: this function
    is one stream over the whole speech (peak memory about 30 MB beyond the samples,
    for any duration).
    """
    y = _check_samples(samples)
    if isinstance(sr, (bool, np.bool_)) or not isinstance(sr, (int, np.integer)) or sr <= 0:
        raise ParameterError(f"sr: expected a positive int sample rate in Hz; got {sr!r}")
    fps = check_fps(fps)
    n_frames = _check_int("n_frames", n_frames, 0, what="an int >= 0")
    n_mfcc = _check_int("n_mfcc", n_mfcc, 1, N_MELS, what=f"an int in [1, {N_MELS}]")
    max_pad_s = _check_nonnegative("max_pad_s", max_pad_s)
    if n_frames == 0:
        return np.zeros((0, n_mfcc + 1), dtype=np.float32)
    _check_shortfall(len(y) / int(sr), n_frames, fps, max_pad_s)

    stream = AudioFeatureStream(int(sr), fps=fps, n_mfcc=n_mfcc, n_frames=n_frames)
    step = FEATURE_BLOCK_FRAMES * stream._hop
    out = np.empty((n_frames, n_mfcc + 1), dtype=np.float32)
    k = 0
    for a in range(0, len(y), step):
        rows = stream.push(y[a:a + step])
        out[k:k + len(rows)] = rows
        k += len(rows)
        if k == n_frames:
            break
    rows = stream.finish(max_pad_s=max_pad_s)
    out[k:k + len(rows)] = rows
    k += len(rows)
    if k != n_frames:  # the stream's own invariant, not user input
        raise RuntimeError(f"audio_features: {k} of {n_frames} frames computed")
    return out


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
