"""The physics of a two-mass axis coupled through a dead-zone backlash, sampled as a drive does.

The simulated drive (``sim_drive``) runs its device on this plant, and the tuning's
closed-loop verification (:mod:`commission.tuning.closedloop`) runs its controller around
the very same compiled integrator, so that a verification and a ``--sim`` run share one
physics. Parameters are a typed, frozen model (:class:`PlantParameters`, SI units); the
compiled loops see them as a :class:`PlantKernel` (a named tuple, read by field name).

Model (METHOD.md, "Plant"), motor side m and load side l::

    J_m·ẍ_m = τ − B_m·ẋ_m − τ_s − F_cm(ẋ_m)
    J_l·ẍ_l = τ_s − B_l·ẋ_l − F_cl(ẋ_l)
    x_s = x_m − x_l,   y = dz(x_s; ε),   τ_s = K·y + D·ẏ

with dz(x; ε) = x − ε (x > ε), 0 (|x| ≤ ε), x + ε (x < −ε), and ẏ = ẋ_m − ẋ_l in contact, 0 in
the gap. Coulomb friction is a smooth sign, F_c(v) = F·tanh(v / v_scale), so the right-hand
side stays continuous inside each mode. Optional: a first-order current loop
dτ/dt = ω_c·(τ_ref − τ) (its output across a held sample is known in closed form), a
computation delay (the reference of tick k reaches the current loop at tick k + d), white
torque noise added after the current loop (``numpy.random.default_rng(seed).normal(0, σ, N)``,
one value per sample, held, drawn only when σ > 0) and encoders of finite resolution.

Sample timing (the identifier relies on it). At tick k, t = k·Ts, the drive

1. latches the encoders: ``position[k] = q(x(k·Ts))``, q(x) = round(x / step)·step,
   step = 2π / 2**bits;
2. computes ``velocity[k] = (position[k] − position[k−1]) / Ts`` (position[−1]: at reset);
3. applies ``torque_ref[k]`` held constant (zero-order hold) over [k·Ts, (k+1)·Ts).

So velocity[k] depends on the torque up to k−1 only: the one-sample delay of METHOD.md.

Integration. τ_s jumps by D·ẏ when the gears touch or separate, so an integrator stepping
across a mode switch loses its order. Each sample is split into ``SUBSTEPS_PER_SAMPLE`` (or
more, for stiff plants and fast current loops) RK4 sub-steps with the mode held fixed; after
each, the twist is checked against |x_s| = ε at the end and, via its cubic Hermite
interpolant, inside (grazing contacts). A crossing is located by Illinois regula falsi on the
length of an RK4 step from the sub-step's start, the step taken up to it, the mode switched
and the rest of the sub-step integrated in the new mode. The state carries the twist x_s, not
x_l, so that the distance to the boundary keeps full precision after hundreds of radians.
Near zero velocity Coulomb friction is stiff (rate F / (v_scale·J)): the sub-step is split
further there. Impact-rich, lightly damped runs can be chaotic (any two step sizes part after
many impacts): that is the model's physics, and it bounds what a whole-record output-error
comparison can mean on such plants.

The per-sample loop is a module-level numba function (``cache=True`` needs that); chunked and
whole-array calls give bitwise-identical results because all the loop's memory lives in the
``Plant`` object between calls.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Annotated, Any, NamedTuple

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator, validate_call

from .ident.twomass import TwoMassParameters

__all__ = [
    "MAX_DELAY_SAMPLES",
    "MAX_LAG_STEP",
    "MAX_RATE_STEP",
    "SUBSTEPS_PER_SAMPLE",
    "Plant",
    "PlantKernel",
    "PlantParameters",
    "PlantResponse",
    "PlantState",
    "advance_sample",
    "initial_state",
    "load_position",
    "motor_position",
    "quantise",
    "twist",
]

#: RK4 sub-steps per sample (the minimum; stiffer plants get more, see MAX_RATE_STEP): errors
#: orders of magnitude below a 24-bit encoder's velocity quantum (bench/bench_plant.py; figures in
#: bench/results/RESULTS.md).
SUBSTEPS_PER_SAMPLE = 4
#: Largest |λ|·h for the fastest contact-mode eigenvalue λ of the linear plant (h = Ts / sub-steps).
MAX_RATE_STEP = 0.06
#: Largest ω_c·h for the current-loop lag, whose exponential enters RK4 as a forcing term.
MAX_LAG_STEP = 0.5
#: Largest rate·h in the stiff zone of the smooth-sign Coulomb friction, rate = F/(v_s·J).
_MAX_COULOMB_STEP = 1.0
#: Fastest contact-mode rate |λ| [1/s] a plant may have (a 20 kHz mode): beyond any servo axis, and
#: the most the simulation resolves at an affordable cost (~250 sub-steps per 8 kHz sample).
MAX_MODE_RATE = 2.0 * math.pi * 20e3
#: Largest stiffness F/(v_s·J) [1/s] of the smooth-sign Coulomb friction (cost grows with it, see Plant).
MAX_COULOMB_RATE = 1e6
#: Most RK4 sub-steps per sample a Plant takes on: more is a plant the sample rate cannot resolve
#: (the compiled loop would run for hours, deaf to Ctrl-C).
MAX_SUBSTEPS_PER_SAMPLE = 1024
#: Mode changes located per sub-step before event location gives up for that sub-step
#: (guards against chattering at a grazing contact; never reached in normal use).
_MAX_EVENTS_PER_SUBSTEP = 16
#: Tolerance of the located crossing, as distance of the twist to the boundary [rad].
_EVENT_TOL_RAD = 1e-13


class PlantParameters(BaseModel):
    """Physical parameters of the simulated axis (SI units; defaults: METHOD.md reference plant).

    Values must be finite and plausible for a servo axis: inertias from 1e-9 to 1e4 kg·m², the
    fastest mode of the coupled axis below 20 kHz (:data:`MAX_MODE_RATE`) and the Coulomb
    friction's smooth sign no stiffer than :data:`MAX_COULOMB_RATE`; anything else would not
    be a machine, and could keep the compiled simulation busy for hours.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    J_m: float = Field(4.78e-4, ge=1e-9, le=1e4, description="Motor-side inertia [kg·m²].")
    J_l: float = Field(1.92e-4, ge=1e-9, le=1e4, description="Load-side inertia [kg·m²].")
    B_m: float = Field(0.84e-2, ge=0, le=1e6, description="Motor-side viscous friction [N·m·s/rad].")
    B_l: float = Field(0.53e-2, ge=0, le=1e6, description="Load-side viscous friction [N·m·s/rad].")
    K: float = Field(23.10, gt=0, le=1e9, description="Shaft stiffness [N·m/rad].")
    D: float = Field(1.54e-2, ge=0, le=1e6, description="Shaft damping [N·m·s/rad].")
    epsilon_deg: float = Field(
        0.40, ge=0, lt=90, description="Backlash half-width ε [deg]; 0 = no backlash."
    )
    coulomb_motor_nm: float = Field(
        0.0, ge=0, le=1e5, description="Coulomb friction level on the motor side [N·m]."
    )
    coulomb_load_nm: float = Field(
        0.0, ge=0, le=1e5, description="Coulomb friction level on the load side [N·m]."
    )
    coulomb_velocity_scale_rad_s: float = Field(
        1e-3,
        gt=0,
        description="Velocity scale v_s of the smooth sign: F_c(v) = F·tanh(v / v_s) [rad/s].",
    )
    current_loop_bandwidth_hz: float | None = Field(
        None,
        gt=0,
        le=1e6,
        description="Bandwidth of a first-order lag from torque reference to motor torque [Hz]; "
        "None = ideal current loop.",
    )
    delay_samples: int = Field(
        0,
        ge=0,
        le=8,
        description="Whole samples between a torque reference and the current loop's input: the "
        "drive's computation and transport delay beyond the zero-order hold's own sample.",
    )
    torque_noise_nm: float = Field(
        0.0,
        ge=0,
        le=1e5,
        description="Standard deviation of white noise added to the motor torque, one value "
        "per sample, held over the sample [N·m].",
    )
    encoder_bits_motor: int = Field(
        24, ge=1, le=32, description="Motor encoder resolution: 2**bits counts per revolution."
    )
    encoder_bits_load: int = Field(
        24, ge=1, le=32, description="Load encoder resolution: 2**bits counts per revolution."
    )
    seed: int = Field(0, ge=0, lt=2**63, description="Seed of the torque-noise generator.")

    @model_validator(mode="after")
    def _plausible(self) -> PlantParameters:
        rate = _fastest_contact_rate(self)
        if not rate <= MAX_MODE_RATE:
            raise ValueError(
                f"the axis's fastest mode (J_m, J_l, B_m, B_l, K, D) is at {rate / (2 * math.pi):.4g} Hz, "
                f"above {MAX_MODE_RATE / (2 * math.pi):.4g} Hz: not a servo axis"
            )
        for side, force, inertia in (("motor", self.coulomb_motor_nm, self.J_m), ("load", self.coulomb_load_nm, self.J_l)):
            stiffness = force / (self.coulomb_velocity_scale_rad_s * inertia)
            if stiffness > MAX_COULOMB_RATE:
                raise ValueError(
                    f"coulomb_{side}_nm / (coulomb_velocity_scale_rad_s · J) is {stiffness:.3g} 1/s, above "
                    f"{MAX_COULOMB_RATE:.3g} 1/s: raise coulomb_velocity_scale_rad_s or lower the friction"
                )
        return self

    @property
    def epsilon_rad(self) -> float:
        """Backlash half-width ε [rad]."""
        return math.radians(self.epsilon_deg)

    @property
    def two_mass(self) -> TwoMassParameters:
        """The linear two-mass part (J_m, J_l, B_m, B_l, K, D)."""
        return TwoMassParameters(J_m=self.J_m, J_l=self.J_l, B_m=self.B_m, B_l=self.B_l, K=self.K, D=self.D)

    @classmethod
    def from_two_mass(cls, params: TwoMassParameters, epsilon_rad: float, **extras: Any) -> PlantParameters:
        """A plant from a two-mass model (an identified one, say) and its backlash ε [rad];
        ``extras``: any other field (friction, current loop, encoders)."""
        return cls(**params.as_dict(), epsilon_deg=math.degrees(epsilon_rad), **extras)


@dataclass(frozen=True)
class PlantState:
    """True continuous state of the plant at a sample instant."""

    x_m: float  # motor position [rad]
    v_m: float  # motor velocity [rad/s]
    x_l: float  # load position [rad]
    v_l: float  # load velocity [rad/s]
    applied_torque: float  # the current loop's output now, without noise (ideal: the reference) [N·m]


@dataclass(frozen=True, eq=False)
class PlantSnapshot:
    """Opaque copy of a Plant's memory, from :meth:`Plant.snapshot`."""

    memory: NDArray[np.float64]
    rng_state: dict[str, Any]


@dataclass(frozen=True, eq=False)  # eq on arrays is ambiguous: compare fields explicitly
class PlantResponse:
    """Sampled signals of one run; every array has shape (N,) and dtype float64."""

    motor_position: NDArray[np.float64]  # [rad], quantised by the motor encoder at t = k·Ts
    motor_velocity: NDArray[np.float64]  # [rad/s] as a drive reports it: (q[k] − q[k−1]) / Ts
    load_position: NDArray[np.float64]  # [rad], quantised by the load encoder
    load_velocity: NDArray[np.float64]  # [rad/s], (q[k] − q[k−1]) / Ts of the load encoder
    torque_ref: NDArray[np.float64]  # applied over [k·Ts, (k+1)·Ts) [N·m] (velocity mode: PI output)
    shaft_torque: NDArray[np.float64]  # true τ_s at t = k·Ts [N·m] (diagnostics)
    twist: NDArray[np.float64]  # true x_m − x_l at t = k·Ts [rad] (diagnostics)


class PlantKernel(NamedTuple):
    """The plant as the compiled loops read it (SI units; built by :attr:`Plant.kernel`).

    A named tuple because numba passes it by value and reads its fields by name; the
    reciprocals are there because a multiplication is cheaper than a division.
    """

    J_m: float
    J_l: float
    B_m: float
    B_l: float
    K: float
    D: float
    epsilon_rad: float
    coulomb_motor_nm: float
    coulomb_load_nm: float
    coulomb_velocity_scale_rad_s: float
    current_loop_rad_s: float  # ω_c = 2π·bandwidth [rad/s]; 0 = ideal
    delay_samples: int  # whole samples between a torque reference and the current loop's input
    encoder_step_motor_rad: float
    encoder_step_load_rad: float
    inv_J_m: float
    inv_J_l: float
    inv_velocity_scale: float
    substeps: int  # RK4 sub-steps per sample
    sample_time_s: float


# Layout of the loop's memory (one float64 vector so that numba can update it in place):
# x_m, v_m, x_s (twist), v_l, applied torque, contact mode, last latched encoder positions
# (motor, load), PI integrator, then the computation delay's line of torque references (the
# newest first). Loops compiled elsewhere use the accessors below.
_XM, _VM, _XS, _VL, _TC, _MODE, _QM, _QL, _INTEG = range(9)
#: Longest computation delay the plant holds [samples] (PlantParameters.delay_samples ≤ this).
MAX_DELAY_SAMPLES = 8
_DELAY0 = 9
_STATE_SIZE = _DELAY0 + MAX_DELAY_SAMPLES


@njit(cache=True)
def _smooth_sign(x: float) -> float:
    """tanh(x), skipping the libm call where tanh is exactly ±1.0 in float64 (|x| > 19.1)."""
    if x > 20.0:
        return 1.0
    if x < -20.0:
        return -1.0
    return math.tanh(x)


@njit(cache=True)
def _accelerations(
    v_m: float, x_s: float, v_l: float, mode: int, tau: float, p: PlantKernel
) -> tuple[float, float]:
    """(ẍ_m, ẍ_l) [rad/s²] in the given contact mode (+1, 0 gap, −1) under motor torque tau."""
    if mode > 0:
        tau_s = p.K * (x_s - p.epsilon_rad) + p.D * (v_m - v_l)
    elif mode < 0:
        tau_s = p.K * (x_s + p.epsilon_rad) + p.D * (v_m - v_l)
    else:
        tau_s = 0.0
    f_m = tau - p.B_m * v_m - tau_s
    f_l = tau_s - p.B_l * v_l
    if p.coulomb_motor_nm > 0.0:
        f_m -= p.coulomb_motor_nm * _smooth_sign(v_m * p.inv_velocity_scale)
    if p.coulomb_load_nm > 0.0:
        f_l -= p.coulomb_load_nm * _smooth_sign(v_l * p.inv_velocity_scale)
    return f_m * p.inv_J_m, f_l * p.inv_J_l


@njit(cache=True)
def _rk4(
    x_m: float,
    v_m: float,
    x_s: float,
    v_l: float,
    mode: int,
    h: float,
    tau0: float,
    tau_mid: float,
    tau1: float,
    p: PlantKernel,
) -> tuple[float, float, float, float]:
    """One classical RK4 step of length h [s] in a fixed mode; returns (x_m, v_m, x_s, v_l)."""
    a_m1, a_l1 = _accelerations(v_m, x_s, v_l, mode, tau0, p)
    vm1, vl1 = v_m, v_l
    hh = 0.5 * h
    vm2 = v_m + hh * a_m1
    vl2 = v_l + hh * a_l1
    a_m2, a_l2 = _accelerations(vm2, x_s + hh * (vm1 - vl1), vl2, mode, tau_mid, p)
    vm3 = v_m + hh * a_m2
    vl3 = v_l + hh * a_l2
    a_m3, a_l3 = _accelerations(vm3, x_s + hh * (vm2 - vl2), vl3, mode, tau_mid, p)
    vm4 = v_m + h * a_m3
    vl4 = v_l + h * a_l3
    a_m4, a_l4 = _accelerations(vm4, x_s + h * (vm3 - vl3), vl4, mode, tau1, p)
    h6 = h / 6.0
    return (
        x_m + h6 * (vm1 + 2.0 * vm2 + 2.0 * vm3 + vm4),
        v_m + h6 * (a_m1 + 2.0 * a_m2 + 2.0 * a_m3 + a_m4),
        x_s + h6 * ((vm1 - vl1) + 2.0 * (vm2 - vl2) + 2.0 * (vm3 - vl3) + (vm4 - vl4)),
        v_l + h6 * (a_l1 + 2.0 * a_l2 + 2.0 * a_l3 + a_l4),
    )


@njit(cache=True)
def _hermite_exit(g0: float, g1: float, m0: float, m1: float) -> float:
    """First θ ∈ (0, 1] at which the cubic Hermite interpolant of g is known to be > 0.

    g0, g1 are the values at θ = 0 and 1, m0, m1 the slopes dg/dθ. Returns 1.0 when
    only the end point is outside (or the earliest interior maximum > 0, if before),
    and −1.0 when the interpolant stays ≤ 0 on (0, 1].
    """
    # Cheap exclusion first: p(θ) = linear + θ(1−θ)·[(1−θ)(m0−Δ) − θ(m1−Δ)], Δ = g1 − g0,
    # so p ≤ max(g0, g1) + max(|m0−Δ|, |m1−Δ|)/4; most sub-steps end here.
    dg = g1 - g0
    if max(g0, g1) + 0.25 * max(abs(m0 - dg), abs(m1 - dg)) <= 0.0:
        return -1.0
    a3 = 2.0 * g0 + m0 - 2.0 * g1 + m1
    a2 = -3.0 * g0 - 2.0 * m0 + 3.0 * g1 - m1
    a1 = m0
    # Critical points: 3·a3·θ² + 2·a2·θ + a1 = 0 (scalars only: this runs every sub-step).
    best = 1.0 if g1 > 0.0 else -1.0
    qa = 3.0 * a3
    qb = 2.0 * a2
    r0 = -1.0
    r1 = -1.0
    if abs(qa) < 1e-300:
        if qb != 0.0:
            r0 = -a1 / qb
    else:
        disc = qb * qb - 4.0 * qa * a1
        if disc >= 0.0:
            sq = math.sqrt(disc)
            r0 = (-qb - sq) / (2.0 * qa)
            r1 = (-qb + sq) / (2.0 * qa)
    for th in (r0, r1):
        if 0.0 < th < 1.0:
            g = ((a3 * th + a2) * th + a1) * th + g0
            if g > 0.0 and (best < 0.0 or th < best):
                best = th
    return best


@njit(cache=True)
def _lag_factor(wc: float, dt: float) -> float:
    """exp(−ω_c·dt): decay of the current-loop deviation over dt (1 for no lag in use)."""
    if wc > 0.0:
        return math.exp(-wc * dt)
    return 1.0


@njit(cache=True)
def _step_in_mode(
    s: NDArray[np.float64], mode: int, dt: float, u: float, c0: float, p: PlantKernel
) -> tuple[float, float, float, float]:
    """RK4 step of length dt from state s with motor torque u + c0·exp(−ω_c·t)."""
    eh = _lag_factor(p.current_loop_rad_s, 0.5 * dt)
    return _rk4(
        s[_XM], s[_VM], s[_XS], s[_VL], mode, dt, u + c0, u + c0 * eh, u + c0 * eh * eh, p
    )


@njit(cache=True)
def _integrate_sample(
    s: NDArray[np.float64],
    u: float,
    c: float,
    p: PlantKernel,
    locate_events: bool,
) -> float:
    """Advance the state s (in place) by one sample under motor torque u + c·exp(−ω_c·t).

    ``u`` is the held torque (reference + noise), ``c`` the current-loop deviation at
    the start of the sample. Returns the deviation at the end of the sample.
    ``locate_events=False`` switches modes at sub-step boundaries instead of locating
    the crossings; it exists only to measure what event location buys (bench).
    """
    eps = p.epsilon_rad
    events_on = locate_events and eps > 0.0
    n_sub = p.substeps
    h = p.sample_time_s / n_sub
    # Coulomb friction: the fastest rate near zero velocity, F / (v_s·J), on each side.
    rate_m = p.coulomb_motor_nm / (p.coulomb_velocity_scale_rad_s * p.J_m)
    rate_l = p.coulomb_load_nm / (p.coulomb_velocity_scale_rad_s * p.J_l)
    coulomb = rate_m > 0.0 or rate_l > 0.0
    mode = int(s[_MODE])
    for _ in range(n_sub):
        t_left = h
        n_events = 0
        while t_left > 0.0:
            dt = t_left
            if coulomb:
                # Split the step where a velocity is (or may get) inside the tanh's stiff zone.
                a_m, a_l = _accelerations(s[_VM], s[_XS], s[_VL], mode, u + c, p)
                rate = 0.0
                if rate_m > 0.0 and abs(s[_VM]) < 5.0 * p.coulomb_velocity_scale_rad_s + abs(a_m) * dt:
                    rate = rate_m
                if rate_l > 0.0 and abs(s[_VL]) < 5.0 * p.coulomb_velocity_scale_rad_s + abs(a_l) * dt:
                    rate = max(rate, rate_l)
                if rate * dt > _MAX_COULOMB_STEP:
                    dt = t_left / math.ceil(rate * t_left / _MAX_COULOMB_STEP)
            x_m1, v_m1, x_s1, v_l1 = _step_in_mode(s, mode, dt, u, c, p)
            if events_on and n_events < _MAX_EVENTS_PER_SUBSTEP:
                # Boundary b and orientation sg such that sg·(x_s − b) > 0 means "left the mode".
                ydot0 = s[_VM] - s[_VL]
                ydot1 = v_m1 - v_l1
                theta = -1.0
                b = 0.0
                sg = 1.0
                new_mode = mode
                if mode == 0:
                    th_up = _hermite_exit(
                        s[_XS] - eps, x_s1 - eps, ydot0 * dt, ydot1 * dt
                    )
                    th_dn = _hermite_exit(
                        -(s[_XS] + eps), -(x_s1 + eps), -ydot0 * dt, -ydot1 * dt
                    )
                    if th_up > 0.0 and (th_dn < 0.0 or th_up <= th_dn):
                        theta, b, sg, new_mode = th_up, eps, 1.0, 1
                    elif th_dn > 0.0:
                        theta, b, sg, new_mode = th_dn, -eps, -1.0, -1
                elif mode > 0:
                    theta = _hermite_exit(
                        -(s[_XS] - eps), -(x_s1 - eps), -ydot0 * dt, -ydot1 * dt
                    )
                    b, sg, new_mode = eps, -1.0, 0
                else:
                    theta = _hermite_exit(s[_XS] + eps, x_s1 + eps, ydot0 * dt, ydot1 * dt)
                    b, sg, new_mode = -eps, 1.0, 0
                if theta > 0.0:
                    # Bracket [ta, tb] on the step length: g(ta) ≤ 0 (inside), g(tb) > 0 (outside).
                    tb = theta * dt
                    if theta < 1.0:
                        x_m1, v_m1, x_s1, v_l1 = _step_in_mode(s, mode, tb, u, c, p)
                    gb = sg * (x_s1 - b)
                    if gb > 0.0:
                        ta = 0.0
                        ga = min(sg * (s[_XS] - b), 0.0)
                        g_end = gb  # true distance past the boundary at tb (gb gets reweighted)
                        side = 0
                        for _it in range(60):
                            if g_end <= _EVENT_TOL_RAD or tb - ta <= 1e-12 * h:
                                break
                            tm = (ta * gb - tb * ga) / (gb - ga)
                            if not (ta < tm < tb):
                                tm = 0.5 * (ta + tb)
                            xm_m, vm_m, xs_m, vl_m = _step_in_mode(s, mode, tm, u, c, p)
                            gm = sg * (xs_m - b)
                            if gm > 0.0:
                                tb, gb, g_end = tm, gm, gm
                                x_m1, v_m1, x_s1, v_l1 = xm_m, vm_m, xs_m, vl_m
                                if side == 1:
                                    ga *= 0.5  # Illinois: halve the stale end's weight
                                side = 1
                            else:
                                ta, ga = tm, gm
                                if side == -1:
                                    gb *= 0.5
                                side = -1
                        # Step up to the crossing (the state is on the new mode's side).
                        mode = new_mode
                        n_events += 1
                    # Either way the step taken ends at tb; an unconfirmed graze (the
                    # interpolant's peak was not outside) just shortens this step.
                    dt = tb
            s[_XM] = x_m1
            s[_VM] = v_m1
            s[_XS] = x_s1
            s[_VL] = v_l1
            c *= _lag_factor(p.current_loop_rad_s, dt)
            t_left -= dt
            if eps > 0.0 and not locate_events:
                # Comparison mode only (bench): switch at the step boundary, no location.
                mode = 1 if x_s1 > eps else (-1 if x_s1 < -eps else 0)
    s[_MODE] = mode
    return c


@njit(cache=True)
def initial_state(p: PlantKernel) -> NDArray[np.float64]:
    """The loop memory at rest: position 0, twist 0 (centre of the gap; in contact without
    backlash), current loop at 0 N·m, encoders latched at 0."""
    s = np.zeros(_STATE_SIZE)
    s[_MODE] = 0.0 if p.epsilon_rad > 0.0 else 1.0
    return s


@njit(cache=True)
def motor_position(s: NDArray[np.float64]) -> float:
    """True motor position x_m [rad] of the loop memory s."""
    return s[_XM]


@njit(cache=True)
def twist(s: NDArray[np.float64]) -> float:
    """True twist x_m − x_l [rad] of the loop memory s."""
    return s[_XS]


@njit(cache=True)
def load_position(s: NDArray[np.float64]) -> float:
    """True load position x_l [rad] of the loop memory s."""
    return s[_XM] - s[_XS]


@njit(cache=True)
def quantise(x: float, step: float) -> float:
    """An encoder's reading of position x [rad]: round(x / step)·step."""
    return np.rint(x / step) * step


@njit(cache=True)
def advance_sample(s: NDArray[np.float64], u: float, noise: float, p: PlantKernel) -> None:
    """Advance the loop memory s by one sample under the torque reference u [N·m], held over
    the sample, plus the noise torque ``noise`` [N·m] after the current loop.

    For loops compiled elsewhere that run their own controller around this plant
    (:mod:`commission.tuning.closedloop`): the encoders are latched by the caller
    (:func:`quantise` of :func:`motor_position` / :func:`load_position`) before u is computed.
    """
    u = _delayed(s, u, p)
    # Current loop: torque = u + c·exp(−ω_c·t) over the sample, c = deviation at its start.
    c = s[_TC] - u if p.current_loop_rad_s > 0.0 else 0.0
    c = _integrate_sample(s, u + noise, c, p, True)
    s[_TC] = u + c


@njit(cache=True)
def _delayed(s: NDArray[np.float64], u: float, p: PlantKernel) -> float:
    """The torque reference that reaches the current loop now: ``u`` itself without a
    computation delay, else the one computed ``delay_samples`` ticks ago (``u`` joins the line)."""
    d = p.delay_samples
    if d <= 0:
        return u
    out = s[_DELAY0 + d - 1]
    for i in range(d - 1, 0, -1):
        s[_DELAY0 + i] = s[_DELAY0 + i - 1]
    s[_DELAY0] = u
    return out


@njit(cache=True)
def _simulate(
    inp: NDArray[np.float64],
    noise: NDArray[np.float64],
    velocity_mode: bool,
    kp: float,
    ki: float,
    limit: float,
    s: NDArray[np.float64],
    p: PlantKernel,
    locate_events: bool,
    out: NDArray[np.float64],
) -> None:
    """Run len(inp) samples from state s (updated in place); out has shape (7, N).

    inp is the torque reference [N·m] (torque mode) or the velocity reference [rad/s]
    (velocity mode); rows of out: motor position, motor velocity, load position,
    load velocity, torque reference, shaft torque, twist.
    """
    q_m = p.encoder_step_motor_rad
    q_l = p.encoder_step_load_rad
    eps = p.epsilon_rad
    Ts = p.sample_time_s
    lag = p.current_loop_rad_s > 0.0
    for k in range(inp.shape[0]):
        # Latch the encoders and differentiate, as the drive does at the tick.
        pos_m = quantise(s[_XM], q_m)
        pos_l = quantise(s[_XM] - s[_XS], q_l)
        vel_m = (pos_m - s[_QM]) / Ts
        vel_l = (pos_l - s[_QL]) / Ts
        s[_QM] = pos_m
        s[_QL] = pos_l
        mode = int(s[_MODE])
        x_s = s[_XS]
        if mode > 0:
            tau_s = p.K * (x_s - eps) + p.D * (s[_VM] - s[_VL])
        elif mode < 0:
            tau_s = p.K * (x_s + eps) + p.D * (s[_VM] - s[_VL])
        else:
            tau_s = 0.0
        if velocity_mode:
            e = inp[k] - vel_m
            d_integ = ki * e * Ts
            u = kp * e + s[_INTEG] + d_integ
            if u > limit:
                u = limit
            elif u < -limit:
                u = -limit
            else:
                s[_INTEG] += d_integ  # anti-windup: integrate only while unsaturated
        else:
            u = inp[k]
        out[0, k] = pos_m
        out[1, k] = vel_m
        out[2, k] = pos_l
        out[3, k] = vel_l
        out[4, k] = u
        out[5, k] = tau_s
        out[6, k] = x_s
        if locate_events:
            advance_sample(s, u, noise[k], p)
        else:  # comparison mode only (bench): mode switches at sub-step boundaries
            ud = _delayed(s, u, p)
            c = s[_TC] - ud if lag else 0.0
            c = _integrate_sample(s, ud + noise[k], c, p, False)
            s[_TC] = ud + c


def _fastest_contact_rate(params: Any) -> float:
    """Largest |eigenvalue| [1/s] of the linear two-mass plant in contact (PlantParameters, or
    anything with its J_m, J_l, B_m, B_l, K, D)."""
    a = np.array(
        [
            [-(params.B_m + params.D) / params.J_m, params.D / params.J_m, -params.K / params.J_m],
            [params.D / params.J_l, -(params.B_l + params.D) / params.J_l, params.K / params.J_l],
            [1.0, -1.0, 0.0],
        ]
    )  # state (v_m, v_l, x_s)
    return float(np.max(np.abs(np.linalg.eigvals(a))))


class Plant:
    """The simulated axis, advanced sample by sample in cyclic synchronous torque or velocity mode.

    Runs continue from the current state, so an experiment may be fed in chunks:
    whole-array and chunked calls give identical results. Each call has a fixed cost on
    top of the samples, so feed arrays rather than one sample per call. Strong Coulomb
    friction is expensive near zero velocity, where each sub-step is split into
    ≈ F·h/(v_s·J) pieces; a larger ``coulomb_velocity_scale_rad_s`` makes it cheaper.
    """

    @validate_call(config=ConfigDict(arbitrary_types_allowed=True))
    def __init__(
        self,
        params: PlantParameters,
        sample_rate_hz: Annotated[float, Field(gt=0)] = 8000.0,
        *,
        substeps_per_sample: Annotated[int, Field(ge=1)] | None = None,
    ) -> None:
        """params: the machine; sample_rate_hz: drive cycle rate [Hz];
        substeps_per_sample: RK4 sub-steps per sample, None = automatic
        (``SUBSTEPS_PER_SAMPLE``, more for stiff plants or fast current loops, see
        ``MAX_RATE_STEP`` and ``MAX_LAG_STEP``)."""
        self.params = params
        self.sample_rate_hz = float(sample_rate_hz)
        self.sample_time_s = 1.0 / self.sample_rate_hz
        bw = params.current_loop_bandwidth_hz
        if substeps_per_sample is None:
            rate = _fastest_contact_rate(params)
            wc = 0.0 if bw is None else 2.0 * math.pi * bw
            substeps_per_sample = max(
                SUBSTEPS_PER_SAMPLE,
                math.ceil(rate * self.sample_time_s / MAX_RATE_STEP),
                math.ceil(wc * self.sample_time_s / MAX_LAG_STEP),
            )
        if substeps_per_sample > MAX_SUBSTEPS_PER_SAMPLE:
            raise ValueError(
                f"the plant needs {substeps_per_sample} sub-steps per sample at {self.sample_rate_hz:g} Hz "
                f"(at most {MAX_SUBSTEPS_PER_SAMPLE}): its modes are too fast for this sample rate"
            )
        self.substeps_per_sample = int(substeps_per_sample)
        self._kernel = PlantKernel(
            J_m=params.J_m,
            J_l=params.J_l,
            B_m=params.B_m,
            B_l=params.B_l,
            K=params.K,
            D=params.D,
            epsilon_rad=params.epsilon_rad,
            coulomb_motor_nm=params.coulomb_motor_nm,
            coulomb_load_nm=params.coulomb_load_nm,
            coulomb_velocity_scale_rad_s=params.coulomb_velocity_scale_rad_s,
            current_loop_rad_s=0.0 if bw is None else 2.0 * math.pi * bw,
            delay_samples=int(params.delay_samples),
            encoder_step_motor_rad=2.0 * math.pi / 2.0**params.encoder_bits_motor,
            encoder_step_load_rad=2.0 * math.pi / 2.0**params.encoder_bits_load,
            inv_J_m=1.0 / params.J_m,
            inv_J_l=1.0 / params.J_l,
            inv_velocity_scale=1.0 / params.coulomb_velocity_scale_rad_s,
            substeps=self.substeps_per_sample,
            sample_time_s=self.sample_time_s,
        )
        self._s = np.zeros(_STATE_SIZE)
        self.reset()

    @property
    def kernel(self) -> PlantKernel:
        """The plant for loops compiled elsewhere (:func:`initial_state`, :func:`advance_sample`)."""
        return self._kernel

    def reset(self) -> None:
        """At rest at position 0, twist 0 (centre of the gap), current loop at 0 N·m,
        encoder memory at 0, PI integrator cleared, noise generator re-seeded."""
        self._s[:] = 0.0
        self._s[_MODE] = 0.0 if self.params.epsilon_rad > 0.0 else 1.0
        self._rng = np.random.default_rng(self.params.seed)

    @property
    def state(self) -> PlantState:
        """True continuous state at the current sample instant."""
        s = self._s
        return PlantState(
            x_m=float(s[_XM]),
            v_m=float(s[_VM]),
            x_l=float(s[_XM] - s[_XS]),
            v_l=float(s[_VL]),
            applied_torque=float(s[_TC]),
        )

    def snapshot(self) -> PlantSnapshot:
        """Everything a later run depends on (state, encoder memory, integrator, noise stream)."""
        return PlantSnapshot(self._s.copy(), copy.deepcopy(self._rng.bit_generator.state))

    def restore(self, snapshot: PlantSnapshot) -> None:
        """Return to a snapshot: the next run continues exactly as it would have from there."""
        self._s[:] = snapshot.memory
        self._rng.bit_generator.state = copy.deepcopy(snapshot.rng_state)

    def run_torque(self, torque_ref: ArrayLike) -> PlantResponse:
        """Cyclic synchronous torque: apply torque_ref [N·m], shape (N,), one value per sample."""
        return self._run(_as_signal(torque_ref, "torque_ref"), False, 0.0, 0.0, 0.0)

    def run_velocity(
        self, velocity_ref: ArrayLike, kp: float, ki: float, torque_limit_nm: float
    ) -> PlantResponse:
        """Cyclic synchronous velocity: the drive's PI loop on the motor encoder velocity.

        torque[k] = clip(kp·e[k] + ki·Σ_{i≤k} e[i]·Ts, ±torque_limit_nm),
        e[k] = velocity_ref[k] − motor_velocity[k]; the sum is not extended while the
        output saturates (anti-windup). velocity_ref [rad/s] shape (N,); kp [N·m·s/rad],
        ki [N·m/rad], torque_limit_nm [N·m]. The integrator is kept between calls
        (stored as torque, so a change of ki between calls is bumpless).
        """
        if not (math.isfinite(kp) and kp >= 0.0 and math.isfinite(ki) and ki >= 0.0):
            raise ValueError(f"PI gains must be finite and >= 0, got kp={kp}, ki={ki}")
        if not (math.isfinite(torque_limit_nm) and torque_limit_nm > 0.0):
            raise ValueError(f"torque_limit_nm must be finite and > 0, got {torque_limit_nm}")
        signal = _as_signal(velocity_ref, "velocity_ref")
        return self._run(signal, True, float(kp), float(ki), float(torque_limit_nm))

    def _run(
        self, signal: NDArray[np.float64], velocity_mode: bool, kp: float, ki: float, limit: float
    ) -> PlantResponse:
        n = signal.shape[0]
        sigma = self.params.torque_noise_nm
        noise = self._rng.normal(0.0, sigma, n) if sigma > 0.0 else np.zeros(n)
        out = np.empty((7, n))
        _simulate(signal, noise, velocity_mode, kp, ki, limit, self._s, self._kernel, True, out)
        return PlantResponse(
            motor_position=out[0],
            motor_velocity=out[1],
            load_position=out[2],
            load_velocity=out[3],
            torque_ref=out[4],
            shaft_torque=out[5],
            twist=out[6],
        )


def _as_signal(x: ArrayLike, name: str) -> NDArray[np.float64]:
    """x as a contiguous float64 array of shape (N,), finite."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must have shape (N,), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a
