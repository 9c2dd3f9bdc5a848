"""The estimator's basin on the plant family (issue 22): how far off a start it recovers a plant from.

For each member, the Kalman prediction-error fit (``commission.ident.estimator.kalman_fit``, the
identifier's estimate) is started from the member's true plant with J_m, J_l and K moved by ± an
offset, one start each way — (1+o, 1−o, 1+o) and (1−o, 1+o, 1−o), D by the square root of K's
factor; ε, the friction and the current loop at their true values with their terms on — and judged
by bench_family's tolerances. No start stage, no scan, no torque-residual fit: what is measured is
the estimator alone, the part the issue asks to be "right by construction", on the records it will
get. Printed per member and start: recovered or not, the estimate's errors, the disturbance its
noise model needs, time; then the share recovered per offset by sensors and by K·ε/A (the shaft
torque that closes the gap against the chirp's amplitude: above ~3 the gear rattles through the
record, bench/results/family.md).

``--search powell`` measures a derivative-free descent on the same likelihood instead (the estimator's
finite-difference steps see a likelihood that is rugged at their scale on the rattling records):
Powell's conjugate directions on the Cauchy likelihood of (ln J_m, ln J_l, ln K, ln D, ln ε), the other
coordinates held at the start's, over a continuation in the torque disturbance (``POWELL_LEVELS``), with
the estimator's larger load share of it or ``--load-share`` (a larger share makes the predictor take the
load's state more from the record: a smoother likelihood on records with few contacts per cycle).

    python bench/bench_basin.py                                  # 8 members of seed 22, offset 0.1, ~5 min
    python bench/bench_basin.py --seed 24 --only 0,43,49 --offsets 0.03,0.1,0.3 --jobs 2
    python bench/bench_basin.py --seed 24 --only 2,8,49 --search powell --jobs 2
    python bench/bench_basin.py --seed 24 --only 2,8,49 --search powell --load-share 3 --jobs 2
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import sys
import time
from contextlib import nullcontext
from dataclasses import replace
from typing import Any

import numpy as np
from bench_family import judge, label, options_for

from commission.exceptions import IdentificationError
from commission.ident.estimator import _LOAD_SHARES, ModelTerms, PemFit, _coordinates, _KalmanObjective, kalman_fit
from commission.ident.kalman import kalman_problem
from commission.ident.residual import motor_position_samples
from commission.ident.twomass import TwoMassParameters, modes
from sim_drive.family import DEFAULT_SEED, Sensors, member

#: The default members: seed 22's first eight (every sensor set, both sides of K·ε/A = 3).
DEFAULT_ONLY = "0,1,2,3,4,5,6,7"
#: K·ε/A above which a motor-side record rattles through the gap (bench/results/family.md, seed 22 and 24).
RATTLE = 3.0
#: ``--search powell``: the torque disturbances (relative to RMS τ_ref) of the noise model the descent is
#: run at in turn (a larger one smooths the likelihood), the evaluations at each, and the bound on each
#: log-coordinate around the start (ln 10: a start a decade off is still inside).
POWELL_LEVELS = (0.1, 0.03, 0.01)
POWELL_EVALUATIONS = 300
POWELL_SPAN = math.log(10.0)


def start_from(m: Any, offset: float, sign: int) -> PemFit:
    """The member's true plant moved by ``offset``: J_m, K by (1 + sign·offset), J_l the other way."""
    up, down = 1.0 + sign * offset, 1.0 - sign * offset
    p = m.two_mass
    moved = replace(p, J_m=p.J_m * up, J_l=p.J_l * down, K=p.K * up, D=p.D * math.sqrt(up))
    lag = 1.0 / (2.0 * math.pi * m.current_loop_bandwidth_hz) if m.current_loop_bandwidth_hz else 0.0
    terms = ModelTerms(coulomb_motor=m.coulomb_motor_nm > 0, coulomb_load=m.coulomb_load_nm > 0, current_loop=lag > 0)
    # only the coordinates are read from a start (its residual, covariance and the like are the fit's own)
    return PemFit(moved, math.radians(m.epsilon_deg), m.coulomb_motor_nm, m.coulomb_load_nm, lag, terms,
                  np.zeros(0), math.nan, (), np.zeros((0, 0)), math.nan, 0, False, "a start")


def rattle(m: Any) -> float:
    """K·ε/A: the shaft torque at a twist of ε against the chirp's amplitude [-]."""
    return m.two_mass.K * math.radians(m.epsilon_deg) / m.excitation.amplitude_nm


def powell_fit(kp: Any, start: PemFit, epsilon_max_rad: float,
               load_share: float = _LOAD_SHARES[-1]) -> tuple[TwoMassParameters, float, float]:
    """Powell's descent on the Cauchy prediction-error likelihood from ``start``, at each of
    ``POWELL_LEVELS`` in turn, ``load_share`` of the disturbance on the load (default: the estimator's
    larger share): (plant, ε [rad], the last level's torque disturbance [N·m])."""
    from scipy.optimize import minimize

    def objective(level: float) -> _KalmanObjective:
        return _KalmanObjective(kp, start.terms, level * kp.torque_rms_nm, load_share, robust=True)

    free = [0, 1, 4, 5]  # ln J_m, ln J_l, ln K, ln D in the estimator's coordinates; ln ε appended
    z0 = _coordinates(start, objective(POWELL_LEVELS[0]), epsilon_max_rad, kp.torque_rms_nm)[0]
    eps_lo = math.log(1e-3)  # [ln deg]

    def coordinates(y: np.ndarray) -> np.ndarray:
        z = z0.copy()
        z[free], z[6] = y[:4], math.exp(y[4])
        return z

    y = np.r_[z0[free], math.log(max(z0[6], math.exp(eps_lo)))]
    bounds = [(v - POWELL_SPAN, v + POWELL_SPAN) for v in y[:4]] + [(eps_lo, math.log(math.degrees(epsilon_max_rad)))]
    for level in POWELL_LEVELS:
        obj = objective(level)
        y = minimize(lambda v: float(np.sum(obj(coordinates(v), remember=False) ** 2)), y, method="Powell",
                     bounds=bounds, options={"maxfev": POWELL_EVALUATIONS, "xtol": 1e-3, "ftol": 1e-6}).x
    p, eps, _ = obj.unpack(coordinates(y))
    return p, eps, POWELL_LEVELS[-1] * kp.torque_rms_nm


def evaluate(args: tuple[int, int, float, int, str, float]) -> dict[str, Any]:
    """One member, one start: the fit's errors, within tolerance or not, its time [s]."""
    seed, index, offset, sign, search, load_share = args
    m = member(seed, index)
    rec = m.simulate()
    opt = options_for(m)
    fs = rec.sample_rate_hz
    kp = kalman_problem(rec.torque_ref, motor_position_samples(rec.motor_position, rec.motor_velocity, fs), fs,
                        load_position=rec.load_position if opt.use_load_encoder else None,
                        velocity_scale_rad_s=opt.coulomb_velocity_scale_rad_s)
    epsilon_max_rad = math.radians(max(4.0 * m.epsilon_deg, 2.0 * opt.epsilon_bounds_deg[1]))
    t0 = time.perf_counter()
    if search == "powell":
        p, eps, disturbance_nm = powell_fit(kp, start_from(m, offset, sign), epsilon_max_rad, load_share)
    else:
        fit = kalman_fit(kp, start_from(m, offset, sign), threads=opt.threads, max_nfev=opt.max_fit_evaluations,
                         epsilon_max_rad=epsilon_max_rad)
        p, eps, disturbance_nm = fit.parameters, fit.epsilon_rad, fit.process_noise_nm
    seconds = time.perf_counter() - t0
    est = {**p.as_dict(), "epsilon_deg": math.degrees(eps)}
    try:
        md = modes(p)
        est.update(f_resonance_hz=md.f_resonance_hz, f_antiresonance_hz=md.f_antiresonance_hz)
    except IdentificationError:  # an estimate with no resonance: its modes are out of tolerance
        est.update(f_resonance_hz=math.nan, f_antiresonance_hz=math.nan)
    j = judge(m.to_dict(), est)
    return {"id": m.id, "index": index, "offset": offset, "sign": sign, "label": label(m),
            "sensors": m.sensors.value, "rattle": rattle(m), "within": all(j["within"].values()),
            "errors": j["errors"], "disturbance": disturbance_nm / kp.torque_rms_nm, "time_s": seconds}


def _line(r: dict[str, Any]) -> str:
    e = r["errors"]
    mark = "recovered" if r["within"] else "NOT recovered"
    return (f"  {r['id']} {'+' if r['sign'] > 0 else '−'}{r['offset']:g}  {mark:<13} ε {e['epsilon_deg']:+.4f}°  "
            f"J_m {100 * e['J_m']:+6.2f} %  J_l {100 * e['J_l']:+6.2f} %  K {100 * e['K']:+6.2f} %  "
            f"disturbance {100 * r['disturbance']:.2g} %  {r['time_s']:5.1f} s")


def _group(r: dict[str, Any]) -> str:
    if r["sensors"] == Sensors.LOAD_ENCODER.value:
        return "load encoder"
    return f"{'motor side' if r['sensors'] == Sensors.MOTOR.value else 'velocity only'}, K·ε/A {'>' if r['rattle'] > RATTLE else '≤'} {RATTLE:g}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED, help=f"family seed (default {DEFAULT_SEED})")
    ap.add_argument("--only", default=DEFAULT_ONLY, help=f"comma-separated member indices (default {DEFAULT_ONLY})")
    ap.add_argument("--offsets", default="0.1", help="comma-separated relative offsets of J_m, J_l, K (default 0.1)")
    ap.add_argument("--jobs", type=int, default=1, help="processes (>1: times are then not representative)")
    ap.add_argument("--search", choices=("kalman", "powell"), default="kalman",
                    help="kalman: the identifier's estimator (kalman_fit, default); powell: a derivative-free "
                         "descent on its likelihood (the disturbance printed is then the last level's)")
    ap.add_argument("--load-share", type=float, default=_LOAD_SHARES[-1],
                    help=f"--search powell: the load's share of the torque disturbance (default {_LOAD_SHARES[-1]:g}, "
                         "the estimator's larger one)")
    args = ap.parse_args(argv)
    try:
        indices = sorted({int(s) for s in args.only.split(",")})
        offsets = sorted({float(s) for s in args.offsets.split(",")})
    except ValueError:
        ap.error("--only takes integers, --offsets numbers, comma-separated")
    if args.jobs < 1 or not all(0.0 < o < 1.0 for o in offsets) or not args.load_share >= 0.0:
        ap.error("--jobs must be ≥ 1, each offset in (0, 1) and --load-share ≥ 0")
    if args.search != "powell" and args.load_share != _LOAD_SHARES[-1]:
        ap.error("--load-share applies to --search powell (kalman_fit chooses its own)")
    timing = "sequential" if args.jobs == 1 else f"{args.jobs} processes: NOT representative"
    search = args.search + (f", load share {args.load_share:g}" if args.search == "powell" else "")
    print(f"# estimator basin ({search}), family seed {args.seed}, members {','.join(map(str, indices))}, offsets "
          f"{', '.join(f'±{o:g}' for o in offsets)}; {timing}; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores")
    tasks = [(args.seed, i, o, s, args.search, args.load_share) for i in indices for o in offsets for s in (1, -1)]
    rows: list[dict[str, Any]] = []
    labels: dict[str, str] = {}
    # --jobs 1: in this process, the times without another process beside them
    with multiprocessing.get_context("spawn").Pool(args.jobs) if args.jobs > 1 else nullcontext() as pool:
        for r in (pool.imap(evaluate, tasks) if pool is not None else map(evaluate, tasks)):
            if r["id"] not in labels:
                labels[r["id"]] = r["label"]
                print(f"{r['id']}  {r['label']}, K·ε/A {r['rattle']:.2g}", flush=True)
            rows.append(r)
            print(_line(r), flush=True)
    print("\nrecovered (within bench_family's tolerances), by class and offset:")
    for g in sorted({_group(r) for r in rows}):
        cells = []
        for o in offsets:
            sel = [r for r in rows if _group(r) == g and r["offset"] == o]
            cells.append(f"±{o:g}: {sum(r['within'] for r in sel)} of {len(sel)}")
        print(f"  {g:<32} " + "   ".join(cells))
    times = [r["time_s"] for r in rows]
    print(f"time per fit [s] ({timing}): median {np.median(times):.1f}, max {max(times):.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
