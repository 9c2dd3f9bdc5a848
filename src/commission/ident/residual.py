"""The drift-free torque residual of the motor equation (METHOD.md, "What works" 1–3).

Instead of simulating the whole two-mass system open loop from τ_ref (which
drifts: a 1 % DC-gain error moves the motor ~0.2 rad/s), the *load* alone is
simulated, driven through the dead-zone spring by the *measured* motor
position. The motor equation is then checked as a torque balance::

    r = J_m·ẍ_m + B_m·ẋ_m + τ_s(sim) − τ_ref          [N·m]

Nothing integrates open loop (the spring ties the simulated load to the real
motor), so the residual has no drift, and its minimum in ε is sharp.

Sample alignment (derived, not tuned)
-------------------------------------
Data convention of the drive: at tick k the encoder is latched, x[k] = x_m(k·Ts),
v[k] = (x[k] − x[k−1])/Ts, then τ_ref[k] is applied by a zero-order hold over
[k·Ts, (k+1)·Ts). Integrating ẍ twice against the triangle kernel
w(s) = 1 − |s| on s ∈ [−1, 1] (time k·Ts + s·Ts) gives the exact identity::

    (x[k+1] − 2x[k] + x[k−1]) / Ts² = ∫ w(s)·ẍ_m(k+s) ds

so every term of the motor equation is averaged with the same kernel:

* τ_ref (ZOH):  ∫ w·τ_ref = (τ_ref[k−1] + τ_ref[k]) / 2          (exact)
* B_m·ẋ_m:      ∫ w·ẋ_m  ≈ (x[k+1] − x[k−1]) / (2·Ts)             (O(Ts²·ẍ'))
* τ_s = K·y + D·ẏ:  ∫ w·y from integrals of y the simulation accumulates over
  each sample interval, and ∫ w·ẏ = (ȳ_k − ȳ_{k−1})/Ts by parts (y is continuous
  across contact and separation, so the impact torque D·ẏ is integrated exactly).

This is the "one sample of delay" of METHOD.md handled in the time domain: half
a sample from the ZOH (τ_ref[k−1] and τ_ref[k] both act on x[k±1]) and the
backward-difference velocity is not used at all (positions are).

Load simulation
---------------
The motor position between samples is a cubic spline through the latched
positions. The load state (x_l, v_l) is integrated with one RK4 step per sample
while the gears are in contact, and analytically (viscous decay) in the gap.
Contact and separation are located inside the step (Hermite interpolation of
the gap variable, checked at interior points so that grazing contacts are
found, then bisection), so the residual is a smooth function of ε and of the
load parameters — a requirement for finite-difference Jacobians.

Filtering
---------
The second difference of a quantised position is blue noise. The residual is
low-passed zero-phase (Butterworth, ``scipy.signal.sosfiltfilt``) and then
decimated to about twice the cut-off, so that its samples are roughly
independent (the effective degrees of freedom used for intervals in
:mod:`commission.ident.jointfit`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline
from scipy.signal import butter, sosfilt_zi, sosfiltfilt

from ..exceptions import IdentificationError

__all__ = [
    "ResidualProblem",
    "Residual",
    "LoadSimulation",
    "prepare_residual",
    "simulate_load",
    "torque_residual",
    "residual_vector",
]

#: Interior points checked per step (and per remaining part of a step) for grazing events.
_GRAZE_POINTS = 4
_BISECT_ITERATIONS = 40
#: max over u ∈ [0, 1] of the Hermite basis functions of the end slopes (4/27), a bit more.
_HERMITE_BOUND = 0.15


# ----------------------------------------------------------------------------
# compiled core (module level so that numba's cache=True works)
# ----------------------------------------------------------------------------
@njit(cache=True, nogil=True, inline="always")
def _motor(c: NDArray[np.float64], k: int, s: float) -> tuple[float, float]:
    """Motor position [rad] and d/ds [rad per sample] at k + s from spline coefficients c (N−1, 4)."""
    a3 = c[k, 0]
    a2 = c[k, 1]
    a1 = c[k, 2]
    a0 = c[k, 3]
    return ((a3 * s + a2) * s + a1) * s + a0, (3.0 * a3 * s + 2.0 * a2) * s + a1


@njit(cache=True, nogil=True, inline="always")
def _hermite(y0: float, d0: float, y1: float, d1: float, u: float) -> float:
    """Cubic Hermite on u ∈ [0, 1] with end values y and end slopes d (per unit u)."""
    u2 = u * u
    u3 = u2 * u
    return ((2 * u3 - 3 * u2 + 1) * y0 + (u3 - 2 * u2 + u) * d0
            + (-2 * u3 + 3 * u2) * y1 + (u3 - u2) * d1)


@njit(cache=True, nogil=True, inline="always")
def _gap_state(xl: float, vl: float, decay: float, ts: float) -> tuple[float, float]:
    """Load position and velocity after ts seconds of free viscous decay (rate decay = B_l/J_l)."""
    if decay * ts < 1e-9:
        return xl + vl * ts, vl
    e = np.exp(-decay * ts)
    return xl + vl * (1.0 - e) / decay, vl * e


@njit(cache=True, nogil=True, inline="always")
def _accel(xm: float, vm: float, xl: float, vl: float, side: float, eps: float,
           kj: float, dj: float, bj: float) -> tuple[float, float]:
    """(y, load acceleration) in contact; kj = K/J_l, dj = D/J_l, bj = B_l/J_l."""
    y = xm - xl - side * eps
    return y, kj * y + dj * (vm - vl) - bj * vl


@njit(cache=True, nogil=True)
def _rk4_contact(c: NDArray[np.float64], k: int, s: float, se: float, Ts: float, xl: float, vl: float,
                 side: float, eps: float, kj: float, dj: float, bj: float
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
    y1, a1 = _accel(xa, va, xl, vl, side, eps, kj, dj, bj)
    x2 = xl + 0.5 * h * vl
    v2 = vl + 0.5 * h * a1
    y2, a2 = _accel(xb, vb, x2, v2, side, eps, kj, dj, bj)
    x3 = xl + 0.5 * h * v2
    v3 = vl + 0.5 * h * a2
    y3, a3 = _accel(xb, vb, x3, v3, side, eps, kj, dj, bj)
    x4 = xl + h * v3
    v4 = vl + h * a3
    y4, a4 = _accel(xc, vc, x4, v4, side, eps, kj, dj, bj)
    xn = xl + h / 6.0 * (vl + 2.0 * v2 + 2.0 * v3 + v4)
    vn = vl + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    ds = se - s
    i0 = ds / 6.0 * (y1 + 2.0 * y2 + 2.0 * y3 + y4)
    i1 = ds / 6.0 * (s * y1 + sm * (2.0 * y2 + 2.0 * y3) + se * y4)
    pe = side * (xc - xn - side * eps)
    dpe = side * (vc - vn) * Ts
    return xn, vn, i0, i1, pe, dpe


@njit(cache=True, nogil=True)
def _simulate_load(c: NDArray[np.float64], Ts: float, J_l: float, B_l: float, K: float, D: float,
                   eps: float, xl0: float, vl0: float
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int]:
    """Load driven by the spline motor position through the dead-zone spring.

    Returns (I0, I1, xl, vl, events): I0[k] = ∫₀¹ y(k+s) ds, I1[k] = ∫₀¹ s·y(k+s) ds over each of
    the N−1 sample intervals [rad]; xl, vl the load state at the N samples; events the number of
    contact/separation events located.

    Events. Separation (contact → gap): the penetration p = side·y is scanned on the cubic
    Hermite interpolant of the RK4 step (end values and slopes, interior points for grazing), the
    first root is bracketed and bisected on the interpolant, then polished by Newton steps on the
    *actual* RK4 step length (p and dp/ds of the RK4 solution), so the switch happens where the
    integrated trajectory really reaches the boundary (matters for stiff, impact-rich plants:
    the impact torque D·ẏ is switched off there). Contact (gap → contact): the load moves
    analytically and the motor is the spline, so |z| = ε is bisected on the exact z(s).
    """
    m = c.shape[0]
    I0 = np.zeros(m)
    I1 = np.zeros(m)
    xl_out = np.empty(m + 1)
    vl_out = np.empty(m + 1)
    kj = K / J_l
    dj = D / J_l
    bj = B_l / J_l
    xl = xl0
    vl = vl0
    xm, _ = _motor(c, 0, 0.0)
    z = xm - xl
    side = 0.0
    if eps <= 0.0:
        side = 1.0
    elif z > eps:
        side = 1.0
    elif z < -eps:
        side = -1.0
    events = 0
    for k in range(m):
        xl_out[k] = xl
        vl_out[k] = vl
        s = 0.0
        guard = 0
        while s < 1.0:
            guard += 1
            if guard > 50:  # pathological chattering: finish the step in the current mode
                break
            h = (1.0 - s) * Ts
            if side != 0.0:
                # --- contact: one RK4 step (plus quadrature of y and s·y) to the end of the interval
                xn, vn, i0, i1, p1, dp1e = _rk4_contact(c, k, s, 1.0, Ts, xl, vl, side, eps, kj, dj, bj)
                if eps > 0.0:
                    xa, da = _motor(c, k, s)
                    p0 = side * (xa - xl - side * eps)
                    dp0 = side * (da / Ts - vl) * h
                    dp1 = dp1e * (1.0 - s)
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
                    if hit > 0.0:
                        hi = hit
                        for _ in range(_BISECT_ITERATIONS):
                            mid = 0.5 * (lo + hi)
                            if _hermite(p0, dp0, p1, dp1, mid) < 0.0:
                                hi = mid
                            else:
                                lo = mid
                        se = s + hi * (1.0 - s)
                        # Newton on the actual RK4 step length
                        xn, vn, i0, i1, pe, dpe = _rk4_contact(c, k, s, se, Ts, xl, vl, side, eps, kj, dj, bj)
                        for _ in range(4):
                            if abs(pe) <= 1e-15 or dpe == 0.0:
                                break
                            sn = se - pe / dpe
                            if not (s < sn <= 1.0):
                                break
                            xq, vq, iq0, iq1, pq, dpq = _rk4_contact(c, k, s, sn, Ts, xl, vl, side, eps,
                                                                     kj, dj, bj)
                            if abs(pq) >= abs(pe):
                                break
                            se, xn, vn, i0, i1, pe, dpe = sn, xq, vq, iq0, iq1, pq, dpq
                        I0[k] += i0
                        I1[k] += i1
                        xl = xn
                        vl = vn
                        s = se
                        side = 0.0
                        events += 1
                        continue
                I0[k] += i0
                I1[k] += i1
                xl = xn
                vl = vn
                s = 1.0
            else:
                # --- gap: free viscous decay of the load, exact; motor: the spline, exact
                xa, da = _motor(c, k, s)
                xc, dc = _motor(c, k, 1.0)
                xn, vn = _gap_state(xl, vl, bj, h)
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
                    xl = xn
                    vl = vn
                    s = 1.0
                    continue
                # bisect on the exact gap variable z(u)
                hi = hit
                zh = 0.0
                for it in range(_BISECT_ITERATIONS + 1):
                    mid = hi if it == 0 else 0.5 * (lo + hi)
                    xq, _ = _motor(c, k, s + mid * (1.0 - s))
                    xlq, _ = _gap_state(xl, vl, bj, mid * h)
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
                    se = s + hit * (1.0 - s)
                    xl, vl = _gap_state(xl, vl, bj, hit * h)
                    s = se
                    continue
                se = s + hi * (1.0 - s)
                xl, vl = _gap_state(xl, vl, bj, hi * h)
                side = 1.0 if zh > 0.0 else -1.0
                s = se
                events += 1
    xl_out[m] = xl
    vl_out[m] = vl
    return I0, I1, xl_out, vl_out, events


@njit(cache=True, nogil=True)
def _sosfilt_inplace(sos: NDArray[np.float64], zi: NDArray[np.float64], x: NDArray[np.float64],
                     forward: bool) -> None:
    """Direct-form-II-transposed second-order sections over x, in place, initial state zi·x[first]."""
    n = x.shape[0]
    ns = sos.shape[0]
    x0 = x[0] if forward else x[n - 1]
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


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _shaft_torque_tri(I0: NDArray[np.float64], I1: NDArray[np.float64], K: float, D: float,
                      Ts: float) -> NDArray[np.float64]:
    """Triangle-kernel average of τ_s = K·y + D·ẏ at samples 1 … N−2 (length N−2)."""
    m = I0.shape[0]
    out = np.empty(m - 1)
    for k in range(1, m):
        out[k - 1] = K * (I1[k - 1] + I0[k] - I1[k]) + D * (I0[k] - I0[k - 1]) / Ts
    return out


# ----------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ResidualProblem:
    """Everything about one recording the residual needs, computed once.

    Arrays indexed by the residual's samples k = 1 … N−2 (length N−2) unless stated.
    """

    sample_rate_hz: float
    """Sample rate [Hz]."""
    spline: NDArray[np.float64]
    """Cubic-spline coefficients of the motor position, shape (N−1, 4), per sample interval, s ∈ [0, 1]."""
    acceleration: NDArray[np.float64]
    """(x[k+1] − 2x[k] + x[k−1]) / Ts² [rad/s²]."""
    velocity: NDArray[np.float64]
    """(x[k+1] − x[k−1]) / (2·Ts) [rad/s]."""
    torque: NDArray[np.float64]
    """(τ_ref[k−1] + τ_ref[k]) / 2 [N·m]."""
    sos: NDArray[np.float64]
    """Zero-phase low-pass (second-order sections) applied to the residual."""
    cutoff_hz: float
    """Low-pass cut-off [Hz]."""
    decimation: int
    """Keep every ``decimation``-th filtered sample (≈ independent samples)."""
    zi: NDArray[np.float64]
    """Steady-state initial conditions of the sections (scipy.signal.sosfilt_zi)."""
    padlen: int
    """Odd-extension length at each end (as scipy.signal.sosfiltfilt)."""
    initial_twist_rad: float
    """x_m − x_l at sample 0 [rad] (0: the gears start centred in the gap, at rest)."""
    load_position: NDArray[np.float64] | None
    """Measured load position at samples 0 … N−1 [rad], when a load encoder is present."""
    # pre-filtered, decimated regressors of the motor equation
    acceleration_f: NDArray[np.float64]
    velocity_f: NDArray[np.float64]
    torque_f: NDArray[np.float64]

    @property
    def n_samples(self) -> int:
        """Samples of the recording (N)."""
        return int(self.spline.shape[0] + 1)

    @property
    def n_residual(self) -> int:
        """Length of the decimated residual vector (motor block + load block)."""
        n = int(self.acceleration_f.shape[0])
        return 2 * n if self.load_position is not None else n

    def lowpass(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Zero-phase low-pass, then decimation (the same operator as the residual's)."""
        return _filtfilt_decimate(self.sos, self.zi, np.ascontiguousarray(x, dtype=np.float64),
                                  self.padlen, self.decimation)


@dataclass(frozen=True, eq=False)
class LoadSimulation:
    """The simulated load of one residual evaluation."""

    shaft_torque: NDArray[np.float64]
    """Triangle-averaged shaft torque K·y + D·ẏ at samples 1 … N−2 [N·m]."""
    load_position: NDArray[np.float64]
    """Simulated load position at samples 0 … N−1 [rad]."""
    load_velocity: NDArray[np.float64]
    """Simulated load velocity at samples 0 … N−1 [rad/s]."""
    events: int
    """Contact and separation events located inside steps."""


@dataclass(frozen=True, eq=False)
class Residual:
    """Result of :func:`torque_residual`."""

    residual: NDArray[np.float64]
    """Low-passed (not decimated) motor-equation residual at samples 1 … N−2 [N·m]."""
    vector: NDArray[np.float64]
    """Decimated residual vector fed to least squares [N·m] (motor block, then load block)."""
    cost: float
    """RMS of ``vector`` [N·m]."""
    simulation: LoadSimulation


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
    """
    tau = np.asarray(torque_ref, dtype=np.float64)
    n = tau.shape[0]
    fs = float(sample_rate_hz)
    if motor_position is not None:
        x = np.asarray(motor_position, dtype=np.float64)
    elif motor_velocity is not None:
        v = np.asarray(motor_velocity, dtype=np.float64)
        x = np.concatenate(([0.0], np.cumsum(v[1:]) / fs))
    else:
        raise IdentificationError("the torque residual needs the motor position or velocity")
    if x.shape[0] != n or n < 16:
        raise IdentificationError(f"the torque residual needs ≥ 16 aligned samples, got {n}")
    if not 0.0 < cutoff_hz < 0.5 * fs:
        raise IdentificationError(f"residual cut-off {cutoff_hz} Hz must lie in (0, {0.5 * fs}) Hz")
    x = x - x[0]
    Ts = 1.0 / fs
    cs = CubicSpline(np.arange(n, dtype=np.float64), x)
    spline = np.ascontiguousarray(cs.c.T)
    acc = (x[2:] - 2.0 * x[1:-1] + x[:-2]) * fs * fs
    vel = (x[2:] - x[:-2]) * (0.5 * fs)
    trq = 0.5 * (tau[:-2] + tau[1:-1])
    sos = butter(filter_order, cutoff_hz, fs=fs, output="sos")
    decimation = max(1, int(fs / (2.0 * cutoff_hz)))
    zi = sosfilt_zi(sos)
    padlen = 3 * (2 * sos.shape[0] + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum())))
    lp = lambda a: _filtfilt_decimate(sos, zi, a, padlen, decimation)  # noqa: E731
    xl = None
    twist0 = 0.0
    if load_position is not None:
        xl = np.asarray(load_position, dtype=np.float64)
        if xl.shape[0] != n:
            raise IdentificationError("load position and motor position differ in length")
        if motor_position is not None:
            x_m0 = float(np.asarray(motor_position, dtype=np.float64)[0])
            twist0 = x_m0 - float(xl[0])
            xl = np.ascontiguousarray(xl - x_m0)
        else:  # motor rebuilt from velocity: no common origin, assume centred gears
            xl = np.ascontiguousarray(xl - xl[0])
    if initial_twist_rad is not None:
        twist0 = float(initial_twist_rad)
    return ResidualProblem(
        sample_rate_hz=fs, spline=spline, acceleration=acc, velocity=vel, torque=trq,
        sos=sos, cutoff_hz=float(cutoff_hz), decimation=decimation, zi=zi, padlen=padlen, initial_twist_rad=twist0,
        load_position=xl,
        acceleration_f=lp(acc), velocity_f=lp(vel), torque_f=lp(trq),
    )


def simulate_load(problem: ResidualProblem, J_l: float, B_l: float, K: float, D: float,
                  epsilon_rad: float) -> LoadSimulation:
    """Simulate the load driven by the measured motor position (see module docstring)."""
    Ts = 1.0 / problem.sample_rate_hz
    xl0 = -problem.initial_twist_rad  # motor position is shifted to start at 0
    I0, I1, xl, vl, events = _simulate_load(problem.spline, Ts, float(J_l), float(B_l), float(K),
                                           float(D), max(float(epsilon_rad), 0.0), xl0, 0.0)
    ts = _shaft_torque_tri(I0, I1, float(K), float(D), Ts)
    return LoadSimulation(shaft_torque=ts, load_position=xl, load_velocity=vl, events=int(events))


def torque_residual(problem: ResidualProblem, J_m: float, J_l: float, B_m: float, B_l: float,
                    K: float, D: float, epsilon_rad: float, *,
                    load_weight_nm_per_rad: float | None = None) -> Residual:
    """r = J_m·Δ²x_m/Ts² + B_m·v_m + τ_s(sim) − τ_ref, low-passed zero-phase, and its RMS cost.

    :param load_weight_nm_per_rad: weight of the load-position block when the problem has a
        load encoder (default K: a load-position error then counts as the shaft torque it implies).
    """
    sim = simulate_load(problem, J_l, B_l, K, D, epsilon_rad)
    vec = _vector(problem, sim, J_m, B_m, K, load_weight_nm_per_rad)
    raw = J_m * problem.acceleration + B_m * problem.velocity + sim.shaft_torque - problem.torque
    res = sosfiltfilt(problem.sos, raw)
    cost = float(np.sqrt(np.mean(vec * vec)))
    return Residual(residual=res, vector=vec, cost=cost, simulation=sim)


def residual_vector(problem: ResidualProblem, J_m: float, J_l: float, B_m: float, B_l: float,
                    K: float, D: float, epsilon_rad: float, *,
                    load_weight_nm_per_rad: float | None = None) -> NDArray[np.float64]:
    """Only the decimated residual vector of :func:`torque_residual` (the fast path for fits)."""
    sim = simulate_load(problem, J_l, B_l, K, D, epsilon_rad)
    return _vector(problem, sim, J_m, B_m, K, load_weight_nm_per_rad)


def _vector(problem: ResidualProblem, sim: LoadSimulation, J_m: float, B_m: float, K: float,
            load_weight_nm_per_rad: float | None) -> NDArray[np.float64]:
    d = problem.decimation
    ts_f = _filtfilt_decimate(problem.sos, problem.zi, sim.shaft_torque, problem.padlen, d)
    vec = J_m * problem.acceleration_f + B_m * problem.velocity_f + ts_f - problem.torque_f
    if problem.load_position is not None:
        w = float(K if load_weight_nm_per_rad is None else load_weight_nm_per_rad)
        vec = np.concatenate((vec, w * (sim.load_position - problem.load_position)[1:-1:d]))
    return vec
