"""The audit's HTML page: per robot a timeline, the fleet's models x recordings heat map.

Self-contained like the run report (``reports/audit.html.j2``, the report's
stylesheet inlined, no scripts). Pictures are SVG drawn with the report's
canvas (:mod:`pipeline.report.svg`):

* per robot, recordings left to right (their dates): the drift of the previous
  calibration and the validated and fresh consistencies (mm), the tolerance, and
  below, each change read, its size with a 2-sigma error bar (mm or deg), labelled
  where no label covers another (:func:`pipeline.report.svg.place_labels`);
* the fleet: one cell per (model, recording), coloured by the held-out error on
  a log scale, the best model of each recording outlined.

Figures are written by :func:`pipeline.numfmt.fmt` (a chi-square of 4e10 as ``4.02e10``).
"""

from __future__ import annotations

import math
from datetime import UTC, datetime
from html import escape

import numpy as np
import pandas as pd

from pipeline import __version__
from pipeline.audit.attribute import display_unit
from pipeline.audit.audit import AuditResult
from pipeline.numfmt import fmt
from pipeline.report.svg import Panel, canvas, legend_height, padded
from pipeline.report.templates import render_template

TEMPLATE = "audit.html.j2"
COLOURS = {
    "drift": "#cf222e", "raw": "#fa8072", "validated": "#0969da", "fresh": "#1a7f37",
    "tol": "#57606a",
}  # fmt: skip
KIND_COLOURS = {
    "arm": "#cf222e", "camera": "#8250df", "base": "#bc4c00",
    "several": "#57606a", "different_robot": "#000000", "none": "#1a7f37",
}  # fmt: skip


def _date(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, tz=UTC).strftime("%Y-%m-%d")


def timeline_svg(recs: pd.DataFrame, changes: pd.DataFrame) -> str:
    """One robot's timeline (see the module docstring)."""
    n = len(recs)
    x = np.arange(n, dtype=float)
    ticks = [(float(i), _date(int(s))) for i, s in zip(x, recs["stamp_ns"], strict=True)]
    vals = np.concatenate(
        [recs[c].to_numpy(float) for c in ("drift_mm", "drift_raw_mm", "validated_mm", "fresh_mm")]
    )
    vals = np.append(vals[np.isfinite(vals)], float(recs["tolerance_mm"].iloc[0]))
    lh = legend_height(5)
    top = Panel((70, 10 + lh, 620, 170), (-0.5, n - 0.5), (0.0, float(vals.max()) * 1.15 or 1.0))
    top.legend_at = "above"
    keys = {
        "drift": "drift of the previous calibration (the change read)",
        "raw": "previous vs own calibration (with their noise)",
        "validated": "previous, validated (consistency)",
        "fresh": "own calibration (consistency)",
    }
    for col, key in (
        ("drift_mm", "drift"), ("drift_raw_mm", "raw"), ("validated_mm", "validated"),
        ("fresh_mm", "fresh"),
    ):  # fmt: skip
        dash = "3 2" if key == "raw" else ""
        top.line(x, recs[col].to_numpy(float), COLOURS[key], markers=6, dash=dash)
        top.key(keys[key], COLOURS[key])
    tol = float(recs["tolerance_mm"].iloc[0])
    top.line([-0.5, n - 0.5], [tol, tol], COLOURS["tol"], dash="4 3")
    top.key("tolerance", COLOURS["tol"])
    ch = changes[changes["changed"]]
    pos = {r: i for i, r in enumerate(recs["recording"])}
    for c in ch.to_dict("records"):
        top.text(pos[c["to_recording"]], 0, c["kind"].replace("_", " "), dy=-14)
    body = [top.render(ylabel="mm (drift, consistency)", xticks=ticks)]
    bottom = _changes_panel(ch, pos, n, ticks, 240 + lh)
    body += [bottom] if bottom else []
    return canvas(720, (240 + CHANGES_HEIGHT + 40 if bottom else 220) + lh, body)


#: height of the changes-read panel, px (room for its labels, stacked where they crowd)
CHANGES_HEIGHT = 190


def _changes_panel(
    ch: pd.DataFrame, pos: dict[str, int], n: int, ticks: list[tuple[float, str]], top: float
) -> str:
    """The timeline's lower panel: each change read, its size with a 2-sigma bar, labelled
    (cause and column) where no label covers another (:meth:`Panel.labels`)."""
    sizes, errs, labels, xs, kinds = [], [], [], [], []
    for c in ch.to_dict("records"):
        cols, size, std = list(c["columns"]), list(c["size"]), list(c["size_std"])
        for k, (col, s, e) in enumerate(zip(cols, size, std, strict=True)):
            f, unit = display_unit(col)
            xs.append(pos[c["to_recording"]] - 0.3 + 0.6 * (k + 0.5) / max(len(cols), 1))
            sizes.append(s * f)
            errs.append(2 * e * f)
            short = f"{col.rsplit('.', 1)[-1]} {unit}"
            labels.append(f"{c['cause']}: {short}" if k == 0 else short)
            kinds.append(c["kind"])
    if not sizes:
        return ""
    lo, hi = padded(min(np.array(sizes) - errs + [0.0]), max(np.array(sizes) + errs + [0.0]), 0.15)
    bot = Panel((70, top, 620, CHANGES_HEIGHT), (-0.5, n - 0.5), (lo, hi))
    bot.line([-0.5, n - 0.5], [0, 0], COLOURS["tol"], width=0.8)
    for xi, s, e, kd in zip(xs, sizes, errs, kinds, strict=True):
        colour = KIND_COLOURS.get(kd, "#000")
        bot.line([xi, xi], [s - e, s + e], colour, width=1.5)
        bot.dots(np.array([xi]), np.array([s]), colour, 6)
    bot.labels(xs, sizes, labels, size=8, bounds=(4.0, top, 716.0, top + CHANGES_HEIGHT))
    return bot.render(
        ylabel="size (mm, deg, ppm)", title="changes read (2-sigma bars)", xticks=ticks
    )


def heatmap_svg(matrix: pd.DataFrame) -> str:
    """Models x recordings, coloured by log10 of the held-out error."""
    recs = list(dict.fromkeys(matrix["recording"]))
    models = list(dict.fromkeys(matrix["model"]))
    cw, ch, left, top = 34.0, 22.0, 80.0, 90.0
    v = matrix["heldout_mm"].to_numpy(float)
    ok = np.isfinite(v) & (v > 0)
    lo, hi = (np.log10(v[ok].min()), np.log10(v[ok].max())) if ok.any() else (0.0, 1.0)
    parts = []
    for r in matrix.to_dict("records"):
        i, j = recs.index(r["recording"]), models.index(r["model"])
        x, y = left + i * cw, top + j * ch
        if np.isfinite(r["heldout_mm"]) and r["heldout_mm"] > 0:
            t = (math.log10(r["heldout_mm"]) - lo) / max(hi - lo, 1e-9)
            colour = f"rgb({int(255 * t)},{int(200 * (1 - t) + 40)},{int(255 * (1 - t))})"
        else:
            colour = "#d0d7de"
        stroke = ' stroke="#000" stroke-width="2"' if r["rank"] == 1 else ""
        parts.append(
            f'<rect x="{x:.1f}" y="{y:.1f}" width="{cw - 2:.1f}" height="{ch - 2:.1f}" '
            f'fill="{colour}"{stroke}><title>{escape(r["model"])} on {escape(r["recording"])}: '
            f"{fmt(r['heldout_mm'], 4)} mm</title></rect>"
        )
    for j, m in enumerate(models):
        parts.append(
            f'<text x="{left - 6}" y="{top + j * ch + 14}" text-anchor="end">{escape(m)}</text>'
        )
    for i, rc in enumerate(recs):
        cx, cy = left + i * cw + 10, top - 6
        parts.append(
            f'<text x="{cx:.1f}" y="{cy}" transform="rotate(-60 {cx:.1f} {cy})" font-size="9">'
            f"{escape(rc)}</text>"
        )
    w = left + len(recs) * cw + 20
    parts.append(
        f'<text x="{left}" y="{top + len(models) * ch + 16}" font-size="10">blue {fmt(10**lo, 4)} mm '
        f"&#8594; red {fmt(10**hi, 4)} mm (log); outlined: best on that recording</text>"
    )
    return canvas(max(w, 420), top + len(models) * ch + 30, parts)


def render_page(res: AuditResult) -> str:
    """The audit's HTML page."""
    robots = []
    for rid, recs in res.recordings.groupby("robot_id", sort=True):
        ch = res.changes[
            (res.changes["comparison"] == "history") & (res.changes["robot_id"] == rid)
        ]
        robots.append(
            {
                "id": rid,
                "model": recs["model"].iloc[0],
                "svg": timeline_svg(recs.reset_index(drop=True), ch),
                "rows": recs.to_dict("records"),
                "changes": ch.to_dict("records"),
            }
        )
    cross = res.changes[res.changes["comparison"] == "robots"].to_dict("records")
    return render_template(
        TEMPLATE, fmt, robots=robots, cross=cross, heat=heatmap_svg(res.models),
        ranking=res.ranking.to_dict("records"), lines=res.lines, version=__version__,
        date=_date,
    )  # fmt: skip
