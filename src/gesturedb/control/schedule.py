"""Control schedules: mask expressions over time ranges of the output, one bitset per search step.
"""
from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from gesturedb.control.bitsets import StepBitsets, _check_count, full_mask
from gesturedb.control.compile import MaskResult, _Compiler
from gesturedb.control.expression import parse_mask_expression
from gesturedb.errors import ParameterError

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
    steps : StepBitsets
        The allowed-frame bitset of every search step (all ones for an
        unconstrained step), each distinct row stored once.
    bitsets : ndarray [shape=(steps, ceil(F / 64))], uint64, C-contiguous
        The same as one array, built on first use (``steps x F / 8`` bytes).
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

    steps: StepBitsets
    labels: list
    step_start: np.ndarray
    step_len: np.ndarray
    fps: float
    masks: dict

    @functools.cached_property
    def bitsets(self) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(self.steps))

    def __iter__(self):
        return iter((self.bitsets, self.labels))

    @property
    def n_steps(self) -> int:
        return len(self.steps)

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
    # row 0: unconstrained, then one row per distinct expression
    row_of = {e: 1 + i for i, e in enumerate(masks)}
    rows = np.stack([full_mask(comp.F)] + [m.words for m in masks.values()])
    of_step = np.array([0 if o < 0 else row_of[items[o][2].expr] for o in owner.tolist()], np.int64)
    labels = [None if o < 0 else items[o][2].expr for o in owner.tolist()]
    return ScheduleBitsets(StepBitsets(rows, of_step), labels, t, n.astype(np.int64), fps, masks)


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

