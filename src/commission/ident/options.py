"""Options of the identifier (validated; units in the names and descriptions)."""

from __future__ import annotations

from enum import Enum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..exceptions import IdentificationError

__all__ = ["IdentificationOptions", "Method", "options_from_mapping"]


class Method(str, Enum):
    """Identification pipeline."""

    HYBRID = "hybrid"
    PAPER = "paper"


class IdentificationOptions(BaseModel):
    """Options of :func:`commission.ident.identify`."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    method: Method = Field(Method.HYBRID, description="Pipeline: 'hybrid' (default) or 'paper'.")
    band_hz: tuple[float, float] | None = Field(
        None, description="Frequency band of the FRD and its fit [Hz], (low, high); default: from the "
        "chirp's start to the top of the band the record's torque excites.")
    resolution_hz: float = Field(
        0.1, gt=0, description="Finest FRD resolution [Hz]; a shorter record is identified at 1/its length.")
    epsilon_bounds_deg: tuple[float, float] = Field(
        (0.01, 1.0), description="Range of the backlash half-width ε's scan [deg] (paper Table 2); the hybrid "
        "scan doubles its top (up to 16°) while its best cell lies there, and the fit may go from 0 to "
        "twice the scanned top.")
    epsilon_resolution_deg: float = Field(
        0.01, gt=0, description="Resolution of the paper method's ε grid [deg]; the hybrid scan steps 5× it.")
    max_iterations: int = Field(5, ge=1, le=50, description="Paper method: passes of steps 4–6 at most.")
    seed: int = Field(0, ge=0, description="Paper method: seed of the Bayesian optimiser.")
    residual_cutoff_hz: float = Field(
        400.0, gt=0, description="Zero-phase low-pass of the torque residual [Hz]; raised to twice the "
        "resonance within the excited band, lowered for a coarse motor encoder.")
    use_load_encoder: bool = Field(True, description="Use the load-side encoder when the recording has one.")
    no_backlash_threshold_deg: float = Field(
        0.01, ge=0, description="ε̂ at or below this [deg] is reported as 'no backlash detected'.")
    damping_splits: tuple[float, ...] = Field(
        (0.2, 0.5, 0.8), description="Hybrid: candidates of φ = B_l/(B_m + B_l) [-] in the start scan.")
    good_fit_ratio: float = Field(
        1e-3, gt=0, description="Hybrid: residual / RMS(low-passed τ_ref) of a model that describes the axis "
        "(24-bit encoders, 1e-4 N·m noise: 3e-4); the result is approximate past 5× this above the "
        "noise floor, unless the residual is white noise [-].")
    observer_bandwidth_factor: float = Field(
        1.0, ge=0, description="Hybrid: bandwidth of the load-state observer as a multiple of the residual's "
        "cut-off (its low-pass on the residual at twice the cut-off; the fit starts with half of it); 0: the "
        "load simulated open loop [-].")
    max_fit_evaluations: int = Field(
        40, ge=5, le=500, description="Hybrid: iterations of the least squares at most.")
    threads: int = Field(2, ge=1, le=64, description="Threads for residual evaluations.")
    model_terms: tuple[Literal["coulomb_motor", "coulomb_load", "current_loop"], ...] = Field(
        ("coulomb_motor", "coulomb_load", "current_loop"),
        description="Hybrid: candidate terms beyond the two-mass + dead-zone model — Coulomb friction "
        "F·tanh(v/v_s) on the motor and on the load side, a first-order current-loop lag. Load friction "
        "is fitted when the start scan's friction column shows friction.")
    term_selection: Literal["bic", "keep_all"] = Field(
        "bic", description="Hybrid: 'bic' keeps a candidate term when its Wald statistic exceeds ln n "
        "(n: the residual's independent samples); 'keep_all' keeps every candidate.")
    coulomb_velocity_scale_rad_s: float = Field(
        2e-3, gt=0, description="Hybrid: velocity scale v_s of the Coulomb terms' smooth sign tanh(v/v_s) [rad/s].")
    quality_threshold: float = Field(
        0.9, ge=0, lt=1, description="Hybrid: FRD bins whose local-polynomial quality is below this are left "
        "out of the frequency-domain start (friction distorts the low frequencies) [-].")
    motor_interpolation: Literal["local", "spline"] = Field(
        "local", description="Hybrid: motor position between samples for the load simulation: 'local' "
        "(Catmull–Rom: a kink at an impact stays local) or 'spline' (global C² spline).")

    @model_validator(mode="after")
    def _check(self) -> IdentificationOptions:
        if self.band_hz is not None and not 0 <= self.band_hz[0] < self.band_hz[1]:
            raise ValueError(f"band_hz must satisfy 0 ≤ low < high, got {self.band_hz}")
        elo, ehi = self.epsilon_bounds_deg
        if not 0 <= elo < ehi < 90:
            raise ValueError(f"epsilon_bounds_deg must satisfy 0 ≤ low < high < 90, got {self.epsilon_bounds_deg}")
        if self.epsilon_resolution_deg > ehi - elo:
            raise ValueError("epsilon_resolution_deg is larger than the search range")
        if not self.damping_splits or not all(0 < p < 1 for p in self.damping_splits):
            raise ValueError("damping_splits must be in (0, 1)")
        return self


def options_from_mapping(data: dict[str, Any]) -> IdentificationOptions:
    """Validated options from a plain mapping (config files); errors as IdentificationError."""
    try:
        return IdentificationOptions.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        loc = ".".join(str(p) for p in first.get("loc", ()))
        raise IdentificationError(f"invalid identification option {loc}: {first.get('msg')}") from err
