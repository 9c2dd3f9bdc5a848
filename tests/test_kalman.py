"""The Kalman predictor (commission.ident.kalman) against records of the independent plant simulator
(sim_drive.plant: RK4 sub-steps, its own event location), and the estimator built on it.

At the true parameters and noise levels the normalized prediction errors are white with unit
variance, whatever the sample rate (the predictor is an exact discretization, not an interpolation);
a parameter a few percent off shows in them at once.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from commission.config import ExcitationConfig
from commission.excitation import chirp
from commission.ident.estimator import Hedge, ModelTerms, PemFit, kalman_fit, kalman_resettled, omitted_term_scores
from commission.ident.kalman import innovations, kalman_problem, position_step_rad
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters, modes
from sim_drive.plant import Plant, PlantParameters


def _record(fs: float, duration_s: float, params: TwoMassParameters = REFERENCE_PLANT, eps_deg: float = 0.4, **kw):
    tau = chirp(ExcitationConfig(sample_rate_hz=fs, duration_s=duration_s)).samples
    r = Plant(PlantParameters(**params.as_dict(), epsilon_deg=eps_deg, **kw), fs).run_torque(tau)
    return tau, r


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x * x)))


def _start(p: TwoMassParameters, epsilon_rad: float, *, coulomb_motor_nm: float = 0.0,
           terms: ModelTerms = ModelTerms()) -> PemFit:
    """A Kalman fit's start: only its coordinates are read (its residual, covariance and the like are the fit's)."""
    return PemFit(parameters=p, epsilon_rad=epsilon_rad, coulomb_motor_nm=coulomb_motor_nm, coulomb_load_nm=0.0,
                  lag_s=0.0, terms=terms, residual=np.zeros(1), cost_nm=math.nan, names=(),
                  covariance=np.zeros((0, 0)), n_effective=1.0, evaluations=0, converged=False, message="")


@pytest.mark.parametrize("fs", [2000.0, 8000.0])
def test_at_the_true_parameters_the_prediction_errors_are_the_encoders_noise(fs: float) -> None:
    tau, r = _record(fs, 4.0, encoder_bits_motor=20)
    kp = kalman_problem(tau, r.motor_position, fs)
    step = 2 * math.pi / 2**20
    assert position_step_rad(r.motor_position) == pytest.approx(step, rel=1e-9)
    noise = 1e-4 * kp.torque_rms_nm  # far below the quantization's effect: the filter trusts the model
    at_truth = innovations(kp, REFERENCE_PLANT, math.radians(0.4), process_noise_nm=noise)
    assert at_truth is not None and at_truth.events > 0
    # white, unit variance: the quantization (step²/12) is all that is left
    assert 0.8 < _rms(at_truth.normalized) < 1.3
    assert np.max(np.abs(at_truth.error)) * step / math.sqrt(12) < 4 * step
    for off in (replace(REFERENCE_PLANT, K=1.03 * REFERENCE_PLANT.K), replace(REFERENCE_PLANT, J_l=1.03 * REFERENCE_PLANT.J_l)):
        worse = innovations(kp, off, math.radians(0.4), process_noise_nm=noise)
        assert worse is not None and _rms(worse.normalized) > 1.5 * _rms(at_truth.normalized)
    wrong_gap = innovations(kp, REFERENCE_PLANT, math.radians(0.3), process_noise_nm=noise)
    assert wrong_gap is not None and _rms(wrong_gap.normalized) > 2 * _rms(at_truth.normalized)


def test_read_only_and_writable_records_share_the_predictors_one_compiled_signature() -> None:
    """A record read from a log (read-only arrays) and one simulated here (writable) give the same prediction
    errors through one compiled predictor: numba compiles once per signature, and writability is part of it
    (before, six signatures of the predictor were compiled in a suite run, about 3 s each per process)."""
    from commission.ident import kalman

    fs = 2000.0
    tau, r = _record(fs, 1.0)
    frozen = [a.copy() for a in (tau, r.motor_position, r.load_position)]
    for a in frozen:
        a.flags.writeable = False
    runs = [innovations(kalman_problem(t, ym, fs, load_position=yl), REFERENCE_PLANT, math.radians(0.4),
                        process_noise_nm=1e-3) for t, ym, yl in ((tau, r.motor_position, r.load_position), frozen)]
    assert runs[0] is not None and runs[1] is not None
    assert np.array_equal(runs[0].error, runs[1].error)
    assert tau.flags.writeable and r.motor_position.flags.writeable  # the caller's arrays left as they were
    assert len(kalman._filter.signatures) == 1, kalman._filter.signatures


def test_a_record_cut_from_a_running_axis_is_predicted_from_its_first_samples_speed() -> None:
    # 1 s into the reference run the motor turns at ~9 rad/s: a record that starts there (a CSV cut from a
    # longer log) is no experiment from rest. At the true parameters its first 1,300 prediction errors were
    # ~130 times the encoder's noise when the predictor started at rest; it starts at the record's speed now
    fs = 8000.0
    tau, r = _record(fs, 4.0, encoder_bits_motor=20)
    cut = slice(int(fs), None)
    kp = kalman_problem(tau[cut], r.motor_position[cut], fs)
    speed = (r.motor_position[int(fs) + 1] - r.motor_position[int(fs) - 1]) * fs / 2
    assert speed > 5.0 and kp.start.speed_rad_s == pytest.approx(speed, rel=0.01)
    assert not kalman_problem(tau, r.motor_position, fs).start.moving  # from rest: as before
    inn = innovations(kp, REFERENCE_PLANT, math.radians(0.4), process_noise_nm=1e-4 * kp.torque_rms_nm)
    assert inn is not None
    assert _rms(inn.normalized[:2000]) < 3.0 and _rms(inn.normalized) < 1.5


def test_a_drives_computation_delay_is_predicted_in_whole_samples() -> None:
    """A drive whose torque acts 2 samples after its reference (beyond the hold's own), behind a 1 kHz
    current loop: with the delay the predictor's errors at the true plant are the encoder's noise; without
    it, or with the loop's lag standing in for it, they are not."""
    fs = 8000.0
    tc = 1.0 / (2 * math.pi * 1000.0)
    tau, r = _record(fs, 3.0, encoder_bits_motor=20, current_loop_bandwidth_hz=1000.0, delay_samples=2)
    kw = dict(lag_s=tc, process_noise_nm=1e-4 * float(np.sqrt(np.mean(tau ** 2))))
    delayed = kalman_problem(tau, r.motor_position, fs, delay_samples=2)
    assert delayed.delay_samples == 2 and np.array_equal(delayed.torque_ref[2:], tau[:-2])
    assert delayed.torque_ref[0] == delayed.torque_ref[1] == 0.0
    right = innovations(delayed, REFERENCE_PLANT, math.radians(0.4), **kw)
    assert right is not None and 0.8 < _rms(right.normalized) < 1.3
    plain = kalman_problem(tau, r.motor_position, fs)
    for lag in (tc, tc + 2 / fs):
        wrong = innovations(plain, REFERENCE_PLANT, math.radians(0.4), **{**kw, "lag_s": lag})
        assert wrong is not None and _rms(wrong.normalized) > 3 * _rms(right.normalized)
    with pytest.raises(ValueError):
        kalman_problem(tau, r.motor_position, fs, delay_samples=tau.size)


def test_the_encoders_step_of_a_record_that_never_stops() -> None:
    """1-4 s of the reference run: the motor turns at 9-17 rad/s throughout, so no sample moves it by a
    single step (the smallest move is ~190 steps, which set the quantization floor and the residual's
    low-pass as if the encoder were 12-bit); a change of the move is a whole number of steps too."""
    fs = 8000.0
    tau, r = _record(fs, 4.0, encoder_bits_motor=20)
    x = r.motor_position[int(fs):]
    step = 2 * math.pi / 2**20
    assert np.min(np.abs(np.diff(x))) > 100 * step
    assert position_step_rad(x) == pytest.approx(step, rel=1e-6)


def test_encoders_latched_a_sample_after_the_torque_are_predicted_a_sample_earlier() -> None:
    """A log that puts each torque beside the next sample's position (x[k+1]): the motion leads its torque
    by a sample, which no lag can explain; with the torque taken a sample earlier (delay −1) the predictor's
    errors at the true plant are the encoder's noise again."""
    fs = 8000.0
    tau, r = _record(fs, 3.0, encoder_bits_motor=20)
    tau, x = tau[:-1], r.motor_position[1:]
    early = kalman_problem(tau, x, fs, delay_samples=-1)
    assert np.array_equal(early.torque_ref[:-1], tau[1:]) and early.torque_ref[-1] == tau[-1]
    half = kalman_problem(tau, x, fs, delay_samples=-0.5)  # a mid-cycle latch: the hold half a sample earlier
    np.testing.assert_allclose(half.torque_ref[:-1], 0.5 * (tau[:-1] + tau[1:]), rtol=0, atol=1e-15)
    with pytest.raises(ValueError):
        kalman_problem(tau, x, fs, delay_samples=0.5)  # (a lag stands in for fractions of a delay)
    kw = dict(process_noise_nm=1e-4 * float(np.sqrt(np.mean(tau ** 2))))
    right = innovations(early, REFERENCE_PLANT, math.radians(0.4), **kw)
    assert right is not None and 0.8 < _rms(right.normalized) < 1.3
    wrong = innovations(kalman_problem(tau, x, fs), REFERENCE_PLANT, math.radians(0.4), **kw)
    assert wrong is not None and _rms(wrong.normalized) > 3 * _rms(right.normalized)


def test_sigma_points_across_the_gap_turn_the_likelihoods_needle_into_a_basin() -> None:
    """At the true plant, the negative log-likelihood per prediction error against ε: the plain predictor's
    is a needle (a gap 1 % off misses the motor's impacts by many standard deviations); with a random walk
    of the twist of 1e-4·ε per sample, whose sigma points take the modes its uncertainty reaches, it rises
    smoothly from the truth, and loses little there."""
    fs, eps = 8000.0, math.radians(1.0)
    tau, r = _record(fs, 4.0, eps_deg=1.0, encoder_bits_motor=22)
    kp = kalman_problem(tau, r.motor_position, fs)
    factors = (0.97, 0.98, 0.99, 1.0, 1.01, 1.02, 1.03)

    def profile(hedged: bool) -> dict[float, float]:
        out = {}
        for f in factors:
            inn = innovations(kp, REFERENCE_PLANT, f * eps, process_noise_nm=1e-2 * kp.torque_rms_nm,
                              twist_noise_rad=1e-4 * f * eps if hedged else 0.0, sigma_points=hedged)
            assert inn is not None
            out[f] = inn.negative_log_likelihood()
        return out

    plain, hedged = profile(False), profile(True)
    assert plain[0.99] > 10 * plain[1.0] and plain[1.01] > 10 * plain[1.0]
    assert hedged[1.0] < 1.05 * plain[1.0]
    assert max(hedged[f] for f in (0.98, 0.99, 1.01, 1.02)) < 1.1 * hedged[1.0]
    assert hedged[0.97] > hedged[0.99] > hedged[1.0] * 0.999 and hedged[1.03] > hedged[1.01]


def test_the_fit_started_by_the_hedged_predictor_ends_at_the_plant() -> None:
    """The record above: from ε 20 % low and K 3 % high, the fit started by the hedged predictor
    (:attr:`Hedge.START`: ε's grid, the twist's random walk taken down) and finished by the plain one ends
    at the plant, following the record without a torque disturbance. (The family's rattling records, where
    the plain fit alone does not: bench/results/family.md.)"""
    fs, eps_deg = 8000.0, 1.0
    tau, r = _record(fs, 4.0, eps_deg=eps_deg, encoder_bits_motor=22)
    kp = kalman_problem(tau, r.motor_position, fs)
    seed = _start(replace(REFERENCE_PLANT, K=1.03 * REFERENCE_PLANT.K), math.radians(0.8 * eps_deg))
    fit = kalman_fit(kp, seed, epsilon_max_rad=math.radians(2.0 * eps_deg), threads=2, max_nfev=30,
                     hedge=Hedge.START)
    assert math.degrees(fit.epsilon_rad) == pytest.approx(eps_deg, rel=0.02)
    for name in ("J_m", "J_l", "K"):
        assert getattr(fit.parameters, name) == pytest.approx(getattr(REFERENCE_PLANT, name), rel=0.02), name
    assert fit.process_noise_nm < 0.01 * kp.torque_rms_nm  # the gap's basin: no disturbance needed to follow it


def test_a_hedged_fit_takes_the_hedged_start_another_fit_computed() -> None:
    """The whole hedged fit after a :attr:`Hedge.START` fit from the same start, sharing ``memo``, is the
    hedged fit computed alone (the hedged start is a deterministic function of the problem and the start),
    for fewer predictor evaluations."""
    fs, eps_deg = 4000.0, 1.0
    tau, r = _record(fs, 2.0, eps_deg=eps_deg, encoder_bits_motor=22)
    kp = kalman_problem(tau, r.motor_position, fs)
    seed = _start(replace(REFERENCE_PLANT, K=1.03 * REFERENCE_PLANT.K), math.radians(0.8 * eps_deg))
    kw = dict(epsilon_max_rad=math.radians(2.0 * eps_deg), threads=2, max_nfev=30)
    alone = kalman_fit(kp, seed, hedge=Hedge.NEAR, **kw)
    memo: dict[str, object] = {}
    kalman_fit(kp, seed, hedge=Hedge.START, memo=memo, **kw)
    shared = kalman_fit(kp, seed, hedge=Hedge.NEAR, memo=memo, **kw)
    assert shared.epsilon_rad == alone.epsilon_rad
    assert shared.parameters == alone.parameters
    assert shared.evaluations < alone.evaluations


def test_a_load_encoder_adds_its_own_channel_and_a_lost_sample_is_no_evidence() -> None:
    fs = 4000.0
    tau, r = _record(fs, 3.0, encoder_bits_motor=22, encoder_bits_load=18)
    lost = np.zeros(tau.size, dtype=bool)
    lost[1000:1010] = True
    kp = kalman_problem(tau, r.motor_position, fs, load_position=r.load_position, lost=lost)
    assert kp.outputs == 2
    # each channel carries its own encoder's quantization
    assert kp.measurement_noise_rad[1] / kp.measurement_noise_rad[0] == pytest.approx(16.0, rel=1e-6)
    inn = innovations(kp, REFERENCE_PLANT, math.radians(0.4), process_noise_nm=1e-4 * kp.torque_rms_nm)
    assert inn is not None and inn.error.shape == (tau.size - 1, 2)
    assert np.all(inn.error[999:1009] == 0.0)
    for channel in (0, 1):
        assert 0.7 < _rms(inn.normalized[:, channel]) < 1.4


def test_a_lost_cycles_torque_is_uncertain_not_evidence() -> None:
    """A streamed record whose lost cycles (5 %, marked) log the setpoint the host meant, where for half
    of them the drive held the one before (a busy host's late setpoint), and a position rebuilt by a
    spline. The encoder's step is read from the samples that arrived; at the true plant the prediction
    errors stay the encoder's noise; the same torques unmarked throw the predictor off."""
    fs = 2000.0
    meant = chirp(ExcitationConfig(sample_rate_hz=fs, duration_s=6.0)).samples
    rng = np.random.default_rng(7)
    lost = np.zeros(meant.size, dtype=bool)
    lost[rng.choice(np.arange(10, meant.size - 10), meant.size // 20, replace=False)] = True
    lost[3] = True  # one at rest, where the spline bends between equal neighbours
    k = np.flatnonzero(lost)
    applied = meant.copy()
    held = k[rng.random(k.size) < 0.5]
    applied[held] = applied[held - 1]
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.4, encoder_bits_motor=20), fs).run_torque(applied)
    position = r.motor_position.copy()
    position[k] = CubicSpline(np.flatnonzero(~lost), position[~lost])(k)  # as the streamed backend does
    step = 2 * math.pi / 2**20
    assert position_step_rad(position, ~lost) == pytest.approx(step, rel=1e-9)
    assert position_step_rad(position) < 0.6 * step  # what the interpolated samples suggest
    kw = dict(process_noise_nm=1e-4 * float(np.sqrt(np.mean(meant**2))))
    marked = innovations(kalman_problem(meant, position, fs, lost=lost), REFERENCE_PLANT, math.radians(0.4), **kw)
    unmarked = innovations(kalman_problem(meant, position, fs), REFERENCE_PLANT, math.radians(0.4), **kw)
    assert marked is not None and unmarked is not None
    assert 0.7 < _rms(marked.normalized) < 1.4
    assert _rms(unmarked.normalized) > 5 * _rms(marked.normalized)


def test_friction_and_a_current_loop_are_predicted() -> None:
    fs = 8000.0
    tau, r = _record(fs, 4.0, coulomb_motor_nm=0.004, coulomb_load_nm=0.003, current_loop_bandwidth_hz=800.0,
                     encoder_bits_motor=20)
    kp = kalman_problem(tau, r.motor_position, fs)
    lag = 1 / (2 * math.pi * 800.0)
    kw = dict(process_noise_nm=1e-3 * kp.torque_rms_nm)
    full = innovations(kp, REFERENCE_PLANT, math.radians(0.4), coulomb_motor_nm=0.004, coulomb_load_nm=0.003,
                       lag_s=lag, **kw)
    without = innovations(kp, REFERENCE_PLANT, math.radians(0.4), **kw)
    assert full is not None and without is not None
    assert _rms(full.normalized) < 1.5
    assert _rms(without.normalized) > 3 * _rms(full.normalized)


@pytest.mark.parametrize("coulomb_motor_nm", [0.0, 5e-4])
def test_a_term_an_estimate_leaves_out_scores_above_its_price_only_where_the_record_has_it(
        coulomb_motor_nm: float) -> None:
    """At the true plant without friction terms, the score of motor friction is above the BIC's price of a
    parameter (ln N) exactly where adding the true friction makes the record likelier by more than that;
    the load's friction, absent from the plant, and the current loop, ideal, score below it without friction."""
    fs = 4000.0
    tau, r = _record(fs, 4.0, coulomb_motor_nm=coulomb_motor_nm, encoder_bits_motor=20, torque_noise_nm=2e-4, seed=3)
    kp = kalman_problem(tau, r.motor_position, fs)
    eps, q = math.radians(0.4), 2e-4
    inn = innovations(kp, REFERENCE_PLANT, eps, process_noise_nm=q)
    assert inn is not None
    n = inn.normalized.size
    estimate = replace(_start(REFERENCE_PLANT, eps), process_noise_nm=q, load_share=0.3, innovations=inn,
                       n_effective=float(n))
    scores = omitted_term_scores(kp, estimate, ModelTerms(coulomb_motor=True, coulomb_load=True, current_loop=True),
                                 epsilon_max_rad=math.radians(2.0))
    truth = innovations(kp, REFERENCE_PLANT, eps, coulomb_motor_nm=coulomb_motor_nm, process_noise_nm=q)
    assert truth is not None
    gain = 2.0 * n * (inn.negative_log_likelihood() - truth.negative_log_likelihood())
    assert (scores["coulomb_motor"] > math.log(n)) == (gain > math.log(n))
    if coulomb_motor_nm == 0.0:
        assert max(scores.values()) < math.log(n), scores


def test_the_estimator_recovers_a_plant_from_a_start_ten_percent_off() -> None:
    fs = 4000.0
    true = REFERENCE_PLANT
    tau, r = _record(fs, 6.0, encoder_bits_motor=19, torque_noise_nm=2e-4, seed=3)
    kp = kalman_problem(tau, r.motor_position, fs)
    start = TwoMassParameters(J_m=1.05 * true.J_m, J_l=0.9 * true.J_l, B_m=1.3 * true.B_m, B_l=0.7 * true.B_l,
                              K=1.1 * true.K, D=0.8 * true.D)
    seed = _start(start, math.radians(0.36))
    fit = kalman_fit(kp, seed, epsilon_max_rad=math.radians(2.0), threads=2, max_nfev=30)
    p = fit.parameters
    for name in ("J_m", "J_l", "K"):
        assert getattr(p, name) == pytest.approx(getattr(true, name), rel=0.01), name
    assert math.degrees(fit.epsilon_rad) == pytest.approx(0.4, abs=0.005)
    assert modes(p).f_resonance_hz == pytest.approx(modes(true).f_resonance_hz, rel=0.003)
    # the intervals hold the truth, and the noise model found the disturbance near the one simulated
    for name in ("J_m", "J_l", "K"):
        assert abs(math.log(getattr(p, name) / getattr(true, name))) <= 4 * fit.stderr("ln " + name) + 1e-4, name
    assert fit.innovations is not None and _rms(fit.innovations.normalized) < 1.3


def test_an_estimate_judged_at_a_wrong_noise_model_is_judged_again_at_its_own() -> None:
    """An estimate at the true plant whose prediction errors were computed assuming a torque disturbance
    of 10 % of RMS τ_ref (where a fit started far away chose its noise model) makes the record less likely
    than it does with the disturbance simulated (0.1 %): chosen again, the noise model is near the simulated
    one, the record is more likely, and the estimate stays at the truth. At its own noise model it is kept."""
    fs = 4000.0
    true = REFERENCE_PLANT
    tau, r = _record(fs, 4.0, encoder_bits_motor=19, torque_noise_nm=2e-4, seed=5)
    kp = kalman_problem(tau, r.motor_position, fs)
    eps = math.radians(0.4)

    def judged_at(level: float) -> PemFit:
        inn = innovations(kp, true, eps, process_noise_nm=level * kp.torque_rms_nm)
        return PemFit(parameters=true, epsilon_rad=eps, coulomb_motor_nm=0.0, coulomb_load_nm=0.0, lag_s=0.0,
                      terms=ModelTerms(), residual=np.zeros(1), cost_nm=math.nan, names=(),
                      covariance=np.zeros((0, 0)), n_effective=1.0, evaluations=0, converged=True, message="",
                      process_noise_nm=level * kp.torque_rms_nm, load_share=0.3, innovations=inn)

    wrong = judged_at(0.1)
    again = kalman_resettled(kp, wrong, epsilon_max_rad=math.radians(2.0), threads=2, max_nfev=30)
    assert again.innovations is not None and wrong.innovations is not None
    assert again.innovations.negative_log_likelihood() < wrong.innovations.negative_log_likelihood() - 0.5
    simulated = 2e-4 / kp.torque_rms_nm
    assert simulated / 3 < again.process_noise_nm / kp.torque_rms_nm < 3 * simulated
    for name in ("J_m", "J_l", "K"):
        assert getattr(again.parameters, name) == pytest.approx(getattr(true, name), rel=0.01), name
    assert math.degrees(again.epsilon_rad) == pytest.approx(0.4, abs=0.005)
    assert again.evaluations > 0
    # at the noise model it chose, a second pass finds nothing likelier to move to
    settled = kalman_resettled(kp, again, epsilon_max_rad=math.radians(2.0), threads=2, max_nfev=30)
    assert settled.innovations is not None
    assert settled.innovations.negative_log_likelihood() <= again.innovations.negative_log_likelihood()
    assert settled.parameters.K == pytest.approx(again.parameters.K, rel=1e-3)


def test_a_start_is_read_off_the_frequency_responses_shape_when_no_rational_fit_gives_one() -> None:
    # the shape start (used when friction distorts the FRD so that no 2/3 fit maps to a plant): its modes
    # from the response's peak and dip, J_m from its high-frequency asymptote — near enough for the fit
    from commission.ident.frd import estimate_frd
    from commission.ident.start import _shape_start

    fs = 8000.0
    true = replace(REFERENCE_PLANT, D=0.0045)
    tau, r = _record(fs, 10.0, params=true, eps_deg=0.0, coulomb_motor_nm=0.02, coulomb_load_nm=0.02)
    frd = estimate_frd(tau, r.motor_velocity, fs, band_hz=(0.1, 400.0), resolution_hz=0.1, quality=False)
    p = _shape_start(frd, 0.25 * fs)
    assert p is not None
    got, want = modes(p), modes(true)
    assert got.f_resonance_hz == pytest.approx(want.f_resonance_hz, rel=0.05)
    assert got.f_antiresonance_hz == pytest.approx(want.f_antiresonance_hz, rel=0.05)
    assert p.J_m == pytest.approx(true.J_m, rel=0.1)


def test_motor_friction_is_predicted_where_a_coarse_encoder_does_not_move() -> None:
    # a 16-bit encoder at 8 kHz steps 0.77 rad/s: where the motor moves less than a step in a sample its
    # measured speed is 0, and the friction (±F_cm or sticking) must come from the predicted state; with
    # the measured speed alone these errors were 8.7× their size
    fs = 8000.0
    tau, r = _record(fs, 4.0, coulomb_motor_nm=0.02, encoder_bits_motor=16)
    kp = kalman_problem(tau, r.motor_position, fs)
    still = np.diff(r.motor_position) == 0.0
    assert still.mean() > 0.01  # the case this test is about
    inn = innovations(kp, REFERENCE_PLANT, math.radians(0.4), coulomb_motor_nm=0.02,
                      process_noise_nm=1e-3 * kp.torque_rms_nm)
    assert inn is not None
    assert _rms(inn.normalized) < 1.5


def test_the_covariance_crosses_a_contact_with_the_dampers_jump() -> None:
    # a heavily damped (ζ 0.28) 310 Hz plant with a 0.95° gap at 4 kHz, 24-bit encoder: the damper's force
    # D·(v_m − v_l) jumps at each contact, so a twist error moves the contact time and both velocities. A
    # covariance propagated with the mode's transition matrix alone misses that: the filter trusts a load
    # state the motor encoder cannot see in the gap, and its prediction errors reached 1000σ (mean ν² 1700)
    p = TwoMassParameters(J_m=8.5e-5, J_l=3.0e-4, B_m=4.2e-4, B_l=6.6e-4, K=254.0, D=0.073)
    fs = 4000.0
    cfg = ExcitationConfig(sample_rate_hz=fs, duration_s=3.0, amplitude_nm=0.046, bias_amplitude_nm=0.016,
                           f_end_hz=780.0, bias_frequency_hz=0.33)
    tau = chirp(cfg).samples
    r = Plant(PlantParameters(**p.as_dict(), epsilon_deg=0.95, encoder_bits_motor=24, torque_noise_nm=1e-4, seed=3),
              fs).run_torque(tau)
    kp = kalman_problem(tau, r.motor_position, fs)
    inn = innovations(kp, p, math.radians(0.95), process_noise_nm=3e-3 * kp.torque_rms_nm)
    assert inn is not None and inn.events > 1000  # impact-rich: the case this test is about
    assert 0.7 < _rms(inn.normalized) < 1.3
    assert np.max(np.abs(inn.normalized)) < 6.0




#: A load 1/5 of the motor: B_l trades with B_m (a record determines their sum far better than their split).
_LIGHT_LOAD = TwoMassParameters(J_m=1.09e-3, J_l=2.02e-4, B_m=1.74e-3, B_l=9.6e-4, K=364.0, D=0.0517)


def _light_load_fit(start: TwoMassParameters, max_nfev: int) -> PemFit:
    """The Kalman fit from ``start`` of a 6 s, 4 kHz record of ``_LIGHT_LOAD`` without a gap (20-bit encoder)."""
    fs = 4000.0
    tau, r = _record(fs, 6.0, _LIGHT_LOAD, eps_deg=0.0, encoder_bits_motor=20, seed=5)
    return kalman_fit(kalman_problem(tau, r.motor_position, fs), _start(start, 0.0),
                      epsilon_max_rad=math.radians(2.0), threads=2, max_nfev=max_nfev)


def test_a_damping_the_record_does_not_determine_does_not_keep_the_fit_from_converging() -> None:
    # from a start with B_l at 5 % of the truth the fit crawled toward B_l = 0 on its log scale until its
    # evaluations ran out
    true = _LIGHT_LOAD
    fit = _light_load_fit(TwoMassParameters(J_m=1.03 * true.J_m, J_l=0.95 * true.J_l, B_m=1.3 * true.B_m,
                                            B_l=0.05 * true.B_l, K=0.95 * true.K, D=1.1 * true.D), max_nfev=30)
    assert fit.converged, fit.message
    p = fit.parameters
    for name in ("J_m", "J_l", "K"):
        assert getattr(p, name) == pytest.approx(getattr(true, name), rel=0.005), name
    assert p.B_m + p.B_l == pytest.approx(true.B_m + true.B_l, rel=0.05)


def test_a_fit_still_descending_at_its_evaluation_limit_goes_on_to_the_optimum() -> None:
    # motor Coulomb friction at 9 % of the peak torque and a start with B_m, B_l a factor 3 off either way:
    # the final least squares descends a long valley where friction and the dampings trade (family member
    # 23:012). With 14 iterations it stopped half way (K +2 %, not converged) before it was given more rounds.
    fs = 4000.0
    true = REFERENCE_PLANT
    tau = chirp(ExcitationConfig(sample_rate_hz=fs, duration_s=4.0)).samples
    friction = 0.09 * float(np.max(np.abs(tau)))
    r = Plant(PlantParameters(**true.as_dict(), epsilon_deg=0.0, coulomb_motor_nm=friction, encoder_bits_motor=20,
                              seed=5), fs).run_torque(tau)
    kp = kalman_problem(tau, r.motor_position, fs)
    start = TwoMassParameters(J_m=1.02 * true.J_m, J_l=0.97 * true.J_l, B_m=0.3 * true.B_m, B_l=3.0 * true.B_l,
                              K=1.02 * true.K, D=true.D)
    seed = _start(start, 0.0, coulomb_motor_nm=0.5 * friction, terms=ModelTerms(coulomb_motor=True))
    fit = kalman_fit(kp, seed, epsilon_max_rad=math.radians(2.0), threads=2, max_nfev=14)
    assert fit.converged, fit.message
    for name in ("J_m", "J_l", "K"):
        assert getattr(fit.parameters, name) == pytest.approx(getattr(true, name), rel=0.005), name
    assert fit.coulomb_motor_nm == pytest.approx(friction, rel=0.005)


def test_a_fit_that_ties_the_dampings_sum_and_not_their_split_goes_along_the_valley_to_the_truth() -> None:
    # the record fixes B_m + B_l tightly and their split loosely, a valley that is curved in (ln B_m, ln B_l);
    # from B_m ×2, B_l ×0.3 the least squares crawled along it (family member 23:054: 200 evaluations for a
    # third of the way) and stopped at its limit with B_m 7σ off the truth
    true = _LIGHT_LOAD
    fit = _light_load_fit(TwoMassParameters(J_m=1.01 * true.J_m, J_l=0.99 * true.J_l, B_m=2.0 * true.B_m,
                                            B_l=0.3 * true.B_l, K=1.01 * true.K, D=true.D), max_nfev=14)
    assert fit.converged, fit.message
    p = fit.parameters
    for name in ("J_m", "J_l", "K"):
        assert getattr(p, name) == pytest.approx(getattr(true, name), rel=0.005), name
    # each damping within 2.5 of its standard errors (the fit's covariance, in its log-coordinates) of the truth
    sd = np.sqrt(np.diag(fit.covariance))
    for name in ("B_m", "B_l"):
        i = fit.names.index(f"ln {name}")
        assert abs(math.log(getattr(p, name) / getattr(true, name))) < 2.5 * sd[i], (name, sd[i])


def test_a_fit_stopped_at_its_limit_within_a_tenth_of_a_standard_error_of_its_optimum_has_converged() -> None:
    from scipy.optimize import least_squares

    from commission.ident.estimator import _covariance, _within_a_step

    # a straight line through noisy points: the optimum and its covariance are known in closed form
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 1.0, 400)
    y = 2.0 + 3.0 * t + 0.1 * rng.standard_normal(t.size)
    A = np.stack((np.ones_like(t), t), axis=1)
    best = np.linalg.lstsq(A, y, rcond=None)[0]
    sd = np.sqrt(np.diag(_covariance(A, A @ best - y)))

    def stopped(at: np.ndarray):  # a least squares that evaluates once and stops where it starts
        return least_squares(lambda x: A @ x - y, at, jac=lambda x: A, max_nfev=1, method="trf")

    for offset, expected in ((0.05, True), (0.5, False), (3.0, False)):
        res = stopped(best + offset * sd)
        assert res.status == 0
        assert _within_a_step(res.jac, res.fun, _covariance(res.jac, res.fun)) is expected, offset
        assert _within_a_step(res.jac, res.fun) is expected, offset  # the default: the same covariance
    # differences taken across a divergence plateau: no step, and no error from the linear algebra
    huge = np.stack((np.full(t.size, 1e200), t), axis=1)
    assert _within_a_step(huge, A @ best - y) is False
    assert _within_a_step(np.stack((np.full(t.size, np.inf), t), axis=1), A @ best - y) is False


def test_a_least_squares_stopped_within_a_tenth_of_a_standard_error_is_at_the_optimum_with_its_jacobian() -> None:
    """The fits' least squares (finite differences, stopped where the Gauss–Newton step is within a tenth of
    a standard error) ends at the optimum a least squares with the analytic Jacobian finds, within a fifth of a
    standard error, and returns the Jacobian there (the covariance's, the intervals'). With two threads (a
    point's first column started beside its own evaluation, wasted where the step is rejected) it ends on the
    same bits and counts the same evaluations as with one."""
    from scipy.optimize import least_squares

    from commission.ident.estimator import _covariance, _least_squares, _Workers

    # a decaying oscillation, z = (ln a, ln b, ln w), through noisy samples
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 2.0, 2000)
    truth = np.log([1.5, 0.8, 9.0])

    def model(z: np.ndarray) -> np.ndarray:
        a, b, w = np.exp(z)
        return a * np.exp(-b * t) * np.sin(w * t)

    def jacobian(z: np.ndarray) -> np.ndarray:
        a, b, w = np.exp(z)
        e, s, c = np.exp(-b * t), np.sin(w * t), np.cos(w * t)
        return np.stack((a * e * s, -a * b * t * e * s, a * w * t * e * c), axis=1)

    y = model(truth) + 0.05 * rng.standard_normal(t.size)

    class Residual:
        """Counts its evaluations as the fits' objectives do (``calls``, which a fit takes back for a column it
        started and did not use) and as run (``passes``)."""

        def __init__(self) -> None:
            self.calls = self.passes = 0

        def __call__(self, z: np.ndarray, remember: bool = True) -> np.ndarray:
            self.calls += 1
            self.passes += 1
            return model(z) - y

    residual = Residual()
    best = least_squares(residual, truth, jac=jacobian, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    sd = np.sqrt(np.diag(_covariance(jacobian(best), residual(best))))
    n = truth.size
    # the second start is one where trf rejects two steps (10 evaluations, 8 Jacobians)
    for offset in ([0.3, -0.4, 0.08], [-1.0, 1.0, 0.1]):
        runs = []
        for threads in (1, 2):
            counted = Residual()
            with _Workers(threads) as pool:
                z, res = _least_squares(counted, truth + np.array(offset),  # type: ignore[arg-type]
                                        np.ones(n, dtype=bool), np.full(n, -5.0), np.full(n, 5.0), np.ones(n),
                                        np.full(n, 1e-7), pool, 200)
            assert res.status > 0, res.message
            assert np.all(np.abs(z - best) <= 0.2 * sd), (z - best) / sd
            assert np.asarray(res.jac) == pytest.approx(jacobian(z), rel=1e-4, abs=1e-5 * np.abs(jacobian(z)).max())
            runs.append((z, np.asarray(res.jac), counted, res))
        (z1, jac1, one, res1), (z2, jac2, two, res2) = runs
        assert np.array_equal(z1, z2) and np.array_equal(jac1, jac2)
        assert one.calls == one.passes == two.calls and res1.nfev == res2.nfev
        # each rejected step's column ran beside it, uncounted
        assert two.passes - two.calls == res2.nfev - res2.njev


def test_a_predictor_that_breaks_down_is_no_optimum_of_the_noise_model_nor_of_the_gaps_profile() -> None:
    """A likelihood that is NaN (a predictor whose covariance broke down) is never taken for the least: the
    noise model is chosen among the finite ones, and a profile of ε that is NaN throughout gives no start and
    an unbounded interval (before: the NaN cell was chosen, and the profile raised IndexError)."""
    from concurrent.futures import ThreadPoolExecutor

    from commission.ident.estimator import _PROCESS_NOISE_GRID, _epsilon_polish, _noise_level
    from commission.ident.kalman import Innovations

    def with_nll(value: float) -> Innovations:
        v = np.full((4, 1), value)
        return Innovations(error=v, normalized=np.sqrt(np.abs(v)), log_variance=np.zeros_like(v), events=0)

    best = _PROCESS_NOISE_GRID[5]

    def at(level: float, share: float) -> Innovations:
        if level == _PROCESS_NOISE_GRID[1]:
            return with_nll(math.nan)
        return with_nll(1.0 + math.log(level / best) ** 2)

    class Broken:
        def innovations(self, z: np.ndarray, remember: bool = True) -> Innovations:
            return with_nll(math.nan)

    with ThreadPoolExecutor(2) as pool:
        level, _ = _noise_level(at, pool)
        assert level == pytest.approx(best, rel=0.01)
        starts, interval = _epsilon_polish(Broken(), np.array([0.0] * 6 + [0.4]), 16.0, pool)  # type: ignore[arg-type]
    assert starts == [] and interval == (0.0, 16.0)


def test_a_start_whose_damping_collapsed_to_zero_gives_prediction_errors_and_an_assessment() -> None:
    # a torque-residual fit on a record no model explains can leave B_m at 1e-16 of the truth: there the gap's
    # two motor poles coincide and the predictor has no eigen decomposition; a Kalman fit started there stayed
    # there, and the assessment of its estimate (no prediction errors at all) crashed the identification
    from commission.ident.assess import assess

    fs = 4000.0
    true = REFERENCE_PLANT
    tau, r = _record(fs, 6.0, encoder_bits_motor=19, torque_noise_nm=2e-4, seed=3)
    kp = kalman_problem(tau, r.motor_position, fs)
    start = replace(true, J_m=1.05 * true.J_m, K=1.1 * true.K, B_m=1e-16 * true.B_m)
    assert innovations(kp, start, math.radians(0.4), process_noise_nm=1e-3) is None
    seed = _start(start, math.radians(0.38))
    fit = kalman_fit(kp, seed, epsilon_max_rad=math.radians(2.0), threads=2, max_nfev=30)
    assert fit.innovations is not None and fit.parameters.B_m > 0.0
    q = assess(fit, torque_rms_nm=_rms(tau), sample_rate_hz=fs)
    # from there the estimate is flagged, or right: never silently wrong
    within = all(getattr(fit.parameters, n) == pytest.approx(getattr(true, n), rel=0.02) for n in ("J_m", "J_l", "K"))
    assert q.approximate or (within and math.degrees(fit.epsilon_rad) == pytest.approx(0.4, abs=0.01))
    # an estimate with no prediction errors is reported as undetermined and flagged, never an error
    q = assess(replace(fit, innovations=None), torque_rms_nm=_rms(tau), sample_rate_hz=fs)
    assert q.approximate and not q.determined and q.model_error and "cannot be evaluated" in q.reasons[0]


def test_an_estimate_whose_resonance_the_record_does_not_show_is_flagged_and_claims_no_stiffness() -> None:
    """The assessment flags an estimate (here the true plant) whose resonance lies beyond where the record's
    torque stops, or beyond Nyquist, and leaves its intervals unbounded; with a band past the resonance the
    same estimate keeps its intervals."""
    from commission.ident.assess import assess

    f_r = modes(REFERENCE_PLANT).f_resonance_hz
    stiff = replace(REFERENCE_PLANT, K=300 * REFERENCE_PLANT.K, D=10 * REFERENCE_PLANT.D)
    assert modes(stiff).f_resonance_hz > 1000.0
    for p, fs, eps_deg, band_top_hz, shown in ((REFERENCE_PLANT, 4000.0, 0.4, 2.0 * f_r, True),
                                               (REFERENCE_PLANT, 4000.0, 0.4, 0.5 * f_r, False),
                                               (stiff, 2000.0, 0.0, 2000.0, False)):
        tau, r = _record(fs, 4.0, params=p, eps_deg=eps_deg, encoder_bits_motor=20, torque_noise_nm=2e-4, seed=3)
        kp = kalman_problem(tau, r.motor_position, fs)
        inn = innovations(kp, p, math.radians(eps_deg), process_noise_nm=2e-4)
        assert inn is not None and _rms(inn.normalized) < 1.5  # the record is this plant's
        estimate = replace(_start(p, math.radians(eps_deg)), process_noise_nm=2e-4, innovations=inn,
                           n_effective=float(inn.normalized.size), converged=True, covariance=np.diag([1e-8] * 7),
                           names=("ln J_m", "ln J_l", "ln B_m", "ln B_l", "ln K", "ln D", "epsilon_deg"))
        for load_encoder in (False, True):
            q = assess(estimate, torque_rms_nm=_rms(tau), sample_rate_hz=fs, band_top_hz=band_top_hz,
                       load_encoder=load_encoder)
            beyond = [x for x in q.reasons if "beyond the" in x]
            assert q.determined == shown and (not beyond) == shown, (band_top_hz, q.reasons)
            if not shown:
                assert q.approximate and f"{modes(p).f_resonance_hz:.3g} Hz" in beyond[0]
                assert f"{p.J_m + p.J_l:.4g} kg·m²" in beyond[0]
                assert any("finer encoder" in x for x in q.remedies)
            else:
                assert not q.remedies


def test_an_objective_runs_its_predictor_once_per_point_and_keeps_no_difference_columns() -> None:
    """A least squares starts where its objective's plateau was set, and what follows it evaluates its
    optimum again: the objective keeps its last points (the same bits a fresh evaluation gives), not the
    finite-difference columns, which are never asked for twice."""
    from commission.ident.estimator import _KalmanObjective

    fs = 2000.0
    tau, r = _record(fs, 2.0, encoder_bits_motor=20)
    kp = kalman_problem(tau, r.motor_position, fs)
    z = np.array([math.log(getattr(REFERENCE_PLANT, n)) for n in ("J_m", "J_l", "B_m", "B_l", "K", "D")] + [0.4])

    def objective() -> _KalmanObjective:
        return _KalmanObjective(kp, ModelTerms(), 1e-3 * kp.torque_rms_nm, 0.0)

    obj = objective()
    first = obj(z)
    again = obj(z.copy())
    assert obj.calls == 1 and np.array_equal(first, again)
    assert np.array_equal(objective()(z), first)
    column = z.copy()
    column[4] += 1e-6
    obj(column, remember=False)
    obj(column, remember=False)
    assert obj.calls == 3
    inn = obj.innovations(z)
    assert obj.calls == 3 and inn is not None and inn.normalized.size == first.size
