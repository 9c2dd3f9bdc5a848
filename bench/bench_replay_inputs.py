"""Replays of the records a CSV export gets wrong (ident.consistency and a record cut from a running axis):
what ``commission --replay X.csv --no-tune`` gives on each, and how long it takes.

The source is the reference plant (ε 0.4°, 1e-4 N·m torque noise) under the default 10 s chirp at 8 kHz;
each case changes 3 s of it (or all 10 s) the way a real log can differ: two latch the encoders half a
sample and a sample after their torque; two give the velocity alone, as a signal sampled at the sample
instants rather than a difference of counts; one is in encoder counts; three have a load encoder that counts the other way, from
its own zero (5 rad from the motor's) or behind a gear; three a one-sample glitch of the encoder (with
and without the position) or of the velocity. Then the 3 s record with its time column written as
loggers and spreadsheets write it, with a decimal comma, and with rows a logger dropped. Each line: the
exit code, the wall time of the command in a fresh process (numba's kernels already cached), ε and its
interval, the errors of J_m, J_l and K against the plant, whether the result is flagged, and the first
note or error.

Then the margins of the same checks on the default family (seed 22, every member): how far each member
is from being changed by them.

    python bench/bench_replay_inputs.py
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

from commission.config import ExcitationConfig
from commission.csvlog import write_csv
from commission.excitation import chirp
from commission.ident.twomass import REFERENCE_PLANT
from commission.recording import Recording
from sim_drive.plant import Plant, PlantParameters
from sim_drive.sampled import sampled_motor_velocity

FS = 8000.0
N3 = int(3 * FS)
COUNTS_PER_RAD = 2**24 / (2 * math.pi)  # the simulator's 24-bit encoder


def cases() -> dict[str, Recording]:
    """Each case's record, by name."""
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.40, torque_noise_nm=1e-4, seed=11),
              FS).run_torque(chirp(ExcitationConfig()).samples)
    full = Recording.uniform(FS, r.torque_ref, r.motor_velocity, motor_position=r.motor_position)
    head = full.head(N3)
    loaded = full.replace(load_position=r.load_position, load_velocity=r.load_velocity)

    def cut(start_s: float) -> Recording:
        a = int(start_s * FS)
        return Recording.uniform(FS, full.torque_ref[a:a + N3], full.motor_velocity[a:a + N3],
                                 motor_position=full.motor_position[a:a + N3])

    wrapped = np.mod(full.motor_position + math.pi, 2 * math.pi) - math.pi
    a = math.exp(-2 * math.pi * 500.0 / FS)
    filtered = lfilter([1 - a], [1, -a], full.motor_velocity)
    return {
        "as simulated (3 s)": head,
        "single-turn position (10 s)": full.replace(motor_position=wrapped),
        "position column constant 0": head.replace(motor_position=np.zeros(N3)),
        "torque sign reversed": head.replace(torque_ref=-head.torque_ref),
        "position in degrees": head.replace(motor_position=np.degrees(head.motor_position)),
        "velocity in rpm": head.replace(motor_velocity=head.motor_velocity * 60 / (2 * math.pi)),
        "position and velocity in counts": head.replace(motor_position=np.round(head.motor_position * COUNTS_PER_RAD),
                                                        motor_velocity=head.motor_velocity * COUNTS_PER_RAD),
        "cut at 3.5 s (moving, one reversal)": cut(3.5),
        "cut at 1 s (moving, never reverses)": cut(1.0),
        "encoders a sample late (10 s)": Recording.uniform(FS, full.torque_ref[:-1], full.motor_velocity[1:],
                                                           motor_position=full.motor_position[1:]),
        "encoders half a sample late (10 s)": half_sample_late(),
        "velocity only, sampled (10 s)": sampled_velocity(),
        "velocity only, filtered 500 Hz (10 s)": Recording.uniform(FS, full.torque_ref, filtered),
        "load encoder counting backwards (10 s)": loaded.replace(load_position=-loaded.load_position,
                                                                   load_velocity=-loaded.load_velocity),
        "encoder glitch, 1 sample (10 s)": glitched(full),
        "encoder glitch, velocity only (10 s)": glitched(full).replace(motor_position=None),
        "velocity glitch, 1 sample (10 s)": full.replace(motor_velocity=full.motor_velocity
                                                         + 50.0 * (np.arange(len(full)) == 40_000)),
        "load encoder with its own zero (10 s)": loaded.replace(load_position=loaded.load_position + 5.0),
        "load encoder behind a 1:10 gear": loaded.head(N3).replace(load_position=0.1 * loaded.load_position[:N3],
                                                                   load_velocity=0.1 * loaded.load_velocity[:N3]),
    }


def glitched(rec: Recording) -> Recording:
    """``rec`` with its encoder misread by 0.05 rad at one sample (t = 5 s), and the drive's velocity the
    difference of that position (a spike up and one down)."""
    x = rec.motor_position.copy()
    x[40_000] += 0.05
    return rec.replace(motor_position=x, motor_velocity=np.diff(x, prepend=x[0]) * FS)


def half_sample_late() -> Recording:
    """The reference run with its encoder latched half a sample after each torque (mid-cycle): the plant at
    twice the rate, the odd samples."""
    tau = chirp(ExcitationConfig()).samples
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.40, torque_noise_nm=1e-4, seed=11),
              2 * FS).run_torque(np.repeat(tau, 2))
    x = r.motor_position[1::2]
    return Recording.uniform(FS, tau, np.diff(x, prepend=x[0]) * FS, motor_position=x)


def sampled_velocity() -> Recording:
    """The reference run with its motor velocity sampled at the sample instants (a simulator's state), velocity
    only."""
    tau = chirp(ExcitationConfig()).samples
    v, _ = sampled_motor_velocity(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.40,
                                                  torque_noise_nm=1e-4, seed=11), tau, FS)
    return Recording.uniform(FS, tau, v)


def replay(path: Path, out: Path) -> tuple[int, float, str]:
    """(exit code, wall time [s], last stderr line) of the command in a new process."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "commission.cli", "--replay", str(path), "--out", str(out),
                           "--no-tune"], capture_output=True, text=True)
    lines = proc.stderr.strip().splitlines()
    return proc.returncode, time.perf_counter() - t0, lines[-1] if lines else ""


def row(name: str, code: int, seconds: float, err: str, out: Path) -> str:
    head = f"{name:38s} exit {code}  {seconds:5.1f} s  "
    if not (out / "result.json").exists():
        return head + err.removeprefix("commission: error: ")[:110]
    doc = json.loads((out / "result.json").read_text())
    bl, tm, fit = doc["backlash"], doc["two_mass"], doc["fit"]
    lo, hi = bl["epsilon_interval_deg"]
    e = {p: 100 * (tm[p] / getattr(REFERENCE_PLANT, p) - 1) for p in ("J_m", "J_l", "K")}
    first = next((n for n in doc["notes"] if not n.startswith("a 3 s record")), "")
    return (head + f"ε {bl['epsilon_deg']:.4f}° [{lo:.4f}, {hi:.4f}]"
            + ("" if bl.get("determined", True) else " (not determined)")
            + "  " + "  ".join(f"{p} {v:+.2f} %" for p, v in e.items())
            + ("  FLAGGED" if fit["approximate"] else "") + (f"  | {first[:70]}" if first else ""))


def family_margins() -> list[str]:
    """How far the default family's records are from what the checks act on (none may be acted on)."""
    from commission.ident import consistency as c
    from commission.ident.hybrid import _CROSSING_LEVEL, _CROSSING_SAMPLES
    from commission.ident.residual import motor_position_samples, prepare_residual, simulate_load
    from sim_drive.family import DEFAULT_SEED, family

    power, motor, load, moving, sides, changed, velocity_only, off_lattice = [], [], [], [], [], 0, 0, 0
    for m in family(DEFAULT_SEED):
        rec = m.simulate()
        fs, p = rec.sample_rate_hz, m.two_mass
        changed += c.reconcile(rec)[1] != []
        if rec.motor_position is None:
            velocity_only += 1
            off_lattice += not c._on_a_lattice(rec.motor_velocity, rec.lost_mask)
        v = rec.motor_velocity
        power.append(float(np.mean(rec.torque_ref * v) / (np.std(rec.torque_ref) * np.std(v))))
        x = motor_position_samples(rec.motor_position, v, fs)
        if rec.motor_position is not None:
            motor.append(c._step_ratio(x, c._motion(v, rec.t)))
        if rec.load_position is not None:
            load.append(c._displacement_ratio(rec.load_position, x))
        n = max(8, int(round(c._START_WINDOW_S * fs)))
        moving.append(abs(np.polyfit(np.arange(n) / fs, x[:n], 1)[0]) / (np.max(np.abs(np.diff(x))) * fs))
        pr = prepare_residual(rec.torque_ref, fs, motor_position=rec.motor_position, motor_velocity=v,
                              cutoff_hz=min(300.0, 0.4 * fs), load_position=rec.load_position)
        shaft = simulate_load(pr, p.J_l, p.B_l, p.K, p.D, math.radians(m.epsilon_deg)).shaft_torque
        level = _CROSSING_LEVEL * np.max(np.abs(shaft))
        sides.append(int(min(np.sum(shaft > level), np.sum(shaft < -level))))
    return [f"family seed {DEFAULT_SEED}, {len(power)} members: changed by the checks {changed}",
            f"  correlation of torque and velocity: lowest {min(power):+.3f} (reversed below {c.REVERSED_POWER:+g})",
            f"  motor position / velocity step ratio: {min(motor):.6f}–{max(motor):.6f} (acted on outside "
            f"{c.SCALE_RANGE[0]:g}–{c.SCALE_RANGE[1]:g})",
            f"  load / motor displacement ratio: {min(load):.4f}–{max(load):.4f} (acted on outside "
            f"{c.SCALE_RANGE[0]:g}–{c.SCALE_RANGE[1]:g})",
            f"  speed over the first ms / top speed: largest {max(moving):.2e} (moving above {c._START_MOVING:g})",
            f"  velocity-only members whose velocity is no difference of counts: {off_lattice} of {velocity_only}",
            f"  shaft torque at the truth, samples on its rarer side: fewest {min(sides)} (not crossing below {_CROSSING_SAMPLES})"]


#: How a spreadsheet or a logger may write the time column of the 3 s record (k: sample index).
TIME_COLUMNS = {
    "t as a Unix time (0.24 µs resolution)": lambda k: 1.764e9 + k / FS,
    "t rounded to 0.1 ms": lambda k: np.round(k / FS, 4),
    "t in milliseconds": lambda k: k * 1e3 / FS,
}
#: Other ways a logger writes the 3 s record: (separator, decimal mark, sample indices it dropped).
LAYOUTS = {
    "';' and a decimal comma": (";", ",", ()),
    "12 rows a logger dropped": (",", ".", tuple(range(1000, 24000, 2000))),
}


def write_with_time(path: Path, rec: Recording, t: np.ndarray, sep: str = ",", decimal: str = ".",
                    dropped: tuple[int, ...] = ()) -> None:
    """``rec`` as a CSV whose time column is ``t`` [s] (no directives: the rate comes from t)."""
    cols = [t, rec.torque_ref, rec.motor_velocity, rec.motor_position]
    gone = set(dropped)
    rows = (r for k, r in enumerate(zip(*cols)) if k not in gone)
    path.write_text(sep.join(("t", "torque_ref", "motor_velocity", "motor_position")) + "\n"
                    + "".join(sep.join(repr(float(v)).replace(".", decimal) for v in r) + "\n" for r in rows))


def main() -> int:
    print(__doc__.split("\n\n")[0].replace("\n", " "))
    with tempfile.TemporaryDirectory() as tmp:
        all_cases = cases()
        for i, (name, rec) in enumerate(all_cases.items()):
            path, out = Path(tmp) / f"case{i}.csv", Path(tmp) / f"out{i}"
            write_csv(path, rec)
            code, seconds, err = replay(path, out)
            print(row(name, code, seconds, err, out), flush=True)
        head = all_cases["as simulated (3 s)"]
        for i, (name, time_of) in enumerate(TIME_COLUMNS.items()):
            path, out = Path(tmp) / f"time{i}.csv", Path(tmp) / f"tout{i}"
            write_with_time(path, head, time_of(np.arange(len(head))))
            code, seconds, err = replay(path, out)
            print(row(name, code, seconds, err, out), flush=True)
        for i, (name, (sep, decimal, dropped)) in enumerate(LAYOUTS.items()):
            path, out = Path(tmp) / f"layout{i}.csv", Path(tmp) / f"lout{i}"
            write_with_time(path, head, np.arange(len(head)) / FS, sep, decimal, dropped)
            code, seconds, err = replay(path, out)
            print(row(name, code, seconds, err, out), flush=True)
    for line in family_margins():
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
