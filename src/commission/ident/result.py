"""Results of the identifier: typed, SI units, written to result.json by one schema (:meth:`Identification.to_dict`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .options import Method
from .twomass import Modes, TwoMassParameters

__all__ = ["FitQuality", "Identification", "StageResult"]


@dataclass(frozen=True)
class StageResult:
    """One stage of a pipeline: its name, wall time and what it found."""

    name: str
    seconds: float
    """Wall time [s]."""
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class FitQuality:
    """How well the identified model reproduces the record: read it before trusting the numbers."""

    residual_ratio: float
    """RMS of the motor equation's residual / RMS of the (equally low-passed) τ_ref [-], every sample
    but the low-pass's edge transients."""
    noise_floor_ratio: float
    """What the encoder's quantization alone leaves, as the same ratio [-]."""
    spectral_flatness: float
    """Of the residual's spectrum (1: white) [-]."""
    window_rms_p90_over_median: float
    """90th percentile / median of the residual's RMS over 50 windows (1: stationary) [-]."""
    noise_limited: bool
    """The residual over the good-fit level is white, stationary noise (not model error)."""
    approximate: bool
    """The result may be off by more than its intervals say, or its intervals are wide: see ``reasons``."""
    reasons: tuple[str, ...]
    """Why the result is approximate (empty when it is not)."""
    cutoff_hz: float
    """Low-pass of the residual [Hz]."""
    observer_bandwidth_hz: float
    """Bandwidth of the load-state observer [Hz] (0: the load simulated open loop)."""
    effective_samples: float
    """Independent residual samples behind the intervals."""
    interval_scale: float = 1.0
    """Factor (≥ 1) the covariance's intervals are widened by: the residual over its noise (the good-fit
    level, the quantization floor or its own white, stationary part): model error, which the residual's
    statistics cannot show [-]."""
    converged: bool = True
    """The least squares stopped at a stationary point (its step or cost change below tolerance), not at
    its evaluation limit: only then do the intervals, from the curvature there, describe the estimate."""
    model_error: bool = False
    """The residual is model error (dynamics the model does not reproduce), not the record's noise: above
    the approximate level and not white, or in bursts above the good-fit level."""
    determined: bool = True
    """False when the model explains none of the torque (its residual is at least RMS τ_ref, as much as no
    model at all leaves), or the estimate's resonance lies beyond what the record shows: the estimates carry
    no information on the shaft, and every interval is the whole range the fit searched."""

    innovation_rms: float | None = None
    """Kalman fit: RMS of its normalized one-step prediction errors e/√S (1: the model and the noise
    model explain the record; more is model error) [-]."""
    process_noise_ratio: float | None = None
    """Kalman fit: the torque disturbance per sample its noise model assumes (chosen by likelihood; the larger of
    the motor's and the load's) / RMS τ_ref [-]."""
    remedies: tuple[str, ...] = ()
    """What a new record would need, when a record without a load encoder leaves model error the predictor still
    follows (a start in a wrong basin, typically): for the technician, not a reason; empty otherwise."""

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["reasons"] = list(self.reasons)
        out["remedies"] = list(self.remedies)
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in out.items()}


@dataclass(frozen=True)
class Identification:
    """Result of :func:`commission.ident.identify` (SI units unless the name says otherwise)."""

    method: Method
    parameters: TwoMassParameters
    epsilon_rad: float
    """Backlash half-width ε [rad] (the estimate, also when no backlash is detected)."""
    epsilon_interval_rad: tuple[float, float]
    """95 % interval of ε [rad]: hybrid, from the estimator's covariance; paper, the search's."""
    evaluations: int
    """Residual evaluations (hybrid: scan and least squares; paper: the ε searches)."""
    modes: Modes
    num: NDArray[np.float64]
    """V_m/T_ref numerator, descending powers of s (from ``parameters``)."""
    den: NDArray[np.float64]
    """V_m/T_ref denominator, descending powers of s, den[0] = 1."""
    delay_s: float
    """Pure delay of the data [s] (one sample: the drive convention)."""
    iterations: list[dict[str, float]]
    """Step-5 checks: {"frd_error", "epsilon_deg"} per iteration."""
    stages: list[StageResult]
    source_samples: int
    sample_rate_hz: float
    backlash_detected: bool
    notes: list[str] = field(default_factory=list)
    fit: FitQuality | None = None
    """Hybrid: how well the model reproduces the record."""
    parameter_stderr: dict[str, float] | None = None
    """Relative standard errors of J_m … D (hybrid) [-]."""
    parameter_interval: dict[str, tuple[float, float]] | None = None
    """95 % intervals of J_m … D in their units (hybrid)."""
    friction: dict[str, Any] | None = None
    """Kept Coulomb terms (hybrid): velocity_scale_rad_s and, per kept side, motor_nm / load_nm [N·m]
    with motor_interval_nm / load_interval_nm (95 %); None when none kept."""
    current_loop: dict[str, Any] | None = None
    """Kept current-loop lag (hybrid): bandwidth_hz, bandwidth_interval_hz, time_constant_s; None when not kept."""
    cogging: dict[str, Any] | None = None
    """A torque periodic in the motor's position taken out of τ_ref (hybrid; commission.ident.cogging.Cogging's
    fields): harmonics_per_revolution, cos_nm, sin_nm, peak_nm, explained; None when none found."""
    selection: dict[str, Any] | None = None
    """Model selection (hybrid): per candidate term its Wald z², the threshold ln n, kept."""
    measured_band_hz: tuple[float, float] | None = None
    """The band the record measured with good signal (the FRD's quality), where the model is known [Hz]."""
    epsilon_determined: bool = True
    """False when the record does not determine ε (its model explains nothing, or the load never crosses
    the gap): ``epsilon_interval_rad`` is then every ε the identifier searched."""

    @property
    def epsilon_deg(self) -> float:
        return math.degrees(self.epsilon_rad)

    @property
    def approximate(self) -> bool:
        """True when the fit quality says the result is approximate (hybrid)."""
        return bool(self.fit is not None and self.fit.approximate)

    def stage(self, name: str) -> StageResult:
        """The stage called ``name``."""
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(name)

    def to_dict(self, source_file: str | None = None) -> dict[str, Any]:
        """The result.json document."""
        lo, hi = self.epsilon_interval_rad
        m = self.modes
        out: dict[str, Any] = {
            "backlash": {"epsilon_deg": math.degrees(self.epsilon_rad),
                         "epsilon_interval_deg": [math.degrees(lo), math.degrees(hi)],
                         "evaluations": int(self.evaluations), "method": self.method.value,
                         "detected": bool(self.backlash_detected), "determined": bool(self.epsilon_determined)},
            "two_mass": self.parameters.as_dict(),
            "modes": {"f_resonance_hz": float(m.f_resonance_hz), "zeta_resonance": float(m.zeta_resonance),
                      "f_antiresonance_hz": float(m.f_antiresonance_hz),
                      "zeta_antiresonance": float(m.zeta_antiresonance)},
            "transfer_function": {"num": [float(v) for v in self.num], "den": [float(v) for v in self.den],
                                  "delay_s": float(self.delay_s)},
            "iterations": [{"frd_error": float(it["frd_error"]), "epsilon_deg": float(it["epsilon_deg"])}
                           for it in self.iterations],
            "source": {"file": source_file, "sample_rate_hz": float(self.sample_rate_hz),
                       "samples": int(self.source_samples)},
            "stages": [{"name": s.name, "seconds": float(s.seconds)} for s in self.stages],
            "notes": list(self.notes),
        }
        if self.fit is not None:
            out["fit"] = self.fit.to_dict()
        if self.parameter_stderr is not None:
            out["two_mass_relative_stderr"] = {k: float(v) for k, v in self.parameter_stderr.items()}
        if self.parameter_interval is not None:
            out["two_mass_interval"] = {k: [float(a), float(b)] for k, (a, b) in self.parameter_interval.items()}
        if self.friction is not None:
            out["friction"] = dict(self.friction)
        if self.current_loop is not None:
            out["current_loop"] = dict(self.current_loop)
        if self.cogging is not None:
            out["cogging"] = dict(self.cogging)
        if self.selection is not None:
            out["model_selection"] = dict(self.selection)
        if self.measured_band_hz is not None:
            out["measured_band_hz"] = [float(v) for v in self.measured_band_hz]
        return _finite(out)


def _finite(x: Any) -> Any:
    """``x`` with every non-finite float as None: JSON has no NaN or infinity (an interval without an
    end, a standard error the fit could not give)."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x
