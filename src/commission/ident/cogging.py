"""A torque periodic in the motor's position: cogging and torque ripple.

A permanent-magnet motor's magnets cog against its stator's slots, and its current loop's ripple follows
the electrical angle: both repeat n times per mechanical revolution (n the slots' and poles' least common
multiple, six times the pole pairs, and their multiples), typically at 0.5–2 % of rated torque. The
two-mass model has no such term, so the Kalman fit covers it with a torque disturbance and flags the
record. The torque residual at an estimate holds it as a function of the motor's position, which the
encoder measures: a periodogram over whole harmonics per revolution finds it, and least squares fits it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["Cogging", "find_cogging"]

#: Highest harmonic per revolution searched (a 48-slot, 40-pole motor's cogging is the 240th).
MAX_HARMONIC = 600
#: Periods of a harmonic the record's travel must hold: a slower one is the motion's own time course.
MIN_CYCLES = 10.0
#: Periodogram power over its median that makes a harmonic significant (white residual: the largest
#: of 600 sits near 10).
SIGNIFICANCE = 50.0
#: Harmonics fitted at most.
MAX_TERMS = 8
#: Share of the residual's variance a series must explain to be taken out of the torque: 6–96 % where
#: simulated cogging of 0.3–3 % of the peak torque needed a disturbance, 1 % on a family member without any.
MIN_EXPLAINED = 0.03
#: Largest difference of a harmonic's complex amplitude between two halves of the samples (slow and fast,
#: either direction), relative to the larger: 0.05–0.27 on simulated cogging, 0.55–1.05 on model error.
CONSISTENCY = 0.5


@dataclass(frozen=True)
class Cogging:
    """τ_c(x_m) = Σ_i a_i·cos(n_i·x_m) + b_i·sin(n_i·x_m): the torque acting on the motor beside τ_ref [N·m]."""

    harmonics: tuple[int, ...]
    """n_i, periods per motor revolution."""
    cos_nm: tuple[float, ...]
    """a_i [N·m]."""
    sin_nm: tuple[float, ...]
    """b_i [N·m]."""
    explained: float
    """Share of the residual's variance the series explains [-]."""

    def torque(self, motor_position_rad: NDArray[np.float64]) -> NDArray[np.float64]:
        """τ_c at each position [N·m], shape of ``motor_position_rad``."""
        x = np.asarray(motor_position_rad, dtype=np.float64)
        return _basis(x, self.harmonics) @ np.ravel(np.column_stack((self.cos_nm, self.sin_nm)))

    def interval_torque(self, motor_position_rad: NDArray[np.float64]) -> NDArray[np.float64]:
        """τ_c over each sample interval [k·Ts, (k+1)·Ts), at the motor's mean position there (the last interval's
        repeated for the last sample) [N·m], shape (N,) of ``motor_position_rad`` [rad]: what is added to τ_ref."""
        x = np.asarray(motor_position_rad, dtype=np.float64)
        tau = self.torque(0.5 * (x[:-1] + x[1:]))
        return np.append(tau, tau[-1])

    @property
    def peak_nm(self) -> float:
        """Largest |τ_c| over one revolution [N·m]."""
        return float(np.max(np.abs(self.torque(np.linspace(0.0, 2.0 * math.pi, 8192, endpoint=False)))))

    def to_dict(self) -> dict[str, Any]:
        return {"harmonics_per_revolution": list(self.harmonics), "cos_nm": list(self.cos_nm),
                "sin_nm": list(self.sin_nm), "peak_nm": self.peak_nm, "explained": self.explained}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Cogging:
        """The inverse of :meth:`to_dict` (result.json's ``cogging``)."""
        return cls(tuple(int(n) for n in doc["harmonics_per_revolution"]), tuple(map(float, doc["cos_nm"])),
                   tuple(map(float, doc["sin_nm"])), float(doc["explained"]))


def _basis(x: NDArray[np.float64], harmonics: tuple[int, ...]) -> NDArray[np.float64]:
    """cos(n·x), sin(n·x) per harmonic, shape (len(x), 2·len(harmonics))."""
    return np.column_stack([f(n * x) for n in harmonics for f in (np.cos, np.sin)])


def _periodogram(r: NDArray[np.float64], x: NDArray[np.float64], lo: int, hi: int) -> NDArray[np.float64]:
    """|Σ_k r_k·exp(−i·n·x_k)|² for n = lo … hi (the positions need not be uniform)."""
    z = np.exp(-1j * x)
    zn = z ** lo
    out = np.empty(hi - lo + 1)
    for i in range(out.size):
        out[i] = abs(np.dot(r, zn)) ** 2
        zn *= z
    return out


def find_cogging(residual_nm: NDArray[np.float64], motor_position_rad: NDArray[np.float64],
                 lowpass: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
                 decimation: int = 1, harmonics: tuple[int, ...] | None = None) -> Cogging | None:
    """The harmonics of the motor's position that a torque residual holds beyond its noise, fitted (None: none).

    :param residual_nm: the model's torque residual, J_m·ẍ_m + … − τ_ref [N·m], shape (N,): τ_c where the
        model lacks it.
    :param motor_position_rad: the motor's position at the same samples [rad], shape (N,).
    :param lowpass: the filter the residual went through, applied to the series' columns too (a harmonic
        passed fast is attenuated as the residual's torque was).
    :param decimation: every how many samples the periodogram reads (the residual's band allows).
    :param harmonics: fit these, without a search or a check (what an earlier call found, again).

    Harmonics are taken one at a time, the strongest first, each fitted with those before it: a harmonic's
    own periodogram leaks into its neighbours where the travel is short. A harmonic is kept when the slower and
    the faster half of the samples, and the two directions, give it the same amplitude and phase: a cogging
    torque depends on the position alone, where model error that the motion maps onto a position's harmonic
    (a constant speed turns a time's frequency into one) depends on the speed.
    """
    x = np.asarray(motor_position_rad, dtype=np.float64)
    r = np.asarray(residual_nm, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        # (a fit's load simulation can diverge at an estimate far off: no torque to search then)
        r = r - r.mean()
        finite = math.isfinite(float(np.dot(r, r)))
    span = float(x.max() - x.min()) if x.size else 0.0
    lo = max(1, math.ceil(MIN_CYCLES * 2.0 * math.pi / span)) if span > 0.0 else MAX_HARMONIC + 1
    if lo > MAX_HARMONIC or not finite or not np.any(r):
        return None

    def columns(harmonics: list[int]) -> NDArray[np.float64]:
        A = _basis(x, tuple(harmonics))
        return A if lowpass is None else np.column_stack([lowpass(a) for a in A.T])

    def fitted(harmonics: list[int], rows: NDArray[np.bool_] | slice = slice(None)) -> NDArray[np.float64]:
        return np.linalg.lstsq(columns(harmonics)[rows], r[rows] - r[rows].mean(), rcond=None)[0]

    def series(harmonics: list[int]) -> Cogging:
        A = columns(harmonics)
        coef = np.linalg.lstsq(A, r, rcond=None)[0]
        return Cogging(tuple(harmonics), tuple(float(a) for a in coef[0::2]), tuple(float(b) for b in coef[1::2]),
                       float(1.0 - np.var(r - A @ coef) / np.var(r)))

    if harmonics:
        return series(list(harmonics))
    chosen: list[int] = []
    left = r
    for _ in range(MAX_TERMS):
        power = _periodogram(left[::decimation], x[::decimation], lo, MAX_HARMONIC)
        power[[n - lo for n in chosen]] = 0.0
        best = int(np.argmax(power))
        if not power[best] > SIGNIFICANCE * float(np.median(power)):
            break
        chosen.append(lo + best)
        left = r - columns(chosen) @ fitted(chosen)
    velocity = np.gradient(x)
    speed = np.abs(velocity)
    # (a direction the motor seldom takes holds too few samples to fit the series on)
    forward = velocity > 0.0
    halves = [speed < np.median(speed)] + ([forward] if 0.2 <= forward.mean() <= 0.8 else [])
    for half in halves:
        if not chosen:
            break
        a, b = fitted(chosen, half), fitted(chosen, ~half)
        za, zb = a[0::2] + 1j * a[1::2], b[0::2] + 1j * b[1::2]
        agree = np.abs(za - zb) < CONSISTENCY * np.maximum(np.abs(za), np.abs(zb))
        chosen = [n for n, ok in zip(chosen, agree) if ok]
    found = series(chosen) if chosen else None
    return found if found is not None and found.explained >= MIN_EXPLAINED else None
