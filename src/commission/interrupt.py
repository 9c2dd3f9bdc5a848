"""Ctrl-C (SIGINT) during a command: noted at once, acted on where that is safe.

SIGTERM (``kill``, a service manager, ``docker stop``) and SIGHUP (the terminal closed) are
handled the same way: each ends the run, and every end stops and disables the drive.
While :func:`handling_interrupts` is active (the ``commission`` command installs it first thing):

* the first SIGINT raises :class:`KeyboardInterrupt` in the main thread, as Python does by
  default, so that whatever is waiting (a link, the drive's player, the identifier) ends now;
* inside a :func:`deferred` block (stopping the drive, writing the log) it is only noted, and
  raised when the outermost such block ends: a stop or a log is never cut in half;
* every later SIGINT is noted and never raised: the tool is already on its way out, and a second
  Ctrl-C must not cut the stop of the drive short (it says so on stderr).

:func:`requested` tells an error handler that the user interrupted, also when a library turned
the :class:`KeyboardInterrupt` into an error of its own (canopen's "Block download
unsuccessful"), so that the command still ends as interrupted (exit 130).

A signal that lands inside the standard library's lock code (entering or leaving a
``threading.Condition``, as ``queue.Queue`` does for every SDO response) is not raised there: an
exception between a lock's acquire and the ``with`` that releases it leaves the lock held, or
releases one that another thread holds (CPython issue 29988), and canopen's receive thread then
blocks on it for good, so the stop of the drive that follows never gets its answers. Such a signal
is sent again a few milliseconds later, when the main thread is elsewhere; a thread blocked in a
wait is interrupted at once, as Python does.

Without the handler (library use) Python's default applies and :func:`deferred` changes nothing.
"""

from __future__ import annotations

import contextlib
import linecache
import os
import signal
import threading
import time
from collections.abc import Iterator
from types import FrameType

__all__ = ["Held", "caused_by_interrupt", "deferred", "handling_interrupts", "requested", "what"]

#: The signals that end a run like Ctrl-C, and how the log and the messages name them.
_SIGNALS = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}
if hasattr(signal, "SIGHUP"):  # not on Windows
    _SIGNALS[signal.SIGHUP] = "SIGHUP (the terminal closed)"


#: Seconds until a signal that landed in lock code is sent again: far longer than any stretch of
#: lock bookkeeping, far shorter than a person notices.
RESEND_S = 0.005


class _State:
    def __init__(self) -> None:
        self.installed = False
        self.count = 0  # SIGINTs received while installed
        self.depth = 0  # nesting of deferred() blocks
        self.pending = False  # a SIGINT arrived inside a deferred() block
        self.first = "Ctrl-C"  # what the first signal was
        self.resending = False  # the first signal landed in lock code and is being sent again
        self.closing = False  # handling_interrupts is ending
        self.resender: _Resender | None = None


_state = _State()


def _blocking_lines() -> frozenset[int]:
    """Lines of threading.py where the main thread blocks in an acquire that an exception may leave
    (a wait's own lock, a join's): a signal there is raised at once, as Python does. Without the source
    every line of threading.py defers."""
    lines: set[int] = set()
    for function, call in ((threading.Condition.wait, "waiter.acquire("),
                           (getattr(threading.Thread, "_wait_for_tstate_lock", None), "lock.acquire(")):
        code = getattr(function, "__code__", None)
        if code is not None:  # the function's lines of code, read from the file (linecache, not inspect: start-up)
            lines.update(n for *_, n in code.co_lines()
                         if n is not None and call in linecache.getline(code.co_filename, n))
    return frozenset(lines)


_THREADING_FILE = threading.__file__
_BLOCKING_LINES = _blocking_lines()


def _in_lock_code(frame: FrameType | None) -> bool:
    """True when the main thread is in threading.py's lock bookkeeping, where an exception can leave a
    lock held or release another thread's (module docstring)."""
    return (frame is not None and frame.f_code.co_filename == _THREADING_FILE
            and frame.f_lineno not in _BLOCKING_LINES)


class _Resender:
    """A thread that sends a signal again :data:`RESEND_S` after the handler asked it to, through a
    pipe: the handler only writes a byte, which takes no lock."""

    def __init__(self) -> None:
        self._read, self._write = os.pipe()
        self._thread = threading.Thread(target=self._run, name="commission-interrupt", daemon=True)
        self._thread.start()

    def request(self, signum: int) -> None:
        os.write(self._write, bytes([signum]))

    def _run(self) -> None:
        with contextlib.suppress(OSError):  # the pipe closed under a thread that never got the CPU
            while (data := os.read(self._read, 1)) not in (b"", b"\0"):
                time.sleep(RESEND_S)
                if _state.resending:
                    signal.raise_signal(data[0])

    def close(self) -> None:
        # a signal still on its way is dropped, not sent to the restored handlers: the thread is waited for
        # (it sleeps 5 ms at most), and meanwhile the handler only counts
        _state.closing, _state.resending = True, False
        os.write(self._write, b"\0")
        self._thread.join(timeout=10.0)
        os.close(self._read)
        os.close(self._write)


def _on_sigint(signum: int, frame: FrameType | None) -> None:
    if _state.closing:  # the block has ended: nothing is raised on its way out
        _state.count = max(_state.count, 1)
        return
    if _state.resending:  # the first signal again (or a repeat before it was raised: the same request)
        _state.resending = False
    else:
        _state.count += 1
        if _state.count == 1:
            _state.first = _SIGNALS.get(signal.Signals(signum), "a signal")
        if _state.count > 1:
            # os.write, not print: the handler may run in the middle of a print to stderr
            os.write(2, b"commission: interrupted again: still stopping the drive and closing the log\n")
            return
    if _state.depth > 0:
        _state.pending = True
        return
    if _in_lock_code(frame) and _state.resender is not None:
        _state.resending = True
        _state.resender.request(signum)
        return
    raise KeyboardInterrupt


@contextlib.contextmanager
def handling_interrupts() -> Iterator[None]:
    """Install the SIGINT policy of the module docstring for the duration of the block (main
    thread only; elsewhere, or when already installed, the block runs unchanged)."""
    if _state.installed or threading.current_thread() is not threading.main_thread():
        yield
        return
    _state.installed, _state.count, _state.depth, _state.pending = True, 0, 0, False
    _state.first, _state.resending, _state.closing, _state.resender = "Ctrl-C", False, False, _Resender()
    previous = {sig: signal.signal(sig, _on_sigint) for sig in _SIGNALS}
    try:
        yield
    finally:
        _state.resender.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _state.installed, _state.resender, _state.closing = False, None, False


@contextlib.contextmanager
def deferred(*, raise_after: bool = True) -> Iterator[None]:
    """A block that a Ctrl-C does not cut: the interrupt is raised when the block is done, or,
    with ``raise_after=False`` (an error path that goes on by itself), only left to
    :func:`requested`."""
    _state.depth += 1
    try:
        yield
    finally:
        _state.depth -= 1
        if _state.depth == 0 and _state.pending:
            _state.pending = False
            if raise_after:
                raise KeyboardInterrupt


class Held:
    """A stretch of code that a Ctrl-C does not cut, begun with :meth:`hold` at a point of one's
    choosing (e.g. the last statement of a ``try`` body, so that no statement lies between the
    end of an experiment and the hold) and ended with :meth:`release`; a Ctrl-C meanwhile is only
    left to :func:`requested`. Both are idempotent."""

    def __init__(self) -> None:
        self.active = False

    def hold(self) -> None:
        if not self.active:
            _state.depth += 1
            self.active = True

    def release(self) -> None:
        if self.active:
            self.active = False
            _state.depth -= 1
            if _state.depth == 0:
                _state.pending = False


def requested() -> bool:
    """True once the user pressed Ctrl-C under :func:`handling_interrupts`."""
    return _state.installed and _state.count > 0


def what() -> str:
    """How the log and the messages name the interruption: "Ctrl-C", "SIGTERM", …"""
    return _state.first


def caused_by_interrupt(err: BaseException) -> bool:
    """True when ``err`` is, or was raised while handling, a KeyboardInterrupt, or the user
    pressed Ctrl-C (a library may have replaced the KeyboardInterrupt by its own error)."""
    seen: set[int] = set()
    e: BaseException | None = err
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return requested()
