"""The CANopen CiA 402 backend: :class:`CanopenDrive`.

Bring-up (at construction, before anything moves): connect the bus, find the
node (SDO 0x1000 device type, profile 402), read its identity (0x1018, 0x1008,
0x100A), pre-operational, heartbeat producer time 0x1017 and our heartbeat
consumer, our own heartbeat and the drive's consumer of it (0x1016), EMCY listener, unit scaling (0x6076 rated torque, 0x608F encoder
resolution), and for the streamed fallback the bus budget and the PDO mapping;
then NMT start.

Excitation, by the drive description's ``excitation``:

* ``trace`` (primary): SDO block download of the waveform, start, poll progress
  (heartbeat and EMCY watched), SDO block upload of every trace channel, a
  uniform Recording at the drive's clock;
* ``streamed`` (fallback): SYNC + RPDO target torque (per mille of rated, 0x6071)
  + TPDOs at the highest rate the bus budget allows; the Recording carries the
  real SYNC times; achieved rate and jitter in :attr:`CanopenDrive.stream_report`
  and in the Recording's metadata.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from typing import Any

import can
import canopen
import numpy as np
from numpy.typing import NDArray

from ...exceptions import ConfigError, DriveError, DriveFault, DriveNotFound, DriveTimeout
from ...recording import DriveInfo, Recording
from ..base import Drive, ProgressCallback
from ..cia402 import Mode, State, decode_statusword
from ..description import (
    DriveDescription,
    ExcitationMethod,
    ObjectRef,
    load_description,
    parameter_raw,
)
from .emcy import EmcyListener
from .nmt import HeartbeatConsumer, NmtCommand, send_nmt
from .pdo import (
    BusBudget,
    CyclicStreamer,
    StreamReport,
    frame_bits,
    interpolation_period,
    plan_cycle,
    waveform_band_hz,
)
from .sdo import SdoAccess, TransferStats
from .trace import channel_from_bus, waveform_to_bus

# Standard CiA 301 / 402 objects (the description names only what is vendor-specific).
DEVICE_TYPE = ObjectRef(index=0x1000)
DEVICE_NAME = ObjectRef(index=0x1008)
SOFTWARE_VERSION = ObjectRef(index=0x100A)
HEARTBEAT_TIME = ObjectRef(index=0x1017)
CONSUMER_HEARTBEAT = ObjectRef(index=0x1016, subindex=1)
VENDOR_ID = ObjectRef(index=0x1018, subindex=1)
PRODUCT_CODE = ObjectRef(index=0x1018, subindex=2)
REVISION = ObjectRef(index=0x1018, subindex=3)
SERIAL = ObjectRef(index=0x1018, subindex=4)
ERROR_CODE = ObjectRef(index=0x603F)
CONTROLWORD = ObjectRef(index=0x6040)
STATUSWORD = ObjectRef(index=0x6041)
MODE = ObjectRef(index=0x6060)
MODE_DISPLAY = ObjectRef(index=0x6061)
POSITION_ACTUAL = ObjectRef(index=0x6064)
MAX_TORQUE = ObjectRef(index=0x6072)
POSITION_LIMIT_MIN = ObjectRef(index=0x607D, subindex=1)
POSITION_LIMIT_MAX = ObjectRef(index=0x607D, subindex=2)
MAX_MOTOR_SPEED = ObjectRef(index=0x6080)
INTERPOLATION_PERIOD = ObjectRef(index=0x60C2, subindex=1)
INTERPOLATION_INDEX = ObjectRef(index=0x60C2, subindex=2)

#: longest wait of the receive thread, so closing the link takes no more than this
NOTIFIER_CYCLE_S = 0.1
#: seconds between progress polls during a trace run
POLL_S = 0.02
#: a trace run whose progress stays unchanged this long (beyond its duration) is a timeout
STALL_S = 2.0
#: bytes of the frames of one streamed cycle: SYNC, RPDO 0x6071, TPDO 0x6064+0x606C, TPDO 0x6077+0x6041
STREAM_FRAMES = (0, 2, 8, 4)


class CanopenDrive(Drive):
    """A CiA 402 drive on a CANopen bus.

    :param port: CAN channel (``can0``; for the virtual interface, any name).
    :param interface: python-can interface (default ``socketcan``).
    :param bitrate: bit rate [bit/s] for the adapter and the bus budget (default: the description's).
    :param node_id: the drive's node id (default: the description's).
    :param drive: drive description name under drivers/ (default ``generic-cia402``) or a loaded one.
    :param excitation: ``trace`` or ``streamed`` to override the description's method.
    :param band_hz: excitation band the streamed path must cover (else estimated from the waveform).
    :param allow_narrow_band: stream even when the bus cannot cover the band (the usable band is reported).
    :param network: an already connected canopen Network to use (not disconnected on close).
    :param on_close: called after the link is released (the in-process simulated node's shutdown).
    :param simulator: the in-process simulated node behind the bus, if any (kept for tests: ``.simulator``).
    """

    def __init__(
        self,
        port: str | None = None,
        *,
        interface: str | None = None,
        bitrate: int | None = None,
        node_id: int | None = None,
        drive: str | DriveDescription | None = None,
        excitation: str | ExcitationMethod | None = None,
        band_hz: float | None = None,
        allow_narrow_band: bool = False,
        network: canopen.Network | None = None,
        on_close: Callable[[], None] | None = None,
        simulator: Any = None,
        **bus_options: Any,
    ) -> None:
        super().__init__()
        self.description = drive if isinstance(drive, DriveDescription) else load_description(drive or "generic-cia402")
        desc = self.description
        try:
            self.method = ExcitationMethod(excitation) if excitation is not None else desc.excitation
        except ValueError:
            raise ConfigError(f"excitation must be 'trace' or 'streamed', not '{excitation}'") from None
        if self.method is ExcitationMethod.TRACE and desc.trace is None:
            raise ConfigError(f"drive '{desc.name}' has no trace buffer: use the streamed excitation")
        self.node_id = node_id or desc.node_id
        if not 1 <= self.node_id <= 127:
            raise ConfigError(f"node id must be 1..127, not {self.node_id}")
        self.interface = interface or "socketcan"
        self.port = port or ""
        self.bitrate = int(bitrate or desc.bitrate)
        self.band_hz = band_hz
        self.allow_narrow_band = allow_narrow_band
        self._on_close = on_close
        self.simulator = simulator
        self._own_network = network is None
        self.stream_report: StreamReport | None = None
        self.budget: BusBudget | None = None
        self._streamer: CyclicStreamer | None = None
        self._start_time: datetime | None = None
        self._last_partial: Recording | None = None
        self._excite_mode = Mode.CYCLIC_SYNC_TORQUE
        self._run_total = 0
        self._closed_link = False
        self._downloaded: bytes | None = None  # the waveform in the drive's player (prepare_excitation)

        if network is None:
            network = canopen.Network()
            network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
            options = {"channel": self.port, "interface": self.interface, **bus_options}
            if bitrate is not None:
                options["bitrate"] = bitrate
            try:
                network.connect(**options)
            except (can.CanError, OSError, ValueError, ImportError) as err:
                hint = " (is the SocketCAN link up? ip link show)" if self.interface == "socketcan" else ""
                raise DriveNotFound(
                    f"cannot open CAN interface '{self.interface}' channel '{self.port}': {err}{hint}"
                ) from err
        self.network = network
        try:
            self._bring_up()
        except BaseException:
            self._release()
            raise

    # -- bring-up ---------------------------------------------------------------------------------
    def _bring_up(self) -> None:
        desc = self.description
        self.node = canopen.RemoteNode(self.node_id, str(desc.eds_path))
        self.network.add_node(self.node)
        self.heartbeat = HeartbeatConsumer(self.network, self.node_id, desc.heartbeat_timeout_ms / 1000,
                                           desc.heartbeat_ms / 1000)
        self.emcy = EmcyListener(self.network, self.node_id, desc.describe_error)
        self.sdo = SdoAccess(self.node, desc.sdo_timeout_s, self.heartbeat.check)
        try:
            device_type = int(self.sdo.read(DEVICE_TYPE))
        except DriveTimeout as err:
            heard = sorted(set(self.network.scanner.nodes) - {self.node_id})
            hint = f"; nodes heard on the bus: {', '.join(map(str, heard))}" if heard else ""
            raise DriveNotFound(
                f"no CANopen node answers at node id {self.node_id} on {self.interface}:{self.port} "
                f"(no SDO response to 0x1000 within {desc.sdo_timeout_s:g} s){hint}"
            ) from err
        if device_type & 0xFFFF != desc.device_type_profile:
            raise DriveError(
                f"node {self.node_id} is not a CiA {desc.device_type_profile} drive "
                f"(device type 0x{device_type:08X}, profile {device_type & 0xFFFF})"
            )
        send_nmt(self.network, NmtCommand.ENTER_PRE_OPERATIONAL, self.node_id)
        self.sdo.write(HEARTBEAT_TIME, desc.heartbeat_ms)
        if not self.heartbeat.wait(3 * desc.heartbeat_ms / 1000 + desc.heartbeat_timeout_ms / 1000):
            raise DriveTimeout(f"node {self.node_id} sends no heartbeat after 0x1017 = {desc.heartbeat_ms} ms")
        self._start_host_heartbeat()
        self._read_identity()
        self._read_units()
        if self.method is ExcitationMethod.STREAMED:
            self._plan_stream()
            self._configure_pdos()
        else:
            self._trace_rate_hz = self._read_trace_rate()
        send_nmt(self.network, NmtCommand.START, self.node_id)

    def _start_host_heartbeat(self) -> None:
        """Our own heartbeat, and the drive's consumer of it (0x1016): if this host dies mid-run,
        the drive stops itself within the consumer time."""
        desc = self.description
        self._host_heartbeat = None
        if CONSUMER_HEARTBEAT.index not in self.node.object_dictionary:
            return
        host = desc.host_node_id if desc.host_node_id != self.node_id else desc.host_node_id - 1
        self._host_heartbeat = self.network.send_periodic(0x700 + host, bytes([0x05]), desc.heartbeat_ms / 1000)
        self.sdo.write(CONSUMER_HEARTBEAT, (host << 16) | min(0xFFFF, desc.heartbeat_timeout_ms))

    def _read_identity(self) -> None:
        def optional(ref: ObjectRef) -> Any:
            if ref.index not in self.node.object_dictionary:
                return None
            try:
                return self.sdo.read(ref)
            except DriveError:
                return None

        vendor_id = optional(VENDOR_ID)
        name = optional(DEVICE_NAME) or self.node.object_dictionary.device_information.product_name or ""
        vendor = self.node.object_dictionary.device_information.vendor_name or ""
        self.identity = {
            "vendor_id": vendor_id, "product_code": optional(PRODUCT_CODE),
            "revision": optional(REVISION), "serial": optional(SERIAL),
        }
        self.rated_torque_nm = int(self.sdo.read(self.description.units.rated_torque_mnm)) / 1000.0
        if not self.rated_torque_nm > 0:
            raise DriveError(f"node {self.node_id} reports a rated torque of 0 (0x6076)")
        serial = self.identity["serial"]
        self._info = DriveInfo(
            backend="canopen",
            vendor=vendor if vendor_id is None else f"{vendor} (0x{vendor_id:08X})".strip(),
            product=str(name),
            serial_number="" if serial is None else str(serial),
            firmware=str(optional(SOFTWARE_VERSION) or ""),
            rated_torque_nm=self.rated_torque_nm,
        )

    def _read_units(self) -> None:
        units = self.description.units
        if units.motor_increments is not None and units.motor_increments.index in self.node.object_dictionary:
            increments = int(self.sdo.read(units.motor_increments))
            revolutions = int(self.sdo.read(units.motor_revolutions)) if units.motor_revolutions else 1
            self.motor_increments = increments / max(1, revolutions)
        elif units.motor_increments_per_rev:
            self.motor_increments = float(units.motor_increments_per_rev)
        else:
            raise ConfigError(f"drive '{self.description.name}': no encoder resolution (units.motor_increments)")
        if units.load_increments is not None:
            self.load_increments = float(self.sdo.read(units.load_increments))
        else:
            self.load_increments = float(units.load_increments_per_rev or self.motor_increments)

    def _read_trace_rate(self) -> float:
        trace = self.description.trace
        assert trace is not None
        if trace.waveform.sample_period_ns is not None:
            return 1e9 / int(self.sdo.read(trace.waveform.sample_period_ns))
        return self.description.drive_sample_rate_hz

    # -- streamed fallback: budget and PDO mapping ------------------------------------------------------
    def _plan_stream(self) -> None:
        desc = self.description
        heartbeat_bps = 2 * frame_bits(1) / (desc.heartbeat_ms / 1000)  # the drive's and ours
        self.budget = plan_cycle(self.bitrate, STREAM_FRAMES, 1.0 / desc.drive_sample_rate_hz,
                                 max_load=desc.streamed.max_load, background_bps=heartbeat_bps)
        if self.band_hz is not None:
            self._check_band(self.band_hz)

    def _check_band(self, band_hz: float) -> None:
        assert self.budget is not None
        if band_hz > self.budget.usable_band_hz * (1 + 1e-9) and not self.allow_narrow_band:
            raise ConfigError(
                f"the bus allows {self.budget.describe()}, below the excitation band {band_hz:.0f} Hz: "
                "use a higher bit rate, a drive with a trace buffer, a lower f_end_hz, or allow a narrow band"
            )

    def _configure_pdos(self) -> None:
        """RPDO: 0x6071; TPDO a: 0x6064 + 0x606C; TPDO b: 0x6077 + 0x6041; all synchronous (type 1)."""
        spec = self.description.streamed
        assert self.budget is not None
        try:
            rpdo = self.node.rpdo[spec.rpdo]
            tpdo_a, tpdo_b = self.node.tpdo[spec.tpdo[0]], self.node.tpdo[spec.tpdo[1]]
            for pdo_map, objects, cob in (
                (rpdo, (0x6071,), 0x200 + 0x100 * (spec.rpdo - 1) + self.node_id),
                (tpdo_a, (0x6064, 0x606C), 0x180 + 0x100 * (spec.tpdo[0] - 1) + self.node_id),
                (tpdo_b, (0x6077, 0x6041), 0x180 + 0x100 * (spec.tpdo[1] - 1) + self.node_id),
            ):
                pdo_map.clear()
                for index in objects:
                    pdo_map.add_variable(index)
                pdo_map.cob_id = cob
                pdo_map.trans_type = 1
                pdo_map.enabled = True
                pdo_map.save()
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError, KeyError) as err:
            raise DriveError(f"node {self.node_id} refused the PDO mapping for streamed CST: {err}") from err
        # the PdoMaps subscribed themselves; our streamer reads the frames instead
        for pdo_map in (tpdo_a, tpdo_b):
            try:
                self.network.unsubscribe(pdo_map.cob_id, pdo_map.on_message)
            except (KeyError, ValueError):
                pass
        period = interpolation_period(self.budget.cycle_s)
        if period is not None and INTERPOLATION_PERIOD.index in self.node.object_dictionary:
            self.sdo.write(INTERPOLATION_PERIOD, period[0])
            self.sdo.write(INTERPOLATION_INDEX, period[1])
        self._streamer = CyclicStreamer(self.network, rpdo.cob_id, tpdo_a.cob_id, tpdo_b.cob_id)

    # -- Drive hooks --------------------------------------------------------------------------------
    @property
    def info(self) -> DriveInfo:
        return self._info

    def _write_controlword(self, controlword: int) -> None:
        self.sdo.write(CONTROLWORD, int(controlword))

    def _read_statusword(self) -> int:
        return int(self.sdo.read(STATUSWORD))

    def _write_mode(self, mode: Mode) -> None:
        self.sdo.write(MODE, int(mode))
        shown = int(self.sdo.read(MODE_DISPLAY))
        if shown != int(mode):
            raise DriveError(f"node {self.node_id} did not take mode {mode.name}: 0x6061 shows {shown}")

    def _limit_units(self, max_torque_nm: float, max_speed_rad_s: float) -> tuple[int, int]:
        """0x6072 in whole per mille of the rated torque and 0x6080 in whole rpm, rounded down."""
        if not (math.isfinite(max_torque_nm) and math.isfinite(max_speed_rad_s)):
            raise ConfigError(f"limits must be finite, got {max_torque_nm:g} N·m and {max_speed_rad_s:g} rad/s")
        permille = math.floor(max_torque_nm / self.rated_torque_nm * 1000)
        if not 1 <= permille <= 0xFFFF:
            raise ConfigError(f"torque limit {max_torque_nm:g} N·m is {permille} per mille of the rated torque: out of range")
        rpm = math.floor(max_speed_rad_s * 60 / (2 * math.pi))
        if rpm < 1:
            raise ConfigError(f"speed limit {max_speed_rad_s:g} rad/s is below 1 rpm, the unit of 0x6080")
        return permille, rpm

    def limits_as_held(self, max_torque_nm: float, max_speed_rad_s: float) -> tuple[float, float]:
        """The torque [N·m] and speed [rad/s] limits as this drive will hold them (sequencer hook)."""
        permille, rpm = self._limit_units(max_torque_nm, max_speed_rad_s)
        return permille * self.rated_torque_nm / 1000, rpm * 2 * math.pi / 60

    def _write_limits(self, max_torque_nm: float, max_speed_rad_s: float, max_travel_rad: float | None) -> None:
        permille, rpm = self._limit_units(max_torque_nm, max_speed_rad_s)
        self.sdo.write(MAX_TORQUE, permille)
        self.sdo.write(MAX_MOTOR_SPEED, rpm)
        if max_travel_rad is not None and POSITION_LIMIT_MIN.index in self.node.object_dictionary:
            here = int(self.sdo.read(POSITION_ACTUAL))
            span = math.floor(max_travel_rad / (2 * math.pi) * self.motor_increments)
            lo, hi = max(-(2**31), here - span), min(2**31 - 1, here + span)
            self.sdo.write(POSITION_LIMIT_MIN, lo)
            self.sdo.write(POSITION_LIMIT_MAX, hi)

    def _fault_message(self) -> str:
        try:
            code = int(self.sdo.read(ERROR_CODE))
        except DriveError:
            return "drive is in Fault state (error code unreadable)"
        return f"drive fault 0x{code:04X} ({self.description.describe_error(code)})"

    def _check_link(self) -> None:
        self.heartbeat.check()

    def _emcy_fault(self, since: int, played: int, total: int, rate_hz: float) -> None:
        errors = self.emcy.since(since)
        if errors:
            e = errors[0]
            raise DriveFault(
                f"EMCY 0x{e.code:04X} ({e.text}) from node {self.node_id} after "
                f"{played / rate_hz:.3f} s of {total / rate_hz:.3g} s",
                code=e.code,
            )

    def prepare_excitation(self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode) -> None:
        """Before enabling (sequencer hook): the trace path checks the rate and downloads the
        waveform (seconds on a slow link); the streamed path checks the band and 0x6071's range."""
        if self.method is ExcitationMethod.STREAMED:
            budget = self.budget
            assert budget is not None
            self._check_band(self.band_hz if self.band_hz is not None else waveform_band_hz(waveform, sample_rate_hz))
            if np.abs(np.round(waveform / self.rated_torque_nm * 1000)).max() > 0x7FFF:
                raise DriveError("torque waveform exceeds the range of 0x6071 (INT16 per mille of rated torque)")
            return
        self._download(waveform, sample_rate_hz, mode)

    def _download(self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode) -> None:
        """The waveform into the drive's player, unless exactly this one is there already."""
        trace = self.description.trace
        assert trace is not None
        rate = self._trace_rate_hz
        if abs(sample_rate_hz - rate) > 1e-9 * rate:
            raise ConfigError(f"drive '{self.description.name}' plays waveforms at {rate:g} Hz, not {sample_rate_hz:g} Hz")
        data = waveform_to_bus(waveform, mode, trace.waveform, self.rated_torque_nm, self.motor_increments)
        if self._downloaded != data:
            self._downloaded = None
            self.sdo.download_block(trace.waveform.samples, data)
            self._downloaded = data

    def _excite(
        self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode, progress: ProgressCallback | None
    ) -> Recording:
        self._last_partial = None
        self._excite_mode = mode
        if self.method is ExcitationMethod.STREAMED:
            return self._excite_streamed(waveform, sample_rate_hz, mode, progress)
        return self._excite_trace(waveform, sample_rate_hz, mode, progress)

    # -- primary path: waveform download, trace upload -------------------------------------------------
    def _excite_trace(
        self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode, progress: ProgressCallback | None
    ) -> Recording:
        trace = self.description.trace
        assert trace is not None
        rate = self._trace_rate_hz
        self._download(waveform, sample_rate_hz, mode)
        self._downloaded = None  # the player consumes it: a next run downloads again
        emcy_mark = len(self.emcy)
        total = waveform.size
        self._run_total = total
        self._start_time = datetime.now(timezone.utc)
        self.sdo.write(trace.start, trace.start_value)
        def read_played() -> int:
            self._check_link()  # a silent heartbeat is the cause to report, not the SDO timeout after it
            return int(self.sdo.read(trace.progress))

        self._await_playback(read_played, total, rate, progress, poll_s=POLL_S, stall_s=STALL_S,
                             on_poll=lambda played: self._emcy_fault(emcy_mark, played, total, rate))
        rec = self._upload_trace()
        if rec is None or len(rec) != total:
            raise DriveError(f"trace holds {0 if rec is None else len(rec)} samples, expected {total}")
        return rec

    def _upload_trace(self) -> Recording | None:
        trace = self.description.trace
        assert trace is not None
        length = int(self.sdo.read(trace.length))
        if length < 2 or self._start_time is None:
            return None
        rate = self._trace_rate_hz
        signals: dict[str, NDArray[np.float64]] = {}
        for name, channel in trace.channels.items():
            data, _ = self.sdo.upload_block(channel.object)
            increments = self.motor_increments if channel.encoder == "motor" else self.load_increments
            values = channel_from_bus(data, channel, rated_torque_nm=self.rated_torque_nm,
                                      increments=increments, sample_rate_hz=rate)
            signals[name] = values[:length]
        return Recording.uniform(
            rate,
            signals.pop("torque_ref"),
            signals.pop("motor_velocity"),
            start_time=self._start_time,
            drive=self._info,
            metadata={"link": f"canopen {self.interface}:{self.port} node {self.node_id}",
                      "excitation_path": "drive waveform player + trace (SDO block transfer)"},
            **signals,
        )

    # -- fallback: host-streamed cyclic synchronous torque ---------------------------------------------
    def _excite_streamed(
        self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode, progress: ProgressCallback | None
    ) -> Recording:
        if mode is not Mode.CYCLIC_SYNC_TORQUE:
            raise DriveError(f"the streamed fallback drives cyclic synchronous torque only, not {mode.name}")
        budget, streamer = self.budget, self._streamer
        assert budget is not None and streamer is not None
        self._check_band(self.band_hz if self.band_hz is not None else waveform_band_hz(waveform, sample_rate_hz))
        # hold each cycle's target: the waveform sample at the cycle's start (zero-order hold decimation)
        step = budget.cycle_s * sample_rate_hz
        picks = np.floor(np.arange(int(waveform.size / step)) * step + 1e-9).astype(np.int64)
        permille = np.round(waveform[picks] / self.rated_torque_nm * 1000)
        if np.abs(permille).max() > 0x7FFF:
            raise DriveError("torque waveform exceeds the range of 0x6071 (INT16 per mille of rated torque)")
        targets = permille.astype(np.int16)
        streamer.reset()
        emcy_mark = len(self.emcy)
        total = int(targets.size)
        self._run_total = total
        self._start_time = datetime.now(timezone.utc)

        def check(k: int) -> None:
            self._check_link()
            self._emcy_fault(emcy_mark, k, total, budget.rate_hz)
            status = streamer.feedback.statusword
            if status and decode_statusword(status[-1]) is not State.OPERATION_ENABLED:
                state = decode_statusword(status[-1])
                if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    time.sleep(0.05)  # give the EMCY a moment to arrive: it names the cause
                    self._emcy_fault(emcy_mark, k, total, budget.rate_hz)
                    raise DriveFault(f"{self._fault_message()} after {k / budget.rate_hz:.3f} s")
                raise DriveError(f"drive left 'operation enabled' during the run: it is '{state.value}'")

        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, 2e-4))  # bus threads must get the GIL within a cycle
        try:
            streamer.run(targets, budget.cycle_s, check, progress)
        finally:
            sys.setswitchinterval(switch)
            streamer.wait_feedback(len(streamer.sync_times), timeout_s=0.5)
            self.stream_report = streamer.report(budget)
        self._emcy_fault(emcy_mark, total, total, budget.rate_hz)
        rec = self._streamed_recording()
        if rec is None or len(rec) != total:
            raise DriveError(
                f"streamed run lost feedback: {0 if rec is None else len(rec)} of {total} cycles answered by TPDOs"
            )
        return rec

    def _streamed_recording(self) -> Recording | None:
        streamer, budget = self._streamer, self.budget
        if streamer is None or budget is None or self._start_time is None:
            return None
        fb = streamer.feedback
        n = min(len(streamer.sync_times), len(fb.position), len(fb.velocity))
        if n < 2:
            return None
        t_sync = np.asarray(streamer.sync_times[:n])
        per_inc = 2 * math.pi / self.motor_increments
        report = self.stream_report or streamer.report(budget)
        return Recording(
            t=t_sync - t_sync[0],
            sample_rate_hz=budget.rate_hz,
            torque_ref=np.asarray(streamer.sent_targets[:n], dtype=np.float64) * (self.rated_torque_nm / 1000),
            motor_velocity=np.asarray(fb.velocity[:n], dtype=np.float64) * per_inc,
            motor_position=np.asarray(fb.position[:n], dtype=np.float64) * per_inc,
            start_time=self._start_time,
            drive=self._info,
            metadata={
                "link": f"canopen {self.interface}:{self.port} node {self.node_id}",
                "excitation_path": "host-streamed CST (SYNC + RPDO 0x6071 + TPDOs)",
                "bus_budget": budget.describe(),
                "stream": report.describe(),
                "usable_band_hz": f"{budget.usable_band_hz:.1f}",
            },
        )

    def _recorded_so_far(self) -> Recording | None:
        if self.method is ExcitationMethod.STREAMED:
            return self._streamed_recording()
        if self._last_partial is None:
            self._last_partial = self._upload_trace()
        return self._last_partial

    # -- parameters ---------------------------------------------------------------------------------
    def read_parameter(self, name: str) -> Any:
        spec = self.description.parameters.get(name)
        if spec is None:
            return super().read_parameter(name)
        return float(self.sdo.read(spec.object)) * spec.scale

    def write_parameter(self, name: str, value: Any) -> None:
        spec = self.description.parameters.get(name)
        if spec is None:
            return super().write_parameter(name, value)
        raw = parameter_raw(spec, name, value, f"{spec.object}, drive '{self.description.name}'")
        self.sdo.write(spec.object, raw)

    # -- transfer figures (bench) ---------------------------------------------------------------------
    @property
    def transfers(self) -> list[TransferStats]:
        return self.sdo.transfers

    # -- shutdown -------------------------------------------------------------------------------------
    def _shutdown(self) -> None:
        self._release()

    def _release(self) -> None:
        if self._closed_link:
            return
        self._closed_link = True
        try:
            if getattr(self, "_host_heartbeat", None) is not None:
                try:  # disarm the drive's consumer first, or it faults when our heartbeat stops
                    self.sdo.write(CONSUMER_HEARTBEAT, 0)
                except DriveError:
                    pass
                self._host_heartbeat.stop()
            if self._streamer is not None:
                self._streamer.close()
            if self._own_network and self.network.bus is not None:
                self.network.disconnect()
        finally:
            if self._on_close is not None:
                self._on_close()


def open_simulated(
    plant: dict[str, Any] | None = None,
    *,
    device: Any = None,
    channel: str | None = None,
    node_id: int = 1,
    pace: float | None = None,
    **options: Any,
) -> CanopenDrive:
    """The simulated drive as a CANopen node on python-can's ``virtual`` bus, in this process,
    and this backend connected to it (``commission --sim --sim-link canopen``)."""
    from sim_drive.canopen_slave import CanopenSlave
    from sim_drive.device import SimulatedDevice

    from ..sim import plant_from_options

    dev = device if device is not None else SimulatedDevice(plant_from_options(plant))
    channel = channel or f"sim-canopen-{id(dev):x}"
    slave = CanopenSlave(dev, node_id=node_id, channel=channel, interface="virtual", pace=pace).start()
    try:
        return CanopenDrive(channel, interface="virtual", node_id=node_id, drive=options.pop("drive", "sim"),
                            on_close=slave.close, simulator=slave, **options)
    except BaseException:
        slave.close()
        raise
