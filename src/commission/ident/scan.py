"""The start cell of the estimator: a scan of (ε, damping split) on the projected torque residual.

The frequency-domain start gets the inertias, the modes and the damping sum B_m + B_l right to a
few percent, but not the split φ = B_l/(B_m + B_l) (METHOD.md, "Traps") and not ε. The load
simulation of :mod:`commission.ident.residual` depends only on the load's rates ω_a² = K/J_l,
D/J_l, B_l/J_l and on ε, and the shaft torque is J_l times the simulated one per unit inertia, so

    r = J_m·ẍ_m + B_m·ẋ_m (+ F_cm·sgn ẋ_m + T_c·τ̇_ref) + J_l·g(t; ω_a², D/J_l, B_l/J_l, ε) − τ_ref

is linear in (J_m, B_m, J_l) and the optional motor-side columns: each cell costs one load
simulation and one small linear least-squares problem (variable projection). The cells are a grid
of ε (0 and the coarse grid of the configured range, extended upward while the best cell is at
its top) times the configured splits. The load is simulated open loop here: with the observer
(:class:`commission.ident.residual.Observer`) the cost hardly depends on ε away from the true
linear parameters, which is what the cells are for.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .residual import ResidualProblem, simulate_load
from .twomass import TwoMassParameters

__all__ = ["LoadRates", "ScanCell", "Scan", "cell_rates", "epsilon_grid", "projected_cell", "scan"]

#: The ε range is doubled (up to this [deg]) while the best cell lies within 2.5 steps of its top.
EPSILON_EXTEND_MAX_DEG = 16.0


@dataclass(frozen=True)
class LoadRates:
    """The load's dynamics per unit load inertia: all the load simulation needs."""

    omega2: float
    """K/J_l = ω_a², the squared anti-resonance (locked-motor) frequency [rad²/s²]."""
    d: float
    """D/J_l [1/s]."""
    b: float
    """B_l/J_l [1/s]."""


def cell_rates(start: TwoMassParameters, phi: float) -> LoadRates:
    """Load rates for a damping split φ around ``start``: B_l = φ·(B_m + B_l) (the sum is
    reliable from the DC gain); D/J_l + B_l/J_l = 2·ζ_a·ω_a is kept (the anti-resonance damping,
    well conditioned in the fit), D/J_l ≥ 5 % of it."""
    total = (start.D + start.B_l) / start.J_l
    b = phi * (start.B_m + start.B_l) / start.J_l
    return LoadRates(omega2=start.K / start.J_l, d=max(total - b, 0.05 * total), b=b)


@dataclass(frozen=True)
class ScanCell:
    """One cell of the scan, with its projected linear parameters."""

    epsilon_rad: float
    """Backlash half-width [rad]."""
    phi: float
    """Damping split B_l/(B_m + B_l) [-]."""
    cost_nm: float
    """RMS of the projected residual [N·m] (inf when the simulation diverged)."""
    parameters: TwoMassParameters | None
    """The cell's rates with the projected J_m, B_m, J_l (None when the projection failed)."""
    coulomb_nm: float = 0.0
    """Motor Coulomb column's F [N·m] (standing in for the friction of both sides)."""
    coulomb_z2: float = 0.0
    """Wald statistic (F/σ_F)² of that column (0 without it)."""


@dataclass(frozen=True)
class Scan:
    """Result of :func:`scan`: every cell, best first."""

    cells: tuple[ScanCell, ...]
    """Every evaluated cell, lowest cost first."""
    extended_to_deg: float | None = None
    """Upper end of the ε grid when it was extended beyond the configured range [deg]."""
    history: tuple[ScanCell, ...] = ()
    """Every evaluated cell in the order evaluated."""

    @property
    def best(self) -> ScanCell:
        return self.cells[0]

    @property
    def evaluations(self) -> int:
        return len(self.cells)


def epsilon_grid(bounds_deg: tuple[float, float], step_deg: float) -> NDArray[np.float64]:
    """0 and ``bounds_deg`` in steps of ``step_deg`` (the top included) [rad]."""
    lo, hi = bounds_deg
    n = int(math.floor((hi - lo) / step_deg + 1e-9))
    grid = lo + step_deg * np.arange(n + 1)
    if grid[-1] < hi - 1e-12:
        grid = np.append(grid, hi)
    return np.radians(np.unique(np.concatenate(([0.0], grid))))


def projected_cell(problem: ResidualProblem, rates: LoadRates, epsilon_rad: float, *, phi: float = math.nan,
                   coulomb: bool = False, lag_s: float = 0.0, load_weight_nm_per_rad: float = 0.0,
                   coulomb_load_rate: float | None = None) -> ScanCell:
    """The projected residual at these load rates and ε (see the module docstring).

    :param coulomb: add the motor Coulomb column.
    :param lag_s: the torque behind a first-order current loop of this time constant [s] (0: ideal).
    :param load_weight_nm_per_rad: weight of the load-position block (0: none).
    :param coulomb_load_rate: F_cl/J_l of load Coulomb friction in the simulation [rad/s²] (None: none).
    """
    sim = simulate_load(problem, 1.0, rates.b, rates.omega2, rates.d, epsilon_rad, coulomb_load_rate)
    g_f = problem.lowpass(sim.shaft_torque)
    if not np.all(np.isfinite(g_f)):  # rates far beyond what one step per sample resolves
        return ScanCell(float(epsilon_rad), float(phi), math.inf, None)
    cols = [problem.acceleration_f, problem.velocity_f, g_f]
    if coulomb and problem.coulomb_f is not None:
        cols.append(problem.coulomb_f)
    target = problem.lagged_torque_f(lag_s)
    A = np.stack(cols, axis=1)
    if problem.keep is not None:  # samples a streamed link lost are no evidence
        A, target = A * problem.keep[:, None], target * problem.keep
    with np.errstate(over="ignore"):
        sc = np.sqrt(np.sum(A * A, axis=0))
    if not np.all(np.isfinite(sc)):  # a simulated shaft torque finite but beyond squaring: as unresolved
        return ScanCell(float(epsilon_rad), float(phi), math.inf, None)
    sc[sc == 0.0] = 1.0
    coef = np.linalg.lstsq(A / sc, target, rcond=None)[0] / sc
    r = A @ coef - target
    J_m, B_m, J_l = (float(c) for c in coef[:3])
    if problem.load_position is not None and load_weight_nm_per_rad > 0.0:
        r = np.concatenate((r, load_weight_nm_per_rad * sim.load_error[1:-1:problem.decimation]))
    params = TwoMassParameters(J_m=J_m, J_l=J_l, B_m=B_m, B_l=rates.b * J_l, K=rates.omega2 * J_l,
                               D=rates.d * J_l) if J_m > 0 and J_l > 0 else None
    fc, z2 = 0.0, 0.0
    if len(coef) > 3:
        fc = float(coef[3])
        n = A.shape[0]
        s2 = float(r @ r) / max(n - A.shape[1], 1)
        var = s2 * float(np.linalg.pinv((A / sc).T @ (A / sc))[3, 3]) / sc[3] ** 2
        z2 = fc * fc / var if var > 0 else math.inf
    return ScanCell(float(epsilon_rad), float(phi), float(np.sqrt(np.mean(r * r))), params, fc, z2)


def scan(problem: ResidualProblem, start: TwoMassParameters, bounds_deg: tuple[float, float], step_deg: float,
         phis: Sequence[float], *, coulomb: bool = False, lag_s: float = 0.0, load_weight_nm_per_rad: float = 0.0,
         coulomb_load_nm: float | None = None, threads: int = 2, phi_around: bool = False) -> Scan:
    """Evaluate every (ε, φ) cell around ``start`` (see the module docstring); the ε grid's top is
    doubled, up to :data:`EPSILON_EXTEND_MAX_DEG`, while the best cell lies within 2.5 steps of it.

    :param coulomb_load_nm: load Coulomb friction simulated in every cell [N·m] (None: none).
    :param phi_around: ``start``'s own split as well (a start that is already a fit's).
    """
    if phi_around:
        own = start.B_l / (start.B_m + start.B_l) if start.B_m + start.B_l > 0 else 0.5
        phis = tuple(sorted({*phis, round(own, 12)}))
    rates = {phi: cell_rates(start, phi) for phi in phis}
    rate = None if coulomb_load_nm is None else coulomb_load_nm / start.J_l

    def cells_for(eps: NDArray[np.float64]) -> list[ScanCell]:
        jobs = [(phi, e) for phi in phis for e in eps]
        with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
            return list(pool.map(lambda j: projected_cell(problem, rates[j[0]], j[1], phi=j[0], coulomb=coulomb,
                                                          lag_s=lag_s, load_weight_nm_per_rad=load_weight_nm_per_rad,
                                                          coulomb_load_rate=rate),
                                 jobs))

    eps = epsilon_grid(bounds_deg, step_deg)
    cells = cells_for(eps)
    hi, extended = bounds_deg[1], None
    while hi < EPSILON_EXTEND_MAX_DEG:
        best = min(cells, key=lambda c: c.cost_nm)
        if best.epsilon_rad < float(eps[-1]) - 2.5 * math.radians(step_deg):
            break
        more = epsilon_grid((hi, 2.0 * hi), step_deg * 2.0 * hi / bounds_deg[1])
        more = more[more > eps[-1] + 1e-12]
        eps = np.concatenate((eps, more))
        cells += cells_for(more)
        hi = extended = 2.0 * hi
    return Scan(tuple(sorted(cells, key=lambda c: (c.cost_nm, c.epsilon_rad, c.phi))), extended, tuple(cells))
