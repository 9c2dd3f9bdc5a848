"""The identifier's dead-zone two-mass simulator, its losses and the ε grid search.

Independent answers: scipy's ZOH discretisation of the physical state space
(ε = 0), sim_drive's plant (RK4 sub-steps + Illinois event location, another
integration method) with 32-bit encoders (ε > 0), scipy's DOP853 with its own
event location (a graze). (A plain RK4 with 1000–16000 sub-steps per sample
was tried as the fine reference: its first-order error at the torque jumps
D·ż of each contact stalls at ~3e-7 rad/s on the graze and ~3e-4 rad/s on the
impact-rich chirp, so it cannot check this simulator.)
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import signal

from commission.exceptions import IdentificationError
from commission.ident.backlash import (
    DeadzoneState,
    deadzone,
    epsilon_grid,
    max_output_error,
    nonlinear_torque,
    rms_output_error,
    search_epsilon_grid,
    simulate_deadzone,
    simulate_motor_velocity,
)
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters

FS = 8000.0
TS = 1.0 / FS
EPS = math.radians(0.40)


def excitation(n: int, *, bias: float = 3.0, f1: float = 400.0, T: float = 10.0) -> np.ndarray:
    """The experiment's torque (METHOD.md), optionally shorter / without the slow bias."""
    t = np.arange(n) / FS
    A = 0.0764
    return A * np.sin(2 * np.pi * (0.1 * t + (f1 - 0.1) * t**2 / (2 * T))) + bias * A * np.sin(
        2 * np.pi * 0.1 * t
    )


def physical_zoh_positions(p: TwoMassParameters, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x_m, x_l at the ticks from scipy's ZOH discretisation of (x_m, v_m, x_l, v_l)."""
    A = np.array([
        [0, 1, 0, 0],
        [-p.K / p.J_m, -(p.B_m + p.D) / p.J_m, p.K / p.J_m, p.D / p.J_m],
        [0, 0, 0, 1],
        [p.K / p.J_l, p.D / p.J_l, -p.K / p.J_l, -(p.B_l + p.D) / p.J_l],
    ])
    B = np.array([[0], [1 / p.J_m], [0], [0]])
    C = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    sysd = signal.cont2discrete((A, B, C, np.zeros((2, 1))), TS, method="zoh")
    _, y, _ = signal.dlsim(sysd, tau)
    return y[:, 0], y[:, 1]


def test_linear_case_matches_scipy_zoh_discretisation():
    tau = excitation(40_000)  # 5 s: up to ~200 Hz, resonance included
    r = simulate_deadzone(REFERENCE_PLANT, 0.0, tau, FS)
    xm, xl = physical_zoh_positions(REFERENCE_PLANT, tau)
    v_ref = np.r_[0.0, np.diff(xm) / TS]
    vmax = np.max(np.abs(v_ref))
    assert vmax > 10.0
    # 1e-6 relative to the velocity range (measured: ~1e-11)
    assert_allclose(r.motor_velocity, v_ref, rtol=0, atol=1e-6 * vmax)
    assert_allclose(r.motor_position, xm, rtol=0, atol=1e-9)
    assert_allclose(r.twist, xm - xl, rtol=0, atol=1e-12)
    assert r.n_events == 0


def test_steady_state_of_constant_torque_is_the_dc_gain():
    tau = np.full(8000 * 4, 0.05)  # 4 s ≫ 1/20.45 rad/s time constant
    p = REFERENCE_PLANT
    for eps in (0.0, EPS):
        r = simulate_deadzone(p, eps, tau, FS)
        assert_allclose(r.motor_velocity[-1], 0.05 / (p.B_m + p.B_l), rtol=1e-9)
        # preload: the shaft carries the load's friction, twist = ε + B_l·v/K
        v = 0.05 / (p.B_m + p.B_l)
        assert_allclose(r.twist[-1], eps + p.B_l * v / p.K, rtol=1e-9)


def test_delay_samples_shift_the_response():
    tau = excitation(4000)
    r1 = simulate_deadzone(REFERENCE_PLANT, EPS, tau, FS, delay_samples=1)
    r3 = simulate_deadzone(REFERENCE_PLANT, EPS, tau, FS, delay_samples=3)
    r0 = simulate_deadzone(REFERENCE_PLANT, EPS, tau, FS, delay_samples=0)
    assert_allclose(r3.motor_velocity[2:], r1.motor_velocity[:-2], rtol=0, atol=1e-12)
    assert_allclose(r0.motor_velocity[1:-1], r1.motor_velocity[2:], rtol=0, atol=1e-12)
    # drive convention: velocity[k] ignores torque[k]: a kick at the last sample is invisible
    tau2 = tau.copy()
    tau2[-1] += 1.0
    r1b = simulate_deadzone(REFERENCE_PLANT, EPS, tau2, FS)
    assert_allclose(r1b.motor_velocity, r1.motor_velocity, rtol=0, atol=0)


@pytest.fixture(scope="module")
def plant_module():
    return pytest.importorskip("sim_drive.plant")


@pytest.mark.parametrize(
    "name, tau",
    [
        ("standard 2 s", excitation(16_000)),
        ("no-bias chirp 1 s (impact-rich)", excitation(8000, bias=0.0, T=1.0)),
    ],
)
def test_matches_sim_drive_plant_with_backlash(plant_module, name, tau):
    pm = plant_module
    plant = pm.Plant(
        pm.PlantParameters(epsilon_deg=0.40, encoder_bits_motor=32, encoder_bits_load=32),
        FS,
        substeps_per_sample=40,
    )
    ref = plant.run_torque(tau)
    r = simulate_deadzone(REFERENCE_PLANT, EPS, tau, FS)
    assert r.n_events >= 10
    # measured: twist ≤ 2.2e-10 rad, shaft torque ≤ 5.5e-10 N·m, velocity ≤ 1.2e-5 rad/s
    # (the last is the plant's 32-bit encoder: 2π/2³²·8000 = 1.17e-5 rad/s)
    assert_allclose(r.twist, ref.twist, rtol=0, atol=2e-9)
    assert_allclose(r.shaft_torque, ref.shaft_torque, rtol=0, atol=1e-8)
    assert_allclose(r.motor_velocity, ref.motor_velocity, rtol=0, atol=2.5e-5)


def test_event_location_beats_a_fixed_step(plant_module):
    pm = plant_module
    tau = excitation(8000, bias=0.0, T=1.0)
    plant = pm.Plant(
        pm.PlantParameters(epsilon_deg=0.40, encoder_bits_motor=32, encoder_bits_load=32),
        FS,
        substeps_per_sample=40,
    )
    ref = plant.run_torque(tau)
    located = max_output_error(ref.motor_velocity, simulate_deadzone(REFERENCE_PLANT, EPS, tau, FS).motor_velocity)
    fixed = max_output_error(
        ref.motor_velocity,
        simulate_deadzone(REFERENCE_PLANT, EPS, tau, FS, locate_events=False).motor_velocity,
    )
    # measured: located 1.2e-5 (encoder), fixed step 0.070 rad/s
    assert located < 3e-5
    assert fixed > 1e-2
    assert fixed > 1000 * located


def _ivp_reference(p: TwoMassParameters, eps: float, x0: np.ndarray, u: float, t_end: float) -> np.ndarray:
    """Independent answer: scipy DOP853 (rtol 1e-13) with its own event location at z = ε.

    State (x_m, v_m, z, v_l) at t_end; the torque u is constant; only the +ε
    boundary is handled (enough for the graze below)."""
    from scipy.integrate import solve_ivp

    def rhs(contact):
        def f(t, x):
            xm, vm, z, vl = x
            ts = p.K * (z - eps) + p.D * (vm - vl) if contact else 0.0
            return [vm, (u - p.B_m * vm - ts) / p.J_m, vm - vl, (ts - p.B_l * vl) / p.J_l]

        return f

    t, x, contact = 0.0, np.asarray(x0, float), False
    while True:
        def ev(tt, xx):
            return xx[2] - eps

        ev.terminal = True
        ev.direction = -1.0 if contact else 1.0
        sol = solve_ivp(rhs(contact), (t, t_end), x, method="DOP853", rtol=1e-13, atol=1e-16, events=ev)
        if sol.status != 1:
            return sol.y[:, -1]
        t = float(sol.t_events[0][0])
        x = sol.y_events[0][0].copy()
        x[2] = eps
        contact = not contact


def test_grazing_contact_inside_one_sample_is_located():
    # gap, twist just below ε, closing at w0 = 5 rad/s, decelerated at ~1e5 rad/s²:
    # the twist pokes ~75 µrad above ε and is back inside before the sample ends.
    p = REFERENCE_PLANT
    a = 1.0e5
    w0 = 5.0
    z0 = EPS - 0.5e-4
    x0 = DeadzoneState(motor_position=z0, motor_velocity=w0, load_position=0.0, load_velocity=0.0)
    u = -a * p.J_m
    tau = np.full(3, u)
    # free gap flight would end inside the gap: the event is a graze, invisible at the ends
    z_end_free = z0 + w0 * TS - 0.5 * a * TS**2
    assert abs(z_end_free) < EPS
    ref = np.array([_ivp_reference(p, EPS, np.array([z0, w0, z0, 0.0]), u, k * TS) for k in (1, 2)])
    r = simulate_deadzone(p, EPS, tau, FS, initial=x0, delay_samples=0)
    rf = simulate_deadzone(p, EPS, tau, FS, initial=x0, delay_samples=0, locate_events=False)
    assert r.n_events == 2  # contact and separation inside the first sample
    assert rf.n_events == 0
    err_loc = np.max(np.abs(r.motor_velocity_instant[1:] - ref[:, 1]))
    err_fix = np.max(np.abs(rf.motor_velocity_instant[1:] - ref[:, 1]))
    # measured: located 3.7e-11 rad/s, fixed step 1.8e-4 rad/s (it misses the impact)
    assert err_loc < 1e-9
    assert err_fix > 1e-4
    assert_allclose(r.twist[1:], ref[:, 2], rtol=0, atol=1e-12)
    # the same answer at a 256× finer sampling (events fall elsewhere on the sub-step grid)
    fine = simulate_deadzone(p, EPS, np.full(3 * 256, u), FS * 256, initial=x0, delay_samples=0)
    assert_allclose(fine.motor_velocity_instant[[256, 512]], r.motor_velocity_instant[1:], rtol=0, atol=1e-9)


def test_nonlinear_torque_is_the_difference_to_the_linear_shaft():
    p = REFERENCE_PLANT
    tau = excitation(16_000)
    r = simulate_deadzone(p, EPS, tau, FS)
    w = r.motor_velocity_instant - r.load_velocity_instant
    n = nonlinear_torque(p, EPS, r.twist, w)
    assert_allclose(r.shaft_torque, p.K * r.twist + p.D * w - n, rtol=0, atol=1e-12)
    # in contact n = ±K·ε, in the gap the whole linear shaft torque
    contact = np.abs(r.twist) > EPS
    assert_allclose(n[contact], p.K * EPS * np.sign(r.twist[contact]), rtol=1e-12)
    assert np.any(~contact) and np.any(contact)
    assert_allclose(nonlinear_torque(p, 0.0, r.twist, w), 0.0, atol=0)
    assert_allclose(deadzone([-2.0, -0.5, 0.0, 0.5, 2.0], 1.0), [-1.0, 0.0, 0.0, 0.0, 1.0])


def test_losses():
    a = np.array([0.0, 1.0, -2.0, 3.0])
    b = np.array([0.5, 1.0, -1.0, 3.0])
    assert max_output_error(a, b) == pytest.approx(1.0)
    assert rms_output_error(a, b) == pytest.approx(math.sqrt((0.25 + 1.0) / 4))
    with pytest.raises(IdentificationError):
        max_output_error(a, b[:3])
    with pytest.raises(IdentificationError):
        rms_output_error(a, b[:3])


def test_grid_search_finds_the_true_minimum():
    true = math.radians(0.37)
    calls = []

    def loss(e):
        calls.append(e)
        d = math.degrees(e)  # a V-shaped minimum at 0.37° with ripple
        return 0.02 + abs(d - 0.37) + 0.004 * math.sin(60 * d) ** 2

    res = search_epsilon_grid(loss)
    assert res.method == "grid"
    assert res.evaluations == 100 == len(calls) == len(res.history)
    assert_allclose(res.epsilon_rad, true, atol=1e-12)
    assert res.interval_rad[0] <= res.epsilon_rad <= res.interval_rad[1]
    g = epsilon_grid((math.radians(0.01), math.radians(1.0)), math.radians(0.01))
    assert g.size == 100
    assert_allclose(np.degrees(g[[0, -1]]), [0.01, 1.0], rtol=1e-12)


def test_invalid_inputs_raise():
    tau = np.zeros(10)
    with pytest.raises(IdentificationError):
        simulate_deadzone(REFERENCE_PLANT, -1.0, tau, FS)
    with pytest.raises(IdentificationError):
        simulate_deadzone(REFERENCE_PLANT, EPS, np.array([np.nan]), FS)
    with pytest.raises(IdentificationError):
        simulate_deadzone(REFERENCE_PLANT, EPS, tau, FS, delay_samples=-1)
    with pytest.raises(IdentificationError):
        simulate_deadzone(TwoMassParameters(-1, 1, 1, 1, 1, 1), EPS, tau, FS)


def test_motor_velocity_fast_path_is_bitwise_the_same():
    tau = excitation(16_000)
    for d in (0, 1, 2):
        full = simulate_deadzone(REFERENCE_PLANT, EPS, tau, FS, delay_samples=d)
        fast = simulate_motor_velocity(REFERENCE_PLANT, EPS, tau, FS, delay_samples=d)
        np.testing.assert_array_equal(fast, full.motor_velocity)
