"""The identifier on what a real axis has and the model does not: cogging and torque ripple (a torque
periodic in the motor's position), Stribeck friction, a contact that cannot pull, a gear that stiffens
under load, a spring on the load.

The records come from a simulator of this file's own (not the product's plant): a two-mass + dead-zone
axis integrated by RK4 at 16 sub-steps per sample, no event location, with those effects added; the
reference plant (ε 0.4°), the default 10 s chirp at 8 kHz, a 20-bit encoder whose difference is the
velocity, 1e-4 N·m of white torque noise. The first line (no effect) checks the simulator against the
identifier. Each line: the wall time of ``identify`` in process (numba's kernels compiled by a first
run), ε, the errors of J_m, J_l and K, whether the result is flagged, and the cogging found.

    python bench/bench_unmodelled.py
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit

from commission.config import ExcitationConfig
from commission.excitation import chirp
from commission.ident.hybrid import identify
from commission.ident.twomass import REFERENCE_PLANT
from commission.recording import Recording

FS = 8000.0
CFG = ExcitationConfig()
PEAK_NM = CFG.amplitude_nm + CFG.bias_amplitude_nm


@njit(cache=True)
def _accelerations(x, tau, p, out):
    jm, jl, bm, bl, k, d, eps, fcm, fsm, fcl, fsl, vs, cog, cog_n, ripple, ripple_n, hard, spring, clamp = p
    y = x[0] - x[2]
    dz = y - eps if y > eps else (y + eps if y < -eps else 0.0)
    ts = 0.0
    if dz != 0.0:
        ts = k * dz * (1.0 + hard * dz * dz) + d * (x[1] - x[3])
        if clamp > 0.0 and ts * dz < 0.0:  # a contact pushes, it does not pull
            ts = 0.0
    fm = (fcm + (fsm - fcm) * math.exp(-(x[1] / vs) ** 2)) * math.tanh(x[1] / 1e-4)
    fl = (fcl + (fsl - fcl) * math.exp(-(x[3] / vs) ** 2)) * math.tanh(x[3] / 1e-4)
    # cogging: its fundamental and half of it at twice the rate; ripple at its own
    tc = cog * (math.sin(cog_n * x[0]) + 0.5 * math.cos(2.0 * cog_n * x[0] + 0.7)) + ripple * math.sin(ripple_n * x[0] + 0.3)
    out[0] = x[1]
    out[1] = (tau - bm * x[1] - ts - fm - tc) / jm
    out[2] = x[3]
    out[3] = (ts - bl * x[3] - fl - spring * x[2]) / jl


@njit(cache=True)
def _simulate(u, fs, p, sub):
    x = np.zeros(4)
    xs = np.zeros((u.size, 4))
    h = 1.0 / fs / sub
    k1, k2, k3, k4, t = np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4)
    for n in range(u.size):
        xs[n] = x
        for _ in range(sub):
            _accelerations(x, u[n], p, k1)
            t[:] = x + 0.5 * h * k1
            _accelerations(t, u[n], p, k2)
            t[:] = x + 0.5 * h * k2
            _accelerations(t, u[n], p, k3)
            t[:] = x + h * k3
            _accelerations(t, u[n], p, k4)
            x += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return xs


def record(*, coulomb_motor=0.0, static_motor=None, coulomb_load=0.0, static_load=None, cogging=0.0,
           cogging_n=50, ripple=0.0, ripple_n=24, hardening_per_rad2=0.0, spring=0.0, clamp=False,
           load_encoder=False, velocity_only=False) -> Recording:
    """The chirp on the reference plant with the effects given (torques as shares of the peak torque)."""
    P = REFERENCE_PLANT
    u = chirp(CFG).samples
    p = np.array([P.J_m, P.J_l, P.B_m, P.B_l, P.K, P.D, math.radians(0.4),
                  coulomb_motor * PEAK_NM, (static_motor or coulomb_motor) * PEAK_NM,
                  coulomb_load * PEAK_NM, (static_load or coulomb_load) * PEAK_NM, 0.02,
                  cogging * PEAK_NM, cogging_n, ripple * PEAK_NM, ripple_n, hardening_per_rad2, spring, float(clamp)])
    xs = _simulate(u + np.random.default_rng(11).normal(0.0, 1e-4, u.size), FS, p, 16)
    q = 2 * math.pi / 2**20
    xm, xl = np.round(xs[:, 0] / q) * q, np.round(xs[:, 2] / q) * q
    vm, vl = np.diff(xm, prepend=0.0) * FS, np.diff(xl, prepend=0.0) * FS
    kw = {} if velocity_only else {"motor_position": xm}
    if load_encoder:
        kw.update(load_position=xl, load_velocity=vl)
    return Recording.uniform(FS, u, vm, **kw)


CASES = {
    "no unmodelled effect (the simulator's check)": {},
    "cogging 0.3 % of the peak, 50/rev": {"cogging": 0.003},
    "cogging 1 %, 50/rev": {"cogging": 0.01},
    "cogging 3 %, 50/rev": {"cogging": 0.03},
    "cogging 1 %, 72/rev, ripple 0.5 %, 24/rev": {"cogging": 0.01, "cogging_n": 72, "ripple": 0.005},
    "cogging 1 %, velocity only": {"cogging": 0.01, "velocity_only": True},
    "cogging 1 %, load encoder": {"cogging": 0.01, "load_encoder": True},
    "cogging 1 %, motor Coulomb 5 %": {"cogging": 0.01, "coulomb_motor": 0.05},
    "Stribeck motor friction 3 % (5 % static)": {"coulomb_motor": 0.03, "static_motor": 0.05},
    "Stribeck load friction 3 % (5 % static)": {"coulomb_load": 0.03, "static_load": 0.05},
    "a contact that cannot pull (damping clipped)": {"clamp": True},
    "a gear 20 % stiffer at 10 mrad of twist": {"hardening_per_rad2": 0.2 / 0.01**2},
}


def main() -> None:
    identify(record())  # numba's kernels compiled before anything is timed
    print(f"{'case':46s} {'time':>7s} {'ε [°]':>8s} {'J_m':>8s} {'J_l':>8s} {'K':>8s}  flagged  cogging found")
    for name, kw in CASES.items():
        rec = record(**kw)
        t0 = time.perf_counter()
        res = identify(rec)
        dt = time.perf_counter() - t0
        err = {k: 100 * (getattr(res.parameters, k) / getattr(REFERENCE_PLANT, k) - 1) for k in ("J_m", "J_l", "K")}
        cog = res.cogging
        found = (f"{', '.join(map(str, cog['harmonics_per_revolution']))}/rev, {100 * cog['peak_nm'] / PEAK_NM:.2f} % peak"
                 if cog else "—")
        print(f"{name:46s} {dt:6.1f}s {res.epsilon_deg:8.4f} {err['J_m']:+7.2f}% {err['J_l']:+7.2f}% {err['K']:+7.2f}%  "
              f"{'yes' if res.approximate else 'no ':7s}  {found}", flush=True)


if __name__ == "__main__":
    main()
