"""Inline SVG plots of the report (matplotlib, byte-stable output).

Every function takes plain arrays and returns an ``<svg>`` element as text,
ready to be placed in the HTML as it is. Output is deterministic: the SVG
hash salt is fixed, the date metadata is dropped and fonts are drawn as
paths-free text (``svg.fonttype = none``), so the same inputs give the same bytes.
"""

from __future__ import annotations

import io
import re
from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import FuncFormatter, NullLocator  # noqa: E402

_RC: Any = {
    "svg.hashsalt": "vtcal-report",
    "svg.fonttype": "none",
    "font.family": "sans-serif",
    "font.size": 9.0,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "figure.dpi": 96,
}
#: colours: before / after / rejected / other
BEFORE = "#b0b7c3"
AFTER = "#1f6feb"
REJECT = "#d1242f"
COLORS = ["#1f6feb", "#e36209", "#2da44e", "#8250df", "#bf3989", "#0a7d8c", "#6e7781"]


def _figure(w: float = 6.4, h: float = 2.8) -> Figure:
    """A figure with fixed margins (constrained layout doubles the rendering time)."""
    with plt.rc_context(_RC):
        fig = Figure(figsize=(w, h))
    # margins in inches, so every plot's text has the same room whatever its size
    fig.subplots_adjust(
        left=0.75 / w, right=1 - 0.15 / w, bottom=0.5 / h, top=1 - 0.3 / h, wspace=0.45
    )
    return fig


def to_svg(fig: Figure) -> str:
    """Render a figure to an inline ``<svg>`` string (no XML prolog, no date)."""
    buf = io.StringIO()
    with plt.rc_context(_RC):
        fig.savefig(buf, format="svg", metadata={"Date": None})
    text = buf.getvalue()
    start = text.find("<svg")
    text = text[start:] if start >= 0 else text
    # drop the RDF metadata block (creator links): the page needs none of it
    return re.sub(r"\s*<metadata>.*?</metadata>", "", text, count=1, flags=re.DOTALL)


def _plain(v: float, _pos: Any = None) -> str:
    """A tick label as a plain number (``0.01``, ``1``, ``1e+03``), no mathtext."""
    return f"{v:g}"


def histogram(groups: Mapping[str, np.ndarray], xlabel: str, title: str = "") -> str:
    """Overlaid histograms of one quantity per group (e.g. residual mm, before/after)."""
    with plt.rc_context(_RC):
        fig = _figure()
        ax = fig.add_subplot()
        vals = [np.asarray(v, dtype=float) for v in groups.values()]
        allv = np.concatenate([v[np.isfinite(v)] for v in vals]) if vals else np.zeros(0)
        hi = float(np.max(allv)) if allv.size else 1.0
        bins = np.linspace(0.0, hi * 1.05 if hi > 0 else 1.0, 25)
        ci = 0
        for name, v in groups.items():
            v = np.asarray(v, dtype=float)
            v = v[np.isfinite(v)]
            color = _group_color(name, ci)
            ci += color != BEFORE
            # one filled outline per group (a patch per bar costs a draw call each)
            ax.hist(
                v,
                bins=list(bins),
                histtype="stepfilled",
                alpha=0.6,
                color=color,
                label=f"{name} (n={len(v)})",
            )
        ax.set_xlabel(xlabel)
        ax.set_ylabel("touch-ups")
        if title:
            ax.set_title(title)
        if groups:
            ax.legend(frameon=False)
        return to_svg(fig)


def _group_color(name: str, i: int) -> str:
    """Grey for the nominal (before) group, then blue, orange, ... for the models."""
    if name.lower().startswith(("nominal", "before")):
        return BEFORE
    return COLORS[i % len(COLORS)]


def per_target(
    target_ids: Sequence[str], values_mm: Mapping[str, Sequence[np.ndarray]], ylabel: str
) -> str:
    """Per-target strip plot: each touch-up's residual (mm) as a dot, one column per target."""
    with plt.rc_context(_RC):
        fig = _figure(6.4, 2.8)
        ax = fig.add_subplot()
        ng = max(len(values_mm), 1)
        width = 0.7 / ng
        ci = 0
        for gi, (name, per) in enumerate(values_mm.items()):
            color = _group_color(name, ci)
            ci += color != BEFORE
            for ti, v in enumerate(per):
                v = np.asarray(v, dtype=float)
                x = ti + (gi - (ng - 1) / 2) * width + np.linspace(-0.25, 0.25, len(v)) * width
                ax.scatter(x, v, s=14, color=color, label=name if ti == 0 else None, zorder=3)
                if len(v):
                    rms = float(np.sqrt(np.mean(v * v)))
                    xc = ti + (gi - (ng - 1) / 2) * width
                    ax.hlines(rms, xc - width / 2, xc + width / 2, color=color, lw=2)
        ax.set_xticks(range(len(target_ids)), [f"target {t}" for t in target_ids])
        ax.set_ylabel(ylabel)
        ax.set_ylim(bottom=0)
        ax.legend(frameon=False, title="dots: touch-ups, bars: RMS", title_fontsize=8)
        return to_svg(fig)


def bars(labels: Sequence[str], series: Mapping[str, Sequence[float]], ylabel: str) -> str:
    """Grouped bar chart (e.g. held-out RMS and max per error model)."""
    with plt.rc_context(_RC):
        fig = _figure(6.4, 2.6)
        ax = fig.add_subplot()
        x = np.arange(len(labels))
        ng = max(len(series), 1)
        w = 0.8 / ng
        for i, (name, vals) in enumerate(series.items()):
            v = np.array([np.nan if a is None else a for a in vals], dtype=float)
            ax.bar(
                x + (i - (ng - 1) / 2) * w, v, width=w, color=COLORS[i % len(COLORS)], label=name
            )
        ax.set_xticks(x, list(labels))
        ax.set_ylabel(ylabel)
        allv = np.array([a for vals in series.values() for a in vals if a is not None], float)
        top = float(np.nanmax(allv)) if allv.size and np.isfinite(allv).any() else 1.0
        ax.set_ylim(0, top * 1.3 if top > 0 else 1.0)  # headroom for the legend
        ax.set_xlim(-0.6, len(labels) - 0.4 + (0.6 if len(labels) == 1 else 0.0))
        if len(series) > 1:
            ax.legend(frameon=False, loc="upper right", ncols=len(series))
        return to_svg(fig)


def convergence(
    traces: Mapping[str, np.ndarray], thresholds: Sequence[float | None], units: Sequence[str]
) -> str:
    """e_T per iteration, one panel per component, one line per touch-up.

    ``traces[label]`` is ``(k, 3)``: ``(du, dv, ds)`` of each capture of the
    touch-up, in px. The convergence thresholds are drawn as bands.
    """
    names = ("du", "dv", "ds")
    with plt.rc_context(_RC):
        fig = _figure(6.8, 2.6)
        axes = fig.subplots(1, 3, sharex=True)
        for k, ax in enumerate(axes):
            # one line per colour, the touch-ups joined by NaN breaks: 7 artists a panel,
            # not one per touch-up (rendering time grows with the artists, not the points)
            runs: dict[int, list[np.ndarray]] = {}
            for i, tr in enumerate(traces.values()):
                tr = np.asarray(tr, dtype=float)
                if tr.ndim != 2 or tr.shape[1] <= k:
                    continue
                y = np.abs(tr[:, k])
                y = np.where(y > 0, y, np.nan)
                xy = np.column_stack([np.arange(len(y), dtype=float), y])
                runs.setdefault(i % len(COLORS), []).append(np.vstack([xy, [np.nan, np.nan]]))
            for c, parts in sorted(runs.items()):
                xy = np.vstack(parts)
                ax.plot(xy[:, 0], xy[:, 1], marker=".", lw=0.8, ms=3, color=COLORS[c], alpha=0.8)
            th = thresholds[k] if k < len(thresholds) else None
            if th:
                ax.axhline(th, color=REJECT, lw=0.8, ls="--")
            ax.set_yscale("log")
            # minor ticks of a log axis are a third of the plot's rendering time, and its
            # default labels (10^k) go through the mathtext parser: plain numbers instead
            ax.yaxis.set_minor_locator(NullLocator())
            ax.yaxis.set_major_formatter(FuncFormatter(_plain))
            ax.set_title(f"|{names[k]}| ({units[k] if k < len(units) else ''})")
            ax.set_xlabel("iteration")
        return to_svg(fig)


def scatter_xy(
    points: Mapping[str, np.ndarray], xlabel: str, ylabel: str, labels: Mapping[str, list[str]]
) -> str:
    """Top view (x, y) of point sets in the base frame, in m (targets, pin positions)."""
    with plt.rc_context(_RC):
        fig = _figure(4.2, 3.6)
        ax = fig.add_subplot()
        for i, (name, p) in enumerate(points.items()):
            p = np.asarray(p, dtype=float).reshape(-1, 3)
            first = i == 0  # the first set (targets) on top, as crosses
            ax.scatter(
                p[:, 0],
                p[:, 1],
                s=60 if first else 14,
                marker="x" if first else "o",
                color=COLORS[i % len(COLORS)],
                label=name,
                zorder=4 if first else 3,
            )
            for txt, (x, y) in zip(labels.get(name, []), p[:, :2], strict=False):
                ax.annotate(txt, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.legend(frameon=False, fontsize=7)
        return to_svg(fig)


def singular_values(sv: np.ndarray) -> str:
    """Singular values of the scaled identification Jacobian, log scale."""
    with plt.rc_context(_RC):
        fig = _figure(6.4, 2.4)
        ax = fig.add_subplot()
        s = np.asarray(sv, dtype=float)
        ax.semilogy(np.arange(1, len(s) + 1), s, marker="o", ms=3, color=AFTER)
        ax.set_xlabel("index")
        ax.set_ylabel("singular value")
        return to_svg(fig)


def along_view(tilt_deg: np.ndarray, beta_deg: np.ndarray, r_view_um: np.ndarray) -> str:
    """Touch-ups' residuals along the view (um) against the plate tilt and the long axis' direction."""
    with plt.rc_context(_RC):
        fig = _figure(6.4, 2.6)
        ax1, ax2 = fig.subplots(1, 2, sharey=True)
        ax1.scatter(tilt_deg, r_view_um, s=12, color=AFTER)
        ax1.set_xlabel("plate tilt to the view (deg)")
        ax1.set_ylabel("residual along the view (um)")
        ax2.scatter(np.mod(beta_deg, 180.0), r_view_um, s=12, color=AFTER)
        ax2.set_xlabel("long axis on the plate, beta mod 180 (deg)")
        for ax in (ax1, ax2):
            ax.axhline(0.0, color=BEFORE, lw=0.8)
        return to_svg(fig)
