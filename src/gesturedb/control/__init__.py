"""Control: packed frame bitsets, the mask expression language, schedules.

Pure numpy over arrays it is given: nothing here reads or writes a file, so the
database build (which precomputes the default masks) can sit above it. Keyword
sub-databases, which live in the database file, are in :mod:`gesturedb.db.keywords`.

=================  ====================================================
``bitsets``        packed uint64 frame bitsets and their algebra
``expression``     tokenizer and parser of the mask language (no eval)
``compile``        expressions -> bitsets; units, percentiles, named masks
``suggest``        the nearest percentile that leaves a step candidates
``schedule``       time ranges of the output -> one bitset per search step
=================  ====================================================


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

from gesturedb.control.bitsets import (  # noqa: F401
    StepBitsets,
    candidate_counts,
    count_bits,
    empty_mask,
    full_mask,
    mask_and,
    mask_not,
    mask_or,
    n_words,
    pack_bits,
    slice_bits,
    unpack_bits,
    validate_bitset,
)
from gesturedb.control.compile import (  # noqa: F401
    CONTROL_UNITS,
    DEFAULT_NAMED,
    HIGH_PERCENTILE,
    LOW_PERCENTILE,
    Comparison,
    MaskResult,
    compile_mask,
    feature_unit,
    mask_definitions,
    percentile_masks,
    percentile_threshold,
)
from gesturedb.control.expression import (  # noqa: F401
    MaskExpression,
    parse_mask_expression,
)
from gesturedb.control.schedule import (  # noqa: F401
    ScheduleBitsets,
    ScheduleItem,
    parse_schedule,
    schedule_bitsets,
)
from gesturedb.control.suggest import (  # noqa: F401
    PercentileSuggestion,
    Relaxation,
    closest_percentile_with_candidates,
    suggest_percentiles,
)

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
    "StepBitsets",
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
    "slice_bits",
    "suggest_percentiles",
    "unpack_bits",
    "validate_bitset",
]
