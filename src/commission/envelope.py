"""The safety envelope: the whole excitation is checked before anything moves.

Peak torque is read off the waveform. Speed and travel are predicted with a
rigid-body model of the whole axis, J·dv/dt = τ − B·v (exact ZOH discretisation),
from ``safety.planning_*``. The prediction times ``safety.margin`` must stay within
the limits. A lower planning inertia or damping gives larger predictions, so
underestimating them errs on the safe side; the drive's own torque and speed
limits (written before enabling) are the second layer during the run.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from .config import SafetyConfig
from .exceptions import SafetyLimitExceeded


@dataclass(frozen=True)
class EnvelopeCheck:
    """Predicted peaks of an excitation (before the margin) and the limits they were held to."""

    peak_torque_nm: float
    predicted_peak_speed_rad_s: float
    predicted_peak_travel_rad: float
    margin: float
    max_torque_nm: float
    max_speed_rad_s: float
    max_travel_rad: float


def rigid_body_response(
    torque_nm: NDArray[np.float64], sample_rate_hz: float, inertia_kg_m2: float, damping_nm_s_per_rad: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(velocity [rad/s], position [rad]) of J·dv/dt = τ − B·v under ZOH torque, from rest; shapes (N,)."""
    ts = 1.0 / sample_rate_hz
    x = damping_nm_s_per_rad * ts / inertia_kg_m2
    a = np.exp(-x)
    # expm1: with 1 − a the gain of a nearly undamped axis rounds to 0, and every speed to 0
    gain = -np.expm1(-x) / damping_nm_s_per_rad
    v = lfilter([0.0, gain], [1.0, -a], torque_nm)
    x = np.cumsum(v) * ts
    return v, x


def _checked(
    peak_torque_nm: float, v: NDArray[np.float64], x: NDArray[np.float64], safety: SafetyConfig, what: str
) -> EnvelopeCheck:
    """Hold predicted (or commanded) peaks to the limits; raises naming the limit."""
    check = EnvelopeCheck(
        peak_torque_nm=peak_torque_nm,
        predicted_peak_speed_rad_s=float(np.max(np.abs(v))),
        predicted_peak_travel_rad=float(np.max(np.abs(x))),
        margin=safety.margin,
        max_torque_nm=safety.max_torque_nm,
        max_speed_rad_s=safety.max_speed_rad_s,
        max_travel_rad=safety.max_travel_rad,
    )
    if peak_torque_nm > safety.max_torque_nm:
        raise SafetyLimitExceeded(
            f"{what} torque peaks at {peak_torque_nm:.4g} N·m, above the limit of {safety.max_torque_nm:.4g} N·m"
        )
    m = safety.margin
    if check.predicted_peak_speed_rad_s * m > safety.max_speed_rad_s:
        raise SafetyLimitExceeded(
            f"{what} would reach {check.predicted_peak_speed_rad_s:.4g} rad/s (×{m:g} margin), "
            f"above the speed limit of {safety.max_speed_rad_s:.4g} rad/s"
        )
    if check.predicted_peak_travel_rad * m > safety.max_travel_rad:
        raise SafetyLimitExceeded(
            f"{what} would travel {check.predicted_peak_travel_rad:.4g} rad (×{m:g} margin), "
            f"above the travel limit of {safety.max_travel_rad:.4g} rad"
        )
    return check


@dataclass(frozen=True)
class HeldLimits:
    """The limits as the drive will hold them: the configured ones in the drive's own units,
    rounded as the backend writes them (CiA 402 0x6072 in whole per mille of the rated torque,
    0x6080 in whole rpm, both rounded down)."""

    torque_nm: float
    speed_rad_s: float


def check_held_limits(check: EnvelopeCheck, held: HeldLimits, what: str = "excitation") -> None:
    """Hold the checked peaks to the limits as the drive holds them (a peak just under the
    configured torque limit can be above the limit the drive rounded it down to: it would trip
    mid-run). Raises SafetyLimitExceeded, naming both figures."""
    if check.peak_torque_nm > held.torque_nm:
        raise SafetyLimitExceeded(
            f"{what} torque peaks at {check.peak_torque_nm:.6g} N·m, above the torque limit as the drive will hold "
            f"it, {held.torque_nm:.6g} N·m (safety.max_torque_nm = {check.max_torque_nm:.6g} N·m rounded down to the "
            "drive's unit): raise safety.max_torque_nm or lower the excitation"
        )
    speed = check.predicted_peak_speed_rad_s * check.margin
    if speed > held.speed_rad_s:
        raise SafetyLimitExceeded(
            f"{what} would reach {check.predicted_peak_speed_rad_s:.6g} rad/s (×{check.margin:g} margin), above the "
            f"speed limit as the drive will hold it, {held.speed_rad_s:.6g} rad/s (safety.max_speed_rad_s = "
            f"{check.max_speed_rad_s:.6g} rad/s rounded down to the drive's unit)"
        )


def check_envelope(torque_nm: NDArray[np.float64], sample_rate_hz: float, safety: SafetyConfig) -> EnvelopeCheck:
    """Check a torque waveform against the envelope; raises SafetyLimitExceeded, naming the limit."""
    tau = np.asarray(torque_nm, dtype=float)
    if not np.all(np.isfinite(tau)):
        raise SafetyLimitExceeded("excitation contains non-finite samples")
    v, x = rigid_body_response(tau, sample_rate_hz, safety.planning_inertia_kg_m2, safety.planning_damping_nm_s_per_rad)
    return _checked(float(np.max(np.abs(tau))), v, x, safety, "excitation")


def check_velocity_envelope(velocity_rad_s: NDArray[np.float64], sample_rate_hz: float, safety: SafetyConfig) -> EnvelopeCheck:
    """Check a velocity reference: its peak and its integral (travel), times the margin (torque not predicted)."""
    v = np.asarray(velocity_rad_s, dtype=float)
    if not np.all(np.isfinite(v)):
        raise SafetyLimitExceeded("velocity reference contains non-finite samples")
    return _checked(float("nan"), v, np.cumsum(v) / sample_rate_hz, safety, "velocity reference")
