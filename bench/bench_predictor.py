"""What the drift-free residual leaves at the true parameters, without and with a load-state predictor.

Issue 8, part 4 (impact-rich plants), an exploration, not the identifier's code. The identifier
re-simulates the load from the sampled motor position, open loop in the load: on a stiff,
lightly damped load with many impacts that simulation decorrelates from the real load (the
bouncing in the gap is chaotic), and even the true parameters leave a large residual (stiff
300 Hz: ~80 % of τ_ref). A predictor feeds the motor equation's residual e back into the
simulated load state after every sample, as a Newton step on the shaft torque:
x_l += α·e/K, v_l += β·e/(K·Ts) (:func:`commission.ident.residual.predictor_residual`, which
the identifier uses to refine results it would otherwise report approximate). α = β = 0 is the
plain residual.

Printed per plant and gain: RMS of the low-passed residual / RMS τ_ref at the true parameters
and with ε off by −10 % / +10 % (how sharp ε stays). The predictor's load simulation is
fixed-step RK4 (8 sub-steps per sample) on the exact dead zone, motor position from the
identifier's interpolant; for α = β = 0 it reproduces the plain residual's figures.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_identify import FULL, Case, record  # noqa: E402

from commission.ident.residual import predictor_residual, prepare_residual  # noqa: E402

FS = 8000.0
#: (α, β) gains of the predictor; (0, 0) is the plain residual.
GAINS = ((0.0, 0.0), (0.05, 0.0), (0.1, 0.0), (0.1, 0.01), (0.2, 0.02), (0.5, 0.0))
CASES = [c for c in FULL if c.name in ("reference", "ref zeta=0.07 e=0.25", "stiff light 200Hz", "stiff 300Hz")] + [
    Case("mid 100Hz zeta0.05", 1.0, 100, 0.05, 0.20),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1, help="noise seed of the records")
    args = ap.parse_args()
    print("RMS residual / RMS τ_ref at the true parameters (and ε −10 % / +10 %); 400 Hz low-pass")
    print(f"{'plant':22s} {'α':>5s} {'β':>6s} {'truth':>9s} {'ε −10 %':>9s} {'ε +10 %':>9s}")
    for case in CASES:
        p = case.params()
        rec = record(case, seed=args.seed)
        pr = prepare_residual(rec.torque_ref, FS, motor_position=rec.motor_position, cutoff_hz=400.0)
        ref = float(np.sqrt(np.mean(pr.torque_f ** 2)))
        eps = math.radians(case.eps_deg)
        for alpha, beta in GAINS:
            ratios = []
            for f in (1.0, 0.9, 1.1):
                r = predictor_residual(pr, p.J_m, p.J_l, p.B_m, p.B_l, p.K, p.D, eps * f, gain=alpha,
                                       velocity_gain=beta)
                ratios.append(float(np.sqrt(np.mean(r * r))) / ref)
            print(f"{case.name:22s} {alpha:5.2f} {beta:6.3f} {ratios[0]:9.5f} {ratios[1]:9.5f} {ratios[2]:9.5f}",
                  flush=True)


if __name__ == "__main__":
    main()
