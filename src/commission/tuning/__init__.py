"""Controller-ready settings from the identified model: design, closed-loop verification,
export through the drive's parameter map, and write-back (issue #6).

    settings = design(identification, options)             # .design: loop shaping (python-control)
    verification = verify(settings, plant, options)          # .verify + .closedloop: 8 kHz, backlash
    write_controller_files(out_dir, settings, verification, description)
    apply(drive, drive_parameters(settings, description), yes=..., store=..., log=writer.add_result)
    apply(drive, restore_values("run.mcap", description), ...)   # --restore-from

``plant`` is the true machine in a simulation (``sim_drive.plant.PlantParameters``) or, on a
real axis, the identified model (``identification.parameters`` with ``epsilon_rad=``).
"""

from .design import (
    BacklashCompensation,
    ControllerSettings,
    LoopMargins,
    Notch,
    Preset,
    TuningError,
    TuningOptions,
    design,
    loop_margins,
    velocity_closed_loop,
)
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
from .verify import ScenarioResult, TruePlant, Verification, verify

__all__ = [
    "PARAMETER_TOPIC", "ApplyReport", "ParameterValue", "ScenarioResult", "TruePlant", "Verification",
    "apply", "controller_json", "drive_parameters", "restore_values", "verify", "write_controller_files",
    "BacklashCompensation", "ControllerSettings", "LoopMargins", "Notch", "Preset", "TuningError",
    "TuningOptions", "design", "loop_margins", "velocity_closed_loop",
]
