"""A small SVG canvas for the report's plots: axes, ticks, lines, markers, bars, legends.

The report's plots are a few hundred points each; a plotting library would cost
a second to import and a fraction of one per figure to lay out. This writes the
``<svg>`` text directly: every coordinate is formatted with a fixed precision,
so the same inputs give the same bytes (the report is deterministic).

Conventions: sizes in CSS pixels, text in the page's sans-serif font; a panel
maps data ``(x, y)`` to pixels by ``px = left + (x - x0) / (x1 - x0) * width``
(``log10`` of the values on a log axis), ``y`` upwards.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from html import escape

import numpy as np
from numpy.typing import ArrayLike

from pipeline.io.numfmt import short

FONT = 'font-family="sans-serif" font-size="11"'
GRID = "#d0d7de"
AXIS = "#57606a"


def _f(v: float) -> str:
    """A pixel coordinate as text (0.1 px is finer than any screen shows)."""
    return f"{v:.1f}"


def label(v: float) -> str:
    """A tick value as a short plain number (``0.25``, ``10``, ``1e-5``)."""
    return short(v, 6)


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values (steps 1, 2, 2.5 or 5 times a power of ten) in [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw = (hi - lo) / max(n, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9)
    ticks = []
    k = first
    while k * step <= hi + step * 1e-9:
        ticks.append(round(k * step, 12))
        k += 1
    return ticks


def log_ticks(lo: float, hi: float) -> list[float]:
    """Powers of ten in [lo, hi]; with fewer than two, also their 2x and 5x multiples."""
    a, b = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    dec = [10.0**k for k in range(a, b + 1) if lo * (1 - 1e-9) <= 10.0**k <= hi * (1 + 1e-9)]
    if len(dec) >= 2:
        return dec
    out = [m * 10.0**k for k in range(a, b + 1) for m in (1.0, 2.0, 5.0)]
    return [v for v in out if lo * (1 - 1e-9) <= v <= hi * (1 + 1e-9)]


def padded(lo: float, hi: float, frac: float = 0.05) -> tuple[float, float]:
    """``[lo, hi]`` widened by ``frac`` of its span each side (a unit span if empty)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return 0.0, 1.0
    if hi <= lo:
        d = abs(lo) * 0.1 or 1.0
        return lo - d, hi + d
    d = (hi - lo) * frac
    return lo - d, hi + d


class Panel:
    """One set of axes on a canvas: limits, scales, and the elements drawn in it."""

    def __init__(
        self,
        box: tuple[float, float, float, float],
        xlim: tuple[float, float],
        ylim: tuple[float, float],
        *,
        ylog: bool = False,
        xlog: bool = False,
    ) -> None:
        self.left, self.top, self.width, self.height = box
        self.xlim, self.ylim, self.ylog, self.xlog = xlim, ylim, ylog, xlog
        self.parts: list[str] = []
        self.legend: list[tuple[str, str, str, float]] = []  # (label, colour, kind, size)
        #: where the legend goes: ``inside`` (the axes' top right corner), or off the data:
        #: ``above`` the axes, to their ``right`` or ``below`` them (under the x label); the
        #: caller reserves the room there (:func:`legend_height`, :func:`legend_width`)
        self.legend_at = "inside"

    def X(self, x: np.ndarray | float) -> np.ndarray:
        """Data x to pixels (log10 on a log axis)."""
        v = np.asarray(x, dtype=float)
        x0, x1 = self.xlim
        if self.xlog:
            with np.errstate(divide="ignore", invalid="ignore"):
                v, x0, x1 = np.log10(v), math.log10(x0), math.log10(x1)
        return np.asarray(self.left + (v - x0) / (x1 - x0) * self.width)

    def Y(self, y: np.ndarray | float) -> np.ndarray:
        """Data y to pixels (y up; log10 on a log axis)."""
        v = np.asarray(y, dtype=float)
        y0, y1 = self.ylim
        if self.ylog:
            with np.errstate(divide="ignore", invalid="ignore"):
                v, y0, y1 = np.log10(v), math.log10(y0), math.log10(y1)
        return np.asarray(self.top + self.height - (v - y0) / (y1 - y0) * self.height)

    def line(
        self,
        x: Sequence[float] | np.ndarray,
        y: Sequence[float] | np.ndarray,
        color: str,
        width: float = 1.2,
        *,
        dash: str = "",
        markers: float = 0.0,
        opacity: float = 1.0,
    ) -> None:
        """A polyline broken at non-finite points; ``markers`` > 0 adds dots of that diameter."""
        px, py = self.X(np.asarray(x, float)), self.Y(np.asarray(y, float))
        ok = np.isfinite(px) & np.isfinite(py)
        d, pen = [], False
        for a, b, good in zip(px, py, ok, strict=True):
            if not good:
                pen = False
                continue
            d.append(f"{'L' if pen else 'M'}{_f(a)} {_f(b)}")
            pen = True
        if d:
            extra = f' stroke-dasharray="{dash}"' if dash else ""
            op = f' stroke-opacity="{opacity:g}"' if opacity < 1 else ""
            self.parts.append(
                f'<path d="{"".join(d)}" fill="none" stroke="{color}" '
                f'stroke-width="{width:g}"{extra}{op}/>'
            )
        if markers > 0:
            self.dots(px[ok], py[ok], color, markers, pixels=True, opacity=opacity)

    def dots(
        self,
        x: np.ndarray,
        y: np.ndarray,
        color: str,
        size: float,
        *,
        pixels: bool = False,
        opacity: float = 1.0,
    ) -> None:
        """Round dots of diameter ``size`` px at the points (one path element for all)."""
        px, py = (x, y) if pixels else (self.X(x), self.Y(y))
        ok = np.isfinite(px) & np.isfinite(py)
        if not ok.any():
            return
        d = "".join(f"M{_f(a)} {_f(b)}h0" for a, b in zip(px[ok], py[ok], strict=True))
        op = f' stroke-opacity="{opacity:g}"' if opacity < 1 else ""
        self.parts.append(
            f'<path d="{d}" stroke="{color}" stroke-width="{size:g}" stroke-linecap="round"{op}/>'
        )

    def _marks(
        self, x: np.ndarray, y: np.ndarray, path: Callable[[float, float, float], str],
        size: float, style: str,
    ) -> None:  # fmt: skip
        """One path element of ``path(px, py, size)`` at every finite point, ``style``d."""
        px, py = self.X(x), self.Y(y)
        d = "".join(
            path(float(a), float(b), size)
            for a, b in zip(px, py, strict=True)
            if math.isfinite(a) and math.isfinite(b)
        )
        if d:
            self.parts.append(f'<path d="{d}" {style}/>')

    def crosses(self, x: np.ndarray, y: np.ndarray, color: str, size: float = 8.0) -> None:
        """``x`` markers of ``size`` px at the points."""
        self._marks(x, y, cross_path, size, f'stroke="{color}" stroke-width="1.8"')

    def rings(
        self, x: np.ndarray, y: np.ndarray, color: str, size: float, width: float = 2.0
    ) -> None:
        """Open circles of diameter ``size`` px at the points (one path element for all):
        what lies at a point, e.g. a target's cross, shows through a ring drawn over it."""
        self._marks(x, y, ring_path, size, f'fill="none" stroke="{color}" stroke-width="{width:g}"')

    def rect(self, x0: float, x1: float, y0: float, y1: float, color: str) -> None:
        """A filled rectangle between data corners (a bar)."""
        a, b = self.X(np.array([x0, x1])), self.Y(np.array([y0, y1]))
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            return
        self.parts.append(
            f'<rect x="{_f(min(a))}" y="{_f(min(b))}" width="{_f(abs(a[1] - a[0]))}" '
            f'height="{_f(abs(b[1] - b[0]))}" fill="{color}"/>'
        )

    def polygon(self, x: np.ndarray, y: np.ndarray, color: str, opacity: float) -> None:
        """A filled closed outline (a step histogram)."""
        px, py = self.X(x), self.Y(y)
        d = "".join(
            f"{'L' if i else 'M'}{_f(a)} {_f(b)}"
            for i, (a, b) in enumerate(zip(px, py, strict=True))
        )
        self.parts.append(
            f'<path d="{d}Z" fill="{color}" fill-opacity="{opacity:g}" stroke="{color}"/>'
        )

    def text(
        self, x: float, y: float, s: str, dx: float = 3, dy: float = -3, size: int = 9
    ) -> None:
        """A text label at a data point, offset by ``(dx, dy)`` px."""
        px, py = float(self.X(x)), float(self.Y(y))
        if math.isfinite(px) and math.isfinite(py):
            self.parts.append(
                f'<text x="{_f(px + dx)}" y="{_f(py + dy)}" font-size="{size}">{escape(s)}</text>'
            )

    def labels(
        self,
        x: Sequence[float],
        y: Sequence[float],
        texts: Sequence[str],
        size: int = 8,
        bounds: tuple[float, float, float, float] | None = None,
    ) -> None:
        """Text labels at data points, none over another (:func:`place_labels`): a label
        moved away from its point is tied to it by a thin leader line."""
        px = [float(v) for v in self.X(np.asarray(x, dtype=float))]
        py = [float(v) for v in self.Y(np.asarray(y, dtype=float))]
        area = bounds or (self.left, self.top, self.left + self.width, self.top + self.height)
        for (tx, ty, lead), s, ax, ay in zip(
            place_labels(px, py, texts, size, area), texts, px, py, strict=True
        ):
            if lead:
                w = text_width(s, size)
                ex = min(max(ax, tx), tx + w)  # the leader ends on the label's nearer edge
                ey = ty - size * 0.35
                self.parts.append(
                    f'<path d="M{_f(ax)} {_f(ay)}L{_f(ex)} {_f(ey)}" stroke="{AXIS}" '
                    'stroke-width="0.6"/>'
                )
            self.parts.append(
                f'<text x="{_f(tx)}" y="{_f(ty)}" font-size="{size}">{escape(s)}</text>'
            )

    def key(self, name: str, color: str, kind: str = "line", size: float = 6.0) -> None:
        """Add a legend entry drawn like the marks it names (``kind``: line, dot, box,
        cross, ring; ``size``: the dot's or ring's diameter or the cross's width, px)."""
        self.legend.append((name, color, kind, size))

    def render(
        self,
        *,
        xlabel: str = "",
        ylabel: str = "",
        title: str = "",
        xticks: list[tuple[float, str]] | None = None,
        legend_title: str = "",
    ) -> str:
        """The panel: grid, axes, ticks, labels, its elements and legend."""
        L, T, W, H = self.left, self.top, self.width, self.height
        out = []
        if self.ylog:
            yt = log_ticks(*self.ylim)
        else:
            yt = nice_ticks(*self.ylim)
        auto = log_ticks(*self.xlim) if self.xlog else nice_ticks(*self.xlim)
        xt = xticks if xticks is not None else [(v, label(v)) for v in auto]
        for v in yt:
            y = float(self.Y(v))
            out.append(f'<path d="M{_f(L)} {_f(y)}h{_f(W)}" stroke="{GRID}"/>')
            out.append(
                f'<text x="{_f(L - 4)}" y="{_f(y + 3.5)}" text-anchor="end">{label(v)}</text>'
            )
        for v, s in xt:
            x = float(self.X(v))
            if xticks is None:
                out.append(f'<path d="M{_f(x)} {_f(T)}v{_f(H)}" stroke="{GRID}"/>')
            out.append(
                f'<text x="{_f(x)}" y="{_f(T + H + 13)}" text-anchor="middle">{escape(s)}</text>'
            )
        out.append(
            f'<path d="M{_f(L)} {_f(T)}V{_f(T + H)}H{_f(L + W)}" stroke="{AXIS}" fill="none"/>'
        )
        out.append(f"<g>{''.join(self.parts)}</g>")
        if xlabel:
            out.append(
                f'<text x="{_f(L + W / 2)}" y="{_f(T + H + 28)}" text-anchor="middle">'
                f"{escape(xlabel)}</text>"
            )
        if ylabel:
            cx, cy = L - 42, T + H / 2
            out.append(
                f'<text x="{_f(cx)}" y="{_f(cy)}" text-anchor="middle" '
                f'transform="rotate(-90 {_f(cx)} {_f(cy)})">{escape(ylabel)}</text>'
            )
        if title:
            out.append(
                f'<text x="{_f(L + W / 2)}" y="{_f(T - 8)}" text-anchor="middle">{escape(title)}</text>'
            )
        if self.legend:
            out.append(self._legend(legend_title))
        return "".join(out)

    def _legend(self, title: str) -> str:
        rows = ([(title, "", "title", 0.0)] if title else []) + self.legend
        width = legend_width([n for n, _, _, _ in rows])
        x, y = self.left + self.width - width, self.top + 4
        if self.legend_at == "above":
            y = self.top - legend_height(len(rows))
        elif self.legend_at == "right":
            x = self.left + self.width + LEGEND_GAP
        elif self.legend_at == "below":
            x, y = self.left, self.top + self.height + LEGEND_BELOW
        out = [
            f'<rect x="{_f(x - 4)}" y="{_f(y - 2)}" width="{_f(width + 4)}" '
            f'height="{_f(14 * len(rows) + 2)}" fill="white" fill-opacity="0.8"/>'
        ]
        for i, (name, color, kind, size) in enumerate(rows):
            cy = y + 14 * i + 7
            if kind == "box":
                out.append(
                    f'<rect x="{_f(x)}" y="{_f(cy - 4)}" width="12" height="8" fill="{color}"/>'
                )
            elif kind == "dot":
                out.append(
                    f'<path d="M{_f(x + 6)} {_f(cy)}h0" stroke="{color}" '
                    f'stroke-width="{min(size, 10.0):g}" stroke-linecap="round"/>'
                )
            elif kind == "cross":
                out.append(
                    f'<path d="{cross_path(x + 6, cy, min(size, 10.0))}" stroke="{color}" '
                    'stroke-width="1.8"/>'
                )
            elif kind == "ring":
                out.append(
                    f'<path d="{ring_path(x + 6, cy, min(size, 12.0))}" fill="none" '
                    f'stroke="{color}" stroke-width="2"/>'
                )
            elif kind == "line":
                out.append(f'<path d="M{_f(x)} {_f(cy)}h12" stroke="{color}" stroke-width="2"/>')
            tx = x if kind == "title" else x + 16
            out.append(f'<text x="{_f(tx)}" y="{_f(cy + 3.5)}">{escape(name)}</text>')
        return "".join(out)


#: height of one legend row, px
LEGEND_ROW = 14.0
#: gap between the axes and a legend to their right, px
LEGEND_GAP = 14.0
#: a legend below the axes starts this far under them (below the ticks and x label), px
LEGEND_BELOW = 38.0
#: side of the square a labelled point keeps free of labels, px
POINT_BOX = 7.0
#: estimated advance of one character, in font sizes (the page's sans-serif; wide side)
CHAR_WIDTH = 0.6


def legend_height(rows: int) -> float:
    """Pixels a legend of ``rows`` rows takes (its box and a gap below it)."""
    return LEGEND_ROW * rows + 6.0


def legend_width(names: Sequence[str]) -> float:
    """Pixels a legend with these entries takes across (swatch, gap and the longest name)."""
    return 22 + 6.2 * max([len(n) for n in names] + [0])


def cross_path(x: float, y: float, size: float) -> str:
    """Path data of an ``x`` marker of ``size`` px centred at pixel ``(x, y)``."""
    h = size / 2
    return f"M{_f(x - h)} {_f(y - h)}l{size:g} {size:g}M{_f(x - h)} {_f(y + h)}l{size:g} {-size:g}"


def ring_path(x: float, y: float, size: float) -> str:
    """Path data of a circle of diameter ``size`` px centred at pixel ``(x, y)`` (two arcs)."""
    r = size / 2
    return f"M{_f(x - r)} {_f(y)}a{r:g} {r:g} 0 1 0 {size:g} 0a{r:g} {r:g} 0 1 0 {-size:g} 0"


def text_width(s: str, size: float) -> float:
    """Estimated width in px of ``s`` at font size ``size`` (:data:`CHAR_WIDTH` per char)."""
    return CHAR_WIDTH * size * len(s)


def text_box(x: float, y: float, s: str, size: float) -> tuple[float, float, float, float]:
    """``(x0, y0, x1, y1)`` px of a start-anchored text at baseline ``(x, y)``: from the
    ascender (one font size above the baseline) to the descender (a fifth below)."""
    return (x, y - size, x + text_width(s, size), y + 0.2 * size)


def _overlap(a: tuple[float, ...], b: tuple[float, ...], pad: float = 1.0) -> float:
    """Area (px^2) shared by two boxes ``(x0, y0, x1, y1)``, each grown by ``pad``."""
    w = min(a[2], b[2]) - max(a[0], b[0]) + 2 * pad
    h = min(a[3], b[3]) - max(a[1], b[1]) + 2 * pad
    return max(w, 0.0) * max(h, 0.0)


def place_labels(
    px: Sequence[float],
    py: Sequence[float],
    texts: Sequence[str],
    size: float,
    area: tuple[float, float, float, float],
) -> list[tuple[float, float, bool]]:
    """Greedy placement of text labels next to their points, no two on top of each other.

    Each label (in order of its point's x) takes the first free spot in a fixed list:
    just above its point, then below, then further above and below in steps of one line,
    each to the right of the point and then to its left; a spot must keep the label
    inside ``area`` ``(x0, y0, x1, y1)`` px and off every label already placed (boxes of
    :func:`text_box`) and every point (a :data:`POINT_BOX` px square). When no spot is free
    the one overlapping least is taken. Returns,
    per label in the given order, its baseline start ``(x, y)`` and whether it is off its
    point (then the caller ties it with a leader line).
    """
    line = size * 1.3
    offsets = [-0.5 * size] + [
        d for k in range(1, 12) for d in (-0.5 * size - k * line, 1.2 * size + (k - 1) * line)
    ]
    h = POINT_BOX / 2
    placed = [(x - h, y - h, x + h, y + h) for x, y in zip(px, py, strict=True)]
    out: list[tuple[float, float, bool]] = [(0.0, 0.0, False)] * len(texts)
    for i in sorted(range(len(texts)), key=lambda k: (px[k], py[k])):
        w = text_width(texts[i], size)
        best: tuple[float, float, float, int] | None = None  # (overlap, x, y, rank)
        for rank, dy in enumerate(offsets):
            for x in (px[i] + 6, px[i] - 6 - w):
                y = py[i] + dy
                box = text_box(x, y, texts[i], size)
                if box[0] < area[0] or box[2] > area[2] or box[1] < area[1] or box[3] > area[3]:
                    continue
                cost = sum(_overlap(box, b) for b in placed)
                if best is None or cost < best[0]:
                    best = (cost, x, y, rank)
                if cost == 0:
                    break
            if best is not None and best[0] == 0:
                break
        if best is None:  # no spot inside the area: above the point, clamped across
            x = min(max(px[i] + 6, area[0]), area[2] - w)
            best = (0.0, x, py[i] - 0.5 * size, 0)
        _, x, y, rank = best
        placed.append(text_box(x, y, texts[i], size))
        out[i] = (x, y, rank > 0)
    return out


def canvas(width: float, height: float, body: Sequence[str]) -> str:
    """The ``<svg>`` element holding the rendered panels."""
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:g}" height="{height:g}" '
        f'viewBox="0 0 {width:g} {height:g}" {FONT} fill="#24292f">{"".join(body)}</svg>'
    )


def sparkline(
    xs: ArrayLike,
    ys: ArrayLike,
    ref: float | None = None,
    *,
    width: float = 96.0,
    height: float = 20.0,
    colour: str = "#57606a",
    over: str = "#cf222e",
    title: str = "",
) -> str:
    """A word-sized ``<svg>`` of ``ys`` over ``xs``: one line through the finite points,
    ``ref`` as a dashed line, the last point a dot (``over`` when above ``ref``). No axes,
    no text: a table cell's picture of a history, for an HTML page (no ``xmlns``). Empty
    when no point is finite."""
    x, y = np.asarray(xs, float), np.asarray(ys, float)
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return ""
    x, y = x[ok], y[ok]
    pad = 2.5
    hi = max(float(y.max()), ref if ref is not None and math.isfinite(ref) else 0.0, 0.0)
    hi = hi * 1.1 or 1.0
    lo = min(float(y.min()), 0.0)
    x0, span = float(x.min()), float(x.max() - x.min())
    px = pad + (x - x0) / span * (width - 2 * pad) if span > 0 else np.full(len(x), width / 2)
    py = height - pad - (y - lo) / (hi - lo) * (height - 2 * pad)
    parts = [f"<title>{escape(title)}</title>"] if title else []
    if ref is not None and math.isfinite(ref):
        ry = _f(height - pad - (ref - lo) / (hi - lo) * (height - 2 * pad))
        parts.append(
            f'<path d="M0 {ry}H{width:g}" stroke="{GRID}" stroke-dasharray="3 2" fill="none"/>'
        )
    if len(px) > 1:
        d = "M" + "L".join(f"{_f(a)} {_f(b)}" for a, b in zip(px, py, strict=True))
        parts.append(f'<path d="{d}" stroke="{colour}" stroke-width="1.3" fill="none"/>')
    last = over if ref is not None and y[-1] > ref else colour
    parts.append(f'<circle cx="{_f(px[-1])}" cy="{_f(py[-1])}" r="2.2" fill="{last}"/>')
    return (
        f'<svg class="spark" width="{width:g}" '
        f'height="{height:g}" viewBox="0 0 {width:g} {height:g}">{"".join(parts)}</svg>'
    )
