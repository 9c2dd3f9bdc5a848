"""The motor-equation torque residual and the load-state observer behind it (METHOD.md, "What works").

The load alone is simulated, driven through the dead-zone spring by the *measured* motor
position, and the motor equation is checked as a torque balance at samples 1 … N−2::

    e = J_m·ẍ_m + B_m·ẋ_m (+ F_cm·tanh(ẋ_m/v_s)) + τ_s(sim) − τ      [N·m]

Nothing integrates open loop against the real motor, so e has no drift and its minimum in ε is
sharp. :func:`residual_vector` is the objective of :mod:`commission.ident.estimator`.

Observer (:class:`Observer`, applied inside :func:`_simulate_load`). Over many impacts a load
simulated open loop parts from the real one (the bouncing in the gap is chaotic). So after each
sample interval k is integrated, its residual e_k, low-passed by a causal biquad, moves the
simulated load by ``gain``·ẽ_k [rad per N·m] (and, with a load encoder, by a fraction of its
distance to the measured position). The move is spread as a ramp over the next interval, so the
load's state stays continuous and contact and separation are located as always: the residual
stays a continuous function of the parameters. e is then the one-step prediction error of a
fixed-gain predictor of the load state; gain 0 (:data:`OPEN_LOOP`) is the open-loop residual.

Sample alignment (derived, not tuned). At tick k the encoder is latched, x[k] = x_m(k·Ts), then
τ_ref[k] is held over [k·Ts, (k+1)·Ts). The triangle kernel w(s) = 1 − |s| on s ∈ [−1, 1] gives
the exact identity (x[k+1] − 2x[k] + x[k−1])/Ts² = ∫ w(s)·ẍ_m(k+s) ds, so every term of the motor
equation is averaged with the same kernel: τ_ref (ZOH) exactly as (τ_ref[k−1] + τ_ref[k])/2;
ẋ_m as (x[k+1] − x[k−1])/(2·Ts) (O(Ts²)); τ_s = K·y + D·ẏ from the integrals of y the simulation
accumulates over each interval, ∫ w·ẏ by parts (y is continuous across contact and separation,
so the impact torque D·ẏ is integrated exactly). This is METHOD.md's "one sample of delay"
handled in the time domain; the backward-difference velocity is not used.

Load simulation. The motor position between samples is a cubic (:func:`motor_interpolant`). In
contact the load obeys a linear ODE driven by it: a whole interval is mapped exactly
(:func:`contact_map`), parts of an interval (between events) and contact steps with load Coulomb
friction take RK4 steps; in the gap the load decays analytically (viscous) or by RK4 with
friction. Contact and separation are located inside the step (Hermite interpolant of the gap
variable checked at interior points for grazes, then bisection), so the residual is a smooth
function of ε and the load parameters, as finite-difference Jacobians need.

Optional terms: motor Coulomb friction, a regressor linear in F_cm (``ResidualProblem.coulomb``,
the triangle average of tanh(ẋ_m/v_s) by Gauss–Legendre); load Coulomb friction F_cl·tanh(ẋ_l/v_s)
in the load simulation, where explicit RK4 steps in the smooth sign's stiff zone are cut so that
rate·h stays below RK4's stability limit (:data:`_STIFF_STEP`) and v_s stays the stated one (beyond
:data:`_MAX_STIFF_PARTS` sub-steps, L-stable steps instead); a first-order current-loop lag
T_c·τ̇ = τ_ref − τ (:func:`lagged_torque`, exact for a held τ_ref).

Filtering. The second difference of a quantised position is blue noise, so the residual is
low-passed zero-phase (Butterworth, as ``scipy.signal.sosfiltfilt``) and decimated to about twice
the cut-off, where its samples are roughly independent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline
from scipy.signal import butter, sosfilt_zi, sosfiltfilt

from ..exceptions import IdentificationError
from .compiled import inlined, per_sample, read_only
from .consistency import InitialMotion, initial_motion

__all__ = [
    "ResidualProblem",
    "Residual",
    "LoadSimulation",
    "prepare_residual",
    "simulate_load",
    "lagged_torque",
    "motor_interpolant",
    "torque_residual",
    "residual_vector",
    "motor_part",
    "Observer",
    "OPEN_LOOP",
]

#: Interior points checked per step (and per remaining part of a step) for grazing events.
_GRAZE_POINTS = 4
_BISECT_ITERATIONS = 40
#: max over u ∈ [0, 1] of the Hermite basis functions of the end slopes (4/27), a bit more.
_HERMITE_BOUND = 0.15
#: Load speeds within this many v_s of zero are in the smooth sign's stiff zone (tanh' < 2e-4 outside).
_STIFF_ZONE = 5.0
#: rate·h per RK4 sub-step where the smooth sign is stiff (rate = (F_cl/J_l)/v_s; RK4 is stable up
#: to 2.785, and at 2 the fast mode still decays by R(−2) = 1/3 per sub-step): half the sub-steps of
#: 1, close to Radau and within the bench's tolerances (measured: see bench/results/RESULTS.md).
_STIFF_STEP = 2.0
#: |v_l|/v_s beyond which the smooth sign is ±1 in float64 (tanh(x) = 1 − 2e^(−2x): 1 − 4e−22 at
#: 25, below half an ulp) at both ends of a contact interval: the load friction is then a
#: constant force there and the interval is stepped exactly (:func:`_exact_contact`).
_SATURATED = 25.0
#: Partial steps per sample interval; past them the interval ends where it stands. Seen only where the
#: observer had driven the simulation unstable (|x_l| ~1e18 rad: a contact step per part), whose residual
#: is a plateau whatever the rest of the interval does.
_MAX_PARTS = 200
#: Most RK4 sub-steps per interval in the stiff zone of the load's smooth sign. Only parameters far
#: from any plant need more (F_cl/J_l ≫ the plant's: a load inertia driven to zero by a fit, the
#: smooth sign's time constant below Ts/128); there the steps are L-stable instead (:func:`_sdirk_gap`,
#: :func:`_sdirk_contact`, four sub-steps per interval): the load sticks as hard friction would.
_MAX_STIFF_PARTS = 64
#: γ of the two-stage, stiffly accurate, L-stable SDIRK method (order 2; Alexander 1977).
_SDIRK_GAMMA = 1.0 - 1.0 / math.sqrt(2.0)
#: Newton steps at most per stage equation (bracketed: it converges in a handful).
_TANH_ROOT_ITERATIONS = 60
#: L-stable sub-steps per contact step: as many as RK4 takes in the gap.
_SDIRK_PARTS = 4


# --- compiled core (module level, so that numba's cache=True works) ----------
# error_model="numpy" drops Python's division checks from the loops and the step functions are
# inlined: the same arithmetic, bit-identical results, markedly faster.
@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _motor(c: NDArray[np.float64], k: int, s: float) -> tuple[float, float]:
    """Motor position [rad] and d/ds [rad per sample] at k + s from spline coefficients c (N−1, 4)."""
    a3 = c[k, 0]
    a2 = c[k, 1]
    a1 = c[k, 2]
    a0 = c[k, 3]
    return ((a3 * s + a2) * s + a1) * s + a0, (3.0 * a3 * s + 2.0 * a2) * s + a1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _hermite(y0: float, d0: float, y1: float, d1: float, u: float) -> float:
    """Cubic Hermite on u ∈ [0, 1] with end values y and end slopes d (per unit u)."""
    u2 = u * u
    u3 = u2 * u
    return ((2 * u3 - 3 * u2 + 1) * y0 + (u3 - 2 * u2 + u) * d0
            + (-2 * u3 + 3 * u2) * y1 + (u3 - u2) * d1)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _smooth_sign(x: float) -> float:
    """tanh(x), exactly ±1 where float64 tanh is (|x| > 20)."""
    if x > 20.0:
        return 1.0
    if x < -20.0:
        return -1.0
    return math.tanh(x)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _tanh_root(a: float, b: float, ivs: float, r: float) -> float:
    """The root V of a·V + b·tanh(V·ivs) = r (a > 0, b ≥ 0: one root, in [(r − b)/a, (r + b)/a]),
    by Newton's method kept inside the bracket (bisection where a step leaves it)."""
    if b == 0.0:
        return r / a
    lo = (r - b) / a
    hi = (r + b) / a
    v = r / (a + b * ivs)  # the root of the linearisation at 0
    if not lo < v < hi:
        v = 0.5 * (lo + hi)
    for _ in range(_TANH_ROOT_ITERATIONS):
        t = _smooth_sign(v * ivs)
        g = a * v + b * t - r
        if g > 0.0:
            hi = v
        elif g < 0.0:
            lo = v
        else:
            return v
        vn = v - g / (a + b * ivs * (1.0 - t * t))
        if not lo < vn < hi:
            vn = 0.5 * (lo + hi)
        if abs(vn - v) <= 1e-15 * abs(v) + 1e-300 or hi - lo <= 1e-15 * abs(v):
            return vn
        v = vn
    return v


@per_sample  # (called, not inlined: taken rarely, and each inlined copy is compiled again)
def _sdirk_gap(xl: float, vl: float, decay: float, ts: float, cj: float, ivs: float,
               n: int) -> tuple[float, float]:
    """:func:`_gap_state` by the L-stable two-stage SDIRK method on n equal sub-steps: each stage is
    one scalar equation in the load speed (:func:`_tanh_root`)."""
    h = ts / n
    hg = h * _SDIRK_GAMMA
    a = 1.0 + hg * decay
    b = hg * cj
    x = xl
    v = vl
    for _ in range(n):
        v1 = _tanh_root(a, b, ivs, v)
        f1 = (v1 - v) / hg
        v2 = _tanh_root(a, b, ivs, v + (h - hg) * f1)
        x = x + (h - hg) * v1 + hg * v2
        v = v2
    return x, v


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _gap_state(xl: float, vl: float, decay: float, ts: float, cj: float, ivs: float,
               Ts: float) -> tuple[float, float]:
    """Load position and velocity after ts seconds in the gap.

    Without load Coulomb friction (cj = 0) the free viscous decay (rate decay = B_l/J_l) is
    exact. With it, v̇ = −decay·v − cj·tanh(v·ivs) (cj = F_cl/J_l) is integrated by RK4 on
    sub-steps of at most Ts/4, more in the smooth sign's stiff zone (L-stable ones beyond the cap)
    — a smooth function of ts, as the event bisection needs.
    """
    if cj == 0.0:
        if decay * ts < 1e-9:
            return xl + vl * ts, vl
        e = np.exp(-decay * ts)
        return xl + vl * (1.0 - e) / decay, vl * e
    n = int(math.ceil(4.0 * ts / Ts - 1e-9))
    if n < 1:
        n = 1
    # stiff zone of the smooth sign: |v̇| ≤ decay·|v| + cj bounds how near zero v can get
    rate_ts = cj * ivs * ts / _STIFF_STEP
    if rate_ts > n and abs(vl) * ivs < _STIFF_ZONE + (decay * abs(vl) + cj) * ts * ivs:
        if rate_ts > _MAX_STIFF_PARTS:
            return _sdirk_gap(xl, vl, decay, ts, cj, ivs, n)
        n = int(math.ceil(rate_ts))
    h = ts / n
    x = xl
    v = vl
    for _ in range(n):
        a1 = -decay * v - cj * _smooth_sign(v * ivs)
        v2 = v + 0.5 * h * a1
        a2 = -decay * v2 - cj * _smooth_sign(v2 * ivs)
        v3 = v + 0.5 * h * a2
        a3 = -decay * v3 - cj * _smooth_sign(v3 * ivs)
        v4 = v + h * a3
        a4 = -decay * v4 - cj * _smooth_sign(v4 * ivs)
        x = x + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    return x, v


@per_sample
def _gap_state_at_event(xl: float, vl: float, decay: float, ts: float, cj: float, ivs: float,
                        Ts: float) -> tuple[float, float]:
    """:func:`_gap_state`, called: the gap step's evaluations that locate a contact (at events only) share
    one compiled copy instead of three inlined ones."""
    return _gap_state(xl, vl, decay, ts, cj, ivs, Ts)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _accel(xm: float, vm: float, xl: float, vl: float, side: float, eps: float,
           kj: float, dj: float, bj: float, cj: float, ivs: float) -> tuple[float, float]:
    """(y, load acceleration) in contact; kj = K/J_l, dj = D/J_l, bj = B_l/J_l, cj = F_cl/J_l,
    ivs = 1/(velocity scale of the smooth sign)."""
    y = xm - xl - side * eps
    a = kj * y + dj * (vm - vl) - bj * vl
    if cj != 0.0:
        a -= cj * _smooth_sign(vl * ivs)
    return y, a


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _rk4_contact(c: NDArray[np.float64], k: int, s: float, se: float, Ts: float, xl: float, vl: float,
                 side: float, eps: float, kj: float, dj: float, bj: float, cj: float, ivs: float
                 ) -> tuple[float, float, float, float, float, float]:
    """One RK4 step in contact from k+s to k+se.

    Returns (x_l, v_l, ∫y ds, ∫s·y ds over the step, penetration side·y at the end, its rate
    d(side·y)/ds at the end).
    """
    h = (se - s) * Ts
    sm = 0.5 * (s + se)
    xa, da = _motor(c, k, s)
    xb, db = _motor(c, k, sm)
    xc, dc = _motor(c, k, se)
    va = da / Ts
    vb = db / Ts
    vc = dc / Ts
    y1, a1 = _accel(xa, va, xl, vl, side, eps, kj, dj, bj, cj, ivs)
    x2 = xl + 0.5 * h * vl
    v2 = vl + 0.5 * h * a1
    y2, a2 = _accel(xb, vb, x2, v2, side, eps, kj, dj, bj, cj, ivs)
    x3 = xl + 0.5 * h * v2
    v3 = vl + 0.5 * h * a2
    y3, a3 = _accel(xb, vb, x3, v3, side, eps, kj, dj, bj, cj, ivs)
    x4 = xl + h * v3
    v4 = vl + h * a3
    y4, a4 = _accel(xc, vc, x4, v4, side, eps, kj, dj, bj, cj, ivs)
    xn = xl + h / 6.0 * (vl + 2.0 * v2 + 2.0 * v3 + v4)
    vn = vl + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    ds = se - s
    i0 = ds / 6.0 * (y1 + 2.0 * y2 + 2.0 * y3 + y4)
    i1 = ds / 6.0 * (s * y1 + sm * (2.0 * y2 + 2.0 * y3) + se * y4)
    pe = side * (xc - xn - side * eps)
    dpe = side * (vc - vn) * Ts
    return xn, vn, i0, i1, pe, dpe


@per_sample  # (called, not inlined: taken rarely, and each inlined copy is compiled again)
def _sdirk_contact(c: NDArray[np.float64], k: int, s: float, se: float, Ts: float, xl: float, vl: float,
                   side: float, eps: float, kj: float, dj: float, bj: float, cj: float, ivs: float
                   ) -> tuple[float, float, float, float, float, float]:
    """:func:`_rk4_contact` by the L-stable two-stage SDIRK method on _SDIRK_PARTS equal sub-steps, for
    friction too stiff for RK4 (:data:`_MAX_STIFF_PARTS`): each stage's position is linear in its speed,
    so a stage is one scalar equation (:func:`_tanh_root`); the quadratures integrate the cubic
    Hermite of y on each sub-step."""
    ds = (se - s) / _SDIRK_PARTS
    h = ds * Ts
    hg = h * _SDIRK_GAMMA
    a = 1.0 + hg * (dj + bj) + hg * hg * kj
    b = hg * cj
    xa, da = _motor(c, k, s)
    y0 = xa - xl - side * eps
    dy0 = (da - vl * Ts) * ds
    i0 = 0.0
    i1 = 0.0
    sa = s
    for j in range(_SDIRK_PARTS):
        sb = se if j == _SDIRK_PARTS - 1 else s + (j + 1) * ds
        x1m, d1m = _motor(c, k, sa + _SDIRK_GAMMA * ds)
        xc, dc = _motor(c, k, sb)
        v1 = _tanh_root(a, b, ivs, vl + hg * (kj * (x1m - xl - side * eps) + dj * d1m / Ts))
        f1 = (v1 - vl) / hg
        p = xl + (h - hg) * v1  # X2 = p + hg·V2
        vl = _tanh_root(a, b, ivs, vl + (h - hg) * f1 + hg * (kj * (xc - p - side * eps) + dj * dc / Ts))
        xl = p + hg * vl
        y1 = xc - xl - side * eps
        dy1 = (dc - vl * Ts) * ds
        j0 = 0.5 * (y0 + y1) + (dy0 - dy1) / 12.0
        j1 = 0.15 * y0 + dy0 / 30.0 + 0.35 * y1 - 0.05 * dy1  # ∫₀¹ u·y du
        i0 += ds * j0
        i1 += ds * (sa * j0 + ds * j1)
        y0 = y1
        dy0 = dy1
        sa = sb
    return xl, vl, i0, i1, side * y0, side * (dc - vl * Ts)


@per_sample  # (called, not inlined: taken rarely, and each inlined copy is compiled again)
def _contact_rk(c: NDArray[np.float64], k: int, s: float, se: float, Ts: float, xl: float, vl: float,
                side: float, eps: float, kj: float, dj: float, bj: float, cj: float, ivs: float, implicit: bool
                ) -> tuple[float, float, float, float, float, float]:
    """:func:`_sdirk_contact` if ``implicit``, else :func:`_rk4_contact`."""
    if implicit:
        return _sdirk_contact(c, k, s, se, Ts, xl, vl, side, eps, kj, dj, bj, cj, ivs)
    return _rk4_contact(c, k, s, se, Ts, xl, vl, side, eps, kj, dj, bj, cj, ivs)


def contact_map(Ts: float, kj: float, dj: float, bj: float) -> NDArray[np.float64]:
    """Exact map of one whole sample interval in contact, without load Coulomb friction or with
    a saturated one (a constant force, see :func:`_exact_contact`).

    In contact the load obeys a linear ODE driven by the motor position, which is a cubic in
    s ∈ [0, 1] over the interval (x_m = a3·s³ + a2·s² + a1·s + a0), so the interval's end state
    and the quadratures of y = x_m − x_l − side·ε are linear in (x_l, v_l, a0 − side·ε, a1, 2·a2,
    6·a3): one matrix exponential of the augmented system (in s, d/ds = Ts·d/dt)::

        x_l' = Ts·v_l                      m0' = m1, m1' = m2, m2' = m3, m3' = 0
        v_l' = Ts·(kj·(m0 − x_l) + dj·(m1/Ts − v_l) − bj·v_l)        (m0 = x_m − side·ε)
        Y' = m0 − x_l,  YY' = Y          ∫₀¹ y ds = Y(1),  ∫₀¹ s·y ds = Y(1) − YY(1) (by parts)

    :returns: (4, 6) rows (x_l [rad], v_l [rad/s], ∫y ds, ∫s·y ds at s = 1) over columns
        (x_l, v_l, m0, m1, m2, m3) at s = 0.
    """
    from scipy.linalg import expm

    A = np.zeros((8, 8))
    A[0, 1] = Ts
    A[1, 0] = -Ts * kj
    A[1, 1] = -Ts * (dj + bj)
    A[1, 4] = Ts * kj
    A[1, 5] = dj
    A[2, 4] = 1.0
    A[2, 0] = -1.0
    A[3, 2] = 1.0
    A[4, 5] = 1.0
    A[5, 6] = 1.0
    A[6, 7] = 1.0
    E = expm(A)
    cols = [0, 1, 4, 5, 6, 7]
    return np.ascontiguousarray(np.stack((E[0, cols], E[1, cols], E[2, cols], E[2, cols] - E[3, cols])))


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _exact_contact(cm: NDArray[np.float64], c: NDArray[np.float64], k: int, Ts: float, xl: float,
                   vl: float, side: float, eps: float, shift: float
                   ) -> tuple[float, float, float, float, float, float]:
    """:func:`_rk4_contact` over the whole interval k, exactly, by :func:`contact_map` ``cm``.

    ``shift`` = F/K [rad] for a constant force −F on the load over the interval (a saturated
    Coulomb term, F = F_cl·sign(v_l)): kj·y − F/J_l = kj·(y − shift), so the map runs on
    y − shift and the quadratures get shift back (∫₀¹ shift ds = shift, ∫₀¹ s·shift ds = shift/2).
    """
    a3 = c[k, 0]
    a2 = c[k, 1]
    a1 = c[k, 2]
    a0 = c[k, 3]
    m0 = a0 - side * eps - shift
    m2 = 2.0 * a2
    m3 = 6.0 * a3
    xn = cm[0, 0] * xl + cm[0, 1] * vl + cm[0, 2] * m0 + cm[0, 3] * a1 + cm[0, 4] * m2 + cm[0, 5] * m3
    vn = cm[1, 0] * xl + cm[1, 1] * vl + cm[1, 2] * m0 + cm[1, 3] * a1 + cm[1, 4] * m2 + cm[1, 5] * m3
    i0 = cm[2, 0] * xl + cm[2, 1] * vl + cm[2, 2] * m0 + cm[2, 3] * a1 + cm[2, 4] * m2 + cm[2, 5] * m3
    i1 = cm[3, 0] * xl + cm[3, 1] * vl + cm[3, 2] * m0 + cm[3, 3] * a1 + cm[3, 4] * m2 + cm[3, 5] * m3
    if shift != 0.0:
        i0 += shift
        i1 += 0.5 * shift
    xc = ((a3 + a2) + a1) + a0
    dc = (3.0 * a3 + 2.0 * a2) + a1
    return xn, vn, i0, i1, side * (xc - xn - side * eps), side * (dc - vn * Ts)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _contact_step(cs: NDArray[np.float64], s: float, Ts: float, xl: float, vl: float, side: float, eps: float,
                  kj: float, dj: float, bj: float, cj: float, ivs: float, cm: NDArray[np.float64], friction: bool
                  ) -> tuple[float, float, float, float, float, float, float, bool]:
    """One step in contact from k+s (the interval's motor ``cs``, (1, 4)) to its end, exact or RK4, with the
    quadratures of y and s·y; cut into ceil(rate·h/_STIFF_STEP) parts where the load speed is, or may get,
    within _STIFF_ZONE·v_s of zero (the stiff zone of the Coulomb smooth sign, rate cj·ivs); the L-stable
    step (:func:`_sdirk_contact`) to the end where that would take more than _MAX_STIFF_PARTS.

    Returns (x_l, v_l, ∫y ds, ∫s·y ds, the step's end s, penetration and its rate there
    (:func:`_rk4_contact`), whether the step was the L-stable one)."""
    send = 1.0
    if cj != 0.0:
        rate_h = cj * ivs * (1.0 - s) * Ts / _STIFF_STEP
        if rate_h > 1.0:
            xa, da = _motor(cs, 0, s)
            _, a0 = _accel(xa, da / Ts, xl, vl, side, eps, kj, dj, bj, cj, ivs)
            if abs(vl) * ivs < _STIFF_ZONE + abs(a0) * (1.0 - s) * Ts * ivs:
                if rate_h > _MAX_STIFF_PARTS:
                    xn, vn, i0, i1, p1, dp1e = _sdirk_contact(cs, 0, s, 1.0, Ts, xl, vl, side, eps, kj, dj, bj,
                                                              cj, ivs)
                    return xn, vn, i0, i1, 1.0, p1, dp1e, True
                send = s + (1.0 - s) / math.ceil(rate_h)
    if send == 1.0 and s == 0.0:
        if not friction:  # the common case: a whole interval, linear
            xn, vn, i0, i1, p1, dp1e = _exact_contact(cm, cs, 0, Ts, xl, vl, side, eps, 0.0)
            return xn, vn, i0, i1, send, p1, dp1e, False
        if abs(vl) * ivs > _SATURATED:
            # the load moves fast enough that the smooth sign is ±1 in float64 over the
            # whole interval (checked at its end): a constant force, the step is exact
            sg = 1.0 if vl > 0.0 else -1.0
            xn, vn, i0, i1, p1, dp1e = _exact_contact(cm, cs, 0, Ts, xl, vl, side, eps, sg * cj / kj)
            if vn * sg * ivs > _SATURATED:
                return xn, vn, i0, i1, send, p1, dp1e, False
    if send == 1.0:  # the interval's end as a constant: a few % faster
        xn, vn, i0, i1, p1, dp1e = _rk4_contact(cs, 0, s, 1.0, Ts, xl, vl, side, eps, kj, dj, bj, cj, ivs)
    else:
        xn, vn, i0, i1, p1, dp1e = _rk4_contact(cs, 0, s, send, Ts, xl, vl, side, eps, kj, dj, bj, cj, ivs)
    return xn, vn, i0, i1, send, p1, dp1e, False


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _separation(cs: NDArray[np.float64], s: float, send: float, Ts: float, xl: float, vl: float, side: float,
                eps: float, kj: float, dj: float, bj: float, cj: float, ivs: float, xn: float, vn: float, i0: float,
                i1: float, p1: float, dp1e: float, implicit: bool) -> tuple[bool, float, float, float, float, float]:
    """Whether the contact step from k+s to k+send (ending at xn, vn, i0, i1, penetration p1 and its rate
    dp1e) separates: the penetration p = side·y scanned on the step's cubic Hermite interpolant (interior
    points for grazes), bisected, then polished by Newton steps on the actual RK4 step length, so that
    the impact torque D·ẏ is switched off where the integrated trajectory really reaches the boundary.
    ``implicit``: the step was :func:`_sdirk_contact`'s, and so are the polishing steps.
    Returns (separated, the step's end, x_l, v_l, ∫y ds, ∫s·y ds), the step unchanged if not."""
    h = (send - s) * Ts
    xa, da = _motor(cs, 0, s)
    p0 = side * (xa - xl - side * eps)
    dp0 = side * (da / Ts - vl) * h
    dp1 = dp1e * (send - s)
    hit = -1.0
    lo = 0.0
    # Hermite cubic ≥ min(p0, p1) − (4/27)(|dp0| + |dp1|): skip the scan when safe
    jstart = 1
    if min(p0, p1) > _HERMITE_BOUND * (abs(dp0) + abs(dp1)):
        jstart = _GRAZE_POINTS + 2
    for j in range(jstart, _GRAZE_POINTS + 2):
        u = j / (_GRAZE_POINTS + 1.0)
        if _hermite(p0, dp0, p1, dp1, u) < 0.0:
            hit = u
            break
        lo = u
    if not hit > 0.0:
        return False, send, xn, vn, i0, i1
    hi = hit
    for _ in range(_BISECT_ITERATIONS):
        mid = 0.5 * (lo + hi)
        if _hermite(p0, dp0, p1, dp1, mid) < 0.0:
            hi = mid
        else:
            lo = mid
    se = s + hi * (send - s)
    # Newton on the actual step length
    xn, vn, i0, i1, pe, dpe = _contact_rk(cs, 0, s, se, Ts, xl, vl, side, eps, kj, dj, bj, cj, ivs, implicit)
    for _ in range(4):
        if abs(pe) <= 1e-15 or dpe == 0.0:
            break
        sn = se - pe / dpe
        if not (s < sn <= send):
            break
        xq, vq, iq0, iq1, pq, dpq = _contact_rk(cs, 0, s, sn, Ts, xl, vl, side, eps, kj, dj, bj, cj, ivs,
                                                implicit)
        if abs(pq) >= abs(pe):
            break
        se, xn, vn, i0, i1, pe, dpe = sn, xq, vq, iq0, iq1, pq, dpq
    return True, se, xn, vn, i0, i1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _gap_step(cs: NDArray[np.float64], s: float, Ts: float, xl: float, vl: float, bj: float, cj: float, ivs: float,
              eps: float) -> tuple[float, float, float, float, int]:
    """One step in the gap from k+s to the interval's end or the contact: the load's free decay exact, the
    motor the spline's; |z| = ε scanned on z's cubic Hermite interpolant, then bisected on the exact z(s).
    Returns (x_l, v_l, s, side (0: still in the gap), contact events (0 or 1))."""
    h = (1.0 - s) * Ts
    xa, da = _motor(cs, 0, s)
    xc, dc = _motor(cs, 0, 1.0)
    xn, vn = _gap_state(xl, vl, bj, h, cj, ivs, Ts)
    z0 = xa - xl
    z1 = xc - xn
    dz0 = (da / Ts - vl) * h
    dz1 = (dc / Ts - vn) * h
    hit = -1.0
    lo = 0.0
    jstart = 1
    if max(abs(z0), abs(z1)) + _HERMITE_BOUND * (abs(dz0) + abs(dz1)) < eps:
        jstart = _GRAZE_POINTS + 2
    for j in range(jstart, _GRAZE_POINTS + 2):
        u = j / (_GRAZE_POINTS + 1.0)
        zu = _hermite(z0, dz0, z1, dz1, u)
        if zu >= eps or zu <= -eps:
            hit = u
            break
        lo = u
    if hit < 0.0:
        return xn, vn, 1.0, 0.0, 0
    hi = hit
    zh = 0.0
    for it in range(_BISECT_ITERATIONS + 1):
        mid = hi if it == 0 else 0.5 * (lo + hi)
        xq, _ = _motor(cs, 0, s + mid * (1.0 - s))
        xlq, _ = _gap_state_at_event(xl, vl, bj, mid * h, cj, ivs, Ts)
        zq = xq - xlq
        if zq >= eps or zq <= -eps:
            hi = mid
            zh = zq
        elif it == 0:
            # the interpolant overshot the boundary but z does not: a near-graze that
            # the exact z misses; continue in the gap from there
            break
        else:
            lo = mid
    if zh == 0.0:
        xl, vl = _gap_state_at_event(xl, vl, bj, hit * h, cj, ivs, Ts)
        return xl, vl, s + hit * (1.0 - s), 0.0, 0
    xl, vl = _gap_state_at_event(xl, vl, bj, hi * h, cj, ivs, Ts)
    return xl, vl, s + hi * (1.0 - s), 1.0 if zh > 0.0 else -1.0, 1


@inlined  # (into the simulation's loop, as the steps it takes at every sample are into it)
def _interval(cs: NDArray[np.float64], Ts: float, xl: float, vl: float, side: float, eps: float, kj: float, dj: float,
              bj: float, cj: float, ivs: float, cm: NDArray[np.float64], friction: bool
              ) -> tuple[float, float, float, float, float, int]:
    """One sample interval (the motor ``cs``, (1, 4)) from the load state (xl, vl) in mode ``side`` (0: the
    gap), step by step to each contact or separation event. Returns (x_l, v_l, side at its end,
    ∫₀¹ y ds, ∫₀¹ s·y ds [rad], events)."""
    i0_sum = 0.0
    i1_sum = 0.0
    events = 0
    s = 0.0
    guard = 0
    while s < 1.0:
        guard += 1
        if guard > _MAX_PARTS:  # a diverged simulation: the rest of the interval is not integrated
            break
        if side != 0.0:
            xn, vn, i0, i1, send, p1, dp1e, implicit = _contact_step(cs, s, Ts, xl, vl, side, eps, kj, dj, bj,
                                                                     cj, ivs, cm, friction)
            separated = False
            if eps > 0.0:
                separated, send, xn, vn, i0, i1 = _separation(cs, s, send, Ts, xl, vl, side, eps, kj, dj, bj, cj,
                                                              ivs, xn, vn, i0, i1, p1, dp1e, implicit)
            i0_sum += i0
            i1_sum += i1
            xl = xn
            vl = vn
            s = send
            if separated:
                side = 0.0
                events += 1
        else:
            xl, vl, s, side, contact = _gap_step(cs, s, Ts, xl, vl, bj, cj, ivs, eps)
            events += contact
    return xl, vl, side, i0_sum, i1_sum, events


@njit(cache=True, nogil=True, error_model="numpy")
def _simulate_load(c: NDArray[np.float64], Ts: float, J_l: float, B_l: float, K: float, D: float,
                   eps: float, xl0: float, vl0: float, F_l: float, ivs: float, cm: NDArray[np.float64],
                   friction: bool, motor_part: NDArray[np.float64], gain: float,
                   lp: NDArray[np.float64], load_meas: NDArray[np.float64], load_gain: float
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
                              NDArray[np.float64], int, NDArray[np.float64], NDArray[np.float64]]:
    """Load driven by the spline motor position through the dead-zone spring, corrected after every
    sample by the observer (``gain`` = 0: open loop; module docstring).

    Returns (I0, I1, xl, vl, events, e, el): I0[k] = ∫₀¹ y(k+s) ds, I1[k] = ∫₀¹ s·y(k+s) ds over each
    of the N−1 sample intervals [rad]; xl, vl the load state at the N samples; events the number of
    contact/separation events located; e the motor-equation residual at samples 1 … N−2 [N·m],
    ``motor_part`` (J_m·Δ²x/Ts² + B_m·v (+ F_cm·sgn) − τ) + the triangle-averaged shaft torque; el the
    load position's prediction error x_l,sim − x_l,meas at samples 0 … N−1 before each correction
    [rad] (zeros without a load encoder).

    Observer: e_k is known once interval k is integrated (the triangle kernel spans k − 1 … k + 1);
    the causal biquad ``lp`` = (b0, b1, b2, a1, a2) filters it, and the correction ``gain``·ẽ_k
    (minus ``load_gain`` times the load-position error when ``load_meas`` has shape (N,), else (0,))
    is applied as a ramp on the motor position the load sees over the next interval: a jump of the
    load's position would switch modes without event location and kink the cost.

    Events. Separation: the penetration p = side·y is scanned on the step's cubic Hermite
    interpolant (interior points for grazes), bisected, then polished by Newton steps on the actual
    RK4 step length, so that the impact torque D·ẏ is switched off where the integrated trajectory
    really reaches the boundary. Contact: the load moves analytically and the motor is the spline,
    so |z| = ε is bisected on the exact z(s).
    """
    m = c.shape[0]
    I0 = np.zeros(m)
    I1 = np.zeros(m)
    xl_out = np.empty(m + 1)
    vl_out = np.empty(m + 1)
    E = np.zeros(m - 1)
    EL = np.zeros(m + 1)
    events = _load_loop(c, Ts, J_l, B_l, K, D, eps, xl0, vl0, F_l, ivs, cm, friction, motor_part, gain, lp, load_meas,
                        load_gain, I0, I1, xl_out, vl_out, E, EL, np.empty((1, 4)))
    return I0, I1, xl_out, vl_out, events, E, EL


@per_sample  # (the interval's steps inlined into it: one function, no calls, no reference counts)
def _load_loop(c: NDArray[np.float64], Ts: float, J_l: float, B_l: float, K: float, D: float, eps: float, xl0: float,
               vl0: float, F_l: float, ivs: float, cm: NDArray[np.float64], friction: bool,
               motor_part: NDArray[np.float64], gain: float, lp: NDArray[np.float64], load_meas: NDArray[np.float64],
               load_gain: float, I0: NDArray[np.float64], I1: NDArray[np.float64], xl_out: NDArray[np.float64],
               vl_out: NDArray[np.float64], E: NDArray[np.float64], EL: NDArray[np.float64],
               cs: NDArray[np.float64]) -> int:
    """:func:`_simulate_load`'s loop over the sample intervals, into its outputs (``cs``: scratch); returns the
    events located."""
    m = c.shape[0]
    kj = K / J_l
    dj = D / J_l
    bj = B_l / J_l
    cj = F_l / J_l
    xl = xl0
    vl = vl0
    z = _motor(c, 0, 0.0)[0] - xl
    side = 1.0 if eps <= 0.0 or z > eps else (-1.0 if z < -eps else 0.0)
    events = 0
    has_load = load_meas.shape[0] == m + 1
    w1 = 0.0
    w2 = 0.0
    offset = 0.0  # corrections applied so far [rad]: the load sits at xl + offset
    ramp = 0.0    # correction applied over the current interval [rad]
    for k in range(m):
        xl_out[k] = xl + offset
        vl_out[k] = vl
        # the motor as the load sees it: x_m − offset − ramp·s (the load moved by the corrections)
        cs[0, 0] = c[k, 0]
        cs[0, 1] = c[k, 1]
        cs[0, 2] = c[k, 2] - ramp
        cs[0, 3] = c[k, 3] - offset
        xl, vl, side, I0[k], I1[k], ev = _interval(cs, Ts, xl, vl, side, eps, kj, dj, bj, cj, ivs, cm, friction)
        events += ev
        offset += ramp
        ramp = 0.0
        if k >= 1:
            e = motor_part[k - 1] + K * (I1[k - 1] + I0[k] - I1[k]) + D * (I0[k] - I0[k - 1]) / Ts
            E[k - 1] = e
            if gain != 0.0:
                ef = lp[0] * e + w1
                w1 = lp[1] * e - lp[3] * ef + w2
                w2 = lp[2] * e - lp[4] * ef
                ramp = gain * ef
        if has_load:
            EL[k + 1] = xl + offset - load_meas[k + 1]
            ramp -= load_gain * EL[k + 1]
    xl_out[m] = xl + offset
    vl_out[m] = vl
    return events


@njit(cache=True, nogil=True, error_model="numpy")
def _sosfilt_inplace(sos: NDArray[np.float64], zi: NDArray[np.float64], x: NDArray[np.float64],
                     forward: bool) -> None:
    """Direct-form-II-transposed second-order sections over x, in place, initial state zi·x[first]."""
    n = x.shape[0]
    ns = sos.shape[0]
    x0 = x[0] if forward else x[n - 1]
    if ns == 2:  # the default 4th-order filter: the same arithmetic on scalar states (faster)
        _sos2_inplace(sos, zi, x, forward, x0)
        return
    z1 = np.empty(ns)
    z2 = np.empty(ns)
    for i in range(ns):
        z1[i] = zi[i, 0] * x0
        z2[i] = zi[i, 1] * x0
    for jj in range(n):
        j = jj if forward else n - 1 - jj
        v = x[j]
        for i in range(ns):
            y = sos[i, 0] * v + z1[i]
            z1[i] = sos[i, 1] * v - sos[i, 4] * y + z2[i]
            z2[i] = sos[i, 2] * v - sos[i, 5] * y
            v = y
        x[j] = v


@njit(cache=True, nogil=True, error_model="numpy")
def _sos2_inplace(sos: NDArray[np.float64], zi: NDArray[np.float64], x: NDArray[np.float64],
                  forward: bool, x0: float) -> None:
    """:func:`_sosfilt_inplace` for two sections, states in scalars (same operations, same order)."""
    n = x.shape[0]
    b00, b01, b02, a01, a02 = sos[0, 0], sos[0, 1], sos[0, 2], sos[0, 4], sos[0, 5]
    b10, b11, b12, a11, a12 = sos[1, 0], sos[1, 1], sos[1, 2], sos[1, 4], sos[1, 5]
    p1 = zi[0, 0] * x0
    p2 = zi[0, 1] * x0
    q1 = zi[1, 0] * x0
    q2 = zi[1, 1] * x0
    for jj in range(n):
        j = jj if forward else n - 1 - jj
        v = x[j]
        y = b00 * v + p1
        p1 = b01 * v - a01 * y + p2
        p2 = b02 * v - a02 * y
        v = y
        y = b10 * v + q1
        q1 = b11 * v - a11 * y + q2
        q2 = b12 * v - a12 * y
        x[j] = y


@njit(cache=True, nogil=True, error_model="numpy")
def _filtfilt_decimate(sos: NDArray[np.float64], zi: NDArray[np.float64], x: NDArray[np.float64],
                       padlen: int, step: int) -> NDArray[np.float64]:
    """scipy.signal.sosfiltfilt(sos, x)[::step] (odd padding, same initial conditions)."""
    n = x.shape[0]
    ext = np.empty(n + 2 * padlen)
    for i in range(padlen):
        ext[i] = 2.0 * x[0] - x[padlen - i]
        ext[n + padlen + i] = 2.0 * x[n - 1] - x[n - 2 - i]
    ext[padlen:padlen + n] = x
    _sosfilt_inplace(sos, zi, ext, True)
    _sosfilt_inplace(sos, zi, ext, False)
    m = (n + step - 1) // step
    out = np.empty(m)
    for i in range(m):
        out[i] = ext[padlen + i * step]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _shaft_torque_tri(I0: NDArray[np.float64], I1: NDArray[np.float64], K: float, D: float,
                      Ts: float) -> NDArray[np.float64]:
    """Triangle-kernel average of τ_s = K·y + D·ẏ at samples 1 … N−2 (length N−2)."""
    m = I0.shape[0]
    out = np.empty(m - 1)
    for k in range(1, m):
        out[k - 1] = K * (I1[k - 1] + I0[k] - I1[k]) + D * (I0[k] - I0[k - 1]) / Ts
    return out


# --- public API --------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ResidualProblem:
    """Everything about one recording the residual needs, computed once.

    Arrays indexed by the residual's samples k = 1 … N−2 (length N−2) unless stated.
    """

    sample_rate_hz: float  # [Hz]
    spline: NDArray[np.float64]  # motor-position cubic per interval, s ∈ [0, 1] (N−1, 4)
    acceleration: NDArray[np.float64]  # (x[k+1] − 2x[k] + x[k−1]) / Ts² [rad/s²]
    velocity: NDArray[np.float64]  # (x[k+1] − x[k−1]) / (2·Ts) [rad/s]
    torque: NDArray[np.float64]  # (τ_ref[k−1] + τ_ref[k]) / 2 [N·m]
    sos: NDArray[np.float64]  # zero-phase low-pass of the residual (second-order sections)
    cutoff_hz: float  # its cut-off [Hz]
    decimation: int  # keep every decimation-th filtered sample (≈ independent samples)
    zi: NDArray[np.float64]  # steady-state initial conditions of the sections (sosfilt_zi)
    padlen: int  # odd-extension length at each end (as scipy.signal.sosfiltfilt)
    initial_twist_rad: float  # x_m − x_l at sample 0 [rad] (0: at rest, centred in the gap)
    load_position: NDArray[np.float64] | None  # measured, samples 0 … N−1 [rad]; None: no encoder
    # pre-filtered, decimated regressors of the motor equation
    acceleration_f: NDArray[np.float64]
    velocity_f: NDArray[np.float64]
    torque_f: NDArray[np.float64]
    coulomb: NDArray[np.float64] | None = None  # tanh(ẋ_m/v_s), triangle-averaged, 1 … N−2 [-]
    coulomb_f: NDArray[np.float64] | None = None  # the same low-passed, decimated: F_cm's column
    #: Low-passed, decimated Δτ_ref/Ts [N·m/s]: the current-loop-lag column (τ ≈ τ_ref − T_c·τ̇_ref),
    #: which starts T_c by linear projection.
    torque_rate_f: NDArray[np.float64] | None = None
    torque_ref: NDArray[np.float64] | None = None  # raw, samples 0 … N−1 [N·m], for lagged_torque
    velocity_scale_rad_s: float = 2e-3  # v_s of both Coulomb terms' smooth sign tanh(v/v_s) [rad/s]
    #: Weight (1 or 0) of each decimated motor-block sample: 0 where a sample the link lost reaches
    #: the residual through the triangle kernel and the low-pass (None: every sample counts).
    keep: NDArray[np.float64] | None = None
    #: How the motor (and the load with it) moves at sample 0: at rest, but in a record cut from a longer one.
    start: InitialMotion = field(default_factory=InitialMotion)

    @property
    def n_samples(self) -> int:
        """Samples of the recording (N)."""
        return int(self.spline.shape[0] + 1)

    def lagged_torque_f(self, lag_s: float) -> NDArray[np.float64]:
        """Low-passed, decimated motor torque behind a first-order current loop of time
        constant ``lag_s`` [s] (``torque_f`` for 0), see :func:`lagged_torque`."""
        if lag_s <= 0.0 or self.torque_ref is None:
            return self.torque_f
        return self.lowpass(lagged_torque(self.torque_ref, self.sample_rate_hz, lag_s))

    def lowpass(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Zero-phase low-pass, then decimation (the same operator as the residual's)."""
        return _filtfilt_decimate(self.sos, self.zi, np.ascontiguousarray(x, dtype=np.float64),
                                  self.padlen, self.decimation)


@dataclass(frozen=True, eq=False)
class LoadSimulation:
    """The simulated load of one residual evaluation."""

    shaft_torque: NDArray[np.float64]  # triangle-averaged K·y + D·ẏ at samples 1 … N−2 [N·m]
    load_position: NDArray[np.float64]  # simulated, samples 0 … N−1 [rad]
    load_velocity: NDArray[np.float64]  # simulated, samples 0 … N−1 [rad/s]
    events: int  # contact and separation events located inside steps
    residual: NDArray[np.float64]  # motor equation at 1 … N−2 [N·m] (shaft torque if no motor part)
    load_error: NDArray[np.float64]  # with a load encoder: x_l,sim − x_l,meas, 0 … N−1 [rad]


@dataclass(frozen=True, eq=False)
class Residual:
    """Result of :func:`torque_residual`."""

    residual: NDArray[np.float64]  # low-passed (not decimated), samples 1 … N−2 [N·m]
    vector: NDArray[np.float64]  # decimated, fed to least squares (motor, then load block) [N·m]
    cost: float  # RMS of vector [N·m]
    simulation: LoadSimulation


def motor_position_samples(motor_position: NDArray[np.float64] | None, motor_velocity: NDArray[np.float64] | None,
                           sample_rate_hz: float) -> NDArray[np.float64]:
    """The motor position [rad], shape (N,): as latched, or rebuilt exactly from the
    backward-difference velocity (x[k] = x[k−1] + Ts·v[k], x[0] = 0) when there is none."""
    if motor_position is not None:
        return np.asarray(motor_position, dtype=np.float64)
    if motor_velocity is not None:
        v = np.asarray(motor_velocity, dtype=np.float64)
        return np.concatenate(([0.0], np.cumsum(v[1:]) / float(sample_rate_hz)))
    raise IdentificationError("the torque residual needs the motor position or velocity")


def prepare_residual(
    torque_ref: NDArray[np.float64],
    sample_rate_hz: float,
    *,
    motor_position: NDArray[np.float64] | None = None,
    motor_velocity: NDArray[np.float64] | None = None,
    cutoff_hz: float = 300.0,
    filter_order: int = 4,
    load_position: NDArray[np.float64] | None = None,
    initial_twist_rad: float | None = None,
    velocity_scale_rad_s: float = 2e-3,
    interpolation: str = "local",
    lost: NDArray[np.bool_] | None = None,
) -> ResidualProblem:
    """Precompute the motor-side regressors of the torque residual.

    :param torque_ref: torque reference [N·m], shape (N,).
    :param sample_rate_hz: sample rate [Hz].
    :param motor_position: latched motor position [rad]; if absent it is rebuilt exactly from the
        backward-difference velocity (x[k] = x[k−1] + Ts·v[k], x[0] = 0).
    :param motor_velocity: backward-difference motor velocity [rad/s] (used only without position).
    :param cutoff_hz: low-pass cut-off of the residual [Hz].
    :param filter_order: Butterworth order (applied twice, forward and backward).
    :param load_position: measured load position [rad]; adds a second residual block
        K̂·(x_l,sim − x_l,meas) and fixes the initial twist.
    :param initial_twist_rad: x_m − x_l at sample 0 [rad]; default from the load encoder, else 0.
    :param velocity_scale_rad_s: v_s of the Coulomb terms' smooth sign tanh(v/v_s) [rad/s].
    :param interpolation: motor position between samples (:func:`motor_interpolant`):
        "local" (default) or "spline".
    :param lost: (N,) true at samples a streamed link lost (interpolated in the record): the residual
        samples they reach are left out (:attr:`ResidualProblem.keep`).
    """
    tau = np.asarray(torque_ref, dtype=np.float64)
    n = tau.shape[0]
    fs = float(sample_rate_hz)
    x = motor_position_samples(motor_position, motor_velocity, fs)
    if x.shape[0] != n or n < 16:
        raise IdentificationError(f"the torque residual needs ≥ 16 aligned samples, got {n}")
    if not 0.0 < cutoff_hz < 0.5 * fs:
        raise IdentificationError(f"residual cut-off {cutoff_hz} Hz must lie in (0, {0.5 * fs}) Hz")
    x = x - x[0]
    spline = motor_interpolant(x, interpolation)
    acc = (x[2:] - 2.0 * x[1:-1] + x[:-2]) * fs * fs
    vel = (x[2:] - x[:-2]) * (0.5 * fs)
    trq = 0.5 * (tau[:-2] + tau[1:-1])
    sos = butter(filter_order, cutoff_hz, fs=fs, output="sos")
    decimation = max(1, int(fs / (2.0 * cutoff_hz)))
    zi = sosfilt_zi(sos)
    padlen = 3 * (2 * sos.shape[0] + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum())))
    lp = lambda a: _filtfilt_decimate(sos, zi, a, padlen, decimation)  # noqa: E731
    xl, twist0 = _load_origin(load_position, motor_position, n)
    if initial_twist_rad is not None:
        twist0 = float(initial_twist_rad)
    if not velocity_scale_rad_s > 0.0:
        raise IdentificationError(f"velocity scale {velocity_scale_rad_s} rad/s must be positive")
    coul = _coulomb_average(spline, fs, velocity_scale_rad_s)
    rate = np.diff(tau)[:-1] * fs  # (τ_ref[k] − τ_ref[k−1])/Ts at samples 1 … N−2
    keep = None
    if lost is not None and np.any(lost):
        # a lost sample reaches the residual at k − 1 … k + 1 and the low-pass spreads it by ~2/f_c
        reach = int(math.ceil(2.0 * fs / cutoff_hz)) + 1
        hit = np.convolve(np.asarray(lost, dtype=float), np.ones(2 * reach + 1), mode="same") > 0
        keep = np.ascontiguousarray((~hit[1:-1][::decimation]).astype(float))
    return ResidualProblem(
        sample_rate_hz=fs, spline=spline, acceleration=acc, velocity=vel, torque=trq,
        sos=sos, cutoff_hz=float(cutoff_hz), decimation=decimation, zi=zi, padlen=padlen, initial_twist_rad=twist0,
        load_position=xl,
        acceleration_f=lp(acc), velocity_f=lp(vel), torque_f=lp(trq),
        coulomb=coul, coulomb_f=lp(np.ascontiguousarray(coul)), torque_rate_f=lp(np.ascontiguousarray(rate)),
        torque_ref=np.ascontiguousarray(tau), velocity_scale_rad_s=float(velocity_scale_rad_s), keep=keep,
        start=initial_motion(x, fs),
    )


def _load_origin(load_position: NDArray[np.float64] | None, motor_position: NDArray[np.float64] | None,
                 n: int) -> tuple[NDArray[np.float64] | None, float]:
    """The load position [rad] from the motor's origin (shape (N,), None without one) and the twist at
    sample 0 [rad] it shows."""
    if load_position is None:
        return None, 0.0
    xl = np.asarray(load_position, dtype=np.float64)
    if xl.shape[0] != n:
        raise IdentificationError("load position and motor position differ in length")
    if motor_position is None:  # motor rebuilt from velocity: no common origin, assume centred gears
        return np.ascontiguousarray(xl - xl[0]), 0.0
    x_m0 = float(np.asarray(motor_position, dtype=np.float64)[0])
    return np.ascontiguousarray(xl - x_m0), x_m0 - float(xl[0])


def _coulomb_average(spline: NDArray[np.float64], fs: float, velocity_scale_rad_s: float) -> NDArray[np.float64]:
    """The motor Coulomb regressor at samples 1 … N−2: the triangle average of tanh(ẋ_m/v_s) with ẋ_m
    from the position's cubic ``spline`` (N−1, 4), by 8-point Gauss–Legendre per sample interval (a
    reversal inside an interval is then weighted where it happens, not at the interval's chord velocity)."""
    gx, gw = np.polynomial.legendre.leggauss(8)
    sq = 0.5 * (gx + 1.0)
    vq = ((3.0 * spline[:, 0:1] * sq + 2.0 * spline[:, 1:2]) * sq + spline[:, 2:3]) * fs
    sgn = np.tanh(vq / velocity_scale_rad_s)
    w_up = 0.5 * gw * sq          # ∫ s·f(s) ds on [0, 1]: the interval before sample k
    w_dn = 0.5 * gw * (1.0 - sq)  # ∫ (1 − s)·f(s) ds: the interval after sample k
    return sgn[:-1] @ w_up + sgn[1:] @ w_dn


def motor_interpolant(x: NDArray[np.float64], interpolation: str = "local") -> NDArray[np.float64]:
    """Cubic coefficients (N−1, 4) of the motor position on each sample interval, s ∈ [0, 1].

    ``"spline"``: the not-a-knot cubic spline (C², error O(Ts⁴) on smooth motion). It is
    *global*: at an impact the motor acceleration jumps (D·ẏ switches) and the spline spreads
    that kink over many samples (ringing, decaying ×0.27 per sample), biasing the simulated
    load around every impact. ``"local"`` (the default): cubic Hermite with central-difference
    slopes (Catmull–Rom, C¹, error O(Ts³)): a kink disturbs only the two intervals beside it.
    """
    n = x.shape[0]
    if interpolation == "spline":
        cs = CubicSpline(np.arange(n, dtype=np.float64), x)
        return np.ascontiguousarray(cs.c.T)
    if interpolation != "local":
        raise IdentificationError(f"unknown motor interpolation {interpolation!r}")
    m = np.gradient(x)  # per sample; one-sided at the ends
    x0, x1, m0, m1 = x[:-1], x[1:], m[:-1], m[1:]
    return np.ascontiguousarray(np.stack(
        (2.0 * (x0 - x1) + m0 + m1, 3.0 * (x1 - x0) - 2.0 * m0 - m1, m0, x0), axis=1))


def lagged_torque(torque_ref: NDArray[np.float64], sample_rate_hz: float,
                  lag_s: float) -> NDArray[np.float64]:
    """Triangle-kernel average (see the module docstring) of the motor torque behind a
    first-order current loop, T_c·τ̇ = τ_ref − τ, τ_ref held over each sample, τ(0) = τ_ref[0],
    at samples 1 … N−2 [N·m]. Exact: within sample k, τ(k+s) = u_k + d_k·e^{−αs},
    α = Ts/T_c, d_k = τ(k) − u_k, so the kernel integrals are closed forms in α.
    ``lag_s`` = 0 gives (τ_ref[k−1] + τ_ref[k])/2, the ideal loop.
    """
    u = np.asarray(torque_ref, dtype=np.float64)
    if lag_s <= 0.0:
        return 0.5 * (u[:-2] + u[1:-1])
    a = (1.0 / sample_rate_hz) / lag_s
    e = math.exp(-a)
    if a < 1e-4:  # series: g1 = ∫s e^{−as} = 1/2 − a/3, g2 = ∫(1−s)e^{−as} = 1/2 − a/6
        g1, g2 = 0.5 - a / 3.0, 0.5 - a / 6.0
    else:
        g1 = (1.0 - (1.0 + a) * e) / (a * a)
        g2 = (a - 1.0 + e) / (a * a)
    # τ_{k+1} = e·τ_k + (1 − e)·u_k, τ_0 = u_0 (compiled; the arithmetic of
    # scipy.signal.lfilter([0, 1 − e], [1, −e], u, zi=[u_0]) and of the array expression
    # 0.5·(u[:-2] + u[1:-1]) + g1·d[:-2] + g2·d[1:-1], d = τ − u, operation for operation)
    return _lagged_torque(read_only(u), e, g1, g2)


@njit(cache=True, nogil=True, error_model="numpy")
def _lagged_torque(u: NDArray[np.float64], e: float, g1: float, g2: float) -> NDArray[np.float64]:
    n = u.shape[0]
    b1 = 1.0 - e
    a1 = -e
    out = np.empty(n - 2)
    z = u[0]
    d_prev = 0.0
    for k in range(n - 1):
        t = 0.0 * u[k] + z
        z = b1 * u[k] - a1 * t
        d = t - u[k]
        if k >= 1:
            out[k - 1] = 0.5 * (u[k - 1] + u[k]) + g1 * d_prev + g2 * d
        d_prev = d
    return out


@dataclass(frozen=True, eq=False)
class Observer:
    """The load-state observer of the residual (module docstring; gain 0: open loop).

    The residual is then the one-step prediction error of a fixed-gain predictor whose state is the
    load's, the estimator a prediction-error method (Ljung, *System Identification*, ch. 7). The
    low-pass keeps the encoder's quantization noise out of the correction. The gain is fixed for a
    fit, from a bandwidth and the start's K and D: as a parameter the fit would take the largest,
    since a stronger correction always lowers the residual.
    """

    gain_rad_per_nm: float = 0.0  # load-position correction per N·m of filtered residual
    #: Causal biquad on the residual before the correction: (b0, b1, b2, a1, a2).
    lowpass: NDArray[np.float64] = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0, 0.0]))
    bandwidth_hz: float = 0.0  # 1 − exp(−2π·bandwidth/fs) of a twist error is removed per sample
    filter_hz: float | None = None  # cut-off of the low-pass on the residual [Hz] (None: none)
    load_gain: float = 0.0  # with a load encoder: fraction of the way to its position per sample

    @classmethod
    def design(cls, sample_rate_hz: float, bandwidth_hz: float, filter_hz: float | None, K: float,
               D: float, load_encoder: bool = False) -> Observer:
        """An observer removing 1 − exp(−2π·bandwidth/fs) of a twist error per sample.

        A load-position step δ changes the next residual by (K + D·fs)·δ — the damping's share
        through the triangle-averaged twist rate — so the gain is that fraction over K + D·fs:
        normalised by K alone the correction is unstable on damped, soft plants (D·fs ≫ K).
        """
        fs = float(sample_rate_hz)
        alpha = 1.0 - math.exp(-2.0 * math.pi * bandwidth_hz / fs) if bandwidth_hz > 0 else 0.0
        lp = np.array([1.0, 0.0, 0.0, 0.0, 0.0])
        if filter_hz is not None and filter_hz < 0.45 * fs:
            b, a = butter(2, filter_hz, fs=fs)
            lp = np.array([b[0], b[1], b[2], a[1], a[2]])
        else:
            filter_hz = None
        return cls(gain_rad_per_nm=alpha / (float(K) + float(D) * fs), lowpass=lp,
                   bandwidth_hz=float(bandwidth_hz), filter_hz=filter_hz,
                   load_gain=alpha if load_encoder else 0.0)


#: The open-loop load simulation.
OPEN_LOOP = Observer()
_NONE = np.zeros(0)


def motor_part(problem: ResidualProblem, J_m: float, B_m: float, *, coulomb_motor_nm: float = 0.0,
               lag_s: float = 0.0) -> NDArray[np.float64]:
    """J_m·Δ²x_m/Ts² + B_m·v_m + F_cm·sgn(v_m) − τ at samples 1 … N−2 [N·m]: the motor equation
    without the shaft torque (τ: the torque behind a first-order current loop of time constant
    ``lag_s`` [s], see :func:`lagged_torque`)."""
    trq = problem.torque if lag_s <= 0.0 or problem.torque_ref is None else \
        lagged_torque(problem.torque_ref, problem.sample_rate_hz, lag_s)
    out = J_m * problem.acceleration + B_m * problem.velocity - trq
    if coulomb_motor_nm != 0.0 and problem.coulomb is not None:
        out = out + coulomb_motor_nm * problem.coulomb
    return np.ascontiguousarray(out)


def simulate_load(problem: ResidualProblem, J_l: float, B_l: float, K: float, D: float,
                  epsilon_rad: float, coulomb_load_nm: float | None = None, *,
                  motor: NDArray[np.float64] | None = None, observer: Observer = OPEN_LOOP) -> LoadSimulation:
    """Simulate the load driven by the measured motor position (see module docstring).

    :param coulomb_load_nm: load-side Coulomb friction F_cl [N·m], as F_cl·tanh(ẋ_l/v_s)
        (v_s: the problem's stated velocity scale); None: not modelled. Whole contact intervals
        are exact without the term; with it, at any value, 0 included, they are exact where the
        load moves faster than ``_SATURATED``·v_s (the smooth sign is then ±1, the friction a
        constant force) and RK4 elsewhere — a choice made by the load's speed, not by F_cl, so the
        simulation is one smooth function of F_cl down to its bound 0, as finite differences need.
    :param motor: :func:`motor_part` (N−2,); needed by an observer, and gives the residual.
    :param observer: the load-state correction (default: none, open loop).
    """
    Ts = 1.0 / problem.sample_rate_hz
    xl0 = -problem.initial_twist_rad  # motor position is shifted to start at 0
    if problem.start.moving and problem.load_position is None:
        xl0 = -problem.start.twist_rad(float(J_l), float(B_l), float(K), max(float(epsilon_rad), 0.0))
    F_l = 0.0 if coulomb_load_nm is None else float(coulomb_load_nm)
    ivs = 1.0 / problem.velocity_scale_rad_s
    gain = observer.gain_rad_per_nm
    if motor is None:
        if gain != 0.0:
            raise ValueError("an observer needs the motor part of the residual")
        motor = np.zeros(problem.n_samples - 2)
    cm = contact_map(Ts, float(K) / float(J_l), float(D) / float(J_l), float(B_l) / float(J_l))
    load = problem.load_position if problem.load_position is not None and observer.load_gain != 0.0 else _NONE
    I0, I1, xl, vl, events, e, el = _simulate_load(problem.spline, Ts, float(J_l), float(B_l), float(K), float(D),
                                                   max(float(epsilon_rad), 0.0), xl0, problem.start.speed_rad_s,
                                                   F_l, ivs, cm,
                                                   coulomb_load_nm is not None, motor, float(gain), observer.lowpass,
                                                   load, float(observer.load_gain))
    ts = _shaft_torque_tri(I0, I1, float(K), float(D), Ts)
    if load.shape[0] == 0 and problem.load_position is not None:
        el = xl - problem.load_position
    return LoadSimulation(shaft_torque=ts, load_position=xl, load_velocity=vl, events=int(events), residual=e,
                          load_error=el)


def torque_residual(problem: ResidualProblem, J_m: float, J_l: float, B_m: float, B_l: float,
                    K: float, D: float, epsilon_rad: float, *,
                    load_weight_nm_per_rad: float | None = None, coulomb_motor_nm: float = 0.0,
                    coulomb_load_nm: float | None = None, lag_s: float = 0.0,
                    observer: Observer = OPEN_LOOP) -> Residual:
    """r = J_m·Δ²x_m/Ts² + B_m·v_m + F_cm·tanh(v_m/v_s) + τ_s(sim) − τ(τ_ref), low-passed
    zero-phase, and its RMS cost.

    :param load_weight_nm_per_rad: weight of the load-position block when the problem has a
        load encoder (default K: a load-position error then counts as the shaft torque it implies).
    :param coulomb_motor_nm: motor-side Coulomb friction F_cm [N·m].
    :param coulomb_load_nm: load-side Coulomb friction F_cl [N·m] (in the load simulation;
        None: not modelled, see :func:`simulate_load`).
    :param lag_s: time constant T_c = 1/ω_c of a first-order current loop [s] (0: ideal).
    :param observer: the load-state correction (:class:`Observer`; default none).
    """
    motor = motor_part(problem, J_m, B_m, coulomb_motor_nm=coulomb_motor_nm, lag_s=lag_s)
    sim = simulate_load(problem, J_l, B_l, K, D, epsilon_rad, coulomb_load_nm, motor=motor, observer=observer)
    vec = _vector(problem, sim, K, load_weight_nm_per_rad)
    res = sosfiltfilt(problem.sos, sim.residual)
    with np.errstate(over="ignore"):  # a diverged simulation's cost is inf, as it should be
        cost = float(np.sqrt(np.mean(vec * vec)))
    return Residual(residual=res, vector=vec, cost=cost, simulation=sim)


def residual_vector(problem: ResidualProblem, J_m: float, J_l: float, B_m: float, B_l: float,
                    K: float, D: float, epsilon_rad: float, *,
                    load_weight_nm_per_rad: float | None = None, coulomb_motor_nm: float = 0.0,
                    coulomb_load_nm: float | None = None, lag_s: float = 0.0,
                    observer: Observer = OPEN_LOOP) -> NDArray[np.float64]:
    """Only the decimated residual vector of :func:`torque_residual` (the fast path for fits)."""
    motor = motor_part(problem, J_m, B_m, coulomb_motor_nm=coulomb_motor_nm, lag_s=lag_s)
    sim = simulate_load(problem, J_l, B_l, K, D, epsilon_rad, coulomb_load_nm, motor=motor, observer=observer)
    return _vector(problem, sim, K, load_weight_nm_per_rad)


def _vector(problem: ResidualProblem, sim: LoadSimulation, K: float,
            load_weight_nm_per_rad: float | None) -> NDArray[np.float64]:
    vec = problem.lowpass(sim.residual)
    if problem.load_position is not None:
        w = float(K if load_weight_nm_per_rad is None else load_weight_nm_per_rad)
        vec = np.concatenate((vec, w * sim.load_error[1:-1:problem.decimation]))
    return vec
