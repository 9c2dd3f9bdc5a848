"""The simulated drive's behaviour: CiA 402, waveform player and trace, limits, faults."""

import numpy as np
import pytest

from commission.drive.cia402 import Command, Mode, State
from sim_drive.device import ErrorCode, InjectedFault, SimulatedDevice
from sim_drive.plant import PlantParameters


def enabled(device: SimulatedDevice, mode: Mode = Mode.CYCLIC_SYNC_TORQUE) -> SimulatedDevice:
    device.write_controlword(Command.SHUTDOWN)
    device.write_controlword(Command.SWITCH_ON)
    device.write_mode(mode)
    device.write_controlword(Command.ENABLE_OPERATION)
    assert device.state is State.OPERATION_ENABLED
    return device


def play(device: SimulatedDevice, chunk: int = 100) -> None:
    device.start()
    while device.playing:
        device.advance(chunk)


def test_power_up_state_and_refuses_to_play_unless_enabled():
    dev = SimulatedDevice()
    assert dev.state is State.SWITCH_ON_DISABLED
    dev.load_waveform(np.zeros(10))
    with pytest.raises(RuntimeError, match="cannot start"):
        dev.start()


def test_trace_is_the_played_waveform_and_the_plant_response():
    dev = enabled(SimulatedDevice())
    wave = 0.05 * np.sin(2 * np.pi * 20 * np.arange(4000) / 8000)
    dev.load_waveform(wave)
    play(dev, chunk=333)  # odd chunk: the player must not care
    tr = dev.trace()
    assert len(tr) == wave.size
    np.testing.assert_array_equal(tr.torque_ref, wave)
    assert np.max(np.abs(tr.motor_velocity)) > 0.1
    assert not dev.playing and dev.state is State.OPERATION_ENABLED


def test_speed_limit_trips_a_fault_and_the_drive_brakes():
    dev = enabled(SimulatedDevice())
    dev.set_limits(max_torque_nm=1.0, max_speed_rad_s=5.0)
    dev.load_waveform(np.full(8000, 0.3))  # accelerates well beyond 5 rad/s
    play(dev)
    assert dev.state is State.FAULT and dev.error_code is ErrorCode.OVERSPEED
    tr = dev.trace()
    assert abs(tr.motor_velocity[-1]) > 5.0 and np.all(np.abs(tr.motor_velocity[:-1]) <= 5.0)
    assert len(tr) < 8000


def test_torque_limit_trips_before_the_sample_is_applied():
    dev = enabled(SimulatedDevice())
    dev.set_limits(max_torque_nm=0.2, max_speed_rad_s=100.0)
    wave = np.linspace(0, 0.3, 1000)
    dev.load_waveform(wave)
    play(dev)
    assert dev.error_code is ErrorCode.OVERCURRENT
    assert np.max(np.abs(dev.trace().torque_ref)) <= 0.2


def test_travel_limit_is_relative_to_where_it_was_set():
    dev = enabled(SimulatedDevice())
    dev.set_limits(1.0, 100.0, max_travel_rad=0.5)
    dev.load_waveform(np.full(8000, 0.1))
    play(dev)
    assert dev.error_code is ErrorCode.POSITION_LIMIT


@pytest.mark.parametrize(
    "kind, code",
    [(InjectedFault.DRIVE_FAULT, ErrorCode.DRIVE_HARDWARE), (InjectedFault.ENCODER_FAULT, ErrorCode.ENCODER),
     (InjectedFault.COMMUNICATION_LOSS, ErrorCode.COMMUNICATION)],
)
def test_injected_fault_mid_run_keeps_the_trace_before_it(kind, code):
    dev = enabled(SimulatedDevice())
    dev.load_waveform(0.05 * np.ones(2000))
    dev.inject_fault(kind, at_sample=700)
    play(dev, chunk=256)
    assert dev.state is State.FAULT and dev.error_code is code
    assert len(dev.trace()) == 700
    assert dev.communication_lost is (kind is InjectedFault.COMMUNICATION_LOSS)


def test_fault_reset_on_rising_edge_only():
    dev = enabled(SimulatedDevice())
    dev.inject_fault(InjectedFault.DRIVE_FAULT)
    assert dev.state is State.FAULT
    dev.write_controlword(0x80)
    assert dev.state is State.SWITCH_ON_DISABLED and dev.error_code is ErrorCode.NONE


def test_quick_stop_brakes_to_rest_and_disables():
    dev = enabled(SimulatedDevice(PlantParameters(epsilon_deg=0.0)))
    dev.load_waveform(np.full(4000, 0.1))
    play(dev)
    assert abs(dev._plant.state.v_m) > 3.0
    dev.write_controlword(Command.QUICK_STOP)
    assert dev.state is State.SWITCH_ON_DISABLED
    assert abs(dev._plant.state.v_m) < 0.05


def test_velocity_mode_follows_the_reference():
    dev = enabled(SimulatedDevice(), Mode.CYCLIC_SYNC_VELOCITY)
    t = np.arange(16000) / 8000
    ref = 1.5 * np.sin(2 * np.pi * 0.5 * t)
    dev.load_waveform(ref)
    play(dev)
    v = dev.trace().motor_velocity
    err = np.abs(v[4000:] - ref[4000:])
    assert np.median(err) < 0.1  # rad/s; the PI loop tracks a 0.5 Hz sine closely
