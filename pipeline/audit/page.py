"""The audit's HTML pages: the fleet page a maintenance engineer starts from, a page per robot.

Self-contained like the run report (``reports/audit.html.j2`` and
``reports/audit_robot.html.j2``, the report's stylesheet inlined, no scripts).

* ``audit.html``: every robot in one compact row, in the order of attention
  (:mod:`pipeline.audit.attention`: failed, changed, overdue, the rest; worst first),
  with its last recording's date, its latest drift, a status word and a sparkline of its
  drift over its history (:func:`pipeline.report.svg.sparkline`), its name a link to its
  page; the comparison of robots of one model; the error models ranked (and the models
  x recordings heat map while it fits a page, :data:`HEAT_MAX`). Small with hundreds of
  robots: no chart but the sparklines.
* ``robots/ROBOT.html`` (:func:`robot_file`), per robot: its timeline, recordings left to
  right (their dates): the drift of the previous calibration and the validated and fresh
  consistencies (mm), the tolerance, and below, each change read, its size with a
  2-sigma error bar (mm or deg), labelled where no label covers another
  (:func:`pipeline.report.svg.place_labels`); its recordings and changes; its
  comparison with robots of its model; its models x recordings heat map, coloured by
  the held-out error on a log scale, the best model of each recording outlined.

Figures are written by :func:`pipeline.io.numfmt.fmt` (a chi-square of 4e10 as ``4.02e10``).
"""

from __future__ import annotations

import hashlib
import math
import re
import time
from datetime import UTC, datetime
from html import escape
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline import __version__
from pipeline.audit.attention import DAY_NS, STATUSES, Rows, fleet_status_rows, reading, rows_of
from pipeline.audit.attribute import display_unit
from pipeline.audit.audit import AuditResult
from pipeline.io.numfmt import fmt, short
from pipeline.report.svg import Panel, canvas, legend_height, padded, sparkline
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


def timeline_svg(recs: pd.DataFrame | Rows, changes: pd.DataFrame | Rows) -> str:
    """One robot's timeline (see the module docstring): its recordings in order and its
    history comparisons (tables or their rows, :func:`rows_of`)."""
    rr = rows_of(recs)
    n = len(rr)
    x = np.arange(n, dtype=float)
    ticks = [(float(i), _date(int(r["stamp_ns"]))) for i, r in zip(x, rr, strict=True)]
    cols = {c: np.array([r[c] for r in rr], float)
            for c in ("drift_mm", "drift_raw_mm", "validated_mm", "fresh_mm")}  # fmt: skip
    vals = np.concatenate(list(cols.values()))
    tol = float(rr[0]["tolerance_mm"])
    vals = np.append(vals[np.isfinite(vals)], tol)
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
        top.line(x, cols[col], COLOURS[key], markers=6, dash=dash)
        top.key(keys[key], COLOURS[key])
    top.line([-0.5, n - 0.5], [tol, tol], COLOURS["tol"], dash="4 3")
    top.key("tolerance", COLOURS["tol"])
    ch = [c for c in rows_of(changes) if c["changed"]]
    pos = {r["recording"]: i for i, r in enumerate(rr)}
    for c in ch:
        top.text(pos[c["to_recording"]], 0, c["kind"].replace("_", " "), dy=-14)
    body = [top.render(ylabel="mm (drift, consistency)", xticks=ticks)]
    bottom = _changes_panel(ch, pos, n, ticks, 240 + lh)
    body += [bottom] if bottom else []
    return canvas(720, (240 + CHANGES_HEIGHT + 40 if bottom else 220) + lh, body)


#: height of the changes-read panel, px (room for its labels, stacked where they crowd)
CHANGES_HEIGHT = 190


def _changes_panel(
    ch: Rows, pos: dict[str, int], n: int, ticks: list[tuple[float, str]], top: float
) -> str:
    """The timeline's lower panel: each change read, its size with a 2-sigma bar, labelled
    (cause and column) where no label covers another (:meth:`Panel.labels`)."""
    sizes, errs, labels, xs, kinds = [], [], [], [], []
    for c in ch:
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


def heatmap_svg(matrix: pd.DataFrame | Rows) -> str:
    """Models x recordings, coloured by log10 of the held-out error."""
    rows = rows_of(matrix)
    recs = {r: i for i, r in enumerate(dict.fromkeys(r["recording"] for r in rows))}
    models = {m: j for j, m in enumerate(dict.fromkeys(r["model"] for r in rows))}
    cw, ch, left, top = 34.0, 22.0, 80.0, 90.0
    v = np.array([r["heldout_mm"] for r in rows], float)
    ok = np.isfinite(v) & (v > 0)
    lo, hi = (np.log10(v[ok].min()), np.log10(v[ok].max())) if ok.any() else (0.0, 1.0)
    parts = []
    for r in rows:
        i, j = recs[r["recording"]], models[r["model"]]
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


#: the fleet page's heat map shows at most this many recordings (each robot's page has its own)
HEAT_MAX = 24
ROBOT_TEMPLATE = "audit_robot.html.j2"


def robot_file(robot_id: str) -> str:
    """The robot's page, relative to ``audit.html``: ``robots/cell-3.html``; a name with
    other characters than letters, digits, ``-`` and ``_`` is kept readable and made unique
    by a hash of it (``robots/cell_3-1a2b3c4d.html`` for ``cell 3``)."""
    rid = str(robot_id)
    slug = re.sub(r"[^A-Za-z0-9_-]+", "_", rid)[:60]
    if slug != rid or not slug:
        slug = f"{slug}-{hashlib.sha1(rid.encode()).hexdigest()[:8]}".lstrip("-")
    return f"robots/{slug}.html"


def _anchor(robot_id: str) -> str:
    """The id of the robot's row on the fleet page."""
    return "robot-" + robot_file(robot_id)[len("robots/") : -len(".html")]


def _spark(recs: Rows) -> str:
    """The robot's drift per recording as a sparkline (dates across), tolerance dashed."""
    drift = np.array([r["drift_mm"] for r in recs], float)
    tol = float(recs[-1].get("tolerance_mm", math.nan))
    shown = ", ".join(fmt(d, 4) for d in drift[np.isfinite(drift)])
    title = f"drift per recording: {shown} mm"
    title += f" (tolerance {short(tol)} mm)" if math.isfinite(tol) else ""
    days = np.array([r["stamp_ns"] for r in recs], float) / DAY_NS
    return sparkline(days, drift, tol, title=title)


class Grouped:
    """The audit's rows grouped once (:func:`rows_of`): per robot its recordings in order,
    its history comparisons and the comparisons of robots it is in; per recording its
    models. Hundreds of robots' pages read these, not the tables."""

    def __init__(self, res: AuditResult) -> None:
        self.recs: dict[str, Rows] = {}
        for r in sorted(rows_of(res.recordings), key=lambda r: (r["index"], r["stamp_ns"])):
            self.recs.setdefault(r["robot_id"], []).append(r)
        self.hist: dict[str, Rows] = {}
        self.cross: dict[str, Rows] = {}
        for c in rows_of(res.changes):
            if c["comparison"] == "history":
                self.hist.setdefault(c["robot_id"], []).append(c)
            elif c["comparison"] == "robots":
                for rid in dict.fromkeys((c["from_robot_id"], c["robot_id"])):
                    self.cross.setdefault(rid, []).append(c)
        self.models: dict[str, Rows] = {}
        for m in rows_of(res.models) if len(res.models) else []:
            self.models.setdefault(m["recording"], []).append(m)


def fleet_rows(res: AuditResult, status: Rows, grouped: Grouped | None = None) -> Rows:
    """The fleet table's rows, in ``status``'s order (:func:`fleet_status_rows`)."""
    recs = (grouped or Grouped(res)).recs
    rows = []
    for r in status:
        rows.append(
            {
                "id": r["robot_id"], "href": robot_file(r["robot_id"]),
                "anchor": _anchor(r["robot_id"]), "status": r["status"],
                "date": _date(r["last_stamp_ns"]), "overdue": r["overdue"],
                "n": r["n_recordings"], "drift": fmt(r["drift_mm"], 4),
                "spark": _spark(recs[r["robot_id"]]), "reading": reading(r),
                "age": f"{r['age_days']:.0f}",
            }
        )  # fmt: skip
    return rows


def render_page(
    res: AuditResult,
    *,
    now_ns: int | None = None,
    interval_days: float | None = None,
    grouped: Grouped | None = None,
) -> str:
    """The fleet page, ``audit.html`` (see the module docstring); ``now_ns`` the audit's
    time (the clock's when None), ``interval_days`` when a robot is overdue."""
    now = time.time_ns() if now_ns is None else int(now_ns)
    status = fleet_status_rows(res.recordings, res.changes, now_ns=now, interval_days=interval_days)
    counts = {s: sum(r["status"] == s for r in status) for s in STATUSES}
    cross = rows_of(res.changes[res.changes["comparison"] == "robots"])
    n_recs = res.recordings["recording"].nunique()
    heat = heatmap_svg(res.models) if 0 < n_recs <= HEAT_MAX and len(res.models) else ""
    rows = fleet_rows(res, status, grouped)
    firsts = {s: next((r["anchor"] for r in rows if r["status"] == s), "") for s in STATUSES}
    return render_template(
        TEMPLATE, fmt, fleet=rows, counts=counts, firsts=firsts, cross=cross, heat=heat,
        n_recordings=n_recs, ranking=rows_of(res.ranking), version=__version__,
        now=_date(now), interval_days=interval_days, short=short, robot_file=robot_file,
    )  # fmt: skip


def _why(row: dict[Any, Any]) -> str:
    """The robot page's reason for its status: the fleet row's, and how late when overdue."""
    parts = [reading(row)] if reading(row) else []
    if row["overdue"]:
        parts.append(f"{row['age_days']:.0f} days since its last recording")
    return "; ".join(parts)


def render_robot_page(
    res: AuditResult,
    robot_id: str,
    row: dict[Any, Any] | None = None,
    grouped: Grouped | None = None,
) -> str:
    """One robot's page, ``robots/ROBOT.html`` (see the module docstring); ``row`` its line
    of :func:`pipeline.audit.attention.fleet_status` (its status said at the top), if known;
    ``grouped`` the audit's rows (:class:`Grouped`) when many pages are written."""
    g = grouped or Grouped(res)
    recs, ch = g.recs[robot_id], g.hist.get(robot_id, [])
    models = [m for r in recs for m in g.models.get(r["recording"], [])]
    return render_template(
        ROBOT_TEMPLATE, fmt, id=robot_id, model=recs[0]["model"], svg=timeline_svg(recs, ch),
        rows=recs, changes=ch, cross=g.cross.get(robot_id, []),
        heat=heatmap_svg(models) if models else "", status=row["status"] if row else "",
        reading=_why(row) if row else "",
        fleet=f"../audit.html#{_anchor(robot_id)}", version=__version__, date=_date,
        robot_file=robot_file,
    )  # fmt: skip


def write_pages(
    res: AuditResult, out: Path, *, now_ns: int | None = None, interval_days: float | None = None
) -> Path:
    """Write ``out/audit.html`` and each robot's ``out/robots/ROBOT.html``; the first's path."""
    from pipeline.io.fileio import atomic_write_bytes

    now = time.time_ns() if now_ns is None else int(now_ns)
    grouped = Grouped(res)
    status = fleet_status_rows(
        [r for recs in grouped.recs.values() for r in recs], res.changes, now_ns=now,
        interval_days=interval_days,
    )  # fmt: skip
    (out / "robots").mkdir(parents=True, exist_ok=True)
    for row in status:
        page = render_robot_page(res, row["robot_id"], row, grouped)
        atomic_write_bytes(out / robot_file(row["robot_id"]), page.encode())
    path = out / "audit.html"
    page = render_page(res, now_ns=now, interval_days=interval_days, grouped=grouped)
    atomic_write_bytes(path, page.encode())
    return path
