"""Inline SVG plots of the report (drawn with :mod:`pipeline.report.svg`, byte-stable).

Every function takes plain arrays and returns an ``<svg>`` element as text,
ready to be placed in the HTML as it is. Output is deterministic: the same
inputs give the same bytes (coordinates are written with a fixed precision,
nothing depends on the date or the machine). No plotting library is loaded:
the report renders in milliseconds and ``vtcal report`` starts without one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from pipeline.io.numfmt import fmt
from pipeline.report.svg import (
    LEGEND_GAP,
    Panel,
    canvas,
    legend_height,
    legend_width,
    padded,
)

#: colours: before / after / rejected / other
BEFORE = "#b0b7c3"
AFTER = "#1f6feb"
REJECT = "#d1242f"
COLORS = ["#1f6feb", "#e36209", "#2da44e", "#8250df", "#bf3989", "#0a7d8c", "#6e7781"]
#: margins of a panel in px: left, right, top, bottom
MARGIN = (62.0, 12.0, 22.0, 40.0)
#: width of a target's cross and diameter of a pin's ring on the targets plot, px
TARGET_CROSS = 8.0
PIN_RING = 13.0


def _box(
    width: float, height: float, col: int = 0, cols: int = 1
) -> tuple[float, float, float, float]:
    """Pixel box ``(left, top, width, height)`` of panel ``col`` of ``cols`` side by side."""
    ml, mr, mt, mb = MARGIN
    cell = width / cols
    return (cell * col + ml, mt, cell - ml - mr, height - mt - mb)


def _finite(values: Sequence[np.ndarray] | list[np.ndarray]) -> np.ndarray:
    parts = [np.asarray(v, dtype=float).ravel() for v in values]
    allv = np.concatenate(parts) if parts else np.zeros(0)
    return allv[np.isfinite(allv)]


def _group_color(name: str, i: int) -> str:
    """Grey for the nominal (before) group, then blue, orange, ... for the models."""
    if name.lower().startswith(("nominal", "before")):
        return BEFORE
    return COLORS[i % len(COLORS)]


def _box_legend_above(width: float, height: float, rows: int) -> tuple[float, float, float, float]:
    """:func:`_box` with ``rows`` legend rows' height added to the top margin (the legend
    goes there, ``Panel.legend_at = "above"``); the canvas is that much taller."""
    left, top, w, h = _box(width, height)
    return (left, top + legend_height(rows), w, h)


def residual_ecdf(groups: Mapping[str, np.ndarray], xlabel: str) -> str:
    """Residuals (mm) per group as empirical cumulative distributions on a log x axis.

    One step curve per group (e.g. the nominal robot and each error model): at residual
    ``x`` the share of the group's touch-ups whose residual is at most ``x``. The log axis
    spreads the fitted models, whose residuals are tens of times below the nominal robot's
    and would share a histogram's first bin; the curve further left is the better fit, and
    its height at 0.5 is the median. The legend (with each group's median) sits to the right
    of the axes, off the data.
    """
    vals = {k: np.sort(_finite([v])) for k, v in groups.items()}
    pos = _finite([v[v > 0] for v in vals.values()])
    lo, hi = (float(pos.min()) / 1.5, float(pos.max()) * 1.5) if pos.size else (1e-3, 1.0)
    names = [
        f"{k}, median {fmt(float(np.median(v)) if len(v) else None)} mm" for k, v in vals.items()
    ]
    W, H = 614.0, 250.0
    left, top, _, h = _box(W, H)
    w = W - left - legend_width(names) - LEGEND_GAP - 6.0
    p = Panel((left, top, w, h), (lo, hi), (0.0, 1.05), xlog=True)
    p.legend_at = "right"
    ci = 0
    for (name, v), text in zip(vals.items(), names, strict=True):
        color = _group_color(name, ci)
        ci += color != BEFORE
        if len(v):
            x = np.clip(v, lo, hi)
            share = np.arange(1, len(v) + 1) / len(v)
            xs = np.r_[np.repeat(x, 2), hi]
            ys = np.r_[0.0, np.repeat(share, 2)]
            p.line(xs, ys, color, 1.8)
        p.key(text, color, "line")
    return canvas(W, H, [p.render(xlabel=xlabel, ylabel="share of touch-ups at or below")])


def per_target(
    target_ids: Sequence[str], values_mm: Mapping[str, Sequence[np.ndarray]], ylabel: str
) -> str:
    """Per-target strip plot: each touch-up's residual (mm) as a dot, one column per target;
    the legend sits above the axes, clear of the dots and bars."""
    allv = _finite([v for per in values_mm.values() for v in per])
    top = float(np.max(allv)) if allv.size else 1.0
    W, H0 = 614.0, 269.0
    box = _box_legend_above(W, H0, len(values_mm) + 1)  # + its title row
    H = H0 + box[1] - _box(W, H0)[1]
    p = Panel(box, (-0.6, len(target_ids) - 0.4), (0.0, top * 1.1 if top > 0 else 1.0))
    p.legend_at = "above"
    ng = max(len(values_mm), 1)
    width = 0.7 / ng
    ci = 0
    for gi, (name, per) in enumerate(values_mm.items()):
        color = _group_color(name, ci)
        ci += color != BEFORE
        for ti, v in enumerate(per):
            v = np.asarray(v, dtype=float)
            xc = ti + (gi - (ng - 1) / 2) * width
            x = xc + np.linspace(-0.25, 0.25, len(v)) * width
            p.dots(x, v, color, 5.0)
            if len(v):
                rms = float(np.sqrt(np.mean(v * v)))
                p.line([xc - width / 2, xc + width / 2], [rms, rms], color, 2.0)
        p.key(name, color, "dot")
    ticks = [(float(i), f"target {t}") for i, t in enumerate(target_ids)]
    return canvas(
        W,
        H,
        [p.render(ylabel=ylabel, xticks=ticks, legend_title="dots: touch-ups, bars: RMS")],
    )


def bars(labels: Sequence[str], series: Mapping[str, Sequence[float | None]], ylabel: str) -> str:
    """Grouped bar chart (e.g. held-out RMS and max per error model)."""
    allv = np.array([a for vals in series.values() for a in vals if a is not None], float)
    top = float(np.nanmax(allv)) if allv.size and np.isfinite(allv).any() else 1.0
    W, H = 614.0, 250.0
    xmax = len(labels) - 0.4 + (0.6 if len(labels) == 1 else 0.0)
    p = Panel(_box(W, H), (-0.6, xmax), (0.0, top * 1.3 if top > 0 else 1.0))
    ng = max(len(series), 1)
    w = 0.8 / ng
    for i, (name, vals) in enumerate(series.items()):
        color = COLORS[i % len(COLORS)]
        for j, a in enumerate(vals):
            if a is not None and math.isfinite(a):
                xc = j + (i - (ng - 1) / 2) * w
                p.rect(xc - w / 2, xc + w / 2, 0.0, float(a), color)
        if len(series) > 1:
            p.key(name, color, "box")
    ticks = [(float(j), str(s)) for j, s in enumerate(labels)]
    return canvas(W, H, [p.render(ylabel=ylabel, xticks=ticks)])


def convergence(
    traces: Mapping[str, np.ndarray], thresholds: Sequence[float | None], units: Sequence[str]
) -> str:
    """e_T per iteration, one panel per component, one line per touch-up (log scale).

    ``traces[label]`` is ``(k, 3)``: ``(du, dv, ds)`` of each capture of the
    touch-up, in px. The convergence thresholds are drawn as dashed lines.
    """
    names = ("du", "dv", "ds")
    W, H = 653.0, 250.0
    body = []
    arrs = [np.asarray(t, dtype=float) for t in traces.values()]
    n_it = max([len(t) for t in arrs] + [2])
    for k in range(3):
        ys = [np.abs(t[:, k]) for t in arrs if t.ndim == 2 and t.shape[1] > k]
        th = thresholds[k] if k < len(thresholds) else None
        pos = _finite([y[y > 0] for y in ys] + ([np.array([th])] if th else []))
        lo, hi = (float(pos.min()), float(pos.max())) if pos.size else (0.1, 10.0)
        lo, hi = (lo / 1.5, hi * 1.5) if hi > lo else (lo / 10, lo * 10)
        p = Panel(_box(W, H, k, 3), (-0.3, n_it - 0.7), (lo, hi), ylog=True)
        for i, y in enumerate(ys):
            y = np.where(y > 0, y, np.nan)
            p.line(np.arange(len(y)), y, COLORS[i % len(COLORS)], 0.8, markers=3.0, opacity=0.8)
        if th:
            p.line([-0.3, n_it - 0.7], [th, th], REJECT, 0.8, dash="4 3")
        unit = units[k] if k < len(units) else ""
        body.append(p.render(xlabel="iteration", title=f"|{names[k]}| ({unit})"))
    return canvas(W, H, body)


def scatter_xy(
    points: Mapping[str, np.ndarray], xlabel: str, ylabel: str, labels: Mapping[str, list[str]]
) -> str:
    """Top view (x, y) of point sets in the base frame, in the units given (the report: mm,
    as its tables), e.g. the targets and the pin at the touch-ups.

    Equal scale on both axes (the limits widen to fill the panel). The first set (the
    targets) is drawn as crosses, the others as rings of :data:`PIN_RING` px drawn over
    them: a pin touches its target, so a dot at a cross would hide it or be hidden, while
    the cross shows inside the ring. The legend, its swatches drawn like the marks, sits
    below the axes.
    """
    W, H0 = 403.0, 346.0
    box = _box(W, H0)
    H = H0 + legend_height(len(points))
    sets = {k: np.asarray(v, dtype=float).reshape(-1, 3) for k, v in points.items()}
    allp = np.vstack(list(sets.values())) if sets else np.zeros((0, 3))
    allp = allp[np.all(np.isfinite(allp[:, :2]), axis=1)]
    if len(allp):
        x0, x1 = padded(float(allp[:, 0].min()), float(allp[:, 0].max()), 0.1)
        y0, y1 = padded(float(allp[:, 1].min()), float(allp[:, 1].max()), 0.1)
    else:
        x0, x1, y0, y1 = 0.0, 1.0, 0.0, 1.0
    # equal aspect: the axis with less data per pixel widens about its centre
    per_px = max((x1 - x0) / box[2], (y1 - y0) / box[3])
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    xlim = (cx - per_px * box[2] / 2, cx + per_px * box[2] / 2)
    ylim = (cy - per_px * box[3] / 2, cy + per_px * box[3] / 2)
    p = Panel(box, xlim, ylim)
    p.legend_at = "below"
    names = list(sets)
    for i, name in enumerate(names):
        color = COLORS[i % len(COLORS)]
        if i == 0:
            p.key(name, color, "cross", TARGET_CROSS)
        else:
            p.key(name, color, "ring", PIN_RING)
    for i, name in enumerate(names):  # the targets first, the rings over them
        pts, color = sets[name], COLORS[i % len(COLORS)]
        if i == 0:
            p.crosses(pts[:, 0], pts[:, 1], color, TARGET_CROSS)
        else:
            p.rings(pts[:, 0], pts[:, 1], color, PIN_RING)
    for name in names:
        for txt, (x, y) in zip(labels.get(name, []), sets[name][:, :2], strict=False):
            p.text(float(x), float(y), txt, dx=8, dy=-7)
    return canvas(W, H, [p.render(xlabel=xlabel, ylabel=ylabel)])


def singular_values(sv: np.ndarray) -> str:
    """Singular values of the scaled identification Jacobian, log scale."""
    s = np.asarray(sv, dtype=float)
    pos = s[np.isfinite(s) & (s > 0)]
    lo, hi = (float(pos.min()) / 2, float(pos.max()) * 2) if pos.size else (0.1, 10.0)
    W, H = 614.0, 230.0
    p = Panel(_box(W, H), padded(1.0, float(max(len(s), 2))), (lo, hi), ylog=True)
    p.line(np.arange(1, len(s) + 1), np.where(s > 0, s, np.nan), AFTER, 1.2, markers=5.0)
    return canvas(W, H, [p.render(xlabel="index", ylabel="singular value")])


def along_view(tilt_deg: np.ndarray, beta_deg: np.ndarray, r_view_um: np.ndarray) -> str:
    """Touch-ups' residuals along the view (um) against the plate tilt and the long axis' direction."""
    r = np.asarray(r_view_um, dtype=float)
    fin = r[np.isfinite(r)]
    ylim = padded(min(float(fin.min()), 0.0), max(float(fin.max()), 0.0)) if fin.size else (-1, 1)
    W, H = 614.0, 250.0
    body = []
    xs = (np.asarray(tilt_deg, dtype=float), np.mod(np.asarray(beta_deg, dtype=float), 180.0))
    xlabels = ("plate tilt to the view (deg)", "long axis on the plate, beta mod 180 (deg)")
    for k, (x, xl) in enumerate(zip(xs, xlabels, strict=True)):
        fx = x[np.isfinite(x)]
        xlim = padded(float(fx.min()), float(fx.max())) if fx.size else (0.0, 1.0)
        p = Panel(_box(W, H, k, 2), xlim, ylim)
        p.line(list(xlim), [0.0, 0.0], BEFORE, 0.8)
        p.dots(x, r, AFTER, 5.0)
        body.append(p.render(xlabel=xl, ylabel="residual along the view (um)" if k == 0 else ""))
    return canvas(W, H, body)
