"""Controller-ready settings from the identified model: design, closed-loop verification,
export through the drive's parameter map, and write-back (issue #6).

    settings = design(identification, options)             # .design: loop shaping on .loop
    verification = verify(settings, plant, options)          # .verify + .scenarios: 8 kHz, backlash
    write_controller_files(out_dir, settings, verification, description)
    apply(drive, drive_parameters(settings, description), yes=..., store=..., log=writer.add_result)
    apply(drive, restore_values("run.mcap", description), ...)   # --restore-from

``plant`` is the true machine in a simulation (:class:`commission.plant.PlantParameters`) or,
on a real axis, the identified model (``identification``, or its ``parameters`` with
``epsilon_rad=``). Dependencies run one way: settings ← loop ← scenarios ← design, verify ← export.
"""

from .design import design
from .export import (
    PARAMETER_TOPIC,
    ApplyReport,
    ParameterValue,
    apply,
    controller_json,
    drive_parameters,
    restore_values,
    write_controller_files,
)
from .loop import loop_margins, open_loop, velocity_closed_loop
from .settings import (
    BacklashCompensation,
    ControllerSettings,
    LoopMargins,
    Notch,
    Preset,
    TuningError,
    TuningOptions,
)
from .verify import ScenarioResult, Verification, verify

__all__ = [
    "PARAMETER_TOPIC", "ApplyReport", "ParameterValue", "ScenarioResult", "Verification",
    "apply", "controller_json", "drive_parameters", "restore_values", "verify", "write_controller_files",
    "BacklashCompensation", "ControllerSettings", "LoopMargins", "Notch", "Preset", "TuningError",
    "TuningOptions", "design", "loop_margins", "open_loop", "velocity_closed_loop",
]
