"""CSV replay logs: a Recording as a table of uniformly sampled columns.

Format::

    # drive-commission recording          (optional '#' comment lines, anywhere)
    # sample_rate_hz: 8000.0              (optional directive, before the header)
    # start_time: 2025-01-01T00:00:00+00:00   (optional directive, before the header)
    # lost_samples: 17,40-43              (optional directive: samples a link lost, interpolated)
    t,torque_ref,motor_velocity,motor_position
    0.0,0.12,0.0,0.0
    0.000125,0.13,0.002,2.5e-07
    ...

Columns, by header name (a unit in brackets may follow, ``t [s]``; it must then
be the SI unit below): ``t`` [s], ``torque_ref`` [N·m] and ``motor_velocity``
[rad/s] are required; ``motor_position`` [rad], ``load_position`` [rad] and
``load_velocity`` [rad/s] are optional; any other column is an error. The
separator is ``,`` (``;`` or tab when the header has no comma); with ``;`` or tab, numbers may have a
decimal comma (``0,125``, a spreadsheet's export in many locales) when the first data row has one.

The file is read line by line (a regular file; lines of at most 64 Ki characters, at most
4.8 million data rows), so its size bounds neither the memory nor the time before an error.

Sampling must be uniform: every interval within 1e-3 of the median interval (or of a whole
multiple of it: a few rows a logger dropped, which are interpolated and marked lost as a streamed
link's lost cycles are, up to 20 % of the record and 0.1 s in one piece), or, for a time column
rounded coarser than that (a Unix time in float64, a spreadsheet's four decimals), every sample
within half its rounding step of a uniform grid; and at least 50 Hz (a ``t`` in milliseconds is an error that says
so). The sample rate is ``sample_rate_hz`` from its directive when given (it must
agree with the data), else 1 / median interval (or the rounded column's grid). ``start_time`` is the
directive's ISO-8601 time when given, else the time column's first value when it is a
Unix time, else the file's modification time in UTC. ``Recording.metadata["source"]`` is the file name; the drive is unknown.

:func:`write_csv` writes the directives and every float with ``repr``, so
that :func:`read_csv` gives back the same samples, rate, start time and lost samples bitwise.
"""

from __future__ import annotations

import csv
import io
import os
import re
from array import array
from collections.abc import Iterator, Sequence
from datetime import datetime, timezone

import numpy as np

from .exceptions import LogFormatError, RecordingError
from .recording import (LOST_SAMPLES_KEY, MAX_GAP_S, MAX_LOST_FRACTION, MAX_SAMPLES, REQUIRED_SIGNALS, SIGNAL_UNITS,
                        Recording, decode_samples, encode_samples)

__all__ = ["UNIFORM_TOLERANCE", "read_csv", "write_csv"]

#: Largest deviation of a sample interval from the median one, relative to it.
UNIFORM_TOLERANCE = 1e-3
#: A time column whose interval changes on this share of its samples (and on 10 at least) is rounded,
#: not jittered or missing a sample ...
ROUNDED_SHARE = 0.05
#: Slowest sample rate read [Hz]: below it a time column is in other units than seconds.
MIN_SAMPLE_RATE_HZ = 50.0
#: A time column from this value on [s] is a Unix time (2001-09-09), the run's start when no directive says.
UNIX_TIME_FROM_S = 1e9
#: Longest line read (a row of six floats written with repr is under 150 characters).
MAX_LINE_CHARS = 1 << 16

_UNITS = {"t": "s", **SIGNAL_UNITS}
_UNIT_ALIASES = {"N·m": {"N·m", "Nm", "N*m", "N.m", "N m", "N⋅m"}}
_HEADER_CELL = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\[\s*([^\]]*?)\s*\])?\s*$")
_DIRECTIVE = re.compile(r"^#\s*(sample_rate_hz|start_time|lost_samples)\s*[:=]\s*(.*?)\s*$")


def _sample_period(t: np.ndarray, p: object,
                   line_numbers: Sequence[int]) -> tuple[float, np.ndarray, np.ndarray | None]:
    """The sample period [s] of the increasing time column ``t``, shape (N,), the sample times, and each
    row's sample index when rows are missing (else None): its median interval, every interval within
    ``UNIFORM_TOLERANCE`` of it or of a whole multiple of it (rows a logger dropped), and ``t``; or, when ``t`` is
    rounded coarser than that (a Unix time in float64, a spreadsheet's decimals), the period of the
    uniform grid through its samples, fitted by least squares, every sample within half the rounding
    step of it, and that grid (the rounding is no jitter of the drive's clock to resample from).

    :raises LogFormatError: the sampling is not uniform (the line of the first sample that is not).
    """
    dt = np.diff(t)
    dt_med = float(np.median(dt))
    change = np.abs(np.diff(dt))
    change = change[change > 1e-9 * dt_med]
    # a rounded column changes its interval by whole rounding steps, often; one gap or glitch does not
    step = float(np.min(change)) if change.size >= max(ROUNDED_SHARE * dt.size, 10) else 0.0
    if step <= UNIFORM_TOLERANCE * dt_med:
        periods = np.maximum(np.round(dt / dt_med), 1.0)
        off = np.abs(dt - periods * dt_med) > UNIFORM_TOLERANCE * dt_med
        if off.any():
            k = int(np.argmax(off)) + 1
            raise LogFormatError(
                f"{p}: line {line_numbers[k]}: non-uniform sampling (interval {dt[k - 1]:.9g} s, "
                f"expected {dt_med:.9g} s or a whole multiple of it, within {UNIFORM_TOLERANCE:g} of it)"
            )
        slots = np.concatenate(([0], np.cumsum(periods.astype(np.int64)))) if np.any(periods > 1.0) else None
        return dt_med, t, slots
    k = np.arange(t.size) - 0.5 * (t.size - 1)
    rel = t - float(np.mean(t))
    period = float(np.dot(k, rel) / np.dot(k, k))  # the grid by least squares: its ties round either way
    off = np.abs(rel - k * period) > 0.5 * step + UNIFORM_TOLERANCE * period
    if off.any() or step >= period:
        i = int(np.argmax(off))
        raise LogFormatError(
            f"{p}: line {line_numbers[i]}: non-uniform sampling (t rounded to {step:.3g} s: t={float(t[i])!r} s "
            f"lies off the uniform grid of {period:.9g} s by more than half of that)"
        )
    return period, float(np.mean(t)) + k * period, None


def _unit_ok(expected: str, given: str) -> bool:
    return given in _UNIT_ALIASES.get(expected, {expected})


def read_csv(path: str | os.PathLike[str]) -> Recording:
    """Read a CSV replay log (format in the module docstring) as a Recording.

    The file is read line by line into float arrays (memory ~8 bytes per value); it must be a
    regular file, lines at most :data:`MAX_LINE_CHARS` long and at most
    :data:`~commission.recording.MAX_SAMPLES` data rows.
    """
    from .mcaplog import regular_file_size

    p = os.fspath(path)
    regular_file_size(p, "a CSV file")
    try:
        mtime = os.stat(p).st_mtime
        with open(p, encoding="utf-8-sig", newline="") as f:
            lines = _Lines(p, f)
            try:
                return _read(p, lines, mtime)
            except UnicodeDecodeError as err:
                raise LogFormatError(f"{p}: not a text file (invalid UTF-8 in line {lines.lineno + 1})") from err
    except FileNotFoundError as err:
        raise LogFormatError(f"{p}: no such file") from err
    except OSError as err:
        raise LogFormatError(f"{p}: cannot read ({err.strerror or err})") from err


class _Lines:
    """The lines of a text file, each at most MAX_LINE_CHARS long, numbered from 1 (``lineno``:
    the last line handed out)."""

    def __init__(self, path: str, f: io.TextIOBase) -> None:
        self._path, self._f = path, f
        self.lineno = 0

    def __iter__(self) -> Iterator[str]:
        return self

    def __next__(self) -> str:
        line = self._f.readline(MAX_LINE_CHARS + 1)
        if not line:
            raise StopIteration
        self.lineno += 1
        if len(line) > MAX_LINE_CHARS:
            raise LogFormatError(f"{self._path}: line {self.lineno} is longer than {MAX_LINE_CHARS:,} characters: "
                                 "not a CSV log")
        return line


def _read(p: str, lines: _Lines, mtime: float) -> Recording:
    directives: dict[str, tuple[int, str]] = {}
    header_line = None
    seen_text = False
    for line in lines:
        stripped = line.strip()
        if not stripped:
            continue
        seen_text = True
        if stripped.startswith("#"):
            m = _DIRECTIVE.match(stripped)
            if m:
                directives[m.group(1)] = (lines.lineno, m.group(2))
            continue
        header_line = line
        break
    if not seen_text:
        raise LogFormatError(f"{p}: empty file")
    if header_line is None:
        raise LogFormatError(f"{p}: no header line (only comments)")
    header_at = lines.lineno
    header_line = header_line.rstrip("\r\n")
    delimiter = "," if "," in header_line else ";" if ";" in header_line else "\t" if "\t" in header_line else ","
    try:
        header_cells = next(csv.reader([header_line], delimiter=delimiter))
    except (csv.Error, StopIteration) as err:
        raise LogFormatError(f"{p}: line {header_at}: not a CSV header ({err})") from None
    columns = _parse_header(p, header_at, header_cells)

    values = [array("d") for _ in columns]
    line_numbers = array("q")
    reader = csv.reader(lines, delimiter=delimiter)
    number = float
    try:
        for cells in reader:
            lineno = lines.lineno
            if not cells or (len(cells) == 1 and not cells[0].strip()) or cells[0].lstrip().startswith("#"):
                continue
            if not line_numbers and delimiter != "," and any("," in cell for cell in cells):
                number = _decimal_comma  # a spreadsheet's export in a locale that writes 0,125
            if len(cells) != len(columns):
                raise LogFormatError(f"{p}: line {lineno}: {len(cells)} cells, the header has {len(columns)} columns")
            if len(line_numbers) >= MAX_SAMPLES:
                raise LogFormatError(f"{p}: more than {MAX_SAMPLES:,} data rows, more than a run records "
                                     "(10 minutes at 8 kHz)")
            for name, cell, column in zip(columns, cells, values):
                try:
                    column.append(number(cell))
                except ValueError:
                    what = "empty cell" if not cell.strip() else f"not a number ({cell.strip()[:40]!r})"
                    raise LogFormatError(f"{p}: line {lineno}, column '{name}': {what}") from None
            line_numbers.append(lineno)
    except csv.Error as err:
        raise LogFormatError(f"{p}: line {lines.lineno}: not CSV ({err})") from None

    n_rows = len(line_numbers)
    if n_rows < 2:
        raise LogFormatError(f"{p}: {n_rows} data row{'s' if n_rows != 1 else ''}, a recording needs at least 2")
    data = {name: np.frombuffer(column, dtype=np.float64) for name, column in zip(columns, values)}
    for name in columns:
        bad = ~np.isfinite(data[name])
        if bad.any():
            r = int(np.argmax(bad))
            raise LogFormatError(
                f"{p}: line {line_numbers[r]}, column '{name}': {float(data[name][r])!r} is not a finite number"
            )

    t = data["t"]
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0)) + 1
        raise LogFormatError(
            f"{p}: line {line_numbers[k]}: time does not increase (t={float(t[k])!r} s after t={float(t[k - 1])!r} s)"
        )
    dt_med, t, slots = _sample_period(t, p, line_numbers)
    sample_rate_hz = 1.0 / dt_med
    if sample_rate_hz < MIN_SAMPLE_RATE_HZ:
        raise LogFormatError(
            f"{p}: the t column gives {sample_rate_hz:.6g} Hz, slower than any servo drive's log: t must be in "
            f"seconds (if it is in milliseconds, the log is at {1e3 * sample_rate_hz:.6g} Hz)"
        )
    if "sample_rate_hz" in directives:
        lineno, value = directives["sample_rate_hz"]
        try:
            given = float(value)
        except ValueError:
            raise LogFormatError(f"{p}: line {lineno}: sample_rate_hz {value[:40]!r} is not a number") from None
        if not (np.isfinite(given) and given > 0) or abs(given * dt_med - 1.0) > UNIFORM_TOLERANCE:
            raise LogFormatError(
                f"{p}: line {lineno}: sample_rate_hz {value[:40]} disagrees with the time column "
                f"({sample_rate_hz:.9g} Hz from the median interval)"
            )
        sample_rate_hz = given
    # a t column that counts Unix time (since 2001, before the file was written) says when the run started
    unix = UNIX_TIME_FROM_S <= float(t[0]) <= mtime
    start_time = datetime.fromtimestamp(float(t[0]) if unix else mtime, tz=timezone.utc)
    if "start_time" in directives:
        lineno, value = directives["start_time"]
        try:
            start_time = datetime.fromisoformat(value)
        except ValueError:
            raise LogFormatError(f"{p}: line {lineno}: start_time {value[:40]!r} is not an ISO-8601 time") from None
        if start_time.tzinfo is None:
            raise LogFormatError(f"{p}: line {lineno}: start_time {value!r} has no time zone (add +00:00 for UTC)")

    signals = {name: data[name] for name in columns if name != "t"}
    metadata = {"source": os.path.basename(p)}
    lost = None
    if slots is not None:
        t, signals, lost = _with_missing_rows(p, slots, t, signals, sample_rate_hz, line_numbers)
    if "lost_samples" in directives:
        lineno, value = directives["lost_samples"]
        try:
            marked = decode_samples(value, t.size)
        except RecordingError as err:
            raise LogFormatError(f"{p}: line {lineno}: {err}") from None
        lost = marked if lost is None else lost | marked
    if lost is not None and lost.any():
        metadata[LOST_SAMPLES_KEY] = encode_samples(lost)
    try:
        return Recording(
            t=t,
            sample_rate_hz=sample_rate_hz,
            start_time=start_time,
            metadata=metadata,
            **signals,
        )
    except RecordingError as err:
        raise LogFormatError(f"{p}: {err}") from err


def _with_missing_rows(p: str, slots: np.ndarray, t: np.ndarray, signals: dict[str, np.ndarray], sample_rate_hz: float,
                       line_numbers: Sequence[int]) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """The record on its whole sample grid, the rows a logger dropped interpolated and marked lost (as a
    streamed link's lost cycles are: the identification leaves them out), and the mask of those, shape (M,).

    :param slots: each row's sample index, shape (N,), increasing from 0.
    :raises LogFormatError: more rows are missing than ``MAX_LOST_FRACTION`` of the record, or a stretch
        longer than ``MAX_GAP_S`` (the record would be mostly guessed).
    """
    n = int(slots[-1]) + 1
    lost = np.ones(n, dtype=bool)
    lost[slots] = False
    gaps = np.diff(slots) - 1
    k = int(np.argmax(gaps))
    if lost.mean() > MAX_LOST_FRACTION or gaps[k] / sample_rate_hz > MAX_GAP_S:
        raise LogFormatError(
            f"{p}: {int(lost.sum()):,} of {n:,} samples are missing ({lost.mean():.1%}; {gaps[k]:,} in one piece "
            f"before line {line_numbers[k + 1]}): more than a record can lose and still be identified "
            f"({MAX_LOST_FRACTION:.0%} of it, or {MAX_GAP_S * 1e3:g} ms in one piece)")
    grid = np.arange(n, dtype=np.float64)
    full = {name: np.interp(grid, slots, x) for name, x in signals.items()}
    return np.interp(grid, slots, t), full, lost


def _parse_header(path: str, lineno: int, cells: Sequence[str]) -> list[str]:
    if all(_looks_numeric(c) for c in cells):
        raise LogFormatError(f"{path}: line {lineno}: no header line (the first line holds numbers)")
    names: list[str] = []
    for cell in cells:
        m = _HEADER_CELL.match(cell)
        if not m:
            raise LogFormatError(f"{path}: line {lineno}: bad column name {cell.strip()!r} in the header")
        name, unit = m.group(1), m.group(2)
        if name in _UNITS and unit is not None and not _unit_ok(_UNITS[name], unit):
            raise LogFormatError(f"{path}: line {lineno}: column '{name}' is in {unit!r}, expected {_UNITS[name]!r}")
        names.append(name)
    unknown = [n for n in names if n not in _UNITS]
    if unknown:
        more = f" and {len(unknown) - 5:,} more" if len(unknown) > 5 else ""
        raise LogFormatError(
            f"{path}: line {lineno}: unknown column(s) {', '.join(map(repr, unknown[:5]))}{more}; "
            f"known: {', '.join(_UNITS)}"
        )
    duplicate = sorted({n for n in names if names.count(n) > 1})
    if duplicate:
        raise LogFormatError(f"{path}: line {lineno}: duplicate column(s) {', '.join(map(repr, duplicate))}")
    missing = [n for n in ("t", *REQUIRED_SIGNALS) if n not in names]
    if missing:
        raise LogFormatError(f"{path}: line {lineno}: missing required column(s) {', '.join(map(repr, missing))}")
    return names


def _decimal_comma(cell: str) -> float:
    if "." in cell:
        raise ValueError(cell)  # 1.000,5 (a thousands separator) or a mix of both: not read as a guess
    return float(cell.replace(",", "."))


def _looks_numeric(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def write_csv(path: str | os.PathLike[str], recording: Recording) -> None:
    """Write ``recording`` as a CSV replay log (exact floats; directives for rate, start time and the
    samples a link lost).

    Drive identity and other metadata are not stored. :class:`RecordingError` when the recording
    is not uniformly sampled within :data:`UNIFORM_TOLERANCE` (the CSV format requires it).
    """
    dt = np.diff(recording.t)
    dt_med = float(np.median(dt))
    if np.any(np.abs(dt - dt_med) > UNIFORM_TOLERANCE * dt_med):
        raise RecordingError("CSV logs need uniform sampling; this recording is not (write MCAP instead)")
    if abs(recording.sample_rate_hz * dt_med - 1.0) > UNIFORM_TOLERANCE:
        raise RecordingError(
            f"sample_rate_hz {recording.sample_rate_hz!r} disagrees with the sample times "
            f"({1.0 / dt_med:.9g} Hz); a CSV log could not be read back"
        )
    names = ["t", *(name for name, _ in recording.signals())]
    columns = [recording.t.tolist(), *(arr.tolist() for _, arr in recording.signals())]
    units = ", ".join(f"{n} [{_UNITS[n]}]" for n in names)
    with open(os.fspath(path), "w", encoding="utf-8", newline="\n") as f:
        f.write(f"# drive-commission recording; units: {units}\n")
        f.write(f"# sample_rate_hz: {recording.sample_rate_hz!r}\n")
        f.write(f"# start_time: {recording.start_time.isoformat()}\n")
        if recording.lost_mask.any():
            f.write(f"# lost_samples: {encode_samples(recording.lost_mask)}\n")
        f.write(",".join(names) + "\n")
        f.writelines(",".join(map(repr, row)) + "\n" for row in zip(*columns))
