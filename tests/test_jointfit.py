"""Search of the starts and the joint least-squares fit on the torque residual."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from commission.config import ExcitationConfig
from commission.excitation import chirp
from commission.ident.jointfit import (
    SearchCell,
    burst_mask,
    joint_fit,
    linear_start,
    search_starts,
)
from commission.ident.residual import prepare_residual
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters
from sim_drive.plant import Plant, PlantParameters

FS = 8000.0
EPS_DEG = 0.40


@pytest.fixture(scope="module")
def problem():
    tau = chirp(ExcitationConfig()).samples
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=EPS_DEG,
                              torque_noise_nm=1e-4, seed=5), FS).run_torque(tau)
    return prepare_residual(r.torque_ref, FS, motor_position=r.motor_position, cutoff_hz=400.0)


def test_linear_start_is_exact_on_a_physical_fit():
    num, den = REFERENCE_PLANT.velocity_tf()
    p, how = linear_start(num, den)
    assert how == "exact"
    assert_allclose(p.as_array(), REFERENCE_PLANT.as_array(), rtol=1e-9)


def test_linear_start_survives_an_unphysical_damping_split():
    num, den = REFERENCE_PLANT.velocity_tf()
    num = num.copy()
    num[1] *= 0.2  # (D + B_l)/(J_m J_l) far too low: B_l or D comes out negative in the exact map
    p, how = linear_start(num, den)
    assert how == "modes"
    assert min(p.as_array()) > 0
    assert_allclose(p.J_m, REFERENCE_PLANT.J_m, rtol=1e-9)
    assert_allclose(p.B_m + p.B_l, REFERENCE_PLANT.B_m + REFERENCE_PLANT.B_l, rtol=1e-9)


def test_joint_fit_converges_from_a_start_fifteen_percent_off(problem):
    f = np.array([1.15, 0.85, 1.3, 0.7, 0.85, 1.2])  # J_m J_l B_m B_l K D
    start = TwoMassParameters(*(REFERENCE_PLANT.as_array() * f))
    jf = joint_fit(problem, start, [SearchCell(math.radians(0.3), 0.5, 1.0, 0.0)])
    assert abs(math.degrees(jf.epsilon_rad) - EPS_DEG) < 1e-3
    assert_allclose(jf.parameters.as_array(), REFERENCE_PLANT.as_array(), rtol=2e-3)
    lo, hi = jf.epsilon_interval_rad
    assert lo <= jf.epsilon_rad <= hi
    assert jf.cost < 1e-4
    assert all(v < 0.01 for v in jf.relative_stderr.values())


def test_robust_scale_changes_nothing_when_the_first_start_converges(problem):
    # the Cauchy loss is only switched on for starts stuck on a bursty plateau: a start that
    # converges gives the same evaluations and the same result, bit for bit
    f = np.array([1.1, 0.9, 1.2, 0.8, 0.9, 1.1])
    start = TwoMassParameters(*(REFERENCE_PLANT.as_array() * f))
    cells = [SearchCell(math.radians(0.35), 0.5, 1.0, 0.0), SearchCell(math.radians(0.2), 0.5, 1.0, 0.0)]
    ref = float(np.sqrt(np.mean(problem.torque_f ** 2)))
    plain = joint_fit(problem, start, cells, stop_cost_nm=1e-3 * ref)
    robust = joint_fit(problem, start, cells, stop_cost_nm=1e-3 * ref, robust_scale_nm=3e-3 * ref)
    assert not plain.robust_loss and not robust.robust_loss
    assert robust.evaluations == plain.evaluations
    assert robust.epsilon_rad == plain.epsilon_rad
    assert_allclose(robust.parameters.as_array(), plain.parameters.as_array(), rtol=0, atol=0)
    assert abs(math.degrees(robust.epsilon_rad) - EPS_DEG) < 1e-3


def test_joint_fit_reaches_zero_when_started_with_backlash():
    tau = chirp(ExcitationConfig()).samples
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.0,
                              torque_noise_nm=1e-4, seed=5), FS).run_torque(tau)
    p = prepare_residual(r.torque_ref, FS, motor_position=r.motor_position)
    jf = joint_fit(p, REFERENCE_PLANT, [SearchCell(math.radians(0.05), 0.4, 1.0, 0.0)])
    assert math.degrees(jf.epsilon_rad) < 0.002


def test_bayes_finds_the_grid_cell_with_fewer_evaluations(problem):
    start = TwoMassParameters(*(REFERENCE_PLANT.as_array() * np.array([1.0, 1.03, 1.2, 0.7, 1.01, 1.07])))
    eps = np.radians(np.round(np.arange(0.01, 1.00001, 0.01), 4))
    g = search_starts(problem, start, eps, (0.2, 0.5, 0.8), method="grid", n_best=1)
    b = search_starts(problem, start, eps, (0.2, 0.5, 0.8), method="bayes", n_best=1)
    assert g.evaluations == 300
    assert b.evaluations < g.evaluations / 3
    assert abs(b.best[0].epsilon_rad - g.best[0].epsilon_rad) <= math.radians(0.02)
    assert b.best[0].cost <= 1.05 * g.best[0].cost


def test_burst_mask_keeps_gaussian_noise_and_drops_bursts():
    rng = np.random.default_rng(1)
    r = rng.standard_normal(10_000)
    assert burst_mask(r, 800.0).all()
    r[5000:5010] += 100.0
    keep = burst_mask(r, 800.0, guard_s=0.01)
    assert not keep[5000:5010].any()
    assert not keep[4992] and not keep[5017]
    assert keep.mean() > 0.99


def test_projected_fit_solves_motor_coulomb_and_first_order_lag_linearly():
    """The motor Coulomb level is a linear column (exact); the lag column gives T_c to first order."""
    from commission.ident.jointfit import LoadRates, ModelTerms, projected_fit

    tau = chirp(ExcitationConfig()).samples
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=EPS_DEG, torque_noise_nm=1e-4,
                              seed=5, coulomb_motor_nm=0.01, current_loop_bandwidth_hz=1000.0),
              FS).run_torque(tau)
    p = prepare_residual(r.torque_ref, FS, motor_position=r.motor_position, cutoff_hz=400.0,
                         velocity_scale_rad_s=2e-3)
    rates = LoadRates.of(REFERENCE_PLANT)
    eps = math.radians(EPS_DEG)
    tc = 1.0 / (2 * math.pi * 1000.0)
    exact = projected_fit(p, rates, eps, coulomb_motor=True, lag_s=tc)
    assert exact.coulomb_motor_nm == pytest.approx(0.01, rel=0.01)
    assert exact.parameters.J_m == pytest.approx(REFERENCE_PLANT.J_m, rel=1e-3)
    first_order = projected_fit(p, rates, eps, coulomb_motor=True, lag_linear=True)
    assert first_order.lag_linear_s == pytest.approx(tc, rel=0.2)
    assert ModelTerms(current_loop=True).names() == ("current_loop",)


def _exp_problem():
    """A small smooth nonlinear least-squares problem: y = a·exp(−b·t) + c·sin(d·t) + noise."""
    t = np.linspace(0.0, 4.0, 400)
    truth = np.array([2.0, 0.7, 0.5, 3.0])
    rng = np.random.default_rng(3)
    y = truth[0] * np.exp(-truth[1] * t) + truth[2] * np.sin(truth[3] * t) + 1e-3 * rng.standard_normal(t.size)
    calls = [0]
    cache: dict[bytes, np.ndarray] = {}

    def fun(x):
        key = np.asarray(x, dtype=float).tobytes()
        if key not in cache:
            calls[0] += 1
            cache[key] = x[0] * np.exp(-x[1] * t) + x[2] * np.sin(x[3] * t) - y
        return cache[key]

    def fd(x, f0):
        cols = []
        for i in range(x.size):
            xi = x.copy()
            xi[i] += 1e-7
            cols.append((fun(xi) - f0) / 1e-7)
        return np.stack(cols, axis=1)

    return fun, fd, calls, truth


@pytest.mark.parametrize("x0", [(1.5, 0.5, 0.8, 2.8), (2.5, 1.0, 0.3, 3.2)])
def test_broyden_and_finite_difference_jacobians_reach_the_same_solution(x0):
    """Same end point (the convergence safeguard ends on a finite-difference Jacobian) with
    fewer residual evaluations (Jacobians included)."""
    from commission.ident.jointfit import _Jacobian, _least_squares

    lo, hi = np.full(4, -10.0), np.full(4, 10.0)
    sols, counts = {}, {}
    for broyden in (False, True):
        fun, fd, calls, truth = _exp_problem()
        jac = _Jacobian(fun, fd, broyden=broyden)
        sol = _least_squares(fun, np.array(x0), jac, lo, hi, 60)
        assert sol.status > 0
        sols[broyden], counts[broyden] = sol.x, calls[0]
        if broyden:
            assert jac.n_broyden > 0
    assert_allclose(sols[True], sols[False], rtol=1e-6, atol=1e-8)
    assert_allclose(sols[False], truth, rtol=1e-2)
    assert counts[True] < counts[False]


def test_joint_fit_broyden_matches_finite_differences_with_fewer_evaluations(problem):
    f = np.array([1.15, 0.85, 1.3, 0.7, 0.85, 1.2])  # J_m J_l B_m B_l K D
    start = TwoMassParameters(*(REFERENCE_PLANT.as_array() * f))
    cell = [SearchCell(math.radians(0.3), 0.5, 1.0, 0.0)]
    fd = joint_fit(problem, start, cell, jacobian="finite_difference")
    br = joint_fit(problem, start, cell, jacobian="broyden")
    assert abs(math.degrees(br.epsilon_rad - fd.epsilon_rad)) < 1e-4
    assert_allclose(br.parameters.as_array(), fd.parameters.as_array(), rtol=1e-4)
    assert br.cost == pytest.approx(fd.cost, rel=1e-6)
    assert br.evaluations < fd.evaluations
    with pytest.raises(ValueError):
        joint_fit(problem, start, cell, jacobian="newton")
