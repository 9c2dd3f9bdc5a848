"""Write-back of controller settings to the simulated CANopen node (issue #6): old → new,
read-back, store to 0x1010 on request, every write logged in the run's MCAP file, restore
from that log; refusal on a range violation."""

from __future__ import annotations

import math
from dataclasses import replace
from datetime import datetime, timezone

import pytest

from commission.drive import open_drive
from commission.ident.twomass import REFERENCE_PLANT
from commission.mcaplog import RecordingWriter, read_results
from commission.tuning import (
    PARAMETER_TOPIC,
    Notch,
    TuningError,
    TuningOptions,
    apply,
    design,
    drive_parameters,
    restore_values,
)

_settings = {}


def _design():
    if "s" not in _settings:
        _settings["s"] = design(REFERENCE_PLANT, TuningOptions(), epsilon_rad=math.radians(0.4))
    return _settings["s"]


def test_write_back_round_trip_and_restore(tmp_path) -> None:
    s = _design()
    log_path = tmp_path / "run.mcap"
    lines: list[str] = []
    with open_drive(sim=True, sim_link="canopen", drive="sim") as drive:
        params = drive_parameters(s, drive.description)
        names = {p.name for p in params}
        assert {"velocity_kp", "velocity_ki", "position_loop_gain", "backlash_compensation"} <= names
        before = {p.name: drive.read_parameter(p.name) for p in params}
        with RecordingWriter(log_path, sample_rate_hz=8000.0, start_time=datetime.now(timezone.utc),
                             drive=drive.info, signals=("torque_ref", "motor_velocity")) as log:
            # a refusal at the prompt writes nothing
            report = apply(drive, params, confirm=lambda q: False, log=log.add_result, echo=lines.append)
            assert not report.applied
            assert drive.read_parameter("velocity_kp") == pytest.approx(before["velocity_kp"])
            report = apply(drive, params, yes=True, store=True, log=log.add_result, echo=lines.append)
        assert report.applied and report.stored
        for p in params:
            assert report.read_back[p.name] == pytest.approx(p.value, rel=1e-6, abs=1e-9)
        # the device's own loop took the new gains
        assert drive.simulator.device.velocity_kp == pytest.approx(s.velocity_gain, rel=1e-6)
        assert any("→" in line for line in lines)
        events = read_results(log_path)[PARAMETER_TOPIC]
        writes = [e for e in events if e["event"] == "write"]
        assert {e["name"] for e in writes} == names
        assert [e["event"] for e in events].count("store") == 1
        # restore the previous values from the log
        old = restore_values(log_path, drive.description)
        apply(drive, old, yes=True, echo=lines.append)
        for p in params:
            assert drive.read_parameter(p.name) == pytest.approx(before[p.name], rel=1e-6, abs=1e-9)


def test_refuses_to_apply_on_a_range_violation() -> None:
    s = replace(_design(), notches=(Notch(frequency_hz=5.0, q=1.0, depth=0.2),))  # sim range: 10–4000 Hz
    with open_drive(sim=True, sim_link="canopen", drive="sim") as drive:
        params = drive_parameters(s, drive.description)
        assert [p.name for p in params if p.clamped] == ["notch1_frequency"]
        kp_before = drive.read_parameter("velocity_kp")
        with pytest.raises(TuningError, match="notch1_frequency"):
            apply(drive, params, yes=True, echo=lambda _: None)
        assert drive.read_parameter("velocity_kp") == pytest.approx(kp_before)
