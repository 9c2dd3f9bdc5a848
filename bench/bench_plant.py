"""Speed and accuracy of the plant physics (commission.plant, the simulated drive's machine).

Run: ``python bench/bench_plant.py``. Prints

1. speed: median wall time of ``run_torque`` on METHOD.md's 10 s, 8 kHz chirp
   experiment (80,000 samples), its real-time factor and the first call's time
   (JIT compile, or loading numba's on-disk cache); the same for ``run_velocity``,
   and the per-call overhead when a drive loop feeds one sample at a time;
2. accuracy against the sub-step count, the measurement behind
   ``SUBSTEPS_PER_SAMPLE``: the largest difference of the true sampled motor/load
   velocity and twist to a 320-sub-step solution, with event location and with
   mode switches at sub-step boundaries only.

Part 2 calls the private kernel so that it can switch the encoders and the event
location off; the public API offers neither. To time a cold JIT compile rather than
a load from numba's cache, run with ``NUMBA_CACHE_DIR=$(mktemp -d)``.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from commission import plant as plant_module
from commission.plant import Plant, PlantParameters

FS = 8000.0
TS = 1.0 / FS
DURATION_S = 10.0
RUNS = 7


def method_chirp(amplitude: float = 0.0764, f0: float = 0.1, f1: float = 400.0) -> np.ndarray:
    """METHOD.md experiment, 80,000 samples:
    A·sin(2π(f0·t + (f1−f0)·t²/(2T))) + 3A·sin(2π·0.1·t)."""
    t = np.arange(int(DURATION_S * FS)) * TS
    phase = 2.0 * np.pi * (f0 * t + (f1 - f0) * t**2 / (2.0 * DURATION_S))
    return amplitude * np.sin(phase) + 3.0 * amplitude * np.sin(2.0 * np.pi * 0.1 * t)


def time_runs(run, reset) -> tuple[float, float, float]:
    """(first call, median wall time, median CPU time) [s] of RUNS calls; reset() before each.

    The CPU time is the process's, so it is less affected by other load on the machine.
    """
    reset()
    t0 = time.perf_counter()
    run()
    first = time.perf_counter() - t0
    wall, cpu = [], []
    for _ in range(RUNS):
        reset()
        t0, c0 = time.perf_counter(), time.process_time()
        run()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return first, float(np.median(wall)), float(np.median(cpu))


def speed() -> None:
    torque = method_chirp()
    velocity_ref = method_chirp(amplitude=5.0)  # rad/s: ±20 rad/s bias, ±5 rad/s chirp
    j = 4.78e-4 + 1.92e-4
    kp = 2.0 * math.pi * 30.0 * j  # 30 Hz velocity loop on the rigid-body inertia
    ki = kp * 2.0 * math.pi * 6.0
    cases = [
        ("torque, reference plant", PlantParameters(), lambda p: p.run_torque(torque)),
        ("torque, no backlash", PlantParameters(epsilon_deg=0.0), lambda p: p.run_torque(torque)),
        (
            "torque, all options",
            PlantParameters(
                coulomb_motor_nm=0.01,
                coulomb_load_nm=0.005,
                current_loop_bandwidth_hz=1000.0,
                torque_noise_nm=0.002,
            ),
            lambda p: p.run_torque(torque),
        ),
        (
            "velocity PI, reference plant",
            PlantParameters(),
            lambda p: p.run_velocity(velocity_ref, kp, ki, 0.64),
        ),
    ]
    print(f"Speed: {torque.size} samples = {DURATION_S:.0f} s at {FS / 1000:.0f} kHz, "
          f"median of {RUNS} runs")
    print(f"  {'case':<30} {'sub-steps':>9} {'first call':>11} {'median':>9} {'real-time x':>12} "
          f"{'CPU median':>11}")
    for name, params, run in cases:
        p = Plant(params)
        first, median, cpu = time_runs(lambda: run(p), p.reset)
        print(f"  {name:<30} {p.substeps_per_sample:>9d} {first * 1e3:>8.0f} ms "
              f"{median * 1e3:>6.1f} ms {DURATION_S / median:>11.0f}x {cpu * 1e3:>8.1f} ms")
    print(f"  (machine load average now: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
    stats = plant_module._simulate.stats
    loaded = "loaded from numba's cache" if sum(stats.cache_hits.values()) else "compiled"
    print(f"  (first call: kernel {loaded}; the median excludes it)")
    p = Plant(PlantParameters())
    one = np.zeros(1)
    n = 8000
    t0 = time.perf_counter()
    for _ in range(n):
        p.run_torque(one)
    per_call = (time.perf_counter() - t0) / n
    print(f"  one sample per call: {per_call * 1e6:.1f} µs per call "
          f"({TS / per_call:.1f}x real time at 8 kHz)")


def true_run(params: PlantParameters, u: np.ndarray, substeps: int, locate: bool) -> np.ndarray:
    """Rows: motor velocity, load velocity (sample means, encoders off), twist, shaft torque."""
    p = Plant(params, substeps_per_sample=substeps)
    # encoders off: rounding to 1e-14 rad is exact enough
    kernel = p.kernel._replace(encoder_step_motor_rad=1e-14, encoder_step_load_rad=1e-14)
    out = np.empty((7, u.size))
    plant_module._simulate(u, np.zeros(u.size), False, 0.0, 0.0, 0.0, p._s, kernel, locate, out)
    return out[[1, 3, 6, 5]]


def accuracy() -> None:
    torque = method_chirp()
    plants = [
        ("reference plant, 65 Hz", PlantParameters(), torque.size),
        # Its impacts near t = 5 s (bias crossing zero, chirp near 200 Hz) are chaotic:
        # solutions with any two step sizes part there, so compare the first 4 s.
        ("K x10, J_l 0.8e-4, 292 Hz", PlantParameters(K=231.0, J_l=0.8e-4), int(4 * FS)),
    ]
    print("\nAccuracy vs RK4 sub-steps per sample, METHOD.md chirp, ε = 0.4°: max |difference|")
    print("to 320 sub-steps with event location (true sampled velocities, encoders off)")
    print(f"  {'plant':<26} {'sub':>4} {'|λ|h':>6} {'v_m rad/s':>10} {'v_l rad/s':>10} "
          f"{'twist rad':>10} {'no-loc v_m':>11} {'no-loc v_l':>11}")
    for name, params, n in plants:
        rate = plant_module._fastest_contact_rate(params)
        ref = true_run(params, torque, 320, True)[:, :n]
        for substeps in (1, 2, 4, 8, 16):
            err = np.abs(true_run(params, torque, substeps, True)[:, :n] - ref).max(axis=1)
            err_nl = np.abs(true_run(params, torque, substeps, False)[:, :n] - ref).max(axis=1)
            mark = " <- default" if substeps == plant_module.SUBSTEPS_PER_SAMPLE else ""
            print(f"  {name:<26} {substeps:>4d} {rate * TS / substeps:>6.3f} {err[0]:>10.1e} "
                  f"{err[1]:>10.1e} {err[2]:>10.1e} {err_nl[0]:>11.1e} {err_nl[1]:>11.1e}{mark}")
    params = PlantParameters(K=231.0, J_l=0.8e-4)
    a = true_run(params, torque, 160, True)
    b = true_run(params, torque, 320, True)
    print(f"  chaos check, 292 Hz plant over 10 s: 160 vs 320 sub-steps differ by "
          f"{np.abs(a[0] - b[0]).max():.2f} rad/s (motor), {np.abs(a[1] - b[1]).max():.2f} "
          f"rad/s (load)")
    quantum = 2.0 * math.pi / 2**24 / TS
    print(f"  (velocity quantum of a 24-bit encoder at 8 kHz: {quantum:.1e} rad/s)")


if __name__ == "__main__":
    speed()
    accuracy()
