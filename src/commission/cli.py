"""`commission`: the command line. Thin: parse, load the config, call the sequencer.

Results (the summary table and a last ``next:`` line saying what to do next) go to
stdout; progress, diagnostics and warnings to stderr; with ``--json`` stdout carries one
JSON document and nothing else. Every CommissionError ends as one line on stderr and a
non-zero exit code; no traceback (``-v`` shows the cause chain). Ctrl-C at any moment ends
in exit 130 with the drive stopped and disabled (:mod:`commission.interrupt`); the heavy
modules are imported only after that handler is in place.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import traceback
import warnings
from collections.abc import Iterator, Sequence
from datetime import datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .exceptions import Aborted, CommissionError, ConfigError, IdentificationError, LogFormatError, OutputError
from .interrupt import caused_by_interrupt, handling_interrupts, requested

if TYPE_CHECKING:
    from .config import Config
    from .recording import Recording

EPILOG = """\
modes:
  commission --sim                       full experiment on the built-in simulated drive
  commission --port can0                 CANopen drive on SocketCAN can0 (CiA 402)
  commission --sim --sim-link canopen    the simulated drive as a CANopen node on a virtual bus
  commission --port /dev/ttyACM0 --interface slcan --drive NAME   CANopen through a serial-line CAN adapter
  commission --port /dev/ttyUSB0 --protocol modbus [--drive NAME]  Modbus RTU on the drive's service port
  commission --replay run.mcap --out D   identify again from a log (.mcap or .csv)
  commission --replay FOLDER [MORE ...] --out D [--scheduler tcp://HOST:PORT]
                                         fleet: identify every log on Dask into D/fleet.parquet + D/fleet.html
  commission --warm-cache                compile the numerical kernels once (a first run does it otherwise)

outputs (in --out DIR, default ./commissioning/<date-time>/):
  run.mcap       every sample sent and measured, the config and the drive's identity
  result.json    the identified two-mass model, its modes and the backlash (SI units)
  controller.json          velocity/position loop, filters, notch, feedforward, backlash compensation,
                           margins, closed-loop verification and `ready`
  controller-<drive>.yaml  the same through the drive's parameter map (with --drive / a drive description)
  report.html    self-contained report: Bode and time plots, the backlash search, metadata
  backlash-check.mcap   the velocity-reversal experiment (with --measure-backlash)

The summary goes to stdout, progress and warnings to stderr; the last line says what to do next.

exit codes: 0 ok, 1 other error, 2 config, 3 input file, 4 drive, 5 safety limit, 6 identification,
            7 output file, 8 done but the identification is approximate (result.json's fit.reasons say why),
            130 interrupted (Ctrl-C, SIGTERM or SIGHUP: the drive is stopped and disabled, the log kept)
"""


def _version() -> str:
    try:
        return version("drive-commission")
    except PackageNotFoundError:  # pragma: no cover
        return "0+unknown"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="commission",
        description="Commission a servo axis: inject a chirp torque, log it to MCAP, "
        "identify the two-mass model and its gear backlash.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False,  # `--pres soft` is a typo, not --preset
    )
    src = p.add_argument_group("drive or input (choose one)")
    x = src.add_mutually_exclusive_group(required=True)
    x.add_argument("--sim", action="store_true", help="use the built-in simulated drive (plant from the config's 'sim' section)")
    x.add_argument("--port", metavar="PORT", help="drive connection: a CAN channel (can0) or a serial device (/dev/ttyUSB0)")
    x.add_argument("--replay", metavar="LOG_OR_FOLDER", type=Path, nargs="+",
                   help="no drive: read a recorded run (.mcap or .csv) and identify it; with more than one log "
                   "or a folder: fleet mode (every log on Dask, one row each in DIR/fleet.parquet)")
    x.add_argument("--warm-cache", action="store_true",
                   help="compile the numerical kernels into numba's cache with a short simulated run, then exit "
                   "(`make run` and the Docker image do this at install; otherwise the first run does it)")
    link = p.add_argument_group("link options (with --port)")
    link.add_argument("--interface", metavar="NAME", help="python-can interface for CAN ports (default: socketcan)")
    link.add_argument("--bitrate", metavar="BIT/S", type=int,
                      help="CAN bit rate; with --protocol modbus: the line's baud rate (default: the drive description's)")
    link.add_argument("--node-id", metavar="ID", type=int, help="CANopen node id, or the Modbus device address")
    link.add_argument("--protocol", choices=["canopen", "modbus"], help="protocol on the port (default: canopen for CAN)")
    link.add_argument("--drive", metavar="NAME", help="drive description under drivers/ (sim, generic-cia402, yaskawa-sigma7); default: the one "
                      "matching the drive's identity (0x1018), else generic-cia402; one that does not match is refused")
    link.add_argument(
        "--excitation", choices=["trace", "streamed"],
        help="CANopen: waveform played and traced by the drive (primary), or host-streamed cyclic torque "
        "over SYNC+PDO (fallback); default: what the drive description supports",
    )
    link.add_argument(
        "--allow-narrow-band", action="store_true",
        help="CANopen streamed: if the bus budget's usable band is below the configured f_end_hz, end the chirp "
        "there instead of refusing",
    )
    link.add_argument("--rate", metavar="HZ", type=float,
                      help="CANopen streamed: highest cycle rate to use (default: the highest the bus allows)")
    run = p.add_argument_group("run")
    run.add_argument("--config", metavar="FILE", type=Path,
                     help="commissioning recipe: a YAML file, or the name of a shipped one (default, paper-literal, "
                     "quick); default: the paper's experiment (configs/default.yaml)")
    run.add_argument("--out", metavar="DIR", type=Path, help="output folder (default: ./commissioning/<date-time>/)")
    run.add_argument(
        "--method", choices=["hybrid", "paper"],
        help="identification method: 'hybrid' (default; accurate) or 'paper' (the published procedure, "
        "to reproduce it); overrides identification.method of the config",
    )
    run.add_argument(
        "--sim-link", choices=["direct", "canopen"], default="direct",
        help="with --sim: drive the simulated drive directly (default), or as a CANopen node on an "
        "in-process python-can virtual bus (the whole CANopen path, every frame on the bus)",
    )
    run.add_argument("--no-identify", action="store_true", help="stop after the log (no result.json, no tuning)")
    tune = p.add_argument_group("controller settings")
    tune.add_argument("--preset", choices=["soft", "standard", "stiff"],
                      help="tuning target: soft (PM 60°, GM 12 dB), standard (45°, 8 dB), stiff; overrides tuning.preset")
    tune.add_argument("--no-tune", action="store_true", help="identify only: no controller.json")
    tune.add_argument("--apply", action="store_true",
                      help="write the settings to the drive: shows old → new, asks (or --yes), reads back; "
                      "refused when the settings are not ready or a value was clamped to its range")
    tune.add_argument("--yes", action="store_true", help="do not ask before writing parameters")
    tune.add_argument("--store", action="store_true",
                      help="after --apply / --restore-from, store the parameters to non-volatile memory (0x1010)")
    tune.add_argument("--restore-from", metavar="LOG", type=Path,
                      help="no experiment: write back the parameter values logged before an earlier --apply "
                      "(the run.mcap of that run)")
    run.add_argument("--seed", type=int, help="seed of the simulated plant's noise (overrides sim.seed)")
    run.add_argument(
        "--measure-backlash", action="store_true",
        help="after the run, also measure the backlash at velocity reversals (paper §4.2; needs a load encoder; "
        "settings in the config's 'backlash_check' section)",
    )
    fleet = p.add_argument_group("fleet mode (--replay with several logs or a folder)")
    fleet.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                       help="run the identifications on this existing Dask scheduler's workers (they must see the "
                       "logs' paths); default: a local cluster, one worker per core")
    fleet.add_argument("--workers", metavar="N", type=int, help="local cluster: worker processes (default: one per core)")
    fleet.add_argument("--growth-threshold", metavar="DEG", type=float, default=0.05,
                       help="fleet.html lists first the axes whose backlash grew by more than this (default 0.05°)")
    out = p.add_argument_group("output")
    out.add_argument("--json", action="store_true", help="print one JSON document on stdout and nothing else")
    out.add_argument("-v", "--verbose", action="store_true", help="more detail; show the cause of errors")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    return p


def _default_out_dir() -> Path:
    base = Path("commissioning") / datetime.now().strftime("%Y%m%d-%H%M%S")
    out, n = base, 1
    while out.exists():
        n += 1
        out = base.with_name(f"{base.name}-{n}")
    return out


def _recording_summary(rec: Recording) -> dict[str, Any]:
    import numpy as np

    return {
        "samples": len(rec),
        "sample_rate_hz": rec.sample_rate_hz,
        "duration_s": rec.duration_s,
        "signals": [name for name, _ in rec.signals()],
        "peak_torque_nm": float(np.max(np.abs(rec.torque_ref))),
        "peak_motor_velocity_rad_s": float(np.max(np.abs(rec.motor_velocity))),
        "drive": rec.drive.to_dict(),
        "status": rec.metadata.get("status", "unknown"),
        **{key: rec.metadata[key] for key in ("bus_budget", "stream") if key in rec.metadata},
        "lost_samples": int(rec.lost_mask.sum()),
    }


class _Terminal:
    """Results on stdout (``out``), progress and diagnostics on stderr (``console``), with rich;
    silent in --json mode."""

    def __init__(self, quiet: bool, verbose: bool) -> None:
        from rich.console import Console

        self.quiet = quiet
        self.verbose = verbose
        self.out = Console(quiet=quiet, highlight=False)
        self.console = Console(stderr=True, quiet=quiet, highlight=False)
        self._progress: Any = None
        self._tasks: dict[str, Any] = {}
        self._tenths: dict[str, int] = {}

    def say(self, text: str) -> None:
        """A diagnostic line on stderr (rich markup), never wrapped (a log keeps it on one line)."""
        self.console.print(text, soft_wrap=True)

    def stage(self, name: str) -> None:
        """-v: ``stage: NAME`` on stderr as each step of a run on a drive begins (open, limits, download,
        enable, excitation, log, identification, tuning, report)."""
        if self.verbose:
            self.console.print(f"stage: {name}", markup=False, soft_wrap=True)

    def result(self, text: str) -> None:
        """A plain result line on stdout, never wrapped (a path stays whole)."""
        self.out.print(text, markup=False, soft_wrap=True)

    def progress(self, label: str, done: int, total: int, detail: str = "") -> None:
        if self.quiet:
            return
        if self.verbose and not self.console.is_terminal:  # a log file gets a line per tenth instead of a bar
            tenth = 10 * done // max(1, total)
            if tenth > self._tenths.get(label, -1):
                self._tenths[label] = tenth
                self.console.print(f"{label}: {10 * tenth} %", markup=False, soft_wrap=True)
            return
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        if self._progress is None:
            self._progress = Progress(
                TextColumn("{task.description:<12}"), BarColumn(), TextColumn("{task.percentage:>5.1f} %"),
                TimeElapsedColumn(), TextColumn("{task.fields[detail]}"),
                console=self.console, transient=not self.console.is_terminal,
            )
            self._progress.start()
        if label not in self._tasks:
            self._tasks[label] = self._progress.add_task(label, total=total, detail=detail)
        self._progress.update(self._tasks[label], completed=done, total=total, detail=detail)

    def close(self) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def summary(self, title: str, rows: list[tuple[str, str]], files: Sequence[str] = ()) -> None:
        """The rows as a table, then ``files`` under it, one path per line and never wrapped (a path
        folded at the table's edge cannot be copied)."""
        from rich.table import Table
        from rich.text import Text

        table = Table(title=title, show_header=False, title_justify="left")
        table.add_column(style="bold")
        table.add_column()
        for k, v in rows:
            table.add_row(k, v)
        self.out.print(table)
        for f in files:
            self.out.print(Text.assemble(("file", "bold"), " ", f), soft_wrap=True)


def _identifier(config: Config, args: argparse.Namespace, term: _Terminal) -> Any:
    """The identification seam: a callable Recording -> Identification, or None (--no-identify)."""
    if args.no_identify:
        return None
    from .ident.hybrid import identify

    options = config.identification
    if args.method is not None:
        options = _override(options, method=args.method)

    def run(recording: Recording) -> Any:
        def progress(stage: str, fraction: float, info: dict[str, Any] | None = None) -> None:
            detail = stage
            if info and "evaluations" in info:
                detail = f"{stage}: {info['evaluations']} evaluations"
                if info.get("best_epsilon_deg") is not None:
                    detail += f", best ε {info['best_epsilon_deg']:.3f}°"
            term.progress("identify", int(round(1000 * fraction)), 1000, detail)

        try:
            return identify(recording, options, progress=progress)
        except IdentificationError as err:
            if "stream" in recording.metadata:  # a streamed record: say how the stream went, it may be why
                err.args = (f"{err} ({recording.metadata['stream']})",)
            raise
        finally:
            term.close()

    return run


def _replay(args: argparse.Namespace, config: Config, term: _Terminal, identify: Any, out_dir: Path,
            result: dict[str, Any]) -> dict[str, Any]:
    """--replay FILE: identify, tune and report from a recorded run (no drive)."""
    from .recording import read_log

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        recording = read_log(args.replay)
    for w in caught:
        term.say(f"[yellow]warning:[/] {w.message}")
        result.setdefault("warnings", []).append(str(w.message))
    result["source"] = str(args.replay)
    result["recording"] = _recording_summary(recording)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create output folder {out_dir}: {err.strerror or err}") from err
    identification = None
    tuning = None
    recorded = _recorded_config(args.replay, config)
    plant = _simulated_plant(recorded, recording)
    if identify is not None:
        from .sequencer import tune_and_export, write_result

        identification = identify(recording)
        result["identification"] = identification.to_dict(str(args.replay))
        result["files"].append(str(write_result(out_dir, identification, str(args.replay))))
        if not args.no_tune:
            # the excitation's band, when the log says what it was (a CSV file does not)
            exc = (recorded.get("excitation") or {}) if args.replay.suffix.lower() == ".mcap" else {}
            band = ((float(exc["f_start_hz"]), float(exc["f_end_hz"])) if {"f_start_hz", "f_end_hz"} <= set(exc)
                    else None)
            tuning = tune_and_export(out_dir, identification, _tuning_options(config, args), _description(args),
                                     plant, band)
            if tuning is not None:
                result["controller"] = tuning.controller
                result["files"] += [str(f) for f in tuning.files]
    from .sequencer import write_run_report

    report = write_run_report(out_dir, recording, identification, recorded,
                              str(args.replay), [Path(f) for f in result["files"]], tuning, true_plant=plant)
    if report is not None:
        result["files"].append(str(report))
    term.summary(f"replay of {args.replay}", _rows(result), result["files"])
    _details(term, result)
    return result


def _run(args: argparse.Namespace, term: _Terminal) -> dict[str, Any]:
    from .config import load_config

    config: Config = load_config(args.config)
    out_dir = args.out or _default_out_dir()
    result: dict[str, Any] = {"out_dir": str(out_dir), "files": []}
    identify = _identifier(config, args, term)

    if args.replay is not None:
        # a folder is a fleet, unless it is named like a log (then reading it says what is wrong)
        one = args.replay[0]
        if len(args.replay) > 1 or args.scheduler is not None or (
                one.is_dir() and one.suffix.lower() not in (".mcap", ".csv")):
            return _fleet(args, config, term, out_dir, result)
        args.replay = args.replay[0]
        return _replay(args, config, term, identify, out_dir, result)

    from .drive import open_drive
    from .sequencer import release

    sim_plant = dict(config.sim)
    if args.seed is not None:
        sim_plant["seed"] = args.seed
        config = config.model_copy(update={"sim": sim_plant})  # the log's config says which seed ran
    link_options = {k: v for k, v in (("bitrate", args.bitrate), ("node_id", args.node_id), ("drive", args.drive))
                    if v is not None}
    over_can = (args.sim and args.sim_link == "canopen") or (
        args.port is not None and args.protocol != "modbus"
        and (args.interface is not None or not args.port.startswith("/dev/"))
    )
    if over_can:
        link_options.update(band_hz=config.excitation.f_end_hz, allow_narrow_band=args.allow_narrow_band)
        if args.rate is not None:
            link_options["max_rate_hz"] = args.rate
        if args.excitation:
            link_options["excitation"] = args.excitation
    if (args.apply or args.restore_from is not None) and not args.yes and not sys.stdin.isatty():
        what = "--apply" if args.apply else "--restore-from"
        raise ConfigError(f"{what} asks before it writes, and the input is not a terminal: pass --yes "
                          "(nothing was run or written)")
    term.stage("open")
    drive = open_drive(
        sim=args.sim, port=args.port, interface=args.interface, protocol=args.protocol,
        sim_plant=sim_plant if args.sim else None, sim_link=args.sim_link, **link_options,
    )
    try:
        return _with_drive(args, term, config, drive, out_dir, identify, sim_plant, result)
    finally:
        problem = release(drive)
        if problem and not requested():
            warnings.warn(problem, stacklevel=1)


def _with_drive(args: argparse.Namespace, term: _Terminal, config: Config, drive: Any, out_dir: Path, identify: Any,
                sim_plant: dict[str, Any], result: dict[str, Any]) -> dict[str, Any]:
    """The run on an open drive (the caller stops and closes it, whatever happens here)."""
    import numpy as np

    from .sequencer import Sequencer

    if args.restore_from is not None:
        return _restore(args, drive, out_dir, term, result)
    if args.apply:  # refuse before anything moves, not after the experiment
        problem = None
        if args.no_identify or args.no_tune:
            problem = "--apply needs controller settings: do not combine it with --no-identify or --no-tune"
        elif getattr(drive, "description", None) is None:
            problem = (f"the {drive.info.backend} drive has no parameter map for --apply: use a drive with a "
                       "description (e.g. --sim --sim-link canopen, or --drive NAME)")
        elif args.json and not args.yes:
            problem = "--apply with --json needs --yes (there is no one to ask)"
        if problem is not None:
            raise ConfigError(problem)
    config = config.model_copy(update={"tuning": _tuning_options(config, args)})
    budget = getattr(drive, "budget", None)
    if budget is not None:  # host-streamed: the bus budget before anything moves
        term.say(f"streamed cycle: {budget.describe()}")
        if config.excitation.f_end_hz > budget.usable_band_hz:  # --allow-narrow-band: the chirp ends there
            term.say(f"chirp end frequency {config.excitation.f_end_hz:g} Hz -> {budget.usable_band_hz:g} Hz "
                     "(the usable band of the streamed cycle)")
            config = config.model_copy(update={"excitation": config.excitation.model_copy(
                update={"f_end_hz": budget.usable_band_hz})})
    true_plant = None
    if args.sim:
        from .drive.sim import plant_from_options

        true_plant = plant_from_options(sim_plant)
    term.say(f"drive: {drive.info.vendor} {drive.info.product} ({drive.info.backend})")
    sequencer = Sequencer(config, drive, out_dir, progress=term.progress, identify=identify,
                          tune=not args.no_tune, true_plant=true_plant, stage=term.stage,
                          description=getattr(drive, "description", None) or _description(args))
    outcome = sequencer.run()
    if "stream" in outcome.recording.metadata:
        term.say(outcome.recording.metadata["stream"])
    check = sequencer.measure_backlash() if args.measure_backlash else None
    term.close()
    if args.apply:
        result["apply"] = _apply(args, drive, outcome, term, sequencer, config)
    if check is not None:
        _, reversals, check_log = check
        result["backlash_check"] = {
            "epsilon_deg": reversals.epsilon_deg,
            "spread_deg": float(np.degrees(reversals.spread_rad)),
            "reversals": len(reversals.reversals),
            "log": str(check_log),
        }
        _add_to_result_json(out_dir, "backlash_check", result["backlash_check"])
        from .config import config_to_dict
        from .sequencer import write_run_report

        # the check runs after the report was written: draw it again with the check in it
        write_run_report(outcome.out_dir, outcome.recording, outcome.identification, config_to_dict(config),
                         str(outcome.log_path), [*(f for f in outcome.files if f.name != "report.html"), check_log],
                         outcome.tuning,
                         true_plant=true_plant, backlash_check=result["backlash_check"])
    result["source"] = drive.info.backend
    result["recording"] = _recording_summary(outcome.recording)
    result["envelope"] = {
        "peak_torque_nm": outcome.envelope.peak_torque_nm,
        "predicted_peak_speed_rad_s": outcome.envelope.predicted_peak_speed_rad_s,
        "predicted_peak_travel_rad": outcome.envelope.predicted_peak_travel_rad,
    }
    if outcome.identification is not None:
        result["identification"] = outcome.identification.to_dict(str(outcome.log_path))
    if outcome.tuning is not None:
        result["controller"] = outcome.tuning.controller
    result["files"] = [str(f) for f in outcome.files]
    if check is not None:
        result["files"].append(str(check[2]))
        if str(out_dir / "result.json") not in result["files"]:  # --no-identify: the check alone
            result["files"].append(str(out_dir / "result.json"))
    term.summary("commissioning run", _rows(result), result["files"])
    _details(term, result)
    return result


def _fleet(args: argparse.Namespace, config: Config, term: _Terminal, out_dir: Path,
           result: dict[str, Any]) -> dict[str, Any]:
    """--replay with several logs or a folder: every log identified on Dask (commission.fleet)."""
    from . import fleet
    from .exceptions import ConfigError

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {args.workers}")
    if not args.growth_threshold >= 0:
        raise ConfigError(f"--growth-threshold must be 0° or more, got {args.growth_threshold}")
    options = fleet.FleetOptions(scheduler=args.scheduler, workers=args.workers,
                                 growth_threshold_deg=args.growth_threshold,
                                 identification=_identifier_options(config, args))
    summary = fleet.run(args.replay, out_dir, options,
                        progress=lambda done, total, detail: term.progress("fleet", done, total, detail))
    term.close()
    result["fleet"] = summary.to_dict()
    result["files"] += [str(summary.table), str(summary.report)]
    c = summary.counts
    where = "nothing to identify"
    if summary.cluster is not None:
        n = summary.cluster.workers
        where = (f"{n} worker{'' if n == 1 else 's'} ({'local' if summary.cluster.local else summary.cluster.scheduler}), "
                 f"{summary.seconds:.1f} s, {summary.logs_per_minute:.1f} logs/min")
    rows = [("logs", f"{summary.found} found, {summary.skipped} already in the table, {summary.identified} identified"),
            ("outcome", f"{c['ok']} ok ({summary.approximate} approximate), {c['failed']} failed, {c['crashed']} crashed"),
            ("ran on", where),
            ("backlash grew", ", ".join(f"{a.name} +{a.growth_deg:.3f}°" for a in summary.grown) or "on no axis")]
    term.summary("fleet", rows, result["files"])
    return result


def _identifier_options(config: Config, args: argparse.Namespace) -> Any:
    options = config.identification
    return options if args.method is None else _override(options, method=args.method)


def _add_to_result_json(out_dir: Path, key: str, value: Any) -> None:
    """Put one more top-level section into DIR/result.json (created when the run identified nothing)."""
    from .sequencer import RESULT_NAME

    path = out_dir / RESULT_NAME
    try:
        doc = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
        doc[key] = value
        path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    except (OSError, ValueError) as err:
        raise OutputError(f"cannot add {key} to {path}: {err}") from err


def _tuning_options(config: Config, args: argparse.Namespace) -> Any:
    options = config.tuning
    if args.preset is not None:
        options = _override(options, preset=args.preset)
    return options


def _override(options: Any, **changes: Any) -> Any:
    """A copy of a settings model with changes validated like the config file's (so "paper" becomes
    ``Method.PAPER``; pydantic's ``model_copy`` would keep the bare string)."""
    return type(options).model_validate({**options.model_dump(), **changes})


def _description(args: argparse.Namespace) -> Any | None:
    """The drive description named by --drive (for controller-<drive>.yaml on replays)."""
    if not args.drive:
        return None
    from .drive.description import load_description

    return load_description(args.drive)


def _simulated_plant(config: dict[str, Any], recording: Recording) -> Any | None:
    """The simulator's plant when the replayed run came from the simulated drive (the log says
    so), else None."""
    from .sequencer import simulated_plant

    return simulated_plant(recording, config)


def _confirm(term: _Terminal) -> Any:
    def ask(question: str) -> bool:
        if not sys.stdin.isatty():
            term.say("not a terminal: pass --yes to write without asking")
            return False
        return input(f"{question} [y/N] ").strip().lower() in ("y", "yes")

    return ask


def _apply(args: argparse.Namespace, drive: Any, outcome: Any, term: _Terminal, sequencer: Any,
           config: Config) -> dict[str, Any]:
    """--apply: write the verified settings in two stages through the drive's parameter map (a
    conservative set, a closed-loop check on the drive, the final set and its check; the previous
    values back on a failed check), every value logged in run.mcap."""
    from .mcaplog import append_result
    from .tuning import TuningError, apply_staged, conservative_settings, drive_parameters

    if outcome.tuning is None:  # the identification is approximate and its model no plant (warned)
        raise TuningError(f"no settings to write: {_UNCHECKED}")
    if not outcome.tuning.controller["verification"]["ready"]:
        raise TuningError("settings are not ready, nothing written: "
                          + "; ".join(outcome.tuning.controller["verification"]["reasons"]))
    settings, options = outcome.tuning.settings, config.tuning
    checks = iter(range(1, 3))
    report = apply_staged(
        drive, drive_parameters(conservative_settings(settings, options.apply_conservative_fraction), drive.description),
        drive_parameters(settings, drive.description),
        lambda reference: sequencer.closed_loop_check(reference, f"apply-check-{next(checks)}.mcap"), options,
        torque_limit_nm=config.safety.max_torque_nm, sample_rate_hz=config.excitation.sample_rate_hz, yes=args.yes,
        confirm=_confirm(term), store=args.store,
        log=lambda topic, payload: append_result(outcome.log_path, topic, payload), echo=term.say)
    return report.as_dict()


def _restore(args: argparse.Namespace, drive: Any, out_dir: Path, term: _Terminal,
             result: dict[str, Any]) -> dict[str, Any]:
    """--restore-from LOG: write back the values logged before an earlier --apply (logged again)."""
    from .exceptions import ConfigError
    from .mcaplog import ResultLog
    from .tuning import apply, restore_values

    description = getattr(drive, "description", None)
    if description is None:
        raise ConfigError(f"the {drive.info.backend} drive has no parameter map to restore through")
    if args.json and not args.yes:
        raise ConfigError("--restore-from with --json needs --yes (there is no one to ask)")
    values = restore_values(args.restore_from, description)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create output folder {out_dir}: {err.strerror or err}") from err
    log_path = out_dir / "restore.mcap"
    with ResultLog(log_path, metadata={"restored_from": str(args.restore_from)}) as log:
        report = apply(drive, values, yes=args.yes, confirm=_confirm(term), store=args.store,
                       log=log.add, echo=term.say)
    result.update(source=drive.info.backend, files=[str(log_path)],
                  restore={"from": str(args.restore_from), "applied": report.applied, "written": report.written,
                           "stored": report.stored})
    term.result(f"restored {len(report.written)} parameters from {args.restore_from}" if report.applied
                else "nothing restored")
    return result


def _recorded_config(path: Path, config: Config) -> dict[str, Any]:
    """The config stored in a replayed .mcap (it describes that run, e.g. its simulated
    plant), else the current one."""
    if path.suffix.lower() == ".mcap":
        from .mcaplog import read_config

        try:
            return read_config(path)
        except LogFormatError:
            pass
    from .config import config_to_dict

    return config_to_dict(config)


def _details(term: _Terminal, result: dict[str, Any]) -> None:
    """-v: the identification's stages, iterations and notes."""
    ident = result.get("identification")
    if not term.verbose or ident is None:
        return
    rows = [(f"stage {s['name']}", f"{s['seconds']:.3f} s") for s in ident.get("stages", [])]
    rows += [(f"iteration {i}", f"FRD error {it['frd_error']:.3g}  ε {it['epsilon_deg']:.4f}°")
             for i, it in enumerate(ident.get("iterations", []))]
    term.summary("details", rows)
    for note in ident.get("notes", []):
        term.out.print(f"note: {note}", markup=False)


def _rows(result: dict[str, Any]) -> list[tuple[str, str]]:
    rec = result["recording"]
    rows = [
        ("source", str(result.get("source"))),
        ("samples", f"{rec['samples']} at {rec['sample_rate_hz']:g} Hz ({rec['duration_s']:g} s)"
                    + (f", {rec['lost_samples']} lost and interpolated" if rec.get("lost_samples") else "")),
        ("signals", ", ".join(rec["signals"])),
        ("peak torque / speed", f"{rec['peak_torque_nm']:.4g} N·m / {rec['peak_motor_velocity_rad_s']:.4g} rad/s"),
        ("status", rec["status"]),
    ]
    ident = result.get("identification")
    if ident is not None:
        tm, md, bl = ident["two_mass"], ident["modes"], ident["backlash"]
        lo, hi = bl["epsilon_interval_deg"]
        detected = ("  (not determined by this record)" if not bl.get("determined", True)
                    else "" if bl.get("detected", True) else "  (no backlash detected)")
        rows += [
            ("method", bl["method"]),
            ("backlash ε", f"{bl['epsilon_deg']:.4f}°  [{lo:.4f}°, {hi:.4f}°]{detected}"),
            ("inertias", f"J_m {tm['J_m']:.4g}  J_l {tm['J_l']:.4g} kg·m²  (ratio {tm['J_l'] / tm['J_m']:.3g})"),
            ("shaft", f"K {tm['K']:.4g} N·m/rad  D {tm['D']:.3g} N·m·s/rad"),
            ("friction", f"B_m {tm['B_m']:.3g}  B_l {tm['B_l']:.3g} N·m·s/rad"),
            ("resonance", _mode_text(md, "resonance")),
            ("anti-resonance", _mode_text(md, "antiresonance")),
        ]
        if ident.get("cogging"):
            cg = ident["cogging"]
            rows.append(("cogging / ripple", f"{', '.join(map(str, cg['harmonics_per_revolution']))} per revolution, "
                                             f"{cg['peak_nm']:.3g} N·m peak (taken out of the torque)"))
        fit = ident.get("fit")
        if fit is not None:
            rows.append(("model fit", f"{100 * fit['residual_ratio']:.3g} % of the torque unexplained"
                         + (" (white torque noise)" if fit.get("noise_limited") else "")
                         + ("  APPROXIMATE: " + "; ".join(fit.get("reasons", [])) if fit["approximate"] else "")))
    ctl = result.get("controller")
    if ctl is not None:
        vl, m, ver = ctl["velocity_loop"], ctl["margins"], ctl["verification"]
        notch = ", ".join(f"{n['frequency_hz']:.1f} Hz Q {n['q']:.2g}" for n in ctl.get("notch", [])) or "none"
        bc = ctl.get("backlash_compensation", {})
        rows += [
            ("velocity loop", f"gain {vl['gain']:.4g} N·m·s/rad  Ti {vl['integral_time_s'] * 1e3:.3g} ms  "
                              f"bandwidth {vl['bandwidth_hz']:.0f} Hz"),
            ("position loop", f"{ctl['position_loop']['gain_per_s']:.4g} 1/s"
                              + (f"  reference filter {ctl['position_loop']['reference_filter_time_constant_ms']:.3g} ms"
                                 if ctl["position_loop"].get("reference_filter_time_constant_s") else "")),
            ("notch / backlash comp.", f"{notch} / {bc.get('amount_rad', 0.0) * 1e3:.3g} mrad"),
            ("margins", f"PM {m['phase_margin_deg']:.1f}°  GM {m['gain_margin_db']:.1f} dB"),
            *_drive_loop_rows(ctl),
            *_robust_rows(ctl),
            ("controller ready", "yes" if ver.get("ready") else "NO: " + "; ".join(ver.get("reasons", []))),
        ]
    if "backlash_check" in result:
        bc = result["backlash_check"]
        rows.append(("backlash check (§4.2)",
                     f"ε = {bc['epsilon_deg']:.3f}° ± {bc['spread_deg']:.3f}° over {bc['reversals']} reversals"))
    return rows


def _warm_cache() -> dict[str, Any]:
    """--warm-cache: a short commissioning of the simulated drive (the shipped ``quick`` recipe) in a
    temporary folder, so that numba compiles and caches every kernel a run uses; only the cache is kept."""
    import tempfile
    import time

    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="commission-warm-") as tmp:
        args = build_parser().parse_args(["--sim", "--config", "quick", "--out", tmp, "--json"])
        _run(args, _Terminal(quiet=True, verbose=False))
    return {"warm_cache": {"seconds": time.perf_counter() - start}, "files": []}


@contextlib.contextmanager
def _announce_compilation(term: _Terminal) -> Iterator[None]:
    """Say on stderr when numba starts compiling: a first run after an install spends tens of
    seconds there, which would otherwise look like a hang."""
    if term.quiet:
        yield
        return
    from numba.core import event

    class FirstCompile(event.Listener):
        said = False

        def on_start(self, ev: event.Event) -> None:
            if not self.said:
                self.said = True
                from . import jitcache

                if jitcache.uncached_reason:
                    term.say(f"compiling the numerical kernels (numba, about a minute): {jitcache.uncached_reason}, "
                             "so on every run")
                else:
                    term.say("compiling the numerical kernels (numba; once after an install, about a minute; "
                             "`commission --warm-cache` does it ahead)")

        def on_end(self, ev: event.Event) -> None:
            pass

    with event.install_listener("numba:compile", FirstCompile()):
        yield


def _mode_text(md: dict[str, Any], name: str) -> str:
    """A mode of result.json's ``modes`` as a table cell ("none" where the estimate has none: JSON null)."""
    f, z = md.get(f"f_{name}_hz"), md.get(f"zeta_{name}")
    return "none" if f is None or z is None else f"{f:.2f} Hz  ζ {z:.3f}"


def _next_step(args: argparse.Namespace, result: dict[str, Any]) -> str:
    """The last line: what to do with what this run left."""
    if "fleet" in result:
        return f"next: open {result['fleet']['report']}; the table is {result['fleet']['table']} (pyarrow, pandas)"
    if "warm_cache" in result:
        return (f"next: the kernels are compiled and cached ({result['warm_cache']['seconds']:.1f} s); "
                "`commission --sim` or a drive's run starts without compiling")
    report = next((f for f in result.get("files", []) if f.endswith(".html")), None)
    see = f"open the report at {report}" if report else f"the files are in {result.get('out_dir')}"
    if "restore" in result:
        stored = result["restore"]["stored"]
        return ("next: the previous values are back on the drive"
                + ("" if stored else "; add --store to keep them after a power cycle"))
    if "apply" in result:
        if not result["apply"]["applied"]:
            return f"next: nothing was written; {see}, then run again with --apply when ready"
        return (f"next: the settings are on the drive; {see}"
                + ("" if result["apply"]["stored"] else "; --store keeps them after a power cycle")
                + f"; --restore-from {Path(result['out_dir']) / 'run.mcap'} puts the old values back")
    remedies = ((result.get("identification") or {}).get("fit") or {}).get("remedies") or []
    if remedies:
        see += ("; the identification is approximate: unless something else moved the axis during the run, a new "
                "record would help: " + "; or ".join(remedies))
    ctl = result.get("controller")
    if ctl is None:
        if getattr(args, "no_identify", False) or getattr(args, "no_tune", False):
            missing = "--no-identify" if "identification" not in result else "--no-tune"
            return f"next: {see}; run without {missing} for controller settings"
        return f"next: {see}; no controller settings: {_UNCHECKED}"
    verification = ctl.get("verification", {})
    if not verification.get("ready"):
        reasons = "; ".join(verification.get("reasons", [])) or "see the report"
        return f"next: {see}; the settings are NOT ready to apply ({reasons})"
    if args.replay is not None:
        return f"next: {see}; the settings are ready: to write them, commission the axis itself with --apply"
    if args.sim and args.sim_link == "direct":
        return (f"next: {see}; the settings are ready (--apply writes through a drive's parameter map: "
                "try `commission --sim --sim-link canopen --drive sim --apply`)")
    return f"next: {see}; the settings are ready: run again with --apply to write them to the drive"


def _drive_loop_rows(ctl: dict[str, Any]) -> list[tuple[str, str]]:
    """The drive's loop the design assumed, each figure with where it came from ('confirm': an
    assumption, or a description's figure not from the drive's manual)."""
    sources = (ctl.get("drive_model") or {}).get("sources") or {}

    def said(key: str, value: str) -> str:
        src = sources[key]
        return f"{value} ({src['from']}{', confirm' if src.get('confirm') else ''})"

    items = []
    if "current_loop_bandwidth_hz" in sources:
        bw = sources["current_loop_bandwidth_hz"]["value"]
        items.append("current loop " + said("current_loop_bandwidth_hz", "ideal" if bw is None else f"{bw:.0f} Hz"))
    if "computation_delay_samples" in sources and "encoder_delay_samples" in sources:
        comp, enc = (float(sources[k]["value"] or 0.0) for k in ("computation_delay_samples", "encoder_delay_samples"))
        items.append(f"delay {said('computation_delay_samples', f'computation {comp:g}')} + "
                     f"{said('encoder_delay_samples', f'encoder {enc:g}')} samples")
    return [("drive loop (design)", ";  ".join(items))] if items else []


def _robust_rows(ctl: dict[str, Any]) -> list[tuple[str, str]]:
    """The worst case over the uncertainty set and what limited the bandwidth (controller.json)."""
    rows = []
    rb, lim, band = ctl.get("robust"), ctl.get("bandwidth_limit"), ctl.get("measured_band") or {}
    if rb:
        rows.append(("worst-case margins", f"PM {rb['phase_margin_deg']:.1f}° ({rb['phase_margin_member']['description']})"
                     f"  GM {rb['gain_margin_db']:.1f} dB ({rb['gain_margin_member']['description']})"
                     f" over {rb['members']} members"))
    if band.get("band_hz") and band.get("crossover_hz") is not None:
        lo, hi = band["band_hz"]
        rows.append(("crossover / band", f"{band['crossover_hz']:.0f} Hz in the measured {lo:g}–{hi:g} Hz"
                     + (f" (limit {band['crossover_limit_hz']:.0f} Hz)" if band.get("crossover_limit_hz") else "")))
    if lim:
        rows.append(("bandwidth limited by", f"{lim['factor']}: {lim['detail']}"))
    return rows


#: Why a run has no controller settings although tuning was asked for (sequencer.tune_and_export warns).
_UNCHECKED = "the identified model could not be checked in closed loop"

#: Exit code of a run that wrote all its outputs but whose identification is approximate.
APPROXIMATE_EXIT_CODE = 8


def main(argv: Sequence[str] | None = None) -> int:
    """The ``commission`` command; returns its exit code."""
    with handling_interrupts():
        try:
            return _main(argv)
        except KeyboardInterrupt:  # before or after _main's own handlers (start-up, the last print)
            print("commission: interrupted", file=sys.stderr)
            return Aborted.exit_code


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    notes = " ".join(" ".join(str(n).split()) for n in getattr(err, "__notes__", ()))
    return f"{text} ({notes})" if notes else text


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    term = _Terminal(quiet=args.json, verbose=args.verbose)
    try:
        with warnings.catch_warnings(record=True) as caught, _announce_compilation(term):
            warnings.simplefilter("always")
            result = _warm_cache() if args.warm_cache else _run(args, term)
        for w in caught:  # e.g. a report that could not be drawn: said once, in one line
            term.say(f"[yellow]warning:[/] {w.message}")
            result.setdefault("warnings", []).append(str(w.message))
    except CommissionError as err:
        term.close()
        if requested() and not isinstance(err, Aborted):  # a library turned Ctrl-C into its own error
            print(f"commission: error: interrupted ({_one_line(err)})", file=sys.stderr)
            return Aborted.exit_code
        print(f"commission: error: {_one_line(err)}", file=sys.stderr)
        if args.verbose and err.__cause__ is not None and str(err.__cause__):
            print(f"  caused by: {type(err.__cause__).__name__}: {err.__cause__}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        term.close()
        print("commission: interrupted", file=sys.stderr)
        return Aborted.exit_code
    except Exception as err:  # noqa: BLE001 - a bug still ends in one line (the drive was stopped on the way out)
        term.close()
        if caused_by_interrupt(err):
            print(f"commission: error: interrupted ({type(err).__name__}: {_one_line(err)})", file=sys.stderr)
            return Aborted.exit_code
        print(f"commission: internal error: {type(err).__name__}: {_one_line(err)} "
              "(a bug in drive-commission: please report it with the output of -v)", file=sys.stderr)
        if args.verbose:
            traceback.print_exception(err, file=sys.stderr)
        return 1
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        term.result(_next_step(args, result))
    # everything was written, but the model may be off by more than its intervals say
    approximate = bool(((result.get("identification") or {}).get("fit") or {}).get("approximate"))
    return APPROXIMATE_EXIT_CODE if approximate else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
