"""The CANopen CiA 402 backend: :class:`CanopenDrive`.

Bring-up (at construction, before anything moves): connect the bus, find the
node (SDO 0x1000 device type, profile 402), read its identity (0x1018, 0x1008,
0x100A) and pick the drive description it matches when none was given (a given
one that does not match the identity is refused), pre-operational, heartbeat producer time 0x1017 and our heartbeat
consumer, our own heartbeat and the drive's consumer of it (0x1016), EMCY listener, unit scaling (0x6076 rated torque, 0x608F encoder
resolution), and for the streamed fallback the bus budget and the PDO mapping;
then NMT start.

Excitation, by the drive description's ``excitation``:

* ``trace`` (primary): SDO block download of the waveform, start, poll progress
  (heartbeat and EMCY watched), SDO block upload of every trace channel, a
  uniform Recording at the drive's clock;
* ``streamed`` (fallback): on the drive's clock (it produces SYNC with a counter),
  the host answers each SYNC with the next target torque (per mille of rated,
  0x6071) and the drive answers with position, applied torque and statusword
  (:mod:`.pdo`), at the highest rate the bus budget allows; the Recording is on the
  drive's cycle grid, with the torque the drive applied and lost cycles marked
  (``lost_samples``); lost, late and jitter figures in
  :attr:`CanopenDrive.stream_report` and the Recording's metadata.
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
from ...recording import LOST_SAMPLES_KEY, MAX_GAP_S, MAX_LOST_FRACTION, DriveInfo, Recording, encode_samples
from ..base import Drive, ProgressCallback
from ..cia402 import Mode, State, decode_statusword
from ..description import (
    GENERIC_DRIVE,
    DriveDescription,
    ExcitationMethod,
    ObjectRef,
    find_description,
    load_description,
    parameter_raw,
)
from .emcy import EmcyListener
from .nmt import HeartbeatConsumer, NmtCommand, send_nmt
from .pdo import (
    STREAM_FRAMES,
    SYNC_COB_ID,
    SYNC_COUNTER_OVERFLOW,
    BusBudget,
    StreamReport,
    SyncedStream,
    frame_bits,
    interpolation_period,
    plan_cycle,
    record_signals,
    slcan_line_bytes,
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
SYNC_COB = ObjectRef(index=0x1005)
CYCLE_PERIOD = ObjectRef(index=0x1006)
SYNC_OVERFLOW = ObjectRef(index=0x1019)
#: 0x1005 bit 30: the node produces SYNC
SYNC_PRODUCER = 1 << 30

#: longest wait of the receive thread, so closing the link takes no more than this
NOTIFIER_CYCLE_S = 0.1
#: seconds between progress polls during a trace run
POLL_S = 0.02
#: a trace run whose progress stays unchanged this long (beyond its duration) is a timeout
STALL_S = 2.0
#: seconds of bus traffic listened to before planning the streamed cycle (other nodes' load)
LISTEN_S = 0.2
#: A streamed run fails when more of its cycles were lost than recording.MAX_LOST_FRACTION, or the link was
#: silent longer than recording.MAX_GAP_S in one piece (the record is then mostly guessed) ...
#: ... or when late setpoints paused the excitation for more than this fraction of its length: the host then
#: answered fewer than half of the SYNCs in time, and the played chirp is a slower one (a narrower band).
#: Pauses as such cost no accuracy while the record says what was applied (bench_streamed.py measures it).
MAX_STRETCH = 1.0
#: the record holds at most this many times the planned cycles (a run that needs more has failed anyway)
MAX_CYCLES_FACTOR = 3
#: a drive whose SYNCs stay away this long (and four heartbeat consumer times) has stopped keeping the cycle
#: [s]. Not a safety limit (the heartbeats are): a loaded host may itself not read the bus for a while.
SYNC_SILENCE_S = 2.0


class CanopenDrive(Drive):
    """A CiA 402 drive on a CANopen bus.

    :param port: CAN channel (``can0``; for the virtual interface, any name).
    :param interface: python-can interface (default ``socketcan``).
    :param bitrate: bit rate [bit/s] for the adapter and the bus budget (default: the description's).
    :param node_id: the drive's node id (default: the description's).
    :param drive: drive description name under drivers/ or a loaded one; None: the one whose identity
        (0x1018) matches the drive, else ``generic-cia402``.
    :param excitation: ``trace`` or ``streamed`` to override the description's method.
    :param band_hz: excitation band the streamed path must cover (else estimated from the waveform).
    :param allow_narrow_band: stream even when the bus cannot cover the band (the usable band is reported).
    :param max_rate_hz: the highest streamed cycle rate to use (``--rate``), below what the bus allows.
    :param line_bps: an slcan adapter's serial line [bit/s], when it is a UART of known speed: the
        streamed cycle must fit it too.
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
        max_rate_hz: float | None = None,
        line_bps: float | None = None,
        network: canopen.Network | None = None,
        on_close: Callable[[], None] | None = None,
        simulator: Any = None,
        **bus_options: Any,
    ) -> None:
        super().__init__()
        #: True when the description is to be picked from the drive's identity
        self.auto_description = drive is None
        self._excitation_asked = excitation
        self._adopt(drive if isinstance(drive, DriveDescription) else load_description(drive or GENERIC_DRIVE))
        desc = self.description
        self.node_id = node_id or desc.node_id
        if not 1 <= self.node_id <= 127:
            raise ConfigError(f"node id must be 1..127, not {self.node_id}")
        self.interface = interface or "socketcan"
        self.port = port or ""
        self.bitrate = int(bitrate or desc.bitrate)
        self.band_hz = band_hz
        self.allow_narrow_band = allow_narrow_band
        self.max_rate_hz = max_rate_hz
        self.line_bps = line_bps
        #: what 0x1018 reported: vendor_id, product_code, revision, serial
        self.identity: dict[str, Any] = {}
        self._on_close = on_close
        self.simulator = simulator
        self._own_network = network is None
        self.stream_report: StreamReport | None = None
        self.budget: BusBudget | None = None
        self._streamer: SyncedStream | None = None
        self._sync_producer = False
        self._background_bps = 0.0
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

    #: least SDO timeout [s] and heartbeat consumer time [ms] of the link (an slcan adapter needs more)
    MIN_SDO_TIMEOUT_S = 0.0
    MIN_HEARTBEAT_TIMEOUT_MS = 0

    def _adopt(self, desc: DriveDescription) -> None:
        """Use ``desc`` (with this link's least timeouts) and the excitation method it allows."""
        self.description = desc.model_copy(update={
            "sdo_timeout_s": max(desc.sdo_timeout_s, self.MIN_SDO_TIMEOUT_S),
            "heartbeat_timeout_ms": max(desc.heartbeat_timeout_ms, self.MIN_HEARTBEAT_TIMEOUT_MS),
        })
        excitation = self._excitation_asked
        try:
            self.method = ExcitationMethod(excitation) if excitation is not None else desc.excitation
        except ValueError:
            raise ConfigError(f"excitation must be 'trace' or 'streamed', not '{excitation}'") from None
        if self.method is ExcitationMethod.TRACE and desc.trace is None:
            raise ConfigError(f"drive '{desc.name}' has no trace buffer: use the streamed excitation")

    def _no_node(self, err: Exception) -> DriveNotFound:
        heard = sorted(set(self.network.scanner.nodes) - {self.node_id})
        hint = f"; nodes heard on the bus: {', '.join(map(str, heard))}" if heard else ""
        return DriveNotFound(
            f"no CANopen node answers at node id {self.node_id} on {self.interface}:{self.port} "
            f"(no SDO response to 0x1000 within {self.description.sdo_timeout_s:g} s){hint}"
        )

    def _raw_identity(self) -> tuple[int | None, int | None]:
        """0x1018:01 vendor id and :02 product code by plain SDO uploads (no description needed yet)."""
        node = canopen.RemoteNode(self.node_id, canopen.ObjectDictionary())
        self.network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = self.description.sdo_timeout_s
        try:
            try:
                node.sdo.upload(0x1000, 0)
            except canopen.SdoCommunicationError as err:
                raise self._no_node(err) from err
            except canopen.SdoAbortedError:
                pass
            values: list[int | None] = []
            for sub in (1, 2):
                try:
                    values.append(int.from_bytes(node.sdo.upload(0x1018, sub)[:4], "little"))
                except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
                    values.append(None)
        finally:
            node.remove_network()
            self.network.nodes.pop(self.node_id, None)
        return values[0], values[1]

    def _pick_description(self) -> None:
        """No --drive: the description that claims this drive's identity, else the generic one."""
        vendor_id, product_code = self._raw_identity()
        found = find_description(vendor_id, product_code)
        self._adopt(found if found is not None else load_description(GENERIC_DRIVE))
        self.detected = (vendor_id, product_code)

    def _check_identity(self) -> None:
        """A given --drive whose identity is not this drive's: refused before anything moves."""
        spec = self.description.identity
        vendor_id, product_code = self.identity.get("vendor_id"), self.identity.get("product_code")
        if spec is None or self.auto_description or spec.matches(vendor_id, product_code):
            return
        other = find_description(vendor_id, product_code)
        hint = (f"it is a '{other.name}' drive: use --drive {other.name}" if other is not None
                else f"use --drive {GENERIC_DRIVE}")
        shown = "none" if vendor_id is None else f"0x{vendor_id:08X}"
        shown_p = "none" if product_code is None else f"0x{product_code:X}"
        raise ConfigError(
            f"node {self.node_id} is not a '{self.description.name}' drive: its identity (0x1018) is vendor "
            f"{shown}, product {shown_p}, expected {spec.describe()}; {hint}, or omit --drive to pick the "
            "description from the identity")

    # -- bring-up ---------------------------------------------------------------------------------
    def _bring_up(self) -> None:
        if self.auto_description:
            self._pick_description()
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
            raise self._no_node(err) from err
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
        self._check_identity()
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
        claimed = self.description.identity is not None and self.description.identity.vendor_id == vendor_id
        # a generic description's EDS names no vendor ("any"): then only the drive's own id says who it is
        vendor = (self.node.object_dictionary.device_information.vendor_name or "") if claimed else ""
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
            vendor=vendor if vendor_id is None else f"{vendor} (0x{vendor_id:08X})" if vendor else f"vendor 0x{vendor_id:08X}",
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
    def _listen_bps(self, seconds: float) -> float:
        """Bits per second of the traffic on the bus that is not ours or this node's (worst-case bits)."""
        ours = {0x000, SYNC_COB_ID, 0x700 + self.node_id, 0x580 + self.node_id, 0x600 + self.node_id,
                0x080 + self.node_id}
        bits = [0]

        class Counter(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                if msg.arbitration_id not in ours and not (0x700 <= msg.arbitration_id < 0x780):
                    bits[0] += frame_bits(min(8, msg.dlc), msg.is_extended_id)

        listener = Counter()
        notifier = self.network.notifier
        if notifier is None:
            return 0.0
        notifier.add_listener(listener)
        try:
            time.sleep(seconds)
        finally:
            notifier.remove_listener(listener)
        return bits[0] / seconds

    def _plan_stream(self) -> None:
        desc = self.description
        heartbeat_bps = 2 * frame_bits(1) / (desc.heartbeat_ms / 1000)  # the drive's and ours
        self._background_bps = self._listen_bps(LISTEN_S)
        # adapter to host: SYNC + TPDO lines, and the adapter's "z" for the host's RPDO
        line_bytes = slcan_line_bytes(STREAM_FRAMES[0]) + slcan_line_bytes(STREAM_FRAMES[2]) + 2
        try:
            self.budget = plan_cycle(self.bitrate, STREAM_FRAMES, 1.0 / desc.drive_sample_rate_hz,
                                     max_load=desc.streamed.max_load,
                                     background_bps=heartbeat_bps + self._background_bps,
                                     line_bps=self.line_bps, line_bytes_per_cycle=line_bytes,
                                     max_rate_hz=self.max_rate_hz)
        except ValueError as err:
            raise DriveError(f"no streamed cycle fits the link: {err} (other traffic "
                             f"{self._background_bps / 1e3:.0f} kbit/s of {self.bitrate / 1e3:g} kbit/s)") from err
        if self.band_hz is not None:
            self._check_band(self.band_hz)

    def _check_band(self, band_hz: float, what: str = "the excitation band") -> None:
        assert self.budget is not None
        if band_hz > self.budget.usable_band_hz * (1 + 1e-9) and not self.allow_narrow_band:
            raise ConfigError(
                f"the link allows {self.budget.describe()}, below {what} {band_hz:.0f} Hz: "
                "use a higher bit rate, a drive with a trace buffer, a lower f_end_hz, or --allow-narrow-band "
                "(the chirp then ends at the usable band)"
            )

    def _configure_pdos(self) -> None:
        """RPDO: 0x6071; TPDO: 0x6064 + 0x6077 + 0x6041; both synchronous (type 1); the drive's SYNC
        producer prepared (counter 0x1019, period 0x1006), started only for the run."""
        spec = self.description.streamed
        assert self.budget is not None
        try:
            rpdo = self.node.rpdo[spec.rpdo]
            tpdo = self.node.tpdo[spec.tpdo]
            for pdo_map, objects, cob in (
                (rpdo, (0x6071,), 0x200 + 0x100 * (spec.rpdo - 1) + self.node_id),
                (tpdo, (0x6064, 0x6077, 0x6041), 0x180 + 0x100 * (spec.tpdo - 1) + self.node_id),
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
        # the PdoMap subscribed itself; our streamer reads the frames instead
        try:
            self.network.unsubscribe(tpdo.cob_id, tpdo.on_message)
        except (KeyError, ValueError):
            pass
        period = interpolation_period(self.budget.cycle_s)
        if period is not None and INTERPOLATION_PERIOD.index in self.node.object_dictionary:
            self.sdo.write(INTERPOLATION_PERIOD, period[0])
            self.sdo.write(INTERPOLATION_INDEX, period[1])
        self._prepare_sync_producer()
        self._streamer = SyncedStream(self.network, rpdo.cob_id, tpdo.cob_id, self.budget.cycle_s,
                                      self._sync_overflow)

    def _prepare_sync_producer(self) -> None:
        """The drive keeps the cycle: counter overflow (0x1019, written while 0x1006 is 0), period 0x1006.
        A drive without these objects cannot: the host cannot keep 0.5 ms deadlines, so it is refused."""
        assert self.budget is not None
        od = self.node.object_dictionary
        missing = [f"0x{i:04X}" for i in (SYNC_COB.index, CYCLE_PERIOD.index) if i not in od]
        if missing:
            raise DriveError(
                f"drive '{self.description.name}' cannot keep the streamed cycle itself (no {', '.join(missing)} "
                "in its object dictionary): a host cannot keep sub-millisecond deadlines; use a drive with a trace "
                "buffer or one that produces SYNC")
        period_us = int(round(self.budget.cycle_s * 1e6))
        try:
            self.sdo.write(SYNC_COB, SYNC_COB_ID)  # producer off while configuring
            self.sdo.write(CYCLE_PERIOD, 0)
            self._sync_overflow = 0
            if SYNC_OVERFLOW.index in od:
                try:
                    self.sdo.write(SYNC_OVERFLOW, SYNC_COUNTER_OVERFLOW)
                    self._sync_overflow = SYNC_COUNTER_OVERFLOW
                except DriveError:
                    self._sync_overflow = 0  # SYNCs without a counter: cycles are counted on arrival
            self.sdo.write(CYCLE_PERIOD, period_us)
        except DriveError as err:
            raise DriveError(f"node {self.node_id} refused to keep a {period_us} us cycle (0x1006/0x1019): {err}") from err
        try:  # that it will produce SYNC, now, before anything moves (no PDO runs before NMT start)
            self._sync_producer_on(True)
            self._sync_producer_on(False)
        except DriveError as err:
            raise DriveError(
                f"node {self.node_id} will not produce SYNC (0x1005 bit 30): {err}; streaming needs the drive to keep "
                "the cycle (a host cannot keep sub-millisecond deadlines): use a drive with a trace buffer") from err

    def _sync_producer_on(self, on: bool) -> None:
        self.sdo.write(SYNC_COB, SYNC_COB_ID | (SYNC_PRODUCER if on else 0))
        self._sync_producer = on

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

    # -- fallback: host-streamed cyclic synchronous torque, on the drive's clock -----------------------
    def streamed_targets(self, waveform: NDArray[np.float64], sample_rate_hz: float) -> NDArray[np.float64]:
        """The torque [N·m] the streamed run plays, one per cycle: each cycle's first waveform sample
        (zero-order hold decimation), rounded to 0x6071's per mille of the rated torque."""
        assert self.budget is not None
        step = self.budget.cycle_s * sample_rate_hz
        picks = np.floor(np.arange(int(waveform.size / step)) * step + 1e-9).astype(np.int64)
        return np.round(waveform[picks] / self.rated_torque_nm * 1000) * (self.rated_torque_nm / 1000)

    def _excite_streamed(
        self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode, progress: ProgressCallback | None
    ) -> Recording:
        if mode is not Mode.CYCLIC_SYNC_TORQUE:
            raise DriveError(f"the streamed fallback drives cyclic synchronous torque only, not {mode.name}")
        budget, streamer = self.budget, self._streamer
        assert budget is not None and streamer is not None
        played = self.streamed_targets(waveform, sample_rate_hz)
        # the band of what the drive will actually play, not of the configuration
        self._check_band(waveform_band_hz(played, budget.rate_hz), "the band of the waveform to play")
        permille = np.round(played / self.rated_torque_nm * 1000)
        if np.abs(permille).max() > 0x7FFF:
            raise DriveError("torque waveform exceeds the range of 0x6071 (INT16 per mille of rated torque)")
        targets = permille.astype(np.int16)
        emcy_mark = len(self.emcy)
        total = int(targets.size)
        rate = budget.rate_hz
        self._run_total = total
        self._start_time = datetime.now(timezone.utc)
        self.stream_report = None
        silence_s = max(SYNC_SILENCE_S, 4 * self.description.heartbeat_timeout_ms / 1000)

        started = time.monotonic()

        def check() -> None:
            k = streamer.samples_done
            heard = streamer.last_tpdo_monotonic
            if heard is None or time.monotonic() - heard > self.heartbeat.timeout_s:
                # the node's TPDOs every cycle show it alive: a heartbeat dropped or delayed among them by an
                # overrun adapter or a host behind its bus is not a lost link
                self._check_link()
            self._emcy_fault(emcy_mark, k, total, rate)
            state = decode_statusword(streamer.last_status) if streamer.last_status else State.OPERATION_ENABLED
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                time.sleep(0.05)  # give the EMCY a moment to arrive: it names the cause
                self._emcy_fault(emcy_mark, k, total, rate)
                raise DriveFault(f"{self._fault_message()} after {k / rate:.3f} s")
            if state is not State.OPERATION_ENABLED:
                raise DriveError(f"drive left 'operation enabled' during the run: it is '{state.value}'")
            heard = streamer.last_tpdo_monotonic
            if heard is None and time.monotonic() - started > silence_s:
                raise DriveError(f"the drive keeps the cycle but sends no TPDO (0x1800 + {self.description.streamed.tpdo - 1}"
                                 f"): the host has nothing to answer; check the drive's PDO mapping")
            last = streamer.last_sync_monotonic
            if last is None or time.monotonic() - last > silence_s:
                link = "the slcan adapter's serial line" if self.interface == "slcan" else "the bus"
                raise DriveTimeout(
                    f"no SYNC reached the host for {time.monotonic() - (last or 0):.2f} s (after {k / rate:.3f} s of "
                    f"{total / rate:.3g} s): the drive stopped keeping the cycle, or {link} or this host cannot "
                    f"carry the {rate:.0f} Hz cycle; try --rate {rate / 2:.0f}")

        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, 2e-4))  # the notifier thread must get the GIL within a cycle
        streamer.arm(targets, MAX_CYCLES_FACTOR * total)
        try:
            started = time.monotonic()
            self._sync_producer_on(True)
            streamer.last_sync_monotonic = time.monotonic()
            deadline = started + total / rate * MAX_CYCLES_FACTOR + 5.0
            while not streamer.wait(POLL_S):
                check()
                if progress is not None:
                    progress(int(streamer.samples_done * sample_rate_hz / rate), waveform.size)
                if time.monotonic() > deadline:
                    raise DriveTimeout(f"the streamed run did not end: {streamer.samples_done} of {total} setpoints "
                                       f"played after {time.monotonic() - started:.1f} s")
        finally:
            streamer.disarm()
            sys.setswitchinterval(switch)
            try:
                self._sync_producer_on(False)
            except DriveError:
                pass  # the link may be gone; the drive's watchdog stops it
            self.stream_report = streamer.report(budget)
        self._emcy_fault(emcy_mark, total, total, rate)
        report = self.stream_report
        if streamer.last_target_cycle is None:
            raise DriveError(
                f"the host played {streamer.samples_done} of {total} setpoints in {MAX_CYCLES_FACTOR * total} cycles: "
                f"it cannot stream at {rate:.0f} Hz; try --rate {rate / 2:.0f} or a drive with a trace")
        self._check_stream(report)
        rec = self._streamed_recording()
        if rec is None or len(rec) < total:
            raise DriveError(f"streamed run recorded {0 if rec is None else len(rec)} cycles for {total} setpoints")
        return rec

    def _check_stream(self, report: StreamReport) -> None:
        """A run whose record is mostly guessed, or whose excitation was not played, fails with its cause."""
        rate = report.planned_rate_hz
        lower = f"--rate {rate / 2:.0f}"
        if report.lost_fraction > MAX_LOST_FRACTION or report.longest_gap_cycles / rate > MAX_GAP_S:
            via = "the slcan adapter's serial line" if self.interface == "slcan" else "the bus"
            raise DriveError(
                f"{report.lost_fraction:.0%} of cycles lost (longest gap {report.longest_gap_cycles / rate * 1e3:.0f} ms): "
                f"{via} or this host did not carry the {rate:.0f} Hz cycle's feedback; try {lower}"
            )
        if report.stretch > MAX_STRETCH:
            raise DriveError(
                f"{report.pause_cycles / report.cycles:.0%} of cycles late (the drive held the setpoint, the chirp "
                f"took {1 + report.stretch:.1f}x its length): this host cannot stream at {rate:.0f} Hz (longest pause "
                f"{report.longest_pause_cycles / rate * 1e3:.0f} ms); try {lower} or a drive with a trace"
            )

    def _streamed_recording(self) -> Recording | None:
        """The record on the drive's cycle grid: what the drive measured and applied, lost cycles
        interpolated (positions) or as intended (torque), and marked."""
        streamer, budget = self._streamer, self.budget
        if streamer is None or budget is None or self._start_time is None:
            return None
        rec = streamer.record
        received = rec.received & ~rec.ambiguous
        n = streamer.samples()
        if n < 2 or received[1 : n + 1].sum() < 2:
            return None
        rate = budget.rate_hz
        torque, velocity, position, lost = record_signals(
            rec.position, rec.torque, rec.meant()[1 : n + 1], received, rate, self.rated_torque_nm, self.motor_increments)
        report = self.stream_report or streamer.report(budget)
        metadata = {
            "link": f"canopen {self.interface}:{self.port} node {self.node_id}",
            "excitation_path": "host-streamed CST on the drive's clock (drive SYNC + counter, RPDO 0x6071, "
                               "TPDO 0x6064 + 0x6077 + 0x6041)",
            "sample_clock": "the drive's cycle counter (SYNC producer 0x1005); torque is what the drive "
                            "applied (0x6077); velocity is the position difference per cycle",
            "bus_budget": budget.describe(),
            "stream": report.describe(),
            "usable_band_hz": f"{budget.usable_band_hz:.1f}",
            "paused_samples": str(report.pause_cycles),
        }
        if lost.any():
            metadata[LOST_SAMPLES_KEY] = encode_samples(lost)
        return Recording.uniform(
            rate, torque, velocity, motor_position=position, start_time=self._start_time, drive=self._info,
            metadata=metadata,
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
            if self._sync_producer:
                try:
                    self._sync_producer_on(False)
                except DriveError:
                    pass
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
    link: dict[str, Any] | None = None,
    **options: Any,
) -> CanopenDrive:
    """The simulated drive as a CANopen node on python-can's ``virtual`` bus, in this process,
    and this backend connected to it (``commission --sim --sim-link canopen``).

    :param link: more options of the simulated node (:class:`~sim_drive.canopen_slave.CanopenSlave`:
        ``frame_loss``, ``bus_load``, ``identity``, …).
    """
    from sim_drive.canopen_slave import CanopenSlave
    from sim_drive.device import SimulatedDevice

    from ..sim import plant_from_options

    dev = device if device is not None else SimulatedDevice(plant_from_options(plant))
    channel = channel or f"sim-canopen-{id(dev):x}"
    slave = CanopenSlave(dev, node_id=node_id, channel=channel, interface="virtual", pace=pace,
                         **(link or {})).start()
    try:
        return CanopenDrive(channel, interface="virtual", node_id=node_id, drive=options.pop("drive", "sim"),
                            on_close=slave.close, simulator=slave, **options)
    except BaseException:
        slave.close()
        raise
