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
    "BacklashCompensation", "BandwidthLimit", "ControllerSettings", "DriveDynamics", "LimitingFactor", "LoopMargins",
    "Notch", "Preset", "RobustMargins", "Source", "Sourced", "TuningError", "TuningOptions", "UncertaintyMember",
    "UncertaintySet",
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


class UncertaintySet(BaseModel):
    """What the design does not know exactly, as factors and offsets on its nominal values
    (``tuning.uncertainty``); every combination is a member, and the preset's margins must hold
    on each of them. One value each (``(1.0,)``, ``(0,)``) means no uncertainty there."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    current_loop_factors: tuple[float, ...] = Field(
        (0.5, 1.0, 2.0), min_length=1, description="factors on the current-loop bandwidth [-] (an ideal "
        "current loop stays ideal)")
    extra_delay_samples: tuple[float, ...] = Field(
        (0.0, 1.0), min_length=1, description="loop delay added to the nominal [velocity-loop samples]")
    load_inertia_factors: tuple[float, ...] = Field(
        (0.8, 1.0, 1.2), min_length=1, description="factors on the identified J_l [-]")
    stiffness_factors: tuple[float, ...] = Field(
        (0.8, 1.0, 1.2), min_length=1, description="factors on the identified K [-]")
    backlash_factors: tuple[float, ...] = Field(
        (0.0, 1.0, 2.0), min_length=1, description="factors on the identified ε [-]: in the margins, a "
        "member with ε > 0 adds the loop with the gears apart (the motor alone) to the one in contact")

    @classmethod
    def none(cls) -> UncertaintySet:
        """No uncertainty: the nominal model only (for comparisons)."""
        return cls(current_loop_factors=(1.0,), extra_delay_samples=(0.0,), load_inertia_factors=(1.0,),
                   stiffness_factors=(1.0,), backlash_factors=(1.0,))

    def as_dict(self) -> dict[str, Any]:
        return {k: list(v) for k, v in self.model_dump().items()}


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
    sample_rate_hz: float = Field(8000.0, gt=0, description="the drive's velocity-loop clock [Hz] (when set, "
                                  "wins over the drive description's velocity_loop_period_s)")
    current_loop_bandwidth_hz: float | None = Field(
        None, gt=0, description="the drive's current-loop bandwidth, as a first-order lag [Hz]; None = the one "
        "the identification kept, else the drive description's, else assumed_current_loop_bandwidth_hz")
    computation_delay_samples: float | None = Field(
        None, ge=0, le=8, description="the drive's delay from the velocity sample to the torque reserved for "
        "the current loop, beyond the hold's own sample [velocity-loop samples]; None = the whole-sample delay "
        "the identification kept less the encoder delay, else the drive description's, else "
        "assumed_computation_delay_samples")
    encoder_delay_samples: float | None = Field(
        None, ge=0, le=8, description="delay of the position measurement [velocity-loop samples]; None = the "
        "drive description's, else assumed_encoder_delay_samples")
    assumed_current_loop_bandwidth_hz: float = Field(
        2000.0, gt=0, description="current-loop bandwidth assumed when neither the record, the description nor "
        "the config gives one [Hz] (a servo drive's is typically 1–4 kHz; the uncertainty set halves it)")
    assumed_computation_delay_samples: float = Field(
        1.0, ge=0, le=8, description="computation delay assumed when nothing gives one [samples]")
    assumed_encoder_delay_samples: float = Field(
        0.0, ge=0, le=8, description="encoder delay assumed when nothing gives one [samples]")
    ideal_drive: bool = Field(False, description="design as if the current loop were ideal and the loop had no "
                              "delay beyond its sample (only to compare: no real drive is like that)")
    uncertainty: UncertaintySet = Field(UncertaintySet(), description="what the margins must hold over")
    robust_guard_deg: float = Field(0.5, ge=0, le=10, description="extra phase margin the design's search keeps "
                                    "on each member of the uncertainty set [deg] (its margins there are read "
                                    "from a frequency grid, the reported ones exactly)")
    robust_guard_db: float = Field(0.2, ge=0, le=5, description="extra gain margin the search keeps on each "
                                   "member [dB]")
    band_factor: float | None = Field(0.8, gt=0, le=4, description="the velocity loop's crossover stays at or "
                                      "below this × the upper edge of the band the record measured with good "
                                      "signal [-] (None: no band limit)")
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
    verification_current_loop_bandwidth_hz: float | None = Field(
        1000.0, gt=0, description="a simulated plant whose drive is ideal (no current-loop lag, no delay) is "
        "verified with this current loop [Hz], so that a design that holds only on its own assumptions is "
        "caught (None: verify on the plant as it is)")
    verification_delay_samples: int = Field(
        2, ge=0, le=8, description="... and with this computation delay [samples]")
    # staged write-back (--apply)
    apply_conservative_fraction: float = Field(
        0.5, gt=0, lt=1, description="--apply writes first the velocity and position gains × this (integral "
        "time ÷ this, no backlash compensation), checks the closed loop on the drive, then the final set [-]")
    apply_check_segment_s: float = Field(
        0.25, gt=0, le=5, description="--apply's closed-loop check: length of each level of the velocity "
        "reference 0 → +v → −v → 0 (v = velocity_step_rad_s) [s]")
    apply_check_max_overshoot_pct: float = Field(
        50.0, gt=0, description="the check fails above this velocity overshoot after a step [%]")
    apply_check_max_oscillation: float = Field(
        0.05, gt=0, description="the check fails when the velocity oscillates in the second half of a level "
        "with more than this × v (half peak-to-peak) [-]")
    apply_check_max_vibration: float = Field(
        0.10, gt=0, description="the check fails when the torque reference's ripple (RMS after a 2 ms moving "
        "average is removed) in the second half of a level exceeds this × torque_limit_nm [-]")
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


class Source(str, Enum):
    """Where a figure of the drive's loop comes from."""

    CONFIG = "config"
    IDENTIFIED = "identified"
    DESCRIPTION = "drive description"
    ASSUMED = "assumed"
    IDEAL = "ideal"


@dataclass(frozen=True)
class Sourced:
    """A figure the design uses, and where it comes from."""

    value: float | None
    """In the unit its name says (None: none, e.g. an ideal current loop)."""
    how: Source
    source: str
    """The source in words (the manual's section, 'tuning.current_loop_bandwidth_hz', …)."""
    confirm: bool = False
    """The source says it is not from the drive's own manual: confirm it."""

    def as_dict(self) -> dict[str, Any]:
        return {"value": None if self.value is None else float(self.value), "from": self.how.value,
                "source": self.source, "confirm": bool(self.confirm)}


@dataclass(frozen=True)
class DriveDynamics:
    """The drive's own loop as the design models it, each figure with its source."""

    sample_rate_hz: Sourced
    """The velocity loop's clock [Hz]."""
    position_loop_period_s: Sourced
    current_loop_bandwidth_hz: Sourced
    """First-order current loop [Hz]; value None = ideal."""
    computation_delay_samples: Sourced
    """From the sample to the torque reaching the current loop, beyond the hold's sample [samples]."""
    encoder_delay_samples: Sourced
    """Of the position measurement [samples]."""
    gain_limits: dict[str, tuple[float, float]] = field(default_factory=dict)
    """SI ranges the drive's parameters allow: "velocity_gain_hz" (K_v), "velocity_integral_time_s",
    "position_gain_per_s", "velocity_gain" (k_p [N·m·s/rad])."""
    gain_limits_source: str = ""

    @property
    def loop_delay_samples(self) -> float:
        """The loop's delay beyond the hold's sample: computation + encoder [samples]."""
        return float(self.computation_delay_samples.value or 0.0) + float(self.encoder_delay_samples.value or 0.0)

    @property
    def position_loop_delay_samples(self) -> int:
        """Whole velocity-loop samples the position loop's slower clock adds (0: same clock)."""
        period = self.position_loop_period_s.value
        if not period:
            return 0
        return max(0, int(round(period * float(self.sample_rate_hz.value or 0.0))) - 1)

    def as_dict(self) -> dict[str, Any]:
        return {"sample_rate_hz": self.sample_rate_hz.as_dict(),
                "position_loop_period_s": self.position_loop_period_s.as_dict(),
                "current_loop_bandwidth_hz": self.current_loop_bandwidth_hz.as_dict(),
                "computation_delay_samples": self.computation_delay_samples.as_dict(),
                "encoder_delay_samples": self.encoder_delay_samples.as_dict(),
                "loop_delay_samples": self.loop_delay_samples,
                "gain_limits": {k: [_num(a), _num(b)] for k, (a, b) in self.gain_limits.items()},
                "gain_limits_source": self.gain_limits_source}


@dataclass(frozen=True)
class UncertaintyMember:
    """One plant of the uncertainty set: the nominal with these factors and offsets."""

    current_loop_factor: float = 1.0
    extra_delay_samples: float = 0.0
    load_inertia_factor: float = 1.0
    stiffness_factor: float = 1.0
    gap: bool = False
    """The gears apart (the motor alone): a member with ε > 0."""

    @property
    def nominal(self) -> bool:
        return (self.current_loop_factor == 1.0 and self.extra_delay_samples == 0.0
                and self.load_inertia_factor == 1.0 and self.stiffness_factor == 1.0)

    def describe(self, current_loop_hz: float | None = None) -> str:
        parts = []
        if self.current_loop_factor != 1.0 and current_loop_hz is not None:
            parts.append(f"current loop {self.current_loop_factor * current_loop_hz:.0f} Hz "
                         f"(×{self.current_loop_factor:g})")
        if self.extra_delay_samples:
            parts.append(f"delay +{self.extra_delay_samples:g} sample" + ("s" if self.extra_delay_samples != 1 else ""))
        if not self.gap:
            if self.load_inertia_factor != 1.0:
                parts.append(f"J_l ×{self.load_inertia_factor:g}")
            if self.stiffness_factor != 1.0:
                parts.append(f"K ×{self.stiffness_factor:g}")
        parts.append("gears apart (motor alone)" if self.gap else "gears in contact")
        return ", ".join(parts)

    def as_dict(self, current_loop_hz: float | None = None) -> dict[str, Any]:
        return {"current_loop_factor": self.current_loop_factor,
                "current_loop_bandwidth_hz": None if current_loop_hz is None
                else self.current_loop_factor * current_loop_hz,
                "extra_delay_samples": self.extra_delay_samples, "load_inertia_factor": self.load_inertia_factor,
                "stiffness_factor": self.stiffness_factor, "gap": self.gap,
                "description": self.describe(current_loop_hz)}


@dataclass(frozen=True)
class RobustMargins:
    """The worst margins over the uncertainty set, and the members that set them."""

    phase_margin_deg: float
    phase_member: UncertaintyMember
    gain_margin_db: float
    gain_member: UncertaintyMember
    stable: bool
    """Every member's closed loop is stable."""
    unstable: tuple[UncertaintyMember, ...]
    members: int
    """How many members were checked."""
    required_phase_margin_deg: float
    required_gain_margin_db: float
    uncertainty: UncertaintySet
    current_loop_hz: float | None = None
    """The nominal current loop the members' factors apply to [Hz] (None: ideal)."""

    @property
    def holds(self) -> bool:
        """The worst case meets the preset's margins."""
        return (self.stable and self.phase_margin_deg >= self.required_phase_margin_deg
                and self.gain_margin_db >= self.required_gain_margin_db)

    def reasons(self) -> list[str]:
        out = []
        if self.unstable:
            out.append(f"unstable over the uncertainty set: {self.unstable[0].describe(self.current_loop_hz)}"
                       + (f" and {len(self.unstable) - 1} more" if len(self.unstable) > 1 else ""))
        if self.phase_margin_deg < self.required_phase_margin_deg:
            out.append(f"worst-case phase margin {self.phase_margin_deg:.1f}° < {self.required_phase_margin_deg:g}° "
                       f"({self.phase_member.describe(self.current_loop_hz)})")
        if self.gain_margin_db < self.required_gain_margin_db:
            out.append(f"worst-case gain margin {self.gain_margin_db:.1f} dB < {self.required_gain_margin_db:g} dB "
                       f"({self.gain_member.describe(self.current_loop_hz)})")
        return out

    def as_dict(self) -> dict[str, Any]:
        return {"holds": self.holds,
                "phase_margin_deg": _num(self.phase_margin_deg),
                "phase_margin_member": self.phase_member.as_dict(self.current_loop_hz),
                "gain_margin_db": _num(self.gain_margin_db),
                "gain_margin_member": self.gain_member.as_dict(self.current_loop_hz),
                "stable": bool(self.stable),
                "unstable_members": [m.as_dict(self.current_loop_hz) for m in self.unstable],
                "members": int(self.members),
                "required_phase_margin_deg": self.required_phase_margin_deg,
                "required_gain_margin_db": self.required_gain_margin_db,
                "uncertainty": self.uncertainty.as_dict()}


class LimitingFactor(str, Enum):
    """What kept the velocity loop from a higher gain."""

    BAND = "band"
    """The crossover reached the measured band's limit."""
    CURRENT_LOOP = "current loop"
    DELAY = "delay"
    RESONANCE = "resonance"
    MARGINS = "margins"
    """The margins, with no single dominant cause (the sampling, the filters, the mechanics)."""
    GAIN_RANGE = "gain range"
    """The drive's parameter range."""
    SEARCH_RANGE = "search range"
    """The design's own highest gain (sample rate / 8)."""


@dataclass(frozen=True)
class BandwidthLimit:
    """What limited the velocity loop's bandwidth, and why in words."""

    factor: LimitingFactor
    detail: str
    others: tuple[LimitingFactor, ...] = ()
    """Further constraints that bind at the same gain."""

    def as_dict(self) -> dict[str, Any]:
        return {"factor": self.factor.value, "detail": self.detail, "also": [f.value for f in self.others]}


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
    """The current loop the settings were designed for [Hz] (None: ideal)."""
    loop_delay_samples: float = 0.0
    """The loop delay the settings were designed for, beyond the hold's sample: computation +
    encoder [velocity-loop samples]."""
    position_loop_delay_samples: int = 0
    """Whole velocity-loop samples the position loop's slower clock adds."""
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
    dynamics: DriveDynamics | None = None
    """The drive's loop as designed for, with the source of each figure."""
    robust: RobustMargins | None = None
    """The worst margins over the uncertainty set (None: not evaluated)."""
    limit: BandwidthLimit | None = None
    measured_band_hz: tuple[float, float] | None = None
    """The band the record measured with good signal [Hz]."""
    measured_band_source: str = ""
    crossover_limit_hz: float | None = None
    """The highest crossover the band allows (band_factor × its upper edge) [Hz]."""

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
        """The margins hold on the design model and, when evaluated, over the uncertainty set."""
        pm, gm = self.required_phase_margin_deg, self.required_gain_margin_db
        ok = self.margins.meets(pm, gm)
        if self.margins_gap is not None:
            ok = ok and self.margins_gap.meets(pm, gm)
        if self.robust is not None:
            ok = ok and self.robust.holds
        return ok

    def without_notch(self) -> ControllerSettings:
        return replace(self, notches=())

    def without_backlash_compensation(self) -> ControllerSettings:
        """No offset and no reference filter (the filter is there for the compensation)."""
        return replace(self, backlash=replace(self.backlash, amount_rad=0.0), reference_filter_time_constant_s=0.0)
