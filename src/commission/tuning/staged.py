"""Staged write-back (``--apply``), as commercial tuners do it: a conservative set first, a
short closed-loop check on the drive, then the final set and the same check; oscillation puts
the previous values back on the spot.

The check is a velocity reference 0 → +v → −v → 0 (a step and a reversal) that the drive
follows with its own loop while it records its trace (or the host its feedback): the caller
passes ``check(reference) -> Recording`` — the sequencer's, which owns the safety envelope,
the enable and the stop. :func:`judge_check` reads, after each step, the velocity overshoot,
an oscillation of the velocity in the second half of each level (detrended, smoothed over 1 ms
against the encoder's quantisation) and the torque reference's ripple there (vibration).

Every value is logged on the run's ``/parameters`` topic like :func:`.export.apply` (the old
values first, so ``--restore-from`` works after any stage), every stage, check and restore too.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..exceptions import CommissionError
from ..recording import Recording
from .export import PARAMETER_TOPIC, STORE_PARAMETER, STORE_SIGNATURE, ParameterValue, TuningError, write_values
from .scenarios import moving_average
from .settings import ControllerSettings, TuningOptions

__all__ = ["CheckResult", "StagedApplyReport", "apply_staged", "check_reference", "conservative_settings",
           "judge_check"]

#: Lead-in of the check's reference at zero velocity [s].
_LEAD_IN_S = 0.05
#: Smoothing of the measured velocity against the encoder's quantisation [s].
_SMOOTH_S = 1e-3
#: Window of the torque ripple's moving average [s].
_RIPPLE_S = 2e-3

Log = Callable[[str, Mapping[str, Any]], None]
Check = Callable[[NDArray[np.float64]], Recording]


def conservative_settings(settings: ControllerSettings, fraction: float) -> ControllerSettings:
    """The first stage: velocity and position gains × ``fraction``, integral time ÷ ``fraction``,
    no backlash compensation (filters and notches as designed: they are there for stability)."""
    s = settings.without_backlash_compensation()
    return replace(s, velocity_gain=fraction * s.velocity_gain,
                   velocity_integral_time_s=s.velocity_integral_time_s / fraction,
                   position_gain_per_s=fraction * s.position_gain_per_s)


def check_reference(options: TuningOptions, sample_rate_hz: float) -> NDArray[np.float64]:
    """The check's velocity reference [rad/s]: a lead-in at 0, then 0 → +v → −v → 0 for
    ``apply_check_segment_s`` each (v = ``velocity_step_rad_s``)."""
    n0 = int(round(_LEAD_IN_S * sample_rate_hz))
    n = int(round(options.apply_check_segment_s * sample_rate_hz))
    v = options.velocity_step_rad_s
    return np.concatenate([np.zeros(n0), np.full(n, v), np.full(n, -v), np.zeros(n)])


@dataclass(frozen=True)
class CheckResult:
    """What the closed-loop check on the drive saw."""

    stage: str
    ok: bool
    overshoot_pct: float
    """Largest velocity overshoot after a step of the reference [%]."""
    oscillation: float
    """Largest half peak-to-peak of the velocity error in the second half of a level, ÷ v [-]."""
    oscillation_hz: float | None
    vibration: float
    """Largest RMS torque ripple in the second half of a level, ÷ the torque limit [-]."""
    reasons: tuple[str, ...]

    def as_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "ok": self.ok, "overshoot_pct": self.overshoot_pct,
                "oscillation": self.oscillation, "oscillation_hz": self.oscillation_hz,
                "vibration": self.vibration, "reasons": list(self.reasons)}


def judge_check(recording: Recording, reference: NDArray[np.float64], options: TuningOptions,
                torque_limit_nm: float, stage: str) -> CheckResult:
    """Overshoot, oscillation and vibration of the drive's response to ``reference``."""
    fs = recording.sample_rate_hz
    n = min(len(recording), reference.size)
    v = np.asarray(recording.motor_velocity[:n], dtype=float)
    u = np.asarray(recording.torque_ref[:n], dtype=float)
    r = np.asarray(reference[:n], dtype=float)
    y = moving_average(v, max(1, int(round(_SMOOTH_S * fs))))
    starts = np.flatnonzero(np.diff(r) != 0.0) + 1
    ends = np.r_[starts[1:], n]
    amp_ref = max(float(np.max(np.abs(r))), 1e-12)
    overshoot, osc, osc_hz, vib = 0.0, 0.0, None, 0.0
    k_rip = max(1, int(round(_RIPPLE_S * fs)))
    for a, b in zip(starts, ends):
        if b - a < 8:
            continue
        step = r[a] - r[a - 1]
        target = r[a]
        over = float(np.max((v[a:b] - target) * math.copysign(1.0, step))) / abs(step) * 100.0
        overshoot = max(overshoot, over)
        h = a + (b - a) // 2
        e = y[h:b] - target
        k = np.arange(e.size)
        e = e - np.polyval(np.polyfit(k, e, 1), k) if e.size > 2 else e - e.mean()
        amp = 0.5 * float(np.max(e) - np.min(e)) / amp_ref
        if amp > osc:
            crossings = np.flatnonzero(np.sign(e[:-1]) * np.sign(e[1:]) < 0)
            osc = amp
            osc_hz = (0.5 * (crossings.size - 1) * fs / float(crossings[-1] - crossings[0])
                      if crossings.size >= 4 else None)
        ripple = u[h:b] - moving_average(u[h:b], k_rip)
        vib = max(vib, float(np.sqrt(np.mean(ripple * ripple))) / torque_limit_nm)
    reasons = []
    if overshoot > options.apply_check_max_overshoot_pct:
        reasons.append(f"overshoot {overshoot:.0f} % > {options.apply_check_max_overshoot_pct:g} %")
    if osc > options.apply_check_max_oscillation:
        reasons.append(f"oscillation {100 * osc:.1f} % of the step" + (f" at {osc_hz:.0f} Hz" if osc_hz else "")
                       + f" > {100 * options.apply_check_max_oscillation:g} %")
    if vib > options.apply_check_max_vibration:
        reasons.append(f"vibration: torque ripple {100 * vib:.1f} % of the torque limit > "
                       f"{100 * options.apply_check_max_vibration:g} %")
    return CheckResult(stage, not reasons, overshoot, osc, osc_hz, vib, tuple(reasons))


def _in_fault(drive: Any) -> bool:
    return getattr(getattr(drive, "state", None), "name", "") == "FAULT"


def _acknowledge_fault(drive: Any, yes: bool, confirm: Callable[[str], bool] | None,
                       echo: Callable[[str], None]) -> bool:
    """The checks enable the drive: a drive found in Fault (e.g. its heartbeat consumer tripped
    while the host was busy identifying, the axis disabled) is acknowledged only with the
    operator's consent (``yes`` or the prompt); if the cause persists the drive faults again
    in the check and the previous values go back. Returns whether a fault was acknowledged.

    :raises TuningError: no consent, or the fault does not clear (nothing written).
    """
    if not _in_fault(drive):
        return False
    question = "the drive is in Fault: acknowledge the fault and go on with the staged write?"
    if not (yes or (confirm is not None and confirm(question))):
        raise TuningError("the drive is in Fault: find the cause, acknowledge it, then apply again; nothing written")
    drive.fault_reset()
    if _in_fault(drive):
        raise TuningError("the drive stays in Fault after the acknowledgement: find the cause; nothing written")
    echo("the drive was in Fault: acknowledged")
    return True


@dataclass(frozen=True)
class StagedApplyReport:
    """What :func:`apply_staged` did."""

    applied: bool
    """The final set is on the drive (and passed its check)."""
    restored: bool
    """A check failed and the previous values were written back."""
    old: dict[str, float]
    written: dict[str, float]
    """The last values written before any restore."""
    checks: tuple[CheckResult, ...]
    stored: bool
    reason: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {"applied": self.applied, "restored": self.restored, "written": self.written,
                "checks": [c.as_dict() for c in self.checks], "stored": self.stored, "reason": self.reason}


def apply_staged(drive: Any, conservative: Sequence[ParameterValue], final: Sequence[ParameterValue],
                 check: Check, options: TuningOptions, *, torque_limit_nm: float, sample_rate_hz: float,
                 yes: bool = False,
                 confirm: Callable[[str], bool] | None = None, store: bool = False, log: Log | None = None,
                 echo: Callable[[str], None] = print) -> StagedApplyReport:
    """Write ``conservative``, check, write ``final``, check; on a failed check (or an error during
    it) write the previous values back at once and say so.

    :param check: runs the closed-loop check on the drive with a velocity reference and returns
        its record (the sequencer's: envelope, enable, stop, log).
    :param torque_limit_nm: the torque limit the drive runs the check with (the vibration's scale).
    :param sample_rate_hz: the rate ``check`` plays its reference at [Hz].
    :raises TuningError: a value was clamped (nothing written), or the drive cannot store.
    """
    for stage in (conservative, final):
        bad = [p for p in stage if p.clamped]
        if bad:
            raise TuningError("refusing to apply: " + "; ".join(f"{p.name} = {p.requested:g} {p.unit} out of range"
                                                               for p in bad))
    description = getattr(drive, "description", None)
    if store and (description is None or STORE_PARAMETER not in description.parameters):
        raise TuningError(f"the drive description has no '{STORE_PARAMETER}' object: cannot store to "
                          "non-volatile memory")
    acknowledged = _acknowledge_fault(drive, yes, confirm, echo)
    names = list(dict.fromkeys([p.name for p in conservative] + [p.name for p in final]))
    units = {p.name: (p.unit, p.object) for p in [*conservative, *final]}
    old = {n: float(drive.read_parameter(n)) for n in names}
    first = {p.name: p.value for p in conservative}
    last = {p.name: p.value for p in final}
    echo(f"{'parameter':34s} {'old':>12s} → {'stage 1':>12s} → {'final':>12s}  unit")
    for n in names:
        echo(f"{n:34s} {old[n]:12.6g} → {first.get(n, old[n]):12.6g} → {last.get(n, old[n]):12.6g}  {units[n][0]}")
    if not yes and not (confirm is not None and confirm(
            f"write {len(names)} parameters in two stages, each checked with a step and a reversal?")):
        echo("nothing written")
        return StagedApplyReport(False, False, old, {}, (), False, "not confirmed")

    def _log(payload: dict[str, Any]) -> None:
        if log is not None:
            log(PARAMETER_TOPIC, payload)

    drive_name = getattr(description, "name", type(drive).__name__)
    _log({"event": "old_values", "drive": drive_name,
          "values": [{"name": n, "value": old[n], "unit": units[n][0], "object": units[n][1]} for n in names]})
    if acknowledged:
        _log({"event": "fault_reset", "drive": drive_name, "reason": "in Fault before the staged write"})
    reference = check_reference(options, sample_rate_hz)
    written: dict[str, float] = {}
    checks: list[CheckResult] = []

    def restore(why: str) -> StagedApplyReport:
        _log({"event": "restore", "drive": drive_name, "reason": why})
        scale = {n: description.parameters[n].scale if description is not None and n in description.parameters
                 else 1.0 for n in names}
        back = [ParameterValue(name=n, value=old[n], unit=units[n][0], raw=old[n] / scale[n], requested=old[n],
                               clamped=False, object=units[n][1]) for n in names if n in written]
        write_values(drive, back, old=written, log=log, drive_name=drive_name)
        echo(f"check failed ({why}): the previous values of {len(back)} parameters are back on the drive")
        return StagedApplyReport(False, True, old, dict(written), tuple(checks), False, why)

    for label, params in (("conservative", conservative), ("final", final)):
        _log({"event": "stage", "drive": drive_name, "stage": label})
        write_values(drive, params, old={**old, **written}, log=log, drive_name=drive_name)
        written.update({p.name: p.value for p in params})
        try:
            record = check(reference)
        except (CommissionError, KeyboardInterrupt) as err:
            report = restore(f"{label} set: the check ended with {type(err).__name__}: {err}")
            if isinstance(err, KeyboardInterrupt):
                raise
            raise TuningError(f"{report.reason}; previous values restored") from err
        result = judge_check(record, reference, options, torque_limit_nm, label)
        checks.append(result)
        _log({"event": "check", "drive": drive_name, **result.as_dict()})
        echo(f"{label} set: overshoot {result.overshoot_pct:.0f} %, oscillation {100 * result.oscillation:.1f} %, "
             f"torque ripple {100 * result.vibration:.1f} % → " + ("ok" if result.ok else "; ".join(result.reasons)))
        if not result.ok:
            return restore(f"{label} set: " + "; ".join(result.reasons))
    stored = False
    if store:
        _log({"event": "store", "drive": drive_name, "object": str(description.parameters[STORE_PARAMETER].object)})
        drive.write_parameter(STORE_PARAMETER, STORE_SIGNATURE)
        stored = True
    echo(f"{len(written)} parameters written in two stages, each checked on the drive"
         + ("; stored to non-volatile memory" if stored else ""))
    return StagedApplyReport(True, False, old, written, tuple(checks), stored)
