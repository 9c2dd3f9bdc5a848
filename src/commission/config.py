"""Every setting of a commissioning run, validated (pydantic v2), loaded from configs/*.yaml.

A config file is a YAML mapping with up to four sections; anything omitted takes
the default below (which is the paper's experiment with the corrected chirp)::

    excitation:  {amplitude_nm, f_start_hz, f_end_hz, duration_s, sample_rate_hz,
                  bias_amplitude_nm, bias_frequency_hz, phase_deg, form}
    safety:      {max_torque_nm, max_speed_rad_s, max_travel_rad, margin,
                  planning_inertia_kg_m2, planning_damping_nm_s_per_rad}
    backlash_check: {amplitude_rad_s, frequency_hz, duration_s}
    identification: {...}          options of the identifier (commission.ident)
    tuning:      {...}             options of the controller design (commission.tuning)
    sim:         {...}             the simulated plant (commission.plant.PlantParameters)

Unknown keys are errors, so a typo never silently falls back to a default. Every number must
be finite, and a value no servo axis can have (a torque limit of 10⁹ N·m, an experiment of
1e-9 s, a simulated plant that resonates at MHz) is refused here, naming its key, before a
drive is touched.
"""

from __future__ import annotations

import math
import stat
from enum import Enum
from importlib import resources
from pathlib import Path
from typing import Any, get_args

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .exceptions import ConfigError
from .ident.hybrid import IdentificationOptions
from .recording import MAX_SAMPLES
from .tuning import TuningOptions


class ChirpForm(str, Enum):
    """How the chirp's phase is built."""

    LINEAR = "linear"
    """Correct linear chirp: instantaneous frequency sweeps f_start → f_end."""
    PAPER_LITERAL = "paper-literal"
    """The paper's eq. 18–19 taken literally, sin(ω(t)·t): ends near 2·f_end − f_start."""


#: Fewest samples an experiment may have: duration_s × sample_rate_hz (a recording the identifier can use).
MIN_SAMPLES = 1000
#: Largest config file read (a recipe is a few hundred bytes).
MAX_CONFIG_BYTES = 1 << 20
#: Deepest nesting of a config's values (the recipes nest three levels: identification.band_hz[0]).
MAX_CONFIG_DEPTH = 8


def _check_samples(duration_s: float, sample_rate_hz: float, key: str) -> None:
    n = duration_s * sample_rate_hz
    if not MIN_SAMPLES <= n <= MAX_SAMPLES:
        raise ValueError(
            f"{key} {duration_s:g} s at {sample_rate_hz:g} Hz is {n:.4g} samples: an experiment needs "
            f"{MIN_SAMPLES:,} to {MAX_SAMPLES:,}"
        )


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class ExcitationConfig(_Section):
    """Step 1 of the method: the chirp torque of paper eq. 18–19."""

    amplitude_nm: float = Field(0.0764, gt=0, le=1e5, description="chirp amplitude A [N·m] (paper: 12 % of rated)")
    f_start_hz: float = Field(0.1, gt=0, description="chirp start frequency [Hz]")
    f_end_hz: float = Field(400.0, gt=0, description="chirp end frequency [Hz]")
    duration_s: float = Field(10.0, gt=0, le=600, description="experiment length [s]")
    sample_rate_hz: float = Field(8000.0, gt=0, le=100_000, description="drive sample rate [Hz]")
    bias_amplitude_nm: float = Field(0.2292, ge=0, le=1e5, description="slow sine amplitude [N·m] (paper: 3A)")
    bias_frequency_hz: float = Field(0.1, ge=0, description="slow sine frequency [Hz]")
    phase_deg: float = Field(0.0, description="initial chirp phase φ0 [deg]")
    form: ChirpForm = Field(ChirpForm.LINEAR, description="'linear' (default) or 'paper-literal'")

    @model_validator(mode="after")
    def _band(self) -> ExcitationConfig:
        if self.f_end_hz <= self.f_start_hz:
            raise ValueError(f"f_end_hz ({self.f_end_hz}) must be above f_start_hz ({self.f_start_hz})")
        if self.f_end_hz >= self.sample_rate_hz / 2:
            raise ValueError(
                f"f_end_hz ({self.f_end_hz}) must be below Nyquist ({self.sample_rate_hz / 2} Hz)"
            )
        _check_samples(self.duration_s, self.sample_rate_hz, "duration_s")
        return self

    @property
    def n_samples(self) -> int:
        return int(round(self.duration_s * self.sample_rate_hz))


class SafetyConfig(_Section):
    """The envelope the whole excitation is checked against before anything moves.

    Speed and travel are predicted with a rigid-body model J·dv/dt = τ − B·v of
    the whole axis (``planning_*``); the predicted peaks, times ``margin``, must
    stay inside the limits. The drive enforces the same torque and speed limits
    itself during the run.
    """

    # The upper bounds are far beyond any servo axis: they only refuse what cannot be meant.
    max_torque_nm: float = Field(0.5, gt=0, le=1e5, description="largest torque reference allowed [N·m]")
    max_speed_rad_s: float = Field(50.0, gt=0, le=1e5, description="largest motor speed allowed [rad/s]")
    max_travel_rad: float = Field(200.0, gt=0, le=1e9, description="largest motor travel from the start [rad]")
    margin: float = Field(1.25, ge=1.0, le=100.0, description="factor on predicted speed and travel")
    planning_inertia_kg_m2: float = Field(
        6.7e-4, gt=0, le=1e4, description="total axis inertia for the prediction [kg·m²] (lower = more conservative)"
    )
    planning_damping_nm_s_per_rad: float = Field(
        1.37e-2, gt=0, le=1e6,
        description="total viscous friction for the prediction [N·m·s/rad] (lower = more conservative)",
    )


class BacklashCheckConfig(_Section):
    """The independent backlash check of paper §4.2 (``--measure-backlash``): a sine
    velocity reference in cyclic synchronous velocity mode; needs a load-side encoder."""

    amplitude_rad_s: float = Field(1.5, gt=0, le=1e5, description="velocity amplitude [rad/s] (paper: 1.5)")
    frequency_hz: float = Field(0.5, gt=0, description="reference frequency [Hz] (paper: 0.5)")
    duration_s: float = Field(4.0, gt=0, le=600, description="length [s]; 4 s at 0.5 Hz gives 3 reversals")


class Config(_Section):
    """A whole commissioning recipe."""

    excitation: ExcitationConfig = ExcitationConfig()
    safety: SafetyConfig = SafetyConfig()
    backlash_check: BacklashCheckConfig = BacklashCheckConfig()
    identification: IdentificationOptions = IdentificationOptions()
    tuning: TuningOptions = TuningOptions()
    sim: dict[str, Any] = Field(
        default_factory=dict,
        description="simulated plant parameters (commission.plant.PlantParameters), used with --sim",
    )

    @model_validator(mode="after")
    def _envelope_basics(self) -> Config:
        _check_samples(self.backlash_check.duration_s, self.excitation.sample_rate_hz, "backlash_check.duration_s")
        if self.sim:
            _check_plant(self.sim)
        peak = self.excitation.amplitude_nm + self.excitation.bias_amplitude_nm
        if peak > self.safety.max_torque_nm:
            raise ValueError(
                f"excitation peak torque {peak:.4g} N·m exceeds safety.max_torque_nm "
                f"{self.safety.max_torque_nm:.4g} N·m"
            )
        return self


def _check_plant(section: dict[str, Any]) -> None:
    """The ``sim`` section as the simulated drive will take it (key named as ``sim.<key>``)."""
    from .plant import PlantParameters

    try:
        PlantParameters.model_validate(section)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in ("sim", *first["loc"]))
        msg = "unknown key" if first["type"] == "extra_forbidden" else str(first["msg"]).removeprefix("Value error, ")
        raise ValueError(f"{where}: {msg}") from None


def _check_values(data: Any) -> None:
    """Refuse non-finite numbers (also as text: ``.inf``, ``"nan"``, ``"1e400"``) and absurd
    nesting anywhere in a config, naming the key, before the sections validate it. Shared
    values (YAML aliases) are looked at once."""
    seen: set[int] = set()
    stack: list[tuple[Any, str, int]] = [(data, "", 0)]
    while stack:
        value, where, depth = stack.pop()
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{where or '(top level)'}: must be a finite number, got {value}")
        if isinstance(value, str) and len(value) < 64:
            try:
                number = float(value)
            except ValueError:
                number = 0.0
            if not math.isfinite(number):
                raise ConfigError(f"{where}: must be a finite number, got {value!r}")
        if isinstance(value, (dict, list)):
            if id(value) in seen:
                continue
            seen.add(id(value))
            if depth >= MAX_CONFIG_DEPTH:
                raise ConfigError(f"{where}: nested too deeply (more than {MAX_CONFIG_DEPTH} levels)")
            items = list(value.items() if isinstance(value, dict) else enumerate(value))
            for key, item in reversed(items):  # popped in file order: the first bad key is named
                sub = f"{where}[{key}]" if isinstance(value, list) else (f"{where}.{key}" if where else str(key))
                stack.append((item, sub, depth + 1))


def _check_flags(model: type[BaseModel], data: Any, where: str = "") -> None:
    """Refuse a yes/no where a number belongs, naming the key: pydantic would read YAML's ``yes``
    (true) as 1.0, a torque limit twice the default that nobody wrote."""
    if not isinstance(data, dict):
        return
    for key, value in data.items():
        field = model.model_fields.get(key) if isinstance(key, str) else None
        if field is None:
            continue  # an unknown key: the validation names it
        sub = f"{where}.{key}" if where else key
        kinds = [a for a in (get_args(field.annotation) or (field.annotation,)) if a is not type(None)]
        if isinstance(value, bool) and bool not in kinds and any(k in (int, float) for k in kinds):
            raise ConfigError(f"{sub}: must be a number, got {str(value).lower()} (YAML reads yes/no/on/off as true/false)")
        for kind in kinds:
            if isinstance(kind, type) and issubclass(kind, BaseModel):
                _check_flags(kind, value, sub)


def _describe(err: ValidationError, source: str) -> str:
    """``source: key.path: message`` of the first error."""
    first = err.errors()[0]
    where = ".".join(str(p) for p in first["loc"])
    msg = str(first["msg"]).removeprefix("Value error, ")
    if first["type"] == "extra_forbidden":
        msg = "unknown key"
    more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    return f"{source}: {where}: {msg}{more}" if where else f"{source}: {msg}{more}"


def config_from_dict(data: dict[str, Any] | None, source: str = "config") -> Config:
    """Validate a config mapping; errors name the key (``excitation.amplitude_nm: ...``)."""
    try:
        _check_values(data)
        _check_flags(Config, data)
        if isinstance(data, dict) and isinstance(data.get("sim"), dict) and data["sim"]:
            from .plant import PlantParameters  # as _check_plant: only when there is a sim section

            _check_flags(PlantParameters, data["sim"], "sim")
    except ConfigError as err:
        raise ConfigError(f"{source}: {err}") from None
    try:
        return Config.model_validate(data or {})
    except ValidationError as err:
        raise ConfigError(_describe(err, source)) from err


def recipes_dir() -> Path:
    """The commissioning recipes that ship inside the package (the repository's ``configs/``)."""
    shipped = resources.files("commission") / "configs"
    if isinstance(shipped, Path) and shipped.is_dir():
        return shipped
    raise ConfigError(f"the installed package has no configs/ folder ({shipped})")


def recipe_names() -> list[str]:
    """Names of the shipped recipes (``default``, ``paper-literal``, …), usable as ``--config NAME``."""
    return sorted(p.stem for p in recipes_dir().glob("*.yaml"))


def resolve_config_path(path: str | Path | None) -> Path:
    """The YAML file ``--config`` means: an existing file, else a shipped recipe's name
    (``paper-literal`` or ``paper-literal.yaml``); ``None`` is the shipped ``default``."""
    if path is None:
        return recipes_dir() / "default.yaml"
    p = Path(path)
    if p.exists() or p.parent != Path("."):
        return p
    shipped = recipes_dir() / (p.name if p.suffix == ".yaml" else f"{p.name}.yaml")
    return shipped if shipped.is_file() else p


def load_config(path: str | Path | None) -> Config:
    """Load and validate a YAML config (a file or a shipped recipe's name); ``None`` loads the
    shipped ``configs/default.yaml`` (the paper's experiment)."""
    p = resolve_config_path(path)
    try:
        text = _read_text(p)
    except FileNotFoundError as err:
        try:
            known = ", ".join(recipe_names())
        except ConfigError:
            known = "none"
        raise ConfigError(f"{p}: no such config file (shipped recipes: {known})") from err
    except OSError as err:
        raise ConfigError(f"{p}: cannot read config: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        raise ConfigError(f"{p}: not a text file (invalid UTF-8 at byte {err.start})") from err
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{p}: not valid YAML{where}") from err
    except RecursionError as err:
        raise ConfigError(f"{p}: nested too deeply to be a config") from err
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{p}: a config must be a mapping of sections, got {type(data).__name__}")
    return config_from_dict(data, str(p))


def _read_text(path: Path) -> str:
    """A config file's text: a regular file (never a FIFO or a device, which could block or
    never end) of at most MAX_CONFIG_BYTES."""
    info = path.stat()
    if not stat.S_ISREG(info.st_mode):
        raise OSError(0, "not a regular file")
    with path.open("rb") as f:
        data = f.read(MAX_CONFIG_BYTES + 1)
    if len(data) > MAX_CONFIG_BYTES:
        raise OSError(0, f"larger than {MAX_CONFIG_BYTES // 1024} KiB, not a config")
    return data.decode("utf-8")


def config_to_dict(config: Config) -> dict[str, Any]:
    """JSON-ready dict of a config (for logs and reports)."""
    return config.model_dump(mode="json")


