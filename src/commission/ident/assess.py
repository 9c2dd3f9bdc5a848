"""Assessment of the estimate: whether the model and its noise model explain the record, and whether
the intervals are tight enough to act on (:class:`commission.ident.result.FitQuality`).

The Kalman predictor's normalized prediction errors e/√S are white with unit variance when the
model and its noise model describe the record. A result is *approximate* when

* they miss by more than ``INNOVATION_MISFIT`` × their predicted size (``INNOVATION_UNDETERMINED``:
  nothing is determined, every interval unbounded); or
* the noise model needs a torque disturbance of ``DISTURBANCE_MISFIT`` of RMS τ_ref or more to follow
  the record: it then stands in for dynamics the model lacks, and the errors look like noise (the
  intervals are then unbounded: the curvature describes no bias); or
* the estimate's resonance lies beyond where the record's torque stops exciting (or beyond Nyquist): the
  record then shows a rigid body, and only J_m + J_l is determined; or
* the least squares stopped at its evaluation limit, not at a stationary point; or
* a 95 % interval is wider than commissioning needs: ε's (from the curvature, or from the likelihood
  ratio on its profile when the fit polished it) to ``EPSILON_TOLERANCE_DEG`` or
  ``RELATIVE_TOLERANCE`` of itself, J_m, J_l and K to ``RELATIVE_TOLERANCE``, the resonance and
  anti-resonance frequencies to ``MODE_TOLERANCE``.

Where the errors are model error, every interval is widened by their size (``FitQuality.interval_scale``).
An approximate result is still a result: result.json and the report are written and say why.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy.signal import welch

from ..exceptions import IdentificationError
from .estimator import PARAMETER_NAMES, PemFit
from .result import FitQuality
from .start import BAND_TOP_PER_SAMPLE_RATE
from .twomass import TwoMassParameters, modes

__all__ = ["assess", "mode_stderr", "whiteness"]

#: Step of the central differences in the log-parameters behind :func:`mode_stderr`.
_MODE_STEP = 1e-5

#: Spectral flatness and window-RMS stationarity of prediction errors that are white noise (reported,
#: ``FitQuality.noise_limited``).
WHITE_FLATNESS = 0.95
WHITE_STATIONARY = 1.3
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


def _interval_reasons(fit: PemFit) -> list[str]:
    """Why the record determines the estimate too loosely for commissioning (empty: it does not)."""
    reasons: list[str] = []
    eps_deg = math.degrees(fit.epsilon_rad)
    tolerance = max(EPSILON_TOLERANCE_DEG, RELATIVE_TOLERANCE * eps_deg)
    half = 1.96 * fit.stderr("eps_deg")
    if not half <= tolerance:
        reasons.extend(_undetermined({"ε": half}, lambda h: f"{h:.3g}°"))
    elif fit.epsilon_profile_deg is not None:
        # the likelihood ratio on ε's rugged profile: a profile flat past the polished span is no bound
        lo, hi = fit.epsilon_profile_deg
        if not max(eps_deg - lo, hi - eps_deg) <= tolerance:
            reasons.append(f"the record bounds ε only to [{lo:.3g}°, {hi:.3g}°] (95 %, likelihood ratio)")
    halves = {n: 1.96 * fit.stderr("ln " + n) for n in ("J_m", "J_l", "K")}
    reasons.extend(_undetermined({n: h for n, h in halves.items() if not h <= RELATIVE_TOLERANCE}, _percent))
    mode_half = {f"the {k} frequency": 1.96 * v for k, v in mode_stderr(fit).items()}
    reasons.extend(_undetermined({k: h for k, h in mode_half.items() if not h <= MODE_TOLERANCE}, _percent))
    return reasons


def _percent(relative: float) -> str:
    return f"{100 * relative:.2g} %"


def _undetermined(halves: dict[str, float], form: Callable[[float], str]) -> list[str]:
    """Reasons for quantities whose 95 % half-widths (``form`` writes one) exceed their tolerance: one for
    those the record bounds, one for those it does not bound at all (no finite interval, or no mode)."""
    wide = [f"{n} only to ±{form(h)}" for n, h in halves.items() if math.isfinite(h)]
    unknown = [n for n, h in halves.items() if not math.isfinite(h)]
    return ([f"the record determines {', '.join(wide)} (95 %)"] if wide else []) + (
        [f"the record does not determine {' or '.join(unknown)}"] if unknown else [])


#: RMS of the Kalman predictor's normalized prediction errors e/√S above which the model does not
#: describe the record: at the true parameters and noise levels it is 1.
INNOVATION_MISFIT = 1.5
#: ... and at and above which the estimate is not determined at all.
INNOVATION_UNDETERMINED = 100.0
#: Torque disturbance per sample (relative to RMS τ_ref) at and above which the noise model stands in
#: for dynamics the model lacks: the predictor then follows the record whatever the parameters, and
#: its prediction errors look like noise (a drive's torque noise is a fraction of this: the family's
#: 0.5 % of the peak torque is ~1 % of RMS τ_ref). On the family, wrong estimates left unflagged had
#: 4.5–5.4 % (bench/results/family.md). Whiteness is no test here: correct fits of friction-rich
#: records leave non-white errors, wrong ones white.
DISTURBANCE_MISFIT = 0.04
#: ... and at and above which the estimate is flagged all the same, its intervals kept: twice the largest
#: torque noise the family's drives have, where what the disturbance stands in for can already bias the
#: parameters beyond their intervals (a held-out member: J_m +2.8 % at 2.4 %, its interval ±0.07 %;
#: bench/results/family.md).
DISTURBANCE_SUSPECT = 0.02
#: The chirp's end a remedy names, in resonances of the estimate.
CHIRP_END_PER_RESONANCE = 3.5
#: A chirp that reaches this many resonances already is not what keeps a motor-side record from its plant: on
#: the family's flagged members, whose chirps end at 2.5× the true resonance (2.4× an estimate 3 % high, the
#: band's top read a few Hz short), a new record to the named 3.5× rescued none of 10, a load encoder all 21; a
#: stiff plant's chirp at 1.37× was rescued by one to 3.4× (bench/results/family.md).
CHIRP_END_ENOUGH_PER_RESONANCE = 2.4
#: What lets a motor-side record whose fit leaves model error determine the plant: such records are mostly of
#: gears whose gap is wide against the chirp (it rattles them), where the start lies in a wrong basin; a load
#: encoder's start does not (README, Known limits; bench/results/family.md).
LOAD_ENCODER_REMEDY = "record with a load encoder: the start then comes from both encoders' equations of motion"
#: ... and, where the record does not show the estimate's resonance (or its band is unknown), a chirp past it.
MOTOR_SIDE_REMEDIES = (LOAD_ENCODER_REMEDY, f"end the chirp at {CHIRP_END_PER_RESONANCE:g}× the resonance or more "
                       "(excitation.f_end_hz), within the sample rate")


def assess(fit: PemFit, *, torque_rms_nm: float, sample_rate_hz: float, load_encoder: bool = True,
           band_top_hz: float | None = None) -> FitQuality:
    """The quality of the estimate (:func:`commission.ident.estimator.kalman_fit`; see the module docstring).
    ``load_encoder``: whether the record had one (without, a fit that leaves model error but follows the record
    names what a new record needs, ``FitQuality.remedies``); ``band_top_hz``: where the record's torque stops
    exciting [Hz] (None: unknown), which lets a remedy name the chirp's end a new record needs."""
    inn = fit.innovations
    if inn is None:
        return _unevaluated(fit, torque_rms_nm, sample_rate_hz)
    nu = inn.normalized[:, 0]
    level = inn.rms
    flat, stationary = whiteness(nu, sample_rate_hz)
    white = flat >= WHITE_FLATNESS and stationary <= WHITE_STATIONARY
    disturbance = fit.disturbance_nm / max(torque_rms_nm, 1e-300)
    absorbed = disturbance >= DISTURBANCE_MISFIT
    suspect = disturbance >= DISTURBANCE_SUSPECT
    misfit = level > INNOVATION_MISFIT or absorbed or suspect
    # a noise model that stands in for missing dynamics leaves curvature that describes no error of the
    # estimate's (a bias): nothing is claimed then
    explained = level < INNOVATION_UNDETERMINED and not absorbed
    resonance_hz = _resonance_hz(fit.parameters)
    unseen_hz = _unseen_resonance_hz(resonance_hz, band_top_hz, sample_rate_hz)
    determined = explained and unseen_hz is None
    scale = max(1.0, level) if misfit else 1.0
    if scale > 1.0:
        fit = replace(fit, covariance=fit.covariance * scale ** 2)
    reasons: list[str] = []
    if level >= INNOVATION_UNDETERMINED:
        reasons.append(f"the model's one-step predictions miss by {level:.0f}× what the noise explains: the record "
                       "does not determine the parameters or ε under this model; their intervals are unbounded")
    elif absorbed:
        reasons.append(f"the model follows the record only with a torque disturbance of {100 * disturbance:.2g} % of "
                       "RMS τ_ref per sample, far more than a drive's noise: the rest is torque the model leaves "
                       "unexplained; how far off the parameters are the record does not say, and their intervals "
                       "are unbounded")
    elif level <= INNOVATION_MISFIT and suspect:
        reasons.append(f"the model follows the record only with a torque disturbance of {100 * disturbance:.2g} % of "
                       "RMS τ_ref per sample, more than a drive's noise: torque the model leaves unexplained may bias "
                       "the parameters by more than their intervals")
    elif misfit:
        reasons.append(f"the model's one-step predictions miss by {level:.2g}× what the encoders' and the torque's "
                       "noise explain" + ("" if white else ", and not as white noise") + ": torque the model leaves unexplained, "
                       "dynamics it does not reproduce; the parameters may be off by more than their intervals")
    if unseen_hz is not None and level < INNOVATION_UNDETERMINED:
        p = fit.parameters
        reasons.append(f"the estimate puts the resonance at {unseen_hz:.3g} Hz, beyond the "
                       f"{_shown_top_hz(band_top_hz, sample_rate_hz):.0f} Hz this record shows: it determines the "
                       f"total inertia J_m + J_l ({p.J_m + p.J_l:.4g} kg·m²) but neither how it splits between motor "
                       "and load nor the shaft's stiffness, damping and gap; their intervals are unbounded")
    if not fit.converged:
        reasons.append("the least squares stopped at its evaluation limit before converging: the parameters "
                       "may not be at the fit's optimum, and the intervals (from the curvature there) may not hold")
    if determined:  # else the first reason says the intervals are unbounded: no narrower one is named
        reasons += _interval_reasons(fit)
    return FitQuality(residual_ratio=disturbance * max(1.0, level), noise_floor_ratio=0.0, spectral_flatness=flat,
                      window_rms_p90_over_median=stationary, noise_limited=bool(white and not misfit),
                      approximate=bool(reasons), reasons=tuple(reasons), cutoff_hz=0.5 * sample_rate_hz,
                      observer_bandwidth_hz=0.0, effective_samples=fit.n_effective, converged=fit.converged,
                      interval_scale=scale, model_error=bool(misfit or not explained), determined=determined,
                      innovation_rms=level, process_noise_ratio=disturbance,
                      remedies=(_remedies(resonance_hz, band_top_hz, sample_rate_hz)
                                if misfit and level < INNOVATION_UNDETERMINED and not load_encoder
                                else (_unseen_remedy(band_top_hz, sample_rate_hz),) if unseen_hz is not None else ()))


def _unseen_remedy(band_top_hz: float | None, sample_rate_hz: float) -> str:
    """What a record whose shaft :func:`_unseen_resonance_hz` found hidden needs (22:083: at 20 bits instead of
    17 its motor encoder gave J and K within 0.05 %; a chirp 5× as large, or a 20-bit load encoder
    beside the 17-bit motor's, left it flagged)."""
    return (f"log the motor's position with a finer encoder (more bits): this record shows no resonance below "
            f"{_shown_top_hz(band_top_hz, sample_rate_hz):.0f} Hz, where a damped shaft hides in a coarse encoder's "
            "steps; or end the chirp higher (excitation.f_end_hz) if the shaft resonates above that")


def _shown_top_hz(band_top_hz: float | None, sample_rate_hz: float) -> float:
    """The highest frequency a record shows: where its torque stops exciting, and below Nyquist [Hz]."""
    return min(band_top_hz if band_top_hz is not None else math.inf, 0.5 * sample_rate_hz)


def _resonance_hz(estimate: TwoMassParameters) -> float:
    """The estimate's resonance [Hz]; NaN where it has no complex pole pair (the assessment of the modes says so)."""
    try:
        return modes(estimate).f_resonance_hz
    except IdentificationError:
        return math.nan


def _unseen_resonance_hz(resonance_hz: float, band_top_hz: float | None, sample_rate_hz: float) -> float | None:
    """The estimate's resonance where it lies beyond what the record shows (:func:`_shown_top_hz`), else None [Hz].

    Checked only where the excited band is known (the final assessment): a light load on a damped shaft whose
    resonance hides in a coarse encoder's noise gave a rigid body's fit, J_m + J_l exact and the resonance at
    54 kHz for 227 Hz, K ×1100 with a 0.01 % interval (22:083)."""
    if band_top_hz is None or not resonance_hz > _shown_top_hz(band_top_hz, sample_rate_hz):
        return None
    return resonance_hz


def _remedies(resonance_hz: float, band_top_hz: float | None, sample_rate_hz: float) -> tuple[str, ...]:
    """What a new motor-side record needs: a load encoder; and a chirp ending at ``CHIRP_END_PER_RESONANCE``×
    the estimate's resonance (``resonance_hz``, NaN where it has none) where this record's band stops below
    ``CHIRP_END_ENOUGH_PER_RESONANCE``× it (named: a flagged estimate of the family puts the resonance up to 73 % low but at most 3 % high, so the
    frequency is a floor), or does not reach it (not named: the record does not show it; 2 s of a chirp with
    heavy motor friction put it at 2.4 kHz, 37× the plant's). A band past ``CHIRP_END_ENOUGH_PER_RESONANCE``×
    the resonance gets no chirp remedy: a longer sweep did not help there."""
    if band_top_hz is None or not resonance_hz < band_top_hz:
        return MOTOR_SIDE_REMEDIES
    if band_top_hz >= CHIRP_END_ENOUGH_PER_RESONANCE * resonance_hz:
        return (LOAD_ENCODER_REMEDY,)
    end_hz = CHIRP_END_PER_RESONANCE * resonance_hz
    chirp = (f"end the chirp at {end_hz:.0f} Hz or more (excitation.f_end_hz): {CHIRP_END_PER_RESONANCE:g}× the "
             f"resonance this estimate puts at {resonance_hz:.0f} Hz, where this record's torque stops near "
             f"{band_top_hz:.0f} Hz")
    rate_hz = end_hz / BAND_TOP_PER_SAMPLE_RATE
    if rate_hz > sample_rate_hz:
        chirp += f", at a sample rate of {rate_hz:.0f} Hz or more"
    return LOAD_ENCODER_REMEDY, chirp


def _unevaluated(fit: PemFit, torque_rms_nm: float, sample_rate_hz: float) -> FitQuality:
    """The quality of an estimate where the predictor has no prediction errors (a mode with coincident
    poles): nothing is determined, and it says so."""
    reason = ("the Kalman predictor cannot be evaluated at the estimate (a mode with coincident poles): the record "
              "does not determine the parameters or ε under this model; their intervals are unbounded")
    return FitQuality(residual_ratio=math.inf, noise_floor_ratio=0.0, spectral_flatness=0.0,
                      window_rms_p90_over_median=math.inf, noise_limited=False, approximate=True, reasons=(reason,),
                      cutoff_hz=0.5 * sample_rate_hz, observer_bandwidth_hz=0.0, effective_samples=fit.n_effective,
                      converged=fit.converged, model_error=True, determined=False, innovation_rms=math.inf,
                      process_noise_ratio=fit.disturbance_nm / max(torque_rms_nm, 1e-300))
