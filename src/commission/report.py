"""The commissioning report: one self-contained ``report.html`` for the technician at the axis.

The page answers the technician's question first: may these settings go to the drive? It
opens with the verdict (ready / not ready, and every reason), then the figures to check
(ε with its interval, J_m, J_l, K, resonance, anti-resonance, the margins), then the
controller settings with the open loop, the closed-loop verification (tables with units;
step, move and reversal plots), the ``--measure-backlash`` result, the identified model with
the measurement behind it, and the run's metadata.

One loop model: the open-loop Bode plot and every margin on the page come from
:mod:`commission.tuning.loop` on the settings and the identified model — the loop the design
used, whose margins are controller.json's. The plant a verification ran on comes from the run
(``true_plant``: the simulator's machine of a ``--sim`` run, or of a replayed log that says so).

Figures are inline SVG (:mod:`commission.svgplot`, one ``<figure class="plot" id="fig-…">`` each)
with one inline zoom script, so the page opens offline on any laptop. The identification
section's curves are *recomputed* here from the Recording and the Identification (which holds
numbers, not curves) with the identifier's public functions: the measured FRD and the FRD with
the backlash's effect removed (the paper's step 6, output form, v_m − (v̂_m(ε̂) − v̂_m(0))); the
fitted model and, for simulated runs, the true plant as sampled responses
H(j2πf)·e^{−j2πf·T_d}·sinc²(f/f_s), so that they lie on the measured FRD; the measured motor
velocity against the dead-zone simulation with ε̂ and with ε = 0, whole and zoomed on the gap
traversal; the output-error profile over ε with the identifier's own search history
(:func:`search_history`); the step-5 FRD error per iteration.

Public API: :func:`write_report`, :func:`render_report` (the HTML text), :func:`search_history`.
"""

from __future__ import annotations

import html
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from .recording import Recording
from .svgplot import ZOOM_SCRIPT, Figure, Panel

if TYPE_CHECKING:
    from .plant import PlantParameters
    from .sequencer import TuningOutcome

__all__ = ["REPORT_NAME", "render_report", "search_history", "write_report"]

#: File name of the report in the output folder.
REPORT_NAME = "report.html"

_COLORS = {
    "measured": "#9a9a9a",
    "corrected": "#1f77b4",
    "model": "#d62728",
    "true": "#2ca02c",
    "linear": "#ff7f0e",
    "accent": "#6a3d9a",
    "reference": "#555555",
}
#: Points of the ε profile computed for the report (one dead-zone simulation each): over the
#: whole range, and around ε̂.
_PROFILE_POINTS = 21
_PROFILE_NEAR = 8


# --- inputs ----------------------------------------------------------------------------------
def search_history(identification: Any) -> list[dict[str, Any]]:
    """The identifier's evaluations of its ε search, in order, from its stage details.

    Recognised (the identifier decides what it keeps; absent → empty list):

    * stage ``scan`` (hybrid): ``detail["history"]`` = list of
      ``{"epsilon_deg", "cost_nm", "phi"?, "omega_scale"?}`` in evaluation order;
    * stage ``paper``: ``detail["searches"]`` = list (one per pass) of
      ``{"history": [[epsilon_deg, loss], ...] or [{"epsilon_deg", "loss"}], "method"?, …}``.

    Returns dicts ``{"pass", "epsilon_deg", "loss", "phi", "omega_scale", "unit"}``.
    """
    out: list[dict[str, Any]] = []
    for stage in getattr(identification, "stages", []) or []:
        detail = getattr(stage, "detail", {}) or {}
        if stage.name == "scan" and isinstance(detail.get("history"), Sequence):
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


# --- the numbers behind the figures ----------------------------------------------------------
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


def _options(config: Mapping[str, Any] | None, identification: Any = None,
             n_samples: int = 0, fs: float = 0.0) -> tuple[tuple[float, float], float, tuple[float, float]]:
    """FRD band and resolution (the identification's own when it has them) and the ε range."""
    opts = (config or {}).get("identification") or {}
    band = tuple(opts.get("band_hz") or (0.1, 400.0))
    res = max(float(opts.get("resolution_hz") or 0.1), fs / n_samples if n_samples else 0.0)
    for stage in getattr(identification, "stages", []) or []:
        if stage.name == "start" and "band_hz" in stage.detail:
            band = tuple(stage.detail["band_hz"])
            res = float(stage.detail.get("resolution_hz", res))
    eb = tuple(opts.get("epsilon_bounds_deg") or (0.01, 1.0))
    return (float(band[0]), float(band[1])), res, (float(eb[0]), float(eb[1]))


def _curves(rec: Recording, ident: Any, config: Mapping[str, Any] | None,
            true_plant: PlantParameters | None) -> _Curves:
    from .exceptions import IdentificationError
    from .ident.backlash import simulate_deadzone, simulate_motor_velocity
    from .ident.frd import estimate_frd

    fs = rec.sample_rate_hz
    band, res, eb = _options(config, ident, len(rec), fs)
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
        true = _sampled(true_plant.two_mass.velocity_response(f_dense), f_dense, fs, 1.0 / fs)
    if ident is None:
        return _Curves(frd, None, None, f_dense, None, true, None, None, None, None, None, None, band, warnings)

    p, eps = ident.parameters, float(ident.epsilon_rad)
    delay = max(0, int(round(float(ident.delay_s) * fs)))
    model = _sampled(p.velocity_response(f_dense), f_dense, fs, float(ident.delay_s))
    u = _applied_torque(rec, ident)
    sim = simulate_deadzone(p, eps, u, fs, delay_samples=delay)
    sim0 = simulate_deadzone(p, 0.0, u, fs, delay_samples=delay) if eps > 0 else sim
    v_lin_meas = v - (sim.motor_velocity - sim0.motor_velocity)
    frd_corr = estimate_frd(u, v_lin_meas, fs, band_hz=band, resolution_hz=res)
    frd_model = estimate_frd(u, sim0.motor_velocity, fs, band_hz=band, resolution_hz=res)

    hi = max(2.0 * eb[1], 1.5 * math.degrees(eps), 0.05)
    # uniform over the range, denser around ε̂ where the loss has its narrow minimum
    e_hat = math.degrees(eps)
    near = e_hat + 0.1 * hi * np.linspace(-1.0, 1.0, _PROFILE_NEAR)
    grid = np.unique(np.concatenate([np.linspace(0.0, hi, _PROFILE_POINTS), near[near >= 0.0], [e_hat]]))
    rms = np.empty(grid.size)
    mx = np.empty(grid.size)
    for i, e in enumerate(grid):
        d = v - simulate_motor_velocity(p, math.radians(e), u, fs, delay_samples=delay)
        rms[i] = float(np.sqrt(np.mean(d * d)))
        mx[i] = float(np.max(np.abs(d)))
    return _Curves(frd, frd_corr, frd_model, f_dense, model, true, sim.motor_velocity, sim0.motor_velocity,
                   sim.twist, grid, rms, mx, band, warnings)


def _applied_torque(rec: Recording, ident: Any) -> NDArray[np.float64]:
    """τ_ref plus the cogging the identification found (as the hybrid stage added it: over each interval, at the
    motor's mid position) [N·m], shape (N,): the torque the simulations are driven by."""
    found = getattr(ident, "cogging", None)
    if not found:
        return rec.torque_ref
    from .ident.cogging import Cogging
    from .ident.residual import motor_position_samples

    x = motor_position_samples(rec.motor_position, rec.motor_velocity, rec.sample_rate_hz)
    return rec.torque_ref + Cogging.from_dict(found).interval_torque(x)


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


# --- identification figures ------------------------------------------------------------------
def _db(h: NDArray[np.complex128]) -> NDArray[np.float64]:
    return 20.0 * np.log10(np.maximum(np.abs(h), 1e-300))


def _deg(h: NDArray[np.complex128]) -> NDArray[np.float64]:
    return np.degrees(np.unwrap(np.angle(h)))


def _mark_modes(panels: Sequence[Panel], ident: Any) -> None:
    if ident is None:
        return
    m = ident.modes
    for f, name, dash in ((m.f_antiresonance_hz, "anti-resonance", "2 3"), (m.f_resonance_hz, "resonance", "6 3")):
        if not (math.isfinite(f) and f > 0):
            continue
        for i, ax in enumerate(panels):
            ax.vline(f, color=_COLORS["accent"], dash=dash, label=f"{name} {f:.1f} Hz" if i == 0 else None)


def _fig_bode(ident: Any, c: _Curves) -> str:
    fig = Figure(title="Frequency response: torque reference → motor velocity")
    ax_m = fig.panel(300, x_scale="log", y_label="|V_m / T_ref| [dB]")
    ax_p = fig.panel(200, x_scale="log", y_label="phase [deg]")
    ax_q = fig.panel(170, x_scale="log", y_scale="log", y_label="lower is better [-]", x_label="frequency [Hz]")
    f = c.frd.frequency_hz
    ax_m.line(f, _db(c.frd.response), color=_COLORS["measured"], width=0.8, label="measured FRD")
    ax_p.line(f, _deg(c.frd.response), color=_COLORS["measured"], width=0.8)
    if c.frd_corrected is not None:
        ax_m.line(f, _db(c.frd_corrected.response), color=_COLORS["corrected"], width=0.9,
                  label="FRD, backlash effect removed")
        ax_p.line(f, _deg(c.frd_corrected.response), color=_COLORS["corrected"], width=0.9)
    if c.model is not None:
        ax_m.line(c.f_dense, _db(c.model), color=_COLORS["model"], width=1.6, dash="6 3", label="fitted model")
        ax_p.line(c.f_dense, _deg(c.model), color=_COLORS["model"], width=1.6, dash="6 3")
    if c.true is not None:
        ax_m.line(c.f_dense, _db(c.true), color=_COLORS["true"], width=1.6, dash="2 2",
                  label="true plant (simulator)")
        ax_p.line(c.f_dense, _deg(c.true), color=_COLORS["true"], width=1.6, dash="2 2")
    ax_q.line(f, np.maximum(1.0 - c.frd.quality, 1e-9), color=_COLORS["measured"], width=0.8,
              label="1 − quality, measured FRD")
    if c.frd_corrected is not None and c.frd_model is not None:
        ax_q.line(f, np.maximum(1.0 - c.frd_corrected.quality, 1e-9), color=_COLORS["corrected"], width=0.8,
                  label="1 − quality, backlash removed")
        resid = np.abs(c.frd_corrected.response - c.frd_model.response) / np.abs(c.frd_model.response)
        ax_q.line(f, np.maximum(resid, 1e-9), color=_COLORS["model"], width=0.8,
                  label="|FRD (backlash removed) − model| / |model|")
    for ax in (ax_m, ax_p, ax_q):
        ax.x.fixed = (float(c.f_dense[0]), float(c.band_hz[1]))
    _mark_modes((ax_m, ax_p, ax_q), ident)
    return fig.svg("fig-bode")


def _fig_time(rec: Recording, ident: Any, c: _Curves) -> str:
    fig = Figure(title="Motor velocity over the whole run (min/max per pixel column)")
    ax_v = fig.panel(280, y_label="motor velocity [rad/s]")
    ax_v.line(rec.t, rec.motor_velocity, color="#000000", width=1.4, label="measured v_m")
    if c.v_sim is not None and c.v_lin is not None:
        ax_v.line(rec.t, c.v_sim, color=_COLORS["model"], width=0.7, label=f"simulated, ε̂ = {ident.epsilon_deg:.3f}°")
        ax_e = fig.panel(200, y_label="error [rad/s]", x_label="time [s]")
        ax_e.line(rec.t, rec.motor_velocity - c.v_lin, color=_COLORS["linear"], width=0.7,
                  label="measured − simulated with ε = 0 (no backlash)")
        ax_e.line(rec.t, rec.motor_velocity - c.v_sim, color=_COLORS["model"], width=0.7,
                  label="measured − simulated with ε̂")
    else:
        ax_v.x_label = "time [s]"
    return fig.svg("fig-time")


def _fig_zoom(rec: Recording, ident: Any, c: _Curves, window: tuple[int, int, str]) -> str:
    a, b, _ = window
    t = rec.t[a:b] * 1e3
    has_twist = c.twist_sim is not None or (rec.motor_position is not None and rec.load_position is not None)
    fig = Figure(title="Zoom on a reversal")
    ax = fig.panel(260, y_label="motor velocity [rad/s]", x_label="" if has_twist else "time [ms]")
    if c.v_sim is not None and c.v_lin is not None:
        ax.line(t, c.v_sim[a:b], color=_COLORS["model"], width=4.0, opacity=0.4,
                label=f"simulated, ε̂ = {ident.epsilon_deg:.3f}°")
        ax.line(t, c.v_lin[a:b], color=_COLORS["linear"], width=1.1, dash="5 3", label="simulated, ε = 0 (no backlash)")
    ax.line(t, rec.motor_velocity[a:b], color="#000000", width=0.9, label="measured v_m")
    if has_twist:
        ax2 = fig.panel(220, y_label="twist [deg]", x_label="time [ms]")
        if ident is not None and ident.backlash_detected and ident.epsilon_rad > 0:
            e = ident.epsilon_deg
            ax2.hspan(-e, e, color=_COLORS["accent"], opacity=0.12, label=f"gap ±ε̂ = ±{e:.3f}°")
        if c.twist_sim is not None:
            ax2.line(t, np.degrees(c.twist_sim[a:b]), color=_COLORS["model"], width=4.0, opacity=0.4,
                     label="simulated twist (ε̂)")
        if rec.motor_position is not None and rec.load_position is not None:
            twist = rec.motor_position[a:b] - rec.load_position[a:b]
            # the encoders' zero is arbitrary: centre the measured twist on the simulation's
            if c.twist_sim is not None:
                twist = twist - np.median(rec.motor_position - rec.load_position) + np.median(c.twist_sim)
            ax2.line(t, np.degrees(twist), color="#000000", width=0.9, label="measured twist x_m − x_l (encoders)")
    return fig.svg("fig-zoom")


def _fig_search(ident: Any, c: _Curves, history: list[dict[str, Any]]) -> str:
    e_hat = ident.epsilon_deg
    lo, hi = (math.degrees(x) for x in ident.epsilon_interval_rad)
    fig = Figure(share_x=False)

    def mark(ax: Panel, horizontal: bool = False) -> None:
        if horizontal:
            if hi > lo:
                ax.hspan(lo, hi, color=_COLORS["model"], opacity=0.15, label=f"interval [{lo:.4f}°, {hi:.4f}°]")
            ax.hline(e_hat, color=_COLORS["model"], width=1.0, label=f"chosen ε̂ = {e_hat:.4f}°")
        else:
            if hi > lo:
                ax.vspan(lo, hi, color=_COLORS["model"], opacity=0.15, label=f"interval [{lo:.4f}°, {hi:.4f}°]")
            ax.vline(e_hat, color=_COLORS["model"], width=1.0, label=f"chosen ε̂ = {e_hat:.4f}°")

    palette = ["#440154", "#3b528b", "#21918c", "#5ec962", "#fde725", "#1f77b4", "#ff7f0e", "#2ca02c"]
    if history:
        eps = np.array([h["epsilon_deg"] for h in history])
        loss = np.array([h["loss"] for h in history])
        keys = [(h["pass"], h["phi"], h["omega_scale"]) for h in history]
        groups = sorted(set(keys), key=lambda k: tuple(-1 if v is None else v for v in k))
        ax_h = fig.panel(260, y_scale="log", title=f"The identifier's search: {len(history)} evaluations",
                         x_label="ε [deg]", y_label=f"loss [{history[0]['unit']}]")
        for gi, key in enumerate(groups):
            sel = np.array([k == key for k in keys])
            order = np.argsort(eps[sel])
            label = ", ".join(f"{n} {v:g}" for n, v in zip(("pass", "φ", "ω-scale"), key)
                              if v is not None and not (n == "pass" and len(groups) == 1))
            ax_h.markers(eps[sel][order], loss[sel][order], color=palette[gi % len(palette)], size=2.5,
                         label=label or None, line=True)
        mark(ax_h)
        ax_o = fig.panel(220, title="Evaluations in order", x_label="evaluation #", y_label="ε [deg]")
        ax_o.markers(np.arange(1, eps.size + 1), eps, color=_COLORS["corrected"], size=2.5, line=True,
                     label="evaluated ε")
        mark(ax_o, horizontal=True)
    else:
        best: list[Mapping[str, Any]] = []
        for s in ident.stages:
            if s.name == "scan" and isinstance(s.detail.get("best"), Sequence):
                best = [b for b in s.detail["best"] if isinstance(b, Mapping)]
        if best:
            ax_h = fig.panel(220, y_scale="log", x_label="ε [deg]", y_label="torque residual RMS [N·m]",
                             title=f"The identifier's search: {ident.evaluations} evaluations; the best cells "
                             "(the history is not kept)")
            ax_h.markers([b["epsilon_deg"] for b in best], [b.get("cost_nm", math.nan) for b in best],
                         color=_COLORS["corrected"], size=3.5, label="best cells of the search")
            mark(ax_h)
        its = [it["epsilon_deg"] for it in ident.iterations]
        if its:
            ax_o = fig.panel(200, title="ε over the iterations", x_label="iteration", y_label="ε [deg]")
            ax_o.markers(np.arange(1, len(its) + 1), its, color=_COLORS["accent"], size=3.5, line=True,
                         label="ε per iteration")
            mark(ax_o, horizontal=True)
    ax_p = fig.panel(280, y_scale="log", x_label="ε [deg]", y_label="output error [rad/s]",
                     title="Loss over ε, the other parameters at their identified values (computed for this report)")
    if c.profile_eps_deg is not None and c.profile_rms is not None and c.profile_max is not None:
        ax_p.markers(c.profile_eps_deg, c.profile_rms, color=_COLORS["corrected"], size=2.2, line=True,
                     label="RMS(v_m − v̂_m(ε))")
        ax_p.markers(c.profile_eps_deg, c.profile_max, color=_COLORS["linear"], size=2.2, line=True,
                     label="max |v_m − v̂_m(ε)| (paper's loss)")
    mark(ax_p)
    return fig.svg("fig-search")


def _fig_iterations(ident: Any) -> str:
    its = ident.iterations
    if ident.method.value == "hybrid" and len(its) in (2, 3):
        names = ["frequency-domain start", "joint fit", "step-6 refit"][: len(its)]
    else:
        names = [f"pass {i}" for i in range(len(its))]
    err = [max(float(it["frd_error"]), 1e-12) for it in its]
    fig = Figure(title="FRD of the dead-zone simulation vs the measured FRD, per iteration")
    ax = fig.panel(220, y_scale="log", y_label="FRD error (step 5) [-]",
                   y_limits=(min(err) / 3, max(err) * 8))
    ax.bars(names, err, color=_COLORS["corrected"],
            annotations=[f"{100 * it['frd_error']:.3g} %, ε = {it['epsilon_deg']:.4f}°" for it in its])
    return fig.svg("fig-iterations")


# --- tuning and verification figures ---------------------------------------------------------
def _fmt_hz(f: float) -> str:
    return f"{f / 1e3:.3g} kHz" if f >= 1e3 else f"{f:.3g} Hz"


def _fig_open_loop(settings: Any, model: Any) -> str:
    """Bode plot of the velocity loop on the identified model, marked with the design's margins
    (the same loop: :func:`commission.tuning.open_loop`)."""
    from .tuning import open_loop

    fs = settings.sample_rate_hz
    f = np.geomspace(0.5, 0.49 * fs, 900)
    fig = Figure(title="Velocity loop: open loop L = C·G on the identified model")
    ax_m = fig.panel(280, x_scale="log", y_label="|L| [dB]")
    ax_p = fig.panel(250, x_scale="log", y_label="phase of L [deg]", x_label="frequency [Hz]")
    loops = [("gears in contact", False, settings.margins, _COLORS["corrected"])]
    if settings.margins_gap is not None:
        loops.append(("gears apart (motor alone)", True, settings.margins_gap, _COLORS["linear"]))
    for label, gap, m, color in loops:
        L = open_loop(settings, model, f, gap=gap)
        phase = _deg(L)
        phase -= 360.0 * math.floor((phase[0] + 360.0) / 360.0)  # start in (−360°, 0°]
        pm = f"PM {m.phase_margin_deg:.1f}° at {_fmt_hz(m.crossover_hz)}" if math.isfinite(m.crossover_hz) else "no crossover"
        gm = (f"GM {m.gain_margin_db:.1f} dB at {_fmt_hz(m.phase_crossover_hz)}" if math.isfinite(m.phase_crossover_hz)
              else "no phase crossover")
        ax_m.line(f, _db(L), color=color, width=1.4, label=f"{label}: {gm}")
        ax_p.line(f, phase, color=color, width=1.4, label=f"{label}: {pm}")
        if math.isfinite(m.crossover_hz):
            ax_m.vline(m.crossover_hz, color=color, dash="4 3")
            ax_p.vline(m.crossover_hz, color=color, dash="4 3")
        if math.isfinite(m.phase_crossover_hz):
            ax_m.vline(m.phase_crossover_hz, color=color, dash="1 2")
            ax_p.vline(m.phase_crossover_hz, color=color, dash="1 2")
    ax_m.hline(0.0, color="#000000", width=0.9)
    for k in (-180.0, -540.0):
        ax_p.hline(k, color="#000000", width=0.9)
    return fig.svg("fig-openloop")


def _verification_fig(ident: str, title: str, panels: list[tuple[str, list[tuple[str, Any, Any, str, str | None]]]],
                      share_x: bool = True) -> str:
    fig = Figure(title=title, share_x=share_x)
    for k, (ylabel, lines) in enumerate(panels):
        ax = fig.panel(230, y_label=ylabel, x_label="time [ms]" if k == len(panels) - 1 or not share_x else "")
        for label, t, y, color, dash in lines:
            ax.line(np.asarray(t) * 1e3, y, color=color, width=1.3, dash=dash, label=label)
    return fig.svg(ident)


def _fig_steps(v: Any) -> str | None:
    runs = v.runs.get("proposed", {})
    panels: list[tuple[str, list[tuple[str, Any, Any, str, str | None]]]] = []
    vs = runs.get("velocity_step")
    if vs is not None and "t" in vs.signals:
        s = vs.signals
        lines = [("motor velocity", s["t"], s["motor_velocity"], _COLORS["corrected"], None)]
        other = v.runs.get("without_notch", {}).get("velocity_step")
        if other is not None:
            lines.append(("motor velocity, without the notch", other.signals["t"], other.signals["motor_velocity"],
                          _COLORS["linear"], "5 3"))
        panels.append(("velocity step: velocity [rad/s]", lines))
    ps = runs.get("position_step")
    if ps is not None and "t" in ps.signals:
        s = ps.signals
        lines = [("motor position", s["t"], 1e3 * s["motor_position"], _COLORS["corrected"], None),
                 ("load position", s["t"], 1e3 * s["load_position"], _COLORS["true"], None)]
        other = v.runs.get("without_backlash_compensation", {}).get("position_step")
        if other is not None:
            lines.append(("load position, without backlash compensation", other.signals["t"],
                          1e3 * other.signals["load_position"], _COLORS["linear"], "5 3"))
        panels.append(("position step: position [mrad]", lines))
    if not panels:
        return None
    return _verification_fig("fig-step", "Step responses (closed loop on the verification plant)", panels,
                             share_x=False)


def _fig_move(v: Any, scenario: str, fig_id: str, title: str) -> str | None:
    r = v.runs.get("proposed", {}).get(scenario)
    if r is None or "t" not in r.signals:
        return None
    s = r.signals
    ref = s.get("reference")
    lines = []
    if ref is not None:
        lines.append(("reference", s["t"], 1e3 * ref, _COLORS["reference"], "2 2"))
    lines += [("motor position", s["t"], 1e3 * s["motor_position"], _COLORS["corrected"], None),
              ("load position", s["t"], 1e3 * s["load_position"], _COLORS["true"], None)]
    other = v.runs.get("without_backlash_compensation", {}).get(scenario)
    if other is not None:
        lines.append(("load position, without backlash compensation", other.signals["t"],
                      1e3 * other.signals["load_position"], _COLORS["linear"], "5 3"))
    panels: list[tuple[str, list[tuple[str, Any, Any, str, str | None]]]] = [("position [mrad]", lines)]
    if ref is not None:
        err = [("load − reference", s["t"], 1e3 * (s["load_position"] - ref), _COLORS["true"], None)]
        if other is not None:
            err.append(("load − reference, without backlash compensation", other.signals["t"],
                        1e3 * (other.signals["load_position"] - other.signals["reference"]), _COLORS["linear"], "5 3"))
        panels.append(("load error [mrad]", err))
    return _verification_fig(fig_id, title, panels)


# --- HTML ------------------------------------------------------------------------------------
_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,'DejaVu Sans',sans-serif;margin:0;color:#1d1d1f;background:#f6f7f9}
main{max-width:1100px;margin:0 auto;padding:16px 24px 48px}
h1{font-size:1.5em;margin:.6em 0 .2em}h2{font-size:1.2em;margin:1.6em 0 .4em;border-bottom:1px solid #ddd;padding-bottom:.2em}
h3{font-size:1.02em;margin:1.1em 0 .3em}
.sub{color:#555;margin:0 0 1em}
.verdict{border-radius:8px;padding:12px 18px;margin:12px 0;border:2px solid}
.verdict h2{border:0;margin:0 0 .3em;padding:0;font-size:1.35em}
.verdict ul{margin:.3em 0 .2em 1.2em;padding:0}.verdict p{margin:.3em 0}
.verdict.ready{background:#e8f6ec;border-color:#2e9d4f}.verdict.ready h2{color:#1d7a3a}
.verdict.not-ready{background:#fdecea;border-color:#d64541}.verdict.not-ready h2{color:#b3261e}
.verdict.none{background:#f0f1f4;border-color:#b8bcc6}
.cards{display:flex;flex-wrap:wrap;gap:10px;margin:12px 0}
.card{background:#fff;border:1px solid #e0e0e0;border-radius:6px;padding:8px 14px;min-width:130px}
.card b{display:block;font-size:1.2em;font-variant-numeric:tabular-nums}.card span{color:#666;font-size:.85em}
figure.plot{background:#fff;border:1px solid #e0e0e0;border-radius:6px;margin:12px 0;padding:8px}
figure.plot svg{width:100%;height:auto;display:block}
figcaption{color:#444;font-size:.9em;padding:4px 6px}
table{border-collapse:collapse;background:#fff;font-size:.92em;margin:8px 0}
td,th{border:1px solid #e0e0e0;padding:3px 10px;text-align:left;vertical-align:top}
th{background:#f0f1f4}
td.num{font-variant-numeric:tabular-nums;text-align:right}
td.bad{color:#b3261e;font-weight:600}
.note{background:#fff8e1;border:1px solid #f0d98a;border-radius:6px;padding:6px 12px;margin:8px 0}
.placeholder{color:#666;font-style:italic}
pre{background:#fff;border:1px solid #e0e0e0;padding:8px;overflow:auto;font-size:.85em}
nav a{margin-right:12px}
"""


_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _qty(v: float, digits: int = 4) -> str:
    """A number for a person: 23.1, 0.0154, 4.78×10⁻⁴."""
    if v == 0 or not math.isfinite(v) or 1e-2 <= abs(v) < 1e5:
        return f"{v:.{digits}g}"
    m, e = f"{v:.{digits - 1}e}".split("e")
    return f"{m.rstrip('0').rstrip('.')}×10{str(int(e)).translate(_SUPERSCRIPT)}"


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _cell(v: Any) -> str:
    if v is None:
        return '<td class="num">—</td>'
    if isinstance(v, bool):
        return f"<td>{'yes' if v else 'no'}</td>"
    if isinstance(v, float):
        return f'<td class="num">{_qty(v)}</td>' if math.isfinite(v) else '<td class="num">—</td>'
    if isinstance(v, tuple) and len(v) == 2 and v[0] == "html":
        return v[1]
    return f"<td>{_e(v)}</td>"


def _table(rows: Sequence[Sequence[Any]], header: Sequence[str] | None = None, cls: str = "") -> str:
    out = [f'<table class="{cls}">'] if cls else ["<table>"]
    if header:
        out.append("<tr>" + "".join(f"<th>{_e(h)}</th>" for h in header) + "</tr>")
    for row in rows:
        out.append("<tr>" + "".join(_cell(v) for v in row) + "</tr>")
    out.append("</table>")
    return "".join(out)


def _figure(svg: str, fig_id: str, caption: str) -> str:
    return f'<figure class="plot" id="{fig_id}">{svg}<figcaption>{_e(caption)}</figcaption></figure>'


def _margin(value: float, unit: str, key: str, required: float | None = None) -> tuple[str, str]:
    """A margin as a table cell that names its controller.json key (``data-key``), so that the page
    can be checked against the file; red when below the requirement."""
    text = "—" if not math.isfinite(value) else f"{value:.1f}{unit}"
    bad = required is not None and math.isfinite(value) and value < required
    return ("html", f'<td class="num margin{" bad" if bad else ""}" data-key="{_e(key)}">{_e(text)}</td>')


def _tool_version() -> str:
    try:
        from importlib.metadata import version

        return version("drive-commission")
    except Exception:  # noqa: BLE001
        return "0+unknown"


def _verdict(ident: Any, tuning: TuningOutcome | None) -> str:
    """The verdict box: ready / not ready and every reason (controller.json's), or why there is none."""
    notes: list[str] = []
    quality = getattr(ident, "fit", None)
    if quality is not None and quality.approximate:
        notes.append("The identification says its result is approximate: " + "; ".join(quality.reasons)
                     + ". Read its notes under 'Identified model' before trusting the settings.")
        remedies = getattr(quality, "remedies", ())
        if remedies:
            notes.append("Unless something else moved the axis during the run, a new record would help: "
                         + "; or ".join(remedies) + ".")
    if tuning is None:
        why = ("No identification in this run (--no-identify, or it failed): measured data only."
               if ident is None else "No controller settings in this run (--no-tune): the identified model only.")
        body = f"<p>{_e(why)}</p>" + "".join(f"<p>{_e(n)}</p>" for n in notes)
        return (f'<section class="verdict none" id="verdict"><h2>No verdict on controller settings</h2>{body}'
                "</section>")
    ver = tuning.controller["verification"]
    ready = bool(ver["ready"])
    reasons = list(ver.get("reasons", []))
    if ready:
        head = "Ready: the settings passed every check"
        body = ("<p>Margins met on the identified model, over the uncertainty set around it (worst case below) "
                "and on the verification plant; no limit cycle; every step settles.</p>")
        nxt = ("Next: apply them with <code>commission … --apply</code> (shows old → new and asks), or enter "
               "the values of controller.json / controller-&lt;drive&gt;.yaml in the drive's tool.")
    else:
        head = "Not ready: do not apply these settings"
        body = "<ul>" + "".join(f"<li>{_e(r)}</li>" for r in reasons) + "</ul>"
        nxt = ("Next: check the model below (identification notes, fit), then try <code>--preset soft</code> "
               "or give the drive's current-loop bandwidth and delays (its description's loop block, or the "
               "config's tuning section).")
    body += "".join(f"<p>{_e(n)}</p>" for n in notes)
    return (f'<section class="verdict {"ready" if ready else "not-ready"}" id="verdict"><h2>{_e(head)}</h2>'
            f"{body}<p>{nxt}</p></section>")


def _cards(ident: Any, tuning: TuningOutcome | None, true_plant: PlantParameters | None) -> str:
    cards: list[tuple[str, str, str]] = []
    if ident is not None:
        lo, hi = (math.degrees(x) for x in ident.epsilon_interval_rad)
        p, m = ident.parameters, ident.modes
        cards += [
            ("tile-epsilon", f"{ident.epsilon_deg:.4f}°",
             f"backlash ε̂ ({'detected' if ident.backlash_detected else 'none detected'}), "
             f"interval [{lo:.4f}°, {hi:.4f}°]"),
            ("tile-jm", f"{_qty(p.J_m)} kg·m²", "motor inertia J_m"),
            ("tile-jl", f"{_qty(p.J_l)} kg·m²", f"load inertia J_l (J_l/J_m {p.J_l / p.J_m:.3g})"),
            ("tile-k", f"{_qty(p.K)} N·m/rad", "shaft stiffness K"),
            ("tile-resonance", f"{m.f_resonance_hz:.2f} Hz", f"resonance, ζ {m.zeta_resonance:.3f}"),
            ("tile-antiresonance", f"{m.f_antiresonance_hz:.2f} Hz", f"anti-resonance, ζ {m.zeta_antiresonance:.3f}"),
        ]
    if tuning is not None:
        mg = tuning.controller["margins"]
        pm = mg["phase_margin_deg"]
        gm = mg["gain_margin_db"]
        cards += [
            ("tile-pm", "—" if pm is None else f"{pm:.1f}°",
             f"phase margin, velocity loop (required {mg['required_phase_margin_deg']:g}°)"),
            ("tile-gm", "—" if gm is None else f"{gm:.1f} dB",
             f"gain margin, velocity loop (required {mg['required_gain_margin_db']:g} dB)"),
        ]
        rb = tuning.controller.get("robust")
        if rb:
            cards.append(("tile-worst", f"{rb['phase_margin_deg']:.1f}° / {rb['gain_margin_db']:.1f} dB",
                          f"worst case over {rb['members']} members ({rb['phase_margin_member']['description']})"))
        lim = tuning.controller.get("bandwidth_limit")
        if lim:
            cards.append(("tile-limit", str(lim["factor"]), "what limited the velocity loop's bandwidth"))
    if true_plant is not None:
        cards.append(("tile-true-epsilon", f"{true_plant.epsilon_deg:.4f}°", "true ε (simulator)"))
    if not cards:
        return ""
    return '<div class="cards">' + "".join(
        f'<div class="card" id="{i}"><b>{_e(a)}</b><span>{_e(b)}</span></div>' for i, a, b in cards) + "</div>"


def _settings_table(s: Any) -> str:
    rows: list[tuple[Any, ...]] = [
        ("velocity loop gain k_p", s.velocity_gain, "N·m·s/rad"),
        ("velocity loop gain K_v = k_p / (2π·(J_m + J_l))", s.velocity_loop_gain_hz, "Hz"),
        ("velocity integral time T_i", 1e3 * s.velocity_integral_time_s, "ms"),
        ("velocity loop bandwidth (−3 dB, identified model)", s.velocity_bandwidth_hz, "Hz"),
        ("position loop gain K_p", s.position_gain_per_s, "1/s"),
        ("torque filter time constant", 1e3 * s.torque_filter_time_constant_s, "ms"),
    ]
    if s.notches:
        for i, n in enumerate(s.notches, start=1):
            rows.append((f"notch {i}", f"{n.frequency_hz:.1f} Hz, Q {n.q:.2g}, depth {n.depth_db:.1f} dB", ""))
    else:
        rows.append(("notch", "none", ""))
    rows += [
        ("velocity feedforward", 100.0 * s.velocity_feedforward, "%"),
        ("torque feedforward", 100.0 * s.torque_feedforward, "% of (J_m + J_l)·acceleration"),
    ]
    if s.backlash.enabled:
        rows += [
            ("backlash compensation 2ε", 1e3 * s.backlash.amount_rad, "mrad"),
            ("backlash compensation 2ε", 60.0 * math.degrees(s.backlash.amount_rad), "arcmin"),
            ("backlash compensation direction", s.backlash.direction, ""),
            ("backlash compensation time constant", 1e3 * s.backlash.time_constant_s, "ms"),
            ("position reference filter", 1e3 * s.reference_filter_time_constant_s, "ms"),
        ]
    else:
        rows.append(("backlash compensation", "off", ""))
    rows += [
        ("velocity loop clock", s.sample_rate_hz, "Hz"),
        ("preset", s.preset.value if hasattr(s.preset, "value") else str(s.preset), ""),
    ]
    return _table(rows, ["setting", "value", "unit"]) + _drive_table(s)


def _drive_table(s: Any) -> str:
    """The drive's loop the settings were designed for, each figure with where it comes from,
    and the measured band that bounds the crossover."""
    dyn = s.dynamics
    rows: list[list[Any]] = []
    if dyn is not None:
        def row(label: str, sv: Any, text: str) -> list[Any]:
            src = f"{sv.how.value}: {sv.source}" + (" — confirm" if sv.confirm else "")
            return [label, text, src]

        cl = dyn.current_loop_bandwidth_hz
        def samples(x: Any) -> str:
            return f"{float(x or 0.0):g} sample" + ("" if float(x or 0.0) == 1.0 else "s")

        rows += [row("current loop", cl, "ideal" if cl.value is None else f"{cl.value:g} Hz (first order)"),
                 row("computation delay", dyn.computation_delay_samples, samples(dyn.computation_delay_samples.value)),
                 row("encoder delay", dyn.encoder_delay_samples, samples(dyn.encoder_delay_samples.value)),
                 row("velocity loop clock", dyn.sample_rate_hz, f"{dyn.sample_rate_hz.value:g} Hz"),
                 row("position loop period", dyn.position_loop_period_s,
                     f"{1e6 * float(dyn.position_loop_period_s.value or 0.0):g} µs")]
        if dyn.gain_limits:
            rows.append(["gain ranges", "; ".join(f"{k} {a:g}–{b:g}" for k, (a, b) in dyn.gain_limits.items()),
                         dyn.gain_limits_source])
    if s.measured_band_hz is not None:
        lo, hi = s.measured_band_hz
        limit = "" if s.crossover_limit_hz is None else f"; crossover limit {s.crossover_limit_hz:.0f} Hz"
        rows.append(["measured band", f"{lo:g}–{hi:g} Hz{limit}", s.measured_band_source])
    if s.limit is not None:
        rows.append(["bandwidth limited by", s.limit.factor.value, s.limit.detail])
    if not rows:
        return ""
    return ("<h3>The drive's loop, as designed for</h3>" + _table(rows, ["figure", "value", "from"])
            + "<p>The margins must hold with these figures and over the uncertainty set around them (below). "
              "Figures marked confirm are not from the drive's own manual.</p>")


def _margins_table(tuning: TuningOutcome) -> str:
    """Each loop's margins, on the identified model (controller.json's ``margins``) and, when the
    verification ran on another plant, on that plant (``verification.margins``)."""
    s, v = tuning.settings, tuning.verification
    pm_req, gm_req = s.required_phase_margin_deg, s.required_gain_margin_db
    design_rows = [("velocity loop, gears in contact", s.margins, "margins", True),
                   ("velocity loop, gears apart (motor alone)", s.margins_gap, "margins.gap", True),
                   ("position loop (around the velocity loop)", s.position_margins, "position_loop.margins", False)]
    ver_margins = {"margins": v.margins, "margins.gap": v.margins_gap, "position_loop.margins": v.position_margins}
    ver_keys = {"margins": "verification.margins", "margins.gap": "verification.margins_gap",
                "position_loop.margins": "verification.position_margins"}
    same = all(_same_margins(m, ver_margins[k]) for _, m, k, _ in design_rows)
    header = ["loop", "phase margin", "gain margin", "crossover [Hz]", "stable"]
    if not same:
        header += ["phase margin, verification plant", "gain margin, verification plant", "stable"]
    rows = []
    for label, m, key, required in design_rows:
        if m is None:
            continue
        row: list[Any] = [label,
                          _margin(m.phase_margin_deg, "°", f"{key}.phase_margin_deg", pm_req if required else None),
                          _margin(m.gain_margin_db, " dB", f"{key}.gain_margin_db", gm_req if required else None),
                          m.crossover_hz, m.stable]
        if not same:
            vm = ver_margins[key]
            if vm is None:
                row += [None, None, None]
            else:
                row += [_margin(vm.phase_margin_deg, "°", f"{ver_keys[key]}.phase_margin_deg", pm_req if required else None),
                        _margin(vm.gain_margin_db, " dB", f"{ver_keys[key]}.gain_margin_db", gm_req if required else None),
                        vm.stable]
        rows.append(row)
    rb = s.robust
    if rb is not None:
        row = ["velocity loop, worst case over the uncertainty set",
               _margin(rb.phase_margin_deg, "°", "robust.phase_margin_deg", pm_req),
               _margin(rb.gain_margin_db, " dB", "robust.gain_margin_db", gm_req), None, rb.stable]
        if not same:
            row += [None, None, None]
        rows.append(row)
    note = (f"Required on the velocity loop: phase margin ≥ {pm_req:g}°, gain margin ≥ {gm_req:g} dB "
            f"(preset {s.preset.value if hasattr(s.preset, 'value') else s.preset}; the design keeps a guard on the "
            "identified model). ")
    note += ("The verification ran on the identified model: its margins are these." if same else
             f"The verification plant is another machine ({v.plant_note or 'not the design model'}): its own "
             "margins are beside.")
    if rb is not None:
        unc = rb.uncertainty

        def each(xs: Sequence[float]) -> str:
            return "/".join(f"{x:g}" for x in xs)

        note += (f" Worst case over {rb.members} members (current loop ×{each(unc.current_loop_factors)}, "
                 f"delay +{each(unc.extra_delay_samples)} samples, J_l ×{each(unc.load_inertia_factors)}, "
                 f"K ×{each(unc.stiffness_factors)}, ε ×{each(unc.backlash_factors)}): phase margin set by "
                 f"{rb.phase_member.describe(rb.current_loop_hz)}; gain margin by "
                 f"{rb.gain_member.describe(rb.current_loop_hz)}.")
    return _table(rows, header) + f"<p>{_e(note)}</p>"


def _same_margins(a: Any, b: Any) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return all(math.isclose(x, y, rel_tol=1e-9) or (math.isnan(x) and math.isnan(y)) or x == y
               for x, y in ((a.phase_margin_deg, b.phase_margin_deg), (a.gain_margin_db, b.gain_margin_db)))


_SCENARIO_NAMES = {"velocity_step": "velocity step", "position_step": "position step",
                   "position_move": "smooth move", "reversal": "reversals"}
_CONFIG_NAMES = {"proposed": "proposed settings", "without_notch": "without the notch",
                 "without_backlash_compensation": "without backlash compensation"}


def _verification_table(v: Any, options_note: str) -> str:
    header = ["scenario", "settings", "overshoot [%]", "settling time [ms]", "steady-state error",
              "load error [mrad]", "lost motion [mrad]", "limit cycle", "peak torque [N·m]"]
    rows = []
    for sc in ("velocity_step", "position_step", "position_move", "reversal"):
        for cfg, runs in v.runs.items():
            r = runs.get(sc)
            if r is None:
                continue
            velocity = sc == "velocity_step"
            sse = f"{r.steady_state_error:.3g} rad/s" if velocity else f"{1e3 * r.steady_state_error:.3g} mrad"
            if r.limit_cycle_amplitude > 0:
                amp = (f"{r.limit_cycle_amplitude:.3g} rad/s" if velocity else f"{1e3 * r.limit_cycle_amplitude:.3g} mrad")
                cyc = amp + (f" at {r.limit_cycle_frequency_hz:.1f} Hz" if r.limit_cycle_frequency_hz else "")
            else:
                cyc = "none"
            settle = None if r.settling_time_s is None else 1e3 * r.settling_time_s
            if r.settling_time_s is None and sc in ("velocity_step", "position_step"):
                settle_cell: Any = ("html", '<td class="num bad">does not settle</td>')
            elif r.settling_time_s is None:
                settle_cell = "—"
            else:
                settle_cell = settle
            rows.append([_SCENARIO_NAMES.get(sc, sc), _CONFIG_NAMES.get(cfg, cfg), r.overshoot_pct, settle_cell, sse,
                         None if r.load_error_rad is None else 1e3 * r.load_error_rad,
                         None if r.lost_motion_rad is None else 1e3 * r.lost_motion_rad, cyc, r.peak_torque_nm])
    return _table(rows, header) + f"<p>{_e(options_note)}</p>"


def _plant_rows(pp: PlantParameters) -> list[tuple[Any, ...]]:
    rows: list[tuple[Any, ...]] = [(k, float(getattr(pp, k)), u) for k, u in (
        ("J_m", "kg·m²"), ("J_l", "kg·m²"), ("B_m", "N·m·s/rad"), ("B_l", "N·m·s/rad"), ("K", "N·m/rad"),
        ("D", "N·m·s/rad"))]
    rows.append(("ε", pp.epsilon_deg, "deg"))
    if pp.coulomb_motor_nm or pp.coulomb_load_nm:
        rows += [("Coulomb friction, motor", pp.coulomb_motor_nm, "N·m"), ("Coulomb friction, load", pp.coulomb_load_nm, "N·m")]
    rows.append(("current loop", "ideal" if pp.current_loop_bandwidth_hz is None
                 else f"{pp.current_loop_bandwidth_hz:g} Hz", ""))
    rows.append(("computation delay", float(pp.delay_samples), "samples"))
    return rows


def render_report(
    recording: Recording,
    identification: Any | None,
    *,
    config: Mapping[str, Any] | None = None,
    source_file: str | os.PathLike[str] | None = None,
    tuning: TuningOutcome | None = None,
    true_plant: PlantParameters | None = None,
    backlash_check: Mapping[str, Any] | None = None,
    files: Sequence[str | os.PathLike[str]] = (),
) -> str:
    """The report as one HTML document (text). See :func:`write_report`."""
    if config is not None and not isinstance(config, Mapping):
        config = config.model_dump(mode="json")  # a commission.config.Config
    fs = recording.sample_rate_hz
    ident = identification
    c = _curves(recording, ident, config, true_plant)
    parts: list[str] = []
    title = "Commissioning report"
    d = recording.drive
    drive_name = " ".join(x for x in (d.vendor, d.product) if x) or d.backend
    when = recording.start_time.astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    parts.append(f"<h1>{_e(title)} — {_e(drive_name)}</h1>")
    parts.append(f'<p class="sub">Run of {_e(when)} · {len(recording):,} samples at {fs:g} Hz '
                 f"({recording.duration_s:g} s) · status {_e(recording.metadata.get('status', 'unknown'))}"
                 + (f" · input {_e(source_file)}" if source_file else "")
                 + (" · simulated drive" if true_plant is not None else "") + "</p>")
    parts.append(_verdict(ident, tuning))
    parts.append(_cards(ident, tuning, true_plant))
    nav = []
    if tuning is not None:
        nav += ['<a href="#tuning">Controller settings</a>', '<a href="#verification">Verification</a>']
    if backlash_check:
        nav.append('<a href="#backlash-check">Backlash check</a>')
    nav += ['<a href="#model">Identified model</a>', '<a href="#bode">Frequency response</a>',
            '<a href="#time">Time series</a>']
    if ident is not None:
        nav += ['<a href="#search">Backlash search</a>', '<a href="#iterations">Iterations</a>']
    nav.append('<a href="#metadata">Metadata</a>')
    parts.append("<nav>" + "".join(nav) + "</nav>")
    parts.append('<p class="sub">Line plots: drag across a plot to zoom its x axis, double-click to go back.</p>')

    # controller settings and their verification
    if tuning is not None:
        s, v = tuning.settings, tuning.verification
        parts.append('<h2 id="tuning">Controller settings</h2>')
        parts.append(_settings_table(s))
        parts.append("<h3>Margins</h3>" + _margins_table(tuning))
        model = ident.parameters if ident is not None else None
        if model is not None:
            parts.append(_figure(_fig_open_loop(s, model), "fig-openloop",
                                 "Open loop of the velocity controller on the identified model, exactly as the drive "
                                 "runs it (sampled, with the filters, the current loop and the delay assumed): the "
                                 "loop the margins above are computed on. Dashed: crossover (phase margin); dotted: "
                                 "phase crossover (gain margin)."))
        if s.notes:
            parts.append("<h3>Design notes</h3><ul>" + "".join(f"<li>{_e(n)}</li>" for n in s.notes) + "</ul>")
        parts.append('<h2 id="verification">Verification</h2>')
        plant = v.plant
        where = v.plant_note or ("the simulator's true machine (not the identified model)" if true_plant is not None
                                 else "the identified model with its backlash")
        parts.append(f"<p>Closed-loop runs at {s.sample_rate_hz:g} Hz on {_e(where)}, each from rest with the "
                     "gears centred in the gap.</p>")
        parts.append("<details><summary>verification plant</summary>"
                     + _table(_plant_rows(plant), ["parameter", "value", "unit"]) + "</details>")
        note = ("Load error: |load − target| at the end of the run (reversals: after the moves that follow a "
                "reversal); lost motion: difference of the load errors after a move back and a move out; limit cycle: "
                "a sustained oscillation at the end of the run.")
        parts.append(_verification_table(v, note))
        for svg, fig_id, cap in (
            (_fig_steps(v), "fig-step", "Velocity step (velocity loop alone) and position step (position loop, no "
             "feedforward) with the proposed settings; dashed: without the notch / without backlash compensation."),
            (_fig_move(v, "position_move", "fig-move", "Smooth move (minimum-jerk, with feedforward)"), "fig-move",
             "A smooth move as a motion controller issues it; bottom: the load's error against the reference."),
            (_fig_move(v, "reversal", "fig-reversal", "Reversals: out, back and out again"), "fig-reversal",
             "Moves out, back and out again; after each reversal the backlash shows as a load error unless "
             "compensated. Bottom: the load's error against the reference."),
        ):
            if svg is not None:
                parts.append(_figure(svg, fig_id, cap))

    # --measure-backlash
    if backlash_check:
        bc = backlash_check
        rows: list[tuple[Any, ...]] = [
            ("ε from the velocity reversals", f"{float(bc['epsilon_deg']):.4f}", "deg"),
            ("spread over the reversals", f"{float(bc.get('spread_deg', math.nan)):.4f}", "deg"),
            ("reversals", str(bc.get("reversals", "—")), ""),
            ("log", str(bc.get("log", "—")), ""),
        ]
        if ident is not None:
            rows.insert(1, ("ε̂ of the identification", f"{ident.epsilon_deg:.4f}", "deg"))
        parts.append('<h2 id="backlash-check">Backlash check (velocity reversals, paper §4.2)</h2>'
                     + _table(rows, ["item", "value", "unit"])
                     + "<p>An independent measurement of ε with the load encoder: the gap the motor crosses at each "
                       "reversal of a slow sine velocity.</p>")

    # the identified model and the measurement behind it
    parts.append('<h2 id="model">Identified model</h2>')
    if ident is not None:
        stderr = ident.parameter_stderr or {}
        units = {"J_m": "kg·m²", "J_l": "kg·m²", "B_m": "N·m·s/rad", "B_l": "N·m·s/rad", "K": "N·m/rad", "D": "N·m·s/rad"}
        rows2 = []
        for k, val in ident.parameters.as_dict().items():
            row: list[Any] = [k, float(val), units.get(k, ""), f"{100 * stderr[k]:.2g} %" if k in stderr else "—"]
            if true_plant is not None:
                tv = float(getattr(true_plant, k))
                row += [tv, f"{100 * (val / tv - 1):+.3g} %"]
            rows2.append(row)
        lo, hi = (math.degrees(x) for x in ident.epsilon_interval_rad)
        row = ["ε", ident.epsilon_deg, "deg", f"[{lo:.4f}°, {hi:.4f}°]"]
        if true_plant is not None:
            te = true_plant.epsilon_deg
            row += [te, f"{100 * (ident.epsilon_deg / te - 1):+.3g} %" if te > 0 else "—"]
        rows2.append(row)
        header = ["parameter", "identified", "unit", "rel. std. error / interval"] + (
            ["true (simulator)", "deviation"] if true_plant is not None else [])
        parts.append(_table(rows2, header))
        parts.append(f"<p>Method {_e(ident.method.value)}, {ident.evaluations} search evaluations; "
                     f"resonance {ident.modes.f_resonance_hz:.2f} Hz, anti-resonance {ident.modes.f_antiresonance_hz:.2f} Hz.</p>")
        for note in ident.notes:
            parts.append(f'<div class="note">{_e(note)}</div>')
    else:
        parts.append('<div class="note">No identification in this run (--no-identify or it failed): '
                     "measured data only.</div>")
    for w in c.warnings:
        parts.append(f'<div class="note">{_e(w)}</div>')

    parts.append('<h3 id="bode">Frequency response</h3>')
    cap = ("Measured FRD (grey), FRD with the backlash's effect removed (blue: v_m − (v̂_m(ε̂) − v̂_m(0))), "
           "fitted model (red, dashed) and, for simulated runs, the true plant (green, dotted); model curves "
           "include the one-sample delay and the hold. Vertical lines: anti-resonance and resonance. Bottom: "
           "quality per bin — 1 − the coherence-like local-polynomial quality of the FRD, and the relative "
           "difference between the corrected FRD and the model's FRD through the same estimator.")
    if c.frd_corrected is not None and c.frd_model is not None:
        sel = c.frd.frequency_hz >= 1.0
        r = np.abs(c.frd_corrected.response - c.frd_model.response)[sel] / np.abs(c.frd_model.response)[sel]
        r0 = np.abs(c.frd.response - c.frd_model.response)[sel] / np.abs(c.frd_model.response)[sel]
        cap += (f" Relative RMS difference to the model above 1 Hz: measured {100 * np.sqrt(np.mean(r0**2)):.3g} %, "
                f"backlash removed {100 * np.sqrt(np.mean(r**2)):.3g} %.")
    parts.append(_figure(_fig_bode(ident, c), "fig-bode", cap))

    parts.append('<h3 id="time">Time series</h3>')
    parts.append(_figure(_fig_time(recording, ident, c), "fig-time",
                         "Measured motor velocity and the dead-zone simulation with the identified parameters and ε̂, "
                         "driven by the measured torque (open loop). Bottom: what the model leaves unexplained, with "
                         "and without backlash."))
    window = _zoom_window(recording, c, float(ident.epsilon_rad) if ident is not None else 0.0)
    if ident is not None and ident.backlash_detected:
        zoom_cap = (f"Zoom on {window[2]}: the simulation with ε̂ follows the measurement where the linear "
                    "model (ε = 0) misses it. Bottom: the twist x_m − x_l against the gap ±ε̂.")
    elif ident is not None:
        zoom_cap = (f"Zoom on {window[2]}. No backlash was detected: the simulation with ε̂ and the linear "
                    "model coincide. Bottom: the twist x_m − x_l.")
    else:
        zoom_cap = f"Zoom on {window[2]} (no identification: measured data only)."
    parts.append(_figure(_fig_zoom(recording, ident, c, window), "fig-zoom", zoom_cap))

    if ident is not None:
        history = search_history(ident)
        parts.append('<h3 id="search">Backlash search</h3>')
        parts.append(_figure(_fig_search(ident, c, history), "fig-search",
                             "Top: the identifier's own loss at the ε it evaluated, and the evaluations in the order "
                             "they were made. Bottom: the output-error profile over ε computed for this report (the "
                             "other parameters held at their identified values). Red: the chosen ε̂ and its interval."))
        parts.append(f'<h3 id="iterations">Iterations ({_e(ident.method.value)} method)</h3>')
        if ident.iterations:
            parts.append(_figure(_fig_iterations(ident), "fig-iterations",
                                 "FRD error of step 5 (relative RMS difference between the FRD of the simulated "
                                 "dead-zone model and the measured FRD) per iteration."))
        else:
            parts.append('<p class="placeholder">The identification reports no iterations.</p>')
        parts.append("<h3>Stages</h3>" + _table([(s.name, f"{s.seconds:.3f} s") for s in ident.stages],
                                                ["stage", "wall time"]))

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
    meta_rows += [(f"recording: {k}", v) for k, v in recording.metadata.items() if k != "simulated_plant"]
    meta_rows += [("output file", str(f)) for f in files]
    parts.append(_table(meta_rows))
    if true_plant is not None:
        parts.append("<details><summary>simulated plant</summary>"
                     + _table(_plant_rows(true_plant), ["parameter", "value", "unit"]) + "</details>")
    if config is not None:
        parts.append("<details><summary>configuration</summary><pre>"
                     + _e(json.dumps(config, indent=2, default=str)) + "</pre></details>")
    if ident is not None:
        parts.append("<details><summary>result.json</summary><pre>"
                     + _e(json.dumps(ident.to_dict(str(source_file) if source_file else None), indent=2))
                     + "</pre></details>")

    body = "\n".join(p for p in parts if p)
    zoom = f"<script>{ZOOM_SCRIPT}</script>" if 'data-zoom="x"' in body else ""
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<meta name=\"generator\" content=\"drive-commission {_e(_tool_version())}\">"
            f"<title>{_e(title)} — {_e(drive_name)}</title><style>{_CSS}</style></head>"
            f"<body><main>\n{body}\n</main>{zoom}</body></html>\n")


def write_report(
    path: str | os.PathLike[str],
    recording: Recording,
    identification: Any | None,
    *,
    config: Mapping[str, Any] | None = None,
    source_file: str | os.PathLike[str] | None = None,
    tuning: TuningOutcome | None = None,
    true_plant: PlantParameters | None = None,
    backlash_check: Mapping[str, Any] | None = None,
    files: Sequence[str | os.PathLike[str]] = (),
) -> Path:
    """Write the self-contained HTML report and return its path.

    :param path: the file (``DIR/report.html``) or a folder (then ``REPORT_NAME`` inside it).
    :param recording: the run's samples.
    :param identification: a :class:`commission.ident.hybrid.Identification`, or None
        (measured data only).
    :param config: the run's config as a dict (``read_config(run.mcap)`` / ``config_to_dict``)
        or a ``Config``; gives the FRD band and resolution and the ε range.
    :param source_file: the input file named in the metadata (``run.mcap`` or the replayed log).
    :param tuning: the run's :class:`commission.sequencer.TuningOutcome` (settings, verification,
        controller.json's document): the verdict, the settings, the margins and the verification.
    :param true_plant: the simulator's plant when the run was on the simulated drive (the caller
        knows it): drawn beside the model, named as the verification plant.
    :param backlash_check: ``--measure-backlash``'s result as in result.json
        (``epsilon_deg``, ``spread_deg``, ``reversals``, ``log``).
    :param files: output files to list in the metadata.
    :raises OutputError: the file cannot be written.
    """
    from .exceptions import OutputError

    p = Path(path)
    if p.is_dir():
        p = p / REPORT_NAME
    text = render_report(recording, identification, config=config, source_file=source_file, tuning=tuning,
                         true_plant=true_plant, backlash_check=backlash_check, files=files)
    tmp = p.with_name(p.name + ".tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, p)
    except OSError as err:
        raise OutputError(f"cannot write {p}: {err.strerror or err}") from err
    return p
