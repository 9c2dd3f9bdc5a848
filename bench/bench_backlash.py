"""Benchmark of the identifier's backlash simulator, the ε searches and the paper's procedure.

Run: .venv/bin/python bench/bench_backlash.py [--quick]

Prints: compile / cache-load time, median simulate_deadzone time on the
80,000-sample experiment, accuracy against sim_drive's plant, BO vs grid on
the reference plant with the true linear parameters, and the paper method end
to end (true linear model, the package's FRD fit, a 1 %-off start).
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from commission.ident.backlash import (
    max_output_error,
    search_epsilon_bayes,
    search_epsilon_grid,
    simulate_deadzone,
    simulate_motor_velocity,
)
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters

FS = 8000.0
NAMES = ("J_m", "J_l", "B_m", "B_l", "K", "D")


def excitation(n: int = 80_000, *, bias: float = 3.0, T: float = 10.0) -> np.ndarray:
    t = np.arange(n) / FS
    A = 0.0764
    return A * np.sin(2 * np.pi * (0.1 * t + (400 - 0.1) * t**2 / (2 * T))) + bias * A * np.sin(
        2 * np.pi * 0.1 * t
    )


def row(*cols: object, widths: tuple[int, ...] = (44, 16, 16, 16)) -> None:
    print("  ".join(str(c).ljust(w) for c, w in zip(cols, widths)))


def first_call_time(empty_cache: bool) -> float:
    code = (
        "import time, numpy as np\n"
        "t0 = time.perf_counter()\n"
        "from commission.ident.backlash import simulate_deadzone\n"
        "from commission.ident.twomass import REFERENCE_PLANT\n"
        "simulate_deadzone(REFERENCE_PLANT, 0.007, np.zeros(100), 8000.0)\n"
        "print(time.perf_counter() - t0)\n"
    )
    env = dict(os.environ)
    with tempfile.TemporaryDirectory() as d:
        if empty_cache:
            env["NUMBA_CACHE_DIR"] = d
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def timing(f, n: int) -> tuple[float, float]:
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), float(np.min(ts))


def pct(p: TwoMassParameters) -> str:
    e = 100 * (p.as_array() / REFERENCE_PLANT.as_array() - 1)
    return " ".join(f"{n} {v:+.2f}%" for n, v in zip(NAMES, e))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="skip the slow paper-method runs")
    args = ap.parse_args()
    eps = math.radians(0.40)
    tau = excitation()
    print(f"load average at start: {os.getloadavg()}  (2-core machine; timings are wall clock)")

    print("\n== simulate_deadzone, 80,000 samples, reference plant ==")
    row("case", "median [ms]", "min [ms]", "events")
    row("first call, empty numba cache (compile) [s]", f"{first_call_time(True):.2f}")
    row("first call, numba cache present [s]", f"{first_call_time(False):.2f}")
    simulate_deadzone(REFERENCE_PLANT, eps, tau, FS)
    for name, e, loc in (("ε = 0 (linear)", 0.0, True), ("ε = 0.40°, events located", eps, True),
                         ("ε = 0.40°, fixed step (no location)", eps, False)):
        med, mn = timing(lambda: simulate_deadzone(REFERENCE_PLANT, e, tau, FS, locate_events=loc), 50)
        r = simulate_deadzone(REFERENCE_PLANT, e, tau, FS, locate_events=loc)
        row(name, f"{1e3 * med:.2f}", f"{1e3 * mn:.2f}", r.n_events)
    for name, e in (("simulate_motor_velocity (loss fast path), ε=0.40°", eps),):
        med, mn = timing(lambda: simulate_motor_velocity(REFERENCE_PLANT, e, tau, FS), 50)
        row(name, f"{1e3 * med:.2f}", f"{1e3 * mn:.2f}")
    tau_nb = excitation(8000, bias=0.0, T=1.0)
    med, mn = timing(lambda: simulate_deadzone(REFERENCE_PLANT, eps, tau_nb, FS), 50)
    row("no-bias 1 s chirp (8,000 samples), ε=0.40°", f"{1e3 * med:.2f}", f"{1e3 * mn:.2f}",
        simulate_deadzone(REFERENCE_PLANT, eps, tau_nb, FS).n_events)

    try:
        from sim_drive.plant import Plant, PlantParameters
    except ImportError:
        print("sim_drive.plant not available: skipping the comparisons on plant data")
        return

    print("\n== accuracy vs sim_drive plant (RK4 + event location, 40 sub-steps, 32-bit encoders) ==")
    row("record", "max|Δv| [rad/s]", "max|Δtwist| [rad]", "fixed-step |Δv|")
    for name, tt in (("standard 10 s", tau), ("no-bias chirp 1 s", tau_nb)):
        ref = Plant(PlantParameters(encoder_bits_motor=32, encoder_bits_load=32), FS,
                    substeps_per_sample=40).run_torque(tt)
        r = simulate_deadzone(REFERENCE_PLANT, eps, tt, FS)
        rf = simulate_deadzone(REFERENCE_PLANT, eps, tt, FS, locate_events=False)
        row(name, f"{max_output_error(ref.motor_velocity, r.motor_velocity):.2e}",
            f"{np.max(np.abs(ref.twist - r.twist)):.2e}",
            f"{max_output_error(ref.motor_velocity, rf.motor_velocity):.2e}")
    print("  (velocity floor: 32-bit encoder step 2π/2³²·8000 = 1.2e-5 rad/s)")

    v = Plant(PlantParameters(), FS).run_torque(tau).motor_velocity  # 24-bit, ε = 0.40°

    def loss(e: float) -> float:
        return max_output_error(v, simulate_motor_velocity(REFERENCE_PLANT, e, tau, FS))

    print("\n== ε search, paper loss (eq. 31), true linear parameters, plant data ε = 0.40° ==")
    row("method", "ε found [deg]", "evaluations", "time [s]", widths=(44, 16, 16, 16))
    t0 = time.perf_counter()
    g = search_epsilon_grid(loss)
    row("grid (exhaustive, 100 points)", f"{g.epsilon_deg:.2f}", g.evaluations, f"{time.perf_counter() - t0:.2f}")
    for seed in (0, 1, 2):
        t0 = time.perf_counter()
        b = search_epsilon_bayes(loss, seed=seed)
        row(f"bayes (GP+EI, seed {seed})", f"{b.epsilon_deg:.2f}", b.evaluations, f"{time.perf_counter() - t0:.2f}")
    print(f"  loss at 0.01°: {loss(math.radians(0.01)):.3f} rad/s, at 0.40°: {g.loss:.4f} rad/s, "
          f"at ε=0: {loss(0.0):.3f}; interval {np.degrees(g.interval_rad).round(2)}°")

    if args.quick:
        return
    from commission.ident.frd import estimate_frd
    from commission.ident.paper import paper_identify
    from commission.ident.tffit import fit_transfer_function

    print("\n== paper method end to end (plant data, reference plant, ε = 0.40°) ==")
    t0 = time.perf_counter()
    fit = fit_transfer_function(estimate_frd(tau, v, FS))
    t_fit = time.perf_counter() - t0
    near = TwoMassParameters(*(REFERENCE_PLANT.as_array() * [1.01, 1 / 1.01, 1.01, 1.01, 1 / 1.01, 1.01]))
    cases = (
        ("true linear parameters", REFERENCE_PLANT, "output"),
        (f"package FRD + tffit (fit {t_fit:.1f} s)", fit, "output"),
        ("package FRD + tffit, eq.25 input corr.", fit, "input"),
        ("start 1 % off, output correction", near, "output"),
        ("start 1 % off, filtered input corr.", near, "input_filtered"),
    )
    for name, lf, corr in cases:
        t0 = time.perf_counter()
        res = paper_identify(tau, v, FS, lf, correction=corr, max_iterations=5, frd_tol=1e-3)
        el = time.perf_counter() - t0
        print(f"- {name}: {el:.1f} s, stop: {res.stop_reason}; "
              + ", ".join(f"{k} {t:.1f}s" for k, t in res.timings_s.items()))
        for it in res.iterations:
            print(f"    iter {it.index}: ε {it.epsilon_deg:.2f}° (err {it.epsilon_deg - 0.40:+.2f}°, "
                  f"detected {it.backlash_detected}) loss {it.loss:.4f} frd_error {it.frd_error:.4f} "
                  f"evals {it.search.evaluations}  {pct(it.params)}")
        print(f"    chosen: ε {res.epsilon_deg:.2f}°, frd_error {res.frd_error:.4f}, {pct(res.params)}")


if __name__ == "__main__":
    main()
