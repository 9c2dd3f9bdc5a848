"""Ctrl-C while the main thread trades messages with a receiving thread, as canopen's SDO client does:
the lock they share is never left held or broken, so the stop that follows an interrupt still gets
its answers from the drive."""

from __future__ import annotations

import contextlib
import os
import queue
import random
import signal
import threading
import time
from collections.abc import Callable, Iterator

import canopen
import pytest

from commission import interrupt
from sim_drive.canopen_slave import CanopenSlave, sim_eds_path


class _Kicker:
    """Sends SIGINT to this process a random 0.5–4 ms after each :meth:`arm`."""

    def __init__(self, seed: int) -> None:
        self._rng, self._armed, self._done = random.Random(seed), threading.Semaphore(0), False
        self.fired = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def arm(self) -> None:
        self.fired.clear()
        self._armed.release()

    def _run(self) -> None:
        while self._armed.acquire() and not self._done:
            time.sleep(self._rng.uniform(0.0005, 0.004))
            os.kill(os.getpid(), signal.SIGINT)
            self.fired.set()

    def close(self) -> None:
        self._done = True
        self._armed.release()
        self._thread.join(1.0)


def _interrupt(kicker: _Kicker, work: Callable[[], object]) -> bool:
    """Run ``work`` in a loop under the command's handler until the kicker's SIGINT ends it."""
    with interrupt.handling_interrupts():
        try:
            kicker.arm()
            while True:
                work()
        except KeyboardInterrupt:
            return True
        except Exception:
            # a failing work() is reported as such: the SIGINT on its way lands here, under the handler,
            # not in pytest after the handler is gone (which would end the whole test process)
            with contextlib.suppress(KeyboardInterrupt):
                kicker.fired.wait(5.0)
                time.sleep(0.05)
            raise
    return False  # pragma: no cover - the loop only ends by the interrupt


def _get_and_check(q: queue.Queue[int]) -> None:
    """What canopen's SDO client does with its response queue: a short wait for an item, a look."""
    with contextlib.suppress(queue.Empty):  # a busy host may not run the filler within the wait
        q.get(timeout=2e-4)
    q.empty()


@pytest.fixture()
def kicker() -> Iterator[_Kicker]:
    assert threading.current_thread() is threading.main_thread()  # signal handlers run only there
    k = _Kicker(seed=1)
    yield k
    k.close()


def test_an_interrupt_never_leaves_a_queue_lock_held_or_broken(kicker):
    """A queue that another thread fills without pause: an unguarded KeyboardInterrupt leaves its lock
    held (the filler blocks for good) or releases the filler's, after about one interrupt in four."""
    errors: list[BaseException] = []
    previous_hook = threading.excepthook
    threading.excepthook = lambda args: errors.append(args.exc_value)
    try:
        for n in range(1, 61):
            q: queue.Queue[int] = queue.Queue()
            stop = threading.Event()

            def fill() -> None:
                while not stop.is_set():
                    q.put(1)

            filler = threading.Thread(target=fill, daemon=True)
            filler.start()
            assert _interrupt(kicker, lambda: _get_and_check(q))
            stop.set()
            filler.join(1.0)
            assert not filler.is_alive() and not q.mutex.locked(), f"a queue lock stayed held after interrupt {n}"
            assert not errors, f"interrupt {n} broke a queue lock: {errors[0]!r}"
    finally:
        threading.excepthook = previous_hook


@pytest.fixture()
def sdo_client():
    channel = f"interrupt-{os.getpid()}"
    slave = CanopenSlave(channel=channel).start()
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel)
    sdo = net.add_node(1, str(sim_eds_path())).sdo
    sdo.RESPONSE_TIMEOUT = 2.0  # the drive's thread shares a busy host with this test's
    yield sdo
    net.disconnect()
    slave.close()


def test_after_interrupts_during_sdo_reads_the_next_read_is_answered(kicker, sdo_client):
    for n in range(1, 201):
        assert _interrupt(kicker, lambda: sdo_client[0x6041].raw)  # the statusword read of every stop
        lock = sdo_client.responses.mutex
        assert lock.acquire(timeout=1.0), f"the SDO client's queue stayed locked after interrupt {n}"
        lock.release()
    assert isinstance(sdo_client[0x6041].raw, int)
