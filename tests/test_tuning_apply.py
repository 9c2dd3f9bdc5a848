"""Write-back of controller settings to the simulated CANopen node (issue #6): old → new,
read-back, store to 0x1010 on request, every write logged in the run's MCAP file, restore
from that log; refusal on a range violation. Staged write-back (issue #20): a conservative set,
a step-and-reversal check in the drive's trace, the final set, and the previous values back on
oscillation."""

from __future__ import annotations

import math
from dataclasses import replace
from datetime import datetime, timezone

import numpy as np
import pytest

from commission.drive import open_drive
from commission.drive.description import load_description
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


# -- staged write-back (issue #20) -------------------------------------------------------------------
# On the simulated drive's direct link (its own velocity loop takes velocity_kp / velocity_ki, the
# parameters written here): the staging, the check and the restore, without the virtual CAN bus.

#: a simulated drive slower than ideal: a 1 kHz current loop and 2 samples of computation delay
SLOW_DRIVE = {"current_loop_bandwidth_hz": 1000.0, "delay_samples": 2}
LOOP_GAINS = ("velocity_kp", "velocity_ki")


def _gains(settings):
    """The settings' values of the parameters the simulated drive's own loop uses."""
    return [p for p in drive_parameters(settings, load_description("sim")) if p.name in LOOP_GAINS]


def _staged(drive, settings, tmp_path, **kwargs):
    """apply_staged with the sequencer's closed-loop check on ``drive``; returns (report, events)."""
    from commission.config import config_from_dict
    from commission.sequencer import Sequencer
    from commission.tuning import apply_staged, conservative_settings

    config = config_from_dict({"sim": SLOW_DRIVE})
    opt = config.tuning
    seq = Sequencer(config, drive, tmp_path)
    events: list[dict] = []
    n = iter(range(1, 3))
    report = apply_staged(
        drive, _gains(conservative_settings(settings, opt.apply_conservative_fraction)), _gains(settings),
        lambda r: seq.closed_loop_check(r, f"check-{next(n)}.mcap"), opt, torque_limit_nm=config.safety.max_torque_nm,
        sample_rate_hz=config.excitation.sample_rate_hz, log=lambda topic, p: events.append(p), echo=lambda _: None,
        **({"yes": True} | kwargs))
    return report, events


def test_staged_apply_restores_the_previous_values_when_the_check_sees_oscillation(tmp_path) -> None:
    """Settings designed for an ideal drive, applied to a slower one: the conservative set (half
    the gains) passes the step-and-reversal check in the drive's trace, the final set oscillates
    there, and the previous values are back on the drive at once; the log says so and
    --restore-from still finds the old values."""
    from commission.tuning import UncertaintySet

    ideal = design(REFERENCE_PLANT, TuningOptions(ideal_drive=True, uncertainty=UncertaintySet.none(),
                                                  band_factor=None), epsilon_rad=math.radians(0.4))
    with open_drive(sim=True, sim_plant=SLOW_DRIVE) as drive:
        before = {n: drive.read_parameter(n) for n in LOOP_GAINS}
        report, events = _staged(drive, ideal, tmp_path)
        assert not report.applied and report.restored
        first, final = report.checks
        assert first.stage == "conservative" and first.ok
        assert final.stage == "final" and not final.ok
        assert any("oscillation" in r for r in final.reasons)
        assert final.oscillation > 0.05 and final.oscillation_hz is not None and final.oscillation_hz > 100.0
        for n in LOOP_GAINS:
            assert drive.read_parameter(n) == pytest.approx(before[n], rel=1e-12), n
        assert drive.device.velocity_kp == pytest.approx(0.12)  # the device's own loop has its gain back
    kinds = [e["event"] for e in events]
    assert kinds[0] == "old_values" and kinds.count("stage") == 2 and kinds.count("check") == 2
    assert "restore" in kinds and kinds.index("restore") > max(i for i, k in enumerate(kinds) if k == "check")
    restored = [e for e in events[kinds.index("restore"):] if e["event"] == "write"]
    assert {e["name"]: e["value"] for e in restored} == pytest.approx(before)
    assert (tmp_path / "check-1.mcap").is_file() and (tmp_path / "check-2.mcap").is_file()
    old = restore_values({PARAMETER_TOPIC: events}, load_description("sim"))
    assert {p.name: p.value for p in old} == pytest.approx(before)


def test_staged_apply_writes_the_final_set_when_both_checks_pass(tmp_path) -> None:
    """The tool's own design (robust to the slower drive): both checks pass, the final values stay."""
    s = _design()
    with open_drive(sim=True, sim_plant=SLOW_DRIVE) as drive:
        report, events = _staged(drive, s, tmp_path)
        assert report.applied and not report.restored
        assert all(c.ok for c in report.checks) and len(report.checks) == 2
        assert drive.device.velocity_kp == pytest.approx(s.velocity_gain, rel=1e-12)
    assert "restore" not in [e["event"] for e in events]


def test_staged_apply_acknowledges_a_fault_only_with_consent(tmp_path) -> None:
    """The checks must enable the drive: a drive in Fault (here an injected one, as when its
    heartbeat consumer trips while the host identifies) is refused with nothing written unless
    the operator agrees; with consent the fault is acknowledged, logged, and the stages run."""
    from sim_drive.device import InjectedFault

    s = _design()
    with open_drive(sim=True, sim_plant=SLOW_DRIVE) as drive:
        drive.device.inject_fault(InjectedFault.DRIVE_FAULT)
        kp = drive.read_parameter("velocity_kp")
        with pytest.raises(TuningError, match="Fault.*nothing written"):
            _staged(drive, s, tmp_path, yes=False, confirm=lambda q: False)
        assert drive.read_parameter("velocity_kp") == pytest.approx(kp)
        report, events = _staged(drive, s, tmp_path)
        assert report.applied and [e["event"] for e in events][:2] == ["old_values", "fault_reset"]


def test_the_check_reads_overshoot_oscillation_and_vibration() -> None:
    """judge_check on a made-up trace with a known second-order overshoot (ζ = 0.3: 37.2 %), a
    sustained 50 Hz oscillation of 8 % of the step and a 1 kHz torque ripple of 0.1 N·m."""
    from datetime import datetime, timezone

    from commission.recording import Recording
    from commission.tuning.staged import check_reference, judge_check

    fs = 8000.0
    opt = TuningOptions()
    r = check_reference(opt, fs)
    t = np.arange(r.size) / fs
    y = np.zeros_like(r)
    zeta, wn = 0.3, 2 * math.pi * 60.0
    wd = wn * math.sqrt(1 - zeta**2)
    starts = np.flatnonzero(np.diff(r) != 0) + 1
    for a, b in zip(starts, np.r_[starts[1:], r.size]):
        tau = t[a:b] - t[a]
        step = r[a] - r[a - 1]
        resp = 1 - np.exp(-zeta * wn * tau) * (np.cos(wd * tau) + zeta * wn / wd * np.sin(wd * tau))
        y[a:b] = r[a - 1] + step * resp
    y[:starts[0]] = 0.0
    v = opt.velocity_step_rad_s
    osc = 0.08 * v * np.sin(2 * math.pi * 50.0 * t)
    u = 0.2 + 0.1 * math.sqrt(2) * np.sin(2 * math.pi * 1000.0 * t)
    rec = Recording.uniform(fs, u, y + osc, start_time=datetime.now(timezone.utc))
    res = judge_check(rec, r, opt, torque_limit_nm=0.5, stage="final")
    assert res.oscillation == pytest.approx(0.08, rel=0.05)
    assert res.oscillation_hz == pytest.approx(50.0, rel=0.05)
    assert res.vibration == pytest.approx(0.1 / 0.5, rel=0.02)
    assert not res.ok and len(res.reasons) == 2 and "overshoot" not in " ".join(res.reasons)
    clean = judge_check(Recording.uniform(fs, np.full(r.size, 0.2), y, start_time=datetime.now(timezone.utc)),
                        r, opt, torque_limit_nm=0.5, stage="final")
    assert clean.overshoot_pct == pytest.approx(100 * math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2)), abs=0.3)
    assert clean.ok and clean.oscillation < 1e-3 and clean.vibration < 1e-9
    strict = judge_check(Recording.uniform(fs, np.full(r.size, 0.2), y, start_time=datetime.now(timezone.utc)),
                         r, opt.model_copy(update={"apply_check_max_overshoot_pct": 30.0}), torque_limit_nm=0.5,
                         stage="final")
    assert not strict.ok and strict.reasons[0].startswith("overshoot 37 %")
