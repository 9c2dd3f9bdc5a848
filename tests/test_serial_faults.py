"""Serial links, bad input and faults: each ends in a quick stop where the link still allows one, a
stopped drive (by the host, or by the drive's own watchdog), a readable partial log where anything could
be recorded, and one clear line. The simulated adapter and device run in this process behind a real pty
(the host side is python-can's slcan client / pymodbus's serial client, unchanged); 1 s runs."""

from __future__ import annotations

import math
import os
import threading
import time

import can
import numpy as np
import pytest

from commission.cli import main
from commission.config import Config
from commission.drive import State, open_drive
from commission.drive.modbus import ExceptionCode, ModbusDrive, crc16, decode_registers, encode_registers
from commission.drive.slcan import WRITE_TIMEOUT_S, CheckedSlcanBus, _valid_frame
from commission.exceptions import DriveError, DriveNotFound, DriveTimeout
from commission.mcaplog import read_recording
from commission.sequencer import Sequencer
from sim_drive.device import SimulatedDevice
from sim_drive.serial_slave import (
    LinkFault,
    ModbusRtuServer,
    PtyLink,
    SlcanAdapter,
    parse_fault,
    parse_slcan_frame,
    slcan_line,
)


def short_config() -> Config:
    return Config(excitation={"duration_s": 1.0, "bias_frequency_hz": 1.0})


def slcan_drive(adapter: SlcanAdapter, **options):
    return open_drive(port=adapter.path, interface="slcan", drive="sim", **options)


def wait_for(condition, timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def stopped(device: SimulatedDevice) -> bool:
    return device.state in (State.SWITCH_ON_DISABLED, State.FAULT) and abs(device._plant.state.v_m) < 0.05


# -- the wire formats -----------------------------------------------------------------------------
def test_modbus_crc_and_register_codec():
    assert crc16(bytes.fromhex("010300000001")) == bytes.fromhex("840A")  # the spec's classic example
    for value, kind in ((-123456, "int32"), (4_000_000_000, "uint32"), (-2, "int16"), (0.25, "real32")):
        for order in ("big", "little"):
            assert decode_registers(encode_registers(value, kind, order), kind, order) == value
    assert encode_registers(0x12345678, "uint32", "big") == [0x1234, 0x5678]
    assert encode_registers(0x12345678, "uint32", "little") == [0x5678, 0x1234]
    assert ExceptionCode(2).meaning.startswith("illegal data address")


def test_slcan_lines():
    import can

    msg = can.Message(arbitration_id=0x581, data=bytes(range(8)), is_extended_id=False)
    line = slcan_line(msg)
    assert line == b"t58180001020304050607\r" and _valid_frame(line.decode())
    back = parse_slcan_frame(line.decode().rstrip("\r"))
    assert back is not None and back.arbitration_id == 0x581 and bytes(back.data) == bytes(range(8))
    for bad in ("t5818000102030405060G\r", "t581800010203\r", "t58\r", "t5819000102030405060708\r"):
        assert not _valid_frame(bad), bad
    assert _valid_frame("T1234567820102\r") and _valid_frame("r7001\r")
    assert parse_fault("crc@40+") == LinkFault("crc", 40, True)
    assert parse_fault("mute") == LinkFault("mute", 1, True)
    with pytest.raises(ValueError, match="bad fault"):
        parse_fault("smoke@3")


# -- port missing, busy, adapter not answering ------------------------------------------------------
@pytest.mark.parametrize("link", [["--interface", "slcan"], ["--protocol", "modbus"]])
def test_missing_port_is_one_line(link, tmp_path, capsys):
    assert main(["--port", "/dev/ttyNOPE7", *link, "--out", str(tmp_path), "--json"]) == 4
    assert capsys.readouterr().err.strip() == "commission: error: port /dev/ttyNOPE7 does not exist"


def test_busy_port():
    with ModbusRtuServer() as server:
        with ModbusDrive(server.path):
            with pytest.raises(DriveError, match=rf"serial port {server.path} is busy: another program holds it"):
                ModbusDrive(server.path)
    with SlcanAdapter() as adapter:
        with slcan_drive(adapter):
            with pytest.raises(DriveError, match=rf"serial port {adapter.path} is busy"):
                slcan_drive(adapter)


def test_adapter_not_answering():
    master, slave = os.openpty()  # a serial port with nothing behind it
    try:
        path = os.ttyname(slave)
        with pytest.raises(DriveTimeout, match=rf"slcan adapter on {path} does not answer \(no reply to the "
                                               r"version query 'V' within 0.5 s\)"):
            open_drive(port=path, interface="slcan", probe_timeout_s=0.5)
        t0 = time.monotonic()
        with pytest.raises(DriveNotFound, match=rf"no Modbus device answers at address 1 on {path} "
                                                r"\(115200 8N1, timeout 0.2 s, 2 tries\)"):
            ModbusDrive(path, timeout_s=0.2, retries=1)
        assert time.monotonic() - t0 < 2
    finally:
        os.close(master)
        os.close(slave)


def test_wrong_line_settings_show_as_corrupt_answers():
    with ModbusRtuServer(faults=(LinkFault("garble", 1, True),)) as server:
        with pytest.raises(DriveNotFound, match=r"no Modbus device answers .*\(2 answers with a bad CRC, 0 cut "
                                                r"short: wrong baud rate or parity\?\)"):
            ModbusDrive(server.path, timeout_s=0.2, retries=1)


# -- garbled, truncated, CRC errors: isolated ones are recovered, persistent ones end the run -------
@pytest.mark.parametrize("kind", ["garble", "truncate"])
def test_slcan_isolated_bad_frame_is_recovered(kind, tmp_path):
    with SlcanAdapter(faults=(LinkFault(kind, 300),)) as adapter:
        with slcan_drive(adapter) as drive:
            outcome = Sequencer(short_config(), drive, tmp_path).run()
            assert drive.bus.garbled == 1
    assert len(outcome.recording) == 8000 and read_recording(tmp_path / "run.mcap").metadata["status"] == "complete"


def test_slcan_persistent_garbage_ends_the_run_with_its_diagnosis(tmp_path):
    with SlcanAdapter(faults=(LinkFault("garble", 300, True),)) as adapter:
        drive = slcan_drive(adapter)
        with pytest.raises(DriveError, match=r"the adapter sent \d+ garbled frame line\(s\) \(last 't5.*'\)"):
            Sequencer(short_config(), drive, tmp_path).run()
        drive.close()
        # the SDO answers never arrive, so the host cannot stop it; closing stops our heartbeat, and the
        # drive's consumer (0x1016) stops the axis
        assert wait_for(lambda: stopped(adapter.device))


@pytest.mark.parametrize("kind", ["crc", "truncate", "garble"])
def test_modbus_isolated_bad_answer_is_retried(kind, tmp_path):
    with ModbusRtuServer(faults=(LinkFault(kind, 200),)) as server:
        with ModbusDrive(server.path) as drive:
            outcome = Sequencer(short_config(), drive, tmp_path).run()
            assert drive.stats["crc"] + drive.stats["short"] >= 1
    assert len(outcome.recording) == 8000


def test_modbus_persistent_crc_errors_end_the_run_and_the_stop_is_still_sent(tmp_path):
    device = SimulatedDevice()
    with ModbusRtuServer(device, faults=(LinkFault("crc", 200, True),), pace=1.0) as server:
        drive = ModbusDrive(server.path, timeout_s=0.2)
        with pytest.raises(DriveTimeout, match=r"no valid Modbus answer from device 1 on .* after 3 tries "
                                               r"\(timeout 0.2 s, 115200 8N1\); answers: 3 with a bad CRC.*"
                                               r"stopping the drive also failed: quick stop and disable were sent "
                                               r"but cannot be confirmed"):
            Sequencer(short_config(), drive, tmp_path).run()
        drive.close()
        # the requests reach the drive (only its answers are corrupt): the blind quick stop acted
        assert wait_for(lambda: device.state is State.SWITCH_ON_DISABLED) and device.progress[0] > 0
        assert abs(device._plant.state.v_m) < 0.05


# -- Modbus exception responses -----------------------------------------------------------------------
def test_modbus_exception_names_its_code_and_meaning(tmp_path):
    device = SimulatedDevice(trace_capacity=4000)  # the 1 s waveform (8000 samples) does not fit
    with ModbusRtuServer(device) as server, ModbusDrive(server.path) as drive:
        with pytest.raises(DriveError, match=r"Modbus exception 0x03 \(illegal data value: the device refused the "
                                             r"value\) from device 1 on .* writing the waveform length \(register "
                                             r"0x0200\); nothing was recorded"):
            Sequencer(short_config(), drive, tmp_path).run()
        assert drive.state is State.SWITCH_ON_DISABLED and device.trace_length == 0
        drive.write_parameter("velocity_kp", 0.25)
        assert device.velocity_kp == pytest.approx(0.25) and drive.read_parameter("velocity_kp") == pytest.approx(0.25)
        with pytest.raises(DriveError, match="has no parameter 'Pn100'"):
            drive.write_parameter("Pn100", 1)


def test_wrong_register_map_is_refused_before_anything_moves():
    from commission.drive.description import load_description

    desc = load_description("sim")
    other = desc.model_copy(update={"modbus": desc.modbus.model_copy(update={"device_type": 0x1234})})
    with ModbusRtuServer() as server:
        with pytest.raises(DriveError, match=r"device 1 on .* is not a 'sim' drive \(device type 0x0192, expected "
                                             r"0x1234\): choose its description with --drive"):
            ModbusDrive(server.path, drive=other)
    with pytest.raises(Exception, match="parameter access only"):
        ModbusDrive("/dev/null", drive="yaskawa-sigma7")


# -- cable pulled mid-run ---------------------------------------------------------------------------------
def test_slcan_cable_pulled_mid_run(tmp_path):
    with SlcanAdapter(faults=(LinkFault("hangup", 3000),), pace=1.0) as adapter:
        drive = slcan_drive(adapter)
        with pytest.raises(DriveError, match=r"(cable pulled|heartbeat of node 1 lost)"):
            Sequencer(short_config(), drive, tmp_path).run()
        t0 = time.monotonic()
        drive.close()
        assert time.monotonic() - t0 < 2.0
        # the drive's heartbeat consumer stops the axis on its own
        assert wait_for(lambda: adapter.device.state is State.FAULT and stopped(adapter.device))
        assert adapter.device.progress[0] >= 3000


def test_a_host_that_stops_reading_blocks_neither_the_device_nor_its_hang_up():
    """A pty holds ~20 kB for a host that does not read; beyond that the device drops what it sends
    (as a serial line does) and stays able to close. A write that blocked held the link's lock, and
    the adapter's close() then waited for it for ever: a test's teardown hung CI."""
    link = PtyLink()
    link.WRITE_STALL_S = 0.1
    line = b"t701105\r"  # a heartbeat, as the adapter forwards it
    ended = threading.Event()

    def device_sends() -> None:
        while link.write(line * 50):
            pass
        ended.set()

    threading.Thread(target=device_sends, daemon=True).start()
    assert wait_for(lambda: link.dropped_bytes > 0, 10.0), "the device's write blocks while the host reads nothing"
    held = os.open(link.path, os.O_RDONLY | os.O_NONBLOCK)  # the host opens the port and reads again
    try:
        assert wait_for(lambda: len(os.read(held, 65536)) > 0, 3.0)
        t0 = time.monotonic()
        link.hang_up()
        assert time.monotonic() - t0 < 2.0
        assert ended.wait(3.0), "the device's writes go on after the hang-up"
        assert link.bytes_out > 4096  # what the pty held reached the host; only the rest was dropped
    finally:
        os.close(held)


def test_an_adapter_that_takes_nothing_fails_the_send_instead_of_blocking_the_host():
    """A hung adapter (here: a pty nobody reads) fills the port's buffer; the host's next send fails
    within the write timeout with its cause, where python-can's would wait for ever."""
    master, slave = os.openpty()
    bus = CheckedSlcanBus(os.ttyname(slave), sleep_after_open=0)
    try:
        msg = can.Message(arbitration_id=0x201, data=bytes(8), is_extended_id=False)
        t0 = time.monotonic()
        with pytest.raises(can.CanOperationError, match=r"cannot write \(Write timeout\): it took nothing for 2 s"):
            for _ in range(10_000):  # 250 kB: far beyond what the pty holds
                bus.send(msg)
        assert time.monotonic() - t0 < 10 * WRITE_TIMEOUT_S
        with pytest.raises(can.CanOperationError, match="it took nothing"):
            bus.send(msg)  # the link is known to be gone: at once
    finally:
        bus.serialPortOrig.write_timeout = 0  # shutdown's own "C" must not wait either
        bus.shutdown()
        os.close(master)
        os.close(slave)


def test_modbus_cable_pulled_mid_run(tmp_path):
    with ModbusRtuServer(faults=(LinkFault("hangup", 3000),), pace=1.0) as server:
        drive = ModbusDrive(server.path)
        with pytest.raises(DriveError, match=r"serial link to device 1 on .* lost reading .*cable pulled.*"
                                             r"nothing was recorded"):
            Sequencer(short_config(), drive, tmp_path).run()
        drive.close()
        assert wait_for(lambda: server.device.state is State.FAULT and stopped(server.device))
        assert int(server.device.error_code) == 0x8130


def test_modbus_fault_mid_run_keeps_the_partial_trace(tmp_path):
    from sim_drive.device import InjectedFault

    device = SimulatedDevice()
    device.inject_fault(InjectedFault.DRIVE_FAULT, at_sample=3000)
    with ModbusRtuServer(device) as server, ModbusDrive(server.path) as drive:
        with pytest.raises(DriveError, match=r"drive fault 0x5000 \(drive hardware fault\) after 0.375 s of 1 s; "
                                             r"partial log"):
            Sequencer(short_config(), drive, tmp_path).run()
    rec = read_recording(tmp_path / "run.mcap")
    assert len(rec) == 3000 and rec.metadata["status"].startswith("aborted: drive fault 0x5000")
    assert np.all(np.isfinite(rec.motor_velocity)) and math.isfinite(rec.duration_s)


def test_the_modbus_map_names_every_parameter_of_the_canopen_description():
    """A tuning result written back by name works the same over both protocols of the simulated drive."""
    from commission.drive.description import load_description

    desc = load_description("sim")
    assert desc.modbus is not None
    assert set(desc.parameters) <= set(desc.modbus.parameters)
    for name, spec in desc.modbus.parameters.items():
        if name in desc.parameters:
            assert (spec.min, spec.max) == (desc.parameters[name].min, desc.parameters[name].max), name
