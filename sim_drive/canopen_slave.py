"""The simulated drive as a CANopen node (CiA 301 + CiA 402) on any python-can bus.

python-canopen's ``LocalNode`` is a bare object dictionary with an SDO server;
this module adds what a drive's firmware does around it:

* an SDO server with **block transfer** (CiA 301 §7.2.4.3.9–16: CRC-16/XMODEM,
  block size 127), which ``LocalNode``'s server lacks;
* NMT: boot-up, heartbeat producer (0x1017), heartbeat consumer of the host
  (0x1016: the drive faults with 0x8130 and brakes when the host falls silent),
  PDO mapping reloaded on entering Operational;
* CiA 402 through the objects: controlword writes drive the device's state
  machine, statusword/mode/error code are read from it; limits 0x6072, 0x6080,
  0x607D in bus units;
* EMCY on every fault the device enters (and an error reset when it is acknowledged);
* the waveform player and trace buffer at 0x2100–0x2111 (``drivers/sim``);
* PDOs on SYNC: synchronous RPDOs applied and synchronous TPDOs sent at each SYNC
  (``LocalNode`` does neither), for host-streamed cyclic synchronous torque;
* the drive's own cycle clock as SYNC producer (0x1005 bit 30, period 0x1006,
  counter 0x1019), the way a drive that keeps time does it;
* what a real bus and adapter add: frames lost at random (``frame_loss``), other
  nodes' traffic (``bus_load``), and an identity (0x1018) to pose as another drive;
* test hooks: lose the link, stall one object's SDO answers, refuse a command.

Time: the waveform player runs in its own thread, as fast as the plant computes
(``pace=None``) or at ``pace`` × real time. In cyclic operation the plant runs
exactly one communication cycle (0x1006, or 0x60C2) per SYNC the drive produces,
whenever the host's frames arrive: a setpoint that arrived after its SYNC is
not applied, the previous one is held, and the TPDO (0x6077) says which torque
was applied. When the simulation itself falls behind (its thread was not
scheduled: a real drive's clock never is), its clock slips rather than produce
the missed cycles back to back: the host still gets a whole cycle to answer
each SYNC, as from a drive on time, and the plant still runs one cycle per SYNC
(slips counted in :attr:`CanopenSlave.clock_slips`, beyond ``SLIP_AFTER`` of a cycle).
Likewise a cycle waits for frames that are on the virtual bus but not yet taken by
the node's receive thread (``RX_CATCH_UP_S`` at most): a drive has them at once. With the host as SYNC producer the plant runs
as many 8 kHz ticks per SYNC as the SYNC timestamps say elapsed
(``sync_clock="timestamps"``, like a drive whose clock follows SYNC), or the
nominal cycle 0x60C2 (``sync_clock="nominal"``).
"""

from __future__ import annotations

import binascii
import logging
import math
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import canopen
import numpy as np
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError, SdoServer
from canopen.sdo.constants import (
    ABORT_CRC_ERROR,
    ABORT_INVALID_BLOCK_SIZE,
    ABORT_INVALID_COMMAND_SPECIFIER,
    ABORT_OUT_OF_MEMORY,
    REQUEST_ABORTED,
    REQUEST_BLOCK_DOWNLOAD,
    REQUEST_BLOCK_UPLOAD,
    RESPONSE_BLOCK_DOWNLOAD,
    RESPONSE_BLOCK_UPLOAD,
    SDO_STRUCT,
)

from commission.drive.cia402 import Command, Mode, State, decode_controlword

from .device import ErrorCode, SimulatedDevice

__all__ = ["BlockSdoServer", "CanopenSlave", "sim_eds_path"]

logger = logging.getLogger(__name__)

ABORT_VALUE_RANGE = 0x06090030
ABORT_DEVICE_STATE = 0x08000022
SYNC_COB_ID = 0x080
#: 0x1005 bit 30: this node produces SYNC
SYNC_PRODUCER_BIT = 1 << 30
#: a simulated clock later than this fraction of a cycle slips instead of bursting the missed cycles
SLIP_AFTER = 0.5
#: longest the simulated clock waits for frames its own receive thread has not taken yet [s]
RX_CATCH_UP_S = 0.02
#: COB-ID of the other nodes' traffic the ``bus_load`` option puts on the bus (not a CiA 301 service)
BACKGROUND_COB_ID = 0x7F0
#: Bytes per trace/waveform sample on the bus (INT32).
SAMPLE_BYTES = 4
#: Torque unit of the waveform and the trace, as a fraction of the rated torque (drivers/sim:
#: 6.4 nN·m on the default drive; the INT32 range is ±21 × rated).
TORQUE_UNIT = 1e-8


def sim_eds_path() -> Path:
    """The simulated drive's EDS (``drivers/sim/sim.eds``)."""
    from commission.drive.description import load_description

    return load_description("sim").eds_path


# -- SDO server with block transfer ----------------------------------------------------------
class BlockSdoServer(SdoServer):
    """``canopen.SdoServer`` plus block download and block upload (server side).

    :param size_check: called with (index, subindex, size) at a block download's
        initiation; raise :class:`SdoAbortedError` to refuse (e.g. out of memory).
    """

    BLKSIZE = 127
    #: a block transfer silent for this long is over (the client gave up without an abort
    #: frame, as canopen's stream does when it raises on close) [s]
    BLOCK_TIMEOUT_S = 0.5

    def __init__(self, rx_cobid: int, tx_cobid: int, node: canopen.LocalNode,
                 size_check: Callable[[int, int, int], None] | None = None) -> None:
        super().__init__(rx_cobid, tx_cobid, node)
        self.size_check = size_check
        self._mode: Literal["idle", "down", "down_end", "up", "up_end"] = "idle"
        self._block = bytearray()
        self._seq = 0
        self._data = b""
        self._pos = 0
        self._blk_start = 0
        self._blksize = self.BLKSIZE
        self._crc = False
        #: frames this server sent and received during block transfers (for the bench)
        self.frames_out = 0
        self.frames_in = 0
        #: object indices whose requests are ignored (test hook: a stalled firmware)
        self.stalled: set[int] = set()
        self.muted = False
        self._last_frame_s = 0.0

    def on_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.muted:
            return
        self.frames_in += 1
        if self._mode != "idle" and timestamp - self._last_frame_s > self.BLOCK_TIMEOUT_S:
            self._mode = "idle"  # the SDO protocol timeout of a real server
        self._last_frame_s = timestamp
        command = data[0]
        if command == REQUEST_ABORTED or (self._mode != "down" and command & 0xE0 == REQUEST_ABORTED):
            self._mode = "idle"  # in a sub-block only 0x80 (sequence number 0) is an abort
            return super().on_request(can_id, data, timestamp)
        try:
            if self._mode == "down":
                return self._download_segment(data)
            if self._mode == "down_end" and command & 0xE3 == REQUEST_BLOCK_DOWNLOAD | 1:
                return self._download_end(data)
            if command & 0xE0 == REQUEST_BLOCK_UPLOAD and self._mode in ("up", "up_end"):
                return self._upload_command(data)
            _, index, _ = SDO_STRUCT.unpack_from(data)
            if index in self.stalled and command & 0xE0 in (0x20, 0x40, REQUEST_BLOCK_UPLOAD, REQUEST_BLOCK_DOWNLOAD):
                return
            self._mode = "idle"
            return super().on_request(can_id, data, timestamp)
        except SdoAbortedError as exc:
            self._mode = "idle"
            self.abort(exc.code)
        except Exception as exc:  # an application error aborts the transfer, like LocalNode does
            self._mode = "idle"
            logger.exception("SDO server: %s", exc)
            self.abort()

    def send_response(self, response: bytes | bytearray) -> None:
        self.frames_out += 1
        super().send_response(response)

    # download: initiate -> sub-blocks of up to 127 segments, acked -> end with CRC
    def block_download(self, data: bytearray) -> None:
        command, index, subindex = SDO_STRUCT.unpack_from(data)
        self._index, self._subindex = index, subindex
        if command & 0x01:  # cs 1 would be an end without a transfer
            raise SdoAbortedError(ABORT_INVALID_COMMAND_SPECIFIER)
        self._node._find_object(index, subindex)  # noqa: SLF001 - abort 0x0602/0x0609 as LocalNode does
        size = struct.unpack_from("<L", data, 4)[0] if command & 0x02 else None
        if size is not None and self.size_check is not None:
            self.size_check(index, subindex, size)
        self._crc = bool(command & 0x04)
        self._block = bytearray()
        self._seq = 0
        self._mode = "down"
        response = bytearray(8)
        SDO_STRUCT.pack_into(response, 0, RESPONSE_BLOCK_DOWNLOAD | 0x04, index, subindex)
        response[4] = self.BLKSIZE
        self.send_response(response)

    def _download_segment(self, data: bytearray) -> None:
        seq = data[0] & 0x7F
        last = bool(data[0] & 0x80)
        if seq == self._seq + 1:
            self._seq = seq
            self._block.extend(data[1:8])
        # else: out of sequence, ignored; the ack tells the client where to resume
        if seq == self.BLKSIZE or last:
            if last and seq == self._seq:
                self._mode = "down_end"
            self.send_response(bytes([RESPONSE_BLOCK_DOWNLOAD | 0x02, self._seq, self.BLKSIZE, 0, 0, 0, 0, 0]))
            self._seq = 0

    def _download_end(self, data: bytearray) -> None:
        unused = (data[0] >> 2) & 0x07
        payload = bytes(self._block[: len(self._block) - unused])
        self._mode = "idle"
        if self._crc:
            crc = struct.unpack_from("<H", data, 1)[0]
            if crc != binascii.crc_hqx(payload, 0):
                raise SdoAbortedError(ABORT_CRC_ERROR)
        self._node.set_data(self._index, self._subindex, payload, check_writable=True)
        self.send_response(bytes([RESPONSE_BLOCK_DOWNLOAD | 0x01, 0, 0, 0, 0, 0, 0, 0]))

    # upload: initiate (size) -> start -> sub-blocks, acked -> end with CRC -> client's end
    def block_upload(self, data: bytearray) -> None:
        command, index, subindex = SDO_STRUCT.unpack_from(data)
        self._index, self._subindex = index, subindex
        if command & 0x03 != 0:
            raise SdoAbortedError(ABORT_INVALID_COMMAND_SPECIFIER)
        blksize = data[4]
        if not 0 < blksize <= 127:
            raise SdoAbortedError(ABORT_INVALID_BLOCK_SIZE)
        self._data = bytes(self._node.get_data(index, subindex, check_readable=True))
        self._crc = bool(command & 0x04)
        self._blksize = blksize
        self._pos = self._blk_start = 0
        self._mode = "up"
        response = bytearray(8)
        SDO_STRUCT.pack_into(response, 0, RESPONSE_BLOCK_UPLOAD | 0x04 | 0x02, index, subindex)
        struct.pack_into("<L", response, 4, len(self._data))
        self.send_response(response)

    def _upload_command(self, data: bytearray) -> None:
        cs = data[0] & 0x03
        if cs == 3 and self._mode == "up":  # start
            self._send_block()
        elif cs == 2 and self._mode == "up":  # block ack
            ackseq, blksize = data[1], data[2]
            self._pos = min(self._blk_start + 7 * ackseq, len(self._data))
            if blksize:
                self._blksize = blksize
            if self._pos >= len(self._data) and ackseq > 0:
                self._mode = "up_end"
                unused = (7 - len(self._data) % 7) % 7 if self._data else 7
                crc = binascii.crc_hqx(self._data, 0) if self._crc else 0
                self.send_response(struct.pack("<BHxxxxx", RESPONSE_BLOCK_UPLOAD | (unused << 2) | 0x01, crc))
            else:
                self._send_block()
        elif cs == 1 and self._mode == "up_end":  # client's end
            self._mode = "idle"
        elif cs == 0:  # a new initiation: the client gave up the previous transfer
            self.block_upload(data)
        else:
            self._mode = "idle"
            raise SdoAbortedError(ABORT_INVALID_COMMAND_SPECIFIER)

    def _send_block(self) -> None:
        self._blk_start = self._pos
        pos = self._pos
        for seq in range(1, self._blksize + 1):
            chunk = self._data[pos : pos + 7]
            pos += 7
            last = pos >= len(self._data)
            self.send_response(bytes([seq | (0x80 if last else 0)]) + chunk.ljust(7, b"\0"))
            if last:
                break


class _DriveNode(canopen.LocalNode):
    """LocalNode whose SDO server does block transfers."""

    def __init__(self, node_id: int, od: canopen.ObjectDictionary | str,
                 size_check: Callable[[int, int, int], None]) -> None:
        super().__init__(node_id, od)
        self.sdo = BlockSdoServer(0x600 + self.id, 0x580 + self.id, self, size_check)


def _warm_up(device: SimulatedDevice) -> None:
    """Compile (or load from numba's cache) the plant's loops before the node is on the bus:
    a first-call compile inside an SDO answer would exceed the client's timeout."""
    from .plant import Plant

    plant = Plant(device.plant_parameters, device.sample_rate_hz)
    plant.run_torque(np.zeros(2))
    plant.run_velocity(np.zeros(2), device.velocity_kp, device.velocity_ki, device.max_torque_nm)


# -- the drive behind the node -----------------------------------------------------------------
class CanopenSlave:
    """A :class:`~sim_drive.device.SimulatedDevice` as a CiA 402 node on a python-can bus.

    :param device: the simulated drive.
    :param node_id: CANopen node id (1–127).
    :param channel: python-can channel (``vcan0``, or a name for the ``virtual`` interface).
    :param interface: python-can interface (``virtual``, ``socketcan``, …).
    :param pace: waveform playback speed as a multiple of real time; None: as fast as possible.
    :param sync_clock: cyclic mode with the host's SYNC: ticks per SYNC from the SYNC timestamps or
        the nominal 0x60C2.
    :param frame_loss: probability that a cyclic frame (SYNC, TPDO out; RPDO in) is lost.
    :param bus_load: other nodes' traffic as a fraction of ``bitrate_bps`` (8-byte frames).
    :param bitrate_bps: the bus bit rate the ``bus_load`` is a fraction of.
    :param identity: (vendor id, product code, device name) to report in 0x1018 / 0x1008 instead
        of the simulated drive's own: a drive of another family.
    :param seed: seed of the frame-loss draws.
    :param eds: object dictionary (default ``drivers/sim/sim.eds``).
    :param bus_options: more keyword arguments for ``can.Bus`` (e.g. bitrate).
    """

    CHUNK_SAMPLES = 200

    def __init__(
        self,
        device: SimulatedDevice | None = None,
        *,
        node_id: int = 1,
        channel: str = "sim",
        interface: str = "virtual",
        pace: float | None = None,
        sync_clock: Literal["timestamps", "nominal"] = "timestamps",
        frame_loss: float = 0.0,
        bus_load: float = 0.0,
        bitrate_bps: int = 1_000_000,
        identity: tuple[int, int, str] | None = None,
        seed: int = 0,
        eds: str | Path | None = None,
        **bus_options: Any,
    ) -> None:
        if not 0.0 <= frame_loss < 1.0 or not 0.0 <= bus_load < 1.0:
            raise ValueError("frame_loss and bus_load must be in [0, 1)")
        if not 1 <= node_id <= 127:
            raise ValueError("node id must be 1..127")
        self.device = device if device is not None else SimulatedDevice()
        self.node_id = node_id
        self.pace = pace
        self.sync_clock = sync_clock
        self._lock = threading.RLock()
        self.node = _DriveNode(node_id, str(eds or sim_eds_path()), self._check_download_size)
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.1  # the receive thread's longest wait: a quick close
        self._bus_args = {"channel": channel, "interface": interface, **bus_options}
        self._player: threading.Thread | None = None
        self._stop = threading.Event()
        self._closing = threading.Event()
        self._raw_wave = np.zeros(0, dtype=np.int32)
        self._last_error = ErrorCode.NONE
        self._limits = [self.device.max_torque_nm, self.device.max_speed_rad_s, None]
        self._pos_limits: list[int | None] = [None, None]
        self.refused: set[Command] = set()
        # cyclic operation
        self._rpdos: dict[int, list[tuple[int, int, struct.Struct]]] = {}
        self._tpdos: list[tuple[int, int, list[tuple[int, int]], struct.Struct]] = []
        self._pending: dict[tuple[int, int], float] = {}
        self._applied_torque_nm = 0.0
        self._sync_count = 0
        self._first_sync: float | None = None
        self._ticks_done = 0
        self.sync_errors = 0
        self.frame_loss = float(frame_loss)
        self.bus_load = float(bus_load)
        self.bitrate_bps = int(bitrate_bps)
        self.identity = identity
        # one stream of draws per direction: the receive thread (RPDOs) and the clock (SYNC, TPDOs) draw
        # concurrently, and one shared generator would make the loss pattern depend on thread timing
        self._loss_rng = {incoming: np.random.default_rng(s) for incoming, s in
                          zip((True, False), np.random.SeedSequence(seed).spawn(2))}
        self._loss_lock = threading.Lock()
        # the drive's own clock (SYNC producer)
        self._clock: threading.Thread | None = None
        self._clock_stop = threading.Event()
        self._background: threading.Thread | None = None
        self._rpdo_fresh = False
        #: cycles the drive produced, cycles whose setpoint arrived too late (the previous one held),
        #: frames dropped by ``frame_loss``, and slips of the simulated clock (for tests and the bench)
        self.cycles_produced = 0
        self.held_cycles = 0
        self.frames_dropped = 0
        self.clock_slips = 0
        self.clock_lag_max_s = 0.0
        # heartbeat consumer 0x1016: the host's heartbeat, watched by the drive itself
        self._consumer: tuple[int, float] | None = None  # (host node id, timeout s)
        self._host_last: float | None = None
        self._watchdog: threading.Thread | None = None
        #: drive tick (1 / sample rate) at which each SYNC latched its TPDO values, and the torque [N·m]
        #: applied from it on (what its TPDO's 0x6077 says, lost or not), for tests
        self.sync_ticks: list[int] = []
        self.applied_nm: list[float] = []
        self._install_callbacks()
        self._set_constants()

    # -- set-up --------------------------------------------------------------------------------
    def _od(self, index: int, subindex: int = 0) -> ODVariable:
        obj = self.node.object_dictionary[index]
        return obj if isinstance(obj, ODVariable) else obj[subindex]

    def _store(self, index: int, subindex: int, value: Any) -> None:
        self.node.data_store.setdefault(index, {})[subindex] = self._od(index, subindex).encode_raw(value)

    def _set_constants(self) -> None:
        dev = self.device
        p = dev.plant_parameters
        self._motor_inc = 2 ** p.encoder_bits_motor
        self._load_inc = 2 ** p.encoder_bits_load
        self._store(0x6076, 0, int(round(dev.rated_torque_nm * 1000)))
        self._store(0x608F, 1, self._motor_inc)
        self._store(0x608F, 2, 1)
        self._store(0x2111, 0, self._load_inc)
        self._store(0x2100, 2, int(round(1e9 / dev.sample_rate_hz)))
        self._store(0x2100, 3, dev.trace_capacity)
        self._store(0x1008, 0, dev.product)
        serial = int("".join(c for c in dev.serial_number if c.isdigit()) or "0")
        self._store(0x1018, 4, serial)
        self._store(0x6072, 0, int(dev.max_torque_nm / dev.rated_torque_nm * 1000))
        self._store(0x6080, 0, int(dev.max_speed_rad_s * 60 / (2 * math.pi)))
        if self.identity is not None:
            vendor_id, product_code, name = self.identity
            self._store(0x1018, 1, int(vendor_id))
            self._store(0x1018, 2, int(product_code))
            self._store(0x1008, 0, str(name))

    def _install_callbacks(self) -> None:
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)

    def start(self) -> CanopenSlave:
        """Connect to the bus and boot: boot-up message, Pre-operational, heartbeat."""
        _warm_up(self.device)
        self.network.connect(**self._bus_args)
        self.network.add_node(self.node)
        self.network.subscribe(0, self._on_nmt)
        self.network.subscribe(0x80, self._on_sync)
        self.node.nmt.send_command(0x81)  # INITIALISING: boot-up message
        self.node.nmt.send_command(0x80)  # PRE-OPERATIONAL: heartbeat starts (0x1017)
        if self.bus_load > 0:
            self._background = threading.Thread(target=self._other_nodes, name=f"sim-drive-{self.node_id}-load",
                                                daemon=True)
            self._background.start()
        return self

    def close(self) -> None:
        """Stop playing, stop the heartbeat and leave the bus. Safe to call twice."""
        self._stop.set()
        self._closing.set()
        self._stop_clock()
        if self._background is not None:
            self._background.join(timeout=1)
        if self._watchdog is not None:
            self._watchdog.join(timeout=1)
        if self._player is not None:
            self._player.join(timeout=5)
        self.node.nmt.stop_heartbeat()
        if self.network.bus is not None:
            self.network.disconnect()

    def __enter__(self) -> CanopenSlave:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- test hooks ------------------------------------------------------------------------------
    def lose_link(self) -> None:
        """The node falls silent: no heartbeat, no SDO answers, no PDOs (cable pulled)."""
        self.node.sdo.muted = True
        self.node.nmt.stop_heartbeat()
        self._tpdos = []
        self._stop_clock(join=False)  # may run under the lock (a fault seen by the clock itself)

    def stall_sdo(self, index: int) -> None:
        """Requests for ``index`` are never answered (heartbeat and other objects continue)."""
        self.node.sdo.stalled.add(index)

    def refuse(self, command: Command) -> None:
        """Ignore this CiA 402 command (e.g. main power missing: SWITCH_ON does nothing)."""
        self.refused.add(command)

    # -- object access ---------------------------------------------------------------------------
    def _on_read(self, index: int, subindex: int, od: ODVariable) -> Any:
        dev = self.device
        # single attributes: answered without the lock, so the bus never waits for a plant chunk
        if index == 0x6041:
            return dev.statusword
        if index == 0x603F:
            return int(dev.error_code)
        if index == 0x1001:
            return 0x01 if dev.error_code is not ErrorCode.NONE else 0x00
        if index == 0x6061:
            return int(dev.mode)
        if index == 0x2102:
            return dev.progress[0]
        if index == 0x2103:
            return dev.trace_length
        with self._lock:
            if index == 0x6064:
                return self._counts(self._last_sample("motor_position"), self._motor_inc)
            if index == 0x606C:
                return self._counts(self._last_sample("motor_velocity"), self._motor_inc)
            if index == 0x6077:
                return int(round(self._applied_torque_nm / dev.rated_torque_nm * 1000))
            if index == 0x2000:
                return dev.velocity_kp
            if index == 0x2001:
                return dev.velocity_ki
            if index == 0x2110:
                return self._trace_bytes(subindex)
        return None

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        dev = self.device
        if od.data_type == canopen.objectdictionary.DOMAIN:
            value: Any = bytes(data)
        else:
            value = od.decode_raw(data)
        with self._lock:
            if index == 0x6040:
                command = decode_controlword(value)
                if command in self.refused:
                    return
                dev.write_controlword(value)
                self._check_fault()
            elif index == 0x6060:
                try:
                    dev.write_mode(Mode(value))
                except (ValueError, RuntimeError) as err:
                    raise SdoAbortedError(ABORT_VALUE_RANGE) from err
            elif index == 0x6072:
                self._limits[0] = value / 1000 * dev.rated_torque_nm
                self._apply_limits()
            elif index == 0x6080:
                self._limits[1] = value * 2 * math.pi / 60
                self._apply_limits()
            elif index == 0x607D:
                self._pos_limits[subindex - 1] = value
                lo, hi = self._pos_limits
                if lo is not None and hi is not None:
                    here = self._counts(self._last_sample("motor_position"), self._motor_inc)
                    self._limits[2] = max(0, min(hi - here, here - lo)) * 2 * math.pi / self._motor_inc
                    self._apply_limits()
            elif index == 0x1016:
                self._configure_consumer(int(value))
            elif index in (0x1005, 0x1006, 0x1019):
                self._on_sync_config(index, int(value))
            elif index == 0x2000:
                dev.velocity_kp = float(value)
            elif index == 0x2001:
                dev.velocity_ki = float(value)
            elif index == 0x2100 and subindex == 1:
                if len(value) % SAMPLE_BYTES:
                    raise SdoAbortedError(0x06070010)
                self._raw_wave = np.frombuffer(value, dtype="<i4").copy()
            elif index == 0x2101:
                if value == 1:
                    self._start_player()
                else:
                    self._stop_player()

    # -- heartbeat consumer (0x1016): the drive stops itself when the host falls silent ---------------
    def _configure_consumer(self, entry: int) -> None:
        host, time_ms = (entry >> 16) & 0x7F, entry & 0xFFFF
        if self._consumer is not None:
            try:
                self.network.unsubscribe(0x700 + self._consumer[0], self._on_host_heartbeat)
            except (KeyError, ValueError):
                pass
        self._consumer, self._host_last = None, None
        if host and time_ms:
            self._consumer = (host, time_ms / 1000)
            self.network.subscribe(0x700 + host, self._on_host_heartbeat)
            if self._watchdog is None:
                self._watchdog = threading.Thread(target=self._watch_host, name=f"sim-drive-{self.node_id}-hb",
                                                  daemon=True)
                self._watchdog.start()

    def _on_host_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._host_last = time.monotonic()

    def _watch_host(self) -> None:
        while not self._closing.wait(0.02):
            consumer, last = self._consumer, self._host_last
            if consumer is None or last is None or time.monotonic() - last <= consumer[1]:
                continue
            # this process may not have been scheduled: let its receive thread take what is queued first
            self._closing.wait(0.1)
            consumer, last = self._consumer, self._host_last
            if consumer is None or last is None or time.monotonic() - last <= consumer[1]:
                continue
            with self._lock:
                self._consumer = None  # one fault per silence; the host re-arms 0x1016 when it returns
                if self.device.state is not State.FAULT:
                    self.device.trip(ErrorCode.COMMUNICATION)
                self._check_fault()

    def _check_download_size(self, index: int, subindex: int, size: int) -> None:
        if (index, subindex) == (0x2100, 1) and size > SAMPLE_BYTES * self.device.trace_capacity:
            raise SdoAbortedError(ABORT_OUT_OF_MEMORY)

    def _apply_limits(self) -> None:
        torque, speed, travel = self._limits
        self.device.set_limits(float(torque), float(speed), travel)

    @staticmethod
    def _counts(value_si: float, increments: int) -> int:
        return int(round(value_si * increments / (2 * math.pi)))

    def _last_sample(self, name: str) -> float:
        sample = self.device._last_cyclic  # noqa: SLF001 - same package
        if sample is not None:
            return float(getattr(sample, name))
        tr_len = self.device.trace_length
        if tr_len:
            return float(getattr(self.device.trace(), name)[-1])
        return 0.0

    # -- faults -----------------------------------------------------------------------------------
    def _check_fault(self) -> None:
        """EMCY when the device's error code changes (a new fault, or its reset)."""
        code = self.device.error_code
        if code is self._last_error:
            return
        self._last_error = code
        if self.device.communication_lost:
            self.lose_link()
            return
        if self.node.sdo.muted:
            return
        if code is ErrorCode.NONE:
            self.node.emcy.reset()
        else:
            self.node.emcy.send(int(code), 0x01, struct.pack("<H", int(code)) + b"\0\0\0")

    # -- waveform player and trace ---------------------------------------------------------------
    def _wave_si(self) -> np.ndarray:
        dev = self.device
        raw = self._raw_wave.astype(np.float64)
        if dev.mode is Mode.CYCLIC_SYNC_TORQUE:
            return raw * (TORQUE_UNIT * dev.rated_torque_nm)
        return raw * (2 * math.pi / self._motor_inc)

    def _start_player(self) -> None:
        dev = self.device
        if self._player is not None and self._player.is_alive():
            raise SdoAbortedError(ABORT_DEVICE_STATE)
        try:
            dev.load_waveform(self._wave_si())
            dev.start()
        except (ValueError, RuntimeError) as err:
            raise SdoAbortedError(ABORT_DEVICE_STATE) from err
        self._stop.clear()
        self._player = threading.Thread(target=self._play, name=f"sim-drive-{self.node_id}-player", daemon=True)
        self._player.start()

    def _stop_player(self) -> None:
        self._stop.set()

    def _play(self) -> None:
        dev = self.device
        t0 = time.perf_counter()
        while not self._stop.is_set():
            with self._lock:
                if not dev.playing:
                    break
                dev.advance(self.CHUNK_SAMPLES)
                played = dev.progress[0]
                self._check_fault()
            if self.pace:
                ahead = t0 + played / dev.sample_rate_hz / self.pace - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)
            else:
                # a real pause, not sleep(0): the lock is not fair, and the bus thread waiting
                # for it (an SDO read of the progress) would starve
                time.sleep(0.0002)
        with self._lock:
            self._check_fault()

    def _trace_bytes(self, subindex: int) -> bytes:
        dev = self.device
        tr = dev.trace()
        ts = 1.0 / dev.sample_rate_hz
        if subindex == 1:
            raw = np.round(tr.torque_ref / (TORQUE_UNIT * dev.rated_torque_nm))
        elif subindex in (2, 4):
            inc = self._motor_inc if subindex == 2 else self._load_inc
            pos = tr.motor_position if subindex == 2 else tr.load_position
            raw = np.round(pos * inc / (2 * math.pi))
        elif subindex in (3, 5):
            inc = self._motor_inc if subindex == 3 else self._load_inc
            vel = tr.motor_velocity if subindex == 3 else tr.load_velocity
            raw = np.round(vel * ts * inc / (2 * math.pi))
        else:
            raise SdoAbortedError(0x06090011)
        if raw.size == 0:
            raise SdoAbortedError(0x08000024)  # no data available
        return raw.astype(np.int64).astype("<i4").tobytes()  # positions wrap modulo 2**32, as on a drive

    # -- NMT and PDOs -------------------------------------------------------------------------------
    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id) or self.node.sdo.muted:
            return
        if data[0] == 0x01:  # start: the master has configured the PDOs
            try:
                self._load_pdo_config()
            except (SdoAbortedError, KeyError, struct.error):  # a bad mapping: no PDOs (the notifier would swallow it)
                self.sync_errors += 1
                logger.exception("sim drive: invalid PDO mapping")
                self._rpdos, self._tpdos = {}, []
        elif data[0] in (0x02, 0x80):
            self._rpdos, self._tpdos = {}, []
        elif data[0] in (0x81, 0x82):
            self._rpdos, self._tpdos = {}, []
            self.node.nmt.send_command(0x81)
            self.node.nmt.send_command(0x80)

    def _raw(self, index: int, subindex: int) -> int:
        return int(self._od(index, subindex).decode_raw(self.node.get_data(index, subindex)))

    def _mapping(self, map_index: int) -> tuple[list[tuple[int, int]], struct.Struct]:
        entries: list[tuple[int, int]] = []
        fmt = "<"
        for k in range(1, self._raw(map_index, 0) + 1):
            value = self._raw(map_index, k)
            index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
            od = self._od(index, subindex)
            fmt += od.STRUCT_TYPES[od.data_type].format.lstrip("<")
            if bits != len(od):
                raise SdoAbortedError(0x06040043)
            entries.append((index, subindex))
        return entries, struct.Struct(fmt)

    def _load_pdo_config(self) -> None:
        rpdos: dict[int, list[tuple[int, int, struct.Struct]]] = {}
        tpdos = []
        for n in range(4):
            if 0x1400 + n in self.node.object_dictionary:
                cob = self._raw(0x1400 + n, 1)
                if not cob & 0x8000_0000:
                    entries, st = self._mapping(0x1600 + n)
                    rpdos[cob & 0x7FF] = [(i, s, st) for i, s in entries]
                    self.network.subscribe(cob & 0x7FF, self._on_rpdo)
            if 0x1800 + n in self.node.object_dictionary:
                cob = self._raw(0x1800 + n, 1)
                trans = self._raw(0x1800 + n, 2)
                if not cob & 0x8000_0000 and 1 <= trans <= 240:
                    entries, st = self._mapping(0x1A00 + n)
                    tpdos.append((cob & 0x7FF, trans, entries, st))
        with self._lock:
            self._rpdos, self._tpdos = rpdos, tpdos
            self._sync_count = 0
            self._first_sync = None
            self._ticks_done = 0
            self.sync_ticks = []
            self.applied_nm = []

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        layout = self._rpdos.get(can_id)
        if not layout or self.node.sdo.muted or self._lost(incoming=True):
            return
        values = layout[0][2].unpack_from(bytes(data).ljust(layout[0][2].size, b"\0"))
        with self._lock:
            for (index, subindex, _), value in zip(layout, values):
                self._pending[(index, subindex)] = value
            self._rpdo_fresh = True

    def _lost(self, incoming: bool = False) -> bool:
        """One draw of ``frame_loss`` from the direction's own stream: True if this frame is lost on the bus."""
        if self.frame_loss <= 0:
            return False
        with self._loss_lock:
            if self._loss_rng[incoming].random() >= self.frame_loss:
                return False
            self.frames_dropped += 1
        return True

    def _cycle_ticks(self) -> int:
        """Drive ticks per communication cycle: 0x1006 when set (SYNC producer), else 0x60C2."""
        period_us = self._raw(0x1006, 0) if 0x1006 in self.node.object_dictionary else 0
        if period_us:
            return max(1, int(round(period_us * 1e-6 * self.device.sample_rate_hz)))
        try:
            value, exponent = self._raw(0x60C2, 1), self._raw(0x60C2, 2)
        except (SdoAbortedError, KeyError):
            return 1
        return max(1, int(round(value * 10.0**exponent * self.device.sample_rate_hz)))

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self._tpdos or self.node.sdo.muted or self._clock is not None:
            return  # a SYNC producer ignores other SYNCs
        try:
            self._sync(timestamp)
        except Exception:  # an exception here would be swallowed by the notifier: count it
            self.sync_errors += 1
            logger.exception("sim drive: error on SYNC")

    def _sync(self, timestamp: float) -> None:
        """A SYNC from the host: the plant runs to the tick it falls on (timestamps) or one nominal cycle."""
        dev = self.device
        with self._lock:
            if self._first_sync is None:
                self._first_sync = timestamp
            # the tick this SYNC falls on: the plant runs up to it and latches at its start
            if self.sync_clock == "timestamps":
                at_tick = int(round((timestamp - self._first_sync) * dev.sample_rate_hz))
            else:
                at_tick = self._sync_count * self._cycle_ticks()
            ticks = max(1, at_tick - self._ticks_done + 1)
            frames = self._cycle(ticks)
        self._send_cyclic(frames)

    def _cycle(self, ticks: int) -> list[tuple[int, bytes]]:
        """One communication cycle boundary (lock held): apply the setpoint that arrived in time, run
        the plant ``ticks`` ticks to this boundary, latch; returns the TPDO frames to send."""
        dev = self.device
        self._ticks_done += ticks
        self.sync_ticks.append(self._ticks_done - 1)
        if not self._rpdo_fresh and self._sync_count > 0:
            self.held_cycles += 1
        self._rpdo_fresh = False
        command = self._pending.pop((0x6040, 0), None)
        if command is not None:
            dev.write_controlword(int(command))
        target = self._pending.get((0x6071, 0), 0)
        new_torque = float(target) / 1000 * dev.rated_torque_nm
        if dev.state is State.OPERATION_ENABLED and dev.mode is Mode.CYCLIC_SYNC_TORQUE:
            refs = np.full(ticks, self._applied_torque_nm)
            refs[-1] = new_torque
            dev.step_cyclic(refs)
            self._applied_torque_nm = new_torque if dev.state is State.OPERATION_ENABLED else 0.0
        else:
            self._applied_torque_nm = 0.0
        self.applied_nm.append(self._applied_torque_nm)
        self._check_fault()
        self._sync_count += 1
        frames = []
        for cob, trans, entries, st in self._tpdos:
            if self._sync_count % trans == 0:
                frames.append((cob, st.pack(*(self._pdo_value(i, s) for i, s in entries))))
        return frames

    def _send_cyclic(self, frames: list[tuple[int, bytes]]) -> None:
        for cob, payload in frames:
            if not self.node.sdo.muted and not self._lost():
                self.network.send_message(cob, payload)

    # -- the drive's own clock: SYNC producer (0x1005 bit 30) -----------------------------------------
    def _on_sync_config(self, index: int, value: int) -> None:
        """0x1005 / 0x1006 / 0x1019 written (lock held): start or stop the SYNC producer."""
        if index == 0x1019 and self._raw(0x1006, 0) != 0:
            raise SdoAbortedError(ABORT_DEVICE_STATE)  # CiA 301: only while the cycle period is 0
        if index == 0x1005 and value & 0x7FF != SYNC_COB_ID:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        self._store(index, 0, value)  # before the clock thread reads it (LocalNode stores after this call)
        if self._raw(0x1005, 0) & SYNC_PRODUCER_BIT and self._raw(0x1006, 0) > 0:
            self._start_clock()
        else:
            self._clock_stop.set()  # the thread ends before its next cycle

    def _start_clock(self) -> None:
        if self._clock is not None and self._clock.is_alive() and not self._clock_stop.is_set():
            return
        # a stopped clock thread ends by itself at its next cycle (it checks its own event under the
        # lock, which the caller holds): joining it here would wait for that lock
        self._clock_stop = threading.Event()
        self._clock = threading.Thread(target=self._produce, args=(self._clock_stop,),
                                       name=f"sim-drive-{self.node_id}-clock", daemon=True)
        self._clock.start()

    def _stop_clock(self, join: bool = True) -> None:
        """Stop producing SYNC; ``join`` waits for the thread (never while holding the lock)."""
        self._clock_stop.set()
        clock = self._clock
        if join and clock is not None and clock is not threading.current_thread():
            clock.join(timeout=1)
        self._clock = None

    def _produce(self, stop: threading.Event) -> None:
        """SYNC, then the TPDOs, every cycle on the drive's clock; the plant runs one cycle per SYNC."""
        with self._lock:
            ticks = self._cycle_ticks()
            overflow = self._raw(0x1019, 0) if 0x1019 in self.node.object_dictionary else 0
            self._sync_count = 0
            self._ticks_done = 0
            self.sync_ticks = []
            self.applied_nm = []
        period = ticks / self.device.sample_rate_hz
        counter = 0
        due = time.perf_counter()
        first = True
        while not stop.is_set():
            now = time.perf_counter()
            if now < due:
                time.sleep(due - now)
                continue
            if self._receiving(until=now + RX_CATCH_UP_S):
                continue  # frames wait in this process, not on the bus: a drive would have them already
            lag = now - due
            self.clock_lag_max_s = max(self.clock_lag_max_s, lag)
            if lag > SLIP_AFTER * period:
                self.clock_slips += 1
                due = now
            try:
                with self._lock:
                    if stop.is_set():
                        break
                    frames = self._cycle(1 if first else ticks)
                    self.cycles_produced += 1
                first = False
                counter = counter % overflow + 1 if overflow >= 2 else 0
                if not self.node.sdo.muted and not self._lost():
                    self.network.send_message(SYNC_COB_ID, bytes([counter]) if overflow >= 2 else b"")
                self._send_cyclic(frames)
            except Exception:  # a thread's exception would be lost: count it, stop producing
                self.sync_errors += 1
                logger.exception("sim drive: error in the SYNC producer")
                return
            due += period

    def _receiving(self, until: float) -> bool:
        """True while frames that reached this node's bus wait for its receive thread (and until
        ``until``): the simulation, not the bus, is behind, so its clock waits for them (a drive's
        controller has a frame the moment it is on the bus)."""
        queue = getattr(self.network.bus, "queue", None)  # python-can's virtual bus
        if queue is None or queue.qsize() == 0 or time.perf_counter() > until:
            return False
        time.sleep(0.0001)
        return True

    def _other_nodes(self) -> None:
        """Other nodes' traffic: 8-byte frames at ``bus_load`` of the bit rate, in 1 ms bursts."""
        from commission.drive.canopen.pdo import frame_bits

        per_s = self.bus_load * self.bitrate_bps / frame_bits(8)
        sent, t0 = 0, time.perf_counter()
        while not self._closing.wait(0.001):
            due = int((time.perf_counter() - t0) * per_s)
            while sent < due and self.network.bus is not None:
                self.network.send_message(BACKGROUND_COB_ID, sent.to_bytes(8, "little"))
                sent += 1

    def _pdo_value(self, index: int, subindex: int) -> int:
        value = self._on_read(index, subindex, self._od(index, subindex))
        if value is None:
            value = self._raw(index, subindex)
        return int(value)
