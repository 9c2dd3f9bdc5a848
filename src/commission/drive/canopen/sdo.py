"""SDO access for the backend: typed reads and writes, block transfers, and errors in our tree.

Every canopen/python-can error becomes one line that names the node, the object
and what was being done: an abort carries its code and the code's meaning
(CiA 301 table 22), a missing answer is a :class:`DriveTimeout`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can
from canopen import RemoteNode
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError, SdoCommunicationError, SdoVariable

from ...exceptions import DriveError, DriveTimeout
from ..description import ObjectRef


@dataclass
class TransferStats:
    """One SDO block transfer: bytes, frames on the bus, wall time."""

    object: str
    direction: str  # "download" | "upload"
    n_bytes: int
    seconds: float
    frames: int

    @property
    def throughput_bps(self) -> float:
        """Payload bytes per second of wall time."""
        return self.n_bytes / self.seconds if self.seconds > 0 else float("inf")


def block_transfer_frames(n_bytes: int, blksize: int = 127) -> int:
    """Frames an SDO block transfer of ``n_bytes`` puts on the bus (both directions).

    initiate + response, ceil(n/7) segments, one ack per sub-block of ``blksize``,
    end + response; an upload also has the client's start and final end.
    """
    segments = max(1, -(-n_bytes // 7))
    acks = -(-segments // blksize)
    return 2 + segments + acks + 2


class SdoAccess:
    """Reads and writes one node's objects; ``link_check`` runs before and after each failure.

    :param node: the remote node (its SDO client).
    :param link_check: raises when the link is known lost (heartbeat consumer), so a lost
        heartbeat is reported as the cause rather than the SDO timeout it produces; called with
        ``missed=2`` after a timeout (two missed heartbeat periods then suffice).
    """

    def __init__(self, node: RemoteNode, timeout_s: float, link_check: Callable[..., None]) -> None:
        self.node = node
        self.timeout_s = timeout_s
        self.node.sdo.RESPONSE_TIMEOUT = timeout_s
        self.node.sdo.MAX_RETRIES = 1
        self._link_check = link_check
        self.transfers: list[TransferStats] = []

    def _name(self, ref: ObjectRef) -> str:
        try:
            obj = self.node.object_dictionary[ref.index]
            if not isinstance(obj, ODVariable):
                obj = obj[ref.subindex]
            return f"{ref} ({obj.name})"
        except KeyError:
            return str(ref)

    def _fail(self, err: Exception, action: str, ref: ObjectRef) -> DriveError:
        what = f"{action} {self._name(ref)}"
        if isinstance(err, SdoAbortedError):
            meaning = SdoAbortedError.CODES.get(err.code, "unknown abort code")
            return DriveError(f"SDO abort 0x{err.code:08X} ({meaning}) from node {self.node.id} {what}")
        if isinstance(err, SdoCommunicationError):
            self._link_check(missed=2)  # a silent heartbeat is the better explanation
            return DriveTimeout(
                f"no SDO answer from node {self.node.id} {what} (timeout {self.timeout_s:g} s): {err}"
            )
        if isinstance(err, KeyError):
            return DriveError(f"object {ref} is not in the object dictionary of node {self.node.id} ({what})")
        return DriveError(f"CAN error {what}: {err}")

    def _var(self, ref: ObjectRef) -> SdoVariable:
        obj = self.node.sdo[ref.index]
        return obj if isinstance(obj, SdoVariable) else obj[ref.subindex]

    def read(self, ref: ObjectRef) -> Any:
        """The object's value as the EDS types it (int, float, str)."""
        self._link_check()
        try:
            return self._var(ref).raw
        except (SdoAbortedError, SdoCommunicationError, KeyError, can.CanError, OSError) as err:
            raise self._fail(err, "reading", ref) from err

    def write(self, ref: ObjectRef, value: Any) -> None:
        self._link_check()
        try:
            self._var(ref).raw = value
        except (SdoAbortedError, SdoCommunicationError, KeyError, can.CanError, OSError) as err:
            raise self._fail(err, "writing", ref) from err

    def download_block(self, ref: ObjectRef, data: bytes) -> TransferStats:
        """SDO block download of ``data`` into a DOMAIN object."""
        self._link_check()
        t0 = time.perf_counter()
        try:
            with self.node.sdo.open(ref.index, ref.subindex, "wb", size=len(data), block_transfer=True,
                                    buffering=0) as stream:
                view = memoryview(data)
                for pos in range(0, len(data), 7):
                    stream.write(view[pos : pos + 7])
        except (SdoAbortedError, SdoCommunicationError, KeyError, can.CanError, OSError) as err:
            raise self._fail(err, "block-downloading", ref) from err
        stats = TransferStats(str(ref), "download", len(data), time.perf_counter() - t0,
                              block_transfer_frames(len(data)))
        self.transfers.append(stats)
        return stats

    def upload_block(self, ref: ObjectRef) -> tuple[bytes, TransferStats]:
        """SDO block upload of a DOMAIN object."""
        self._link_check()
        t0 = time.perf_counter()
        try:
            with self.node.sdo.open(ref.index, ref.subindex, "rb", block_transfer=True, buffering=0) as stream:
                data = stream.readall()
                expected = stream.size
        except (SdoAbortedError, SdoCommunicationError, KeyError, can.CanError, OSError) as err:
            raise self._fail(err, "block-uploading", ref) from err
        if expected is not None and len(data) != expected:
            raise DriveError(f"block upload of {self._name(ref)} gave {len(data)} bytes, the node announced {expected}")
        stats = TransferStats(str(ref), "upload", len(data), time.perf_counter() - t0,
                              block_transfer_frames(len(data)) + 1)
        self.transfers.append(stats)
        return data, stats
