"""fleet.html: each axis's backlash, stiffness and resonance over time, worn axes first.

An axis is a drive serial number (with its vendor and product); a log whose drive has no serial
(a CSV file, say) is an axis of its own, named by its file. The page opens with the axes whose
backlash grew by more than a threshold between their first and last trusted records (identified,
not ``approximate``), largest growth first; then every axis with ε, K and the resonance over time
with their 95 % intervals; then the logs that failed before their drive was known. Figures are inline SVG
(:mod:`commission.svgplot`): the page opens offline, with no script.
"""

from __future__ import annotations

import html
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import OutputError
from ..svgplot import Figure
from .table import LogStatus

__all__ = ["REPORT_NAME", "AxisTrend", "axis_trends", "render_fleet_report", "write_fleet_report"]

#: File name of the page in the output folder.
REPORT_NAME = "fleet.html"


@dataclass(frozen=True)
class AxisTrend:
    """One axis over its records (rows of fleet.parquet in start-time order)."""

    key: str
    """The drive serial, or ``file:<source>`` for a log whose drive has no serial."""
    name: str
    """Vendor, product and serial for a reader."""
    rows: list[dict[str, Any]] = field(repr=False)
    """Every row of the axis, identified or not, by record start."""
    growth_deg: float | None
    """ε of the last trusted record minus that of the first [deg]; None with fewer than two."""
    stiffness_change: float | None
    """K of the last trusted record over that of the first, minus 1 [-]."""
    resonance_change: float | None
    """The same for the resonance frequency [-]."""
    grew: bool
    """The backlash grew by more than the threshold."""

    @property
    def trusted(self) -> list[dict[str, Any]]:
        return [r for r in self.rows if _trusted(r)]

    @property
    def failed(self) -> int:
        return sum(r["status"] != LogStatus.OK.value for r in self.rows)


def _trusted(row: Mapping[str, Any]) -> bool:
    return row["status"] == LogStatus.OK.value and row.get("approximate") is not True


def _unattributed(row: Mapping[str, Any]) -> bool:
    """A failed log with no drive serial (unreadable, say): it belongs to no axis."""
    return row["status"] != LogStatus.OK.value and not row.get("drive_serial")


def _axis_key(row: Mapping[str, Any]) -> str:
    return row.get("drive_serial") or f"file:{row['source']}"


def _far_past() -> datetime:
    return datetime.min.replace(tzinfo=timezone.utc)


def axis_trends(rows: Sequence[Mapping[str, Any]], growth_threshold_deg: float) -> list[AxisTrend]:
    """Axes of the fleet, those whose ε grew by more than ``growth_threshold_deg`` first (largest
    growth first), then the others by growth, then those with fewer than two trusted records."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        if _unattributed(row):
            continue
        groups.setdefault(_axis_key(row), []).append(dict(row))
    trends = []
    for key, members in groups.items():
        members.sort(key=lambda r: (r.get("start_time") or _far_past(), r["source"]))
        good = [r for r in members if _trusted(r)]
        growth = stiffness = resonance = None
        if len(good) >= 2:
            first, last = good[0], good[-1]
            growth = last["epsilon_deg"] - first["epsilon_deg"]
            stiffness = last["K_nm_per_rad"] / first["K_nm_per_rad"] - 1.0
            resonance = last["f_resonance_hz"] / first["f_resonance_hz"] - 1.0
        head = members[0]
        name = " ".join(x for x in (head.get("drive_vendor"), head.get("drive_product")) if x)
        name = (f"{name} serial {head['drive_serial']}".strip() if head.get("drive_serial")
                else f"{name} {Path(head['source']).name} (no serial in the log)".strip())
        trends.append(AxisTrend(key=key, name=name, rows=members, growth_deg=growth, stiffness_change=stiffness,
                                resonance_change=resonance,
                                grew=growth is not None and growth > growth_threshold_deg))
    return sorted(trends, key=lambda a: (not a.grew, a.growth_deg is None, -(a.growth_deg or 0.0), a.key))


# ---------------------------------------------------------------------------------------------
# page
# ---------------------------------------------------------------------------------------------
_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,'DejaVu Sans',sans-serif;margin:0;color:#1d1d1f;background:#f6f7f9}
main{max-width:1100px;margin:0 auto;padding:16px 24px 48px}
h1{font-size:1.5em;margin:.6em 0 .2em}h2{font-size:1.2em;margin:1.6em 0 .4em;border-bottom:1px solid #ddd;padding-bottom:.2em}
.sub{color:#555;margin:0 0 1em}
.verdict{border-radius:8px;padding:12px 18px;margin:12px 0;border:2px solid}
.verdict.worn{background:#fdecea;border-color:#d64541}.verdict.fine{background:#e8f6ec;border-color:#2e9d4f}
.verdict h2{border:0;margin:0 0 .3em;padding:0}
figure.plot{background:#fff;border:1px solid #e0e0e0;border-radius:6px;margin:12px 0;padding:8px}
figure.plot svg{width:100%;height:auto;display:block}
figcaption{color:#444;font-size:.9em;padding:4px 6px}
table{border-collapse:collapse;background:#fff;font-size:.92em;margin:8px 0}
td,th{border:1px solid #e0e0e0;padding:3px 10px;text-align:left;vertical-align:top}
th{background:#f0f1f4}td.num{font-variant-numeric:tabular-nums;text-align:right}
tr.grew td{background:#fdecea}td.bad{color:#b3261e;font-weight:600}
"""
_COLORS = {"estimate": "#1f77b4", "interval": "#1f77b4", "approximate": "#ff7f0e", "threshold": "#d62728"}


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _num(v: float | None, digits: int = 4) -> str:
    if v is None or not math.isfinite(v):
        return "—"
    return f"{v:.{digits}g}"


def _pct(v: float | None) -> str:
    return "—" if v is None else f"{100 * v:+.1f} %"


def _date(t: datetime | None) -> str:
    return "—" if t is None else t.astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M")


def _days(rows: Sequence[Mapping[str, Any]], origin: datetime) -> np.ndarray:
    return np.array([(r["start_time"] - origin).total_seconds() / 86400.0 for r in rows])


def _intervals(x: np.ndarray, lo: Sequence[float | None], hi: Sequence[float | None]) -> tuple[np.ndarray, np.ndarray]:
    """Vertical bars as one polyline broken by NaN (svgplot breaks a line at non-finite points)."""
    xs, ys = [], []
    for xi, a, b in zip(x, lo, hi):
        if a is not None and b is not None:
            xs += [xi, xi, math.nan]
            ys += [a, b, math.nan]
    return np.array(xs, dtype=float), np.array(ys, dtype=float)


def _axis_figure(axis: AxisTrend, index: int, growth_threshold_deg: float) -> str | None:
    rows = [r for r in axis.rows if r["status"] == LogStatus.OK.value and r.get("start_time") is not None]
    if not rows:
        return None
    origin = rows[0]["start_time"]
    x = _days(rows, origin)
    fig = Figure(width=960, zoom=False)
    quantities = [
        ("ε [°]", "epsilon_deg", "epsilon_low_deg", "epsilon_high_deg"),
        ("K [N·m/rad]", "K_nm_per_rad", "K_low_nm_per_rad", "K_high_nm_per_rad"),
        ("resonance [Hz]", "f_resonance_hz", "f_resonance_low_hz", "f_resonance_high_hz"),
    ]
    approx = np.array([r.get("approximate") is True for r in rows])
    for label, col, lo, hi in quantities:
        ax = fig.panel(height=150, y_label=label, x_label=f"days since {_date(origin)} UTC")
        ix, iy = _intervals(x, [r[lo] for r in rows], [r[hi] for r in rows])
        if ix.size:
            ax.line(ix, iy, color=_COLORS["interval"], width=2.0, opacity=0.45,
                    label="95 % interval" if col == "epsilon_deg" else None)
        y = np.array([r[col] for r in rows], dtype=float)
        ax.markers(x[~approx], y[~approx], color=_COLORS["estimate"], line=True,
                   label="identified" if col == "epsilon_deg" else None)
        if approx.any():
            ax.markers(x[approx], y[approx], color=_COLORS["approximate"],
                       label="approximate (not trusted)" if col == "epsilon_deg" else None)
        trusted = axis.trusted
        if col == "epsilon_deg" and trusted:
            ax.hline(trusted[0]["epsilon_deg"] + growth_threshold_deg, color=_COLORS["threshold"], dash="5 4",
                     label=f"first ε + {growth_threshold_deg:g}°")
    return (f'<figure class="plot" id="fig-axis-{index}">{fig.svg(f"fig-axis-{index}")}'
            f"<figcaption>{_e(axis.name)}: backlash ε, stiffness K and resonance of each identified record "
            "with its 95 % interval.</figcaption></figure>")


def _log_table(axis: AxisTrend) -> str:
    head = ("record start", "status", "ε [°]", "ε interval [°]", "K [N·m/rad]", "resonance [Hz]",
            "anti-resonance [Hz]", "approximate", "source")
    out = ["<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for r in axis.rows:
        ok = r["status"] == LogStatus.OK.value
        interval = (f"[{_num(r['epsilon_low_deg'])}, {_num(r['epsilon_high_deg'])}]" if ok else "—")
        approx = "—" if r.get("approximate") is None else ("yes: " + (r.get("approximate_reasons") or "")
                                                            if r["approximate"] else "no")
        cells = [_date(r.get("start_time")), r["status"] if ok else f"{r['status']}: {r.get('error') or ''}",
                 _num(r["epsilon_deg"]), interval, _num(r["K_nm_per_rad"]), _num(r["f_resonance_hz"]),
                 _num(r["f_antiresonance_hz"]), approx, r["source"]]
        out.append("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in cells) + "</tr>")
    out.append("</table>")
    return "".join(out)


def render_fleet_report(rows: Sequence[Mapping[str, Any]], growth_threshold_deg: float) -> str:
    """The page as one HTML document (text)."""
    axes = axis_trends(rows, growth_threshold_deg)
    grown = [a for a in axes if a.grew]
    counts = {s: sum(r["status"] == s.value for r in rows) for s in LogStatus}
    approximate = sum(r.get("approximate") is True for r in rows)
    parts = ["<h1>Fleet report</h1>",
             f'<p class="sub">{len(rows)} logs of {len(axes)} ax{"is" if len(axes) == 1 else "es"} · {counts[LogStatus.OK]} identified '
             f"({approximate} approximate) · {counts[LogStatus.FAILED]} failed · {counts[LogStatus.CRASHED]} "
             f"crashed · backlash growth threshold {growth_threshold_deg:g}°</p>"]
    if grown:
        items = "".join(f"<li><a href=\"#axis-{axes.index(a)}\">{_e(a.name)}</a>: ε grew by "
                        f"{a.growth_deg:.3f}° ({_num(a.trusted[0]['epsilon_deg'])}° → "
                        f"{_num(a.trusted[-1]['epsilon_deg'])}°), K {_pct(a.stiffness_change)}</li>" for a in grown)
        parts.append(f'<div class="verdict worn"><h2>Backlash grew on {len(grown)} of {len(axes)} axes</h2>'
                     f'<ol id="grown">{items}</ol></div>')
    else:
        parts.append(f'<div class="verdict fine"><h2>No axis\'s backlash grew by more than '
                     f"{growth_threshold_deg:g}°</h2></div>")
    head = ("axis", "logs", "failed", "first record", "last record", "ε first → last [°]", "growth [°]",
            "K change", "resonance change")
    table = ['<table id="axes"><tr>' + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for i, a in enumerate(axes):
        t = a.trusted
        span = f"{_num(t[0]['epsilon_deg'])} → {_num(t[-1]['epsilon_deg'])}" if t else "—"
        times = [r["start_time"] for r in a.rows if r.get("start_time") is not None]
        cells = [f'<td><a href="#axis-{i}">{_e(a.name)}</a></td>', f'<td class="num">{len(a.rows)}</td>',
                 f'<td class="num">{a.failed}</td>', f"<td>{_date(min(times) if times else None)}</td>",
                 f"<td>{_date(max(times) if times else None)}</td>", f'<td class="num">{span}</td>',
                 f'<td class="num{" bad" if a.grew else ""}">{_num(a.growth_deg, 3)}</td>',
                 f'<td class="num">{_pct(a.stiffness_change)}</td>', f'<td class="num">{_pct(a.resonance_change)}</td>']
        table.append(f'<tr class="{"grew" if a.grew else "axis"}" data-axis="{_e(a.key)}">{"".join(cells)}</tr>')
    table.append("</table>")
    parts += ["<h2>Axes</h2>", "".join(table)]
    for i, a in enumerate(axes):
        parts.append(f'<h2 id="axis-{i}">{_e(a.name)}</h2>')
        figure = _axis_figure(a, i, growth_threshold_deg)
        if figure is not None:
            parts.append(figure)
        parts.append(_log_table(a))
    lost = [r for r in rows if _unattributed(r)]
    if lost:
        parts.append(f'<h2 id="failed">Logs that failed with no drive identity ({len(lost)})</h2>')
        parts.append("<table><tr><th>source</th><th>status</th><th>error</th></tr>" + "".join(
            f"<tr><td>{_e(r['source'])}</td><td>{_e(r['status'])}</td><td>{_e(r.get('error') or '')}</td></tr>"
            for r in sorted(lost, key=lambda r: r["source"])) + "</table>")
    body = "\n".join(parts)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>Fleet report</title><style>{_CSS}</style></head><body><main>\n{body}\n</main></body></html>\n")


def write_fleet_report(path: str | os.PathLike[str], rows: Sequence[Mapping[str, Any]],
                       growth_threshold_deg: float) -> Path:
    """Write fleet.html (atomically) and return its path."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(render_fleet_report(rows, growth_threshold_deg), encoding="utf-8")
        os.replace(tmp, p)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"cannot write {p}: {err.strerror or err}") from err
    return p
