"""EMCY consumer for the backend: every emergency message of the node, with its text."""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from canopen import Network


@dataclass(frozen=True)
class Emergency:
    """One EMCY frame (CiA 301 §7.2.7)."""

    code: int
    """error code (0x603F style; 0x0000 = error reset)."""
    register: int
    """error register 0x1001."""
    data: bytes
    received: float
    """monotonic time of reception [s]."""
    text: str


class EmcyListener:
    """Collects a node's EMCYs; ``describe(code)`` gives the text (drive description first)."""

    def __init__(self, network: Network, node_id: int, describe: Callable[[int], str]) -> None:
        self.network = network
        self.node_id = node_id
        self.describe = describe
        self.log: list[Emergency] = []
        self._lock = threading.Lock()
        network.subscribe(0x80 + node_id, self._on_emcy)

    def _on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        raw = bytes(data).ljust(8, b"\0")
        code, register = struct.unpack_from("<HB", raw)
        entry = Emergency(code, register, raw[3:8], time.monotonic(), self.describe(code))
        with self._lock:
            self.log.append(entry)

    def since(self, index: int) -> list[Emergency]:
        """Errors (not resets) received after the first ``index`` log entries."""
        with self._lock:
            return [e for e in self.log[index:] if e.code != 0]

    def __len__(self) -> int:
        return len(self.log)

    def close(self) -> None:
        try:
            self.network.unsubscribe(0x80 + self.node_id, self._on_emcy)
        except (KeyError, ValueError):
            pass
