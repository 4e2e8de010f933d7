"""Evaluation reports a person can look at: plots (matplotlib), renders and one HTML page.

:func:`write_motion_report` turns a :class:`gesturedb.eval.evaluate.MotionEvaluation`
into a folder::

    metrics.json        every number, per input, the mean over inputs, the settings
    metrics.txt         the same tables as text
    index.html          tables + the pictures below, self-explanatory
    speed_<i>.png       joint-speed histograms of every system (what the Hellinger distance compares)
    wrist_<i>.png       left wrist height over time with the database's p15/p85 control thresholds
    summary_<i>.png     the headline metrics per system next to the reference
    sheet_<i>.png       contact sheet: ground truth | rank-sum | random (or audio-only without ground truth)
    video_0.mp4         the same side by side with the speech (first input; .gif on request)
    controls.png        controlled vs unconstrained over time (when the controls evaluation ran)

:func:`write_controls_report` writes the outputs of ``gesturedb eval controls``.
Plots use the non-interactive Agg backend, so no display is needed.
"""
from __future__ import annotations

import html
import json
import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.eval.common import SYSTEM_LABELS, _centred, _fmt
from gesturedb.eval.strokes import BANDS_HZ, STROKE_COLUMNS, band_key
from gesturedb.io.atomic import write_text
from gesturedb.render import render_contact_sheet, render_video
from gesturedb.synth import methods

__all__ = [
    "plot_speed_histograms",
    "plot_band_power",
    "plot_wrist_height",
    "plot_metric_summary",
    "plot_controls",
    "render_comparison",
    "write_controls_report",
    "write_motion_report",
]

# one colour per system, the same in every plot
_COLORS = {
    "reference": "#7f7f7f",
    "ground_truth": "#222222",
    "random": "#d62728",
    "pose_only": "#9467bd",
    "audio_only": "#ff7f0e",
    **{s.name: s.color for s in methods.eval_systems()},
    "ranksum_refined": "#17becf",
}


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _label(name: str) -> str:
    return SYSTEM_LABELS.get(name, name)


def _save(fig, path) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    _plt().close(fig)
    return path


# ---------------------------------------------------------------------- plots
def plot_band_power(path, metrics: dict) -> Path:
    """Band power against the database's own motion: one panel per joint group, bars per band and system.

    Parameters
    ----------
    metrics : dict name -> row
        Rows of ``gesturedb eval motion`` with ``band_<group>_<band>_db`` keys
        (:func:`gesturedb.eval.strokes.stroke_metrics`). 1 is the database's own motion;
        the shaded band is 0.67-1.5x.
    """
    plt = _plt()
    groups = [g for g in ("arms", "hands", "head") if any(f"band_{g}_{band_key(BANDS_HZ[0])}_db" in r
                                                          for r in metrics.values())]
    names = list(metrics)
    fig, axes = plt.subplots(1, max(len(groups), 1), figsize=(4.2 * max(len(groups), 1), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    width = 0.8 / max(len(names), 1)
    x = np.arange(len(BANDS_HZ))
    for ax, g in zip(axes, groups):
        ax.axhspan(0.67, 1.5, color="0.92", zorder=0)
        ax.axhline(1.0, color="0.5", lw=1, ls="--", zorder=1)
        for i, n in enumerate(names):
            vals = [metrics[n].get(f"band_{g}_{band_key(b)}_db", np.nan) for b in BANDS_HZ]
            ax.bar(x - 0.4 + (i + 0.5) * width, vals, width, label=_label(n), color=_COLORS.get(n), zorder=2)
        ax.set_xticks(x, [f"{band_key(b)} Hz" for b in BANDS_HZ])
        ax.set_yscale("log")
        ax.set_title(f"{g}: velocity power / database's")
    axes[0].set_ylabel("ratio (log); shaded 0.67-1.5")
    axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return _save(fig, path)


def plot_speed_histograms(path, counts: dict, edges: np.ndarray, *, reference: np.ndarray | None = None,
                          max_speed_m_s: float = 1.5) -> Path:
    """Normalised joint-speed histograms, one line per system (and the database reference).

    Parameters
    ----------
    counts : dict name -> ndarray [shape=(n_bins,)]
        Speed histogram counts (``gesturedb.eval.metrics.speed_histogram``).
    edges : ndarray [shape=(n_bins + 1,)], m/s
    reference : ndarray [shape=(n_bins,)], optional
        The database's histogram, drawn grey and dashed.
    """
    plt = _plt()
    # the metric's 0.01 m/s bins are too noisy to read on a short clip: draw groups of `merge` bins
    merge = 4
    n = (edges.size - 1) // merge * merge
    e = edges[: n + 1 : merge]
    centres = 0.5 * (e[:-1] + e[1:])
    visible = centres <= max_speed_m_s

    def density(c):
        c = np.asarray(c[:n], dtype=np.float64).reshape(-1, merge).sum(axis=1)
        return c / max(np.asarray(c).sum(), 1.0)

    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    top = 0.0
    if reference is not None:
        d = density(reference)
        top = max(top, d[visible].max())
        ax.plot(centres, d, color=_COLORS["reference"], ls="--", lw=1.5, label=_label("reference"))
    for name, c in counts.items():
        d = density(c)
        top = max(top, d[visible].max())
        ax.plot(centres, d, color=_COLORS.get(name), lw=2.2 if name in ("ground_truth", "ranksum_pose") else 1.3,
                label=_label(name))
    ax.set_xlim(0, max_speed_m_s)
    ax.set_ylim(0, 1.08 * top)
    ax.set_xlabel(f"joint speed (m/s), upper body ({e[1] - e[0]:.2f} m/s bins)")
    ax.set_ylabel("share of (frame, joint) samples")
    ax.set_title("Joint-speed distributions (compared by the Hellinger distance)")
    ax.legend(fontsize=8, frameon=False)
    ax.grid(alpha=0.25)
    return _save(fig, path)


def plot_wrist_height(path, series: dict, *, fps: float, p15: float, p85: float, start_s: float = 0.0,
                      systems: Sequence[str] | None = None) -> Path:
    """Left wrist height (cm above the root) over time per system, with the p15/p85 control thresholds.

    Parameters
    ----------
    series : dict name -> ndarray [shape=(T,)], metres
    p15, p85 : float, metres
        The database's 15th / 85th percentiles (the wrist low / high masks).
    start_s : float
        Time of frame 0 in the source (a held-out stretch starts later).
    """
    plt = _plt()
    names = [n for n in (systems or series) if n in series]
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 1.25 + 1.05 * len(names)), sharex=True, squeeze=False)
    for ax, n in zip(axes[:, 0], names):
        v = 100 * np.asarray(series[n])
        t = start_s + np.arange(v.size) / fps
        ax.axhspan(100 * p85, max(100 * p85, v.max()) + 5, color="#1f77b4", alpha=0.07)
        ax.axhspan(min(100 * p15, v.min()) - 5, 100 * p15, color="#d62728", alpha=0.07)
        ax.axhline(100 * p85, color="#1f77b4", ls="--", lw=0.9)
        ax.axhline(100 * p15, color="#d62728", ls="--", lw=0.9)
        ax.plot(t, v, color=_COLORS.get(n, "k"), lw=1.2)
        ax.set_ylabel("cm", fontsize=8)
        ax.text(0.005, 0.92, _label(n), transform=ax.transAxes, fontsize=8, va="top",
                bbox=dict(facecolor="white", alpha=0.8, lw=0))
        ax.grid(alpha=0.2)
    axes[0, 0].set_title(f"Left wrist height above the root; dashed: database p85 = {100 * p85:.1f} cm "
                         f"(wrist high) and p15 = {100 * p15:.1f} cm (wrist low)", fontsize=9)
    axes[-1, 0].set_xlabel("time (s)")
    return _save(fig, path)


_SUMMARY_METRICS = (
    ("average_jerk_m_s3", "average jerk (m/s³)", "closer to the reference"),
    ("speed_hellinger_gt", "H(speed) vs ground truth", "lower is better"),
    ("speed_hellinger_db", "H(speed) vs database", "lower is better"),
    ("beat_align", "BeatAlign", "higher = more aligned"),
    ("l1_diversity_m", "L1 diversity (m)", "closer to the reference"),
    ("seam_ratio", "seam / inside jerk", "1 = invisible seams"),
)


def plot_metric_summary(path, rows: dict, *, reference: dict | None = None) -> Path:
    """Bar charts of the headline metrics per system; the reference (ground truth or database) as a line.

    Parameters
    ----------
    rows : dict name -> dict
        Metric rows of :func:`gesturedb.eval.evaluate.system_metrics`.
    reference : dict, optional
        The database reference row.
    """
    plt = _plt()
    mets = [m for m in _SUMMARY_METRICS if any(np.isfinite(r.get(m[0], np.nan)) for r in rows.values())]
    ncol = 3
    nrow = max(1, math.ceil(len(mets) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(12, 2.9 * nrow), squeeze=False)
    systems = [n for n in rows if n != "ground_truth"]
    for ax, (key, title, hint) in zip(axes.ravel(), mets):
        vals = [rows[n].get(key, np.nan) for n in systems]
        ax.barh(range(len(systems)), [v if np.isfinite(v) else 0 for v in vals],
                color=[_COLORS.get(n, "k") for n in systems])
        ax.set_yticks(range(len(systems)))
        ax.set_yticklabels([_label(n).replace(", ", ",\n") for n in systems], fontsize=7)
        ax.invert_yaxis()
        for i, v in enumerate(vals):
            if np.isfinite(v):
                ax.text(v, i, f" {v:.3g}", va="center", fontsize=7)
        refs = []
        if "ground_truth" in rows and np.isfinite(rows["ground_truth"].get(key, np.nan)) and key != "speed_hellinger_gt":
            refs.append((rows["ground_truth"][key], _COLORS["ground_truth"], "ground truth"))
        if reference is not None and np.isfinite(reference.get(key, np.nan)) and key != "speed_hellinger_db":
            refs.append((reference[key], _COLORS["reference"], "database"))
        for v, c, _lab in refs:
            ax.axvline(v, color=c, ls="--", lw=1.2)
        ref_text = " · ".join(f"{lab} {v:.3g}" for v, _, lab in refs)
        ax.set_title(f"{title} ({hint})" + (f"\ndashed: {ref_text}" if ref_text else "\n"), fontsize=9)
        ax.margins(x=0.25)
        ax.grid(axis="x", alpha=0.2)
    for ax in axes.ravel()[len(mets):]:
        ax.axis("off")
    fig.tight_layout()
    return _save(fig, path)


def plot_controls(path, report) -> Path:
    """The controlled variable over time, controlled vs unconstrained, one panel per control (cf. Fig. 2 of the paper).

    Parameters
    ----------
    report : gesturedb.eval.evaluate.ControlsReport
    """
    plt = _plt()
    rows = report.rows
    ncol = 2
    nrow = math.ceil(len(rows) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(12, 2.4 * nrow), squeeze=False, sharex=True)
    for ax, r in zip(axes.ravel(), rows):
        s, u = r.scale, r.display_unit
        free = report.series["unconstrained"][r.case.feature] * s
        t = np.arange(free.size) / report.fps
        ax.plot(t, free, color="#9a9a9a", lw=0.9, label=f"unconstrained {r.free_mean * s:.1f} ± {r.free_std * s:.1f}")
        if r.case.name in report.series:
            v = report.series[r.case.name] * s
            ax.plot(t[: v.size], v, color="#1f77b4" if r.case.direction > 0 else "#d62728", lw=1.2,
                    label=f"controlled {r.mean * s:.1f} ± {r.std * s:.1f}")
        ax.axhline(r.threshold * s, color="k", ls="--", lw=0.9, label=f"threshold {r.threshold * s:.1f} {u}")
        status = r.status if r.status == "PASS" else f"{r.status}"
        ax.set_title(f"{r.case.name}: {r.case.expr}  [{status}]", fontsize=9,
                     color="black" if r.status == "PASS" else "#b00000")
        ax.set_ylabel(u, fontsize=8)
        ax.legend(fontsize=7, frameon=False, loc="upper right", ncol=3)
        ax.grid(alpha=0.2)
    for ax in axes.ravel()[len(rows):]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    fig.suptitle("Controlled synthesis vs unconstrained (Habibie et al. 2022, Table 2 / Fig. 2)", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


# ---------------------------------------------------------------------- renders
def _panel_systems(outputs) -> list[str]:
    if "ground_truth" in outputs:
        prefer = ("ground_truth", "ranksum_pose", "random")
    else:
        prefer = ("ranksum_pose", "audio_only", "random")
    names = [n for n in prefer if n in outputs]
    return names or list(outputs)[:3]


def render_comparison(out_dir, inp, *, parents, root: int, index: int = 0, video: str | None = "mp4",
                      video_seconds: float | None = None, sheet_frames: int = 8) -> list[Path]:
    """Contact sheet (and optionally a video with the speech) of up to three systems side by side.

    Panels: ground truth | rank-sum | random, or rank-sum | audio-only | random
    without ground truth. Each panel's root starts at the origin so all stand
    in the same spot under one camera.

    Returns
    -------
    list of Path
    """

    out_dir = Path(out_dir)
    names = _panel_systems(inp.outputs)
    panels = [(_centred(inp.outputs[n].positions, root), parents, _label(n)) for n in names]
    written = [render_contact_sheet(out_dir / f"sheet_{index}.png", panels, n=sheet_frames, fps=inp.fps,
                                    size=(260, 300))]
    if video:
        if video not in ("mp4", "gif"):
            raise ParameterError(f"video: expected 'mp4', 'gif' or None, got {video!r}")
        n = panels[0][0].shape[0]
        if video_seconds is not None:
            n = max(2, min(n, int(round(video_seconds * inp.fps))))
        panels_v = [(p[:n], par, cap) for p, par, cap in panels]
        captions = None
        if inp.transcript is not None and len(inp.transcript):
            captions = inp.transcript
        written.append(render_video(out_dir / f"video_{index}.{video}", panels_v, fps=inp.fps,
                                    audio=(inp.samples[: int(round(n / inp.fps * inp.sr))], inp.sr),
                                    captions=captions, size=(320, 360)))
    return written


# ---------------------------------------------------------------------- HTML
_CSS = """
body { font-family: system-ui, -apple-system, Segoe UI, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; font-size: 0.86em; margin: 0.6em 0; }
th, td { padding: 0.3em 0.6em; border-bottom: 1px solid #e4e4e4; text-align: right; }
th:first-child, td:first-child { text-align: left; }
tr.ref td { color: #666; font-style: italic; } tr.gt td { font-weight: 600; }
td.fail { color: #b00000; font-weight: 600; } td.pass { color: #0a7a0a; }
img, video { max-width: 100%; border: 1px solid #ddd; margin: 0.4em 0; }
.note { color: #555; font-size: 0.9em; } code { background: #f3f3f3; padding: 0 0.2em; white-space: nowrap; }
dl { font-size: 0.9em; } dt { font-weight: 600; margin-top: 0.4em; } dd { margin-left: 1.2em; color: #444; }
"""

_METRIC_DOCS = (
    ("jerk, accel", "average magnitude of the 3rd / 2nd finite difference of the upper-body joint positions "
     "(GENEA). Natural motion has the ground truth's value; much higher means jittery, much lower over-smoothed."),
    ("H(speed) vs GT / DB", "Hellinger distance between the histograms of joint speeds (0.01 m/s bins) of the "
     "system and of the ground truth / the database's own motion: 0 = same distribution of speeds, 1 = disjoint."),
    ("BeatAlign", "Gaussian-weighted distance (sigma 0.3 s) from every motion beat (local minimum of wrist speed) "
     "to the nearest speech onset (BEAT, Liu et al. 2022); higher = gestures land on the speech's accents."),
    ("L1 div", "mean L1 distance between pairs of 2.27 s windows of the same output: how varied the gestures are."),
    ("rhythm Ham / rhythm beyond", "per clip of the speech (split at its pauses), the 32 bins that hold a word onset "
     "against the 32 that hold a prominent minimum of hand speed (GestureMaster's rhythm signatures), averaged over "
     "the clips; lower = the motion pauses and turns where the words start. rhythm Ham is the paper's Hamming "
     "distance, which also grows with every speed minimum that misses a word, so calmer motion scores better at "
     "chance level; rhythm beyond takes out what the two numbers of set bits explain (random placement scores the "
     "same whatever the number of minima)."),
    ("pauses seam/inside", "hand-speed minima per frame within 1/15 s of a window boundary vs elsewhere; above 1 "
     "the hands pause at the search step's rate (every 0.53 s) rather than with the speech; the ground truth, "
     "measured at the same frames, shows what chance looks like."),
    ("seam jerk / inside / seam/inside", "jerk of the stencils that straddle a window boundary vs all others; "
     "a ratio near 1 means the seams cannot be told from the inside of the windows. The ground truth is measured "
     "at the same frames."),
)


def _html_table(ev, rows: dict, spec=None) -> str:
    cols = ev.columns(rows) if spec is None else ev.columns(rows, spec)
    head = "<tr><th>system</th>" + "".join(f"<th>{html.escape(h)}</th>" for _, h, _ in cols) + "</tr>"
    body = []
    for n, r in {"reference": ev.reference_row(), **rows}.items():
        cls = "ref" if n == "reference" else ("gt" if n == "ground_truth" else "")
        cells = "".join(f"<td>{_fmt(r.get(k), f)}</td>" for k, _, f in cols)
        body.append(f'<tr class="{cls}"><td>{html.escape(_label(n))}</td>{cells}</tr>')
    return "<table>" + head + "".join(body) + "</table>"


#: Columns per table of the random starts: each cell holds mean +- sd and [min, max], so more would not fit a page.
STARTS_PER_TABLE = 8


def _starts_html(ev, inp) -> str:
    cols, rows = ev.starts_columns(inp), ev.starts_rows(inp)
    cell = lambda c: html.escape(c).replace(" [", "<br>[")  # noqa: E731  (the range under the mean)
    tables = []
    per = -(-len(cols) // -(-len(cols) // STARTS_PER_TABLE)) if cols else 1  # tables of even widths
    for a in range(0, len(cols), per):
        head = "<tr><th>system</th>" + "".join(f"<th>{html.escape(h)}</th>" for _, h, _ in cols[a:a + per])
        body = "".join(f"<tr><td>{html.escape(label)}</td>" + "".join(f"<td>{cell(c)}</td>" for c in cells[a:a + per])
                       + "</tr>" for label, cells in rows)
        tables.append(f"<table>{head}</tr>{body}</table>")
    return f'<p class="note">{html.escape(ev.starts_title(inp))}</p>' + "".join(tables)


def _controls_html(report, img: str | None) -> str:
    d = report.to_dict()
    head = ("<tr><th>control</th><th>mask</th><th>threshold</th><th>controlled mean ± std</th>"
            "<th>unconstrained mean ± std</th><th>allowed DB frames mean ± std</th><th>in range (ctl / free)</th>"
            "<th>direction</th><th>no freeze</th><th>status</th></tr>")
    body = []
    for r in d["rows"]:
        u = r["unit"]
        f = lambda v: "-" if v is None or not math.isfinite(v) else f"{v:.1f}"  # noqa: E731
        pct = lambda v: "-" if v is None or not math.isfinite(v) else f"{100 * v:.0f}%"  # noqa: E731
        ok = lambda b: '<td class="pass">ok</td>' if b else '<td class="fail">FAIL</td>'  # noqa: E731
        empty = r["status"] == "EMPTY"
        body.append(
            f"<tr><td>{html.escape(r['control'])}</td><td><code>{html.escape(r['expression'])}</code></td>"
            f"<td>{f(r['threshold'])} {u}</td><td>{f(r['mean'])} ± {f(r['std'])} {u}</td>"
            f"<td>{f(r['unconstrained_mean'])} ± {f(r['unconstrained_std'])} {u}</td>"
            f"<td>{f(r['allowed_frames_mean'])} ± {f(r['allowed_frames_std'])} {u} ({r['database_frames_allowed']})</td>"
            f"<td>{pct(r['in_range_fraction'])} / {pct(r['unconstrained_in_range_fraction'])}</td>"
            + ("<td>-</td><td>-</td>" if empty else
               ok(r["direction_ok"]) + ok(r["no_freeze_ok"]).replace("</td>", f" ({r['std_ratio']:.2f})</td>"))
            + f'<td class="{"pass" if r["status"] == "PASS" else "fail"}">{r["status"]}</td></tr>'
        )
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in report._notes())
    out = ["<h2>Controlled synthesis (Habibie et al. 2022, Table 2)</h2>",
           f'<p class="note">{html.escape(report._title().split(": ", 1)[-1])}</p>',
           "<table>" + head + "".join(body) + "</table>", f'<ul class="note">{notes}</ul>']
    if img:
        out.append(f'<img src="{img}" alt="controlled vs unconstrained">')
    return "\n".join(out)


def _write_html(path: Path, ev, files: dict) -> Path:
    s = ev.settings
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>gesturedb evaluation: {html.escape(os.path.basename(ev.database))}</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>gesturedb: objective evaluation</h1>",
        '<p class="note">'
        + (f"Held-out evaluation: {html.escape(s['holdout']['recording'])} "
           f"{s['holdout']['start_s']:g}–{s['holdout']['end_s']:g} s was left out of the database "
           f"({s['holdout']['training_frames']} training frames{', mirrored' if s['holdout']['mirror'] else ''}) "
           "and synthesized from its speech; the ground truth is its motion capture."
           if ev.mode == "holdout" else
           f"New speech without motion capture against the database {html.escape(ev.database)}; "
           "the reference is the database's own motion.")
        + f" Every system chooses one database window every {s['step']} frames and is assembled the same way "
        f"(seams inertialized over {s['seam_decay_s']:.2f} s); random seed {s['seed']}."
        + (f" Pose feature: {html.escape(ev.pose_stride_note())}." if ev.pose_stride_note() else "") + "</p>",
        "<p class='note'>Systems: <b>random</b> windows (real motion, mismatched audio); <b>pose-only</b> "
        "(nearest entry pose, audio ignored); <b>audio-only</b> (nearest audio by cosine, pose ignored); "
        "<b>rank-sum</b> (Habibie et al. 2022: rank by pose and by audio, pick the smallest rank sum) with pose or "
        "audio pre-selection.</p>",
    ]
    for i, inp in enumerate(ev.inputs):
        parts.append(f"<h2>{html.escape(inp.name)} — {inp.n_frames} frames, {inp.n_frames / inp.fps:.1f} s</h2>")
        parts.append(_html_table(ev, inp.metrics))
        parts.append('<p class="note">Strokes: power of root-relative joint velocity per band, divided by the '
                     "database's own motion (1 = the database's; docs/metrics.md), and the 95th percentile of wrist "
                     "speed.</p>")
        parts.append(_html_table(ev, inp.metrics, STROKE_COLUMNS))
        if inp.starts:
            parts.append(_starts_html(ev, inp))
        for key, alt in (("video", "side-by-side video with speech"), ("sheet", "contact sheet"),
                         ("summary", "metric summary"), ("bands", "strokes: velocity power per band against the database"),
                         ("speed", "speed histograms"), ("wrist", "left wrist height")):
            f = files.get((key, i))
            if f is None:
                continue
            if key == "video" and f.endswith(".mp4"):
                parts.append(f'<video controls preload="metadata" src="{f}"></video>')
            else:
                parts.append(f'<img src="{f}" alt="{alt}">')
    if len(ev.inputs) > 1:
        parts.append(f"<h2>Mean over {len(ev.inputs)} inputs</h2>")
        parts.append(_html_table(ev, ev.summary()))
    if ev.controls is not None:
        parts.append(_controls_html(ev.controls, files.get(("controls", 0))))
    parts.append("<h2>What the columns mean</h2><dl>")
    parts += [f"<dt>{html.escape(a)}</dt><dd>{html.escape(b)}</dd>" for a, b in _METRIC_DOCS]
    parts.append("</dl>")
    parts.append(f"<p class='note'>Positions: the root's horizontal position removed in every frame; metrics over "
                 f"{len(s['joints'])} upper-body joints. All numbers: <a href='metrics.json'>metrics.json</a>, "
                 "<a href='metrics.txt'>metrics.txt</a>.</p>")
    parts.append("</body></html>")
    write_text(path, "\n".join(parts))
    return path


def write_motion_report(ev, out_dir, *, render: bool = True, video: str | None = "mp4",
                        video_seconds: float | None = None) -> list[Path]:
    """Write every output of ``gesturedb eval motion`` into ``out_dir`` (created if needed).

    Parameters
    ----------
    ev : gesturedb.eval.evaluate.MotionEvaluation
    render : bool
        Render contact sheets (every input) and a video (first input only: video
        is the slow part, about 40 ms per panel and frame).
    video : {"mp4", "gif"} or None
        Video format; None for contact sheets only.
    video_seconds : float, optional
        Render only the first seconds of the video.

    Returns
    -------
    list of Path
        Every file written, ``index.html`` last.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    write_text(out / "metrics.json", json.dumps(ev.to_dict(), indent=1))
    written.append(out / "metrics.json")
    write_text(out / "metrics.txt", ev.to_text())
    written.append(out / "metrics.txt")

    files: dict = {}
    edges = ev.reference["speed_edges"]
    th = ev.thresholds["left_wrist_height"]
    for i, inp in enumerate(ev.inputs):
        files[("speed", i)] = plot_speed_histograms(out / f"speed_{i}.png", inp.speed_counts, edges,
                                                    reference=ev.reference["speed_counts"]).name
        files[("wrist", i)] = plot_wrist_height(out / f"wrist_{i}.png", inp.wrist_height, fps=inp.fps,
                                                p15=th["p15"], p85=th["p85"], start_s=inp.start_s).name
        files[("bands", i)] = plot_band_power(out / f"bands_{i}.png", inp.metrics).name
        files[("summary", i)] = plot_metric_summary(out / f"summary_{i}.png", inp.metrics,
                                                    reference=ev.reference_row()).name
        if render:
            for p in render_comparison(out, inp, parents=ev.parents, root=ev.root, index=i,
                                       video=video if i == 0 else None, video_seconds=video_seconds):
                files[("video" if p.suffix in (".mp4", ".gif") else "sheet", i)] = p.name
    if ev.controls is not None:
        files[("controls", 0)] = plot_controls(out / "controls.png", ev.controls).name
    written += [out / f for f in files.values()]
    written.append(_write_html(out / "index.html", ev, files))
    return written


def write_controls_report(report, *, json_path=None, md_path=None, plot_path=None) -> list[Path]:
    """Write the outputs of ``gesturedb eval controls``: JSON, Markdown and/or the plot.

    Parameters
    ----------
    report : gesturedb.eval.evaluate.ControlsReport
    json_path, md_path, plot_path : path, optional

    Returns
    -------
    list of Path
    """
    written = []
    if json_path:
        write_text(json_path, json.dumps(report.to_dict(), indent=1))
        written.append(Path(json_path))
    if md_path:
        write_text(md_path, report.to_markdown())
        written.append(Path(md_path))
    if plot_path:
        written.append(plot_controls(plot_path, report))
    return written
