"""MCAP log of a Recording: one JSON channel per signal, readable after any abort.

File layout (in file order)::

    magic, Header (library "drive-commission/<version>; mcap-python/<version>")
    Metadata "recording"           everything needed to rebuild the Recording but samples
    Metadata "recording_metadata"  the Recording's own metadata (str -> str), verbatim
    Metadata "config"              the run's config: top-level key -> JSON text of its value
    Chunk (zstd) ...               Schema + Channel records (first chunk), then messages
    Metadata "recording_end"       sample_count, status ("complete" | "aborted: <Error>")
    DataEnd, summary, Footer, magic

The three leading metadata records are written, and flushed to the OS, before
any sample, so a file cut anywhere after them still says what it holds.

Channels (message encoding ``json``, schema encoding ``jsonschema``, one
schema per channel named ``commission.<signal>``; channel metadata ``unit``)::

    /torque_ref      N·m      required
    /motor_velocity  rad/s    required
    /motor_position  rad      optional
    /load_position   rad      optional
    /load_velocity   rad/s    optional

Every message carries a block of consecutive samples with its own times::

    {"first_sample": 160,            # index of t_s[0] in the recording
     "t_s": [0.02, 0.020125, ...],   # Recording.t (seconds since start_time), exact
     "values": [0.51, 0.49, ...],    # the signal, in "unit"
     "unit": "rad/s"}

Blocks hold ``samples_per_message`` samples (the last may hold fewer); the
messages of one block follow each other on all channels with the same
``log_time`` = ``publish_time`` = start_time + t_s[0] in integer nanoseconds
and ``sequence`` = block number. Floats are written with ``repr`` and so
round-trip bitwise; non-uniform (host-streamed) sample times are stored as
they are. Sample times are repeated on every channel so that each message is
self-contained (a topic can be read alone, in Foxglove or a script); zstd
removes the repetition (+0.8 % file size, measured).

For Foxglove (whose Plot panel plots message *fields* over log time, so the arrays of a
block are not a time series there), the writer can add one more channel, opt-in with
``plot_every=n``::

    /samples   schema commission.samples, one message per n-th sample, all signals:
               {"sample": 160, "t_s": 0.02, "torque_ref": 0.51, "motor_velocity": 3.2, ...}

with ``log_time`` = ``publish_time`` = start_time + t_s and ``sequence`` = sample index, so
``/samples.motor_velocity`` plots as a series. Its values are exact samples (every n-th, no
filter); the blocks stay the exact, complete record, and readers here ignore ``/samples``.
n = 8 gives 1 kHz for an 8 kHz trace (10,000 messages for 10 s). The ``recording`` metadata
names the topic and n (``plot_topic``, ``plot_every``).

Chunks end only between blocks: a chunk is closed (``Writer.flush``) once it
holds ``chunk_size`` uncompressed bytes, so after a cut every signal has the
same number of samples. Any other non-signal topic (``/identification`` …)
carries one JSON object per message, see :meth:`RecordingWriter.add_result`; a finished
file gets one with :func:`append_result` (the file is rewritten, then replaced atomically).

Reading walks the top-level records (opcode, length) to find where the last
complete one ends, then parses them in one pass with mcap's ``StreamReader``
(CRCs checked): the same path for whole and cut files. ``make_reader`` fails
on a file without footer, and ``NonSeekingReader`` allows one query only
(metadata or messages) and raises at the cut. A run of zeros at the end
(space a power loss left unwritten) counts as a cut; anything else that does
not parse is a corrupt file, not a cut.

A truncated or unfinished file (no footer: power loss, killed process) is
read up to the last complete record before the cut, with a
:class:`TruncatedLogWarning` saying how many samples came back; the chunk
that was being filled in memory is lost: at most ``chunk_size`` uncompressed
bytes plus fewer than ``samples_per_message`` pending samples. The default
64 KiB holds about 560 samples of 5 signals (70 ms at 8 kHz) and compresses
as well as 256 KiB or 1 MiB; 16 KiB makes the file 3 % larger
(``bench/bench_mcaplog.py``).
"""

from __future__ import annotations

import errno
import io
import json
import math
import os
import stat
import struct
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from types import TracebackType
from typing import Any, Callable

import numpy as np
import zstandard
from mcap.decoder import DecoderFactory
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer
from numpy.typing import ArrayLike, NDArray

from .exceptions import LogFormatError, RecordingError
from .recording import MAX_SAMPLES, REQUIRED_SIGNALS, SIGNAL_UNITS, DriveInfo, Recording

__all__ = [
    "FORMAT_VERSION",
    "JsonDecoderFactory",
    "RecordingWriter",
    "PLOT_TOPIC",
    "TruncatedLogWarning",
    "append_result",
    "plot_schema",
    "read_config",
    "read_recording",
    "read_results",
    "signal_schema",
    "write_recording",
]

#: Version of the layout described in the module docstring.
FORMAT_VERSION = 1
_FORMAT = "drive-commission.recording"
_MAGIC = b"\x89MCAP0\r\n"
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)
#: Bytes a Message record adds around its data (opcode, length, channel, sequence, 2 times).
_MESSAGE_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8
_SIGNAL_TOPICS: Mapping[str, str] = {f"/{name}": name for name in SIGNAL_UNITS}
#: Topic of the per-sample messages for Foxglove's Plot panel (``plot_every``).
PLOT_TOPIC = "/samples"
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
#: Largest log file read: ten minutes at 8 kHz take ~240 MB; the file is read into memory whole.
MAX_LOG_BYTES = 512 << 20
#: Largest chunk a log may hold once decompressed (this writer's are 64 KiB): a compressed chunk
#: declaring more is refused before it is decompressed.
MAX_CHUNK_BYTES = 64 << 20

try:
    TOOL_VERSION = version("drive-commission")
except PackageNotFoundError:  # running from a source tree that is not installed
    TOOL_VERSION = "0+unknown"


class TruncatedLogWarning(UserWarning):
    """The log was cut (no footer) or the run was aborted: fewer samples than planned."""


class JsonDecoderFactory(DecoderFactory):
    """Decodes ``json`` messages for mcap's own readers (``make_reader(f, decoder_factories=[...])``)."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        return json.loads if message_encoding == MessageEncoding.JSON else None


def signal_schema(name: str) -> dict[str, Any]:
    """The JSON schema of the messages on the channel of signal ``name``."""
    unit = SIGNAL_UNITS[name]
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"commission.{name}",
        "description": f"Consecutive samples of {name} [{unit}] with their times.",
        "type": "object",
        "properties": {
            "first_sample": {
                "type": "integer",
                "minimum": 0,
                "description": "index of t_s[0] in the recording",
            },
            "t_s": {
                "type": "array",
                "items": {"type": "number"},
                "description": "sample times since the recording's start_time [s]",
            },
            "values": {
                "type": "array",
                "items": {"type": "number"},
                "description": f"{name} [{unit}], one per entry of t_s",
            },
            "unit": {"type": "string", "const": unit},
        },
        "required": ["first_sample", "t_s", "values", "unit"],
        "additionalProperties": False,
    }


def plot_schema(signals: Sequence[str]) -> dict[str, Any]:
    """The JSON schema of the ``/samples`` messages carrying ``signals`` (one sample each)."""
    props: dict[str, Any] = {
        "sample": {"type": "integer", "minimum": 0, "description": "index of the sample in the recording"},
        "t_s": {"type": "number", "description": "sample time since the recording's start_time [s]"},
    }
    for name in signals:
        props[name] = {"type": "number", "description": f"{name} [{SIGNAL_UNITS[name]}]"}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "commission.samples",
        "description": "One sample of every signal, for plotting as series (every n-th sample of the recording).",
        "type": "object",
        "properties": props,
        "required": list(props),
        "additionalProperties": False,
    }


_RESULT_SCHEMA: Mapping[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "description": "A result of drive-commission (identification, tuning …) as a JSON object.",
}


def _ns_since_epoch(when: datetime) -> int:
    delta = when - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000


def _dumps(value: Any) -> str:
    return json.dumps(value, allow_nan=False, separators=(",", ":"))


# ---------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------
class RecordingWriter:
    """Writes a Recording to MCAP block by block, so that an abort leaves a readable file.

    :param path: the ``.mcap`` file (overwritten).
    :param sample_rate_hz: nominal sample rate [Hz].
    :param start_time: wall-clock time of t = 0 (timezone-aware).
    :param drive: identity of the drive.
    :param signals: names of the signals that :meth:`append` will receive (``torque_ref`` and
        ``motor_velocity`` at least), any order.
    :param config: the run's configuration; stored as JSON text per top-level key.
    :param metadata: the Recording's free-form metadata (str -> str).
    :param samples_per_message: samples per message and channel.
    :param chunk_size: uncompressed bytes after which a chunk is closed and written out; this is
        the most a crash can lose (plus fewer than ``samples_per_message`` samples).
    :param compression: ``"zstd"``, ``"lz4"`` or ``"none"``.
    :param expected_samples: how many samples will come, when known; lets a reader of a cut
        file say how many are missing.
    :param plot_every: also write every ``plot_every``-th sample as one message on ``/samples``
        (all signals in one JSON object) for Foxglove's Plot panel; None (default): no such topic.

    Closing (or leaving the ``with`` block, also through an exception) writes the rest and the
    MCAP summary; an exception is recorded as ``status`` in the ``recording_end`` metadata.
    Chunks that are complete are handed to the OS as they are closed; call :meth:`flush` to
    push out everything so far (e.g. between phases of a slow host-streamed run).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        sample_rate_hz: float,
        start_time: datetime,
        drive: DriveInfo,
        signals: Sequence[str],
        config: Mapping[str, Any] | None = None,
        metadata: Mapping[str, str] | None = None,
        samples_per_message: int = 80,
        chunk_size: int = 64 * 1024,
        compression: str = "zstd",
        expected_samples: int | None = None,
        plot_every: int | None = None,
    ) -> None:
        unknown = [s for s in signals if s not in SIGNAL_UNITS]
        if unknown:
            raise RecordingError(f"unknown signal(s) {', '.join(map(repr, unknown))}; known: {', '.join(SIGNAL_UNITS)}")
        missing = [s for s in REQUIRED_SIGNALS if s not in signals]
        if missing:
            raise RecordingError(f"required signal(s) missing: {', '.join(missing)}")
        if not (np.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise RecordingError(f"sample rate must be positive, got {sample_rate_hz!r} Hz")
        if start_time.tzinfo is None:
            raise RecordingError("start_time must be timezone-aware")
        if samples_per_message < 1:
            raise ValueError(f"samples_per_message must be >= 1, got {samples_per_message}")
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {', '.join(_COMPRESSION)}, got {compression!r}")
        if plot_every is not None and (int(plot_every) != plot_every or plot_every < 1):
            raise ValueError(f"plot_every must be a positive integer or None, got {plot_every!r}")
        self._plot_every = int(plot_every) if plot_every is not None else None
        self._path = os.fspath(path)
        self._signals: tuple[str, ...] = tuple(s for s in SIGNAL_UNITS if s in signals)
        self._spm = int(samples_per_message)
        self._chunk_size = int(chunk_size)
        self._start_ns = _ns_since_epoch(start_time)
        self._units_json = {name: json.dumps(SIGNAL_UNITS[name]) for name in self._signals}
        self._n_written = 0  # samples handed to the MCAP writer
        self._n_appended = 0
        self._last_t = -np.inf
        self._block = 0
        self._chunk_bytes = 0
        self._pending_t: list[NDArray[np.float64]] = []
        self._pending: dict[str, list[NDArray[np.float64]]] = {name: [] for name in self._signals}
        self._pending_n = 0
        self._result_channels: dict[str, int] = {}
        self._closed = False
        self._cut = False  # a block was cut short on some channels (an exception inside _emit_block)

        self._file = open(self._path, "wb")  # noqa: SIM115 - closed in close()
        try:
            # Writer.flush() (mcap >= 1.6) lets chunks end between blocks; without it the Writer
            # closes chunks by itself at chunk_size, possibly inside a block (readers trim).
            self._can_flush = callable(getattr(Writer, "flush", None))
            self._writer = Writer(
                self._file,
                chunk_size=2**62 if self._can_flush else self._chunk_size,
                compression=_COMPRESSION[compression],
            )
            self._writer.start(profile="", library=f"drive-commission/{TOOL_VERSION}; {LIBRARY_IDENTIFIER}")
            info = {
                "format": _FORMAT,
                "format_version": str(FORMAT_VERSION),
                "tool_version": TOOL_VERSION,
                "sample_rate_hz": repr(float(sample_rate_hz)),
                "start_time": start_time.isoformat(),
                "drive": json.dumps(drive.to_dict(), allow_nan=False),
                "signals": json.dumps(list(self._signals)),
                "units": json.dumps({"t": "s", **{s: SIGNAL_UNITS[s] for s in self._signals}}),
                "samples_per_message": str(self._spm),
            }
            if expected_samples is not None:
                info["expected_samples"] = str(int(expected_samples))
            if self._plot_every is not None:
                info["plot_topic"] = PLOT_TOPIC
                info["plot_every"] = str(self._plot_every)
            self._writer.add_metadata("recording", info)
            self._writer.add_metadata("recording_metadata", {str(k): str(v) for k, v in (metadata or {}).items()})
            self._writer.add_metadata(
                "config", {str(k): json.dumps(v, default=str) for k, v in (config or {}).items()}
            )
            self._file.flush()
            self._channels: dict[str, int] = {}
            for name in self._signals:
                schema_id = self._writer.register_schema(
                    name=f"commission.{name}",
                    encoding=SchemaEncoding.JSONSchema,
                    data=json.dumps(signal_schema(name)).encode(),
                )
                self._channels[name] = self._writer.register_channel(
                    topic=f"/{name}",
                    message_encoding=MessageEncoding.JSON,
                    schema_id=schema_id,
                    metadata={"unit": SIGNAL_UNITS[name]},
                )
            self._plot_channel: int | None = None
            if self._plot_every is not None:
                plot_schema_id = self._writer.register_schema(
                    name="commission.samples",
                    encoding=SchemaEncoding.JSONSchema,
                    data=json.dumps(plot_schema(self._signals)).encode(),
                )
                self._plot_channel = self._writer.register_channel(
                    topic=PLOT_TOPIC,
                    message_encoding=MessageEncoding.JSON,
                    schema_id=plot_schema_id,
                    metadata={"plot_every": str(self._plot_every),
                              **{name: SIGNAL_UNITS[name] for name in self._signals}},
                )
        except BaseException:
            self._file.close()
            raise

    # -- public ------------------------------------------------------------------------------
    @property
    def signals(self) -> tuple[str, ...]:
        """The signals this writer takes, in SIGNAL_UNITS order."""
        return self._signals

    @property
    def n_samples(self) -> int:
        """Samples appended so far."""
        return self._n_appended

    def append(self, t: ArrayLike, **signals: ArrayLike) -> None:
        """Add a block of samples: times [s] since start_time and every signal, same length."""
        self._check_open()
        t_arr = _block_array("t", t, None)
        n = t_arr.shape[0]
        if set(signals) != set(self._signals):
            missing = [s for s in self._signals if s not in signals]
            extra = [s for s in signals if s not in self._signals]
            parts = ([f"missing {', '.join(missing)}"] if missing else []) + (
                [f"not declared {', '.join(extra)}"] if extra else []
            )
            raise RecordingError(f"append(): signals do not match the writer's ({'; '.join(parts)})")
        arrays = {name: _block_array(name, signals[name], n) for name in self._signals}
        if n == 0:
            return
        if t_arr[0] <= self._last_t or (n > 1 and np.any(np.diff(t_arr) <= 0)):
            raise RecordingError(
                f"append(): time must increase strictly (sample {self._n_appended} onwards, "
                f"last t={self._last_t!r} s, block starts at t={float(t_arr[0])!r} s)"
            )
        self._last_t = float(t_arr[-1])
        self._n_appended += n
        self._pending_t.append(t_arr)
        for name, arr in arrays.items():
            self._pending[name].append(arr)
        self._pending_n += n
        if self._pending_n >= self._spm:
            self._emit(partial=False)
        if not self._can_flush:
            self._file.flush()

    def add_result(
        self,
        topic: str,
        payload: Mapping[str, Any],
        *,
        schema: Mapping[str, Any] | None = None,
        log_time_ns: int | None = None,
    ) -> None:
        """Write ``payload`` as one JSON message on ``topic`` (e.g. ``"/identification"``).

        The topic's channel is made on first use, with ``schema`` (a JSON schema) or a generic
        object schema. The result is written out at once (its chunk is closed).
        """
        self._check_open()
        if not (isinstance(topic, str) and topic.startswith("/") and len(topic) > 1):
            raise ValueError(f"topic must start with '/', got {topic!r}")
        if topic in _SIGNAL_TOPICS:
            raise ValueError(f"topic {topic} is reserved for the signal {_SIGNAL_TOPICS[topic]}")
        if topic == PLOT_TOPIC:
            raise ValueError(f"topic {topic} is reserved for the per-sample plot messages")
        if not isinstance(payload, Mapping):
            raise TypeError(f"result payload must be a mapping, got {type(payload).__name__}")
        try:
            data = _dumps(dict(payload)).encode()
        except (TypeError, ValueError) as err:
            raise ValueError(f"result for {topic} is not JSON-serialisable: {err}") from err
        channel_id = self._result_channels.get(topic)
        if channel_id is None:
            schema_id = self._writer.register_schema(
                name=f"commission{topic.replace('/', '.')}",
                encoding=SchemaEncoding.JSONSchema,
                data=json.dumps(dict(schema) if schema is not None else _RESULT_SCHEMA).encode(),
            )
            channel_id = self._writer.register_channel(topic, MessageEncoding.JSON, schema_id)
            self._result_channels[topic] = channel_id
        stamp = time.time_ns() if log_time_ns is None else int(log_time_ns)
        self._writer.add_message(channel_id, log_time=stamp, data=data, publish_time=stamp)
        self._chunk_bytes += len(data) + _MESSAGE_OVERHEAD
        self._close_chunk()

    def flush(self) -> None:
        """Write out every sample appended so far (a short message, a small chunk) to the OS."""
        self._check_open()
        if self._pending_n:
            self._emit(partial=True)
        self._close_chunk()
        self._file.flush()

    def close(self) -> None:
        """Write what is pending and the MCAP summary. Safe to call twice."""
        self._close("complete")

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._close("complete" if exc_type is None else f"aborted: {exc_type.__name__}")

    # -- internals ---------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self._path}: the recording writer is closed")

    def _close(self, status: str) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            if self._cut:
                status = status if status != "complete" else "aborted"
                status += " (the last block was cut while it was written)"
            elif self._pending_n:
                self._emit(partial=True)
            self._close_chunk()
            self._writer.add_metadata(
                "recording_end", {"sample_count": str(self._n_written), "status": status}
            )
            self._writer.finish()
        finally:
            self._file.close()

    def _close_chunk(self) -> None:
        if self._can_flush and self._chunk_bytes:
            self._writer.flush()  # type: ignore[attr-defined]
            self._chunk_bytes = 0

    def _emit(self, *, partial: bool) -> None:
        """Write the pending samples as whole blocks; keep a remainder unless ``partial``."""
        t_all = np.concatenate(self._pending_t)
        sig_all = {name: np.concatenate(parts) for name, parts in self._pending.items()}
        total = t_all.shape[0]
        end = total if partial else total - total % self._spm
        done = 0
        try:
            for i0 in range(0, end, self._spm):
                i1 = min(i0 + self._spm, end)
                self._emit_block(t_all[i0:i1], {name: arr[i0:i1] for name, arr in sig_all.items()})
                done = i1
        finally:
            # written blocks leave the queue even when an exception (Ctrl-C) cut the loop, so that
            # closing the file afterwards does not write them a second time
            self._pending_t = [t_all[done:]] if done < total else []
            self._pending = {name: ([arr[done:]] if done < total else []) for name, arr in sig_all.items()}
            self._pending_n = total - done

    def _emit_block(self, t: NDArray[np.float64], signals: Mapping[str, NDArray[np.float64]]) -> None:
        self._cut = True  # until every channel has the block: closing then writes no more samples
        t_json = _dumps(t.tolist())
        stamp = max(0, min(self._start_ns + round(float(t[0]) * 1e9), 2**64 - 1))
        for name in self._signals:
            data = (
                f'{{"first_sample":{self._n_written},"t_s":{t_json},'
                f'"values":{_dumps(signals[name].tolist())},"unit":{self._units_json[name]}}}'
            ).encode()
            self._writer.add_message(
                self._channels[name], log_time=stamp, data=data, publish_time=stamp, sequence=self._block
            )
            self._chunk_bytes += len(data) + _MESSAGE_OVERHEAD
        if self._plot_channel is not None:
            self._emit_plot(t, signals)
        self._n_written += t.shape[0]
        self._block += 1
        self._cut = False
        if self._chunk_bytes >= self._chunk_size:
            self._close_chunk()


    def _emit_plot(self, t: NDArray[np.float64], signals: Mapping[str, NDArray[np.float64]]) -> None:
        """One ``/samples`` message per ``plot_every``-th sample of the block about to be written."""
        assert self._plot_every is not None and self._plot_channel is not None
        first = self._n_written
        offset = (-first) % self._plot_every
        idx = range(offset, t.shape[0], self._plot_every)
        if not idx:
            return
        t_list = t.tolist()
        columns = [(f',"{name}":', signals[name].tolist()) for name in self._signals]
        for k in idx:
            tk = t_list[k]
            stamp = max(0, min(self._start_ns + round(tk * 1e9), 2**64 - 1))
            data = (f'{{"sample":{first + k},"t_s":{tk!r}'
                    + "".join(f"{key}{col[k]!r}" for key, col in columns) + "}").encode()
            self._writer.add_message(
                self._plot_channel, log_time=stamp, data=data, publish_time=stamp, sequence=first + k
            )
            self._chunk_bytes += len(data) + _MESSAGE_OVERHEAD


def _block_array(name: str, values: ArrayLike, n: int | None) -> NDArray[np.float64]:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 1:
        raise RecordingError(f"append(): '{name}' must be one-dimensional, got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise RecordingError(f"append(): '{name}' has {arr.shape[0]} samples, t has {n}")
    if not np.all(np.isfinite(arr)):
        raise RecordingError(f"append(): '{name}' has non-finite values")
    return arr


def write_recording(
    path: str | os.PathLike[str],
    recording: Recording,
    *,
    config: Mapping[str, Any] | None = None,
    samples_per_message: int = 80,
    chunk_size: int = 64 * 1024,
    compression: str = "zstd",
    plot_every: int | None = None,
) -> None:
    """Write ``recording`` (and the run's ``config``) to the MCAP file ``path``.

    ``plot_every=n`` adds the ``/samples`` topic for Foxglove (module docstring)."""
    with RecordingWriter(
        path,
        sample_rate_hz=recording.sample_rate_hz,
        start_time=recording.start_time,
        drive=recording.drive,
        signals=[name for name, _ in recording.signals()],
        config=config,
        metadata=recording.metadata,
        samples_per_message=samples_per_message,
        chunk_size=chunk_size,
        compression=compression,
        expected_samples=len(recording),
        plot_every=plot_every,
    ) as writer:
        writer.append(recording.t, **dict(recording.signals()))


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------
#: A decoded sample block: index of its first sample, its times [s], its values.
_Block = tuple[int, NDArray[np.float64], NDArray[np.float64]]


@dataclass
class _Framing:
    """Where the readable records of a file end, and whether the file is complete."""

    stop: int  # offset of the footer, or of the first incomplete record
    complete: bool


@dataclass
class _Contents:
    complete: bool
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    blocks: dict[str, list[_Block]] = field(default_factory=dict)
    samples: dict[str, int] = field(default_factory=dict)
    results: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    message_counts: dict[int, int] = field(default_factory=dict)
    n_messages: int = 0
    statistics: Statistics | None = None


def regular_file_size(path: str, what: str) -> int:
    """The size [bytes] of ``path``, a regular file (a FIFO or a device could block or never end);
    LogFormatError naming ``what`` the file should be otherwise."""
    try:
        info = os.stat(path)
    except FileNotFoundError as err:
        raise LogFormatError(f"{path}: no such file") from err
    except OSError as err:
        raise LogFormatError(f"{path}: cannot read ({err.strerror or err})") from err
    if stat.S_ISDIR(info.st_mode):
        raise LogFormatError(f"{path}: is a directory, not {what}") from IsADirectoryError(
            errno.EISDIR, os.strerror(errno.EISDIR), path)
    if not stat.S_ISREG(info.st_mode):
        raise LogFormatError(f"{path}: not a regular file (a pipe or a device), not {what}")
    return info.st_size


def _load(path: str) -> bytes:
    size = regular_file_size(path, "an MCAP file")
    if size > MAX_LOG_BYTES:
        raise LogFormatError(f"{path}: {size / 2**20:.0f} MiB, larger than a log can be ({MAX_LOG_BYTES >> 20} MiB)")
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_LOG_BYTES + 1)
    except OSError as err:
        raise LogFormatError(f"{path}: cannot read ({err.strerror or err})") from err
    if not data:
        raise LogFormatError(f"{path}: empty file")
    if len(data) > MAX_LOG_BYTES:  # grew while it was read
        raise LogFormatError(f"{path}: larger than a log can be ({MAX_LOG_BYTES >> 20} MiB)")
    return data


def _frame(path: str, data: bytes) -> _Framing:
    """Walk the top-level records (opcode, length) to find where complete records end."""
    size = len(data)
    if data[: len(_MAGIC)] != _MAGIC:
        if size < len(_MAGIC) and _MAGIC.startswith(data):
            raise LogFormatError(f"{path}: truncated MCAP file, no complete samples before the cut")
        raise LogFormatError(f"{path}: not an MCAP file (bad magic bytes {data[:8]!r})")
    if data[-8:] == bytes(8):
        # A complete file ends with the magic; a run of zeros at the end is space that a crash
        # (power loss) left unwritten: the file is cut where the zeros start.
        size = len(data.rstrip(b"\0"))
    pos = len(_MAGIC)
    first = True
    while size - pos >= 9:
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if opcode == 0:
            raise LogFormatError(f"{path}: corrupt MCAP file (invalid record at byte {pos})")
        if first and opcode != Opcode.HEADER:
            raise LogFormatError(f"{path}: corrupt MCAP file (first record is not a header)")
        first = False
        end = pos + 9 + length
        if end > size:
            break  # the cut falls inside this record
        if opcode == Opcode.FOOTER:
            tail = data[end:size]
            if tail == _MAGIC:
                return _Framing(stop=pos, complete=True)
            if len(tail) < len(_MAGIC) and _MAGIC.startswith(tail):
                return _Framing(stop=pos, complete=False)
            raise LogFormatError(f"{path}: corrupt MCAP file ({len(tail)} unexpected bytes after the footer)")
        pos = end
    return _Framing(stop=pos, complete=False)


#: What mcap's readers raise on bytes that are not a valid record.
_CORRUPT = (McapError, ValueError, struct.error, zstandard.ZstdError, EOFError, IndexError, KeyError, OverflowError,
            RuntimeError, MemoryError)


def _records(path: str, data: bytes, framing: _Framing, *, emit_chunks: bool = False) -> Iterator[Any]:
    """Records up to ``framing.stop`` (chunks opened, CRCs checked), via mcap's StreamReader; with
    ``emit_chunks`` the chunks themselves (see :func:`open_chunk`)."""
    reader = StreamReader(io.BytesIO(data[len(_MAGIC) : framing.stop]), skip_magic=True, validate_crcs=True,
                          emit_chunks=True)
    try:
        for record in reader.records:
            if isinstance(record, Chunk) and not emit_chunks:
                yield from open_chunk(path, record)
            else:
                yield record
    except EndOfFile:  # framing.stop is a record boundary: the stream ends cleanly there
        return
    except _CORRUPT as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise LogFormatError(f"{path}: corrupt MCAP file ({reason})") from err


def open_chunk(path: str, chunk: Chunk) -> list[Any]:
    """The records of a chunk (CRC checked), decompressed to at most its declared size, which may
    be at most MAX_CHUNK_BYTES: a chunk that claims or inflates to more is refused, never
    decompressed into memory (a zstd frame's own content size would be believed otherwise)."""
    size = chunk.uncompressed_size
    if size > MAX_CHUNK_BYTES:
        raise LogFormatError(f"{path}: corrupt MCAP file (a chunk of {size:,} bytes, at most {MAX_CHUNK_BYTES:,})")
    try:
        if chunk.compression == "zstd":
            with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(chunk.data)) as reader:
                raw = reader.read(size + 1)
        elif chunk.compression == "lz4":
            import lz4.frame

            raw = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
        elif chunk.compression == "":
            raw = chunk.data
        else:
            raise LogFormatError(f"{path}: unsupported chunk compression {chunk.compression!r}")
        if len(raw) != size:
            raise LogFormatError(f"{path}: corrupt MCAP file (a chunk holds {len(raw):,} bytes, it says {size:,})")
        plain = Chunk(message_start_time=chunk.message_start_time, message_end_time=chunk.message_end_time,
                      uncompressed_size=size, uncompressed_crc=chunk.uncompressed_crc, compression="", data=raw)
        return breakup_chunk(plain, validate_crc=True)
    except LogFormatError:
        raise
    except (*_CORRUPT, ImportError) as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise LogFormatError(f"{path}: corrupt MCAP file ({reason})") from err


def _scan(path: str, *, signals: bool = True, results: bool = True, stop_after: str | None = None) -> _Contents:
    data = _load(path)
    framing = _frame(path, data)
    contents = _Contents(complete=framing.complete)
    channels: dict[int, Channel] = {}
    for record in _records(path, data, framing):
        if isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                raise LogFormatError(f"{path}: corrupt MCAP file (message on unknown channel {record.channel_id})")
            contents.n_messages += 1
            contents.message_counts[record.channel_id] = contents.message_counts.get(record.channel_id, 0) + 1
            name = _SIGNAL_TOPICS.get(channel.topic)
            if channel.topic == PLOT_TOPIC:
                continue  # a decimated copy of the blocks, for Foxglove
            if name is not None:
                if signals:
                    block = _decode_block(path, channel.topic, record)
                    contents.blocks.setdefault(name, []).append(block)
                    n = contents.samples[name] = contents.samples.get(name, 0) + len(block[1])
                    if n > MAX_SAMPLES:
                        raise LogFormatError(f"{path}: more than {MAX_SAMPLES:,} samples of {name}, more than a run "
                                             "records (10 minutes at 8 kHz)")
            elif results:
                contents.results.setdefault(channel.topic, []).append(_decode_result(path, channel, record))
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Metadata):
            contents.metadata.setdefault(record.name, record.metadata)
            if record.name == stop_after:
                return contents
        elif isinstance(record, Statistics):
            contents.statistics = record
    return contents


def _numbers(values: list[Any]) -> bool:
    """Every entry a JSON number (not a bool, a string, a list or null)."""
    return all(type(v) is float or type(v) is int for v in values)


def _decode_block(path: str, topic: str, message: Message) -> _Block:
    ok = False
    try:
        block = json.loads(message.data)
        if isinstance(block, dict):
            first, t, values = block.get("first_sample"), block.get("t_s"), block.get("values")
            ok = (type(first) is int and first >= 0 and isinstance(t, list) and isinstance(values, list)
                  and len(t) == len(values) and _numbers(t) and _numbers(values))
    except (ValueError, RecursionError):  # not JSON (UnicodeDecodeError is a ValueError), or nested absurdly deep
        ok = False
    if ok:
        try:
            return first, np.array(t, dtype=np.float64), np.array(values, dtype=np.float64)
        except OverflowError:  # an integer beyond the float range
            ok = False
    raise LogFormatError(f"{path}: corrupt MCAP file (bad sample block on {topic}, sequence {message.sequence})")


def _decode_result(path: str, channel: Channel, message: Message) -> dict[str, Any]:
    if channel.message_encoding != MessageEncoding.JSON:
        raise LogFormatError(f"{path}: topic {channel.topic} is not JSON ({channel.message_encoding!r})")
    try:
        payload = json.loads(message.data)
    except (ValueError, RecursionError) as err:
        raise LogFormatError(f"{path}: corrupt MCAP file (bad JSON on {channel.topic})") from err
    if not isinstance(payload, dict):
        raise LogFormatError(f"{path}: message on {channel.topic} is not a JSON object")
    return payload


def _header_info(path: str, contents: _Contents) -> dict[str, Any]:
    info = contents.metadata.get("recording")
    if info is None:
        if not contents.complete and contents.n_messages == 0:
            raise LogFormatError(f"{path}: truncated MCAP file, no complete samples before the cut")
        raise LogFormatError(f"{path}: not a drive-commission recording (no 'recording' metadata)")
    try:
        if info["format"] != _FORMAT:
            raise LogFormatError(f"{path}: not a drive-commission recording (format {info['format']!r})")
        if int(info["format_version"]) > FORMAT_VERSION:
            raise LogFormatError(
                f"{path}: written in log format {info['format_version']} by drive-commission "
                f"{info.get('tool_version', '?')}; this version reads format <= {FORMAT_VERSION}"
            )
        start_time = datetime.fromisoformat(info["start_time"])
        if start_time.tzinfo is None:
            raise ValueError("start_time without a time zone")
        expected = info.get("expected_samples")
        rate = float(info["sample_rate_hz"])
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"sample_rate_hz {info['sample_rate_hz']!r}")
        signals = json.loads(info["signals"])
        if not (isinstance(signals, list) and all(isinstance(x, str) for x in signals)):
            raise ValueError("signals is not a list of names")
        return {
            "sample_rate_hz": rate,
            "start_time": start_time,
            "drive": _drive_info(json.loads(info["drive"])),
            "signals": signals,
            "expected_samples": int(expected) if expected is not None else None,
        }
    except (KeyError, ValueError, TypeError, RecursionError) as err:
        raise LogFormatError(f"{path}: invalid 'recording' metadata ({type(err).__name__}: {err})") from err


def _drive_info(data: Any) -> DriveInfo:
    """The ``drive`` of the recording metadata, every field of its type (TypeError otherwise)."""
    if not isinstance(data, dict):
        raise TypeError(f"drive is a {type(data).__name__}, not an object")
    info = DriveInfo.from_dict(data)
    for name, value in info.to_dict().items():
        if name == "rated_torque_nm":
            if value is not None and not (type(value) in (int, float) and math.isfinite(value) and value > 0):
                raise TypeError(f"drive.rated_torque_nm is {value!r}")
        elif not isinstance(value, str):
            raise TypeError(f"drive.{name} is a {type(value).__name__}, not text")
    return info


def _concat(path: str, name: str, blocks: list[_Block]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    expected_first = 0
    for first, t, _ in blocks:
        if first != expected_first:
            raise LogFormatError(
                f"{path}: corrupt MCAP file (/{name} jumps from sample {expected_first} to {first})"
            )
        expected_first += len(t)
    if not blocks:
        return np.zeros(0), np.zeros(0)
    return np.concatenate([b[1] for b in blocks]), np.concatenate([b[2] for b in blocks])


def _samples_text(n: int) -> str:
    return f"{n:,} sample" + ("" if n == 1 else "s")


def read_recording(path: str | os.PathLike[str]) -> Recording:
    """Read the Recording of an MCAP log written by :func:`write_recording` / RecordingWriter.

    A cut or unfinished file gives the samples complete before the cut, with a
    :class:`TruncatedLogWarning`; :class:`LogFormatError` when nothing usable is left or the
    file is not such a log.
    """
    p = os.fspath(path)
    contents = _scan(p, results=False)
    info = _header_info(p, contents)
    signals = info["signals"]
    if not set(REQUIRED_SIGNALS) <= set(signals) or not set(signals) <= set(SIGNAL_UNITS):
        raise LogFormatError(f"{p}: invalid 'recording' metadata (signals {signals})")
    arrays = {name: _concat(p, name, contents.blocks.get(name, [])) for name in signals}
    lengths = {name: arr[0].shape[0] for name, arr in arrays.items()}
    n = min(lengths.values())
    ref_t = arrays[signals[0]][0][:n]
    for name, (t, _) in arrays.items():
        if not np.array_equal(t[:n], ref_t):
            k = int(np.argmax(t[:n] != ref_t))
            raise LogFormatError(f"{p}: corrupt MCAP file (/{name} has other sample times from sample {k})")

    end = contents.metadata.get("recording_end", {})
    expected = info["expected_samples"]
    if "sample_count" in end:
        try:
            expected = int(end["sample_count"])
        except ValueError as err:
            raise LogFormatError(f"{p}: invalid 'recording_end' metadata (sample_count {end['sample_count']!r})") from err
    notes: list[str] = []
    status = str(end.get("status", "complete"))
    if contents.complete:
        if len(set(lengths.values())) > 1 and (status == "complete" or expected is None or n != expected):
            raise LogFormatError(f"{p}: corrupt MCAP file (signals of different lengths: {lengths})")
        if expected is not None and n != expected:
            raise LogFormatError(f"{p}: corrupt MCAP file ({n} samples, the log says {expected})")
        stats = contents.statistics
        if stats is not None and (stats.message_count != contents.n_messages):
            raise LogFormatError(
                f"{p}: corrupt MCAP file ({contents.n_messages} messages, the summary says {stats.message_count})"
            )
        planned = info["expected_samples"]
        if status != "complete":
            notes.append(f"{p}: the recording was {status}; read {_samples_text(n)}")
        elif planned is not None and n < planned:
            notes.append(f"{p}: the log holds {_samples_text(n)} of the {planned:,} planned")
    else:
        if n == 0:
            raise LogFormatError(f"{p}: truncated MCAP file, no complete samples before the cut")
        of = f" of {expected:,}" if expected is not None else ""
        note = (
            f"{p}: file is truncated or was not closed (no MCAP footer); recovered "
            f"{_samples_text(n)}{of} ({n / info['sample_rate_hz']:.4g} s)"
        )
        if len(set(lengths.values())) > 1:
            longer = ", ".join(f"{k} {v:,}" for k, v in lengths.items() if v > n)
            note += f"; signals trimmed to the common length {n:,} ({longer})"
        notes.append(note)
    if n < 2:
        raise LogFormatError(f"{p}: only {_samples_text(n)} in the log, a recording needs at least 2")
    try:
        recording = Recording(
            t=ref_t,
            sample_rate_hz=info["sample_rate_hz"],
            start_time=info["start_time"],
            drive=info["drive"],
            metadata=contents.metadata.get("recording_metadata", {}),
            **{name: arrays[name][1][:n] for name in signals},
        )
    except RecordingError as err:
        raise LogFormatError(f"{p}: unusable samples ({err})") from err
    for note in notes:
        warnings.warn(note, TruncatedLogWarning, stacklevel=2)
    return recording


def read_results(path: str | os.PathLike[str]) -> dict[str, list[dict[str, Any]]]:
    """The JSON objects on the non-signal topics of a log, by topic, in file order."""
    p = os.fspath(path)
    contents = _scan(p, signals=False)
    if not contents.complete:
        warnings.warn(
            f"{p}: file is truncated or was not closed (no MCAP footer); results after the cut are lost",
            TruncatedLogWarning,
            stacklevel=2,
        )
    return contents.results


def append_result(
    path: str | os.PathLike[str],
    topic: str,
    payload: Mapping[str, Any],
    *,
    schema: Mapping[str, Any] | None = None,
    log_time_ns: int | None = None,
) -> None:
    """Add ``payload`` as one JSON message on ``topic`` to a *finished* log (e.g. the
    identification after the run: the log is closed before the identifier runs, so that a
    crash there cannot cost the samples).

    An MCAP file cannot grow after its summary, so the file is rewritten record by record
    (same chunks, same messages, metadata and attachments, CRCs checked while reading) with
    the result in a chunk of its own just before the ``recording_end`` metadata, into a
    temporary file beside it that then replaces it atomically: a crash leaves the old file.
    ``log_time_ns`` defaults to the last log time in the file (the end of the recording), so
    the result sits at the end of Foxglove's timeline instead of stretching it to "now".

    :raises LogFormatError: the file is not a complete MCAP file (no footer) or is corrupt.
    :raises ValueError: bad topic, or a payload that is not JSON-serialisable.
    """
    from mcap.records import Attachment, DataEnd, Header, MessageIndex

    p = os.fspath(path)
    if not (isinstance(topic, str) and topic.startswith("/") and len(topic) > 1):
        raise ValueError(f"topic must start with '/', got {topic!r}")
    if topic in _SIGNAL_TOPICS or topic == PLOT_TOPIC:
        raise ValueError(f"topic {topic} is reserved for samples")
    if not isinstance(payload, Mapping):
        raise TypeError(f"result payload must be a mapping, got {type(payload).__name__}")
    try:
        result_data = _dumps(dict(payload)).encode()
    except (TypeError, ValueError) as err:
        raise ValueError(f"result for {topic} is not JSON-serialisable: {err}") from err
    data = _load(p)
    framing = _frame(p, data)
    if not framing.complete:
        raise LogFormatError(f"{p}: cannot add a result to a truncated or unfinished MCAP file")

    tmp = f"{p}.tmp-{os.getpid()}"
    try:
        with open(tmp, "wb") as out:
            writer: Writer | None = None
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            topics: dict[str, int] = {}
            last_time = 0
            done = False

            def add_result_now() -> None:
                assert writer is not None
                channel_id = topics.get(topic)
                if channel_id is None:
                    schema_id = writer.register_schema(
                        name=f"commission{topic.replace('/', '.')}",
                        encoding=SchemaEncoding.JSONSchema,
                        data=json.dumps(dict(schema) if schema is not None else _RESULT_SCHEMA).encode(),
                    )
                    channel_id = writer.register_channel(topic, MessageEncoding.JSON, schema_id)
                stamp = last_time if log_time_ns is None else int(log_time_ns)
                writer.add_message(channel_id, log_time=stamp, data=result_data, publish_time=stamp)
                writer.flush()  # type: ignore[attr-defined]

            def copy(record: Any) -> None:
                nonlocal last_time
                assert writer is not None
                if isinstance(record, Schema):
                    schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel):
                    channel_ids[record.id] = writer.register_channel(
                        record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0),
                        dict(record.metadata),
                    )
                    topics.setdefault(record.topic, channel_ids[record.id])
                elif isinstance(record, Message):
                    last_time = max(last_time, record.log_time)
                    writer.add_message(channel_ids[record.channel_id], log_time=record.log_time,
                                       data=record.data, publish_time=record.publish_time,
                                       sequence=record.sequence)

            for record in _records(p, data, _Framing(stop=framing.stop, complete=True), emit_chunks=True):
                if isinstance(record, Header):
                    writer = Writer(out, chunk_size=2**62, compression=_compression_of(data, framing))
                    writer.start(profile=record.profile, library=record.library)
                elif writer is None:
                    raise LogFormatError(f"{p}: corrupt MCAP file (first record is not a header)")
                elif isinstance(record, Chunk):
                    for r in open_chunk(p, record):
                        copy(r)
                    writer.flush()  # type: ignore[attr-defined]  # keep the chunk boundaries
                elif isinstance(record, (Schema, Channel, Message)):  # unchunked files
                    copy(record)
                elif isinstance(record, Metadata):
                    if record.name == "recording_end" and not done:
                        add_result_now()
                        done = True
                    writer.add_metadata(record.name, dict(record.metadata))
                elif isinstance(record, Attachment):
                    writer.add_attachment(record.create_time, record.log_time, record.name,
                                          record.media_type, record.data)
                elif isinstance(record, DataEnd):
                    break
                elif isinstance(record, MessageIndex):
                    continue  # rebuilt by the writer
            if writer is None:
                raise LogFormatError(f"{p}: corrupt MCAP file (no header)")
            if not done:
                add_result_now()
            writer.finish()
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, p)
    except OSError as err:
        raise LogFormatError(f"{p}: cannot rewrite the log to add {topic} ({err.strerror or err})") from err
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _compression_of(data: bytes, framing: _Framing) -> CompressionType:
    """The compression of the first chunk of a file (zstd when it has none)."""
    reader = StreamReader(io.BytesIO(data[len(_MAGIC) : framing.stop]), skip_magic=True, emit_chunks=True)
    try:
        for record in reader.records:
            if isinstance(record, Chunk):
                return {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}.get(
                    record.compression, CompressionType.NONE)
    except (EndOfFile, McapError, ValueError, struct.error):
        pass
    return CompressionType.ZSTD


def read_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The run's config as stored by the writer (top-level keys, JSON values decoded)."""
    p = os.fspath(path)
    contents = _scan(p, signals=False, results=False, stop_after="config")
    stored = contents.metadata.get("config")
    if stored is None:
        if not contents.complete:
            raise LogFormatError(f"{p}: truncated MCAP file, cut before the config")
        raise LogFormatError(f"{p}: not a drive-commission recording (no 'config' metadata)")
    try:
        return {key: json.loads(value) for key, value in stored.items()}
    except (ValueError, RecursionError) as err:
        raise LogFormatError(f"{p}: invalid 'config' metadata ({err})") from err


class ResultLog:
    """An MCAP log of JSON results only (no samples), written message by message.

    For actions that are not experiments, e.g. ``--restore-from``: every message is on disk
    (its chunk closed, the file flushed) before :meth:`add` returns, so a crash keeps what was
    logged; readable with :func:`read_results`.
    """

    def __init__(self, path: str | os.PathLike[str], *, metadata: Mapping[str, str] | None = None) -> None:
        self._path = os.fspath(path)
        self._file = open(self._path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, chunk_size=2**62, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=f"drive-commission/{TOOL_VERSION}; {LIBRARY_IDENTIFIER}")
        self._writer.add_metadata("results", {"tool_version": TOOL_VERSION, **dict(metadata or {})})
        self._channels: dict[str, int] = {}
        self._closed = False

    def add(self, topic: str, payload: Mapping[str, Any]) -> None:
        """Write ``payload`` as one JSON message on ``topic``, now."""
        if self._closed:
            raise ValueError("the result log is closed")
        if not (isinstance(topic, str) and topic.startswith("/") and len(topic) > 1):
            raise ValueError(f"topic must start with '/', got {topic!r}")
        data = _dumps(dict(payload)).encode()
        channel_id = self._channels.get(topic)
        if channel_id is None:
            schema_id = self._writer.register_schema(
                name=f"commission{topic.replace('/', '.')}", encoding=SchemaEncoding.JSONSchema,
                data=json.dumps(_RESULT_SCHEMA).encode(),
            )
            channel_id = self._channels[topic] = self._writer.register_channel(topic, MessageEncoding.JSON, schema_id)
        stamp = time.time_ns()
        self._writer.add_message(channel_id, log_time=stamp, data=data, publish_time=stamp)
        self._writer.flush()  # type: ignore[attr-defined]
        self._file.flush()

    def close(self) -> None:
        """Finish the file (safe to call twice)."""
        if not self._closed:
            self._closed = True
            try:
                self._writer.finish()
            finally:
                self._file.close()

    def __enter__(self) -> ResultLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
