"""Closed-loop verification of controller settings on a plant *with* backlash, at the drive's clock.

The scenarios of :mod:`.scenarios` (velocity step, position step, smooth move, reversals),
each run with the proposed settings, without the notch (if any) and without the backlash
compensation (if any). Margins are computed on the plant's linear model (contact) and on the
motor alone (gap) with the loop of :mod:`.loop`. ``ready`` is False, with the reasons, when a
margin fails or the load limit-cycles above ``max_limit_cycle_rad``.

The plant is the run's: the simulator's true machine on a ``--sim`` run (the caller knows it
ran one), on a real axis the identified model with its backlash.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from ..ident.twomass import TwoMassParameters
from ..plant import PlantParameters
from .loop import loop_margins
from .scenarios import SCENARIOS, ScenarioResult, plant_from_model, run_scenario
from .settings import ControllerSettings, LoopMargins, TuningOptions

__all__ = ["ScenarioResult", "Verification", "verify"]


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

    def as_dict(self) -> dict[str, Any]:
        return {
            "ready": bool(self.ready),
            "reasons": list(self.reasons),
            "margins": self.margins.as_dict(),
            "margins_gap": None if self.margins_gap is None else self.margins_gap.as_dict(),
            "position_margins": self.position_margins.as_dict(),
            "plant": {**self.plant.two_mass.as_dict(), "epsilon_rad": self.plant.epsilon_rad,
                      "current_loop_bandwidth_hz": self.plant.current_loop_bandwidth_hz},
            "runs": {cfg: {sc: r.as_dict() for sc, r in runs.items()} for cfg, runs in self.runs.items()},
        }


def verify(settings: ControllerSettings, plant: PlantParameters | TwoMassParameters | Any,
           options: TuningOptions | None = None, *, epsilon_rad: float | None = None,
           scenarios: tuple[str, ...] = SCENARIOS, compare: bool = True) -> Verification:
    """Verify ``settings`` on ``plant``: a :class:`~commission.plant.PlantParameters` (the true
    machine of a simulation), or on a real axis the identified model: an Identification (with
    the friction it kept) or a :class:`TwoMassParameters` with ``epsilon_rad``. The model's
    current loop is the one the settings were designed for."""
    opt = options or TuningOptions()
    if isinstance(plant, PlantParameters):
        tp = plant
    elif isinstance(plant, TwoMassParameters) or isinstance(getattr(plant, "parameters", None), TwoMassParameters):
        eps = epsilon_rad if epsilon_rad is not None else getattr(plant, "epsilon_rad", 0.0)
        tp = plant_from_model(plant, float(eps or 0.0), settings.current_loop_bandwidth_hz)
    else:
        raise TypeError(f"verify() needs PlantParameters, an Identification or TwoMassParameters, "
                        f"got {type(plant).__name__}")
    # margins on the verification plant, with its own current loop
    s_true = replace(settings, current_loop_bandwidth_hz=tp.current_loop_bandwidth_hz)
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
            reasons.append(f"phase margin {mm.phase_margin_deg:.1f}° < {pm_req:g}° ({label})")
        if mm.gain_margin_db < gm_req:
            reasons.append(f"gain margin {mm.gain_margin_db:.1f} dB < {gm_req:g} dB ({label})")
    if not mp.stable:
        reasons.append("position loop unstable on the verification plant")
    for sc, r in runs["proposed"].items():
        if sc != "velocity_step" and r.limit_cycle_amplitude > opt.max_limit_cycle_rad:
            reasons.append(f"{sc}: load limit cycle {r.limit_cycle_amplitude:.2e} rad > {opt.max_limit_cycle_rad:.2e} rad"
                           + (f" at {r.limit_cycle_frequency_hz:.1f} Hz" if r.limit_cycle_frequency_hz else ""))
        if r.settling_time_s is None and sc in ("velocity_step", "position_step"):
            reasons.append(f"{sc}: does not settle within the run")
    return Verification(margins=m, margins_gap=mg, position_margins=mp, runs=runs, ready=not reasons,
                        reasons=tuple(reasons), plant=tp)
