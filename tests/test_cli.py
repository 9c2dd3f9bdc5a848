"""The command line: modes, outputs, and bad input as one line with a non-zero exit."""

import argparse
import json
import subprocess
import sys

import numpy as np
import pytest

from commission.cli import main
from commission.config import ExcitationConfig
from commission.csvlog import read_csv, write_csv
from commission.excitation import chirp
from commission.ident.twomass import REFERENCE_PLANT
from commission.mcaplog import read_recording
from commission.recording import Recording
from sim_drive.plant import Plant, PlantParameters


@pytest.fixture(scope="module")
def sim_run(default_sim_run):
    return default_sim_run.out


def test_sim_run_writes_the_log(sim_run):
    rec = read_recording(sim_run / "run.mcap")
    assert len(rec) == 80_000 and rec.metadata["status"] == "complete"


RESULT_KEYS = {
    "backlash": {"epsilon_deg", "epsilon_interval_deg", "evaluations", "method"},
    "two_mass": {"J_m", "J_l", "B_m", "B_l", "K", "D"},
    "modes": {"f_resonance_hz", "zeta_resonance", "f_antiresonance_hz", "zeta_antiresonance"},
    "transfer_function": {"num", "den"},
    "source": {"file", "sample_rate_hz", "samples"},
    "fit": {"residual_ratio", "noise_floor_ratio", "approximate", "reasons", "noise_limited", "cutoff_hz"},
}


def test_sim_run_writes_result_json_with_the_documented_keys(sim_run):
    doc = json.loads((sim_run / "result.json").read_text())
    for section, keys in RESULT_KEYS.items():
        assert keys <= set(doc[section]), section
    assert isinstance(doc["iterations"], list) and {"frd_error", "epsilon_deg"} <= set(doc["iterations"][0])
    assert len(doc["transfer_function"]["num"]) == 3 and len(doc["transfer_function"]["den"]) == 4
    assert doc["backlash"]["method"] == "hybrid"
    assert doc["source"] == {"file": str(sim_run / "run.mcap"), "sample_rate_hz": 8000.0, "samples": 80000}
    assert abs(doc["backlash"]["epsilon_deg"] - 0.40) < 0.01  # the default plant's backlash
    assert doc["fit"]["residual_ratio"] < 0.002 and doc["fit"]["approximate"] is False


def test_replay_csv(sim_run, tmp_path, capsys):
    rec = read_recording(sim_run / "run.mcap")
    write_csv(tmp_path / "axis.csv", rec.head(8000))
    capsys.readouterr()
    assert main(["--replay", str(tmp_path / "axis.csv"), "--out", str(tmp_path / "o"), "--json", "--no-identify"]) == 0
    assert json.loads(capsys.readouterr().out)["recording"]["samples"] == 8000


def test_truncated_log_is_replayed_with_a_warning(sim_run, tmp_path, capsys):
    data = (sim_run / "run.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    capsys.readouterr()
    assert main(["--replay", str(cut), "--out", str(tmp_path / "o"), "--json", "--no-identify"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert 20_000 < doc["recording"]["samples"] < 60_000
    assert doc["warnings"]


def _one_line_error(argv, capsys, code):
    capsys.readouterr()
    assert main(argv) == code
    err = capsys.readouterr().err.strip().splitlines()[-1]  # progress/info lines may precede it
    assert err.startswith("commission: error: ") and "\n" not in err and "Traceback" not in err
    return err


@pytest.mark.parametrize(
    "content, code, fragment",
    [
        (None, 3, "no such file"),
        (b"", 3, "empty"),
        (b"\x89MCAP0\r\ngarbage garbage garbage", 3, ""),
        (b"this is not an mcap file at all", 3, ""),
    ],
)
def test_bad_mcap(tmp_path, capsys, content, code, fragment):
    f = tmp_path / "x.mcap"
    if content is not None:
        f.write_bytes(content)
    err = _one_line_error(["--replay", str(f), "--out", str(tmp_path / "o")], capsys, code)
    assert fragment in err


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("t,torque_ref\n0,1\n0.1,2\n", "motor_velocity"),
        ("t,torque_ref,motor_velocity\n0,1,nan\n0.1,2,3\n", "line 2, column 'motor_velocity'"),
        ("t,torque_ref,motor_velocity\n0,1,2\n0.1,2,3\n0.25,2,3\n0.3,1,1\n", "uniform"),
        ("t,torque_ref,motor_velocity\n0,1,2\n0.2,2,3\n0.1,2,3\n", "does not increase"),
    ],
)
def test_bad_csv(tmp_path, capsys, text, fragment):
    f = tmp_path / "x.csv"
    f.write_text(text)
    err = _one_line_error(["--replay", str(f), "--out", str(tmp_path / "o")], capsys, 3)
    assert fragment in err


def test_bad_config_and_envelope_and_port(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("excitation:\n  amplitude: 1\n")
    assert "excitation.amplitude: unknown key" in _one_line_error(["--sim", "--config", str(cfg)], capsys, 2)
    cfg.write_text("safety:\n  max_speed_rad_s: 5\n")
    err = _one_line_error(["--sim", "--config", str(cfg), "--out", str(tmp_path / "o")], capsys, 5)
    assert "speed limit" in err
    assert not (tmp_path / "o" / "run.mcap").exists()
    assert "does not exist" in _one_line_error(["--port", "/dev/ttyNOPE9"], capsys, 4)
    _one_line_error(["--replay", str(tmp_path / "x.txt")], capsys, 3)


def test_help_explains_every_mode():
    out = subprocess.run([sys.executable, "-m", "commission.cli", "--help"], capture_output=True, text=True).stdout
    for word in ("--sim", "--port", "--replay", "--config", "--out", "--interface", "--json", "run.mcap"):
        assert word in out


@pytest.fixture(scope="module")
def good_csv(sim_run, tmp_path_factory):
    path = tmp_path_factory.mktemp("csv") / "axis.csv"
    write_csv(path, read_recording(sim_run / "run.mcap"))
    return path


@pytest.mark.parametrize(
    "change, config, fragment",
    [
        ("short", None, "too short to identify"),
        (None, "identification:\n  band_hz: [0.1, 4500]\n", "above Nyquist"),
        ("flat_torque", None, "torque_ref is constant"),
        ("saturated", None, "saturated"),
    ],
)
def test_identification_bad_input_is_one_line_exit_6(good_csv, tmp_path, capsys, change, config, fragment):
    rec = read_csv(good_csv)
    if change == "short":
        rec = rec.head(50)
    elif change == "flat_torque":
        rec = rec.replace(torque_ref=np.full(len(rec), 0.1))
    elif change == "saturated":
        rec = rec.replace(motor_velocity=np.clip(rec.motor_velocity, -5.0, 5.0))
    f = tmp_path / "in.csv"
    write_csv(f, rec)
    argv = ["--replay", str(f), "--out", str(tmp_path / "o")]
    if config is not None:
        (tmp_path / "c.yaml").write_text(config)
        argv += ["--config", str(tmp_path / "c.yaml")]
    assert fragment in _one_line_error(argv, capsys, 6)


def test_a_record_the_model_cannot_explain_writes_everything_and_exits_8(tmp_path, capsys):
    # a 3 Hz, 10 rad/s motion the torque did not cause (an external disturbance) on a velocity-only log: a
    # result, flagged approximate with its reasons, result.json and the report written; the exit code says so
    fs = 8000.0  # a 2 s chirp: the flagged path's stages at a fifth of the 10 s cost
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.4, torque_noise_nm=1e-4, seed=11),
              fs).run_torque(chirp(ExcitationConfig(duration_s=2.0)).samples)
    t = np.arange(len(r.torque_ref)) / fs
    f = tmp_path / "in.csv"
    write_csv(f, Recording.uniform(fs, r.torque_ref, r.motor_velocity + 10.0 * np.sin(2 * np.pi * 3.0 * t)))
    out = tmp_path / "o"
    assert main(["--replay", str(f), "--out", str(out), "--no-tune"]) == 8
    doc = json.loads((out / "result.json").read_text())
    assert doc["fit"]["approximate"] is True
    assert any("unexplained" in r for r in doc["fit"]["reasons"]), doc["fit"]["reasons"]
    # predictions that miss by far more than their predicted size determine nothing: ε's interval is then
    # everything the identifier could have reported, not a narrow band around the estimate
    assert doc["fit"]["determined"] is False
    lo, hi = doc["backlash"]["epsilon_interval_deg"]
    assert lo == 0.0 and hi >= 16.0 and hi >= doc["backlash"]["epsilon_deg"]
    # and no reason names a narrower one (it said "the record bounds ε only to [1.01°, 4°]" beside it)
    assert not any("only to" in r for r in doc["fit"]["reasons"]), doc["fit"]["reasons"]
    assert (out / "report.html").exists()
    assert "APPROXIMATE" in capsys.readouterr().out


def test_apply_is_refused_before_the_axis_moves_when_the_drive_has_no_parameter_map(tmp_path, capsys):
    err = _one_line_error(["--sim", "--apply", "--yes", "--out", str(tmp_path / "o")], capsys, 2)
    assert "no parameter map for --apply" in err
    assert not (tmp_path / "o" / "run.mcap").exists()


# -- conventions: results on stdout, diagnostics on stderr, a last "next:" line -------------------
def test_options_are_not_abbreviable(capsys):
    """`--pres soft` is a typo, not --preset soft: refused before anything runs."""
    with pytest.raises(SystemExit) as info:
        main(["--sim", "--pres", "soft"])
    assert info.value.code == 2 and "unrecognized arguments: --pres soft" in capsys.readouterr().err


def test_summary_on_stdout_and_a_last_line_saying_what_next(quick_sim_run, tmp_path):
    """As `commission --replay run.mcap > out.txt` is used: the summary and the next step land in the
    file; the terminal (stderr) gets only diagnostics."""
    proc = subprocess.run([sys.executable, "-m", "commission.cli", "--replay", str(quick_sim_run.out / "run.mcap"),
                           "--config", "quick", "--out", str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert "backlash ε" in proc.stdout and "controller ready" in proc.stdout
    assert "backlash ε" not in proc.stderr and "next:" not in proc.stderr
    # the drive's loop the design assumed, said where it comes from (here nothing knew the current loop)
    assert "drive loop (design)" in proc.stdout and "current loop 2000 Hz (assumed" in proc.stdout
    assert lines[-1] == (f"next: open the report at {tmp_path / 'report.html'}; the settings are ready: "
                         "to write them, commission the axis itself with --apply")
    assert sum(line.startswith("next:") for line in lines) == 1


def test_a_first_run_says_that_it_compiles(tmp_path):
    """With an empty numba cache the run says on stderr that it compiles (tens of seconds after an
    install); the next run loads the cache and says nothing of it."""
    import os

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    argv = [sys.executable, "-m", "commission.cli", "--sim", "--config", "quick", "--no-identify"]
    first = subprocess.run([*argv, "--out", str(tmp_path / "a")], capture_output=True, text=True, env=env)
    again = subprocess.run([*argv, "--out", str(tmp_path / "b")], capture_output=True, text=True, env=env)
    assert first.returncode == again.returncode == 0, first.stderr + again.stderr
    assert "compiling the numerical kernels" in first.stderr and "compiling" not in first.stdout
    assert "compiling" not in again.stderr
    assert any((tmp_path / "numba-cache").rglob("*.nbi"))  # the cache went where numba was told


def test_the_last_line_says_what_a_new_record_needs_when_the_identification_names_it() -> None:
    from commission.cli import _next_step

    args = argparse.Namespace(replay=None, sim=False)
    fit = {"approximate": True, "reasons": ["r"], "remedies": ["record with a load encoder", "a longer chirp"]}
    line = _next_step(args, {"out_dir": "o", "identification": {"fit": fit}})
    assert "a new record would help: record with a load encoder; or a longer chirp" in line
    assert "new record" not in _next_step(args, {"out_dir": "o", "identification": {"fit": {**fit, "remedies": []}}})
    # no controller: --no-tune is named only when it was given, else the closed-loop check that could not run
    assert "could not be checked in closed loop" in line and "--no-tune" not in line
    tuned_not = _next_step(argparse.Namespace(replay=None, sim=False, no_identify=False, no_tune=True),
                           {"out_dir": "o", "identification": {"fit": fit}})
    assert "run without --no-tune" in tuned_not
