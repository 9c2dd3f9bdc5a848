"""Controller-ready settings from the identified model: design, closed-loop verification,
export through the drive's parameter map, and write-back (issue #6).

    settings = design(identification, options)             # .design: loop shaping on .loop
    verification = verify(settings, plant, options)          # .verify + .scenarios: 8 kHz, backlash
    write_controller_files(out_dir, settings, verification, description)
    apply(drive, drive_parameters(settings, description), yes=..., store=..., log=writer.add_result)
    apply_staged(drive, conservative, final, check, options, ...)  # --apply: conservative set, check, final
    apply(drive, restore_values("run.mcap", description), ...)   # --restore-from

``plant`` is the true machine in a simulation (:class:`commission.plant.PlantParameters`) or,
on a real axis, the identified model (``identification``, or its ``parameters`` with
``epsilon_rad=``). The design reads the identification through :mod:`.identified`, the drive's
loop through :mod:`.dynamics`, and holds its margins over the uncertainty set of :mod:`.robust`.
Dependencies run one way: settings ← loop ← robust, scenarios ← design, verify ← export ← staged.
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
from .robust import robust_margins
from .settings import (
    BacklashCompensation,
    BandwidthLimit,
    ControllerSettings,
    DriveDynamics,
    LimitingFactor,
    LoopMargins,
    Notch,
    Preset,
    RobustMargins,
    TuningError,
    TuningOptions,
    UncertaintyMember,
    UncertaintySet,
)
from .staged import CheckResult, StagedApplyReport, apply_staged, conservative_settings
from .verify import ScenarioResult, Verification, verify

__all__ = [
    "PARAMETER_TOPIC", "ApplyReport", "ParameterValue", "ScenarioResult", "Verification",
    "apply", "controller_json", "drive_parameters", "restore_values", "verify", "write_controller_files",
    "BacklashCompensation", "BandwidthLimit", "CheckResult", "ControllerSettings", "DriveDynamics", "LimitingFactor",
    "LoopMargins", "Notch", "Preset", "RobustMargins", "StagedApplyReport", "TuningError", "TuningOptions",
    "UncertaintyMember", "UncertaintySet", "apply_staged", "conservative_settings", "design", "loop_margins",
    "open_loop", "robust_margins", "velocity_closed_loop",
]
