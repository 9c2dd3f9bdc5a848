"""Robustness of the default (hybrid) identifier over noise seeds.

The lightly damped and friction plants are path-sensitive: a change to the fit's arithmetic can
move which local minimum a pass ends in on one seed and not another. Run this before and after
such a change. Per plant (bench_identify.py's spread, motor-side data only) and seed, it prints
the error of ε [deg], the largest error of J_m, J_l, K [%], of the modes [%], whether the issue's
tolerances hold (ε ±0.02°, J and K 3 %, modes 1 %), the wall time and whether the second pass
was taken; then a summary per plant: seeds within tolerance, median and mean wall time.

    python bench/bench_seeds.py                                  # the issue-8 plants, seeds 1–6
    python bench/bench_seeds.py --plants "ref zeta=0.07 e=0.25" --seeds 1-15
    python bench/bench_seeds.py --noise 1e-3                     # 10× the torque noise
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_identify import FULL, record  # noqa: E402

from commission.exceptions import IdentificationError  # noqa: E402
from commission.ident.hybrid import IdentificationOptions, identify  # noqa: E402
from commission.ident.twomass import modes  # noqa: E402

DEFAULT_PLANTS = ("ref zeta=0.07 e=0.25", "reference +coulomb", "reference +lag1k", "reference +both")


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", default=",".join(DEFAULT_PLANTS), help="comma-separated bench_identify plant names")
    ap.add_argument("--seeds", default="1-6", help="noise seeds, e.g. 1-6 or 1,4,9")
    ap.add_argument("--noise", type=float, default=1e-4, help="torque noise [N·m] (default 1e-4)")
    args = ap.parse_args()
    names = [n.strip() for n in args.plants.split(",")]
    unknown = set(names) - {c.name for c in FULL}
    if unknown:
        ap.error(f"unknown plants: {', '.join(sorted(unknown))}")
    # warm-up (numba's compiled kernels load or compile on first use): not timed
    identify(record(FULL[0], seed=0))
    print(f"# load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; torque noise {args.noise:g} N·m")
    for case in (c for c in FULL if c.name in names):
        p = case.params()
        walls: list[float] = []
        ok_count = 0
        seeds = _seeds(args.seeds)
        for seed in seeds:
            rec = record(case, seed=seed, noise_nm=args.noise)
            t0 = time.perf_counter()
            try:
                res = identify(rec, IdentificationOptions(max_residual_ratio=1.0))
            except IdentificationError as err:
                print(f"{case.name:24s} seed {seed:2d}: error: {err}", flush=True)
                continue
            wall = time.perf_counter() - t0
            walls.append(wall)
            jk = max(abs(getattr(res.parameters, k) / getattr(p, k) - 1) * 100 for k in ("J_m", "J_l", "K"))
            mi, mt = res.modes, modes(p)
            fm = 100 * max(abs(mi.f_resonance_hz / mt.f_resonance_hz - 1),
                           abs(mi.f_antiresonance_hz / mt.f_antiresonance_hz - 1))
            de = res.epsilon_deg - case.eps_deg
            ok = abs(de) <= 0.02 and jk <= 3 and fm <= 1
            ok_count += ok
            sp = res.stage("joint").detail.get("second_pass")
            second = "-" if not sp else ("taken" if sp["taken"] else "not taken")
            print(f"{case.name:24s} seed {seed:2d}: Δε {de:+.4f}°  J,K {jk:5.2f} %  modes {fm:4.2f} %  "
                  f"{'ok ' if ok else 'OFF'}  {wall:5.2f} s  second pass {second}", flush=True)
        if walls:
            print(f"{case.name:24s} within tolerance on {ok_count} of {len(seeds)} seeds; wall median "
                  f"{statistics.median(walls):.2f} s, mean {statistics.mean(walls):.2f} s, max {max(walls):.2f} s",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
