"""MCAP log: exact round trips, recovery of cut and unfinished files, clear errors."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import textwrap
import warnings
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Header, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from commission import mcaplog
from commission.exceptions import LogFormatError, RecordingError
from commission.mcaplog import (
    JsonDecoderFactory,
    RecordingWriter,
    TruncatedLogWarning,
    read_config,
    read_recording,
    read_results,
    write_recording,
)
from commission.recording import SIGNAL_UNITS, DriveInfo, Recording

START = datetime(2025, 3, 14, 15, 9, 26, 535897, tzinfo=timezone.utc)
DRIVE = DriveInfo(backend="sim", vendor="ACME", product="X1", serial_number="42", firmware="1.2", rated_torque_nm=1.27)
CONFIG = {"excitation": {"kind": "chirp", "f1_hz": 1.0, "f2_hz": 2000.0}, "limits": {"torque_nm": 0.5}, "note": "ü"}
MAGIC = b"\x89MCAP0\r\n"


def make_recording(n: int, *, optional: bool = True, uniform: bool = True, seed: int = 0) -> Recording:
    """Full-mantissa random samples (every bit matters), plus a few extreme values."""
    rng = np.random.default_rng(seed)
    fs = 8000.0
    if uniform:
        t = np.arange(n) / fs
    else:  # host-streamed: jittered, irregular times
        t = np.cumsum(rng.uniform(0.5, 1.5, n)) / fs + 0.1234567890123
    signals = {name: rng.standard_normal(n) * 10.0 ** rng.integers(-6, 6) for name in SIGNAL_UNITS}
    signals["torque_ref"][:4] = [5e-324, -1.7976931348623157e308, 2.2250738585072014e-308, 0.1 + 0.2]
    if not optional:
        signals = {k: signals[k] for k in ("torque_ref", "motor_velocity")}
    return Recording(t=t, sample_rate_hz=fs, start_time=START, drive=DRIVE,
                     metadata={"operator": "Zoë", "axis": "X", "empty": ""}, **signals)


def assert_bitwise_equal(a: Recording, b: Recording) -> None:
    assert a.equals(b)
    for name in ("t", *SIGNAL_UNITS):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.view(np.uint64).tolist() == y.view(np.uint64).tolist(), name


def read_with_warning(path: Path) -> tuple[Recording, str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = read_recording(path)  # a LogFormatError passes through
    messages = [str(w.message) for w in caught if issubclass(w.category, TruncatedLogWarning)]
    assert len(messages) == 1, [str(w.message) for w in caught]
    return rec, messages[0]


def records(path: Path) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of every top-level record of a complete file."""
    data = path.read_bytes()
    out, pos = [], 8
    while pos < len(data) - 8:
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        out.append((opcode, pos, pos + 9 + length))
        pos += 9 + length
    return out


@pytest.fixture(scope="module")
def big(tmp_path_factory: pytest.TempPathFactory) -> tuple[Recording, Path]:
    rec = make_recording(80_000)
    path = tmp_path_factory.mktemp("mcap") / "big.mcap"
    write_recording(path, rec, config=CONFIG)
    return rec, path


# -- round trips --------------------------------------------------------------------------------
def test_round_trip_80000_samples_all_signals_bitwise(big: tuple[Recording, Path]) -> None:
    rec, path = big
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = read_recording(path)
    assert_bitwise_equal(back, rec)
    assert back.drive == DRIVE and back.start_time == START and dict(back.metadata) == dict(rec.metadata)


def test_round_trip_required_only_non_uniform_times(tmp_path: Path) -> None:
    rec = make_recording(1001, optional=False, uniform=False, seed=3)
    assert not rec.is_uniform
    write_recording(tmp_path / "r.mcap", rec, samples_per_message=64)
    back = read_recording(tmp_path / "r.mcap")
    assert_bitwise_equal(back, rec)
    assert back.motor_position is None and back.load_position is None and back.load_velocity is None


@pytest.mark.parametrize("spm, compression", [(1, "zstd"), (7, "lz4"), (1000, "none")])
def test_round_trip_message_sizes_and_compressions(tmp_path: Path, spm: int, compression: str) -> None:
    rec = make_recording(523, seed=spm)
    write_recording(tmp_path / "r.mcap", rec, samples_per_message=spm, chunk_size=4096, compression=compression)
    assert_bitwise_equal(read_recording(tmp_path / "r.mcap"), rec)


def test_start_time_in_another_zone_and_pathlike(tmp_path: Path) -> None:
    zone = timezone(timedelta(hours=5, minutes=30))
    rec = make_recording(100).replace(start_time=datetime(1999, 12, 31, 23, 59, 59, 999999, tzinfo=zone))
    write_recording(tmp_path / "r.mcap", rec)
    back = read_recording(str(tmp_path / "r.mcap"))
    assert back.start_time == rec.start_time and back.start_time.utcoffset() == timedelta(hours=5, minutes=30)


def test_config_round_trip(big: tuple[Recording, Path]) -> None:
    assert read_config(big[1]) == CONFIG


def test_incremental_writer_with_ragged_blocks_equals_one_shot(tmp_path: Path) -> None:
    rec = make_recording(2000, seed=7)
    edges = [0, 1, 2, 50, 333, 334, 1500, 1999, 2000]
    with RecordingWriter(tmp_path / "r.mcap", sample_rate_hz=rec.sample_rate_hz, start_time=rec.start_time,
                         drive=rec.drive, signals=list(SIGNAL_UNITS)[::-1], metadata=rec.metadata,
                         samples_per_message=80, chunk_size=2048) as w:
        for a, b in zip(edges, edges[1:]):
            w.append(rec.t[a:b], **{name: arr[a:b] for name, arr in rec.signals()})
        w.append([], **{name: [] for name in SIGNAL_UNITS})  # an empty block is fine
        assert w.n_samples == 2000
    assert_bitwise_equal(read_recording(tmp_path / "r.mcap"), rec)


# -- the file as other readers see it -----------------------------------------------------------
def test_standard_mcap_reader_sees_json_channels_with_schemas(big: tuple[Recording, Path]) -> None:
    rec, path = big
    start_ns = int(START.timestamp()) * 10**9 + START.microsecond * 1000
    values: dict[str, list[float]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[JsonDecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        assert {c.topic for c in summary.channels.values()} == {f"/{n}" for n in SIGNAL_UNITS}
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        for schema, channel, message, payload in reader.iter_decoded_messages(log_time_order=False):
            name = channel.topic[1:]
            assert channel.message_encoding == "json" and channel.metadata["unit"] == SIGNAL_UNITS[name]
            spec = json.loads(schema.data)
            assert spec["properties"]["unit"]["const"] == payload["unit"] == SIGNAL_UNITS[name]
            assert set(payload) == set(spec["required"])
            t0 = payload["t_s"][0]
            assert t0 == rec.t[payload["first_sample"]]
            assert message.log_time == message.publish_time == start_ns + round(t0 * 1e9)
            values.setdefault(name, []).extend(payload["values"])
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    for name, arr in rec.signals():
        assert np.array_equal(values[name], arr)
    assert metadata["recording"]["tool_version"] and metadata["recording"]["format_version"] == "1"
    assert metadata["recording_end"] == {"sample_count": "80000", "status": "complete"}


def test_metadata_is_written_before_any_chunk(big: tuple[Recording, Path]) -> None:
    with open(big[1], "rb") as f:
        kinds = []
        for record in StreamReader(f, emit_chunks=True).records:
            kinds.append(record.name if isinstance(record, Metadata) else type(record).__name__)
            if isinstance(record, Chunk):
                break
    assert kinds == ["Header", "recording", "recording_metadata", "config", "Chunk"]


# -- cut and unfinished files -------------------------------------------------------------------
@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_cut_file_gives_the_complete_prefix(big: tuple[Recording, Path], tmp_path: Path, fraction: float) -> None:
    rec, path = big
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    back, message = read_with_warning(cut)
    n = len(back)
    assert 0 < n < len(rec)
    assert abs(n / len(rec) - fraction) < 0.05  # 64 KiB chunks: little is lost
    assert_bitwise_equal(back, rec.head(n))
    assert f"recovered {n:,} samples of 80,000" in message and "trimmed" not in message


def test_cut_in_summary_recovers_everything(tmp_path: Path) -> None:
    rec = make_recording(3000, seed=4)
    write_recording(tmp_path / "r.mcap", rec)
    data = (tmp_path / "r.mcap").read_bytes()
    for cut_at in (len(data) - 3, len(data) - 200):
        (tmp_path / "cut.mcap").write_bytes(data[:cut_at])
        back, message = read_with_warning(tmp_path / "cut.mcap")
        assert_bitwise_equal(back, rec)
        assert "3,000 samples of 3,000" in message


def test_cut_inside_metadata_or_first_chunk_is_an_error(big: tuple[Recording, Path], tmp_path: Path) -> None:
    path = big[1]
    data = path.read_bytes()
    recs = records(path)
    first_chunk = next(r for r in recs if r[0] == 0x06)
    metadata = [r for r in recs if r[0] == 0x0C][:3]
    cuts = [3, 8, 20] + [(a + b) // 2 for _, a, b in metadata] + [first_chunk[1] + 5, first_chunk[2] - 1]
    for cut_at in cuts:
        (tmp_path / "cut.mcap").write_bytes(data[:cut_at])
        with pytest.raises(LogFormatError, match="no complete samples before the cut"):
            read_recording(tmp_path / "cut.mcap")


def cut_points(path: Path) -> list[int]:
    """Start, second byte, middle and last byte of every record: every kind of cut."""
    points = {1, 5, 8}
    for _, a, b in records(path):
        points |= {a + 1, (a + b) // 2, b - 1}
    return sorted(points)


def test_every_kind_of_cut_of_a_small_file(tmp_path: Path) -> None:
    rec = make_recording(400, seed=11)
    path = tmp_path / "small.mcap"
    write_recording(path, rec, samples_per_message=40, chunk_size=6000)
    data = path.read_bytes()
    last_n = 0
    for cut_at in cut_points(path):
        (tmp_path / "cut.mcap").write_bytes(data[:cut_at])
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", TruncatedLogWarning)
                back = read_recording(tmp_path / "cut.mcap")
        except LogFormatError as err:
            assert last_n == 0 and "no complete samples before the cut" in str(err)
            continue
        n = len(back)
        assert n >= last_n and n % 40 == 0
        assert_bitwise_equal(back, rec.head(n))
        last_n = n
    assert last_n == 400


def test_unfinished_writer_is_readable(tmp_path: Path) -> None:
    rec = make_recording(5000, seed=5)
    path = tmp_path / "live.mcap"
    w = RecordingWriter(path, sample_rate_hz=rec.sample_rate_hz, start_time=rec.start_time, drive=rec.drive,
                        signals=[n for n, _ in rec.signals()], metadata=rec.metadata, chunk_size=8192)
    for a in range(0, 3000, 250):
        w.append(rec.t[a:a + 250], **{name: arr[a:a + 250] for name, arr in rec.signals()})
    snapshot = tmp_path / "snapshot.mcap"
    snapshot.write_bytes(path.read_bytes())  # what a crash now would leave on disk
    back, message = read_with_warning(snapshot)
    assert 0 < len(back) < 3000 and "recovered" in message
    assert_bitwise_equal(back, rec.head(len(back)))
    w.flush()  # everything appended so far reaches the file
    snapshot.write_bytes(path.read_bytes())
    assert_bitwise_equal(read_with_warning(snapshot)[0], rec.head(3000))
    w.close()
    w.close()  # twice is fine
    assert_bitwise_equal(read_recording(path), rec.head(3000))


def test_killed_process_leaves_a_readable_file(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    child = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_mcaplog import make_recording
        from commission.mcaplog import RecordingWriter
        rec = make_recording(4000, seed=9)
        w = RecordingWriter({str(path)!r}, sample_rate_hz=rec.sample_rate_hz, start_time=rec.start_time,
                            drive=rec.drive, signals=[n for n, _ in rec.signals()], metadata=rec.metadata,
                            chunk_size=16384, expected_samples=4000)
        for a in range(0, 3000, 100):
            w.append(rec.t[a:a + 100], **{{n: x[a:a + 100] for n, x in rec.signals()}})
        os._exit(1)  # no close(), no Python buffers flushed
    """)
    result = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1, result.stderr
    back, message = read_with_warning(path)
    assert 1000 < len(back) < 3000 and "of 4,000" in message
    assert_bitwise_equal(back, make_recording(4000, seed=9).head(len(back)))


def test_zero_filled_tail_counts_as_a_cut(tmp_path: Path) -> None:
    rec = make_recording(6000, seed=8)
    write_recording(tmp_path / "r.mcap", rec, chunk_size=8192)
    data = (tmp_path / "r.mcap").read_bytes()
    chunk_ends = [b for op, _, b in records(tmp_path / "r.mcap") if op == 0x06]
    # power loss: the file has its final size but the end was never written (zeros)
    for cut_at in (len(data) // 3, len(data) // 2, chunk_ends[3]):
        (tmp_path / "z.mcap").write_bytes(data[:cut_at] + bytes(4096))
        back, _ = read_with_warning(tmp_path / "z.mcap")
        assert 0 < len(back) < len(rec) and back.equals(rec.head(len(back)))


def test_chunks_inside_blocks_are_trimmed_to_common_length(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Without Writer.flush (mcap < 1.6) the Writer closes chunks itself, also between channels.
    monkeypatch.delattr(Writer, "flush")
    rec = make_recording(400, seed=2)
    path = tmp_path / "old.mcap"
    write_recording(path, rec, samples_per_message=50, chunk_size=4000)
    assert_bitwise_equal(read_recording(path), rec)
    data = path.read_bytes()
    trimmed = 0
    recovered = 0
    for cut_at in cut_points(path)[::2]:
        (tmp_path / "cut.mcap").write_bytes(data[:cut_at])
        try:
            back, message = read_with_warning(tmp_path / "cut.mcap")
        except LogFormatError as err:  # before every signal has a complete message
            assert recovered == 0 and "no complete samples before the cut" in str(err)
            continue
        assert_bitwise_equal(back, rec.head(len(back)))
        recovered = len(back)
        trimmed += "signals trimmed to the common length" in message
    assert trimmed > 0 and recovered == 400


def test_aborted_run_is_readable_and_says_so(tmp_path: Path) -> None:
    rec = make_recording(500)
    with pytest.raises(KeyboardInterrupt):
        with RecordingWriter(tmp_path / "a.mcap", sample_rate_hz=rec.sample_rate_hz, start_time=rec.start_time,
                             drive=rec.drive, signals=["torque_ref", "motor_velocity"], metadata=rec.metadata) as w:
            w.append(rec.t[:300], torque_ref=rec.torque_ref[:300], motor_velocity=rec.motor_velocity[:300])
            raise KeyboardInterrupt
    with pytest.warns(TruncatedLogWarning, match="aborted: KeyboardInterrupt"):
        back = read_recording(tmp_path / "a.mcap")
    assert len(back) == 300 and np.array_equal(back.torque_ref, rec.torque_ref[:300])


def test_fewer_samples_than_planned_is_said(tmp_path: Path) -> None:
    rec = make_recording(500)
    with RecordingWriter(tmp_path / "p.mcap", sample_rate_hz=rec.sample_rate_hz, start_time=rec.start_time,
                         drive=rec.drive, signals=["torque_ref", "motor_velocity"], expected_samples=500) as w:
        w.append(rec.t[:300], torque_ref=rec.torque_ref[:300], motor_velocity=rec.motor_velocity[:300])
    with pytest.warns(TruncatedLogWarning, match="300 samples of the 500 planned"):
        assert len(read_recording(tmp_path / "p.mcap")) == 300


# -- errors -------------------------------------------------------------------------------------
def assert_one_line_error(path: Path, reason: str) -> None:
    with pytest.raises(LogFormatError) as info:
        read_recording(path)
    text = str(info.value)
    assert reason in text and str(path) in text
    assert "\n" not in text and "Traceback" not in text


def test_missing_empty_garbage_files(tmp_path: Path) -> None:
    assert_one_line_error(tmp_path / "nope.mcap", "no such file")
    (tmp_path / "empty.mcap").write_bytes(b"")
    assert_one_line_error(tmp_path / "empty.mcap", "empty file")
    (tmp_path / "text.mcap").write_text("t,torque_ref\n0,1\n")
    assert_one_line_error(tmp_path / "text.mcap", "not an MCAP file (bad magic")
    (tmp_path / "noise.mcap").write_bytes(np.random.default_rng(0).bytes(5000))
    assert_one_line_error(tmp_path / "noise.mcap", "not an MCAP file")
    (tmp_path / "dir.mcap").mkdir()
    assert_one_line_error(tmp_path / "dir.mcap", "is a directory")
    (tmp_path / "magic.mcap").write_bytes(MAGIC + np.random.default_rng(1).bytes(3000))
    assert_one_line_error(tmp_path / "magic.mcap", "corrupt MCAP file")


def test_corrupt_chunk_is_an_error_not_a_cut(big: tuple[Recording, Path], tmp_path: Path) -> None:
    path = big[1]
    data = bytearray(path.read_bytes())
    chunks = [r for r in records(path) if r[0] == 0x06]
    _, a, b = chunks[len(chunks) // 2]
    data[(a + b) // 2] ^= 0xFF
    (tmp_path / "bad.mcap").write_bytes(bytes(data))
    assert_one_line_error(tmp_path / "bad.mcap", "corrupt MCAP file")


def test_foreign_mcap_is_not_a_recording(tmp_path: Path) -> None:
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        channel = w.register_channel("/chatter", "json", 0)
        w.add_message(channel, log_time=1, data=b'{"a": 1}', publish_time=1)
        w.finish()
    assert_one_line_error(path, "not a drive-commission recording")


def test_newer_format_version_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mcaplog, "FORMAT_VERSION", 99)
    write_recording(tmp_path / "new.mcap", make_recording(100))
    monkeypatch.undo()
    assert_one_line_error(tmp_path / "new.mcap", "log format 99")


def test_single_sample_log_is_an_error(tmp_path: Path) -> None:
    with RecordingWriter(tmp_path / "one.mcap", sample_rate_hz=8000.0, start_time=START, drive=DRIVE,
                         signals=["torque_ref", "motor_velocity"]) as w:
        w.append([0.0], torque_ref=[1.0], motor_velocity=[2.0])
    assert_one_line_error(tmp_path / "one.mcap", "only 1 sample")


def test_writer_refuses_bad_input(tmp_path: Path) -> None:
    kw = dict(sample_rate_hz=8000.0, start_time=START, drive=DRIVE)
    with pytest.raises(RecordingError, match="required signal"):
        RecordingWriter(tmp_path / "w.mcap", signals=["torque_ref"], **kw)
    with pytest.raises(RecordingError, match="unknown signal"):
        RecordingWriter(tmp_path / "w.mcap", signals=["torque_ref", "motor_velocity", "speed"], **kw)
    with pytest.raises(RecordingError, match="timezone"):
        RecordingWriter(tmp_path / "w.mcap", signals=["torque_ref", "motor_velocity"],
                        sample_rate_hz=8000.0, start_time=datetime(2025, 1, 1), drive=DRIVE)
    w = RecordingWriter(tmp_path / "w.mcap", signals=["torque_ref", "motor_velocity"], **kw)
    with pytest.raises(RecordingError, match="missing motor_velocity"):
        w.append([0.0, 1.0], torque_ref=[0.0, 0.0])
    with pytest.raises(RecordingError, match="has 1 samples"):
        w.append([0.0, 1.0], torque_ref=[0.0, 0.0], motor_velocity=[1.0])
    with pytest.raises(RecordingError, match="non-finite"):
        w.append([0.0, 1.0], torque_ref=[0.0, np.nan], motor_velocity=[1.0, 1.0])
    w.append([0.0, 1.0], torque_ref=[0.0, 0.0], motor_velocity=[1.0, 1.0])
    with pytest.raises(RecordingError, match=r"increase strictly .*last t=1.0 s, block starts at t=1.0 s"):
        w.append([1.0, 2.0], torque_ref=[0.0, 0.0], motor_velocity=[1.0, 1.0])
    with pytest.raises(ValueError, match="reserved"):
        w.add_result("/torque_ref", {"a": 1})
    with pytest.raises(ValueError, match="not JSON-serialisable"):
        w.add_result("/identification", {"a": float("nan")})
    w.close()
    with pytest.raises(ValueError, match="closed"):
        w.append([3.0], torque_ref=[0.0], motor_velocity=[1.0])
    assert len(read_recording(tmp_path / "w.mcap")) == 2


# -- results ------------------------------------------------------------------------------------
def test_results_round_trip(tmp_path: Path) -> None:
    rec = make_recording(400)
    ident = {"J_m": 1.5e-4, "J_l": 3.2e-4, "epsilon_rad": 0.0021, "modes_hz": [88.5, 412.0], "ok": True}
    path = tmp_path / "res.mcap"
    with RecordingWriter(path, sample_rate_hz=rec.sample_rate_hz, start_time=rec.start_time, drive=rec.drive,
                         signals=[n for n, _ in rec.signals()], metadata=rec.metadata) as w:
        w.append(rec.t, **dict(rec.signals()))
        w.add_result("/identification", ident, schema={"type": "object", "title": "Identification"})
        w.add_result("/identification", {"iteration": 2})
        w.add_result("/tuning", {"kp": 0.3})
    assert read_results(path) == {"/identification": [ident, {"iteration": 2}], "/tuning": [{"kp": 0.3}]}
    assert_bitwise_equal(read_recording(path), rec)
    with open(path, "rb") as f:
        schemas = {s.name: json.loads(s.data) for s in make_reader(f).get_summary().schemas.values()}
    assert schemas["commission.identification"]["title"] == "Identification"
    # a result is written out at once: a cut right after it keeps it
    data = path.read_bytes()
    end_meta = next(r for r in records(path) if r[0] == 0x0C and b"recording_end" in data[r[1]:r[2]])
    (tmp_path / "cut.mcap").write_bytes(data[: end_meta[1]])
    with pytest.warns(TruncatedLogWarning):
        assert read_results(tmp_path / "cut.mcap")["/tuning"] == [{"kp": 0.3}]


def test_header_names_the_tool(big: tuple[Recording, Path]) -> None:
    with open(big[1], "rb") as f:
        header = next(iter(StreamReader(f).records))
    assert isinstance(header, Header) and header.library.startswith("drive-commission/")
