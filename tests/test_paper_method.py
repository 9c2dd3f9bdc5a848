"""The paper's procedure (steps 4–6) on data from sim_drive's plant (the "real machine")."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from numpy.testing import assert_allclose

from commission.ident.backlash import max_output_error, search_epsilon_grid, simulate_motor_velocity
from commission.ident.paper import frd_error, paper_identify
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters

FS = 8000.0


def excitation(n: int = 80_000) -> np.ndarray:
    t = np.arange(n) / FS
    A = 0.0764
    return A * np.sin(2 * np.pi * (0.1 * t + (400 - 0.1) * t**2 / 20.0)) + 3 * A * np.sin(
        2 * np.pi * 0.1 * t
    )


@pytest.fixture(scope="module")
def record():
    """Reference plant, ε = 0.40°, 24-bit encoders: (torque, motor velocity)."""
    pm = pytest.importorskip("sim_drive.plant")
    tau = excitation()
    resp = pm.Plant(pm.PlantParameters(), FS).run_torque(tau)
    return tau, resp.motor_velocity


def _rel_errors(p: TwoMassParameters) -> np.ndarray:
    return p.as_array() / REFERENCE_PLANT.as_array() - 1.0


def test_paper_loss_has_its_minimum_at_the_true_epsilon(record):
    tau, v = record

    def loss(e: float) -> float:
        return max_output_error(v, simulate_motor_velocity(REFERENCE_PLANT, e, tau, FS))

    res = search_epsilon_grid(loss)
    assert math.degrees(res.epsilon_rad) == pytest.approx(0.40, abs=0.02)
    # METHOD.md: 0.55 rad/s at 0.01°, 0.017 at 0.40°. Measured here: 0.557 and 0.0030
    # (the 24-bit encoder's velocity step 2π/2²⁴·8000 = 0.0030 rad/s is the floor).
    assert loss(math.radians(0.01)) == pytest.approx(0.55, rel=0.1)
    assert res.loss < 0.017


def test_paper_identify_with_the_true_linear_model(record):
    tau, v = record
    res = paper_identify(tau, v, FS, REFERENCE_PLANT, search="bayes", seed=0)
    it0 = res.iterations[0]
    assert res.stop_reason == "frd_tol"
    assert res.backlash_detected
    assert res.epsilon_deg == pytest.approx(0.40, abs=0.02)
    assert it0.search.evaluations < 100
    assert res.frd_error < 0.01
    assert set(res.timings_s) >= {"search", "frd", "fit", "simulate", "total"}


def test_step6_brings_a_near_fit_closer_to_the_truth(record):
    tau, v = record
    # 1 % off in every parameter (J_l and K the other way)
    start = TwoMassParameters(*(REFERENCE_PLANT.as_array() * [1.01, 1 / 1.01, 1.01, 1.01, 1 / 1.01, 1.01]))
    res = paper_identify(tau, v, FS, start, search="grid", correction="output",
                         max_iterations=2, frd_tol=1e-6)
    a, b = res.iterations[:2]
    # measured: frd_error 0.017 → 0.0042, worst parameter error 1.0 % → 0.6 % (B_m), ε 0.39° → 0.40°
    assert b.frd_error < 0.5 * a.frd_error
    assert np.max(np.abs(_rel_errors(b.params))) < np.max(np.abs(_rel_errors(a.params)))
    assert abs(b.epsilon_deg - 0.40) <= abs(a.epsilon_deg - 0.40)


def test_paper_identify_end_to_end_from_the_frequency_fit(record):
    """Steps 2–6 with the package's FRD and transfer-function fit. Accuracy is whatever
    it is (METHOD.md predicts failure on a biased linear fit); this checks the chain runs
    and reports coherent figures."""
    frd_mod = pytest.importorskip("commission.ident.frd")
    tf_mod = pytest.importorskip("commission.ident.tffit")
    tau, v = record
    fit = tf_mod.fit_transfer_function(frd_mod.estimate_frd(tau, v, FS))
    res = paper_identify(tau, v, FS, fit, search="grid", max_iterations=2)
    assert 1 <= len(res.iterations) <= 2
    assert np.all(np.isfinite(res.params.as_array()))
    assert math.isfinite(res.frd_error) and res.frd_error >= 0.0
    assert res.epsilon_rad == 0.0 or math.radians(0.01) - 1e-12 <= res.epsilon_rad <= math.radians(1.0) + 1e-12
    assert res.stop_reason


@dataclass(frozen=True)
class _FRD:
    frequency_hz: np.ndarray
    response: np.ndarray


def test_frd_error_is_the_relative_rms_of_the_complex_difference():
    f = np.linspace(0.1, 400.0, 4000)
    g = REFERENCE_PLANT.velocity_response(f)
    assert frd_error(_FRD(f, g), _FRD(f, g)) == 0.0
    assert_allclose(frd_error(_FRD(f, g), _FRD(f, 1.1 * g)), 0.1, rtol=1e-12)
    assert_allclose(frd_error(_FRD(f, g), _FRD(f, 1j * g)), math.sqrt(2.0), rtol=1e-12)
