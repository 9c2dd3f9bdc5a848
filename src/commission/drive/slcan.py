"""CANopen through a serial-line CAN adapter (Lawicel / slcan), on python-can's own ``slcan`` client.

What this adds around :class:`~commission.drive.canopen.CanopenDrive` for
``--interface slcan``:

* before python-can opens the port: the port is **locked** (``flock``, as
  pyserial's ``exclusive=True``: a second commissioning on the same adapter is
  refused, "busy") and the adapter is **probed** with the version query ``V``;
  no answer is "adapter not answering", one clear line, before anything is
  sent on the bus. An adapter that answers at once needs none of python-can's
  default 2 s wait after opening (kept for adapters that reboot on open);
* :class:`CheckedSlcanBus`: python-can's ``slcanBus`` that checks every line the
  adapter sends. A garbled or truncated frame is dropped and counted (as a CAN
  controller drops a frame with a bad CRC), so the CANopen layer sees a lost
  frame, which SDO block transfers and retries recover from, instead of a
  Python exception that kills the receive thread; a serial port that fails
  (cable pulled) becomes ``CanOperationError`` with the port's name;
* :class:`SlcanCanopenDrive`: every error the drive raises gets the link's
  diagnosis appended when the adapter sent garbage.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import re
import struct
import time
from collections.abc import Callable, Iterator
from typing import Any

import can
import canopen
import serial
from can.interfaces.slcan import slcanBus

from ..exceptions import DriveError, DriveNotFound, DriveTimeout
from .canopen import CanopenDrive
from .cia402 import Command

__all__ = ["CheckedSlcanBus", "SlcanCanopenDrive", "open_slcan", "probe_adapter"]

# the receive thread logs at ERROR when it stops; our error already says why, in one line
for _name in ("can", "canopen"):
    logging.getLogger(_name).addHandler(logging.NullHandler())

#: seconds to wait for the adapter's answer to ``V`` (an adapter that reboots on open takes longer)
PROBE_TIMEOUT_S = 2.5
#: an adapter that answered faster than this needs no wait after opening
FAST_ANSWER_S = 0.3
#: least SDO timeout and heartbeat consumer time through a serial adapter: USB and two hosts'
#: schedulers sit between the nodes (0.3 s timed out now and then on a loaded 2-core machine)
MIN_SDO_TIMEOUT_S = 1.0
MIN_HEARTBEAT_TIMEOUT_MS = 1000
#: a line the adapter does not take within this long fails the send [s] (a hung adapter, or a USB
#: link that stalled), where python-can's would wait for ever
WRITE_TIMEOUT_S = 2.0

_FRAME = re.compile(r"^(?:t[0-9A-Fa-f]{3}([0-8])|T[0-9A-Fa-f]{8}([0-8]))([0-9A-Fa-f]*)(?:[0-9A-Fa-f]{4})?\r$")
_REMOTE = re.compile(r"^(?:r[0-9A-Fa-f]{3}[0-8]|R[0-9A-Fa-f]{8}[0-8])(?:[0-9A-Fa-f]{4})?\r$")


def _valid_frame(line: str) -> bool:
    if line[:1] in "rR":
        return bool(_REMOTE.match(line))
    m = _FRAME.match(line)
    if not m:
        return False
    dlc = int(m.group(1) or m.group(2))
    data = m.group(3)
    return len(data) == 2 * dlc or len(data) == 2 * dlc + 4  # with an optional time stamp


class CheckedSlcanBus(slcanBus):
    """python-can's slcan bus, checking every line the adapter sends (see the module docstring)."""

    def __init__(self, channel: str, **kwargs: Any) -> None:
        self.port_name = channel
        #: arrival time (time.time) of the bytes read so far: (end offset in the stream, time)
        self._arrivals: list[tuple[int, float]] = []
        self._consumed = 0
        self._line_time = 0.0
        self.garbled = 0
        self.last_garbled = ""
        self.frames = 0
        self.failure: can.CanOperationError | None = None
        super().__init__(channel, **kwargs)
        self.serialPortOrig.write_timeout = WRITE_TIMEOUT_S

    def _read(self, timeout: float | None) -> str | None:
        """One line from the adapter (with its terminator), or None after ``timeout``.

        python-can's own ``_read`` makes one system call per byte (~10 µs each: a 22-byte frame
        line costs ~0.2 ms, which caps an SDO block upload at ~30 kB/s on any link); this reads
        what is waiting in one call and splits the lines here.
        """
        expiry = serial.Timeout(timeout)
        buf = self._buffer
        while True:
            ends = [i for i in (buf.find(b"\r"), buf.find(b"\a")) if i >= 0]
            if ends:
                end = min(ends)
                line = buf[: end + 1].decode("ascii", "replace")
                del buf[: end + 1]
                self._stamp(end + 1)
                return self._checked(line)
            if self.failure is not None:  # the receive thread keeps waiting; send() reports it
                time.sleep(0.1 if timeout is None else min(timeout, 0.1))
                return None
            try:
                waiting = self.serialPortOrig.in_waiting
                chunk = self.serialPortOrig.read(max(1, waiting))
            except (serial.SerialException, OSError, TypeError) as err:
                # raising here would end python-can's receive thread with a traceback on stderr
                self.failure = can.CanOperationError(
                    f"slcan adapter on {self.port_name} stopped answering: the serial port failed "
                    f"({err}): cable pulled or adapter unplugged?")
                return None
            if chunk:
                buf.extend(chunk)
                self._arrivals.append((self._consumed + len(buf), time.time()))
            elif expiry.expired():
                return None

    def _stamp(self, length: int) -> None:
        """The arrival time of the line just taken from the buffer (its last byte's read)."""
        end = self._consumed + length
        for at, when in self._arrivals:
            if at >= end:
                self._line_time = when
                break
        self._consumed = end
        self._arrivals = [(at, when) for at, when in self._arrivals if at > end]

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """python-can's, with each frame stamped when its line reached this host (python-can stamps it
        when parsed): the streamed cycle tells an answer that waited in the host from a fresh one."""
        msg, filtered = super()._recv_internal(timeout)
        if msg is not None and self._line_time:
            msg.timestamp = self._line_time
        return msg, filtered

    def _checked(self, line: str) -> str | None:
        if line and line[0] in "tTrR":
            if not _valid_frame(line):
                self.garbled += 1
                self.last_garbled = line.rstrip("\r")[:30]
                return None
            self.frames += 1
        return line

    def _write(self, string: str) -> None:
        """python-can's, without its tcdrain after every line: that waits, with no time limit, until
        the adapter has taken the line; the write timeout bounds the wait instead."""
        try:
            self.serialPortOrig.write(string.encode() + self.LINE_TERMINATOR)
        except (serial.SerialException, OSError, TypeError) as err:
            raise can.CanOperationError(f"Could not write to serial device: {err}") from err

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.failure is not None:
            raise can.CanOperationError(str(self.failure))
        try:
            super().send(msg, WRITE_TIMEOUT_S if timeout is None else timeout)
        except can.CanOperationError as err:
            cause = err.__cause__ or err
            if isinstance(cause, serial.SerialTimeoutException):
                why = (f"it took nothing for {self.serialPortOrig.write_timeout:g} s: the adapter hangs or its USB "
                       "link stalled")
            else:
                why = "cable pulled or adapter unplugged?"
            self.failure = can.CanOperationError(f"slcan adapter on {self.port_name}: cannot write ({cause}): {why}")
            raise self.failure from err

    def _send_periodic_internal(self, msgs: Any, period: float, duration: float | None = None,
                                autostart: bool = True, modifier_callback: Any = None) -> Any:
        """As python-can's, but a send that fails (port gone) ends the task quietly instead of with a
        traceback from its thread; the drive's heartbeat consumer then notices the silence."""
        task = super()._send_periodic_internal(msgs, period, duration, autostart=False,
                                               modifier_callback=modifier_callback)
        if hasattr(task, "on_error"):
            task.on_error = lambda exc: False
        if autostart:
            task.start()
        return task

    def shutdown(self) -> None:
        try:
            super().shutdown()
        except can.CanError:
            pass  # the port failed (cable pulled): closing it must not raise
        finally:
            try:
                self.serialPortOrig.close()
            except (serial.SerialException, OSError):
                pass

    def diagnosis(self) -> str:
        if not self.garbled:
            return ""
        return (f"; the adapter sent {self.garbled} garbled frame line(s) (last '{self.last_garbled}'): "
                "check the USB cable, the adapter's firmware and its serial speed")


def probe_adapter(port: str, tty_baudrate: int = 115200, timeout_s: float = PROBE_TIMEOUT_S) -> tuple[str, float]:
    """Send ``C`` + ``V`` until the adapter answers ``V…``; returns (version, seconds to answer).

    :raises DriveTimeout: no answer within ``timeout_s``.
    """
    try:
        ser = serial.serial_for_url(port, baudrate=tty_baudrate, timeout=0.05)
    except (serial.SerialException, OSError, ValueError) as err:
        raise DriveNotFound(f"cannot open serial port {port}: {err}") from err
    t0 = time.monotonic()
    buffer = b""
    try:
        next_query = t0
        while time.monotonic() - t0 < timeout_s:
            if time.monotonic() >= next_query:
                ser.write(b"C\rV\r")
                next_query = time.monotonic() + 0.25
            buffer += ser.read(64)
            for line in buffer.split(b"\r"):
                if line.startswith(b"V") and len(line) >= 5:
                    return line.decode("ascii", "replace"), time.monotonic() - t0
            buffer = buffer[-64:]
    except (serial.SerialException, OSError) as err:
        raise DriveError(f"slcan adapter on {port}: serial port failed during the probe: {err}") from err
    finally:
        ser.close()
    heard = f" (it sent {buffer[:20]!r})" if buffer.strip(b"\r\a") else ""
    raise DriveTimeout(
        f"slcan adapter on {port} does not answer (no reply to the version query 'V' within {timeout_s:g} s){heard}: "
        "is it an slcan/Lawicel adapter, and is its firmware running?")


@contextlib.contextmanager
def _locked(port: str) -> Iterator[int | None]:
    """An exclusive flock on the port for the lifetime of the drive (None for non-device URLs)."""
    if not os.path.exists(port):
        yield None
        return
    fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        os.close(fd)
        raise DriveError(f"serial port {port} is busy: another program holds it ({err.strerror})") from err
    try:
        yield fd
    finally:
        os.close(fd)


class SlcanCanopenDrive(CanopenDrive):
    """:class:`CanopenDrive` on a :class:`CheckedSlcanBus`: errors carry the link's diagnosis, and a
    stop that cannot be confirmed is still sent."""

    #: the adapter's answer to ``V`` (e.g. ``V1013``)
    adapter_version: str = ""
    MIN_SDO_TIMEOUT_S = MIN_SDO_TIMEOUT_S
    MIN_HEARTBEAT_TIMEOUT_MS = MIN_HEARTBEAT_TIMEOUT_MS

    def __init__(self, port: str, *, bus: CheckedSlcanBus, **options: Any) -> None:
        self.bus = bus
        with self._diagnosed():
            super().__init__(port, interface="slcan", **options)

    @contextlib.contextmanager
    def _diagnosed(self) -> Iterator[None]:
        try:
            yield
        except DriveError as err:
            extra = self.bus.diagnosis()
            if extra and extra not in str(err):
                err.args = (f"{err}{extra}",)
            raise

    # -- stopping on a failed link: the commands are still sent, without waiting for answers ---------
    def _blind(self, command: Command) -> bool:
        """Expedited SDO download of the controlword (0x6040), not waiting for the answer: the frames
        towards the drive may still arrive when its answers do not (garbled, adapter half-broken)."""
        request = struct.pack("<BHBH2x", 0x2B, 0x6040, 0, int(command))
        try:
            self.network.send_message(0x600 + self.node_id, request)
        except (can.CanError, OSError, RuntimeError):
            return False
        time.sleep(0.05)
        return True

    def quick_stop(self) -> None:
        self._stop(super().quick_stop, Command.QUICK_STOP, "quick stop")

    def disable(self) -> None:
        self._stop(super().disable, Command.DISABLE_VOLTAGE, "disable voltage")

    def _stop(self, confirmed: Callable[[], None], command: Command, what: str) -> None:
        """``confirmed`` (the command through the state machine); when its answers do not come, the command
        sent blind and confirmed once more: an answer can queue behind an interrupted transfer's frames past
        the SDO timeout (Ctrl-C during the download, on a loaded 2-core machine)."""
        try:
            confirmed()
        except DriveError as err:
            sent = self._blind(command)
            if isinstance(err, DriveTimeout):
                with contextlib.suppress(DriveError):
                    confirmed()
                    return
            raise DriveError(f"{err} ({what} {'sent without confirmation' if sent else 'could not be sent'})") from err

    def _write_controlword(self, controlword: int) -> None:
        with self._diagnosed():
            super()._write_controlword(controlword)

    def _read_statusword(self) -> int:
        with self._diagnosed():
            return super()._read_statusword()

    def _write_mode(self, mode: Any) -> None:
        with self._diagnosed():
            super()._write_mode(mode)

    def _write_limits(self, max_torque_nm: float, max_speed_rad_s: float, max_travel_rad: float | None) -> None:
        with self._diagnosed():
            super()._write_limits(max_torque_nm, max_speed_rad_s, max_travel_rad)

    def _excite(self, *args: Any, **kwargs: Any) -> Any:
        with self._diagnosed():
            return super()._excite(*args, **kwargs)

    def _recorded_so_far(self) -> Any:
        with self._diagnosed():
            return super()._recorded_so_far()

    def read_parameter(self, name: str) -> Any:
        with self._diagnosed():
            return super().read_parameter(name)

    def write_parameter(self, name: str, value: Any) -> None:
        with self._diagnosed():
            super().write_parameter(name, value)


def open_slcan(
    port: str,
    *,
    bitrate: int | None = None,
    tty_baudrate: int = 115200,
    sleep_after_open: float | None = None,
    probe_timeout_s: float = PROBE_TIMEOUT_S,
    line_bps: float | None = None,
    **options: Any,
) -> SlcanCanopenDrive:
    """The CANopen backend through the slcan adapter on ``port`` (``commission --interface slcan``).

    :param bitrate: CAN bit rate the adapter is set to (``S0``–``S8``; default: the adapter's own).
    :param tty_baudrate: the adapter's serial speed (USB CDC adapters ignore it).
    :param line_bps: the adapter's serial line [bit/s] when it is a UART of known speed (the streamed
        cycle must fit it); None for a USB adapter, whose line is not the limit.
    :param options: passed on to :class:`CanopenDrive` (node_id, drive (None: from the drive's
        identity), excitation, band_hz, max_rate_hz, …).
    """
    lock = contextlib.ExitStack()
    lock.enter_context(_locked(port))  # "busy" before anything is written to the port
    try:
        version, answered_s = probe_adapter(port, tty_baudrate, probe_timeout_s)
        if sleep_after_open is None:
            sleep_after_open = 0.0 if answered_s < FAST_ANSWER_S else slcanBus._SLEEP_AFTER_SERIAL_OPEN
        bus_options: dict[str, Any] = {"tty_baudrate": tty_baudrate, "sleep_after_open": sleep_after_open}
        if bitrate is not None:
            bus_options["bitrate"] = bitrate
        try:
            bus = CheckedSlcanBus(port, **bus_options)
        except (can.CanError, ValueError, OSError) as err:
            raise DriveNotFound(f"cannot open slcan adapter on {port}: {err}") from err
    except BaseException:
        lock.close()
        raise
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = 0.1  # the receive thread's longest wait: a quick close
    network.connect()
    closed = False

    def close() -> None:
        nonlocal closed
        if closed:
            return
        closed = True
        try:
            network.disconnect()  # stops the receive thread, shuts the bus down (sends 'C')
        except (can.CanError, OSError, ValueError):
            pass  # the port may be gone (cable pulled); the error was reported already
        finally:
            lock.close()

    try:
        drive = SlcanCanopenDrive(port, bus=bus, network=network, on_close=close, bitrate=bitrate,
                                  line_bps=line_bps, **options)
    except BaseException:
        close()
        raise
    drive.adapter_version = version
    return drive
