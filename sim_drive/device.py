"""Drive behaviour around the simulated plant: what a servo drive does, at 8 kHz.

The device is protocol-neutral: a CANopen node, a Modbus server or the direct
``sim`` backend all drive it through the same few calls, the way a drive's
firmware sits under its fieldbus stack:

* CiA 402 state machine: controlword in, statusword out, error code (0x603F);
* modes cyclic synchronous torque (CST) and velocity (CSV, with the drive's own
  PI velocity loop);
* a waveform player and a trace buffer, clocked by the drive's own 8 kHz;
* torque, speed and travel limits that trip a fault; a fault reaction that
  brakes (velocity loop to zero) or, without an encoder, lets the axis coast;
* fault injection for tests: drive fault, encoder fault, loss of communication.

Time only advances inside :meth:`SimulatedDevice.advance` (and the braking of a
stop), so a test or a fieldbus front-end decides how fast the drive runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, IntEnum

import numpy as np
from numpy.typing import NDArray

from commission.drive.cia402 import (
    STATUS_BITS,
    STATUS_TARGET_REACHED,
    Command,
    Mode,
    State,
    decode_controlword,
    next_state,
)

from .plant import Plant, PlantParameters, PlantResponse


class ErrorCode(IntEnum):
    """Error codes the device reports in 0x603F (CiA 402 / CiA 301 EMCY classes)."""

    NONE = 0x0000
    DRIVE_HARDWARE = 0x5000
    OVERCURRENT = 0x2310  # torque reference beyond the torque limit
    COMMUNICATION = 0x8130  # heartbeat / life guard lost
    OVERSPEED = 0x8400
    POSITION_LIMIT = 0x8612
    ENCODER = 0x7305

    @property
    def text(self) -> str:
        return _ERROR_TEXT[self]


_ERROR_TEXT = {
    ErrorCode.NONE: "no error",
    ErrorCode.DRIVE_HARDWARE: "drive hardware fault",
    ErrorCode.OVERCURRENT: "torque reference above the torque limit",
    ErrorCode.COMMUNICATION: "communication lost (heartbeat timeout)",
    ErrorCode.OVERSPEED: "motor speed above the speed limit",
    ErrorCode.POSITION_LIMIT: "motor position outside the travel limit",
    ErrorCode.ENCODER: "encoder fault",
}


class InjectedFault(Enum):
    """Faults a test can inject."""

    DRIVE_FAULT = "drive"
    ENCODER_FAULT = "encoder"
    COMMUNICATION_LOSS = "communication"
    SOFTWARE_ERROR = "exception"
    """A bug: :meth:`SimulatedDevice.advance` raises :class:`InjectedError` with the drive still
    enabled and its player armed, as an unexpected exception from a backend would."""


class InjectedError(RuntimeError):
    """The exception of :attr:`InjectedFault.SOFTWARE_ERROR`."""


@dataclass(frozen=True)
class Trace:
    """The trace buffer's content, arrays of shape (N,)."""

    torque_ref: NDArray[np.float64]  # N·m, the reference applied at each tick
    motor_position: NDArray[np.float64]  # rad
    motor_velocity: NDArray[np.float64]  # rad/s
    load_position: NDArray[np.float64]  # rad
    load_velocity: NDArray[np.float64]  # rad/s

    def __len__(self) -> int:
        return int(self.torque_ref.shape[0])


_TRACE_SIGNALS = ("torque_ref", "motor_position", "motor_velocity", "load_position", "load_velocity")


@dataclass(frozen=True)
class CyclicSample:
    """What the drive latches at one cycle of host-streamed operation (SI units)."""

    motor_position: float  # rad, encoder-quantised
    motor_velocity: float  # rad/s, (q[k] - q[k-1]) / Ts at the drive's tick
    load_position: float  # rad
    load_velocity: float  # rad/s
    torque_nm: float  # torque reference applied from this instant on (0 unless enabled)


class SimulatedDevice:
    """A CiA 402 servo drive with a two-mass + backlash axis behind it.

    :param plant: the mechanics (defaults: the paper's torsion test machine).
    :param sample_rate_hz: the drive's control and trace rate [Hz].
    :param rated_torque_nm: motor rated torque [N·m] (0x6076).
    :param velocity_kp: velocity-loop proportional gain [N·m·s/rad] (CSV mode and braking).
    :param velocity_ki: velocity-loop integral gain [N·m/rad].
    :param trace_capacity: samples the trace buffer holds.
    """

    vendor = "drive-commission"
    product = "simulated two-mass drive"

    def __init__(
        self,
        plant: PlantParameters | None = None,
        *,
        sample_rate_hz: float = 8000.0,
        rated_torque_nm: float = 0.637,
        velocity_kp: float = 0.12,
        velocity_ki: float = 4.0,
        trace_capacity: int = 8000 * 60,
        serial_number: str = "SIM-0001",
    ) -> None:
        self.plant_parameters = plant or PlantParameters()
        self.sample_rate_hz = float(sample_rate_hz)
        self.rated_torque_nm = float(rated_torque_nm)
        self.velocity_kp = float(velocity_kp)
        self.velocity_ki = float(velocity_ki)
        self.trace_capacity = int(trace_capacity)
        self.serial_number = serial_number
        self.max_torque_nm = 3.0 * self.rated_torque_nm
        self.max_speed_rad_s = 600.0
        self.max_travel_rad = float("inf")
        self._travel_origin_rad = 0.0
        self._plant = Plant(self.plant_parameters, self.sample_rate_hz)
        self._state = State.SWITCH_ON_DISABLED
        self._mode = Mode.CYCLIC_SYNC_TORQUE
        self._error = ErrorCode.NONE
        self._last_controlword = 0
        self._waveform: NDArray[np.float64] | None = None
        self._played = 0
        self._playing = False
        self._trace = {name: np.zeros(0) for name in _TRACE_SIGNALS}
        self._trace_len = 0
        self._pending: dict[InjectedFault, int] = {}
        self.communication_lost = False
        self.samples_run = 0  # every sample the plant has run, for tests
        self._cyclic_ticks = 0  # ticks run by step_cyclic (host-streamed operation)
        self._last_cyclic: CyclicSample | None = None

    # -- CiA 402 -----------------------------------------------------------------------
    @property
    def state(self) -> State:
        return self._state

    @property
    def statusword(self) -> int:
        word = STATUS_BITS[self._state]
        if not self._playing:
            word |= STATUS_TARGET_REACHED
        return word

    @property
    def error_code(self) -> ErrorCode:
        return self._error

    @property
    def mode(self) -> Mode:
        return self._mode

    def write_mode(self, mode: Mode) -> None:
        """Modes of operation (0x6060); CST and CSV are supported, changes refused while playing."""
        mode = Mode(mode)
        if mode not in (Mode.CYCLIC_SYNC_TORQUE, Mode.CYCLIC_SYNC_VELOCITY):
            raise ValueError(f"mode {mode.name} is not supported by the simulated drive")
        if self._playing:
            raise RuntimeError("cannot change mode while a waveform plays")
        self._mode = mode

    def write_controlword(self, controlword: int) -> None:
        """Controlword (0x6040): applies the CiA 402 transition it commands."""
        command = decode_controlword(controlword)
        rising_reset = bool(controlword & 0x80) and not (self._last_controlword & 0x80)
        self._last_controlword = controlword
        if command is Command.FAULT_RESET and not rising_reset:
            return
        if command is Command.FAULT_RESET and self._state is State.FAULT:
            self._error = ErrorCode.NONE
        new = next_state(self._state, command)
        if self._state is State.OPERATION_ENABLED and new is not State.OPERATION_ENABLED:
            self._stop_playing()
        if new is State.QUICK_STOP_ACTIVE:
            self._brake()
            new = State.SWITCH_ON_DISABLED  # quick stop option code 2: stop, then switch on disabled
        self._state = new

    # -- limits --------------------------------------------------------------------------
    def set_limits(self, max_torque_nm: float, max_speed_rad_s: float, max_travel_rad: float | None = None) -> None:
        """Max torque (0x6072), max motor speed (0x6080) and a software travel limit (0x607D)
        around the present motor position, in SI units."""
        self.max_torque_nm = float(max_torque_nm)
        self.max_speed_rad_s = float(max_speed_rad_s)
        if max_travel_rad is not None:
            self.max_travel_rad = float(max_travel_rad)
            self._travel_origin_rad = self._plant.state.x_m

    # -- waveform player and trace ----------------------------------------------------------
    def load_waveform(self, samples: NDArray[np.float64]) -> None:
        """Download a waveform: torque [N·m] in CST, velocity [rad/s] in CSV, one per tick."""
        wave = np.asarray(samples, dtype=np.float64)
        if wave.ndim != 1 or wave.size == 0:
            raise ValueError("waveform must be a non-empty 1-D array")
        if wave.size > self.trace_capacity:
            raise ValueError(f"waveform of {wave.size} samples exceeds the trace capacity of {self.trace_capacity}")
        if self._playing:
            raise RuntimeError("a waveform is playing")
        self._waveform = wave.copy()

    def start(self) -> None:
        """Arm the trace and start playing the loaded waveform from its first sample."""
        if self._state is not State.OPERATION_ENABLED:
            raise RuntimeError(f"cannot start in state '{self._state.value}'")
        if self._waveform is None:
            raise RuntimeError("no waveform loaded")
        n = self._waveform.size
        self._trace = {name: np.empty(n) for name in _TRACE_SIGNALS}
        self._trace_len = 0
        self._played = 0
        self._playing = True

    @property
    def playing(self) -> bool:
        return self._playing

    @property
    def progress(self) -> tuple[int, int]:
        """(samples played, samples in the waveform)."""
        return self._played, 0 if self._waveform is None else self._waveform.size

    @property
    def trace_length(self) -> int:
        """Samples in the trace buffer (recorded since the last start)."""
        return self._trace_len

    def trace(self) -> Trace:
        """Everything traced since the last start (a copy)."""
        n = self._trace_len
        return Trace(**{name: arr[:n].copy() for name, arr in self._trace.items()})

    def inject_fault(self, kind: InjectedFault, at_sample: int | None = None) -> None:
        """Inject a fault now, or when playback reaches ``at_sample``."""
        if at_sample is None or (self._playing and at_sample <= self._played):
            self._trigger(kind)
        else:
            self._pending[kind] = int(at_sample)

    def advance(self, max_samples: int) -> int:
        """Play up to ``max_samples`` ticks of the waveform; returns how many were played."""
        if not self._playing or self._waveform is None:
            return 0
        start = self._played
        stop = min(start + int(max_samples), self._waveform.size)
        for kind, at in list(self._pending.items()):
            if at <= start:
                self._trigger(kind)
                return 0
            stop = min(stop, at)
        chunk = self._waveform[start:stop]
        fault: ErrorCode | None = None
        if self._mode is Mode.CYCLIC_SYNC_TORQUE:
            over = np.flatnonzero(np.abs(chunk) > self.max_torque_nm)
            if over.size:  # the torque limit trips before the offending sample is applied
                chunk, fault = chunk[: over[0]], ErrorCode.OVERCURRENT
        snapshot = self._plant.snapshot()
        response = self._play(chunk)
        n = 0 if response is None else len(response.motor_velocity)
        if response is not None:
            n, limit_fault = self._check_response(response)
            if limit_fault is not None:
                # the limit tripped at tick n-1: replay only up to it, so the fault
                # reaction starts from the state the drive saw when it tripped
                self._plant.restore(snapshot)
                response = self._play(chunk[:n])
                fault = limit_fault
            self._record(response, n)
        self.samples_run += 0 if response is None else len(response.motor_velocity)
        self._played = start + n
        if fault is not None:
            self._enter_fault(fault)
        elif self._played >= self._waveform.size:
            self._playing = False
        return n

    def trip(self, code: ErrorCode) -> None:
        """Enter the fault reaction with ``code``: a fieldbus front-end's own watchdogs
        (e.g. the CANopen heartbeat consumer 0x1016 when the host falls silent)."""
        self._enter_fault(ErrorCode(code))

    # -- host-streamed (cyclic synchronous) operation ---------------------------------------
    def step_cyclic(self, references: NDArray[np.float64]) -> CyclicSample | None:
        """Run one cycle of host-streamed CST/CSV: tick i holds ``references[i]``.

        A fieldbus front-end calls this on each SYNC with the previous target held
        for the ticks elapsed since the last SYNC, then the new target for one tick,
        so the returned sample is the one latched at this SYNC (start of the last
        tick), before the new target acts. Limits trip exactly as in :meth:`advance`;
        pending injected faults count ticks of this cyclic run. Nothing moves
        unless the drive is in Operation enabled (then the last sample is repeated).
        """
        refs = np.asarray(references, dtype=np.float64)
        if refs.ndim != 1 or refs.size == 0:
            raise ValueError("references must be a non-empty 1-D array")
        if self._state is not State.OPERATION_ENABLED or self._playing:
            return self._last_cyclic
        start = self._cyclic_ticks
        for kind, at in list(self._pending.items()):
            if at <= start:
                self._trigger(kind)
                return self._last_cyclic
            refs = refs[: max(0, at - start)] if at < start + refs.size else refs
        fault: ErrorCode | None = None
        if self._mode is Mode.CYCLIC_SYNC_TORQUE:
            over = np.flatnonzero(np.abs(refs) > self.max_torque_nm)
            if over.size:
                refs, fault = refs[: over[0]], ErrorCode.OVERCURRENT
        snapshot = self._plant.snapshot()
        response = self._play(refs)
        if response is not None:
            n, limit_fault = self._check_response(response)
            if limit_fault is not None:
                self._plant.restore(snapshot)
                response = self._play(refs[:n])
                fault = limit_fault
            assert response is not None
            self.samples_run += len(response.motor_velocity)
            self._cyclic_ticks += len(response.motor_velocity)
            self._last_cyclic = CyclicSample(
                motor_position=float(response.motor_position[-1]),
                motor_velocity=float(response.motor_velocity[-1]),
                load_position=float(response.load_position[-1]),
                load_velocity=float(response.load_velocity[-1]),
                torque_nm=float(response.torque_ref[-1]),
            )
        if fault is not None:
            self._enter_fault(fault)
        elif self._pending and min(self._pending.values()) <= self._cyclic_ticks:
            self._trigger(min(self._pending, key=lambda k: self._pending[k]))
        return self._last_cyclic

    # -- internals ---------------------------------------------------------------------------
    def _play(self, chunk: NDArray[np.float64]) -> PlantResponse | None:
        if chunk.size == 0:
            return None
        if self._mode is Mode.CYCLIC_SYNC_TORQUE:
            return self._plant.run_torque(chunk)
        return self._plant.run_velocity(chunk, self.velocity_kp, self.velocity_ki, self.max_torque_nm)

    def _check_response(self, r: PlantResponse) -> tuple[int, ErrorCode | None]:
        """Samples up to and including the first speed/travel violation, and its fault (None: all fine)."""
        n = len(r.motor_velocity)
        fault: ErrorCode | None = None
        speed = np.abs(r.motor_velocity)
        travel = np.abs(r.motor_position - self._travel_origin_rad)
        if speed.max() <= self.max_speed_rad_s and travel.max() <= self.max_travel_rad:
            return n, None  # the common case, without searching
        fast = np.flatnonzero(speed > self.max_speed_rad_s)
        far = np.flatnonzero(travel > self.max_travel_rad)
        first = n
        if fast.size and fast[0] < first:
            first, fault = int(fast[0]), ErrorCode.OVERSPEED
        if far.size and far[0] < first:
            first, fault = int(far[0]), ErrorCode.POSITION_LIMIT
        return (first + 1 if first < n else n), fault

    def _record(self, r: PlantResponse, n: int) -> None:
        i = self._trace_len
        for name in _TRACE_SIGNALS:
            self._trace[name][i : i + n] = getattr(r, name)[:n]
        self._trace_len = i + n

    def _trigger(self, kind: InjectedFault) -> None:
        self._pending.pop(kind, None)
        if kind is InjectedFault.SOFTWARE_ERROR:
            raise InjectedError(f"injected software error at sample {self._played}")
        if kind is InjectedFault.COMMUNICATION_LOSS:
            self.communication_lost = True
            self._enter_fault(ErrorCode.COMMUNICATION)
        elif kind is InjectedFault.ENCODER_FAULT:
            self._enter_fault(ErrorCode.ENCODER)
        else:
            self._enter_fault(ErrorCode.DRIVE_HARDWARE)

    def _enter_fault(self, code: ErrorCode) -> None:
        """Fault reaction: brake with the velocity loop (coast without an encoder), then Fault."""
        self._stop_playing()
        if self._state is State.OPERATION_ENABLED:
            self._state = State.FAULT_REACTION_ACTIVE
            if code is ErrorCode.ENCODER:
                self._coast()
            else:
                self._brake()
        self._error = code
        self._state = State.FAULT

    def _stop_playing(self) -> None:
        self._playing = False
        self._pending.clear()

    def _brake(self, max_time_s: float = 2.0) -> None:
        """Velocity loop to zero speed at the torque limit, until the motor is nearly at rest."""
        block = max(1, int(0.01 * self.sample_rate_hz))
        for _ in range(int(max_time_s * self.sample_rate_hz) // block):
            r = self._plant.run_velocity(np.zeros(block), self.velocity_kp, self.velocity_ki, self.max_torque_nm)
            self.samples_run += block
            if np.max(np.abs(r.motor_velocity)) < 0.01:
                break

    def _coast(self, time_s: float = 1.0) -> None:
        n = int(time_s * self.sample_rate_hz)
        self._plant.run_torque(np.zeros(n))
        self.samples_run += n
