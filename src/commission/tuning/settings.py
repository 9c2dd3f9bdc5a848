"""Types of the controller design: options, presets, settings, margins (SI units).

Kept apart from the design's search (:mod:`.design`), the loop analysis (:mod:`.loop`) and
the closed-loop checks (:mod:`.scenarios`, :mod:`.verify`), which all depend on them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ..exceptions import CommissionError

__all__ = [
    "BacklashCompensation", "ControllerSettings", "LoopMargins", "Notch", "Preset", "TuningError", "TuningOptions",
]


class TuningError(CommissionError):
    """No controller settings can be derived (invalid model, no feasible gain)."""


class Preset(str, Enum):
    """Margins and ratios of the design (``tuning.preset`` in the config)."""

    SOFT = "soft"
    STANDARD = "standard"
    STIFF = "stiff"


#: preset -> (PM [deg], GM [dB], integral ratio T_i·ω_c, position ratio ω_bw/K_p,
#:            anti-resonance fraction K_p/ω_a, velocity FF, torque FF)
_PRESETS: dict[Preset, tuple[float, float, float, float, float, float, float]] = {
    Preset.SOFT: (60.0, 12.0, 6.0, 6.0, 0.25, 0.7, 0.7),
    Preset.STANDARD: (45.0, 8.0, 4.0, 4.0, 0.35, 1.0, 1.0),
    Preset.STIFF: (40.0, 6.0, 3.0, 3.0, 0.5, 1.0, 1.0),
}


class TuningOptions(BaseModel):
    """Options of the controller design and of its closed-loop verification (``tuning:`` in the config).

    ``None`` takes the preset's value.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    preset: Preset = Field(Preset.STANDARD, description="'soft' (PM 60°, GM 12 dB), 'standard' (45°, 8 dB) "
                           "or 'stiff' (40°, 6 dB)")
    phase_margin_deg: float | None = Field(None, gt=0, lt=90, description="required phase margin [deg]")
    gain_margin_db: float | None = Field(None, gt=0, lt=40, description="required gain margin [dB]")
    design_guard_deg: float = Field(3.0, ge=0, le=30, description="extra phase margin the design keeps on the "
                                    "identified model, for model error [deg]")
    design_guard_db: float = Field(1.0, ge=0, le=10, description="extra gain margin the design keeps [dB]")
    sample_rate_hz: float = Field(8000.0, gt=0, description="the drive's velocity-loop clock [Hz]")
    current_loop_bandwidth_hz: float | None = Field(
        None, gt=0, description="first-order current-loop bandwidth [Hz]; None = ideal (the simulated drive)")
    computation_delay_samples: int = Field(
        0, ge=0, le=8, description="extra whole samples between velocity sample and torque output")
    notch: Literal["auto", "on", "off"] = Field("auto", description="notch at the identified resonance: "
                                                "'auto' = when it raises the bandwidth")
    notch_min_gain: float = Field(0.10, ge=0, description="'auto': relative bandwidth gain that justifies a notch")
    notch_peak_db: float = Field(1.0, ge=0, description="'auto': a closed-loop peak near the resonance above "
                                 "this, without a notch, calls for one [dB]")
    notch_damping: float = Field(0.5, gt=0.05, le=1.0, description="damping of the notch's poles "
                                 "(Q = 1/(2·ζ)); its zeros take the identified resonance damping")
    torque_filter_ratios: tuple[float, ...] = Field(
        (2.0, 3.0, 4.0, 6.0), description="candidate torque-filter corners, as multiples of the "
        "high-frequency crossover k_p/(2π·J_m)")
    max_torque_filter_fraction: float = Field(0.35, gt=0, lt=0.5, description="highest torque-filter corner "
                                              "as a fraction of the sample rate")
    integral_ratio: float | None = Field(None, ge=1.5, le=20, description="T_i·2π·K_v [-] (preset: 6/4/3)")
    position_ratio: float | None = Field(None, ge=1.5, le=20, description="velocity bandwidth / position "
                                         "bandwidth, 2π·f_bw/K_p [-] (preset: 6/4/3)")
    antiresonance_fraction: float | None = Field(None, gt=0, le=2, description="K_p ≤ this·2π·f_antiresonance "
                                                 "(load vibration in semi-closed loop) (preset: .25/.35/.5)")
    velocity_feedforward: float | None = Field(None, ge=0, le=1.2, description="velocity feedforward [-]")
    torque_feedforward: float | None = Field(None, ge=0, le=1.2, description="torque feedforward [-] "
                                             "(× (J_m + J_l) × reference acceleration)")
    backlash_compensation: bool = Field(True, description="compensate the identified backlash")
    backlash_threshold_deg: float = Field(0.01, ge=0, description="ε at or below this is 'no backlash' [deg]")
    backlash_max_residual_ratio: float = Field(0.005, gt=0, description="no backlash compensation when the "
                                               "identification leaves more than this fraction of the torque "
                                               "unexplained (its ε is then not trusted), unless it found that "
                                               "residual to be white torque noise [-]")
    backlash_time_constant_s: float | None = Field(None, gt=0, le=1.0, description="smoothing of the "
                                                   "compensation [s]; None = 1/K_p")
    backlash_approach_filter: bool = Field(True, description="with backlash compensation, smooth the position "
                                           "reference so that the load comes to rest on the driving flank "
                                           "(first-order, backlash_approach_factor·J_l/B_l); off = faster, but the load "
                                           "may stop anywhere in the gap")
    backlash_approach_factor: float = Field(2.0, ge=1.0, le=10.0, description="reference filter time constant "
                                            "as a multiple of the load's own decay time J_l/B_l [-]")
    backlash_approach_max_s: float = Field(0.5, gt=0, le=2.0, description="longest reference filter time "
                                           "constant the design will set [s]")
    # verification
    torque_limit_nm: float = Field(1.9, gt=0, description="torque limit of the verification runs [N·m]")
    velocity_step_rad_s: float = Field(5.0, gt=0, description="verification: velocity step [rad/s]")
    position_step_rad: float = Field(0.1, gt=0, description="verification: position step [rad]")
    reversal_move_rad: float = Field(0.5, gt=0, description="verification: reversal move, each way [rad]")
    reversal_move_time_s: float = Field(0.2, gt=0, description="verification: time of each move [s]")
    max_limit_cycle_rad: float = Field(2e-4, gt=0, description="largest limit-cycle amplitude of the load "
                                       "position allowed for 'ready' [rad]")
    settle_band: float = Field(0.02, gt=0, lt=0.5, description="settling band, fraction of the step [-]")

    def requirements(self) -> tuple[float, float]:
        """(required PM [deg], required GM [dB])."""
        pm, gm = _PRESETS[self.preset][:2]
        return (self.phase_margin_deg if self.phase_margin_deg is not None else pm,
                self.gain_margin_db if self.gain_margin_db is not None else gm)

    def ratio(self, name: str) -> float:
        """A preset-dependent ratio: integral, position, antiresonance, vff, tff."""
        idx = {"integral": 2, "position": 3, "antiresonance": 4, "vff": 5, "tff": 6}[name]
        own = {"integral": self.integral_ratio, "position": self.position_ratio,
               "antiresonance": self.antiresonance_fraction, "vff": self.velocity_feedforward,
               "tff": self.torque_feedforward}[name]
        return float(own) if own is not None else _PRESETS[self.preset][idx]


@dataclass(frozen=True)
class Notch:
    """A notch filter H(s) = (s² + 2·d·ζ·ω·s + ω²)/(s² + 2·ζ·ω·s + ω²), ζ = 1/(2Q)."""

    frequency_hz: float
    q: float
    depth: float
    """Gain at the centre d [-] (0 = full notch, 1 = none)."""

    @property
    def depth_db(self) -> float:
        return 20.0 * math.log10(max(self.depth, 1e-6))


@dataclass(frozen=True)
class BacklashCompensation:
    """The position offset added at reversals (amount 2ε in motor position)."""

    amount_rad: float
    """Total offset between the two directions, 2ε [rad] (0 = off)."""
    time_constant_s: float
    """First-order smoothing of the offset [s]."""
    direction: Literal["forward", "reverse"] = "forward"
    """"forward": the motor is sent ε further in the direction of motion (the load rests on the
    driving flank after a move); "reverse": ε less (the load coasts onto the braking flank).
    A drive that compensates one way only (YASKAWA Pn230) adds the amount in this direction."""

    @property
    def sign(self) -> float:
        return 1.0 if self.direction == "forward" else -1.0

    @property
    def enabled(self) -> bool:
        return self.amount_rad > 0.0


@dataclass(frozen=True)
class LoopMargins:
    """Margins of one velocity loop (discrete time, at the drive's clock)."""

    phase_margin_deg: float
    """Smallest over every gain crossover of the angle between L and −1, |∠(−L)| [deg] (inf: none):
    the smallest phase change that makes the loop marginal there."""
    gain_margin_db: float
    """Smallest over the phase crossovers where |L| < 1 [dB] (inf: none)."""
    crossover_hz: float
    """Highest gain crossover [Hz]."""
    phase_crossover_hz: float
    """Phase crossover of the gain margin [Hz] (nan: none)."""
    stability_margin: float
    """Smallest distance of L(e^{jωT}) from −1 [-]."""
    stable: bool
    """All closed-loop poles inside the unit circle."""

    def meets(self, pm: float, gm: float) -> bool:
        return self.stable and self.phase_margin_deg >= pm and self.gain_margin_db >= gm

    def as_dict(self) -> dict[str, Any]:
        return {"phase_margin_deg": _num(self.phase_margin_deg), "gain_margin_db": _num(self.gain_margin_db),
                "crossover_hz": _num(self.crossover_hz), "phase_crossover_hz": _num(self.phase_crossover_hz),
                "stability_margin": _num(self.stability_margin), "stable": bool(self.stable)}


def _num(x: float) -> float | None:
    """JSON-safe float (None for inf/nan)."""
    return float(x) if math.isfinite(x) else None


@dataclass(frozen=True)
class ControllerSettings:
    """Controller-ready settings (SI units) and how they were found."""

    sample_rate_hz: float
    motor_inertia_kg_m2: float
    load_inertia_kg_m2: float
    velocity_gain: float
    """k_p [N·m·s/rad]."""
    velocity_integral_time_s: float
    """T_i [s] (k_i = k_p / T_i)."""
    velocity_bandwidth_hz: float
    """−3 dB bandwidth of v_m/v* on the identified model (contact) [Hz]."""
    position_gain_per_s: float
    """K_p [1/s]."""
    torque_filter_time_constant_s: float
    """First-order torque-reference low-pass [s] (0 = none)."""
    notches: tuple[Notch, ...]
    velocity_feedforward: float
    """[-] (1 = the reference velocity fully fed forward)."""
    torque_feedforward: float
    """[-] (× (J_m + J_l) × reference acceleration)."""
    backlash: BacklashCompensation
    margins: LoopMargins
    """On the identified model in contact (python-control)."""
    margins_gap: LoopMargins | None
    """On the motor alone (gears apart), when backlash was identified."""
    required_phase_margin_deg: float
    required_gain_margin_db: float
    preset: Preset
    position_margins: LoopMargins | None = None
    """Of the position loop around the closed velocity loop, on the identified model (contact)."""
    current_loop_bandwidth_hz: float | None = None
    computation_delay_samples: int = 0
    reference_filter_time_constant_s: float = 0.0
    """First-order position-reference filter [s] (0 = none): set with the backlash compensation,
    it makes every move end slower than the load decays by itself, so the load rests on the
    driving flank and the compensation is exact (YASKAWA Pn216)."""
    epsilon_rad: float = 0.0
    """Identified backlash half-width ε [rad]."""
    resonance_hz: float = math.nan
    antiresonance_hz: float = math.nan
    candidates: tuple[dict[str, Any], ...] = ()
    """Best candidate per (notch, filter ratio): {"notch", "filter_ratio", "bandwidth_hz", "kv_hz"}."""
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def inertia_ratio(self) -> float:
        """J_l / J_m [-]."""
        return self.load_inertia_kg_m2 / self.motor_inertia_kg_m2

    @property
    def total_inertia_kg_m2(self) -> float:
        return self.motor_inertia_kg_m2 + self.load_inertia_kg_m2

    @property
    def velocity_integral_gain(self) -> float:
        """k_i = k_p / T_i [N·m/rad]."""
        return self.velocity_gain / self.velocity_integral_time_s

    @property
    def velocity_loop_gain_hz(self) -> float:
        """Rigid-body velocity-loop gain K_v = k_p / (2π·(J_m + J_l)) [Hz] (YASKAWA Pn100's meaning)."""
        return self.velocity_gain / (2.0 * math.pi * self.total_inertia_kg_m2)

    @property
    def meets_margins(self) -> bool:
        pm, gm = self.required_phase_margin_deg, self.required_gain_margin_db
        ok = self.margins.meets(pm, gm)
        if self.margins_gap is not None:
            ok = ok and self.margins_gap.meets(pm, gm)
        return ok

    def without_notch(self) -> ControllerSettings:
        return replace(self, notches=())

    def without_backlash_compensation(self) -> ControllerSettings:
        """No offset and no reference filter (the filter is there for the compensation)."""
        return replace(self, backlash=replace(self.backlash, amount_rad=0.0), reference_filter_time_constant_s=0.0)
