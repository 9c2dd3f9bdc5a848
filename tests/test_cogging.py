"""A torque periodic in the motor's position (cogging, ripple): found in a residual, and taken out of a record."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from commission.config import ExcitationConfig
from commission.excitation import chirp
from commission.ident.hybrid import identify
from commission.cli import main
from commission.csvlog import write_csv
from commission.ident.cogging import Cogging, find_cogging
from commission.ident.twomass import REFERENCE_PLANT
from commission.plant import Plant, PlantParameters
from commission.recording import Recording
from commission.report import _curves


def _wandering(n: int, fs: float, seed: int = 1) -> np.ndarray:
    """A motor position that moves back and forth at many speeds over ~30 rad [rad], shape (n,)."""
    t = np.arange(n) / fs
    rng = np.random.default_rng(seed)
    v = 6.0 * np.sin(2 * np.pi * 0.15 * t) + 3.0 + 2.0 * np.sin(2 * np.pi * 1.3 * t + rng.uniform(0, 6))
    return np.cumsum(v) / fs


def test_harmonics_of_the_position_are_found_with_their_amplitude_and_phase():
    fs, n = 4000.0, 40_000
    x = _wandering(n, fs)
    truth = 3e-3 * np.sin(50 * x + 0.4) + 1.2e-3 * np.cos(100 * x - 1.0)
    noise = np.random.default_rng(2).normal(0.0, 2e-3, n)
    c = find_cogging(truth + noise, x)
    assert c is not None and sorted(c.harmonics) == [50, 100]
    grid = np.linspace(0.0, 2 * np.pi, 1000)
    expected = 3e-3 * np.sin(50 * grid + 0.4) + 1.2e-3 * np.cos(100 * grid - 1.0)
    # white noise of 2 mN·m over 40,000 samples: each coefficient to within ~2e-5 N·m (1 σ)
    assert np.max(np.abs(c.torque(grid) - expected)) < 1.5e-4
    assert c.explained == pytest.approx(np.var(truth) / np.var(truth + noise), abs=0.02)


def test_noise_alone_and_a_travel_too_short_hold_no_cogging():
    fs, n = 4000.0, 40_000
    x = _wandering(n, fs)
    assert find_cogging(np.random.default_rng(3).normal(0.0, 1e-3, n), x) is None
    # 0.5 rad of travel: the 50th harmonic fits 4 periods, fewer than a harmonic needs to be told from motion
    short = 0.25 * np.sin(2 * np.pi * 0.5 * np.arange(n) / fs)
    assert find_cogging(3e-3 * np.sin(50 * short), short) is None
    # a diverged simulation's residual
    assert all(find_cogging(np.where(x > 5.0, bad, 0.0), x) is None for bad in (1e200, np.inf, np.nan))


def test_model_error_that_constant_speed_maps_onto_a_harmonic_is_not_cogging():
    """A torque at 80 Hz while the motor runs at 10 rad/s is the 50th harmonic of its position there, and
    nowhere else: at other speeds and in the other direction the position holds no such torque."""
    fs = 4000.0
    v = np.concatenate((np.full(8000, 10.0), np.full(8000, -4.0), np.full(8000, 2.5), np.full(8000, -6.0)))
    x = np.cumsum(v) / fs
    t = np.arange(v.size) / fs
    r = np.where(np.arange(v.size) < 8000, 5e-3 * np.sin(2 * np.pi * 80 * t), 0.0)
    r = r + np.random.default_rng(4).normal(0.0, 1e-4, v.size)
    assert find_cogging(r, x) is None
    # the same torque as cogging (a function of the position) is found
    c = find_cogging(5e-3 * np.sin(50 * x) + np.random.default_rng(4).normal(0.0, 1e-4, v.size), x)
    assert c is not None and c.harmonics == (50,) and c.peak_nm == pytest.approx(5e-3, rel=0.02)


def _cogging_record(amplitude_nm: float, periods: int, *, load: bool = False) -> Recording:
    """The reference plant (ε 0.4°) with a cogging torque −A·sin(n·x_m) on the motor, 4 s of the chirp at
    8 kHz: the plant advanced one sample at a time, the cogging at the sample's mid-point position."""
    cfg = ExcitationConfig(duration_s=4.0)
    tau = chirp(cfg).samples
    plant = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.4, torque_noise_nm=1e-4, seed=5),
                  cfg.sample_rate_hz)
    half = 0.5 / cfg.sample_rate_hz
    rows = []
    for u in tau:
        s = plant.state
        r = plant.run_torque([u - amplitude_nm * math.sin(periods * (s.x_m + half * s.v_m))])
        rows.append((r.motor_velocity[0], r.motor_position[0], r.load_position[0], r.load_velocity[0]))
    vm, xm, xl, vl = np.array(rows).T
    return Recording.uniform(cfg.sample_rate_hz, tau, vm, motor_position=xm,
                             **(dict(load_position=xl, load_velocity=vl) if load else {}))


def _checked(doc: dict, amplitude_nm: float) -> None:
    """A result.json document: within the tolerances, not flagged, the cogging found."""
    assert doc["fit"]["approximate"] is False, doc["fit"]["reasons"]
    for name in ("J_m", "J_l", "K"):
        assert doc["two_mass"][name] == pytest.approx(getattr(REFERENCE_PLANT, name), rel=0.02), name
    assert doc["backlash"]["epsilon_deg"] == pytest.approx(0.4, abs=0.008)
    cg = doc["cogging"]
    assert 50 in cg["harmonics_per_revolution"]
    # the torque acting beside τ_ref is −A·sin(50·x) (the residual's observer follows 17 % of it as the load's
    # motion on this 4 s record: the stage fits the rest again at its new estimate)
    found = Cogging.from_dict(cg)
    grid = np.linspace(0.0, 2 * np.pi, 1000)
    assert np.max(np.abs(found.torque(grid) + amplitude_nm * np.sin(50 * grid))) < 0.1 * amplitude_nm


_ONE_PERCENT = 0.01 * (ExcitationConfig().amplitude_nm + ExcitationConfig().bias_amplitude_nm)


def test_a_replayed_record_with_cogging_is_identified_within_tolerance_and_says_so(tmp_path, capsys):
    # before the cogging stage: flagged, the model needing a torque disturbance of 2.8 % of RMS τ_ref
    write_csv(tmp_path / "axis.csv", _cogging_record(_ONE_PERCENT, 50))
    assert main(["--replay", str(tmp_path / "axis.csv"), "--out", str(tmp_path / "o")]) == 0
    _checked(json.loads((tmp_path / "o" / "result.json").read_text()), _ONE_PERCENT)
    assert "cogging / ripple" in capsys.readouterr().out
    # what is left is the record's noise: the tuning keeps its backlash compensation (it drops it where more than
    # 0.5 % of the torque is left unexplained and not white, as 17 % of this cogging left it)
    assert json.loads((tmp_path / "o" / "controller.json").read_text())["backlash_compensation"]["enabled"]


def test_a_record_with_cogging_and_a_load_encoder_is_identified_within_tolerance_and_the_report_applies_it():
    rec = _cogging_record(_ONE_PERCENT, 50, load=True)
    ident = identify(rec)
    _checked(ident.to_dict(), _ONE_PERCENT)
    # the report's "measured − simulated" velocity: the simulation driven by τ_ref and the cogging found misses
    # the record by far less than one driven by τ_ref alone (the cogging's speed ripple is the misfit's bulk)
    with_cogging = _curves(rec, ident, None, None)
    without = _curves(rec, replace(ident, cogging=None), None, None)
    assert np.std(rec.motor_velocity - with_cogging.v_sim) < 0.5 * np.std(rec.motor_velocity - without.v_sim)
