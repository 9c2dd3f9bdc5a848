"""Config validation (one line naming the key) and the safety envelope."""

from pathlib import Path

import numpy as np
import pytest

from commission.config import Config, SafetyConfig, load_config
from commission.envelope import check_envelope, rigid_body_response
from commission.exceptions import ConfigError, SafetyLimitExceeded
from commission.excitation import chirp

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_shipped_configs_load():
    default = load_config(CONFIGS / "default.yaml")
    assert default.excitation == Config().excitation
    literal = load_config(CONFIGS / "paper-literal.yaml")
    assert literal.excitation.form.value == "paper-literal"


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("excitation:\n  amplitud_nm: 0.1\n", "excitation.amplitud_nm: unknown key"),
        ("excitation:\n  amplitude_nm: -1\n", "excitation.amplitude_nm: Input should be greater than 0"),
        ("excitation:\n  f_end_hz: 5000\n", "below Nyquist"),
        ("safety:\n  max_torque_nm: 0.1\n", "exceeds safety.max_torque_nm"),
        ("bogus: 1\n", "bogus: unknown key"),
        ("- a\n- b\n", "must be a mapping"),
        ("excitation: [\n", "not valid YAML at line"),
        ("safety:\n  max_torque_nm: yes\n", "safety.max_torque_nm: must be a number, got true"),
        ("identification:\n  threads: on\n", "identification.threads: must be a number, got true"),
        ("sim:\n  epsilon_deg: no\n", "sim.epsilon_deg: must be a number, got false"),
    ],
)
def test_bad_config_is_one_line_naming_the_key(tmp_path, text, fragment):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(f)
    msg = str(info.value)
    assert fragment in msg and "\n" not in msg and str(f) in msg


def test_missing_config():
    with pytest.raises(ConfigError, match="no such config file"):
        load_config("/nonexistent/x.yaml")


def test_rigid_body_prediction_matches_the_closed_form():
    # constant torque from rest: v(t) = τ/B·(1 − exp(−B t / J))
    J, B, tau, fs = 1e-3, 1e-2, 0.2, 8000.0
    v, x = rigid_body_response(np.full(8000, tau), fs, J, B)
    t = np.arange(1, 8001) / fs
    np.testing.assert_allclose(v[1:], tau / B * (1 - np.exp(-B * t[:-1] / J)), rtol=1e-9)
    assert x[-1] == pytest.approx(np.sum(v) / fs)


def test_default_experiment_passes_and_reports_its_peaks():
    cfg = Config()
    w = chirp(cfg.excitation)
    check = check_envelope(w.samples, w.sample_rate_hz, cfg.safety)
    assert 15 < check.predicted_peak_speed_rad_s < 20  # METHOD.md: about ±17 rad/s on the reference plant
    assert check.peak_torque_nm == pytest.approx(np.max(np.abs(w.samples)))


@pytest.mark.parametrize(
    "safety, fragment",
    [
        (SafetyConfig(max_speed_rad_s=15.0), "above the speed limit"),
        (SafetyConfig(max_travel_rad=40.0), "above the travel limit"),
        (SafetyConfig(max_torque_nm=0.2), "excitation torque peaks at 0.3056 N·m, above the limit of 0.2 N·m"),
    ],
)
def test_envelope_refuses(safety, fragment):
    w = chirp(Config().excitation)
    with pytest.raises(SafetyLimitExceeded, match=fragment):
        check_envelope(w.samples, w.sample_rate_hz, safety)


def test_velocity_reference_envelope():
    from commission.envelope import check_velocity_envelope
    from commission.excitation import velocity_reversal

    w = velocity_reversal(1.5, 0.5, 4.0, 8000.0)
    check = check_velocity_envelope(w.samples, w.sample_rate_hz, SafetyConfig())
    assert check.predicted_peak_speed_rad_s == pytest.approx(1.5, rel=1e-6)
    assert check.predicted_peak_travel_rad == pytest.approx(2 * 1.5 / (2 * np.pi * 0.5), rel=1e-3)
    with pytest.raises(SafetyLimitExceeded, match="velocity reference would reach 1.5 rad/s"):
        check_velocity_envelope(w.samples, w.sample_rate_hz, SafetyConfig(max_speed_rad_s=1.6))
