"""`commission` imports the simulator (sim_drive) only where --sim is chosen.

Each case runs the command in a fresh interpreter, as a user does, and records at exit which
``sim_drive`` modules were loaded. The replay of a --sim run's log verifies on the simulator's
plant without importing the simulator: the log says which plant it ran on.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from commission.config import ExcitationConfig
from commission.csvlog import write_csv
from commission.excitation import chirp
from commission.plant import Plant, PlantParameters
from commission.recording import Recording

#: Runs commission's main() with the given arguments; at exit, writes the sim_drive modules loaded.
WRAPPER = r"""
import atexit, json, sys
out = sys.argv[1]

def dump():
    with open(out, "w", encoding="utf-8") as f:
        json.dump(sorted(m for m in sys.modules if m == "sim_drive" or m.startswith("sim_drive.")), f)

atexit.register(dump)
from commission.cli import main
sys.exit(main(sys.argv[2:]))
"""


def _commission(tmp_path: Path, *args: str) -> tuple[int, list[str], str]:
    """(exit code, sim_drive modules loaded, stderr) of `commission ARGS` in a new process."""
    modules = tmp_path / f"modules-{len(list(tmp_path.glob('modules-*')))}.json"
    done = subprocess.run([sys.executable, "-c", WRAPPER, str(modules), *args], capture_output=True, text=True,
                          timeout=600, check=False)
    return done.returncode, json.loads(modules.read_text(encoding="utf-8")), done.stderr


def test_help_imports_no_simulator(tmp_path: Path) -> None:
    code, loaded, err = _commission(tmp_path, "--help")
    assert code == 0, err
    assert loaded == []


def test_replay_of_a_csv_imports_no_simulator(tmp_path: Path) -> None:
    r = Plant(PlantParameters(torque_noise_nm=1e-4, seed=3)).run_torque(chirp(ExcitationConfig()).samples)
    rec = Recording.uniform(8000.0, r.torque_ref, r.motor_velocity, motor_position=r.motor_position)
    write_csv(tmp_path / "run.csv", rec)
    out = tmp_path / "out"
    code, loaded, err = _commission(tmp_path, "--replay", str(tmp_path / "run.csv"), "--out", str(out), "--json")
    assert code == 0, err
    assert loaded == []
    assert {"result.json", "controller.json", "report.html"} <= {p.name for p in out.iterdir()}
    text = (out / "report.html").read_text(encoding="utf-8")
    assert "true plant (simulator)" not in text  # a CSV says nothing of a simulator


def test_sim_imports_the_simulator_and_the_replay_of_its_log_does_not(tmp_path: Path) -> None:
    run = tmp_path / "sim"  # (the shipped 2 s recipe: what is imported does not depend on the record's length)
    code, loaded, err = _commission(tmp_path, "--sim", "--config", "quick", "--out", str(run), "--json")
    assert code == 0, err
    assert "sim_drive.device" in loaded
    replay = tmp_path / "replay"
    code, loaded, err = _commission(tmp_path, "--replay", str(run / "run.mcap"), "--config", "quick", "--out", str(replay),
                                    "--json")
    assert code == 0, err
    assert loaded == []
    # the log said which plant the run was on: the replay verifies on it and draws it
    truth = PlantParameters()
    plant = json.loads((replay / "controller.json").read_text(encoding="utf-8"))["verification"]["plant"]
    np.testing.assert_allclose([plant["K"], plant["J_l"], plant["epsilon_rad"]],
                               [truth.K, truth.J_l, truth.epsilon_rad], rtol=1e-12)
    assert "true plant (simulator)" in (replay / "report.html").read_text(encoding="utf-8")
