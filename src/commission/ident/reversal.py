"""Independent check of the backlash at velocity reversals (paper §4.2, Villwock & Pacas).

With a load-side encoder, a slow sine velocity reference (paper: 0.5 Hz, 1.5 rad/s)
makes the gears separate at every reversal: the motor crosses the gap while the
load coasts, until the teeth meet again on the other flank. Then (paper eq. 32)

    2ε = | ∫_{t1}^{t2} (v_m − v_l) dt | = | twist(t2) − twist(t1) |

between separation t1 and re-contact t2. In contact the twist changes only elastically; in the
gap at the full relative speed, which keeps growing (the motor is driven, the load coasts)
until the impact ends it abruptly. So re-contact is the peak of the burst of twist rate around
each reversal, and separation the last sample before it where the rate is below
``rate_fraction`` of the peak.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..exceptions import IdentificationError
from ..recording import Recording


@dataclass(frozen=True)
class Reversal:
    """One direction reversal: gear separation, re-contact and the gap crossed."""

    t_separation_s: float
    t_recontact_s: float
    gap_rad: float  # |∫(v_m − v_l) dt| between separation and re-contact = 2ε [rad]


@dataclass(frozen=True)
class ReversalCheck:
    """Backlash from velocity reversals (paper eq. 32)."""

    epsilon_rad: float  # half the median gap over all reversals [rad]
    spread_rad: float  # (max − min) of the gaps / 4 [rad]: how much reversals disagree on ε
    reversals: tuple[Reversal, ...]

    @property
    def epsilon_deg(self) -> float:
        return float(np.degrees(self.epsilon_rad))


def _twist(rec: Recording) -> NDArray[np.float64]:
    if rec.motor_position is not None and rec.load_position is not None:
        return rec.motor_position - rec.load_position
    if rec.load_velocity is None:
        raise IdentificationError("the backlash check needs a load-side encoder (load position or velocity)")
    rate = rec.motor_velocity - rec.load_velocity
    return np.concatenate(([0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(rec.t))))


def _smooth(x: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    return np.convolve(x, np.ones(n) / n, mode="same") if n > 1 else x


def backlash_from_reversals(rec: Recording, *, rate_fraction: float = 0.05) -> ReversalCheck:
    """2ε from each reversal of a velocity-reversal experiment with a load encoder.

    :param rec: the experiment (motor velocity, load position or velocity), shape (N,) each.
    :param rate_fraction: edge threshold as a fraction of the peak twist rate of a reversal.
    """
    twist = _twist(rec)
    fs = rec.sample_rate_hz
    rate = np.gradient(twist, rec.t)
    v = _smooth(rec.motor_velocity, max(1, int(0.01 * fs)))
    level = 0.2 * np.max(np.abs(v))
    if level <= 0:
        raise IdentificationError("the motor did not move during the backlash check")
    # direction changes with hysteresis, then one window per reversal reaching halfway to its neighbours
    sign = np.where(v > level, 1, np.where(v < -level, -1, 0))
    idx = np.flatnonzero(sign)
    flips = np.flatnonzero(np.diff(sign[idx]) != 0)
    centres = (idx[flips] + idx[flips + 1]) // 2
    # the first and last windows are as wide as their neighbours, so that the take-up of
    # the gap at start-up (from wherever the teeth were) is not mistaken for a reversal
    half = int(np.min(np.diff(centres))) // 2 if centres.size > 1 else len(twist)
    edges = np.concatenate((
        [max(0, int(centres[0]) - half)] if centres.size else [0],
        (centres[1:] + centres[:-1]) // 2,
        [min(len(twist) - 1, int(centres[-1]) + half)] if centres.size else [len(twist) - 1],
    )).astype(int)
    reversals = []
    for a, b in zip(edges[:-1], edges[1:]):
        r = np.abs(rate[a : b + 1])
        peak = int(np.argmax(r))
        if r[peak] <= 0:
            continue
        quiet = r < rate_fraction * r[peak]
        before = np.flatnonzero(quiet[:peak])
        if before.size == 0 or not quiet[peak:].any():
            continue  # the window does not contain the whole crossing
        i1 = a + int(before[-1])
        i2 = a + peak  # the relative speed grows across the gap and collapses at the impact
        reversals.append(Reversal(float(rec.t[i1]), float(rec.t[i2]), float(abs(twist[i2] - twist[i1]))))
    if not reversals:
        raise IdentificationError("no complete direction reversal found in the backlash check")
    gaps = np.array([r.gap_rad for r in reversals])
    return ReversalCheck(float(np.median(gaps)) / 2, float(np.ptp(gaps)) / 4, tuple(reversals))
