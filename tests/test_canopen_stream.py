"""Host-streamed CiA 402 on the drive's clock, beside a CPU-bound process: what a busy host may cost
(held setpoints, lost frames) and what it must not (a wrong record); the bus budget; the drive's
identity. The simulated drive is a CANopen node on python-can's virtual bus; the real canopen stack
runs on both ends."""

from __future__ import annotations

import itertools
import json
import math
import struct
import time

import can
import canopen
import numpy as np
import pytest

from commission.cli import main
from commission.config import Config
from commission.drive import State
from commission.drive.canopen import open_simulated, plan_cycle
from commission.drive.canopen.pdo import (
    STREAM_FRAMES, SYNC_COB_ID, SyncedStream, frame_bits, record_signals, slcan_line_bytes,
)
from commission.exceptions import ConfigError, DriveError, RecordingError
from commission.excitation import chirp
from commission.mcaplog import read_recording
from commission.recording import Recording, decode_samples, encode_samples
from commission.sequencer import Sequencer
from sim_drive.device import SimulatedDevice
from sim_drive.plant import Plant, PlantParameters

from busy_host import cpu_hog  # noqa: F401 - a fixture

_channels = itertools.count()
RATED_NM = 0.637


def short_config(**excitation) -> Config:
    return Config(excitation={"duration_s": 1.0, "bias_frequency_hz": 1.0, **excitation})


def streamed(device: SimulatedDevice | None = None, **options):
    options.setdefault("drive", "generic-cia402")
    return open_simulated(device=device, channel=f"test-stream-{next(_channels)}", **options)


# -- the record ----------------------------------------------------------------------------------------
def test_lost_frames_leave_marked_samples_and_the_rest_exact(tmp_path, cpu_hog):
    """2 % of the cyclic frames lost at random (SYNC, TPDO, RPDO): the run completes, the lost cycles
    are marked in the log (and survive it), and every sample that arrived is the plant's own."""
    with streamed(plant={"seed": 2}, link={"frame_loss": 0.02, "seed": 5}) as drive:
        Sequencer(short_config(), drive, tmp_path).run()
        report, dropped = drive.stream_report, drive.simulator.frames_dropped
        applied = np.asarray(drive.simulator.applied_nm)
    rec = read_recording(tmp_path / "run.mcap")
    lost = rec.lost_mask
    assert len(rec) >= 2000 and rec.is_uniform and dropped > 0  # a lost TPDO also pauses the excitation
    # a lost TPDO or SYNC loses its cycle (a lost RPDO only pauses the excitation): about 4 % of 2000
    assert 20 < lost.sum() < 200 and report.lost_cycles == lost.sum()
    assert rec.metadata["lost_samples"] == encode_samples(lost)
    # the plant fed with the recorded torque: exact wherever the drive's TPDO arrived. A lost cycle's torque
    # is the intended one, which the drive may not have applied, so compare up to the first loss only
    first = int(np.argmax(lost))
    exact = Plant(PlantParameters(seed=2)).run_torque(np.concatenate((np.zeros(4), np.repeat(rec.torque_ref, 4))))
    np.testing.assert_array_equal(rec.motor_position[:first], exact.motor_position[4::4][:first])
    # lost positions are interpolated: within a few counts of the neighbours' trend, never a jump
    jumps = np.abs(np.diff(rec.motor_position))
    assert jumps.max() < 60.0 / 2000 * 1.5  # below the peak speed's step (well under 60 rad/s)
    # every received sample's torque is the drive's own for its cycle (one offset, c0 + 1, fits a chirp)
    def same(o: int) -> np.ndarray:  # (the record's per mille × rated, the drive's rated × per mille)
        return np.isclose(rec.torque_ref, applied[o:o + len(rec)], rtol=0, atol=1e-9)

    fits = [o for o in range(applied.size - len(rec) + 1) if same(o)[~lost].all()]
    assert len(fits) == 1
    # (a lost cycle's torque is the setpoint the host meant for it, which a busy host's late answer, held
    # by the drive, can make wrong: how often depends on the machine's load; the hand-fed test below
    # checks the meaning on its own, and the streamed identification that the identifier copes)


def _hand_fed(targets: list[int], period_s: float, cycles: int, lost: dict[int, str] | None = None,
              gap_s: float = 0.005, applied: list[int] | None = None) -> tuple[SyncedStream, list[int]]:
    """The host's side of the stream (SyncedStream) fed a drive's frames by hand on a virtual bus: per cycle
    a SYNC with its counter, then the TPDO latched at it (position 100 × cycle, applied torque 0), either
    lost where ``lost`` says ("sync", "tpdo", "both"); returns the stream and the setpoints the drive got.
    ``applied``: filled with the setpoint the drive applies from each cycle's SYNC on (the last one it got
    before), the drive then waiting for the host's answer to each TPDO the host hears (no late answers)."""
    channel = f"test-hand-fed-{next(_channels)}"
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    drive = can.Bus(interface="virtual", channel=channel)
    tpdo, rpdo = 0x181, 0x201
    try:
        stream = SyncedStream(network, rpdo_cob=rpdo, tpdo_cob=tpdo, period_s=period_s, counter_overflow=240)
        stream.arm(np.asarray(targets, dtype=np.int16), max_cycles=2 * cycles)
        got: list[int] = []

        def received(timeout: float) -> None:
            while (msg := drive.recv(timeout=timeout)) is not None:
                if msg.arbitration_id == rpdo:
                    got.append(SyncedStream.RPDO_STRUCT.unpack(msg.data)[0])
                    if timeout:
                        return

        for cycle in range(1, cycles + 1):
            what = (lost or {}).get(cycle, "")
            if applied is not None:
                received(0.0)
                applied.append(got[-1] if got else 0)
            if what not in ("sync", "both"):
                drive.send(can.Message(arbitration_id=SYNC_COB_ID, data=[cycle], is_extended_id=False))
            if what not in ("tpdo", "both"):
                drive.send(can.Message(arbitration_id=tpdo, data=struct.pack("<ihH", 100 * cycle, 0, 0x1237),
                                       is_extended_id=False))
                if applied is not None:
                    received(2.0)  # the host's answer, before the next SYNC
            time.sleep(gap_s)
        time.sleep(0.2)
        received(0.0)
    finally:
        network.disconnect()
        drive.shutdown()
    return stream, got


@pytest.mark.parametrize("lost", [
    {3: "tpdo", 4: "sync"},  # cycle 3's TPDO and cycle 4's SYNC: the TPDO heard in between is cycle 4's
    {4: "sync"},  # cycle 4's SYNC alone: two TPDOs after cycle 3's SYNC
    {4: "both"},  # cycle 4's SYNC and TPDO: the one TPDO heard is cycle 3's, but that is not known
])
def test_no_cycle_is_given_another_cycles_position(lost: dict[int, str]) -> None:
    """Whatever SYNCs and TPDOs are lost, every sample the record keeps is its own cycle's (found on a busy
    CI machine: a lost TPDO then a lost SYNC put the next cycle's position on a sample, 42 % off the plant's)."""
    stream, _ = _hand_fed(list(range(1, 11)), 1e-3, 11, lost)
    rec = stream.record
    kept = np.flatnonzero(rec.received & ~rec.ambiguous)
    # record index i is the drive's cycle i + 1 (the first SYNC heard is cycle 1); cycles 3 and 4 cannot be
    # told apart in any of the three cases, so both are left out (interpolated and marked in the record)
    np.testing.assert_array_equal(rec.position[kept], 100 * (kept + 1))
    assert set((kept + 1).tolist()) == set(range(1, 12)) - {3, 4}


@pytest.mark.parametrize("lost, unknowable", [
    # TPDO 4, heard after SYNC 3 with TPDO 3 lost, passes for TPDO 3: the drive held cycle 3's setpoint
    # in cycle 4, the host cannot know (the identifier takes a lost cycle's torque as uncertain)
    ({3: "tpdo", 4: "sync"}, {4}),
    ({4: "sync"}, set()),  # two TPDOs after SYNC 3: the answer to the second acts in cycle 5
    ({4: "both"}, set()),  # no answer for cycle 5: the drive holds cycle 4's setpoint
])
def test_the_record_means_the_setpoint_the_drive_applied_in_each_cycle(lost: dict[int, str],
                                                                       unknowable: set[int]) -> None:
    """Whatever SYNCs and TPDOs are lost, the setpoint the record means for a cycle (the torque of a lost
    one) is the one the drive applied there, where the host's answers came in time (found on the lossy
    virtual bus: a lost SYNC's answers were booked a cycle early, a third of the lost cycles' torques off)."""
    applied: list[int] = []
    # (a 20 ms cycle, TPDOs 10 ms apart: answers neither stale nor in bursts, so each is the next setpoint)
    stream, _ = _hand_fed(list(range(1, 11)), 0.02, 11, lost, gap_s=0.01, applied=applied)
    meant = stream.record.meant()
    # record index i is the drive's cycle i + 1
    cycles = [c for c in range(1, 12) if c not in unknowable]
    assert [int(meant[c - 1]) for c in cycles] == [applied[c - 1] for c in cycles]


def test_a_host_late_to_the_end_holds_the_last_setpoint_no_longer_than_the_pause_budget() -> None:
    """A host whose answers all come in bursts (each within a quarter cycle of the one before, the drive
    reporting the setpoint before not yet applied) repeats setpoints, then skips ahead once it is the
    budget behind the drive's clock; at the last setpoint there is nothing to skip to, and the excitation
    ends there, zero torque sent. (It held the last setpoint for as long as the host stayed late: a CI
    run's record came out 2 cycles past the 50 ms the budget allows.)"""
    period = 0.2  # a 50 ms burst window; the budget (50 ms) rounds to one cycle
    targets = [10, 20, 30]
    stream, got = _hand_fed(targets, period, 8, gap_s=0.0)
    assert stream.max_lag_cycles == 1 and stream.catch_ups >= 1
    assert stream.last_target_cycle is not None
    assert len(targets) <= stream.samples() <= len(targets) + stream.max_lag_cycles
    assert got[-1] == 0 and set(got) <= {0, *targets}


def test_a_run_that_lost_most_of_its_cycles_fails_with_the_cause_and_keeps_the_record(tmp_path):
    device = SimulatedDevice()
    drive = streamed(device, link={"frame_loss": 0.3, "seed": 1})
    with pytest.raises(DriveError, match=r"\d+% of cycles lost \(longest gap \d+ ms\): the bus or this host did "
                                         r"not carry the 2000 Hz cycle's feedback; try --rate 1000.*partial log"):
        Sequencer(short_config(), drive, tmp_path).run()
    assert drive.state is State.SWITCH_ON_DISABLED
    rec = read_recording(tmp_path / "run.mcap")
    assert len(rec) > 1000 and rec.metadata["status"].startswith("aborted:") and rec.lost_mask.mean() > 0.2
    drive.close()


def test_the_band_is_checked_on_the_waveform_actually_played():
    """No configured band: the drive refuses a waveform whose played samples exceed the usable band,
    before a single setpoint is sent."""
    device = SimulatedDevice()
    with streamed(device) as drive:
        drive.set_limits(0.5, 50.0, 200.0)
        drive.enable()
        wave = chirp(short_config(f_end_hz=700.0).excitation)
        with pytest.raises(ConfigError, match=r"usable band 400 Hz, below the band of the waveform to play (6[5-9]\d|70\d) Hz"):
            drive.run_excitation(wave.samples, wave.sample_rate_hz)
        assert device.samples_run == 0


def test_streamed_identification_matches_the_plant_beside_a_cpu_hog(tmp_path, cpu_hog):
    """The paper's 10 s experiment streamed at 2 kHz on a busy host that loses 1 % of the bus's frames:
    the identified axis is the plant within the accuracy the direct run reaches (ε ±0.02°, J_m, J_l, K
    ±2 %), and not flagged: the lost cycles' torque is the one the drive applied (with a lost SYNC's
    answers recorded a cycle early, the model needed a torque disturbance of 4.7 % and was flagged)."""
    hybrid = pytest.importorskip("commission.ident.hybrid")
    with streamed(plant={"seed": 4}, link={"frame_loss": 0.01, "seed": 3}) as drive:
        outcome = Sequencer(Config(), drive, tmp_path, identify=hybrid.identify, tune=False).run()
    result, truth = outcome.identification, PlantParameters()
    assert len(outcome.recording) >= 20_000  # 20000 setpoints, and the cycles a late host paused them
    assert outcome.recording.lost_mask.sum() > 100
    assert not result.fit.approximate, result.fit.reasons
    assert math.degrees(result.epsilon_rad) == pytest.approx(truth.epsilon_deg, abs=0.02)
    for name in ("J_m", "J_l", "K"):
        assert getattr(result.parameters, name) == pytest.approx(getattr(truth, name), rel=0.02), name


# -- the budget ------------------------------------------------------------------------------------------
def test_other_traffic_heard_on_the_bus_lowers_the_rate():
    """30 % of a 1 Mbit/s bus taken by other nodes: measured before planning, the cycle slows down."""
    with streamed(link={"bus_load": 0.3}) as drive:
        budget = drive.budget
    assert budget.background_bps == pytest.approx(0.3e6, rel=0.25)
    # SYNC + RPDO + TPDO within 80 % of what is left: 275 bit / (800 - ~300) kbit/s -> 6 ticks of 125 us
    assert budget.rate_hz == pytest.approx(8000 / 6) and budget.load <= 0.8
    assert "limited by bus" in budget.describe()


def test_an_slcan_uart_bounds_the_cycle():
    """Each frame crosses an slcan adapter's UART again as ASCII (8 + 22 bytes, and the adapter's 'z'
    for the host's RPDO): at 115200 bit/s that, not the CAN bus, sets the rate."""
    line = slcan_line_bytes(1) + slcan_line_bytes(8) + 2
    assert line == 32
    budget = plan_cycle(1_000_000, STREAM_FRAMES, 1 / 8000, line_bps=115_200, line_bytes_per_cycle=line)
    assert budget.limited_by == "serial line" and budget.line_load <= 0.8
    assert budget.rate_hz == pytest.approx(8000 / 28)  # 32 B · 10 bit / (0.8 · 115200) = 3.47 ms -> 28 ticks
    fast = plan_cycle(1_000_000, STREAM_FRAMES, 1 / 8000, line_bps=2_000_000, line_bytes_per_cycle=line)
    assert fast.limited_by == "bus" and fast.rate_hz == pytest.approx(2000)
    capped = plan_cycle(1_000_000, STREAM_FRAMES, 1 / 8000, max_rate_hz=1000)
    assert capped.limited_by == "--rate" and capped.rate_hz == pytest.approx(1000)
    assert sum(frame_bits(n) for n in STREAM_FRAMES) == budget.bits_per_cycle == 275


# -- the drive's identity -----------------------------------------------------------------------------------
def test_no_drive_given_picks_the_description_from_the_identity():
    with streamed(drive=None) as drive:
        assert drive.description.name == "sim" and drive.method.value == "trace"
    with streamed(drive=None, link={"identity": (0, 0, "CiA 402 servo drive")}) as drive:
        assert drive.description.name == "generic-cia402" and drive.method.value == "streamed"
    with streamed(drive=None, link={"identity": (0x539, 0x2200001, "SGD7S")}) as drive:
        assert drive.description.name == "yaskawa-sigma7"


def test_a_mismatched_drive_is_refused_before_anything_moves():
    device = SimulatedDevice()
    with pytest.raises(ConfigError, match=r"node 1 is not a 'yaskawa-sigma7' drive: its identity \(0x1018\) is "
                                          r"vendor 0x00000DC0, product 0x402, expected vendor 0x00000539.*"
                                          r"it is a 'sim' drive: use --drive sim"):
        streamed(device, drive="yaskawa-sigma7")
    assert device.samples_run == 0 and device.state is State.SWITCH_ON_DISABLED


def test_cli_refuses_a_mismatched_drive_in_one_line(tmp_path, capsys):
    rc = main(["--sim", "--sim-link", "canopen", "--drive", "yaskawa-sigma7", "--out", str(tmp_path), "--json"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "is not a 'yaskawa-sigma7' drive" in err[0]
    assert not (tmp_path / "run.mcap").exists()


def test_cli_ends_the_chirp_at_the_usable_band_when_allowed(tmp_path, capsys):
    config = tmp_path / "short.yaml"
    config.write_text("excitation: {duration_s: 1.0, bias_frequency_hz: 1.0}\n")
    argv = ["--sim", "--sim-link", "canopen", "--drive", "generic-cia402", "--rate", "1000", "--config", str(config),
            "--no-identify", "--json"]
    assert main([*argv, "--out", str(tmp_path / "refused")]) == 2
    assert "usable band 200 Hz, below the excitation band 400 Hz" in capsys.readouterr().err
    assert main([*argv, "--allow-narrow-band", "--out", str(tmp_path / "narrow")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["recording"]["sample_rate_hz"] == pytest.approx(1000) and doc["recording"]["samples"] >= 1000
    assert "1000 Hz cycle" in doc["recording"]["bus_budget"] and "limited by --rate" in doc["recording"]["bus_budget"]
    rec = read_recording(tmp_path / "narrow" / "run.mcap")
    assert "0.1→200 Hz" in rec.metadata["excitation"]


# -- the lost-samples mark in a Recording --------------------------------------------------------------------
def test_lost_samples_round_trip_as_ranges():
    mask = np.zeros(12, dtype=bool)
    mask[[0, 3, 4, 5, 11]] = True
    assert encode_samples(mask) == "0,3-5,11"
    np.testing.assert_array_equal(decode_samples("0,3-5,11", 12), mask)
    assert encode_samples(np.zeros(3, dtype=bool)) == "" and not decode_samples("", 3).any()
    rec = Recording.uniform(1000.0, np.zeros(12), np.zeros(12), metadata={"lost_samples": "3-5"})
    assert rec.lost_mask.sum() == 3 and rec.head(4).lost_mask.tolist() == [False, False, False, True]
    with pytest.raises(RecordingError, match="'lost_samples': 'x' is not an index"):
        decode_samples("1,x", 4)


def test_a_lost_cycle_is_rebuilt_from_its_neighbours_and_marked():
    """Positions on a cubic (a spline through the received cycles reproduces it exactly), torque as the
    host meant it where the drive's report is missing, velocity the position difference per cycle."""
    n, rate, inc = 40, 2000.0, 2**24
    k = np.arange(n + 1, dtype=np.float64)
    counts = (3 * k**3 - 50 * k**2 + 7 * k + 1000).astype(np.int64)
    applied = np.arange(n + 1) % 7
    intended = (np.arange(1, n + 1) % 7) + 100  # differs from applied: shows which one was used
    received = np.ones(n + 1, dtype=bool)
    received[[5, 17, 18, 30]] = False
    torque, velocity, position, lost = record_signals(counts, applied, intended, received, rate, RATED_NM, inc)
    step = 2 * math.pi / inc
    np.testing.assert_allclose(position, counts[1:] * step, rtol=0, atol=1e-6 * step)
    np.testing.assert_array_equal(lost, ~received[1:])
    np.testing.assert_allclose(torque, np.where(lost, intended, applied[1:]) * RATED_NM / 1000)
    np.testing.assert_allclose(velocity, np.diff(counts) * step * rate, rtol=1e-9)


def test_the_record_ends_once_the_drive_has_applied_the_last_setpoint() -> None:
    """Answers that reach the drive after its next SYNC act a cycle late (the drive holds the one before),
    so near the end it runs behind the host: the record goes on until the drive reports the last setpoint
    applied. (Ending it when the host had sent the last one left the chirp's last steps out of the record
    and unplayed: a CI run's record ended 4–7 setpoints short.)"""
    channel = f"test-late-end-{next(_channels)}"
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    drive = can.Bus(interface="virtual", channel=channel)
    tpdo, rpdo = 0x181, 0x201
    targets, late = [10, 20, 30, 40, 50, 60], set(range(4, 16))  # the answers to these cycles' TPDOs come late
    answers: list[tuple[int, int]] = []  # (first cycle it acts in, setpoint)
    applied: list[int] = []
    try:
        stream = SyncedStream(network, rpdo_cob=rpdo, tpdo_cob=tpdo, period_s=0.02, counter_overflow=240)
        stream.arm(np.asarray(targets, dtype=np.int16), max_cycles=40)
        for cycle in range(1, 16):
            acting = [v for c, v in answers if c <= cycle]
            applied.append(acting[-1] if acting else 0)
            drive.send(can.Message(arbitration_id=SYNC_COB_ID, data=[cycle], is_extended_id=False))
            drive.send(can.Message(arbitration_id=tpdo, data=struct.pack("<ihH", 100 * cycle, applied[-1], 0x1237),
                                   is_extended_id=False))
            msg = drive.recv(timeout=2.0)
            while msg is not None and msg.arbitration_id != rpdo:
                msg = drive.recv(timeout=2.0)
            assert msg is not None
            answers.append((cycle + (2 if cycle in late else 1), SyncedStream.RPDO_STRUCT.unpack(msg.data)[0]))
            time.sleep(0.01)
    finally:
        network.disconnect()
        drive.shutdown()
    n = stream.samples()
    recorded = [int(t) for t in stream.record.torque[1:n + 1]]
    assert recorded == applied[1:n + 1]  # (record index i is the drive's cycle i + 1)
    # every setpoint was applied, in order, and the record holds the last one: one cycle later than planned
    assert [v for i, v in enumerate(recorded) if v and (i == 0 or v != recorded[i - 1])] == targets
    assert recorded[-1] == targets[-1] and len(targets) + 1 <= n <= len(targets) + 1 + stream.max_lag_cycles
