"""CSV replay logs: exact round trip, and a one-line error naming every kind of bad input."""

from __future__ import annotations

import os
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest

from commission.csvlog import read_csv, write_csv
from commission.exceptions import LogFormatError, RecordingError
from commission.recording import SIGNAL_UNITS, DriveInfo, Recording

START = datetime(2025, 3, 14, 15, 9, 26, 535897, tzinfo=timezone.utc)


def make_recording(n: int, *, optional: bool = True, seed: int = 0) -> Recording:
    rng = np.random.default_rng(seed)
    signals = {name: rng.standard_normal(n) * 10.0 ** rng.integers(-6, 6) for name in SIGNAL_UNITS}
    signals["torque_ref"][:3] = [5e-324, -1.7976931348623157e308, 0.1 + 0.2]
    if not optional:
        signals = {k: signals[k] for k in ("torque_ref", "motor_velocity")}
    return Recording.uniform(8000.0, start_time=START, **signals)


def write(tmp_path: Path, text: str, name: str = "log.csv") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def assert_error(path: Path, *parts: str) -> None:
    with pytest.raises(LogFormatError) as info:
        read_csv(path)
    text = str(info.value)
    assert str(path) in text and "\n" not in text
    for part in parts:
        assert part in text, text


GOOD = "t,torque_ref,motor_velocity\n0,0.5,0\n0.001,0.5,0.1\n0.002,0.4,0.2\n0.003,0.3,0.3\n"


# -- good input ---------------------------------------------------------------------------------
@pytest.mark.parametrize("optional", [True, False])
def test_round_trip_exact(tmp_path: Path, optional: bool) -> None:
    rec = make_recording(8000 if optional else 500, optional=optional)
    write_csv(tmp_path / "r.csv", rec)
    back = read_csv(tmp_path / "r.csv")
    assert back.equals(rec.replace(metadata={"source": "r.csv"}, drive=DriveInfo()))
    for name in ("t", *SIGNAL_UNITS):
        a, b = getattr(back, name), getattr(rec, name)
        assert (a is None) == (b is None)
        if a is not None:
            assert a.view(np.uint64).tolist() == b.view(np.uint64).tolist(), name


def test_plain_file_rate_from_median_interval_start_from_mtime(tmp_path: Path) -> None:
    text = ("# exported by a scope\n\nt [s],torque_ref [Nm],motor_velocity [rad/s],load_position\n"
            "0.0,0.5,0,1\n0.001,0.5,0.1,2\n\n0.002,0.4,0.2,3\n# a note\n0.0030000001,0.3,0.3,4\n")
    path = write(tmp_path, text)
    os.utime(path, (1_700_000_000.25, 1_700_000_000.25))
    rec = read_csv(path)
    assert len(rec) == 4 and rec.load_position.tolist() == [1, 2, 3, 4] and rec.motor_position is None
    assert rec.sample_rate_hz == pytest.approx(1000.0, rel=1e-9)
    assert rec.start_time == datetime.fromtimestamp(1_700_000_000.25, tz=timezone.utc)
    assert rec.metadata == {"source": "log.csv"}


@pytest.mark.parametrize("sep", [";", "\t"])
def test_other_separators(tmp_path: Path, sep: str) -> None:
    rec = read_csv(write(tmp_path, GOOD.replace(",", sep)))
    assert rec.torque_ref.tolist() == [0.5, 0.5, 0.4, 0.3]


@pytest.mark.parametrize("sep", [";", "\t"])
def test_a_decimal_comma_reads_the_same_samples(tmp_path: Path, sep: str) -> None:
    # a spreadsheet's export in a locale that writes 0,125: separator ';' (or tab), decimal comma
    rec = make_recording(2000)
    write_csv(tmp_path / "r.csv", rec)
    lines = (tmp_path / "r.csv").read_text().splitlines(keepends=True)
    text = "".join(line if line.startswith("#") else line.replace(",", sep).replace(".", ",") for line in lines)
    back = read_csv(write(tmp_path, text, "comma.csv"))
    for name in ("t", *SIGNAL_UNITS):
        assert getattr(back, name).view(np.uint64).tolist() == getattr(rec, name).view(np.uint64).tolist(), name
    # a thousands separator is not guessed at
    assert_error(write(tmp_path, "t;torque_ref;motor_velocity\n0;0,5;0\n0,001;1.000,5;0,1\n"),
                 "line 3, column 'torque_ref': not a number ('1.000,5')")


def test_rows_a_logger_dropped_are_interpolated_and_marked_lost(tmp_path: Path) -> None:
    rec = make_recording(1000, optional=False)
    write_csv(tmp_path / "r.csv", rec)
    lines = (tmp_path / "r.csv").read_text().splitlines(keepends=True)
    header = next(i for i, line in enumerate(lines) if line.startswith("t,"))
    dropped = {10, 500, 501, 502}  # sample indices: one row, then three in a row
    text = "".join(line for i, line in enumerate(lines) if i - header - 1 not in dropped)
    back = read_csv(write(tmp_path, text, "dropped.csv"))
    assert len(back) == 1000 and back.sample_rate_hz == rec.sample_rate_hz
    assert np.flatnonzero(back.lost_mask).tolist() == sorted(dropped)
    kept = ~back.lost_mask
    assert np.array_equal(back.torque_ref[kept], rec.torque_ref[kept])
    assert np.allclose(back.t, rec.t, rtol=0.0, atol=1e-15)
    # a lost sample lies on the line between its neighbours
    assert back.torque_ref[10] == pytest.approx(0.5 * (rec.torque_ref[9] + rec.torque_ref[11]), rel=1e-12, abs=1e-300)
    # and a record written with lost samples keeps them
    write_csv(tmp_path / "again.csv", back)
    assert np.array_equal(read_csv(tmp_path / "again.csv").lost_mask, back.lost_mask)


def test_a_record_missing_too_much_is_refused(tmp_path: Path) -> None:
    header = "t,torque_ref,motor_velocity\n"
    rows = [f"{k / 1000!r},1,2\n" for k in range(1000)]
    assert_error(write(tmp_path, header + "".join(rows[:300] + rows[401:])), "101 of 1,000 samples are missing",
                 "101 in one piece before line 302", "100 ms in one piece")
    # three gaps of 90 ms each: none too long, 21 % in all
    rows = [f"{k / 1000!r},1,2\n" for k in range(1270)]
    gone = {k for start in (100, 500, 900) for k in range(start, start + 90)}
    assert_error(write(tmp_path, header + "".join(r for k, r in enumerate(rows) if k not in gone)),
                 "270 of 1,270 samples are missing (21.3%")
    assert_error(write(tmp_path, "# lost_samples: 3-x\n" + header + "".join(rows)), "line 1", "'3-x' is not an index")


def test_utf8_bom_and_crlf(tmp_path: Path) -> None:
    path = tmp_path / "bom.csv"
    path.write_bytes(b"\xef\xbb\xbf" + GOOD.replace("\n", "\r\n").encode())
    assert len(read_csv(path)) == 4


# -- bad input ----------------------------------------------------------------------------------
def test_missing_empty_and_no_header(tmp_path: Path) -> None:
    assert_error(tmp_path / "nope.csv", "no such file")
    assert_error(write(tmp_path, ""), "empty file")
    assert_error(write(tmp_path, "\n  \n"), "empty file")
    assert_error(write(tmp_path, "# only\n# comments\n"), "no header line")
    assert_error(write(tmp_path, "0,0.5,0\n0.001,0.5,0.1\n"), "line 1", "no header line")
    (tmp_path / "dir.csv").mkdir()
    assert_error(tmp_path / "dir.csv", "is a directory")
    (tmp_path / "bin.csv").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00")
    assert_error(tmp_path / "bin.csv", "not a text file")


def test_columns(tmp_path: Path) -> None:
    assert_error(write(tmp_path, "t,torque_ref\n0,1\n1,2\n"), "missing required column", "'motor_velocity'")
    assert_error(write(tmp_path, "time,torque_ref,motor_velocity\n0,1,2\n1,2,3\n"),
                 "unknown column", "'time'", "known: t")
    assert_error(write(tmp_path, "t,torque_ref,motor_velocity,temp,current\n0,1,2,3,4\n"),
                 "unknown column(s) 'temp', 'current'")
    assert_error(write(tmp_path, "t,torque_ref,motor_velocity,torque_ref\n0,1,2,3\n"),
                 "duplicate column", "'torque_ref'")
    assert_error(write(tmp_path, "t,torque_ref,motor_velocity [rpm]\n0,1,2\n1,2,3\n"),
                 "'motor_velocity' is in 'rpm'", "rad/s")
    assert_error(write(tmp_path, "t,torque_ref,motor velocity\n0,1,2\n"), "bad column name 'motor velocity'")


def test_cells(tmp_path: Path) -> None:
    base = "t,torque_ref,motor_velocity\n0,0.5,0\n"
    assert_error(write(tmp_path, base + "0.001,,0.1\n"), "line 3, column 'torque_ref': empty cell")
    assert_error(write(tmp_path, base + "0.001,0.5,fast\n"), "line 3, column 'motor_velocity': not a number ('fast')")
    assert_error(write(tmp_path, base + "0.001,0.5,0.1\n0.002,nan,0.2\n"), "line 4, column 'torque_ref': nan is not a finite")
    assert_error(write(tmp_path, base + "0.001,0.5,inf\n"), "line 3, column 'motor_velocity': inf is not a finite")
    assert_error(write(tmp_path, base + "0.001,0.5\n"), "line 3: 2 cells, the header has 3 columns")


def test_rows_and_time(tmp_path: Path) -> None:
    header = "t,torque_ref,motor_velocity\n"
    assert_error(write(tmp_path, header), "0 data rows", "at least 2")
    assert_error(write(tmp_path, header + "0,1,2\n"), "1 data row,", "at least 2")
    assert_error(write(tmp_path, header + "0,1,2\n0.001,1,2\n0.001,1,2\n"), "line 4: time does not increase")
    assert_error(write(tmp_path, header + "0,1,2\n0.001,1,2\n0.0005,1,2\n0.002,1,2\n"),
                 "line 4: time does not increase", "t=0.0005 s after t=0.001 s")
    rows = "".join(f"{k * 0.001!r},1,2\n" for k in range(10)) + "0.0105,1,2\n0.0115,1,2\n"
    assert_error(write(tmp_path, header + rows), "line 12: non-uniform sampling", "0.0015 s", "expected 0.001 s")


def test_small_jitter_is_accepted(tmp_path: Path) -> None:
    t = np.arange(200) * 1e-3 + np.random.default_rng(0).uniform(-2e-7, 2e-7, 200)
    text = "t,torque_ref,motor_velocity\n" + "".join(f"{x!r},1,2\n" for x in t.tolist())
    assert len(read_csv(write(tmp_path, text))) == 200


def test_directives(tmp_path: Path) -> None:
    body = "t,torque_ref,motor_velocity\n0,1,2\n0.001,1,2\n0.002,1,2\n"
    rec = read_csv(write(tmp_path, "# sample_rate_hz: 1000\n# start_time: 2025-01-02T03:04:05.5+01:00\n" + body))
    assert rec.sample_rate_hz == 1000.0
    assert rec.start_time == datetime(2025, 1, 2, 2, 4, 5, 500000, tzinfo=timezone.utc)
    assert_error(write(tmp_path, "# sample_rate_hz: 8000\n" + body), "line 1: sample_rate_hz 8000 disagrees")
    assert_error(write(tmp_path, "# sample_rate_hz: fast\n" + body), "line 1: sample_rate_hz 'fast' is not a number")
    assert_error(write(tmp_path, "#\n# start_time: yesterday\n" + body), "line 2: start_time 'yesterday'")
    assert_error(write(tmp_path, "# start_time: 2025-01-02T03:04:05\n" + body), "has no time zone")


def test_write_refuses_what_it_could_not_read_back(tmp_path: Path) -> None:
    rec = make_recording(100)
    jittered = rec.replace(t=rec.t + np.r_[0.0, 5e-5, np.zeros(98)])
    with pytest.raises(RecordingError, match="uniform sampling"):
        write_csv(tmp_path / "j.csv", jittered)
    with pytest.raises(RecordingError, match="disagrees"):
        write_csv(tmp_path / "r.csv", rec.replace(sample_rate_hz=4000.0))


def _table(t: np.ndarray) -> str:
    return "t,torque_ref,motor_velocity\n" + "".join(f"{x!r},{k % 7},{k % 5}\n" for k, x in enumerate(t.tolist()))


def test_a_time_column_in_milliseconds_is_one_error_that_says_so(tmp_path: Path) -> None:
    t = np.arange(2000) * 0.125  # 8 kHz in ms
    assert_error(write(tmp_path, _table(t)), "the t column gives 8 Hz", "t must be in seconds",
                 "in milliseconds, the log is at 8000 Hz")


@pytest.mark.parametrize("name, t", [
    # a Unix time in float64 resolves 0.24 µs: its 125 µs intervals jitter by 0.2 %
    ("unix time", 1.764e9 + np.arange(24000) / 8000.0),
    # a spreadsheet's four decimals: 125 µs intervals read as 100 or 200 µs
    ("four decimals", np.round(np.arange(24000) / 8000.0, 4)),
])
def test_a_rounded_time_column_is_read_on_its_uniform_grid(tmp_path: Path, name: str, t: np.ndarray) -> None:
    assert np.max(np.abs(np.diff(t) * 8000.0 - 1.0)) > 1e-3  # (what the interval check alone refused)
    rec = read_csv(write(tmp_path, _table(t)))
    assert len(rec) == t.size and rec.is_uniform
    assert rec.sample_rate_hz == pytest.approx(8000.0, rel=1e-7)
    exact = t[0] + np.arange(t.size) / 8000.0
    # (within the float64's own resolution at a Unix time, 0.24 µs)
    assert np.max(np.abs((rec.t - rec.t[0]) - (exact - exact[0]))) < 0.3e-6
    assert rec.torque_ref.tolist() == [float(k % 7) for k in range(t.size)]
    if name == "unix time":  # the run's start, to the column's resolution
        assert abs(rec.start_time.timestamp() - 1.764e9) < 1e-6


def test_a_rounded_time_column_with_a_sample_missing_is_refused(tmp_path: Path) -> None:
    t = np.round(np.delete(np.arange(24000), 12000) / 8000.0, 4)
    assert_error(write(tmp_path, _table(t)), "non-uniform sampling", "t rounded to 0.0001 s", "off the uniform grid")
