"""How many times faster than real time the simulated drive runs the paper's experiment.

The whole drive path: SimDrive (CiA 402 traffic) → SimulatedDevice (player, limits,
trace in 10 ms chunks) → Plant, for the 10 s, 8 kHz chirp. Target: ≥ 100× real time.
Run: python bench/bench_sim_drive.py
"""

from __future__ import annotations

import statistics
import time

from commission.config import Config
from commission.drive.sim import SimDrive
from commission.excitation import chirp

RUNS = 7


def one_run(samples) -> float:
    drive = SimDrive()
    drive.set_limits(0.5, 50.0, 200.0)
    drive.enable()
    t0 = time.perf_counter()
    drive.run_excitation(samples, 8000.0)
    elapsed = time.perf_counter() - t0
    drive.close()
    return elapsed


def main() -> None:
    wave = chirp(Config().excitation)
    t0 = time.perf_counter()
    first = one_run(wave.samples)
    startup = time.perf_counter() - t0
    times = [one_run(wave.samples) for _ in range(RUNS)]
    med = statistics.median(times)
    print("simulated drive, 10 s chirp at 8 kHz (80,000 samples), SimDrive end to end")
    print(f"  first run (incl. numba load/compile) {first * 1e3:8.1f} ms   ({startup:.2f} s with setup)")
    print(f"  median of {RUNS}                      {med * 1e3:8.1f} ms   (min {min(times) * 1e3:.1f}, max {max(times) * 1e3:.1f})")
    print(f"  real-time factor                    {wave.duration_s / med:8.0f} x   (target >= 100 x)")


if __name__ == "__main__":
    main()
