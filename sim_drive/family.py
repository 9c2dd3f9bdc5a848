"""A fixed-seed random family of simulated plants and chirp records: what users have.

Each :class:`Member` is one axis and one experiment on it: the true two-mass
parameters (:class:`commission.ident.twomass.TwoMassParameters`), the backlash
half-width ε, the extra effects the identifier's model may or may not describe
(Coulomb friction, a current-loop lag, torque noise, encoder resolution), the
drive's sample rate, the record length, which signals the log holds, and the
excitation (the paper's chirp + slow bias, :func:`commission.excitation.chirp`).
:meth:`Member.simulate` runs it on ``sim_drive.plant`` and returns the
:class:`commission.recording.Recording` a user would hand to the identifier.

The ranges (module constants below) follow issue 22: J_l/J_m 0.1–10, resonance
20–400 Hz, resonance damping ratio 0.03–0.3, ε 0–3° (a share exactly 0),
Coulomb friction 0–15 % of the peak torque (a share none), current loop 300 Hz
to ideal, torque noise 0–0.5 % of the peak torque, 16–24-bit encoders, 2–16 kHz,
5–20 s, and three kinds of log: motor encoder only, with a load encoder, and
velocity only (no motor position). Scale-like quantities are drawn on log
scales. Member 0 is the paper's reference plant and experiment (METHOD.md), an
anchor every run can be checked against.

Draws. Member ``i`` of the family with seed ``s`` is the i-th point of a
scrambled Halton sequence (seeded with ``s``) mapped onto the ranges, plus a
noise seed from ``numpy.random.default_rng((s, i))``; a member therefore does
not depend on the family's size or on which other members are built, and the
low-discrepancy points cover the corners of the ranges better than independent
draws would with 200 members.

Amplitudes. On the reference plant the chirp amplitude A gives an acceleration
A/(J_m + J_l) of 114 rad/s², and the slow bias 3A moves the motor about
±17 rad/s, which the viscous friction sets (mechanical time constant
(J_m + J_l)/(B_m + B_l) = 49 ms, well below the bias period). Here A scales
with the total inertia (60–250 rad/s²), and the bias is 3A unless that would
drive the rigid axis, J·v̇ = τ − B·v, faster than the member's bias speed
(10–25 rad/s): lightly damped plants, whose viscous friction must be small for
a resonance damping ratio of 0.03, get a smaller bias instead of running away.
Then both amplitudes are scaled down, where needed, so that the linear plant's
motor speed under the whole excitation stays within ``SPEED_LIMIT_RAD_S`` (a
lightly damped resonance with a heavy load moves the motor more than the bias).
The bias frequency is the paper's 0.1 Hz, or 1/duration on records shorter
than 10 s, so that every record holds a whole bias period.

Damping. The viscous friction alone damps the resonance (at 20 Hz with a 50 ms
time constant, ζ = 0.08–0.5 depending on the inertia ratio), so a drawn damping ratio is reached by first
lengthening the mechanical time constant until the friction gives at most half
of it, then solving for the shaft damping D; the stiffness is corrected so
that the resonance of the damped plant is the drawn one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone
from enum import Enum
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.signal import lfilter, residue
from scipy.stats import qmc

from commission.config import ExcitationConfig
from commission.excitation import chirp
from commission.ident.twomass import REFERENCE_PLANT, Modes, TwoMassParameters, modes
from commission.recording import DriveInfo, Recording

# The family's one link to the simulator: repoint here when the physics moves.
from sim_drive.plant import Plant, PlantParameters

__all__ = [
    "DEFAULT_SEED",
    "DEFAULT_SIZE",
    "Member",
    "Sensors",
    "family",
    "member",
]

#: Seed of the baseline family (bench/bench_family.py's default).
DEFAULT_SEED = 22
#: Members in the default family (member 0 is the reference plant).
DEFAULT_SIZE = 200

RATIO_RANGE = (0.1, 10.0)
"""J_l / J_m [-], log scale."""
RESONANCE_RANGE_HZ = (20.0, 400.0)
"""Resonance (undamped natural frequency of the pole pair) [Hz], log scale."""
ZETA_RANGE = (0.03, 0.3)
"""Resonance damping ratio [-], log scale."""
EPSILON_RANGE_DEG = (0.02, 3.0)
"""Backlash half-width ε when there is backlash [deg], log scale."""
NO_BACKLASH_SHARE = 0.15
"""Share of members with ε = 0 exactly."""
COULOMB_RANGE = (0.005, 0.15)
"""Coulomb friction (motor + load) as a fraction of the peak torque reference, log scale."""
NO_COULOMB_SHARE = 0.35
"""Share of members without Coulomb friction."""
CURRENT_LOOP_RANGE_HZ = (300.0, 3000.0)
"""Bandwidth of the first-order current loop when it is not ideal [Hz], log scale."""
IDEAL_LOOP_SHARE = 0.3
"""Share of members with an ideal current loop."""
NOISE_RANGE = (2e-4, 5e-3)
"""Torque noise standard deviation as a fraction of the peak torque reference, log scale."""
NO_NOISE_SHARE = 0.15
"""Share of members without torque noise."""
ENCODER_BITS_RANGE = (16, 24)
"""Encoder resolution, motor and load independently [bits per revolution]."""
SAMPLE_RATES_HZ = (2000.0, 4000.0, 5000.0, 8000.0, 10000.0, 16000.0)
"""Drive cycle rates [Hz], equally likely."""
DURATION_RANGE_S = (5.0, 20.0)
"""Record length [s], uniform, rounded to 0.5 s."""
J_M_RANGE = (5e-5, 5e-3)
"""Motor inertia [kg·m²], log scale."""
DAMPING_SPLIT_RANGE = (0.15, 0.7)
"""B_l / (B_m + B_l) [-], uniform."""
TIME_CONSTANT_RANGE_S = (0.02, 0.5)
"""Mechanical time constant (J_m + J_l)/(B_m + B_l) before the damping correction [s], log scale."""
ACCELERATION_RANGE = (60.0, 250.0)
"""Chirp amplitude over total inertia, A/(J_m + J_l) [rad/s²], log scale."""
BIAS_SPEED_RANGE = (10.0, 25.0)
"""Peak rigid-body speed the slow bias may drive [rad/s], log scale."""
SPEED_LIMIT_RAD_S = 30.0
"""Largest motor speed the excitation may drive the linear plant (no backlash) to [rad/s];
amplitudes are scaled down to it (the reference experiment reaches 17)."""
CHIRP_START_HZ = 0.1
"""Chirp start frequency and the paper's bias frequency [Hz]."""
CHIRP_END_MIN_HZ = 400.0
"""The paper's chirp end; raised to 2.5× the resonance, capped at 0.4·fs [Hz]."""

# Halton coordinates, one per drawn quantity.
_DIMS = ("ratio", "f_r", "zeta", "eps", "coulomb", "coulomb_split", "loop", "noise", "bits_m",
         "bits_l", "rate", "duration", "sensors", "J_m", "split", "tau", "accel", "bias_speed")
_FIXED_START = datetime(2000, 1, 1, tzinfo=timezone.utc)


class Sensors(str, Enum):
    """Which signals the log holds (torque_ref and motor_velocity always)."""

    MOTOR = "motor"
    """Motor position and velocity."""
    LOAD_ENCODER = "load_encoder"
    """Motor position and velocity, load position and velocity."""
    VELOCITY_ONLY = "velocity_only"
    """Motor velocity only: no position in the log."""


@dataclass(frozen=True)
class Member:
    """One plant and one chirp experiment on it (SI units unless the name says otherwise)."""

    seed: int
    """Seed of the family the member belongs to."""
    index: int
    """Position in the family (0: the reference plant)."""
    two_mass: TwoMassParameters
    """True linear two-mass parameters."""
    epsilon_deg: float
    """True backlash half-width ε [deg]; 0 = no backlash."""
    coulomb_motor_nm: float
    """Motor-side Coulomb friction [N·m] (0: none)."""
    coulomb_load_nm: float
    """Load-side Coulomb friction [N·m] (0: none)."""
    current_loop_bandwidth_hz: float | None
    """First-order current-loop bandwidth [Hz]; None = ideal."""
    torque_noise_nm: float
    """Standard deviation of the white motor-torque noise [N·m]."""
    encoder_bits_motor: int
    encoder_bits_load: int
    sensors: Sensors
    excitation: ExcitationConfig
    """The experiment: chirp + slow bias, at the member's sample rate and duration."""
    noise_seed: int
    """Seed of the simulator's torque-noise generator."""

    @property
    def id(self) -> str:
        """Stable name, ``"<seed>:<index>"``."""
        return f"{self.seed}:{self.index:03d}"

    @property
    def sample_rate_hz(self) -> float:
        return self.excitation.sample_rate_hz

    @property
    def duration_s(self) -> float:
        return self.excitation.duration_s

    @property
    def epsilon_rad(self) -> float:
        return math.radians(self.epsilon_deg)

    @property
    def modes(self) -> Modes:
        """True resonance / anti-resonance of V_m/T_ref (backlash closed)."""
        return modes(self.two_mass)

    @property
    def peak_torque_nm(self) -> float:
        """Largest torque reference the excitation can reach, A + A_bias [N·m]."""
        return self.excitation.amplitude_nm + self.excitation.bias_amplitude_nm

    @property
    def velocity_quantum_rad_s(self) -> float:
        """One motor-encoder count per sample period [rad/s]: the velocity signal's step."""
        return 2.0 * math.pi / 2.0**self.encoder_bits_motor * self.sample_rate_hz

    def plant_parameters(self) -> PlantParameters:
        """The simulator's parameters for this member."""
        return PlantParameters(
            **self.two_mass.as_dict(), epsilon_deg=self.epsilon_deg,
            coulomb_motor_nm=self.coulomb_motor_nm, coulomb_load_nm=self.coulomb_load_nm,
            current_loop_bandwidth_hz=self.current_loop_bandwidth_hz,
            torque_noise_nm=self.torque_noise_nm, encoder_bits_motor=self.encoder_bits_motor,
            encoder_bits_load=self.encoder_bits_load, seed=self.noise_seed)

    def torque_ref(self) -> NDArray[np.float64]:
        """The excitation's torque reference, one value per sample [N·m], shape (N,)."""
        return chirp(self.excitation).samples

    def simulate(self) -> Recording:
        """Run the experiment on the simulator; the log holds the member's ``sensors``."""
        fs = self.sample_rate_hz
        r = Plant(self.plant_parameters(), fs).run_torque(self.torque_ref())
        signals: dict[str, Any] = {}
        if self.sensors is not Sensors.VELOCITY_ONLY:
            signals["motor_position"] = r.motor_position
        if self.sensors is Sensors.LOAD_ENCODER:
            signals["load_position"] = r.load_position
            signals["load_velocity"] = r.load_velocity
        return Recording.uniform(fs, r.torque_ref, r.motor_velocity, start_time=_FIXED_START,
                                 drive=DriveInfo(backend="sim"),
                                 metadata={"family_member": self.id}, **signals)

    def classes(self) -> dict[str, str]:
        """Labels for breakdowns: dimension name → class of this member."""
        m = self.modes
        z = m.zeta_resonance
        bw = self.current_loop_bandwidth_hz
        q = self.velocity_quantum_rad_s
        ratio = self.two_mass.J_l / self.two_mass.J_m
        return {
            "sample rate": f"{self.sample_rate_hz / 1000:g} kHz",
            "zeta_r": "< 0.06" if z < 0.06 else ("0.06–0.12" if z < 0.12 else "≥ 0.12"),
            "resonance": ("< 60 Hz" if m.f_resonance_hz < 60
                          else ("60–150 Hz" if m.f_resonance_hz < 150 else "≥ 150 Hz")),
            "J_l/J_m": "< 0.5" if ratio < 0.5 else ("0.5–2" if ratio < 2 else "≥ 2"),
            "backlash": ("none" if self.epsilon_deg == 0
                         else ("< 0.3°" if self.epsilon_deg < 0.3 else "≥ 0.3°")),
            "friction": "Coulomb" if self.coulomb_motor_nm + self.coulomb_load_nm > 0 else "none",
            "current loop": "ideal" if bw is None else ("< 1 kHz" if bw < 1000 else "≥ 1 kHz"),
            "torque noise": "none" if self.torque_noise_nm == 0 else (
                "< 0.1 %" if self.torque_noise_nm < 1e-3 * self.peak_torque_nm else "≥ 0.1 %"),
            "velocity quantum": ("< 0.01 rad/s" if q < 0.01
                                 else ("0.01–0.1 rad/s" if q < 0.1 else "≥ 0.1 rad/s")),
            "duration": "< 10 s" if self.duration_s < 10 else ("10–15 s" if self.duration_s < 15 else "≥ 15 s"),
            "sensors": self.sensors.value,
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (the true values a benchmark compares with)."""
        m = self.modes
        x = self.excitation
        return {
            "id": self.id, "seed": self.seed, "index": self.index,
            "two_mass": self.two_mass.as_dict(), "epsilon_deg": self.epsilon_deg,
            "modes": {"f_resonance_hz": m.f_resonance_hz, "zeta_resonance": m.zeta_resonance,
                      "f_antiresonance_hz": m.f_antiresonance_hz,
                      "zeta_antiresonance": m.zeta_antiresonance},
            "coulomb_motor_nm": self.coulomb_motor_nm, "coulomb_load_nm": self.coulomb_load_nm,
            "current_loop_bandwidth_hz": self.current_loop_bandwidth_hz,
            "torque_noise_nm": self.torque_noise_nm,
            "encoder_bits_motor": self.encoder_bits_motor, "encoder_bits_load": self.encoder_bits_load,
            "sensors": self.sensors.value, "sample_rate_hz": x.sample_rate_hz,
            "duration_s": x.duration_s, "chirp_hz": [x.f_start_hz, x.f_end_hz],
            "amplitude_nm": x.amplitude_nm, "bias_amplitude_nm": x.bias_amplitude_nm,
            "bias_frequency_hz": x.bias_frequency_hz, "noise_seed": self.noise_seed,
        }


def family(seed: int = DEFAULT_SEED, size: int = DEFAULT_SIZE) -> list[Member]:
    """Members 0 … size−1 of the family with this seed (member 0: the reference plant)."""
    if size < 1:
        raise ValueError(f"a family needs at least one member, got size={size}")
    points = qmc.Halton(len(_DIMS), scramble=True, rng=seed).random(size)
    return [_member(seed, i, points[i]) for i in range(size)]


def member(seed: int, index: int) -> Member:
    """Member ``index`` of the family with this seed (same as ``family(seed, n)[index]``)."""
    if index < 0:
        raise ValueError(f"member index must be ≥ 0, got {index}")
    engine = qmc.Halton(len(_DIMS), scramble=True, rng=seed)
    engine.fast_forward(index)
    return _member(seed, index, engine.random(1)[0])


def _member(seed: int, index: int, point: NDArray[np.float64]) -> Member:
    noise_seed = int(np.random.default_rng((seed, index)).integers(2**31))
    if index == 0:
        return _reference(seed, noise_seed)
    u = dict(zip(_DIMS, (float(v) for v in point)))
    J_m = _log(u["J_m"], J_M_RANGE)
    J_l = J_m * _log(u["ratio"], RATIO_RANGE)
    two_mass = _two_mass(J_m, J_l, _log(u["f_r"], RESONANCE_RANGE_HZ), _log(u["zeta"], ZETA_RANGE),
                         _log(u["tau"], TIME_CONSTANT_RANGE_S), _lin(u["split"], DAMPING_SPLIT_RANGE))
    fs = SAMPLE_RATES_HZ[min(int(u["rate"] * len(SAMPLE_RATES_HZ)), len(SAMPLE_RATES_HZ) - 1)]
    duration = round(2.0 * _lin(u["duration"], DURATION_RANGE_S)) / 2.0
    excitation = _excitation(two_mass, fs, duration, _log(u["accel"], ACCELERATION_RANGE),
                             _log(u["bias_speed"], BIAS_SPEED_RANGE))
    peak = excitation.amplitude_nm + excitation.bias_amplitude_nm
    coulomb = _optional(u["coulomb"], NO_COULOMB_SHARE, COULOMB_RANGE)
    coulomb_nm = 0.0 if coulomb is None else coulomb * peak
    noise = _optional(u["noise"], NO_NOISE_SHARE, NOISE_RANGE)
    sensors = list(Sensors)[min(int(u["sensors"] * 3), 2)]
    return Member(
        seed=seed, index=index, two_mass=two_mass,
        epsilon_deg=_optional(u["eps"], NO_BACKLASH_SHARE, EPSILON_RANGE_DEG) or 0.0,
        coulomb_motor_nm=coulomb_nm * u["coulomb_split"],
        coulomb_load_nm=coulomb_nm * (1.0 - u["coulomb_split"]),
        current_loop_bandwidth_hz=_optional(u["loop"], IDEAL_LOOP_SHARE, CURRENT_LOOP_RANGE_HZ),
        torque_noise_nm=0.0 if noise is None else noise * peak,
        encoder_bits_motor=_bits(u["bits_m"]), encoder_bits_load=_bits(u["bits_l"]),
        sensors=sensors, excitation=excitation, noise_seed=noise_seed)


def _reference(seed: int, noise_seed: int) -> Member:
    """The paper's plant and experiment (METHOD.md), 1e-4 N·m of torque noise, 24-bit encoders."""
    return Member(seed=seed, index=0, two_mass=REFERENCE_PLANT, epsilon_deg=0.40,
                  coulomb_motor_nm=0.0, coulomb_load_nm=0.0, current_loop_bandwidth_hz=None,
                  torque_noise_nm=1e-4, encoder_bits_motor=24, encoder_bits_load=24,
                  sensors=Sensors.MOTOR, excitation=ExcitationConfig(), noise_seed=noise_seed)


def _log(u: float, bounds: tuple[float, float]) -> float:
    lo, hi = bounds
    return float(lo * (hi / lo) ** u)


def _lin(u: float, bounds: tuple[float, float]) -> float:
    lo, hi = bounds
    return float(lo + (hi - lo) * u)


def _optional(u: float, none_share: float, bounds: tuple[float, float]) -> float | None:
    """None for u below none_share, else the rest of [0, 1) mapped log-uniformly onto bounds."""
    if u < none_share:
        return None
    return _log((u - none_share) / (1.0 - none_share), bounds)


def _bits(u: float) -> int:
    lo, hi = ENCODER_BITS_RANGE
    return min(lo + int(u * (hi - lo + 1)), hi)


def _two_mass(J_m: float, J_l: float, f_r_hz: float, zeta: float, tau_s: float,
              split: float) -> TwoMassParameters:
    """Parameters whose resonance is f_r_hz with damping ratio zeta (see the module docstring)."""
    w = 2.0 * math.pi * f_r_hz
    K = w * w * J_m * J_l / (J_m + J_l)
    B = (J_m + J_l) / tau_s

    def plant(B: float, K: float, D: float) -> TwoMassParameters:
        return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=(1 - split) * B, B_l=split * B, K=K, D=D)

    while modes(plant(B, K, 0.0)).zeta_resonance > 0.5 * zeta:
        B *= 0.8
    D = 0.0
    for _ in range(4):  # K and D interact only weakly: a few fixed-point passes converge
        D_hi = 4.0 * zeta * w / (1.0 / J_m + 1.0 / J_l)
        while modes(plant(B, K, D_hi)).zeta_resonance < zeta:
            D_hi *= 2.0
        D = brentq(lambda d: modes(plant(B, K, d)).zeta_resonance - zeta, 0.0, D_hi, xtol=1e-14 * D_hi)
        K *= (f_r_hz / modes(plant(B, K, D)).f_resonance_hz) ** 2
    return plant(B, K, D)


def _excitation(p: TwoMassParameters, fs: float, duration_s: float, accel: float,
                bias_speed: float) -> ExcitationConfig:
    """The paper's chirp + bias scaled to the member (see the module docstring)."""
    J = p.J_m + p.J_l
    A = accel * J
    f_r = modes(p).f_resonance_hz
    f_end = min(0.4 * fs, max(CHIRP_END_MIN_HZ, 2.5 * f_r))
    # one whole bias period at least, as in the paper's 10 s record
    f_bias = max(CHIRP_START_HZ, 1.0 / duration_s)
    B = p.B_m + p.B_l
    rigid = abs(complex(B, 2.0 * math.pi * f_bias * J))
    cfg = ExcitationConfig(amplitude_nm=A, f_start_hz=CHIRP_START_HZ, f_end_hz=f_end,
                           duration_s=duration_s, sample_rate_hz=fs,
                           bias_amplitude_nm=min(3.0 * A, bias_speed * rigid), bias_frequency_hz=f_bias)
    # the resonance (and the chirp's first seconds on a lightly damped axis) can move the motor
    # faster than the bias: bound the linear plant's peak motor speed
    peak = float(np.max(np.abs(_linear_motor_velocity(p, chirp(cfg).samples, fs))))
    if peak <= SPEED_LIMIT_RAD_S:
        return cfg
    scale = SPEED_LIMIT_RAD_S / peak
    return cfg.model_copy(update={"amplitude_nm": A * scale,
                                  "bias_amplitude_nm": cfg.bias_amplitude_nm * scale})


def _linear_motor_velocity(p: TwoMassParameters, torque_nm: NDArray[np.float64],
                           fs: float) -> NDArray[np.float64]:
    """Motor velocity [rad/s] of the linear plant under a zero-order-held torque, from rest:
    each pole of V_m/T's partial fractions r/(s − λ) discretised exactly (well conditioned
    where the polynomial form is not: the poles crowd around z = 1 at 16 kHz)."""
    residues, poles, _ = residue(*p.velocity_tf())
    v = np.zeros(torque_nm.shape, dtype=complex)
    for r, lam in zip(residues, poles):
        z = np.exp(lam / fs)
        v += lfilter([0.0, r * (z - 1.0) / lam], [1.0, -z], torque_nm.astype(complex))
    return v.real
