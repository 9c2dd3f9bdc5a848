"""Fleet mode: identify many axes' logs at once on a Dask cluster, and watch their backlash grow.

``commission --replay FOLDER [MORE ...] --out DIR`` comes here with more than one log (or a
folder, or ``--scheduler``): every .mcap / .csv log is identified in a Dask task
(:mod:`.cluster`), each task returns one row of ``DIR/fleet.parquet`` (:mod:`.table`), and
``DIR/fleet.html`` (:mod:`.report`) shows each axis over time, the axes whose backlash grew
first. A log that fails is a row, never the end of the batch; a re-run identifies only the logs
whose content is not in the table yet.

Threads: each task is one log on one worker thread; a local cluster runs one single-threaded
worker process per core and each identification with ``threads_per_log`` threads
(bench/bench_fleet.py measures the choice).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from ..ident.hybrid import IdentificationOptions
from .cluster import ClusterError, ClusterInfo, Task, connect, identify_all
from .report import REPORT_NAME, AxisTrend, axis_trends, write_fleet_report
from .table import SCHEMA, FleetTable, LogStatus, content_hash, find_logs, identify_log

__all__ = ["REPORT_NAME", "SCHEMA", "TABLE_NAME", "AxisTrend", "ClusterError", "FleetOptions", "FleetSummary",
           "LogStatus", "axis_trends", "identify_log", "run"]

#: File name of the table in the output folder.
TABLE_NAME = "fleet.parquet"

#: How often the table is written while results come in [s]: an interrupted batch keeps them.
FLUSH_INTERVAL_S = 10.0

#: Progress callback: (logs done, logs to do, detail).
Progress = Callable[[int, int, str], None]


class FleetOptions(BaseModel):
    """Options of :func:`run` (validated)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scheduler: str | None = Field(
        None, description="Address of an existing Dask scheduler (tcp://HOST:PORT); None: a local cluster.")
    workers: int | None = Field(
        None, ge=1, description="Local cluster: worker processes (one thread each); None: one per core.")
    threads_per_log: int = Field(
        1, ge=1, le=64, description="Threads of each identification (IdentificationOptions.threads): one, "
        "since every core already runs a worker (bench/bench_fleet.py).")
    growth_threshold_deg: float = Field(
        0.05, ge=0, description="An axis whose ε grew by more than this between its first and last "
        "trusted records is listed first in fleet.html [deg].")
    identification: IdentificationOptions = Field(
        default_factory=IdentificationOptions, description="Options of every identification (the recipe's).")


@dataclass(frozen=True)
class FleetSummary:
    """What one fleet run did."""

    table: Path
    report: Path
    found: int
    """Logs named or found under the folders."""
    skipped: int
    """Logs whose content was in the table already (or twice in this batch)."""
    identified: int
    """Logs run as tasks this time."""
    rows: int
    """Rows of the table after the run."""
    counts: dict[str, int]
    """Rows of this run by status (ok, failed, crashed)."""
    approximate: int
    """Rows of this run identified but flagged approximate."""
    seconds: float
    """Wall time of the tasks (cluster start-up included) [s]."""
    cluster: ClusterInfo | None
    """Where the tasks ran; None when there was nothing to do."""
    grown: list[AxisTrend] = field(default_factory=list)
    """Axes whose backlash grew beyond the threshold, largest growth first (whole table)."""

    @property
    def logs_per_minute(self) -> float:
        return 60.0 * self.identified / self.seconds if self.seconds > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "table": str(self.table), "report": str(self.report), "found": self.found, "skipped": self.skipped,
            "identified": self.identified, "rows": self.rows, "counts": dict(self.counts),
            "approximate": self.approximate, "seconds": self.seconds,
            "logs_per_minute": self.logs_per_minute,
            "cluster": None if self.cluster is None else {
                "scheduler": self.cluster.scheduler, "local": self.cluster.local,
                "workers": self.cluster.workers, "threads": self.cluster.threads},
            "grown": [{"axis": a.key, "name": a.name, "growth_deg": a.growth_deg} for a in self.grown],
        }


def run(paths: Sequence[Path], out_dir: Path, options: FleetOptions | None = None, *,
        progress: Progress | None = None, task: Task = identify_log) -> FleetSummary:
    """Identify every log of ``paths`` (files, folders) not yet in ``out_dir/fleet.parquet``,
    add their rows to it, and write ``out_dir/fleet.html``.

    :param task: what runs per log (``identify_log``; a test passes one that crashes a worker).
    :raises LogFormatError: a path does not exist, or there is no log at all.
    :raises ClusterError: the scheduler cannot be reached or has no workers.
    :raises OutputError: the table or the page cannot be written (or DIR/fleet.parquet is not a table).
    """
    opt = options if options is not None else FleetOptions()
    logs = find_logs(paths)
    table = FleetTable(out_dir / TABLE_NAME)  # refuses an unreadable table before any work
    todo: dict[str, str] = {}
    for log in logs:
        digest = content_hash(log)
        if not table.done(digest) and digest not in todo:
            todo[digest] = str(log)
    id_options = opt.identification.model_copy(update={"threads": opt.threads_per_log})
    counts = {s.value: 0 for s in LogStatus}
    approximate = 0
    start = time.perf_counter()
    info = None
    if todo:
        last_flush = time.monotonic()
        done = 0

        def on_row(row: dict[str, Any]) -> None:
            nonlocal done, approximate, last_flush
            table.add(row)
            done += 1
            counts[row["status"]] += 1
            approximate += row.get("approximate") is True
            if progress is not None:
                progress(done, len(todo), f"{Path(row['source']).name}: {row['status']}")
            if time.monotonic() - last_flush > FLUSH_INTERVAL_S:
                table.write()
                last_flush = time.monotonic()

        try:
            with connect(opt.scheduler, opt.workers) as (client, info):
                if progress is not None:
                    progress(0, len(todo), f"{info.workers} worker(s), {info.threads} thread(s)")
                identify_all(client, [(src, digest) for digest, src in todo.items()],
                             id_options.model_dump(mode="json"), task, on_row)
        finally:
            if done:
                table.write()  # whatever came in, also when interrupted
    seconds = time.perf_counter() - start
    rows = table.rows()
    report = write_fleet_report(out_dir / REPORT_NAME, rows, opt.growth_threshold_deg)
    grown = [a for a in axis_trends(rows, opt.growth_threshold_deg) if a.grew]
    return FleetSummary(table=table.path, report=report, found=len(logs), skipped=len(logs) - len(todo),
                        identified=len(todo), rows=len(table), counts=counts, approximate=approximate,
                        seconds=seconds, cluster=info, grown=grown)
