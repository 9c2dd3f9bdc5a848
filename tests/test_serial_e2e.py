"""Serial links end to end, across two processes: ``python -m sim_drive --slcan`` / ``--modbus`` on a pty,
``commission --port PTY --interface slcan`` / ``--protocol modbus`` in this process, through the real
serial stacks (python-can's slcan client, pymodbus's serial client, pyserial). Both must identify what
the direct simulated run identifies, for the same plant and seed."""

from __future__ import annotations

import contextlib
import json
import math
import select
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from commission.cli import main
from commission.mcaplog import read_recording

from busy_host import cpu_hog  # noqa: F401 - a fixture

SEED = "3"
STEP = 2 * math.pi / 2**24  # rad per increment of the simulated 24-bit encoders


@contextlib.contextmanager
def sim_drive(link: str, *args: str, stop: int = signal.SIGTERM) -> Iterator[str]:
    """``python -m sim_drive --LINK`` in a second process; yields the pty path (its first stdout line)."""
    proc = subprocess.Popen([sys.executable, "-m", "sim_drive", f"--{link}", "--seed", SEED, "--pace", "0", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 60)
        assert ready, "sim_drive printed no pty path within 60 s"
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/"), f"first line is not a path: {path!r} ({proc.stderr.read()})"
        yield path
    finally:
        proc.send_signal(stop)
        try:
            rc = proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            rc = proc.wait()
    assert rc == 0, f"sim_drive did not end cleanly on signal {stop}: exit {rc}"


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    capsys.readouterr()
    rc = main([*argv, "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    return json.loads(out)


@pytest.fixture(scope="module")
def direct(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("direct")
    assert main(["--sim", "--seed", SEED, "--out", str(out), "--json"]) == 0
    return out


def assert_same_run(out: Path, direct: Path) -> None:
    rec, expected = read_recording(out / "run.mcap"), read_recording(direct / "run.mcap")
    assert len(rec) == len(expected) == 80_000 and rec.metadata["status"] == "complete"
    # torque: the drive's unit is 1e-8 of the rated torque, rounded to nearest
    np.testing.assert_allclose(rec.torque_ref, expected.torque_ref, rtol=0, atol=0.5e-8 * 0.637 + 1e-15)
    # responses: within one encoder increment (the unit-rounded torque may flip a count now and then)
    for name in ("motor_position", "load_position"):
        np.testing.assert_allclose(getattr(rec, name), getattr(expected, name), rtol=0, atol=STEP * 1.001)
    for name in ("motor_velocity", "load_velocity"):
        np.testing.assert_allclose(getattr(rec, name), getattr(expected, name), rtol=0, atol=STEP * 8000 * 1.001)
    got = json.loads((out / "result.json").read_text())
    want = json.loads((direct / "result.json").read_text())
    for key in ("J_m", "J_l", "B_m", "B_l", "K", "D"):
        assert got["two_mass"][key] == pytest.approx(want["two_mass"][key], rel=1e-3), key
    assert got["backlash"]["epsilon_deg"] == pytest.approx(want["backlash"]["epsilon_deg"], abs=0.002)
    for key in ("f_resonance_hz", "f_antiresonance_hz"):
        assert got["modes"][key] == pytest.approx(want["modes"][key], rel=1e-3), key


def test_canopen_through_an_slcan_adapter_in_a_second_process(direct, tmp_path, capsys):
    """No --drive: the description comes from the drive's identity (0x1018: the simulated drive, whose
    waveform player and trace are then used)."""
    with sim_drive("slcan") as port:
        doc = run_cli(capsys, "--port", port, "--interface", "slcan", "--out", str(tmp_path))
    assert doc["source"] == "canopen" and doc["recording"]["status"] == "complete"
    assert_same_run(tmp_path, direct)


def test_streamed_through_an_slcan_adapter_beside_a_cpu_hog(direct, tmp_path, capsys, cpu_hog):
    """A drive no description claims (generic identity) behind an slcan adapter in another process, a
    CPU-bound process beside both: host-streamed CST on the drive's clock identifies what the direct
    run identifies (ε ±0.02°, J_m, J_l, K ±2 %)."""
    with sim_drive("slcan", "--identity", "generic") as port:
        doc = run_cli(capsys, "--port", port, "--interface", "slcan", "--no-tune", "--out", str(tmp_path))
    rec = read_recording(tmp_path / "run.mcap")
    assert len(rec) >= 20_000 and rec.sample_rate_hz == 2000 and rec.is_uniform
    assert "host-streamed CST on the drive's clock" in rec.metadata["excitation_path"]
    assert doc["recording"]["drive"]["vendor"] == "vendor 0x00000000"
    got = json.loads((tmp_path / "result.json").read_text())
    want = json.loads((direct / "result.json").read_text())
    for key in ("J_m", "J_l", "K"):
        assert got["two_mass"][key] == pytest.approx(want["two_mass"][key], rel=0.02), key
    assert got["backlash"]["epsilon_deg"] == pytest.approx(want["backlash"]["epsilon_deg"], abs=0.02)


def test_modbus_rtu_in_a_second_process(direct, tmp_path, capsys):
    with sim_drive("modbus", stop=signal.SIGINT) as port:
        doc = run_cli(capsys, "--port", port, "--protocol", "modbus", "--out", str(tmp_path))
    assert doc["source"] == "modbus" and doc["recording"]["drive"]["product"] == "simulated two-mass drive"
    assert_same_run(tmp_path, direct)


def test_cable_pulled_mid_run_is_one_line_and_the_drive_stops_itself(tmp_path, capsys):
    """The pty closes 0.375 s into a real-time run: one line on stderr, exit code 4, and the sim
    process (whose communication watchdog stopped the drive) still ends cleanly."""
    config = tmp_path / "short.yaml"
    config.write_text("excitation: {duration_s: 1.0, bias_frequency_hz: 1.0}\n")
    with sim_drive("modbus", "--inject", "hangup@3000", "--pace", "1") as port:
        capsys.readouterr()
        rc = main(["--port", port, "--protocol", "modbus", "--config", str(config), "--no-identify",
                   "--out", str(tmp_path / "out"), "--json"])
        err = capsys.readouterr().err
    assert rc == 4
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("commission: error: serial link to device 1 on /dev/") and "cable pulled" in lines[0]
