"""Drive abstraction layer: one small interface, backends registered by name.

Backends are imported lazily (like python-can's interface registry), so a
missing optional dependency of one backend does not break the others, and
``sim_drive`` is imported only when the simulated drive is chosen.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from ..exceptions import DriveError, DriveFault, DriveNotFound, DriveTimeout
from .base import Drive, DriveInfo, ProgressCallback
from .cia402 import Mode, State

__all__ = [
    "BACKENDS", "Drive", "DriveError", "DriveFault", "DriveInfo", "DriveNotFound", "DriveTimeout",
    "Mode", "ProgressCallback", "State", "open_drive",
]

#: backend name -> (module, class). Backends still to come (issue #4, #5) are listed
#: in PLANNED so the error says so instead of "unknown".
BACKENDS: dict[str, tuple[str, str]] = {
    "sim": ("commission.drive.sim", "SimDrive"),
}
PLANNED: dict[str, str] = {
    "canopen": "the CANopen CiA 402 backend",
    "modbus": "the Modbus RTU backend",
}


def _backend_class(name: str) -> type[Drive]:
    if name not in BACKENDS:
        if name in PLANNED:
            raise DriveNotFound(f"{PLANNED[name]} ('{name}') is not available in this version yet")
        raise DriveNotFound(f"unknown drive backend '{name}' (known: {', '.join(sorted(BACKENDS))})")
    module_name, class_name = BACKENDS[name]
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise DriveError(f"backend '{name}' cannot be loaded: {err}") from err
    cls: type[Drive] = getattr(module, class_name)
    return cls


def open_drive(
    *,
    sim: bool = False,
    port: str | None = None,
    interface: str | None = None,
    protocol: str | None = None,
    sim_plant: dict[str, Any] | None = None,
    **options: Any,
) -> Drive:
    """Open the drive a command line describes.

    :param sim: the built-in simulated drive (``sim_plant``: its plant parameters).
    :param port: ``can0``-style CAN channel, or a serial device path.
    :param interface: python-can interface (``socketcan``, ``slcan``, …) for CAN ports.
    :param protocol: ``canopen`` (default for CAN) or ``modbus`` (serial service ports).
    """
    if sim:
        if port is not None:
            raise DriveError("choose either --sim or --port, not both")
        return _backend_class("sim")(plant=sim_plant)
    if not port:
        raise DriveNotFound("no drive given: use --port PORT, --sim, or --replay FILE")
    if port.startswith("/dev/") and not Path(port).exists():
        raise DriveNotFound(f"port {port} does not exist")
    backend = protocol or ("modbus" if port.startswith("/dev/") and interface is None else "canopen")
    return _backend_class(backend)(port=port, interface=interface, **options)
