"""A log whose motor velocity is sampled at the sample instants (a simulator's state, an observer's
estimate), not the drive's difference of encoder counts: what an independent simulator or another
tool's export gives.

The plant runs at twice the rate, each torque held over both halves, with a 32-bit motor encoder; the
velocity at sample k is the central difference across it (within (ω·Ts/2)²/6 of the true velocity), plus
a float's last digits as noise.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from commission.plant import Plant, PlantParameters

__all__ = ["sampled_motor_velocity"]


def sampled_motor_velocity(params: PlantParameters, torque_ref: NDArray[np.float64], sample_rate_hz: float,
                           seed: int = 3) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(the motor velocity at t = k·Ts [rad/s], the motor position there [rad]), each shape (N,), under
    ``torque_ref`` [N·m], shape (N,), held over each sample."""
    fs = float(sample_rate_hz)
    r = Plant(params.model_copy(update={"encoder_bits_motor": 32}), 2 * fs).run_torque(np.repeat(torque_ref, 2))
    x = np.concatenate((r.motor_position, [2 * r.motor_position[-1] - r.motor_position[-2]]))
    k = np.arange(1, len(torque_ref))
    v = np.concatenate(([0.0], (x[2 * k + 1] - x[2 * k - 1]) * fs))
    return v + 1e-7 * np.random.default_rng(seed).standard_normal(v.size), x[0:2 * len(torque_ref):2]
