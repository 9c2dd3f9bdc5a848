"""Closed-loop verification of controller settings on a plant *with* backlash, at the drive's clock.

The scenarios of :mod:`.scenarios` (velocity step, position step, smooth move, reversals),
each run with the proposed settings, without the notch (if any) and without the backlash
compensation (if any). Margins are computed on the plant's linear model (contact) and on the
motor alone (gap) with the loop of :mod:`.loop`, with the plant's own current loop and delay.
``ready`` is False, with the reasons, when a margin fails or the load limit-cycles above
``max_limit_cycle_rad``, and on a real axis also when the identification is approximate.

The plant is never the design model itself, so that a design that holds only on its own
assumptions is caught:

* on a ``--sim`` run, the simulator's true machine (the caller knows it ran one); when its
  drive is ideal (no current-loop lag, no delay), the verification adds
  ``verification_current_loop_bandwidth_hz`` and ``verification_delay_samples`` (a 1 kHz
  current loop and 2 samples by default, the slow corner of an unknown drive's set);
* on a real axis, the identified model (with the friction it kept and its backlash) as the
  uncertainty set's worst member for the phase margin: its J_l, K, current loop and delay
  (rounded up to whole samples). An approximate identification's model does not describe the
  record, so a pass on it is no evidence about the machine: never ready.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import math

from threadpoolctl import threadpool_limits

from ..ident.twomass import TwoMassParameters
from ..plant import PlantParameters
from .loop import loop_margins
from .robust import member_plant
from .scenarios import SCENARIOS, ScenarioResult, plant_from_model, run_scenario
from .settings import ControllerSettings, LoopMargins, TuningOptions, UncertaintyMember

__all__ = ["APPROXIMATE_MODEL", "ScenarioResult", "Verification", "verify"]

#: The reason a check on an approximate identification's own model does not make the settings ready.
APPROXIMATE_MODEL = "the identification is approximate: the check ran on a model that does not describe the record"


@dataclass(frozen=True)
class Verification:
    """Margins on the verification plant and the closed-loop runs; ``ready`` and why not."""

    margins: LoopMargins
    margins_gap: LoopMargins | None
    position_margins: LoopMargins
    """Of the position loop around the closed velocity loop, on the verification plant (contact)."""
    runs: dict[str, dict[str, ScenarioResult]]
    """configuration ("proposed", "without_notch", "without_backlash_compensation") → scenario → result."""
    ready: bool
    reasons: tuple[str, ...]
    plant: PlantParameters
    """The plant the runs and the margins are on."""
    plant_note: str = ""
    """How that plant differs from the design model."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "ready": bool(self.ready),
            "reasons": list(self.reasons),
            "margins": self.margins.as_dict(),
            "margins_gap": None if self.margins_gap is None else self.margins_gap.as_dict(),
            "position_margins": self.position_margins.as_dict(),
            "plant": {**self.plant.two_mass.as_dict(), "epsilon_rad": self.plant.epsilon_rad,
                      "current_loop_bandwidth_hz": self.plant.current_loop_bandwidth_hz,
                      "delay_samples": self.plant.delay_samples, "note": self.plant_note},
            "runs": {cfg: {sc: r.as_dict() for sc, r in runs.items()} for cfg, runs in self.runs.items()},
        }


def verification_plant(settings: ControllerSettings, plant: PlantParameters | TwoMassParameters | Any,
                       options: TuningOptions, epsilon_rad: float | None = None) -> tuple[PlantParameters, str]:
    """The plant to verify ``settings`` on, and how it differs from the design model (module docstring)."""
    if isinstance(plant, PlantParameters):
        cl = options.verification_current_loop_bandwidth_hz
        if plant.current_loop_bandwidth_hz is None and plant.delay_samples == 0 and cl is not None:
            d = options.verification_delay_samples
            return (plant.model_copy(update={"current_loop_bandwidth_hz": cl, "delay_samples": d}),
                    f"the simulated machine, its ideal drive given a {cl:g} Hz current loop and {d} samples of delay")
        return plant, "the simulated machine with its own drive"
    if isinstance(plant, TwoMassParameters) or isinstance(getattr(plant, "parameters", None), TwoMassParameters):
        eps = epsilon_rad if epsilon_rad is not None else getattr(plant, "epsilon_rad", 0.0)
        m = settings.robust.phase_member if settings.robust is not None else UncertaintyMember()
        params = plant if isinstance(plant, TwoMassParameters) else plant.parameters
        cl = settings.current_loop_bandwidth_hz
        cl = None if cl is None else cl * m.current_loop_factor
        delay = int(math.ceil(settings.loop_delay_samples + m.extra_delay_samples - 1e-9))
        linear = member_plant(params, UncertaintyMember(1.0, 0.0, m.load_inertia_factor, m.stiffness_factor, False))
        return (plant_from_model(plant, float(eps or 0.0), cl, delay_samples=delay, parameters=linear),
                f"the identified model as the uncertainty set's worst member "
                f"({m.describe(settings.current_loop_bandwidth_hz)}; delay {delay} whole samples)")
    raise TypeError(f"verify() needs PlantParameters, an Identification or TwoMassParameters, "
                    f"got {type(plant).__name__}")


def verify(settings: ControllerSettings, plant: PlantParameters | TwoMassParameters | Any,
           options: TuningOptions | None = None, *, epsilon_rad: float | None = None,
           scenarios: tuple[str, ...] = SCENARIOS, compare: bool = True) -> Verification:
    """Verify ``settings`` on ``plant``: a :class:`~commission.plant.PlantParameters` (the true
    machine of a simulation), or on a real axis the identified model: an Identification (with
    the friction it kept) or a :class:`TwoMassParameters` with ``epsilon_rad``. Either way the
    plant is made to differ from the design model (module docstring)."""
    opt = options or TuningOptions()
    tp, note = verification_plant(settings, plant, opt, epsilon_rad)
    with threadpool_limits(1):
        v = _verify(settings, tp, note, opt, scenarios, compare)
    fit = getattr(plant, "fit", None)
    if getattr(fit, "approximate", False):
        # a check on a model that does not describe the record says nothing about the machine: settings
        # that pass it on a flagged identification are not to be written to a drive
        v = replace(v, ready=False, reasons=(*v.reasons, APPROXIMATE_MODEL))
    return v


def _verify(settings: ControllerSettings, tp: PlantParameters, note: str, opt: TuningOptions,
            scenarios: tuple[str, ...], compare: bool) -> Verification:
    # margins on the verification plant, with its own current loop and delay
    s_true = replace(settings, current_loop_bandwidth_hz=tp.current_loop_bandwidth_hz,
                     loop_delay_samples=float(tp.delay_samples))
    linear = tp.two_mass
    m = loop_margins(s_true, linear)
    mg = loop_margins(s_true, linear, gap=True) if tp.epsilon_rad > 0 else None
    mp = loop_margins(s_true, linear, loop="position")
    configs: dict[str, ControllerSettings] = {"proposed": settings}
    if compare and settings.notches:
        configs["without_notch"] = settings.without_notch()
    if compare and settings.backlash.enabled:
        configs["without_backlash_compensation"] = settings.without_backlash_compensation()
    runs = {name: {sc: run_scenario(tp, s, opt, sc) for sc in scenarios} for name, s in configs.items()}
    reasons: list[str] = []
    pm_req, gm_req = settings.required_phase_margin_deg, settings.required_gain_margin_db
    for label, mm in (("contact", m), ("gap", mg)):
        if mm is None:
            continue
        if not mm.stable:
            reasons.append(f"velocity loop unstable on the verification plant ({label})")
        if mm.phase_margin_deg < pm_req:
            reasons.append(f"phase margin {mm.phase_margin_deg:.1f}° < {pm_req:g}° on the verification plant ({label})")
        if mm.gain_margin_db < gm_req:
            reasons.append(f"gain margin {mm.gain_margin_db:.1f} dB < {gm_req:g} dB on the verification plant ({label})")
    if not mp.stable:
        reasons.append("position loop unstable on the verification plant")
    for sc, r in runs["proposed"].items():
        if sc != "velocity_step" and r.limit_cycle_amplitude > opt.max_limit_cycle_rad:
            reasons.append(f"{sc}: load limit cycle {r.limit_cycle_amplitude:.2e} rad > {opt.max_limit_cycle_rad:.2e} rad"
                           + (f" at {r.limit_cycle_frequency_hz:.1f} Hz" if r.limit_cycle_frequency_hz else ""))
        if r.settling_time_s is None and sc in ("velocity_step", "position_step"):
            reasons.append(f"{sc}: does not settle within the run")
    return Verification(margins=m, margins_gap=mg, position_margins=mp, runs=runs, ready=not reasons,
                        reasons=tuple(reasons), plant=tp, plant_note=note)
