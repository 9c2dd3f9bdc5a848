"""The Modbus RTU backend (MEMOBUS-compatible): a drive's serial service port, through registers.

pymodbus's synchronous serial client on pyserial does the framing; the drive
description's ``modbus`` map (``drivers/<name>/modbus.yaml``) says where every
value lives: identity strings, CiA 402-style controlword/statusword/mode and
error code, units, limits, the waveform player (download in blocks of
[offset, samples…] by FC 16) and the trace (channel + offset selected and the
window read in one FC 23 transaction). No register address appears in code.

Errors are one line in our tree: a Modbus exception response names its code
and meaning (:class:`ExceptionCode`), a missing or corrupt answer (after the
map's retries) is a :class:`DriveTimeout` that says how many answers failed
their CRC or came short, a port that vanishes is a :class:`DriveError`. Once
the link has failed, the stop commands are still *sent* (without waiting for
answers that cannot come) and the drive's own communication watchdog is the
last line of defence.

Reading is by RTU length (address, function, byte count), not by pymodbus's
default of polling ``in_waiting`` every max(4 characters, 1 ms) until it
settles: that costs ≥ 2 ms per transaction, 10× the pty's round trip.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from enum import IntEnum
from typing import Any

import numpy as np
import serial
from numpy.typing import NDArray
from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from ..exceptions import ConfigError, DriveError, DriveNotFound, DriveTimeout
from ..recording import DriveInfo, Recording
from .base import Drive, ProgressCallback
from .cia402 import Command, Mode
from .description import (
    INT_TYPES,
    ChannelUnit,
    DriveDescription,
    ModbusRegister,
    ModbusSpec,
    load_description,
    parameter_raw,
)

__all__ = [
    "ExceptionCode", "ModbusDrive", "ModbusTransfer", "crc16", "decode_registers", "encode_registers",
    "line_seconds", "string_to_registers",
]

# a library does not print: pymodbus logs every retry at ERROR, which would reach stderr through
# logging's last-resort handler and break the CLI's one-line errors (the host app may configure it)
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

#: seconds between progress polls during a run
POLL_S = 0.02
#: a run whose progress stays unchanged this long (beyond its duration) is a timeout
STALL_S = 2.0
BITS_PER_CHARACTER = {"N": 10, "E": 11, "O": 11}  # start + 8 data (+ parity) + 1 stop


class ExceptionCode(IntEnum):
    """Modbus exception codes (Modbus Application Protocol V1.1b3, §7)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    ACKNOWLEDGE = 0x05
    SERVER_DEVICE_BUSY = 0x06
    MEMORY_PARITY_ERROR = 0x08
    GATEWAY_PATH_UNAVAILABLE = 0x0A
    GATEWAY_TARGET_FAILED = 0x0B

    @property
    def meaning(self) -> str:
        return _EXCEPTION_MEANING[self]


_EXCEPTION_MEANING = {
    ExceptionCode.ILLEGAL_FUNCTION: "illegal function: the device does not support this request",
    ExceptionCode.ILLEGAL_DATA_ADDRESS: "illegal data address: no such register, or not writable",
    ExceptionCode.ILLEGAL_DATA_VALUE: "illegal data value: the device refused the value",
    ExceptionCode.SERVER_DEVICE_FAILURE: "server device failure: the device could not carry it out",
    ExceptionCode.ACKNOWLEDGE: "acknowledge: accepted, still processing",
    ExceptionCode.SERVER_DEVICE_BUSY: "server device busy: try again later",
    ExceptionCode.MEMORY_PARITY_ERROR: "memory parity error",
    ExceptionCode.GATEWAY_PATH_UNAVAILABLE: "gateway path unavailable",
    ExceptionCode.GATEWAY_TARGET_FAILED: "gateway target device failed to respond",
}


def exception_text(code: int) -> str:
    try:
        return ExceptionCode(code).meaning
    except ValueError:
        return "unknown exception code"


# -- the wire format -----------------------------------------------------------------------------
def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> bytes:
    """CRC-16/MODBUS of ``data``, as sent on the line (low byte first)."""
    crc = 0xFFFF
    for b in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ b) & 0xFF]
    return struct.pack("<H", crc)


def encode_registers(value: float, type_name: str, word_order: str = "big") -> list[int]:
    """A value of ``type_name`` as 16-bit registers (each big-endian on the wire)."""
    code, size = INT_TYPES[type_name]
    if code in "fd":
        raw = struct.pack(f">{code}", float(value))
    else:
        raw = struct.pack(f">{code}", int(value))
    if size == 1:  # 8-bit types still take a whole register
        raw = (b"\xff" if code == "b" and int(value) < 0 else b"\0") + raw
    words = list(struct.unpack(f">{len(raw) // 2}H", raw))
    return words if word_order == "big" else words[::-1]


def decode_registers(words: list[int], type_name: str, word_order: str = "big") -> float:
    """The inverse of :func:`encode_registers` (ints come back as int)."""
    code, size = INT_TYPES[type_name]
    ordered = list(words) if word_order == "big" else list(words)[::-1]
    raw = struct.pack(f">{len(ordered)}H", *(w & 0xFFFF for w in ordered))
    if size == 1:
        raw = raw[1:]
    value = struct.unpack(f">{code}", raw)[0]
    return value  # type: ignore[no-any-return]


def string_to_registers(text: str, registers: int) -> list[int]:
    """ASCII, two characters per register (high byte first), NUL-padded and cut to fit."""
    raw = text.encode("ascii", "replace")[: 2 * registers].ljust(2 * registers, b"\0")
    return list(struct.unpack(f">{registers}H", raw))


def registers_to_string(words: list[int]) -> str:
    return struct.pack(f">{len(words)}H", *words).split(b"\0", 1)[0].decode("ascii", "replace").strip()


def _words_array(words: list[int], type_name: str, word_order: str) -> NDArray[Any]:
    """Many values of one type from consecutive registers."""
    code, size = INT_TYPES[type_name]
    per = max(1, size // 2)
    arr = np.asarray(words, dtype=np.uint16)
    if per > 1 and word_order == "little":
        arr = arr.reshape(-1, per)[:, ::-1].reshape(-1)
    raw = arr.astype(">u2").tobytes()
    if size == 1:
        raw = raw[1::2]
    return np.frombuffer(raw, dtype=f">{code}")


def line_seconds(n_bytes: int, baudrate: float, parity: str = "N") -> float:
    """Time ``n_bytes`` take on a UART line (8 data bits, 1 stop bit, optional parity)."""
    return n_bytes * BITS_PER_CHARACTER.get(parity, 10) / baudrate


@dataclass
class ModbusTransfer:
    """One waveform download or trace upload: payload, line bytes (both directions), wall time."""

    what: str
    direction: str  # "download" | "upload"
    n_bytes: int
    requests: int
    line_bytes: int
    seconds: float

    def modelled_seconds(self, baudrate: float, parity: str = "N") -> float:
        """The same transfer on a real line: every byte at ``baudrate``, plus the RTU silence
        (3.5 characters) after each request and each response; the drive's own reaction time is not
        included."""
        gaps = 2 * 3.5 * self.requests
        return line_seconds(self.line_bytes, baudrate, parity) + line_seconds(int(gaps), baudrate, parity)


# -- the client --------------------------------------------------------------------------------------
class _RtuClient(ModbusSerialClient):
    """pymodbus's serial client, reading answers by their RTU length, and raising on open."""

    def __init__(self, port: str, *, line_stats: dict[str, int], **kwargs: Any) -> None:
        super().__init__(port, trace_packet=self._trace, **kwargs)
        self.line_stats = line_stats
        self.open_error: Exception | None = None

    def _trace(self, sending: bool, data: bytes) -> bytes:
        self.line_stats["bytes"] += len(data) if sending else 0
        return data

    def connect(self) -> bool:
        if self.socket:
            return True
        try:
            self.socket = serial.serial_for_url(
                self.comm_params.host,
                timeout=self.comm_params.timeout_connect,
                write_timeout=self.comm_params.timeout_connect,
                bytesize=self.comm_params.bytesize,
                stopbits=self.comm_params.stopbits,
                baudrate=self.comm_params.baudrate,
                parity=self.comm_params.parity,
                exclusive=True,  # flock: a second program on the port is refused, not interleaved
            )
        except (serial.SerialException, OSError, ValueError) as err:
            self.open_error = err
            self.socket = None
            return False
        self.open_error = None
        return True

    def recv(self, size: int | None) -> bytes:
        if not self.socket:
            raise ConnectionException(str(self))
        try:
            head = self.socket.read(3)
            if len(head) < 3:
                self.line_stats["short"] += bool(head)
                self.line_stats["bytes"] += len(head)
                return head
            fc = head[1]
            if fc & 0x80:
                rest = 2
            elif fc in (0x03, 0x04, 0x17):
                rest = head[2] + 2
            elif fc in (0x05, 0x06, 0x0F, 0x10):
                rest = 5
            else:
                rest = self.socket.in_waiting
            frame = head + self.socket.read(rest)
        except (serial.SerialException, OSError) as err:
            self.close()
            raise ConnectionException(f"{self.comm_params.host}: {err}") from err
        self.line_stats["bytes"] += len(frame)
        if len(frame) < 3 + rest:
            self.line_stats["short"] += 1
        elif crc16(frame[:-2]) != frame[-2:]:
            self.line_stats["crc"] += 1
        return frame


class ModbusDrive(Drive):
    """A drive on its serial service port, in Modbus RTU.

    :param port: serial device (``/dev/ttyUSB0``, a pty, or any pyserial URL).
    :param drive: drive description name under drivers/ with a ``modbus`` map (default ``sim``;
        the map's device-type register is checked, so a wrong map is refused before anything moves).
    :param device_id: Modbus device address (default: the map's); ``node_id`` is accepted as an alias.
    :param baudrate: line baud rate (default: the map's); ``bitrate`` is accepted as an alias.
    :param interface: must be None (a python-can interface makes no sense here).
    """

    def __init__(
        self,
        port: str,
        *,
        drive: str | DriveDescription | None = None,
        device_id: int | None = None,
        baudrate: int | None = None,
        interface: str | None = None,
        node_id: int | None = None,
        bitrate: int | None = None,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> None:
        super().__init__()
        if interface is not None:
            raise ConfigError(f"--interface {interface} is for CAN ports; Modbus RTU talks to the serial port itself")
        self.description = drive if isinstance(drive, DriveDescription) else load_description(drive or "sim")
        desc = self.description
        spec = desc.modbus
        if spec is None:
            raise ConfigError(f"drive '{desc.name}' has no Modbus register map (drivers/{desc.name}/modbus.yaml)")
        if spec.registers is None or spec.trace is None or spec.waveform is None:
            raise ConfigError(
                f"drive '{desc.name}': its {spec.dialect.upper()} map gives parameter access only "
                "(no state control, waveform player or trace through registers): commission it over CANopen"
            )
        self.spec: ModbusSpec = spec
        self.port = port
        self.device_id = int(device_id or node_id or spec.device_id)
        if not 1 <= self.device_id <= 247:
            raise ConfigError(f"Modbus device address must be 1..247, not {self.device_id}")
        self.baudrate = int(baudrate or bitrate or spec.baudrate)
        self.timeout_s = float(timeout_s or spec.timeout_s)
        self.retries = spec.retries if retries is None else int(retries)
        self.line = f"{self.baudrate} 8{spec.parity}{spec.stopbits}"
        self.stats = {"bytes": 0, "crc": 0, "short": 0}
        self.transfers: list[ModbusTransfer] = []
        self._failure: DriveError | None = None
        self._start_time: datetime | None = None
        self._last_partial: Recording | None = None
        self._downloaded: NDArray[Any] | None = None  # the waveform in the drive's player (prepare_excitation)
        self.client = _RtuClient(
            port, line_stats=self.stats, framer=FramerType.RTU, baudrate=self.baudrate, parity=spec.parity,
            stopbits=spec.stopbits, timeout=self.timeout_s, retries=self.retries, reconnect_delay=0,
        )
        try:
            self._open()
            self._bring_up()
        except BaseException:
            self.client.close()
            raise

    # -- link ---------------------------------------------------------------------------------------
    def _open(self) -> None:
        if self.client.connect():
            return
        err = self.client.open_error
        text = str(err)
        if "lock" in text.lower() or "busy" in text.lower():
            raise DriveError(f"serial port {self.port} is busy: another program holds it ({text})") from err
        if isinstance(err, serial.SerialException) and "No such file" in text:
            raise DriveNotFound(f"serial port {self.port} does not exist") from err
        raise DriveNotFound(f"cannot open serial port {self.port}: {text}") from err

    def _where(self) -> str:
        return f"device {self.device_id} on {self.port}"

    def _call(self, what: str, fn: Any, **kwargs: Any) -> Any:
        """One Modbus transaction; every failure becomes one line in our tree."""
        if self._failure is not None:
            raise type(self._failure)(str(self._failure))
        crc0, short0 = self.stats["crc"], self.stats["short"]
        try:
            rr = fn(device_id=self.device_id, **kwargs)
        except ConnectionException as err:
            cause = self.client.open_error or err.__cause__
            detail = f" ({cause})" if cause is not None else ""
            self._failure = DriveError(
                f"serial link to {self._where()} lost {what}: the port failed{detail}: cable pulled or adapter unplugged?")
            raise self._failure from err
        except ModbusIOException as err:
            crc, short = self.stats["crc"] - crc0, self.stats["short"] - short0
            seen = [f"{crc} with a bad CRC" if crc else "", f"{short} cut short" if short else ""]
            detail = "; answers: " + ", ".join(s for s in seen if s) if crc or short else ""
            self._failure = DriveTimeout(
                f"no valid Modbus answer from {self._where()} {what} after {self.retries + 1} tries "
                f"(timeout {self.timeout_s:g} s, {self.line}){detail}")
            raise self._failure from err
        except ModbusException as err:
            raise DriveError(f"Modbus error from {self._where()} {what}: {err}") from err
        if rr.isError():
            code = int(getattr(rr, "exception_code", 0))
            raise DriveError(f"Modbus exception 0x{code:02X} ({exception_text(code)}) from {self._where()} {what}")
        return rr

    def _read(self, reg: ModbusRegister, what: str) -> float:
        rr = self._call(f"reading {what} ({reg})", self.client.read_holding_registers, address=reg.address,
                        count=reg.words)
        return decode_registers(rr.registers, reg.type, self.spec.word_order)

    def _write(self, reg: ModbusRegister, value: float, what: str) -> None:
        words = encode_registers(value, reg.type, self.spec.word_order)
        if len(words) == 1:
            self._call(f"writing {what} ({reg})", self.client.write_register, address=reg.address, value=words[0])
        else:
            self._call(f"writing {what} ({reg})", self.client.write_registers, address=reg.address, values=words)

    # -- bring-up -----------------------------------------------------------------------------------
    def _bring_up(self) -> None:
        spec, regs = self.spec, self.spec.registers
        assert regs is not None
        if regs.device_type is not None:
            try:
                found = int(self._read(regs.device_type, "the device type"))
            except DriveTimeout as err:
                self._failure = None
                raise DriveNotFound(
                    f"no Modbus device answers at address {self.device_id} on {self.port} ({self.line}, timeout "
                    f"{self.timeout_s:g} s, {self.retries + 1} tries): check the cable, the address and the line "
                    f"settings{self._diagnosis()}") from err
            if spec.device_type is not None and found != spec.device_type:
                raise DriveError(
                    f"{self._where()} is not a '{self.description.name}' drive (device type 0x{found:04X}, "
                    f"expected 0x{spec.device_type:04X}): choose its description with --drive")
        ident: dict[str, str] = {}
        for key, s in spec.identity.items():
            rr = self._call(f"reading the {key} string", self.client.read_holding_registers, address=s.address,
                            count=s.registers)
            ident[key] = registers_to_string(rr.registers)
        self.rated_torque_nm = float(self._read(regs.rated_torque_mnm, "the rated torque")) / 1000
        if not self.rated_torque_nm > 0:
            raise DriveError(f"{self._where()} reports a rated torque of 0")
        self.motor_increments = float(self._read(regs.motor_increments, "the encoder resolution"))
        self.load_increments = (float(self._read(regs.load_increments, "the load encoder resolution"))
                                if regs.load_increments is not None else self.motor_increments)
        self.sample_rate_hz = (1e9 / float(self._read(regs.sample_period_ns, "the trace period"))
                               if regs.sample_period_ns is not None else self.description.drive_sample_rate_hz)
        self._info = DriveInfo(
            backend="modbus",
            vendor=ident.get("vendor", ""),
            product=ident.get("product", ""),
            serial_number=ident.get("serial", ""),
            firmware=ident.get("firmware", ""),
            rated_torque_nm=self.rated_torque_nm,
        )

    def _diagnosis(self) -> str:
        crc, short = self.stats["crc"], self.stats["short"]
        if crc or short:
            return f" ({crc} answers with a bad CRC, {short} cut short: wrong baud rate or parity?)"
        return ""

    # -- Drive hooks --------------------------------------------------------------------------------
    @property
    def info(self) -> DriveInfo:
        return self._info

    @property
    def _regs(self) -> Any:
        return self.spec.registers

    def _write_controlword(self, controlword: int) -> None:
        self._write(self._regs.controlword, int(controlword), "the controlword")

    def _read_statusword(self) -> int:
        return int(self._read(self._regs.statusword, "the statusword"))

    def _write_mode(self, mode: Mode) -> None:
        self._write(self._regs.mode, int(mode), "the mode of operation")
        if self._regs.mode_display is not None:
            shown = int(self._read(self._regs.mode_display, "the mode display"))
            if shown != int(mode):
                raise DriveError(f"{self._where()} did not take mode {mode.name}: it shows {shown}")

    def _limit_units(self, max_torque_nm: float, max_speed_rad_s: float) -> tuple[int, int]:
        """The torque limit in whole per mille of the rated torque and the speed limit in whole rpm,
        rounded down (the CiA 402 units the register map carries)."""
        if not (math.isfinite(max_torque_nm) and math.isfinite(max_speed_rad_s)):
            raise ConfigError(f"limits must be finite, got {max_torque_nm:g} N·m and {max_speed_rad_s:g} rad/s")
        permille = math.floor(max_torque_nm / self.rated_torque_nm * 1000)
        if not 1 <= permille <= 0xFFFF:
            raise ConfigError(f"torque limit {max_torque_nm:g} N·m is {permille} per mille of the rated torque: out of range")
        rpm = math.floor(max_speed_rad_s * 60 / (2 * math.pi))
        if rpm < 1:
            raise ConfigError(f"speed limit {max_speed_rad_s:g} rad/s is below 1 rpm, the unit of the speed limit")
        return permille, rpm

    def limits_as_held(self, max_torque_nm: float, max_speed_rad_s: float) -> tuple[float, float]:
        """The torque [N·m] and speed [rad/s] limits as this drive will hold them (sequencer hook)."""
        permille, rpm = self._limit_units(max_torque_nm, max_speed_rad_s)
        return permille * self.rated_torque_nm / 1000, rpm * 2 * math.pi / 60

    def _write_limits(self, max_torque_nm: float, max_speed_rad_s: float, max_travel_rad: float | None) -> None:
        regs = self._regs
        permille, rpm = self._limit_units(max_torque_nm, max_speed_rad_s)
        self._write(regs.max_torque, permille, "the torque limit")
        self._write(regs.max_speed, rpm, "the speed limit")
        if max_travel_rad is not None and None not in (regs.position_actual, regs.travel_min, regs.travel_max):
            here = int(self._read(regs.position_actual, "the position"))
            span = math.floor(max_travel_rad / (2 * math.pi) * self.motor_increments)
            self._write(regs.travel_min, max(-(2**31), here - span), "the travel limit")
            self._write(regs.travel_max, min(2**31 - 1, here + span), "the travel limit")

    def _fault_message(self) -> str:
        try:
            code = int(self._read(self._regs.error_code, "the error code"))
        except DriveError:
            return "drive is in Fault state (error code unreadable)"
        return f"drive fault 0x{code:04X} ({self.description.describe_error(code)})"

    # -- stopping on a failed link: send without waiting for answers that cannot come -----------------
    def _blind(self, command: Command) -> bool:
        words = encode_registers(int(command), self._regs.controlword.type, self.spec.word_order)
        try:
            self.client.write_register(self._regs.controlword.address, words[0], device_id=self.device_id,
                                       no_response_expected=True)
            time.sleep(max(0.02, line_seconds(16, self.baudrate, self.spec.parity)))  # let it reach the drive
            return True
        except ModbusException:
            return False

    def quick_stop(self) -> None:
        if self._failure is None:
            return super().quick_stop()
        self._blind(Command.QUICK_STOP)
        return None

    def disable(self) -> None:
        if self._failure is None:
            return super().disable()
        sent = self._blind(Command.DISABLE_VOLTAGE)
        how = "quick stop and disable were sent but cannot be confirmed" if sent else "the port is gone"
        raise DriveError(f"{how}; the drive's communication watchdog must stop it")

    # -- excitation ---------------------------------------------------------------------------------
    def _waveform_words(self, waveform: NDArray[np.float64], mode: Mode) -> NDArray[Any]:
        wf = self.spec.waveform
        assert wf is not None
        if mode is Mode.CYCLIC_SYNC_TORQUE:
            unit = self.rated_torque_nm * wf.torque_scale
        elif mode is Mode.CYCLIC_SYNC_VELOCITY:
            unit = 2 * math.pi / self.motor_increments * wf.velocity_scale
        else:
            raise DriveError(f"the waveform player plays CST or CSV, not {mode.name}")
        code, size = INT_TYPES[wf.type]
        raw = np.round(waveform / unit) if code not in "fd" else waveform / unit
        if code not in "fd":
            bits = 8 * size
            lo, hi = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if code.islower() else (0, 2**bits - 1)
            if raw.min() < lo or raw.max() > hi:
                raise DriveError(f"waveform exceeds the range of {wf.type} in the drive's unit ({unit:.3g} per count)")
        data = raw.astype(f">{code}").tobytes()
        if size == 1:
            data = b"".join(b"\0" + bytes([b]) for b in data)
        words = np.frombuffer(data, dtype=">u2").astype(np.int64)
        per = max(1, size // 2)
        if per > 1 and self.spec.word_order == "little":
            words = words.reshape(-1, per)[:, ::-1].reshape(-1)
        return words

    def prepare_excitation(self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode) -> None:
        """Check the rate and download the waveform, before enabling (sequencer hook); nothing is
        sent when exactly this waveform is in the drive's player already."""
        wf = self.spec.waveform
        assert wf is not None
        rate = self.sample_rate_hz
        if abs(sample_rate_hz - rate) > 1e-9 * rate:
            raise ConfigError(f"drive '{self.description.name}' plays waveforms at {rate:g} Hz, not {sample_rate_hz:g} Hz")
        words = self._waveform_words(waveform, mode)
        if self._downloaded is not None and np.array_equal(self._downloaded, words):
            return
        self._downloaded = None
        total = waveform.size
        per = max(1, INT_TYPES[wf.type][1] // 2)
        block = (wf.registers // per) * per
        t0, bytes0 = time.perf_counter(), self.stats["bytes"]
        self._write(wf.length, total, "the waveform length")
        requests = 1
        for pos in range(0, words.size, block):
            offset = pos // per
            chunk = [int(w) for w in words[pos : pos + block]]
            self._call(f"writing the waveform at sample {offset}", self.client.write_registers, address=wf.select,
                       values=encode_registers(offset, "uint32", self.spec.word_order) + chunk)
            requests += 1
        self.transfers.append(ModbusTransfer("waveform", "download", 2 * words.size, requests,
                                             self.stats["bytes"] - bytes0, time.perf_counter() - t0))
        self._downloaded = words

    def _excite(
        self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode, progress: ProgressCallback | None
    ) -> Recording:
        wf, tr = self.spec.waveform, self.spec.trace
        assert wf is not None and tr is not None
        self._last_partial = None
        rate = self.sample_rate_hz
        self.prepare_excitation(waveform, sample_rate_hz, mode)
        self._downloaded = None  # the player consumes it: a next run downloads again
        total = waveform.size
        self._start_time = datetime.now(timezone.utc)
        self._write(tr.start, tr.start_value, "the start trigger")
        self._await_playback(lambda: int(self._read(tr.progress, "the progress")), total, rate, progress,
                             poll_s=POLL_S, stall_s=STALL_S)
        rec = self._upload_trace()
        if rec is None or len(rec) != total:
            raise DriveError(f"trace holds {0 if rec is None else len(rec)} samples, expected {total}")
        return rec

    def _upload_channel(self, name: str, length: int) -> NDArray[np.float64]:
        tr = self.spec.trace
        assert tr is not None
        ch = tr.channels[name]
        per = max(1, INT_TYPES[ch.type][1] // 2)
        samples_per_read = tr.registers // per
        t0, bytes0 = time.perf_counter(), self.stats["bytes"]
        parts: list[NDArray[Any]] = []
        requests = 0
        for offset in range(0, length, samples_per_read):
            n = min(samples_per_read, length - offset)
            select = [ch.channel] + encode_registers(offset, "uint32", self.spec.word_order)
            what = f"uploading trace channel {ch.channel} ({name}) at sample {offset}"
            if tr.read_write:
                rr = self._call(what, self.client.readwrite_registers, read_address=tr.window, read_count=n * per,
                                write_address=tr.select, values=select)
                requests += 1
            else:
                self._call(what, self.client.write_registers, address=tr.select, values=select)
                rr = self._call(what, self.client.read_holding_registers, address=tr.window, count=n * per)
                requests += 2
            if len(rr.registers) < n * per:
                raise DriveError(f"{self._where()} answered {len(rr.registers)} registers {what}, expected {n * per}")
            parts.append(_words_array(rr.registers[: n * per], ch.type, self.spec.word_order))
        raw = np.concatenate(parts) if parts else np.zeros(0)
        self.transfers.append(ModbusTransfer(f"trace {name}", "upload", raw.size * 2 * per, requests,
                                             self.stats["bytes"] - bytes0, time.perf_counter() - t0))
        return self._to_si(raw, ch.unit, ch.scale, ch.encoder, ch.type)

    def _to_si(self, raw: NDArray[Any], unit: ChannelUnit, scale: float, encoder: str, type_name: str) -> NDArray[np.float64]:
        code, size = INT_TYPES[type_name]
        if unit is ChannelUnit.INCREMENT and code in "iI" and size == 4 and raw.size:
            steps = (np.diff(raw.astype(np.int64)) + 2**31) % 2**32 - 2**31  # a drive's counter wraps
            values = np.concatenate(([int(raw[0])], int(raw[0]) + np.cumsum(steps))).astype(np.float64)
        else:
            values = raw.astype(np.float64)
        values = values * scale
        if unit is ChannelUnit.RATED_TORQUE:
            return values * self.rated_torque_nm
        per_inc = 2 * math.pi / (self.motor_increments if encoder == "motor" else self.load_increments)
        if unit is ChannelUnit.INCREMENT_PER_SAMPLE:
            return values * per_inc * self.sample_rate_hz
        return values * per_inc

    def _upload_trace(self) -> Recording | None:
        tr = self.spec.trace
        assert tr is not None
        length = int(self._read(tr.length, "the trace length"))
        if length < 2 or self._start_time is None:
            return None
        signals = {name: self._upload_channel(name, length) for name in tr.channels}
        return Recording.uniform(
            self.sample_rate_hz,
            signals.pop("torque_ref"),
            signals.pop("motor_velocity"),
            start_time=self._start_time,
            drive=self._info,
            metadata={"link": f"modbus rtu {self.port} device {self.device_id} ({self.line})",
                      "excitation_path": "drive waveform player + trace (Modbus registers, FC 16 / FC 23)"},
            **signals,
        )

    def _recorded_so_far(self) -> Recording | None:
        if self._last_partial is None and self._failure is None:
            self._last_partial = self._upload_trace()
        return self._last_partial

    # -- parameters ---------------------------------------------------------------------------------
    def read_parameter(self, name: str) -> Any:
        spec = self.spec.parameters.get(name)
        if spec is None:
            return super().read_parameter(name)
        return float(self._read(spec.register, name)) * spec.scale

    def write_parameter(self, name: str, value: Any) -> None:
        spec = self.spec.parameters.get(name)
        if spec is None:
            return super().write_parameter(name, value)
        raw = parameter_raw(spec, name, value, f"{spec.register}, drive '{self.description.name}'")
        self._write(spec.register, raw, name)

    def _shutdown(self) -> None:
        self.client.close()
