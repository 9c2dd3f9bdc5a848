"""The drift-free torque residual, checked against the simulated machine (sim_drive.plant).

Independent answers: sim_drive integrates the full two-mass system with its own
event location; the residual re-simulates only the load from the measured
motor position. With the true parameters the two must agree to the noise
floor, and the load the residual simulates must be the plant's load.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.signal import sosfiltfilt

from commission.config import ExcitationConfig
from commission.exceptions import IdentificationError
from commission.excitation import chirp
from commission.ident.residual import prepare_residual, torque_residual
from sim_drive.plant import Plant, PlantParameters

FS = 8000.0
TRUE = dict(J_m=4.78e-4, J_l=1.92e-4, B_m=0.84e-2, B_l=0.53e-2, K=23.10, D=1.54e-2)
NOISE_NM = 1e-4


def _run(epsilon_deg: float):
    tau = chirp(ExcitationConfig()).samples
    return Plant(PlantParameters(**TRUE, epsilon_deg=epsilon_deg, torque_noise_nm=NOISE_NM, seed=3),
                 FS).run_torque(tau)


@pytest.fixture(scope="module")
def reference():
    return _run(0.40)


@pytest.fixture(scope="module")
def problem(reference):
    return prepare_residual(reference.torque_ref, FS, motor_position=reference.motor_position,
                            cutoff_hz=400.0)


def test_residual_at_truth_is_at_the_noise_floor(problem):
    r = torque_residual(problem, **TRUE, epsilon_rad=math.radians(0.40))
    # white torque noise σ = 1e-4 N·m, low-passed to 400 of 4000 Hz: ≈ 3.2e-5 N·m; allow bursts
    assert r.cost < 1e-4
    ref = float(np.sqrt(np.mean(problem.torque_f ** 2)))
    assert r.cost / ref < 1e-3
    assert r.simulation.events > 10


def test_a_record_cut_from_a_running_axis_starts_its_load_at_the_motors_speed(reference, problem):
    # 1 s into the run the axis turns at ~9 rad/s: a load simulated from rest needed most of the record to
    # catch up, and the residual at the truth was far above the noise floor
    cut = slice(int(FS), None)
    moving = prepare_residual(reference.torque_ref[cut], FS, motor_position=reference.motor_position[cut],
                              cutoff_hz=400.0)
    assert moving.start.speed_rad_s > 5.0 and not problem.start.moving
    r = torque_residual(moving, **TRUE, epsilon_rad=math.radians(0.40))
    # (the rest: the load's own oscillation about the motor's speed, which the start does not know)
    assert r.cost / float(np.sqrt(np.mean(moving.torque_f ** 2))) < 5e-3


def test_minimum_in_epsilon_is_sharp(problem):
    c0 = torque_residual(problem, **TRUE, epsilon_rad=math.radians(0.40)).cost
    for de in (-0.05, -0.01, 0.01, 0.05):
        c = torque_residual(problem, **TRUE, epsilon_rad=math.radians(0.40 + de)).cost
        assert c > 5 * c0, (de, c, c0)


def test_simulated_load_follows_the_plant(reference, problem):
    r = torque_residual(problem, **TRUE, epsilon_rad=math.radians(0.40))
    # the plant's load (24-bit encoder, ±1.9e-7 rad quantisation) vs the load simulated from the
    # measured motor position: the same trajectory outside the short chaotic impact windows
    err = np.abs(r.simulation.load_position - (reference.load_position - reference.motor_position[0]))
    assert np.median(err) < 2e-6
    assert np.mean(err < 1e-5) > 0.99


def test_alignment_one_sample_off_is_much_worse(reference):
    """The derived alignment ((τ[k−1]+τ[k])/2 against Δ²x[k]) beats shifting τ by one sample."""
    p = prepare_residual(reference.torque_ref, FS, motor_position=reference.motor_position)
    tau_shift = np.concatenate(([0.0], reference.torque_ref[:-1]))
    q = prepare_residual(tau_shift, FS, motor_position=reference.motor_position)
    c_right = torque_residual(p, **TRUE, epsilon_rad=math.radians(0.4)).cost
    c_wrong = torque_residual(q, **TRUE, epsilon_rad=math.radians(0.4)).cost
    assert c_wrong > 20 * c_right


def test_position_rebuilt_from_velocity_gives_the_same_residual(reference, problem):
    q = prepare_residual(reference.torque_ref, FS, motor_velocity=reference.motor_velocity, cutoff_hz=400.0)
    a = torque_residual(problem, **TRUE, epsilon_rad=math.radians(0.4))
    b = torque_residual(q, **TRUE, epsilon_rad=math.radians(0.4))
    assert_allclose(b.cost, a.cost, rtol=1e-3)


def test_compiled_filter_equals_scipy(problem):
    x = np.random.default_rng(0).standard_normal(problem.acceleration.size)
    assert_allclose(problem.lowpass(x), sosfiltfilt(problem.sos, x)[:: problem.decimation], atol=1e-12)


def test_no_backlash_plant_residual_is_minimal_at_zero():
    rec = _run(0.0)
    p = prepare_residual(rec.torque_ref, FS, motor_position=rec.motor_position)
    c0 = torque_residual(p, **TRUE, epsilon_rad=0.0).cost
    c1 = torque_residual(p, **TRUE, epsilon_rad=math.radians(0.01)).cost
    assert c0 < 1e-4
    assert c1 > 3 * c0


def test_bad_inputs_raise():
    with pytest.raises(IdentificationError):
        prepare_residual(np.zeros(100), FS)
    with pytest.raises(IdentificationError):
        prepare_residual(np.zeros(100), FS, motor_velocity=np.zeros(100), cutoff_hz=5000.0)


# --------------------------------------------------------------------------- issue 8 terms
def test_lagged_torque_matches_a_brute_force_integration():
    """Closed form of the triangle-averaged first-order lag vs a fine explicit integration."""
    from commission.ident.residual import lagged_torque

    rng = np.random.default_rng(1)
    u = rng.standard_normal(60)
    tc = 1.0 / (2 * math.pi * 1000.0)
    sub = 4000  # sub-steps per sample, exact exponential update of the lag (ZOH input)
    h = 1.0 / FS / sub
    e = math.exp(-h / tc)
    tau = u[0]
    fine = np.empty(u.size * sub)
    for k in range(u.size):
        for j in range(sub):
            # mid-point value of the sub-step (exact exponential, evaluated at h/2)
            fine[k * sub + j] = u[k] + (tau - u[k]) * math.exp(-0.5 * h / tc)
            tau = u[k] + (tau - u[k]) * e
    s = (np.arange(sub) + 0.5) / sub
    ref = np.array([np.sum(s * fine[(k - 1) * sub:k * sub]) / sub + np.sum((1 - s) * fine[k * sub:(k + 1) * sub]) / sub
                    for k in range(1, u.size - 1)])
    assert_allclose(lagged_torque(u, FS, tc), ref, atol=1e-8)
    assert_allclose(lagged_torque(u, FS, 0.0), 0.5 * (u[:-2] + u[1:-1]))


def test_local_motor_interpolant_is_exact_on_a_parabola_and_local():
    from commission.ident.residual import motor_interpolant

    n = 40
    k = np.arange(n, dtype=float)
    x = 0.3 * k**2 - 2.0 * k + 1.0
    c = motor_interpolant(x, "local")
    s = 0.37
    mid = ((c[:, 0] * s + c[:, 1]) * s + c[:, 2]) * s + c[:, 3]
    xs = k[:-1] + s
    # interior intervals (the one-sided end slopes are exact for a parabola too with np.gradient)
    assert_allclose(mid[1:-1], (0.3 * xs**2 - 2.0 * xs + 1.0)[1:-1], rtol=1e-12)
    # a kink disturbs only the intervals next to it ("spline" rings through the whole record)
    kink = np.where(k > 20, k - 20.0, 0.0)
    local = motor_interpolant(kink, "local")
    spline = motor_interpolant(kink, "spline")
    far = slice(0, 15)
    assert np.all(local[far] == 0.0)
    assert np.max(np.abs(spline[far])) > 1e-6


@pytest.fixture(scope="module")
def unideal():
    tau = chirp(ExcitationConfig()).samples
    return Plant(PlantParameters(**TRUE, epsilon_deg=0.40, torque_noise_nm=NOISE_NM, seed=3,
                                 coulomb_motor_nm=0.01, coulomb_load_nm=0.01,
                                 current_loop_bandwidth_hz=1000.0), FS).run_torque(tau)


def test_residual_with_the_true_friction_and_lag_is_at_the_noise_floor(unideal):
    p = prepare_residual(unideal.torque_ref, FS, motor_position=unideal.motor_position, cutoff_hz=400.0,
                         velocity_scale_rad_s=2e-3)
    ref = float(np.sqrt(np.mean(p.torque_f ** 2)))
    tc = 1.0 / (2 * math.pi * 1000.0)
    full = torque_residual(p, **TRUE, epsilon_rad=math.radians(0.40), coulomb_motor_nm=0.01,
                           coulomb_load_nm=0.01, lag_s=tc)
    no_lag = torque_residual(p, **TRUE, epsilon_rad=math.radians(0.40), coulomb_motor_nm=0.01,
                             coulomb_load_nm=0.01)
    lumped = torque_residual(p, **TRUE, epsilon_rad=math.radians(0.40), coulomb_motor_nm=0.02, lag_s=tc)
    # outside the few stick windows (velocity reversals, the identifier's own v_s) at the floor
    v = np.abs(full.vector)
    assert np.median(v) / ref < 5e-4
    assert full.cost / ref < 5e-3
    assert no_lag.cost > 10 * full.cost
    assert lumped.cost > 5 * full.cost  # load friction is not motor friction: the gap shows it


@pytest.mark.parametrize("coulomb_load_nm", [0.05])
def test_load_simulation_with_stiff_coulomb_friction_matches_an_implicit_solver(coulomb_load_nm):
    # F_cl/J_l over v_s = 1e-3 rad/s makes the smooth sign's rate 33× the sample rate: explicit
    # RK4 needs sub-steps near zero speed. Reference: scipy's Radau (implicit) on the same ODE, no
    # backlash (always in contact), the motor moved by the same interpolant of a recorded position.
    from scipy.integrate import solve_ivp

    from commission.ident.residual import simulate_load

    tau = chirp(ExcitationConfig()).samples[:1600]  # 0.2 s: the load reverses several times
    r = Plant(PlantParameters(**TRUE, epsilon_deg=0.0, seed=3), FS).run_torque(tau)
    vs = 1e-3
    p = prepare_residual(r.torque_ref, FS, motor_position=r.motor_position, cutoff_hz=400.0,
                         velocity_scale_rad_s=vs)
    sim = simulate_load(p, TRUE["J_l"], TRUE["B_l"], TRUE["K"], TRUE["D"], 0.0, coulomb_load_nm)
    c, Ts = p.spline, 1.0 / FS
    kj, dj, bj = (TRUE[k] / TRUE["J_l"] for k in ("K", "D", "B_l"))
    cj = coulomb_load_nm / TRUE["J_l"]

    def motor(t: float) -> tuple[float, float]:
        k = min(int(t / Ts), c.shape[0] - 1)
        s = t / Ts - k
        a3, a2, a1, a0 = c[k]
        return ((a3 * s + a2) * s + a1) * s + a0, ((3 * a3 * s + 2 * a2) * s + a1) / Ts

    def rhs(t: float, y: np.ndarray) -> list[float]:
        xm, vm = motor(t)
        return [y[1], kj * (xm - y[0]) + dj * (vm - y[1]) - bj * y[1] - cj * math.tanh(y[1] / vs)]

    n = c.shape[0]
    t_eval = np.arange(n + 1) * Ts
    ref = solve_ivp(rhs, (0.0, n * Ts), [sim.load_position[0], 0.0], method="Radau", t_eval=t_eval,
                    rtol=1e-8, atol=1e-12)
    assert ref.success
    motion = float(np.ptp(ref.y[0]))
    assert motion > 1e-3
    assert np.max(np.abs(sim.load_position - ref.y[0])) < 1e-5 * motion


@pytest.mark.parametrize(("epsilon_deg", "coulomb_load_nm"), [(0.4, 0.05), (2.0, 0.05), (2.0, 0.2)])
def test_load_friction_beyond_rk4s_reach_matches_an_implicit_solver(epsilon_deg, coulomb_load_nm):
    # v_s = 1e-5 rad/s puts the smooth sign's rate hundreds of times above the sample rate, beyond
    # the RK4 sub-steps' cap (a fit's load inertia driven towards zero does that): the load sticks
    # and slips, in the gap and in contact. Reference: scipy's Radau on the dead-zone spring.
    from scipy.integrate import solve_ivp

    from commission.ident.residual import _MAX_STIFF_PARTS, simulate_load

    vs = 1e-5
    eps = math.radians(epsilon_deg)
    tau = 0.3 * np.sin(2 * np.pi * 20.0 * np.arange(1600) / FS)  # the motor crosses the gap 16 times
    r = Plant(PlantParameters(**TRUE, epsilon_deg=epsilon_deg, seed=3), FS).run_torque(tau)
    p = prepare_residual(r.torque_ref, FS, motor_position=r.motor_position, cutoff_hz=400.0,
                         velocity_scale_rad_s=vs)
    sim = simulate_load(p, TRUE["J_l"], TRUE["B_l"], TRUE["K"], TRUE["D"], eps, coulomb_load_nm)
    c, Ts = p.spline, 1.0 / FS
    kj, dj, bj = (TRUE[k] / TRUE["J_l"] for k in ("K", "D", "B_l"))
    cj = coulomb_load_nm / TRUE["J_l"]
    assert cj / vs * Ts / 2 > 2 * _MAX_STIFF_PARTS

    def rhs(t: float, y: np.ndarray) -> list[float]:
        k = min(int(t / Ts), c.shape[0] - 1)
        s = t / Ts - k
        a3, a2, a1, a0 = c[k]
        xm, vm = ((a3 * s + a2) * s + a1) * s + a0, ((3 * a3 * s + 2 * a2) * s + a1) / Ts
        z = xm - y[0]
        spring = kj * (z - math.copysign(eps, z)) + dj * (vm - y[1]) if abs(z) > eps else 0.0
        return [y[1], spring - bj * y[1] - cj * math.tanh(y[1] / vs)]

    n = c.shape[0]
    ref = solve_ivp(rhs, (0.0, n * Ts), [sim.load_position[0], sim.load_velocity[0]], method="Radau",
                    t_eval=np.arange(n + 1) * Ts, rtol=1e-9, atol=1e-13, max_step=Ts)
    assert ref.success
    assert np.mean(np.abs(ref.y[1]) < 5 * vs) > 0.05  # it sticks
    assert sim.events >= 6
    motion = float(np.ptp(ref.y[0]))
    assert np.max(np.abs(sim.load_position - ref.y[0])) < 3e-4 * motion


def test_contact_steps_are_exact_on_a_stiff_light_load():
    # In contact (no backlash, no load friction) each sample interval is the exact solution of the
    # linear ODE driven by the cubic motor interpolant (contact_map). Reference: DOP853 at
    # rtol 1e-13 on each interval of the same cubic. ω_a·Ts = 0.16, where one RK4 step per
    # sample (the previous integrator) was off by 3e-9 in position and 1.6e-8 in velocity.
    from scipy.integrate import solve_ivp

    from commission.ident.residual import _simulate_load, contact_map, simulate_load

    plant = dict(J_m=4.78e-4, J_l=1.0e-4, B_m=0.84e-2, B_l=0.3e-2, K=160.0, D=2e-3)
    tau = chirp(ExcitationConfig()).samples[:800]
    r = Plant(PlantParameters(**plant, epsilon_deg=0.0, seed=3), FS).run_torque(tau)
    p = prepare_residual(r.torque_ref, FS, motor_position=r.motor_position, cutoff_hz=400.0)
    sim = simulate_load(p, plant["J_l"], plant["B_l"], plant["K"], plant["D"], 0.0)
    c, Ts = p.spline, 1.0 / FS
    kj, dj, bj = (plant[k] / plant["J_l"] for k in ("K", "D", "B_l"))
    I0, I1, *_ = _simulate_load(c, Ts, 1.0, bj, kj, dj, 0.0, sim.load_position[0], 0.0, 0.0, 1.0,
                                contact_map(Ts, kj, dj, bj), False, np.zeros(c.shape[0] - 1), 0.0,
                                np.array([1.0, 0.0, 0.0, 0.0, 0.0]), np.zeros(0), 0.0)
    q = [sim.load_position[0], 0.0]
    xs, vs, i0s, i1s = [q[0]], [q[1]], [], []
    for k in range(c.shape[0]):
        a3, a2, a1, a0 = c[k]

        def rhs(s: float, z: np.ndarray, a3=a3, a2=a2, a1=a1, a0=a0) -> list[float]:
            xm = ((a3 * s + a2) * s + a1) * s + a0
            vm = ((3 * a3 * s + 2 * a2) * s + a1) / Ts
            y = xm - z[0]
            return [Ts * z[1], Ts * (kj * y + dj * (vm - z[1]) - bj * z[1]), y, s * y]

        sol = solve_ivp(rhs, (0.0, 1.0), [q[0], q[1], 0.0, 0.0], method="DOP853", rtol=1e-13, atol=1e-16)
        q = sol.y[:2, -1]
        xs.append(q[0])
        vs.append(q[1])
        i0s.append(sol.y[2, -1])
        i1s.append(sol.y[3, -1])
    xs, vs = np.array(xs), np.array(vs)
    assert np.max(np.abs(sim.load_position - xs)) < 1e-11 * np.ptp(xs)
    assert np.max(np.abs(sim.load_velocity - vs)) < 1e-11 * np.ptp(vs)
    assert_allclose(I0, i0s, rtol=0, atol=1e-11 * np.max(np.abs(i0s)))
    assert_allclose(I1, i1s, rtol=0, atol=1e-11 * np.max(np.abs(i1s)))


def test_contact_steps_with_saturated_load_friction_are_exact():
    # Where the load moves faster than _SATURATED·v_s at both ends of a contact interval, the
    # smooth sign is ±1 in float64 and the load friction a constant force: the interval is the
    # exact solution (contact_map with the force folded in). Reference: DOP853 at rtol 1e-13 on
    # each such interval, from the simulation's own state at its start (local error). One RK4
    # step per sample was off by ~1e-9 of the motion there.
    from scipy.integrate import solve_ivp

    from commission.ident.residual import _SATURATED, _simulate_load, contact_map

    plant = dict(J_m=4.78e-4, J_l=1.0e-4, B_m=0.84e-2, B_l=0.3e-2, K=160.0, D=2e-3)
    tau = chirp(ExcitationConfig()).samples[:1600]
    r = Plant(PlantParameters(**plant, epsilon_deg=0.0, seed=3), FS).run_torque(tau)
    p = prepare_residual(r.torque_ref, FS, motor_position=r.motor_position, cutoff_hz=400.0)
    c, Ts = p.spline, 1.0 / FS
    kj, dj, bj = (plant[k] / plant["J_l"] for k in ("K", "D", "B_l"))
    cj, vs = 0.01 / plant["J_l"], 1e-3
    I0, I1, xl, vl, *_ = _simulate_load(c, Ts, 1.0, bj, kj, dj, 0.0, 0.0, 0.0, cj, 1.0 / vs,
                                        contact_map(Ts, kj, dj, bj), True, np.zeros(c.shape[0] - 1), 0.0,
                                        np.array([1.0, 0.0, 0.0, 0.0, 0.0]), np.zeros(0), 0.0)
    saturated = np.flatnonzero((np.abs(vl[:-1]) > _SATURATED * vs) & (np.abs(vl[1:]) > _SATURATED * vs)
                               & (np.sign(vl[:-1]) == np.sign(vl[1:])))
    assert saturated.size > 0.5 * c.shape[0]  # most of the record: the check covers the common case
    worst = 0.0
    for k in saturated[::20]:
        a3, a2, a1, a0 = c[k]

        def rhs(s: float, z: np.ndarray, a3=a3, a2=a2, a1=a1, a0=a0) -> list[float]:
            xm = ((a3 * s + a2) * s + a1) * s + a0
            vm = ((3 * a3 * s + 2 * a2) * s + a1) / Ts
            y = xm - z[0]
            f = cj * math.tanh(z[1] / vs)
            return [Ts * z[1], Ts * (kj * y + dj * (vm - z[1]) - bj * z[1] - f), y, s * y]

        sol = solve_ivp(rhs, (0.0, 1.0), [xl[k], vl[k], 0.0, 0.0], method="DOP853", rtol=1e-13, atol=1e-16)
        x1, v1, i0, i1 = sol.y[:, -1]
        worst = max(worst, abs(xl[k + 1] - x1) / np.ptp(xl), abs(vl[k + 1] - v1) / np.ptp(vl),
                    abs(I0[k] - i0) / np.max(np.abs(I0)), abs(I1[k] - i1) / np.max(np.abs(I1)))
    assert worst < 1e-11


def test_load_simulation_is_continuous_in_the_load_friction_down_to_zero(problem):
    # F_cl = 0 modelled (RK4 contact steps) and F_cl → 0⁺ must be one smooth function, as the
    # finite differences of the F_cl column at its bound 0 need: the change is linear in F_cl
    # down to round-off. Without the term (None) whole contact intervals are exact instead; the
    # two integrators differ by about what 3e-10 N·m of friction changes.
    from commission.ident.residual import simulate_load

    args = (TRUE["J_l"], TRUE["B_l"], TRUE["K"], TRUE["D"], math.radians(0.40))
    at0 = simulate_load(problem, *args, 0.0).shaft_torque
    gain = [float(np.max(np.abs(simulate_load(problem, *args, f).shaft_torque - at0))) / f
            for f in (1e-12, 1e-11, 1e-10)]
    assert max(gain) < 1.2 * min(gain)
    none = simulate_load(problem, *args).shaft_torque
    assert 0 < np.max(np.abs(none - at0)) < 1e-5 * np.max(np.abs(at0))


def test_the_observer_without_gain_is_the_open_loop_simulation_and_with_it_follows_the_load():
    # 100 Hz, J_l = J_m, ζ 0.05: over its impacts the load simulated open loop parts from the real
    # one and the true parameters leave ~30 % of τ_ref; corrected after every sample from its own
    # residual it stays with it (the noise floor, 3e-4), and ε 10 % off still shows
    from commission.ident.residual import Observer, residual_vector

    J = 4.78e-4
    true = dict(J_m=J, J_l=J, B_m=0.84e-2, B_l=0.53e-2 * math.sqrt(2.5), K=(2 * math.pi * 100) ** 2 * J / 2,
                D=0.05 * 2 * math.pi * 100 * J)
    tau = chirp(ExcitationConfig()).samples
    r = Plant(PlantParameters(**true, epsilon_deg=0.20, torque_noise_nm=1e-4, seed=3), FS).run_torque(tau)
    p = prepare_residual(r.torque_ref, FS, motor_position=r.motor_position, cutoff_hz=400.0)
    ref = float(np.sqrt(np.mean(p.torque_f ** 2)))
    rms = lambda v: float(np.sqrt(np.mean(v[4:-4] ** 2))) / ref  # noqa: E731
    eps = math.radians(0.20)
    open_loop = residual_vector(p, **true, epsilon_rad=eps)
    assert np.array_equal(open_loop, residual_vector(p, **true, epsilon_rad=eps, observer=Observer()))
    assert rms(open_loop) > 0.1
    observer = Observer.design(FS, 600.0, 800.0, true["K"], true["D"])
    at_truth = rms(residual_vector(p, **true, epsilon_rad=eps, observer=observer))
    assert at_truth < 1e-3
    assert rms(residual_vector(p, **true, epsilon_rad=0.9 * eps, observer=observer)) > 10 * at_truth


def test_the_encoders_note_says_whether_the_residuals_low_pass_could_go_lower() -> None:
    """A 17-bit encoder on a 227 Hz plant (family member 22:083): from a start resonating at a quarter of
    that, the low-pass is lowered until the quantization leaves the target, and the note names both
    cut-offs; from the true plant, twice its resonance is the cut-off already, and the note says the
    quantization stays above the target there (it once read "at 453 Hz instead of 453 Hz")."""
    from dataclasses import replace

    from commission.ident.options import IdentificationOptions
    from commission.ident.start import cutoff_note, excited_band_hz, residual_cutoff
    from commission.ident.twomass import modes
    from sim_drive.family import member

    m = member(22, 83)
    rec = m.simulate()
    opt, target = IdentificationOptions(), 2.5e-3
    ref = float(np.sqrt(np.mean(rec.torque_ref ** 2)))
    band = excited_band_hz(rec.torque_ref, rec.sample_rate_hz)
    soft = replace(m.two_mass, K=m.two_mass.K / 16, D=m.two_mass.D / 4)
    lowered = residual_cutoff(rec, soft, band, opt.residual_cutoff_hz, ref, target)
    assert lowered["cutoff_hz"] < 0.5 * lowered["unlowered_cutoff_hz"]
    assert lowered["quantization_floor_ratio"] == pytest.approx(target, rel=1e-6)
    note = cutoff_note(lowered)
    assert note is not None
    assert f"at {lowered['cutoff_hz']:.0f} Hz instead of {lowered['unlowered_cutoff_hz']:.0f} Hz" in note
    floor = residual_cutoff(rec, m.two_mass, band, opt.residual_cutoff_hz, ref, target)
    assert floor["cutoff_hz"] == pytest.approx(2.0 * modes(m.two_mass).f_resonance_hz, rel=1e-9)
    assert floor["quantization_floor_ratio"] > 10 * target
    note = cutoff_note(floor)
    assert note is not None and "instead of" not in note
    assert f"{100 * floor['quantization_floor_ratio']:.2g} % of RMS τ_ref even low-passed at {floor['cutoff_hz']:.0f} Hz" in note
    # where the quantization stays below the target the cut-off is left alone, with no note
    fine = residual_cutoff(rec, m.two_mass, band, opt.residual_cutoff_hz, ref, 10.0)
    assert "unlowered_cutoff_hz" not in fine and cutoff_note(fine) is None
