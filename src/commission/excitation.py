"""Excitation signals: the paper's chirp torque (eq. 18–19), corrected.

The paper writes τ(t) = A·sin(ω(t)·t + φ0) + 3A·sin(2π·0.1·t) with ω(t) linear
in t. Taken literally, the instantaneous frequency d(ω(t)·t)/dt / 2π ends at
2·f1 − f0 ≈ 800 Hz, not 400 Hz. The default is therefore a true linear chirp
whose instantaneous frequency sweeps f0 → f1; the literal form is kept as an
explicit option (``form: paper-literal``) to reproduce the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .config import ChirpForm, ExcitationConfig


@dataclass(frozen=True)
class Waveform:
    """Reference samples for the drive's waveform player.

    :param samples: reference per tick, shape (N,) [N·m for torque, rad/s for velocity].
    :param sample_rate_hz: tick rate [Hz].
    :param description: one line saying what it is.
    """

    samples: NDArray[np.float64]
    sample_rate_hz: float
    description: str

    @property
    def t(self) -> NDArray[np.float64]:
        """Sample times [s], shape (N,)."""
        return np.arange(self.samples.size) / self.sample_rate_hz

    @property
    def duration_s(self) -> float:
        return self.samples.size / self.sample_rate_hz


def chirp_phase(t: NDArray[np.float64], cfg: ExcitationConfig) -> NDArray[np.float64]:
    """Phase of the chirp term [rad] at times ``t`` [s]."""
    f0, f1, T = cfg.f_start_hz, cfg.f_end_hz, cfg.duration_s
    phi0 = np.deg2rad(cfg.phase_deg)
    if cfg.form is ChirpForm.LINEAR:
        return 2 * np.pi * (f0 * t + (f1 - f0) * t**2 / (2 * T)) + phi0
    omega = 2 * np.pi * (f0 + (f1 - f0) * t / T)  # paper eq. 19
    return omega * t + phi0  # paper eq. 18, literally


def instantaneous_frequency_hz(t: NDArray[np.float64], cfg: ExcitationConfig) -> NDArray[np.float64]:
    """Instantaneous frequency of the chirp term [Hz] (derivative of the phase / 2π)."""
    f0, f1, T = cfg.f_start_hz, cfg.f_end_hz, cfg.duration_s
    if cfg.form is ChirpForm.LINEAR:
        return f0 + (f1 - f0) * t / T
    return f0 + 2 * (f1 - f0) * t / T


def chirp(cfg: ExcitationConfig) -> Waveform:
    """The chirp torque of the config: A·sin(φ(t)) + A_bias·sin(2π·f_bias·t), N samples from t = 0."""
    t = np.arange(cfg.n_samples) / cfg.sample_rate_hz
    tau = cfg.amplitude_nm * np.sin(chirp_phase(t, cfg))
    tau += cfg.bias_amplitude_nm * np.sin(2 * np.pi * cfg.bias_frequency_hz * t)
    desc = (
        f"{cfg.form.value} chirp {cfg.f_start_hz:g}→{cfg.f_end_hz:g} Hz, A = {cfg.amplitude_nm:g} N·m, "
        f"bias {cfg.bias_amplitude_nm:g} N·m at {cfg.bias_frequency_hz:g} Hz, "
        f"{cfg.duration_s:g} s at {cfg.sample_rate_hz:g} Hz"
    )
    return Waveform(samples=tau, sample_rate_hz=cfg.sample_rate_hz, description=desc)


def velocity_reversal(amplitude_rad_s: float, frequency_hz: float, duration_s: float, sample_rate_hz: float) -> Waveform:
    """Sine velocity reference for the backlash check of paper §4.2 (0.5 Hz, 1.5 rad/s there)."""
    t = np.arange(int(round(duration_s * sample_rate_hz))) / sample_rate_hz
    v = amplitude_rad_s * np.sin(2 * np.pi * frequency_hz * t)
    return Waveform(v, sample_rate_hz, f"velocity sine {amplitude_rad_s:g} rad/s at {frequency_hz:g} Hz")
