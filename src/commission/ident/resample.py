"""Host-streamed recordings carry the real, jittered sample times: bring them to a uniform grid.

The identifier's FRD and residual assume uniform sampling. A streamed run
(SYNC + PDO from the host) has its samples at the actual SYNC instants, which
jitter by tens of µs to ms on a busy host. Resampling onto the nominal grid
n / f_s (from the first sample time):

* torque: the drive held each target from its SYNC to the next; each uniform
  period gets the mean of that staircase over the period, so the impulse
  (∫τ dt) it delivered is kept exactly;
* positions: cubic spline through the measured positions at their real times;
* velocities: rebuilt with the drive's own rule, backward difference of the
  resampled position over the nominal period (motor velocity falls back to a
  cubic spline of the reported velocity when no position was recorded).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline

from ..exceptions import IdentificationError
from ..recording import Recording


@dataclass(frozen=True)
class Resampling:
    """What resampling did: jitter of the original sample times against the nominal grid."""

    jitter_rms_s: float
    """RMS deviation of the period from nominal [s]."""
    jitter_max_s: float
    """Largest deviation of a period from nominal [s]."""
    samples_in: int
    samples_out: int


def _held_mean(t: NDArray[np.float64], x: NDArray[np.float64], tu: NDArray[np.float64], fs: float) -> NDArray[np.float64]:
    """Mean over [tu[k], tu[k] + 1/fs) of x held from t[i] to t[i+1] (the impulse each uniform period received)."""
    cum = np.concatenate(([0.0], np.cumsum(x[:-1] * np.diff(t))))

    def integral(at: NDArray[np.float64]) -> NDArray[np.float64]:
        i = np.clip(np.searchsorted(t, at, side="right") - 1, 0, len(t) - 1)
        return cum[i] + x[i] * (at - t[i])

    return (integral(tu + 1.0 / fs) - integral(tu)) * fs


def _velocity_from_position(pos: NDArray[np.float64], v0: float, fs: float) -> NDArray[np.float64]:
    v = np.empty_like(pos)
    v[0] = v0
    v[1:] = np.diff(pos) * fs
    return v


def to_uniform(rec: Recording) -> tuple[Recording, Resampling]:
    """The recording on the uniform grid t0 + n / sample_rate_hz, and the jitter it had."""
    t = rec.t
    fs = rec.sample_rate_hz
    periods = np.diff(t)
    dev = periods - 1.0 / fs
    info_jitter = (float(np.sqrt(np.mean(dev**2))), float(np.max(np.abs(dev))))
    if np.max(periods) > 20.0 / fs:
        k = int(np.argmax(periods))
        raise IdentificationError(
            f"sample times have a gap of {periods[k] * 1e3:.1f} ms at sample {k + 1} "
            f"(nominal period {1e3 / fs:.3f} ms): too much lost to resample; rerun with less load on the host "
            "or use the drive's trace"
        )
    n = int(np.floor((t[-1] - t[0]) * fs + 1e-9)) + 1
    tu = t[0] + np.arange(n) / fs
    out: dict[str, NDArray[np.float64] | None] = {"torque_ref": _held_mean(t, rec.torque_ref, tu, fs)}
    for pos_name, vel_name in (("motor_position", "motor_velocity"), ("load_position", "load_velocity")):
        pos = getattr(rec, pos_name)
        vel = getattr(rec, vel_name)
        if pos is not None:
            p = CubicSpline(t, pos)(tu)
            out[pos_name] = p
            out[vel_name] = _velocity_from_position(p, float(vel[0]) if vel is not None else 0.0, fs)
        elif vel is not None:
            out[pos_name] = None
            out[vel_name] = CubicSpline(t, vel)(tu)
    resampled = rec.replace(t=tu - t[0], **out)
    return resampled, Resampling(info_jitter[0], info_jitter[1], len(rec), n)
