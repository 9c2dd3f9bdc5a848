"""The chirp of paper eq. 18–19: correct linear sweep by default, the literal form as an option."""

import numpy as np
from scipy.signal import hilbert

from commission.config import ChirpForm, ExcitationConfig
from commission.excitation import chirp, instantaneous_frequency_hz, velocity_reversal


def _measured_instantaneous_frequency(cfg):
    """Instantaneous frequency of the chirp term from its analytic signal (independent of chirp_phase)."""
    chirp_only = chirp(cfg.model_copy(update={"bias_amplitude_nm": 0.0}))
    phase = np.unwrap(np.angle(hilbert(chirp_only.samples)))
    return np.gradient(phase) * cfg.sample_rate_hz / (2 * np.pi)


def test_default_is_the_papers_experiment():
    cfg = ExcitationConfig()
    w = chirp(cfg)
    assert w.samples.size == 80_000 and w.sample_rate_hz == 8000.0
    t = w.t
    expected = 0.0764 * np.sin(2 * np.pi * (0.1 * t + 399.9 * t**2 / 20)) + 0.2292 * np.sin(2 * np.pi * 0.1 * t)
    np.testing.assert_allclose(w.samples, expected, atol=1e-12)
    assert w.samples[0] == 0.0  # φ0 = 0


def test_linear_chirp_ends_at_f_end():
    cfg = ExcitationConfig()
    f = _measured_instantaneous_frequency(cfg)
    n = f.size
    # away from the Hilbert transform's edge effects
    assert abs(np.median(f[int(0.97 * n) : int(0.99 * n)]) - 392.0) < 2.0
    assert abs(np.median(f[n // 2 - 400 : n // 2 + 400]) - 200.05) < 1.0


def test_literal_form_reaches_twice_the_band():
    cfg = ExcitationConfig(form=ChirpForm.PAPER_LITERAL)
    f = _measured_instantaneous_frequency(cfg)
    n = f.size
    assert abs(np.median(f[int(0.97 * n) : int(0.99 * n)]) - 784.0) < 4.0  # 2·f1 − f0 at the end
    t_end = np.array([cfg.duration_s])
    assert abs(instantaneous_frequency_hz(t_end, cfg)[0] - 799.9) < 1e-9


def test_velocity_reversal_reference():
    w = velocity_reversal(1.5, 0.5, 4.0, 8000.0)
    assert w.samples.size == 32000
    assert abs(np.max(w.samples) - 1.5) < 1e-6
