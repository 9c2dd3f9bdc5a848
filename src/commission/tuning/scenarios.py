"""Closed-loop scenarios at the drive's clock, on a plant *with* backlash (:mod:`.closedloop`).

Each scenario starts from rest, the gears centred in the gap:

* ``velocity_step`` — velocity loop alone, a step of the velocity reference: overshoot,
  settling time and steady-state error of the measured motor velocity, limit cycle of it;
* ``position_step`` — position loop, a step of the position reference (no feedforward):
  overshoot and settling of the motor position, steady-state error and limit cycle of the
  *load* position (what backlash spoils);
* ``position_move`` — the same step as a motion controller issues it: minimum-jerk over
  ``reversal_move_time_s``, with feedforward: settling after the move, load error;
* ``reversal`` — smooth moves (minimum-jerk, with velocity and torque feedforward) out, back
  and out again: load position error after the two moves that follow a reversal and the lost
  motion between the two directions (the first move, from the centred gap, is not scored).

The design uses them to choose the backlash compensation's direction on the identified
model (:func:`choose_backlash_direction`); the verification (:mod:`.verify`) runs them all.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..ident.twomass import TwoMassParameters
from ..plant import MAX_COULOMB_RATE, Plant, PlantKernel, PlantParameters
from .closedloop import MAX_NOTCHES, simulate_closed_loop
from .loop import notch_coefficients
from .settings import ControllerSettings, TuningOptions

__all__ = ["SCENARIOS", "ScenarioResult", "choose_backlash_direction", "controller_vector", "plant_from_model",
           "run_scenario"]

#: Final dwell of the position scenarios [s] and the window at its end searched for a limit cycle.
_FINAL_DWELL_S = 0.6
_CYCLE_WINDOW_S = 0.3

SCENARIOS = ("velocity_step", "position_step", "position_move", "reversal")



@functools.lru_cache(maxsize=16)
def _kernel(plant: PlantParameters, sample_rate_hz: float) -> PlantKernel:
    """The compiled loop's view of the plant (the same plant is run a dozen times per design)."""
    return Plant(plant, sample_rate_hz).kernel


def plant_from_model(model: Any, epsilon_rad: float, current_loop_bandwidth_hz: float | None,
                     delay_samples: int = 0, parameters: TwoMassParameters | None = None) -> PlantParameters:
    """The identified model as a plant to simulate, with a drive's current loop and computation
    delay [whole samples]: an Identification brings the Coulomb friction it kept (``friction``
    section); a bare :class:`TwoMassParameters` has none. ``parameters``: other two-mass
    parameters than the model's (a member of the uncertainty set). Friction on an inertia so small that
    its smooth sign would be stiffer than the simulation takes (:data:`commission.plant.MAX_COULOMB_RATE`:
    a flagged fit can leave an almost weightless load) gets the narrowest smooth sign that it takes."""
    params = parameters if parameters is not None else (model if isinstance(model, TwoMassParameters)
                                                        else model.parameters)
    fr = getattr(model, "friction", None) or {}
    extras: dict[str, Any] = {"current_loop_bandwidth_hz": current_loop_bandwidth_hz,
                              "delay_samples": int(delay_samples)}
    if fr:
        f_m, f_l = float(fr.get("motor_nm", 0.0)), float(fr.get("load_nm", 0.0))
        scale = max(float(fr.get("velocity_scale_rad_s", 1e-3)), f_m / (MAX_COULOMB_RATE * params.J_m),
                    f_l / (MAX_COULOMB_RATE * params.J_l))
        extras.update(coulomb_motor_nm=f_m, coulomb_load_nm=f_l, coulomb_velocity_scale_rad_s=scale)
    return PlantParameters.from_two_mass(params, float(epsilon_rad), **extras)


@dataclass(frozen=True)
class ScenarioResult:
    """Figures of one closed-loop run (SI units; None where not applicable)."""

    overshoot_pct: float
    """Of the controlled motor quantity (velocity or position) [%]."""
    settling_time_s: float | None
    """Last exit from the settling band after the step [s] (None: never settles)."""
    steady_state_error: float
    """Motor quantity, mean over the last 10 % [rad/s or rad]."""
    load_error_rad: float | None
    """|load position − target| at the end [rad] (position scenarios)."""
    limit_cycle_amplitude: float
    """Half peak-to-peak over the last 25 % of the run, after detrending: load position [rad]
    (position scenarios) or motor velocity [rad/s] (velocity step)."""
    limit_cycle_frequency_hz: float | None
    """From the zero crossings of that window (None: no oscillation)."""
    peak_torque_nm: float
    lost_motion_rad: float | None = None
    """Reversal: difference of the load errors after a move back and a move out [rad]."""
    signals: dict[str, NDArray[np.float64]] = field(default_factory=dict, repr=False, compare=False)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k in ("overshoot_pct", "settling_time_s", "steady_state_error", "load_error_rad",
                  "limit_cycle_amplitude", "limit_cycle_frequency_hz", "peak_torque_nm", "lost_motion_rad"):
            v = getattr(self, k)
            out[k] = None if v is None or not math.isfinite(v) else float(v)
        return out


def controller_vector(settings: ControllerSettings, *, position_mode: bool, torque_limit_nm: float) -> NDArray[np.float64]:
    """The compiled controller's parameter vector (layout in :mod:`.closedloop`)."""
    Ts = 1.0 / settings.sample_rate_hz
    if len(settings.notches) > MAX_NOTCHES:
        raise ValueError(f"at most {MAX_NOTCHES} notches can be simulated")
    tf_s = settings.torque_filter_time_constant_s
    alpha_f = 1.0 if tf_s <= 0 else 1.0 - math.exp(-Ts / tf_s)
    tb = settings.backlash.time_constant_s
    alpha_b = 1.0 if tb <= 0 else 1.0 - math.exp(-Ts / tb)
    c = [settings.velocity_gain, settings.velocity_integral_gain, settings.position_gain_per_s,
         settings.velocity_feedforward, settings.torque_feedforward * settings.total_inertia_kg_m2, alpha_f,
         torque_limit_nm, 0.5 * settings.backlash.sign * settings.backlash.amount_rad, alpha_b, 1.0 if position_mode else 0.0,
         float(len(settings.notches))]
    tr = settings.reference_filter_time_constant_s
    c.append(1.0 if tr <= 0 else 1.0 - math.exp(-Ts / tr))
    for n in settings.notches:
        b, a = notch_coefficients(n, Ts)
        c += [b[0], b[1], b[2], a[1], a[2]]
    c += [0.0] * (5 * (MAX_NOTCHES - len(settings.notches)))
    return np.array(c, dtype=float)


def _min_jerk(n: int, Ts: float, amplitude: float) -> tuple[NDArray[np.float64], ...]:
    """Position, velocity, acceleration of a minimum-jerk move of n samples."""
    T = n * Ts
    s = np.arange(n) * Ts / T
    pos = amplitude * (10 * s**3 - 15 * s**4 + 6 * s**5)
    vel = amplitude / T * (30 * s**2 - 60 * s**3 + 30 * s**4)
    acc = amplitude / T**2 * (60 * s - 180 * s**2 + 120 * s**3)
    return pos, vel, acc


def _settling(t: NDArray[np.float64], y: NDArray[np.float64], target: float, band: float, t0: float) -> float | None:
    outside = np.flatnonzero((np.abs(y - target) > band) & (t >= t0))
    if outside.size == 0:
        return 0.0
    last = outside[-1]
    if last >= t.size - max(2, t.size // 20):
        return None
    return float(t[last + 1] - t0)


def _limit_cycle(y: NDArray[np.float64], Ts: float, floor: float) -> tuple[float, float | None]:
    """(half peak-to-peak, frequency) of a sustained oscillation in y; (0, None) when there is none.

    A quadratic trend (drift of a load coasting in the gap) is removed first; an oscillation
    needs two full periods (four zero crossings) in the window, an amplitude above ``floor``,
    and must not be dying out (the second half keeps 80 % of the first half's amplitude:
    a lightly damped ringing that decays is not a limit cycle).
    """
    n = y.size
    k = np.arange(n) / max(n - 1, 1)
    r = y - np.polyval(np.polyfit(k, y, 2), k)
    amp = 0.5 * float(np.max(r) - np.min(r))
    crossings = np.flatnonzero(np.sign(r[:-1]) * np.sign(r[1:]) < 0)
    if amp <= floor or crossings.size < 4:
        return 0.0, None
    h = n // 2
    a1 = 0.5 * float(np.max(r[:h]) - np.min(r[:h]))
    a2 = 0.5 * float(np.max(r[h:]) - np.min(r[h:]))
    if a2 < 0.8 * a1:
        return 0.0, None
    f = 0.5 * (crossings.size - 1) / ((crossings[-1] - crossings[0]) * Ts)
    return amp, float(f)


def run_scenario(plant: PlantParameters, settings: ControllerSettings, opt: TuningOptions, scenario: str) -> ScenarioResult:
    """One closed-loop run of ``settings`` on ``plant`` (its torque noise is not simulated; its
    current loop and computation delay are the drive's, whatever the settings were designed for)."""
    Ts = 1.0 / settings.sample_rate_hz
    kernel = _kernel(plant, 1.0 / Ts)
    q_m = 2.0 * math.pi / 2.0**plant.encoder_bits_motor
    q_l = 2.0 * math.pi / 2.0**plant.encoder_bits_load
    t_pre = 0.01
    kpos = settings.position_gain_per_s
    t_ref = 8.0 * settings.reference_filter_time_constant_s  # the reference filter's own settling
    n0 = int(t_pre / Ts)
    # smooth moves (position_move, reversal): samples of a move, of the dwell after it, of the last dwell
    n_move = int(round(opt.reversal_move_time_s / Ts))
    n_dwell = int(round((min(1.0, max(0.2, 10.0 / kpos)) + t_ref) / Ts))
    n_final = max(n_dwell, int(round(_FINAL_DWELL_S / Ts)))

    def position_run(r: NDArray[np.float64], v: NDArray[np.float64], a: NDArray[np.float64]) -> NDArray[np.float64]:
        return simulate_closed_loop(kernel, controller_vector(settings, position_mode=True,
                                                              torque_limit_nm=opt.torque_limit_nm), r, v, a)

    if scenario == "velocity_step":
        dur = t_pre + min(2.0, max(0.1, 40.0 * settings.velocity_integral_time_s))
        n = int(round(dur / Ts))
        t = np.arange(n) * Ts
        v = np.where(t >= t_pre, opt.velocity_step_rad_s, 0.0)
        zero = np.zeros(n)
        out = simulate_closed_loop(kernel, controller_vector(settings, position_mode=False,
                                                             torque_limit_nm=opt.torque_limit_nm), zero, v, zero)
        y = out[1]
        A = opt.velocity_step_rad_s
        tail = y[-max(1, n // 10):]
        amp, f = _limit_cycle(y[-max(8, n // 4):], Ts, 4.0 * q_m / Ts)
        return ScenarioResult(
            overshoot_pct=max(0.0, (float(np.max(y)) - A) / A * 100.0),
            settling_time_s=_settling(t, moving_average(y, 8), A, opt.settle_band * A, t_pre),
            steady_state_error=abs(float(np.mean(tail)) - A), load_error_rad=None,
            limit_cycle_amplitude=amp, limit_cycle_frequency_hz=f, peak_torque_nm=float(np.max(np.abs(out[4]))),
            signals={"t": t, "motor_velocity": y, "load_velocity": out[3], "torque": out[4]})
    if scenario == "position_step":
        dur = t_pre + min(3.0, max(0.25, 15.0 / kpos)) + t_ref
        n = int(round(dur / Ts))
        t = np.arange(n) * Ts
        A = opt.position_step_rad
        r = np.where(t >= t_pre, A, 0.0)
        zero = np.zeros(n)
        out = position_run(r, zero, zero)
        xm, xl = out[0], out[2]
        tail = max(1, n // 10)
        amp, f = _limit_cycle(xl[-max(8, n // 4):], Ts, 2.0 * q_l)
        target_m = A + float(out[6][-1])  # the motor's own target includes the compensation offset
        return ScenarioResult(
            overshoot_pct=max(0.0, (float(np.max(xm)) - target_m) / A * 100.0),
            settling_time_s=_settling(t, xm, target_m, opt.settle_band * A, t_pre),
            steady_state_error=abs(float(np.mean(xm[-tail:])) - target_m),
            load_error_rad=abs(float(np.mean(xl[-tail:])) - A),
            limit_cycle_amplitude=amp, limit_cycle_frequency_hz=f, peak_torque_nm=float(np.max(np.abs(out[4]))),
            signals={"t": t, "motor_position": xm, "load_position": xl, "torque": out[4], "offset": out[6],
                     "reference_filtered": out[7]})
    if scenario == "position_move":
        A = opt.position_step_rad
        p1, v1, a1 = _min_jerk(n_move, Ts, A)
        r = np.concatenate([np.zeros(n0), p1, np.full(n_final, A)])
        v = np.concatenate([np.zeros(n0), v1, np.zeros(n_final)])
        a = np.concatenate([np.zeros(n0), a1, np.zeros(n_final)])
        out = position_run(r, v, a)
        n = r.size
        t = np.arange(n) * Ts
        xm, xl = out[0], out[2]
        tail = max(1, n_dwell // 10)
        target_m = A + float(out[6][-1])
        amp, f = _limit_cycle(xl[-int(round(_CYCLE_WINDOW_S / Ts)):], Ts, 2.0 * q_l)
        return ScenarioResult(
            overshoot_pct=max(0.0, (float(np.max(xm)) - target_m) / A * 100.0),
            settling_time_s=_settling(t, xm, target_m, opt.settle_band * A, (n0 + n_move) * Ts),
            steady_state_error=abs(float(np.mean(xm[-tail:])) - target_m),
            load_error_rad=abs(float(np.mean(xl[-tail:])) - A),
            limit_cycle_amplitude=amp, limit_cycle_frequency_hz=f, peak_torque_nm=float(np.max(np.abs(out[4]))),
            signals={"t": t, "reference": r, "motor_position": xm, "load_position": xl, "torque": out[4],
                     "offset": out[6], "reference_filtered": out[7]})
    if scenario == "reversal":
        # out, back, out again: the first move starts from the centred gap (an artificial start);
        # the figures come from the second and third moves, each after a reversal
        A = opt.reversal_move_rad
        p1, v1, a1 = _min_jerk(n_move, Ts, A)
        z0, zd, zf = np.zeros(n0), np.zeros(n_dwell), np.zeros(n_final)
        r = np.concatenate([z0, p1, np.full(n_dwell, A), A - p1, zd, p1, np.full(n_final, A)])
        v = np.concatenate([z0, v1, zd, -v1, zd, v1, zf])
        a = np.concatenate([z0, a1, zd, -a1, zd, a1, zf])
        out = position_run(r, v, a)
        n = r.size
        t = np.arange(n) * Ts
        xm, xl = out[0], out[2]
        avg = max(1, n_dwell // 10)
        i2 = n0 + 2 * (n_move + n_dwell)
        e2 = float(np.mean(xl[i2 - avg:i2])) - 0.0
        i3 = i2 + n_move + n_dwell
        e3 = float(np.mean(xl[i3 - avg:i3])) - A  # same dwell as e2: a fair comparison
        amp, f = _limit_cycle(xl[-int(round(_CYCLE_WINDOW_S / Ts)):], Ts, 2.0 * q_l)
        err_m = xm - out[7] - out[6]  # tracking of the (filtered) reference the loop follows
        return ScenarioResult(
            overshoot_pct=max(0.0, float(np.max(xm - out[6])) - A) / A * 100.0,
            settling_time_s=None, steady_state_error=float(np.max(np.abs(err_m))),
            load_error_rad=max(abs(e2), abs(e3)), limit_cycle_amplitude=amp, limit_cycle_frequency_hz=f,
            peak_torque_nm=float(np.max(np.abs(out[4]))), lost_motion_rad=abs(e3 - e2),
            signals={"t": t, "reference": r, "motor_position": xm, "load_position": xl, "torque": out[4],
                     "offset": out[6], "reference_filtered": out[7]})
    raise ValueError(f"unknown scenario '{scenario}'")


def moving_average(y: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """Moving average over n samples (the quantised velocity is noisy); the first n-1 average what there is."""
    if n <= 1:
        return y
    c = np.cumsum(np.r_[0.0, y])
    out = np.empty_like(y)
    out[n - 1:] = (c[n:] - c[:-n]) / n
    out[:n - 1] = c[1:n] / np.arange(1, n)
    return out


def choose_backlash_direction(settings: ControllerSettings, model: PlantParameters,
                              options: TuningOptions) -> ControllerSettings:
    """The compensation direction that leaves the load closest to its target on the model.

    Whether the load rests on the driving flank after a move (dragged: its friction brakes it
    harder than the motor decelerates) or coasts onto the braking flank depends on the move
    and on B_l/J_l; both directions and no compensation are simulated on the identified model
    with the verification's ``reversal`` and the best is kept (score: lost motion + largest load
    error after the moves that follow a reversal). Compensation is switched off, with a note, when it
    does not help.
    """
    if not settings.backlash.enabled:
        return settings

    def score(s: ControllerSettings) -> float:
        b = run_scenario(model, s, options, "reversal")
        return float((b.load_error_rad or 0.0) + (b.lost_motion_rad or 0.0))

    candidates = {d: replace(settings, backlash=replace(settings.backlash, direction=d))
                  for d in ("forward", "reverse")}
    scores = {d: score(s) for d, s in candidates.items()}
    off = score(settings.without_backlash_compensation())
    best = min(scores, key=lambda d: scores[d])
    if scores[best] >= off:
        return replace(settings.without_backlash_compensation(),
                       notes=settings.notes + (f"backlash compensation off: it does not reduce the load error on "
                                               f"the model (score {off:.2e} rad off, {scores[best]:.2e} rad on)",))
    return replace(candidates[best], notes=settings.notes + (
        f"backlash compensation {best}: load error + lost motion {off:.2e} → {scores[best]:.2e} rad on the model",))
