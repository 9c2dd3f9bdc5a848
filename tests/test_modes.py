"""Every row of the README's "Modes" table, run as a user runs it (``commission.cli.main([...])``
in-process; the serial rows as two processes on a pty in test_serial_e2e.py), and checked for what
the row says it does. ``test_every_readme_mode_has_its_test`` keeps the table and the tests together.

Modes that only need *a* run use the shipped 2 s recipe (``--config quick``; it identifies the
reference plant as the 10 s default does); the paper's method needs the default's 0.1 Hz bins.
"""

from __future__ import annotations

import importlib
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import CliRun, run_cli

from commission.csvlog import write_csv
from commission.mcaplog import read_config, read_recording, read_results

README = Path(__file__).resolve().parents[1] / "README.md"
EPSILON_DEG = 0.40  # the backlash of the shipped recipes' simulated plant (configs/default.yaml, sim)
STEP = 2 * math.pi / 2**24  # rad per increment of the simulated 24-bit encoders

#: README "Modes" row (its first cell) -> the tests that run it
ROW_TESTS = {
    "simulated drive": ["test_modes::test_sim"],
    "simulated drive, other recipe / folder / noise seed": [
        "test_modes::test_other_recipe_and_folder", "test_modes::test_noise_seed"],
    "CANopen drive (CiA 402)": ["test_modes::test_canopen_port"],
    "the simulated drive over CANopen": ["test_modes::test_sim_over_canopen"],
    "streamed fallback, simulated": ["test_modes::test_streamed_fallback"],
    "the paper's method instead of the default": ["test_modes::test_paper_method"],
    "write the settings to the drive": ["test_modes::test_apply_then_restore"],
    "put the previous values back": ["test_modes::test_apply_then_restore"],
    "softer or stiffer tuning": ["test_modes::test_presets"],
    "independent backlash check (paper §4.2)": ["test_modes::test_measure_backlash"],
    "serial-line CAN adapter (slcan)": ["test_serial_e2e::test_canopen_through_an_slcan_adapter_in_a_second_process"],
    "serial service port (Modbus RTU / MEMOBUS)": ["test_serial_e2e::test_modbus_rtu_in_a_second_process"],
    "the simulated drive on a pty": ["test_serial_e2e::test_canopen_through_an_slcan_adapter_in_a_second_process",
                                     "test_serial_e2e::test_modbus_rtu_in_a_second_process"],
    "replay an MCAP log": ["test_modes::test_replay_mcap"],
    "replay a CSV file": ["test_modes::test_replay_csv"],
    "fleet: many logs on Dask": ["test_fleet::test_the_table_reads_with_pyarrow_one_row_per_log",
                                 "test_fleet::test_on_an_existing_scheduler_a_rerun_identifies_only_new_logs"],
    "machine-readable output": ["test_modes::test_json"],
}


def readme_modes() -> list[str]:
    """First cells of the rows of the README's "Modes" table."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Modes"):]
    section = section[: section.index("\n## ", 1)] if "\n## " in section[1:] else section
    rows = [line for line in section.splitlines() if line.startswith("|")]
    return [row.split("|")[1].strip() for row in rows[2:]]  # past the header and its rule


def test_every_readme_mode_has_its_test() -> None:
    assert readme_modes() and set(readme_modes()) == set(ROW_TESTS)
    for tests in ROW_TESTS.values():
        for ref in tests:
            module, name = ref.split("::")
            assert callable(getattr(importlib.import_module(module), name, None)), ref


def _result(run: CliRun) -> dict:
    return json.loads((run.out / "result.json").read_text())


def _controller(run: CliRun) -> dict:
    return json.loads((run.out / "controller.json").read_text())


# -- simulated drive ------------------------------------------------------------------------------
def test_sim(default_sim_run: CliRun) -> None:
    """`commission --sim`: the whole commissioning; the model and the backlash of the simulated plant."""
    out, doc = default_sim_run.out, default_sim_run.doc
    for name in ("run.mcap", "result.json", "controller.json", "report.html"):
        assert (out / name).is_file(), name
    ident = _result(default_sim_run)
    assert ident["backlash"]["epsilon_deg"] == pytest.approx(EPSILON_DEG, abs=0.01)
    assert ident["two_mass"]["K"] == pytest.approx(23.10, rel=0.01)  # configs/default.yaml sim.K
    assert doc["source"] == "sim" and doc["controller"]["verification"]["ready"] is True


def test_other_recipe_and_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--config paper-literal --out runs/lit`: the shipped recipe's chirp (paper eq. 18–19 taken
    literally), in the folder named relative to where the command runs."""
    monkeypatch.chdir(tmp_path)
    run = run_cli("--sim", "--config", "paper-literal", "--out", "runs/lit", "--no-identify", "--json")
    assert run.code == 0, run.stderr
    log = tmp_path / "runs" / "lit" / "run.mcap"
    rec = read_recording(log)
    assert read_config(log)["excitation"]["form"] == "paper-literal"
    # eq. 18–19 literally: A·sin(ω(t)·t) + 3A·sin(2π·0.1 Hz·t), ω(t) = 2π(f0 + (f1 − f0)·t/T)
    a, f0, f1, duration = 0.0764, 0.1, 400.0, 10.0
    t = np.arange(80_000) / 8000.0
    expected = a * np.sin(2 * np.pi * (f0 + (f1 - f0) * t / duration) * t) + 3 * a * np.sin(2 * np.pi * 0.1 * t)
    np.testing.assert_allclose(rec.torque_ref, expected, rtol=0, atol=1e-9)


def test_noise_seed(tmp_path: Path) -> None:
    """`--seed N`: the plant's noise follows the seed (same seed, same record; another, another), and
    the log's config says which seed ran."""
    recipe = tmp_path / "noisy.yaml"
    recipe.write_text("excitation: {duration_s: 1.0, f_start_hz: 1.0, bias_frequency_hz: 1.0}\n"
                      "sim: {torque_noise_nm: 1.0e-3}\n")

    def velocity(seed: int, name: str) -> np.ndarray:
        run = run_cli("--sim", "--config", recipe, "--seed", str(seed), "--no-identify", "--json", out=tmp_path / name)
        assert run.code == 0, run.stderr
        assert read_config(run.out / "run.mcap")["sim"]["seed"] == seed
        return read_recording(run.out / "run.mcap").motor_velocity

    a, again, other = velocity(7, "a"), velocity(7, "again"), velocity(8, "other")
    np.testing.assert_array_equal(a, again)
    assert np.max(np.abs(a - other)) > 2 * STEP * 8000  # more than the encoder's quantum of velocity


# -- CANopen ------------------------------------------------------------------------------------
def test_canopen_port(quick_sim_run: CliRun, tmp_path: Path) -> None:
    """`--port CHANNEL --interface virtual --drive sim --node-id 5`: the CANopen path a real drive takes,
    through the real canopen stack, to the simulated drive as node 5 on python-can's virtual bus."""
    from sim_drive.canopen_slave import CanopenSlave

    with CanopenSlave(channel="test-modes-port", interface="virtual", node_id=5):
        run = run_cli("--port", "test-modes-port", "--interface", "virtual", "--drive", "sim", "--node-id", "5",
                      "--config", "quick", "--json", out=tmp_path)
    assert run.code == 0, run.stderr
    assert run.doc["source"] == "canopen" and run.doc["recording"]["status"] == "complete"
    assert (tmp_path / "controller-sim.yaml").is_file()  # the settings through the drive's parameter map
    _same_identification(_result(run), _result(quick_sim_run))


def _same_identification(got: dict, want: dict) -> None:
    """Two runs of one plant through different links: the same model (the bus rounds the torque)."""
    for key in ("J_m", "J_l", "B_m", "B_l", "K", "D"):
        assert got["two_mass"][key] == pytest.approx(want["two_mass"][key], rel=1e-3), key
    assert got["backlash"]["epsilon_deg"] == pytest.approx(want["backlash"]["epsilon_deg"], abs=0.002)


def test_sim_over_canopen(quick_sim_run: CliRun, tmp_path: Path) -> None:
    """`--sim --sim-link canopen`: every frame on the virtual bus, the same result as the direct run."""
    run = run_cli("--sim", "--sim-link", "canopen", "--config", "quick", "--json", out=tmp_path)
    assert run.code == 0, run.stderr
    assert run.doc["source"] == "canopen" and run.doc["recording"]["drive"]["backend"] == "canopen"
    rec, direct = read_recording(tmp_path / "run.mcap"), read_recording(quick_sim_run.out / "run.mcap")
    assert len(rec) == len(direct) == 16_000
    np.testing.assert_allclose(rec.motor_position, direct.motor_position, rtol=0, atol=1.001 * STEP)
    _same_identification(_result(run), _result(quick_sim_run))


def test_streamed_fallback(tmp_path: Path) -> None:
    """`--sim --sim-link canopen --drive generic-cia402`: no trace buffer, so SYNC + PDO streaming at the
    rate the bus budget allows (2 kHz at 1 Mbit/s), on the drive's clock. Not identified here (the
    streamed path's own tests identify): a late host pauses the excitation, up to 50 ms in a run."""
    run = run_cli("--sim", "--sim-link", "canopen", "--drive", "generic-cia402", "--config", "quick",
                  "--no-identify", "--json", out=tmp_path)
    assert run.code == 0, run.stderr
    rec = read_recording(tmp_path / "run.mcap")
    # 2 s at 2 kHz, and the cycles a late host paused the excitation for (at most 50 ms)
    assert run.doc["recording"]["status"] == "complete" and 4000 <= len(rec) <= 4100
    assert rec.sample_rate_hz == pytest.approx(2000) and "jitter" in rec.metadata["stream"]


def test_apply_then_restore(tmp_path: Path) -> None:
    """`--apply --yes --store` writes the verified settings (old values logged in run.mcap, stored to
    non-volatile memory); `--restore-from run.mcap` puts the old values back."""
    run = run_cli("--sim", "--sim-link", "canopen", "--drive", "sim", "--config", "quick", "--apply", "--yes",
                  "--store", "--json", out=tmp_path / "run")
    assert run.code == 0, run.stderr
    doc = run.doc
    assert doc["apply"]["applied"] and doc["apply"]["stored"] and doc["controller"]["verification"]["ready"]
    assert doc["apply"]["written"]["velocity_kp"] == pytest.approx(doc["controller"]["velocity_loop"]["gain"],
                                                                    rel=1e-6)
    events = read_results(run.out / "run.mcap")["/parameters"]
    old = {v["name"]: v["value"] for v in events[0]["values"]}
    assert events[0]["event"] == "old_values" and old["velocity_kp"] == pytest.approx(0.12)
    assert (run.out / "controller-sim.yaml").is_file()
    restore = run_cli("--sim", "--sim-link", "canopen", "--drive", "sim", "--restore-from", run.out / "run.mcap",
                      "--yes", "--json", out=tmp_path / "restore")
    assert restore.code == 0, restore.stderr
    assert restore.doc["restore"]["applied"] and restore.doc["restore"]["written"] == pytest.approx(old)
    assert read_results(tmp_path / "restore" / "restore.mcap")["/parameters"][0]["event"] == "old_values"


# -- method and tuning --------------------------------------------------------------------------
def test_paper_method(tmp_path: Path) -> None:
    """`--method paper`: the published procedure runs (its stage, not the hybrid's search and joint fit),
    and the summary and result.json say so."""
    run = run_cli("--sim", "--method", "paper", out=tmp_path)
    assert run.code == 0, run.stderr
    ident = _result(run)
    assert ident["backlash"]["method"] == "paper"
    stages = {s["name"] for s in ident["stages"]}
    assert "paper" in stages and not stages & {"search", "joint"}
    assert re.search(r"^\W*method\W+paper\W*$", run.stdout, re.MULTILINE), run.stdout


@pytest.mark.parametrize("preset, phase_margin_deg, gain_margin_db", [("soft", 60.0, 12.0), ("stiff", 40.0, 6.0)])
def test_presets(quick_sim_run: CliRun, tmp_path: Path, preset: str, phase_margin_deg: float,
                 gain_margin_db: float) -> None:
    """`--preset soft|stiff`: the preset's margins (README/--help: soft PM 60°, GM 12 dB; stiff 40°, 6 dB)
    on the identified model, contact and gap; soft is slower than standard, stiff faster."""
    run = run_cli("--sim", "--config", "quick", "--preset", preset, "--json", out=tmp_path)
    assert run.code == 0, run.stderr
    ctl = _controller(run)
    assert ctl["preset"] == preset
    for case in (ctl["margins"], ctl["margins"]["gap"]):
        assert case["phase_margin_deg"] >= phase_margin_deg - 0.05
        assert case["gain_margin_db"] >= gain_margin_db - 0.05
    standard = _controller(quick_sim_run)
    assert standard["preset"] == "standard"
    faster = ctl["velocity_loop"]["bandwidth_hz"] > standard["velocity_loop"]["bandwidth_hz"]
    assert faster is (preset == "stiff")


def test_measure_backlash(tmp_path: Path) -> None:
    """`--measure-backlash`: the velocity-reversal check (paper §4.2) finds the plant's ε within its
    stated ±4 %, and result.json carries it under "backlash_check"."""
    run = run_cli("--sim", "--config", "quick", "--measure-backlash", "--no-tune", "--json", out=tmp_path)
    assert run.code == 0, run.stderr
    check = _result(run)["backlash_check"]
    assert check == run.doc["backlash_check"]
    assert check["epsilon_deg"] == pytest.approx(EPSILON_DEG, rel=0.04)
    assert check["reversals"] == 3 and 0 <= check["spread_deg"] < 0.04 * EPSILON_DEG  # 4 s of a 0.5 Hz sine
    assert Path(check["log"]).is_file() and Path(check["log"]).name == "backlash-check.mcap"


# -- replay and output --------------------------------------------------------------------------
def test_replay_mcap(default_sim_run: CliRun, tmp_path: Path) -> None:
    """`--replay run.mcap`: the same identification as the live run."""
    run = run_cli("--replay", default_sim_run.out / "run.mcap", "--json", out=tmp_path)
    assert run.code == 0, run.stderr
    assert run.doc["recording"]["samples"] == 80_000
    live, replay = _result(default_sim_run), _result(run)
    for section in ("backlash", "two_mass", "modes", "transfer_function", "iterations"):
        assert replay[section] == live[section], section


def test_replay_csv(quick_sim_run: CliRun, tmp_path: Path) -> None:
    """`--replay axis.csv`: a CSV file of the same run identifies the same axis."""
    csv = tmp_path / "axis.csv"
    write_csv(csv, read_recording(quick_sim_run.out / "run.mcap"))
    run = run_cli("--replay", csv, "--config", "quick", "--json", out=tmp_path / "replay")
    assert run.code == 0, run.stderr
    assert run.doc["recording"]["samples"] == 16_000
    _same_identification(_result(run), _result(quick_sim_run))


def test_json(default_sim_run: CliRun) -> None:
    """`--json`: stdout is one JSON document, strict (no NaN), and nothing else is printed."""
    assert default_sim_run.stderr == ""
    doc = json.loads(default_sim_run.stdout)
    json.dumps(doc, allow_nan=False)
    assert doc["identification"]["backlash"] == _result(default_sim_run)["backlash"]
