"""Compiling mask expressions to bitsets over the database's control features.

Thresholds and units (percentiles over all database frames, float64 comparisons),
the predefined named masks and the ``<feature>_high`` / ``<feature>_low`` masks.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from gesturedb.control.bitsets import (
    _check_count,
    count_bits,
    mask_and,
    mask_not,
    mask_or,
    n_words,
    pack_bits,
    unpack_bits,
    validate_bitset,
)
from gesturedb.control.expression import (
    _KEYWORDS,
    _NAME_RE,
    _OPS,
    _PCT_RE,
    _UNITS,
    MaskExpression,
    _Bin,
    _caret_error,
    _Cmp,
    _Not,
    _Ref,
    parse_mask_expression,
)
from gesturedb.errors import ParameterError, echo, echo_list

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
                f"units[{echo(feature)}]: expected one of {', '.join(_UNITS)} or None; got {echo(unit)}"
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
        for k, _v in named.items():
            if not isinstance(k, str) or not _NAME_RE.fullmatch(k) or k.lower() in _KEYWORDS:
                raise ParameterError(
                    f"named: mask names must be identifiers (letters, digits, '_') other than "
                    f"and/or/not; got {echo(k)}"
                )
            if _PCT_RE.fullmatch(k):
                raise ParameterError(f"named: {echo(k)} reads as a percentile; choose another mask name")
        defs.update(named)
    return defs


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
        raise ParameterError(f"{what}: expected a number in [0, 100]; got {echo(p)}")
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
            # an h5py dataset is checked by its shape and dtype and read only when an
            # expression uses it (Database.control_datasets)
            a = v if all(hasattr(v, x) for x in ("shape", "ndim", "dtype")) else np.asarray(v)
            if a.ndim != 1 or a.dtype.kind not in "fiu":
                raise ParameterError(
                    f"controls[{echo(name)}]: expected a 1-D array of per-frame values (F,); "
                    f"got {a.dtype} {a.shape}"
                )
            if F is None:
                F, first = a.shape[0], name
            elif a.shape[0] != F:
                against = f"controls[{echo(first)}]" if first is not None else "n_frames"
                raise ParameterError(
                    f"controls[{echo(name)}]: expected {F} frames like {against}; got {a.shape[0]}"
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
        # the nodes behind the keys of _cmp, kept alive: a freed node's id can be
        # reused by a node of a later expression, which would then get this
        # node's cached bits (seen as wrong default masks in built databases)
        self._cmp_nodes: dict[int, _Cmp] = {}
        self._stack: list[str] = []
        # Comparisons met by the current compile(), id(node) -> (node, Comparison);
        # None while evaluating with an overridden threshold.
        self._recording: dict[int, tuple[_Cmp, Comparison]] | None = None
        self.last_nodes: list[_Cmp] = []  # comparison nodes of the last compile(), in order

    # ---- lookups -------------------------------------------------------------------
    def values(self, feature: str) -> np.ndarray:
        if feature not in self._values:
            self._values[feature] = _finite_values(self.controls[feature], f"controls[{echo(feature)}]")
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
                f"{echo(node.feature)} has no unit; write the value without {echo(node.unit)}",
            )
        dim, exp = _UNITS[node.unit]
        fdim, fexp = _UNITS[unit]
        if dim != fdim:
            raise _caret_error(
                text,
                node.value_col,
                f"unit {echo(node.unit)} is a {dim} but {echo(node.feature)} is a {fdim} in {unit}",
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
                        f"named[{echo(name)}]: expected a bool mask ({self.F},); got {arr.shape}"
                    )
                arr = pack_bits(arr)
            else:
                validate_bitset(arr, self.F, name=f"named[{echo(name)}]")
                if arr.ndim != 1:
                    raise ParameterError(
                        f"named[{echo(name)}]: expected one bitset ({n_words(self.F)},); got {arr.shape}"
                    )
            self._saved[name] = arr
        return self._saved[name]

    def parsed(self, name: str, expr: str) -> MaskExpression:
        if name not in self._parsed:
            try:
                self._parsed[name] = parse_mask_expression(expr)
            except ParameterError as e:
                raise ParameterError(f"named mask {echo(name)} = {echo(expr)}: {e}") from e
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
                        f"{echo(node.feature)} is a named mask, not a control feature; use it alone "
                        f"(e.g. '{node.feature} and ...'), or compare a feature: "
                        f"{_known(self.controls)}",
                    )
                raise _caret_error(
                    text,
                    node.col,
                    f"unknown control feature {echo(node.feature)}"
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
            self._cmp_nodes[key] = node
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
                    f"{echo(name)} is a control feature, not a mask: compare it with a value, "
                    f"e.g. '{name} > p{HIGH_PERCENTILE:g}'",
                )
            raise _caret_error(
                text,
                node.col,
                f"unknown mask name {echo(name)}{_did_you_mean(name, list(self.defs) + list(self.controls))}; "
                f"known names: {_known(self.defs)}",
            )
        definition = self.defs[name]
        if not isinstance(definition, str):
            return self.saved(name, definition)
        if name in self._stack:
            cycle = " -> ".join(self._stack[self._stack.index(name) :] + [name])
            raise ParameterError(f"named mask {echo(name)} refers to itself: "
                                 f"{echo_list(cycle.split(' -> ')).replace(', ', ' -> ')}")
        parsed = self.parsed(name, definition)
        self._stack.append(name)
        try:
            return self.evaluate(parsed._tree, parsed.text, override)
        except ParameterError as e:
            if str(e).startswith("named mask "):
                raise
            raise ParameterError(f"named mask {echo(name)} = {echo(definition)}: {e}") from e
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
    return " (did you mean " + " or ".join(echo(c) for c in close) + "?)"


#: known names a message lists before it counts the rest
MESSAGE_NAMES = 60


def _known(names) -> str:
    names = sorted(names)
    return echo_list(names, MESSAGE_NAMES) if names else "(none)"


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


