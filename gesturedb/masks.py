"""Control masks: packed frame bitsets, a small mask expression language, schedules.

The search kernel (``../shared/spec/search.md``) restricts its candidates with a
packed bitset over database frames: ``ceil(F / 64)`` uint64 words, frame ``f`` is
bit ``f & 63`` of word ``f >> 6`` (little-endian bit order inside each word). A
candidate window is allowed when its first and last frame are both set
(Habibie et al. 2022, Sec. 3.1), so a mask is a per-frame property here.

Masks are written as expressions over the per-frame control features of the
database (:mod:`gesturedb.features.controls`)::

    left_wrist_height > p85                   # above the database's 85th percentile
    left_wrist_speed < 20 cm/s and symmetric   # units convert to the feature's unit
    not (left_wrist_high or right_wrist_high)

Grammar (keywords are case-insensitive, names are not)::

    expr       := or_expr
    or_expr    := and_expr ("or" and_expr)*
    and_expr   := not_expr ("and" not_expr)*
    not_expr   := "not" not_expr | primary
    primary    := "(" or_expr ")" | FEATURE OP value | NAME
    OP         := "<" | "<=" | ">" | ">="
    value      := ["-" | "+"] NUMBER [UNIT] | PERCENTILE
    UNIT       := m | cm | mm | m/s | cm/s | mm/s
    PERCENTILE := "p" NUMBER        (0..100, e.g. p85, p97.5)

so ``a or b and not c`` means ``a or (b and (not c))``. A bare ``NAME`` is a
named mask: a caller's saved mask (packed words) or expression, one of
:data:`DEFAULT_NAMED` (``symmetric``, ``asymmetric``, ``left_wrist_high``, ...),
or one of the ``<feature>_high`` / ``<feature>_low`` masks generated for every
control feature (above its 85th / below its 15th percentile, the masks the
paper's Sec. 4.1 evaluates). Percentiles are taken over all database frames with
``np.percentile`` (linear interpolation) in float64, and every comparison is
evaluated in float64, so a threshold means exactly what it reports.

A control schedule assigns expressions to time ranges of the *output*::

    0-12: left_wrist_height > p85; 12-24: left_wrist_speed < p15 and symmetric; 24-: asymmetric

Each search step (output frames ``t .. t+n-1``, ``t = 0, N, 2N, ...``) takes the
control active at the centre of its span ``[t/fps, (t+n)/fps)``: a schedule
boundary switches the control at the step boundary nearest to it, and a step that
a boundary cuts follows the side covering more of it. Steps whose centre no range
covers are unconstrained (all frames allowed, label ``None``).
"""
from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field
from typing import Callable, Iterator, Mapping, NamedTuple, Sequence

import numpy as np

from gesturedb.errors import ParameterError

__all__ = [
    "CONTROL_UNITS",
    "DEFAULT_NAMED",
    "HIGH_PERCENTILE",
    "LOW_PERCENTILE",
    "Comparison",
    "MaskExpression",
    "MaskResult",
    "PercentileSuggestion",
    "Relaxation",
    "ScheduleBitsets",
    "ScheduleItem",
    "candidate_counts",
    "closest_percentile_with_candidates",
    "compile_mask",
    "count_bits",
    "empty_mask",
    "feature_unit",
    "full_mask",
    "mask_and",
    "mask_definitions",
    "mask_not",
    "mask_or",
    "n_words",
    "pack_bits",
    "parse_mask_expression",
    "parse_schedule",
    "percentile_masks",
    "percentile_threshold",
    "schedule_bitsets",
    "suggest_percentiles",
    "unpack_bits",
    "validate_bitset",
]

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


# --------------------------------------------------------------------------------------
# Control features, units and named masks
# --------------------------------------------------------------------------------------

HIGH_PERCENTILE = 85.0
"""Percentile above which ``<feature>_high`` holds (Habibie et al. 2022, Sec. 4.1)."""
LOW_PERCENTILE = 15.0
"""Percentile below which ``<feature>_low`` holds."""

# One definition of the control features' units: the module that computes them.
# (features/controls.py is plain numpy, so masks stays importable without the readers.)
from gesturedb.features.controls import CONTROL_UNITS  # noqa: E402

# Features not listed above get a unit from their name, so a new control feature
# named like the others works with units without touching this module.
_UNIT_BY_SUFFIX = (
    ("_speed", "m/s"),
    ("_velocity", "m/s"),
    ("_height", "m"),
    ("_radius", "m"),
    ("_distance", "m"),
    ("_asymmetry", "m"),
    ("_width", "m"),
)

# unit -> (dimension, power of ten relative to the SI unit)
_UNITS: dict[str, tuple[str, int]] = {
    "m": ("length", 0),
    "cm": ("length", -2),
    "mm": ("length", -3),
    "m/s": ("speed", 0),
    "cm/s": ("speed", -2),
    "mm/s": ("speed", -3),
}

DEFAULT_NAMED: dict[str, str] = {
    "symmetric": "height_asymmetry < p15",
    "asymmetric": "height_asymmetry > p85",
    "left_wrist_high": "left_wrist_height > p85",
    "left_wrist_low": "left_wrist_height < p15",
    "right_wrist_high": "right_wrist_height > p85",
    "right_wrist_low": "right_wrist_height < p15",
    "left_wrist_fast": "left_wrist_speed > p85",
    "left_wrist_slow": "left_wrist_speed < p15",
    "right_wrist_fast": "right_wrist_speed > p85",
    "right_wrist_slow": "right_wrist_speed < p15",
}
"""Predefined named masks, name -> expression (the paper's Sec. 4.1 control levels).

Pass ``named={...}`` to :func:`compile_mask` to add names or override these. On
top of these, every control feature ``X`` gets ``X_high`` (``X > p85``) and
``X_low`` (``X < p15``).
"""


def feature_unit(feature: str, units: Mapping[str, str | None] | None = None) -> str | None:
    """Base unit of a control feature: ``units`` override, :data:`CONTROL_UNITS`, name suffix.

    Returns ``None`` for a unitless feature (numbers in expressions must then
    carry no unit).
    """
    if units is not None and feature in units:
        unit = units[feature]
        if unit is not None and unit not in _UNITS:
            raise ParameterError(
                f"units[{feature!r}]: expected one of {', '.join(_UNITS)} or None; got {unit!r}"
            )
        return unit
    if feature in CONTROL_UNITS:
        return CONTROL_UNITS[feature]
    for suffix, unit in _UNIT_BY_SUFFIX:
        if feature.endswith(suffix):
            return unit
    return None


def _percentile_definitions(features) -> dict[str, str]:
    defs = {}
    for f in features:
        defs[f"{f}_high"] = f"{f} > p{HIGH_PERCENTILE:g}"
        defs[f"{f}_low"] = f"{f} < p{LOW_PERCENTILE:g}"
    return defs


def mask_definitions(
    controls: Mapping[str, np.ndarray], named: Mapping[str, object] | None = None
) -> dict[str, object]:
    """Every name a mask expression can use, with its definition.

    Parameters
    ----------
    controls : mapping str -> ndarray [shape=(F,)]
        Control features of the database; their names define ``<feature>_high``
        and ``<feature>_low``.
    named : mapping str -> str or ndarray, optional
        Caller's masks: expressions, packed uint64 bitsets ``(ceil(F / 64),)`` or
        bool arrays ``(F,)``. They override :data:`DEFAULT_NAMED`, which overrides
        the generated percentile masks.

    Returns
    -------
    dict str -> str or ndarray
    """
    defs: dict[str, object] = _percentile_definitions(controls.keys())
    defs.update(DEFAULT_NAMED)
    if named is not None:
        if not isinstance(named, Mapping):
            raise ParameterError(
                f"named: expected a mapping of name -> expression or bitset; got {type(named).__name__}"
            )
        for k, v in named.items():
            if not isinstance(k, str) or not _NAME_RE.fullmatch(k) or k.lower() in _KEYWORDS:
                raise ParameterError(
                    f"named: mask names must be identifiers (letters, digits, '_') other than "
                    f"and/or/not; got {k!r}"
                )
            if _PCT_RE.fullmatch(k):
                raise ParameterError(f"named: {k!r} reads as a percentile; choose another mask name")
        defs.update(named)
    return defs


# --------------------------------------------------------------------------------------
# Expression tokenizer and parser
# --------------------------------------------------------------------------------------

_KEYWORDS = frozenset({"and", "or", "not"})
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_NUM_RE = re.compile(r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_PCT_RE = re.compile(r"[pP](\d+(?:\.\d*)?|\.\d+)(?![A-Za-z0-9_.])")
_UNIT_AFTER_NUM_RE = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*(?:/[A-Za-z_][A-Za-z0-9_]*)?)")
_OP_RE = re.compile(r"<=|>=|==|!=|=>|=<|<>|<|>|=")
_BAD_OPS = {
    "==": "equality is not supported on continuous features; use <, <=, > or >=",
    "=": "'=' is not an operator; use <, <=, > or >=",
    "!=": "'!=' is not supported; use 'not (...)' or <, >",
    "<>": "'<>' is not supported; use 'not (...)' or <, >",
    "=>": "did you mean '>='?",
    "=<": "did you mean '<='?",
}
_CHAR_HINTS = {"&": "use 'and'", "|": "use 'or'", "!": "use 'not'", "~": "use 'not'"}
_OPS = {"<": np.less, "<=": np.less_equal, ">": np.greater, ">=": np.greater_equal}


def _caret_error(text: str, col: int, message: str) -> ParameterError:
    shown = text.translate({9: " ", 10: " ", 13: " "})
    return ParameterError(
        f"mask expression: column {col + 1}: {message}\n    {shown}\n    {' ' * col}^"
    )


class _Tok(NamedTuple):
    kind: str  # num pct name kw op lpar rpar sign eof
    text: str
    col: int
    unit: str | None = None
    unit_col: int | None = None


def _tokenize(text: str) -> list[_Tok]:
    toks: list[_Tok] = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c.isspace():
            i += 1
            continue
        m = _PCT_RE.match(text, i)
        if m:
            toks.append(_Tok("pct", m.group(0), i))
            i = m.end()
            continue
        m = _NAME_RE.match(text, i)
        if m:
            word = m.group(0)
            kind = "kw" if word.lower() in _KEYWORDS else "name"
            toks.append(_Tok(kind, word.lower() if kind == "kw" else word, i))
            i = m.end()
            continue
        m = _NUM_RE.match(text, i)
        if m:
            j = m.end()
            unit = unit_col = None
            mu = _UNIT_AFTER_NUM_RE.match(text, j)
            if mu and mu.group(1).lower() not in _KEYWORDS:
                unit, unit_col, j = mu.group(1), mu.start(1), mu.end()
            toks.append(_Tok("num", m.group(0), i, unit, unit_col))
            i = j
            continue
        m = _OP_RE.match(text, i)
        if m:
            op = m.group(0)
            if op in _BAD_OPS:
                raise _caret_error(text, i, f"operator {op!r}: {_BAD_OPS[op]}")
            toks.append(_Tok("op", op, i))
            i = m.end()
            continue
        if c in "()":
            toks.append(_Tok("lpar" if c == "(" else "rpar", c, i))
        elif c in "+-":
            toks.append(_Tok("sign", c, i))
        else:
            hint = f" ({_CHAR_HINTS[c]})" if c in _CHAR_HINTS else ""
            raise _caret_error(text, i, f"unexpected character {c!r}{hint}")
        i += 1
    toks.append(_Tok("eof", "", n))
    return toks


@dataclass(eq=False)
class _Cmp:
    feature: str
    col: int
    op: str
    value: float  # as written, in `unit` (or the feature's unit when unit is None)
    unit: str | None
    percentile: bool
    value_text: str
    value_col: int

    def text(self) -> str:
        return f"{self.feature} {self.op} {self.value_text}"


@dataclass(eq=False)
class _Ref:
    name: str
    col: int


@dataclass(eq=False)
class _Not:
    operand: object
    col: int


@dataclass(eq=False)
class _Bin:
    op: str  # "and" | "or"
    left: object
    right: object


def _describe_tok(t: _Tok) -> str:
    if t.kind == "eof":
        return "the end of the expression"
    return repr(t.text)


class _Parser:
    def __init__(self, text: str):
        self.text = text
        self.toks = _tokenize(text)
        self.pos = 0

    def peek(self) -> _Tok:
        return self.toks[self.pos]

    def take(self) -> _Tok:
        t = self.toks[self.pos]
        self.pos += 1
        return t

    def error(self, tok: _Tok, message: str) -> ParameterError:
        return _caret_error(self.text, tok.col, message)

    def parse(self):
        if self.peek().kind == "eof":
            raise ParameterError("mask expression is empty: expected e.g. 'left_wrist_height > p85'")
        node = self.or_expr()
        t = self.peek()
        if t.kind != "eof":
            if t.kind == "rpar":
                raise self.error(t, "unmatched ')'")
            raise self.error(
                t, f"expected 'and', 'or' or the end of the expression; got {_describe_tok(t)}"
            )
        return node

    def or_expr(self):
        node = self.and_expr()
        while self.peek().kind == "kw" and self.peek().text == "or":
            self.take()
            node = _Bin("or", node, self.and_expr())
        return node

    def and_expr(self):
        node = self.not_expr()
        while self.peek().kind == "kw" and self.peek().text == "and":
            self.take()
            node = _Bin("and", node, self.not_expr())
        return node

    def not_expr(self):
        t = self.peek()
        if t.kind == "kw" and t.text == "not":
            self.take()
            return _Not(self.not_expr(), t.col)
        return self.primary()

    def primary(self):
        t = self.take()
        if t.kind == "lpar":
            node = self.or_expr()
            close = self.peek()
            if close.kind != "rpar":
                raise self.error(
                    close,
                    f"expected ')' to close the '(' at column {t.col + 1}; got {_describe_tok(close)}",
                )
            self.take()
            return node
        if t.kind == "name":
            if self.peek().kind == "op":
                return self.comparison(t)
            return _Ref(t.text, t.col)
        expected = "expected a mask name, a comparison such as 'left_wrist_height > p85', or '('"
        if t.kind == "num":
            raise self.error(t, f"{expected}; got the number {t.text!r} (the feature goes on the left)")
        if t.kind == "pct":
            raise self.error(
                t, f"{expected}; got the percentile {t.text!r} (percentiles go on the right of <, >)"
            )
        if t.kind == "op":
            raise self.error(t, f"comparison {t.text!r} needs a control feature on its left")
        raise self.error(t, f"{expected}; got {_describe_tok(t)}")

    def comparison(self, feature: _Tok) -> _Cmp:
        op = self.take()
        sign = 1.0
        first = self.peek()
        if first.kind == "sign":
            self.take()
            sign = -1.0 if first.text == "-" else 1.0
        t = self.take()
        if t.kind == "pct":
            if first.kind == "sign":
                raise self.error(first, "a percentile takes no sign")
            p = float(t.text[1:])
            if not 0.0 <= p <= 100.0:
                raise self.error(t, f"percentile {t.text!r} is outside p0..p100")
            return _Cmp(feature.text, feature.col, op.text, p, None, True, t.text.lower(), t.col)
        if t.kind == "num":
            value = sign * float(t.text)
            if not math.isfinite(value):
                raise self.error(t, f"number {t.text!r} is not finite")
            if t.unit is not None and t.unit not in _UNITS:
                raise _caret_error(
                    self.text,
                    t.unit_col,
                    f"unknown unit {t.unit!r} after {t.text}; expected one of "
                    f"{', '.join(_UNITS)} (comparisons combine with 'and' / 'or')",
                )
            value_text = ("-" if sign < 0 else "") + t.text + (f" {t.unit}" if t.unit else "")
            start = first.col if first.kind == "sign" else t.col
            return _Cmp(feature.text, feature.col, op.text, value, t.unit, False, value_text, start)
        raise self.error(
            t,
            f"expected a number (e.g. 0.3, 5 cm, 20 cm/s) or a percentile (e.g. p85) after "
            f"{op.text!r}; got {_describe_tok(t)}",
        )


def _canonical(node) -> str:
    if isinstance(node, _Cmp):
        return node.text()
    if isinstance(node, _Ref):
        return node.name
    if isinstance(node, _Not):
        return f"(not {_canonical(node.operand)})"
    return f"({_canonical(node.left)} {node.op} {_canonical(node.right)})"


def _walk(node) -> Iterator[object]:
    yield node
    if isinstance(node, _Not):
        yield from _walk(node.operand)
    elif isinstance(node, _Bin):
        yield from _walk(node.left)
        yield from _walk(node.right)


@dataclass(frozen=True, eq=False)
class MaskExpression:
    """A parsed mask expression (syntax checked, names not yet resolved).

    Attributes
    ----------
    text : str
        The expression as written (stripped).
    canonical : str
        Fully parenthesised form, showing how precedence grouped it:
        ``a or b and not c`` -> ``(a or (b and (not c)))``.
    features : tuple of str
        Control features compared, in order of appearance.
    names : tuple of str
        Named masks referenced, in order of appearance.
    """

    text: str
    canonical: str
    features: tuple[str, ...]
    names: tuple[str, ...]
    _tree: object = field(repr=False)


def parse_mask_expression(text: str) -> MaskExpression:
    """Tokenize and parse a mask expression.

    Raises
    ------
    ParameterError
        On a syntax error, with the column and a caret under the offending token.
    """
    if not isinstance(text, str):
        raise ParameterError(f"mask expression: expected a string; got {type(text).__name__}")
    text = text.strip()
    tree = _Parser(text).parse()
    nodes = list(_walk(tree))
    features = tuple(dict.fromkeys(n.feature for n in nodes if isinstance(n, _Cmp)))
    names = tuple(dict.fromkeys(n.name for n in nodes if isinstance(n, _Ref)))
    return MaskExpression(text, _canonical(tree), features, names, tree)


# --------------------------------------------------------------------------------------
# Compiling expressions to bitsets
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Comparison:
    """One resolved ``FEATURE OP VALUE`` of a compiled mask.

    Attributes
    ----------
    feature : str
    op : str
        ``<``, ``<=``, ``>`` or ``>=``.
    value_text : str
        The value as written: ``p85``, ``0.3``, ``5 cm``.
    threshold : float
        The value the frames are compared with, in the feature's unit.
    unit : str or None
        The feature's unit.
    percentile : float or None
        ``p`` when the value is a database percentile.
    n_set : int
        Database frames satisfying this comparison alone.
    source : str or None
        The named mask whose definition holds this comparison, ``None`` when it is
        written in the expression itself.
    """

    feature: str
    op: str
    value_text: str
    threshold: float
    unit: str | None
    percentile: float | None
    n_set: int
    source: str | None = None

    @property
    def text(self) -> str:
        """``"left_wrist_height > p85"``."""
        return f"{self.feature} {self.op} {self.value_text}"

    def __str__(self) -> str:
        thr = f"{self.threshold:.4g}" + (f" {self.unit}" if self.unit else "")
        where = f" [in '{self.source}']" if self.source else ""
        if self.percentile is not None:
            return f"{self.text} ({self.value_text} = {thr}){where}"
        return f"{self.text} ({thr}){where}"


@dataclass(frozen=True, eq=False)
class MaskResult:
    """A compiled mask.

    Attributes
    ----------
    words : ndarray [shape=(ceil(F / 64),)], uint64
        The packed bitset (padding bits clear).
    expr : str
        The expression as written.
    thresholds : dict str -> float
        Resolved threshold of every comparison, keyed by its text
        (``"left_wrist_height > p85" -> 0.223``), in the feature's unit; includes
        comparisons inside named masks the expression used.
    n_set : int
        Number of allowed database frames.
    n_frames : int
        ``F``.
    comparisons : tuple of Comparison
        Details of every comparison (unit, percentile, frames each one allows).
    """

    words: np.ndarray
    expr: str
    thresholds: dict[str, float]
    n_set: int
    n_frames: int
    comparisons: tuple[Comparison, ...] = ()

    @property
    def fraction(self) -> float:
        """Share of database frames allowed, 0..1."""
        return self.n_set / self.n_frames if self.n_frames else 0.0

    def bits(self) -> np.ndarray:
        """Per-frame booleans ``(F,)``."""
        return unpack_bits(self.words, self.n_frames)

    def describe(self) -> str:
        """One line for logs and errors: frames allowed and resolved thresholds."""
        head = f"'{self.expr}': {self.n_set} of {self.n_frames} frames ({100 * self.fraction:.1f}%)"
        if not self.comparisons:
            return head
        return head + "; " + ", ".join(str(c) for c in self.comparisons)


def percentile_threshold(values: np.ndarray, p: float) -> float:
    """The ``p``-th percentile of ``values`` (``np.percentile``, linear, float64).

    Parameters
    ----------
    values : ndarray [shape=(F,)], float
        A control feature over the database frames (finite).
    p : float
        Percentile in ``[0, 100]``.

    Returns
    -------
    float
        In the unit of ``values``.
    """
    values = _finite_values(values, "percentile_threshold: values")
    p = _check_percentile(p, "percentile_threshold: p")
    return float(np.percentile(values, p))


def _check_percentile(p, what: str) -> float:
    if isinstance(p, (bool, np.bool_)) or not isinstance(p, (int, float, np.integer, np.floating)):
        raise ParameterError(f"{what}: expected a number in [0, 100]; got {p!r}")
    if not 0.0 <= float(p) <= 100.0:
        raise ParameterError(f"{what}: expected a number in [0, 100]; got {p}")
    return float(p)


def _finite_values(values, what: str) -> np.ndarray:
    a = np.asarray(values)
    if a.ndim != 1 or a.size == 0 or a.dtype.kind not in "fiu":
        raise ParameterError(
            f"{what}: expected a non-empty 1-D array of real numbers (F,); got {a.dtype} {a.shape}"
        )
    a = a.astype(np.float64, copy=False)
    bad = ~np.isfinite(a)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ParameterError(
            f"{what}: expected finite values; got {int(bad.sum())} NaN/inf (first at frame {first})"
        )
    return a


def _compare(values64: np.ndarray, op: str, threshold: float) -> np.ndarray:
    # values are float64 already, so the threshold is never rounded to float32 first.
    return pack_bits(_OPS[op](values64, threshold))


class _Compiler:
    """Resolves names and evaluates parsed expressions against one database's controls."""

    def __init__(self, controls, named, units, n_frames):
        if not isinstance(controls, Mapping):
            raise ParameterError(
                f"controls: expected a mapping of feature name -> (F,) array; got {type(controls).__name__}"
            )
        F = None if n_frames is None else _check_count(n_frames, "n_frames", minimum=1)
        first = None
        for name, v in controls.items():
            a = np.asarray(v)
            if a.ndim != 1 or a.dtype.kind not in "fiu":
                raise ParameterError(
                    f"controls[{name!r}]: expected a 1-D array of per-frame values (F,); "
                    f"got {a.dtype} {a.shape}"
                )
            if F is None:
                F, first = a.shape[0], name
            elif a.shape[0] != F:
                against = f"controls[{first!r}]" if first is not None else "n_frames"
                raise ParameterError(
                    f"controls[{name!r}]: expected {F} frames like {against}; got {a.shape[0]}"
                )
        if F is None:
            raise ParameterError(
                "controls is empty and n_frames is not given: cannot tell how many database frames "
                "the mask covers"
            )
        if F == 0:
            raise ParameterError("controls: the database has no frames")
        self.controls = controls
        self.F = F
        self.units = units
        self.defs = mask_definitions(controls, named)
        self._values: dict[str, np.ndarray] = {}
        self._percentiles: dict[tuple[str, float], float] = {}
        self._parsed: dict[str, MaskExpression] = {}
        self._saved: dict[str, np.ndarray] = {}
        self._cmp: dict[int, tuple[np.ndarray, Comparison]] = {}
        self._stack: list[str] = []
        # Comparisons met by the current compile(), id(node) -> (node, Comparison);
        # None while evaluating with an overridden threshold.
        self._recording: dict[int, tuple[_Cmp, Comparison]] | None = None
        self.last_nodes: list[_Cmp] = []  # comparison nodes of the last compile(), in order

    # ---- lookups -------------------------------------------------------------------
    def values(self, feature: str) -> np.ndarray:
        if feature not in self._values:
            self._values[feature] = _finite_values(self.controls[feature], f"controls[{feature!r}]")
        return self._values[feature]

    def percentile(self, feature: str, p: float) -> float:
        key = (feature, p)
        if key not in self._percentiles:
            self._percentiles[key] = float(np.percentile(self.values(feature), p))
        return self._percentiles[key]

    def threshold(self, node: _Cmp, text: str) -> tuple[float, str | None]:
        unit = feature_unit(node.feature, self.units)
        if node.percentile:
            return self.percentile(node.feature, node.value), unit
        if node.unit is None:
            return node.value, unit
        if unit is None:
            raise _caret_error(
                text,
                node.value_col,
                f"{node.feature!r} has no unit; write the value without {node.unit!r}",
            )
        dim, exp = _UNITS[node.unit]
        fdim, fexp = _UNITS[unit]
        if dim != fdim:
            raise _caret_error(
                text,
                node.value_col,
                f"unit {node.unit!r} is a {dim} but {node.feature!r} is a {fdim} in {unit}",
            )
        shift = exp - fexp
        # One correctly rounded operation: 5 cm -> 5 / 100, not 5 * 0.01.
        value = node.value * 10.0**shift if shift >= 0 else node.value / 10.0 ** (-shift)
        return value, unit

    def saved(self, name: str, value) -> np.ndarray:
        if name not in self._saved:
            arr = value if isinstance(value, np.ndarray) else np.asarray(value)
            if arr.dtype == np.bool_:
                if arr.shape != (self.F,):
                    raise ParameterError(
                        f"named[{name!r}]: expected a bool mask ({self.F},); got {arr.shape}"
                    )
                arr = pack_bits(arr)
            else:
                validate_bitset(arr, self.F, name=f"named[{name!r}]")
                if arr.ndim != 1:
                    raise ParameterError(
                        f"named[{name!r}]: expected one bitset ({n_words(self.F)},); got {arr.shape}"
                    )
            self._saved[name] = arr
        return self._saved[name]

    def parsed(self, name: str, expr: str) -> MaskExpression:
        if name not in self._parsed:
            try:
                self._parsed[name] = parse_mask_expression(expr)
            except ParameterError as e:
                raise ParameterError(f"named mask {name!r} = {expr!r}: {e}") from e
        return self._parsed[name]

    # ---- evaluation ----------------------------------------------------------------
    def evaluate(self, node, text: str, override=None) -> np.ndarray:
        """Packed words of ``node``; ``override = (cmp_node, threshold)`` swaps one threshold."""
        if isinstance(node, _Bin):
            a = self.evaluate(node.left, text, override)
            b = self.evaluate(node.right, text, override)
            return (mask_and if node.op == "and" else mask_or)(a, b)
        if isinstance(node, _Not):
            return mask_not(self.evaluate(node.operand, text, override), self.F)
        if isinstance(node, _Cmp):
            if override is not None and override[0] is node:
                return _compare(self.values(node.feature), node.op, override[1])
            return self.comparison(node, text)[0]
        return self.reference(node, text, override)

    def comparison(self, node: _Cmp, text: str) -> tuple[np.ndarray, Comparison]:
        key = id(node)
        if key not in self._cmp:
            if node.feature not in self.controls:
                if node.feature in self.defs:
                    raise _caret_error(
                        text,
                        node.col,
                        f"{node.feature!r} is a named mask, not a control feature; use it alone "
                        f"(e.g. '{node.feature} and ...'), or compare a feature: "
                        f"{_known(self.controls)}",
                    )
                raise _caret_error(
                    text,
                    node.col,
                    f"unknown control feature {node.feature!r}"
                    f"{_did_you_mean(node.feature, self.controls)}; known features: "
                    f"{_known(self.controls)}",
                )
            threshold, unit = self.threshold(node, text)
            words = _compare(self.values(node.feature), node.op, threshold)
            cmp = Comparison(
                feature=node.feature,
                op=node.op,
                value_text=node.value_text,
                threshold=float(threshold),
                unit=unit,
                percentile=node.value if node.percentile else None,
                n_set=count_bits(words),
                source=self._stack[-1] if self._stack else None,
            )
            self._cmp[key] = (words, cmp)
        if self._recording is not None:
            self._recording.setdefault(key, (node, self._cmp[key][1]))
        return self._cmp[key]

    def reference(self, node: _Ref, text: str, override) -> np.ndarray:
        name = node.name
        if name not in self.defs:
            if name in self.controls:
                raise _caret_error(
                    text,
                    node.col,
                    f"{name!r} is a control feature, not a mask: compare it with a value, "
                    f"e.g. '{name} > p{HIGH_PERCENTILE:g}'",
                )
            raise _caret_error(
                text,
                node.col,
                f"unknown mask name {name!r}{_did_you_mean(name, list(self.defs) + list(self.controls))}; "
                f"known names: {_known(self.defs)}",
            )
        definition = self.defs[name]
        if not isinstance(definition, str):
            return self.saved(name, definition)
        if name in self._stack:
            cycle = " -> ".join(self._stack[self._stack.index(name) :] + [name])
            raise ParameterError(f"named mask {name!r} refers to itself: {cycle}")
        parsed = self.parsed(name, definition)
        self._stack.append(name)
        try:
            return self.evaluate(parsed._tree, parsed.text, override)
        except ParameterError as e:
            if str(e).startswith("named mask "):
                raise
            raise ParameterError(f"named mask {name!r} = {definition!r}: {e}") from e
        finally:
            self._stack.pop()

    def compile(self, parsed: MaskExpression) -> MaskResult:
        self._recording = {}
        try:
            words = self.evaluate(parsed._tree, parsed.text)
            recorded = self._recording
        finally:
            self._recording = None
        self.last_nodes = [node for node, _ in recorded.values()]
        # The words may be a cached comparison or the caller's saved mask: never alias them.
        words = words.copy()
        comparisons = tuple(c for _, c in recorded.values())
        return MaskResult(
            words=words,
            expr=parsed.text,
            thresholds={c.text: c.threshold for c in comparisons},
            n_set=count_bits(words),
            n_frames=self.F,
            comparisons=comparisons,
        )


def _did_you_mean(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=2, cutoff=0.6)
    if not close:
        return ""
    return " (did you mean " + " or ".join(repr(c) for c in close) + "?)"


def _known(names) -> str:
    names = sorted(names)
    return ", ".join(names) if names else "(none)"


def compile_mask(
    expr: str | MaskExpression,
    *,
    controls: Mapping[str, np.ndarray],
    named: Mapping[str, object] | None = None,
    units: Mapping[str, str | None] | None = None,
    n_frames: int | None = None,
) -> MaskResult:
    """Compile a mask expression into a packed bitset over the database frames.

    Parameters
    ----------
    expr : str or MaskExpression
        See the module docstring for the grammar, e.g.
        ``"left_wrist_speed < p15 and symmetric"``.
    controls : mapping str -> ndarray [shape=(F,)], float
        Per-frame control features of the database (finite), in their base units
        (metres, m/s).
    named : mapping str -> str or ndarray, optional
        Extra named masks: expressions, saved packed bitsets ``(ceil(F / 64),)``
        uint64, or bool ``(F,)``. They extend and override :data:`DEFAULT_NAMED`.
    units : mapping str -> str or None, optional
        Base unit of features not in :data:`CONTROL_UNITS` (``None``: unitless).
    n_frames : int, optional
        ``F``; needed only when ``controls`` is empty.

    Returns
    -------
    MaskResult

    Raises
    ------
    ParameterError
        Syntax errors (column and caret), unknown features or names (with the
        known ones and the closest match), unit mismatches, non-finite controls,
        cyclic named masks.
    """
    parsed = expr if isinstance(expr, MaskExpression) else parse_mask_expression(expr)
    return _Compiler(controls, named, units, n_frames).compile(parsed)


def percentile_masks(
    controls: Mapping[str, np.ndarray],
    *,
    low: float = LOW_PERCENTILE,
    high: float = HIGH_PERCENTILE,
) -> dict[str, MaskResult]:
    """The ``<feature>_high`` / ``<feature>_low`` masks of every control feature.

    Meant for the database build, which stores them so synthesis can pass them
    back as saved ``named`` masks.

    Parameters
    ----------
    controls : mapping str -> ndarray [shape=(F,)]
    low, high : float
        Percentiles, ``0 <= low <= high <= 100``.

    Returns
    -------
    dict str -> MaskResult
        Keys ``f"{feature}_high"`` (``feature > p{high}``) and ``f"{feature}_low"``
        (``feature < p{low}``), in the order of ``controls``.
    """
    low = _check_percentile(low, "percentile_masks: low")
    high = _check_percentile(high, "percentile_masks: high")
    if low > high:
        raise ParameterError(f"percentile_masks: expected low <= high; got low={low:g}, high={high:g}")
    comp = _Compiler(controls, None, None, None)  # checks and converts each feature once
    out = {}
    for f in controls:
        out[f"{f}_high"] = comp.compile(parse_mask_expression(f"{f} > p{high:g}"))
        out[f"{f}_low"] = comp.compile(parse_mask_expression(f"{f} < p{low:g}"))
    return out


# --------------------------------------------------------------------------------------
# "No candidates": nearest percentile that leaves some
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PercentileSuggestion:
    """The nearest percentile that leaves candidates.

    Attributes
    ----------
    percentile : float
        ``p'``.
    threshold : float
        The value at ``p'``, in the feature's unit.
    n_set : int
        Frames allowed with ``p'`` (after intersecting with ``within`` / the rest
        of the expression).
    """

    percentile: float
    threshold: float
    n_set: int


def _outward(p: float, step: float, *, down_first: bool = True) -> list[float]:
    """``p``, then ``p -/+ step``, ``p -/+ 2 step``, ... clipped to [0, 100], each value once."""
    order = [p]
    seen = {p}
    for k in range(1, int(math.ceil(100.0 / step)) + 2):
        pair = (p - k * step, p + k * step)
        for q in pair if down_first else pair[::-1]:
            q = min(100.0, max(0.0, q))
            if q not in seen:
                seen.add(q)
                order.append(q)
    return order


def _default_accept(words: np.ndarray) -> bool:
    return bool(np.any(words))


def closest_percentile_with_candidates(
    values: np.ndarray,
    op: str,
    p: float,
    *,
    within: np.ndarray | None = None,
    accept: Callable[[np.ndarray], bool] | None = None,
    step: float = 1.0,
) -> PercentileSuggestion | None:
    """Nearest percentile ``p'`` for which ``values OP percentile(values, p')`` leaves candidates.

    Searches outward from ``p`` in steps of ``step`` (``p, p-1, p+1, p-2, ...`` for
    ``>``; ``p, p+1, p-1, ...`` for ``<``; clipped to ``[0, 100]``), so a ``> p85`` that emptied a step can be reported
    as "``> p80`` would leave 42 frames".

    Parameters
    ----------
    values : ndarray [shape=(F,)], float
        The control feature over the database frames.
    op : {"<", "<=", ">", ">="}
    p : float
        The percentile that left no candidates.
    within : ndarray [shape=(ceil(F / 64),)], uint64, optional
        The rest of the constraint (other terms of an ``and``, a keyword
        sub-database): the comparison is intersected with it.
    accept : callable, optional
        ``accept(words) -> bool`` decides whether a mask leaves candidates (e.g.
        ``lambda w: candidate_counts(w, ...).sum() > 0``); the default is "any
        frame set".
    step : float
        Percentile increment, > 0.

    Returns
    -------
    PercentileSuggestion or None
        ``None`` when no percentile in ``[0, 100]`` leaves candidates. If ``p``
        itself does, it is returned.
    """
    values = _finite_values(values, "closest_percentile_with_candidates: values")
    if op not in _OPS:
        raise ParameterError(
            f"closest_percentile_with_candidates: op: expected one of {', '.join(_OPS)}; got {op!r}"
        )
    p = _check_percentile(p, "closest_percentile_with_candidates: p")
    if not isinstance(step, (int, float)) or not step > 0 or not math.isfinite(step):
        raise ParameterError(f"closest_percentile_with_candidates: step: expected a number > 0; got {step!r}")
    if within is not None:
        validate_bitset(within, values.shape[0], name="closest_percentile_with_candidates: within")
    accept = accept or _default_accept
    # Lowering p loosens '>' and tightening a mask that left nothing cannot help, so
    # the loosening side goes first at each distance (it matters only for an accept()
    # that is not monotone).
    ps = _outward(p, float(step), down_first=op in (">", ">="))
    thresholds = np.percentile(values, ps)  # one sort for every candidate percentile
    for q, thr in zip(ps, thresholds):
        words = _compare(values, op, float(thr))
        if within is not None:
            words = mask_and(words, within)
        if accept(words):
            return PercentileSuggestion(float(q), float(thr), count_bits(words))
    return None


@dataclass(frozen=True)
class Relaxation:
    """A way to make an expression leave candidates by moving one percentile.

    Attributes
    ----------
    comparison : Comparison
        The comparison as compiled (its percentile and threshold).
    suggestion : PercentileSuggestion
        The nearest percentile for it, every other term unchanged.
    """

    comparison: Comparison
    suggestion: PercentileSuggestion

    def __str__(self) -> str:
        c, s = self.comparison, self.suggestion
        unit = f" {c.unit}" if c.unit else ""
        where = f" (in '{c.source}')" if c.source else ""
        return (
            f"'{c.feature} {c.op} p{s.percentile:g}'{where} instead of '{c.text}' "
            f"(threshold {s.threshold:.4g}{unit}) would leave {s.n_set} frames"
        )


def suggest_percentiles(
    expr: str | MaskExpression,
    *,
    controls: Mapping[str, np.ndarray],
    named: Mapping[str, object] | None = None,
    units: Mapping[str, str | None] | None = None,
    accept: Callable[[np.ndarray], bool] | None = None,
    within: np.ndarray | None = None,
    step: float = 1.0,
) -> list[Relaxation]:
    """For each percentile comparison of ``expr``, the nearest percentile that leaves candidates.

    Every percentile comparison (including those inside named expressions such as
    ``symmetric``) is moved on its own, outward from its ``p`` in steps of
    ``step``, with the rest of the expression unchanged; because ``not`` may flip
    which direction loosens, both directions are tried.

    Parameters
    ----------
    expr, controls, named, units
        As in :func:`compile_mask`.
    accept : callable, optional
        ``accept(words) -> bool``; default "any frame set".
    within : ndarray [shape=(ceil(F / 64),)], uint64, optional
        Intersected with the expression's mask before ``accept``.
    step : float

    Returns
    -------
    list of Relaxation
        In order of appearance; comparisons that no percentile rescues are left out
        (an empty list means no single percentile change helps).
    """
    parsed = expr if isinstance(expr, MaskExpression) else parse_mask_expression(expr)
    comp = _Compiler(controls, named, units, None)
    result = comp.compile(parsed)  # resolves every name and records the comparisons
    if within is not None:
        validate_bitset(within, comp.F, name="suggest_percentiles: within")
    if not isinstance(step, (int, float)) or not step > 0 or not math.isfinite(step):
        raise ParameterError(f"suggest_percentiles: step: expected a number > 0; got {step!r}")
    accept = accept or _default_accept
    out = []
    for node, c in zip(comp.last_nodes, result.comparisons):
        if c.percentile is None:
            continue
        ps = _outward(c.percentile, float(step))
        for q, thr in zip(ps, np.percentile(comp.values(c.feature), ps)):
            words = comp.evaluate(parsed._tree, parsed.text, override=(node, float(thr)))
            if within is not None:
                words = mask_and(words, within)
            if accept(words):
                out.append(Relaxation(c, PercentileSuggestion(float(q), float(thr), count_bits(words))))
                break
    return out


# --------------------------------------------------------------------------------------
# Control schedules
# --------------------------------------------------------------------------------------


class ScheduleItem(NamedTuple):
    """One ``START-END: EXPRESSION`` of a control schedule.

    Attributes
    ----------
    start_s : float
        Start in seconds of output time (0 for an open start such as ``-12:``).
    end_s : float or None
        End in seconds, exclusive; ``None`` for an open end (``24-:``).
    expr : str
        The mask expression.
    """

    start_s: float
    end_s: float | None
    expr: str


_SECONDS_RE = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*s?")


def _fmt_s(x: float | None) -> str:
    return "the end" if x is None else f"{x:g} s"


def _item_error(k: int, label: str, message: str) -> ParameterError:
    return ParameterError(f"control schedule item {k} ({label!r}): {message}")


def _parse_range(rng: str, k: int, label: str) -> tuple[float, float | None]:
    if rng.count("-") != 1:
        raise _item_error(
            k,
            label,
            f"range {rng!r}: expected START-END in seconds, either end may be left open "
            "(e.g. '0-12', '-12', '24-')",
        )
    a, b = (part.strip() for part in rng.split("-"))
    bounds = []
    for which, txt in (("start", a), ("end", b)):
        if not txt:
            bounds.append(None)
            continue
        if not _SECONDS_RE.fullmatch(txt):
            raise _item_error(k, label, f"{which} {txt!r} is not a number of seconds")
        bounds.append(float(txt.rstrip("s ")))
    start, end = bounds
    return (0.0 if start is None else start), end


def _schedule_items(schedule) -> list[tuple[int, str, ScheduleItem]]:
    """Validated ``(written position, label, item)``, sorted by start time."""
    items: list[tuple[int, str, ScheduleItem]] = []
    if isinstance(schedule, str):
        parts = [p.strip() for p in re.split(r"[;\n]", schedule)]
        for k, label in enumerate((p for p in parts if p), start=1):
            if ":" not in label:
                raise _item_error(
                    k, label, "expected 'START-END: EXPRESSION', e.g. '0-12: left_wrist_high'; no ':' found"
                )
            rng, expr = label.split(":", 1)
            start, end = _parse_range(rng.strip(), k, label)
            items.append((k, label, ScheduleItem(start, end, expr.strip())))
    elif isinstance(schedule, Sequence):
        for k, entry in enumerate(schedule, start=1):
            if not isinstance(entry, (tuple, list)) or len(entry) != 3:
                raise ParameterError(
                    f"control schedule item {k}: expected (start_s, end_s or None, expression); got {entry!r}"
                )
            start, end, expr = entry
            label = f"{'' if start is None else f'{start:g}'}-{'' if end is None else f'{end:g}'}: {expr}"
            for which, v in (("start_s", start), ("end_s", end)):
                if v is not None and (
                    isinstance(v, (bool, np.bool_))
                    or not isinstance(v, (int, float, np.integer, np.floating))
                    or not math.isfinite(v)
                    or v < 0
                ):
                    raise _item_error(k, label, f"{which}: expected seconds >= 0 or None; got {v!r}")
            if not isinstance(expr, str):
                raise _item_error(k, label, f"expression: expected a string; got {type(expr).__name__}")
            start = 0.0 if start is None else float(start)
            end = None if end is None else float(end)
            items.append((k, label, ScheduleItem(start, end, expr.strip())))
    else:
        raise ParameterError(
            f"control schedule: expected a string such as '0-12: left_wrist_high; 12-: symmetric' "
            f"or a list of (start_s, end_s, expression); got {type(schedule).__name__}"
        )
    if not items:
        raise ParameterError("control schedule is empty: expected e.g. '0-12: left_wrist_high'")
    for k, label, item in items:
        if item.end_s is not None and item.end_s <= item.start_s:
            raise _item_error(
                k, label, f"end {_fmt_s(item.end_s)} is not after start {_fmt_s(item.start_s)}"
            )
        if not item.expr:
            raise _item_error(k, label, "no mask expression after ':'")
        try:
            parse_mask_expression(item.expr)
        except ParameterError as e:
            raise _item_error(k, label, str(e)) from e
    items.sort(key=lambda x: x[2].start_s)
    for (k1, l1, a), (k2, l2, b) in zip(items, items[1:]):
        if a.end_s is None or a.end_s > b.start_s:
            ends = [e for e in (a.end_s, b.end_s) if e is not None]
            overlap_end = min(ends) if ends else None
            first, second = sorted([(k1, l1), (k2, l2)])
            raise ParameterError(
                f"control schedule items {first[0]} ({first[1]!r}) and {second[0]} ({second[1]!r}) "
                f"overlap from {_fmt_s(b.start_s)} to {_fmt_s(overlap_end)} "
                "(ranges are [start, end), so '0-12' and '12-24' do not overlap)"
            )
    return items


def parse_schedule(text: str) -> list[ScheduleItem]:
    """Parse a control schedule such as ``"0-12: left_wrist_high; 12-: symmetric"``.

    Items are separated by ``;`` or newlines and written ``START-END: EXPRESSION``
    with times in seconds of output (an optional ``s`` suffix is allowed). Either
    end may be left open: ``-12:`` runs from 0, ``24-:`` to the end of the output,
    ``-:`` covers everything. Ranges are half-open ``[start, end)`` and may leave
    gaps (unconstrained) but may not overlap.

    Returns
    -------
    list of ScheduleItem
        ``(start_s, end_s or None, expr)``, sorted by start time.

    Raises
    ------
    ParameterError
        Naming the item (its position as written and its text): missing ``:``,
        malformed or reversed range, empty or syntactically wrong expression,
        overlapping items.
    """
    if not isinstance(text, str):
        raise ParameterError(f"control schedule: expected a string; got {type(text).__name__}")
    return [item for _, _, item in _schedule_items(text)]


@dataclass(frozen=True, eq=False)
class ScheduleBitsets:
    """Per-step masks for a search, and what each step is constrained by.

    Unpacks as ``bitsets, labels = schedule_bitsets(...)``.

    Attributes
    ----------
    bitsets : ndarray [shape=(steps, ceil(F / 64))], uint64, C-contiguous
        Row ``i`` is the allowed-frame bitset of search step ``i`` (all ones for an
        unconstrained step).
    labels : list of (str or None)
        The schedule expression constraining each step, ``None`` when unconstrained.
    step_start : ndarray [shape=(steps,)], int64
        First output frame ``t = i * step`` of each step.
    step_len : ndarray [shape=(steps,)], int64
        Window length ``n = min(step, n_out_frames - t)``.
    fps : float
        Output frame rate.
    masks : dict str -> MaskResult
        The compiled mask of each schedule expression (thresholds for reports).
    """

    bitsets: np.ndarray
    labels: list
    step_start: np.ndarray
    step_len: np.ndarray
    fps: float
    masks: dict

    def __iter__(self):
        return iter((self.bitsets, self.labels))

    @property
    def n_steps(self) -> int:
        return int(self.bitsets.shape[0])

    def step_time_s(self, i: int) -> float:
        """Start time of step ``i`` in seconds of output."""
        return float(self.step_start[i]) / self.fps

    def describe_step(self, i: int) -> str:
        """E.g. ``"step 7 (t=3.73 s), control 'left_wrist_speed < p15 and symmetric'"``."""
        if not 0 <= i < self.n_steps:
            raise ParameterError(f"describe_step: step index {i} is outside 0..{self.n_steps - 1}")
        head = f"step {i} (t={self.step_time_s(i):.2f} s)"
        label = self.labels[i]
        return f"{head}, no control" if label is None else f"{head}, control '{label}'"


def schedule_bitsets(
    schedule: str | Sequence[tuple],
    *,
    controls: Mapping[str, np.ndarray],
    named: Mapping[str, object] | None = None,
    n_out_frames: int,
    n_steps: int | None = None,
    step: int = 8,
    fps: float = 15.0,
    units: Mapping[str, str | None] | None = None,
    n_frames: int | None = None,
) -> ScheduleBitsets:
    """One allowed-frame bitset per search step from a control schedule.

    Search step ``i`` writes output frames ``t .. t+n-1`` with ``t = i * step`` and
    ``n = min(step, n_out_frames - t)``, i.e. the time span ``[t/fps, (t+n)/fps)``.
    **A step takes the control active at the centre of its span**, ``(t + n/2)/fps``
    (ranges half-open, so a boundary exactly at a centre goes to the later item).
    A schedule boundary therefore switches the control at the step boundary
    nearest to it (up to half a step early or late), and a step cut by a
    boundary follows the side that covers more of it, including a gap: a step
    mostly outside every range is unconstrained (all ones, label None). An item
    that contains no step centre would constrain nothing and is an error.

    Parameters
    ----------
    schedule : str or sequence of (start_s, end_s or None, expr)
        See :func:`parse_schedule`.
    controls, named, units, n_frames
        As in :func:`compile_mask`.
    n_out_frames : int
        ``T``, output frames of the synthesis.
    n_steps : int, optional
        If given, must equal ``ceil(T / step)`` (a consistency check).
    step : int
        Search window ``N`` in frames.
    fps : float
        Output frame rate.

    Returns
    -------
    ScheduleBitsets
        ``bitsets (steps, ceil(F / 64))`` uint64 and per-step ``labels``; also the
        step times and the compiled masks.

    Raises
    ------
    ParameterError
        Any schedule error of :func:`parse_schedule`; an item that contains no
        step centre (shorter than a step, or starting after the output) so it
        would constrain nothing; compile errors, naming the item.
    """
    items = _schedule_items(schedule)
    T = _check_count(n_out_frames, "n_out_frames", minimum=1)
    N = _check_count(step, "step", minimum=1)
    if (
        isinstance(fps, (bool, np.bool_))
        or not isinstance(fps, (int, float, np.integer, np.floating))
        or not math.isfinite(fps)
        or fps <= 0
    ):
        raise ParameterError(f"fps: expected a frame rate > 0; got {fps!r}")
    fps = float(fps)
    S = -(-T // N)
    if n_steps is not None and _check_count(n_steps, "n_steps", minimum=1) != S:
        raise ParameterError(
            f"n_steps: expected ceil(n_out_frames / step) = ceil({T} / {N}) = {S}; got {n_steps}"
        )
    t = np.arange(S, dtype=np.int64) * N
    n = np.minimum(N, T - t)
    centre = t + n / 2.0  # in output frames, exact
    owner = np.full(S, -1, dtype=np.int64)
    for idx, (k, label, item) in enumerate(items):
        # Compare in frames; rounding to 1e-9 frame keeps decimal seconds that land on
        # a centre (0.2 s * 15 fps) from drifting to either side of it.
        a = round(item.start_s * fps, 9)
        b = math.inf if item.end_s is None else round(item.end_s * fps, 9)
        sel = (centre >= a) & (centre < b)
        if not sel.any():
            raise _item_error(k, label, _no_step_message(a, b, centre, N, fps, T))
        owner[sel] = idx
    comp = _Compiler(controls, named, units, n_frames)
    masks: dict[str, MaskResult] = {}
    for k, label, item in items:
        if item.expr not in masks:
            try:
                masks[item.expr] = comp.compile(parse_mask_expression(item.expr))
            except ParameterError as e:
                raise _item_error(k, label, str(e)) from e
    bitsets = np.empty((S, n_words(comp.F)), dtype=np.uint64)
    bitsets[owner < 0] = full_mask(comp.F)
    for idx, (_, _, item) in enumerate(items):
        bitsets[owner == idx] = masks[item.expr].words
    labels = [None if o < 0 else items[o][2].expr for o in owner.tolist()]
    return ScheduleBitsets(bitsets, labels, t, n.astype(np.int64), fps, masks)


def _no_step_message(a: float, b: float, centre: np.ndarray, N: int, fps: float, T: int) -> str:
    why = (
        f"each search step of {N} frames ({N / fps:.3g} s at {fps:g} fps) takes the control "
        "active at its centre"
    )
    if a >= centre[-1]:
        return (
            f"starts at {a / fps:g} s, after the centre of the last search step "
            f"({centre[-1] / fps:.3g} s; the output is {T / fps:.3g} s long), so it would "
            f"constrain nothing ({why})"
        )
    before = np.flatnonzero(centre < a)
    after = np.flatnonzero(centre >= b)
    near = []
    if before.size:
        near.append(f"{centre[before[-1]] / fps:.3g} s (step {before[-1]})")
    if after.size:
        near.append(f"{centre[after[0]] / fps:.3g} s (step {after[0]})")
    return (
        f"contains no search-step centre, so it would constrain nothing: {why}; the nearest "
        f"centres are {' and '.join(near)}"
    )
