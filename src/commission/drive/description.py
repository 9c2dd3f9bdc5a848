"""Drive descriptions: what a drive family's object dictionary means, loaded from ``drivers/<name>/``.

A description is data (``description.yaml`` + an EDS file); the CANopen backend
reads from it which objects carry the waveform, the trace, the trigger and the
progress, how the bus integers scale to SI units, and the vendor parameters a
tuning result maps to. No object index of a vendor area appears in code.

Where the folders are found: ``$COMMISSION_DRIVERS`` when it is set (your own
descriptions), else the ``drivers/`` that ships inside the package (the repository's
top-level ``drivers/``, found through :mod:`importlib.resources` in a wheel and in an
editable install alike).

A drive reachable on a serial service port also has a Modbus RTU / MEMOBUS
register map: ``modbus:`` inline, or ``modbus.yaml`` beside ``description.yaml``
(:class:`ModbusSpec`), read by the ``modbus`` backend and by ``sim_drive --modbus``.

Errors are one-liners: an unknown drive name or a missing folder is a
:class:`~commission.exceptions.ConfigError`, as is an invalid description file.
"""

from __future__ import annotations

import math
import os
from importlib import resources
from enum import Enum
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..exceptions import ConfigError, DriveError
from ..recording import REQUIRED_SIGNALS, SIGNAL_UNITS


def _check_trace_signals(channels: dict[str, object]) -> None:
    """A trace records only Recording signals, and at least the required ones."""
    unknown = sorted(set(channels) - set(SIGNAL_UNITS))
    if unknown:
        raise ValueError(f"unknown trace signal(s) {', '.join(unknown)} (known: {', '.join(sorted(SIGNAL_UNITS))})")
    for needed in REQUIRED_SIGNALS:
        if needed not in channels:
            raise ValueError(f"trace must record '{needed}'")


def parameter_raw(spec: ParameterSpec | ModbusParameter, name: str, value: float, where: str) -> float:
    """The raw value to write for ``value`` (in the parameter's unit): value / scale, an integer
    unless the type is real; refused (DriveError naming the parameter) outside ``min``..``max``.

    :param where: the object or register and drive, for the message.
    """
    raw = float(value) / spec.scale
    if spec.type not in ("real32", "real64"):
        raw = int(round(raw))
    if (spec.min is not None and raw < spec.min) or (spec.max is not None and raw > spec.max):
        raise DriveError(f"{name} = {value:g} {spec.unit} is raw {raw:g}, outside {spec.min:g}..{spec.max:g} ({where})")
    return raw

__all__ = [
    "DRIVERS_ENV", "GENERIC_DRIVE", "ChannelUnit", "DriveDescription", "ExcitationMethod", "IdentitySpec",
    "LoopSpec", "ObjectRef", "ParameterSpec", "SourcedValue", "TraceChannel", "drivers_dir", "find_description",
    "list_drives", "load_description",
    "ModbusParameter", "ModbusRegister", "ModbusRegisters", "ModbusSpec", "ModbusString", "ModbusTrace",
    "ModbusTraceChannel", "ModbusWaveform",
]

#: Environment variable naming the folder of drive descriptions.
DRIVERS_ENV = "COMMISSION_DRIVERS"
DESCRIPTION_FILE = "description.yaml"
#: Optional register map for the Modbus RTU backend, beside description.yaml (or inline: ``modbus:``).
MODBUS_FILE = "modbus.yaml"

#: struct format and size of the integer types a description may use.
INT_TYPES: dict[str, tuple[str, int]] = {
    "int8": ("b", 1), "uint8": ("B", 1), "int16": ("h", 2), "uint16": ("H", 2),
    "int32": ("i", 4), "uint32": ("I", 4), "real32": ("f", 4), "real64": ("d", 8),
}
IntType = Literal["int8", "uint8", "int16", "uint16", "int32", "uint32", "real32", "real64"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ObjectRef(_Model):
    """One object of the dictionary: ``{index: 0x2100, subindex: 1}``."""

    index: int = Field(ge=0x1000, le=0xFFFF)
    subindex: int = Field(0, ge=0, le=0xFF)

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X}"


class ExcitationMethod(str, Enum):
    """How the excitation reaches the drive."""

    TRACE = "trace"
    """The drive plays a downloaded waveform from its own clock and records a trace (primary path)."""
    STREAMED = "streamed"
    """The host streams target torque by SYNC + RPDO and records TPDO feedback (fallback)."""


class ChannelUnit(str, Enum):
    """Unit of an integer on the bus, before the channel's ``scale``."""

    RATED_TORQUE = "rated_torque"
    """fraction of the motor rated torque (0x6076): N·m = raw · scale · rated."""
    INCREMENT = "increment"
    """encoder increments: rad = raw · scale · 2π / increments per revolution."""
    INCREMENT_PER_SAMPLE = "increment_per_sample"
    """increments per trace sample: rad/s = raw · scale · 2π / increments · sample rate."""
    INCREMENT_PER_SECOND = "increment_per_second"
    """increments per second: rad/s = raw · scale · 2π / increments."""


class TraceChannel(_Model):
    """One recorded signal: an INT32 array (little-endian) in a DOMAIN object."""

    object: ObjectRef
    type: IntType = "int32"
    unit: ChannelUnit
    scale: float = Field(1.0, gt=0)
    encoder: Literal["motor", "load"] = "motor"


class WaveformSpec(_Model):
    """The waveform player: samples (DOMAIN of ``type``), its clock and capacity."""

    samples: ObjectRef
    type: IntType = "int32"
    torque_unit: ChannelUnit = ChannelUnit.RATED_TORQUE
    torque_scale: float = Field(1e-6, gt=0, description="CST samples: fraction of rated torque per count")
    velocity_unit: ChannelUnit = ChannelUnit.INCREMENT_PER_SECOND
    velocity_scale: float = Field(1.0, gt=0, description="CSV samples: increments/s per count")
    sample_period_ns: ObjectRef | None = None
    capacity: ObjectRef | None = None


class TraceSpec(_Model):
    """Everything the primary path needs: waveform, trigger, progress, trace channels."""

    waveform: WaveformSpec
    start: ObjectRef
    start_value: int = 1
    stop_value: int = 0
    progress: ObjectRef
    """samples played so far (UNSIGNED32)."""
    length: ObjectRef
    """samples recorded in the trace (UNSIGNED32)."""
    channels: dict[str, TraceChannel]

    @model_validator(mode="after")
    def _known_signals(self) -> TraceSpec:
        _check_trace_signals(self.channels)
        return self


class StreamedSpec(_Model):
    """The host-streamed fallback (standard objects; PDO numbers configurable)."""

    rpdo: int = Field(1, ge=1, le=4, description="RPDO number carrying target torque 0x6071")
    tpdo: int = Field(1, ge=1, le=4, description="TPDO number carrying 0x6064 + 0x6077 + 0x6041 (8 bytes)")
    max_load: float = Field(0.8, gt=0, le=1.0, description="largest bus load allowed")


class IdentitySpec(_Model):
    """What the drives of a family report in 0x1018 (identity object)."""

    vendor_id: int = Field(ge=0, le=0xFFFFFFFF, description="0x1018:01")
    product_codes: tuple[int, ...] = Field((), description="0x1018:02 values of the family; empty: any")

    def matches(self, vendor_id: int | None, product_code: int | None) -> bool:
        if vendor_id != self.vendor_id:
            return False
        return not self.product_codes or product_code in self.product_codes

    def describe(self) -> str:
        codes = ", ".join(f"0x{c:X}" for c in self.product_codes) or "any"
        return f"vendor 0x{self.vendor_id:08X}, product {codes}"


class ParameterSpec(_Model):
    """A named drive parameter: ``value [unit] = raw · scale``; ``min``/``max`` bound ``raw``."""

    object: ObjectRef
    type: IntType
    unit: str = ""
    scale: float = Field(1.0, gt=0)
    min: float | None = None
    max: float | None = None
    maps_to: str = Field("", description="what a tuning result writes here")
    note: str = ""


class SourcedValue(_Model):
    """One figure of the drive's loop structure, with where it comes from (``{value, source}``)."""

    value: float = Field(ge=0)
    source: str = Field(min_length=1, description="where the figure comes from: the manual's section, "
                        "a catalogue, or 'assumed: …'")
    confirm: bool = Field(False, description="true where the figure is not from the drive's own manual: "
                          "confirm it before relying on it")


class LoopSpec(_Model):
    """The drive's own control loops (``loop:``), what the tuning needs and a record cannot always show.

    Each figure is optional; the tuning states a conservative assumption for what is missing.
    The gain ranges are the parameter map's (``parameters:``, min/max in each parameter's unit).
    """

    current_loop_bandwidth_hz: SourcedValue | None = Field(
        None, description="closed current (torque) loop bandwidth, as a first-order lag [Hz]")
    velocity_loop_period_s: SourcedValue | None = Field(None, description="velocity-loop sample period [s]")
    position_loop_period_s: SourcedValue | None = Field(None, description="position-loop sample period [s]")
    computation_delay_s: SourcedValue | None = Field(
        None, description="from the velocity sample to the torque reference reaching the current loop, beyond "
        "the zero-order hold's own sample [s]")
    encoder_delay_s: SourcedValue | None = Field(
        None, description="from the position's instant to its use in the velocity loop (serial encoder "
        "transmission) [s]")


class UnitsSpec(_Model):
    """Where the unit scaling comes from (standard CiA 402 objects by default)."""

    rated_torque_mnm: ObjectRef = ObjectRef(index=0x6076)
    motor_increments: ObjectRef | None = ObjectRef(index=0x608F, subindex=1)
    motor_revolutions: ObjectRef | None = ObjectRef(index=0x608F, subindex=2)
    motor_increments_per_rev: int | None = Field(None, gt=0, description="used when the drive has no 0x608F")
    load_increments: ObjectRef | None = None
    load_increments_per_rev: int | None = Field(None, gt=0)
    velocity_unit: ChannelUnit = ChannelUnit.INCREMENT_PER_SECOND
    """unit of 0x606C velocity actual value."""


# -- Modbus RTU / MEMOBUS register map (drivers/<name>/modbus.yaml) --------------------------------
#: registers (16 bit) each integer type occupies
REGISTER_WORDS: dict[str, int] = {name: max(1, size // 2) for name, (_, size) in INT_TYPES.items()}


class ModbusRegister(_Model):
    """One value in holding registers: ``{address: 0x0101, type: uint16}`` (32-bit types take two)."""

    address: int = Field(ge=0, le=0xFFFF)
    type: IntType = "uint16"

    @property
    def words(self) -> int:
        return REGISTER_WORDS[self.type]

    def __str__(self) -> str:
        return f"register 0x{self.address:04X}"


class ModbusString(_Model):
    """An ASCII string, two characters per register (high byte first), NUL-padded."""

    address: int = Field(ge=0, le=0xFFFF)
    registers: int = Field(ge=1, le=125)


class ModbusRegisters(_Model):
    """The CiA 402-like state control and unit registers the backend needs (roles fixed, addresses data)."""

    device_type: ModbusRegister | None = None
    """a signature register checked at connection against ``ModbusSpec.device_type`` (like CANopen 0x1000)."""
    controlword: ModbusRegister
    statusword: ModbusRegister
    mode: ModbusRegister
    mode_display: ModbusRegister | None = None
    error_code: ModbusRegister
    rated_torque_mnm: ModbusRegister
    motor_increments: ModbusRegister
    load_increments: ModbusRegister | None = None
    sample_period_ns: ModbusRegister | None = None
    capacity: ModbusRegister | None = None
    max_torque: ModbusRegister
    """per mille of the rated torque (as CiA 402 0x6072)."""
    max_speed: ModbusRegister
    """rpm (as CiA 402 0x6080)."""
    position_actual: ModbusRegister | None = None
    travel_min: ModbusRegister | None = None
    travel_max: ModbusRegister | None = None


class ModbusWaveform(_Model):
    """Waveform download: write ``length`` (samples), then blocks of [offset (uint32), samples…] by FC 16
    at ``select`` (the window follows the offset's two registers)."""

    length: ModbusRegister
    select: int = Field(ge=0, le=0xFFFF)
    registers: int = Field(120, ge=2, le=121, description="sample registers per write (FC 16 carries <= 123)")
    type: IntType = "int32"
    torque_unit: ChannelUnit = ChannelUnit.RATED_TORQUE
    torque_scale: float = Field(1e-6, gt=0)
    velocity_unit: ChannelUnit = ChannelUnit.INCREMENT_PER_SECOND
    velocity_scale: float = Field(1.0, gt=0)


class ModbusTraceChannel(_Model):
    """One recorded signal, selected by number in the trace window."""

    channel: int = Field(ge=0, le=0xFFFF)
    type: IntType = "int32"
    unit: ChannelUnit
    scale: float = Field(1.0, gt=0)
    encoder: Literal["motor", "load"] = "motor"


class ModbusTrace(_Model):
    """Trigger, progress and the trace window: [channel (uint16), offset (uint32)] at ``select``, then the
    window's ``registers`` at ``window``; read together by FC 23 (``read_write``) or FC 16 + FC 3."""

    start: ModbusRegister
    start_value: int = 1
    stop_value: int = 0
    progress: ModbusRegister
    length: ModbusRegister
    select: int = Field(ge=0, le=0xFFFF)
    window: int = Field(ge=0, le=0xFFFF)
    registers: int = Field(124, ge=2, le=125, description="registers per read (FC 3/23 carry <= 125)")
    read_write: bool = Field(True, description="select and read in one FC 23 transaction")
    channels: dict[str, ModbusTraceChannel]

    @model_validator(mode="after")
    def _known_signals(self) -> ModbusTrace:
        _check_trace_signals(self.channels)
        return self


class ModbusParameter(_Model):
    """A named parameter in registers: ``value [unit] = raw · scale``; ``min``/``max`` bound ``raw``."""

    address: int = Field(ge=0, le=0xFFFF)
    type: IntType = "uint16"
    unit: str = ""
    scale: float = Field(1.0, gt=0)
    min: float | None = None
    max: float | None = None
    maps_to: str = ""
    note: str = ""

    @property
    def register(self) -> ModbusRegister:
        return ModbusRegister(address=self.address, type=self.type)


class ModbusSpec(_Model):
    """The drive's serial service port in Modbus RTU (MEMOBUS-compatible): line, framing, register map."""

    dialect: Literal["modbus", "memobus"] = "modbus"
    device_id: int = Field(1, ge=1, le=247)
    baudrate: int = Field(115200, gt=0)
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    word_order: Literal["big", "little"] = Field(
        "big", description="32-bit values: 'big' = high word at the lower address")
    timeout_s: float = Field(0.5, gt=0, le=10)
    retries: int = Field(2, ge=0, le=10)
    device_type: int | None = Field(None, description="value the device_type register must hold")
    identity: dict[Literal["vendor", "product", "serial", "firmware"], ModbusString] = Field(default_factory=dict)
    registers: ModbusRegisters | None = None
    waveform: ModbusWaveform | None = None
    trace: ModbusTrace | None = None
    parameters: dict[str, ModbusParameter] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _complete(self) -> ModbusSpec:
        if (self.waveform is None) != (self.trace is None):
            raise ValueError("'waveform' and 'trace' go together")
        if self.trace is not None and self.registers is None:
            raise ValueError("a trace needs the state-control 'registers'")
        return self


class DriveDescription(_Model):
    """One drive family (``drivers/<name>/description.yaml``)."""

    name: str
    summary: str = ""
    eds: str = Field(description="EDS file name in the same folder")
    device_type_profile: int = Field(402, description="low 16 bits of 0x1000")
    node_id: int = Field(1, ge=1, le=127, description="default node id")
    bitrate: int = Field(1_000_000, gt=0, description="bit rate assumed for the bus budget when the adapter has none")
    heartbeat_ms: int = Field(100, ge=10, le=60_000, description="producer heartbeat written to 0x1017")
    heartbeat_timeout_ms: int = Field(500, ge=10, description="consumer: link lost after this long without one")
    host_node_id: int = Field(127, ge=1, le=127, description="node id of the host's own heartbeat, which the "
                              "drive watches through 0x1016 (same consumer time) when it has that object")
    sdo_timeout_s: float = Field(0.3, gt=0, le=10)
    drive_sample_rate_hz: float = Field(8000.0, gt=0, description="the drive's control/trace clock")
    excitation: ExcitationMethod
    identity: IdentitySpec | None = Field(
        None, description="0x1018 of the family: picked when --drive is omitted, checked when given; "
        "a description without one fits any CiA 402 drive (generic)")
    trace: TraceSpec | None = None
    streamed: StreamedSpec = StreamedSpec()
    units: UnitsSpec = UnitsSpec()
    error_codes: dict[int, str] = Field(default_factory=dict, description="0x603F / EMCY code -> text")
    parameters: dict[str, ParameterSpec] = Field(default_factory=dict)
    loop: LoopSpec = Field(LoopSpec(), description="the drive's own loop structure, for the tuning")
    modbus: ModbusSpec | None = Field(None, description="Modbus RTU register map (inline, or modbus.yaml beside)")
    folder: Path = Field(Path("."), exclude=True)

    @model_validator(mode="after")
    def _trace_if_needed(self) -> DriveDescription:
        if self.excitation is ExcitationMethod.TRACE and self.trace is None:
            raise ValueError("excitation 'trace' needs a 'trace' section")
        return self

    @property
    def eds_path(self) -> Path:
        return self.folder / self.eds

    def describe_error(self, code: int) -> str:
        """Readable text of a 0x603F / EMCY error code (the description's, else the CiA 301 class)."""
        if code in self.error_codes:
            return self.error_codes[code]
        return _CIA301_CLASSES.get(code & 0xFF00) or _CIA301_CLASSES.get(code & 0xF000) or "unknown error"

    def parameter(self, name: str) -> ParameterSpec:
        try:
            return self.parameters[name]
        except KeyError:
            known = ", ".join(sorted(self.parameters)) or "none"
            raise ConfigError(f"drive '{self.name}' has no parameter '{name}' (known: {known})") from None


_CIA301_CLASSES = {
    0x1000: "generic error", 0x2000: "current", 0x3000: "voltage", 0x4000: "temperature",
    0x5000: "device hardware", 0x6000: "device software", 0x7000: "additional modules",
    0x8000: "monitoring", 0x9000: "external error", 0xF000: "additional functions", 0xFF00: "device specific",
}


def drivers_dir() -> Path:
    """The folder of drive descriptions: ``$COMMISSION_DRIVERS``, else the package's own ``drivers/``."""
    env = os.environ.get(DRIVERS_ENV)
    if env:
        path = Path(env)
        if not path.is_dir():
            raise ConfigError(f"${DRIVERS_ENV} is {env}, which is not a folder")
        return path
    shipped = resources.files("commission") / "drivers"
    if isinstance(shipped, Path) and shipped.is_dir():
        return shipped
    raise ConfigError(
        f"no drive descriptions found: the installed package has no drivers/ folder ({shipped}); "
        f"set ${DRIVERS_ENV} to one"
    )


def list_drives() -> list[str]:
    """Names of the drive families available."""
    return sorted(p.name for p in drivers_dir().iterdir() if (p / DESCRIPTION_FILE).is_file())


#: the description used for a drive whose identity no description claims
GENERIC_DRIVE = "generic-cia402"


def find_description(vendor_id: int | None, product_code: int | None) -> DriveDescription | None:
    """The description whose ``identity`` claims this drive (a product match before a vendor-only
    one), or None. Descriptions that fail to load are skipped: they cannot claim a drive."""
    best: tuple[int, DriveDescription] | None = None
    for name in list_drives():
        try:
            desc = load_description(name)
        except ConfigError:
            continue
        if desc.identity is None or not desc.identity.matches(vendor_id, product_code):
            continue
        rank = 2 if desc.identity.product_codes else 1
        if best is None or rank > best[0]:
            best = (rank, desc)
    return None if best is None else best[1]


def load_description(name_or_path: str | Path) -> DriveDescription:
    """Load ``drivers/<name>/description.yaml`` (or a folder path); errors name the file and key."""
    candidate = Path(name_or_path)
    folder = candidate if (candidate / DESCRIPTION_FILE).is_file() else drivers_dir() / str(name_or_path)
    path = folder / DESCRIPTION_FILE
    if not path.is_file():
        try:
            known = ", ".join(list_drives()) or "none"
        except ConfigError:
            known = "none"
        raise ConfigError(f"unknown drive '{name_or_path}' (known: {known})")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML") from err
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a drive description must be a mapping")
    modbus = data.get("modbus", MODBUS_FILE if (folder / MODBUS_FILE).is_file() else None)
    if isinstance(modbus, str):  # a file beside description.yaml
        try:
            modbus = yaml.safe_load((folder / modbus).read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError) as err:
            raise ConfigError(f"{folder / str(data.get('modbus', MODBUS_FILE))}: cannot read the Modbus map: {err}") from err
        data = {**data, "modbus": modbus}
    try:
        desc = DriveDescription.model_validate({**data, "folder": folder})
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        msg = "unknown key" if first["type"] == "extra_forbidden" else first["msg"]
        raise ConfigError(f"{path}: {where}: {msg}") from err
    if not desc.eds_path.is_file():
        raise ConfigError(f"{path}: EDS file {desc.eds} not found in {folder}")
    return desc


def increments_to_rad(increments_per_rev: float) -> float:
    """rad per encoder increment."""
    return 2.0 * math.pi / increments_per_rev
