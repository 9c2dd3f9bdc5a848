"""Assessment of a fit: how much of the record it explains, whether what it leaves is noise, and
whether its intervals are tight enough to act on (:class:`commission.ident.result.FitQuality`).

A result is *approximate* when

* the model explains none of the torque (its residual at least RMS τ_ref, ``UNDETERMINED_RATIO``):
  nothing is determined, and every interval is the whole range the fit searched; or
* the model leaves more than ``APPROXIMATE_FACTOR`` × max(good-fit level, quantization floor) of
  the torque unexplained and that residual is not white, stationary noise, or more than
  ``APPROXIMATE_FACTOR`` × the good-fit level in bursts (the quantization floor is stationary) — the
  axis has dynamics the model does not reproduce, and the parameters may be biased beyond their
  intervals; or
* the drive samples fewer than ``SAMPLES_PER_RESONANCE`` times per resonance period; or
* the least squares stopped at its evaluation limit, not at a stationary point: the intervals, from
  the curvature there, do not describe the estimate; or
* its 95 % interval is wider than what commissioning needs: ε to ``EPSILON_TOLERANCE_DEG`` or
  ``RELATIVE_TOLERANCE`` of itself, J_m, J_l and K to ``RELATIVE_TOLERANCE``, the resonance and
  anti-resonance frequencies to ``MODE_TOLERANCE`` — the record does not
  determine them (a short or noisy record, a backlash the excitation barely opens).

Intervals. The estimator's covariance describes the noise's effect on the estimate, not a model
error's: when the residual exceeds its noise — the good-fit level, the quantization floor, or its
own white, stationary part (:func:`noise_part`; not where the first rule above found the residual
to be model error), whichever is largest — every interval is widened by that ratio (the Birge
ratio, ``FitQuality.interval_scale``) before it is reported and checked.

An approximate result is still a result: result.json and the report are written and say why.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy.signal import welch

from ..exceptions import IdentificationError
from .estimator import EDGE_SAMPLES, PARAMETER_NAMES, PemFit
from .result import FitQuality
from .twomass import TwoMassParameters, modes

__all__ = ["assess", "mode_stderr", "noise_part", "whiteness"]

#: Step of the central differences in the log-parameters behind :func:`mode_stderr`.
_MODE_STEP = 1e-5

APPROXIMATE_FACTOR = 5.0
#: Residual / RMS τ_ref at and above which nothing is determined: τ_ref's own RMS is what a model
#: predicting no motion at all leaves.
UNDETERMINED_RATIO = 1.0
#: Spectral flatness and window-RMS stationarity of a residual that is white torque noise.
WHITE_FLATNESS = 0.95
WHITE_STATIONARY = 1.3
#: Below this many samples per resonance period the motor's motion between samples, which the load
#: simulation interpolates, limits K and J_l to several percent (bench/bench_family.py: no member
#: under 22 was within the tolerances).
SAMPLES_PER_RESONANCE = 25.0
#: What commissioning needs of the result (the tolerances of bench/bench_family.py).
EPSILON_TOLERANCE_DEG = 0.01
RELATIVE_TOLERANCE = 0.02
#: ... and of the resonance and anti-resonance frequencies (a notch filter's centre) [-].
MODE_TOLERANCE = 0.005


def whiteness(v: NDArray[np.float64], rate_hz: float) -> tuple[float, float]:
    """(spectral flatness, window RMS p90/median) of a residual sampled at ``rate_hz``.

    Flatness: geometric / arithmetic mean of its Welch PSD (256-sample segments) from 5 Hz to
    0.8 × Nyquist — near 1 for white noise. Stationarity: the 90th percentile / median of its RMS
    over 50 equal windows — near 1 when stationary, large when bursts (impacts) carry it.
    """
    f, P = welch(v, fs=rate_hz, nperseg=min(256, v.size))
    band = (f > 5.0) & (f < 0.4 * rate_hz) & (P > 0)
    flat = float(np.exp(np.mean(np.log(P[band]))) / np.mean(P[band])) if band.any() else 0.0
    w = np.array([np.sqrt(np.mean(x * x)) for x in np.array_split(v, 50) if x.size])
    med = float(np.median(w))
    return flat, (float(np.percentile(w, 90)) / med if med > 0 else math.inf)


def noise_part(v: NDArray[np.float64], rate_hz: float) -> float:
    """RMS of the white, stationary noise in a residual sampled at ``rate_hz`` [its unit]: its RMS if
    its spectrum were flat at its median level (narrow-band structure lifts the mean, not the median),
    and at most its median window RMS (bursts lift the mean, not the median) — windows and band as
    :func:`whiteness`."""
    f, P = welch(v, fs=rate_hz, nperseg=min(256, v.size))
    band = (f > 5.0) & (f < 0.4 * rate_hz) & (P > 0)
    rms = float(np.sqrt(np.mean(v * v)))
    flat_rms = rms * math.sqrt(float(np.median(P[band]) / np.mean(P[band]))) if band.any() else 0.0
    w = np.array([np.sqrt(np.mean(x * x)) for x in np.array_split(v, 50) if x.size])
    return min(flat_rms, float(np.median(w)))


def mode_stderr(fit: PemFit) -> dict[str, float]:
    """Relative standard errors of the resonance and anti-resonance frequencies [-] (delta method: the
    gradient of their logarithms in the fit's log-parameters, by central differences, through the
    covariance); NaN where the plant has no such mode."""
    names = [f"ln {n}" for n in PARAMETER_NAMES]
    if any(n not in fit.names for n in names):
        return {"resonance": math.nan, "anti-resonance": math.nan}
    idx = [fit.names.index(n) for n in names]
    C = fit.covariance[np.ix_(idx, idx)]
    z = np.log([getattr(fit.parameters, n) for n in PARAMETER_NAMES])

    def log_modes(zz: NDArray[np.float64]) -> NDArray[np.float64]:
        m = modes(TwoMassParameters(**dict(zip(PARAMETER_NAMES, (float(v) for v in np.exp(zz))))))
        return np.log([m.f_resonance_hz, m.f_antiresonance_hz])

    try:
        G = np.stack([(log_modes(z + h) - log_modes(z - h)) / (2 * _MODE_STEP)
                      for h in np.eye(len(z)) * _MODE_STEP], axis=1)
    except (IdentificationError, ValueError):
        return {"resonance": math.nan, "anti-resonance": math.nan}
    var = np.einsum("ij,jk,ik->i", G, C, G)
    return {"resonance": float(np.sqrt(max(var[0], 0.0))), "anti-resonance": float(np.sqrt(max(var[1], 0.0)))}


def assess(fit: PemFit, *, torque_rms_nm: float, motor_samples: int, decimated_rate_hz: float,
           good_fit_ratio: float, noise_floor_ratio: float, cutoff_hz: float,
           observer_bandwidth_hz: float, sample_rate_hz: float, resonance_hz: float) -> FitQuality:
    """The fit's quality (see the module docstring).

    :param motor_samples: length of the residual's motor block (before edge trimming).
    """
    motor = fit.residual[:motor_samples - 2 * EDGE_SAMPLES]
    ratio = float(np.sqrt(np.mean(motor * motor))) / max(torque_rms_nm, 1e-300)
    flat, stationary = whiteness(motor, decimated_rate_hz)
    level = APPROXIMATE_FACTOR * max(good_fit_ratio, noise_floor_ratio)
    white = flat >= WHITE_FLATNESS and stationary <= WHITE_STATIONARY
    noise_limited = ratio > level and white
    # the quantization floor is stationary noise: a residual that comes in bursts (impacts the model does not
    # follow) is model error above the good-fit level, however coarse the encoder
    bursts = ratio > APPROXIMATE_FACTOR * good_fit_ratio and stationary > WHITE_STATIONARY
    misfit = (ratio > level and not noise_limited) or bursts
    # a residual as large as the torque itself (no model leaves that much) or a diverged one: the local
    # curvature says nothing about where the plant is
    determined = bool(ratio < UNDETERMINED_RATIO)
    # the Birge ratio: what the model leaves beyond its noise is model error, whose effect on the estimate
    # the residual's statistics cannot show; the noise is the known floors, and, unless the residual was
    # just found to be model error, its own white, stationary part
    noise = max(good_fit_ratio, noise_floor_ratio)
    if not misfit:
        noise = max(noise, noise_part(motor, decimated_rate_hz) / max(torque_rms_nm, 1e-300))
    scale = max(1.0, ratio / noise)
    if scale > 1.0:
        fit = replace(fit, covariance=fit.covariance * scale ** 2)
    reasons: list[str] = []
    if not determined:
        reasons.append(f"the model leaves {100 * ratio:.0f} % of the torque unexplained, as much as no model at "
                       "all: the record does not determine the parameters or ε under this model; their intervals "
                       "are unbounded, ε's the whole range the fit searched")
    elif misfit:
        reasons.append(f"the model leaves {100 * ratio:.2f} % of the torque unexplained "
                       f"({ratio / max(good_fit_ratio, noise_floor_ratio):.0f}× what a model that describes the "
                       "axis leaves), and not as white noise: the axis has dynamics the model does not reproduce; "
                       "the parameters may be off by more than their intervals")
    if sample_rate_hz < SAMPLES_PER_RESONANCE * resonance_hz:
        reasons.append(f"the drive samples only {sample_rate_hz / resonance_hz:.0f}× per resonance period "
                       f"({resonance_hz:.0f} Hz at {sample_rate_hz:g} Hz): the motor's motion between samples is "
                       "interpolated, and K and J_l may be off by several percent")
    if not fit.converged:
        reasons.append("the least squares stopped at its evaluation limit before converging: the parameters "
                       "may not be at the fit's optimum, and the intervals (from the curvature there) may not hold")
    eps_deg = math.degrees(fit.epsilon_rad)
    half = 1.96 * fit.stderr("eps_deg")
    if not half <= max(EPSILON_TOLERANCE_DEG, RELATIVE_TOLERANCE * eps_deg):
        reasons.append(f"the record determines ε only to ±{half:.3g}° (95 %)")
    wide = [n for n in ("J_m", "J_l", "K") if not 1.96 * fit.stderr("ln " + n) <= RELATIVE_TOLERANCE]
    if wide:
        reasons.append("the record determines " + ", ".join(
            f"{n} only to ±{100 * 1.96 * fit.stderr('ln ' + n):.2g} %" for n in wide) + " (95 %)")
    mode_half = {k: 1.96 * v for k, v in mode_stderr(fit).items()}
    wide_modes = [k for k, h in mode_half.items() if not h <= MODE_TOLERANCE]
    if wide_modes:
        reasons.append("the record determines " + ", ".join(
            f"the {k} frequency only to ±{100 * mode_half[k]:.2g} %" for k in wide_modes) + " (95 %)")
    return FitQuality(residual_ratio=ratio, noise_floor_ratio=noise_floor_ratio, spectral_flatness=flat,
                      window_rms_p90_over_median=stationary, noise_limited=noise_limited,
                      approximate=bool(reasons), reasons=tuple(reasons), cutoff_hz=cutoff_hz,
                      observer_bandwidth_hz=observer_bandwidth_hz, effective_samples=fit.n_effective,
                      converged=fit.converged, interval_scale=scale, model_error=bool(misfit or not determined),
                      determined=determined)
