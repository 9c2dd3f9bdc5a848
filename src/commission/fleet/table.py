"""The fleet table: one row per identified log, kept in ``fleet.parquet``.

A row is what :func:`identify_log` returns: a flat dict of scalars (where the log came from, the
drive's identity, the record's start, the identified model with its 95 % intervals, the fit's
verdict, and for a log that failed, why). It is all that travels back through the scheduler, so a
row stays about a kilobyte however long the record. Column names carry their SI unit.

Logs are known by the SHA-256 of their bytes: a re-run skips every log whose content is in the
table already (moved or renamed logs too), except those whose worker crashed, which are tried again.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
import warnings
from collections.abc import Iterable, Mapping, Sequence
from datetime import datetime, timezone
from enum import Enum
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from ..exceptions import CommissionError, LogFormatError, OutputError
from ..recording import read_log

__all__ = [
    "LOG_SUFFIXES",
    "SCHEMA",
    "FleetTable",
    "LogStatus",
    "content_hash",
    "crashed_row",
    "find_logs",
    "identify_log",
]

#: File name endings of the logs a folder is searched for (lower case).
LOG_SUFFIXES = (".mcap", ".csv")

#: The six parameters of the two-mass model: result.json key → column stem with its unit.
_PARAMETERS = {
    "J_m": "J_m_{}kg_m2",
    "J_l": "J_l_{}kg_m2",
    "B_m": "B_m_{}nm_s_per_rad",
    "B_l": "B_l_{}nm_s_per_rad",
    "K": "K_{}nm_per_rad",
    "D": "D_{}nm_s_per_rad",
}
#: Two-sided 95 % quantile of the normal distribution (intervals from relative standard errors).
_Z95 = 1.959963984540054


class LogStatus(str, Enum):
    """What became of one log."""

    OK = "ok"
    """Identified (read ``approximate`` before trusting the numbers)."""
    FAILED = "failed"
    """The log could not be read or identified (the same on every try): ``error`` says why."""
    CRASHED = "crashed"
    """The worker died, or the task raised an unexpected error, twice: tried again on a re-run."""


def _param(name: str, which: str = "") -> str:
    return _PARAMETERS[name].format(f"{which}_" if which else "")


def _schema() -> pa.Schema:
    fields: list[pa.Field] = [
        pa.field("source", pa.string(), nullable=False),
        pa.field("content_sha256", pa.string(), nullable=False),
        pa.field("status", pa.string(), nullable=False),
        pa.field("error", pa.string()),
        pa.field("warnings", pa.string()),
        pa.field("drive_backend", pa.string()),
        pa.field("drive_vendor", pa.string()),
        pa.field("drive_product", pa.string()),
        pa.field("drive_serial", pa.string()),
        pa.field("drive_firmware", pa.string()),
        pa.field("start_time", pa.timestamp("us", tz="UTC")),
        pa.field("samples", pa.int64()),
        pa.field("sample_rate_hz", pa.float64()),
        pa.field("method", pa.string()),
        pa.field("epsilon_deg", pa.float64()),
        pa.field("epsilon_low_deg", pa.float64()),
        pa.field("epsilon_high_deg", pa.float64()),
        pa.field("backlash_detected", pa.bool_()),
    ]
    for name in _PARAMETERS:
        fields += [pa.field(_param(name, w), pa.float64()) for w in ("", "low", "high")]
    for mode in ("resonance", "antiresonance"):
        fields += [pa.field(f"f_{mode}_{w}hz", pa.float64()) for w in ("", "low_", "high_")]
    fields += [
        pa.field("approximate", pa.bool_()),
        pa.field("approximate_reasons", pa.string()),
        pa.field("residual_ratio", pa.float64()),
        pa.field("identify_s", pa.float64()),
        pa.field("worker", pa.string()),
        pa.field("identified_at", pa.timestamp("us", tz="UTC")),
    ]
    return pa.schema(fields)


#: Columns of fleet.parquet, in order (units in the names: deg, kg_m2, nm_per_rad, hz, s).
SCHEMA = _schema()


# ---------------------------------------------------------------------------------------------
# finding and hashing logs (on the client)
# ---------------------------------------------------------------------------------------------
def find_logs(paths: Sequence[Path]) -> list[Path]:
    """Every log named, and every .mcap / .csv under each folder named (recursively, sorted);
    a path given twice counts once."""
    found: list[Path] = []
    for path in paths:
        if path.is_dir():
            found += sorted(p for p in path.rglob("*") if p.suffix.lower() in LOG_SUFFIXES and p.is_file())
        elif path.exists():
            found.append(path)
        else:
            raise LogFormatError(f"{path}: no such file or folder")
    unique = list(dict.fromkeys(p.resolve() for p in found))
    if not unique:
        raise LogFormatError(f"no .mcap or .csv logs in {', '.join(str(p) for p in paths)}")
    return unique


def content_hash(path: Path) -> str:
    """SHA-256 of the file's bytes, hex (an unreadable file hashes its name and error, so that it
    still becomes a row, and a failed one)."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    except OSError as err:
        digest.update(f"unreadable:{path}:{err}".encode())
    return digest.hexdigest()


# ---------------------------------------------------------------------------------------------
# one log → one row (runs on a worker)
# ---------------------------------------------------------------------------------------------
def _empty_row(source: str, digest: str, status: LogStatus) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(SCHEMA.names)
    row.update(source=source, content_sha256=digest, status=status.value)
    return row


def _worker_address() -> str | None:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):  # called outside a Dask worker (a direct call)
        return None


def _interval(doc: Mapping[str, Any], name: str, value: float) -> tuple[float | None, float | None]:
    """95 % interval of a two-mass parameter: result.json's ``two_mass_interval`` when it has one,
    else ±1.96 relative standard errors, else unknown."""
    given = doc.get("two_mass_interval", {}).get(name)
    if given is not None:
        return float(given[0]), float(given[1])
    rel = doc.get("two_mass_relative_stderr", {}).get(name)
    if rel is not None and math.isfinite(rel):
        return value * (1.0 - _Z95 * rel), value * (1.0 + _Z95 * rel)
    return None, None


def _mode_intervals(tm: Mapping[str, float], iv: Mapping[str, tuple[float | None, float | None]],
                    f_r: float, f_a: float) -> dict[str, float | None]:
    """Intervals of the resonance and anti-resonance from those of J_m, J_l and K.

    The undamped frequencies √(K(1/J_m + 1/J_l)) and √(K/J_l) rise with K and fall with either
    inertia, so their extremes over the box of the three intervals lie on its corners; the ratio
    of a corner's to the nominal value scales the identified (damped) frequency. The box ignores
    the parameters' correlation: the interval is wider than the joint one, never narrower."""
    out: dict[str, float | None] = {k: None for k in ("f_resonance_low_hz", "f_resonance_high_hz",
                                                       "f_antiresonance_low_hz", "f_antiresonance_high_hz")}
    (jm_lo, jm_hi), (jl_lo, jl_hi), (k_lo, k_hi) = iv["J_m"], iv["J_l"], iv["K"]
    if None in (jm_lo, jm_hi, jl_lo, jl_hi, k_lo, k_hi) or min(jm_lo, jl_lo, k_lo) <= 0:  # type: ignore[type-var]
        return out

    def resonance(k: float, jm: float, jl: float) -> float:
        return math.sqrt(k * (1.0 / jm + 1.0 / jl))

    nominal_r = resonance(tm["K"], tm["J_m"], tm["J_l"])
    nominal_a = math.sqrt(tm["K"] / tm["J_l"])
    out["f_resonance_low_hz"] = f_r * resonance(k_lo, jm_hi, jl_hi) / nominal_r  # type: ignore[arg-type]
    out["f_resonance_high_hz"] = f_r * resonance(k_hi, jm_lo, jl_lo) / nominal_r  # type: ignore[arg-type]
    out["f_antiresonance_low_hz"] = f_a * math.sqrt(k_lo / jl_hi) / nominal_a  # type: ignore[operator]
    out["f_antiresonance_high_hz"] = f_a * math.sqrt(k_hi / jl_lo) / nominal_a  # type: ignore[operator]
    return out


def row_from_result(doc: Mapping[str, Any]) -> dict[str, Any]:
    """The identification columns of a row from a result.json document (``Identification.to_dict()``)."""
    bl, tm, md = doc["backlash"], doc["two_mass"], doc["modes"]
    lo, hi = bl["epsilon_interval_deg"]
    row: dict[str, Any] = {
        "method": bl.get("method"),
        "epsilon_deg": float(bl["epsilon_deg"]),
        "epsilon_low_deg": float(lo),
        "epsilon_high_deg": float(hi),
        "backlash_detected": bool(bl.get("detected", True)),
    }
    intervals = {}
    for name in _PARAMETERS:
        value = float(tm[name])
        intervals[name] = _interval(doc, name, value)
        row[_param(name)] = value
        row[_param(name, "low")], row[_param(name, "high")] = intervals[name]
    f_r, f_a = (math.nan if md[k] is None else float(md[k]) for k in ("f_resonance_hz", "f_antiresonance_hz"))
    row.update(f_resonance_hz=f_r, f_antiresonance_hz=f_a)
    row.update(_mode_intervals(tm, intervals, f_r, f_a))
    fit = doc.get("fit")
    if fit is not None:
        row["approximate"] = bool(fit.get("approximate", False))
        row["approximate_reasons"] = "; ".join(fit.get("reasons", [])) or None
        row["residual_ratio"] = float(fit["residual_ratio"]) if "residual_ratio" in fit else None
    return row


def identify_log(source: str, digest: str, options: Mapping[str, Any]) -> dict[str, Any]:
    """The Dask task: read one log, identify it, return its row (never the record's arrays).

    ``options`` is :class:`IdentificationOptions` as a plain mapping (small, and independent of
    the client's pickled classes). A log that cannot be read or identified is a row with status
    ``failed``; any other exception propagates, so that the scheduler retries the task."""
    from ..ident.hybrid import IdentificationOptions, identify

    start = time.perf_counter()
    row = _empty_row(source, digest, LogStatus.OK)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            recording = read_log(Path(source))
            drive = recording.drive
            row.update(drive_backend=drive.backend, drive_vendor=drive.vendor, drive_product=drive.product,
                       drive_serial=drive.serial_number, drive_firmware=drive.firmware,
                       start_time=recording.start_time.astimezone(timezone.utc), samples=len(recording),
                       sample_rate_hz=recording.sample_rate_hz)
            result = identify(recording, IdentificationOptions.model_validate(dict(options)))
        row.update(row_from_result(result.to_dict(source)))
    except CommissionError as err:
        row.update(status=LogStatus.FAILED.value, error=f"{type(err).__name__}: {err}")
    row["warnings"] = "; ".join(dict.fromkeys(str(w.message) for w in caught)) or None
    row["identify_s"] = time.perf_counter() - start
    row["worker"] = _worker_address()
    row["identified_at"] = datetime.now(timezone.utc)
    return row


def crashed_row(source: str, digest: str, error: str) -> dict[str, Any]:
    """The row of a log whose task could not finish (the worker died, or an unexpected error), twice."""
    row = _empty_row(source, digest, LogStatus.CRASHED)
    row.update(error=error, identified_at=datetime.now(timezone.utc))
    return row


# ---------------------------------------------------------------------------------------------
# the table file
# ---------------------------------------------------------------------------------------------
class FleetTable:
    """fleet.parquet in memory: the rows read from the file plus those added since; written whole,
    atomically (a temporary file renamed over the old one), so an interrupted run loses nothing
    that was written before."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._rows: dict[str, dict[str, Any]] = {}
        if path.exists():
            try:
                table = pq.read_table(path)
            except (OSError, pa.ArrowException) as err:
                raise OutputError(f"{path} exists but is not a readable Parquet table ({err}): "
                                  "move it away or choose another --out") from err
            missing = set(SCHEMA.names) - set(table.column_names)
            if missing & {"source", "content_sha256", "status"}:
                raise OutputError(f"{path} is not a fleet table (no {', '.join(sorted(missing))} columns): "
                                  "move it away or choose another --out")
            for row in table.to_pylist():
                self._rows[row["content_sha256"]] = {name: row.get(name) for name in SCHEMA.names}
        self.read_rows = len(self._rows)

    def __len__(self) -> int:
        return len(self._rows)

    def done(self, digest: str) -> bool:
        """True when a log with this content has a row that a re-run keeps (ok or failed)."""
        row = self._rows.get(digest)
        return row is not None and row["status"] != LogStatus.CRASHED.value

    def add(self, row: Mapping[str, Any]) -> None:
        """Add a row, replacing one of the same content (a crashed log tried again)."""
        self._rows[row["content_sha256"]] = {name: row.get(name) for name in SCHEMA.names}

    def rows(self) -> list[dict[str, Any]]:
        """Every row, ordered by drive serial, record start and source."""
        far = datetime.min.replace(tzinfo=timezone.utc)
        return sorted(self._rows.values(), key=lambda r: (r["drive_serial"] or "", r["start_time"] or far,
                                                          r["source"]))

    def to_arrow(self) -> pa.Table:
        return pa.Table.from_pylist(self.rows(), schema=SCHEMA)

    def write(self) -> Path:
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(self.to_arrow(), tmp)
            os.replace(tmp, self.path)
        except OSError as err:
            tmp.unlink(missing_ok=True)
            raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err
        return self.path


def rows_of(table: pa.Table | Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Rows as dicts, from an Arrow table or any iterable of mappings."""
    if isinstance(table, pa.Table):
        return table.to_pylist()
    return [dict(r) for r in table]
