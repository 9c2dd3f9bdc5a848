"""Controller design from the identified two-mass model and backlash.

The loop (motor-side feedback, the drive's cascade at its own clock Ts)::

    position P ─► velocity PI ─► torque low-pass ─► notch(es) ─► current loop ─► plant

Design rule (issue #6): the highest velocity-loop gain whose loop, on the identified
model *with* the filters, the sampling (zero-order hold + backward-difference
velocity: one sample) and the current-loop / computation delay, keeps a phase
margin ≥ PM and a gain margin ≥ GM (presets ``soft`` / ``standard`` / ``stiff``).
Every candidate is analysed in discrete time, exactly: the plant is the ZOH
discretisation of V_m/T·(1/s) followed by the drive's (1 − z⁻¹)/Ts, the PI,
the low-pass and the notches are the very difference equations the drive (and
:mod:`.closedloop`) runs.

With backlash the loop has two plants: in contact, the two-mass model; in the
gap, the motor alone (1/(J_m·s + B_m)), whose gain below the resonance is
(J_m + J_l)/J_m times higher. Both must meet the margins (the gap without the
design guard), or the loop may oscillate while the gears are apart.

The search: for each torque-filter ratio and with/without a notch at the
identified resonance, a log-spaced scan of the rigid-body velocity-loop gain
K_v = k_p / (2π·(J_m + J_l)) [Hz] and a bisection at the edge; the candidate
with the highest closed-loop bandwidth wins; a notch is kept only when it raises
the bandwidth by more than ``notch_min_gain`` (a resonance well inside the
velocity-loop bandwidth is damped by the collocated loop; a notch there only costs
phase). Margins for the search are read from a dense frequency grid (fast); the
reported margins of the chosen settings come from ``control.stability_margins``
(python-control) on the same loop, and the two are checked against each other.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any, Literal

import numpy as np
import scipy.signal
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from ..exceptions import CommissionError
from ..ident.twomass import TwoMassParameters, modes

__all__ = [
    "BacklashCompensation", "ControllerSettings", "LoopMargins", "Notch", "Preset", "TuningError",
    "TuningOptions", "design", "loop_margins", "velocity_closed_loop",
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


# --------------------------------------------------------------------------------------------
# discrete-time loop pieces: (num, den) in descending powers of z
# --------------------------------------------------------------------------------------------
Poly = NDArray[np.float64]


def _plant_z(num_s: Poly, den_s: Poly, Ts: float, current_loop_hz: float | None,
             delay_samples: int) -> tuple[Poly, Poly]:
    """Torque samples → velocity samples: z^{-d}·(1 − z⁻¹)/Ts·ZOH{lag(s)·P(s)/s}."""
    num = np.asarray(num_s, dtype=float)
    den = np.polymul(np.asarray(den_s, dtype=float), [1.0, 0.0])
    if current_loop_hz is not None:
        wc = 2.0 * math.pi * current_loop_hz
        num = num * wc
        den = np.polymul(den, [1.0, wc])
    numd, dend, _ = scipy.signal.cont2discrete((num, den), Ts, "zoh")
    nd = np.trim_zeros(np.atleast_2d(numd)[0], "f")
    # (z − 1)/(Ts·z) and z^{-d}
    nd = np.polymul(nd, [1.0 / Ts, -1.0 / Ts])
    dd = np.polymul(dend, np.r_[1.0, np.zeros(1 + delay_samples)])
    # cancel the common (z − 1): the plant has no integrator, ZOH{P/s} has its pole at z = 1
    q_n, r_n = np.polydiv(nd, [1.0, -1.0])
    q_d, r_d = np.polydiv(dd, [1.0, -1.0])
    scale_n = max(np.max(np.abs(nd)), 1e-300)
    scale_d = max(np.max(np.abs(dd)), 1e-300)
    if np.max(np.abs(r_n)) < 1e-9 * scale_n and np.max(np.abs(r_d)) < 1e-9 * scale_d:
        nd, dd = q_n, q_d
    return nd, dd


def _pi_z(kp: float, Ti: float, Ts: float) -> tuple[Poly, Poly]:
    """u = k_p·e + k_i·T_s·Σe (the sum including e[k]): ((k_p + k_i T_s) z − k_p)/(z − 1)."""
    ki = kp / Ti
    return np.array([kp + ki * Ts, -kp]), np.array([1.0, -1.0])


def _lowpass_alpha(tf_s: float, Ts: float) -> float:
    return 1.0 if tf_s <= 0.0 else 1.0 - math.exp(-Ts / tf_s)


def _lowpass_z(tf_s: float, Ts: float) -> tuple[Poly, Poly]:
    """y += α(x − y): α z/(z − (1 − α))."""
    a = _lowpass_alpha(tf_s, Ts)
    return np.array([a, 0.0]), np.array([1.0, -(1.0 - a)])


def notch_coefficients(n: Notch, Ts: float) -> tuple[Poly, Poly]:
    """Tustin discretisation, prewarped at the centre: (b0, b1, b2), (1, a1, a2)."""
    w = 2.0 * math.pi * n.frequency_hz
    zeta = 1.0 / (2.0 * n.q)
    c = w / math.tan(w * Ts / 2.0)  # prewarped bilinear constant
    # H(s) = (s² + 2dζω s + ω²)/(s² + 2ζω s + ω²), s = c (z − 1)/(z + 1)
    def _quad(two_z_w: float) -> Poly:
        return np.array([c * c + two_z_w * c + w * w, 2.0 * (w * w - c * c), c * c - two_z_w * c + w * w])
    b = _quad(2.0 * n.depth * zeta * w)
    a = _quad(2.0 * zeta * w)
    return b / a[0], a / a[0]


def _controller_z(kp: float, Ti: float, tf_s: float, notches: tuple[Notch, ...], Ts: float) -> tuple[Poly, Poly]:
    num, den = _pi_z(kp, Ti, Ts)
    n2, d2 = _lowpass_z(tf_s, Ts)
    num, den = np.polymul(num, n2), np.polymul(den, d2)
    for n in notches:
        b, a = notch_coefficients(n, Ts)
        num, den = np.polymul(num, b), np.polymul(den, a)
    return num, den


def _freq_grid(fs: float, f_low: float = 0.05) -> NDArray[np.float64]:
    """Angular frequencies [rad/s] from f_low to just below Nyquist."""
    return 2.0 * math.pi * np.geomspace(f_low, 0.4999 * fs, 6000)


def _eval(num: Poly, den: Poly, w: NDArray[np.float64], Ts: float) -> NDArray[np.complex128]:
    z = np.exp(1j * w * Ts)
    return np.polyval(num, z) / np.polyval(den, z)


def _grid_margins(L: NDArray[np.complex128], w: NDArray[np.float64], num: Poly, den: Poly) -> LoopMargins:
    """Margins from a dense frequency response (crossings interpolated linearly)."""
    mag = np.abs(L)
    lm = np.log(mag)
    idx = np.flatnonzero(np.sign(lm[:-1]) != np.sign(lm[1:]))
    pms = []
    wgc = []
    for i in idx:
        t = lm[i] / (lm[i] - lm[i + 1])
        wc = w[i] + t * (w[i + 1] - w[i])
        Lc = L[i] + t * (L[i + 1] - L[i])
        pms.append(abs(math.degrees(np.angle(-Lc))))
        wgc.append(wc)
    im = L.imag
    jdx = np.flatnonzero((np.sign(im[:-1]) != np.sign(im[1:])))
    gms = []
    wpc = []
    for i in jdx:
        t = im[i] / (im[i] - im[i + 1])
        Lp = L[i] + t * (L[i + 1] - L[i])
        if Lp.real < 0 and abs(Lp.real) < 1.0:
            gms.append(-20.0 * math.log10(abs(Lp.real)))
            wpc.append(w[i] + t * (w[i + 1] - w[i]))
    pm = min(pms) if pms else math.inf
    if gms:
        j = int(np.argmin(gms))
        gm, fpc = gms[j], wpc[j] / (2 * math.pi)
    else:
        gm, fpc = math.inf, math.nan
    stable = _stable(num, den)
    return LoopMargins(phase_margin_deg=float(pm), gain_margin_db=float(gm),
                       crossover_hz=float(max(wgc) / (2 * math.pi)) if wgc else math.nan,
                       phase_crossover_hz=float(fpc), stability_margin=float(np.min(np.abs(L + 1.0))),
                       stable=stable)


def _stable(num: Poly, den: Poly) -> bool:
    char = np.polyadd(den, num)
    roots = np.roots(char)
    return bool(np.all(np.abs(roots) < 1.0 - 1e-9))


def _bandwidth_hz(L: NDArray[np.complex128], w: NDArray[np.float64]) -> float:
    """−3 dB bandwidth of T = L/(1 + L) [Hz]: the lowest frequency from which |T| stays below
    −3 dB for an octave. A lightly damped anti-resonance inside the loop (a zero pair of the
    plant) notches |T| below −3 dB over a few percent of frequency; that dip is not where the loop
    stops following (measured: 100 Hz, ζ 0.05 plant, notch at 71 Hz read as the bandwidth of a
    loop whose gain crosses 0 dB at 716 Hz)."""
    T = np.abs(L / (1.0 + L))
    low = T < 1.0 / math.sqrt(2.0)
    # the grid is geometric: an octave is a fixed number of points
    octave = max(1, int(round(math.log(2.0) / math.log(w[1] / w[0])))) if w.size > 1 else 1
    for i in np.flatnonzero(low):
        if low[i:i + octave + 1].all() or i + octave >= w.size:
            return float(w[i] / (2 * math.pi))
    return float(w[-1] / (2 * math.pi))


# --------------------------------------------------------------------------------------------
# the design
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Model:
    params: TwoMassParameters
    epsilon_rad: float
    backlash: bool


def _as_model(model: Any, epsilon_rad: float | None, options: TuningOptions) -> _Model:
    if isinstance(model, TwoMassParameters):
        eps = float(epsilon_rad or 0.0)
        return _Model(model, eps, eps > math.radians(options.backlash_threshold_deg))
    params = getattr(model, "parameters", None)
    if not isinstance(params, TwoMassParameters):
        raise TuningError(f"design() needs an Identification or TwoMassParameters, got {type(model).__name__}")
    eps = float(model.epsilon_rad if epsilon_rad is None else epsilon_rad)
    detected = bool(getattr(model, "backlash_detected", True))
    return _Model(params, eps, detected and eps > math.radians(options.backlash_threshold_deg))


def _check_params(p: TwoMassParameters) -> None:
    arr = p.as_array()
    if not np.all(np.isfinite(arr)) or p.J_m <= 0 or p.J_l <= 0 or p.K <= 0 or min(p.B_m, p.B_l, p.D) < 0:
        raise TuningError(f"the two-mass model is not physical: {p}")


@dataclass
class _Loop:
    """Everything the search needs for one plant, evaluated once."""

    Ts: float
    w: NDArray[np.float64]
    contact: tuple[Poly, Poly, NDArray[np.complex128]]
    gap: tuple[Poly, Poly, NDArray[np.complex128]] | None
    motor_alone: NDArray[np.complex128]
    """Response of the motor alone (the two-mass model's high-frequency asymptote)."""


def _loop_plants(p: TwoMassParameters, with_gap: bool, options: TuningOptions) -> _Loop:
    Ts = 1.0 / options.sample_rate_hz
    w = _freq_grid(options.sample_rate_hz)
    num, den = p.velocity_tf()
    pn, pd = _plant_z(num, den, Ts, options.current_loop_bandwidth_hz, options.computation_delay_samples)
    contact = (pn, pd, _eval(pn, pd, w, Ts))
    gn, gd = _plant_z(np.array([1.0 / p.J_m]), np.array([1.0, p.B_m / p.J_m]), Ts,
                      options.current_loop_bandwidth_hz, options.computation_delay_samples)
    alone = _eval(gn, gd, w, Ts)
    return _Loop(Ts, w, contact, (gn, gd, alone) if with_gap else None, alone)


def _evaluate(loop: _Loop, kp: float, Ti: float, tf_s: float, notches: tuple[Notch, ...]
              ) -> tuple[LoopMargins, LoopMargins | None, float]:
    cn, cd = _controller_z(kp, Ti, tf_s, notches, loop.Ts)
    C = _eval(cn, cd, loop.w, loop.Ts)
    pn, pd, P = loop.contact
    L = C * P
    m = _grid_margins(L, loop.w, np.polymul(cn, pn), np.polymul(cd, pd))
    bw = _bandwidth_hz(L, loop.w)
    mg = None
    if loop.gap is not None:
        gn, gd, G = loop.gap
        mg = _grid_margins(C * G, loop.w, np.polymul(cn, gn), np.polymul(cd, gd))
    return m, mg, bw


def _gains(kv_hz: float, J: float, J_m: float, filter_ratio: float, options: TuningOptions) -> tuple[float, float, float]:
    """(k_p, T_i, T_f) of a rigid-body gain K_v."""
    wv = 2.0 * math.pi * kv_hz
    kp = J * wv
    Ti = options.ratio("integral") / wv
    f_hf = kp / (2.0 * math.pi * J_m)  # crossover on the motor inertia alone
    f_filter = min(filter_ratio * f_hf, options.max_torque_filter_fraction * options.sample_rate_hz)
    return kp, Ti, 1.0 / (2.0 * math.pi * f_filter)


def _notch_for(p: TwoMassParameters, options: TuningOptions) -> Notch:
    m = modes(p)
    zn = options.notch_damping
    depth = min(1.0, max(0.0, m.zeta_resonance / zn))
    return Notch(frequency_hz=float(m.f_resonance_hz), q=1.0 / (2.0 * zn), depth=float(depth))


def _search(loop: _Loop, p: TwoMassParameters, notches: tuple[Notch, ...], filter_ratio: float,
            options: TuningOptions) -> tuple[float, float] | None:
    """Highest feasible K_v [Hz] and its bandwidth; None if none is feasible."""
    pm_req, gm_req = options.requirements()
    pm_d, gm_d = pm_req + options.design_guard_deg, gm_req + options.design_guard_db
    J = p.J_m + p.J_l

    def feasible(kv: float) -> tuple[bool, float]:
        kp, Ti, tf_s = _gains(kv, J, p.J_m, filter_ratio, options)
        m, mg, bw = _evaluate(loop, kp, Ti, tf_s, notches)
        ok = m.meets(pm_d, gm_d) and (mg is None or mg.meets(pm_req, gm_req))
        return ok, bw

    grid = np.geomspace(0.5, options.sample_rate_hz / 8.0, 48)
    ok = [feasible(float(kv))[0] for kv in grid]
    if not any(ok):
        return None
    i = max(j for j, good in enumerate(ok) if good)
    last_ok = float(grid[i])
    if i + 1 < grid.size:
        lo, hi = last_ok, float(grid[i + 1])
        for _ in range(10):
            mid = math.sqrt(lo * hi)
            if feasible(mid)[0]:
                lo = mid
            else:
                hi = mid
        last_ok = lo
    return last_ok, feasible(last_ok)[1]


def _peaks(loop: _Loop, p: TwoMassParameters, notches: tuple[Notch, ...], best: tuple[float, float, float],
           f_r: float, options: TuningOptions) -> tuple[float, float]:
    """(resonance peak, load peak) [dB] of a candidate: the largest excess of |v_m/v*| over the same loop
    around the motor alone within 0.7–1.4·f_r, and the peak of |v_l/v*|."""
    kv, _, ratio = best
    kp, Ti, tf_s = _gains(kv, p.J_m + p.J_l, p.J_m, ratio, options)
    cn, cd = _controller_z(kp, Ti, tf_s, notches, loop.Ts)
    L = _eval(cn, cd, loop.w, loop.Ts) * loop.contact[2]
    T = L / (1.0 + L)
    La = _eval(cn, cd, loop.w, loop.Ts) * loop.motor_alone
    Ta = La / (1.0 + La)
    f = loop.w / (2.0 * math.pi)
    band = (f >= 0.7 * f_r) & (f <= 1.4 * f_r)
    s = 1j * loop.w
    Tl = T * (p.D * s + p.K) / (p.J_l * s * s + (p.D + p.B_l) * s + p.K)
    excess = 20.0 * np.log10(np.abs(T[band]) / np.abs(Ta[band]))
    return float(np.max(excess)), float(20.0 * np.log10(np.max(np.abs(Tl))))


def design(model: Any, options: TuningOptions | None = None, *, epsilon_rad: float | None = None) -> ControllerSettings:
    """Controller settings from an :class:`~commission.ident.hybrid.Identification` (or
    :class:`TwoMassParameters` and ``epsilon_rad``), by the rule of the module docstring.

    A current-loop lag the identification kept is designed for when
    ``options.current_loop_bandwidth_hz`` is not set (a value entered there wins).

    :raises TuningError: the model is not physical, or no gain meets the margins.
    """
    opt = options or TuningOptions()
    mdl = _as_model(model, epsilon_rad, opt)
    p = mdl.params
    _check_params(p)
    md = modes(p)
    first_notes: list[str] = []
    identified_cl = (getattr(model, "current_loop", None) or {}).get("bandwidth_hz")
    if opt.current_loop_bandwidth_hz is None and identified_cl:
        opt = opt.model_copy(update={"current_loop_bandwidth_hz": float(identified_cl)})
        first_notes.append(f"current-loop bandwidth {float(identified_cl):.0f} Hz from the identification "
                           "(tuning.current_loop_bandwidth_hz not set)")
    loop = _loop_plants(p, mdl.backlash, opt)
    notch_options: list[tuple[Notch, ...]] = []
    if opt.notch in ("auto", "off"):
        notch_options.append(())
    if opt.notch in ("auto", "on"):
        notch_options.append((_notch_for(p, opt),))
    candidates: list[dict[str, Any]] = []
    best: dict[tuple[Notch, ...], tuple[float, float, float]] = {}
    for notches in notch_options:
        for ratio in opt.torque_filter_ratios:
            found = _search(loop, p, notches, ratio, opt)
            if found is None:
                candidates.append({"notch": bool(notches), "filter_ratio": ratio, "kv_hz": None, "bandwidth_hz": None})
                continue
            kv, bw = found
            candidates.append({"notch": bool(notches), "filter_ratio": ratio, "kv_hz": kv, "bandwidth_hz": bw})
            if notches not in best or kv > best[notches][0]:
                best[notches] = (kv, bw, ratio)
    if not best:
        pm_req, gm_req = opt.requirements()
        raise TuningError(f"no velocity-loop gain meets PM ≥ {pm_req:g}° and GM ≥ {gm_req:g} dB on the identified "
                          f"model (resonance {md.f_resonance_hz:.1f} Hz, J_l/J_m {p.J_l / p.J_m:.2f})")
    notes: list[str] = first_notes
    chosen: tuple[Notch, ...] = ()
    if opt.notch == "on" or () not in best:
        chosen = next(k for k in best if k)
    elif opt.notch == "auto":
        with_notch = [k for k in best if k]
        if with_notch:
            k_n = with_notch[0]
            pk_nn, lp_nn = _peaks(loop, p, (), best[()], md.f_resonance_hz, opt)
            pk_n, lp_n = _peaks(loop, p, k_n, best[k_n], md.f_resonance_hz, opt)
            shows = pk_nn > opt.notch_peak_db and pk_n < pk_nn
            faster = best[k_n][0] > (1.0 + opt.notch_min_gain) * best[()][0] and lp_n <= lp_nn + 0.5
            if shows or faster:
                chosen = k_n
                why = (f"the resonance shows as a {pk_nn:.1f} dB peak in the velocity loop without it ({pk_n:.1f} dB with)"
                       if shows else f"velocity-loop gain {best[()][0]:.1f} → {best[k_n][0]:.1f} Hz")
                notes.append(f"notch at {k_n[0].frequency_hz:.1f} Hz: {why}")
            else:
                notes.append(f"no notch: the resonance ({md.f_resonance_hz:.1f} Hz) lies inside the velocity loop, "
                             f"which damps it (peak {pk_nn:.1f} dB near it; a notch would give "
                             f"K_v {best[k_n][0]:.1f} instead of {best[()][0]:.1f} Hz and a load-side peak "
                             f"{lp_n:.1f} instead of {lp_nn:.1f} dB)")
    kv, _, ratio = best[chosen]
    kp, Ti, tf_s = _gains(kv, p.J_m + p.J_l, p.J_m, ratio, opt)
    m_grid, mg_grid, bw = _evaluate(loop, kp, Ti, tf_s, chosen)
    wa = 2.0 * math.pi * md.f_antiresonance_hz
    kpos = min(2.0 * math.pi * bw / opt.ratio("position"), opt.ratio("antiresonance") * wa)
    if kpos < 2.0 * math.pi * bw / opt.ratio("position"):
        notes.append(f"position gain limited by the anti-resonance ({md.f_antiresonance_hz:.1f} Hz)")
    amount = 2.0 * mdl.epsilon_rad if (mdl.backlash and opt.backlash_compensation) else 0.0
    ratio_unexplained = _residual_ratio(model)
    # a residual the identification found to be white, stationary noise is no sign of a wrong ε
    noise_limited = bool(getattr(getattr(model, "fit", None), "noise_limited", False))
    if (amount > 0.0 and ratio_unexplained is not None and ratio_unexplained > opt.backlash_max_residual_ratio
            and noise_limited):
        notes.append(f"backlash compensation kept although the identified model leaves {100 * ratio_unexplained:.2f} % "
                     f"of the torque unexplained (> {100 * opt.backlash_max_residual_ratio:g} %): the identification "
                     "found that residual to be the record's white torque noise")
    elif amount > 0.0 and ratio_unexplained is not None and ratio_unexplained > opt.backlash_max_residual_ratio:
        amount = 0.0
        notes.append(f"backlash compensation off: the identified model leaves {100 * ratio_unexplained:.2f} % of the "
                     f"torque unexplained (> {100 * opt.backlash_max_residual_ratio:g} %), so its ε is not trusted; "
                     "a wrong amount can double the load error")
    elif amount > 0.0 and _approximate(model):
        amount = 0.0
        notes.append("backlash compensation off: the identification is approximate (see its notes), so its ε "
                     "is not trusted; a wrong amount can double the load error")
    tau_b = opt.backlash_time_constant_s if opt.backlash_time_constant_s is not None else 1.0 / kpos
    tau_r, filter_note = 0.0, ""
    if amount > 0.0 and opt.backlash_approach_filter:
        tau_r, filter_note = approach_time_constant(p, kpos, opt)
    pm_req, gm_req = opt.requirements()
    settings = ControllerSettings(
        sample_rate_hz=opt.sample_rate_hz, motor_inertia_kg_m2=p.J_m, load_inertia_kg_m2=p.J_l,
        velocity_gain=kp, velocity_integral_time_s=Ti, velocity_bandwidth_hz=bw, position_gain_per_s=kpos,
        torque_filter_time_constant_s=tf_s, notches=chosen, velocity_feedforward=opt.ratio("vff"),
        torque_feedforward=opt.ratio("tff"),
        backlash=BacklashCompensation(amount_rad=amount, time_constant_s=tau_b),
        margins=m_grid, margins_gap=mg_grid, required_phase_margin_deg=pm_req, required_gain_margin_db=gm_req,
        preset=opt.preset, current_loop_bandwidth_hz=opt.current_loop_bandwidth_hz,
        computation_delay_samples=opt.computation_delay_samples, epsilon_rad=mdl.epsilon_rad,
        reference_filter_time_constant_s=tau_r, resonance_hz=md.f_resonance_hz, antiresonance_hz=md.f_antiresonance_hz,
        candidates=tuple(candidates), notes=tuple(notes),
    )
    if settings.backlash.enabled:
        from .verify import TruePlant, choose_backlash_direction

        model_plant = TruePlant.from_model(model, mdl.epsilon_rad, opt.current_loop_bandwidth_hz)
        settings = choose_backlash_direction(settings, model_plant, opt)
        if settings.backlash.enabled and filter_note:
            settings = replace(settings, notes=settings.notes + (filter_note,))
    # the reported margins: python-control on the same loop
    m_ct = loop_margins(settings, p, gap=False)
    mg_ct = loop_margins(settings, p, gap=True) if mdl.backlash else None
    return replace(settings, margins=m_ct, margins_gap=mg_ct,
                   position_margins=loop_margins(settings, p, loop="position"))


def _residual_ratio(model: Any) -> float | None:
    """RMS residual / RMS torque of a hybrid identification (None when unknown)."""
    quality = getattr(model, "fit", None)
    return None if quality is None else float(quality.residual_ratio)


def _approximate(model: Any) -> bool:
    """Whether a hybrid identification said its result is approximate (False when unknown)."""
    return bool(getattr(getattr(model, "fit", None), "approximate", False))


def approach_time_constant(p: TwoMassParameters, kpos: float, opt: TuningOptions) -> tuple[float, str]:
    """Time constant of the position-reference filter that lets the backlash compensation work [s],
    and a note saying why.

    After a move the compensation holds the motor ε ahead of the load's target: exact only if
    the load rests on the driving flank. It does when the motor never decelerates faster than the
    load does by itself; at the end of a first-order approach the deceleration is v/τ_r, the
    load's own (viscous) v·B_l/J_l, so τ_r ≥ J_l/B_l keeps the flank in contact. A step of the
    reference (velocity jump) makes the motor hit the load across the gap, and the load leaves with
    up to 2·J_m/(J_m + J_l) < 2 times the motor's speed (elastic impact): with τ_r ≥ 2·J_l/B_l
    (``backlash_approach_factor``, default 2) the motor still travels further than the load
    coasts, and they meet again on the driving flank (measured over bench_tuning's plants:
    factor 1.5 leaves the load up to 20 mrad off after a step, 2 within 0.2 mrad). Without
    it a load without friction stops anywhere in the gap, and where depends on the move (the
    compensation then helps on some moves and doubles the error on others). Load-side Coulomb
    friction only helps (the bound is conservative then). Never shorter than 2/K_p (the
    position loop's own lag); at most ``backlash_approach_max_s``.
    """
    decay = p.J_l / p.B_l if p.B_l > 0 else math.inf
    want = opt.backlash_approach_factor * decay
    tau = min(max(want, 2.0 / kpos), opt.backlash_approach_max_s)
    why = (f"position reference filter {1e3 * tau:.1f} ms: {opt.backlash_approach_factor:g} × the load's own decay "
           f"time J_l/B_l = {1e3 * decay:.1f} ms, so moves end with the load on the driving flank and the backlash "
           f"compensation is exact (backlash_approach_filter: false for faster moves)")
    if want > opt.backlash_approach_max_s:
        why = (f"position reference filter {1e3 * tau:.1f} ms (capped by backlash_approach_max_s; the load's own decay "
               f"time J_l/B_l is {1e3 * decay:.1f} ms, so a load without friction may still leave the driving flank "
               f"at the end of a move)")
    return tau, why


# --------------------------------------------------------------------------------------------
# analysis of given settings on a given plant (python-control)
# --------------------------------------------------------------------------------------------
def _loop_tf(settings: ControllerSettings, p: TwoMassParameters, *, gap: bool, notches: bool = True) -> Any:
    import control as ct

    Ts = 1.0 / settings.sample_rate_hz
    if gap:
        num, den = np.array([1.0 / p.J_m]), np.array([1.0, p.B_m / p.J_m])
    else:
        num, den = p.velocity_tf()
    pn, pd = _plant_z(num, den, Ts, settings.current_loop_bandwidth_hz, settings.computation_delay_samples)
    cn, cd = _controller_z(settings.velocity_gain, settings.velocity_integral_time_s,
                           settings.torque_filter_time_constant_s, settings.notches if notches else (), Ts)
    return ct.tf(cn, cd, Ts) * ct.tf(pn, pd, Ts)


def loop_margins(settings: ControllerSettings, plant: TwoMassParameters, *, gap: bool = False,
                 notches: bool = True, loop: Literal["velocity", "position"] = "velocity") -> LoopMargins:
    """Margins of the velocity loop (or, ``loop="position"``, of the position loop around the
    closed velocity loop) of ``settings`` around ``plant`` (python-control).

    ``gap=True``: the motor alone (gears apart). The position loop is exact in discrete time:
    the drive's velocity is the backward difference of the position it measures, so
    x̂_m = Ts·z/(z − 1)·v̂_m and L_pos = K_p·Ts·z/(z − 1)·T_v(z) with T_v the closed velocity loop.
    The loop is evaluated on a dense grid (``control.frd``) and ``control.stability_margins``
    finds every crossing; the phase margin is the smallest over all gain crossovers, the gain
    margin the smallest over the phase crossovers with |L| < 1; stability from the
    closed-loop poles (``control.feedback``).
    """
    import control as ct

    L = _loop_tf(settings, plant, gap=gap, notches=notches)
    if loop == "position":
        Ts = L.dt
        L = settings.position_gain_per_s * ct.tf([Ts, 0.0], [1.0, -1.0], Ts) * ct.feedback(L, 1)
    w = 2.0 * math.pi * np.geomspace(0.05, 0.4999 * settings.sample_rate_hz, 1500)
    resp = L(np.exp(1j * w * L.dt))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gm, pm, sm, wpc, wgc, _ = ct.stability_margins(ct.frd(resp, w), returnall=True)
    gm = np.atleast_1d(gm)
    pm = np.atleast_1d(pm)
    wpc = np.atleast_1d(wpc)
    wgc = np.atleast_1d(wgc)
    upper = [(float(g), float(f)) for g, f in zip(gm, wpc) if np.isfinite(g) and g > 1.0]
    if upper:
        g, f = min(upper)
        gm_db, fpc = 20.0 * math.log10(g), f / (2 * math.pi)
    else:
        gm_db, fpc = math.inf, math.nan
    cl = ct.feedback(L, 1)
    stable = bool(np.all(np.abs(cl.poles()) < 1.0 - 1e-9))
    return LoopMargins(
        phase_margin_deg=float(np.min(np.abs(pm))) if pm.size else math.inf, gain_margin_db=float(gm_db),
        crossover_hz=float(np.max(wgc) / (2 * math.pi)) if wgc.size else math.nan,
        phase_crossover_hz=float(fpc),
        stability_margin=float(np.min(np.abs(resp + 1.0))), stable=stable)


def velocity_closed_loop(settings: ControllerSettings, plant: TwoMassParameters, f_hz: NDArray[np.float64], *,
                         notches: bool = True, output: Literal["motor", "load"] = "motor") -> NDArray[np.complex128]:
    """Closed-loop response v/v* at f_hz (contact, linear): motor velocity, or load velocity
    (motor closed loop × the shaft's load/motor velocity ratio (D s + K)/(J_l s² + (D + B_l) s + K))."""
    import control as ct

    L = _loop_tf(settings, plant, gap=False, notches=notches)
    T = ct.feedback(L, 1)
    z = np.exp(2j * np.pi * np.asarray(f_hz, dtype=float) * L.dt)
    out = np.asarray(T(z), dtype=complex)
    if output == "load":
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        p = plant
        out = out * (p.D * s + p.K) / (p.J_l * s * s + (p.D + p.B_l) * s + p.K)
    return out
