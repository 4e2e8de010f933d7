"""Packed frame bitsets: the form in which masks reach the search kernel.

A mask is ``ceil(F / 64)`` uint64 words over the database frames ``F``: frame ``f`` is
bit ``f & 63`` of word ``f >> 6``. A candidate window is allowed when its first and
last frame are both set (Habibie et al. 2022, Sec. 3.1).
"""
from __future__ import annotations

import numpy as np

from gesturedb.errors import ParameterError

# --------------------------------------------------------------------------------------
# Packed bitsets
# --------------------------------------------------------------------------------------

_ALL_ONES = np.uint64(0xFFFF_FFFF_FFFF_FFFF)


def n_words(n_frames: int) -> int:
    """Number of uint64 words in a bitset over ``n_frames`` frames: ``ceil(F / 64)``."""
    n_frames = _check_count(n_frames, "n_frames", minimum=0)
    return (n_frames + 63) >> 6


def _check_count(value, what: str, *, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ParameterError(f"{what}: expected an integer >= {minimum}; got {value!r}")
    if value < minimum:
        raise ParameterError(f"{what}: expected an integer >= {minimum}; got {value}")
    return int(value)


def _last_word_mask(n_frames: int) -> np.uint64:
    """Bits of the last word that hold frames (all ones when F is a multiple of 64)."""
    rem = n_frames & 63
    return _ALL_ONES if rem == 0 else np.uint64((1 << rem) - 1)


def pack_bits(bits: np.ndarray) -> np.ndarray:
    """Pack per-frame booleans into the kernel's uint64 bitset layout.

    Parameters
    ----------
    bits : ndarray [shape=(..., F)], bool
        True where a frame is allowed. Leading axes (e.g. one row per search step)
        are packed independently.

    Returns
    -------
    words : ndarray [shape=(..., ceil(F / 64))], uint64, C-contiguous
        Frame ``f`` is bit ``f & 63`` of word ``f >> 6``; the padding bits past
        ``F`` in the last word are zero.
    """
    bits = np.asarray(bits)
    if bits.dtype != np.bool_:
        raise ParameterError(
            f"pack_bits: expected a bool array (..., F); got {bits.dtype} {bits.shape} "
            "(compare explicitly, e.g. values > 0, so no non-zero float is taken as True)"
        )
    if bits.ndim == 0:
        raise ParameterError("pack_bits: expected a bool array (..., F); got a scalar")
    n_frames = bits.shape[-1]
    nw = n_words(n_frames)
    # packbits pads the last byte with zero bits; little bit order puts frame f at
    # bit f & 7 of byte f >> 3, and eight little-endian bytes make word f >> 6.
    packed = np.packbits(bits, axis=-1, bitorder="little")
    pad = nw * 8 - packed.shape[-1]
    if pad:
        packed = np.concatenate(
            [packed, np.zeros(packed.shape[:-1] + (pad,), dtype=np.uint8)], axis=-1
        )
    words = np.ascontiguousarray(packed).view("<u8")
    # A no-op on little-endian machines; on big-endian ones it converts the values.
    return np.ascontiguousarray(words.astype(np.uint64, copy=False))


def unpack_bits(words: np.ndarray, n_frames: int) -> np.ndarray:
    """Unpack a bitset into per-frame booleans (inverse of :func:`pack_bits`).

    Parameters
    ----------
    words : ndarray [shape=(..., ceil(F / 64))], uint64
    n_frames : int
        ``F``, the number of frames the bitset covers.

    Returns
    -------
    bits : ndarray [shape=(..., F)], bool
    """
    words = _as_words(words, "unpack_bits: words")
    n_frames = _check_count(n_frames, "unpack_bits: n_frames", minimum=0)
    nw = n_words(n_frames)
    if words.shape[-1] != nw:
        raise ParameterError(
            f"unpack_bits: words: expected {nw} uint64 words for {n_frames} frames; "
            f"got {words.shape[-1]} (shape {words.shape})"
        )
    as_bytes = np.ascontiguousarray(words.astype("<u8", copy=False)).view(np.uint8)
    bits = np.unpackbits(as_bytes, axis=-1, count=n_frames, bitorder="little")
    return bits.view(np.bool_)


if hasattr(np, "bitwise_count"):

    def _popcount(words: np.ndarray) -> np.ndarray:
        return np.bitwise_count(words)

else:  # numpy < 2.0
    _BYTE_COUNTS = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)

    def _popcount(words: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(words).view(np.uint8).reshape(words.shape + (8,))
        return _BYTE_COUNTS[b].sum(axis=-1, dtype=np.uint8)


def count_bits(words: np.ndarray):
    """Number of set bits (allowed frames) along the last axis.

    Parameters
    ----------
    words : ndarray [shape=(..., W)], uint64

    Returns
    -------
    int or ndarray [shape=(...)], int64
        A Python int for a single bitset, one count per row otherwise.
    """
    words = _as_words(words, "count_bits: words")
    counts = _popcount(words).sum(axis=-1, dtype=np.int64)
    return int(counts) if words.ndim == 1 else counts


def full_mask(n_frames: int) -> np.ndarray:
    """Bitset with every one of ``n_frames`` frames allowed (padding bits clear)."""
    n_frames = _check_count(n_frames, "full_mask: n_frames", minimum=0)
    words = np.full(n_words(n_frames), _ALL_ONES, dtype=np.uint64)
    if words.size:
        words[-1] = _last_word_mask(n_frames)
    return words


def slice_bits(words: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Frames ``[start, stop)`` of a bitset as a bitset of their own (a shard's frames).

    Parameters
    ----------
    words : ndarray [shape=(W,)], uint64
    start, stop : int
        Frame range, ``0 <= start <= stop <= 64 W``.

    Returns
    -------
    ndarray [shape=(ceil((stop - start) / 64),)], uint64
        Bit ``i`` is bit ``start + i`` of ``words``; padding bits clear. Works on
        the words (two shifts per word), so a client never unpacks a row to one
        byte per frame.
    """
    words = _as_words(words, "slice_bits: words")
    if words.ndim != 1:
        raise ParameterError(f"slice_bits: words: expected one bitset (W,); got shape {words.shape}")
    start = _check_count(start, "slice_bits: start", minimum=0)
    stop = _check_count(stop, "slice_bits: stop", minimum=start)
    if stop > 64 * words.shape[0]:
        raise ParameterError(f"slice_bits: stop: expected <= {64 * words.shape[0]} (the bitset's {words.shape[0]} "
                             f"words); got {stop}")
    n = stop - start
    nw = n_words(n)
    q, r = divmod(start, 64)
    w = np.zeros(nw + 1, dtype=np.uint64)
    src = words[q:q + nw + 1]
    w[:src.shape[0]] = src
    out = (w[:nw] >> np.uint64(r)) | (w[1:] << np.uint64(64 - r)) if r else w[:nw].copy()
    if nw:
        out[-1] &= _last_word_mask(n)
    return out


class StepBitsets:
    """One allowed bitset per search step, each distinct row stored once.

    A control schedule or a keyword transcript gives a few distinct rows for
    many steps: a minute of output is 117 steps, each row ``F / 8`` bytes (6.75
    MB at 1,000 hours), so the ``(steps, W)`` array would be 790 MB where its
    distinct rows take a few.

    Reads like the ``(S, W)`` array it stands for: ``len``, ``shape``,
    ``dtype``, ``b[i]`` (step ``i``'s row, a read-only view) and
    ``np.asarray(b)`` (the whole array, built on demand); ``a & b`` is the
    step-wise intersection, again with each distinct row once.

    Parameters
    ----------
    rows : ndarray [shape=(U, W)], uint64
        The distinct bitsets (kept read-only).
    of_step : ndarray [shape=(S,)], int
        The row of each step, ``0 <= of_step < U``.
    """

    ndim = 2
    dtype = np.dtype(np.uint64)

    def __init__(self, rows: np.ndarray, of_step: np.ndarray):
        rows = _as_words(rows, "StepBitsets: rows")
        if rows.ndim != 2:
            raise ParameterError(f"StepBitsets: rows: expected distinct bitsets (U, W); got shape {rows.shape}")
        of_step = np.asarray(of_step)
        if of_step.ndim != 1 or (of_step.size and (of_step.dtype.kind not in "iu" or of_step.min() < 0
                                                   or of_step.max() >= rows.shape[0])):
            raise ParameterError(f"StepBitsets: of_step: expected (S,) indices into the {rows.shape[0]} rows; "
                                 f"got {of_step.dtype} {of_step.shape}")
        self.rows = np.ascontiguousarray(rows)
        self.rows.setflags(write=False)
        self.of_step = of_step.astype(np.int64)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.of_step.shape[0]), int(self.rows.shape[1]))

    def __len__(self) -> int:
        return int(self.of_step.shape[0])

    def __getitem__(self, i):
        if isinstance(i, (int, np.integer)):
            return self.rows[self.of_step[i]]
        return np.asarray(self)[i]

    def __array__(self, dtype=None, copy=None):
        out = self.rows[self.of_step]
        return out if dtype is None else out.astype(dtype, copy=False)

    def __and__(self, other: "StepBitsets") -> "StepBitsets":
        if not isinstance(other, StepBitsets) or other.shape != self.shape:
            raise ParameterError(f"StepBitsets &: expected StepBitsets of shape {self.shape}; got "
                                 f"{getattr(other, 'shape', type(other).__name__)}")
        pairs, of = np.unique(np.stack([self.of_step, other.of_step], 1), axis=0, return_inverse=True)
        return StepBitsets(self.rows[pairs[:, 0]] & other.rows[pairs[:, 1]], of.reshape(-1))


def empty_mask(n_frames: int) -> np.ndarray:
    """Bitset with no frame allowed."""
    return np.zeros(n_words(n_frames), dtype=np.uint64)


def _as_words(x, what: str) -> np.ndarray:
    if not isinstance(x, np.ndarray) or x.dtype != np.uint64:
        desc = f"{x.dtype} {x.shape}" if isinstance(x, np.ndarray) else type(x).__name__
        raise ParameterError(f"{what}: expected a uint64 bitset array (..., W); got {desc}")
    if x.ndim == 0:
        raise ParameterError(f"{what}: expected a uint64 bitset array (..., W); got a scalar")
    return x


def _binary(name: str, ufunc, masks) -> np.ndarray:
    arrays = [_as_words(m, f"{name}: argument {i + 1}") for i, m in enumerate(masks)]
    width = arrays[0].shape[-1]
    for i, a in enumerate(arrays[1:], start=2):
        if a.shape[-1] != width:
            raise ParameterError(
                f"{name}: argument {i} has {a.shape[-1]} words, argument 1 has {width} "
                f"(shapes {a.shape} and {arrays[0].shape}): masks over different databases?"
            )
    try:
        out = ufunc(arrays[0], arrays[1])
        for a in arrays[2:]:
            out = ufunc(out, a)
    except ValueError as e:
        shapes = ", ".join(str(a.shape) for a in arrays)
        raise ParameterError(f"{name}: shapes {shapes} do not broadcast") from e
    return out


def mask_and(a: np.ndarray, b: np.ndarray, *more: np.ndarray) -> np.ndarray:
    """Frames allowed by every mask (bitwise AND).

    Parameters
    ----------
    a, b, *more : ndarray [shape=(..., W)], uint64
        Same word count; leading axes broadcast, so a single mask ``(W,)`` can
        restrict every row of a per-step ``(steps, W)`` array.

    Returns
    -------
    ndarray [shape=broadcast shape], uint64
    """
    return _binary("mask_and", np.bitwise_and, (a, b) + more)


def mask_or(a: np.ndarray, b: np.ndarray, *more: np.ndarray) -> np.ndarray:
    """Frames allowed by any of the masks (bitwise OR); shapes as in :func:`mask_and`."""
    return _binary("mask_or", np.bitwise_or, (a, b) + more)


def mask_not(words: np.ndarray, n_frames: int) -> np.ndarray:
    """Frames not allowed by ``words``.

    The padding bits past ``n_frames`` stay clear, so :func:`count_bits` of the
    result is ``n_frames - count_bits(words)``.

    Parameters
    ----------
    words : ndarray [shape=(..., ceil(F / 64))], uint64
    n_frames : int
        ``F``.

    Returns
    -------
    ndarray [shape=words.shape], uint64
    """
    words = _as_words(words, "mask_not: words")
    n_frames = _check_count(n_frames, "mask_not: n_frames", minimum=0)
    nw = n_words(n_frames)
    if words.shape[-1] != nw:
        raise ParameterError(
            f"mask_not: words: expected {nw} uint64 words for {n_frames} frames; "
            f"got {words.shape[-1]} (shape {words.shape})"
        )
    out = np.invert(words)
    if nw:
        out[..., -1] &= _last_word_mask(n_frames)
    return out


def validate_bitset(
    words, n_frames: int, *, name: str = "allowed", n_steps: int | None = None
) -> np.ndarray:
    """Check a bitset the way the search boundary needs it, and return it unchanged.

    Parameters
    ----------
    words : ndarray [shape=(W,) or (steps, W)], uint64, C-contiguous
        ``W = ceil(n_frames / 64)``.
    n_frames : int
        Number of database frames ``F``.
    name : str
        What to call the array in messages.
    n_steps : int, optional
        If given, a 2-D bitset must have exactly this many rows.

    Raises
    ------
    ParameterError
        Wrong type, dtype, shape, layout, or bits set past frame ``F - 1`` (a
        bitset built for a larger database).
    """
    n_frames = _check_count(n_frames, f"{name}: n_frames", minimum=0)
    nw = n_words(n_frames)
    if not isinstance(words, np.ndarray):
        raise ParameterError(
            f"{name}: expected a uint64 ndarray ({nw},) or (steps, {nw}); got {type(words).__name__}"
        )
    if words.dtype != np.uint64 or words.ndim not in (1, 2) or words.shape[-1] != nw:
        raise ParameterError(
            f"{name}: expected uint64 ({nw},) or (steps, {nw}) for {n_frames} frames; "
            f"got {words.dtype} {words.shape}"
        )
    if words.ndim == 2 and n_steps is not None and words.shape[0] != n_steps:
        raise ParameterError(
            f"{name}: expected one bitset per search step, ({n_steps}, {nw}); got {words.shape}"
        )
    if not words.flags.c_contiguous:
        raise ParameterError(
            f"{name}: expected a C-contiguous array; got strides {words.strides} "
            "(pass np.ascontiguousarray(...))"
        )
    if nw and (n_frames & 63):
        stray = words[..., -1] & ~_last_word_mask(n_frames)
        if np.any(stray):
            raise ParameterError(
                f"{name}: bits set past the last frame {n_frames - 1}: "
                "the bitset was built for a larger database"
            )
    return words


def candidate_counts(
    allowed: np.ndarray,
    *,
    n_frames: int,
    seg_start: np.ndarray,
    seg_len: np.ndarray,
    n: int,
    exclude: np.ndarray | None = None,
) -> np.ndarray:
    """Allowed search candidates per segment for one step, as the search spec defines them.

    A candidate ``(m, s)`` has ``1 <= s <= seg_len[m] - n``; with ``g = seg_start[m] + s``
    it is allowed iff ``exclude[m]`` is false and frames ``g`` and ``g + n - 1`` are
    both set. This is a numpy oracle for the kernel's candidate rule and lets the
    synthesis tell *why* a step has no candidate.

    Parameters
    ----------
    allowed : ndarray [shape=(ceil(F / 64),)], uint64
    n_frames : int
        ``F``.
    seg_start, seg_len : ndarray [shape=(M,)], int
        Segment ``m`` covers frames ``[seg_start[m], seg_start[m] + seg_len[m])``.
    n : int
        Window length of the step, ``min(N, T - t)``.
    exclude : ndarray [shape=(M,)], bool, optional

    Returns
    -------
    counts : ndarray [shape=(M,)], int64
    """
    n_frames = _check_count(n_frames, "candidate_counts: n_frames", minimum=1)
    n = _check_count(n, "candidate_counts: n", minimum=1)
    validate_bitset(allowed, n_frames, name="candidate_counts: allowed")
    if allowed.ndim != 1:
        raise ParameterError(
            f"candidate_counts: allowed: expected one bitset ({n_words(n_frames)},); got {allowed.shape}"
        )
    seg_start = np.asarray(seg_start)
    seg_len = np.asarray(seg_len)
    if (
        seg_start.ndim != 1
        or seg_start.shape != seg_len.shape
        or seg_start.dtype.kind not in "iu"
        or seg_len.dtype.kind not in "iu"
    ):
        raise ParameterError(
            "candidate_counts: seg_start, seg_len: expected two integer arrays (M,); "
            f"got {seg_start.dtype} {seg_start.shape} and {seg_len.dtype} {seg_len.shape}"
        )
    seg_start = seg_start.astype(np.int64)
    seg_len = seg_len.astype(np.int64)
    if seg_start.size and (
        seg_start.min() < 0 or seg_len.min() < 0 or (seg_start + seg_len).max() > n_frames
    ):
        raise ParameterError(
            f"candidate_counts: segments must lie within the {n_frames} database frames"
        )
    counts = np.zeros(seg_start.shape, dtype=np.int64)
    if n > n_frames:
        return counts
    bits = unpack_bits(allowed, n_frames)
    ok = bits[: n_frames - n + 1] & bits[n - 1 :]  # ok[g]: first and last frame of window g set
    prefix = np.concatenate([[0], np.cumsum(ok, dtype=np.int64)])
    lo = seg_start + 1
    hi = seg_start + seg_len - n  # inclusive last window start
    live = hi >= lo
    if exclude is not None:
        exclude = np.asarray(exclude)
        if exclude.dtype != np.bool_ or exclude.shape != seg_start.shape:
            raise ParameterError(
                f"candidate_counts: exclude: expected bool {seg_start.shape}; "
                f"got {exclude.dtype} {exclude.shape}"
            )
        live &= ~exclude
    counts[live] = prefix[hi[live] + 1] - prefix[lo[live]]
    return counts


