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
    "Mode", "ProgressCallback", "SIM_LINKS", "State", "open_drive",
]

#: backend name -> (module, class). Backends still to come (issue #4, #5) are listed
#: in PLANNED so the error says so instead of "unknown".
BACKENDS: dict[str, tuple[str, str]] = {
    "sim": ("commission.drive.sim", "SimDrive"),
    "canopen": ("commission.drive.canopen", "CanopenDrive"),
    "modbus": ("commission.drive.modbus", "ModbusDrive"),
}
PLANNED: dict[str, str] = {}
#: How ``--sim`` reaches the simulated drive: directly, or as a CANopen node on python-can's
#: in-process ``virtual`` bus with the canopen backend in front of it.
SIM_LINKS = ("direct", "canopen")


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
    sim_link: str = "direct",
    **options: Any,
) -> Drive:
    """Open the drive a command line describes.

    :param sim: the built-in simulated drive (``sim_plant``: its plant parameters).
    :param sim_link: ``direct`` (default) or ``canopen``: the simulated drive as a CANopen node on
        the in-process virtual bus, driven by the canopen backend (``options`` go to it).
    :param port: ``can0``-style CAN channel, or a serial device path.
    :param interface: python-can interface (``socketcan``, ``slcan``, …) for CAN ports.
    :param protocol: ``canopen`` (default for CAN, and for ``--interface slcan`` adapters on serial
        ports) or ``modbus`` (serial service ports; the default for a /dev/ port without an interface).
    """
    if sim:
        if port is not None:
            raise DriveError("choose either --sim or --port, not both")
        if sim_link == "canopen":
            try:
                module = importlib.import_module("commission.drive.canopen")
            except ImportError as err:
                raise DriveError(f"backend 'canopen' cannot be loaded: {err}") from err
            drive: Drive = module.open_simulated(sim_plant, **options)
            return drive
        if sim_link != "direct":
            raise DriveError(f"unknown --sim-link '{sim_link}' (choose from {', '.join(SIM_LINKS)})")
        return _backend_class("sim")(plant=sim_plant)
    if not port:
        raise DriveNotFound("no drive given: use --port PORT, --sim, or --replay FILE")
    if port.startswith("/dev/") and not Path(port).exists():
        raise DriveNotFound(f"port {port} does not exist")
    backend = protocol or ("modbus" if port.startswith("/dev/") and interface is None else "canopen")
    if backend == "canopen" and interface == "slcan":
        # a serial-line CAN adapter: port locked, adapter probed, every line it sends checked
        _backend_class("canopen")  # loads, or says why the canopen backend cannot
        from .slcan import open_slcan

        return open_slcan(port, **options)
    if backend == "modbus" and interface is not None:
        raise DriveError(f"--interface {interface} is for CAN adapters; --protocol modbus talks to the serial port itself")
    return _backend_class(backend)(port=port, interface=interface, **options)
