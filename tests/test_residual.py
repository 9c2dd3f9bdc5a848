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
