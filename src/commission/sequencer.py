"""The commissioning sequence, and the owner of safety.

preflight (whole excitation checked against the envelope; drive state) → the envelope
again against the limits as the drive will hold them → limits → waveform download and
the drive's own checks (sample rate) → enable → excite → quick stop + disable on every
path → write the log → identify (the seam where ``commission.ident`` plugs in) → tune →
report. Optionally, the paper's independent backlash check (§4.2) in velocity mode.

Nothing is sent to the drive before the whole waveform has passed the envelope check,
and the drive is enabled only when everything that can be checked beforehand has been.
Whatever ends the experiment — its end, a drive error, a bug (any exception), Ctrl-C —
goes through one ``finally`` that quick-stops and disables the drive, each step tried
whatever the other did, a Ctrl-C held until it is done (:mod:`commission.interrupt`);
whatever was recorded is then in the log, which is written once and whole.

Two optional backend hooks, looked up on the drive: ``limits_as_held(max_torque_nm,
max_speed_rad_s) -> (N·m, rad/s)``, the limits as the drive will hold them (a backend
that rounds them to its units says how; without it they are held exactly), and
``prepare_excitation(samples, sample_rate_hz, mode)``, which downloads the waveform and
runs the drive-side checks while the drive is still disabled.
"""

from __future__ import annotations

import json
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from .config import Config, config_to_dict
from .drive import Drive, DriveError, Mode, State
from .envelope import EnvelopeCheck, HeldLimits, check_envelope, check_held_limits, check_velocity_envelope
from .excitation import Waveform, chirp, velocity_reversal
from .exceptions import Aborted, CommissionError, DriveFault, LogFormatError, OutputError
from .interrupt import Held, caused_by_interrupt, deferred, requested
from .interrupt import what as interrupt_what
from .mcaplog import append_result, write_recording
from .ident.reversal import ReversalCheck, backlash_from_reversals
from .plant import PlantParameters
from .recording import Recording

#: progress(label, done, total)
Progress = Callable[[str, int, int], None]
#: stage(name): a step of the run begins (limits, download, enable, excitation, log,
#: identification, tuning, report)
Stage = Callable[[str], None]
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
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        msg = str(first["msg"]).removeprefix("Value error, ")
        warnings.warn(f"the log's simulated plant is not valid ({where + ': ' if where else ''}{msg}), "
                      "verifying on the identified model", stacklevel=2)
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
                    excitation_band_hz: tuple[float, float] | None = None) -> TuningOutcome | None:
    """Design the controller from the identification, verify it in closed loop and write
    ``controller.json`` (and ``controller-<drive>.yaml`` with a drive description).

    None, with a warning, when an approximate identification's model is no plant the closed-loop check
    can simulate (a flagged fit can end far from any machine): its result and report are still written.

    :param description: the drive's description: its loop structure and parameter map.
    :param true_plant: the simulator's plant on simulated runs (the caller knows it ran one): the
        settings are then verified on the true machine; otherwise on the identified model with its
        backlash.
    :param excitation_band_hz: the band the experiment swept (the design's measured band when the
        identification states none).
    """
    from .tuning import TuningError, controller_json, design, verify, write_controller_files

    try:
        settings = design(identification, options, description=description, excitation_band_hz=excitation_band_hz)
        if true_plant is not None:
            verification = verify(settings, true_plant, options)
        else:
            verification = verify(settings, identification, options)
    except ValidationError as err:  # the model is not a plant the closed-loop check can simulate
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        why = (f"the closed-loop check cannot simulate the identified model: "
               f"{where + ': ' if where else ''}{str(first['msg']).removeprefix('Value error, ')}")
        if getattr(getattr(identification, "fit", None), "approximate", False):
            warnings.warn(f"no controller settings: {why} (the identification is approximate)", stacklevel=2)
            return None
        raise TuningError(why) from err
    with deferred():  # whole files, even when Ctrl-C comes meanwhile
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
        text = json.dumps(identification.to_dict(source_file), indent=2) + "\n"
        with deferred():
            path.write_text(text, encoding="utf-8")
    except OSError as err:
        raise OutputError(f"cannot write {path}: {err.strerror or err}") from err
    return path


def add_identification_to_log(log_path: Path, identification: Any) -> None:
    """Put the identification on the log's ``/identification`` topic (the log is finished
    before the identifier runs; the file is rewritten and replaced atomically)."""
    try:
        with deferred():
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
        with deferred():
            return write_report(path, recording, identification, config=config, source_file=source_file,
                                files=[*files, path], tuning=tuning, true_plant=true_plant,
                                backlash_check=backlash_check)
    except OSError as err:
        raise OutputError(f"cannot write {path}: {err.strerror or err}") from err
    except Exception as err:  # noqa: BLE001 - a plotting failure must not cost the commissioning result
        warnings.warn(f"report.html not written: {type(err).__name__}: {err}", stacklevel=2)
        return None


@dataclass(frozen=True)
class StopOutcome:
    """How stopping the drive went."""

    disabled: bool
    """The drive reports a state without torque (anything but 'operation enabled' or 'quick stop active')."""
    problems: tuple[str, ...] = ()
    interrupted: bool = False
    """A KeyboardInterrupt arrived during the stop (library use, without the CLI's handler): held
    until the stop was done."""

    @property
    def clean(self) -> bool:
        """Quick-stopped and disabled, nothing went wrong."""
        return self.disabled and not self.problems

    def describe(self, *, also: bool = False) -> str:
        """'drive stopped and disabled', or what went wrong (``also``: after another error)."""
        detail = "; ".join(self.problems) or "the drive's state is unknown"
        if self.clean:
            return "drive stopped and disabled"
        if self.disabled:
            return f"drive disabled ({detail})"
        return f"stopping the drive {'also ' if also else ''}failed: {detail}"


def _reason(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text}" if not isinstance(err, CommissionError) else text


#: CiA 402 states with torque on the motor.
_TORQUE_ON = (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)


def safe_stop(drive: Drive) -> StopOutcome:
    """Quick stop, then disable, each tried whatever the other did or raised, then the drive's
    state read back. A step that fails without a timeout is tried once more (a transfer cut by
    Ctrl-C can leave one stale answer on a link); one that times out is not (a dead link costs a
    timeout per step, and the state is then not read). Never raises: whatever is raised
    meanwhile (a bug in a backend, a lost link, Ctrl-C) is reported in the outcome."""
    problems: dict[str, str] = {}  # text -> step, in order, each text once
    interrupted = False
    timeouts = 0

    def attempt(step: str, action: Callable[[], Any], prefix: str = "") -> bool:
        nonlocal interrupted, timeouts
        last = ""
        for _ in range(2):
            try:
                action()
                return True
            except KeyboardInterrupt:
                interrupted = True
                last = f"{prefix}interrupted"
            except Exception as err:  # noqa: BLE001 - the stop must go on, whatever a backend raises
                last = f"{prefix}{_reason(err)}"
                if isinstance(err, TimeoutError):
                    timeouts += 1
                    break
        problems.setdefault(last, step)
        return False

    attempt("quick stop", drive.quick_stop, "quick stop failed: ")
    attempt("disable", drive.disable)
    state: list[State] = []
    if timeouts < 2 and attempt("state", lambda: state.append(drive.state), "state unreadable: ") \
            and state[0] in _TORQUE_ON:
        problems.setdefault(f"the drive still reports '{state[0].value}'", "state")
    disabled = bool(state) and state[0] not in _TORQUE_ON
    kept = [text for text, step in problems.items() if not (disabled and step == "disable")]
    return StopOutcome(disabled, tuple(kept), interrupted)


def release(drive: Drive) -> str | None:
    """Close the drive (its close() stops and disables it, then releases the link), held past
    Ctrl-C; never raises: returns what went wrong. Only an experiment enables the drive, and it
    stops the drive itself on every path (:func:`safe_stop`); this is the last word on the link."""
    with deferred(raise_after=False):
        try:
            drive.close()
        except Exception as err:  # noqa: BLE001 - closing a link must not hide the run's own outcome
            return f"closing the drive failed: {_reason(err)}"
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
    :param stage: called with the name of each step as it begins (:data:`Stage`).
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
        stage: Stage | None = None,
        description: Any | None = None,
    ) -> None:
        self.config = config
        self.drive = drive
        self.out_dir = Path(out_dir)
        self.progress = progress
        self.identify = identify
        self.tune = tune
        self.true_plant = true_plant
        self.stage = stage
        self.description = description if description is not None else getattr(drive, "description", None)

    def _stage(self, name: str) -> None:
        if self.stage is not None:
            self.stage(name)

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
        recording = self._experiment(waveform, Mode.CYCLIC_SYNC_TORQUE, log_path, envelope)
        files = [log_path]
        identification = None
        tuning = None
        if self.identify is not None:
            self._stage("identification")
            identification = self.identify(recording)
            files.append(write_result(self.out_dir, identification, str(log_path)))
            add_identification_to_log(log_path, identification)
            if self.tune:
                self._stage("tuning")
                exc = self.config.excitation
                tuning = tune_and_export(self.out_dir, identification, self.config.tuning, self.description,
                                         self.true_plant, (exc.f_start_hz, exc.f_end_hz))
                files += tuning.files if tuning is not None else []
        self._stage("report")
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
        envelope = check_velocity_envelope(waveform.samples, waveform.sample_rate_hz, self.config.safety)
        self._check_drive()
        log_path = self.out_dir / CHECK_LOG_NAME
        recording = self._experiment(waveform, Mode.CYCLIC_SYNC_VELOCITY, log_path, envelope, label="backlash check")
        return recording, backlash_from_reversals(recording), log_path

    def closed_loop_check(self, velocity_rad_s: Any, log_name: str) -> Recording:
        """A short closed-loop check of the drive's own velocity loop (``--apply``'s stages): the
        velocity reference checked against the envelope, played in velocity mode and recorded
        (logged to ``log_name`` in the output folder), the drive stopped and disabled after it."""
        rate = self.config.excitation.sample_rate_hz
        waveform = Waveform(velocity_rad_s, rate, "closed-loop check: velocity step and reversal")
        envelope = check_velocity_envelope(waveform.samples, rate, self.config.safety)
        self._check_drive()
        return self._experiment(waveform, Mode.CYCLIC_SYNC_VELOCITY, self.out_dir / log_name, envelope,
                                label="loop check")

    def _experiment(self, waveform: Waveform, mode: Mode, log_path: Path, envelope: EnvelopeCheck,
                    label: str = "excitation") -> Recording:
        """held limits → limits → download → enable → play → quick stop + disable on every path →
        log (partial after an abort)."""
        self._check_output(log_path)
        check_held_limits(envelope, self._held_limits(), "velocity reference" if mode is Mode.CYCLIC_SYNC_VELOCITY
                          else "excitation")

        def on_progress(done: int, total: int) -> None:
            if self.progress is not None:
                self.progress(label, done, total)

        failure: BaseException | None = None
        recording: Recording | None = None
        held = Held()  # from the end of the run on, a Ctrl-C waits for the stop and the log
        try:
            try:
                self._arm(waveform, mode)
                self._stage("enable")
                self.drive.enable(mode)
                self._stage(label)
                recording = self.drive.run_excitation(
                    waveform.samples, waveform.sample_rate_hz, mode=mode, progress=on_progress
                )
                held.hold()
            except BaseException as err:  # noqa: BLE001 - whatever ends the run, the drive is stopped first
                held.hold()
                failure = err
            finally:
                held.hold()
                stop = safe_stop(self.drive)
            if failure is None and stop.interrupted:
                failure = KeyboardInterrupt()
            if failure is not None:
                self._raise_after_abort(failure, stop, log_path)
            if not stop.disabled:
                raise DriveError(f"the experiment ended but the drive did not disable: {stop.describe()}")
            assert recording is not None
            recording = recording.replace(
                metadata={**recording.metadata, **self._plant_metadata(), "status": "complete",
                          "excitation": waveform.description}
            )
            self._stage("log")
            self._write_log(log_path, recording)  # written once and whole
            if requested():
                raise Aborted(f"interrupted: {stop.describe()}; the log is complete: {log_path}")
        finally:
            held.release()
        return recording

    def _check_output(self, log_path: Path) -> None:
        """The output folder exists and takes files, before anything moves."""
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            tempfile.TemporaryFile(dir=self.out_dir).close()
        except OSError as err:
            raise OutputError(f"cannot create output folder {self.out_dir}: {err.strerror or err}") from err
        if log_path.is_dir():
            raise OutputError(f"cannot write {log_path}: it is a folder")

    def _held_limits(self) -> HeldLimits:
        safety = self.config.safety
        as_held = getattr(self.drive, "limits_as_held", None)
        if as_held is None:
            return HeldLimits(safety.max_torque_nm, safety.max_speed_rad_s)
        torque_nm, speed_rad_s = as_held(safety.max_torque_nm, safety.max_speed_rad_s)
        return HeldLimits(float(torque_nm), float(speed_rad_s))

    def _arm(self, waveform: Waveform, mode: Mode) -> None:
        """Everything the drive can check before it is enabled: its limits, and the waveform
        downloaded with the drive-side checks (sample rate, ranges)."""
        safety = self.config.safety
        self._stage("limits")
        self.drive.set_limits(safety.max_torque_nm, safety.max_speed_rad_s, safety.max_travel_rad)
        prepare = getattr(self.drive, "prepare_excitation", None)
        if prepare is not None:
            self._stage("download")
            prepare(waveform.samples, waveform.sample_rate_hz, mode)

    def _raise_after_abort(self, failure: BaseException, stop: StopOutcome, log_path: Path) -> None:
        """Raise the error that ended the experiment, saying how the drive stopped and where the
        partial log is: Aborted for Ctrl-C (also when a library turned it into its own error)."""
        saved = self._save_partial(log_path, failure)
        tail = f"; partial log: {saved}" if saved else "; nothing was recorded"
        if caused_by_interrupt(failure):  # also an error a library made of it, or one that came meanwhile
            why = "" if isinstance(failure, KeyboardInterrupt) else f" ({_reason(failure)})"
            raise Aborted(f"interrupted{why}: {stop.describe()}{tail}") from failure
        if not stop.clean:
            tail += f"; {stop.describe(also=True)}"
        if isinstance(failure, CommissionError):
            failure.args = (f"{failure}{tail}",)
        elif hasattr(failure, "add_note"):  # a bug: the CLI shows the note with the error
            failure.add_note(f"{stop.describe()}{tail}")
        raise failure

    def _plant_metadata(self) -> dict[str, str]:
        return {} if self.true_plant is None else {SIMULATED_PLANT: self.true_plant.model_dump_json()}

    def _write_log(self, log_path: Path, recording: Recording) -> None:
        try:
            write_recording(log_path, recording, config=config_to_dict(self.config), plot_every=PLOT_EVERY)
        except OSError as err:
            raise OutputError(f"cannot write {log_path}: {err.strerror or err}") from err

    def _save_partial(self, log_path: Path, err: BaseException) -> Path | None:
        """Whatever the drive recorded before ``err``, as the log (None: nothing, or not saved)."""
        try:
            partial = self.drive.recorded_so_far()
        except Exception:  # noqa: BLE001 - the log of an abort is what can be saved; the abort's error is reported
            return None
        if partial is None:
            return None
        reason = f"interrupted ({interrupt_what()})" if caused_by_interrupt(err) else _reason(err) or type(err).__name__
        try:
            partial = partial.replace(metadata={**partial.metadata, **self._plant_metadata(),
                                                "status": f"aborted: {reason}"})
            self._write_log(log_path, partial)
        except Exception:  # noqa: BLE001 - as above
            return None
        return log_path
