"""Line plots as inline SVG for the report: panels stacked on a shared x axis, nothing else.

The report's figures are simple (lines, markers, bars, bands, marks at a frequency), and
drawing them directly costs milliseconds where a general plotting library spends most of a
run's time laying out text. Long records are drawn as their min/max envelope per pixel
column (what the screen can show), so a 10 s record at 8 kHz costs ~1,600 points per line.

    fig = Figure(width=960, title="…")
    ax = fig.panel(height=260, x_scale="log", y_label="|L| [dB]")
    ax.line(f, mag, color="#1f77b4", label="velocity loop")
    ax.vline(f_c, dash="4 3", label="crossover")
    svg_text = fig.svg("fig-openloop")      # one <svg> element, ids prefixed

Coordinates are rounded to 0.1 px; text uses the page's font (``font-family: inherit``). A page
that includes :data:`ZOOM_SCRIPT` once can zoom the x axis of line plots (drag, double-click).
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ZOOM_SCRIPT", "Figure", "Panel", "envelope"]

Scale = Literal["linear", "log"]

_FONT = 12.0  # px: tick labels, legend
_CHAR_W = 0.58  # average glyph width / font size, for a text's width before the browser lays it out
_LEFT, _RIGHT = 68.0, 16.0  # px: room for the y tick labels and the axis label; right margin
_TOP_TITLE = 20.0  # px above a panel with a title
_LEGEND_ROW = 17.0  # px per row of legend entries, drawn above the plot area


def envelope(x: NDArray[np.float64], y: NDArray[np.float64], columns: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(x, y) reduced to the min and max of y per column of an x range split in ``columns``
    (x increasing): the line a screen of that many pixel columns shows, peaks kept."""
    n = y.size
    if n <= 2 * columns:
        return x, y
    size = -(-n // columns)  # samples per column; the last column is padded with the last sample
    columns = -(-n // size)
    yp = np.concatenate([y, np.full(columns * size - n, y[-1])]).reshape(columns, size)
    start = np.arange(columns) * size
    arg_lo = np.minimum(start + np.argmin(yp, axis=1), n - 1)
    arg_hi = np.minimum(start + np.argmax(yp, axis=1), n - 1)
    # each column's two points in time order, so that a steep edge is not drawn backwards
    first_lo = arg_lo <= arg_hi
    a = np.where(first_lo, arg_lo, arg_hi)
    b = np.where(first_lo, arg_hi, arg_lo)
    idx = np.empty(2 * columns, dtype=int)
    idx[0::2], idx[1::2] = a, b
    return x[idx], y[idx]


def _fmt(v: float) -> str:
    """Tick label: short, no trailing zeros, exponent only for very large or small values."""
    if v == 0:
        return "0"
    a = abs(v)
    if a >= 1e5 or a < 1e-3:
        m, e = f"{v:.0e}".split("e")
        return f"{m}e{int(e)}"
    text = f"{v:.6g}"
    return text


def _nice_step(span: float, target: int) -> float:
    raw = span / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if raw <= m * mag * 1.0001:
            return m * mag
    return 10.0 * mag


def _linear_ticks(lo: float, hi: float, target: int) -> list[float]:
    step = _nice_step(hi - lo, target)
    first = math.ceil(lo / step - 1e-9)
    ticks = []
    k = first
    while k * step <= hi + 1e-9 * step:
        t = k * step
        ticks.append(0.0 if abs(t) < 1e-12 * step else t)
        k += 1
    return ticks


def _log_ticks(lo: float, hi: float, target: int) -> tuple[list[float], list[float]]:
    """(major ticks with labels, minor ticks) on a log axis from lo to hi (> 0)."""
    d0, d1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    if d1 - d0 <= 1:
        return [t for t in _linear_ticks(lo, hi, target) if t > 0], []
    every = max(1, math.ceil((d1 - d0) / max(target, 1)))
    major = [10.0**d for d in range(d0, d1 + 1) if (d - d0) % every == 0 and lo <= 10.0**d <= hi * (1 + 1e-9)]
    minor = []
    if every == 1 and d1 - d0 <= 8:
        minor = [m * 10.0**d for d in range(d0, d1 + 1) for m in range(2, 10) if lo <= m * 10.0**d <= hi]
    return major, minor


@dataclass
class _Axis:
    scale: Scale
    lo: float = math.inf
    hi: float = -math.inf
    fixed: tuple[float, float] | None = None

    def include(self, values: NDArray[np.float64]) -> None:
        v = values[np.isfinite(values)]
        if self.scale == "log":
            v = v[v > 0]
        if v.size:
            self.lo = min(self.lo, float(np.min(v)))
            self.hi = max(self.hi, float(np.max(v)))

    def limits(self, pad: float) -> tuple[float, float]:
        if self.fixed is not None:
            return self.fixed
        lo, hi = self.lo, self.hi
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return (1.0, 10.0) if self.scale == "log" else (0.0, 1.0)
        if self.scale == "log":
            if hi <= lo:
                lo, hi = lo / 2, hi * 2
            f = (hi / lo) ** pad
            return lo / f, hi * f
        if hi <= lo:
            d = abs(lo) * 0.1 or 1.0
            return lo - d, hi + d
        d = (hi - lo) * pad
        return lo - d, hi + d

    def transform(self, v: NDArray[np.float64], lo: float, hi: float, a: float, b: float) -> NDArray[np.float64]:
        """Data → pixels: lo ↦ a, hi ↦ b."""
        if self.scale == "log":
            with np.errstate(divide="ignore", invalid="ignore"):
                u = (np.log10(np.where(v > 0, v, np.nan)) - math.log10(lo)) / (math.log10(hi) - math.log10(lo))
        else:
            u = (v - lo) / (hi - lo)
        return a + u * (b - a)


@dataclass
class _Item:
    kind: str
    x: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    y: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    color: str = "#1f77b4"
    width: float = 1.2
    dash: str | None = None
    opacity: float = 1.0
    label: str | None = None
    text: str = ""
    anchor: str = "start"
    size: float = 3.0


class Panel:
    """One plot area: data are added with :meth:`line`, :meth:`markers`, :meth:`bars`,
    :meth:`vline`, :meth:`hline`, :meth:`vspan`, :meth:`hspan` and :meth:`text`."""

    def __init__(self, height: float, x_scale: Scale, y_scale: Scale, title: str, x_label: str, y_label: str,
                 y_limits: tuple[float, float] | None) -> None:
        self.height = height
        self.x = _Axis(x_scale)
        self.y = _Axis(y_scale, fixed=y_limits)
        self.title = title
        self.x_label = x_label
        self.y_label = y_label
        self.items: list[_Item] = []
        self.categories: list[str] | None = None
        self.x_pad = 0.0  # fraction of the x range left free at each end (markers are not cut)

    def line(self, x: ArrayLike, y: ArrayLike, *, color: str = "#1f77b4", width: float = 1.2,
             dash: str | None = None, opacity: float = 1.0, label: str | None = None) -> Panel:
        xa, ya = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        self.x.include(xa)
        self.y.include(ya)
        self.items.append(_Item("line", xa, ya, color, width, dash, opacity, label))
        return self

    def markers(self, x: ArrayLike, y: ArrayLike, *, color: str = "#1f77b4", size: float = 3.0,
                label: str | None = None, line: bool = False) -> Panel:
        xa, ya = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        self.x.include(xa)
        self.y.include(ya)
        self.x_pad = 0.03
        if line:
            self.items.append(_Item("line", xa, ya, color, 0.8, None, 0.6, None))
        self.items.append(_Item("markers", xa, ya, color, label=label, size=size))
        return self

    def bars(self, labels: Sequence[str], values: ArrayLike, *, color: str = "#1f77b4",
             annotations: Sequence[str] | None = None) -> Panel:
        v = np.asarray(values, dtype=float)
        self.categories = list(labels)
        x = np.arange(len(labels), dtype=float)
        self.x.fixed = (-0.6, len(labels) - 0.4)
        self.y.include(v)
        self.items.append(_Item("bars", x, v, color))
        for xi, vi, a in zip(x, v, annotations or []):
            self.items.append(_Item("text", np.array([xi]), np.array([vi]), "#333333", text=a, anchor="middle"))
        return self

    def vline(self, x: float, *, color: str = "#6a3d9a", dash: str | None = None, width: float = 1.0,
              label: str | None = None) -> Panel:
        self.items.append(_Item("vline", np.array([x]), np.empty(0), color, width, dash, 1.0, label))
        return self

    def hline(self, y: float, *, color: str = "#000000", dash: str | None = None, width: float = 0.9,
              label: str | None = None) -> Panel:
        self.items.append(_Item("hline", np.empty(0), np.array([y]), color, width, dash, 1.0, label))
        return self

    def vspan(self, x0: float, x1: float, *, color: str = "#6a3d9a", opacity: float = 0.12,
              label: str | None = None) -> Panel:
        self.items.append(_Item("vspan", np.array([x0, x1]), np.empty(0), color, opacity=opacity, label=label))
        return self

    def hspan(self, y0: float, y1: float, *, color: str = "#6a3d9a", opacity: float = 0.12,
              label: str | None = None) -> Panel:
        self.y.include(np.array([y0, y1]))
        self.items.append(_Item("hspan", np.empty(0), np.array([y0, y1]), color, opacity=opacity, label=label))
        return self

    def text(self, x: float, y: float, text: str, *, color: str = "#333333", anchor: str = "start") -> Panel:
        """A note at data point (x, y); y = nan: at the top of the panel."""
        self.items.append(_Item("text", np.array([x]), np.array([y]), color, text=text, anchor=anchor))
        return self


class Figure:
    """Panels stacked vertically; x axes shared when ``share_x`` (labels on the last panel only)."""

    def __init__(self, width: float = 960.0, *, title: str = "", share_x: bool = True, zoom: bool = True) -> None:
        self.width = width
        self.title = title
        self.share_x = share_x
        self.zoom = zoom
        self.panels: list[Panel] = []

    def panel(self, height: float = 240.0, *, x_scale: Scale = "linear", y_scale: Scale = "linear",
              title: str = "", x_label: str = "", y_label: str = "",
              y_limits: tuple[float, float] | None = None) -> Panel:
        """A new panel below the others; ``height`` [px] is its plot area with the axes' labels (the
        legend, drawn above it, adds its own rows)."""
        p = Panel(height, x_scale, y_scale, title, x_label, y_label, y_limits)
        self.panels.append(p)
        return p

    def svg(self, ident: str) -> str:
        """The figure as one ``<svg>`` element; every id inside starts with ``ident``."""
        out: list[str] = []
        y0 = 6.0
        if self.title:
            out.append(_text(8.0, 18.0, self.title, size=14.0, weight="600"))
            y0 = 30.0
        shared = self.share_x and len(self.panels) > 1 and all(p.categories is None for p in self.panels)
        if shared:
            xs = [p.x for p in self.panels]
            lo = min(a.lo for a in xs)
            hi = max(a.hi for a in xs)
            fixed = next((a.fixed for a in xs if a.fixed is not None), None)
            pad = max(p.x_pad for p in self.panels)
            for a, q in zip(xs, self.panels):
                a.lo, a.hi, a.fixed = lo, hi, fixed
                q.x_pad = pad
        for k, p in enumerate(self.panels):
            last = k == len(self.panels) - 1
            show_x = last or not shared
            head = _TOP_TITLE if p.title else 4.0
            placed, rows = _legend_layout([it for it in p.items if it.label], _LEFT, self.width - _RIGHT)
            top = y0 + head + _LEGEND_ROW * rows
            plot_h = p.height - head - (40.0 if show_x else 10.0)
            out.append(self._panel_svg(p, f"{ident}-p{k}", top, plot_h, show_x, placed))
            y0 += p.height + _LEGEND_ROW * rows
        h = y0 + 4.0
        zoom = ' data-zoom="x"' if self._zoomable(shared) else ""
        return (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {self.width:.0f} {h:.0f}" '
                f'width="{self.width:.0f}" height="{h:.0f}" font-family="inherit" font-size="{_FONT:g}" '
                f'role="img"{zoom}>' + "".join(out) + "</svg>")

    def _zoomable(self, shared: bool) -> bool:
        """Zoom on x (:data:`ZOOM_SCRIPT`) for line plots whose panels share their x axis."""
        return (self.zoom and (shared or len(self.panels) == 1) and bool(self.panels)
                and all(p.categories is None and not any(it.kind in ("markers", "text") for it in p.items)
                        for p in self.panels))

    def _panel_svg(self, p: Panel, pid: str, top: float, plot_h: float, show_x: bool,
                   legend: list[tuple[_Item, float, int]]) -> str:
        left, right = _LEFT, self.width - _RIGHT
        bottom = top + plot_h
        xlo, xhi = p.x.limits(p.x_pad)
        ylo, yhi = p.y.limits(0.06)
        out: list[str] = []
        rows = 1 + max((r for _, _, r in legend), default=-1)
        if p.title:
            out.append(_text(left, top - 6.0 - _LEGEND_ROW * rows, p.title, size=13.0, weight="600"))
        # grid and ticks
        if p.categories is not None:
            xt, xminor = [float(i) for i in range(len(p.categories))], []
            xlabels = p.categories
        elif p.x.scale == "log":
            xt, xminor = _log_ticks(xlo, xhi, 8)
            xlabels = [_fmt(v) for v in xt]
        else:
            xt, xminor = _linear_ticks(xlo, xhi, 8), []
            xlabels = [_fmt(v) for v in xt]
        if p.y.scale == "log":
            yt, yminor = _log_ticks(ylo, yhi, 5)
        else:
            yt, yminor = _linear_ticks(ylo, yhi, 5), []
        px = p.x.transform(np.array(xt, dtype=float), xlo, xhi, left, right)
        py = p.y.transform(np.array(yt, dtype=float), ylo, yhi, bottom, top)
        pxm = p.x.transform(np.array(xminor, dtype=float), xlo, xhi, left, right)
        pym = p.y.transform(np.array(yminor, dtype=float), ylo, yhi, bottom, top)
        out.append(f'<g class="panel" data-x0="{xlo!r}" data-x1="{xhi!r}" data-scale="{p.x.scale}" '
                   f'data-left="{left:g}" data-right="{right:g}" data-top="{top:.1f}" data-bottom="{bottom:.1f}" '
                   f'data-labels="{int(show_x)}">')
        ygrid = "".join(f"M{left:.1f} {v:.1f}H{right:.1f}" for v in py if top - 0.5 <= v <= bottom + 0.5)
        yminor = "".join(f"M{left:.1f} {v:.1f}H{right:.1f}" for v in pym)
        xgrid = "".join(f"M{v:.1f} {top:.1f}V{bottom:.1f}" for v in px if left - 0.5 <= v <= right + 0.5)
        xminor = "".join(f"M{v:.1f} {top:.1f}V{bottom:.1f}" for v in pxm)
        out.append(f'<path d="{ygrid}" stroke="#d6d6d6" stroke-width="0.8" fill="none"/>')
        if yminor:
            out.append(f'<path d="{yminor}" stroke="#ececec" stroke-width="0.6" fill="none"/>')
        # the x axis's grid and labels in a group of their own: the zoom redraws them
        out.append(f'<g class="xaxis"><path d="{xminor}" stroke="#ececec" stroke-width="0.6" fill="none"/>'
                   f'<path d="{xgrid}" stroke="#d6d6d6" stroke-width="0.8" fill="none"/>')
        if show_x:
            for v, lab in zip(px, xlabels):
                if left - 0.5 <= v <= right + 0.5:
                    out.append(_text(v, bottom + 15.0, lab, anchor="middle"))
        out.append("</g>")
        for v, lab in zip(py, (_fmt(t) for t in yt)):
            if top - 0.5 <= v <= bottom + 0.5:
                out.append(_text(left - 5.0, v + 4.0, lab, anchor="end"))
        if show_x:
            if p.x_label:
                out.append(_text((left + right) / 2, bottom + 32.0, p.x_label, anchor="middle"))
        if p.y_label:
            cy = (top + bottom) / 2
            out.append(f'<text x="14" y="{cy:.1f}" text-anchor="middle" transform="rotate(-90 14 {cy:.1f})">'
                       f"{html.escape(p.y_label)}</text>")
        # data, clipped to the plot area
        clip = f"{pid}-clip"
        out.append(f'<clipPath id="{clip}"><rect x="{left:.1f}" y="{top:.1f}" width="{right - left:.1f}" '
                   f'height="{plot_h:.1f}"/></clipPath><g clip-path="url(#{clip})"><g class="data">')
        columns = int(right - left)
        for it in p.items:
            out.append(self._item_svg(it, p, xlo, xhi, ylo, yhi, left, right, top, bottom, columns))
        out.append("</g></g>")
        out.append(f'<path d="M{left:.1f} {top:.1f}V{bottom:.1f}H{right:.1f}" stroke="#444444" '
                   'stroke-width="1" fill="none"/>')
        if legend:
            out.append(_legend(legend, top - _LEGEND_ROW * rows))
        out.append("</g>")
        return "".join(out)

    @staticmethod
    def _item_svg(it: _Item, p: Panel, xlo: float, xhi: float, ylo: float, yhi: float, left: float,
                  right: float, top: float, bottom: float, columns: int) -> str:
        style = f'stroke="{it.color}" stroke-width="{it.width:g}" fill="none" vector-effect="non-scaling-stroke"'
        if it.dash:
            style += f' stroke-dasharray="{it.dash}"'
        if it.opacity < 1.0:
            style += f' stroke-opacity="{it.opacity:g}"'
        if it.kind == "line":
            x, y = it.x, it.y
            if x.size > 2 * columns and np.all(np.diff(x) >= 0):
                x, y = envelope(x, y, columns)
            X = p.x.transform(x, xlo, xhi, left, right)
            Y = p.y.transform(y, ylo, yhi, bottom, top)
            return f'<path d="{_path(X, Y)}" {style} stroke-linejoin="round"/>'
        if it.kind == "markers":
            X = p.x.transform(it.x, xlo, xhi, left, right)
            Y = p.y.transform(it.y, ylo, yhi, bottom, top)
            r = it.size
            d = "".join(f"M{a - r:.1f} {b:.1f}a{r:g} {r:g} 0 1 0 {2 * r:g} 0a{r:g} {r:g} 0 1 0 {-2 * r:g} 0"
                        for a, b in zip(X, Y) if math.isfinite(a) and math.isfinite(b))
            return f'<path d="{d}" fill="{it.color}" fill-opacity="0.8" stroke="none"/>'
        if it.kind == "bars":
            X = p.x.transform(it.x, xlo, xhi, left, right)
            base = bottom if p.y.scale == "log" else float(p.y.transform(np.array([0.0]), ylo, yhi, bottom, top)[0])
            Y = p.y.transform(it.y, ylo, yhi, bottom, top)
            w = 0.5 * (right - left) / max(1.0, xhi - xlo)
            d = "".join(f"M{a - w / 2:.1f} {base:.1f}V{b:.1f}H{a + w / 2:.1f}V{base:.1f}Z"
                        for a, b in zip(X, Y) if math.isfinite(b))
            return f'<path d="{d}" fill="{it.color}" stroke="none"/>'
        if it.kind == "vline":
            v = float(p.x.transform(it.x, xlo, xhi, left, right)[0])
            return f'<path d="M{v:.1f} {top:.1f}V{bottom:.1f}" {style}/>' if math.isfinite(v) else ""
        if it.kind == "hline":
            v = float(p.y.transform(it.y, ylo, yhi, bottom, top)[0])
            return f'<path d="M{left:.1f} {v:.1f}H{right:.1f}" {style}/>' if math.isfinite(v) else ""
        if it.kind in ("vspan", "hspan"):
            if it.kind == "vspan":
                a, b = p.x.transform(it.x, xlo, xhi, left, right)
                x0, x1, y0, y1 = min(a, b), max(a, b), top, bottom
            else:
                a, b = p.y.transform(it.y, ylo, yhi, bottom, top)
                x0, x1, y0, y1 = left, right, min(a, b), max(a, b)
            if not all(math.isfinite(v) for v in (x0, x1, y0, y1)):
                return ""
            return (f'<path d="M{x0:.1f} {y0:.1f}H{x1:.1f}V{y1:.1f}H{x0:.1f}Z" fill="{it.color}" '
                    f'fill-opacity="{it.opacity:g}" stroke="none"/>')
        if it.kind == "text":
            X = float(p.x.transform(it.x, xlo, xhi, left, right)[0])
            yv = float(it.y[0])
            Y = top + 14.0 if not math.isfinite(yv) else float(p.y.transform(it.y, ylo, yhi, bottom, top)[0]) - 5.0
            if not math.isfinite(X):
                return ""
            return _text(X, max(top + 12.0, Y), it.text, anchor=it.anchor, color=it.color, size=11.0)
        raise ValueError(f"unknown plot item '{it.kind}'")


def _path(X: NDArray[np.float64], Y: NDArray[np.float64]) -> str:
    """A polyline with breaks at non-finite points (formatted in one call per run of points)."""
    ok = np.isfinite(X) & np.isfinite(Y)
    edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(np.int8), 0]))
    parts = []
    for a, b in zip(edges[0::2], edges[1::2]):
        xy = np.empty(2 * (b - a))
        xy[0::2], xy[1::2] = X[a:b], Y[a:b]
        parts.append(("M%.1f %.1f" + "L%.1f %.1f" * (b - a - 1)) % tuple(xy.tolist()))
    return "".join(parts)


def _text(x: float, y: float, text: str, *, anchor: str = "start", size: float | None = None,
          weight: str | None = None, color: str | None = None) -> str:
    attrs = f'x="{x:.1f}" y="{y:.1f}"'
    if anchor != "start":
        attrs += f' text-anchor="{anchor}"'
    if size is not None:
        attrs += f' font-size="{size:g}"'
    if weight is not None:
        attrs += f' font-weight="{weight}"'
    if color is not None:
        attrs += f' fill="{color}"'
    return f"<text {attrs}>{html.escape(text)}</text>"


def _legend_layout(items: list[_Item], left: float, right: float) -> tuple[list[tuple[_Item, float, int]], int]:
    """Legend entries placed left to right in rows above the plot: [(item, x, row)], rows."""
    placed: list[tuple[_Item, float, int]] = []
    x, row = left, 0
    for it in items:
        w = 30.0 + len(it.label or "") * 11.0 * _CHAR_W + 14.0
        if x > left and x + w > right:
            x, row = left, row + 1
        placed.append((it, x, row))
        x += w
    return placed, (row + 1) if items else 0


def _legend(placed: list[tuple[_Item, float, int]], y0: float) -> str:
    out = []
    for it, x0, row in placed:
        cy = y0 + _LEGEND_ROW * row + _LEGEND_ROW / 2
        if it.kind in ("vspan", "hspan", "bars"):
            out.append(f'<path d="M{x0:.1f} {cy - 5:.1f}h22v10h-22Z" fill="{it.color}" '
                       f'fill-opacity="{max(it.opacity, 0.25):g}"/>')
        elif it.kind == "markers":
            out.append(f'<path d="M{x0 + 8:.1f} {cy:.1f}a3 3 0 1 0 6 0a3 3 0 1 0 -6 0" fill="{it.color}"/>')
        else:
            dash = f' stroke-dasharray="{it.dash}"' if it.dash else ""
            opacity = f' stroke-opacity="{it.opacity:g}"' if it.opacity < 1.0 else ""
            out.append(f'<path d="M{x0:.1f} {cy:.1f}h22" stroke="{it.color}" '
                       f'stroke-width="{max(it.width, 1.4):g}"{dash}{opacity}/>')
        out.append(_text(x0 + 28.0, cy + 4.0, it.label or "", size=11.0))
    return "".join(out)


#: The page's zoom on x, for every ``<svg data-zoom="x">``: drag across a plot to zoom its x
#: axis (every panel of the figure together), double-click to go back. The data are moved by a
#: transform (strokes keep their width); the x grid and labels are drawn again for the new range.
#: Long records are drawn as their min/max envelope, so a zoom shows that envelope magnified.
ZOOM_SCRIPT = r"""
(function () {
  var NS = 'http://www.w3.org/2000/svg';
  function fmt(v) {
    if (v === 0) return '0';
    var a = Math.abs(v);
    if (a >= 1e5 || a < 1e-3) { var e = Math.floor(Math.log10(a)); return (v / Math.pow(10, e)).toFixed(0) + 'e' + e; }
    return String(parseFloat(v.toPrecision(6)));
  }
  function linear(lo, hi, n) {
    var raw = (hi - lo) / n, mag = Math.pow(10, Math.floor(Math.log10(raw))), step = 10 * mag;
    [1, 2, 2.5, 5, 10].some(function (m) { if (raw <= m * mag * 1.0001) { step = m * mag; return true; } return false; });
    var out = [];
    for (var k = Math.ceil(lo / step - 1e-9); k * step <= hi + 1e-9 * step; k++) out.push(Math.abs(k * step) < 1e-12 * step ? 0 : k * step);
    return {major: out, minor: []};
  }
  function logTicks(lo, hi) {
    var d0 = Math.floor(Math.log10(lo)), d1 = Math.ceil(Math.log10(hi));
    if (d1 - d0 <= 1) return linear(lo, hi, 8);
    var every = Math.max(1, Math.ceil((d1 - d0) / 8)), major = [], minor = [];
    for (var d = d0; d <= d1; d++) {
      var p = Math.pow(10, d);
      if ((d - d0) % every === 0 && p >= lo && p <= hi * (1 + 1e-9)) major.push(p);
      if (every === 1 && d1 - d0 <= 8) for (var m = 2; m < 10; m++) if (m * p >= lo && m * p <= hi) minor.push(m * p);
    }
    return {major: major, minor: minor};
  }
  function zoomable(svg) {
    var panels = Array.prototype.slice.call(svg.querySelectorAll('g.panel'));
    if (!panels.length) return;
    var L = +panels[0].dataset.left, R = +panels[0].dataset.right, view = [0, 1], start = null;
    var band = document.createElementNS(NS, 'rect');
    band.setAttribute('fill', '#1f77b4'); band.setAttribute('fill-opacity', '0.15'); band.setAttribute('visibility', 'hidden');
    svg.appendChild(band);
    function point(evt) {
      var pt = svg.createSVGPoint(); pt.x = evt.clientX; pt.y = evt.clientY;
      return pt.matrixTransform(svg.getScreenCTM().inverse());
    }
    function unit(x) { return view[0] + (Math.min(R, Math.max(L, x)) - L) / (R - L) * (view[1] - view[0]); }
    function draw() {
      var s = 1 / (view[1] - view[0]);
      panels.forEach(function (g) {
        g.querySelector('g.data').setAttribute('transform', 'translate(' + (L - s * (L + view[0] * (R - L))) + ',0) scale(' + s + ',1)');
        var x0 = +g.dataset.x0, x1 = +g.dataset.x1, log = g.dataset.scale === 'log', top = +g.dataset.top, bottom = +g.dataset.bottom;
        function u(v) { return log ? (Math.log10(v) - Math.log10(x0)) / (Math.log10(x1) - Math.log10(x0)) : (v - x0) / (x1 - x0); }
        function at(w) { return log ? Math.pow(10, Math.log10(x0) + w * (Math.log10(x1) - Math.log10(x0))) : x0 + w * (x1 - x0); }
        function px(v) { return L + (u(v) - view[0]) * s * (R - L); }
        var lo = at(view[0]), hi = at(view[1]), t = log ? logTicks(lo, hi) : linear(lo, hi, 8);
        var axis = g.querySelector('g.xaxis'), paths = axis.querySelectorAll('path');
        paths[0].setAttribute('d', t.minor.map(function (v) { return 'M' + px(v).toFixed(1) + ' ' + top + 'V' + bottom; }).join(''));
        paths[1].setAttribute('d', t.major.map(function (v) { return 'M' + px(v).toFixed(1) + ' ' + top + 'V' + bottom; }).join(''));
        Array.prototype.slice.call(axis.querySelectorAll('text')).forEach(function (n) { axis.removeChild(n); });
        if (g.dataset.labels === '1') t.major.forEach(function (v) {
          var n = document.createElementNS(NS, 'text');
          n.setAttribute('x', px(v).toFixed(1)); n.setAttribute('y', bottom + 15); n.setAttribute('text-anchor', 'middle');
          n.textContent = fmt(v); axis.appendChild(n);
        });
      });
    }
    svg.addEventListener('mousedown', function (evt) {
      var p = point(evt);
      if (p.x < L || p.x > R) return;
      start = p.x; evt.preventDefault();
      var top = +panels[0].dataset.top, bottom = +panels[panels.length - 1].dataset.bottom;
      band.setAttribute('y', top); band.setAttribute('height', bottom - top);
      band.setAttribute('x', start); band.setAttribute('width', 0); band.setAttribute('visibility', 'visible');
    });
    svg.addEventListener('mousemove', function (evt) {
      if (start === null) return;
      var x = Math.min(R, Math.max(L, point(evt).x));
      band.setAttribute('x', Math.min(start, x)); band.setAttribute('width', Math.abs(x - start));
    });
    window.addEventListener('mouseup', function (evt) {
      if (start === null) return;
      var x = point(evt).x, wide = Math.abs(x - start) > 3, a = unit(Math.min(start, x)), b = unit(Math.max(start, x));
      start = null; band.setAttribute('visibility', 'hidden');
      if (wide && b - a > 1e-9) { view = [a, b]; draw(); }
    });
    svg.addEventListener('dblclick', function () { view = [0, 1]; draw(); });
    svg.style.cursor = 'crosshair';
  }
  Array.prototype.slice.call(document.querySelectorAll('svg[data-zoom]')).forEach(zoomable);
})();
"""
