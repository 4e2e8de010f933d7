"""When a control leaves a step no candidate: the nearest percentile that leaves some.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from gesturedb.control.bitsets import count_bits, mask_and, validate_bitset
from gesturedb.control.compile import Comparison, _check_percentile, _compare, _Compiler, _finite_values
from gesturedb.control.expression import _OPS, MaskExpression, parse_mask_expression
from gesturedb.errors import ParameterError

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


