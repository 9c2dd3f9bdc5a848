"""Closed-loop simulation at the drive's clock: the controller of :mod:`.design` around the
two-mass + dead-zone plant, one compiled loop.

Physics (the same model as ``sim_drive.plant``, METHOD.md "Plant")::

    J_m·ẍ_m = τ − B_m·ẋ_m − τ_s − F_cm·tanh(ẋ_m/v_s)
    J_l·ẍ_l = τ_s − B_l·ẋ_l − F_cl·tanh(ẋ_l/v_s)
    τ_s = K·dz(x_m − x_l; ε) + D·ẏ      (0 in the gap)
    τ̇  = ω_c·(u − τ)                   (current loop; τ = u when ideal)

Integration: each sample is split into RK4 sub-steps with the contact mode held
fixed (4 at least; more for stiff plants, a fast current loop or steep Coulomb
friction, with the limits ``sim_drive.plant`` uses); after every sub-step the
twist is checked against ±ε at its end and, through the cubic Hermite
interpolant of the twist, inside it (grazing contacts); a crossing is located
by Illinois regula falsi on the step length, the step is taken to the crossing
and finished in the new mode. This is the scheme of ``sim_drive.plant`` written
again here so that the controller runs inside the compiled loop (the package
does not import ``sim_drive``). The current loop is integrated as a state of
RK4 rather than in closed form; both are exact to far below the encoder step.
``tests/test_tuning_closedloop.py`` checks the loop against
``Plant.run_velocity`` with a PI controller (the drive's velocity mode).

Sample timing (the drive's, as in ``sim_drive.plant``): at tick k the encoders
are latched and quantised, the velocity is the backward difference of the
quantised positions, the controller computes u[k], and u[k] is held over
[k·Ts, (k+1)·Ts).

Controller at tick k (every gain in SI units, see :class:`ControllerGains`)::

    r_f[k] = r_f[k−1] + (r[k] − r_f[k−1])·α_r            position-reference filter (also
                                                            on ṙ and r̈ for the feedforward)
    o[k]   = o[k−1] + (dir[k]·a/2 − o[k−1])·α_b        backlash compensation
    v*[k]  = K_p·(r_f[k] + o[k] − x̂_m[k]) + k_vff·ṙ_f[k]  (position mode)
    e[k]   = v*[k] − v̂_m[k]
    u_pi   = k_p·e[k] + I[k−1] + k_i·T_s·e[k]             (I[k] = I[k−1] + k_i·T_s·e[k]
                                                            unless the output saturates)
    u[k]   = clip(N(F(u_pi + k_tff·J·r̈_f[k])), ±limit)     F: 1st-order low-pass,
                                                            N: notch biquads
    applied over [(k+d)·Ts, (k+d+1)·Ts), d = computation delay [samples]
with dir[k] the sign of the last non-zero increment of the unfiltered reference (0 before any).
The compensation is written symmetric (±a/2): a drive that adds the whole amount
a in one direction only (YASKAWA Pn230/231) differs by the constant a/2, which
homing absorbs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

__all__ = ["MAX_NOTCHES", "simulate_closed_loop"]

#: Notch biquads the compiled controller can hold.
MAX_NOTCHES = 2
_MAX_RATE_STEP = 0.06
_MAX_LAG_STEP = 0.5
_MAX_COULOMB_STEP = 1.0
_MIN_SUBSTEPS = 4
_EVENT_TOL_RAD = 1e-13
_MAX_EVENTS_PER_SUBSTEP = 16

# plant vector
(_JM, _JL, _BM, _BL, _K, _D, _EPS, _FM, _FL, _VSC, _WC, _QM, _QL) = range(13)
_N_PLANT = 13
# controller vector
(_KP, _KI, _KPOS, _KVFF, _KTFF, _ALPHA_F, _LIMIT, _BC_HALF, _ALPHA_B, _POSMODE, _NNOTCH, _DELAY,
 _ALPHA_R) = range(13)
_NOTCH0 = 13  # then 5 coefficients per notch: b0, b1, b2, a1, a2
_N_CTRL = _NOTCH0 + 5 * MAX_NOTCHES


@njit(cache=True)
def _deriv(v_m: float, x_s: float, v_l: float, tau: float, u: float, mode: int,
           p: NDArray[np.float64]) -> tuple[float, float, float, float]:
    """(v̇_m, ẋ_s, v̇_l, τ̇) in a fixed contact mode (+1, 0 gap, −1)."""
    if mode > 0:
        ts = p[_K] * (x_s - p[_EPS]) + p[_D] * (v_m - v_l)
    elif mode < 0:
        ts = p[_K] * (x_s + p[_EPS]) + p[_D] * (v_m - v_l)
    else:
        ts = 0.0
    t_m = tau if p[_WC] > 0.0 else u
    f_m = t_m - p[_BM] * v_m - ts
    f_l = ts - p[_BL] * v_l
    if p[_FM] > 0.0:
        f_m -= p[_FM] * math.tanh(v_m / p[_VSC])
    if p[_FL] > 0.0:
        f_l -= p[_FL] * math.tanh(v_l / p[_VSC])
    dtau = p[_WC] * (u - tau) if p[_WC] > 0.0 else 0.0
    return f_m / p[_JM], v_m - v_l, f_l / p[_JL], dtau


@njit(cache=True)
def _rk4(x_m: float, v_m: float, x_s: float, v_l: float, tau: float, u: float, mode: int, h: float,
         p: NDArray[np.float64]) -> tuple[float, float, float, float, float]:
    """One RK4 step of length h in a fixed mode: (x_m, v_m, x_s, v_l, τ)."""
    a1, s1, b1, t1 = _deriv(v_m, x_s, v_l, tau, u, mode, p)
    hh = 0.5 * h
    a2, s2, b2, t2 = _deriv(v_m + hh * a1, x_s + hh * s1, v_l + hh * b1, tau + hh * t1, u, mode, p)
    a3, s3, b3, t3 = _deriv(v_m + hh * a2, x_s + hh * s2, v_l + hh * b2, tau + hh * t2, u, mode, p)
    a4, s4, b4, t4 = _deriv(v_m + h * a3, x_s + h * s3, v_l + h * b3, tau + h * t3, u, mode, p)
    h6 = h / 6.0
    vm2 = v_m + hh * a1
    vm3 = v_m + hh * a2
    vm4 = v_m + h * a3
    return (
        x_m + h6 * (v_m + 2.0 * vm2 + 2.0 * vm3 + vm4),
        v_m + h6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
        x_s + h6 * (s1 + 2.0 * s2 + 2.0 * s3 + s4),
        v_l + h6 * (b1 + 2.0 * b2 + 2.0 * b3 + b4),
        tau + h6 * (t1 + 2.0 * t2 + 2.0 * t3 + t4),
    )


@njit(cache=True)
def _hermite_exit(g0: float, g1: float, m0: float, m1: float) -> float:
    """First θ ∈ (0, 1] where the cubic Hermite interpolant of g (values g0, g1, slopes
    m0, m1 per unit θ) is > 0; −1 when it stays ≤ 0."""
    dg = g1 - g0
    if max(g0, g1) + 0.25 * max(abs(m0 - dg), abs(m1 - dg)) <= 0.0:
        return -1.0
    a3 = 2.0 * g0 + m0 - 2.0 * g1 + m1
    a2 = -3.0 * g0 - 2.0 * m0 + 3.0 * g1 - m1
    a1 = m0
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
def _advance(s: NDArray[np.float64], u: float, n_sub: int, Ts: float, p: NDArray[np.float64]) -> None:
    """Advance s = [x_m, v_m, x_s, v_l, τ, mode] by one sample under the held reference u."""
    eps = p[_EPS]
    h = Ts / n_sub
    mode = int(s[5])
    for _ in range(n_sub):
        t_left = h
        n_events = 0
        while t_left > 0.0:
            dt = t_left
            x_m1, v_m1, x_s1, v_l1, tau1 = _rk4(s[0], s[1], s[2], s[3], s[4], u, mode, dt, p)
            if eps > 0.0 and n_events < _MAX_EVENTS_PER_SUBSTEP:
                w0 = s[1] - s[3]
                w1 = v_m1 - v_l1
                theta = -1.0
                b = 0.0
                sg = 1.0
                new_mode = mode
                if mode == 0:
                    th_up = _hermite_exit(s[2] - eps, x_s1 - eps, w0 * dt, w1 * dt)
                    th_dn = _hermite_exit(-(s[2] + eps), -(x_s1 + eps), -w0 * dt, -w1 * dt)
                    if th_up > 0.0 and (th_dn < 0.0 or th_up <= th_dn):
                        theta, b, sg, new_mode = th_up, eps, 1.0, 1
                    elif th_dn > 0.0:
                        theta, b, sg, new_mode = th_dn, -eps, -1.0, -1
                elif mode > 0:
                    theta = _hermite_exit(-(s[2] - eps), -(x_s1 - eps), -w0 * dt, -w1 * dt)
                    b, sg, new_mode = eps, -1.0, 0
                else:
                    theta = _hermite_exit(s[2] + eps, x_s1 + eps, w0 * dt, w1 * dt)
                    b, sg, new_mode = -eps, 1.0, 0
                if theta > 0.0:
                    tb = theta * dt
                    if theta < 1.0:
                        x_m1, v_m1, x_s1, v_l1, tau1 = _rk4(s[0], s[1], s[2], s[3], s[4], u, mode, tb, p)
                    gb = sg * (x_s1 - b)
                    if gb > 0.0:
                        ta = 0.0
                        ga = min(sg * (s[2] - b), 0.0)
                        g_end = gb
                        side = 0
                        for _it in range(60):
                            if g_end <= _EVENT_TOL_RAD or tb - ta <= 1e-12 * h:
                                break
                            tm = (ta * gb - tb * ga) / (gb - ga)
                            if not (ta < tm < tb):
                                tm = 0.5 * (ta + tb)
                            xm_m, vm_m, xs_m, vl_m, tau_m = _rk4(s[0], s[1], s[2], s[3], s[4], u, mode, tm, p)
                            gm = sg * (xs_m - b)
                            if gm > 0.0:
                                tb, gb, g_end = tm, gm, gm
                                x_m1, v_m1, x_s1, v_l1, tau1 = xm_m, vm_m, xs_m, vl_m, tau_m
                                if side == 1:
                                    ga *= 0.5
                                side = 1
                            else:
                                ta, ga = tm, gm
                                if side == -1:
                                    gb *= 0.5
                                side = -1
                        mode = new_mode
                        n_events += 1
                    dt = tb
            s[0] = x_m1
            s[1] = v_m1
            s[2] = x_s1
            s[3] = v_l1
            s[4] = tau1
            t_left -= dt
    s[5] = mode


@njit(cache=True)
def _run(r: NDArray[np.float64], v_ref: NDArray[np.float64], a_ref: NDArray[np.float64],
         p: NDArray[np.float64], c: NDArray[np.float64], n_sub: int, Ts: float,
         out: NDArray[np.float64]) -> None:
    """The closed loop over len(r) samples from rest (twist 0, centre of the gap).

    Rows of out: measured motor position, measured motor velocity, true load position,
    measured load velocity, torque reference u, true twist, backlash-compensation offset,
    filtered position reference r_f (position mode; 0 in velocity mode).
    """
    n = r.shape[0]
    s = np.zeros(6)
    s[5] = 0.0 if p[_EPS] > 0.0 else 1.0
    q_m = p[_QM]
    q_l = p[_QL]
    integ = 0.0
    y_f = 0.0
    n_notch = int(c[_NNOTCH])
    z1 = np.zeros(MAX_NOTCHES)
    z2 = np.zeros(MAX_NOTCHES)
    pos_prev = 0.0
    posl_prev = 0.0
    offset = 0.0
    direction = 0.0
    r_prev = r[0]
    r_f = r[0]
    v_f = v_ref[0]
    a_f = a_ref[0]
    alpha_r = c[_ALPHA_R]
    pos_mode = c[_POSMODE] > 0.0
    n_delay = int(c[_DELAY])
    line = np.zeros(n_delay + 1)  # computation delay: u[k] acts n_delay samples later
    for k in range(n):
        pos_m = np.rint(s[0] / q_m) * q_m
        x_l = s[0] - s[2]
        pos_l = np.rint(x_l / q_l) * q_l
        vel_m = (pos_m - pos_prev) / Ts
        vel_l = (pos_l - posl_prev) / Ts
        pos_prev = pos_m
        posl_prev = pos_l
        if pos_mode:
            dr = r[k] - r_prev
            r_prev = r[k]
            if dr > 1e-15:
                direction = 1.0
            elif dr < -1e-15:
                direction = -1.0
            offset += (direction * c[_BC_HALF] - offset) * c[_ALPHA_B]
            r_f += (r[k] - r_f) * alpha_r
            v_f += (v_ref[k] - v_f) * alpha_r
            a_f += (a_ref[k] - a_f) * alpha_r
            v_cmd = c[_KPOS] * (r_f + offset - pos_m) + c[_KVFF] * v_f
        else:
            v_cmd = v_ref[k]
            a_f = a_ref[k]
        e = v_cmd - vel_m
        d_integ = c[_KI] * e * Ts
        x = c[_KP] * e + integ + d_integ + c[_KTFF] * a_f
        y_f += (x - y_f) * c[_ALPHA_F]
        y = y_f
        for i in range(n_notch):
            o = _NOTCH0 + 5 * i
            yn = c[o] * y + z1[i]
            z1[i] = c[o + 1] * y - c[o + 3] * yn + z2[i]
            z2[i] = c[o + 2] * y - c[o + 4] * yn
            y = yn
        lim = c[_LIMIT]
        if y > lim:
            u = lim
        elif y < -lim:
            u = -lim
        else:
            u = y
            integ += d_integ  # anti-windup: integrate only while unsaturated
        out[0, k] = pos_m
        out[1, k] = vel_m
        out[2, k] = x_l
        out[3, k] = vel_l
        out[4, k] = u
        out[5, k] = s[2]
        out[6, k] = offset
        out[7, k] = r_f if pos_mode else 0.0
        if n_delay > 0:
            line[k % (n_delay + 1)] = u
            u = line[(k + 1) % (n_delay + 1)]
        _advance(s, u, n_sub, Ts, p)


def substeps(J_m: float, J_l: float, B_m: float, B_l: float, K: float, D: float,
             current_loop_hz: float | None, coulomb_nm: float, coulomb_scale: float, Ts: float) -> int:
    """RK4 sub-steps per sample: ``sim_drive.plant``'s rule, plus steep Coulomb friction."""
    a = np.array([
        [-(B_m + D) / J_m, D / J_m, -K / J_m],
        [D / J_l, -(B_l + D) / J_l, K / J_l],
        [1.0, -1.0, 0.0],
    ])
    rate = float(np.max(np.abs(np.linalg.eigvals(a))))
    wc = 0.0 if current_loop_hz is None else 2.0 * math.pi * current_loop_hz
    coulomb_rate = coulomb_nm / (coulomb_scale * min(J_m, J_l)) if coulomb_nm > 0 else 0.0
    return max(_MIN_SUBSTEPS, math.ceil(rate * Ts / _MAX_RATE_STEP), math.ceil(wc * Ts / _MAX_LAG_STEP),
               math.ceil(coulomb_rate * Ts / _MAX_COULOMB_STEP))


def simulate_closed_loop(plant: NDArray[np.float64], controller: NDArray[np.float64], n_sub: int, Ts: float,
                         position_ref: NDArray[np.float64], velocity_ref: NDArray[np.float64],
                         accel_ref: NDArray[np.float64]) -> NDArray[np.float64]:
    """Run the compiled loop; returns out of shape (8, N) (rows: see ``_run``)."""
    r = np.ascontiguousarray(position_ref, dtype=np.float64)
    v = np.ascontiguousarray(velocity_ref, dtype=np.float64)
    a = np.ascontiguousarray(accel_ref, dtype=np.float64)
    if not (r.shape == v.shape == a.shape and r.ndim == 1):
        raise ValueError("position, velocity and acceleration references must have the same shape (N,)")
    out = np.empty((8, r.shape[0]))
    _run(r, v, a, np.ascontiguousarray(plant, dtype=np.float64),
         np.ascontiguousarray(controller, dtype=np.float64), int(n_sub), float(Ts), out)
    return out
