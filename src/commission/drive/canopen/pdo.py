"""PDOs for host-streamed cyclic synchronous torque: the bus budget, the cycle, the record.

Bus budget. A classic CAN data frame with an 11-bit identifier and ``n`` data
bytes takes at most ``8n + 47 + floor((34 + 8n - 1) / 4)`` bit times, including
the worst-case stuff bits and the 3-bit interframe space (Davis, Burns, Bril,
Lukkien 2007, eq. 1). One cycle is SYNC (1 byte: the SYNC counter) + the RPDO
(target torque) + one TPDO (position, applied torque, statusword); the cycle
period is the smallest multiple of the drive's tick whose bus time stays within
``max_load`` (80 %) of the period, with the heartbeats and the other traffic
heard on the bus. Through an slcan adapter the serial line carries every frame
again as ASCII (``t0801xx\\r`` is 8 bytes for a 1-byte frame, an 8-byte TPDO 22),
so a UART's byte rate bounds the cycle too. The usable excitation band is then
rate / 2 / 2.5 (Nyquist with the 2.5 margin the identifier needs).

Cycle. The drive keeps time: it produces SYNC k with its counter (0x1005 bit 30,
0x1006, 0x1019), applies the setpoint that reached it before SYNC k (else holds
the previous one), and answers with the TPDO latched at SYNC k: position, the
torque it applies from SYNC k on (0x6077, per mille of rated: the unit of the
setpoint, so the echo is exact) and the statusword. The host answers each TPDO
k at once with the setpoint for cycle k + 1, from the bus's notifier thread (no
thread switch in between). A late host costs a held setpoint, not a wrong
record: sample j of the record is cycle c0 + 1 + j on the drive's clock, with the
torque the drive says it applied; the setpoints are played in order, a late one
pausing the excitation rather than being skipped (see :class:`SyncedStream`). A cycle whose TPDO never arrived is marked
lost (the SYNC counter says which); a SYNC lost on the way leaves the TPDO heard
before it unattributable (it may be the lost SYNC's, its own lost too), so that
cycle is marked lost too.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from canopen import Network

SYNC_COB_ID = 0x080
#: data bytes of the frames of one cycle: SYNC (counter), RPDO 0x6071, TPDO 0x6064 + 0x6077 + 0x6041
STREAM_FRAMES: tuple[int, ...] = (1, 2, 8)
#: SYNC counter overflow value written to 0x1019 (CiA 301: 2..240)
SYNC_COUNTER_OVERFLOW = 240
#: bits per byte on a UART line (8N1)
LINE_BITS_PER_BYTE = 10
#: ``CycleRecord.sent`` of a cycle the host sent no setpoint for
NOT_SENT = np.iinfo(np.int64).min
#: a TPDO that waited longer than this many cycles is stale: the drive's next SYNC has passed
STALE_AFTER = 0.75
#: pauses may let the setpoints fall this far behind the drive's clock [s]; beyond, they skip ahead
#: (each paused cycle holds a torque the envelope check did not plan for)
MAX_LAG_S = 0.05


def slcan_line_bytes(n_bytes: int) -> int:
    """Bytes of one standard-id frame as an slcan line: ``t`` + 3 id + 1 dlc + 2 per byte + ``\\r``."""
    return 6 + 2 * n_bytes


def frame_bits(n_bytes: int, extended_id: bool = False) -> int:
    """Worst-case bit times of one CAN data frame (stuffing and interframe space included)."""
    if not 0 <= n_bytes <= 8:
        raise ValueError("a classic CAN frame carries 0..8 data bytes")
    if extended_id:
        return 8 * n_bytes + 67 + (54 + 8 * n_bytes - 1) // 4
    return 8 * n_bytes + 47 + (34 + 8 * n_bytes - 1) // 4


@dataclass(frozen=True)
class BusBudget:
    """The cycle the link allows for host-streamed CST, and why."""

    bitrate_bps: int
    frame_bytes: tuple[int, ...]
    """data bytes of the frames of one cycle (SYNC, RPDO, TPDO)."""
    bits_per_cycle: int
    cycle_s: float
    max_load: float
    background_bps: float
    """bus load outside the cycle (heartbeats, other nodes' traffic) [bit/s]."""
    line_bps: float | None = None
    """an slcan adapter's serial line [bit/s, 8N1], when it is a UART of known speed."""
    line_bytes_per_cycle: int = 0
    """bytes per cycle in the busier direction of that line (adapter to host)."""
    rate_cap_hz: float | None = None
    """the highest rate the user allowed (``--rate``)."""
    limited_by: str = "bus"
    """what set the rate: ``bus``, ``serial line``, ``--rate`` or ``drive tick``."""

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.cycle_s

    @property
    def frames_per_cycle(self) -> int:
        return len(self.frame_bytes)

    @property
    def load(self) -> float:
        """Fraction of the bus the cycle (and background) uses."""
        return (self.bits_per_cycle / self.cycle_s + self.background_bps) / self.bitrate_bps

    @property
    def line_load(self) -> float | None:
        """Fraction of the serial line (adapter to host) the cycle uses, if the line is known."""
        if not self.line_bps:
            return None
        return self.line_bytes_per_cycle * LINE_BITS_PER_BYTE / self.cycle_s / self.line_bps

    @property
    def usable_band_hz(self) -> float:
        """Highest excitation frequency the identifier can use: rate / 2 / 2.5."""
        return self.rate_hz / 2.0 / 2.5

    def describe(self) -> str:
        line = ""
        if self.line_bps:
            line = (f", slcan line {self.line_bytes_per_cycle} B per cycle = {self.line_load:.0%} of "
                    f"{self.line_bps / 1e3:g} kbit/s")
        return (
            f"{self.rate_hz:.0f} Hz cycle ({self.cycle_s * 1e6:.0f} us, {self.frames_per_cycle} frames per cycle, "
            f"{self.bits_per_cycle} bit worst case, bus load {self.load:.0%} of {self.bitrate_bps / 1e3:g} kbit/s "
            f"incl. {self.background_bps / 1e3:.1f} kbit/s of heartbeats and other traffic{line}; limited by {self.limited_by}) "
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
    line_bps: float | None = None,
    line_bytes_per_cycle: int = 0,
    max_rate_hz: float | None = None,
) -> BusBudget:
    """The fastest cycle that keeps the bus (and an slcan adapter's serial line, when its speed is
    known) within ``max_load`` and the rate within ``max_rate_hz``: a whole number of drive ticks
    that 0x60C2 (interpolation time period, value · 10^index s) can state exactly."""
    bits = sum(frame_bits(n) for n in frame_bytes)
    available = max_load * bitrate_bps - background_bps
    if available <= 0:
        raise ValueError("no bus capacity left for cyclic traffic")
    shortest = {"drive tick": tick_s, "bus": bits / available}
    if line_bps:
        shortest["serial line"] = line_bytes_per_cycle * LINE_BITS_PER_BYTE / (max_load * line_bps)
    if max_rate_hz is not None:
        if not max_rate_hz > 0:
            raise ValueError("the cycle rate must be positive")
        shortest["--rate"] = 1.0 / max_rate_hz
    limited_by = max(shortest, key=lambda k: shortest[k])
    ticks = max(1, math.ceil(shortest[limited_by] / tick_s - 1e-9))
    while ticks <= max_ticks and interpolation_period(ticks * tick_s) is None:
        ticks += 1
    if ticks > max_ticks:
        raise ValueError(f"the link cannot carry a cycle within {max_ticks} drive ticks")
    return BusBudget(bitrate_bps, tuple(frame_bytes), bits, ticks * tick_s, max_load, background_bps,
                     line_bps, line_bytes_per_cycle, max_rate_hz, limited_by)


def waveform_band_hz(samples: NDArray[np.float64], sample_rate_hz: float, energy: float = 0.999) -> float:
    """Frequency below which ``energy`` of the waveform's (mean-removed) spectral energy lies."""
    x = np.asarray(samples, dtype=np.float64)
    spectrum = np.abs(np.fft.rfft(x - x.mean())) ** 2
    total = spectrum.sum()
    if total <= 0:
        return 0.0
    k = int(np.searchsorted(np.cumsum(spectrum), energy * total))
    return float(k * sample_rate_hz / x.size)


@dataclass(frozen=True)
class StreamReport:
    """How a drive-clocked streamed run went, cycle by cycle on the drive's clock."""

    planned_rate_hz: float
    targets: int
    """setpoints of the excitation (each played once, in order)."""
    cycles: int
    """cycles of the record (samples): the targets plus the pauses."""
    lost_cycles: int
    """cycles whose TPDO did not arrive (or could not be attributed): interpolated and marked."""
    longest_gap_cycles: int
    """the longest run of consecutive lost cycles."""
    longest_pause_cycles: int
    """the longest run of answers the host repeated because it was behind (the excitation paused)."""
    catch_ups: int
    """late answers that advanced anyway, the pauses having used the ``MAX_LAG_S`` budget (each such
    setpoint acted a cycle late, or was overwritten by the next: a step of the chirp left out)."""
    sync_jitter_rms_s: float
    """RMS deviation of the SYNC arrival intervals at the host from the period (bus + host delays)."""
    sync_jitter_max_s: float
    latency_median_s: float
    """host response: the SYNC frame's time stamp to the setpoint sent (after the cycle's TPDO), median (the
    time stamp is the bus's on SocketCAN and the virtual bus; an slcan adapter's frames are stamped on
    arrival at the host)."""
    latency_p99_s: float
    latency_max_s: float
    budget: BusBudget

    @property
    def lost_fraction(self) -> float:
        return self.lost_cycles / self.cycles if self.cycles else 0.0

    @property
    def pause_cycles(self) -> int:
        """Cycles in which the drive held a setpoint because the host's next one came late."""
        return max(0, self.cycles - self.targets)

    @property
    def stretch(self) -> float:
        """How much longer the excitation took than planned (0: not at all)."""
        return self.pause_cycles / self.targets if self.targets else 0.0

    def describe(self) -> str:
        return (
            f"streamed CST on the drive's clock: {self.targets} setpoints in {self.cycles} cycles at "
            f"{self.planned_rate_hz:.0f} Hz ({self.pause_cycles} paused by late setpoints, {self.stretch:.1%}, "
            f"longest pause {self.longest_pause_cycles}; {self.catch_ups} late answers once the {MAX_LAG_S * 1e3:.0f} ms "
            f"pause budget was used, acting late or skipped); {self.lost_cycles} lost ({self.lost_fraction:.1%}, "
            f"longest gap {self.longest_gap_cycles}); SYNC arrival jitter rms {self.sync_jitter_rms_s * 1e6:.0f} us, "
            f"max {self.sync_jitter_max_s * 1e6:.0f} us; host response median {self.latency_median_s * 1e6:.0f} us, "
            f"p99 {self.latency_p99_s * 1e6:.0f} us, max {self.latency_max_s * 1e6:.0f} us"
        )


@dataclass
class CycleRecord:
    """What happened per cycle of a run (index 0: the cycle before the first sample)."""

    position: NDArray[np.int64]
    torque: NDArray[np.int64]
    """applied torque, per mille of rated (0x6077)."""
    status: NDArray[np.int64]
    received: NDArray[np.bool_]
    ambiguous: NDArray[np.bool_]
    sent: NDArray[np.int64]
    """the setpoint [per mille] the host sent for the cycle (``NOT_SENT`` where it sent none: see :meth:`meant`)."""
    sync_time: NDArray[np.float64]
    """time stamp of the cycle's SYNC (time.time clock); NaN if it did not arrive."""
    latency: NDArray[np.float64]
    """host response time to the SYNC of the cycle [s]; NaN where none was sent."""

    @classmethod
    def empty(cls, n: int) -> CycleRecord:
        return cls(np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, bool),
                   np.zeros(n, bool), np.full(n, NOT_SENT, np.int64), np.full(n, np.nan), np.full(n, np.nan))

    def meant(self) -> NDArray[np.int64]:
        """Per cycle, the setpoint [per mille] the drive applies when every RPDO arrived in time: the one
        sent for the cycle, else the last one sent before (a drive holds it), 0 before the first."""
        sent = self.sent
        has = sent != NOT_SENT
        last = np.maximum.accumulate(np.where(has, np.arange(sent.size), -1))
        return np.where(last >= 0, sent[np.maximum(last, 0)], 0)


class SyncedStream:
    """Host side of drive-clocked CST: the drive's SYNC (with counter) and TPDO pace the host.

    The host answers each cycle's TPDO (sent by the drive right after its SYNC) with the next
    setpoint. The setpoints advance one per answer, not with the clock: a host that stalls pauses
    the excitation (the drive holds the last setpoint) and goes on where it stopped, instead of
    jumping to where the clock says; such jumps, after every stall of a busy host, bring load impacts
    that cost the identifier accuracy (bench_streamed.py). After a stall the queued TPDOs are
    answered back to back, and each answer overwrites the one before in the drive before it acts:
    a TPDO older than ``STALE_AFTER`` cycles by its time stamp (the bus's, or its arrival at the host
    for slcan), or handled within a quarter cycle of the previous one while the drive reports that
    one not yet applied, is answered with the last setpoint again instead of the next. Pauses add
    up to at most ``MAX_LAG_S`` behind the drive's clock: a held torque is an impulse the envelope
    check did not plan, and a host stalled longer skips ahead instead.
    (A drive that receives two answers within one cycle for another reason still skips one
    setpoint: a step of one sample, as the chirp itself makes.)

    The PDO mapping is configured over SDO by the backend; the cyclic frames are packed here with
    precompiled structs (a Python PdoMap per frame would cost more than the cycle allows), and the
    callbacks run in the bus's notifier thread, which answers each TPDO before anything else runs.

    :param counter_overflow: the SYNC counter's overflow (0x1019), 0 if SYNCs carry no counter.
    """

    RPDO_STRUCT = struct.Struct("<h")
    TPDO_STRUCT = struct.Struct("<ihH")

    def __init__(self, network: Network, rpdo_cob: int, tpdo_cob: int, period_s: float,
                 counter_overflow: int) -> None:
        self.network = network
        self.rpdo_cob = rpdo_cob
        self.tpdo_cob = tpdo_cob
        self.period_s = period_s
        self.counter_overflow = counter_overflow
        self._send = network.send_message
        self._pack = self.RPDO_STRUCT.pack
        self._unpack = self.TPDO_STRUCT.unpack_from
        self._targets: NDArray[np.int16] = np.zeros(0, np.int16)
        self._armed = False
        self._c0: int | None = None
        self._cycle = -1
        self._last_raw: int | None = None
        self._tpdo_for: int | None = None
        self._unheard = 0  # SYNCs lost since the last one heard, as the TPDOs heard after it show
        self._next = 0
        self._last_sent: int | None = None
        self._handled_at = 0.0
        self._pause = 0
        self.longest_pause = 0
        #: the most the setpoints may run behind the drive's clock [cycles] before they skip ahead
        self.max_lag_cycles = max(1, int(round(MAX_LAG_S / period_s)))
        self.catch_ups = 0
        self.last_target_cycle: int | None = None
        """record index of the cycle in which the drive applied the last setpoint."""
        self.record = CycleRecord.empty(1)
        self.last_sync_monotonic: float | None = None
        self.last_tpdo_monotonic: float | None = None
        self.last_status = 0
        self.samples_done = 0
        """setpoints sent so far (for progress)."""
        self._done = threading.Event()
        network.subscribe(SYNC_COB_ID, self._on_sync)
        network.subscribe(tpdo_cob, self._on_tpdo)

    # -- notifier thread ----------------------------------------------------------------------------------
    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        previous = self._cycle
        if self.counter_overflow >= 2 and len(data) >= 1:
            raw = data[0]
            if self._last_raw is None:
                cycle = raw
            else:
                step = (raw - self._last_raw) % self.counter_overflow
                cycle = self._cycle + (step or self.counter_overflow)
            self._last_raw = raw
        else:
            cycle = self._cycle + 1
        self._cycle = cycle
        self._tpdo_for = None
        self._unheard = 0
        self.last_sync_monotonic = time.monotonic()
        if not self._armed:
            return
        if self._c0 is None:
            self._c0 = cycle
        i = cycle - self._c0
        rec = self.record
        j = previous - self._c0
        if cycle - previous > 1 and 0 <= j < rec.received.size and rec.received[j]:
            # a SYNC was lost: the one TPDO heard since the last SYNC heard may be the lost SYNC's (its own
            # cycle's TPDO lost too), which would put a later position and torque on this cycle
            rec.ambiguous[j] = True
        if i < rec.received.size:
            rec.sync_time[i] = timestamp
        if i + 1 >= rec.received.size:
            self._done.set()  # out of room: the run took far longer than planned
        last = self.last_target_cycle
        if last is not None and i >= last + 2:
            self._done.set()  # the last setpoint's cycle has passed

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        position, torque, status = self._unpack(bytes(data))
        self.last_status = status
        self.last_tpdo_monotonic = time.monotonic()
        if self._c0 is None:
            return
        i = self._cycle - self._c0  # record index: 0 is the cycle before the first sample
        rec = self.record
        if not 0 <= i < rec.received.size - 1:
            return
        if self._tpdo_for == self._cycle:  # two TPDOs for one SYNC: a SYNC was lost in between
            rec.ambiguous[i] = True
            # this TPDO is the lost SYNC's cycle's, so the answer acts a cycle later than the last one
            self._unheard += 1
        else:
            self._tpdo_for = self._cycle
            rec.position[i] = position
            rec.torque[i] = torque
            rec.status[i] = status
            rec.received[i] = True
        if not self._armed:
            return
        if self.last_target_cycle is not None:
            self._send(self.rpdo_cob, self._pack(0))  # the excitation is over
            return
        # the next setpoint, unless this TPDO is stale: it waited in the host (or reached it in a burst
        # while the drive still holds the last setpoint) so long that the drive's next SYNC has passed,
        # and a queued TPDO's answer will overwrite this one before it acts: then repeat the last one
        handled = time.perf_counter()
        n = self._targets.size
        k = self._next
        waited = time.time() - timestamp
        burst = handled - self._handled_at < 0.25 * self.period_s and torque != self._last_sent
        if self._last_sent is not None and (waited > STALE_AFTER * self.period_s or burst):
            k -= 1
            self._pause += 1
            self.longest_pause = max(self.longest_pause, self._pause)
            if i - k > self.max_lag_cycles:
                # paused too long in all: every held cycle adds the held torque's impulse, so the axis
                # would drift beyond what the envelope check predicted; catch up with the drive's clock,
                # or end the excitation when the setpoint held is the last one (it has acted already)
                if k + 1 >= n:
                    self._finish(i)
                    return
                k = min(n - 1, i - self.max_lag_cycles)
                self.catch_ups += 1
        else:
            self._pause = 0
            if k == n:
                if torque == self._last_sent or i - (n - 1) > self.max_lag_cycles:
                    self._finish(i)
                    return
                # the drive has not applied the last setpoint yet (an answer reached it after its SYNC, and it
                # held the one before): ending the record here would leave the chirp's last steps out of it
                # and unplayed; the last one again, within the lag the envelope allows
                k = n - 1
        self._handled_at = handled
        value = int(self._targets[k])
        self._send(self.rpdo_cob, self._pack(value))
        self._next = k + 1
        self._last_sent = value
        if i + 1 + self._unheard < rec.sent.size:
            rec.sent[i + 1 + self._unheard] = value
        sync_at = rec.sync_time[i]
        rec.latency[i] = time.time() - sync_at if np.isfinite(sync_at) else np.nan
        self.samples_done = k + 1

    def _finish(self, i: int) -> None:
        """The last setpoint acts in cycle ``i``: the record ends there, and the drive gets zero torque."""
        self.last_target_cycle = i
        self._done.set()
        self._send(self.rpdo_cob, self._pack(0))

    # -- main thread ------------------------------------------------------------------------------------------
    def arm(self, targets: NDArray[np.int16], max_cycles: int) -> None:
        """Stream ``targets`` (per mille of rated), in order, from the next SYNC on; the record holds
        at most ``max_cycles`` cycles."""
        self._armed = False
        self._targets = np.asarray(targets, dtype=np.int16)
        self.record = CycleRecord.empty(max(max_cycles, self._targets.size) + 2)
        self.samples_done = 0
        self._next = 0
        self._last_sent = None
        self._pause = 0
        self.longest_pause = 0
        self.catch_ups = 0
        self.last_target_cycle = None
        self.last_tpdo_monotonic = None
        self._done.clear()
        self._c0 = None
        self._armed = True

    def disarm(self) -> None:
        """Stop answering SYNCs (the drive then holds the last setpoint: send zero first)."""
        if self._armed:
            self._send(self.rpdo_cob, self._pack(0))
        self._armed = False

    def wait(self, timeout_s: float) -> bool:
        """Wait until every setpoint has been played, up to ``timeout_s``; True when done."""
        return self._done.wait(timeout_s)

    @property
    def targets(self) -> NDArray[np.int16]:
        return self._targets

    def samples(self) -> int:
        """Samples of the record so far: every cycle up to the last setpoint's (or the last TPDO heard)."""
        if self.last_target_cycle is not None:
            return self.last_target_cycle
        heard = np.flatnonzero(self.record.received & ~self.record.ambiguous)
        return max(0, int(heard[-1]) if heard.size else 0)

    def lost_mask(self, n: int) -> NDArray[np.bool_]:
        """Samples 0..n-1 whose cycle's TPDO is missing or unattributable."""
        rec = self.record
        return ~rec.received[1 : n + 1] | rec.ambiguous[1 : n + 1]

    def report(self, budget: BusBudget) -> StreamReport:
        rec = self.record
        n = self.samples()
        lost = self.lost_mask(n)
        runs = np.diff(np.flatnonzero(np.diff(np.concatenate(([0], lost.astype(np.int8), [0])))))[::2]
        t = rec.sync_time[: n + 1]
        dt = np.diff(t)
        dt = dt[np.isfinite(dt)]
        jitter = dt - budget.cycle_s if dt.size else np.zeros(1)
        lat = rec.latency[: n + 1]
        lat = lat[np.isfinite(lat)]
        if lat.size == 0:
            lat = np.zeros(1)
        return StreamReport(
            planned_rate_hz=budget.rate_hz, targets=int(min(self._targets.size, self.samples_done)), cycles=n,
            lost_cycles=int(lost.sum()), longest_gap_cycles=int(runs.max()) if runs.size else 0,
            longest_pause_cycles=self.longest_pause, catch_ups=self.catch_ups, sync_jitter_rms_s=float(np.sqrt(np.mean(jitter**2))),
            sync_jitter_max_s=float(np.max(np.abs(jitter))), latency_median_s=float(np.median(lat)),
            latency_p99_s=float(np.percentile(lat, 99)), latency_max_s=float(np.max(lat)), budget=budget,
        )

    def close(self) -> None:
        self._armed = False
        for cob, cb in ((SYNC_COB_ID, self._on_sync), (self.tpdo_cob, self._on_tpdo)):
            try:
                self.network.unsubscribe(cob, cb)
            except (KeyError, ValueError):
                pass


def record_signals(
    counts: NDArray[np.int64],
    applied_permille: NDArray[np.int64],
    intended_permille: NDArray[np.int64],
    received: NDArray[np.bool_],
    rate_hz: float,
    rated_torque_nm: float,
    increments_per_rev: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """The record's signals from what the drive reported per cycle.

    ``counts``, ``applied_permille`` and ``received`` have one entry per cycle, index 0 being the cycle
    before the first sample (it gives the first velocity); ``intended_permille`` has one per sample: the
    setpoint the drive applies there if its RPDOs arrived in time (:meth:`CycleRecord.meant`). Lost cycles
    get their position from a cubic spline through the received ones and that torque (the drive's own
    report of it is lost; wrong only where the setpoint's RPDO was lost or late too).

    :returns: torque [N·m], motor velocity [rad/s] (position difference over the cycle, as the
        identifier models a drive's velocity), motor position [rad], and the mask of lost samples.
    """
    n = int(np.asarray(intended_permille).size)
    ok = np.asarray(received[: n + 1], dtype=bool)
    counts_f = np.asarray(counts[: n + 1], dtype=np.float64)
    idx = np.arange(n + 1)
    if not ok.all():
        if ok.sum() >= 4:
            from scipy.interpolate import CubicSpline  # smooth positions across a lost cycle

            counts_f = np.where(ok, counts_f, CubicSpline(idx[ok], counts_f[ok])(idx))
        else:
            counts_f = np.interp(idx, idx[ok], counts_f[ok])
    position = counts_f * (2 * math.pi / increments_per_rev)
    lost = ~ok[1:]
    applied = np.asarray(applied_permille[1 : n + 1], dtype=np.float64)
    torque = np.where(lost, np.asarray(intended_permille, dtype=np.float64), applied) * (rated_torque_nm / 1000)
    return torque, np.diff(position) * rate_hz, position[1:], lost
