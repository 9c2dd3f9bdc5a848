"""The commissioning sequence, and the owner of safety.

preflight (whole excitation checked against the envelope; drive state) → limits →
enable → excite → quick stop + disable on every path (success, error, Ctrl-C) →
write the log → identify (the seam where ``commission.ident`` plugs in).
Optionally, the paper's independent backlash check (§4.2) in velocity mode.

Nothing is sent to the drive before the whole waveform has passed the envelope
check; after an abort the drive is left disabled and whatever was recorded is
in the log.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .config import Config, config_to_dict
from .drive import Drive, DriveError, Mode, State
from .envelope import EnvelopeCheck, check_envelope, check_velocity_envelope
from .excitation import Waveform, chirp, velocity_reversal
from .exceptions import Aborted, CommissionError, DriveFault, LogFormatError, OutputError
from .mcaplog import append_result, write_recording
from .ident.reversal import ReversalCheck, backlash_from_reversals
from .plant import PlantParameters
from .recording import Recording

#: progress(label, done, total)
Progress = Callable[[str, int, int], None]
#: identify(recording) -> an identification result (commission.ident)
Identifier = Callable[[Recording], Any]

LOG_NAME = "run.mcap"
RESULT_NAME = "result.json"
CHECK_LOG_NAME = "backlash-check.mcap"
REPORT_NAME = "report.html"
#: Every n-th sample also goes to the log's /samples topic, for Foxglove's Plot panel
#: (1 kHz at the 8 kHz trace rate; the exact record stays in the sample blocks).
PLOT_EVERY = 8
#: Recording metadata of a run on the simulated drive: its plant (PlantParameters as JSON), so
#: that a replay of the log verifies on the same machine.
SIMULATED_PLANT = "simulated_plant"


def simulated_plant(recording: Recording, config: dict[str, Any] | None = None) -> PlantParameters | None:
    """The plant a recording was made on, when the run was on the simulated drive; else None.

    The run says so in the recording's metadata (:data:`SIMULATED_PLANT`). Logs written before
    it did: a drive whose backend is ``sim``, with the config's ``sim`` section as its plant.
    """
    stored = recording.metadata.get(SIMULATED_PLANT)
    try:
        if stored:
            return PlantParameters.model_validate_json(stored)
        if recording.drive.backend == "sim" and config is not None and isinstance(config.get("sim"), dict):
            return PlantParameters.model_validate(config["sim"])
    except ValueError as err:  # pydantic's ValidationError is a ValueError
        warnings.warn(f"the log's simulated plant is not valid, verifying on the identified model: {err}",
                      stacklevel=2)
    return None


@dataclass(frozen=True)
class TuningOutcome:
    """Controller settings from the identified model, their closed-loop verification, and files."""

    settings: Any
    """commission.tuning.ControllerSettings"""
    verification: Any
    """commission.tuning.Verification (on the true plant for simulated runs)"""
    controller: dict[str, Any]
    """controller.json's document"""
    files: list[Path]


def tune_and_export(out_dir: Path, identification: Any, options: Any, description: Any | None,
                    true_plant: PlantParameters | None = None,
                    excitation_band_hz: tuple[float, float] | None = None) -> TuningOutcome:
    """Design the controller from the identification, verify it in closed loop and write
    ``controller.json`` (and ``controller-<drive>.yaml`` with a drive description).

    :param description: the drive's description: its loop structure and parameter map.
    :param true_plant: the simulator's plant on simulated runs (the caller knows it ran one): the
        settings are then verified on the true machine; otherwise on the identified model with its
        backlash.
    :param excitation_band_hz: the band the experiment swept (the design's measured band when the
        identification states none).
    """
    from .tuning import controller_json, design, verify, write_controller_files

    settings = design(identification, options, description=description, excitation_band_hz=excitation_band_hz)
    if true_plant is not None:
        verification = verify(settings, true_plant, options)
    else:
        verification = verify(settings, identification, options)
    files = write_controller_files(out_dir, settings, verification, description)
    return TuningOutcome(settings, verification, controller_json(settings, verification), files)


@dataclass(frozen=True)
class RunOutcome:
    """What a commissioning run produced."""

    out_dir: Path
    log_path: Path
    recording: Recording
    waveform: Waveform
    envelope: EnvelopeCheck
    identification: Any | None = None
    files: list[Path] = field(default_factory=list)
    tuning: TuningOutcome | None = None


def write_result(out_dir: Path, identification: Any, source_file: str | None) -> Path:
    """Write ``DIR/result.json`` (the identification, SI units) and return its path."""
    path = Path(out_dir) / RESULT_NAME
    try:
        path.write_text(json.dumps(identification.to_dict(source_file), indent=2) + "\n", encoding="utf-8")
    except OSError as err:
        raise OutputError(f"cannot write {path}: {err.strerror or err}") from err
    return path


def add_identification_to_log(log_path: Path, identification: Any) -> None:
    """Put the identification on the log's ``/identification`` topic (the log is finished
    before the identifier runs; the file is rewritten and replaced atomically)."""
    try:
        append_result(log_path, "/identification", identification.to_dict(str(log_path)))
    except (LogFormatError, ValueError) as err:
        raise OutputError(f"cannot add the identification to {log_path}: {err}") from err


def write_run_report(out_dir: Path, recording: Recording, identification: Any | None,
                     config: dict[str, Any], source_file: str, files: list[Path],
                     tuning: TuningOutcome | None = None, *, true_plant: PlantParameters | None = None,
                     backlash_check: dict[str, Any] | None = None) -> Path | None:
    """Write ``DIR/report.html`` (verdict, model, tuning, verification, plots) and return its path.

    :param true_plant: the simulator's plant when the run (or the replayed log) was on the
        simulated drive: drawn beside the identified model.
    :param backlash_check: ``--measure-backlash``'s result (result.json's ``backlash_check``).

    The report is a view of results already written: if drawing it fails, the run is
    not failed for it — a warning says why and None is returned.
    """
    from .report import write_report

    path = Path(out_dir) / REPORT_NAME
    try:
        return write_report(path, recording, identification, config=config, source_file=source_file,
                            files=[*files, path], tuning=tuning, true_plant=true_plant,
                            backlash_check=backlash_check)
    except OSError as err:
        raise OutputError(f"cannot write {path}: {err.strerror or err}") from err
    except Exception as err:  # noqa: BLE001 - a plotting failure must not cost the commissioning result
        warnings.warn(f"report.html not written: {type(err).__name__}: {err}", stacklevel=2)
        return None


def _safe_stop(drive: Drive) -> str | None:
    """Quick stop and disable; returns a problem description instead of raising."""
    try:
        drive.quick_stop()
        drive.disable()
    except DriveError as err:
        return str(err)
    return None


class Sequencer:
    """Runs one commissioning experiment on an open drive.

    :param config: the validated recipe.
    :param drive: an open drive (the caller closes it).
    :param out_dir: folder for run.mcap and later outputs (created).
    :param progress: called during the excitation with ("excitation", samples done, total).
    :param identify: the identifier seam; None stops after the log.
    :param tune: design and verify controller settings after the identification.
    :param true_plant: the simulator's plant (a ``--sim`` run), to verify the settings on the
        true machine; it is also stored in the log's recording metadata (:data:`SIMULATED_PLANT`).
    :param description: the drive description the tuning uses (default: the drive's own).
    """

    def __init__(
        self,
        config: Config,
        drive: Drive,
        out_dir: Path,
        *,
        progress: Progress | None = None,
        identify: Identifier | None = None,
        tune: bool = True,
        true_plant: PlantParameters | None = None,
        description: Any | None = None,
    ) -> None:
        self.config = config
        self.drive = drive
        self.out_dir = Path(out_dir)
        self.progress = progress
        self.identify = identify
        self.tune = tune
        self.true_plant = true_plant
        self.description = description if description is not None else getattr(drive, "description", None)

    def _check_drive(self) -> None:
        state = self.drive.state
        if state is State.FAULT:
            raise DriveFault("drive is in Fault state before the run: find the cause and reset it first")
        if state is State.OPERATION_ENABLED:
            raise DriveError("drive is already enabled by someone else: refusing to take over a moving axis")

    def preflight(self) -> tuple[Waveform, EnvelopeCheck]:
        """Build the excitation and check all of it against the envelope; touches only the drive's state."""
        waveform = chirp(self.config.excitation)
        envelope = check_envelope(waveform.samples, waveform.sample_rate_hz, self.config.safety)
        self._check_drive()
        return waveform, envelope

    def run(self) -> RunOutcome:
        """The commissioning experiment: chirp torque, log, identify."""
        waveform, envelope = self.preflight()
        log_path = self.out_dir / LOG_NAME
        recording = self._experiment(waveform, Mode.CYCLIC_SYNC_TORQUE, log_path)
        files = [log_path]
        identification = None
        tuning = None
        if self.identify is not None:
            identification = self.identify(recording)
            files.append(write_result(self.out_dir, identification, str(log_path)))
            add_identification_to_log(log_path, identification)
            if self.tune:
                exc = self.config.excitation
                tuning = tune_and_export(self.out_dir, identification, self.config.tuning, self.description,
                                         self.true_plant, (exc.f_start_hz, exc.f_end_hz))
                files += tuning.files
        report = write_run_report(self.out_dir, recording, identification, config_to_dict(self.config),
                                  str(log_path), files, tuning, true_plant=self.true_plant)
        if report is not None:
            files.append(report)
        return RunOutcome(self.out_dir, log_path, recording, waveform, envelope, identification, files, tuning)

    def measure_backlash(self) -> tuple[Recording, ReversalCheck, Path]:
        """The backlash check of paper §4.2: velocity reversals, needs a load encoder."""
        bc = self.config.backlash_check
        waveform = velocity_reversal(bc.amplitude_rad_s, bc.frequency_hz, bc.duration_s,
                                     self.config.excitation.sample_rate_hz)
        check_velocity_envelope(waveform.samples, waveform.sample_rate_hz, self.config.safety)
        self._check_drive()
        log_path = self.out_dir / CHECK_LOG_NAME
        recording = self._experiment(waveform, Mode.CYCLIC_SYNC_VELOCITY, log_path, label="backlash check")
        return recording, backlash_from_reversals(recording), log_path

    def closed_loop_check(self, velocity_rad_s: Any, log_name: str) -> Recording:
        """A short closed-loop check of the drive's own velocity loop (``--apply``'s stages): the
        velocity reference checked against the envelope, played in velocity mode and recorded
        (logged to ``log_name`` in the output folder), the drive stopped and disabled after it."""
        rate = self.config.excitation.sample_rate_hz
        waveform = Waveform(velocity_rad_s, rate, "closed-loop check: velocity step and reversal")
        check_velocity_envelope(waveform.samples, rate, self.config.safety)
        self._check_drive()
        return self._experiment(waveform, Mode.CYCLIC_SYNC_VELOCITY, self.out_dir / log_name, label="loop check")

    def _experiment(self, waveform: Waveform, mode: Mode, log_path: Path, label: str = "excitation") -> Recording:
        """limits → enable → play → safe stop on every path → log (partial after an abort)."""
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)  # before anything moves
        except OSError as err:
            raise OutputError(f"cannot create output folder {self.out_dir}: {err.strerror or err}") from err
        safety = self.config.safety
        self.drive.set_limits(safety.max_torque_nm, safety.max_speed_rad_s, safety.max_travel_rad)

        def on_progress(done: int, total: int) -> None:
            if self.progress is not None:
                self.progress(label, done, total)

        try:
            self.drive.enable(mode)
            recording = self.drive.run_excitation(
                waveform.samples, waveform.sample_rate_hz, mode=mode, progress=on_progress
            )
        except BaseException as err:
            problem = _safe_stop(self.drive)
            saved = self._save_partial(log_path, err)
            tail = f"; partial log: {saved}" if saved else "; nothing was recorded"
            if problem:
                tail += f"; stopping the drive also failed: {problem}"
            if isinstance(err, KeyboardInterrupt):
                raise Aborted(f"interrupted: drive stopped and disabled{tail}") from err
            if isinstance(err, CommissionError):
                err.args = (f"{err}{tail}",)
            raise
        problem = _safe_stop(self.drive)
        if problem:
            raise DriveError(f"the experiment ended but the drive did not disable: {problem}")
        recording = recording.replace(
            metadata={**recording.metadata, **self._plant_metadata(), "status": "complete",
                      "excitation": waveform.description}
        )
        self._write_log(log_path, recording)
        return recording

    def _plant_metadata(self) -> dict[str, str]:
        return {} if self.true_plant is None else {SIMULATED_PLANT: self.true_plant.model_dump_json()}

    def _write_log(self, log_path: Path, recording: Recording) -> None:
        try:
            write_recording(log_path, recording, config=config_to_dict(self.config), plot_every=PLOT_EVERY)
        except OSError as err:
            raise OutputError(f"cannot write {log_path}: {err.strerror or err}") from err

    def _save_partial(self, log_path: Path, err: BaseException) -> Path | None:
        try:
            partial = self.drive.recorded_so_far()
        except DriveError:
            partial = None
        if partial is None:
            return None
        reason = str(err) or type(err).__name__
        partial = partial.replace(metadata={**partial.metadata, **self._plant_metadata(),
                                            "status": f"aborted: {reason}"})
        try:
            self._write_log(log_path, partial)
        except OutputError:
            return None
        return log_path
