"""Hostile input (issue 21): every malformed log or config is one line on stderr and a documented exit code
(3 input file, 2 config), never a traceback, an internal error or a hang.

The corpus is generated once per session in a temporary folder (nothing checked in): a good MCAP log and CSV
file of a simulated run, then MCAP files forged record by record with one flaw each (samples as strings or
nested lists, deeply nested JSON, a drive given as a list, a chunk that inflates beyond its declared size,
…), cut and bit-flipped copies, CSV files with one flaw each, configs with non-finite, absurd or malformed
values, and files that are not files (a FIFO, /dev/zero, /dev/urandom). Cases run in-process through
``commission.cli.main`` under an alarm (a hang fails the case instead of the session); a few run as
subprocesses with a timeout. A property test then mutates the good log at random."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import zstandard
from mcap.records import Chunk
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer

from commission.cli import main
from commission.config import Config, config_to_dict
from commission.csvlog import write_csv
from commission.excitation import chirp
from commission.mcaplog import FORMAT_VERSION, read_recording, write_recording
from commission.plant import Plant, PlantParameters
from commission.recording import DriveInfo, Recording

#: Exit codes the README documents for a replay (0 ok, 2 config, 3 input file, 6 identification, 7 output).
REPLAY_CODES = {0, 2, 3, 6, 7}
#: Seconds one case may take before it counts as a hang.
HANG_S = 30


class Hung(BaseException):
    """Raised by the alarm: not an Exception, so that the command's own handlers do not catch it."""


@dataclass(frozen=True)
class Case:
    """One hostile input: the command line that reads it and the exit codes it may end with."""

    name: str
    argv: tuple[str, ...]
    codes: frozenset[int]
    setup: Callable[[], Any] | None = field(default=None, compare=False)


def run_main(argv: list[str]) -> tuple[int, str]:
    """``commission ARGV`` in this process under an alarm; (exit code, stderr)."""
    def alarm(signum, frame):
        raise Hung(f"no answer within {HANG_S} s: {argv}")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(HANG_S)
    stdout, stderr = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = main(argv)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    return code, stderr.getvalue()


def check_outcome(case: str, code: int, stderr: str, codes: set[int] | frozenset[int]) -> None:
    lines = stderr.strip().splitlines()
    assert "Traceback" not in stderr and "internal error" not in stderr, f"{case}: {stderr}"
    assert code in codes, f"{case}: exit {code}: {stderr}"
    if code:
        assert lines and lines[-1].startswith("commission: error: "), f"{case}: {stderr}"
        lines = lines[:-1]
    # anything else a replay says is a one-line warning
    assert all(line.startswith("warning: ") for line in lines), f"{case}: {stderr}"


# -- the good log, and a forger of the tool's MCAP layout -----------------------------------------------------
N_GOOD = 2000  # 0.25 s of the default chirp at 8 kHz


def good_recording() -> tuple[Recording, dict[str, Any]]:
    config = Config()
    torque = chirp(config.excitation).samples[:N_GOOD]
    r = Plant(PlantParameters()).run_torque(torque)
    rec = Recording.uniform(8000.0, torque, r.motor_velocity, motor_position=r.motor_position,
                            load_position=r.load_position, load_velocity=r.load_velocity,
                            start_time=datetime(2025, 1, 2, 3, 4, 5, tzinfo=timezone.utc),
                            drive=DriveInfo(backend="sim", vendor="fuzz", rated_torque_nm=0.637),
                            metadata={"status": "complete"})
    return rec, config_to_dict(config)


def block_payloads(rec: Recording) -> dict[str, list[Any]]:
    """topic -> the JSON messages the writer makes of ``rec`` (80 samples each)."""
    from commission.recording import SIGNAL_UNITS

    out: dict[str, list[Any]] = {}
    for name, values in rec.signals():
        out[f"/{name}"] = [{"first_sample": i, "t_s": rec.t[i:i + 80].tolist(), "values": values[i:i + 80].tolist(),
                            "unit": SIGNAL_UNITS[name]} for i in range(0, len(rec), 80)]
    return out


def forge(path: Path, rec: Recording, config: dict[str, Any], *, info: dict[str, Any] | None = None,
          drop_info: tuple[str, ...] = (), end: dict[str, str] | None = None,
          mutate: Callable[[dict[str, list[Any]]], None] | None = None,
          config_text: dict[str, str] | None = None, compression: CompressionType = CompressionType.ZSTD,
          no_recording: bool = False) -> Path:
    """An MCAP file in the tool's layout, written with the mcap library; every part replaceable.
    Payloads that are bytes are written as they are; anything else as JSON."""
    meta = {
        "format": "drive-commission.recording", "format_version": str(FORMAT_VERSION), "tool_version": "fuzz",
        "sample_rate_hz": repr(rec.sample_rate_hz), "start_time": rec.start_time.isoformat(),
        "drive": json.dumps(rec.drive.to_dict()), "signals": json.dumps([n for n, _ in rec.signals()]),
        "samples_per_message": "80", "expected_samples": str(len(rec)),
    }
    meta.update(info or {})
    for key in drop_info:
        meta.pop(key, None)
    blocks = block_payloads(rec)
    if mutate is not None:
        mutate(blocks)
    with open(path, "wb") as f:
        w = Writer(f, compression=compression)
        w.start(profile="", library="fuzz")
        if not no_recording:
            w.add_metadata("recording", meta)
        w.add_metadata("recording_metadata", dict(rec.metadata))
        w.add_metadata("config", config_text if config_text is not None
                       else {k: json.dumps(v) for k, v in config.items()})
        for topic, payloads in blocks.items():
            schema = w.register_schema(f"commission.{topic[1:]}", SchemaEncoding.JSONSchema, b"{}")
            channel = w.register_channel(topic, MessageEncoding.JSON, schema)
            for seq, payload in enumerate(payloads):
                data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
                w.add_message(channel, log_time=seq, publish_time=seq, data=data, sequence=seq)
        w.add_metadata("recording_end", end if end is not None else {"sample_count": str(len(rec)),
                                                                       "status": "complete"})
        w.finish()
    return path


def bomb(path: Path, good: Path) -> Path:
    """The good log with its first chunk replaced by a zstd frame that declares and holds 200 MB of
    zeros, while the chunk record claims a few bytes."""
    from mcap.data_stream import RecordBuilder
    from mcap.stream_reader import StreamReader

    data = good.read_bytes()
    frame = zstandard.ZstdCompressor().compress(bytes(200_000_000))
    out = io.BytesIO()
    out.write(data[:8])
    for record in StreamReader(io.BytesIO(data[8:]), skip_magic=True, emit_chunks=True).records:
        if isinstance(record, Chunk):
            bad = Chunk(message_start_time=record.message_start_time, message_end_time=record.message_end_time,
                        uncompressed_size=1000, uncompressed_crc=0, compression="zstd", data=frame)
            builder = RecordBuilder()
            bad.write(builder)
            out.write(builder.end())
            break
    path.write_bytes(out.getvalue())
    return path


# -- the corpus --------------------------------------------------------------------------------------------------
def _set(topic: str, index: int, key: str, value: Any) -> Callable[[dict[str, list[Any]]], None]:
    def mutate(blocks: dict[str, list[Any]]) -> None:
        blocks[topic][index][key] = value
    return mutate


def _replace(topic: str, index: int, payload: Any) -> Callable[[dict[str, list[Any]]], None]:
    def mutate(blocks: dict[str, list[Any]]) -> None:
        blocks[topic][index] = payload
    return mutate


def _values(topic: str, index: int, fn: Callable[[list[float]], list[Any]]) -> Callable[[dict[str, list[Any]]], None]:
    def mutate(blocks: dict[str, list[Any]]) -> None:
        blocks[topic][index]["values"] = fn(blocks[topic][index]["values"])
    return mutate


def _literal(topic: str, index: int, literal: str) -> Callable[[dict[str, list[Any]]], None]:
    """The block's first value written as ``literal`` (JSON text the writer would never make)."""
    def mutate(blocks: dict[str, list[Any]]) -> None:
        b = blocks[topic][index]
        blocks[topic][index] = json.dumps(b).replace(f'"values": [{json.dumps(b["values"][0])}',
                                                     f'"values": [{literal}', 1).encode()
    return mutate


def _duplicate_block(blocks: dict[str, list[Any]]) -> None:
    for topic in blocks:
        blocks[topic].insert(3, blocks[topic][2])


def _drop_block(blocks: dict[str, list[Any]]) -> None:
    del blocks["/motor_velocity"][5]


DEEP = ("[" * 100_000 + "]" * 100_000).encode()

MCAP_FLAWS: dict[str, dict[str, Any]] = {
    # sample blocks
    "values as strings": {"mutate": _values("/torque_ref", 1, lambda v: [str(x) for x in v])},
    "values as nested lists": {"mutate": _values("/motor_velocity", 0, lambda v: [[x, x] for x in v])},
    "values with null": {"mutate": _values("/motor_velocity", 3, lambda v: [None, *v[1:]])},
    "values as booleans": {"mutate": _values("/torque_ref", 4, lambda v: [True] * len(v))},
    "values as objects": {"mutate": _values("/torque_ref", 4, lambda v: [{"v": x} for x in v])},
    "values as one string": {"mutate": _set("/torque_ref", 0, "values", "0.1,0.2")},
    "values missing": {"mutate": _set("/torque_ref", 0, "values", None)},
    "t_s as strings": {"mutate": _set("/load_position", 2, "t_s", ["0"] * 80)},
    "t_s shorter than values": {"mutate": _set("/torque_ref", 1, "t_s", [0.0])},
    "t_s going back": {"mutate": lambda b: [blk.__setitem__("t_s", blk["t_s"][::-1]) for t in b for blk in b[t][2:3]]},
    "t_s differing between channels": {"mutate": _set("/load_velocity", 1, "t_s", [x + 1e-3 for x in range(80)])},
    "first_sample as string": {"mutate": _set("/torque_ref", 1, "first_sample", "80")},
    "first_sample negative": {"mutate": _set("/torque_ref", 0, "first_sample", -80)},
    "first_sample as float": {"mutate": _set("/torque_ref", 1, "first_sample", 80.0)},
    "first_sample as bool": {"mutate": _set("/torque_ref", 0, "first_sample", False)},
    "first_sample jumps": {"mutate": _set("/torque_ref", 5, "first_sample", 10_000)},
    "a block written twice": {"mutate": _duplicate_block},
    "a block missing on one channel": {"mutate": _drop_block},
    "block as a list": {"mutate": _replace("/torque_ref", 0, [1, 2, 3])},
    "block as a string": {"mutate": _replace("/torque_ref", 0, "x")},
    "block as null": {"mutate": _replace("/motor_velocity", 0, None)},
    "block not JSON": {"mutate": _replace("/motor_velocity", 0, b"{not json")},
    "block invalid UTF-8": {"mutate": _replace("/motor_velocity", 0, b'{"values": "\xff\xfe"}')},
    "block nested 100000 deep": {"mutate": _replace("/torque_ref", 1, DEEP)},
    "block with an integer of 401 digits": {"mutate": _literal("/torque_ref", 2, "1" + "0" * 400)},
    "block with an integer of 5000 digits": {"mutate": _literal("/torque_ref", 2, "1" + "0" * 5000)},
    "block with NaN": {"mutate": _literal("/torque_ref", 1, "NaN")},
    "block with 1e400": {"mutate": _literal("/motor_velocity", 1, "1e400")},
    "block with -Infinity": {"mutate": _literal("/motor_velocity", 1, "-Infinity")},
    # the recording metadata
    "drive as a list": {"info": {"drive": json.dumps(["sim", "x"])}},
    "drive as a string": {"info": {"drive": json.dumps("sim")}},
    "drive as a number": {"info": {"drive": "42"}},
    "drive with nested values": {"info": {"drive": json.dumps({"backend": {"a": [1, {"b": 2}]}, "vendor": [1]})}},
    "drive rated torque as text": {"info": {"drive": json.dumps({"backend": "sim", "rated_torque_nm": "0.6"})}},
    "drive rated torque negative": {"info": {"drive": json.dumps({"backend": "sim", "rated_torque_nm": -1})}},
    "drive not JSON": {"info": {"drive": "{"}},
    "drive nested 100000 deep": {"info": {"drive": DEEP.decode()}},
    "signals as a string": {"info": {"signals": json.dumps("torque_ref")}},
    "signals as numbers": {"info": {"signals": json.dumps([1, 2])}},
    "signals without torque_ref": {"info": {"signals": json.dumps(["motor_velocity"])}},
    "signals unknown": {"info": {"signals": json.dumps(["torque_ref", "motor_velocity", "rotor_flux"])}},
    "signals nested": {"info": {"signals": json.dumps([["torque_ref"], "motor_velocity"])}},
    "sample rate NaN": {"info": {"sample_rate_hz": "nan"}},
    "sample rate infinite": {"info": {"sample_rate_hz": "inf"}},
    "sample rate negative": {"info": {"sample_rate_hz": "-8000"}},
    "sample rate text": {"info": {"sample_rate_hz": "fast"}},
    "start time garbage": {"info": {"start_time": "yesterday"}},
    "start time without zone": {"info": {"start_time": "2025-01-01T00:00:00"}},
    "format version from the future": {"info": {"format_version": "999"}},
    "format version text": {"info": {"format_version": "one"}},
    "another format": {"info": {"format": "ros2"}},
    "expected samples text": {"info": {"expected_samples": "many"}},
    "no recording metadata": {"no_recording": True},
    "no signals key": {"drop_info": ("signals",)},
    "sample count text": {"end": {"sample_count": "lots", "status": "complete"}},
    "sample count wrong": {"end": {"sample_count": "1234", "status": "complete"}},
    # the stored config (replay falls back to the current config when it cannot be read)
    "config not JSON": {"config_text": {"safety": "{"}, "codes": {0, 3}},
    "config nested 100000 deep": {"config_text": {"sim": DEEP.decode()}, "codes": {0, 3}},
    "config sim as a list": {"config_text": {"sim": "[1, 2]"}, "codes": {0, 3}},
    "config sim with absurd values": {"config_text": {"sim": json.dumps({"J_m": 1e-30, "K": 1e12})}, "codes": {0, 3}},
    # compression
    "lz4 chunks": {"compression": CompressionType.LZ4, "codes": {0}},
    "no compression": {"compression": CompressionType.NONE, "codes": {0}},
}


def build_corpus(root: Path) -> tuple[list[Case], Path, Path]:
    rec, config = good_recording()
    good = root / "good.mcap"
    write_recording(good, rec, config=config, plot_every=8)
    good_csv = root / "good.csv"
    write_csv(good_csv, rec)
    cases: list[Case] = []
    replay = ("--no-identify",)

    def mcap_case(name: str, path: Path, codes: set[int] = frozenset({3})) -> None:
        cases.append(Case(f"mcap: {name}", ("--replay", str(path), *replay, "--out", str(root / "out")),
                          frozenset(codes)))

    folder = root / "mcap"
    folder.mkdir()
    for i, (name, flaw) in enumerate(MCAP_FLAWS.items()):
        flaw = dict(flaw)
        codes = flaw.pop("codes", {3})
        mcap_case(name, forge(folder / f"flaw{i:03d}.mcap", rec, config, **flaw), codes)
    data = good.read_bytes()
    rng = np.random.default_rng(21)
    for k, fraction in enumerate(np.linspace(0.0, 0.999, 12)):
        path = folder / f"cut{k:02d}.mcap"
        path.write_bytes(data[: int(fraction * len(data))])
        mcap_case(f"cut at {fraction:.0%}", path, {0, 3})
    for k in range(20):
        flipped = bytearray(data)
        for pos in rng.integers(0, len(data), size=1 + k % 4):
            flipped[pos] ^= 1 << int(rng.integers(0, 8))
        path = folder / f"flip{k:02d}.mcap"
        path.write_bytes(bytes(flipped))
        mcap_case(f"bit flips {k}", path, {0, 3})
    (folder / "zeros.mcap").write_bytes(data[: len(data) // 2] + bytes(len(data) // 2))
    mcap_case("tail of zeros", folder / "zeros.mcap", {0, 3})
    mcap_case("a chunk that inflates to 200 MB", bomb(folder / "bomb.mcap", good))
    (folder / "empty.mcap").write_bytes(b"")
    mcap_case("empty", folder / "empty.mcap")
    (folder / "magic.mcap").write_bytes(b"\x89MCAP0\r\n")
    mcap_case("magic only", folder / "magic.mcap")
    (folder / "random.mcap").write_bytes(b"\x89MCAP0\r\n" + rng.bytes(50_000))
    mcap_case("random after the magic", folder / "random.mcap")
    (folder / "text.mcap").write_text("not an mcap file\n")
    mcap_case("text", folder / "text.mcap")
    (folder / "dir.mcap").mkdir()
    mcap_case("a folder", folder / "dir.mcap")
    os.mkfifo(folder / "fifo.mcap")
    mcap_case("a FIFO", folder / "fifo.mcap")
    (folder / "zero.mcap").symlink_to("/dev/zero")
    mcap_case("/dev/zero", folder / "zero.mcap")
    with open(folder / "sparse.mcap", "wb") as f:  # 600 MB, of which nothing is on disk
        f.truncate(600 << 20)
    mcap_case("600 MB", folder / "sparse.mcap")
    mcap_case("/dev/urandom", Path("/dev/urandom"))
    mcap_case("missing", folder / "missing.mcap")

    # CSV
    csv_dir = root / "csv"
    csv_dir.mkdir()
    lines = good_csv.read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    head = "".join(line + "\n" for line in lines[:at])  # the comment and the directives
    header, rows = lines[at], lines[at + 1:]

    def csv_case(name: str, text: str | bytes, codes: set[int] = frozenset({3})) -> None:
        path = csv_dir / f"c{len(cases):03d}.csv"
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        cases.append(Case(f"csv: {name}", ("--replay", str(path), *replay, "--out", str(root / "out")),
                          frozenset(codes)))

    def table(rows_: list[str], hdr: str = header, pre: str = head) -> str:
        return pre + "\n".join([hdr, *rows_]) + "\n"

    row0 = rows[0].split(",")
    csv_case("invalid UTF-8 in line 600", table(rows).encode().replace(rows[600].encode(), b"\xff\xfe" + rows[600].encode()))
    csv_case("NUL bytes", table(rows[:10]).replace("\n", "\0\n", 3))
    csv_case("a line of 100 000 characters", table([rows[0] + "," + "9" * 100_000, *rows[1:]]))
    csv_case("one row", table(rows[:1]))
    csv_case("header only", table([]))
    csv_case("empty", "")
    csv_case("only comments", "# a\n# b\n")
    csv_case("a word as a sample", table([rows[0], ",".join(["x", *row0[1:]]), *rows[2:]]))
    csv_case("NaN as a sample", table([rows[0], ",".join([row0[0], "nan", *row0[2:]]), *rows[2:]]))
    csv_case("1e400 as a sample", table([*rows[:5], ",".join([rows[5].split(",")[0], "1e400", *row0[2:]]), *rows[6:]]))
    csv_case("an empty cell", table([*rows[:3], ",".join(["", *row0[1:]]), *rows[4:]]))
    csv_case("a row too short", table([*rows[:3], ",".join(row0[:2]), *rows[4:]]))
    csv_case("a row too long", table([*rows[:3], rows[3] + ",1", *rows[4:]]))
    csv_case("duplicate columns", table(rows, header + ",t"))
    csv_case("an unknown column", table([r + ",0" for r in rows], header + ",rotor_flux"))
    csv_case("no motor_velocity", table([",".join(r.split(",")[:2]) for r in rows], "t,torque_ref"))
    csv_case("a column in the wrong unit", table(rows, header.replace("t,", "t [ms],", 1)))
    csv_case("10 000 columns", table(rows[:3], ",".join(f"c{i}" for i in range(10_000))))
    csv_case("time going back", table([rows[1], rows[0], *rows[2:]]))
    t50, period = float(rows[50].split(",")[0]), float(rows[1].split(",")[0]) - float(row0[0])
    csv_case("non-uniform sampling", table([*rows[:50], ",".join([repr(t50 + period / 3), *rows[50].split(",")[1:]]),
                                            *rows[51:]]))
    csv_case("a row a logger dropped (read: interpolated, marked lost)", table([*rows[:50], *rows[51:]]), {0})
    csv_case("rate directive text", table(rows, pre=head.replace("sample_rate_hz: 8000.0", "sample_rate_hz: fast")))
    csv_case("rate directive wrong", table(rows, pre=head.replace("sample_rate_hz: 8000.0", "sample_rate_hz: 4000")))
    csv_case("rate directive infinite", table(rows, pre=head.replace("sample_rate_hz: 8000.0", "sample_rate_hz: inf")))
    csv_case("start time garbage", table(rows, pre=head.replace("start_time: 2025", "start_time: x2025")))
    csv_case("start time without zone", table(rows, pre=head.replace("+00:00", "")))
    csv_case("a quoted cell with a newline", table([*rows[:3], '"0.1\n2",' + ",".join(row0[1:]), *rows[4:]]))
    csv_case("binary garbage", rng.bytes(20_000))
    csv_case("with a BOM", "\ufeff" + table(rows), {0})
    csv_case("semicolons", table([r.replace(",", ";") for r in rows], header.replace(",", ";")), {0})
    csv_case("CR line ends", table(rows).replace("\n", "\r"), {0})

    # configs, read before the (good) log
    cfg_dir = root / "config"
    cfg_dir.mkdir()

    def cfg_case(name: str, text: str | bytes, codes: set[int] = frozenset({2})) -> None:
        path = cfg_dir / f"k{len(cases):03d}.yaml"
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        cases.append(Case(f"config: {name}", ("--replay", str(good_csv), "--config", str(path), *replay,
                                              "--out", str(root / "out")), frozenset(codes)))

    for key in ("max_torque_nm", "max_speed_rad_s", "max_travel_rad", "margin", "planning_inertia_kg_m2",
                "planning_damping_nm_s_per_rad"):
        for value in (".inf", "-.inf", ".nan", "'inf'", "1.0e+400", "1" + "0" * 400):
            cfg_case(f"safety.{key}: {value[:12]}", f"safety: {{{key}: {value}}}\n")
    for body_ in ("sim: {J_m: 1.0e-30}", "sim: {K: 1.0e+12}", "sim: {K: 1.0e+8}", "sim: {J_l: .inf}",
                  "sim: {torque_noise_nm: .nan}", "sim: {encoder_bits_motor: 64}", "sim: {seed: -1}",
                  "sim: {coulomb_load_nm: 1.0, coulomb_velocity_scale_rad_s: 1.0e-12}", "sim: {K: [1, 2]}",
                  "sim: {K: {a: 1}}", "sim: [1, 2]",
                  "excitation: {duration_s: 1.0e-9}", "excitation: {sample_rate_hz: 1.0e-9}",
                  "excitation: {sample_rate_hz: 1.0e+9}", "excitation: {f_end_hz: 5000}",
                  "excitation: {amplitude_nm: {nested: {deeper: 1}}}", "excitation: [1, 2]", "excitation: 3",
                  "excitation: {amplitude_nm: [0.1]}", "excitation: {form: sideways}",
                  "identification: {band_hz: [0.1, .inf]}", "identification: {epsilon_bounds_deg: ['nan', 1]}",
                  "tuning: {sample_rate_hz: 'Infinity'}", "tuning: {current_loop_bandwidth_hz: -.inf}",
                  "backlash_check: {duration_s: 1.0e-6}", "sefety: {}", "safety: {max_torque: 1}",
                  "- a\n- b", "just a string", "42", "{a: !!python/object:os.system {}}",
                  "a: " + "[" * 20 + "]" * 20, "a: " + "[" * 5000 + "]" * 5000,
                  "a: &x [1, 2]\nb: &y [*x, *x, *x, *x, *x, *x, *x, *x, *x]\nc: &z [*y, *y, *y, *y, *y, *y, *y, *y]\n"
                  "d: [*z, *z, *z, *z, *z, *z, *z, *z, *z]\n",
                  "safety:\n\tmax_torque_nm: 1\n", "safety: {max_torque_nm: 1"):
        cfg_case(body_.splitlines()[0][:40], body_ + "\n")
    cfg_case("invalid UTF-8", b"excitation: {amplitude_nm: 0.1}\n# \xff\xfe\n")
    cfg_case("binary garbage", rng.bytes(5000))
    cfg_case("2 MB", "# " + "x" * (2 << 20) + "\n")
    cfg_case("empty", "", {0})
    cfg_case("null", "~\n", {0})
    (cfg_dir / "dir.yaml").mkdir()
    cases.append(Case("config: a folder", ("--replay", str(good_csv), "--config", str(cfg_dir / "dir.yaml"),
                                           *replay), frozenset({2})))
    os.mkfifo(cfg_dir / "fifo.yaml")
    cases.append(Case("config: a FIFO", ("--replay", str(good_csv), "--config", str(cfg_dir / "fifo.yaml"),
                                         *replay), frozenset({2})))
    cases.append(Case("config: /dev/zero", ("--replay", str(good_csv), "--config", "/dev/zero", *replay),
                      frozenset({2})))
    return cases, good, good_csv


@pytest.fixture(scope="session")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Case], Path, Path]:
    return build_corpus(tmp_path_factory.mktemp("fuzz"))


def test_the_corpus_gives_one_line_and_a_documented_exit_code_each(corpus, monkeypatch):
    cases, good, good_csv = corpus
    assert len(cases) >= 100
    assert run_main(["--replay", str(good), "--no-identify", "--out", str(good.parent / "ok")])[0] == 0
    assert run_main(["--replay", str(good_csv), "--no-identify", "--out", str(good.parent / "ok")])[0] == 0
    monkeypatch.chdir(good.parent)
    failures = []
    for case in cases:
        try:
            code, stderr = run_main(list(case.argv))
            check_outcome(case.name, code, stderr, case.codes)
        except (AssertionError, Hung) as err:
            failures.append(str(err))
    assert not failures, f"{len(failures)} of {len(cases)} cases:\n" + "\n".join(failures)


def test_a_csv_longer_than_a_run_is_refused_while_it_is_read(corpus, tmp_path, monkeypatch):
    _, _, good_csv = corpus
    monkeypatch.setattr("commission.csvlog.MAX_SAMPLES", 1000)  # the real bound is 4.8 million rows
    code, stderr = run_main(["--replay", str(good_csv), "--no-identify", "--out", str(tmp_path)])
    assert code == 3
    assert stderr.strip() == f"commission: error: {good_csv}: more than 1,000 data rows, more than a run records " \
                             "(10 minutes at 8 kHz)"


def test_a_replayed_simulated_run_whose_stored_plant_is_absurd_still_tunes(quick_sim_run, tmp_path):
    """A stored sim config or plant J_m 1e-30 / K 1e12 once ended in a LinAlgError in the tuning: the plant
    is refused with a warning and the settings are verified on the identified model."""
    from commission.mcaplog import read_config

    log = quick_sim_run.out / "run.mcap"
    rec = read_recording(log)
    config = read_config(log)
    config["sim"] = {**config.get("sim", {}), "J_m": 1e-30, "K": 1e12}
    plant = json.loads(rec.metadata["simulated_plant"])
    hostile = rec.replace(metadata={**rec.metadata, "simulated_plant": json.dumps({**plant, "J_m": 1e-30, "K": 1e12})})
    path = tmp_path / "absurd.mcap"
    write_recording(path, hostile, config=config)
    code, stderr = run_main(["--replay", str(path), "--config", "quick", "--out", str(tmp_path / "out"), "--json"])
    check_outcome("absurd stored plant", code, stderr, {0})
    doc = json.loads((tmp_path / "out" / "controller.json").read_text())
    assert "verification" in doc


# -- the property test ---------------------------------------------------------------------------------------------
def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One random mutation of a file: flipped bits, a cut, inserted or deleted bytes, a range zeroed or repeated."""
    b = bytearray(data)
    kind = int(rng.integers(0, 6))
    pos = int(rng.integers(0, len(b)))
    if kind == 0:
        for p in rng.integers(0, len(b), size=int(rng.integers(1, 16))):
            b[int(p)] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:
        del b[pos:]
    elif kind == 2:
        b[pos:pos] = rng.bytes(int(rng.integers(1, 64)))
    elif kind == 3:
        del b[pos:pos + int(rng.integers(1, 4096))]
    elif kind == 4:
        n = int(rng.integers(1, 4096))
        b[pos:pos + n] = bytes(len(b[pos:pos + n]))
    else:
        n = int(rng.integers(1, 2048))
        b[pos:pos] = b[pos:pos + n]
    return bytes(b)


def test_random_mutations_of_a_good_log_end_in_a_documented_exit_code(corpus, tmp_path):
    _, good, _ = corpus
    data = good.read_bytes()
    failures = []
    for seed in range(150):
        path = tmp_path / f"m{seed:03d}.mcap"
        path.write_bytes(mutate(data, np.random.default_rng(seed)))
        try:
            code, stderr = run_main(["--replay", str(path), "--no-identify", "--out", str(tmp_path / "out")])
            check_outcome(f"seed {seed}", code, stderr, {0, 3})
        except (AssertionError, Hung) as err:
            failures.append(str(err))
    assert not failures, "\n".join(failures)


def test_files_that_never_end_or_block_are_refused_by_the_command(corpus, tmp_path):
    """As the user meets them: the command in a subprocess, a timeout against a hang; with a few cases of
    the corpus and of the property test."""
    cases, good, _ = corpus
    fifo = tmp_path / "run.mcap"
    os.mkfifo(fifo)
    (tmp_path / "zero.csv").symlink_to("/dev/zero")
    mutated = tmp_path / "mutated.mcap"
    mutated.write_bytes(mutate(good.read_bytes(), np.random.default_rng(7)))
    picked = [c for c in cases if c.name in ("mcap: drive as a list", "config: invalid UTF-8")]
    runs = [(str(fifo), {3}), (str(tmp_path / "zero.csv"), {3}), ("/dev/urandom", {3}), (str(mutated), {0, 3})]
    procs = []
    for path, codes in runs:
        argv = ("--replay", path, "--no-identify", "--out", str(tmp_path / "out"))
        procs.append((path, codes, subprocess.Popen([sys.executable, "-m", "commission.cli", *argv],
                                                    stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)))
    for case in picked:
        procs.append((case.name, set(case.codes), subprocess.Popen([sys.executable, "-m", "commission.cli", *case.argv],
                                                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                                                   text=True, cwd=tmp_path)))
    try:
        for name, codes, proc in procs:
            _, stderr = proc.communicate(timeout=120)
            check_outcome(name, proc.returncode, stderr, codes)
            if name in (str(fifo), "/dev/urandom"):
                assert stderr.strip().endswith("not a regular file (a pipe or a device), not a log (.mcap or .csv)")
    finally:
        for _, _, proc in procs:
            if proc.poll() is None:
                proc.kill()
    assert len(picked) == 2
