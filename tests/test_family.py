"""The plant family (sim_drive.family): deterministic, spans its stated ranges, every member simulates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from commission.config import ExcitationConfig
from commission.excitation import chirp
from commission.ident.consistency import reconcile
from sim_drive import family as fam
from sim_drive.family import DEFAULT_SEED, Sensors, family, member


@pytest.fixture(scope="module")
def members() -> list[fam.Member]:
    return family()


def test_deterministic_for_a_seed_and_independent_of_size(members: list[fam.Member]) -> None:
    again = family(DEFAULT_SEED, 40)
    assert again == members[:40]
    for i in (0, 1, 17, 199):
        assert member(DEFAULT_SEED, i) == members[i]
    other = family(DEFAULT_SEED + 1, 40)
    assert sum(a.two_mass == b.two_mass for a, b in zip(other[1:], members[1:40])) == 0
    assert len({m.id for m in members}) == len(members) == fam.DEFAULT_SIZE >= 200


def test_member_zero_is_the_reference_experiment(members: list[fam.Member]) -> None:
    m = members[0]
    md = m.modes
    # METHOD.md: resonance 65.35 Hz (ζ 0.167), anti-resonance 55.20 Hz; the default chirp
    assert md.f_resonance_hz == pytest.approx(65.35, abs=0.01)
    assert md.zeta_resonance == pytest.approx(0.167, abs=0.001)
    assert md.f_antiresonance_hz == pytest.approx(55.20, abs=0.01)
    assert m.epsilon_deg == 0.40 and m.excitation == ExcitationConfig()


def _span(values: list[float], lo: float, hi: float, log: bool = True, reach: float = 0.1) -> None:
    """All values in [lo, hi] and both ends approached within ``reach`` of the range (log or linear)."""
    v = np.asarray(values, dtype=float)
    assert v.min() >= lo * (1 - 1e-9) and v.max() <= hi * (1 + 1e-9)
    f = np.log if log else (lambda x: x)
    width = f(hi) - f(lo)
    assert f(v.min()) - f(lo) <= reach * width, (v.min(), lo)
    assert f(hi) - f(v.max()) <= reach * width, (v.max(), hi)


def test_spans_the_stated_ranges(members: list[fam.Member]) -> None:
    drawn = members[1:]
    _span([m.two_mass.J_l / m.two_mass.J_m for m in drawn], 0.1, 10.0)
    _span([m.modes.f_resonance_hz for m in drawn], 20.0, 400.0)
    _span([m.modes.zeta_resonance for m in drawn], 0.03, 0.3)
    eps = [m.epsilon_deg for m in drawn]
    assert 0.1 * len(eps) <= eps.count(0.0) <= 0.2 * len(eps)
    _span([e for e in eps if e > 0], 0.02, 3.0)
    friction = [(m.coulomb_motor_nm + m.coulomb_load_nm) / m.peak_torque_nm for m in drawn]
    assert 0.25 * len(drawn) <= friction.count(0.0) <= 0.45 * len(drawn)
    _span([f for f in friction if f > 0], 0.005, 0.15)
    loops = [m.current_loop_bandwidth_hz for m in drawn]
    assert 0.2 * len(drawn) <= loops.count(None) <= 0.4 * len(drawn)
    _span([b for b in loops if b is not None], 300.0, 3000.0)
    noise = [m.torque_noise_nm / m.peak_torque_nm for m in drawn]
    assert noise.count(0.0) >= 0.1 * len(drawn)
    _span([n for n in noise if n > 0], 2e-4, 5e-3)
    for bits in ([m.encoder_bits_motor for m in drawn], [m.encoder_bits_load for m in drawn]):
        assert set(bits) == set(range(16, 25))
    rates = [m.sample_rate_hz for m in drawn]
    assert set(rates) == set(fam.SAMPLE_RATES_HZ) and min(rates) == 2000 and max(rates) == 16000
    _span([m.duration_s for m in drawn], 5.0, 20.0, log=False, reach=0.05)
    kinds = [m.sensors for m in drawn]
    assert all(kinds.count(s) >= 0.25 * len(drawn) for s in Sensors)


def test_every_chirp_covers_the_resonance_below_its_sample_rate(members: list[fam.Member]) -> None:
    for m in members:
        x, md = m.excitation, m.modes
        assert x.duration_s == m.duration_s and x.sample_rate_hz == m.sample_rate_hz
        assert x.f_end_hz <= 0.4 * x.sample_rate_hz + 1e-9
        assert x.f_start_hz < md.f_antiresonance_hz and 2.0 * md.f_resonance_hz <= x.f_end_hz, m.id


def test_every_member_simulates(members: list[fam.Member]) -> None:
    peaks = []
    for m in members:
        rec = m.simulate()
        n = int(round(m.duration_s * m.sample_rate_hz))
        assert len(rec) == n and rec.sample_rate_hz == m.sample_rate_hz and rec.is_uniform
        np.testing.assert_array_equal(rec.torque_ref, chirp(m.excitation).samples)
        assert (rec.motor_position is None) == (m.sensors is Sensors.VELOCITY_ONLY), m.id
        assert rec.has_load_encoder == (m.sensors is Sensors.LOAD_ENCODER), m.id
        assert np.ptp(rec.motor_velocity) > 0, m.id
        # the excitation is scaled so the linear plant stays under SPEED_LIMIT_RAD_S; backlash,
        # friction and quantised velocity (up to 1.5 rad/s per count) may add a little
        smooth = np.convolve(rec.motor_velocity, np.ones(16) / 16, mode="valid")
        peaks.append(float(np.max(np.abs(smooth))))
        assert peaks[-1] < 1.5 * fam.SPEED_LIMIT_RAD_S, (m.id, peaks[-1])
        assert abs(peaks[-1]) > 1.0, m.id  # and the motor moves
        # every signal agrees with the others: the identifier's consistency check changes nothing
        assert reconcile(rec) == (rec, []), m.id
    # the reference experiment's ±17 rad/s is the middle of the family, not its edge
    assert 8.0 < float(np.median(peaks)) < 25.0


def test_simulation_is_repeatable() -> None:
    m = member(DEFAULT_SEED, 7)
    assert m.simulate().equals(m.simulate())


def test_linear_speed_bound_matches_the_simulator() -> None:
    """The amplitude scaling's linear model agrees with sim_drive on a backlash-free plant."""
    m = member(DEFAULT_SEED, 0)
    tau = m.torque_ref()
    v = fam._linear_motor_velocity(m.two_mass, tau, m.sample_rate_hz)
    rec = fam.Plant(fam.PlantParameters(**m.two_mass.as_dict(), epsilon_deg=0.0, encoder_bits_motor=32),
                    m.sample_rate_hz).run_torque(tau)
    # the simulator reports the mean velocity of the past sample, the model the velocity at the
    # sample: they differ by half a sample of acceleration (≤ A/J_m / fs / 2 ≈ 0.02 rad/s here)
    assert np.max(np.abs(v - rec.motor_velocity)) < 0.03
    assert math.isclose(np.max(np.abs(v)), 17.0, rel_tol=0.02)
