"""The simulated drive behind a pty: as an slcan (Lawicel) adapter, or as a Modbus RTU server.

The host opens the pty's path exactly as it would open ``/dev/ttyACM0`` or
``/dev/ttyUSB0``, with its own serial stack (python-can's ``slcan`` interface,
pymodbus's serial client); nothing of the host side is replaced.

* :class:`SlcanAdapter`: a serial-line CAN adapter. It parses the Lawicel
  commands python-can sends (``O``/``L`` open, ``C`` close, ``S0``–``S8`` /
  ``sxxyy`` bit rate, ``t``/``T``/``r``/``R`` transmit, ``V`` version, ``N``
  serial number, ``F`` status, ``Z`` time stamps) and bridges frames to an
  in-process python-can ``virtual`` bus on which the simulated drive sits as
  a CANopen node (:class:`~sim_drive.canopen_slave.CanopenSlave`). Frames from
  the bus reach the host only while the channel is open, as on an adapter.
* :class:`ModbusRtuServer`: the drive's serial service port. Holding
  registers only (FC 3, 6, 16, 23), the register map from the drive
  description (``drivers/sim/modbus.yaml``), CRC-16/MODBUS, exception
  responses 01/02/03/04/06; a communication watchdog stops the drive when the
  host falls silent while it is enabled (as a drive's Modbus timeout does).

Both take fault injections for tests (:class:`LinkFault`): a garbled, truncated
or CRC-corrupted answer, an adapter that stops answering, and the cable
pulled (the pty closed) when playback reaches a sample.

Line rate: a pty moves bytes as fast as the kernel copies them, whatever baud
rate the host sets. With ``line_rate_bps`` the device end paces both
directions to that many bit/s at 10 bits per byte (8N1), so times measured on
the pty model a real line: one direction at a time for Modbus (half duplex, as
RS-485), both at once for the slcan adapter (a UART). An slcan adapter whose
line cannot keep up with the bus drops frames, as a real one's transmit FIFO
overruns: a frame that waited longer than ``SlcanAdapter.FIFO_LINES`` lines take
on the line is dropped (counted in ``overruns``, reported by ``F``); a USB adapter
(no line rate) drops what waited longer than ``SlcanAdapter.FIFO_AGE_S`` for the host.
Without a line rate (default: a USB adapter), times are the pty's.
"""

from __future__ import annotations

import errno
import math
import os
import re
import select
import struct
import threading
import time
import tty
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from commission.drive.cia402 import Mode, State
from commission.drive.description import (
    INT_TYPES,
    DriveDescription,
    ModbusRegister,
    ModbusSpec,
    load_description,
)
from commission.drive.modbus import (
    ExceptionCode,
    crc16,
    decode_registers,
    encode_registers,
    string_to_registers,
)

from .canopen_slave import CanopenSlave
from .device import ErrorCode, SimulatedDevice

__all__ = ["LinkFault", "ModbusRtuServer", "PtyLink", "SlcanAdapter", "parse_fault"]

BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop


# -- faults ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LinkFault:
    """One injected link fault.

    ``kind``: ``garble`` (a character/byte changed), ``truncate`` (the answer cut short), ``crc``
    (Modbus: a wrong CRC; slcan: same as garble, a line has no checksum), ``mute`` (no more
    answers), ``hangup`` (the pty closed: cable pulled).
    ``at``: the answer counted from 1 (slcan: SDO response frames; Modbus: responses), or for
    ``hangup`` the playback sample; ``repeat``: this answer and every later one.
    """

    kind: str
    at: int = 1
    repeat: bool = False

    def hits(self, n: int) -> bool:
        return n == self.at or (self.repeat and n >= self.at)


_FAULT_RE = re.compile(r"^(garble|truncate|crc|mute|hangup)(?:@(\d+)(\+)?)?$")


def parse_fault(text: str) -> LinkFault:
    """``KIND[@N[+]]``: e.g. ``crc@40``, ``garble@100+``, ``mute``, ``hangup@4000``."""
    m = _FAULT_RE.match(text.strip())
    if not m:
        raise ValueError(f"bad fault '{text}': use garble|truncate|crc|mute|hangup[@N[+]]")
    kind, at, plus = m.groups()
    if kind == "mute" and at is None:
        return LinkFault("mute", 1, True)
    if at is None:
        raise ValueError(f"fault '{text}' needs @N")
    return LinkFault(kind, int(at), bool(plus))


# -- the pty --------------------------------------------------------------------------------------
class PtyLink:
    """The device end of a pty pair; the host opens :attr:`path`.

    The device keeps its own handle on the host end too, so a host that closes and reopens the
    port finds the line as it left it; :meth:`hang_up` closes both (the cable pulled): the host's
    next read or write fails.

    :param line_rate_bps: pace both directions to this bit rate (8N1), or None for pty speed.
    :param full_duplex: the two directions do not share the line (a UART; RS-485 does).
    """

    #: bytes may reach the host up to this early: pacing sleeps in steps of at least this long [s]
    PACE_SLACK_S = 0.001
    #: how long a write waits for room when the host stops reading [s]; then the bytes are dropped
    #: (counted in ``dropped_bytes``), as a serial line drops what nobody reads, instead of blocking
    #: the device's thread, and :meth:`hang_up` behind it, for ever once the pty's ~20 kB are full
    WRITE_STALL_S = 0.5

    def __init__(self, line_rate_bps: float | None = None, full_duplex: bool = False) -> None:
        self.master, self._slave = os.openpty()
        os.set_blocking(self.master, False)
        tty.setraw(self._slave)  # no echo, no CR/LF translation before the host configures it
        self.path = os.ttyname(self._slave)
        self.line_rate_bps = line_rate_bps
        self.bytes_in = 0
        self.bytes_out = 0
        self.dropped_bytes = 0
        self.closed = False
        # set before hang_up takes the lock: a writer that releases and at once retakes it (a device
        # sending in a loop) would otherwise starve the hang-up, a lock being no queue
        self._closing = False
        self._write_lock = threading.Lock()
        self.full_duplex = full_duplex
        self._free_at = {"in": 0.0, "out": 0.0}  # when each direction's line is next free

    def _direction(self, direction: str) -> str:
        return direction if self.full_duplex else "in"

    def backlog_s(self, direction: str = "out") -> float:
        """Seconds of bytes still queued for the line in ``direction`` (0 without a line rate)."""
        if not self.line_rate_bps:
            return 0.0
        return max(0.0, self._free_at[self._direction(direction)] - time.perf_counter())

    def _occupy(self, n_bytes: int, direction: str = "in") -> None:
        if not self.line_rate_bps:
            return
        key = self._direction(direction)
        now = time.perf_counter()
        start = max(now, self._free_at[key])
        self._free_at[key] = start + n_bytes * BITS_PER_BYTE / self.line_rate_bps
        delay = self._free_at[key] - now
        if delay > self.PACE_SLACK_S:
            time.sleep(delay)

    def read(self, timeout_s: float) -> bytes | None:
        """Bytes from the host (b'' if none within the timeout); None once hung up."""
        if self.closed:
            return None
        try:
            ready, _, _ = select.select([self.master], [], [], timeout_s)
            if not ready:
                return b""
            data = os.read(self.master, 4096)
        except BlockingIOError:
            return b""
        except (OSError, ValueError) as err:
            if self.closed or getattr(err, "errno", None) in (errno.EIO, errno.EBADF):
                return None
            raise
        self.bytes_in += len(data)
        self._occupy(len(data), "in")
        return data

    def write(self, data: bytes) -> bool:
        """Send to the host; False once hung up."""
        if self._closing:
            return False
        with self._write_lock:
            if self.closed:
                return False
            self._occupy(len(data), "out")
            view = memoryview(data)
            deadline = time.monotonic() + self.WRITE_STALL_S
            while view:
                try:
                    view = view[os.write(self.master, view):]
                    continue
                except BlockingIOError:
                    pass
                except OSError:
                    return False
                wait_s = deadline - time.monotonic()
                if wait_s <= 0.0 or self._closing:
                    self.dropped_bytes += len(view)
                    break
                select.select([], [self.master], [], min(wait_s, 0.05))
            self.bytes_out += len(data) - len(view)
            return True

    def hang_up(self) -> None:
        """Close the pty (both ends the device holds): what a pulled cable looks like. Idempotent."""
        self._closing = True
        with self._write_lock:
            if self.closed:
                return
            self.closed = True
            for fd in (self.master, self._slave):
                try:
                    os.close(fd)
                except OSError:
                    pass

    close = hang_up


def _warm_up(device: SimulatedDevice) -> None:
    from .plant import Plant

    plant = Plant(device.plant_parameters, device.sample_rate_hz)
    plant.run_torque(np.zeros(2))
    plant.run_velocity(np.zeros(2), device.velocity_kp, device.velocity_ki, device.max_torque_nm)


# -- slcan adapter --------------------------------------------------------------------------------
_SLCAN_BITRATES = {"S0": 10_000, "S1": 20_000, "S2": 50_000, "S3": 100_000, "S4": 125_000,
                   "S5": 250_000, "S6": 500_000, "S7": 750_000, "S8": 1_000_000, "S9": 83_300}
OK, BELL = b"\r", b"\a"


def slcan_line(msg: can.Message) -> bytes:
    """A received frame as the adapter reports it (no time stamp)."""
    if msg.is_extended_id:
        head = f"{'R' if msg.is_remote_frame else 'T'}{msg.arbitration_id:08X}{msg.dlc:d}"
    else:
        head = f"{'r' if msg.is_remote_frame else 't'}{msg.arbitration_id:03X}{msg.dlc:d}"
    data = "" if msg.is_remote_frame else bytes(msg.data).hex().upper()
    return (head + data).encode("ascii") + OK


def parse_slcan_frame(line: str) -> can.Message | None:
    """A transmit command (t/T/r/R) as a frame, or None if malformed."""
    kind = line[:1]
    id_len = 3 if kind in "tr" else 8
    try:
        can_id = int(line[1 : 1 + id_len], 16)
        dlc = int(line[1 + id_len])
        if not 0 <= dlc <= 8 or len(line[1 : 1 + id_len]) != id_len:
            return None
        if kind in "tT":
            data = bytes.fromhex(line[2 + id_len :])
            if len(data) != dlc:
                return None
        else:
            data = b""
    except (ValueError, IndexError):
        return None
    if can_id > (0x7FF if id_len == 3 else 0x1FFFFFFF):
        return None
    return can.Message(arbitration_id=can_id, is_extended_id=id_len == 8, is_remote_frame=kind in "rR",
                       dlc=dlc, data=data)


class SlcanAdapter:
    """A serial-line CAN adapter on a pty with the simulated drive as CANopen node ``node_id`` behind it.

    :param device: the simulated drive.
    :param pace: waveform playback speed as a multiple of real time; None: as fast as possible.
    :param faults: injected link faults (:func:`parse_fault`).
    :param line_rate_bps: model a UART at this bit rate (a USB CDC adapter has none: default None).
    :param node_options: more options of the CANopen node behind the adapter
        (:class:`~sim_drive.canopen_slave.CanopenSlave`: ``frame_loss``, ``bus_load``, ``identity``, …).
    """

    VERSION = "V1013"  # hardware 10, software 13, as python-can's get_version() parses it
    SERIAL = "NSIM1"
    #: frame lines the adapter's transmit FIFO holds while its UART is busy; more are dropped (overrun)
    FIFO_LINES = 32
    #: without a UART (USB): a frame the host has not taken within this long is dropped, as the
    #: adapter's FIFO would overflow rather than delay the bus without bound [s]
    FIFO_AGE_S = 0.5

    def __init__(
        self,
        device: SimulatedDevice | None = None,
        *,
        node_id: int = 1,
        pace: float | None = None,
        faults: tuple[LinkFault, ...] = (),
        line_rate_bps: float | None = None,
        node_options: dict[str, Any] | None = None,
    ) -> None:
        self.device = device if device is not None else SimulatedDevice()
        self.node_id = node_id
        self.faults = tuple(faults)
        self.link = PtyLink(line_rate_bps, full_duplex=True)
        self.path = self.link.path
        self.channel = f"slcan-sim-{os.getpid()}-{id(self):x}"
        self.node = CanopenSlave(self.device, node_id=node_id, channel=self.channel, interface="virtual", pace=pace,
                                 **(node_options or {}))
        #: frames dropped because the line to the host could not keep up (transmit FIFO overrun)
        self.overruns = 0
        self.bus: can.BusABC | None = None
        self.is_open = False
        self.bitrate: int | None = None
        self.sdo_responses = 0
        self.frames_to_host = 0
        self.frames_from_host = 0
        self.bad_lines = 0  # malformed commands from the host (answered with BELL)
        self.last_bad_line = ""
        self.muted = False
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    # -- life cycle --------------------------------------------------------------------------------
    def start(self) -> SlcanAdapter:
        self.node.start()
        self.bus = can.Bus(interface="virtual", channel=self.channel, receive_own_messages=False)
        for target, name in ((self._from_host, "rx"), (self._to_host, "tx")):
            t = threading.Thread(target=target, name=f"slcan-sim-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def close(self) -> None:
        """Stop the bridge, the node and the pty. Safe to call twice."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self._threads = []
        self.node.close()
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None
        self.link.hang_up()

    def __enter__(self) -> SlcanAdapter:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def hang_up(self) -> None:
        """The cable pulled: the pty closes; the node behind it keeps running (its watchdog acts)."""
        self.link.hang_up()

    # -- host -> adapter ------------------------------------------------------------------------------
    def _from_host(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            data = self.link.read(0.1)
            if data is None:
                return
            buffer += data
            while b"\r" in buffer:
                line, buffer = buffer.split(b"\r", 1)
                reply = self._command(line.decode("ascii", "replace"))
                if reply and not self.muted:
                    self.link.write(reply)
            if len(buffer) > 64:  # no terminator in sight: garbage
                buffer = b""

    def _command(self, line: str) -> bytes:
        if not line:
            return OK
        c = line[0]
        if c in "tTrR":
            if not self.is_open:
                return BELL
            msg = parse_slcan_frame(line)
            if msg is None or self.bus is None:
                self.bad_lines += 1
                self.last_bad_line = line[:30]
                return BELL
            self.frames_from_host += 1
            self.bus.send(msg)
            return b"z\r" if c in "tr" else b"Z\r"
        if c in "OL":
            if self.is_open:
                return BELL
            self.is_open = True
            return OK
        if c == "C":
            self.is_open = False
            return OK
        if c == "S" and line in _SLCAN_BITRATES:
            if self.is_open:
                return BELL
            self.bitrate = _SLCAN_BITRATES[line]
            return OK
        if c == "s" and len(line) == 5:
            return BELL if self.is_open else OK
        if c == "V":
            return self.VERSION.encode() + OK
        if c == "N":
            return self.SERIAL.encode() + OK
        if c == "F":  # status flags: bit 3 data overrun
            return b"F08\r" if self.overruns else b"F00\r"
        if c == "Z":
            return OK
        return BELL

    # -- bus -> host ------------------------------------------------------------------------------------
    def _to_host(self) -> None:
        assert self.bus is not None
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            self._check_hangup()
            if msg is None or not self.is_open or self.muted:
                continue
            line = slcan_line(msg)
            rate = self.link.line_rate_bps
            fifo_s = self.FIFO_LINES * len(line) * BITS_PER_BYTE / rate if rate else self.FIFO_AGE_S
            if time.time() - msg.timestamp > fifo_s:
                self.overruns += 1  # it waited longer than the FIFO holds: on an adapter it was overwritten
                continue
            if msg.arbitration_id == 0x580 + self.node_id and not msg.is_extended_id:
                self.sdo_responses += 1
                line = self._inject(line, self.sdo_responses)
                if line is None:
                    continue
            self.frames_to_host += 1
            if not self.link.write(line):
                return

    def _check_hangup(self) -> None:
        for f in self.faults:
            if f.kind == "hangup" and self.device.progress[0] >= f.at and self.device.trace_length >= f.at:
                self.link.hang_up()

    def _inject(self, line: bytes, n: int) -> bytes | None:
        for f in self.faults:
            if not f.hits(n):
                continue
            if f.kind in ("garble", "crc"):
                return line[:6] + b"G" + line[7:]  # a non-hex character in the data
            if f.kind == "truncate":
                return line[:-7] + OK
            if f.kind == "mute":
                self.muted = True
                return None
        return line


# -- Modbus RTU server ------------------------------------------------------------------------------
class ModbusException(Exception):
    """An exception response the server sends (code from :class:`ExceptionCode`)."""

    def __init__(self, code: ExceptionCode) -> None:
        super().__init__(code.name)
        self.code = code


def _request_length(buf: bytes) -> int | None:
    """Bytes of the RTU request at the start of ``buf`` (None: not known yet)."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (0x03, 0x04, 0x06, 0x05, 0x08):
        return 8
    if fc in (0x10, 0x0F):
        return 9 + buf[6] if len(buf) >= 7 else None
    if fc == 0x17:
        return 13 + buf[10] if len(buf) >= 11 else None
    return 4  # unknown function: address, function, CRC (answered with exception 01 if the CRC fits)


class ModbusRtuServer:
    """The simulated drive's serial service port in Modbus RTU, register map from the drive description.

    :param device: the simulated drive.
    :param drive: drive description with a ``modbus`` section (default ``sim``).
    :param pace: playback speed as a multiple of real time; None: as fast as possible.
    :param watchdog_s: the drive faults (0x8130) and brakes when no valid request arrives for this
        long while it is enabled (0: off).
    :param faults: injected link faults.
    :param line_rate_bps: model the line (default: the description's baud rate is *not* modelled).
    """

    CHUNK_SAMPLES = 200

    def __init__(
        self,
        device: SimulatedDevice | None = None,
        *,
        drive: str | DriveDescription = "sim",
        pace: float | None = None,
        watchdog_s: float = 1.0,
        faults: tuple[LinkFault, ...] = (),
        line_rate_bps: float | None = None,
    ) -> None:
        self.device = device if device is not None else SimulatedDevice()
        desc = drive if isinstance(drive, DriveDescription) else load_description(drive)
        if desc.modbus is None or desc.modbus.registers is None or desc.modbus.trace is None:
            raise ValueError(f"drive '{desc.name}' has no complete Modbus register map")
        self.spec: ModbusSpec = desc.modbus
        self.pace = pace
        self.watchdog_s = watchdog_s
        self.faults = tuple(faults)
        self.link = PtyLink(line_rate_bps)
        self.path = self.link.path
        self.responses = 0
        self.requests = 0
        self.crc_errors = 0
        self.muted = False
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._player: threading.Thread | None = None
        self._play_stop = threading.Event()
        self._last_request = time.monotonic()
        p = self.device.plant_parameters
        self._motor_inc = 2**p.encoder_bits_motor
        self._load_inc = 2**p.encoder_bits_load
        self._raw_wave = np.zeros(0, dtype=np.int64)
        self._wave_len = 0
        self._limits: list[float | None] = [self.device.max_torque_nm, self.device.max_speed_rad_s, None]
        self._travel: list[int | None] = [None, None]
        self._trace_select = (0, 0)
        self._trace_cache: dict[int, np.ndarray] = {}
        self._trace_cache_len = -1
        self._build_map()

    # -- the register map ---------------------------------------------------------------------------
    def _build_map(self) -> None:
        spec = self.spec
        regs = spec.registers
        assert regs is not None and spec.trace is not None and spec.waveform is not None
        dev = self.device
        #: address -> (register, getter, setter or None)
        self._values: dict[int, tuple[ModbusRegister, Any, Any]] = {}

        def add(reg: ModbusRegister | None, get: Any, put: Any = None) -> None:
            if reg is not None:
                self._values[reg.address] = (reg, get, put)

        add(regs.device_type, lambda: spec.device_type or 0)
        add(regs.controlword, lambda: dev._last_controlword, self._put_controlword)  # noqa: SLF001
        add(regs.statusword, lambda: dev.statusword)
        add(regs.mode, lambda: int(dev.mode), self._put_mode)
        add(regs.mode_display, lambda: int(dev.mode))
        add(regs.error_code, lambda: int(dev.error_code))
        add(regs.rated_torque_mnm, lambda: int(round(dev.rated_torque_nm * 1000)))
        add(regs.motor_increments, lambda: self._motor_inc)
        add(regs.load_increments, lambda: self._load_inc)
        add(regs.sample_period_ns, lambda: int(round(1e9 / dev.sample_rate_hz)))
        add(regs.capacity, lambda: dev.trace_capacity)
        add(regs.max_torque, lambda: int(dev.max_torque_nm / dev.rated_torque_nm * 1000), self._put_max_torque)
        add(regs.max_speed, lambda: int(dev.max_speed_rad_s * 60 / (2 * math.pi)), self._put_max_speed)
        add(regs.position_actual, lambda: self._counts(self._last("motor_position"), self._motor_inc))
        add(regs.travel_min, lambda: self._travel[0] or 0, lambda v: self._put_travel(0, v))
        add(regs.travel_max, lambda: self._travel[1] or 0, lambda v: self._put_travel(1, v))
        tr, wf = spec.trace, spec.waveform
        add(tr.start, lambda: int(dev.playing), self._put_start)
        add(tr.progress, lambda: dev.progress[0])
        add(tr.length, lambda: dev.trace_length)
        add(wf.length, lambda: self._wave_len, self._put_wave_length)
        self._stored: dict[str, float] = {}  # parameters the simulated loop does not use: kept, read back
        for name, param in spec.parameters.items():
            if hasattr(dev, name):
                add(param.register, lambda n=name: getattr(dev, n), lambda v, n=name: setattr(dev, n, float(v)))
            else:
                add(param.register, lambda n=name: self._stored.get(n, 0),
                    lambda v, n=name: self._stored.__setitem__(n, v))
        self._identity: dict[int, int] = {}
        texts = {"vendor": dev.vendor, "product": dev.product, "serial": dev.serial_number,
                 "firmware": "sim_drive"}
        for key, s in spec.identity.items():
            for i, word in enumerate(string_to_registers(texts[key], s.registers)):
                self._identity[s.address + i] = word
        #: address -> (first address of its value, word index)
        self._words: dict[int, tuple[int, int]] = {}
        for addr, (reg, _, _) in self._values.items():
            for i in range(reg.words):
                self._words[addr + i] = (addr, i)

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> ModbusRtuServer:
        _warm_up(self.device)
        for target, name in ((self._serve, "rtu"), (self._watch, "watchdog")):
            t = threading.Thread(target=target, name=f"modbus-sim-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def close(self) -> None:
        self._stop.set()
        self._play_stop.set()
        for t in self._threads:
            t.join(timeout=2)
        if self._player is not None:
            self._player.join(timeout=5)
        self.link.hang_up()

    def __enter__(self) -> ModbusRtuServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def hang_up(self) -> None:
        self.link.hang_up()

    # -- serving ------------------------------------------------------------------------------------
    def _serve(self) -> None:
        buf = b""
        last_byte = time.monotonic()
        while not self._stop.is_set():
            data = self.link.read(0.02)
            if data is None:
                return
            now = time.monotonic()
            if data:
                if buf and now - last_byte > 0.05:  # a silence ends any partial frame (RTU t3.5)
                    buf = b""
                buf += data
                last_byte = now
            elif buf and now - last_byte > 0.05:
                buf = b""
            while buf:
                n = _request_length(buf)
                if n is None or len(buf) < n:
                    break
                frame, buf = buf[:n], buf[n:]
                if crc16(frame[:-2]) != frame[-2:]:
                    self.crc_errors += 1
                    buf = b""  # lost framing: wait for the next silence
                    break
                self._handle(frame)

    def _handle(self, frame: bytes) -> None:
        unit, fc = frame[0], frame[1]
        if unit not in (0, self.spec.device_id):
            return
        self.requests += 1
        self._last_request = time.monotonic()
        try:
            with self._lock:
                pdu = self._execute(fc, frame[2:-2])
        except ModbusException as exc:
            pdu = bytes([fc | 0x80, int(exc.code)])
        if unit == 0:
            return  # broadcast: no answer
        self._respond(bytes([unit]) + pdu)

    def _respond(self, adu: bytes) -> None:
        self.responses += 1
        out = adu + crc16(adu)
        for f in self.faults:
            if not f.hits(self.responses):
                continue
            if f.kind == "crc":
                out = out[:-2] + bytes([out[-2] ^ 0xFF, out[-1]])
            elif f.kind == "garble":
                mid = len(out) // 2
                out = out[:mid] + bytes([out[mid] ^ 0x55]) + out[mid + 1 :]
            elif f.kind == "truncate":
                out = out[: max(1, len(out) // 2)]
            elif f.kind == "mute":
                self.muted = True
        if not self.muted:
            self.link.write(out)

    def _execute(self, fc: int, body: bytes) -> bytes:
        if fc in (0x03, 0x04):
            address, count = struct.unpack(">HH", body[:4])
            if not 1 <= count <= 125:
                raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE)
            words = self._read(address, count)
            return bytes([fc, 2 * count]) + struct.pack(f">{count}H", *words)
        if fc == 0x06:
            address, value = struct.unpack(">HH", body[:4])
            self._write(address, [value])
            return bytes([fc]) + body[:4]
        if fc == 0x10:
            address, count, nbytes = struct.unpack(">HHB", body[:5])
            if not 1 <= count <= 123 or nbytes != 2 * count:
                raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE)
            self._write(address, list(struct.unpack(f">{count}H", body[5 : 5 + nbytes])))
            return bytes([fc]) + body[:4]
        if fc == 0x17:
            r_addr, r_count, w_addr, w_count, nbytes = struct.unpack(">HHHHB", body[:9])
            if not (1 <= r_count <= 125 and 1 <= w_count <= 121 and nbytes == 2 * w_count):
                raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE)
            self._write(w_addr, list(struct.unpack(f">{w_count}H", body[9 : 9 + nbytes])))  # write first
            words = self._read(r_addr, r_count)
            return bytes([fc, 2 * r_count]) + struct.pack(f">{r_count}H", *words)
        raise ModbusException(ExceptionCode.ILLEGAL_FUNCTION)

    # -- registers ----------------------------------------------------------------------------------
    def _read(self, address: int, count: int) -> list[int]:
        tr = self.spec.trace
        assert tr is not None
        if address == tr.window and count <= tr.registers:
            return self._read_trace_window(count)
        out: list[int] = []
        cache: dict[int, list[int]] = {}
        for a in range(address, address + count):
            if a in self._identity:
                out.append(self._identity[a])
                continue
            if a not in self._words:
                raise ModbusException(ExceptionCode.ILLEGAL_DATA_ADDRESS)
            first, i = self._words[a]
            if first not in cache:
                reg, get, _ = self._values[first]
                cache[first] = encode_registers(get(), reg.type, self.spec.word_order)
            out.append(cache[first][i])
        return out

    def _write(self, address: int, words: list[int]) -> None:
        wf, tr = self.spec.waveform, self.spec.trace
        assert wf is not None and tr is not None
        if address == wf.select:
            return self._write_wave_block(words)
        if address == tr.select and len(words) == 3:
            channel = words[0]
            offset = decode_registers(words[1:3], "uint32", self.spec.word_order)
            if channel not in {c.channel for c in tr.channels.values()}:
                raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE)
            self._trace_select = (channel, int(offset))
            return None
        pos = 0
        while pos < len(words):
            a = address + pos
            if a not in self._values:  # writes must cover whole values, from their first register
                raise ModbusException(ExceptionCode.ILLEGAL_DATA_ADDRESS)
            reg, _, put = self._values[a]
            if put is None or pos + reg.words > len(words):
                raise ModbusException(ExceptionCode.ILLEGAL_DATA_ADDRESS)
            put(decode_registers(words[pos : pos + reg.words], reg.type, self.spec.word_order))
            pos += reg.words
        return None

    # -- the drive behind the registers ---------------------------------------------------------------
    def _put_controlword(self, value: float) -> None:
        self.device.write_controlword(int(value))

    def _put_mode(self, value: float) -> None:
        try:
            self.device.write_mode(Mode(int(value)))
        except (ValueError, RuntimeError) as err:
            raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE) from err

    def _put_max_torque(self, permille: float) -> None:
        self._limits[0] = permille / 1000 * self.device.rated_torque_nm
        self._apply_limits()

    def _put_max_speed(self, rpm: float) -> None:
        self._limits[1] = rpm * 2 * math.pi / 60
        self._apply_limits()

    def _put_travel(self, which: int, value: float) -> None:
        self._travel[which] = int(value)
        lo, hi = self._travel
        if lo is not None and hi is not None:
            here = self._counts(self._last("motor_position"), self._motor_inc)
            self._limits[2] = max(0, min(hi - here, here - lo)) * 2 * math.pi / self._motor_inc
            self._apply_limits()

    def _apply_limits(self) -> None:
        torque, speed, travel = self._limits
        self.device.set_limits(float(torque or 0), float(speed or 0), travel)

    def _put_wave_length(self, n: float) -> None:
        if self.device.playing:
            raise ModbusException(ExceptionCode.SERVER_DEVICE_BUSY)
        if not 0 <= n <= self.device.trace_capacity:
            raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE)
        self._wave_len = int(n)
        self._raw_wave = np.zeros(self._wave_len, dtype=np.int64)

    def _write_wave_block(self, words: list[int]) -> None:
        wf = self.spec.waveform
        assert wf is not None
        if self.device.playing:
            raise ModbusException(ExceptionCode.SERVER_DEVICE_BUSY)
        offset = int(decode_registers(words[:2], "uint32", self.spec.word_order))
        per = _words(wf.type)
        data = words[2:]
        if len(data) % per:
            raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE)
        n = len(data) // per
        if offset + n > self._wave_len:
            raise ModbusException(ExceptionCode.ILLEGAL_DATA_ADDRESS)
        values = [decode_registers(data[k * per : (k + 1) * per], wf.type, self.spec.word_order) for k in range(n)]
        self._raw_wave[offset : offset + n] = values

    def _put_start(self, value: float) -> None:
        tr = self.spec.trace
        assert tr is not None
        if int(value) != tr.start_value:
            self._play_stop.set()
            return
        dev = self.device
        if self._player is not None and self._player.is_alive():
            raise ModbusException(ExceptionCode.SERVER_DEVICE_BUSY)
        wf = self.spec.waveform
        assert wf is not None
        raw = self._raw_wave.astype(np.float64)
        if dev.mode is Mode.CYCLIC_SYNC_TORQUE:
            wave = raw * (wf.torque_scale * dev.rated_torque_nm)
        else:
            wave = raw * (wf.velocity_scale * 2 * math.pi / self._motor_inc)
        try:
            dev.load_waveform(wave)
            dev.start()
        except (ValueError, RuntimeError) as err:
            raise ModbusException(ExceptionCode.SERVER_DEVICE_FAILURE) from err
        self._play_stop.clear()
        self._player = threading.Thread(target=self._play, name="modbus-sim-player", daemon=True)
        self._player.start()

    def _play(self) -> None:
        dev = self.device
        t0 = time.perf_counter()
        while not self._play_stop.is_set():
            with self._lock:
                if not dev.playing:
                    break
                dev.advance(self.CHUNK_SAMPLES)
                played = dev.progress[0]
            for f in self.faults:
                if f.kind == "hangup" and played >= f.at:
                    self.link.hang_up()
            if self.pace:
                ahead = t0 + played / dev.sample_rate_hz / self.pace - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)
            else:
                time.sleep(0.0002)  # let the serving thread take the lock

    def _watch(self) -> None:
        """Communication watchdog: no valid request for ``watchdog_s`` while enabled -> fault 0x8130."""
        while not self._stop.wait(0.05):
            if not self.watchdog_s:
                continue
            with self._lock:
                silent = time.monotonic() - self._last_request
                if silent > self.watchdog_s and self.device.state is State.OPERATION_ENABLED:
                    self._play_stop.set()
                    self.device.trip(ErrorCode.COMMUNICATION)

    def _read_trace_window(self, count: int) -> list[int]:
        tr = self.spec.trace
        assert tr is not None
        channel, offset = self._trace_select
        spec = next((c for c in tr.channels.values() if c.channel == channel), None)
        if spec is None:
            raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE)
        length = self.device.trace_length
        if length != self._trace_cache_len:
            self._trace_cache, self._trace_cache_len = {}, length
        if channel not in self._trace_cache:
            self._trace_cache[channel] = self._trace_raw(channel)
        raw = self._trace_cache[channel]
        per = _words(spec.type)
        n = count // per
        if offset >= raw.size:
            raise ModbusException(ExceptionCode.ILLEGAL_DATA_ADDRESS)
        chunk = raw[offset : offset + n]
        words: list[int] = []
        for v in chunk.tolist():
            words.extend(encode_registers(v, spec.type, self.spec.word_order))
        return words + [0] * (count - len(words))

    def _trace_raw(self, channel: int) -> np.ndarray:
        """A trace channel in the map's integers (INT32 positions wrap modulo 2**32, as on a drive)."""
        tr = self.spec.trace
        assert tr is not None
        name = next(n for n, c in tr.channels.items() if c.channel == channel)
        spec = tr.channels[name]
        dev = self.device
        values = getattr(dev.trace(), name)
        inc = self._motor_inc if spec.encoder == "motor" else self._load_inc
        if spec.unit.value == "rated_torque":
            raw = np.round(values / (spec.scale * dev.rated_torque_nm))
        elif spec.unit.value == "increment":
            raw = np.round(values * inc / (2 * math.pi) / spec.scale)
        elif spec.unit.value == "increment_per_sample":
            raw = np.round(values / dev.sample_rate_hz * inc / (2 * math.pi) / spec.scale)
        else:
            raw = np.round(values * inc / (2 * math.pi) / spec.scale)
        code, size = INT_TYPES[spec.type]
        if code in "fd":
            return raw
        bits = 8 * size
        raw_i = raw.astype(np.int64) % (1 << bits)
        if code.islower():
            raw_i = np.where(raw_i >= 1 << (bits - 1), raw_i - (1 << bits), raw_i)
        return raw_i

    @staticmethod
    def _counts(value_si: float, increments: int) -> int:
        return int(round(value_si * increments / (2 * math.pi)))

    def _last(self, name: str) -> float:
        if self.device.trace_length:
            return float(getattr(self.device.trace(), name)[-1])
        return 0.0


def _words(type_name: str) -> int:
    return max(1, INT_TYPES[type_name][1] // 2)

