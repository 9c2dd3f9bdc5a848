"""Accuracy and time of the linear stage (estimate_frd + fit_transfer_function).

For several plants, with ε = 0 and ε = 0.4° (the simulator ``sim_drive.plant``,
24-bit motor encoder, no noise), the METHOD.md chirp: % error of J_m, J_l,
B_m + B_l, K, D and of the resonance / anti-resonance frequencies, and the
median time of each step. A second table shows the naive fit (plain ratio,
no transient term, no delay) for contrast.

    .venv/bin/python bench/bench_linear.py [--repeat N]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from commission.exceptions import IdentificationError
from commission.ident.frd import estimate_frd
from commission.ident.tffit import fit_transfer_function
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters, from_velocity_tf, modes

FS = 8000.0


def chirp_torque(T: float = 10.0, fs: float = FS) -> np.ndarray:
    A, f0, f1 = 0.0764, 0.1, 400.0
    t = np.arange(int(round(T * fs))) / fs
    return A * np.sin(2 * np.pi * (f0 * t + (f1 - f0) * t**2 / (2 * T))) + 3 * A * np.sin(2 * np.pi * 0.1 * t)


def plant_with(ratio: float, f_res_hz: float) -> TwoMassParameters:
    r = REFERENCE_PLANT
    J_l = ratio * r.J_m
    K = (2 * np.pi * f_res_hz) ** 2 * r.J_m * J_l / (r.J_m + J_l)
    return TwoMassParameters(r.J_m, J_l, r.B_m, r.B_l, K, r.D * np.sqrt(K / r.K))


PLANTS = {
    "reference (0.40, 65 Hz)": REFERENCE_PLANT,
    "stiff light (0.2, 250 Hz)": plant_with(0.2, 250.0),
    "soft heavy (4, 25 Hz)": plant_with(4.0, 25.0),
    "heavy (5, 20 Hz)": plant_with(5.0, 20.0),
    "stiff (1, 300 Hz)": plant_with(1.0, 300.0),
}


def simulate(p: TwoMassParameters, eps_deg: float, tq: np.ndarray) -> np.ndarray:
    from sim_drive.plant import Plant, PlantParameters

    return Plant(PlantParameters(epsilon_deg=eps_deg, **p.as_dict()), FS).run_torque(tq).motor_velocity


def errors_pct(p: TwoMassParameters, num: np.ndarray, den: np.ndarray) -> list[float] | str:
    try:
        q = from_velocity_tf(num, den)
    except IdentificationError as err:
        return f"not physical: {str(err)[:60]}"
    mp, mq = modes(p), modes(q)
    return [
        100 * (q.J_m / p.J_m - 1), 100 * (q.J_l / p.J_l - 1),
        100 * ((q.B_m + q.B_l) / (p.B_m + p.B_l) - 1), 100 * (q.K / p.K - 1), 100 * (q.D / p.D - 1),
        100 * (mq.f_resonance_hz / mp.f_resonance_hz - 1),
        100 * (mq.f_antiresonance_hz / mp.f_antiresonance_hz - 1),
    ]


def median_time(fn, repeat: int) -> tuple[float, object]:  # type: ignore[no-untyped-def]
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="timing repeats (median)")
    args = ap.parse_args()
    tq = chirp_torque()
    cols = ["J_m", "J_l", "Bm+Bl", "K", "D", "f_r", "f_a"]
    head = f"{'plant (J_l/J_m, f_r)':27s} {'ε°':>4s} " + " ".join(f"{c:>8s}" for c in cols)
    rows, naive_rows = [], []
    for name, p in PLANTS.items():
        for eps in (0.0, 0.4):
            v = simulate(p, eps, tq)
            t_frd, frd = median_time(lambda: estimate_frd(tq, v, FS), args.repeat)
            t_fit, fit = median_time(lambda: fit_transfer_function(frd), args.repeat)  # type: ignore[arg-type]
            naive = fit_transfer_function(frd, delay_s=0.0, transient=False)  # type: ignore[arg-type]
            for out, f, extra in ((rows, fit, f" {1e3 * t_frd:6.0f} {1e3 * t_fit:6.0f} {fit.iterations:4d}"
                                   f" {'yes' if fit.constrained else 'no':>4s} {fit.fit_error:8.1e}"),
                                  (naive_rows, naive, f" {naive.fit_error:8.1e}")):
                e = errors_pct(p, f.num, f.den)
                cells = e if isinstance(e, str) else " ".join(f"{x:+8.3f}" for x in e)
                out.append(f"{name:27s} {eps:4.2f} {cells}{extra if not isinstance(e, str) else ''}")
    print("Linear stage: % error of the identified parameters (motor side, 24-bit, no noise)")
    print("t_frd / t_fit: median wall time [ms]; it: SK iterations; cstr: physical refit used\n")
    print(head + f" {'t_frd':>6s} {'t_fit':>6s} {'it':>4s} {'cstr':>4s} {'fit_err':>8s}")
    print("\n".join(rows))
    print("\nNaive fit for contrast (plain ratio Y/U: no transient term, no delay, no hold):\n")
    print(head + f" {'fit_err':>8s}")
    print("\n".join(naive_rows))


if __name__ == "__main__":
    main()
