"""Closed-loop simulation at the drive's clock: the controller of :mod:`.design` around the
two-mass + dead-zone plant of :mod:`commission.plant`, one compiled loop.

The plant is advanced by :func:`commission.plant.advance_sample` (RK4 sub-steps, contact and
separation located inside the step, Coulomb friction, the current-loop lag in closed form),
the integrator the simulated drive runs too, so the verification runs on exactly the physics
of ``--sim``; only the controller is written here, inside the same compiled loop.
``tests/test_tuning.py`` checks the loop against ``Plant.run_velocity`` with a PI controller
(the drive's velocity mode).

Sample timing (the drive's, as in :mod:`commission.plant`): at tick k the encoders
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
    applied over [(k+d)·Ts, (k+d+1)·Ts), d = the plant's computation delay [samples]
    (:attr:`commission.plant.PlantParameters.delay_samples`: the drive's, not the design's)
with dir[k] the sign of the last non-zero increment of the unfiltered reference (0 before any).
The compensation is written symmetric (±a/2): a drive that adds the whole amount
a in one direction only (YASKAWA Pn230/231) differs by the constant a/2, which
homing absorbs.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from ..plant import PlantKernel, advance_sample, initial_state, load_position, motor_position, quantise, twist

__all__ = ["MAX_NOTCHES", "simulate_closed_loop"]

#: Notch biquads the compiled controller can hold.
MAX_NOTCHES = 2

# controller vector
(_KP, _KI, _KPOS, _KVFF, _KTFF, _ALPHA_F, _LIMIT, _BC_HALF, _ALPHA_B, _POSMODE, _NNOTCH,
 _ALPHA_R) = range(12)
_NOTCH0 = 12  # then 5 coefficients per notch: b0, b1, b2, a1, a2
_N_CTRL = _NOTCH0 + 5 * MAX_NOTCHES


@njit(cache=True)
def _run(r: NDArray[np.float64], v_ref: NDArray[np.float64], a_ref: NDArray[np.float64],
         p: PlantKernel, c: NDArray[np.float64], out: NDArray[np.float64]) -> None:
    """The closed loop over len(r) samples from rest (twist 0, centre of the gap).

    Rows of out: measured motor position, measured motor velocity, true load position,
    measured load velocity, torque reference u, true twist, backlash-compensation offset,
    filtered position reference r_f (position mode; 0 in velocity mode).
    """
    n = r.shape[0]
    s = initial_state(p)
    Ts = p.sample_time_s
    q_m = p.encoder_step_motor_rad
    q_l = p.encoder_step_load_rad
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
    for k in range(n):
        pos_m = quantise(motor_position(s), q_m)
        x_l = load_position(s)
        pos_l = quantise(x_l, q_l)
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
        out[5, k] = twist(s)
        out[6, k] = offset
        out[7, k] = r_f if pos_mode else 0.0
        advance_sample(s, u, 0.0, p)


def simulate_closed_loop(plant: PlantKernel, controller: NDArray[np.float64],
                         position_ref: NDArray[np.float64], velocity_ref: NDArray[np.float64],
                         accel_ref: NDArray[np.float64]) -> NDArray[np.float64]:
    """Run the compiled loop on ``plant`` (:attr:`commission.plant.Plant.kernel`, whose sample
    time is the loop's); returns out of shape (8, N) (rows: see ``_run``)."""
    r = np.ascontiguousarray(position_ref, dtype=np.float64)
    v = np.ascontiguousarray(velocity_ref, dtype=np.float64)
    a = np.ascontiguousarray(accel_ref, dtype=np.float64)
    if not (r.shape == v.shape == a.shape and r.ndim == 1):
        raise ValueError("position, velocity and acceleration references must have the same shape (N,)")
    out = np.empty((8, r.shape[0]))
    _run(r, v, a, plant, np.ascontiguousarray(controller, dtype=np.float64), out)
    return out
