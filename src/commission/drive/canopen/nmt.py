"""NMT for the backend: node presence, heartbeat consumer, state commands.

The heartbeat consumer is a plain subscriber on 0x700 + node id that notes the
arrival time (monotonic clock); :meth:`HeartbeatConsumer.check` raises
:class:`DriveTimeout` once the node has been silent longer than the consumer
time, so every later access fails at once with the real cause instead of
waiting for its own SDO timeout.
"""

from __future__ import annotations

import threading
import time
from enum import IntEnum

from canopen import Network

from ...exceptions import DriveTimeout


class NmtCommand(IntEnum):
    """NMT command specifiers (CiA 301 §7.2.8.3.1)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as a heartbeat reports them."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


#: how long a check that finds the heartbeat overdue waits for frames still queued in this host [s]
GRACE_S = 0.1


def send_nmt(network: Network, command: NmtCommand, node_id: int) -> None:
    """One NMT command to one node (0: all nodes)."""
    network.send_message(0x000, bytes([int(command), node_id]))


class HeartbeatConsumer:
    """Watches one node's heartbeat.

    :param timeout_s: the link counts as lost after this long without a heartbeat.
    """

    def __init__(self, network: Network, node_id: int, timeout_s: float, period_s: float) -> None:
        self.network = network
        self.node_id = node_id
        self.timeout_s = timeout_s
        self.period_s = period_s
        self.last: float | None = None
        self.state: NmtState | None = None
        self.count = 0
        self.lost = False
        self._event = threading.Event()
        network.subscribe(0x700 + node_id, self._on_heartbeat)

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.last = time.monotonic()
        self.count += 1
        try:
            self.state = NmtState(data[0] & 0x7F) if data else None
        except ValueError:
            self.state = None
        self._event.set()

    def wait(self, timeout_s: float) -> bool:
        """Wait for the next heartbeat; True if one came."""
        self._event.clear()
        return self._event.wait(timeout_s)

    @property
    def silent_for_s(self) -> float:
        return float("inf") if self.last is None else time.monotonic() - self.last

    def check(self, missed: int | None = None) -> None:
        """Raise DriveTimeout if the node's heartbeat has stopped (once armed by a first heartbeat).

        :param missed: also call it lost after this many missed heartbeat periods (used when
            another service has already timed out: the silence then explains it).
        """
        if self.last is None:
            return
        silent = self.silent_for_s
        limit = self.timeout_s if missed is None else min(self.timeout_s, missed * self.period_s)
        if not self.lost and silent > limit:
            # a busy host may run this check before its receive thread has taken the frames that came
            # while it was not scheduled: give that thread a moment before calling the link lost
            self._event.clear()
            self._event.wait(min(self.period_s, GRACE_S))
            silent = self.silent_for_s
        if self.lost or silent > limit:
            self.lost = True
            raise DriveTimeout(
                f"heartbeat of node {self.node_id} lost: none for {silent:.2f} s "
                f"(consumer time {self.timeout_s:g} s); the drive's own watchdog must stop the axis"
            )

    def close(self) -> None:
        try:
            self.network.unsubscribe(0x700 + self.node_id, self._on_heartbeat)
        except (KeyError, ValueError):
            pass
