"""The terminal side of `commission`: summary table, quiet --json, -v, colours only on a TTY.

Driven through ``commission.cli.main([...])`` in-process (stdout/stderr captured, so not a
TTY), and once as a subprocess on a real pseudo-terminal for the TTY case.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import pty
import re
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

from commission.cli import main

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def live(default_sim_run) -> tuple[Path, dict, str]:
    """`commission --sim --out DIR --json` (shared with the other command-line tests: conftest.py)."""
    return default_sim_run.out, default_sim_run.doc, default_sim_run.stderr


@pytest.fixture(scope="module")
def summary(live: tuple[Path, dict, str], tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str, str]:
    """A replay of the live run without --json: the human-readable summary (not a TTY)."""
    # a folder name long enough that a path in it passes the table's edge (80 columns off a terminal)
    out = tmp_path_factory.mktemp("replay") / "customer-site-line-3-axis-12-commissioning-2026-11-28"
    code, stdout, stderr = _run(["--replay", str(live[0] / "run.mcap"), "--out", str(out)])
    assert code == 0, stderr
    return live[1], stdout, stderr


# -- --json -------------------------------------------------------------------------------------
def test_json_is_one_document_on_stdout_and_nothing_else(live: tuple[Path, dict, str]) -> None:
    out, doc, stderr = live
    assert stderr == ""  # no progress bar, no banner, no table
    assert {"out_dir", "files", "source", "recording", "envelope", "identification"} <= set(doc)
    assert doc["out_dir"] == str(out) and doc["source"] == "sim"
    for f in doc["files"]:
        assert Path(f).is_file(), f
    assert {Path(f).name for f in doc["files"]} >= {"run.mcap", "result.json"}
    rec = doc["recording"]
    assert rec["samples"] == 80_000 and rec["sample_rate_hz"] == 8000.0 and rec["status"] == "complete"
    bl = doc["identification"]["backlash"]
    assert bl["epsilon_deg"] == pytest.approx(0.40, abs=0.01) and bl["detected"] is True
    lo, hi = bl["epsilon_interval_deg"]
    assert lo <= bl["epsilon_deg"] <= hi and bl["evaluations"] > 0
    modes = doc["identification"]["modes"]
    assert modes["f_antiresonance_hz"] < modes["f_resonance_hz"]
    json.dumps(doc, allow_nan=False)  # strict JSON: no NaN/Infinity for a script to choke on


def test_json_of_a_replay_matches_result_json(live: tuple[Path, dict, str], tmp_path: Path) -> None:
    code, stdout, stderr = _run(["--replay", str(live[0] / "run.mcap"), "--out", str(tmp_path), "--json"])
    assert code == 0 and stderr == ""
    doc = json.loads(stdout)
    assert doc["source"] == str(live[0] / "run.mcap")
    saved = json.loads((tmp_path / "result.json").read_text())
    assert doc["identification"]["backlash"] == saved["backlash"]
    assert doc["identification"]["two_mass"] == saved["two_mass"]


def test_json_error_is_one_line_on_stderr_and_nothing_on_stdout(tmp_path: Path) -> None:
    code, stdout, stderr = _run(["--replay", str(tmp_path / "missing.mcap"), "--out", str(tmp_path / "o"), "--json"])
    assert code == 3 and stdout == ""
    assert stderr.strip().splitlines() == [f"commission: error: {tmp_path / 'missing.mcap'}: no such file"]


# -- summary ------------------------------------------------------------------------------------
def test_summary_table_shows_model_modes_backlash_and_files(summary: tuple[dict, str, str]) -> None:
    doc, stdout, stderr = summary
    assert "backlash" not in stderr  # the summary is the result: stdout (`commission … > out.txt` keeps it)
    ident = doc["identification"]
    rows = {}
    for line in stdout.splitlines():
        cells = [c.strip() for c in re.split(r"[│|]", line) if c.strip()]
        if len(cells) == 2:
            rows.setdefault(cells[0], []).append(cells[1])
    assert "replay of" in stdout
    for key in ("samples", "method", "backlash ε", "inertias", "shaft", "resonance", "anti-resonance"):
        assert key in rows, f"row {key!r} missing from the summary:\n{stdout}"
    eps = ident["backlash"]["epsilon_deg"]
    lo, hi = ident["backlash"]["epsilon_interval_deg"]
    assert rows["backlash ε"][0].startswith(f"{eps:.4f}°") and f"[{lo:.4f}°, {hi:.4f}°]" in rows["backlash ε"][0]
    assert rows["resonance"][0].startswith(f"{ident['modes']['f_resonance_hz']:.2f} Hz")
    assert rows["anti-resonance"][0].startswith(f"{ident['modes']['f_antiresonance_hz']:.2f} Hz")
    # the files under the table, each path whole on its own line however long (here pytest's tmp path)
    files = [line.split(" ", 1)[1] for line in stdout.splitlines() if line.startswith("file ")]
    assert any(f.endswith("result.json") and Path(f).is_file() for f in files), stdout


def test_no_colours_and_no_progress_animation_when_not_a_tty(summary: tuple[dict, str, str],
                                                             live: tuple[Path, dict, str]) -> None:
    _, stdout, stderr = summary
    for text in (stdout, stderr):
        assert not ANSI.search(text), repr(ANSI.search(text))
        assert "\r" not in text  # no live progress redraws into a log file


def test_report_html_is_among_the_files(live: tuple[Path, dict, str]) -> None:
    out, doc, _ = live
    assert str(out / "report.html") in doc["files"] and (out / "report.html").is_file()


# -- -v -----------------------------------------------------------------------------------------
def test_verbose_adds_the_cause_of_an_error(tmp_path: Path) -> None:
    bad = tmp_path / "folder.mcap"
    bad.mkdir()  # LogFormatError raised from IsADirectoryError: an error with a cause
    argv = ["--replay", str(bad), "--out", str(tmp_path / "o")]
    code, _, quiet = _run(argv)
    code_v, _, verbose = _run([*argv, "-v"])
    assert code == code_v == 3
    assert len(quiet.strip().splitlines()) == 1 and "caused by" not in quiet
    assert verbose.strip().splitlines()[0] == quiet.strip()
    assert "caused by: IsADirectoryError" in verbose


def test_verbose_shows_stages_iterations_and_notes(live: tuple[Path, dict, str], summary: tuple[dict, str, str],
                                                  tmp_path: Path) -> None:
    code, stdout, _ = _run(["--replay", str(live[0] / "run.mcap"), "--out", str(tmp_path), "-v"])
    assert code == 0
    ident = live[1]["identification"]
    for stage in ident["stages"]:
        assert f"stage {stage['name']}" in stdout
    assert "iteration 0" in stdout and f"iteration {len(ident['iterations']) - 1}" in stdout
    plain = " ".join(stdout.split())
    for note in ident["notes"]:
        assert " ".join(f"note: {note}".split()) in plain
    # the same replay without -v (the summary fixture's) says none of it
    assert "iteration 0" not in summary[1] and "stage kalman" not in summary[1]


# -- a real terminal ----------------------------------------------------------------------------
def test_colours_on_a_tty(live: tuple[Path, dict, str], tmp_path: Path) -> None:
    """On a pseudo-terminal the summary has colours/bold; the same run piped has none."""
    env = {k: v for k, v in os.environ.items() if k not in ("NO_COLOR", "FORCE_COLOR", "TERM")}
    env.update(TERM="xterm-256color", COLUMNS="120", LINES="40")
    argv = [sys.executable, "-m", "commission.cli", "--replay", str(live[0] / "run.mcap"), "--out", str(tmp_path / "o")]
    master, slave = pty.openpty()
    proc = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, env=env, close_fds=True)
    os.close(slave)
    chunks: list[bytes] = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        ready, _, _ = select.select([master], [], [], 1.0)
        if ready:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the child closed the terminal
                break
            if not data:
                break
            chunks.append(data)
        elif proc.poll() is not None:
            break
    os.close(master)
    assert proc.wait(timeout=30) == 0
    screen = b"".join(chunks).decode("utf-8", "replace")
    assert ANSI.search(screen), "no colour/bold on a terminal"
    assert "backlash ε" in ANSI.sub("", screen)
