"""Pieces of the CANopen backend checked on their own: bus budget, descriptions, block SDO, cyclic device."""

import os
import shutil
from pathlib import Path

import canopen
import numpy as np
import pytest

from commission.config import Config
from commission.drive.canopen import (
    block_transfer_frames,
    frame_bits,
    interpolation_period,
    plan_cycle,
    waveform_band_hz,
)
from commission.drive.cia402 import Command, Mode, State
from commission.drive.description import DRIVERS_ENV, ExcitationMethod, drivers_dir, list_drives, load_description
from commission.exceptions import ConfigError
from commission.excitation import chirp
from sim_drive.canopen_slave import CanopenSlave, sim_eds_path
from sim_drive.device import ErrorCode, SimulatedDevice
from sim_drive.plant import Plant


# -- bus budget ----------------------------------------------------------------------------------
def test_worst_case_frame_bits_match_the_published_formula():
    # 8n + 47 + floor((34 + 8n - 1) / 4) (Davis et al. 2007): 55 bit for an empty frame, 135 for 8 bytes
    assert [frame_bits(n) for n in (0, 2, 4, 8)] == [55, 75, 95, 135]
    assert frame_bits(8, extended_id=True) == 64 + 67 + (54 + 64 - 1) // 4


def test_cycle_plan_at_1_mbit_gives_2_khz_and_a_400_hz_band():
    budget = plan_cycle(1_000_000, (0, 2, 8, 4), 1 / 8000, max_load=0.8)
    assert budget.bits_per_cycle == 360
    assert budget.cycle_s == pytest.approx(500e-6) and budget.rate_hz == pytest.approx(2000)
    assert budget.usable_band_hz == pytest.approx(400) and budget.load <= 0.8
    # 360 bit / 200 kbit/s = 1.8 ms -> 15 ticks = 1.875 ms, which 0x60C2 cannot state (187.5e-5 s): 2 ms
    slow = plan_cycle(250_000, (0, 2, 8, 4), 1 / 8000)
    assert slow.rate_hz == pytest.approx(500) and slow.load <= 0.8
    assert interpolation_period(500e-6) == (50, -5) and interpolation_period(1.875e-3) is None
    assert plan_cycle(1_000_000, (0, 2, 8, 4), 1 / 8000, background_bps=2 * 550).load <= 0.8


def test_waveform_band_of_the_papers_chirp():
    wave = chirp(Config().excitation)
    assert waveform_band_hz(wave.samples, wave.sample_rate_hz) == pytest.approx(400, rel=0.02)


# -- drive descriptions --------------------------------------------------------------------------
def test_the_three_drive_families_load():
    assert set(list_drives()) >= {"sim", "generic-cia402", "yaskawa-sigma7"}
    sim = load_description("sim")
    assert sim.excitation is ExcitationMethod.TRACE and sim.trace is not None
    assert set(sim.trace.channels) == {"torque_ref", "motor_position", "motor_velocity", "load_position", "load_velocity"}
    assert load_description("generic-cia402").excitation is ExcitationMethod.STREAMED
    for name in ("sim", "generic-cia402", "yaskawa-sigma7"):
        desc = load_description(name)
        od = canopen.import_od(str(desc.eds_path), 1)
        for ref in (0x6040, 0x6041, 0x6060, 0x6064, 0x606C, 0x6071, 0x6072, 0x6076, 0x6077, 0x6080):
            assert ref in od, (name, hex(ref))


def test_yaskawa_parameters_are_all_there_and_all_marked_for_confirmation():
    desc = load_description("yaskawa-sigma7")
    pn = {spec.note.split()[0] for spec in desc.parameters.values()}
    assert pn == {"Pn100", "Pn101", "Pn102", "Pn103", "Pn216", "Pn401", "Pn408", "Pn409", "Pn40A", "Pn40B", "Pn40C",
                  "Pn230", "Pn231", "Pn233"}
    od = canopen.import_od(str(desc.eds_path), 1)
    for spec in desc.parameters.values():
        assert spec.object.index in od
    text = (desc.folder / "description.yaml").read_text()
    blocks = text.split("\nparameters:\n")[1].split("\n  ")
    entries = [b for b in blocks if b and not b.startswith(" ") and not b.startswith("#")]
    assert len(entries) == len(desc.parameters)
    assert all("confirm against the drive's manual before use on hardware" in e for e in entries)
    eds = desc.eds_path.read_text()
    assert eds.count("; vendor-specific: confirm against the drive's manual") == len(desc.parameters)


def test_unknown_drive_and_the_environment_variable(tmp_path, monkeypatch):
    with pytest.raises(ConfigError, match="unknown drive 'nope'.*generic-cia402"):
        load_description("nope")
    shutil.copytree(drivers_dir() / "sim", tmp_path / "mine")
    monkeypatch.setenv(DRIVERS_ENV, str(tmp_path))
    assert list_drives() == ["mine"] and load_description("mine").name == "sim"
    (tmp_path / "mine" / "description.yaml").write_text("name: x\neds: sim.eds\nexcitation: trace\n")
    with pytest.raises(ConfigError, match="excitation 'trace' needs a 'trace' section"):
        load_description("mine")
    monkeypatch.setenv(DRIVERS_ENV, str(tmp_path / "missing"))
    with pytest.raises(ConfigError, match="COMMISSION_DRIVERS"):
        drivers_dir()
    monkeypatch.delenv(DRIVERS_ENV)
    assert (drivers_dir() / "sim" / "sim.eds").is_file()


# -- SDO block transfer against the simulated node's server ---------------------------------------
@pytest.fixture()
def node_pair():
    slave = CanopenSlave(channel=f"blk-{os.getpid()}").start()
    net = canopen.Network()
    net.connect(interface="virtual", channel=f"blk-{os.getpid()}")
    node = net.add_node(1, str(sim_eds_path()))
    yield slave, node
    net.disconnect()
    slave.close()


@pytest.mark.parametrize("n_bytes", [4, 8, 7 * 127, 7 * 127 + 4, 7 * 127 * 2, 40_000])
def test_block_download_and_upload_round_trip(node_pair, n_bytes):
    slave, node = node_pair
    data = np.random.default_rng(n_bytes).integers(-(2**31), 2**31, n_bytes // 4, dtype=np.int64)
    payload = data.astype("<i4").tobytes()
    with node.sdo[0x2100][1].open("wb", size=len(payload), block_transfer=True) as f:
        f.write(payload)
    np.testing.assert_array_equal(slave._raw_wave, data.astype(np.int32))
    with node.sdo[0x2100][1].open("rb", block_transfer=True) as f:
        assert f.read() == payload  # the upload's CRC was checked by the client


def test_block_frame_count_formula():
    assert block_transfer_frames(7 * 127) == 2 + 127 + 1 + 2
    assert block_transfer_frames(320_000) == 2 + 45_715 + 360 + 2


def test_block_download_larger_than_the_buffer_is_aborted_at_once(node_pair):
    slave, node = node_pair
    too_big = 4 * (slave.device.trace_capacity + 1)
    with pytest.raises(canopen.SdoAbortedError) as err:
        node.sdo[0x2100][1].open("wb", size=too_big, block_transfer=True)
    assert err.value.code == 0x05040005


# -- the device's host-streamed mode ----------------------------------------------------------------
def _enabled(dev: SimulatedDevice) -> SimulatedDevice:
    for command in (Command.SHUTDOWN, Command.SWITCH_ON, Command.ENABLE_OPERATION):
        dev.write_controlword(command)
    return dev


def test_step_cyclic_is_the_plant_with_held_targets():
    dev = _enabled(SimulatedDevice())
    targets = 0.05 * np.sin(np.arange(200) / 7)
    ticks = np.r_[1, np.full(199, 4)]  # first SYNC: one tick; then 4 ticks per cycle (2 kHz)
    latched = []
    previous = 0.0
    for target, n in zip(targets, ticks):
        refs = np.full(n, previous)
        refs[-1] = target
        latched.append(dev.step_cyclic(refs).motor_velocity)
        previous = target
    per_tick = np.concatenate([np.r_[np.full(n - 1, p), t] for p, t, n in zip(np.r_[0.0, targets[:-1]], targets, ticks)])
    expected = Plant(dev.plant_parameters).run_torque(per_tick).motor_velocity[np.cumsum(ticks) - 1]
    np.testing.assert_array_equal(latched, expected)


def test_step_cyclic_trips_the_torque_limit_and_does_nothing_unless_enabled():
    dev = SimulatedDevice()
    assert dev.step_cyclic(np.full(4, 0.1)) is None and dev.samples_run == 0
    _enabled(dev)
    dev.set_limits(0.2, 100.0)
    dev.step_cyclic(np.full(4, 0.1))
    dev.step_cyclic(np.full(4, 0.3))
    assert dev.state is State.FAULT and dev.error_code is ErrorCode.OVERCURRENT


def test_sim_drive_module_runs_a_node_for_a_while():
    from sim_drive.__main__ import build_parser, main

    args = build_parser().parse_args(["--canopen", "--interface", "virtual", "--channel", "x"])
    assert args.canopen and args.node_id == 1 and args.interface == "virtual"
    assert main(["--canopen", "--interface", "virtual", "--channel", "main-test", "--run-for", "0.2"]) == 0
    with pytest.raises(SystemExit):
        build_parser().parse_args([])  # a link must be chosen


def test_eds_files_are_where_the_package_finds_them():
    assert Path(sim_eds_path()).is_file()
    assert Mode.CYCLIC_SYNC_TORQUE == 10


def test_block_server_forgets_a_transfer_the_client_abandoned():
    """canopen's client can give up a block download without an abort frame: the server's
    protocol timeout must bring it back to serving ordinary requests."""
    import canopen

    from sim_drive.canopen_slave import BlockSdoServer

    node = canopen.LocalNode(5, canopen.ObjectDictionary())
    server = BlockSdoServer(0x600 + 5, 0x580 + 5, node)
    sent = []
    server.send_response = lambda data: sent.append(bytes(data))  # type: ignore[method-assign]
    server._mode = "down"  # mid-transfer, as after a failed block download
    server._last_frame_s = 100.0
    upload_1000 = bytearray([0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0])  # upload 0x1000:00
    server.on_request(0x605, upload_1000, 100.0 + 2 * BlockSdoServer.BLOCK_TIMEOUT_S)
    assert server._mode == "idle"
    assert sent and sent[-1][0] == 0x80  # a proper answer (abort: 0x1000 is not in this dictionary)
