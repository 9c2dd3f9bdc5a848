"""The primary path's data: waveform samples to bus integers, trace channels back to SI.

Units (from the drive description): torque as a fraction of the rated torque
(``drivers/sim``: 1e-6, i.e. 0.64 uN·m on the simulated drive, where per-mille
would leave 10 bits of a 0.08 N·m chirp); positions in encoder increments
(INT32; unwrapped across the INT32 wrap, so multi-turn travel survives);
velocities in increments per trace sample (exact for a drive whose velocity is
the encoder difference per tick) or per second.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ...exceptions import DriveError
from ..cia402 import Mode
from ..description import INT_TYPES, ChannelUnit, TraceChannel, WaveformSpec


def _int_range(type_name: str) -> tuple[int, int]:
    code, size = INT_TYPES[type_name]
    if code in "fd":
        return -(2**53), 2**53
    bits = 8 * size
    return (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if code.islower() else (0, 2**bits - 1)


def waveform_to_bus(
    waveform: NDArray[np.float64], mode: Mode, spec: WaveformSpec, rated_torque_nm: float, motor_increments: float
) -> bytes:
    """Waveform [N·m in CST, rad/s in CSV] as the little-endian integers the drive plays."""
    if mode is Mode.CYCLIC_SYNC_TORQUE:
        unit = rated_torque_nm * spec.torque_scale
    elif mode is Mode.CYCLIC_SYNC_VELOCITY:
        unit = 2 * math.pi / motor_increments * spec.velocity_scale
    else:
        raise DriveError(f"the waveform player plays CST or CSV, not {mode.name}")
    raw = np.round(waveform / unit)
    lo, hi = _int_range(spec.type)
    if raw.min() < lo or raw.max() > hi:
        raise DriveError(f"waveform exceeds the range of {spec.type} in the drive's unit ({unit:.3g} per count)")
    code, _ = INT_TYPES[spec.type]
    return raw.astype(f"<{code}").tobytes()


def channel_from_bus(
    data: bytes,
    channel: TraceChannel,
    *,
    rated_torque_nm: float,
    increments: float,
    sample_rate_hz: float,
) -> NDArray[np.float64]:
    """One trace channel in SI units."""
    code, size = INT_TYPES[channel.type]
    if len(data) % size:
        raise DriveError(f"trace channel {channel.object}: {len(data)} bytes is not a whole number of {channel.type}")
    raw = np.frombuffer(data, dtype=f"<{code}")
    if channel.unit is ChannelUnit.INCREMENT and code in "iI" and raw.size:
        # unwrap modulo 2**32: a drive's position counter wraps, the axis does not
        steps = np.diff(raw.astype(np.int64))
        steps = (steps + 2**31) % 2**32 - 2**31
        values = np.concatenate(([int(raw[0])], int(raw[0]) + np.cumsum(steps))).astype(np.float64)
    else:
        values = raw.astype(np.float64)
    values = values * channel.scale
    if channel.unit is ChannelUnit.RATED_TORQUE:
        return values * rated_torque_nm
    per_inc = 2 * math.pi / increments
    if channel.unit is ChannelUnit.INCREMENT:
        return values * per_inc
    if channel.unit is ChannelUnit.INCREMENT_PER_SAMPLE:
        return values * per_inc * sample_rate_hz
    return values * per_inc
