"""A busy host for the streamed-path tests: a CPU-bound process beside the run, as on a technician's laptop
(and on a loaded CI machine). Import the fixture into a test module: ``from busy_host import cpu_hog``."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator

import pytest


@pytest.fixture
def cpu_hog() -> Iterator[subprocess.Popen[bytes]]:
    """``while True: pass`` in a second process for the test's duration (ended by its own pid)."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield proc
    finally:
        proc.kill()
        proc.wait()
