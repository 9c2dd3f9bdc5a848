"""The small interface every drive backend implements.

Like python-can's ``BusABC``: :class:`Drive` implements the public methods
(state changes along the CiA 402 graph with timeouts, limits, the excitation
contract, safe shutdown) on top of a few hooks that each backend fills in.
The sequencer talks only to this interface.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..exceptions import DriveError, DriveFault, DriveNotFound, DriveTimeout
from ..recording import DriveInfo, Recording
from .cia402 import Command, Mode, State, command_towards, decode_statusword

__all__ = [
    "Drive", "DriveInfo", "DriveError", "DriveFault", "DriveNotFound", "DriveTimeout",
    "ProgressCallback", "Mode", "State",
]

#: progress(done_samples, total_samples) during an excitation.
ProgressCallback = Callable[[int, int], None]


class Drive(ABC):
    """A servo drive that can play an excitation and record its response.

    Use as a context manager: leaving the block (normally or by an exception)
    stops and disables the drive and releases the link. ``close()`` is safe to
    call twice.
    """

    #: Seconds to wait for each CiA 402 state transition.
    state_timeout_s: float = 1.0

    def __init__(self) -> None:
        self._closed = False

    # -- hooks for backends ------------------------------------------------------
    @property
    @abstractmethod
    def info(self) -> DriveInfo:
        """Identity of the drive (read at connection)."""

    @abstractmethod
    def _write_controlword(self, controlword: int) -> None: ...

    @abstractmethod
    def _read_statusword(self) -> int: ...

    @abstractmethod
    def _write_mode(self, mode: Mode) -> None: ...

    @abstractmethod
    def _write_limits(self, max_torque_nm: float, max_speed_rad_s: float, max_travel_rad: float | None) -> None: ...

    @abstractmethod
    def _excite(
        self,
        waveform: NDArray[np.float64],
        sample_rate_hz: float,
        mode: Mode,
        progress: ProgressCallback | None,
    ) -> Recording: ...

    def _await_playback(
        self,
        read_played: Callable[[], int],
        total: int,
        rate_hz: float,
        progress: ProgressCallback | None,
        *,
        poll_s: float,
        stall_s: float,
        on_poll: Callable[[int], None] | None = None,
    ) -> None:
        """Poll a drive-side waveform player until it has played ``total`` samples.

        Raises DriveFault when the drive faults, DriveError when it leaves Operation enabled,
        DriveTimeout when the played count stops moving for longer than the run plus ``stall_s``.
        ``on_poll(played)`` runs first on every poll (link and EMCY checks of a backend).
        """
        last_progress, last_change = -1, time.monotonic()
        stall_limit = total / rate_hz + stall_s
        while True:
            time.sleep(poll_s)
            played = int(read_played())
            if on_poll is not None:
                on_poll(played)
            if progress is not None:
                progress(played, total)
            if played >= total:
                return
            state = decode_statusword(self._read_statusword())
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                if on_poll is not None:
                    on_poll(played)  # a fault message (EMCY) may have arrived meanwhile: it names the cause
                raise DriveFault(f"{self._fault_message()} after {played / rate_hz:.3f} s of {total / rate_hz:.3g} s")
            if state is not State.OPERATION_ENABLED:
                raise DriveError(f"drive left 'operation enabled' during the run: it is '{state.value}'")
            now = time.monotonic()
            if played != last_progress:
                last_progress, last_change = played, now
            elif now - last_change > stall_limit:
                raise DriveTimeout(f"the drive's waveform player made no progress for {now - last_change:.1f} s")

    def _recorded_so_far(self) -> Recording | None:
        """The part of the last excitation recorded before an abort (backends override)."""
        return None

    def _shutdown(self) -> None:
        """Release the link (backends override)."""

    def _fault_message(self) -> str:
        """A readable description of the drive's active fault (backends override)."""
        return "drive is in Fault state"

    # -- public API --------------------------------------------------------------
    @property
    def state(self) -> State:
        """Current CiA 402 state, read from the drive."""
        return decode_statusword(self._read_statusword())

    def _go_to(self, target: State) -> None:
        deadline = time.monotonic() + self.state_timeout_s
        state = self.state
        while state is not target:
            if state is State.FAULT and target is not State.SWITCH_ON_DISABLED:
                raise DriveFault(f"cannot reach '{target.value}': {self._fault_message()}")
            command = command_towards(state, target)
            if command is None:
                raise DriveError(f"no CiA 402 transition from '{state.value}' to '{target.value}'")
            if command is Command.FAULT_RESET:
                self._write_controlword(0)  # bit 7 acts on its rising edge
            self._write_controlword(int(command))
            new_state = self.state
            if new_state is state and time.monotonic() > deadline:
                raise DriveTimeout(
                    f"drive stayed in '{state.value}' after command {command.name} "
                    f"(waited {self.state_timeout_s:g} s for '{target.value}')"
                )
            state = new_state

    def set_limits(self, max_torque_nm: float, max_speed_rad_s: float, max_travel_rad: float | None = None) -> None:
        """Write the limits the drive enforces itself, before enabling.

        :param max_torque_nm: torque limit [N·m] (CiA 402 0x6072).
        :param max_speed_rad_s: motor speed limit [rad/s] (0x6080).
        :param max_travel_rad: travel limit around the present position [rad] (0x607D), if any.
        """
        if not (max_torque_nm > 0 and max_speed_rad_s > 0) or (max_travel_rad is not None and max_travel_rad <= 0):
            raise ValueError("limits must be positive")
        self._write_limits(float(max_torque_nm), float(max_speed_rad_s),
                           None if max_travel_rad is None else float(max_travel_rad))

    def enable(self, mode: Mode = Mode.CYCLIC_SYNC_TORQUE) -> None:
        """Select ``mode`` and bring the drive to Operation enabled."""
        if self.state is State.FAULT:
            raise DriveFault(f"will not enable: {self._fault_message()}")
        self._go_to(State.SWITCHED_ON)
        self._write_mode(mode)
        self._go_to(State.OPERATION_ENABLED)

    def quick_stop(self) -> None:
        """Quick stop: the drive brakes with its quick-stop ramp (no-op unless enabled)."""
        if self.state is State.OPERATION_ENABLED:
            self._write_controlword(int(Command.QUICK_STOP))

    def disable(self) -> None:
        """Remove torque: to Switch on disabled (from any state except Fault, which stays)."""
        state = self.state
        if state not in (State.SWITCH_ON_DISABLED, State.FAULT, State.FAULT_REACTION_ACTIVE):
            self._go_to(State.SWITCH_ON_DISABLED)

    def fault_reset(self) -> None:
        """Acknowledge a fault (to Switch on disabled)."""
        if self.state is State.FAULT:
            self._go_to(State.SWITCH_ON_DISABLED)

    def run_excitation(
        self,
        waveform: NDArray[np.float64],
        sample_rate_hz: float,
        *,
        mode: Mode = Mode.CYCLIC_SYNC_TORQUE,
        progress: ProgressCallback | None = None,
    ) -> Recording:
        """Play ``waveform`` (torque [N·m] in CST, velocity [rad/s] in CSV) and record the response.

        :param waveform: reference samples, shape (N,), one per 1/``sample_rate_hz`` s.
        :returns: the Recording of the N samples.
        :raises DriveFault: the drive faulted (limit, encoder, …); ``recorded_so_far()``
            then returns what was recorded before.
        """
        wave = np.asarray(waveform, dtype=np.float64)
        if wave.ndim != 1 or wave.size < 2:
            raise ValueError("waveform must be a 1-D array of at least 2 samples")
        if self.state is not State.OPERATION_ENABLED:
            raise DriveError(f"drive must be in 'operation enabled' to excite, it is '{self.state.value}'")
        return self._excite(wave, float(sample_rate_hz), mode, progress)

    def recorded_so_far(self) -> Recording | None:
        """What the last excitation recorded before it ended early (None if nothing)."""
        return self._recorded_so_far()

    def read_parameter(self, name: str) -> Any:
        """Read a named drive parameter (names from the drive description)."""
        raise DriveError(f"{type(self).__name__} has no parameter '{name}'")

    def write_parameter(self, name: str, value: Any) -> None:
        """Write a named drive parameter (names from the drive description)."""
        raise DriveError(f"{type(self).__name__} has no parameter '{name}'")

    def close(self) -> None:
        """Stop, disable and release the drive. Safe to call twice; never raises for a lost link."""
        if self._closed:
            return
        self._closed = True
        try:
            self.quick_stop()
            self.disable()
        except DriveError:
            pass  # the link may be gone; the drive's own watchdog then stops it
        finally:
            self._shutdown()

    def __enter__(self) -> Drive:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
