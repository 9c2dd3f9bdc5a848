"""Positions that wrap: a single-turn encoder or a counter exported as it stands jumps by one period
where the axis crossed it, and no model explains such a record (the fits then spend minutes on it).

A sample-to-sample step of a position is at most the largest velocity times the sample period (the
drive's velocity is that difference); a step far beyond it is a jump. When every jump is a whole
multiple of one period (within ``PERIOD_RTOL``) and the position stays within a period, it is unwrapped
and the note says so; other jumps are glitches, and the position is left out (the identification uses
the velocity, or the motor side alone), with a note that says where it jumped.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ..recording import Recording

__all__ = ["unwrap_positions"]

#: A step beyond this many times the largest motion a sample allows is a jump (a 2π wrap is told
#: from motion up to ~0.5 rad per sample, 4,000 rad/s at 8 kHz).
JUMP_FACTOR = 10.0
#: ... and beyond this [rad] in any case: an encoder's quantization step is never a jump.
JUMP_FLOOR_RAD = 0.05
#: The jumps are one period's multiples when each is within this share of a period of one.
PERIOD_RTOL = 0.01


def unwrap_positions(rec: Recording) -> tuple[Recording, list[str]]:
    """``rec`` with its wrapped positions unwrapped, and glitched ones left out; the notes say which.

    The bound on a sample's motion comes from the motor velocity (and the load velocity, when the
    record has one, for the load position), over the longest sample period of the record."""
    notes: list[str] = []
    dt = np.diff(rec.t)
    v_max = float(np.max(np.abs(rec.motor_velocity)))
    if rec.load_velocity is not None:
        v_max = max(v_max, float(np.max(np.abs(rec.load_velocity))))
    changes: dict[str, NDArray[np.float64] | None] = {}
    for name, v in (("motor_position", rec.motor_velocity), ("load_position", rec.load_velocity)):
        x = getattr(rec, name)
        if x is None:
            continue
        # the step from sample k to k+1 the velocity says (the drive's convention: v[k+1] = Δx/Ts)
        motion = v[1:] * dt if v is not None else np.zeros_like(dt)
        fixed, note = _unwrapped(x, motion, v_max * float(np.max(dt)), name, rec.t)
        if note:
            changes[name] = fixed
            notes.append(note)
    return (rec.replace(**changes) if changes else rec), notes


def _unwrapped(x: NDArray[np.float64], motion: NDArray[np.float64], bound_rad: float, name: str,
               t: NDArray[np.float64]) -> tuple[NDArray[np.float64] | None, str]:
    """(the position unwrapped, or None when its jumps are no period's multiples; the note), or (x, "")
    without jumps.

    :param x: the position [rad], shape (N,).
    :param motion: each step's motion by the velocity [rad], shape (N − 1,) (zeros when unknown).
    :param bound_rad: the largest motion a sample allows [rad].
    """
    step = np.diff(x)
    jumps = np.flatnonzero(np.abs(step) > max(JUMP_FACTOR * bound_rad, JUMP_FLOOR_RAD))
    if jumps.size == 0:
        return x, ""
    excess = step[jumps] - motion[jumps]
    unit = float(np.min(np.abs(excess)))  # a wrap jumps by one period at least
    turns = np.round(excess / unit)
    period = float(np.median(np.abs(excess) / np.abs(turns)))
    if abs(period - 2.0 * math.pi) <= PERIOD_RTOL * 2.0 * math.pi:
        period = 2.0 * math.pi  # a single-turn position in rad: its period exactly
    # a wrapped position stays within one period; a spike and back jumps by equal steps too, but not that
    within = float(np.ptp(x)) <= (1.0 + PERIOD_RTOL) * period + bound_rad
    if within and np.all(np.abs(excess - turns * period) <= PERIOD_RTOL * period + bound_rad):
        correction = np.zeros_like(x)
        correction[jumps + 1] = -turns * period
        return x + np.cumsum(correction), (
            f"{name} wraps {jumps.size} times at a period of {period:.6g} rad (a single-turn or counter "
            "position): unwrapped")
    k = int(jumps[0])
    return None, (f"{name} jumps by {step[k]:.3g} rad at sample {k + 1} (t = {t[k + 1]:.4g} s) where the "
                  f"velocity moves it by at most {bound_rad:.2g} rad, and its {jumps.size} jumps are no "
                  "wrap of one period (a glitch): left out of the identification")
