"""The commissioning sequence on the simulated drive: envelope first, safe stop on every path, log always."""

import numpy as np
import pytest

from commission.config import Config, SafetyConfig
from commission.drive import DriveError, State, open_drive
from commission.drive.sim import SimDrive
from commission.exceptions import Aborted, DriveFault, DriveNotFound, DriveTimeout, SafetyLimitExceeded
from commission.mcaplog import read_recording
from commission.sequencer import Sequencer
from sim_drive.device import InjectedFault, SimulatedDevice
from sim_drive.plant import Plant, PlantParameters


def short_config(**safety) -> Config:
    """A 1 s version of the paper's experiment (same band) for fast tests."""
    return Config(excitation={"duration_s": 1.0, "bias_frequency_hz": 1.0}, safety=SafetyConfig(**safety))


def test_full_run_logs_the_chirp_and_the_plant_response(tmp_path):
    cfg = Config()
    with open_drive(sim=True, sim_plant={"seed": 3}) as drive:
        outcome = Sequencer(cfg, drive, tmp_path).run()
        assert drive.state is State.SWITCH_ON_DISABLED
    rec = read_recording(tmp_path / "run.mcap")
    assert len(rec) == 80_000
    np.testing.assert_array_equal(rec.torque_ref, outcome.waveform.samples)
    # the motor velocity is the plant's response to exactly this torque (independent run of the plant)
    expected = Plant(PlantParameters(seed=3)).run_torque(outcome.waveform.samples)
    np.testing.assert_array_equal(rec.motor_velocity, expected.motor_velocity)
    np.testing.assert_array_equal(rec.load_position, expected.load_position)
    assert rec.metadata["status"] == "complete"
    assert rec.drive.backend == "sim"


def test_envelope_refusal_happens_before_the_drive_is_touched(tmp_path):
    drive = SimDrive()
    with pytest.raises(SafetyLimitExceeded):
        Sequencer(short_config(max_speed_rad_s=1.0), drive, tmp_path).run()
    assert drive.device.samples_run == 0 and drive.state is State.SWITCH_ON_DISABLED
    assert not (tmp_path / "run.mcap").exists()


def test_drive_fault_mid_run_leaves_it_disabled_and_the_partial_log_readable(tmp_path):
    device = SimulatedDevice()
    device.inject_fault(InjectedFault.ENCODER_FAULT, at_sample=3000)
    drive = SimDrive(device)
    with pytest.raises(DriveFault, match=r"0x7305 \(encoder fault\).*partial log"):
        Sequencer(short_config(), drive, tmp_path).run()
    assert drive.state is State.FAULT  # torque off; a fault needs a human to acknowledge it
    rec = read_recording(tmp_path / "run.mcap")
    assert len(rec) == 3000 and rec.metadata["status"].startswith("aborted: drive fault 0x7305")


def test_speed_limit_in_the_drive_is_the_second_layer(tmp_path):
    # the planning model says "slow" (heavy, damped), the real plant is light: the drive trips
    cfg = Config(
        excitation={"duration_s": 1.0, "bias_frequency_hz": 1.0},
        safety={"max_speed_rad_s": 8.0, "planning_inertia_kg_m2": 1e-2, "planning_damping_nm_s_per_rad": 0.1},
    )
    drive = SimDrive()
    with pytest.raises(DriveFault, match="speed limit"):
        Sequencer(cfg, drive, tmp_path).run()
    rec = read_recording(tmp_path / "run.mcap")
    assert np.max(np.abs(rec.motor_velocity)) > 8.0 > np.max(np.abs(rec.motor_velocity[:-1]))


def test_ctrl_c_stops_and_disables(tmp_path):
    drive = SimDrive()

    def progress(label, done, total):
        if done > 2000:
            raise KeyboardInterrupt

    with pytest.raises(Aborted, match="drive stopped and disabled; partial log"):
        Sequencer(short_config(), drive, tmp_path, progress=progress).run()
    assert drive.state is State.SWITCH_ON_DISABLED
    assert abs(drive.device._plant.state.v_m) < 0.05  # quick stop braked the axis
    assert 2000 < len(read_recording(tmp_path / "run.mcap")) < 8000


def test_communication_loss_is_a_timeout_and_the_drive_stops_itself(tmp_path):
    device = SimulatedDevice()
    device.inject_fault(InjectedFault.COMMUNICATION_LOSS, at_sample=1000)
    drive = SimDrive(device)
    with pytest.raises(DriveTimeout, match="communication lost.*nothing was recorded"):
        Sequencer(short_config(), drive, tmp_path).run()
    assert device.state is State.FAULT and abs(device._plant.state.v_m) < 0.05
    drive.close()  # must not raise with the link gone


def test_refuses_a_drive_in_fault(tmp_path):
    device = SimulatedDevice()
    device.inject_fault(InjectedFault.DRIVE_FAULT)
    with pytest.raises(DriveFault, match="reset it first"):
        Sequencer(short_config(), SimDrive(device), tmp_path).run()


def test_unknown_ports():
    with pytest.raises(DriveNotFound, match="/dev/ttyNOPE0 does not exist"):
        open_drive(port="/dev/ttyNOPE0")
    with pytest.raises(DriveError, match="cannot open CAN interface 'socketcan' channel 'nocan7'"):
        open_drive(port="nocan7")  # no such SocketCAN link on any machine
    with pytest.raises(DriveError, match="cannot open serial port /dev/null"):
        open_drive(port="/dev/null", protocol="modbus")
    with pytest.raises(DriveNotFound, match="no drive given"):
        open_drive()


def test_unwritable_output_folder_is_refused_before_anything_moves(tmp_path):
    from commission.exceptions import OutputError

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    drive = SimDrive()
    with pytest.raises(OutputError, match="cannot create output folder"):
        Sequencer(short_config(), drive, blocker / "out").run()
    assert drive.device.samples_run == 0
