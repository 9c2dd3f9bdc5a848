"""Fleet mode (issue 23): a folder of good and corrupt logs identified on Dask, locally and on a
scheduler and worker started on loopback; the table read back with pyarrow; the worn axis first.

The logs are 2 s chirps (the shipped ``quick`` recipe) of the reference plant, simulated here with
the product's plant physics: axis AX-1 wears (ε 0.30° → 0.45° → 0.60° over four months while its
coupling softens), AX-2 stays as it was, a CSV file has no drive identity, and three logs cannot
give a model (a cut MCAP file, a file that is not CSV, a record too short to identify).
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from datetime import datetime, timedelta, timezone
from pathlib import Path

import cloudpickle
import pyarrow.parquet as pq
import pytest

from conftest import run_cli

from commission import fleet
from commission.config import load_config
from commission.csvlog import write_csv
from commission.excitation import chirp
from commission.fleet import cluster
from commission.fleet.report import axis_trends
from commission.mcaplog import write_recording
from commission.plant import Plant, PlantParameters
from commission.recording import DriveInfo, Recording

FS = 8000.0
QUICK = load_config("quick")
TAU = chirp(QUICK.excitation).samples
T0 = datetime(2026, 1, 5, 8, 0, tzinfo=timezone.utc)
MONTH = timedelta(days=30)


def _simulate(path: Path, eps_deg: float, *, K: float = 23.10, serial: str = "", months: int = 0, seed: int = 0,
              samples: int | None = None) -> Path:
    """One log of the reference plant with backlash ε and stiffness K (damping ratio kept)."""
    ref = PlantParameters()
    plant = ref.model_copy(update={"K": K, "D": ref.D * math.sqrt(K / ref.K), "epsilon_deg": eps_deg,
                                   "torque_noise_nm": 1e-4, "seed": seed})
    r = Plant(plant, FS).run_torque(TAU[:samples])
    rec = Recording.uniform(FS, r.torque_ref, r.motor_velocity, motor_position=r.motor_position,
                            start_time=T0 + months * MONTH,
                            drive=DriveInfo(backend="sim", vendor="Acme", product="Servo 7", serial_number=serial))
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".csv":
        write_csv(path, rec)
    else:
        write_recording(path, rec)
    return path


#: file name → (ε [deg], K [N·m/rad], serial, months after T0) of the logs that identify
GOOD = {
    "line1/ax1-jan.mcap": (0.30, 23.10, "AX-1", 0),
    "line1/ax1-mar.mcap": (0.45, 22.20, "AX-1", 2),
    "line1/ax1-may.mcap": (0.60, 21.00, "AX-1", 4),
    "line2/ax2-jan.mcap": (0.40, 23.10, "AX-2", 0),
    "line2/ax2-apr.mcap": (0.41, 23.10, "AX-2", 3),
    "bench/axis.csv": (0.25, 23.10, "", 1),
}
BAD = {"line1/cut.mcap": "LogFormatError", "line2/notes.csv": "LogFormatError", "line2/ax3-short.mcap": "IdentificationError"}


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fleet-logs")
    for i, (name, (eps, K, serial, months)) in enumerate(GOOD.items()):
        _simulate(root / name, eps, K=K, serial=serial, months=months, seed=i)
    whole = (root / "line1/ax1-jan.mcap").read_bytes()
    (root / "line1/cut.mcap").write_bytes(whole[:2000])  # cut inside the first chunk: nothing to recover
    (root / "line2/notes.csv").write_text("axis 3 was serviced on Tuesday\n")
    _simulate(root / "line2/ax3-short.mcap", 0.3, serial="AX-3", samples=200)  # 25 ms: the chirp has not reached a resonance
    return root


@pytest.fixture(scope="module")
def local_run(logs: Path, tmp_path_factory: pytest.TempPathFactory):
    """`commission --replay FOLDER --config quick --json` on a local cluster (two workers, not one per core:
    a test must not start sixty processes on a large machine)."""
    run = run_cli("--replay", logs, "--config", "quick", "--workers", "2", "--json",
                  out=tmp_path_factory.mktemp("fleet-out"))
    assert run.code == 0, run.stderr
    return run


def _rows(out: Path, logs: Path) -> dict[str, dict]:
    """The table's rows by their log's path under ``logs``."""
    return {Path(r["source"]).relative_to(logs.resolve()).as_posix(): r
            for r in pq.read_table(out / "fleet.parquet").to_pylist()}


def test_the_table_reads_with_pyarrow_one_row_per_log(local_run, logs: Path) -> None:
    table = pq.read_table(local_run.out / "fleet.parquet")
    assert table.schema.equals(fleet.SCHEMA)
    rows = _rows(local_run.out, logs)
    assert set(rows) == set(GOOD) | set(BAD)
    for name, row in rows.items():
        assert row["content_sha256"] == hashlib.sha256((logs / name).read_bytes()).hexdigest()
    summary = local_run.doc["fleet"]
    assert summary["counts"] == {"ok": len(GOOD), "failed": len(BAD), "crashed": 0}
    assert summary["cluster"]["local"] and summary["cluster"]["workers"] == 2


def test_each_log_row_holds_its_drive_start_and_model(local_run, logs: Path) -> None:
    rows = _rows(local_run.out, logs)
    for name, (eps, K, serial, months) in GOOD.items():
        row = rows[name]
        assert row["status"] == "ok", row["error"]
        assert (row["drive_serial"] or "") == serial
        if name.endswith(".mcap"):  # a CSV file carries no drive identity
            assert (row["drive_vendor"], row["drive_product"]) == ("Acme", "Servo 7")
        assert row["start_time"] == T0 + months * MONTH
        # against the simulated plant: ε within 0.02°, K within 2 % (a 2 s record)
        assert row["epsilon_deg"] == pytest.approx(eps, abs=0.02), name
        assert row["K_nm_per_rad"] == pytest.approx(K, rel=0.02), name
        assert row["approximate"] is False
        for stem, unit in (("epsilon", "deg"), ("K", "nm_per_rad"), ("f_resonance", "hz"), ("f_antiresonance", "hz")):
            lo, value, hi = row[f"{stem}_low_{unit}"], row[f"{stem}_{unit}"], row[f"{stem}_high_{unit}"]
            assert lo <= value <= hi, (name, stem)
        # the undamped resonance of the identified model lies near the reported one
        undamped = math.sqrt(row["K_nm_per_rad"] * (1 / row["J_m_kg_m2"] + 1 / row["J_l_kg_m2"])) / (2 * math.pi)
        assert row["f_resonance_hz"] == pytest.approx(undamped, rel=0.05)


def test_a_log_that_cannot_be_identified_is_a_row_with_its_reason(local_run, logs: Path) -> None:
    rows = _rows(local_run.out, logs)
    for name, error in BAD.items():
        row = rows[name]
        assert row["status"] == "failed"
        assert row["error"].startswith(error), row["error"]
        assert row["epsilon_deg"] is None
    assert rows["line2/ax3-short.mcap"]["drive_serial"] == "AX-3"  # read, then too short to identify


def test_the_report_lists_the_worn_axis_first(local_run) -> None:
    page = (local_run.out / "fleet.html").read_text()
    assert not any(tag in page for tag in ("<script", "<link", "<img", "src=")), "not self-contained"
    grown = page.split('<ol id="grown">', 1)[1].split("</ol>", 1)[0]
    assert "AX-1" in grown and "AX-2" not in grown
    axes = page.split('<table id="axes">', 1)[1].split("</table>", 1)[0]
    order = [s.split('"', 1)[0] for s in axes.split('data-axis="')[1:]]
    assert order[0] == "AX-1" and set(order) >= {"AX-1", "AX-2", "AX-3"}
    assert page.count('<figure class="plot"') == 3  # AX-1, AX-2, the CSV file; AX-3 has no identified record
    [ax1] = [g for g in local_run.doc["fleet"]["grown"] if g["axis"] == "AX-1"]
    assert ax1["growth_deg"] == pytest.approx(0.30, abs=0.03)


def test_growth_ranking_uses_trusted_records_and_the_threshold() -> None:
    t = [T0 + k * MONTH for k in range(3)]

    def row(serial: str, when: datetime, eps: float, approximate: bool = False, status: str = "ok") -> dict:
        return {"source": f"/{serial}/{when:%m}.mcap", "status": status, "drive_serial": serial, "start_time": when,
                "epsilon_deg": eps, "K_nm_per_rad": 23.0, "f_resonance_hz": 65.0, "approximate": approximate}

    rows = [row("A", t[0], 0.30), row("A", t[2], 0.38),                       # +0.08
            row("B", t[0], 0.20), row("B", t[1], 0.50),                       # +0.30
            row("C", t[0], 0.20), row("C", t[1], 0.90, approximate=True),     # approximate: not trusted
            row("C", t[2], 0.22),                                             # +0.02
            row("D", t[0], 0.40)]                                             # one record
    trends = axis_trends(rows, growth_threshold_deg=0.05)
    assert [a.key for a in trends] == ["B", "A", "C", "D"]
    assert [a.grew for a in trends] == [True, True, False, False]
    assert trends[2].growth_deg == pytest.approx(0.02) and trends[3].growth_deg is None
    assert [a.key for a in axis_trends(rows, growth_threshold_deg=0.1) if a.grew] == ["B"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_for_port(port: int, proc: subprocess.Popen, timeout_s: float = 90.0) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        assert proc.poll() is None, f"the scheduler exited with {proc.returncode}"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise AssertionError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, 15)  # the process group this test started (the worker's nanny has a child)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
            proc.wait()


@contextlib.contextmanager
def _dask_cluster(*worker_options: str) -> Iterator[tuple[str, subprocess.Popen, set[str]]]:
    """``dask scheduler`` and one ``dask worker WORKER_OPTIONS`` (one thread) on loopback, each in a process
    group of its own; yields the scheduler's address, the worker's process and the workers the scheduler
    knows. Both are stopped on exit."""
    from distributed import Client

    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True}
    scheduler = subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                  "--no-dashboard", "--dashboard-address", "127.0.0.1:0"], **quiet)
    worker = None
    try:
        _wait_for_port(port, scheduler)
        worker = subprocess.Popen([sys.executable, "-m", "dask", "worker", address, "--host", "127.0.0.1",
                                   *worker_options, "--nthreads", "1", "--no-dashboard",
                                   "--dashboard-address", "127.0.0.1:0"], **quiet)
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(1, timeout=90)
            workers = set(client.scheduler_info()["workers"])
        yield address, worker, workers
    finally:
        for proc in (worker, scheduler):
            if proc is not None:
                _stop(proc)


def test_on_an_existing_scheduler_a_rerun_identifies_only_new_logs(local_run, logs: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    shutil.copytree(local_run.out, out)
    before = _rows(out, logs)
    new = _simulate(tmp_path / "fleet-logs" / "later" / "ax1-jul.mcap", 0.70, K=20.0, serial="AX-1", months=6, seed=9)
    with _dask_cluster("--nworkers", "1") as (address, _, workers):
        run = run_cli("--replay", logs, new.parent, "--config", "quick", "--scheduler", address, "--json", out=out)
    assert run.code == 0, run.stderr
    summary = run.doc["fleet"]
    assert (summary["identified"], summary["skipped"]) == (1, len(GOOD) + len(BAD))
    assert summary["cluster"]["local"] is False and summary["cluster"]["scheduler"] == address
    table = pq.read_table(out / "fleet.parquet").to_pylist()
    assert len(table) == len(GOOD) + len(BAD) + 1
    [added] = [r for r in table if r["source"] == str(new.resolve())]
    assert added["status"] == "ok" and added["worker"] in workers
    assert added["epsilon_deg"] == pytest.approx(0.70, abs=0.02)
    kept = {r["content_sha256"]: r for r in table}
    for row in before.values():  # the earlier rows are kept as they were
        assert kept[row["content_sha256"]]["identified_at"] == row["identified_at"]
    assert [g["axis"] for g in summary["grown"]][0] == "AX-1"


def crash_some(source: str, digest: str, options: dict) -> dict:
    """The fleet task, but the worker process dies on logs named crash-*: always on crash-always,
    on the first try only on crash-once (a marker file remembers the try across processes)."""
    name = Path(source).name
    if name == "crash-always.mcap":
        os._exit(70)
    if name == "crash-once.mcap":
        marker = Path(source).with_suffix(".tried")
        if not marker.exists():
            marker.touch()
            os._exit(70)
    return fleet.identify_log(source, digest, options=options)


def test_a_worker_crash_is_retried_once_then_recorded(tmp_path: Path) -> None:
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    folder = tmp_path / "logs"
    for i, name in enumerate(("crash-always.mcap", "crash-once.mcap", "fine.mcap")):
        _simulate(folder / name, 0.35, serial=f"C-{i}", seed=20 + i)
    out = tmp_path / "out"
    options = fleet.FleetOptions(workers=1, identification=QUICK.identification)
    summary = fleet.run([folder], out, options, task=crash_some)
    rows = {Path(r["source"]).name: r for r in pq.read_table(out / "fleet.parquet").to_pylist()}
    assert rows["crash-always.mcap"]["status"] == "crashed"
    assert "died" in rows["crash-always.mcap"]["error"]
    assert rows["crash-once.mcap"]["status"] == "ok" and (folder / "crash-once.tried").exists()
    assert rows["fine.mcap"]["status"] == "ok"
    assert summary.counts == {"ok": 2, "failed": 0, "crashed": 1}
    # a re-run tries the crashed log again (its worker died, not necessarily because of the log)
    again = fleet.run([folder], out, options)
    assert (again.identified, again.skipped, again.counts["ok"]) == (1, 2, 1)
    rows = {Path(r["source"]).name: r for r in pq.read_table(out / "fleet.parquet").to_pylist()}
    assert len(rows) == 3 and rows["crash-always.mcap"]["status"] == "ok"


def test_a_cluster_that_loses_every_worker_ends_the_run_and_keeps_what_came_in(tmp_path: Path,
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The only worker (no nanny to restart it) is killed while it identifies a log: Dask would keep the logs
    waiting for ever; the run stops after NO_WORKERS_S with what it has, and the table holds every log that
    finished."""
    from distributed import Client

    monkeypatch.setattr(cluster, "NO_WORKERS_S", 3.0)
    folder = tmp_path / "logs"
    for i in range(3):
        _simulate(folder / f"ax-{i}.mcap", 0.35, serial=f"D-{i}", seed=31 + i)
    out = tmp_path / "out"
    outcome: list[BaseException | fleet.FleetSummary] = []

    def run(address: str) -> None:
        try:
            outcome.append(fleet.run([folder], out, fleet.FleetOptions(scheduler=address,
                                                                       identification=QUICK.identification)))
        except BaseException as err:  # noqa: BLE001 — the test reads it
            outcome.append(err)

    with _dask_cluster("--no-nanny") as (address, worker, _), Client(address, timeout="60s") as client:
        runner = threading.Thread(target=run, args=(address,), daemon=True)
        runner.start()
        deadline = time.monotonic() + 120
        while not any(client.processing().values()) and time.monotonic() < deadline:
            time.sleep(0.05)
        os.killpg(worker.pid, 9)  # mid-identification
        runner.join(timeout=60)
        waits = runner.is_alive()  # before the scheduler goes: its end would end the wait too
    assert not waits, "the run still waits on a cluster with no workers after a minute"
    [err] = outcome
    assert isinstance(err, fleet.ClusterError), err
    found = re.search(r"no workers for \d+ s, with ([123]) log\(s\) waiting; the logs identified so far are kept",
                      str(err))
    assert found, str(err)
    rows = pq.read_table(out / "fleet.parquet").to_pylist() if (out / "fleet.parquet").exists() else []
    assert len(rows) == 3 - int(found.group(1))  # nothing that finished is lost
    assert all(r["status"] == "ok" for r in rows)


def test_bad_fleet_input_is_one_line_and_a_nonzero_exit(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    run = run_cli("--replay", empty, tmp_path / "missing.mcap", out=tmp_path / "out")
    assert run.code == 3 and run.stderr.count("\n") == 1 and "missing.mcap" in run.stderr
    run = run_cli("--replay", empty, out=tmp_path / "out")
    assert run.code == 3 and "no .mcap or .csv logs" in run.stderr
    run = run_cli("--replay", empty, "--workers", "0", out=tmp_path / "out")
    assert run.code == 2 and run.stderr.count("\n") == 1 and "--workers" in run.stderr
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "fleet.parquet").write_text("not a table")
    _simulate(empty / "a.mcap", 0.3, seed=1)
    run = run_cli("--replay", empty, out=tmp_path / "out")
    assert run.code == 7 and "not a readable Parquet table" in run.stderr
    assert (tmp_path / "out" / "fleet.parquet").read_text() == "not a table"  # nothing lost
