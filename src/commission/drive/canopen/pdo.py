"""PDOs for host-streamed cyclic synchronous torque: the bus budget, the mapping, the cycle loop.

Bus budget. A classic CAN data frame with an 11-bit identifier and ``n`` data
bytes takes at most ``8n + 47 + floor((34 + 8n - 1) / 4)`` bit times, including
the worst-case stuff bits and the 3-bit interframe space (Davis, Burns, Bril,
Lukkien 2007, eq. 1). One cycle is SYNC (0 bytes) + the RPDO + the TPDOs; the
cycle period is the smallest multiple of the drive's tick whose bus time stays
within ``max_load`` (80 %) of the period, heartbeats included. The usable
excitation band is then rate / 2 / 2.5 (Nyquist with the 2.5 margin the
identifier needs).

Cycle. The host sends RPDO(target k), then SYNC k, at k·T on its clock; the
drive applies target k at SYNC k and answers with the TPDOs latched at SYNC k.
The time at which each SYNC left the host is recorded as the sample time, so
the Recording carries the real, jittered timing; the jitter is measured.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from canopen import Network

SYNC_COB_ID = 0x080


def frame_bits(n_bytes: int, extended_id: bool = False) -> int:
    """Worst-case bit times of one CAN data frame (stuffing and interframe space included)."""
    if not 0 <= n_bytes <= 8:
        raise ValueError("a classic CAN frame carries 0..8 data bytes")
    if extended_id:
        return 8 * n_bytes + 67 + (54 + 8 * n_bytes - 1) // 4
    return 8 * n_bytes + 47 + (34 + 8 * n_bytes - 1) // 4


@dataclass(frozen=True)
class BusBudget:
    """The cycle the bus allows for host-streamed CST."""

    bitrate_bps: int
    frame_bytes: tuple[int, ...]
    """data bytes of the frames of one cycle (SYNC, RPDO, TPDOs)."""
    bits_per_cycle: int
    cycle_s: float
    max_load: float
    background_bps: float
    """bus load outside the cycle (heartbeats) [bit/s]."""

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.cycle_s

    @property
    def load(self) -> float:
        """Fraction of the bus the cycle (and background) uses."""
        return (self.bits_per_cycle / self.cycle_s + self.background_bps) / self.bitrate_bps

    @property
    def usable_band_hz(self) -> float:
        """Highest excitation frequency the identifier can use: rate / 2 / 2.5."""
        return self.rate_hz / 2.0 / 2.5

    def describe(self) -> str:
        return (
            f"{self.rate_hz:.0f} Hz cycle ({self.cycle_s * 1e6:.0f} us, {len(self.frame_bytes)} frames, "
            f"{self.bits_per_cycle} bit worst case, {self.load:.0%} of {self.bitrate_bps / 1e3:g} kbit/s) "
            f"-> usable band {self.usable_band_hz:.0f} Hz"
        )


def interpolation_period(period_s: float) -> tuple[int, int] | None:
    """0x60C2 (value UNSIGNED8, index INTEGER8) for ``period_s`` exactly (to 1 ns), or None."""
    for exponent in range(-6, 1):
        value = period_s / 10.0**exponent
        if value <= 255 and abs(value - round(value)) * 10.0**exponent < 1e-9 and round(value) >= 1:
            return int(round(value)), exponent
    return None


def plan_cycle(
    bitrate_bps: int,
    frame_bytes: tuple[int, ...],
    tick_s: float,
    *,
    max_load: float = 0.8,
    background_bps: float = 0.0,
    max_ticks: int = 1000,
) -> BusBudget:
    """The fastest cycle that keeps the bus within ``max_load``: a whole number of drive ticks
    that 0x60C2 (interpolation time period, value · 10^index s) can state exactly."""
    bits = sum(frame_bits(n) for n in frame_bytes)
    available = max_load * bitrate_bps - background_bps
    if available <= 0:
        raise ValueError("no bus capacity left for cyclic traffic")
    ticks = max(1, math.ceil(bits / available / tick_s - 1e-9))
    while ticks <= max_ticks and interpolation_period(ticks * tick_s) is None:
        ticks += 1
    if ticks > max_ticks:
        raise ValueError(f"the bus cannot carry a cycle of {bits} bit within {max_ticks} ticks")
    return BusBudget(bitrate_bps, tuple(frame_bytes), bits, ticks * tick_s, max_load, background_bps)


def waveform_band_hz(samples: NDArray[np.float64], sample_rate_hz: float, energy: float = 0.999) -> float:
    """Frequency below which ``energy`` of the waveform's (mean-removed) spectral energy lies."""
    x = np.asarray(samples, dtype=np.float64)
    spectrum = np.abs(np.fft.rfft(x - x.mean())) ** 2
    total = spectrum.sum()
    if total <= 0:
        return 0.0
    k = int(np.searchsorted(np.cumsum(spectrum), energy * total))
    return float(k * sample_rate_hz / x.size)


@dataclass
class StreamReport:
    """How a host-streamed run went: the rate asked for, achieved, and the timing jitter."""

    planned_rate_hz: float
    achieved_rate_hz: float
    jitter_rms_s: float
    jitter_max_s: float
    cycles: int
    late_cycles: int
    """cycles sent more than half a period after their slot (the schedule then shifts)."""
    budget: BusBudget

    def describe(self) -> str:
        return (
            f"streamed CST: planned {self.planned_rate_hz:.1f} Hz, achieved {self.achieved_rate_hz:.1f} Hz over "
            f"{self.cycles} cycles; SYNC interval jitter rms {self.jitter_rms_s * 1e6:.0f} us, "
            f"max {self.jitter_max_s * 1e6:.0f} us; {self.late_cycles} late cycles (schedule shifted)"
        )


@dataclass
class _Feedback:
    """TPDO values as they arrive (notifier thread appends, the cycle loop reads)."""

    position: list[int] = field(default_factory=list)
    velocity: list[int] = field(default_factory=list)
    torque: list[int] = field(default_factory=list)
    statusword: list[int] = field(default_factory=list)


class CyclicStreamer:
    """Host side of SYNC + RPDO (0x6071) + TPDO1 (0x6064, 0x606C) + TPDO2 (0x6077, 0x6041).

    The PDO mapping itself is configured over SDO by the backend (canopen's PdoMap);
    the cyclic frames are packed here with precompiled structs (a Python PdoMap
    per frame would cost more than the cycle allows).
    """

    RPDO_STRUCT = struct.Struct("<h")
    TPDO1_STRUCT = struct.Struct("<ii")
    TPDO2_STRUCT = struct.Struct("<hH")

    def __init__(self, network: Network, rpdo_cob: int, tpdo1_cob: int, tpdo2_cob: int) -> None:
        self.network = network
        self.rpdo_cob = rpdo_cob
        self.tpdo1_cob = tpdo1_cob
        self.tpdo2_cob = tpdo2_cob
        self.feedback = _Feedback()
        self.sent_targets: list[int] = []
        self.sync_times: list[float] = []
        self.late_cycles = 0
        self._lock = threading.Lock()
        network.subscribe(tpdo1_cob, self._on_tpdo1)
        network.subscribe(tpdo2_cob, self._on_tpdo2)

    def _on_tpdo1(self, can_id: int, data: bytearray, timestamp: float) -> None:
        pos, vel = self.TPDO1_STRUCT.unpack_from(bytes(data))
        self.feedback.position.append(pos)
        self.feedback.velocity.append(vel)

    def _on_tpdo2(self, can_id: int, data: bytearray, timestamp: float) -> None:
        torque, status = self.TPDO2_STRUCT.unpack_from(bytes(data))
        self.feedback.torque.append(torque)
        self.feedback.statusword.append(status)

    def reset(self) -> None:
        """Forget the last run (before a new one)."""
        self.feedback = _Feedback()
        self.sent_targets = []
        self.sync_times = []
        self.late_cycles = 0

    def close(self) -> None:
        for cob, cb in ((self.tpdo1_cob, self._on_tpdo1), (self.tpdo2_cob, self._on_tpdo2)):
            try:
                self.network.unsubscribe(cob, cb)
            except (KeyError, ValueError):
                pass

    def run(
        self,
        targets: NDArray[np.int16],
        period_s: float,
        check: Callable[[int], None],
        progress: Callable[[int, int], None] | None = None,
        progress_every: int = 200,
    ) -> None:
        """Send ``targets`` one per cycle; ``check(k)`` runs before each cycle and may raise to abort."""
        n = int(targets.size)
        send = self.network.send_message
        pack = self.RPDO_STRUCT.pack
        clock = time.perf_counter
        t0 = clock() + 0.005
        for k in range(n):
            slot = t0 + k * period_s
            remaining = slot - clock()
            if remaining > 0:
                time.sleep(remaining)  # sleep, never spin: a spinning thread holds the GIL the bus threads need
            elif -remaining > period_s / 2:
                t0 -= remaining  # late by more than half a cycle: shift the schedule rather than burst frames
                self.late_cycles += 1
            check(k)
            value = int(targets[k])
            send(self.rpdo_cob, pack(value))
            before = clock()
            send(SYNC_COB_ID, b"")
            after = clock()
            self.sent_targets.append(value)
            self.sync_times.append(0.5 * (before + after))  # the SYNC left during the send call
            if progress is not None and k % progress_every == 0:
                progress(k, n)

    def wait_feedback(self, cycles: int, timeout_s: float) -> None:
        """Wait until the TPDOs of ``cycles`` SYNCs have arrived (or the timeout)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            fb = self.feedback
            if len(fb.position) >= cycles and len(fb.statusword) >= cycles:
                return
            time.sleep(0.002)

    def report(self, budget: BusBudget) -> StreamReport:
        t = np.asarray(self.sync_times)
        n = t.size
        if n < 3:
            return StreamReport(budget.rate_hz, 0.0, 0.0, 0.0, n, 0, budget)
        dt = np.diff(t)
        jitter = dt - budget.cycle_s
        late = self.late_cycles
        return StreamReport(
            planned_rate_hz=budget.rate_hz,
            achieved_rate_hz=(n - 1) / (t[-1] - t[0]),
            jitter_rms_s=float(np.sqrt(np.mean(jitter**2))),
            jitter_max_s=float(np.max(np.abs(jitter))),
            cycles=n,
            late_cycles=late,
            budget=budget,
        )
