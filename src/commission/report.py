"""The commissioning report: one self-contained ``report.html`` with Bode and time plots.

Everything is drawn with matplotlib (Agg, no pyplot state) and embedded as inline SVG: the
page has no script, no stylesheet link and no image file, so it opens offline on any
laptop. Each figure is a ``<figure class="plot" id="fig-…">`` holding one ``<svg>``.

What the page shows is *recomputed* here from the Recording and the Identification with the
identifier's public functions (the Identification holds numbers, not curves):

* FRD of τ_ref → v_m (:func:`commission.ident.frd.estimate_frd`), and the FRD after the
  backlash's effect is removed — the paper's step 6, output form:
  v_lin = v_m − (v̂_m(ε̂) − v̂_m(0)) with the identified parameters
  (:func:`commission.ident.backlash.simulate_deadzone`);
* the fitted model and, for simulated runs, the true plant, both as sampled responses
  H(j2πf)·e^{−j2πf·T_d}·sinc²(f/f_s) (one-sample delay, zero-order hold and the drive's
  backward-difference velocity), so that they lie on the measured FRD;
* the measured motor velocity against the dead-zone simulation with ε̂ (and with ε = 0 for
  contrast), over the whole run and zoomed on the gap traversal where backlash shows most;
* the output error RMS(v_m − v̂_m(ε)) over ε with the other parameters at their identified
  values (a profile computed here, cheap: one simulation per ε), and the identifier's own
  search history when its stage detail carries one (``detail["history"]`` of the ``search``
  stage, ``detail["searches"]`` of the ``paper`` stage; see :func:`search_history`);
* the step-5 FRD error per iteration, the tuning result when given, and the run's metadata.

Public API: :func:`write_report`, :func:`render_report` (the HTML text),
:func:`true_plant_from_config`.
"""

from __future__ import annotations

import html
import io
import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .recording import Recording

__all__ = ["REPORT_NAME", "render_report", "search_history", "true_plant_from_config", "write_report"]

#: File name of the report in the output folder.
REPORT_NAME = "report.html"

_COLORS = {
    "measured": "#9a9a9a",
    "corrected": "#1f77b4",
    "model": "#d62728",
    "true": "#2ca02c",
    "linear": "#ff7f0e",
    "accent": "#6a3d9a",
}


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------
def true_plant_from_config(config: Mapping[str, Any] | None, recording: Recording | None = None) -> tuple[Any, float] | None:
    """(TwoMassParameters, ε [rad]) of the simulated plant of a ``--sim`` run, else None.

    ``config`` is the run's config as a dict (``commission.mcaplog.read_config`` or
    ``config_to_dict``); its ``sim`` section is ``sim_drive.plant.PlantParameters`` (missing keys
    take that model's defaults, as the simulator does). Only used when the recording's drive is
    the simulator (``drive.backend == "sim"``, or a drive whose product/vendor says simulated);
    a real drive's config may carry a ``sim`` section that says nothing about the machine.
    """
    if config is None or not isinstance(config.get("sim"), Mapping):
        return None
    if recording is not None:
        d = recording.drive
        simulated = d.backend == "sim" or "simulat" in f"{d.product} {d.vendor}".lower()
        if not simulated:
            return None
    try:
        from sim_drive.plant import PlantParameters

        from .ident.twomass import TwoMassParameters

        pp = PlantParameters(**dict(config["sim"]))
    except Exception:  # noqa: BLE001 - a report must not fail on an odd sim section
        return None
    tm = TwoMassParameters(J_m=pp.J_m, J_l=pp.J_l, B_m=pp.B_m, B_l=pp.B_l, K=pp.K, D=pp.D)
    return tm, float(pp.epsilon_rad)


def search_history(identification: Any) -> list[dict[str, Any]]:
    """The identifier's evaluations of its ε search, in order, from its stage details.

    Recognised (the identifier decides what it keeps; absent → empty list):

    * stage ``search`` (hybrid): ``detail["history"]`` = list of
      ``{"epsilon_deg", "cost_nm", "phi"?, "omega_scale"?}`` in evaluation order;
    * stage ``paper``: ``detail["searches"]`` = list (one per pass) of
      ``{"history": [[epsilon_deg, loss], ...] or [{"epsilon_deg", "loss"}], "method"?, …}``.

    Returns dicts ``{"pass", "epsilon_deg", "loss", "phi", "omega_scale", "unit"}``.
    """
    out: list[dict[str, Any]] = []
    for stage in getattr(identification, "stages", []) or []:
        detail = getattr(stage, "detail", {}) or {}
        if stage.name == "search" and isinstance(detail.get("history"), Sequence):
            for h in detail["history"]:
                if isinstance(h, Mapping) and "epsilon_deg" in h:
                    out.append({"pass": 0, "epsilon_deg": float(h["epsilon_deg"]),
                                "loss": float(h.get("cost_nm", h.get("loss", math.nan))),
                                "phi": h.get("phi"), "omega_scale": h.get("omega_scale"),
                                "unit": "N·m (torque residual RMS)"})
        if stage.name == "paper" and isinstance(detail.get("searches"), Sequence):
            for k, search in enumerate(detail["searches"]):
                for h in (search.get("history") or []) if isinstance(search, Mapping) else []:
                    if isinstance(h, Mapping):
                        e, loss = h.get("epsilon_deg"), h.get("loss")
                    else:
                        e, loss = h[0], h[1]
                    out.append({"pass": k, "epsilon_deg": float(e), "loss": float(loss), "phi": None,
                                "omega_scale": None, "unit": "rad/s (max |v_m − v̂_m|)"})
    return out


# ---------------------------------------------------------------------------------------------
# the numbers behind the figures
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Curves:
    frd: Any                                   # FRD of the measurement
    frd_corrected: Any | None                  # FRD with the backlash's effect removed
    frd_model: Any | None                      # FRD of the linear model's simulation (same estimator)
    f_dense: NDArray[np.float64]
    model: NDArray[np.complex128] | None
    true: NDArray[np.complex128] | None
    v_sim: NDArray[np.float64] | None          # dead-zone simulation with ε̂
    v_lin: NDArray[np.float64] | None          # the same with ε = 0
    twist_sim: NDArray[np.float64] | None
    profile_eps_deg: NDArray[np.float64] | None
    profile_rms: NDArray[np.float64] | None
    profile_max: NDArray[np.float64] | None
    band_hz: tuple[float, float]
    warnings: list[str]


def _sampled(resp: NDArray[np.complex128], f: NDArray[np.float64], fs: float, delay_s: float) -> NDArray[np.complex128]:
    return resp * np.exp(-2j * np.pi * f * delay_s) * np.sinc(f / fs) ** 2


def _options(config: Mapping[str, Any] | None) -> tuple[tuple[float, float], float, tuple[float, float]]:
    ident = (config or {}).get("identification") or {}
    band = tuple(ident.get("band_hz", (0.1, 400.0)))
    res = float(ident.get("resolution_hz", 0.1))
    eb = tuple(ident.get("epsilon_bounds_deg", (0.01, 1.0)))
    return (float(band[0]), float(band[1])), res, (float(eb[0]), float(eb[1]))


def _curves(rec: Recording, ident: Any, config: Mapping[str, Any] | None,
            true_plant: tuple[Any, float] | None) -> _Curves:
    from .exceptions import IdentificationError
    from .ident.backlash import simulate_deadzone, simulate_motor_velocity
    from .ident.frd import estimate_frd

    fs = rec.sample_rate_hz
    band, res, eb = _options(config)
    band = (band[0], min(band[1], 0.45 * fs))
    warnings: list[str] = []
    u, v = rec.torque_ref, rec.motor_velocity
    try:
        frd = estimate_frd(u, v, fs, band_hz=band, resolution_hz=res)
    except IdentificationError as err:  # e.g. a short (aborted) record: the whole record, coarser
        res = fs / len(rec)
        frd = estimate_frd(u, v, fs, band_hz=band, resolution_hz=res)
        warnings.append(f"FRD at {res:.3g} Hz resolution ({err})")
    lo = max(band[0], frd.frequency_hz[0])
    f_dense = np.geomspace(lo, band[1], 1500)
    true = None
    if true_plant is not None:
        true = _sampled(true_plant[0].velocity_response(f_dense), f_dense, fs, 1.0 / fs)
    if ident is None:
        return _Curves(frd, None, None, f_dense, None, true, None, None, None, None, None, None, band, warnings)

    p, eps = ident.parameters, float(ident.epsilon_rad)
    delay = max(0, int(round(float(ident.delay_s) * fs)))
    model = _sampled(p.velocity_response(f_dense), f_dense, fs, float(ident.delay_s))
    sim = simulate_deadzone(p, eps, u, fs, delay_samples=delay)
    sim0 = simulate_deadzone(p, 0.0, u, fs, delay_samples=delay) if eps > 0 else sim
    v_lin_meas = v - (sim.motor_velocity - sim0.motor_velocity)
    frd_corr = estimate_frd(u, v_lin_meas, fs, band_hz=band, resolution_hz=res)
    frd_model = estimate_frd(u, sim0.motor_velocity, fs, band_hz=band, resolution_hz=res)

    hi = max(2.0 * eb[1], 1.5 * math.degrees(eps), 0.05)
    grid = np.unique(np.concatenate([np.linspace(0.0, hi, 61), [math.degrees(eps)]]))
    rms = np.empty(grid.size)
    mx = np.empty(grid.size)
    for i, e in enumerate(grid):
        d = v - simulate_motor_velocity(p, math.radians(e), u, fs, delay_samples=delay)
        rms[i] = float(np.sqrt(np.mean(d * d)))
        mx[i] = float(np.max(np.abs(d)))
    return _Curves(frd, frd_corr, frd_model, f_dense, model, true, sim.motor_velocity, sim0.motor_velocity,
                   sim.twist, grid, rms, mx, band, warnings)


def _zoom_window(rec: Recording, c: _Curves, eps: float) -> tuple[int, int, str]:
    """Sample range of the zoom: the gap traversal where the linear model misses most."""
    fs = rec.sample_rate_hz
    n = len(rec)
    v = rec.motor_velocity
    half = int(round(0.015 * fs))
    if c.v_lin is not None and c.twist_sim is not None and eps > 0:
        z = c.twist_sim
        ingap = np.abs(z) <= eps
        step = np.diff(ingap.astype(np.int8))
        entries = np.flatnonzero(step == 1) + 1  # first sample in the gap
        exits = np.flatnonzero(step == -1) + 1   # first sample out of it
        runs = [(int(i), int(exits[exits > i][0])) for i in entries if (exits > i).any()]
        # a traversal: into the gap on one flank, out on the other (a torque reversal)
        crossing = [(i, j) for i, j in runs if np.sign(z[i - 1]) != np.sign(z[j])]
        runs = crossing or runs
        if runs:
            miss = np.abs(v - c.v_lin)
            score = [float(miss[max(0, i - half): j + half].max()) for i, j in runs]
            i, j = runs[int(np.argmax(score))]
            centre = (i + j) // 2
            half = max(half, 2 * (j - i))
            a, b = max(0, centre - half), min(n, centre + half)
            what = "the gears cross the gap" if crossing else "the gears separate"
            return a, b, (f"{what} at t = {i / fs:.4f} s "
                          f"({1e3 * (j - i) / fs:.2f} ms in the gap in the simulation)")
    # no backlash: the largest motor-velocity reversal of the slow motion
    sign = np.sign(v)
    zc = np.flatnonzero(np.diff(sign) != 0)
    i = int(zc[len(zc) // 2]) if zc.size else n // 2
    return max(0, i - half), min(n, i + half), f"a motor-velocity reversal at t = {i / fs:.4f} s"


# ---------------------------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------------------------
_RC = {
    "svg.fonttype": "none",
    "font.family": "sans-serif",
    "font.size": 9.0,
    "axes.grid": True,
    "grid.alpha": 0.35,
    "grid.linewidth": 0.6,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "legend.fontsize": 8.0,
    "legend.framealpha": 0.85,
    "lines.linewidth": 1.2,
}


def _new_figure(width_in: float, height_in: float) -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), layout="constrained")


def _svg(fig: Any, ident: str) -> str:
    import matplotlib

    buf = io.StringIO()
    with matplotlib.rc_context({**_RC, "svg.hashsalt": ident}):
        fig.savefig(buf, format="svg", metadata={"Date": None, "Creator": None})
    text = buf.getvalue()
    text = text[text.index("<svg"):]
    # ids are salted per figure: make them unique page-wide as well
    text = re.sub(r'id="([^"]+)"', lambda m: f'id="{ident}-{m.group(1)}"', text)
    text = re.sub(r'(xlink:href|href)="#([^"]+)"', lambda m: f'{m.group(1)}="#{ident}-{m.group(2)}"', text)
    text = re.sub(r"url\(#([^)]+)\)", lambda m: f"url(#{ident}-{m.group(1)})", text)
    return text


def _envelope(t: NDArray[np.float64], x: NDArray[np.float64], buckets: int = 1500) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Min/max per bucket (what a pixel column shows), as a line that keeps the peaks."""
    n = x.size
    if n <= 2 * buckets:
        return t, x
    edges = np.linspace(0, n, buckets + 1).astype(int)
    lo = np.minimum.reduceat(x, edges[:-1])
    hi = np.maximum.reduceat(x, edges[:-1])
    tt = np.repeat(t[edges[:-1]], 2)
    xx = np.empty(2 * buckets)
    xx[0::2], xx[1::2] = lo, hi
    return tt, xx


def _mark_modes(axes: Sequence[Any], ident: Any, label_ax: Any) -> None:
    if ident is None:
        return
    m = ident.modes
    for f, name, ls in ((m.f_antiresonance_hz, "anti-resonance", ":"), (m.f_resonance_hz, "resonance", "--")):
        if not (math.isfinite(f) and f > 0):
            continue
        for ax in axes:
            ax.axvline(f, color=_COLORS["accent"], ls=ls, lw=0.9, alpha=0.8)
        label_ax.annotate(f"{name}\n{f:.1f} Hz", xy=(f, 1.0), xycoords=("data", "axes fraction"),
                          xytext=(3 if name == "resonance" else -3, -2), textcoords="offset points",
                          ha="left" if name == "resonance" else "right", va="top", fontsize=8,
                          color=_COLORS["accent"])


def _fig_bode(rec: Recording, ident: Any, c: _Curves) -> str:
    fig = _new_figure(10.0, 7.6)
    gs = fig.add_gridspec(3, 1, height_ratios=[3.0, 2.2, 1.5])
    ax_m = fig.add_subplot(gs[0])
    ax_p = fig.add_subplot(gs[1], sharex=ax_m)
    ax_q = fig.add_subplot(gs[2], sharex=ax_m)

    def db(h: NDArray[np.complex128]) -> NDArray[np.float64]:
        return 20 * np.log10(np.maximum(np.abs(h), 1e-300))

    def deg(h: NDArray[np.complex128]) -> NDArray[np.float64]:
        return np.degrees(np.unwrap(np.angle(h)))

    f = c.frd.frequency_hz
    ax_m.semilogx(f, db(c.frd.response), color=_COLORS["measured"], lw=0.8, label="measured FRD")
    ax_p.semilogx(f, deg(c.frd.response), color=_COLORS["measured"], lw=0.8)
    if c.frd_corrected is not None:
        ax_m.semilogx(f, db(c.frd_corrected.response), color=_COLORS["corrected"], lw=0.9,
                      label="FRD, backlash effect removed")
        ax_p.semilogx(f, deg(c.frd_corrected.response), color=_COLORS["corrected"], lw=0.9)
    if c.model is not None:
        ax_m.semilogx(c.f_dense, db(c.model), color=_COLORS["model"], lw=1.4, ls="--", label="fitted model")
        ax_p.semilogx(c.f_dense, deg(c.model), color=_COLORS["model"], lw=1.4, ls="--")
    if c.true is not None:
        ax_m.semilogx(c.f_dense, db(c.true), color=_COLORS["true"], lw=1.4, ls=":", label="true plant (simulator)")
        ax_p.semilogx(c.f_dense, deg(c.true), color=_COLORS["true"], lw=1.4, ls=":")
    ax_m.set_ylabel("|V_m / T_ref|  [dB re 1 rad/s per N·m]")
    ax_p.set_ylabel("phase [deg]")
    ax_m.legend(loc="lower left")
    ax_m.set_title("Frequency response: torque reference → motor velocity", loc="left", fontsize=10)

    ax_q.semilogx(f, np.maximum(1.0 - c.frd.quality, 1e-9), color=_COLORS["measured"], lw=0.8,
                  label="1 − quality, measured FRD")
    if c.frd_corrected is not None and c.frd_model is not None:
        ax_q.semilogx(f, np.maximum(1.0 - c.frd_corrected.quality, 1e-9), color=_COLORS["corrected"], lw=0.8,
                      label="1 − quality, backlash removed")
        resid = np.abs(c.frd_corrected.response - c.frd_model.response) / np.abs(c.frd_model.response)
        ax_q.semilogx(f, np.maximum(resid, 1e-9), color=_COLORS["model"], lw=0.8,
                      label="|FRD (backlash removed) − model| / |model|")
    ax_q.set_yscale("log")
    ax_q.set_ylabel("lower is better  [-]")
    ax_q.set_xlabel("frequency [Hz]")
    ax_q.legend(loc="upper center", bbox_to_anchor=(0.5, -0.32), ncols=3, frameon=False)
    ax_m.set_xlim(c.f_dense[0], c.band_hz[1])
    for ax in (ax_m, ax_p):
        ax.tick_params(labelbottom=False)
    _mark_modes((ax_m, ax_p, ax_q), ident, ax_m)
    return _svg(fig, "fig-bode")


def _fig_time(rec: Recording, ident: Any, c: _Curves) -> str:
    fig = _new_figure(10.0, 5.2)
    ax_v, ax_e = fig.subplots(2, 1, sharex=True, height_ratios=[2.0, 1.3])
    t = rec.t
    ax_v.plot(*_envelope(t, rec.motor_velocity), color="black", lw=1.6, label="measured v_m")
    if c.v_sim is not None:
        ax_v.plot(*_envelope(t, c.v_sim), color=_COLORS["model"], lw=0.6,
                  label=f"simulated, ε̂ = {ident.epsilon_deg:.3f}°")
        ax_e.plot(*_envelope(t, rec.motor_velocity - c.v_lin), color=_COLORS["linear"], lw=0.6,
                  label="measured − simulated with ε = 0 (no backlash)")
        ax_e.plot(*_envelope(t, rec.motor_velocity - c.v_sim), color=_COLORS["model"], lw=0.6,
                  label="measured − simulated with ε̂")
        ax_e.legend(loc="upper right")
    ax_v.set_ylabel("motor velocity [rad/s]")
    ax_e.set_ylabel("error [rad/s]")
    ax_e.set_xlabel("time [s]")
    ax_v.legend(loc="upper right")
    ax_v.set_title("Motor velocity over the whole run (min/max per pixel column)", loc="left", fontsize=10)
    return _svg(fig, "fig-time")


def _fig_zoom(rec: Recording, ident: Any, c: _Curves, window: tuple[int, int, str]) -> str:
    a, b, _ = window
    has_twist = c.twist_sim is not None or (rec.motor_position is not None and rec.load_position is not None)
    fig = _new_figure(10.0, 5.4 if has_twist else 3.4)
    axes = fig.subplots(2 if has_twist else 1, 1, sharex=True, squeeze=False)[:, 0]
    t = rec.t[a:b] * 1e3
    ax = axes[0]
    if c.v_sim is not None:
        ax.plot(t, c.v_sim[a:b], color=_COLORS["model"], lw=4.0, alpha=0.4,
                label=f"simulated, ε̂ = {ident.epsilon_deg:.3f}°")
        ax.plot(t, c.v_lin[a:b], color=_COLORS["linear"], lw=1.1, ls="--", label="simulated, ε = 0 (no backlash)")
    ax.plot(t, rec.motor_velocity[a:b], color="black", lw=0.9, label="measured v_m")
    ax.set_ylabel("motor velocity [rad/s]")
    ax.legend(loc="best")
    ax.set_title("Zoom on a reversal", loc="left", fontsize=10)
    if has_twist:
        ax2 = axes[1]
        if rec.motor_position is not None and rec.load_position is not None:
            twist = rec.motor_position[a:b] - rec.load_position[a:b]
            # the encoders' zero is arbitrary: centre the measured twist on the simulation's
            if c.twist_sim is not None:
                twist = twist - np.median(rec.motor_position - rec.load_position) + np.median(c.twist_sim)
        if c.twist_sim is not None:
            ax2.plot(t, np.degrees(c.twist_sim[a:b]), color=_COLORS["model"], lw=4.0, alpha=0.4,
                     label="simulated twist (ε̂)")
        if rec.motor_position is not None and rec.load_position is not None:
            ax2.plot(t, np.degrees(twist), color="black", lw=0.9, label="measured twist x_m − x_l (encoders)")
        if ident is not None and ident.backlash_detected and ident.epsilon_rad > 0:
            e = ident.epsilon_deg
            ax2.axhspan(-e, e, color=_COLORS["accent"], alpha=0.12, label=f"gap ±ε̂ = ±{e:.3f}°")
        ax2.set_ylabel("twist [deg]")
        ax2.legend(loc="best")
    axes[-1].set_xlabel("time [ms]")
    return _svg(fig, "fig-zoom")


def _fig_search(rec: Recording, ident: Any, c: _Curves, history: list[dict[str, Any]]) -> str:
    from matplotlib import colormaps

    fig = _new_figure(10.0, 6.6)
    gs = fig.add_gridspec(2, 2)
    ax_h = fig.add_subplot(gs[0, 0])
    ax_o = fig.add_subplot(gs[0, 1])
    ax_p = fig.add_subplot(gs[1, :])
    e_hat = ident.epsilon_deg
    lo, hi = (math.degrees(x) for x in ident.epsilon_interval_rad)

    def mark(ax: Any, horizontal: bool = False) -> None:
        line = ax.axhline if horizontal else ax.axvline
        span = ax.axhspan if horizontal else ax.axvspan
        line(e_hat, color=_COLORS["model"], lw=1.0, label=f"chosen ε̂ = {e_hat:.4f}°")
        if hi > lo:
            span(lo, hi, color=_COLORS["model"], alpha=0.15, label=f"interval [{lo:.4f}°, {hi:.4f}°]")

    if history:
        eps = np.array([h["epsilon_deg"] for h in history])
        loss = np.array([h["loss"] for h in history])
        keys = [(h["pass"], h["phi"], h["omega_scale"]) for h in history]
        groups = sorted(set(keys), key=lambda k: tuple(-1 if v is None else v for v in k))
        cmap = colormaps["viridis"]
        for gi, key in enumerate(groups):
            sel = np.array([k == key for k in keys])
            order = np.argsort(eps[sel])
            label = ", ".join(f"{n} {v:g}" for n, v in zip(("pass", "φ", "ω-scale"), key)
                              if v is not None and not (n == "pass" and len(groups) == 1))
            ax_h.plot(eps[sel][order], loss[sel][order], marker="o", ms=3, lw=0.8,
                      color=cmap(gi / max(1, len(groups) - 1)), label=label or None)
        ax_h.set_yscale("log")
        ax_h.set_ylabel(f"loss [{history[0]['unit']}]")
        idx = np.arange(1, eps.size + 1)
        sc = ax_o.scatter(idx, eps, c=np.log10(np.maximum(loss, 1e-300)), cmap="viridis_r", s=14, zorder=3)
        ax_o.plot(idx, eps, color="#bbbbbb", lw=0.6, zorder=2)
        cb = fig.colorbar(sc, ax=ax_o, pad=0.01)
        cb.set_label("log₁₀ loss")
        mark(ax_o, horizontal=True)
        ax_o.set_xlabel("evaluation #")
        ax_o.set_ylabel("ε [deg]")
        ax_o.legend(loc="best")
        ax_h.set_title(f"The identifier's search: {len(history)} evaluations", loc="left", fontsize=10)
        ax_o.set_title("Evaluations in order", loc="left", fontsize=10)
    else:
        best = []
        for s in ident.stages:
            if s.name == "search" and isinstance(s.detail.get("best"), Sequence):
                best = [b for b in s.detail["best"] if isinstance(b, Mapping)]
        if best:
            ax_h.plot([b["epsilon_deg"] for b in best], [b.get("cost_nm", math.nan) for b in best], "o",
                      color=_COLORS["corrected"], label="best cells of the search")
            ax_h.set_yscale("log")
            ax_h.set_ylabel("torque residual RMS [N·m]")
            ax_h.legend(loc="best")
        its = [it["epsilon_deg"] for it in ident.iterations]
        ax_o.plot(np.arange(1, len(its) + 1), its, "o-", color=_COLORS["accent"], label="ε per iteration")
        mark(ax_o, horizontal=True)
        ax_o.set_xlabel("iteration")
        ax_o.set_xticks(np.arange(1, len(its) + 1))
        ax_o.set_ylabel("ε [deg]")
        ax_o.legend(loc="best")
        msg = (f"{ident.evaluations} evaluations; their history is not kept\n"
               "in the Identification (only the best cells)")
        ax_h.set_title("The identifier's search", loc="left", fontsize=10)
        ax_h.text(0.02, 0.04, msg, transform=ax_h.transAxes, fontsize=8, color="#555555")
        ax_o.set_title("ε over the iterations", loc="left", fontsize=10)
    ax_h.set_xlabel("ε [deg]")
    mark(ax_h)
    ax_h.legend(loc="best", fontsize=7)

    ax_p.plot(c.profile_eps_deg, c.profile_rms, "o-", ms=2.5, color=_COLORS["corrected"], label="RMS(v_m − v̂_m(ε))")
    ax_p.set_ylabel("RMS output error [rad/s]")
    ax_p.set_yscale("log")
    ax_p2 = ax_p.twinx()
    ax_p2.plot(c.profile_eps_deg, c.profile_max, "s-", ms=2.0, lw=0.8, color=_COLORS["linear"], alpha=0.8,
               label="max |v_m − v̂_m(ε)| (paper's loss)")
    ax_p2.set_yscale("log")
    ax_p2.set_ylabel("max output error [rad/s]")
    ax_p2.grid(False)
    ax_p2.spines["right"].set_visible(True)
    mark(ax_p)
    h1, l1 = ax_p.get_legend_handles_labels()
    h2, l2 = ax_p2.get_legend_handles_labels()
    ax_p.legend(h1 + h2, l1 + l2, loc="lower right", ncols=2)
    ax_p.set_xlabel("ε [deg]")
    ax_p.set_title("Loss over ε, the other parameters at their identified values (computed for this report)",
                   loc="left", fontsize=10)
    return _svg(fig, "fig-search")


def _fig_iterations(ident: Any) -> str:
    fig = _new_figure(10.0, 3.0)
    ax = fig.subplots()
    its = ident.iterations
    if ident.method.value == "hybrid" and len(its) in (2, 3):
        names = ["frequency-domain start", "joint fit", "step-6 refit"][: len(its)]
        if len(its) == 2 and not any(s.name == "check" and "refit_parameters" in s.detail for s in ident.stages):
            names = ["frequency-domain start", "joint fit"]
    else:
        names = [f"pass {i}" for i in range(len(its))]
    err = [max(float(it["frd_error"]), 1e-12) for it in its]
    x = np.arange(len(its))
    bars = ax.bar(x, err, color=_COLORS["corrected"], width=0.55)
    for rect, it in zip(bars, its):
        ax.annotate(f"{100 * it['frd_error']:.3g} %\nε = {it['epsilon_deg']:.4f}°",
                    xy=(rect.get_x() + rect.get_width() / 2, rect.get_height()),
                    xytext=(0, 2), textcoords="offset points", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, names)
    ax.set_yscale("log")
    ax.set_ylim(min(err) / 3, max(err) * 8)
    ax.set_ylabel("FRD error (step 5) [-]")
    ax.set_title("FRD of the dead-zone simulation vs the measured FRD, per iteration", loc="left", fontsize=10)
    return _svg(fig, "fig-iterations")


# -- tuning -----------------------------------------------------------------------------------
def _find_number(d: Mapping[str, Any], *prefixes: str) -> float | None:
    for k, v in d.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool) and any(k.lower().startswith(p) for p in prefixes):
            return float(v)
    return None


def _open_loop(tuning: Mapping[str, Any], ident: Any, fs: float) -> tuple[NDArray[np.float64], NDArray[np.complex128], str] | None:
    """The open loop (f, L, how): given as curves (``open_loop``), or rebuilt from controller.json.

    Rebuilt (a continuous approximation of the drive's discrete loop): PI
    ``gain·(1 + 1/(integral_time_s·s))`` (or ``gain + integral_gain/s``), the torque filter
    1/(τs + 1), each notch (s² + depth·ω/q·s + ω²)/(s² + ω/q·s + ω²), the current loop
    1/(s/ω_c + 1) and ``computation_delay_samples``, on the identified plant (with its
    one-sample delay and hold).
    """
    ol = tuning.get("open_loop")
    if isinstance(ol, Mapping) and "frequency_hz" in ol:
        f = np.asarray(ol["frequency_hz"], dtype=float)
        if "real" in ol and "imag" in ol:
            return f, np.asarray(ol["real"], float) + 1j * np.asarray(ol["imag"], float), "as computed by the tuning"
        if "magnitude_db" in ol and "phase_deg" in ol:
            mag = 10 ** (np.asarray(ol["magnitude_db"], float) / 20)
            return f, mag * np.exp(1j * np.radians(np.asarray(ol["phase_deg"], float))), "as computed by the tuning"
    vl = tuning.get("velocity_loop")
    if ident is None or not isinstance(vl, Mapping):
        return None
    kp = vl.get("gain") if isinstance(vl.get("gain"), (int, float)) else _find_number(vl, "kp")
    if not kp:
        return None
    ti = vl.get("integral_time_s") if isinstance(vl.get("integral_time_s"), (int, float)) else _find_number(vl, "ti")
    ki = vl.get("integral_gain") if isinstance(vl.get("integral_gain"), (int, float)) else _find_number(vl, "ki")
    rate = float(tuning.get("sample_rate_hz") or fs)
    f = np.geomspace(0.5, 0.45 * rate, 1500)
    s = 2j * np.pi * f
    if ti:
        c = kp * (1 + 1 / (ti * s))
    else:
        c = kp + (ki or 0.0) / s
    tfil = tuning.get("torque_filter")
    if isinstance(tfil, Mapping) and isinstance(tfil.get("time_constant_s"), (int, float)) and tfil["time_constant_s"] > 0:
        c = c / (tfil["time_constant_s"] * s + 1)
    notches = tuning.get("notch")
    for notch in (notches if isinstance(notches, Sequence) else [notches] if isinstance(notches, Mapping) else []):
        if not isinstance(notch, Mapping):
            continue
        fn = _find_number(notch, "frequency")
        if not fn:
            continue
        wn, q = 2 * np.pi * fn, (_find_number(notch, "q") or 1.0)
        depth = notch.get("depth")
        if not isinstance(depth, (int, float)):
            db = _find_number(notch, "depth_db")
            depth = 10 ** (-abs(db) / 20) if db is not None else 0.0
        c = c * (s**2 + depth * wn / q * s + wn**2) / (s**2 + wn / q * s + wn**2)
    dm = tuning.get("drive_model") if isinstance(tuning.get("drive_model"), Mapping) else {}
    if isinstance(dm.get("current_loop_bandwidth_hz"), (int, float)) and dm["current_loop_bandwidth_hz"] > 0:
        c = c / (s / (2 * np.pi * dm["current_loop_bandwidth_hz"]) + 1)
    if isinstance(dm.get("computation_delay_samples"), (int, float)):
        c = c * np.exp(-s * dm["computation_delay_samples"] / rate)
    plant = _sampled(ident.parameters.velocity_response(f), f, fs, float(ident.delay_s))
    return f, c * plant, "rebuilt from the settings (continuous approximation)"


def _curves_in(obj: Any, path: str = "") -> list[tuple[str, NDArray[np.float64], NDArray[np.float64]]]:
    """Every (label, t, y) found in a verification dict: mappings with ``t_s`` and one array."""
    out: list[tuple[str, NDArray[np.float64], NDArray[np.float64]]] = []
    if isinstance(obj, Mapping):
        t = obj.get("t_s")
        if isinstance(t, Sequence) and len(t) > 1:
            for k, v in obj.items():
                if k != "t_s" and isinstance(v, Sequence) and not isinstance(v, str) and len(v) == len(t):
                    try:
                        y = np.asarray(v, dtype=float)
                    except (TypeError, ValueError):
                        continue
                    out.append((f"{path} {k}".strip(), np.asarray(t, dtype=float), y))
        for k, v in obj.items():
            if k != "t_s":
                out += _curves_in(v, f"{path} {k}".strip() if not isinstance(obj.get("t_s"), Sequence) else path)
    elif isinstance(obj, Sequence) and not isinstance(obj, str):
        for i, v in enumerate(obj):
            label = v.get("label", f"{path} {i}") if isinstance(v, Mapping) else f"{path} {i}"
            out += _curves_in(v, str(label))
    return out


def _fig_open_loop(tuning: Mapping[str, Any], ident: Any, fs: float) -> str | None:
    ol = _open_loop(tuning, ident, fs)
    if ol is None:
        return None
    f, L, how = ol
    fig = _new_figure(10.0, 5.0)
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    ax_m.semilogx(f, 20 * np.log10(np.abs(L)), color=_COLORS["corrected"])
    ax_p.semilogx(f, np.degrees(np.unwrap(np.angle(L))), color=_COLORS["corrected"])
    ax_m.axhline(0, color="black", lw=0.8)
    ax_p.axhline(-180, color="black", lw=0.8)
    # margins read off the curve drawn (the tuning's own numbers are in the table below)
    mag_db = 20 * np.log10(np.abs(L))
    phase = np.degrees(np.unwrap(np.angle(L)))
    down = np.flatnonzero((mag_db[:-1] >= 0) & (mag_db[1:] < 0))
    if down.size:
        k = int(down[0])
        fc = float(np.interp(0.0, [mag_db[k + 1], mag_db[k]], [f[k + 1], f[k]]))
        ph = float(np.interp(fc, f[k:k + 2], phase[k:k + 2]))
        pm = 180.0 + ph
        for ax in (ax_m, ax_p):
            ax.axvline(fc, color=_COLORS["model"], ls="--", lw=0.9)
        ax_p.plot([fc, fc], [-180, ph], color=_COLORS["model"], lw=2.5)
        ax_p.annotate(f"phase margin {pm:.1f}° at {fc:.1f} Hz", xy=(fc, ph), xytext=(5, 5),
                      textcoords="offset points", color=_COLORS["model"], fontsize=8)
    cross = np.flatnonzero((phase[:-1] > -180) & (phase[1:] <= -180))
    if cross.size:
        k = int(cross[0])
        fpc = float(np.interp(-180.0, [phase[k + 1], phase[k]], [f[k + 1], f[k]]))
        g = float(np.interp(fpc, f[k:k + 2], mag_db[k:k + 2]))
        ax_m.plot([fpc, fpc], [g, 0], color=_COLORS["linear"], lw=2.5)
        ax_m.annotate(f"gain margin {-g:.1f} dB at {fpc:.1f} Hz", xy=(fpc, g), xytext=(5, -10),
                      textcoords="offset points", color=_COLORS["linear"], fontsize=8)
    ax_m.set_ylabel("|L| [dB]")
    ax_p.set_ylabel("phase of L [deg]")
    ax_p.set_xlabel("frequency [Hz]")
    ax_m.set_title(f"Velocity loop: open loop L = C·G with margins ({how})", loc="left", fontsize=10)
    return _svg(fig, "fig-openloop")


def _fig_steps(tuning: Mapping[str, Any]) -> str | None:
    curves = _curves_in(tuning.get("verification"), "")
    if not curves:
        return None
    fig = _new_figure(10.0, 3.6)
    ax = fig.subplots()
    for label, t, y in curves:
        ax.plot(t * 1e3, y, lw=1.2, label=label.replace("_", " ") or None)
    ax.set_xlabel("time [ms]")
    ax.set_ylabel("response")
    ax.legend(loc="best")
    ax.set_title("Closed-loop step responses", loc="left", fontsize=10)
    return _svg(fig, "fig-steps")


# ---------------------------------------------------------------------------------------------
# HTML
# ---------------------------------------------------------------------------------------------
_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,'DejaVu Sans',sans-serif;margin:0;color:#1d1d1f;background:#f6f7f9}
main{max-width:1100px;margin:0 auto;padding:16px 24px 48px}
h1{font-size:1.5em;margin:.6em 0 .2em}h2{font-size:1.2em;margin:1.6em 0 .4em;border-bottom:1px solid #ddd;padding-bottom:.2em}
.sub{color:#555;margin:0 0 1em}
.cards{display:flex;flex-wrap:wrap;gap:10px;margin:12px 0}
.card{background:#fff;border:1px solid #e0e0e0;border-radius:6px;padding:8px 14px;min-width:150px}
.card b{display:block;font-size:1.25em}.card span{color:#666;font-size:.85em}
figure.plot{background:#fff;border:1px solid #e0e0e0;border-radius:6px;margin:12px 0;padding:8px}
figure.plot svg{width:100%;height:auto;display:block}
figcaption{color:#444;font-size:.9em;padding:4px 6px}
table{border-collapse:collapse;background:#fff;font-size:.92em;margin:8px 0}
td,th{border:1px solid #e0e0e0;padding:3px 10px;text-align:left;vertical-align:top}
th{background:#f0f1f4}
td.num{font-variant-numeric:tabular-nums;text-align:right}
.note{background:#fff8e1;border:1px solid #f0d98a;border-radius:6px;padding:6px 12px;margin:8px 0}
.placeholder{color:#666;font-style:italic}
pre{background:#fff;border:1px solid #e0e0e0;padding:8px;overflow:auto;font-size:.85em}
nav a{margin-right:12px}
"""


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _table(rows: Sequence[Sequence[Any]], header: Sequence[str] | None = None, cls: str = "") -> str:
    out = [f'<table class="{cls}">'] if cls else ["<table>"]
    if header:
        out.append("<tr>" + "".join(f"<th>{_e(h)}</th>" for h in header) + "</tr>")
    for row in rows:
        cells = []
        for v in row:
            if isinstance(v, float):
                cells.append(f'<td class="num">{v:.6g}</td>')
            else:
                cells.append(f"<td>{_e(v)}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "".join(out)


def _figure(svg: str, fig_id: str, caption: str) -> str:
    return f'<figure class="plot" id="{fig_id}">{svg}<figcaption>{caption}</figcaption></figure>'


def _flatten(d: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    rows: list[tuple[str, Any]] = []
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, Mapping):
            rows += _flatten(v, key)
        elif isinstance(v, Sequence) and not isinstance(v, str) and len(v) > 8:
            rows.append((key, f"[{len(v)} values]"))
        else:
            rows.append((key, float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v))
    return rows


def _tool_version() -> str:
    try:
        from importlib.metadata import version

        return version("drive-commission")
    except Exception:  # noqa: BLE001
        return "0+unknown"


def render_report(
    recording: Recording,
    identification: Any | None,
    *,
    config: Mapping[str, Any] | None = None,
    source_file: str | os.PathLike[str] | None = None,
    tuning: Mapping[str, Any] | None = None,
    true_plant: tuple[Any, float] | Any | None = None,
    files: Sequence[str | os.PathLike[str]] = (),
) -> str:
    """The report as one HTML document (text). See :func:`write_report`."""
    if config is not None and not isinstance(config, Mapping):
        config = config.model_dump(mode="json")  # a commission.config.Config
    if true_plant is None:
        true_plant = true_plant_from_config(config, recording)
    elif not isinstance(true_plant, tuple):
        true_plant = (true_plant, math.nan)
    fs = recording.sample_rate_hz
    c = _curves(recording, identification, config, true_plant)
    ident = identification
    parts: list[str] = []
    title = "Commissioning report"
    d = recording.drive
    drive_name = " ".join(x for x in (d.vendor, d.product) if x) or d.backend
    when = recording.start_time.astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    parts.append(f"<h1>{_e(title)} — {_e(drive_name)}</h1>")
    parts.append(f'<p class="sub">Run of {_e(when)} · {len(recording):,} samples at {fs:g} Hz '
                 f"({recording.duration_s:g} s) · status {_e(recording.metadata.get('status', 'unknown'))}"
                 + (f" · input {_e(source_file)}" if source_file else "") + "</p>")
    nav = ['<a href="#bode">Bode</a>', '<a href="#time">Time series</a>']
    if ident is not None:
        nav += ['<a href="#search">Backlash search</a>', '<a href="#iterations">Iterations</a>']
    nav += ['<a href="#tuning">Tuning</a>', '<a href="#metadata">Metadata</a>']
    parts.append("<nav>" + "".join(nav) + "</nav>")

    if ident is not None:
        lo, hi = (math.degrees(x) for x in ident.epsilon_interval_rad)
        m = ident.modes
        last_err = ident.iterations[-1]["frd_error"] if ident.iterations else math.nan
        cards = [
            (f"{ident.epsilon_deg:.4f}°", f"backlash ε̂ ({'detected' if ident.backlash_detected else 'none detected'})"),
            (f"[{lo:.4f}°, {hi:.4f}°]", "ε interval"),
            (f"{m.f_resonance_hz:.2f} Hz", f"resonance, ζ {m.zeta_resonance:.3f}"),
            (f"{m.f_antiresonance_hz:.2f} Hz", f"anti-resonance, ζ {m.zeta_antiresonance:.3f}"),
            (f"{100 * last_err:.3g} %", "FRD error (last iteration)"),
            (ident.method.value, f"method · {ident.evaluations} search evaluations"),
        ]
        if true_plant is not None and math.isfinite(true_plant[1]):
            cards.append((f"{math.degrees(true_plant[1]):.4f}°", "true ε (simulator)"))
        parts.append('<div class="cards">' + "".join(f"<div class=\"card\"><b>{_e(a)}</b><span>{_e(b)}</span></div>"
                                                     for a, b in cards) + "</div>")
        for note in ident.notes:
            parts.append(f'<div class="note">{_e(note)}</div>')
    else:
        parts.append('<div class="note">No identification in this run (--no-identify or it failed): '
                     "measured data only.</div>")
    for w in c.warnings:
        parts.append(f'<div class="note">{_e(w)}</div>')

    # Bode
    parts.append('<h2 id="bode">Frequency response</h2>')
    cap = ("Measured FRD (grey), FRD with the backlash's effect removed (blue: v_m − (v̂_m(ε̂) − v̂_m(0))), "
           "fitted model (red, dashed) and, for simulated runs, the true plant (green, dotted); model curves "
           "include the one-sample delay and the hold. Vertical lines: anti-resonance (dotted) and resonance "
           "(dashed). Bottom: quality per bin — 1 − the coherence-like local-polynomial quality of the FRD, and "
           "the relative difference between the corrected FRD and the model's FRD through the same estimator.")
    if c.frd_corrected is not None and c.frd_model is not None:
        sel = c.frd.frequency_hz >= 1.0
        r = np.abs(c.frd_corrected.response - c.frd_model.response)[sel] / np.abs(c.frd_model.response)[sel]
        r0 = np.abs(c.frd.response - c.frd_model.response)[sel] / np.abs(c.frd_model.response)[sel]
        cap += (f" Relative RMS difference to the model above 1 Hz: measured {100 * np.sqrt(np.mean(r0**2)):.3g} %, "
                f"backlash removed {100 * np.sqrt(np.mean(r**2)):.3g} %.")
    parts.append(_figure(_fig_bode(recording, ident, c), "fig-bode", _e(cap)))

    # time
    parts.append('<h2 id="time">Time series</h2>')
    parts.append(_figure(_fig_time(recording, ident, c), "fig-time", _e(
        "Measured motor velocity and the dead-zone simulation with the identified parameters and ε̂, driven by "
        "the measured torque (open loop). Bottom: what the model leaves unexplained, with and without backlash.")))
    window = _zoom_window(recording, c, float(ident.epsilon_rad) if ident is not None else 0.0)
    if ident is not None and ident.backlash_detected:
        zoom_cap = (f"Zoom on {window[2]}: the simulation with ε̂ follows the measurement where the linear "
                    "model (ε = 0) misses it. Bottom: the twist x_m − x_l against the gap ±ε̂.")
    elif ident is not None:
        zoom_cap = (f"Zoom on {window[2]}. No backlash was detected: the simulation with ε̂ and the linear "
                    "model coincide. Bottom: the twist x_m − x_l.")
    else:
        zoom_cap = f"Zoom on {window[2]} (no identification: measured data only)."
    parts.append(_figure(_fig_zoom(recording, ident, c, window), "fig-zoom", _e(zoom_cap)))

    if ident is not None:
        history = search_history(ident)
        parts.append('<h2 id="search">Backlash search</h2>')
        parts.append(_figure(_fig_search(recording, ident, c, history), "fig-search", _e(
            "Top: the identifier's own loss at the ε it evaluated (by start cell), and the evaluations in the "
            "order they were made. Bottom: the output-error profile over ε computed for this report (the other "
            "parameters held at their identified values). Red: the chosen ε̂ and its interval.")))
        parts.append(f'<h2 id="iterations">Iterations ({_e(ident.method.value)} method)</h2>')
        if ident.iterations:
            parts.append(_figure(_fig_iterations(ident), "fig-iterations", _e(
                "FRD error of step 5 (relative RMS difference between the FRD of the simulated dead-zone model "
                "and the measured FRD) per iteration.")))
        else:
            parts.append('<p class="placeholder">The identification reports no iterations.</p>')
        stderr = ident.parameter_stderr or {}
        prow = [(k, v, f"{100 * stderr[k]:.2g} %" if k in stderr else "") for k, v in ident.parameters.as_dict().items()]
        units = {"J_m": "kg·m²", "J_l": "kg·m²", "B_m": "N·m·s/rad", "B_l": "N·m·s/rad", "K": "N·m/rad", "D": "N·m·s/rad"}
        rows = []
        for k, v, se in prow:
            row = [k, v, units.get(k, ""), se]
            if true_plant is not None:
                tv = float(getattr(true_plant[0], k))
                row += [tv, f"{100 * (v / tv - 1):+.3g} %"]
            rows.append(row)
        header = ["parameter", "identified", "unit", "rel. std. error"] + (["true (simulator)", "deviation"] if true_plant else [])
        parts.append("<h3>Two-mass model</h3>" + _table(rows, header))
        parts.append("<h3>Stages</h3>" + _table([(s.name, f"{s.seconds:.3f} s") for s in ident.stages],
                                                ["stage", "wall time"]))

    # tuning
    parts.append('<h2 id="tuning">Tuning</h2>')
    if tuning is None:
        parts.append('<p class="placeholder" id="tuning-placeholder">No tuning result in this run.</p>')
    else:
        svg = _fig_open_loop(tuning, ident, fs)
        if svg is not None:
            parts.append(_figure(svg, "fig-openloop", "Open loop of the velocity controller on the identified plant, "
                                 "with the gain and phase margins."))
        svg = _fig_steps(tuning)
        if svg is not None:
            parts.append(_figure(svg, "fig-steps", "Closed-loop step responses (as verified by the tuning)."))
        for section in ("velocity_loop", "position_loop", "notch", "backlash_compensation", "margins"):
            v = tuning.get(section)
            if isinstance(v, Mapping) and v:
                parts.append(f"<h3>{_e(section.replace('_', ' '))}</h3>" + _table(_flatten(v), ["parameter", "value"]))
        ver = tuning.get("verification")
        if isinstance(ver, Mapping):
            scalars = [(k, v) for k, v in _flatten(ver) if not (isinstance(v, str) and v.endswith("values]"))]
            if scalars:
                parts.append("<h3>verification</h3>" + _table(scalars, ["item", "value"]))

    # metadata
    parts.append('<h2 id="metadata">Run metadata</h2>')
    meta_rows: list[tuple[str, Any]] = [
        ("drive", drive_name), ("backend", d.backend), ("serial number", d.serial_number or "—"),
        ("firmware", d.firmware or "—"), ("rated torque", f"{d.rated_torque_nm} N·m" if d.rated_torque_nm else "—"),
        ("run started", when), ("report written", datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")),
        ("tool version", f"drive-commission {_tool_version()}"), ("input file", str(source_file) if source_file else "—"),
        ("samples", f"{len(recording):,} at {fs:g} Hz"),
        ("signals", ", ".join(name for name, _ in recording.signals())),
    ]
    meta_rows += [(f"recording: {k}", v) for k, v in recording.metadata.items()]
    meta_rows += [("output file", str(f)) for f in files]
    parts.append(_table(meta_rows))
    if config is not None:
        parts.append("<details><summary>configuration</summary><pre>"
                     + _e(json.dumps(config, indent=2, default=str)) + "</pre></details>")
    if ident is not None:
        parts.append("<details><summary>result.json</summary><pre>"
                     + _e(json.dumps(ident.to_dict(str(source_file) if source_file else None), indent=2)) + "</pre></details>")

    body = "\n".join(parts)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<meta name=\"generator\" content=\"drive-commission {_e(_tool_version())}\">"
            f"<title>{_e(title)} — {_e(drive_name)}</title><style>{_CSS}</style></head>"
            f"<body><main>\n{body}\n</main></body></html>\n")


def write_report(
    path: str | os.PathLike[str],
    recording: Recording,
    identification: Any | None,
    *,
    config: Mapping[str, Any] | None = None,
    source_file: str | os.PathLike[str] | None = None,
    tuning: Mapping[str, Any] | None = None,
    true_plant: tuple[Any, float] | Any | None = None,
    files: Sequence[str | os.PathLike[str]] = (),
) -> Path:
    """Write the self-contained HTML report and return its path.

    :param path: the file (``DIR/report.html``) or a folder (then ``REPORT_NAME`` inside it).
    :param recording: the run's samples.
    :param identification: a :class:`commission.ident.hybrid.Identification`, or None
        (measured data only).
    :param config: the run's config as a dict (``read_config(run.mcap)`` / ``config_to_dict``)
        or a ``Config``; gives the FRD band and resolution, the ε range, and the true plant.
    :param source_file: the input file named in the metadata (``run.mcap`` or the replayed log).
    :param tuning: the tuning result as a dict with controller.json's keys (``velocity_loop``,
        ``position_loop``, ``notch``, ``backlash_compensation``, ``margins``, ``verification``);
        optional ``open_loop`` = {frequency_hz, magnitude_db, phase_deg} (or real/imag) curves,
        and step responses as mappings with ``t_s`` and arrays anywhere under ``verification``.
        Without curves the open loop is rebuilt from controller.json's ``velocity_loop``
        (gain, integral_time_s / integral_gain), ``torque_filter``, ``notch`` list and
        ``drive_model`` on the identified plant (a continuous approximation; margins are read off
        the drawn curve, the tuning's own margins are listed in the table).
    :param true_plant: ``TwoMassParameters`` or (TwoMassParameters, ε [rad]) of the real plant;
        default: from the config's ``sim`` section for simulated runs.
    :param files: output files to list in the metadata.
    :raises OutputError: the file cannot be written.
    """
    from .exceptions import OutputError

    p = Path(path)
    if p.is_dir():
        p = p / REPORT_NAME
    text = render_report(recording, identification, config=config, source_file=source_file,
                         tuning=tuning, true_plant=true_plant, files=files)
    tmp = p.with_name(p.name + ".tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, p)
    except OSError as err:
        raise OutputError(f"cannot write {p}: {err.strerror or err}") from err
    return p
