"""CANopen CiA 402 backend (canopen + python-can: SocketCAN, slcan, virtual, …).

One module per CiA 301 service, like python-canopen: ``nmt`` (presence,
heartbeat consumer), ``sdo`` (typed access, block transfers, abort meanings),
``emcy``, ``pdo`` (bus budget and the streamed cycle), ``trace`` (waveform and
trace units); ``drive`` puts them behind the :class:`~commission.drive.Drive`
interface with the shared CiA 402 vocabulary of :mod:`commission.drive.cia402`.
"""

from __future__ import annotations

from .drive import CanopenDrive, open_simulated
from .pdo import BusBudget, StreamReport, frame_bits, interpolation_period, plan_cycle, waveform_band_hz
from .sdo import TransferStats, block_transfer_frames

__all__ = [
    "BusBudget", "CanopenDrive", "StreamReport", "TransferStats", "block_transfer_frames", "frame_bits",
    "interpolation_period", "open_simulated", "plan_cycle", "waveform_band_hz",
]
