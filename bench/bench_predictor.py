"""What the drift-free residual leaves at the true parameters, without and with a load-state predictor.

Issue 8, part 4 (impact-rich plants), an exploration, not the identifier's code. The identifier
re-simulates the load from the sampled motor position, open loop in the load: on a stiff,
lightly damped load with many impacts that simulation decorrelates from the real load (the
bouncing in the gap is chaotic), and even the true parameters leave a large residual (stiff
300 Hz: ~80 % of τ_ref). A predictor feeds the motor equation's residual e back into the
simulated load state after every sample, as a Newton step on the shaft torque:
x_l += α·e/K, v_l += β·e/(K·Ts). α = β = 0 is the plain residual.

Printed per plant and gain: RMS of the low-passed residual / RMS τ_ref at the true parameters
and with ε off by −10 % / +10 % (how sharp ε stays). The load simulation here is its own:
fixed-step RK4 (8 sub-steps per sample) on the exact dead zone, motor position from the
identifier's interpolant; it reproduces the identifier's figures for α = β = 0.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from numba import njit
from scipy.signal import butter, sosfiltfilt

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_identify import FULL, Case, record  # noqa: E402

from commission.ident.residual import prepare_residual  # noqa: E402

FS = 8000.0
#: (α, β) gains of the predictor; (0, 0) is the plain residual.
GAINS = ((0.0, 0.0), (0.05, 0.0), (0.1, 0.0), (0.1, 0.01), (0.2, 0.02))
CASES = [c for c in FULL if c.name in ("reference", "ref zeta=0.07 e=0.25", "stiff light 200Hz", "stiff 300Hz")] + [
    Case("mid 100Hz zeta0.05", 1.0, 100, 0.05, 0.20),
]


@njit(cache=True)
def _shaft(c: np.ndarray, k: int, s: float, Ts: float, x: float, v: float,
           K: float, D: float, eps: float) -> float:
    a3, a2, a1, a0 = c[k, 0], c[k, 1], c[k, 2], c[k, 3]
    z = ((a3 * s + a2) * s + a1) * s + a0 - x
    if -eps <= z <= eps:
        return 0.0
    vm = ((3.0 * a3 * s + 2.0 * a2) * s + a1) / Ts
    return K * (z - eps if z > eps else z + eps) + D * (vm - v)


@njit(cache=True)
def _innovations(c: np.ndarray, Ts: float, torque: np.ndarray, acc: np.ndarray, vel: np.ndarray,
                 J_m: float, B_m: float, J_l: float, B_l: float, K: float, D: float, eps: float,
                 xl0: float, alpha: float, beta: float, nsub: int) -> np.ndarray:
    """Motor-equation residual at samples 1 … N−2 [N·m] with the load state corrected after each."""
    m = c.shape[0]
    T = np.zeros(m + 1)  # triangle-averaged simulated shaft torque at the samples
    E = np.zeros(m + 1)
    x, v = xl0, 0.0
    h = Ts / nsub
    for k in range(m):
        for j in range(nsub):
            s0 = j / nsub
            sm = s0 + 0.5 / nsub
            s1 = s0 + 1.0 / nsub
            t1 = _shaft(c, k, s0, Ts, x, v, K, D, eps)
            a1 = (t1 - B_l * v) / J_l
            t2 = _shaft(c, k, sm, Ts, x + 0.5 * h * v, v + 0.5 * h * a1, K, D, eps)
            v2 = v + 0.5 * h * a1
            a2 = (t2 - B_l * v2) / J_l
            v3 = v + 0.5 * h * a2
            t3 = _shaft(c, k, sm, Ts, x + 0.5 * h * v2, v3, K, D, eps)
            a3 = (t3 - B_l * v3) / J_l
            v4 = v + h * a3
            t4 = _shaft(c, k, s1, Ts, x + h * v3, v4, K, D, eps)
            a4 = (t4 - B_l * v4) / J_l
            x += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            tm = 0.5 * (t2 + t3)
            w = 1.0 / (6.0 * nsub)  # Simpson on the sub-step, weights 1 − s (sample k), s (k + 1)
            T[k] += w * ((1.0 - s0) * t1 + 4.0 * (1.0 - sm) * tm + (1.0 - s1) * t4)
            T[k + 1] += w * (s0 * t1 + 4.0 * sm * tm + s1 * t4)
        if k >= 1:  # sample k complete: its residual corrects the state at k + 1
            e = J_m * acc[k - 1] + B_m * vel[k - 1] + T[k] - torque[k - 1]
            E[k] = e
            x += alpha * e / K
            v += beta * e / (K * Ts)
    return E[1:-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1, help="noise seed of the records")
    args = ap.parse_args()
    sos = butter(4, 400.0, fs=FS, output="sos")
    print("RMS residual / RMS τ_ref at the true parameters (and ε −10 % / +10 %); 400 Hz low-pass")
    print(f"{'plant':22s} {'α':>5s} {'β':>6s} {'truth':>9s} {'ε −10 %':>9s} {'ε +10 %':>9s}")
    for case in CASES:
        p = case.params()
        rec = record(case, seed=args.seed)
        pr = prepare_residual(rec.torque_ref, FS, motor_position=rec.motor_position, cutoff_hz=400.0)
        ref = float(np.sqrt(np.mean(sosfiltfilt(sos, pr.torque) ** 2)))
        eps = math.radians(case.eps_deg)
        for alpha, beta in GAINS:
            ratios = []
            for f in (1.0, 0.9, 1.1):
                e = _innovations(pr.spline, 1.0 / FS, pr.torque, pr.acceleration, pr.velocity, p.J_m, p.B_m,
                                 p.J_l, p.B_l, p.K, p.D, eps * f, -pr.initial_twist_rad, alpha, beta, 8)
                r = sosfiltfilt(sos, e)[400:-400]  # the filter's edges left out
                ratios.append(float(np.sqrt(np.mean(r * r))) / ref)
            print(f"{case.name:22s} {alpha:5.2f} {beta:6.3f} {ratios[0]:9.5f} {ratios[1]:9.5f} {ratios[2]:9.5f}",
                  flush=True)


if __name__ == "__main__":
    main()
