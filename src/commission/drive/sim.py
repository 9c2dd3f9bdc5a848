"""The ``sim`` backend: the simulated drive (sim_drive) driven directly, in-process.

The same CiA 402 controlword/statusword traffic as a real drive, without a
fieldbus in between. Imported only when ``--sim`` is chosen.
"""

from __future__ import annotations

from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..exceptions import ConfigError, DriveFault, DriveTimeout
from ..recording import DriveInfo, Recording
from .base import Drive, ProgressCallback
from .cia402 import Mode, State

try:
    from pydantic import ValidationError
    from sim_drive.device import SimulatedDevice
    from sim_drive.plant import PlantParameters
except ImportError as err:  # pragma: no cover - packaging error
    raise ImportError("the sim backend needs the sim_drive package (installed with drive-commission)") from err

#: Ticks played per step of the device (25 ms at 8 kHz): the granularity of progress
#: reports and of a host-side abort; the device trips its limits at the exact tick regardless.
CHUNK_SAMPLES = 200


def _tool_version() -> str:
    try:
        return version("drive-commission")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "0+unknown"


def plant_from_options(options: dict[str, Any] | None) -> PlantParameters:
    """PlantParameters from the config's ``sim`` section; errors name the key."""
    try:
        return PlantParameters.model_validate(options or {})
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        msg = "unknown key" if first["type"] == "extra_forbidden" else first["msg"]
        raise ConfigError(f"sim.{where}: {msg}") from err


class SimDrive(Drive):
    """A :class:`~sim_drive.device.SimulatedDevice` behind the Drive interface."""

    def __init__(self, device: SimulatedDevice | None = None, *, plant: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.device = device if device is not None else SimulatedDevice(plant_from_options(plant))
        self._info = DriveInfo(
            backend="sim",
            vendor=self.device.vendor,
            product=self.device.product,
            serial_number=self.device.serial_number,
            firmware=_tool_version(),
            rated_torque_nm=self.device.rated_torque_nm,
        )
        self._start_time: datetime | None = None
        self._sample_rate_hz = self.device.sample_rate_hz
        self._prepared: NDArray[np.float64] | None = None

    # -- hooks -------------------------------------------------------------------------
    @property
    def info(self) -> DriveInfo:
        return self._info

    def _link(self) -> SimulatedDevice:
        if self.device.communication_lost:
            raise DriveTimeout("no answer from the simulated drive (communication lost)")
        return self.device

    def _write_controlword(self, controlword: int) -> None:
        self._link().write_controlword(controlword)

    def _read_statusword(self) -> int:
        return self._link().statusword

    def _write_mode(self, mode: Mode) -> None:
        self._link().write_mode(mode)

    def _write_limits(self, max_torque_nm: float, max_speed_rad_s: float, max_travel_rad: float | None) -> None:
        self._link().set_limits(max_torque_nm, max_speed_rad_s, max_travel_rad)

    def _fault_message(self) -> str:
        code = self.device.error_code
        return f"drive fault 0x{int(code):04X} ({code.text})"

    def prepare_excitation(self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode) -> None:
        """Check the sample rate and load the waveform into the player while the drive is disabled."""
        dev = self._link()
        if abs(sample_rate_hz - dev.sample_rate_hz) > 1e-9 * dev.sample_rate_hz:
            raise ConfigError(
                f"the simulated drive plays waveforms at {dev.sample_rate_hz:g} Hz, not {sample_rate_hz:g} Hz"
            )
        wave = np.asarray(waveform, dtype=np.float64)
        try:
            dev.load_waveform(wave)
        except ValueError as err:  # longer than the trace buffer
            raise ConfigError(f"the simulated drive refuses the waveform: {err}") from err
        self._prepared = wave

    def _excite(
        self, waveform: NDArray[np.float64], sample_rate_hz: float, mode: Mode, progress: ProgressCallback | None
    ) -> Recording:
        dev = self._link()
        if mode is not dev.mode:
            raise DriveTimeout(f"drive is in mode {dev.mode.name}, not {mode.name}")
        prepared, self._prepared = self._prepared, None
        if prepared is None or prepared.shape != waveform.shape or not np.array_equal(prepared, waveform):
            self.prepare_excitation(waveform, sample_rate_hz, mode)
        self._start_time = datetime.now(timezone.utc)
        dev.start()
        total = waveform.size
        while dev.playing:
            dev.advance(CHUNK_SAMPLES)
            self._link()  # a lost link shows as a timeout, as it would on a fieldbus
            if progress is not None:
                progress(dev.progress[0], total)
        if dev.state is State.FAULT:
            played = dev.progress[0]
            raise DriveFault(
                f"{self._fault_message()} after {played / sample_rate_hz:.3f} s of {total / sample_rate_hz:.3g} s",
                code=int(dev.error_code),
            )
        rec = self._recording()
        assert rec is not None
        return rec

    def _recorded_so_far(self) -> Recording | None:
        self._link()
        return self._recording()

    def _recording(self) -> Recording | None:
        trace = self.device.trace()
        if len(trace) < 2 or self._start_time is None:
            return None
        return Recording.uniform(
            self._sample_rate_hz,
            trace.torque_ref,
            trace.motor_velocity,
            motor_position=trace.motor_position,
            load_position=trace.load_position,
            load_velocity=trace.load_velocity,
            start_time=self._start_time,
            drive=self._info,
        )

    # -- parameters ----------------------------------------------------------------------
    _PARAMETERS = ("velocity_kp", "velocity_ki", "max_torque_nm", "max_speed_rad_s")

    def read_parameter(self, name: str) -> Any:
        if name not in self._PARAMETERS:
            return super().read_parameter(name)
        return getattr(self._link(), name)

    def write_parameter(self, name: str, value: Any) -> None:
        if name not in self._PARAMETERS:
            return super().write_parameter(name, value)
        setattr(self._link(), name, float(value))
