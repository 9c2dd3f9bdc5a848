"""Controller design from the identified two-mass model and backlash.

The loop (motor-side feedback, the drive's cascade at its own clock Ts)::

    position P ─► velocity PI ─► torque low-pass ─► notch(es) ─► current loop ─► plant

Design rule (issue #6): the highest velocity-loop gain whose loop, on the identified
model *with* the filters, the sampling (zero-order hold + backward-difference
velocity: one sample) and the current-loop / computation delay, keeps a phase
margin ≥ PM and a gain margin ≥ GM (presets ``soft`` / ``standard`` / ``stiff``).
Every candidate is analysed in discrete time, exactly, on the loop of :mod:`.loop`
(the one loop model the report and the verification use too).

With backlash the loop has two plants: in contact, the two-mass model; in the
gap, the motor alone (1/(J_m·s + B_m)), whose gain below the resonance is
(J_m + J_l)/J_m times higher. Both must meet the margins (the gap without the
design guard), or the loop may oscillate while the gears are apart.

The search: for each torque-filter ratio and with/without a notch at the
identified resonance, a log-spaced scan of the rigid-body velocity-loop gain
K_v = k_p / (2π·(J_m + J_l)) [Hz] and a bisection at the edge; the candidate
with the highest closed-loop bandwidth wins; a notch is kept only when it raises
the bandwidth by more than ``notch_min_gain`` (a resonance well inside the
velocity-loop bandwidth is damped by the collocated loop; a notch there only costs
phase). Margins for the search are read from a dense frequency grid (crossings
interpolated); the reported margins of the chosen settings locate each crossing exactly
on the same loop (:func:`.loop.loop_margins`; the tests check them against python-control).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..ident.twomass import TwoMassParameters, modes
from .loop import (
    Poly,
    _bandwidth_hz,
    _controller_z,
    _eval,
    _freq_grid,
    _grid_margins,
    _grid_meets,
    _plant_z,
    _polymul,
    loop_margins,
)
from .scenarios import choose_backlash_direction, plant_from_model
from .settings import (
    BacklashCompensation,
    ControllerSettings,
    LoopMargins,
    Notch,
    TuningError,
    TuningOptions,
)

__all__ = ["approach_time_constant", "design"]


# --------------------------------------------------------------------------------------------
# the design
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Model:
    params: TwoMassParameters
    epsilon_rad: float
    backlash: bool


def _as_model(model: Any, epsilon_rad: float | None, options: TuningOptions) -> _Model:
    if isinstance(model, TwoMassParameters):
        eps = float(epsilon_rad or 0.0)
        return _Model(model, eps, eps > math.radians(options.backlash_threshold_deg))
    params = getattr(model, "parameters", None)
    if not isinstance(params, TwoMassParameters):
        raise TuningError(f"design() needs an Identification or TwoMassParameters, got {type(model).__name__}")
    eps = float(model.epsilon_rad if epsilon_rad is None else epsilon_rad)
    detected = bool(getattr(model, "backlash_detected", True))
    return _Model(params, eps, detected and eps > math.radians(options.backlash_threshold_deg))


def _check_params(p: TwoMassParameters) -> None:
    arr = p.as_array()
    if not np.all(np.isfinite(arr)) or p.J_m <= 0 or p.J_l <= 0 or p.K <= 0 or min(p.B_m, p.B_l, p.D) < 0:
        raise TuningError(f"the two-mass model is not physical: {p}")


@dataclass
class _Loop:
    """Everything the search needs for one plant, evaluated once."""

    Ts: float
    w: NDArray[np.float64]
    contact: tuple[Poly, Poly, NDArray[np.complex128]]
    gap: tuple[Poly, Poly, NDArray[np.complex128]] | None
    motor_alone: NDArray[np.complex128]
    """Response of the motor alone (the two-mass model's high-frequency asymptote)."""


def _loop_plants(p: TwoMassParameters, with_gap: bool, options: TuningOptions) -> _Loop:
    Ts = 1.0 / options.sample_rate_hz
    w = _freq_grid(options.sample_rate_hz)
    num, den = p.velocity_tf()
    pn, pd = _plant_z(num, den, Ts, options.current_loop_bandwidth_hz, options.computation_delay_samples)
    contact = (pn, pd, _eval(pn, pd, w, Ts))
    gn, gd = _plant_z(np.array([1.0 / p.J_m]), np.array([1.0, p.B_m / p.J_m]), Ts,
                      options.current_loop_bandwidth_hz, options.computation_delay_samples)
    alone = _eval(gn, gd, w, Ts)
    return _Loop(Ts, w, contact, (gn, gd, alone) if with_gap else None, alone)


def _evaluate(loop: _Loop, kp: float, Ti: float, tf_s: float, notches: tuple[Notch, ...]
              ) -> tuple[LoopMargins, LoopMargins | None, float]:
    cn, cd = _controller_z(kp, Ti, tf_s, notches, loop.Ts)
    C = _eval(cn, cd, loop.w, loop.Ts)
    pn, pd, P = loop.contact
    L = C * P
    m = _grid_margins(L, loop.w, _polymul(cn, pn), _polymul(cd, pd))
    bw = _bandwidth_hz(L, loop.w)
    mg = None
    if loop.gap is not None:
        gn, gd, G = loop.gap
        mg = _grid_margins(C * G, loop.w, _polymul(cn, gn), _polymul(cd, gd))
    return m, mg, bw


def _gains(kv_hz: float, J: float, J_m: float, filter_ratio: float, options: TuningOptions) -> tuple[float, float, float]:
    """(k_p, T_i, T_f) of a rigid-body gain K_v."""
    wv = 2.0 * math.pi * kv_hz
    kp = J * wv
    Ti = options.ratio("integral") / wv
    f_hf = kp / (2.0 * math.pi * J_m)  # crossover on the motor inertia alone
    f_filter = min(filter_ratio * f_hf, options.max_torque_filter_fraction * options.sample_rate_hz)
    return kp, Ti, 1.0 / (2.0 * math.pi * f_filter)


def _notch_for(p: TwoMassParameters, options: TuningOptions) -> Notch:
    m = modes(p)
    zn = options.notch_damping
    depth = min(1.0, max(0.0, m.zeta_resonance / zn))
    return Notch(frequency_hz=float(m.f_resonance_hz), q=1.0 / (2.0 * zn), depth=float(depth))


def _search(loop: _Loop, p: TwoMassParameters, notches: tuple[Notch, ...], filter_ratio: float,
            options: TuningOptions) -> tuple[float, float] | None:
    """Highest feasible K_v [Hz] and its bandwidth; None if none is feasible."""
    pm_req, gm_req = options.requirements()
    pm_d, gm_d = pm_req + options.design_guard_deg, gm_req + options.design_guard_db
    J = p.J_m + p.J_l

    def feasible(kv: float) -> bool:
        kp, Ti, tf_s = _gains(kv, J, p.J_m, filter_ratio, options)
        cn, cd = _controller_z(kp, Ti, tf_s, notches, loop.Ts)
        C = _eval(cn, cd, loop.w, loop.Ts)
        pn, pd, P = loop.contact
        if not _grid_meets(C * P, loop.w, _polymul(cn, pn), _polymul(cd, pd), pm_d, gm_d):
            return False
        if loop.gap is None:
            return True
        gn, gd, G = loop.gap
        return _grid_meets(C * G, loop.w, _polymul(cn, gn), _polymul(cd, gd), pm_req, gm_req)

    grid = np.geomspace(0.5, options.sample_rate_hz / 8.0, 48)
    # the highest feasible grid point: scanned from the top, the first one found
    i = next((j for j in range(grid.size - 1, -1, -1) if feasible(float(grid[j]))), None)
    if i is None:
        return None
    last_ok = float(grid[i])
    if i + 1 < grid.size:
        lo, hi = last_ok, float(grid[i + 1])
        for _ in range(10):
            mid = math.sqrt(lo * hi)
            if feasible(mid):
                lo = mid
            else:
                hi = mid
        last_ok = lo
    kp, Ti, tf_s = _gains(last_ok, J, p.J_m, filter_ratio, options)
    return last_ok, _evaluate(loop, kp, Ti, tf_s, notches)[2]


def _peaks(loop: _Loop, p: TwoMassParameters, notches: tuple[Notch, ...], best: tuple[float, float, float],
           f_r: float, options: TuningOptions) -> tuple[float, float]:
    """(resonance peak, load peak) [dB] of a candidate: the largest excess of |v_m/v*| over the same loop
    around the motor alone within 0.7–1.4·f_r, and the peak of |v_l/v*|."""
    kv, _, ratio = best
    kp, Ti, tf_s = _gains(kv, p.J_m + p.J_l, p.J_m, ratio, options)
    cn, cd = _controller_z(kp, Ti, tf_s, notches, loop.Ts)
    L = _eval(cn, cd, loop.w, loop.Ts) * loop.contact[2]
    T = L / (1.0 + L)
    La = _eval(cn, cd, loop.w, loop.Ts) * loop.motor_alone
    Ta = La / (1.0 + La)
    f = loop.w / (2.0 * math.pi)
    band = (f >= 0.7 * f_r) & (f <= 1.4 * f_r)
    s = 1j * loop.w
    Tl = T * (p.D * s + p.K) / (p.J_l * s * s + (p.D + p.B_l) * s + p.K)
    excess = 20.0 * np.log10(np.abs(T[band]) / np.abs(Ta[band]))
    return float(np.max(excess)), float(20.0 * np.log10(np.max(np.abs(Tl))))


def design(model: Any, options: TuningOptions | None = None, *, epsilon_rad: float | None = None) -> ControllerSettings:
    """Controller settings from an :class:`~commission.ident.hybrid.Identification` (or
    :class:`TwoMassParameters` and ``epsilon_rad``), by the rule of the module docstring.

    A current-loop lag the identification kept is designed for when
    ``options.current_loop_bandwidth_hz`` is not set (a value entered there wins).

    :raises TuningError: the model is not physical, or no gain meets the margins.
    """
    opt = options or TuningOptions()
    mdl = _as_model(model, epsilon_rad, opt)
    p = mdl.params
    _check_params(p)
    md = modes(p)
    first_notes: list[str] = []
    identified_cl = (getattr(model, "current_loop", None) or {}).get("bandwidth_hz")
    if opt.current_loop_bandwidth_hz is None and identified_cl:
        opt = opt.model_copy(update={"current_loop_bandwidth_hz": float(identified_cl)})
        first_notes.append(f"current-loop bandwidth {float(identified_cl):.0f} Hz from the identification "
                           "(tuning.current_loop_bandwidth_hz not set)")
    loop = _loop_plants(p, mdl.backlash, opt)
    notch_options: list[tuple[Notch, ...]] = []
    if opt.notch in ("auto", "off"):
        notch_options.append(())
    if opt.notch in ("auto", "on"):
        notch_options.append((_notch_for(p, opt),))
    candidates: list[dict[str, Any]] = []
    best: dict[tuple[Notch, ...], tuple[float, float, float]] = {}
    for notches in notch_options:
        for ratio in opt.torque_filter_ratios:
            found = _search(loop, p, notches, ratio, opt)
            if found is None:
                candidates.append({"notch": bool(notches), "filter_ratio": ratio, "kv_hz": None, "bandwidth_hz": None})
                continue
            kv, bw = found
            candidates.append({"notch": bool(notches), "filter_ratio": ratio, "kv_hz": kv, "bandwidth_hz": bw})
            if notches not in best or kv > best[notches][0]:
                best[notches] = (kv, bw, ratio)
    if not best:
        pm_req, gm_req = opt.requirements()
        raise TuningError(f"no velocity-loop gain meets PM ≥ {pm_req:g}° and GM ≥ {gm_req:g} dB on the identified "
                          f"model (resonance {md.f_resonance_hz:.1f} Hz, J_l/J_m {p.J_l / p.J_m:.2f})")
    notes: list[str] = first_notes
    chosen: tuple[Notch, ...] = ()
    if opt.notch == "on" or () not in best:
        chosen = next(k for k in best if k)
    elif opt.notch == "auto":
        with_notch = [k for k in best if k]
        if with_notch:
            k_n = with_notch[0]
            pk_nn, lp_nn = _peaks(loop, p, (), best[()], md.f_resonance_hz, opt)
            pk_n, lp_n = _peaks(loop, p, k_n, best[k_n], md.f_resonance_hz, opt)
            shows = pk_nn > opt.notch_peak_db and pk_n < pk_nn
            faster = best[k_n][0] > (1.0 + opt.notch_min_gain) * best[()][0] and lp_n <= lp_nn + 0.5
            if shows or faster:
                chosen = k_n
                why = (f"the resonance shows as a {pk_nn:.1f} dB peak in the velocity loop without it ({pk_n:.1f} dB with)"
                       if shows else f"velocity-loop gain {best[()][0]:.1f} → {best[k_n][0]:.1f} Hz")
                notes.append(f"notch at {k_n[0].frequency_hz:.1f} Hz: {why}")
            else:
                notes.append(f"no notch: the resonance ({md.f_resonance_hz:.1f} Hz) lies inside the velocity loop, "
                             f"which damps it (peak {pk_nn:.1f} dB near it; a notch would give "
                             f"K_v {best[k_n][0]:.1f} instead of {best[()][0]:.1f} Hz and a load-side peak "
                             f"{lp_n:.1f} instead of {lp_nn:.1f} dB)")
    kv, _, ratio = best[chosen]
    kp, Ti, tf_s = _gains(kv, p.J_m + p.J_l, p.J_m, ratio, opt)
    m_grid, mg_grid, bw = _evaluate(loop, kp, Ti, tf_s, chosen)
    wa = 2.0 * math.pi * md.f_antiresonance_hz
    kpos = min(2.0 * math.pi * bw / opt.ratio("position"), opt.ratio("antiresonance") * wa)
    if kpos < 2.0 * math.pi * bw / opt.ratio("position"):
        notes.append(f"position gain limited by the anti-resonance ({md.f_antiresonance_hz:.1f} Hz)")
    amount = 2.0 * mdl.epsilon_rad if (mdl.backlash and opt.backlash_compensation) else 0.0
    ratio_unexplained = _residual_ratio(model)
    # a residual the identification found to be white, stationary noise is no sign of a wrong ε
    noise_limited = bool(getattr(getattr(model, "fit", None), "noise_limited", False))
    if (amount > 0.0 and ratio_unexplained is not None and ratio_unexplained > opt.backlash_max_residual_ratio
            and noise_limited):
        notes.append(f"backlash compensation kept although the identified model leaves {100 * ratio_unexplained:.2f} % "
                     f"of the torque unexplained (> {100 * opt.backlash_max_residual_ratio:g} %): the identification "
                     "found that residual to be the record's white torque noise")
    elif amount > 0.0 and ratio_unexplained is not None and ratio_unexplained > opt.backlash_max_residual_ratio:
        amount = 0.0
        notes.append(f"backlash compensation off: the identified model leaves {100 * ratio_unexplained:.2f} % of the "
                     f"torque unexplained (> {100 * opt.backlash_max_residual_ratio:g} %), so its ε is not trusted; "
                     "a wrong amount can double the load error")
    elif amount > 0.0 and _approximate(model):
        amount = 0.0
        notes.append("backlash compensation off: the identification is approximate (see its notes), so its ε "
                     "is not trusted; a wrong amount can double the load error")
    tau_b = opt.backlash_time_constant_s if opt.backlash_time_constant_s is not None else 1.0 / kpos
    tau_r, filter_note = 0.0, ""
    if amount > 0.0 and opt.backlash_approach_filter:
        tau_r, filter_note = approach_time_constant(p, kpos, opt)
    pm_req, gm_req = opt.requirements()
    settings = ControllerSettings(
        sample_rate_hz=opt.sample_rate_hz, motor_inertia_kg_m2=p.J_m, load_inertia_kg_m2=p.J_l,
        velocity_gain=kp, velocity_integral_time_s=Ti, velocity_bandwidth_hz=bw, position_gain_per_s=kpos,
        torque_filter_time_constant_s=tf_s, notches=chosen, velocity_feedforward=opt.ratio("vff"),
        torque_feedforward=opt.ratio("tff"),
        backlash=BacklashCompensation(amount_rad=amount, time_constant_s=tau_b),
        margins=m_grid, margins_gap=mg_grid, required_phase_margin_deg=pm_req, required_gain_margin_db=gm_req,
        preset=opt.preset, current_loop_bandwidth_hz=opt.current_loop_bandwidth_hz,
        computation_delay_samples=opt.computation_delay_samples, epsilon_rad=mdl.epsilon_rad,
        reference_filter_time_constant_s=tau_r, resonance_hz=md.f_resonance_hz, antiresonance_hz=md.f_antiresonance_hz,
        candidates=tuple(candidates), notes=tuple(notes),
    )
    if settings.backlash.enabled:
        model_plant = plant_from_model(model, mdl.epsilon_rad, opt.current_loop_bandwidth_hz)
        settings = choose_backlash_direction(settings, model_plant, opt)
        if settings.backlash.enabled and filter_note:
            settings = replace(settings, notes=settings.notes + (filter_note,))
    # the reported margins: every crossing located exactly on the same loop
    m_ct = loop_margins(settings, p, gap=False)
    mg_ct = loop_margins(settings, p, gap=True) if mdl.backlash else None
    return replace(settings, margins=m_ct, margins_gap=mg_ct,
                   position_margins=loop_margins(settings, p, loop="position"))


def _residual_ratio(model: Any) -> float | None:
    """RMS residual / RMS torque of a hybrid identification (None when unknown)."""
    quality = getattr(model, "fit", None)
    return None if quality is None else float(quality.residual_ratio)


def _approximate(model: Any) -> bool:
    """Whether a hybrid identification said its result is approximate (False when unknown)."""
    return bool(getattr(getattr(model, "fit", None), "approximate", False))


def approach_time_constant(p: TwoMassParameters, kpos: float, opt: TuningOptions) -> tuple[float, str]:
    """Time constant of the position-reference filter that lets the backlash compensation work [s],
    and a note saying why.

    After a move the compensation holds the motor ε ahead of the load's target: exact only if
    the load rests on the driving flank. It does when the motor never decelerates faster than the
    load does by itself; at the end of a first-order approach the deceleration is v/τ_r, the
    load's own (viscous) v·B_l/J_l, so τ_r ≥ J_l/B_l keeps the flank in contact. A step of the
    reference (velocity jump) makes the motor hit the load across the gap, and the load leaves with
    up to 2·J_m/(J_m + J_l) < 2 times the motor's speed (elastic impact): with τ_r ≥ 2·J_l/B_l
    (``backlash_approach_factor``, default 2) the motor still travels further than the load
    coasts, and they meet again on the driving flank (measured over bench_tuning's plants:
    factor 1.5 leaves the load up to 20 mrad off after a step, 2 within 0.2 mrad). Without
    it a load without friction stops anywhere in the gap, and where depends on the move (the
    compensation then helps on some moves and doubles the error on others). Load-side Coulomb
    friction only helps (the bound is conservative then). Never shorter than 2/K_p (the
    position loop's own lag); at most ``backlash_approach_max_s``.
    """
    decay = p.J_l / p.B_l if p.B_l > 0 else math.inf
    want = opt.backlash_approach_factor * decay
    tau = min(max(want, 2.0 / kpos), opt.backlash_approach_max_s)
    why = (f"position reference filter {1e3 * tau:.1f} ms: {opt.backlash_approach_factor:g} × the load's own decay "
           f"time J_l/B_l = {1e3 * decay:.1f} ms, so moves end with the load on the driving flank and the backlash "
           f"compensation is exact (backlash_approach_filter: false for faster moves)")
    if want > opt.backlash_approach_max_s:
        why = (f"position reference filter {1e3 * tau:.1f} ms (capped by backlash_approach_max_s; the load's own decay "
               f"time J_l/B_l is {1e3 * decay:.1f} ms, so a load without friction may still leave the driving flank "
               f"at the end of a move)")
    return tau, why
