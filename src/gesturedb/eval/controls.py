"""Controlled synthesis (Habibie et al. 2022, Table 2): does each control move what it promises?

For left wrist high/low (``left_wrist_height`` above its 85th / below its 15th
database percentile), fast/slow (``left_wrist_speed``) and asymmetric/symmetric
(``height_asymmetry``) the same speech is synthesized once without control and
once per control; the controlled variable is recomputed on the synthesized joint
positions with the database's own code
(:func:`gesturedb.features.controls.control_features`) and its mean and standard
deviation over the output frames are reported next to the resolved threshold
and the unconstrained synthesis. Two checks per row: *direction* (the controlled
mean moved past the unconstrained mean in the requested direction) and *no
freeze* (the controlled standard deviation is at least ``min_std_ratio`` of a
reference spread: control must not pin the hand, the failure the paper reports
for MoGlow). By default *no freeze* compares with the standard deviation of the
database frames the mask allows (``freeze_reference="allowed"``): the low and
symmetric ends of these features are physically narrow (a hanging arm), so their
natural spread is a small fraction of the unconstrained one; the paper's own k-NN
rows (2.1 cm for wrist low, 1.2 cm for symmetric) would fail a comparison with
the unconstrained spread. ``freeze_reference="unconstrained"`` selects that
stricter comparison; both ratios are always reported.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from gesturedb import control
from gesturedb.errors import InputFileError, ParameterError, SearchError
from gesturedb.eval.common import _fmt, _read_samples, _stats, feature_joint_indices, json_clean
from gesturedb.eval.texttable import text_table
from gesturedb.features.controls import control_features
from gesturedb.synth.matching import Searcher
from gesturedb.synth.options import SearchOptions

#: Default share of the unconstrained standard deviation a controlled synthesis must keep.
DEFAULT_MIN_STD_RATIO = 0.3

@dataclass(frozen=True)
class ControlCase:
    """One row of Table 2: a control and the variable it should move.

    Attributes
    ----------
    name : str
        Row label (``"wrist high"``).
    feature : str
        Control feature measured on the output (a key of ``db.controls``).
    expr : str
        Mask expression handed to the search (``"left_wrist_height > p85"``).
    direction : int
        +1 when the control should raise the feature, -1 when it should lower it.
    """

    name: str
    feature: str
    expr: str
    direction: int


#: The six controls of Habibie et al. 2022, Table 2, in the paper's order.
TABLE2_CASES: tuple[ControlCase, ...] = (
    ControlCase("wrist high", "left_wrist_height", "left_wrist_height > p85", +1),
    ControlCase("wrist low", "left_wrist_height", "left_wrist_height < p15", -1),
    ControlCase("wrist fast", "left_wrist_speed", "left_wrist_speed > p85", +1),
    ControlCase("wrist slow", "left_wrist_speed", "left_wrist_speed < p15", -1),
    ControlCase("asymmetric", "height_asymmetry", "height_asymmetry > p85", +1),
    ControlCase("symmetric", "height_asymmetry", "height_asymmetry < p15", -1),
)

_OPS = {"<": np.less, "<=": np.less_equal, ">": np.greater, ">=": np.greater_equal}

# metres -> centimetres for display, like the paper
_DISPLAY = {"m": ("cm", 100.0), "m/s": ("cm/s", 100.0)}


@dataclass
class ControlRow:
    """One evaluated control. Values in the feature's unit (m or m/s); ``scale`` converts to ``display_unit``.

    ``status`` is ``"PASS"`` (both checks hold), ``"FAIL"`` (a check failed) or
    ``"EMPTY"`` (the search found no candidate for some step: ``error`` says which).
    """

    case: ControlCase
    unit: str
    display_unit: str
    scale: float
    threshold: float
    db_frames_allowed: int
    db_fraction: float
    db_mean: float
    db_std: float
    allowed_mean: float
    allowed_std: float
    mean: float = float("nan")
    std: float = float("nan")
    free_mean: float = float("nan")
    free_std: float = float("nan")
    in_range: float = float("nan")
    free_in_range: float = float("nan")
    min_candidates: int | None = None
    n_steps: int = 0
    direction_ok: bool = False
    no_freeze_ok: bool = False
    std_ratio: float = float("nan")
    std_ratio_unconstrained: float = float("nan")
    std_ratio_allowed: float = float("nan")
    status: str = "EMPTY"
    error: str | None = None

    def to_dict(self) -> dict:
        s = self.scale
        return {
            "control": self.case.name,
            "expression": self.case.expr,
            "feature": self.case.feature,
            "direction": "higher" if self.case.direction > 0 else "lower",
            "unit": self.display_unit,
            "threshold": self.threshold * s,
            "mean": self.mean * s,
            "std": self.std * s,
            "unconstrained_mean": self.free_mean * s,
            "unconstrained_std": self.free_std * s,
            "database_mean": self.db_mean * s,
            "database_std": self.db_std * s,
            "allowed_frames_mean": self.allowed_mean * s,
            "allowed_frames_std": self.allowed_std * s,
            "in_range_fraction": self.in_range,
            "unconstrained_in_range_fraction": self.free_in_range,
            "database_frames_allowed": self.db_frames_allowed,
            "database_fraction_allowed": self.db_fraction,
            "steps": self.n_steps,
            "min_candidates_per_step": self.min_candidates,
            "std_ratio": self.std_ratio,
            "std_ratio_unconstrained": self.std_ratio_unconstrained,
            "std_ratio_allowed": self.std_ratio_allowed,
            "direction_ok": self.direction_ok,
            "no_freeze_ok": self.no_freeze_ok,
            "status": self.status,
            "error": self.error,
        }


@dataclass
class ControlsReport:
    """Result of :func:`evaluate_controls`.

    Attributes
    ----------
    rows : list of ControlRow
    unconstrained : dict feature -> (mean, std)
        Of the unconstrained synthesis, feature units.
    series : dict
        ``"unconstrained"``: feature -> ndarray (T,), and case name -> ndarray (T,)
        (the controlled feature over the output frames; absent for EMPTY rows),
        for plots.
    """

    database: str
    audio: str | None
    fps: float
    n_frames: int
    settings: dict
    rows: list
    unconstrained: dict
    series: dict = field(default_factory=dict, repr=False)

    @property
    def passed(self) -> bool:
        return all(r.status == "PASS" for r in self.rows)

    def to_dict(self) -> dict:
        """Everything as plain JSON types (NaN and inf become None)."""
        return json_clean({
            "database": self.database,
            "audio": self.audio,
            "fps": self.fps,
            "n_frames": self.n_frames,
            "duration_s": self.n_frames / self.fps,
            "settings": self.settings,
            "unconstrained": {k: {"mean": m, "std": s} for k, (m, s) in self.unconstrained.items()},
            "rows": [r.to_dict() for r in self.rows],
            "passed": self.passed,
        })

    def _cells(self):
        head = ["control", "mask", "threshold", "controlled mean ± std", "unconstrained mean ± std",
                "allowed DB frames mean ± std", "in range (ctl / free)", "direction", "no freeze", "status"]
        body = []
        for r in self.rows:
            s, u = r.scale, r.display_unit
            ok = lambda b: "ok" if b else "FAIL"  # noqa: E731
            body.append([
                r.case.name,
                r.case.expr,
                f"{r.threshold * s:.1f} {u}",
                f"{_fmt(r.mean * s, '.1f')} ± {_fmt(r.std * s, '.1f')} {u}",
                f"{_fmt(r.free_mean * s, '.1f')} ± {_fmt(r.free_std * s, '.1f')} {u}",
                f"{_fmt(r.allowed_mean * s, '.1f')} ± {_fmt(r.allowed_std * s, '.1f')} {u} ({r.db_frames_allowed})",
                f"{_fmt(100 * r.in_range, '.0f')}% / {_fmt(100 * r.free_in_range, '.0f')}%",
                ok(r.direction_ok) if r.status != "EMPTY" else "-",
                (ok(r.no_freeze_ok) + f" ({_fmt(r.std_ratio, '.2f')})") if r.status != "EMPTY" else "-",
                r.status,
            ])
        return head, body

    def _title(self) -> str:
        aud = os.path.basename(self.audio) if self.audio else "speech"
        return (f"Controlled synthesis (Habibie et al. 2022, Table 2): {aud}, "
                f"{self.n_frames / self.fps:.1f} s at {self.fps:g} fps; database {os.path.basename(self.database)}")

    def _notes(self) -> list[str]:
        notes = [
            f"threshold = the mask's percentile resolved on the database; mean ± std over the "
            f"{self.n_frames} synthesized frames, recomputed on the output joint positions",
            "direction: controlled mean past the unconstrained mean in the requested direction",
            f"no freeze: controlled std >= {self.settings['min_std_ratio']:g} x the std of the "
            + ("database frames the mask allows" if self.settings["freeze_reference"] == "allowed"
               else "unconstrained synthesis") + " (ratio in brackets)",
        ]
        for r in self.rows:
            if r.error:
                notes.append(f"{r.case.name}: {r.error}")
        return notes

    def to_text(self) -> str:
        head, body = self._cells()
        out = [self._title(), "", text_table(head, body, align="left")]
        out += [""] + self._notes()
        out.append("all checks passed" if self.passed else
                   "FAILED: " + ", ".join(f"{r.case.name} ({r.status})" for r in self.rows if r.status != "PASS"))
        return "\n".join(out)

    def to_markdown(self) -> str:
        head, body = self._cells()
        out = [f"### {self._title()}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        out += ["| " + " | ".join(c.replace("|", "\\|") for c in b) + " |" for b in body]
        out += [""] + [f"- {n}" for n in self._notes()]
        return "\n".join(out) + "\n"


def evaluate_controls(
    db,
    audio,
    *,
    sr: int | None = None,
    cases: Sequence[ControlCase] = TABLE2_CASES,
    segments: str = "chunks",
    min_std_ratio: float = DEFAULT_MIN_STD_RATIO,
    freeze_reference: str = "allowed",
    options: SearchOptions | None = None,
    **changes,
) -> ControlsReport:
    """Reproduce Table 2 of Habibie et al. 2022 on one speech input.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    audio : path or ndarray [shape=(n,)]
        Speech (a WAV file, or mono samples with ``sr``).
    cases : sequence of ControlCase
        Controls to evaluate (default: the paper's six).
    segments : {"chunks", "clips"}
        What the search runs over (:class:`gesturedb.synth.Searcher`).
    options : SearchOptions, optional
        Search settings, the same for the unconstrained and every controlled
        synthesis (``k``, ``preselect``, ``init``, ``seed``, ``step``, ``seam_decay_s``,
        ``exclude``, ...; see :class:`gesturedb.synth.options.SearchOptions`); any of its
        fields may also be given as keywords. Keyword sub-databases and a control of
        the options' own are not used: each row sets its control.
    min_std_ratio : float
        The no-freeze check: controlled std >= ``min_std_ratio`` x the reference std.
    freeze_reference : {"allowed", "unconstrained"}
        Reference std of the no-freeze check: the database frames the mask
        allows, or the unconstrained synthesis.

    Returns
    -------
    ControlsReport
        A control whose mask leaves some step without a candidate gets status
        ``"EMPTY"`` and the search's explanation in ``error``; the others get
        ``"PASS"`` or ``"FAIL"``.
    """

    if not (isinstance(min_std_ratio, (int, float)) and 0 <= min_std_ratio):
        raise ParameterError(f"min_std_ratio: expected a number >= 0, got {min_std_ratio!r}")
    if freeze_reference not in ("allowed", "unconstrained"):
        raise ParameterError(f"freeze_reference: expected 'allowed' or 'unconstrained', got {freeze_reference!r}")
    cases = list(cases)
    if not cases:
        raise ParameterError("cases: expected at least one ControlCase")
    missing = sorted({c.feature for c in cases} - set(db.controls))
    if missing:
        raise InputFileError(db.path, f"controls: expected control features {missing}; the database has {sorted(db.controls)}")

    samples, rate, audio_path = _read_samples(db, audio, sr)
    joints = feature_joint_indices(db)
    searcher = Searcher(db, segments=segments)
    opts = SearchOptions.of(options, **changes).replace(keywords=False, control=None)

    def measure(res) -> dict[str, np.ndarray]:
        return control_features(res.positions, joints=joints, fps=db.fps)

    free = searcher.synthesize(samples, sr=rate, options=opts)
    free_c = measure(free)
    feats = sorted({c.feature for c in cases})
    unconstrained = {f: _stats(free_c[f]) for f in feats}
    series: dict[str, Any] = {"unconstrained": {f: free_c[f].astype(np.float64) for f in feats}}

    rows = []
    for case in cases:
        compiled = control.compile_mask(case.expr, controls=db.controls, named=db.masks)
        cmp = [c for c in compiled.comparisons if c.feature == case.feature]
        if len(cmp) != 1:
            raise ParameterError(f"cases: {case.name!r}: expected one comparison on {case.feature} in {case.expr!r}, "
                                 f"got {len(cmp)}")
        thr = float(cmp[0].threshold)
        op = cmp[0].op
        unit = db.control_units.get(case.feature, "") or (cmp[0].unit or "")
        disp, scale = _DISPLAY.get(unit, (unit, 1.0))
        vals_db = np.asarray(db.controls[case.feature], dtype=np.float64)
        allowed = vals_db[compiled.bits()]
        am, ast = _stats(allowed) if allowed.size else (float("nan"), float("nan"))
        row = ControlRow(case=case, unit=unit, display_unit=disp, scale=scale, threshold=thr,
                         db_frames_allowed=int(compiled.n_set), db_fraction=float(compiled.fraction),
                         db_mean=float(vals_db.mean()), db_std=float(vals_db.std()),
                         allowed_mean=am, allowed_std=ast)
        fm, fs = unconstrained[case.feature]
        row.free_mean, row.free_std = fm, fs
        row.free_in_range = float(np.mean(_OPS[op](free_c[case.feature].astype(np.float64), thr)))
        try:
            res = searcher.synthesize(samples, sr=rate, options=opts.replace(control=case.expr))
        except SearchError as exc:
            row.status, row.error = "EMPTY", f"no synthesis: {exc}"
            rows.append(row)
            continue
        v = measure(res)[case.feature].astype(np.float64)
        series[case.name] = v
        row.mean, row.std = _stats(v)
        row.in_range = float(np.mean(_OPS[op](v, thr)))
        row.n_steps = len(res.steps)
        row.min_candidates = int(min(s["candidates"] for s in res.steps))
        row.direction_ok = bool((row.mean - fm) * case.direction > 0)
        row.std_ratio_unconstrained = row.std / fs if fs > 0 else float("inf")
        row.std_ratio_allowed = row.std / ast if ast > 0 else float("inf")
        ref_std = ast if freeze_reference == "allowed" else fs
        row.std_ratio = row.std / ref_std if ref_std > 0 else float("inf")
        row.no_freeze_ok = bool(row.std >= min_std_ratio * ref_std)
        row.status = "PASS" if row.direction_ok and row.no_freeze_ok else "FAIL"
        rows.append(row)

    settings = dict(k=opts.k, preselect=opts.preselect, init=opts.init, seed=opts.seed, step=opts.step,
                    seam_decay_s=opts.seam_decay_s, keywords=False, exclude=opts.exclude, segments=segments,
                    min_std_ratio=float(min_std_ratio), freeze_reference=freeze_reference)
    return ControlsReport(database=db.path, audio=audio_path, fps=db.fps, n_frames=free.n_frames,
                          settings=settings, rows=rows, unconstrained=unconstrained, series=series)


