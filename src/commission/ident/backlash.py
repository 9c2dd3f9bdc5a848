"""Two-mass model with a dead-zone backlash: event-located simulation, output-error losses, ε search.

Plant (METHOD.md, paper eqs. 1–5), twist z = x_m − x_l (the dead zone's input)::

    J_m·ẍ_m = τ − B_m·ẋ_m − τ_s          J_l·ẍ_l = τ_s − B_l·ẋ_l
    τ_s = K·(z ∓ ε) + D·ż in contact (z ≷ ±ε),   τ_s = 0 in the gap (|z| ≤ ε)

Simulation. The torque is held over a sample and each mode (contact+, gap, contact−) is
linear, so a step is one precomputed matrix exponential of the 6×6 augmented system (state
``[x_m, v_m, z, v_l]``, inputs ``[τ, 1]``; ``exp(M·Ts/2^j)`` for j = 0 … 28). A step that may
leave its mode — at its end point, or in between (a graze, found from the Hermite interpolant
of z with a margin far above its error) — is halved down to Ts/2^28 (0.47 ps at 8 kHz), where
the mode switches; the rest of the sample continues in the new mode. The event time is thus
the only approximation, and ε = 0 is one linear mode, exact up to rounding. Event location
matters: a fixed step per sample is off by far more than an encoder step on impact-rich plants
(measured with bench/bench_backlash.py: see bench/results/RESULTS.md).

Sampling convention (the drive's): at tick k the encoder is latched, ``velocity[k] =
(pos[k] − pos[k−1])/Ts``, then ``torque_ref[k]`` is held over ``[k·Ts, (k+1)·Ts)``.
``delay_samples = d`` applies ``torque_ref[j − d + 1]`` over ``[j·Ts, (j+1)·Ts)``: d = 1 is
the drive's convention (``velocity[k]`` depends on ``torque_ref[0 … k−1]``), d > 1 adds
transport delay (zero torque before the record), d = 0 removes the ZOH/backward-difference
sample of delay (the last value is held).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from commission.exceptions import IdentificationError
from commission.ident.compiled import read_only
from commission.ident.twomass import TwoMassParameters

__all__ = [
    "DeadzoneState", "DeadzoneResponse", "EpsilonSearch", "simulate_deadzone",
    "simulate_motor_velocity", "deadzone", "nonlinear_torque", "max_output_error",
    "rms_output_error", "epsilon_grid", "search_epsilon_grid", "search_epsilon_bayes",
    "epsilon_interval",
]

#: Finest sub-step is Ts/2**28 (0.47 ps at 8 kHz): the event-time resolution.
_J_LEVELS = 28
#: Hysteresis on the mode boundaries z = ±ε [rad], so that a state on a boundary cannot chatter.
_TOL_Z = 1e-13
#: Margin factor of the Hermite graze detector (see ``_leaves``).
_MARGIN = 0.05
#: Zeno guard: after this many mode switches in one sample the rest is finished in the current mode.
_MAX_EVENTS_PER_SAMPLE = 64

_MODE_PLUS, _MODE_GAP, _MODE_MINUS, _MODE_LINEAR = 0, 1, 2, 3


# --- compiled core ---------------------------------------------------------- #
@njit(cache=True)
def _mode_matrix(J_m, J_l, B_m, B_l, K, D, eps, mode):
    """Augmented 6×6 matrix M of one mode: d/dt [x_m, v_m, z, v_l, τ, 1] = M·[…]."""
    M = np.zeros((6, 6))
    M[0, 1] = 1.0
    M[2, 1] = 1.0
    M[2, 3] = -1.0
    M[1, 1] = -B_m / J_m
    M[1, 4] = 1.0 / J_m
    M[3, 3] = -B_l / J_l
    if mode != _MODE_GAP:
        sigma = 0.0
        if mode == _MODE_PLUS:
            sigma = 1.0
        elif mode == _MODE_MINUS:
            sigma = -1.0
        # τ_s = K·z + D·(v_m − v_l) − σ·K·ε
        M[1, 2] -= K / J_m
        M[1, 1] -= D / J_m
        M[1, 3] += D / J_m
        M[1, 5] += sigma * K * eps / J_m
        M[3, 2] += K / J_l
        M[3, 1] += D / J_l
        M[3, 3] -= D / J_l
        M[3, 5] -= sigma * K * eps / J_l
    return M


@njit(cache=True)
def _matmul6(X, Y):
    n = X.shape[0]
    Z = np.zeros((n, n))
    for i in range(n):
        for k in range(n):
            x = X[i, k]
            if x != 0.0:
                for j in range(n):
                    Z[i, j] += x * Y[k, j]
    return Z


@njit(cache=True)
def _expm_levels(M, h, levels):
    """exp(M·h/2^j) for j = 0 … levels.

    Taylor series of F = exp(A) − I at the finest level (‖A‖ ~ 1e-7), then
    F_{j} = 2·F_{j+1} + F_{j+1}² up to the full step: carrying F rather than
    I + F keeps full relative precision through the 28 squarings (squaring
    I + F directly loses ~8 digits).
    """
    n = M.shape[0]
    out = np.empty((levels + 1, n, n))
    A = M * (h / 2.0**levels)
    F = A.copy()
    term = A.copy()
    for k in range(2, 8):
        term = _matmul6(term, A) / k
        F = F + term
    for j in range(levels, -1, -1):
        if j < levels:
            F = 2.0 * F + _matmul6(F, F)
        out[j] = F
        for i in range(n):
            out[j, i, i] += 1.0
    return out


@njit(cache=True)
def _spectral_radius_bound(M):
    """Cheap upper bound of the fastest rate in M's 4×4 block (√ of ‖A²‖∞ keeps the
    unbalanced K/J entries from inflating it: for a stiff oscillator A² ≈ −ω²)."""
    A = M[:4, :4]
    A2 = _matmul6(A.copy(), A.copy())
    r = 0.0
    for i in range(4):
        s = 0.0
        for j in range(4):
            s += abs(A2[i, j])
        if s > r:
            r = s
    r1 = 0.0
    for i in range(4):
        if abs(A[i, i]) > r1:
            r1 = abs(A[i, i])
    return max(math.sqrt(r), r1)


@njit(cache=True)
def _hermite_range(z0, z1, w0, w1, T):
    """(min, max) over [0, T] of the cubic Hermite interpolant of z with slopes w."""
    a = z0
    b = T * w0
    c = -3.0 * z0 - 2.0 * T * w0 + 3.0 * z1 - T * w1
    d = 2.0 * z0 + T * w0 - 2.0 * z1 + T * w1
    lo = min(z0, z1)
    hi = max(z0, z1)
    # p'(s) = b + 2c s + 3d s²: its roots in (0, 1)
    qa = 3.0 * d
    qb = 2.0 * c
    qc = b
    r0 = -1.0
    r1 = -1.0
    if abs(qa) < 1e-300:
        if abs(qb) > 1e-300:
            r0 = -qc / qb
    else:
        disc = qb * qb - 4.0 * qa * qc
        if disc >= 0.0:
            q = -0.5 * (qb + math.copysign(math.sqrt(disc), qb))
            if q != 0.0:
                r0 = q / qa
                r1 = qc / q
    if 0.0 < r0 < 1.0:
        p = a + r0 * (b + r0 * (c + r0 * d))
        lo = min(lo, p)
        hi = max(hi, p)
    if 0.0 < r1 < 1.0:
        p = a + r1 * (b + r1 * (c + r1 * d))
        lo = min(lo, p)
        hi = max(hi, p)
    return lo, hi


@njit(cache=True)
def _leaves(mode, eps, z0, z1, w0, w1, T, omega):
    """True if the trajectory may leave ``mode`` within the step (end point or graze)."""
    if mode == _MODE_LINEAR:
        return False
    # end point
    if mode == _MODE_PLUS:
        if z1 < eps - _TOL_Z:
            return True
    elif mode == _MODE_MINUS:
        if z1 > -eps + _TOL_Z:
            return True
    else:
        if z1 > eps + _TOL_Z or z1 < -eps - _TOL_Z:
            return True
    # graze: Hermite interpolant with a margin ≫ its error T⁴·|z''''|/384
    wt = omega * T
    margin = _MARGIN * wt * wt * T * (abs(w0) + abs(w1) + abs(w1 - w0))
    # cheap bound first: |h10|, |h11| ≤ 4/27 on [0, 1]
    spread = 0.15 * T * (abs(w0) + abs(w1)) + margin
    lo = min(z0, z1) - spread
    hi = max(z0, z1) + spread
    if mode == _MODE_PLUS:
        if lo >= eps - _TOL_Z:
            return False
    elif mode == _MODE_MINUS:
        if hi <= -eps + _TOL_Z:
            return False
    elif hi <= eps + _TOL_Z and lo >= -eps - _TOL_Z:
        return False
    lo, hi = _hermite_range(z0, z1, w0, w1, T)
    if mode == _MODE_PLUS:
        return lo - margin < eps - _TOL_Z
    if mode == _MODE_MINUS:
        return hi + margin > -eps + _TOL_Z
    return hi + margin > eps + _TOL_Z or lo - margin < -eps - _TOL_Z


@njit(cache=True)
def _classify(z, eps, linear):
    if linear:
        return _MODE_LINEAR
    if z > eps:
        return _MODE_PLUS
    if z < -eps:
        return _MODE_MINUS
    return _MODE_GAP


@njit(cache=True)
def _simulate_core(J_m, J_l, B_m, B_l, K, D, eps, h, tau, shift, x0, locate, full):
    """Compiled loop. The torque acting over [k·Ts, (k+1)·Ts) is tau[k − shift]
    (0 before the record, the last value held after it).

    Returns x_m, z, x_l, v_m, v_l (backward differences), ẋ_m, ẋ_l, τ_s at the
    ticks, the final state and the number of events; with ``full = False`` only
    v_m is filled and the other arrays are empty (fresh output arrays cost more
    than the loop itself)."""
    n = tau.shape[0]
    L = _J_LEVELS
    linear = eps <= 0.0
    nmodes = 4
    P, omega, dt = _mode_maps(J_m, J_l, B_m, B_l, K, D, eps, h, L, nmodes)
    nf = n if full else 0
    xm = np.empty(nf)
    zz = np.empty(nf)
    vm_tick = np.empty(nf)
    vl_tick = np.empty(nf)
    ts = np.empty(nf)
    vm = np.empty(n)
    inv_h = 1.0 / h
    vm[0] = x0[1]
    s0, s1, s2, s3 = x0[0], x0[1], x0[2], x0[3]
    mode = _classify(s2, eps, linear)
    NT = np.int64(1) << L
    events = 0
    x_prev = s0
    for k in range(n):
        if k > 0:
            vm[k] = (s0 - x_prev) * inv_h
        x_prev = s0
        if full:
            xm[k] = s0
            zz[k] = s2
            vm_tick[k] = s1
            vl_tick[k] = s3
            if mode == _MODE_GAP:
                ts[k] = 0.0
            else:
                sig = 1.0 if mode == _MODE_PLUS else (-1.0 if mode == _MODE_MINUS else 0.0)
                ts[k] = K * (s2 - sig * eps) + D * (s1 - s3)
        u = _held_input(tau, k - shift)
        if not locate:
            # fixed step: the mode is decided at the sample boundary only
            mode = _classify(s2, eps, linear)
        t = np.int64(0)
        j = 0
        sample_events = 0
        while t < NT:
            Pm = P[mode, j]
            n0 = Pm[0, 0] * s0 + Pm[0, 1] * s1 + Pm[0, 2] * s2 + Pm[0, 3] * s3 + Pm[0, 4] * u + Pm[0, 5]
            n1 = Pm[1, 0] * s0 + Pm[1, 1] * s1 + Pm[1, 2] * s2 + Pm[1, 3] * s3 + Pm[1, 4] * u + Pm[1, 5]
            n2 = Pm[2, 0] * s0 + Pm[2, 1] * s1 + Pm[2, 2] * s2 + Pm[2, 3] * s3 + Pm[2, 4] * u + Pm[2, 5]
            n3 = Pm[3, 0] * s0 + Pm[3, 1] * s1 + Pm[3, 2] * s2 + Pm[3, 3] * s3 + Pm[3, 4] * u + Pm[3, 5]
            ok = (linear or not locate or sample_events >= _MAX_EVENTS_PER_SAMPLE
                  or _stays(mode, eps, s2, n2, s1 - s3, n1 - n3, dt[j], omega[mode]))
            if ok or j == L:
                s0, s1, s2, s3 = n0, n1, n2, n3
                t += NT >> j
                if not ok:
                    # resolution reached: switch if the end point left the mode
                    m2 = _classify(s2, eps, linear)
                    if m2 != mode:
                        mode = m2
                        events += 1
                        sample_events += 1
                if t < NT:
                    # next: the largest aligned dyadic chunk starting at t
                    j = L
                    tt = t
                    while (tt & 1) == 0:
                        tt >>= 1
                        j -= 1
            else:
                j += 1  # halve the step and try again
    xl, vl = _load_ticks(xm, zz, x0[3], inv_h)
    return xm, zz, xl, vm, vl, vm_tick, vl_tick, ts, np.array([s0, s1, s2, s3]), events


@njit(cache=True, inline="always")
def _held_input(tau, k):
    """tau[k]: 0 before the record, the last value held after it."""
    if k < 0:
        return 0.0
    return tau[tau.shape[0] - 1] if k >= tau.shape[0] else tau[k]


@njit(cache=True, inline="always")
def _stays(mode, eps, s2, n2, w0, w1, T, omega):
    """Whether the step of length T from twist s2 (twist rate w0) to n2 (w1) stays in ``mode``: a cheap
    bound first (see :func:`_leaves`), the full test only near ±ε."""
    wt = omega * T
    spread = T * (abs(w0) + abs(w1)) * (0.15 + _MARGIN * wt * wt) + _MARGIN * wt * wt * T * abs(w1 - w0)
    if mode == _MODE_PLUS:
        ok = min(s2, n2) - spread >= eps - _TOL_Z
    elif mode == _MODE_MINUS:
        ok = max(s2, n2) + spread <= -eps + _TOL_Z
    else:
        ok = max(s2, n2) + spread <= eps + _TOL_Z and min(s2, n2) - spread >= -eps - _TOL_Z
    return ok or not _leaves(mode, eps, s2, n2, w0, w1, T, omega)


@njit(cache=True)
def _mode_maps(J_m, J_l, B_m, B_l, K, D, eps, h, L, nmodes):
    """Per mode the exact maps of the dyadic steps h/2^j, j = 0 … L ((nmodes, L + 1, 4, 6): state and input
    and constant columns), a bound on its spectral radius, and the step lengths [s]."""
    P = np.empty((nmodes, L + 1, 4, 6))
    omega = np.zeros(nmodes)
    for m in range(nmodes):
        M = _mode_matrix(J_m, J_l, B_m, B_l, K, D, eps, m)
        P[m] = _expm_levels(M, h, L)[:, :4, :]
        omega[m] = _spectral_radius_bound(M)
    dt = np.empty(L + 1)
    for j in range(L + 1):
        dt[j] = h / 2.0**j
    return P, omega, dt


@njit(cache=True)
def _load_ticks(xm, zz, vl0, inv_h):
    """The load position x_m − z at the ticks and its backward-difference velocity (v_l0 at tick 0)."""
    nf = xm.shape[0]
    xl = np.empty(nf)
    vl = np.empty(nf)
    if nf:
        for k in range(nf):
            xl[k] = xm[k] - zz[k]
        vl[0] = vl0
        for k in range(1, nf):
            vl[k] = (xl[k] - xl[k - 1]) * inv_h
    return xl, vl


# --- public API ------------------------------------------------------------- #
@dataclass(frozen=True)
class DeadzoneState:
    """State of the two-mass + dead-zone model at one instant (SI units)."""

    motor_position: float = 0.0  # x_m [rad]
    motor_velocity: float = 0.0  # ẋ_m [rad/s]
    load_position: float = 0.0  # x_l [rad]; twist x_m − x_l = 0 is the centre of the gap
    load_velocity: float = 0.0  # ẋ_l [rad/s]


@dataclass(frozen=True)
class DeadzoneResponse:
    """Sampled response of :func:`simulate_deadzone`, every array of shape (N,).

    Positions, twist and shaft torque are the values at the ticks t = k·Ts;
    velocities follow the drive's convention ``v[k] = (x[k] − x[k−1])/Ts``
    (``v[0]`` is the initial velocity).
    """

    motor_velocity: NDArray[np.float64]  # [rad/s], backward difference of motor_position
    motor_position: NDArray[np.float64]  # x_m(k·Ts) [rad]
    load_velocity: NDArray[np.float64]  # [rad/s], backward difference of load_position
    load_position: NDArray[np.float64]  # x_l(k·Ts) [rad]
    twist: NDArray[np.float64]  # z = x_m − x_l at k·Ts [rad]
    shaft_torque: NDArray[np.float64]  # τ_s = K·dz(z) + D·ẏ at k·Ts [N·m] (0 in the gap)
    motor_velocity_instant: NDArray[np.float64]  # ẋ_m(k·Ts) [rad/s], not what a drive reports
    load_velocity_instant: NDArray[np.float64]  # ẋ_l(k·Ts) [rad/s]
    final_state: DeadzoneState  # state at N·Ts (to continue a simulation)
    n_events: int  # mode switches (contact, separation) located inside the steps


def _prepare(params: TwoMassParameters, epsilon_rad: float, torque_ref: ArrayLike,
             sample_rate_hz: float, delay_samples: int,
             initial: DeadzoneState | None) -> tuple[list[float], NDArray[np.float64], NDArray[np.float64], DeadzoneState]:
    """Validate the arguments: (parameters as floats, torque, initial state vector, initial)."""
    tau = read_only(torque_ref)  # (one compiled signature, whatever the caller passes)
    if tau.ndim != 1 or tau.size == 0:
        raise IdentificationError(f"torque_ref must be a non-empty 1-D array, got shape {tau.shape}")
    if not np.all(np.isfinite(tau)):
        raise IdentificationError("torque_ref contains NaN or inf")
    if not (np.isfinite(epsilon_rad) and epsilon_rad >= 0.0):
        raise IdentificationError(f"epsilon_rad must be finite and >= 0, got {epsilon_rad}")
    if not sample_rate_hz > 0.0:
        raise IdentificationError(f"sample_rate_hz must be > 0, got {sample_rate_hz}")
    if delay_samples < 0:
        raise IdentificationError(f"delay_samples must be >= 0, got {delay_samples}")
    p = params.as_array()
    if not np.all(np.isfinite(p)) or params.J_m <= 0.0 or params.J_l <= 0.0:
        raise IdentificationError(f"invalid two-mass parameters: {params}")
    ini = initial if initial is not None else DeadzoneState()
    x0 = np.array([ini.motor_position, ini.motor_velocity, ini.motor_position - ini.load_position,
                   ini.load_velocity])
    return [float(v) for v in p], tau, x0, ini


def simulate_deadzone(params: TwoMassParameters, epsilon_rad: float, torque_ref: ArrayLike,
                      sample_rate_hz: float, *, delay_samples: int = 1, initial: DeadzoneState | None = None,
                      locate_events: bool = True) -> DeadzoneResponse:
    """Simulate the open-loop two-mass model with dead-zone backlash, driven by torque.

    :param params: linear two-mass parameters.
    :param epsilon_rad: half-width ε of the dead zone [rad] (≥ 0; 0 = no backlash,
        one linear mode, exact).
    :param torque_ref: motor torque reference [N·m], shape (N,), zero-order hold.
    :param sample_rate_hz: 1/Ts [Hz].
    :param delay_samples: d ≥ 0, ``torque_ref[j − d + 1]`` acts over ``[j·Ts, (j+1)·Ts)``
        (module docstring; 1 is the drive's convention).
    :param initial: state at t = 0; default at rest, twist 0 (centre of the gap).
    :param locate_events: locate contacts/separations inside the step (default).
        ``False`` decides the mode once per sample from the twist at the tick
        (a fixed-step scheme, kept to measure what event location buys).
    :raises IdentificationError: invalid parameters or torque.
    """
    pv, tau, x0, ini = _prepare(params, epsilon_rad, torque_ref, sample_rate_hz, delay_samples, initial)
    h = 1.0 / sample_rate_hz
    xm, z, xl, vm, vl, vm_i, vl_i, ts, s_end, events = _simulate_core(
        *pv, float(epsilon_rad), h, tau, int(delay_samples) - 1, x0, bool(locate_events), True
    )
    final = DeadzoneState(motor_position=float(s_end[0]), motor_velocity=float(s_end[1]),
                          load_position=float(s_end[0] - s_end[2]), load_velocity=float(s_end[3]))
    return DeadzoneResponse(
        motor_velocity=vm, motor_position=xm, load_velocity=vl, load_position=xl, twist=z, shaft_torque=ts,
        motor_velocity_instant=vm_i, load_velocity_instant=vl_i, final_state=final, n_events=int(events),
    )


def simulate_motor_velocity(params: TwoMassParameters, epsilon_rad: float, torque_ref: ArrayLike,
                            sample_rate_hz: float, *, delay_samples: int = 1,
                            initial: DeadzoneState | None = None, locate_events: bool = True
                            ) -> NDArray[np.float64]:
    """Only ``simulate_deadzone(...).motor_velocity`` [rad/s], shape (N,): the fast path for
    losses (bitwise the same values; one output array instead of ten, which costs more than
    the loop)."""
    pv, tau, x0, _ = _prepare(params, epsilon_rad, torque_ref, sample_rate_hz, delay_samples, initial)
    out = _simulate_core(
        *pv, float(epsilon_rad), 1.0 / sample_rate_hz, tau, int(delay_samples) - 1, x0,
        bool(locate_events), False,
    )
    return out[3]


def deadzone(x: ArrayLike, epsilon_rad: float) -> NDArray[np.float64]:
    """dz(x; ε) = x − ε (x > ε), 0 (|x| ≤ ε), x + ε (x < −ε) — paper eq. 1."""
    xa = np.asarray(x, dtype=float)
    return np.where(xa > epsilon_rad, xa - epsilon_rad, np.where(xa < -epsilon_rad, xa + epsilon_rad, 0.0))


def nonlinear_torque(params: TwoMassParameters, epsilon_rad: float, twist: ArrayLike,
                     twist_rate: ArrayLike) -> NDArray[np.float64]:
    """Internal torque n(t) by which the backlash differs from the linear shaft [N·m]::

        τ_s = K·dz(z) + D·ẏ = (K·z + D·ż) − n,   n = K·(z − dz(z)) + D·(ż − ẏ)

    (n = K·ε·sign(z) in contact, K·z + D·ż in the gap). n acts between the masses, +n on
    the motor and −n on the load, so V_m = G_mm·(T_ref + N) − G_ml·N; the paper's eq. 25
    (T̂_input = T_ref − T̂_s, T̂_s ≡ −n) neglects the −n on the load.

    :param twist: z = x_m − x_l [rad], simulated (:attr:`DeadzoneResponse.twist`) or measured.
    :param twist_rate: ż [rad/s] (``motor_velocity_instant − load_velocity_instant`` of a
        simulation, or v_m − v_l measured).
    """
    z = np.asarray(twist, dtype=float)
    w = np.asarray(twist_rate, dtype=float)
    gap = np.abs(z) <= epsilon_rad
    return params.K * (z - deadzone(z, epsilon_rad)) + np.where(gap, params.D * w, 0.0)


def max_output_error(v_meas: ArrayLike, v_sim: ArrayLike) -> float:
    """The paper's loss (eq. 31): max_t |v_meas − v_sim| [rad/s]."""
    a = np.asarray(v_meas, dtype=float)
    b = np.asarray(v_sim, dtype=float)
    if a.shape != b.shape:
        raise IdentificationError(f"shape mismatch {a.shape} vs {b.shape}")
    return float(np.max(np.abs(a - b)))


def rms_output_error(v_meas: ArrayLike, v_sim: ArrayLike) -> float:
    """sqrt(mean((v_meas − v_sim)²)) [rad/s]."""
    a = np.asarray(v_meas, dtype=float)
    b = np.asarray(v_sim, dtype=float)
    if a.shape != b.shape:
        raise IdentificationError(f"shape mismatch {a.shape} vs {b.shape}")
    return float(np.sqrt(np.mean((a - b) ** 2)))


# --- ε search --------------------------------------------------------------- #
#: The paper's search range and resolution for ε (Table 2) [rad].
EPSILON_BOUNDS_RAD = (math.radians(0.01), math.radians(1.0))
EPSILON_RESOLUTION_RAD = math.radians(0.01)


@dataclass(frozen=True)
class EpsilonSearch:
    """Result of a 1-D search for the backlash half-width ε on a grid."""

    epsilon_rad: float  # best grid value [rad]
    loss: float  # loss at epsilon_rad
    evaluations: int  # distinct loss calls (repeated grid points are served from a cache)
    history: list[tuple[float, float]] = field(default_factory=list)  # (ε [rad], loss), in order
    interval_rad: tuple[float, float] = (math.nan, math.nan)  # see epsilon_interval [rad]
    method: Literal["grid", "bayes"] = "grid"

    @property
    def epsilon_deg(self) -> float:
        return math.degrees(self.epsilon_rad)


def epsilon_grid(bounds_rad: tuple[float, float], resolution_rad: float) -> NDArray[np.float64]:
    """lo, lo + r, …, up to hi (inclusive within 1e-9·r) [rad]."""
    lo, hi = float(bounds_rad[0]), float(bounds_rad[1])
    if not (resolution_rad > 0.0 and hi >= lo):
        raise IdentificationError(f"invalid grid bounds {bounds_rad} / resolution {resolution_rad}")
    n = int(math.floor((hi - lo) / resolution_rad + 1e-9)) + 1
    return lo + resolution_rad * np.arange(n)


def epsilon_interval(grid: NDArray[np.float64], loss_at: Callable[[int], tuple[float, float]], i_best: int,
                     f_best: float, rel_tol: float) -> tuple[float, float]:
    """Connected run of grid values around the argmin whose loss may be within tolerance.

    Walks outwards from ``i_best`` while ``loss_at(i)[0] ≤ f_best·(1 + rel_tol)``;
    ``loss_at(i)`` returns (lower bound, known): the loss of an evaluated point, the GP's
    optimistic bound μ − 2σ for an unevaluated one. ``rel_tol`` is the loss's noise level
    (0.05: losses within 5 % of the minimum cannot be told apart).
    """
    thr = f_best * (1.0 + rel_tol) if f_best >= 0 else f_best * (1.0 - rel_tol)
    lo = hi = i_best
    while lo - 1 >= 0 and loss_at(lo - 1)[0] <= thr:
        lo -= 1
    while hi + 1 < grid.size and loss_at(hi + 1)[0] <= thr:
        hi += 1
    return float(grid[lo]), float(grid[hi])


def search_epsilon_grid(loss: Callable[[float], float], bounds_rad: tuple[float, float] = EPSILON_BOUNDS_RAD,
                        resolution_rad: float = EPSILON_RESOLUTION_RAD, *, rel_tol: float = 0.05
                        ) -> EpsilonSearch:
    """Exhaustive search: evaluate ``loss(ε)`` on every grid value (ε in rad).

    ``interval_rad`` is the connected run of grid values around the argmin whose
    loss is ≤ (1 + rel_tol)·min (see :func:`epsilon_interval`).
    """
    grid = epsilon_grid(bounds_rad, resolution_rad)
    values = np.empty(grid.size)
    history: list[tuple[float, float]] = []
    for i, e in enumerate(grid):
        values[i] = float(loss(float(e)))
        history.append((float(e), float(values[i])))
    if not np.all(np.isfinite(values)):
        raise IdentificationError("the loss returned NaN/inf on the ε grid")
    ib = int(np.argmin(values))
    interval = epsilon_interval(grid, lambda i: (values[i], 1.0), ib, float(values[ib]), rel_tol)
    return EpsilonSearch(epsilon_rad=float(grid[ib]), loss=float(values[ib]), evaluations=int(grid.size),
                         history=history, interval_rad=interval, method="grid")


def search_epsilon_bayes(loss: Callable[[float], float], bounds_rad: tuple[float, float] = EPSILON_BOUNDS_RAD,
                         resolution_rad: float = EPSILON_RESOLUTION_RAD, *, n_initial: int = 5,
                         max_calls: int = 40, seed: int = 0, stop_when: Sequence[str] | None = None,
                         rel_tol: float = 0.05, ei_tol: float = 1e-3) -> EpsilonSearch:
    """Bayesian optimisation (GP + expected improvement) of ``loss(ε)`` on the grid.

    Thin wrapper over :func:`commission.ident.bayesopt.minimize_on_grid`; see
    there for the stopping rule and the interval. ``stop_when`` selects the
    stopping criteria (default: ``("ei", "local_min")``).
    """
    from commission.ident.bayesopt import minimize_on_grid

    grid = epsilon_grid(bounds_rad, resolution_rad)
    res = minimize_on_grid(loss, grid, n_initial=n_initial, max_evaluations=max_calls, seed=seed,
                           stop_when=tuple(stop_when) if stop_when is not None else ("ei", "local_min"),
                           rel_tol=rel_tol, ei_tol=ei_tol)
    return EpsilonSearch(epsilon_rad=res.x, loss=res.fun, evaluations=res.evaluations, history=res.history,
                         interval_rad=res.interval, method="bayes")
