"""Controller design from the identified two-mass model and backlash.

The loop (motor-side feedback, the drive's cascade at its own clock Ts)::

    position P ─► velocity PI ─► torque low-pass ─► notch(es) ─► current loop ─► plant

Design rule (issues #6, #20): the highest velocity-loop gain whose loop keeps the preset's
phase margin ≥ PM and gain margin ≥ GM (``soft`` / ``standard`` / ``stiff``)

* on the identified model *with* the filters, the sampling (zero-order hold + backward-difference
  velocity: one sample) and the drive's own loop — current loop, computation and encoder
  delays — taken from the config, the identification, the drive description or a stated
  conservative assumption (:mod:`.dynamics`), with a guard for model error;
* on every member of the uncertainty set (:mod:`.robust`: current loop ×0.5–2, +1 sample of
  delay, J_l and K ±20 %, the gears in contact and apart);
* with its crossover inside the band the record measured with good signal (``band_factor``
  × its upper edge): above it the loop would rest on the model's extrapolation;
* within the drive's gain ranges (the description's parameter map).

Every candidate is analysed in discrete time, exactly, on the loop of :mod:`.loop` (the one
loop model the report and the verification use too). With backlash the loop has two plants:
in contact, the two-mass model; in the gap, the motor alone (1/(J_m·s + B_m)), whose gain below
the resonance is (J_m + J_l)/J_m times higher.

The search: for each torque-filter ratio and with/without a notch at the identified resonance,
a log-spaced scan of the rigid-body velocity-loop gain K_v = k_p / (2π·(J_m + J_l)) [Hz] and
a bisection at the edge; the candidate with the highest closed-loop bandwidth wins; a notch is
kept only when it raises the bandwidth by more than ``notch_min_gain`` or removes a closed-loop
peak. The search checks the members of the uncertainty set that broke an earlier round's
choice (starting from the slowest drive corner): the chosen gains are checked on all members,
and a member that fails joins the search's set for the next round. Margins for the search are
read from a dense frequency grid (crossings interpolated); the reported margins of the chosen
settings locate each crossing exactly on the same loop (:func:`.loop.loop_margins`; the tests
check them against python-control), and the worst case over the set is reported with the
member that set it (:func:`.robust.robust_margins`). The settings also say what limited the
bandwidth (:class:`~.settings.BandwidthLimit`): the band, the current loop, the delay, the
resonance, the margins in general, or the drive's gain range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from ..exceptions import IdentificationError
from ..ident.twomass import TwoMassParameters, modes
from .dynamics import resolve_dynamics
from .identified import IdentifiedModel, read_identification
from .loop import (
    SEARCH_POINTS,
    Poly,
    _bandwidth_hz,
    _controller_z,
    _eval,
    _freq_grid,
    _grid_crossings,
    _grid_margins,
    _plant_z,
    _polymul,
    _stable,
    loop_margins,
)
from .robust import MemberResponses, members, robust_margins
from .scenarios import choose_backlash_direction, plant_from_model
from .settings import (
    BacklashCompensation,
    BandwidthLimit,
    ControllerSettings,
    DriveDynamics,
    LimitingFactor,
    LoopMargins,
    Notch,
    Source,
    TuningError,
    TuningOptions,
)

__all__ = ["approach_time_constant", "design"]

#: Rounds of the search against the uncertainty set (each adds the members the last choice broke).
_MAX_ROUNDS = 4


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


def _loop_plants(p: TwoMassParameters, with_gap: bool, fs: float, current_loop_hz: float | None,
                 delay_samples: float) -> _Loop:
    Ts = 1.0 / fs
    w = _freq_grid(fs, points=SEARCH_POINTS)
    num, den = p.velocity_tf()
    pn, pd = _plant_z(num, den, Ts, current_loop_hz, delay_samples)
    contact = (pn, pd, _eval(pn, pd, w, Ts))
    gn, gd = _plant_z(np.array([1.0 / p.J_m]), np.array([1.0, p.B_m / p.J_m]), Ts, current_loop_hz, delay_samples)
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


@dataclass
class _Search:
    """The design's constraints on one model: its loops, the uncertainty set's members, the band
    limit and the drive's gain ranges."""

    loop: _Loop
    p: TwoMassParameters
    opt: TuningOptions
    fs: float
    robust: MemberResponses
    crossover_limit_hz: float | None
    limits: dict[str, tuple[float, float]]
    current_loop_hz: float | None
    """The design's nominal current loop [Hz] (None: ideal)."""
    delay_samples: float
    """The design's nominal loop delay beyond the sample [samples]."""

    @property
    def J(self) -> float:
        return self.p.J_m + self.p.J_l

    def kv_range(self) -> tuple[float, float]:
        """(lowest, highest) K_v [Hz] the search scans: the drive's range within 0.5 Hz … fs/8."""
        lo, hi = 0.5, self.fs / 8.0
        for key, scale in (("velocity_gain_hz", 1.0), ("velocity_gain", 1.0 / (2.0 * math.pi * self.J))):
            if key in self.limits:
                a, b = self.limits[key]
                lo, hi = max(lo, a * scale), min(hi, b * scale)
        return lo, hi

    def gains(self, kv_hz: float, filter_ratio: float) -> tuple[float, float, float]:
        """(k_p, T_i, T_f) of a rigid-body gain K_v (T_i within the drive's range)."""
        wv = 2.0 * math.pi * kv_hz
        kp = self.J * wv
        Ti = self.opt.ratio("integral") / wv
        if "velocity_integral_time_s" in self.limits:
            a, b = self.limits["velocity_integral_time_s"]
            Ti = min(max(Ti, a), b)
        f_hf = kp / (2.0 * math.pi * self.p.J_m)  # crossover on the motor inertia alone
        f_filter = min(filter_ratio * f_hf, self.opt.max_torque_filter_fraction * self.fs)
        return kp, Ti, 1.0 / (2.0 * math.pi * f_filter)

    def failures(self, kv: float, ratio: float, notches: tuple[Notch, ...], active: list[int] | None,
                 first_only: bool = True) -> list[tuple[str, int | None]]:
        """The constraints K_v breaks: ("band" | "nominal" | "gap" | "member", member index).
        ``first_only``: stop at the first (margins before the costlier closed-loop poles)."""
        opt = self.opt
        pm_req, gm_req = opt.requirements()
        kp, Ti, tf_s = self.gains(kv, ratio)
        cn, cd = _controller_z(kp, Ti, tf_s, notches, self.loop.Ts)
        C = _eval(cn, cd, self.loop.w, self.loop.Ts)
        pn, pd, P = self.loop.contact
        pm, gm, wc, _ = _grid_crossings(C * P, self.loop.w)
        out: list[tuple[str, int | None]] = []
        if self.crossover_limit_hz is not None and wc / (2.0 * math.pi) > self.crossover_limit_hz:
            out.append(("band", None))
            if first_only:
                return out
        nominal_ok = pm >= pm_req + opt.design_guard_deg and gm >= gm_req + opt.design_guard_db
        if not nominal_ok:
            out.append(("nominal", None))
            if first_only:
                return out
        gap_ok = True
        if self.loop.gap is not None:
            gn, gd, G = self.loop.gap
            pg, gg, _, _ = _grid_crossings(C * G, self.loop.w)
            gap_ok = pg >= pm_req and gg >= gm_req
            if not gap_ok:
                out.append(("gap", None))
                if first_only:
                    return out
        pm_r, gm_r = pm_req + opt.robust_guard_deg, gm_req + opt.robust_guard_db
        if first_only:
            i = self.robust.first_failure(C, cn, cd, pm_r, gm_r, active)
            if i is not None:
                return [("member", i)]
        else:
            out += [("member", i) for i in self.robust.failures(C, cn, cd, pm_r, gm_r)]
        if nominal_ok and not _stable(_polymul(cn, pn), _polymul(cd, pd)):
            out.append(("nominal", None))
        if gap_ok and self.loop.gap is not None and not _stable(_polymul(cn, self.loop.gap[0]),
                                                                _polymul(cd, self.loop.gap[1])):
            out.append(("gap", None))
        return out

    def search(self, notches: tuple[Notch, ...], filter_ratio: float, active: list[int],
               upper: tuple[float, float] | None = None) -> tuple[float, float, float] | None:
        """(highest feasible K_v [Hz], its bandwidth [Hz], the lowest infeasible K_v above it);
        None if none is feasible. ``upper``: an earlier round's (K_v, lowest infeasible K_v above
        it): the set of members only grows, so the gain can only fall."""
        lo_hz, hi_hz = self.kv_range()
        if upper is not None:
            hi_hz = min(hi_hz, upper[0])
        if hi_hz < lo_hz:
            return None

        def feasible(kv: float) -> bool:
            return not self.failures(kv, filter_ratio, notches, active)

        grid = np.geomspace(lo_hz, hi_hz, 48) if hi_hz > lo_hz else np.array([hi_hz])
        # the highest feasible grid point: scanned from the top, the first one found
        i = next((j for j in range(grid.size - 1, -1, -1) if feasible(float(grid[j]))), None)
        if i is None:
            return None
        last_ok = float(grid[i])
        first_bad = upper[1] if upper is not None else math.inf
        if i + 1 < grid.size:
            lo, hi = last_ok, float(grid[i + 1])
            for _ in range(10):
                mid = math.sqrt(lo * hi)
                if feasible(mid):
                    lo = mid
                else:
                    hi = mid
            last_ok, first_bad = lo, hi
        kp, Ti, tf_s = self.gains(last_ok, filter_ratio)
        return last_ok, _evaluate(self.loop, kp, Ti, tf_s, notches)[2], first_bad


def _notch_for(p: TwoMassParameters, options: TuningOptions) -> Notch:
    m = modes(p)
    zn = options.notch_damping
    depth = min(1.0, max(0.0, m.zeta_resonance / zn))
    return Notch(frequency_hz=float(m.f_resonance_hz), q=1.0 / (2.0 * zn), depth=float(depth))


def _peaks(srch: _Search, notches: tuple[Notch, ...], best: tuple[float, float, float, float],
           f_r: float) -> tuple[float, float]:
    """(resonance peak, load peak) [dB] of a candidate: the largest excess of |v_m/v*| over the same loop
    around the motor alone within 0.7–1.4·f_r, and the peak of |v_l/v*|."""
    loop, p = srch.loop, srch.p
    kv, _, ratio, _ = best
    kp, Ti, tf_s = srch.gains(kv, ratio)
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


#: (K_v, bandwidth, filter ratio, lowest infeasible K_v above) per notch choice
_Best = dict[tuple[Notch, ...], tuple[float, float, float, float]]


#: an earlier round's (K_v, lowest infeasible K_v above it) per (notch choice, filter ratio)
_Upper = dict[tuple[tuple[Notch, ...], float], tuple[float, float]]


def _choose(srch: _Search, notch_options: list[tuple[Notch, ...]], active: list[int],
            upper: _Upper) -> tuple[_Best, list[dict[str, Any]]]:
    candidates: list[dict[str, Any]] = []
    best: _Best = {}
    for notches in notch_options:
        for ratio in srch.opt.torque_filter_ratios:
            found = srch.search(notches, ratio, active, upper.get((notches, ratio)))
            if found is None:
                candidates.append({"notch": bool(notches), "filter_ratio": ratio, "kv_hz": None, "bandwidth_hz": None})
                upper[(notches, ratio)] = (0.0, 0.0)
                continue
            kv, bw, bad = found
            upper[(notches, ratio)] = (kv * (1.0 + 1e-9), bad)
            candidates.append({"notch": bool(notches), "filter_ratio": ratio, "kv_hz": kv, "bandwidth_hz": bw})
            if notches not in best or _better(srch, (kv, ratio), best[notches], notches):
                best[notches] = (kv, bw, ratio, bad)
    return best, candidates


#: Candidates whose gains lie within this fraction of each other count as equal (a band or a
#: gain range stops them all at about the same gain): the one with more phase margin wins.
_TIE = 0.02


def _better(srch: _Search, new: tuple[float, float], old: tuple[float, float, float, float],
            notches: tuple[Notch, ...]) -> bool:
    """Whether candidate ``new`` (K_v, filter ratio) beats ``old``: a higher gain, or about the
    same gain with more phase margin on the design model (less lag in its filter)."""
    kv, ratio = new
    if kv > (1.0 + _TIE) * old[0]:
        return True
    if kv < (1.0 - _TIE) * old[0]:
        return False

    def pm(k: float, r: float) -> float:
        kp, Ti, tf_s = srch.gains(k, r)
        return _evaluate(srch.loop, kp, Ti, tf_s, notches)[0].phase_margin_deg

    return pm(kv, ratio) > pm(old[0], old[2])


def _pick_notch(srch: _Search, best: _Best, f_r: float, notes: list[str]) -> tuple[Notch, ...]:
    opt = srch.opt
    if opt.notch == "on" or () not in best:
        return next(k for k in best if k)
    with_notch = [k for k in best if k]
    if opt.notch != "auto" or not with_notch:
        return ()
    k_n = with_notch[0]
    pk_nn, lp_nn = _peaks(srch, (), best[()], f_r)
    pk_n, lp_n = _peaks(srch, k_n, best[k_n], f_r)
    shows = pk_nn > opt.notch_peak_db and pk_n < pk_nn
    faster = best[k_n][0] > (1.0 + opt.notch_min_gain) * best[()][0] and lp_n <= lp_nn + 0.5
    if shows or faster:
        why = (f"the resonance shows as a {pk_nn:.1f} dB peak in the velocity loop without it ({pk_n:.1f} dB with)"
               if shows else f"velocity-loop gain {best[()][0]:.1f} → {best[k_n][0]:.1f} Hz")
        notes.append(f"notch at {k_n[0].frequency_hz:.1f} Hz: {why}")
        return k_n
    notes.append(f"no notch: the resonance ({f_r:.1f} Hz) lies inside the velocity loop, "
                 f"which damps it (peak {pk_nn:.1f} dB near it; a notch would give "
                 f"K_v {best[k_n][0]:.1f} instead of {best[()][0]:.1f} Hz and a load-side peak "
                 f"{lp_n:.1f} instead of {lp_nn:.1f} dB)")
    return ()


def _phase_budget(f_hz: float, Ts: float, current_loop_hz: float | None, delay_samples: float) -> tuple[float, float]:
    """(phase lag of the loop's delay — the sample's own plus ``delay_samples`` —, of the current
    loop) at f_hz [deg]."""
    delay = 360.0 * f_hz * Ts * (1.0 + delay_samples)
    cl = 0.0 if current_loop_hz is None else math.degrees(math.atan(f_hz / current_loop_hz))
    return delay, cl


def _cause(srch: _Search, kv: float, ratio: float, notches: tuple[Notch, ...], which: str, index: int | None,
           f_r: float, f_a: float) -> tuple[LimitingFactor, str]:
    """Why the margins fail just above the chosen gain, on the nominal model, the gap or a member:
    a crossing near the resonance, else the larger phase cost at the crossing (delay or
    current loop), else the margins in general."""
    loop = srch.loop
    cl_hz, delay = srch.current_loop_hz, srch.delay_samples
    kp, Ti, tf_s = srch.gains(kv, ratio)
    cn, cd = _controller_z(kp, Ti, tf_s, notches, loop.Ts)
    C = _eval(cn, cd, loop.w, loop.Ts)
    where = {"nominal": "the design model", "gap": "the design model with the gears apart"}.get(which, "")
    if which == "member" and index is not None:
        r = srch.robust.items[index]
        P = r.P
        m = r.member
        cl_hz = None if cl_hz is None else cl_hz * m.current_loop_factor
        delay += m.extra_delay_samples
        where = f"the worst member of the uncertainty set ({m.describe(srch.current_loop_hz)})"
    elif which == "gap" and loop.gap is not None:
        P = loop.gap[2]
    else:
        P = loop.contact[2]
    pm_req, gm_req = srch.opt.requirements()
    pm, gm, wc, wp = _grid_crossings(C * P, loop.w)
    if pm - pm_req <= gm - gm_req or not math.isfinite(wp):
        f, what = wc / (2.0 * math.pi), f"phase margin {pm:.1f}° at the {wc / (2.0 * math.pi):.0f} Hz crossover"
    else:
        f, what = wp / (2.0 * math.pi), f"gain margin {gm:.1f} dB at {wp / (2.0 * math.pi):.0f} Hz"
    if not math.isfinite(f):
        return LimitingFactor.MARGINS, f"the margins on {where}"
    near = [x for x in (f_r, f_a) if math.isfinite(x) and 0.7 * x <= f <= 1.4 * x]
    if near:
        return LimitingFactor.RESONANCE, (f"{what} on {where}, near the "
                                          f"{'resonance' if near[0] == f_r else 'anti-resonance'} ({near[0]:.0f} Hz)")
    d_lag, cl_lag = _phase_budget(f, loop.Ts, cl_hz, delay)
    budget = (f"there the delay ({_samples(1.0 + delay)} with the sample's own) costs {d_lag:.0f}° of phase"
              + ("" if cl_hz is None else f", the current loop ({cl_hz:.0f} Hz) {cl_lag:.0f}°"))
    if max(d_lag, cl_lag) < 10.0:
        return LimitingFactor.MARGINS, f"{what} on {where}; {budget}"
    factor = LimitingFactor.DELAY if d_lag >= cl_lag else LimitingFactor.CURRENT_LOOP
    return factor, f"{what} on {where}; {budget}"


def _limit(srch: _Search, best: tuple[float, float, float, float], notches: tuple[Notch, ...],
           f_r: float, f_a: float) -> BandwidthLimit:
    """What stopped the gain at ``best``: the constraints the next (infeasible) gain breaks."""
    kv, _, ratio, bad = best
    hi_hz = srch.kv_range()[1]
    if not math.isfinite(bad):
        if hi_hz < srch.fs / 8.0 * (1.0 - 1e-9):
            return BandwidthLimit(LimitingFactor.GAIN_RANGE, f"K_v {kv:.1f} Hz: the top of the drive's range "
                                  f"({hi_hz:.1f} Hz, from its parameter map)")
        return BandwidthLimit(LimitingFactor.SEARCH_RANGE, f"K_v {kv:.1f} Hz: the design's highest gain (fs/8)")
    broken = [(w, i, bad) for w, i in srch.failures(bad, ratio, notches, None, first_only=False)]
    if not broken:
        return BandwidthLimit(LimitingFactor.MARGINS, "the margins (the search's edge)")
    # constraints that bind a little higher up count too (a band and a margin often meet)
    above = bad * (1.0 + _TIE)
    broken += [(w, i, above) for w, i in srch.failures(above, ratio, notches, None, first_only=False)
               if w not in {b[0] for b in broken}]
    factors: list[tuple[LimitingFactor, str]] = []
    members_seen = False
    for which, idx, at in broken:
        if which == "band":
            factors.append((LimitingFactor.BAND, f"crossover at the band's limit {srch.crossover_limit_hz:.0f} Hz "
                            f"({srch.opt.band_factor:g} × the measured band's upper edge): above it the loop would "
                            "rest on the model's extrapolation (a high-band sweep in the experiment would allow more)"))
        elif which != "member" or not members_seen:  # the worst member stands for the set
            members_seen = members_seen or which == "member"
            factors.append(_cause(srch, at, ratio, notches, which, idx, f_r, f_a))
    first = factors[0]
    others = tuple(dict.fromkeys(f for f, _ in factors[1:] if f is not first[0]))
    return BandwidthLimit(first[0], first[1], others)


def design(model: Any, options: TuningOptions | None = None, *, epsilon_rad: float | None = None,
           description: Any | None = None, excitation_band_hz: tuple[float, float] | None = None
           ) -> ControllerSettings:
    """Controller settings from an :class:`~commission.ident.hybrid.Identification` (or
    :class:`TwoMassParameters` and ``epsilon_rad``), by the rule of the module docstring.

    :param description: the drive's description (its ``loop:`` block and parameter map), if known.
    :param excitation_band_hz: the band the experiment swept: the measured band when the
        identification states none.
    :raises TuningError: the model is not physical, or no gain meets the margins.
    """
    opt = options or TuningOptions()
    with threadpool_limits(1):  # small matrices: BLAS threads only cost (milliseconds per call)
        return _design(read_identification(model, epsilon_rad=epsilon_rad, excitation_band_hz=excitation_band_hz),
                       opt, description)


def _samples(x: float) -> str:
    return f"{x:g} sample" + ("" if x == 1 else "s")


def _dynamics_notes(dyn: DriveDynamics) -> list[str]:
    """One note per figure of the drive's loop: its value and where it comes from."""
    def say(name: str, text: str, sv: Any) -> str:
        return f"{name} {text}: {sv.how.value} ({sv.source})" + (" — confirm" if sv.confirm else "")

    cl = dyn.current_loop_bandwidth_hz
    out = [say("current loop", "ideal" if cl.value is None else f"{cl.value:.0f} Hz", cl),
           say("computation delay", _samples(float(dyn.computation_delay_samples.value or 0.0)),
               dyn.computation_delay_samples),
           say("encoder delay", _samples(float(dyn.encoder_delay_samples.value or 0.0)), dyn.encoder_delay_samples)]
    if dyn.sample_rate_hz.how is not Source.ASSUMED:
        out.append(say("velocity loop clock", f"{dyn.sample_rate_hz.value:g} Hz", dyn.sample_rate_hz))
    return out


def _design(facts: IdentifiedModel, opt: TuningOptions, description: Any | None) -> ControllerSettings:
    p = facts.parameters
    _check_params(p)
    try:
        md = modes(p)
    except IdentificationError as err:  # the identification says so too (approximate); nothing to design for
        raise IdentificationError(f"the identified model has no resonance to design against ({err}); "
                                  "the identification's result.json is written") from err
    backlash = facts.backlash_detected and facts.epsilon_rad > math.radians(opt.backlash_threshold_deg)
    dyn = resolve_dynamics(facts, opt, description)
    fs = float(dyn.sample_rate_hz.value or opt.sample_rate_hz)
    cl_hz = dyn.current_loop_bandwidth_hz.value
    delay = dyn.loop_delay_samples
    loop = _loop_plants(p, backlash, fs, cl_hz, delay)
    robust = MemberResponses(p, members(opt.uncertainty, backlash, cl_hz is None), cl_hz, delay, 1.0 / fs, loop.w)
    band = facts.measured_band_hz
    limit_hz = None if (band is None or opt.band_factor is None) else opt.band_factor * band[1]
    srch = _Search(loop, p, opt, fs, robust, limit_hz, dyn.gain_limits, cl_hz, delay)
    notch_options: list[tuple[Notch, ...]] = []
    if opt.notch in ("auto", "off"):
        notch_options.append(())
    if opt.notch in ("auto", "on"):
        notch_options.append((_notch_for(p, opt),))
    # the search against the members that broke an earlier choice, from the slowest drive corner
    active = [0] + next(([i] for i, r in enumerate(robust.items) if r.member.gap), [])
    upper: _Upper = {}
    notes: list[str] = _dynamics_notes(dyn)
    for _ in range(_MAX_ROUNDS):
        best, candidates = _choose(srch, notch_options, active, upper)
        if not best:
            pm_req, gm_req = opt.requirements()
            raise TuningError(f"no velocity-loop gain meets PM ≥ {pm_req:g}° and GM ≥ {gm_req:g} dB on the "
                              f"identified model and over the uncertainty set (resonance {md.f_resonance_hz:.1f} Hz, J_l/J_m "
                              f"{p.J_l / p.J_m:.2f}, current loop {'ideal' if cl_hz is None else f'{cl_hz:.0f} Hz'}, "
                              f"delay {delay:g} samples)")
        round_notes: list[str] = []
        chosen = _pick_notch(srch, best, md.f_resonance_hz, round_notes)
        kv, _, ratio, _ = best[chosen]
        broken = [i for w, i in srch.failures(kv, ratio, chosen, None, first_only=False) if w == "member"]
        new = [i for i in broken if i is not None and i not in active]
        if not new:
            break
        active += new
    notes += round_notes
    kv, _, ratio, _ = best[chosen]
    kp, Ti, tf_s = srch.gains(kv, ratio)
    m_grid, mg_grid, bw = _evaluate(loop, kp, Ti, tf_s, chosen)
    limit = _limit(srch, best[chosen], chosen, md.f_resonance_hz, md.f_antiresonance_hz)
    notes.append(f"bandwidth limited by the {limit.factor.value}: {limit.detail}"
                 + (f" (also binding: {', '.join(f.value for f in limit.others)})" if limit.others else ""))
    wa = 2.0 * math.pi * md.f_antiresonance_hz
    kpos = min(2.0 * math.pi * bw / opt.ratio("position"), opt.ratio("antiresonance") * wa)
    if kpos < 2.0 * math.pi * bw / opt.ratio("position"):
        notes.append(f"position gain limited by the anti-resonance ({md.f_antiresonance_hz:.1f} Hz)")
    if "position_gain_per_s" in dyn.gain_limits:
        a, b = dyn.gain_limits["position_gain_per_s"]
        if not a <= kpos <= b:
            kpos = min(max(kpos, a), b)
            notes.append(f"position gain {kpos:.1f} 1/s: the drive's range ({a:g}–{b:g} 1/s)")
    amount = 2.0 * facts.epsilon_rad if (backlash and opt.backlash_compensation) else 0.0
    fit = facts.fit
    ratio_unexplained = fit.residual_ratio
    if (amount > 0.0 and ratio_unexplained is not None and ratio_unexplained > opt.backlash_max_residual_ratio
            and fit.noise_limited):
        # a residual the identification found to be white, stationary noise is no sign of a wrong ε
        notes.append(f"backlash compensation kept although the identified model leaves {100 * ratio_unexplained:.2f} % "
                     f"of the torque unexplained (> {100 * opt.backlash_max_residual_ratio:g} %): the identification "
                     "found that residual to be the record's white torque noise")
    elif amount > 0.0 and ratio_unexplained is not None and ratio_unexplained > opt.backlash_max_residual_ratio:
        amount = 0.0
        notes.append(f"backlash compensation off: the identified model leaves {100 * ratio_unexplained:.2f} % of the "
                     f"torque unexplained (> {100 * opt.backlash_max_residual_ratio:g} %), so its ε is not trusted; "
                     "a wrong amount can double the load error")
    elif amount > 0.0 and fit.approximate:
        amount = 0.0
        notes.append("backlash compensation off: the identification is approximate (see its notes), so its ε "
                     "is not trusted; a wrong amount can double the load error")
    tau_b = opt.backlash_time_constant_s if opt.backlash_time_constant_s is not None else 1.0 / kpos
    tau_r, filter_note = 0.0, ""
    if amount > 0.0 and opt.backlash_approach_filter:
        tau_r, filter_note = approach_time_constant(p, kpos, opt)
    pm_req, gm_req = opt.requirements()
    settings = ControllerSettings(
        sample_rate_hz=fs, motor_inertia_kg_m2=p.J_m, load_inertia_kg_m2=p.J_l,
        velocity_gain=kp, velocity_integral_time_s=Ti, velocity_bandwidth_hz=bw, position_gain_per_s=kpos,
        torque_filter_time_constant_s=tf_s, notches=chosen, velocity_feedforward=opt.ratio("vff"),
        torque_feedforward=opt.ratio("tff"),
        backlash=BacklashCompensation(amount_rad=amount, time_constant_s=tau_b),
        margins=m_grid, margins_gap=mg_grid, required_phase_margin_deg=pm_req, required_gain_margin_db=gm_req,
        preset=opt.preset, current_loop_bandwidth_hz=cl_hz, loop_delay_samples=delay,
        position_loop_delay_samples=dyn.position_loop_delay_samples, epsilon_rad=facts.epsilon_rad,
        reference_filter_time_constant_s=tau_r, resonance_hz=md.f_resonance_hz, antiresonance_hz=md.f_antiresonance_hz,
        candidates=tuple(candidates), notes=tuple(notes), dynamics=dyn, limit=limit, measured_band_hz=band,
        measured_band_source=facts.band_source, crossover_limit_hz=limit_hz,
    )
    if settings.backlash.enabled:
        model_plant = plant_from_model(facts.source, facts.epsilon_rad, cl_hz, delay_samples=int(math.ceil(delay)))
        settings = choose_backlash_direction(settings, model_plant, opt)
        if settings.backlash.enabled and filter_note:
            settings = replace(settings, notes=settings.notes + (filter_note,))
    # the reported margins: every crossing located exactly on the same loop, and the worst case
    m_ct = loop_margins(settings, p, gap=False)
    mg_ct = loop_margins(settings, p, gap=True) if backlash else None
    settings = replace(settings, margins=m_ct, margins_gap=mg_ct,
                       position_margins=loop_margins(settings, p, loop="position"))
    return replace(settings, robust=robust_margins(settings, p, opt, backlash, robust))


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
