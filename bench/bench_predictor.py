"""The cost of one pass of the identifier's two compiled models, per record sample.

Every fit of the identifier evaluates one of them again and again (a Kalman fit some hundreds of times):
the Kalman predictor (``commission.ident.kalman.innovations``: the plain pass, and the pass with sigma
points across the gap that the hedged fits use) and the load simulation of the torque residual
(``commission.ident.residual.simulate_load``, open loop and with the observer). Each is timed at the
member's true parameters on members of the plant family chosen for their spread (motor side and load
encoder, 2–16 kHz, few and many contact events), a warm call first, then the median of ``--repeat``
passes, printed in ms and in ns per sample. Nothing is asserted; a code change that should leave the
results alone (a faster kernel) is compared by running this before and after it.

    python bench/bench_predictor.py
    python bench/bench_predictor.py --members 23:0,22:14 --repeat 21
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable
from typing import Any

from commission.ident.consistency import rebuilt_position_noise_rad
from commission.ident.kalman import innovations, kalman_problem
from commission.ident.residual import Observer, motor_part, motor_position_samples, prepare_residual, simulate_load
from commission.ident.twomass import TwoMassParameters, modes
from sim_drive.family import member

MEMBERS = "23:0,23:4,23:12,23:13,23:21,22:14,24:8"
"""Family members (seed:index): 8 and 16 kHz motor side, 16 kHz with a load encoder, a 5 kHz velocity log, and
three with many contact events per second (2 kHz, 8 kHz)."""


def _median_s(f: Callable[[], Any], repeat: int) -> float:
    f()  # (compiles, or loads the cache, the first time)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--members", default=MEMBERS, help=f"comma-separated seed:index (default {MEMBERS})")
    ap.add_argument("--repeat", type=int, default=9, help="timed passes per model and member (default 9)")
    args = ap.parse_args(argv)
    print(f"{'member':<8} {'record':<24} {'predictor':>18} {'sigma points':>18} {'open loop':>18} "
          f"{'observer':>18}   (median ms, ns per sample)")
    for spec in args.members.split(","):
        seed, index = (int(v) for v in spec.split(":"))
        m = member(seed, index)
        rec = m.simulate()
        truth = m.to_dict()
        p = TwoMassParameters(**truth["two_mass"])
        eps = math.radians(truth["epsilon_deg"])
        fs = rec.sample_rate_hz
        kp = kalman_problem(rec.torque_ref, motor_position_samples(rec.motor_position, rec.motor_velocity, fs), fs,
                            load_position=rec.load_position, motor_noise_rad=rebuilt_position_noise_rad(rec))
        q = 1e-3 * kp.torque_rms_nm
        rp = prepare_residual(rec.torque_ref, fs, motor_position=rec.motor_position,
                              motor_velocity=rec.motor_velocity, load_position=rec.load_position)
        motor = motor_part(rp, p.J_m, p.B_m)
        # (as the identifier's fit stage designs it: its bandwidth a share of the resonance, a 2× low-pass)
        fc = modes(p).f_resonance_hz
        observer = Observer.design(fs, 0.5 * fc, 2.0 * fc, p.K, p.D, rec.load_position is not None)
        passes = {
            "predictor": lambda: innovations(kp, p, eps, process_noise_nm=q),
            "sigma": lambda: innovations(kp, p, eps, process_noise_nm=q, sigma_points=True,
                                         twist_noise_rad=1e-4 * eps),
            "open": lambda: simulate_load(rp, p.J_l, p.B_l, p.K, p.D, eps, None, motor=motor),
            "observer": lambda: simulate_load(rp, p.J_l, p.B_l, p.K, p.D, eps, None, motor=motor,
                                              observer=observer),
        }
        n = rec.torque_ref.size
        cells = []
        for f in passes.values():
            s = _median_s(f, args.repeat)
            cells.append(f"{1e3 * s:8.2f} {1e9 * s / n:6.0f} ns")
        label = f"{fs / 1e3:g} kHz {truth['duration_s']:g} s {truth['sensors']}"
        print(f"{spec:<8} {label:<24} " + " ".join(f"{c:>18}" for c in cells), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
