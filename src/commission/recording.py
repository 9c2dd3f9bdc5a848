"""The Recording: sampled signals of one experiment, plus where they came from.

Shared by the drive layer (which produces it), the MCAP/CSV log (which stores
it) and the identifier (which consumes it). The identifier never knows whether
a Recording came from a live drive, the simulator, an MCAP log or a CSV file.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .exceptions import LogFormatError, RecordingError

#: Every signal a Recording can carry, in a fixed order, with its SI unit.
SIGNAL_UNITS: Mapping[str, str] = MappingProxyType(
    {
        "torque_ref": "N·m",
        "motor_position": "rad",
        "motor_velocity": "rad/s",
        "load_position": "rad",
        "load_velocity": "rad/s",
    }
)
#: Signals every Recording has; the others are optional.
REQUIRED_SIGNALS: tuple[str, ...] = ("torque_ref", "motor_velocity")

#: Most samples a recording read from a file may hold (ten minutes at 8 kHz): the longest experiment a
#: config allows, and a bound on the memory a replayed log can take.
MAX_SAMPLES = 4_800_000

#: Relative tolerance on sample spacing for a record to count as uniformly sampled.
UNIFORM_RTOL = 1e-6
#: A record is refused when more of its samples than this were lost (it is then mostly guessed) ...
MAX_LOST_FRACTION = 0.2
#: ... or when this long a stretch of it was lost in one piece [s].
MAX_GAP_S = 0.1
#: Metadata key of the samples the link lost: their values in the arrays are interpolated (positions,
#: velocities) or the intended reference (torque), and a time-domain fit should leave them out.
#: The value lists sample indices and inclusive ranges, ``"17,40-43"`` (see :func:`encode_samples`).
LOST_SAMPLES_KEY = "lost_samples"


def encode_samples(mask: ArrayLike) -> str:
    """Sample indices where ``mask`` is true, as ``"17,40-43"`` (empty string: none)."""
    edges = np.diff(np.concatenate(([0], np.asarray(mask, dtype=np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return ",".join(str(a) if a == b else f"{a}-{b}" for a, b in zip(starts.tolist(), stops.tolist()))


def decode_samples(text: str, n: int) -> NDArray[np.bool_]:
    """The boolean mask of ``n`` samples that :func:`encode_samples` wrote (indices ≥ n ignored)."""
    mask = np.zeros(n, dtype=bool)
    for part in filter(None, (p.strip() for p in text.split(","))):
        try:
            first, _, last = part.partition("-")
            a, b = int(first), int(last or first)
        except ValueError:
            raise RecordingError(f"metadata '{LOST_SAMPLES_KEY}': '{part}' is not an index or a range") from None
        if a < 0 or b < a:
            raise RecordingError(f"metadata '{LOST_SAMPLES_KEY}': bad range '{part}'")
        mask[a : b + 1] = True
    return mask


@dataclass(frozen=True)
class DriveInfo:
    """Identity of the drive a Recording was taken on (all fields informative)."""

    backend: str = "unknown"
    """Backend name as registered in :mod:`commission.drive` (``sim``, ``canopen``…)."""
    vendor: str = ""
    product: str = ""
    serial_number: str = ""
    firmware: str = ""
    rated_torque_nm: float | None = None
    """Motor rated torque [N·m], when the drive reports it (CiA 402 0x6076)."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DriveInfo:
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


def _as_signal(name: str, values: ArrayLike | None, n: int | None) -> NDArray[np.float64] | None:
    if values is None:
        return None
    arr = np.array(values, dtype=np.float64, copy=True)
    if arr.ndim != 1:
        raise RecordingError(f"signal '{name}' must be one-dimensional, got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise RecordingError(f"signal '{name}' has {arr.shape[0]} samples, expected {n}")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise RecordingError(
            f"signal '{name}' has {int(bad.sum())} non-finite values (first at sample {int(np.argmax(bad))})"
        )
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Recording:
    """Sampled signals of one experiment.

    All arrays have shape ``(N,)`` and dtype float64, are read-only and finite.

    :param t: sample times since the start of the experiment [s], strictly increasing.
        Uniform (``n / sample_rate_hz``) for drive traces and for host-streamed experiments
        on the drive's clock (cycles counted by the drive); the actual sample times where the
        host kept time (records from older versions, CSV files).
    :param sample_rate_hz: nominal sample rate [Hz].
    :param torque_ref: torque reference sent to the current loop [N·m].
    :param motor_velocity: motor velocity as the drive reports it [rad/s].
    :param motor_position: motor position [rad], optional.
    :param load_position: load-side encoder position [rad], optional.
    :param load_velocity: load-side velocity [rad/s], optional.
    :param start_time: wall-clock time of sample 0 (timezone-aware, UTC).
    :param drive: identity of the drive.
    :param metadata: free-form strings (source file, config digest, notes). ``lost_samples``
        (:data:`LOST_SAMPLES_KEY`) marks samples a streamed link lost: see :attr:`lost_mask`.
    """

    t: NDArray[np.float64]
    sample_rate_hz: float
    torque_ref: NDArray[np.float64]
    motor_velocity: NDArray[np.float64]
    motor_position: NDArray[np.float64] | None = None
    load_position: NDArray[np.float64] | None = None
    load_velocity: NDArray[np.float64] | None = None
    start_time: datetime = field(default_factory=lambda: datetime.now(timezone.utc))
    drive: DriveInfo = field(default_factory=DriveInfo)
    metadata: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = _as_signal("t", self.t, None)
        assert t is not None
        n = t.shape[0]
        if n < 2:
            raise RecordingError(f"a recording needs at least 2 samples, got {n}")
        dt = np.diff(t)
        if np.any(dt <= 0):
            k = int(np.argmax(dt <= 0))
            raise RecordingError(f"time is not strictly increasing at sample {k + 1} (t={t[k + 1]!r} s)")
        if not (np.isfinite(self.sample_rate_hz) and self.sample_rate_hz > 0):
            raise RecordingError(f"sample rate must be positive, got {self.sample_rate_hz!r} Hz")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "sample_rate_hz", float(self.sample_rate_hz))
        for name in SIGNAL_UNITS:
            object.__setattr__(self, name, _as_signal(name, getattr(self, name), n))
        if self.start_time.tzinfo is None:
            raise RecordingError("start_time must be timezone-aware")
        object.__setattr__(self, "metadata", MappingProxyType(dict(self.metadata)))

    @classmethod
    def uniform(
        cls,
        sample_rate_hz: float,
        torque_ref: ArrayLike,
        motor_velocity: ArrayLike,
        **kwargs: Any,
    ) -> Recording:
        """A Recording sampled at exactly ``sample_rate_hz``, starting at t = 0."""
        n = np.shape(torque_ref)[0]
        t = np.arange(n, dtype=np.float64) / float(sample_rate_hz)
        return cls(t=t, sample_rate_hz=sample_rate_hz, torque_ref=torque_ref,
                   motor_velocity=motor_velocity, **kwargs)

    # -- views -----------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def n_samples(self) -> int:
        return len(self)

    @property
    def duration_s(self) -> float:
        """Duration covered by the samples [s] (N sample periods)."""
        return len(self) / self.sample_rate_hz

    @property
    def is_uniform(self) -> bool:
        """True when sample times are n / sample_rate_hz within UNIFORM_RTOL of a period."""
        ideal = self.t[0] + np.arange(len(self)) / self.sample_rate_hz
        return bool(np.max(np.abs(self.t - ideal)) <= UNIFORM_RTOL / self.sample_rate_hz * len(self))

    @property
    def lost_mask(self) -> NDArray[np.bool_]:
        """True at the samples the link lost (metadata ``lost_samples``); all false when none were."""
        return decode_samples(self.metadata.get(LOST_SAMPLES_KEY, ""), len(self))

    @property
    def has_load_encoder(self) -> bool:
        return self.load_position is not None or self.load_velocity is not None

    def signals(self) -> Iterator[tuple[str, NDArray[np.float64]]]:
        """(name, samples) of every signal present, in SIGNAL_UNITS order."""
        for name in SIGNAL_UNITS:
            arr = getattr(self, name)
            if arr is not None:
                yield name, arr

    def replace(self, **changes: Any) -> Recording:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def head(self, n: int) -> Recording:
        """The first ``n`` samples (for partial traces after an abort)."""
        sliced = {name: arr[:n] for name, arr in self.signals()}
        return self.replace(t=self.t[:n], **sliced)

    def equals(self, other: Recording) -> bool:
        """Exact equality of every sample, the rate, start time, drive and metadata."""
        if not isinstance(other, Recording):
            return NotImplemented
        if (self.sample_rate_hz, self.start_time, self.drive, dict(self.metadata)) != (
            other.sample_rate_hz, other.start_time, other.drive, dict(other.metadata)
        ):
            return False
        if not np.array_equal(self.t, other.t):
            return False
        for name in SIGNAL_UNITS:
            a, b = getattr(self, name), getattr(other, name)
            if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
                return False
        return True


def read_log(path: Path) -> Recording:
    """A Recording from a .mcap or .csv file, by its name's ending (a truncated MCAP file gives
    what was written, with a warning). A FIFO or a device is refused: it could block or never end."""
    from .mcaplog import read_recording, regular_file_size

    regular_file_size(str(path), "a log (.mcap or .csv)")
    suffix = path.suffix.lower()
    if suffix == ".mcap":
        return read_recording(path)
    if suffix == ".csv":
        from .csvlog import read_csv

        return read_csv(path)
    raise LogFormatError(f"{path}: unknown log format '{suffix or '(none)'}': expected .mcap or .csv")
