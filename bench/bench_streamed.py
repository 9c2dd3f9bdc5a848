"""The host-streamed CiA 402 path under a busy host: success count and spread against the direct run.

What a technician would type, each run a fresh process, with a CPU-bound process
(``while True: pass``) running beside every run:

1. ``commission --sim --json`` once, without the hog: the reference (the plant stepped
   directly, 8 kHz trace);
2. ``commission --sim --sim-link canopen --drive generic-cia402 --json`` N times: the
   simulated drive as a CANopen node on the in-process virtual bus, streamed CST at
   the rate the bus allows, on the drive's clock;
3. over an slcan adapter in another process (``python -m sim_drive --slcan``, a fresh
   one per run): ``commission --port PTY --interface slcan`` without ``--drive`` (the
   description picked from the drive's identity) and with ``--drive generic-cia402``
   (streamed through the adapter), M times each.

A run counts when it exits 0 and ε is within ±0.02° and J_m, J_l, K within ±2 % of the
reference. Printed: the count, the spread of each deviation (min / median / max), the
stream figures (lost cycles, late setpoints, host response p99), and the wall time.

4. what late setpoints and lost cycles cost the identifier, without a bus: the plant
   stepped per cycle as the drive steps it, setpoints held at random (late host) or
   cycles dropped (lost TPDOs, rebuilt as the backend rebuilds them), identified,
   and compared with the plant's true parameters.

Run: python bench/bench_streamed.py [--runs 20] [--slcan-runs 5] [--no-hog] [--tune] [--robustness-only]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

EPS_TOL_DEG = 0.02
REL_TOL = 0.02
PY = sys.executable


def commission(args: list[str], out: Path, tune: bool) -> tuple[int, dict | None, str, float]:
    cmd = [PY, "-m", "commission.cli", *args, "--json", "--out", str(out)] + ([] if tune else ["--no-tune"])
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    wall = time.perf_counter() - t0
    doc = None
    if proc.returncode == 0:
        try:
            doc = json.loads(proc.stdout)
        except json.JSONDecodeError:
            doc = None
    err = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else ""
    return proc.returncode, doc, err, wall


def figures(doc: dict) -> dict[str, float]:
    ident = doc["identification"]
    tm = ident["two_mass"]
    return {"eps_deg": ident["backlash"]["epsilon_deg"], "J_m": tm["J_m"], "J_l": tm["J_l"], "K": tm["K"]}


def deviations(f: dict[str, float], ref: dict[str, float]) -> dict[str, float]:
    return {"eps_deg": f["eps_deg"] - ref["eps_deg"],
            **{k: f[k] / ref[k] - 1 for k in ("J_m", "J_l", "K")}}


def within(dev: dict[str, float]) -> bool:
    return abs(dev["eps_deg"]) <= EPS_TOL_DEG and all(abs(dev[k]) <= REL_TOL for k in ("J_m", "J_l", "K"))


def stream_figures(doc: dict) -> str:
    s = doc.get("recording", {}).get("stream", "")
    lost = re.search(r"(\d+) lost", s)
    paused = re.search(r"\((\d+) paused by late setpoints, ([\d.]+)%, longest pause (\d+); (\d+) late answers", s)
    p99 = re.search(r"p99 (\d+) us", s)
    if not lost:
        return "trace"
    pause = (f"paused {paused.group(2)} % (longest {paused.group(3)} cycles; {paused.group(4)} late past the budget)"
             if paused else "paused ?")
    return f"lost {lost.group(1)}, {pause}, host p99 {int(p99.group(1)) / 1e3 if p99 else 0:.1f} ms"


class Hog:
    """A CPU-bound process beside the run (ended by its own pid)."""

    def __init__(self, enabled: bool) -> None:
        self.proc = subprocess.Popen([PY, "-c", "while True: pass"]) if enabled else None

    def close(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()


class SlcanDrive:
    """``python -m sim_drive --slcan`` in its own process; its first stdout line is the pty."""

    def __init__(self, extra: list[str]) -> None:
        self.proc = subprocess.Popen([PY, "-m", "sim_drive", "--slcan", *extra], stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True)
        assert self.proc.stdout is not None
        self.port = self.proc.stdout.readline().strip()

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def series(label: str, runs: int, args_for_run, ref: dict[str, float], tmp: Path, tune: bool, hog: bool,
           sim_extra: list[str] | None = None) -> int:
    print(f"\n{label}: {runs} runs{' beside a CPU hog' if hog else ''}")
    devs, walls, ok = [], [], 0
    for i in range(runs):
        sim = SlcanDrive(sim_extra or []) if sim_extra is not None else None
        h = Hog(hog)
        try:
            code, doc, err, wall = commission(args_for_run(sim), tmp / f"{label.split()[0]}-{i}", tune)
        finally:
            h.close()
            if sim is not None:
                sim.close()
        walls.append(wall)
        if code != 0 or doc is None:
            print(f"  run {i + 1:>2}: FAILED (exit {code}) {err}")
            continue
        dev = deviations(figures(doc), ref)
        good = within(dev)
        ok += good
        devs.append(dev)
        print(f"  run {i + 1:>2}: {'ok ' if good else 'OUT'} Δε {dev['eps_deg']:+.4f}°  ΔJ_m {dev['J_m']:+.3%}  "
              f"ΔJ_l {dev['J_l']:+.3%}  ΔK {dev['K']:+.3%}  ({stream_figures(doc)}; {wall:.0f} s)")
    print(f"  {label}: {ok} of {runs} within ε ±{EPS_TOL_DEG}° and J_m, J_l, K ±{REL_TOL:.0%} of the direct run")
    if devs:
        for key, unit in (("eps_deg", "°"), ("J_m", "%"), ("J_l", "%"), ("K", "%")):
            v = np.array([d[key] for d in devs]) * (1 if unit == "°" else 100)
            print(f"    spread {key:<7} min {v.min():+.4f}{unit}  median {np.median(v):+.4f}{unit}  "
                  f"max {v.max():+.4f}{unit}")
    print(f"    wall time per run: median {np.median(walls):.0f} s")
    return ok


def robustness() -> None:
    """Identification on ideal 2 kHz cycle records with held setpoints or lost cycles (no bus, no host)."""
    from commission.config import Config
    from commission.drive.canopen.pdo import record_signals
    from commission.excitation import chirp
    from commission.ident.hybrid import identify
    from commission.recording import LOST_SAMPLES_KEY, Recording, encode_samples
    from sim_drive.plant import Plant, PlantParameters

    rated, inc, ticks, rate = 0.637, 2**24, 4, 2000.0
    truth = PlantParameters()
    cfg = Config()
    targets = np.round(chirp(cfg.excitation).samples[::ticks] / rated * 1000).astype(np.int64)
    print("\nwhat a late host and lost frames cost the identifier (ideal 2 kHz cycle records, the plant's true "
          "parameters as reference; lost cycles rebuilt as the backend does and marked, the identifier not told)")
    cases = [("none", 0.0, 0.0, 1), ("30 % of setpoints late", 0.3, 0.0, 1), ("70 % late", 0.7, 0.0, 1),
             ("93 % late", 0.93, 0.0, 1), ("1 % cycles lost, single", 0.0, 0.01, 1),
             ("5 % cycles lost, single", 0.0, 0.05, 1), ("1 % lost in gaps of 5", 0.0, 0.01, 5),
             ("1 % lost in gaps of 20", 0.0, 0.01, 20)]
    for label, late, lost_frac, burst in cases:
        rng = np.random.default_rng(1)
        applied = targets.copy()
        for k in np.flatnonzero(rng.random(targets.size) < late):
            if k:
                applied[k] = applied[k - 1]  # the drive held the previous cycle's setpoint
        r = Plant(truth, 8000.0).run_torque(np.concatenate((np.zeros(ticks), np.repeat(applied * rated / 1000, ticks))))
        counts = np.round(r.motor_position[::ticks] * inc / (2 * np.pi)).astype(np.int64)
        n = targets.size
        ok = np.ones(n + 1, dtype=bool)
        if lost_frac:
            starts = rng.choice(n - burst - 2, int(lost_frac * n / burst), replace=False) + 1
            for a in starts:
                ok[a : a + burst] = False
        torque, velocity, position, lost = record_signals(counts[: n + 1], np.concatenate(([0], applied)), targets,
                                                          ok, rate, rated, inc)
        meta = {LOST_SAMPLES_KEY: encode_samples(lost)} if lost.any() else {}
        rec = Recording.uniform(rate, torque, velocity, motor_position=position, metadata=meta)
        t0 = time.perf_counter()
        res = identify(rec, cfg.identification)
        eps = np.degrees(res.epsilon_rad) - truth.epsilon_deg
        rel = {k: getattr(res.parameters, k) / getattr(truth, k) - 1 for k in ("J_m", "J_l", "K")}
        fit = res.to_dict(None).get("fit", {})
        flag = "  (approximate)" if fit.get("approximate") else ""
        print(f"  {label:<26} Δε {eps:+.4f}°  ΔJ_m {rel['J_m']:+.3%}  ΔJ_l {rel['J_l']:+.3%}  ΔK {rel['K']:+.3%}  "
              f"residual {fit.get('residual_ratio', float('nan')):.2%}{flag}  {time.perf_counter() - t0:.1f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--slcan-runs", type=int, default=5)
    ap.add_argument("--no-hog", action="store_true")
    ap.add_argument("--tune", action="store_true", help="also design and verify the controller (slower)")
    ap.add_argument("--robustness-only", action="store_true", help="only part 4 (no bus, no processes)")
    opt = ap.parse_args()
    if opt.robustness_only:
        robustness()
        return
    hog = not opt.no_hog
    print(f"host: {os.cpu_count()} cores; load average {os.getloadavg()[0]:.1f} before the runs")
    with tempfile.TemporaryDirectory(prefix="bench-streamed-") as d:
        tmp = Path(d)
        code, doc, err, wall = commission(["--sim"], tmp / "direct", opt.tune)
        if code != 0 or doc is None:
            raise SystemExit(f"the direct run failed: {err}")
        ref = figures(doc)
        print(f"reference (commission --sim, {wall:.0f} s): ε {ref['eps_deg']:.5f}°  J_m {ref['J_m']:.6g}  "
              f"J_l {ref['J_l']:.6g}  K {ref['K']:.6g}")
        series("canopen streamed (--sim --sim-link canopen --drive generic-cia402)", opt.runs,
               lambda _: ["--sim", "--sim-link", "canopen", "--drive", "generic-cia402"], ref, tmp, opt.tune, hog)
        if opt.slcan_runs:
            series("slcan, no --drive (identity -> sim: trace)", opt.slcan_runs,
                   lambda sim: ["--port", sim.port, "--interface", "slcan"], ref, tmp, opt.tune, hog, [])
            series("slcan streamed (--drive generic-cia402)", opt.slcan_runs,
                   lambda sim: ["--port", sim.port, "--interface", "slcan", "--drive", "generic-cia402"],
                   ref, tmp, opt.tune, hog, [])
    robustness()


if __name__ == "__main__":
    main()
