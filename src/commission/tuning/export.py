"""Export of controller settings (controller.json, controller-<drive>.yaml) and write-back to a drive.

The drive-specific file goes through the drive description's parameter map
(``drivers/<name>/description.yaml``, ``parameters:``): each parameter this module
knows by name gets the tuning value converted to the parameter's own unit, then
to its raw integer (``raw = value / scale``), clamped to ``min``/``max`` and
flagged when clamped. :func:`apply` refuses to write anything when a value was
clamped.

Write-back (:func:`apply`): read every old value, show old → new, ask (or ``yes``),
log the old values, write each value, read it back and compare, log every write;
store to non-volatile memory (CiA 301 0x1010, the description's ``store_parameters``)
only on request. :func:`restore_values` reads the old values back from the log
(``/parameters`` topic of the run's MCAP file) for ``--restore-from``.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..exceptions import DriveError, LogFormatError, OutputError
from .settings import ControllerSettings, TuningError

__all__ = [
    "PARAMETER_TOPIC", "ApplyReport", "ParameterValue", "apply", "controller_json", "drive_parameters",
    "restore_values", "write_controller_files", "write_values",
]

#: MCAP topic of the write-back log (old values, every write, store).
PARAMETER_TOPIC = "/parameters"
#: CiA 301 0x1010 signature "save".
STORE_SIGNATURE = 0x65766173
STORE_PARAMETER = "store_parameters"

_INT_TYPES = {"int8", "uint8", "int16", "uint16", "int32", "uint32"}
_INT_RANGES = {"int8": (-(2**7), 2**7 - 1), "uint8": (0, 2**8 - 1), "int16": (-(2**15), 2**15 - 1),
               "uint16": (0, 2**16 - 1), "int32": (-(2**31), 2**31 - 1), "uint32": (0, 2**32 - 1)}
_REAL_MAX = {"real32": 3.4028234663852886e38, "real64": 1.7976931348623157e308}


def file_name_part(name: str) -> str:
    """``name`` as a safe part of a file name: letters, digits, ``_``, ``-`` and single dots
    (anything else becomes ``_``), no leading dot, at most 64 characters (a drive description's
    name goes into ``controller-<name>.yaml``, and must not reach outside the output folder)."""
    safe = re.sub(r"[^A-Za-z0-9._-]|\.{2,}", "_", str(name))
    safe = re.sub(r"_{2,}", "_", safe).strip("._")[:64]
    return safe or "drive"


# --------------------------------------------------------------------------------------------
# generic controller.json
# --------------------------------------------------------------------------------------------
def controller_json(settings: ControllerSettings, verification: Any | None = None) -> dict[str, Any]:
    """The generic document (SI values, engineering units beside them)."""
    s = settings
    ready = bool(s.meets_margins and (verification is None or verification.ready))
    reasons: list[str] = []
    pm, gm = s.required_phase_margin_deg, s.required_gain_margin_db
    if not (s.margins.meets(pm, gm) and (s.margins_gap is None or s.margins_gap.meets(pm, gm))):
        reasons.append("the settings do not meet the required margins on the identified model")
    if s.robust is not None:
        reasons += s.robust.reasons()
    if verification is not None:
        reasons += list(verification.reasons)
    doc: dict[str, Any] = {
        "preset": s.preset.value,
        "sample_rate_hz": s.sample_rate_hz,
        "inertia": {"motor_kg_m2": s.motor_inertia_kg_m2, "load_kg_m2": s.load_inertia_kg_m2,
                    "ratio": s.inertia_ratio, "ratio_pct": 100.0 * s.inertia_ratio},
        "velocity_loop": {
            "gain": s.velocity_gain, "gain_unit": "N·m·s/rad",
            "integral_gain": s.velocity_integral_gain,
            "integral_time_s": s.velocity_integral_time_s, "integral_time_ms": 1e3 * s.velocity_integral_time_s,
            "bandwidth_hz": s.velocity_bandwidth_hz,
            "crossover_hz": _f(s.margins.crossover_hz),
            "loop_gain_hz": s.velocity_loop_gain_hz,
        },
        "position_loop": {"gain_per_s": s.position_gain_per_s,
                          "bandwidth_hz": s.position_gain_per_s / (2.0 * math.pi),
                          "reference_filter_time_constant_s": s.reference_filter_time_constant_s,
                          "reference_filter_time_constant_ms": 1e3 * s.reference_filter_time_constant_s,
                          "margins": None if s.position_margins is None else s.position_margins.as_dict()},
        "torque_filter": {"time_constant_s": s.torque_filter_time_constant_s,
                          "time_constant_ms": 1e3 * s.torque_filter_time_constant_s,
                          "corner_hz": (1.0 / (2.0 * math.pi * s.torque_filter_time_constant_s)
                                        if s.torque_filter_time_constant_s > 0 else None)},
        "notch": [{"frequency_hz": n.frequency_hz, "q": n.q, "depth_db": n.depth_db, "depth": n.depth}
                  for n in s.notches],
        "feedforward": {"velocity": s.velocity_feedforward, "velocity_pct": 100.0 * s.velocity_feedforward,
                        "torque": s.torque_feedforward, "torque_pct": 100.0 * s.torque_feedforward,
                        "torque_inertia_kg_m2": s.total_inertia_kg_m2},
        "backlash_compensation": {
            "enabled": s.backlash.enabled, "amount_rad": s.backlash.amount_rad,
            "amount_deg": math.degrees(s.backlash.amount_rad),
            "amount_arcmin": 60.0 * math.degrees(s.backlash.amount_rad),
            "direction": s.backlash.direction, "time_constant_s": s.backlash.time_constant_s,
            "epsilon_rad": s.epsilon_rad,
        },
        "margins": {**s.margins.as_dict(),
                    "required_phase_margin_deg": s.required_phase_margin_deg,
                    "required_gain_margin_db": s.required_gain_margin_db,
                    "gap": None if s.margins_gap is None else s.margins_gap.as_dict(),
                    "model": "identified, contact (gap: motor alone)"},
        "robust": None if s.robust is None else s.robust.as_dict(),
        "bandwidth_limit": None if s.limit is None else s.limit.as_dict(),
        "measured_band": {"band_hz": None if s.measured_band_hz is None else list(s.measured_band_hz),
                          "source": s.measured_band_source, "crossover_limit_hz": s.crossover_limit_hz,
                          "crossover_hz": _f(s.margins.crossover_hz),
                          "inside": (s.crossover_limit_hz is None or not math.isfinite(s.margins.crossover_hz)
                                     or s.margins.crossover_hz <= s.crossover_limit_hz * (1.0 + 1e-6))},
        "drive_model": {"current_loop_bandwidth_hz": s.current_loop_bandwidth_hz,
                        "loop_delay_samples": s.loop_delay_samples,
                        "position_loop_delay_samples": s.position_loop_delay_samples,
                        **({} if s.dynamics is None else {"sources": s.dynamics.as_dict()})},
        "modes": {"f_resonance_hz": _f(s.resonance_hz), "f_antiresonance_hz": _f(s.antiresonance_hz)},
        "design": {"candidates": list(s.candidates), "notes": list(s.notes)},
        "verification": {"ready": ready, "reasons": reasons},
    }
    if verification is not None:
        doc["verification"].update({k: v for k, v in verification.as_dict().items() if k not in ("ready", "reasons")})
    return doc


def _f(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


# --------------------------------------------------------------------------------------------
# drive parameter map
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ParameterValue:
    """One drive parameter to write: value in the parameter's unit, raw bus value, range check."""

    name: str
    value: float
    """After rounding to the raw resolution and clamping, in ``unit``."""
    unit: str
    raw: float
    requested: float
    """The tuning value before clamping, in ``unit``."""
    clamped: bool
    object: str
    min_value: float | None = None
    max_value: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "value": self.value, "unit": self.unit, "raw": self.raw,
                "requested": self.requested, "clamped": self.clamped, "object": self.object,
                "min": self.min_value, "max": self.max_value}


def _si_values(s: ControllerSettings, reference_units_per_rev: float) -> dict[str, tuple[float, str]]:
    """Tuning values by description parameter name: (value, SI unit kind)."""
    notch_bits = (1 if len(s.notches) >= 1 else 0) | (0x0100 if len(s.notches) >= 2 else 0)
    out: dict[str, tuple[float, str]] = {
        "velocity_kp": (s.velocity_gain, "N·m·s/rad"),
        "velocity_ki": (s.velocity_integral_gain, "N·m/rad"),
        "speed_loop_gain": (s.velocity_loop_gain_hz, "Hz"),
        "speed_loop_integral_time": (s.velocity_integral_time_s, "s"),
        "position_loop_gain": (s.position_gain_per_s, "1/s"),
        "inertia_ratio": (s.inertia_ratio, "fraction"),
        "torque_filter_time": (s.torque_filter_time_constant_s, "s"),
        "velocity_feedforward": (s.velocity_feedforward, "fraction"),
        "torque_feedforward": (s.torque_feedforward, "fraction"),
        "backlash_compensation_direction": (0.0 if s.backlash.direction == "forward" else 1.0, "count"),
        "backlash_compensation": (s.backlash.amount_rad, "rad"),
        "backlash_compensation_time": (s.backlash.time_constant_s, "s"),
        "position_reference_filter_time": (s.reference_filter_time_constant_s, "s"),
    }
    if s.notches:  # without a notch the drive's notch settings are left alone (it may have its own)
        out["notch_switches"] = (float(notch_bits), "count")
    for i, n in enumerate(s.notches[:2], start=1):
        out[f"notch{i}_frequency"] = (n.frequency_hz, "Hz")
        out[f"notch{i}_q"] = (n.q, "count")
        out[f"notch{i}_depth"] = (n.depth, "count")
    out["_reference_units_per_rad"] = (reference_units_per_rev / (2.0 * math.pi), "")
    return out


def _convert(value: float, kind: str, unit: str, ref_per_rad: float, name: str) -> float:
    u = unit.strip()
    if kind == "s":
        factors = {"s": 1.0, "ms": 1e3, "us": 1e6, "µs": 1e6}
    elif kind == "fraction":
        factors = {"%": 100.0, "": 1.0, "-": 1.0}
    elif kind == "rad":
        factors = {"rad": 1.0, "deg": 180.0 / math.pi, "reference unit": ref_per_rad, "increment": ref_per_rad}
    elif kind == "count":
        factors = {"": 1.0, "-": 1.0}
    else:
        factors = {kind: 1.0}
    if u not in factors:
        raise TuningError(f"parameter '{name}': cannot express {kind} in the description's unit '{unit}'")
    return value * factors[u]


def drive_parameters(settings: ControllerSettings, description: Any, *,
                     reference_units_per_rev: float = 2.0**24) -> list[ParameterValue]:
    """The settings through ``description.parameters`` (a :class:`DriveDescription`).

    Parameters the tuning has no value for are skipped, and so are all notch entries when no
    notch is used (a notch the drive already has, e.g. for a resonance above the identified
    band, is left alone). ``reference_units_per_rev``: position reference units per motor revolution
    (YASKAWA: set by the electronic gear; default a 24-bit encoder with gear 1:1).
    """
    values = _si_values(settings, reference_units_per_rev)
    ref_per_rad = values.pop("_reference_units_per_rad")[0]
    out: list[ParameterValue] = []
    for name, spec in description.parameters.items():
        if name not in values:
            continue
        si, kind = values[name]
        requested = _convert(si, kind, spec.unit, ref_per_rad, name)
        raw = requested / spec.scale
        if spec.type in _INT_TYPES:
            raw = float(round(raw))
        clamped = False
        if spec.min is not None and raw < spec.min:
            raw, clamped = float(spec.min), True
        if spec.max is not None and raw > spec.max:
            raw, clamped = float(spec.max), True
        out.append(ParameterValue(name=name, value=raw * spec.scale, unit=spec.unit, raw=raw, requested=requested,
                                  clamped=clamped, object=str(spec.object),
                                  min_value=None if spec.min is None else spec.min * spec.scale,
                                  max_value=None if spec.max is None else spec.max * spec.scale))
    return out


def write_controller_files(out_dir: str | Path, settings: ControllerSettings, verification: Any | None,
                           description: Any | None, *, reference_units_per_rev: float = 2.0**24) -> list[Path]:
    """Write ``controller.json`` and, with a description, ``controller-<drive>.yaml`` into out_dir."""
    folder = Path(out_dir)
    doc = controller_json(settings, verification)
    paths = []
    try:
        folder.mkdir(parents=True, exist_ok=True)
        p = folder / "controller.json"
        p.write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        paths.append(p)
        if description is not None:
            params = drive_parameters(settings, description, reference_units_per_rev=reference_units_per_rev)
            clamped = [v.name for v in params if v.clamped]
            ydoc = {
                "drive": description.name,
                "ready": doc["verification"]["ready"] and not clamped,
                "clamped": clamped,
                "note": "values in each parameter's own unit; raw = value / scale; clamped values must be "
                        "reviewed (commission --apply refuses them)",
                "parameters": [v.as_dict() for v in params],
            }
            py = folder / f"controller-{file_name_part(description.name)}.yaml"
            py.write_text(yaml.safe_dump(ydoc, sort_keys=False, allow_unicode=True), encoding="utf-8")
            paths.append(py)
    except OSError as err:
        raise OutputError(f"cannot write the controller files to {folder}: {err.strerror}") from err
    return paths


# --------------------------------------------------------------------------------------------
# write-back
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ApplyReport:
    """What :func:`apply` did."""

    applied: bool
    old: dict[str, float]
    written: dict[str, float]
    read_back: dict[str, float]
    stored: bool


Log = Callable[[str, Mapping[str, Any]], None]


def _close(a: float, b: float, spec: Any) -> bool:
    tol = 0.5 * spec.scale if spec.type in _INT_TYPES else 1e-6 * max(abs(a), abs(b), 1e-12) + 1e-12
    return abs(a - b) <= tol


def apply(drive: Any, parameters: Sequence[ParameterValue], *, yes: bool = False,
          confirm: Callable[[str], bool] | None = None, store: bool = False, log: Log | None = None,
          echo: Callable[[str], None] = print) -> ApplyReport:
    """Write ``parameters`` to ``drive`` (a :class:`~commission.drive.base.Drive`).

    :param yes: do not ask. Otherwise ``confirm(question)`` must return True (None: refuse).
    :param store: afterwards write "save" to the description's ``store_parameters`` (0x1010:01).
    :param log: ``writer.add_result`` of the run's MCAP log: the old values, every write and the
        store are logged on :data:`PARAMETER_TOPIC` before they happen.
    :raises TuningError: a value was clamped to the parameter's range (nothing is written), or
        the drive cannot store.
    :raises DriveError: a write failed or a read-back differs (the writes before it stay; the log
        has the old values for ``--restore-from``).
    """
    bad = [p for p in parameters if p.clamped]
    if bad:
        raise TuningError("refusing to apply: " + "; ".join(
            f"{p.name} = {p.requested:g} {p.unit} outside {p.min_value:g}…{p.max_value:g}"
            if p.min_value is not None and p.max_value is not None else f"{p.name} = {p.requested:g} {p.unit} out of range"
            for p in bad))
    description = getattr(drive, "description", None)
    if store and (description is None or STORE_PARAMETER not in description.parameters):
        raise TuningError(f"the drive description has no '{STORE_PARAMETER}' object: cannot store to "
                          "non-volatile memory")
    old = {p.name: float(drive.read_parameter(p.name)) for p in parameters}
    echo(f"{'parameter':34s} {'old':>14s} → {'new':>14s}  unit")
    for p in parameters:
        echo(f"{p.name:34s} {old[p.name]:14.6g} → {p.value:14.6g}  {p.unit}")
    if not yes and not (confirm is not None and confirm(f"write {len(parameters)} parameters to the drive?")):
        echo("nothing written")
        return ApplyReport(applied=False, old=old, written={}, read_back={}, stored=False)

    def _log(payload: dict[str, Any]) -> None:
        if log is not None:
            log(PARAMETER_TOPIC, payload)

    drive_name = getattr(description, "name", type(drive).__name__)
    _log({"event": "old_values", "drive": drive_name,
          "values": [{"name": p.name, "value": old[p.name], "unit": p.unit, "object": p.object} for p in parameters]})
    back = write_values(drive, parameters, old=old, log=log, drive_name=drive_name)
    written = {p.name: p.value for p in parameters}
    stored = False
    if store:
        _log({"event": "store", "drive": drive_name, "object": str(description.parameters[STORE_PARAMETER].object)})
        drive.write_parameter(STORE_PARAMETER, STORE_SIGNATURE)
        stored = True
    echo(f"{len(written)} parameters written and verified" + ("; stored to non-volatile memory" if stored else ""))
    return ApplyReport(applied=True, old=old, written=written, read_back=back, stored=stored)


def write_values(drive: Any, parameters: Sequence[ParameterValue], *, old: Mapping[str, float], log: Log | None,
                 drive_name: str) -> dict[str, float]:
    """Write each value, read it back and compare, logging every write and read-back on
    :data:`PARAMETER_TOPIC`; returns the values read back.

    :raises DriveError: a read-back differs (the writes before it stay).
    """
    description = getattr(drive, "description", None)
    back: dict[str, float] = {}
    for p in parameters:
        if log is not None:
            log(PARAMETER_TOPIC, {"event": "write", "drive": drive_name, "name": p.name, "value": p.value,
                                  "unit": p.unit, "raw": p.raw, "object": p.object, "old": old.get(p.name)})
        drive.write_parameter(p.name, p.value)
        got = float(drive.read_parameter(p.name))
        back[p.name] = got
        spec = description.parameters.get(p.name) if description is not None else None
        ok = _close(got, p.value, spec) if spec is not None else math.isclose(got, p.value, rel_tol=1e-6)
        if log is not None:
            log(PARAMETER_TOPIC, {"event": "read_back", "drive": drive_name, "name": p.name, "value": got, "ok": ok})
        if not ok:
            raise DriveError(f"{p.name}: wrote {p.value:g} {p.unit}, read back {got:g}")
    return back


def restore_values(results: Mapping[str, Sequence[Mapping[str, Any]]] | str | Path,
                   description: Any) -> list[ParameterValue]:
    """The old values logged by :func:`apply` (the first ``old_values`` event), as parameters to write.

    ``results``: ``commission.mcaplog.read_results(path)`` or the path itself. Every value is
    checked as a tuning value would be, before anything is written: a parameter the description
    has (not the store command), in its unit, a finite number, an integer for integer objects,
    within the type's range and the description's ``min``/``max``.

    :raises LogFormatError: the log's entry is malformed (not a list of name/value objects).
    :raises TuningError: a value is outside what the description allows (nothing is written).
    """
    if isinstance(results, (str, Path)):
        from ..mcaplog import read_results

        results = read_results(results)
    events = [e for e in results.get(PARAMETER_TOPIC, []) if isinstance(e, Mapping) and e.get("event") == "old_values"]
    if not events:
        raise TuningError(f"the log has no old parameter values on {PARAMETER_TOPIC}: nothing to restore")
    items = events[0].get("values")
    if not isinstance(items, list) or not items:
        raise LogFormatError(f"the log's old parameter values on {PARAMETER_TOPIC} are not a list of values")
    out: list[ParameterValue] = []
    problems: list[str] = []
    for item in items:
        name = item.get("name") if isinstance(item, Mapping) else None
        value = item.get("value") if isinstance(item, Mapping) else None
        if not isinstance(name, str) or type(value) not in (int, float):
            raise LogFormatError(f"the log's old parameter values on {PARAMETER_TOPIC}: entry {str(item)[:80]!r} "
                                 "is not a name with a number")
        if name == STORE_PARAMETER or any(p.name == name for p in out):
            raise LogFormatError(f"the log's old parameter values on {PARAMETER_TOPIC} list '{name}' "
                                 + ("twice" if name != STORE_PARAMETER else "(a command, not a setting)"))
        spec = description.parameter(name)
        problem = _restore_problem(name, float(value), item.get("unit", spec.unit), spec)
        if problem:
            problems.append(problem)
            continue
        out.append(ParameterValue(name=name, value=float(value), unit=spec.unit, raw=float(value) / spec.scale,
                                  requested=float(value), clamped=False, object=str(spec.object),
                                  min_value=None if spec.min is None else spec.min * spec.scale,
                                  max_value=None if spec.max is None else spec.max * spec.scale))
    if problems:
        raise TuningError("refusing to restore, nothing written: " + "; ".join(problems))
    return out


def _restore_problem(name: str, value: float, unit: Any, spec: Any) -> str | None:
    """Why ``value`` (in ``unit``) cannot be written to ``spec``; None when it can."""
    if unit != spec.unit:
        return f"{name} is logged in {unit!r}, the drive description says {spec.unit!r}"
    if not math.isfinite(value):
        return f"{name} = {value} is not a finite number"
    raw = value / spec.scale
    if spec.type in _INT_TYPES:
        if abs(raw - round(raw)) > 1e-6 * max(1.0, abs(raw)):
            return f"{name} = {value:g} {spec.unit} is not a whole number of its unit ({spec.scale:g})"
        lo, hi = _INT_RANGES[spec.type]
        if not lo <= round(raw) <= hi:
            return f"{name} = {value:g} {spec.unit} is outside the range of {spec.type}"
    elif abs(raw) > _REAL_MAX.get(spec.type, math.inf):
        return f"{name} = {value:g} {spec.unit} is outside the range of {spec.type}"
    if (spec.min is not None and raw < spec.min) or (spec.max is not None and raw > spec.max):
        lo = "-∞" if spec.min is None else f"{spec.min * spec.scale:g}"
        hi = "∞" if spec.max is None else f"{spec.max * spec.scale:g}"
        return f"{name} = {value:g} {spec.unit} outside {lo}…{hi}"
    return None
