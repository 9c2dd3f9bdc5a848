"""Search of the starts and the joint least-squares fit on the torque residual.

Parametrisation (measured: it decides whether the fit converges). The load
simulation of :mod:`commission.ident.residual` depends only on the load's rates
ω_a² = K/J_l, D/J_l, B_l/J_l and on ε, and the shaft torque is J_l times the
simulated one per unit inertia. So the residual

    r = J_m·ẍ_m + B_m·ẋ_m + J_l·g(t; ω_a², D/J_l, B_l/J_l, ε) − τ_ref

is *linear* in (J_m, B_m, J_l): they are solved by linear least squares in every
evaluation (variable projection) and only (ω_a², D/J_l, B_l/J_l, ε) are
nonlinear. With J_l nonlinear instead, starts whose J_l was 40 % off (the FRD
of a light load with backlash) never recovered.

1. **Starts** (:func:`search_starts`). B_m + B_l is reliable from the FRD's DC
   gain, the split φ = B_l/(B_m + B_l) is not (METHOD.md, "Traps"), and a wrong
   split makes the simulated gears chatter; the FRD of a plant with backlash
   also puts the modes low when the gears separate near them. So cells
   (ε, φ, scale on ω_a) are evaluated, the rest at the frequency-domain start:
   an exhaustive grid, or Bayesian optimisation of ε per (φ, scale) pair through
   :func:`commission.ident.bayesopt.minimize_on_grid`; both count evaluations.
2. **Joint fit** (:func:`joint_fit`). From the best cells in turn,
   ``scipy.optimize.least_squares`` (trf, bounds) on the three log-rates and ε ≥ 0
   in degrees; finite-difference columns on two threads (the compiled
   simulation releases the GIL), the first column of each new point computed on the
   second core while least_squares evaluates the point itself (speculation: same results,
   three rounds of simulations per iteration instead of four); one BLAS thread throughout. Two starts that agree end the loop. A start that
   stalls far above the noise floor is paused and only continued (exactly where it
   stopped) when it could be the best or agree with another start, so the result is
   that of running every start to its end. Then chaotic impact bursts are dropped
   (:func:`burst_mask`) and the fit repeated.
   ``jacobian="broyden"`` (opt-in) replaces most finite-difference Jacobians by Broyden
   updates (:class:`_Jacobian`); not the default: see :func:`joint_fit`.

Optional terms (:class:`ModelTerms`, issue 8). Motor Coulomb friction is one more linear
column of the projection (F_cm solved like J_m); the load's Coulomb rate F_cl/J_l and the
current-loop time constant T_c [µs] are further nonlinear parameters (bounded ≥ 0). In the
start search the lag enters in its first-order form τ ≈ τ_ref − T_c·τ̇_ref (a linear column,
so the cells carry a T_c estimate), and the motor column stands in for both frictions.

Interval. At the optimum the full 7-column Jacobian in (ln J_m, ln J_l, ln B_m,
ln B_l, ln K, ln D, ε) — J_m and B_m columns analytic, the rest by finite
differences — gives cov = s²·(JᵀJ)⁻¹, s² = SSR/(n − 7), n the number of kept
residual samples after the low-pass and the decimation to ~2× the cut-off (so
that the samples are roughly independent: n is the effective degrees of
freedom). ε's interval is ε̂ ± 1.96·σ_ε, clipped at 0; the other parameters get
relative standard errors; the terms get absolute standard errors (``term_stderr``), from
which :mod:`commission.ident.hybrid` selects them. This is a statistical interval: it assumes the model
is right and the residual is noise; model errors (unmodelled friction, lag) are
not in it.
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import OptimizeResult, least_squares
from threadpoolctl import threadpool_limits

from ..exceptions import IdentificationError
from .residual import ResidualProblem, simulate_load, _filtfilt_decimate
from .twomass import TwoMassParameters, from_velocity_tf

__all__ = [
    "SearchCell",
    "SplitSearch",
    "JointFit",
    "linear_start",
    "LoadRates",
    "cell_rates",
    "projected_residual",
    "projected_fit",
    "ProjectedFit",
    "ModelTerms",
    "burst_mask",
    "search_starts",
    "combine_searches",
    "joint_fit",
]

T = TypeVar("T")

_PARAM_NAMES = ("J_m", "J_l", "B_m", "B_l", "K", "D")
#: Forward-difference steps: relative (log-parameters) and absolute for ε [deg].
_FD_LOG_STEP = 1e-6
_FD_EPS_STEP_DEG = 1e-5
#: Upper bound of the current-loop time constant in the fit [µs] (a 32 Hz loop).
_LAG_MAX_US = 5000.0


def _one_blas_thread(fn: Callable[..., T]) -> Callable[..., T]:
    """Run ``fn`` with one BLAS thread. The fits call small LAPACK problems (lstsq on a few
    columns, trf's SVD) from two threads at once; OpenBLAS's own threads then spin against
    them. Measured (bench/bench_identify.py, reference +lag1k): 10.3 s → 5.7 s of CPU, same
    result."""
    @functools.wraps(fn)
    def wrapped(*args: object, **kwargs: object) -> T:
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)
    return wrapped


# ----------------------------------------------------------------------------
# linear start
# ----------------------------------------------------------------------------
def linear_start(num: NDArray[np.float64], den: NDArray[np.float64],
                 phi: float = 0.5) -> tuple[TwoMassParameters, str]:
    """Physical parameters from a fitted V_m/T_ref = num/den, robust to a bad damping split.

    Exact inversion (:func:`commission.ident.twomass.from_velocity_tf`) when it gives a
    physical plant; otherwise (typical on backlash data: B_m or B_l comes out negative) the
    well-conditioned quantities are kept — J_m = 1/b2, B_m + B_l = a0/b0, ω_a² = b0/b2 = K/J_l,
    the resonance ω_r² ≈ K·(1/J_m + 1/J_l), D + B_l = b1·J_m·J_l — and the friction is split
    with ``phi``. Returns the parameters and how they were obtained ("exact" or "modes").
    """
    num = np.asarray(num, dtype=float) / float(den[0])
    den = np.asarray(den, dtype=float) / float(den[0])
    try:
        return from_velocity_tf(num, den), "exact"
    except IdentificationError:
        pass
    b2, b1, b0 = num
    a0 = den[3]
    if not (b2 > 0 and b0 > 0 and a0 > 0):
        raise IdentificationError(
            "the fitted transfer function is not that of a two-mass plant "
            f"(b2={b2:.3g}, b0={b0:.3g}, a0={a0:.3g} must be positive)")
    J_m = 1.0 / b2
    S = a0 / b0
    wa2 = b0 / b2
    poles = np.roots(den)
    cplx = poles[np.abs(poles.imag) > 1e-9 * np.abs(poles)]
    if cplx.size == 0:
        raise IdentificationError("the fitted transfer function has no resonance (no complex poles)")
    wr2 = float(np.max(np.abs(cplx)) ** 2)
    if wr2 <= wa2:
        raise IdentificationError("the fitted anti-resonance lies above the resonance: not a two-mass plant")
    J_l = J_m * (wr2 / wa2 - 1.0)
    K = wa2 * J_l
    B_l = phi * S
    X = max(b1 * J_m * J_l, 0.0)
    D = max(X - B_l, 0.05 * X, 1e-6 * K / math.sqrt(wr2))
    return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=(1.0 - phi) * S, B_l=B_l, K=K, D=D), "modes"


# ----------------------------------------------------------------------------
# residual with the inertias and B_m projected out
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class LoadRates:
    """The load's dynamics per unit load inertia: all the load simulation needs."""

    omega2: float
    """K/J_l = ω_a², the squared anti-resonance (locked-motor) frequency [rad²/s²]."""
    d: float
    """D/J_l [1/s]."""
    b: float
    """B_l/J_l [1/s]."""

    @classmethod
    def of(cls, p: TwoMassParameters) -> LoadRates:
        return cls(omega2=p.K / p.J_l, d=p.D / p.J_l, b=p.B_l / p.J_l)


@dataclass(frozen=True)
class ModelTerms:
    """Optional terms of the model beyond the paper's two-mass + dead zone (each off by default).

    * ``coulomb_motor`` — F_cm·tanh(ẋ_m/v_s) in the motor equation: a linear column of the
      torque residual, projected out like J_m and B_m.
    * ``coulomb_load`` — F_cl·tanh(ẋ_l/v_s) in the load equation: inside the load simulation,
      a nonlinear parameter (F_cl/J_l).
    * ``current_loop`` — a first-order lag T_c·τ̇ = τ_ref − τ between the torque reference and
      the motor torque: T_c is a nonlinear parameter (the torque regressor is refiltered).
    """

    coulomb_motor: bool = False
    coulomb_load: bool = False
    current_loop: bool = False

    @property
    def any(self) -> bool:
        return self.coulomb_motor or self.coulomb_load or self.current_loop

    def names(self) -> tuple[str, ...]:
        return tuple(n for n in ("coulomb_motor", "coulomb_load", "current_loop") if getattr(self, n))


@dataclass(frozen=True)
class ProjectedFit:
    """Result of :func:`projected_fit`: residual and the linearly solved parameters."""

    residual: NDArray[np.float64]
    parameters: TwoMassParameters
    coulomb_motor_nm: float = 0.0
    """F_cm [N·m] (0 when the column is not in the model)."""
    lag_linear_s: float = 0.0
    """T_c [s] of the first-order lag column τ ≈ τ_ref − T_c·τ̇_ref (only with ``lag_linear``)."""


def projected_fit(problem: ResidualProblem, rates: LoadRates, epsilon_rad: float, *,
                  load_weight_nm_per_rad: float = 0.0, keep: NDArray[np.bool_] | None = None,
                  coulomb_motor: bool = False, coulomb_load_rate: float | None = None, lag_s: float = 0.0,
                  lag_linear: bool = False) -> ProjectedFit:
    """:func:`projected_residual` with the optional terms (see :class:`ModelTerms`).

    :param coulomb_motor: add the motor Coulomb column (F_cm solved linearly).
    :param coulomb_load_rate: F_cl/J_l of the load simulation [rad/s²]; None: not modelled.
    :param lag_s: exact first-order current-loop time constant T_c [s] on τ_ref.
    :param lag_linear: add the column Δτ_ref/Ts (T_c solved linearly to first order; for the
        start search, where T_c is not yet a parameter).
    """
    g_f, load_position = _load_response(problem, rates, epsilon_rad, coulomb_load_rate)
    return _project(problem, rates, g_f, load_position, problem.lagged_torque_f(lag_s),
                    load_weight_nm_per_rad=load_weight_nm_per_rad, keep=keep,
                    coulomb_motor=coulomb_motor, lag_linear=lag_linear)


def _load_response(problem: ResidualProblem, rates: LoadRates, epsilon_rad: float,
                   coulomb_load_rate: float | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The load simulation per unit J_l: (low-passed, decimated shaft torque, load position)."""
    sim = simulate_load(problem, 1.0, rates.b, rates.omega2, rates.d, epsilon_rad, coulomb_load_rate)
    g_f = _filtfilt_decimate(problem.sos, problem.zi, sim.shaft_torque, problem.padlen,
                             problem.decimation)
    return g_f, sim.load_position


def _project(problem: ResidualProblem, rates: LoadRates, g_f: NDArray[np.float64],
             load_position: NDArray[np.float64], target: NDArray[np.float64], *,
             load_weight_nm_per_rad: float = 0.0, keep: NDArray[np.bool_] | None = None,
             coulomb_motor: bool = False, lag_linear: bool = False) -> ProjectedFit:
    """The linear part of :func:`projected_fit`, from a load response and a torque target.

    A load simulation that diverged (non-finite torque: rates far beyond what one RK4 step per
    sample resolves) gives an infinite residual — the search ranks the cell last, least
    squares rejects the step — instead of NaN into LAPACK."""
    if not np.all(np.isfinite(g_f)):
        n = target.shape[0]
        if problem.load_position is not None and load_weight_nm_per_rad > 0.0:
            n += problem.load_position[1:-1:problem.decimation].shape[0]
        nan = math.nan
        return ProjectedFit(residual=np.full(n, np.inf),
                            parameters=TwoMassParameters(J_m=nan, J_l=nan, B_m=nan, B_l=nan, K=nan, D=nan))
    cols = [problem.acceleration_f, problem.velocity_f, g_f]
    if coulomb_motor and problem.coulomb_f is not None:
        cols.append(problem.coulomb_f)
    if lag_linear and problem.torque_rate_f is not None:
        cols.append(problem.torque_rate_f)
    A = np.stack(cols, axis=1)
    sc = np.sqrt(np.sum(A * A, axis=0))
    sc[sc == 0.0] = 1.0
    if keep is None:
        coef, *_ = np.linalg.lstsq(A / sc, target, rcond=None)
    else:
        coef, *_ = np.linalg.lstsq(A[keep] / sc, target[keep], rcond=None)
    coef = coef / sc
    J_m, B_m, J_l = coef[:3]
    r = A @ coef - target
    if keep is not None:
        r = np.where(keep, r, 0.0)
    if problem.load_position is not None and load_weight_nm_per_rad > 0.0:
        r = np.concatenate((r, load_weight_nm_per_rad
                            * (load_position - problem.load_position)[1:-1:problem.decimation]))
    params = TwoMassParameters(J_m=float(J_m), J_l=float(J_l), B_m=float(B_m),
                               B_l=float(rates.b * J_l), K=float(rates.omega2 * J_l),
                               D=float(rates.d * J_l))
    i = 3
    fcm = 0.0
    if coulomb_motor and problem.coulomb_f is not None:
        fcm = float(coef[i])
        i += 1
    tl = float(coef[i]) if lag_linear and problem.torque_rate_f is not None else 0.0
    return ProjectedFit(residual=r, parameters=params, coulomb_motor_nm=fcm, lag_linear_s=tl)


def projected_residual(problem: ResidualProblem, rates: LoadRates, epsilon_rad: float, *,
                       load_weight_nm_per_rad: float = 0.0,
                       keep: NDArray[np.bool_] | None = None,
                       ) -> tuple[NDArray[np.float64], TwoMassParameters]:
    """Decimated residual vector with the best J_m, B_m, J_l for these load rates and ε.

    The load simulation depends on K/J_l, D/J_l, B_l/J_l and ε only, and the shaft torque is
    J_l times the simulated one per unit inertia, so r = J_m·ẍ_m + B_m·ẋ_m + J_l·g − τ_ref is
    linear in (J_m, B_m, J_l): they are solved by linear least squares in every evaluation
    (variable projection). Returns (vector, parameters); the vector has a second block
    w·(x_l,sim − x_l,meas) when the problem carries a load encoder and w > 0. ``keep`` (a mask
    over the decimated motor samples) drops samples from the projection and zeroes them in the
    vector (see :func:`burst_mask`). The optional terms: :func:`projected_fit`.
    """
    pf = projected_fit(problem, rates, epsilon_rad, load_weight_nm_per_rad=load_weight_nm_per_rad,
                       keep=keep)
    return pf.residual, pf.parameters


def _rms(v: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(v * v)))


def _robust_rms(v: NDArray[np.float64], scale: float) -> float:
    """sqrt(mean(c²·ln(1 + (v/c)²))), c = ``scale``: the Cauchy loss least_squares minimises,
    in the units of an RMS (equal to the RMS where |v| ≪ c, smaller where bursts exceed c)."""
    return float(scale * np.sqrt(np.mean(np.log1p((v / scale) ** 2))))


def burst_mask(r: NDArray[np.float64], decimated_rate_hz: float, *, threshold: float = 10.0,
               guard_s: float = 0.02) -> NDArray[np.bool_]:
    """Samples to keep: drop bursts where |r| > threshold·σ (σ = 1.4826·MAD), ± guard_s.

    Measured on a light, lightly damped load: where the load floats in the gap while the motor
    vibrates near the resonance (the paper's chirp crosses the gap around t = 5 s at ~200 Hz),
    the contact sequence is chaotic; the load simulated from the measured motor position loses
    track for a few hundred ms even with the true parameters and its residual there is 1000×
    the noise. Those windows carry no usable information and would bias every parameter.
    On Gaussian residual nothing is dropped (10σ).
    """
    a = np.abs(r)
    sigma = 1.4826 * float(np.median(a))
    bad = a > threshold * max(sigma, 1e-300)
    if not bad.any():
        return np.ones(r.shape, dtype=bool)
    g = max(1, int(round(guard_s * decimated_rate_hz)))
    kernel = np.ones(2 * g + 1)
    grown = np.convolve(bad.astype(float), kernel, mode="same") > 0.0
    return ~grown


# ----------------------------------------------------------------------------
# search of (ε, φ, ω_a scale)
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class SearchCell:
    """One evaluated cell of the start search."""

    epsilon_rad: float
    """Backlash half-width [rad]."""
    phi: float
    """Damping split B_l/(B_m + B_l) of the start [-]."""
    omega_scale: float
    """Factor on the start's anti-resonance frequency [-]."""
    cost: float
    """RMS of the projected residual [N·m]."""
    coulomb_motor_nm: float = 0.0
    """F_cm of the projection when the search had the Coulomb column [N·m]."""
    lag_s: float = 0.0
    """First-order T_c of the projection when the search had the lag column [s]."""

    def rates(self, start: TwoMassParameters) -> LoadRates:
        """Load rates of this cell around ``start`` (see :func:`cell_rates`)."""
        return cell_rates(start, self.phi, self.omega_scale)


def cell_rates(start: TwoMassParameters, phi: float, omega_scale: float = 1.0) -> LoadRates:
    """Load rates for a damping split φ and a scale on ω_a, around ``start``.

    B_l = φ·(B_m + B_l) (the sum is reliable from the DC gain); D/J_l + B_l/J_l = 2·ζ_a·ω_a is
    kept (the anti-resonance damping, well conditioned in the fit), D/J_l ≥ 5 % of it.
    """
    S = start.B_m + start.B_l
    rates = LoadRates.of(start)
    total = rates.d + rates.b
    b = phi * S / start.J_l
    d = max(total - b, 0.05 * total)
    return LoadRates(omega2=rates.omega2 * omega_scale**2, d=d * omega_scale, b=b)


@dataclass(frozen=True)
class SplitSearch:
    """Result of :func:`search_starts`."""

    method: str
    """"grid" or "bayes"."""
    best: tuple[SearchCell, ...]
    """Best cells, lowest cost first, distinct in ε by at least 2.5 resolutions."""
    evaluations: int
    """Residual evaluations spent."""
    history: tuple[SearchCell, ...]
    """Every evaluation in order."""
    seconds: float
    """Wall time [s]."""


def _cell_cost(problem: ResidualProblem, start: TwoMassParameters, eps: float, phi: float,
               scale: float, w_load: float, terms: ModelTerms | None = None,
               fixed: tuple[float | None, float] | None = None) -> SearchCell:
    t = terms or ModelTerms()
    if fixed is not None and fixed[0] is None:  # T_c known, exact; friction as without ``fixed``
        pf = projected_fit(problem, cell_rates(start, phi, scale), eps, load_weight_nm_per_rad=w_load,
                           coulomb_motor=t.coulomb_motor or t.coulomb_load, lag_s=fixed[1])
        return SearchCell(float(eps), float(phi), float(scale), _rms(pf.residual),
                          coulomb_motor_nm=pf.coulomb_motor_nm, lag_s=fixed[1])
    if fixed is not None:  # (F_cl [N·m], T_c [s]) known from a previous fit: exact terms
        fcl, lag = fixed
        pf = projected_fit(problem, cell_rates(start, phi, scale), eps, load_weight_nm_per_rad=w_load,
                           coulomb_motor=t.coulomb_motor, coulomb_load_rate=fcl / start.J_l, lag_s=lag)
        return SearchCell(float(eps), float(phi), float(scale), _rms(pf.residual),
                          coulomb_motor_nm=2.0 * fcl, lag_s=lag)
    pf = projected_fit(problem, cell_rates(start, phi, scale), eps, load_weight_nm_per_rad=w_load,
                       coulomb_motor=t.coulomb_motor or t.coulomb_load, lag_linear=t.current_loop)
    return SearchCell(float(eps), float(phi), float(scale), _rms(pf.residual),
                      coulomb_motor_nm=pf.coulomb_motor_nm, lag_s=max(pf.lag_linear_s, 0.0))


def _eps_resolution(epsilons_rad: Sequence[float] | NDArray[np.float64]) -> float:
    """Finest spacing of the ε candidates [rad] (1e-4 for a single candidate)."""
    eps = np.unique(np.asarray(epsilons_rad, dtype=float))
    return float(np.min(np.diff(eps))) if eps.size > 1 else 1e-4


def combine_searches(parts: Sequence[SplitSearch], epsilons_rad: Sequence[float] | NDArray[np.float64],
                     n_best: int = 3) -> SplitSearch:
    """One search from searches of disjoint cells over the same ε candidates: the best cells are
    those one search over all the cells would give (same distinctness rule as
    :func:`search_starts`)."""
    history = tuple(c for p in parts for c in p.history)
    return SplitSearch(method=parts[0].method,
                       best=_distinct_best(history, n_best, 2.5 * _eps_resolution(epsilons_rad)),
                       evaluations=sum(p.evaluations for p in parts), history=history,
                       seconds=sum(p.seconds for p in parts))


def _distinct_best(cells: Sequence[SearchCell], n: int, min_sep_rad: float) -> tuple[SearchCell, ...]:
    out: list[SearchCell] = []
    for c in sorted(cells, key=lambda c: c.cost):
        if all(abs(c.epsilon_rad - o.epsilon_rad) >= min_sep_rad or abs(c.omega_scale - o.omega_scale) > 1e-9
               for o in out):
            out.append(c)
        if len(out) >= n:
            break
    return tuple(out)


@_one_blas_thread
def search_starts(
    problem: ResidualProblem,
    start: TwoMassParameters,
    epsilons_rad: Sequence[float],
    phis: Sequence[float],
    omega_scales: Sequence[float] = (1.0,),
    *,
    method: str = "grid",
    n_best: int = 3,
    n_calls: int = 40,
    seed: int = 0,
    threads: int = 2,
    load_weight_nm_per_rad: float = 0.0,
    terms: ModelTerms | None = None,
    fixed_terms: tuple[float | None, float] | None = None,
) -> SplitSearch:
    """Search (ε, φ, ω_a scale) on the projected torque residual, the rest at ``start``.

    :param epsilons_rad: the ε candidates [rad] (a grid at the search resolution).
    :param phis: the φ = B_l/(B_m + B_l) candidates.
    :param omega_scales: factors on the start's anti-resonance frequency (the FRD of a plant
        with backlash puts the modes too low when the gears separate near them).
    :param method: "grid" evaluates every cell (on ``threads`` threads); "bayes" runs
        ``gp_minimize`` (expected improvement, one BLAS thread) for ``n_calls`` evaluations
        on the same cells (repeated cells are not re-evaluated nor counted).
    :param terms: candidate terms; their linear forms are projected in every cell (the motor
        Coulomb column, also standing in for the load's, and the first-order lag column), so
        that friction and lag cannot move the best cells; the cells carry their estimates.
    :param fixed_terms: (F_cl [N·m], T_c [s]) from a previous fit, used exactly instead;
        F_cl None: only T_c exact (the motor column stands in for both frictions, as without).
    """
    t0 = time.perf_counter()
    eps = np.asarray(epsilons_rad, dtype=float)
    ph = np.asarray(phis, dtype=float)
    sc = np.asarray(omega_scales, dtype=float)
    res = _eps_resolution(eps)
    history: list[SearchCell] = []
    w = load_weight_nm_per_rad
    if method == "grid":
        cells = [(e, p, k) for k in sc for p in ph for e in eps]
        with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
            history = list(pool.map(
                lambda c: _cell_cost(problem, start, c[0], c[1], c[2], w, terms, fixed_terms), cells))
    elif method == "bayes":
        # one 1-D Bayesian search over ε per (φ, scale) pair, through the project's
        # gp_minimize wrapper (one BLAS thread, cached repeats, local-minimum polish)
        from .bayesopt import minimize_on_grid

        grid = np.unique(eps)
        for k in sc:
            for p in ph:
                def f(e: float, _p: float = float(p), _k: float = float(k)) -> float:
                    c = _cell_cost(problem, start, e, _p, _k, w, terms, fixed_terms)
                    history.append(c)
                    return c.cost

                minimize_on_grid(f, grid, n_initial=5, max_evaluations=n_calls, seed=seed)
    else:
        raise ValueError(f"unknown search method {method!r}")
    best = _distinct_best(history, n_best, 2.5 * res)
    return SplitSearch(method=method, best=best, evaluations=len(history),
                       history=tuple(history), seconds=time.perf_counter() - t0)


# ----------------------------------------------------------------------------
# joint least squares
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class JointFit:
    """Result of :func:`joint_fit`."""

    parameters: TwoMassParameters
    epsilon_rad: float
    """Backlash half-width [rad] (≥ 0)."""
    cost: float
    """RMS of the decimated residual at the optimum [N·m]."""
    epsilon_stderr_rad: float
    """Standard error of ε from the Jacobian [rad]."""
    epsilon_interval_rad: tuple[float, float]
    """ε̂ ± 1.96·σ_ε, clipped at 0 [rad]."""
    relative_stderr: dict[str, float]
    """Standard error of each of J_m … D relative to its value [-]."""
    dof: int
    """Residual samples (after decimation) minus parameters."""
    evaluations: int
    """Residual evaluations over all starts (least squares, Jacobians, covariance)."""
    starts: tuple[tuple[float, float, float, float], ...]
    """Per start, best first: (ε start [rad], φ start, final cost [N·m], final ε [rad])."""
    seconds: float
    success: bool
    message: str
    residual: NDArray[np.float64] = field(repr=False, default_factory=lambda: np.zeros(0))
    """Decimated residual vector at the optimum [N·m] (dropped bursts are zero)."""
    dropped_fraction: float = 0.0
    """Fraction of the residual samples dropped as chaotic bursts (:func:`burst_mask`)."""
    terms: ModelTerms = field(default_factory=ModelTerms)
    """The optional terms that were in the model."""
    coulomb_motor_nm: float = 0.0
    """F_cm [N·m] (0 when not in the model)."""
    coulomb_load_nm: float = 0.0
    """F_cl [N·m] (0 when not in the model)."""
    lag_s: float = 0.0
    """Current-loop time constant T_c [s] (0 when not in the model)."""
    term_stderr: dict[str, float] = field(default_factory=dict)
    """Standard errors of the terms' values: coulomb_motor_nm, coulomb_load_nm [N·m], lag_s [s]."""
    mask: NDArray[np.bool_] | None = field(repr=False, default=None)
    """Kept decimated motor samples (None: all)."""
    n_used: int = 0
    """Residual samples used (after dropping bursts)."""
    robust_loss: bool = False
    """Whether the starts switched to the Cauchy loss (``robust_scale_nm`` of :func:`joint_fit`)."""
    rescan_epsilon_rad: tuple[float, float] | None = None
    """(ε where the scanned Cauchy-loss start ended, ε of the scanned cell the next start took)
    [rad] when an ε scan of ``rescan_epsilons_rad`` found a better cell; else None."""


class _Counter:
    def __init__(self) -> None:
        self.n = 0


#: Pause of a start stalled far above the noise floor (see :class:`_Start`): after at least
#: ``_STALL_MIN_NFEV`` evaluations, a best cost that fell by less than ``_STALL_RTOL``
#: (relative) over the last ``_STALL_WINDOW`` evaluations. Measured (bench/bench_identify.py):
#: the stalled starts of the ζ = 0.07, Coulomb and current-loop plants then change their cost
#: by < 0.06 % up to max_nfev; converging starts keep falling (the slowest, soft heavy 25 Hz,
#: by ≥ 1 % per 8 evaluations before it drops to the noise floor).
_STALL_MIN_NFEV = 10
_STALL_WINDOW = 8
_STALL_RTOL = 1e-3


class _Abandoned(Exception):
    pass


class _Start:
    """One start's ``least_squares`` (trf), run on its own thread so that it can be paused.

    A start that has stalled above ``stall_above`` (after at least ``_STALL_MIN_NFEV``
    evaluations its cost fell by less than ``_STALL_RTOL`` relative over the last
    ``_STALL_WINDOW``) is *paused*, not ended: its thread waits inside the residual function,
    so that :meth:`finish` continues exactly the trajectory it would have followed (same
    steps, same result), and :meth:`abandon` drops it. While paused, :attr:`cost` and
    :attr:`x` are its best evaluated point, which is trf's current iterate (trf accepts a step
    only when it lowers the cost). ``stall_above`` ≤ 0: never paused. With ``robust_scale`` > 0
    the cost tracked is that of the Cauchy loss (:func:`_robust_rms`), the one trf lowers.
    """

    def __init__(self, fun: Callable[[NDArray[np.float64]], NDArray[np.float64]],
                 x0: NDArray[np.float64], jac: Callable[..., NDArray[np.float64]],
                 lo: NDArray[np.float64], hi: NDArray[np.float64], max_nfev: int,
                 stall_above: float, robust_scale: float = 0.0) -> None:
        import threading

        self._fun, self._stall_above, self._scale = fun, stall_above, robust_scale
        self.cost = math.inf
        self.x: NDArray[np.float64] | None = None
        self.fun: NDArray[np.float64] | None = None
        self._hist: list[float] = []
        self._cv = threading.Condition()
        self._state = "running"  # running → paused → running → done
        self._abandon = False
        self.sol: OptimizeResult | None = None
        self._error: BaseException | None = None

        def run() -> None:
            try:
                sol = _least_squares(self._f, x0, jac, lo, hi, max_nfev, robust_scale)
            except _Abandoned:
                sol = None
            except BaseException as err:  # noqa: BLE001 - re-raised on the caller's thread
                sol, self._error = None, err
            with self._cv:
                self.sol = sol
                self._state = "done"
                self._cv.notify_all()

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()
        self._wait()

    def _f(self, th: NDArray[np.float64]) -> NDArray[np.float64]:
        r = self._fun(th)
        c = _robust_rms(r, self._scale) if self._scale > 0.0 else _rms(r)
        if c < self.cost:
            self.cost, self.x, self.fun = c, np.array(th, dtype=np.float64), r
        h = self._hist
        h.append(self.cost)
        k = len(h)
        if (self._stall_above > 0.0 and k >= _STALL_MIN_NFEV and k > _STALL_WINDOW
                and self.cost > self._stall_above
                and h[-1 - _STALL_WINDOW] - self.cost < _STALL_RTOL * self.cost):
            self._stall_above = 0.0  # pause once; once resumed, run to the end
            with self._cv:
                self._state = "paused"
                self._cv.notify_all()
                while self._state == "paused":
                    self._cv.wait()
            if self._abandon:
                raise _Abandoned
        return r

    def _wait(self) -> None:
        with self._cv:
            while self._state == "running":
                self._cv.wait()
        if self._state == "done":
            self._thread.join()
            if self._error is not None:
                raise self._error

    @property
    def paused(self) -> bool:
        return self._state == "paused"

    def finish(self) -> OptimizeResult:
        """The result of the whole run (continues a paused start to its end)."""
        if self._state == "paused":
            with self._cv:
                self._state = "running"
                self._cv.notify_all()
            self._wait()
        assert self.sol is not None
        return self.sol

    def abandon(self) -> OptimizeResult:
        """Drop a paused start: its best point so far as the result."""
        if self._state == "paused":
            with self._cv:
                self._abandon = True
                self._state = "running"
                self._cv.notify_all()
            self._wait()
            self.sol = OptimizeResult(
                x=self.x, fun=self.fun, cost=0.5 * float(self.fun @ self.fun), success=False,
                status=0, nfev=len(self._hist),
                message=f"stalled: cost fell by < {_STALL_RTOL:g} (relative) over "
                        f"{_STALL_WINDOW} evaluations, far above the best start")
        assert self.sol is not None
        return self.sol


#: A first start that ends above this factor × the stop cost with a bursty residual switches the
#: joint fit's starts to the Cauchy loss (``robust_scale_nm`` of :func:`joint_fit`). The
#: plateaus measured (ζ = 0.07, Coulomb, 1 kHz lag plants) lie at 20–25× the stop cost.
_PLATEAU_FACTOR = 10.0

#: A paused start is continued when its cost is within this factor of the best start's.
_RESUME_FACTOR = 1.05


def _near(e: list, f: list, rtol: float) -> bool:
    """Whether two starts (entries [cost, result, _Start, …]) could end in consensus."""
    ca, cb = e[0], f[0]
    xa = e[1].x[3] if e[1] is not None else e[2].x[3]
    xb = f[1].x[3] if f[1] is not None else f[2].x[3]
    return (abs(ca - cb) <= 10.0 * rtol * min(ca, cb)
            and abs(xa - xb) <= 10.0 * max(1e-4, rtol * abs(xa)))


def _least_squares(fun: Callable[[NDArray[np.float64]], NDArray[np.float64]], x0: NDArray[np.float64],
                   jac: Callable[..., NDArray[np.float64]], lo: NDArray[np.float64],
                   hi: NDArray[np.float64], max_nfev: int, robust_scale: float = 0.0) -> OptimizeResult:
    """trf on (lo, hi); with a Broyden :class:`_Jacobian`, the convergence safeguard.

    ``robust_scale`` > 0: the Cauchy loss ρ(z) = ln(1 + z), z = (r/robust_scale)², instead of
    the squares (see ``robust_scale_nm`` in :func:`joint_fit`).

    A run whose end rests on a Broyden Jacobian (gtol: the last Jacobian; ftol/xtol: the one
    the last step came from) is not trusted: a finite-difference Jacobian is computed at its
    end point and trf continued from there (within the same budget, ``_BROYDEN_NFEV_FACTOR``
    × ``max_nfev`` trial points), until it ends on a step from a finite-difference Jacobian.
    So every converged run ends by the same tests as with finite differences throughout.
    """
    def run(x: NDArray[np.float64], n: int) -> OptimizeResult:
        loss = {"loss": "cauchy", "f_scale": robust_scale} if robust_scale > 0.0 else {}
        return least_squares(fun, x, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                             xtol=1e-8, ftol=1e-10, gtol=1e-8, max_nfev=n, **loss)

    if not (isinstance(jac, _Jacobian) and jac.broyden):
        return run(x0, max_nfev)
    max_nfev = int(round(_BROYDEN_NFEV_FACTOR * max_nfev))
    sol = run(x0, max_nfev)
    used, njev = int(sol.nfev), int(sol.njev)
    while sol.status > 0 and not jac.trusted_end(int(sol.status)) and used < max_nfev:
        jac.restart_at(sol.x)
        # the start point is cached (no evaluation): its nfev is not counted again
        s2 = run(np.clip(sol.x, lo, hi), max_nfev - used + 1)
        used += int(s2.nfev) - 1
        njev += int(s2.njev)
        sol = s2
    sol.nfev, sol.njev = used, njev
    return sol


#: Broyden Jacobian (see :class:`_Jacobian`): a fresh finite-difference Jacobian at least every
#: ``_BROYDEN_REFRESH`` calls, and whenever the last step's actual cost reduction fell below
#: ``_BROYDEN_RATIO`` times the reduction its (Broyden) linear model predicted. A Broyden step
#: gains less than a finite-difference one (rejected steps shrink trf's trust region), so a
#: Broyden run may take ``_BROYDEN_NFEV_FACTOR`` × max_nfev trial points. Measured on the
#: ζ = 0.07 plant of bench/bench_identify.py (seed 7): factor 1 ends at ε −0.027°, 1.5 at
#: −0.00001°, 2 at +0.115° — the result depends on the trajectory (see jacobian in
#: :func:`joint_fit`), not monotonically on the budget.
_BROYDEN_REFRESH = 4
_BROYDEN_RATIO = 0.25
_BROYDEN_NFEV_FACTOR = 1.5


class _Jacobian:
    """The Jacobian callable of one least-squares run: finite differences or Broyden updates.

    ``broyden=False``: a finite-difference Jacobian (``fd``) at every call (trf calls it at
    every accepted point). ``broyden=True``: at most calls the rank-one (good) Broyden update
    J ← J + (f₁ − f₀ − J·Δx)·Δxᵀ/(Δxᵀ·Δx) of the previous Jacobian from the residuals trf
    has already evaluated (no evaluation); a fresh finite-difference Jacobian at the first
    call, every ``every``-th call, and after a poor step — trf rejected a trial point since the
    last call (its residual function saw more than one point: :meth:`trial`), or the accepted
    step's cost reduction is below ``ratio`` times the reduction the linear model predicted.
    :func:`_least_squares` adds the convergence safeguard. ``residual(th)`` must return the
    (cached) residual at a point trf has just evaluated.
    """

    def __init__(self, residual: Callable[[NDArray[np.float64]], NDArray[np.float64]],
                 fd: Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]],
                 broyden: bool, every: int = _BROYDEN_REFRESH, ratio: float = _BROYDEN_RATIO) -> None:
        self._residual, self._fd = residual, fd
        self.broyden, self.every, self.ratio = broyden, max(1, int(every)), ratio
        self.x: NDArray[np.float64] | None = None
        self.f: NDArray[np.float64] | None = None
        self.J: NDArray[np.float64] | None = None
        self.fresh = False
        """Whether :attr:`J` is a finite-difference Jacobian at :attr:`x`."""
        self.since_fd = 0
        self.trials = 0
        """Residual evaluations (trial points) since the last call."""
        self.trial_fresh = False
        """Whether the last trial point was stepped from a finite-difference Jacobian."""
        self.n_fd = 0
        self.n_broyden = 0

    def trial(self) -> None:
        """Note a trial point (trf evaluates the residual there); call before evaluating."""
        self.trials += 1
        self.trial_fresh = self.fresh

    def next_is_fd(self) -> bool:
        """Whether the call after the trial point about to be evaluated will certainly be a
        finite-difference Jacobian (used to speculate its first column)."""
        return (not self.broyden or self.J is None or self.trials >= 1
                or self.since_fd + 1 >= self.every)

    def trusted_end(self, status: int) -> bool:
        """Whether trf's convergence (``status`` > 0) rests on a finite-difference Jacobian: the
        last Jacobian (gtol) or the one the last trial step was computed from (any test)."""
        return self.trial_fresh or (status == 1 and self.fresh)

    def _refresh(self, x: NDArray[np.float64], f: NDArray[np.float64]) -> NDArray[np.float64]:
        self.J = self._fd(x, f)
        self.x, self.f, self.fresh, self.since_fd = x, f, True, 0
        self.n_fd += 1
        return self.J.copy()

    def restart_at(self, x: NDArray[np.float64]) -> None:
        """A fresh finite-difference Jacobian at ``x`` (an evaluated point) for a new run."""
        x = np.array(x, dtype=np.float64)
        if not (self.fresh and self.x is not None and np.array_equal(x, self.x)):
            self._refresh(x, self._residual(x))
        self.trials = 0

    def __call__(self, th: NDArray[np.float64], *_: object) -> NDArray[np.float64]:
        x = np.array(th, dtype=np.float64)
        f = self._residual(x)
        trials, self.trials = self.trials, 0
        if self.J is not None and self.x is not None and np.array_equal(x, self.x):
            return self.J.copy()  # a new run from the last point (see restart_at)
        if not self.broyden or self.J is None or self.x is None or self.f is None:
            return self._refresh(x, f)
        self.since_fd += 1
        dx = x - self.x
        y = f - (self.f + self.J @ dx)  # the linear model's error at the accepted point
        f0 = float(self.f @ self.f)
        predicted = f0 - float((f - y) @ (f - y))
        actual = f0 - float(f @ f)
        if trials > 1 or self.since_fd >= self.every or not (actual >= self.ratio * predicted > 0.0):
            return self._refresh(x, f)
        self.J = self.J + np.outer(y, dx / float(dx @ dx))
        self.x, self.f, self.fresh = x, f, False
        self.n_broyden += 1
        return self.J.copy()


def _fd_jacobian(fun: Callable[[NDArray[np.float64]], NDArray[np.float64]], th: NDArray[np.float64],
                 f0: NDArray[np.float64], steps: NDArray[np.float64], upper: NDArray[np.float64],
                 pool: ThreadPoolExecutor) -> NDArray[np.float64]:
    def col(i: int) -> NDArray[np.float64]:
        t, h = _fd_point(th, i, steps, upper)
        return (fun(t) - f0) / h
    return np.stack(list(pool.map(col, range(th.size))), axis=1)


#: "the mask in force" (default of the joint fit's projected residual).
_CURRENT = object()


def _fd_point(th: NDArray[np.float64], i: int, steps: NDArray[np.float64],
              upper: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """The point of the i-th forward-difference column of :func:`_fd_jacobian` and its step."""
    h = steps[i]
    if th[i] + h > upper[i]:
        h = -h
    t = th.copy()
    t[i] += h
    return t, h


@_one_blas_thread
def joint_fit(
    problem: ResidualProblem,
    start: TwoMassParameters,
    starts: Sequence[SearchCell] | Sequence[tuple[float, float]],
    *,
    epsilon_max_rad: float = math.radians(2.0),
    max_nfev: int = 40,
    threads: int = 2,
    load_weight_nm_per_rad: float = 0.0,
    trim_rounds: int = 3,
    trim_threshold: float = 10.0,
    consensus_rtol: float = 1e-3,
    stop_cost_nm: float = 0.0,
    terms: ModelTerms | None = None,
    initial_mask: NDArray[np.bool_] | None = None,
    jacobian: str = "finite_difference",
    robust_scale_nm: float = 0.0,
    rescan_epsilons_rad: Sequence[float] | None = None,
) -> JointFit:
    """Least squares of (K/J_l, D/J_l, B_l/J_l, ε) with (J_m, B_m, J_l) projected, per start.

    All seven physical parameters are thus fitted jointly; the log-rates make K, D, B_l
    positive, ε is in degrees with bounds [0, epsilon_max]. Each start is a
    :class:`SearchCell` or an (ε [rad], φ) pair around ``start``; starts run in order and stop
    once two of them agree on cost and ε within ``consensus_rtol`` (ε within 1e-4°), or one
    reaches ``stop_cost_nm`` (RMS residual, e.g. the noise floor). Then the
    best solution is refitted without chaotic bursts (:func:`burst_mask`, ``trim_rounds``).

    ``terms`` adds the optional model terms (:class:`ModelTerms`): F_cm projected, F_cl/J_l ≥ 0
    [rad/s²] and T_c ≥ 0 [µs] as further nonlinear parameters, started from the cell's
    estimates (the search's linear forms). ``initial_mask`` starts with samples dropped.

    ``jacobian``: "finite_difference" computes trf's Jacobian by finite differences at every
    accepted point; "broyden" updates it by rank-one Broyden updates from the residuals trf
    evaluates anyway, with finite differences at the first point, every few points, after poor
    steps, and at the end (see :class:`_Jacobian` and :func:`_least_squares`). Measured
    (bench/bench_identify.py, issue 8): Broyden cuts the joint fit's evaluations by 30–60 % and
    reaches the same end point on a single start, but it changes the trajectories, and the
    ζ = 0.07 plant's result depends on them (second pass, burst trimming): over noise seeds 1–7
    finite differences found ε within 0.0001° every time, Broyden missed by 0.02–0.03° on one
    or two seeds. Hence finite differences by default.

    ``robust_scale_nm`` > 0: when the first start ends (or stalls) on a plateau above
    ``_PLATEAU_FACTOR`` × ``stop_cost_nm`` with bursts in its residual (:func:`burst_mask` drops
    samples), its cell is run again, and the further starts are run, minimising the Cauchy loss
    Σ ln(1 + (r/c)²), c = robust_scale_nm, instead of the squares: chaotic impact bursts
    (residual 100–1000× the noise) then cannot hold a start on the plateau; samples within a few
    c of zero count as in least squares. Plants whose first start converges are untouched (same
    evaluations, same result). The burst trimming that follows is plain least squares on the
    kept samples, so the result, its intervals and the model selection are least-squares ones.
    Costs, consensus and stops are judged on the RMS residual either way. Measured effect: see
    ``robust_loss_ratio`` in :class:`commission.ident.hybrid.IdentificationOptions`.

    ``rescan_epsilons_rad`` (a grid of ε [rad]): after a start with the Cauchy loss, the RMS
    residual is evaluated at its end point (a paused start's: its best point) with ε replaced by
    each grid value (the other parameters held). When it is still on a plateau and a grid value
    does better, the next start is that point (result: :attr:`JointFit.rescan_epsilon_rad`) and
    there are no more scans; otherwise the next Cauchy start is scanned too (two scans at most).
    The Cauchy loss gets the load rates right through the impacts but can leave ε in a
    neighbouring minimum (ζ = 0.07 plant: rates within 0.5 %, ε 0.33° for 0.25°); the scan at
    right rates ranks the true ε's cell first. Measured (bench/bench_seeds.py, ζ = 0.07, against
    the same code without the scan): seeds 1–30 median 3.10 → 1.74 s, 29 of 30 within tolerance
    before and after, second passes 23 → 9; seeds 31–60 median 3.75 → 2.24 s, 29 → 30 of 30,
    second passes 24 → 15; no other bench plant's result changed. One scan only: 1.79 s and 12
    second passes on seeds 1–30; a scan after every Cauchy start: 58 of 60 within tolerance; a
    scan only at a start that ended (not paused): 2.71 s.
    """
    if jacobian not in ("broyden", "finite_difference"):
        raise ValueError(f"unknown jacobian {jacobian!r}")
    t0 = time.perf_counter()
    tm = terms or ModelTerms()
    counter = _Counter()
    w = load_weight_nm_per_rad
    mask: list[NDArray[np.bool_] | None] = [initial_mask]
    i_cl = 4 if tm.coulomb_load else -1
    i_lag = (4 + int(tm.coulomb_load)) if tm.current_loop else -1
    n_th = 4 + int(tm.coulomb_load) + int(tm.current_loop)

    def unpack(th: NDArray[np.float64]) -> tuple[LoadRates, float, float | None, float]:
        o2, d, b = np.exp(th[:3])
        q = float(th[i_cl]) if i_cl >= 0 else None  # None: not modelled (see simulate_load)
        lag = float(th[i_lag]) * 1e-6 if i_lag >= 0 else 0.0
        return LoadRates(o2, d, b), math.radians(th[3]), q, lag

    # Caches (results are bit-identical with or without them; they only skip repeated work):
    # the load simulation depends on (ω_a², D/J_l, B_l/J_l, ε, F_cl/J_l) only, not on T_c, so
    # the T_c column of a finite-difference Jacobian and the final projection reuse it; the
    # lagged torque target depends on T_c only, so the other columns reuse it; and residuals
    # are remembered per point and mask (least_squares asks for the Jacobian at the point it
    # has just evaluated; the burst trimming and the final projection revisit the solution).
    sims: dict[bytes, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
    targets: dict[float, NDArray[np.float64]] = {}
    resids: dict[bytes, tuple[object, NDArray[np.float64]]] = {}

    def _remember(cache: dict, key: object, value: object, size: int) -> None:
        cache[key] = value
        while len(cache) > size:
            try:
                del cache[next(iter(cache))]
            except (KeyError, RuntimeError, StopIteration):  # another thread got there first
                break

    def pfit(th: NDArray[np.float64], keep: object = _CURRENT) -> ProjectedFit:
        keep = mask[0] if keep is _CURRENT else keep
        rates, eps, q, lag = unpack(th)
        n_sim = 4 + int(tm.coulomb_load)
        skey = np.asarray(th[:n_sim], dtype=np.float64).tobytes()
        resp = sims.get(skey)
        if resp is None:
            resp = _load_response(problem, rates, eps, q)
            _remember(sims, skey, resp, 16)
        target = targets.get(lag)
        if target is None:
            target = problem.lagged_torque_f(lag)
            _remember(targets, lag, target, 16)
        return _project(problem, rates, resp[0], resp[1], target, load_weight_nm_per_rad=w,
                        keep=keep, coulomb_motor=tm.coulomb_motor)

    # Speculation (two threads or more): while least_squares evaluates a new point on its own
    # thread, the second core computes the first finite-difference column at that point (trf
    # asks for the Jacobian at every accepted point, and most points are accepted). Results
    # are identical; a rejected point wastes only the otherwise idle core. Speculative
    # evaluations are counted when used.
    speculate = threads >= 2
    pending: dict[bytes, tuple[object, Future]] = {}
    lock = threading.Lock()

    def _speculative(t: NDArray[np.float64], m: object) -> NDArray[np.float64]:
        return pfit(t, m).residual

    def fun(th: NDArray[np.float64]) -> NDArray[np.float64]:
        key = np.asarray(th, dtype=np.float64).tobytes()
        hit = resids.get(key)
        if hit is not None and hit[0] is mask[0]:
            return hit[1]
        with lock:
            pend = pending.pop(key, None)
        counter.n += 1
        if pend is not None and pend[0] is mask[0]:
            r = pend[1].result()
        else:
            r = pfit(th).residual
        _remember(resids, key, (mask[0], r), 16)
        return r

    def new_jacobian(hi_: NDArray[np.float64]) -> _Jacobian:
        return _Jacobian(fun, lambda t, f0: _fd_jacobian(fun, t, f0, steps, hi_, pool),
                         broyden=jacobian == "broyden")

    def primary(hi_: NDArray[np.float64], js: _Jacobian) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
        """The residual as least_squares calls it: speculates the first Jacobian column when
        the Jacobian at the point will be by finite differences."""
        def f(th: NDArray[np.float64]) -> NDArray[np.float64]:
            spec = speculate and js.next_is_fd()
            js.trial()
            if spec:
                key = np.asarray(th, dtype=np.float64).tobytes()
                hit = resids.get(key)
                if hit is None or hit[0] is not mask[0]:
                    t, _ = _fd_point(np.asarray(th, dtype=np.float64), 0, steps, hi_)
                    tkey = t.tobytes()
                    m = mask[0]
                    with lock:
                        if tkey not in pending:
                            pending[tkey] = (m, pool.submit(_speculative, t, m))
                            while len(pending) > 8:
                                del pending[next(iter(pending))]
            return fun(th)
        return f

    steps = np.array([_FD_LOG_STEP] * 3 + [_FD_EPS_STEP_DEG] + [1e-4] * (n_th - 4))
    eps_max_deg = math.degrees(epsilon_max_rad)
    n_motor = problem.acceleration_f.shape[0]
    rate = problem.sample_rate_hz / problem.decimation
    def start_point(cell: SearchCell | tuple[float, float] | _Rescan
                    ) -> tuple[float, float, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(ε₀ [rad], φ, θ₀, lower, upper bounds) of a queued start."""
        if isinstance(cell, _Rescan):  # a point of a previous start, in its bounds
            return math.radians(float(cell.theta[3])), cell.phi, cell.theta, cell.lo, cell.hi
        if isinstance(cell, SearchCell):
            eps0, phi, rates = cell.epsilon_rad, cell.phi, cell.rates(start)
            fcm0, lag0 = cell.coulomb_motor_nm, cell.lag_s
        else:
            eps0, phi = cell[0], cell[1]
            rates = cell_rates(start, phi)
            fcm0, lag0 = 0.0, 0.0
        extra0: list[float] = []
        lo_x: list[float] = []
        hi_x: list[float] = []
        if tm.coulomb_load:
            # the search's motor column holds F_cm + F_cl: start with half of it on the load
            extra0.append(max(0.5 * fcm0, 0.0) / max(start.J_l, 1e-12))
            lo_x.append(0.0)
            hi_x.append(1e7)
        if tm.current_loop:
            extra0.append(min(max(lag0, 0.0) * 1e6, 0.9 * _LAG_MAX_US))
            lo_x.append(0.0)
            hi_x.append(_LAG_MAX_US)
        th0 = np.array([math.log(rates.omega2), math.log(rates.d), math.log(rates.b),
                        min(math.degrees(eps0), eps_max_deg)] + extra0)
        lo = np.concatenate((th0[:3] - 4.0, [0.0], lo_x))
        hi = np.concatenate((th0[:3] + 4.0, [eps_max_deg], hi_x))
        return eps0, phi, th0, lo, hi

    entries: list[list] = []  # [cost, result (None while paused), _Start, ε0, φ, lo, hi]
    queue: list[SearchCell | tuple[float, float] | _Rescan] = list(starts)
    scale_now = 0.0  # least squares until a start ends on a bursty plateau (robust_scale_nm)
    scans_left = 0 if rescan_epsilons_rad is None else 2  # until one finds a better cell
    rescan: tuple[float, float] | None = None
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        qi = 0
        while qi < len(queue):
            cell = queue[qi]
            qi += 1
            eps0, phi, th0, lo, hi = start_point(cell)
            th0 = np.clip(th0, lo + 1e-9, hi - 1e-9)

            jac = new_jacobian(hi)
            # A start stalled far above the noise floor is paused (see _Start) and continued at
            # the end only when it could be the best (_RESUME_FACTOR). The multi-start decisions
            # stay those of running every start to its end: a paused start whose cost and ε are
            # near another start's (10× the consensus tolerances; a stalled start moves < 0.1 %)
            # could reach consensus with it and is continued at once; any other paused start
            # cannot, so the consensus check is made only when the two best starts have ended.
            try:
                run = _Start(primary(hi, jac), th0, jac, lo, hi, max_nfev, stop_cost_nm,
                             scale_now)
            except BaseException:
                for e in entries:
                    if e[1] is None:
                        e[2].abandon()
                raise
            entry = [run.cost, None, run, eps0, phi, lo, hi]
            entries.append(entry)
            if run.paused and consensus_rtol > 0:
                near = [e for e in entries if e is not entry and _near(e, entry, consensus_rtol)]
                for e in ([entry] + near) if near else []:
                    if e[1] is None:
                        e[1] = e[2].finish()
                        e[0] = _rms(e[1].fun)
            elif not run.paused:
                entry[1] = run.finish()
                entry[0] = _rms(entry[1].fun)
            if entry[1] is not None and entry[0] <= stop_cost_nm:
                break  # at the noise floor: no other start can do materially better
            # the first start ended (or stalled) on a plateau far above the noise floor, with
            # bursts in its residual: that cell again, and the rest, with the Cauchy loss
            if (scale_now == 0.0 and robust_scale_nm > 0.0 and stop_cost_nm > 0.0
                    and len(entries) == 1 and run.cost > _PLATEAU_FACTOR * stop_cost_nm):
                r1 = (entry[1].fun if entry[1] is not None else run.fun)[:n_motor]
                if not burst_mask(r1, rate, threshold=trim_threshold).all():
                    if entry[1] is None:
                        entry[1] = run.abandon()
                        entry[0] = _rms(entry[1].fun)
                    scale_now = robust_scale_nm
                    queue.insert(qi, cell)
                    continue
            # a start with the Cauchy loss: when it still ends on a plateau, scan ε at its other
            # parameters (see rescan_epsilons_rad); a paused start's point is its best
            if scans_left > 0 and scale_now > 0.0 and stop_cost_nm > 0.0 and not isinstance(cell, _Rescan):
                scans_left -= 1
                x_end = (entry[1].x if entry[1] is not None else run.x).copy()
                grid = [math.degrees(e) for e in np.unique(np.asarray(rescan_epsilons_rad, dtype=float))
                        if lo[3] <= math.degrees(e) <= hi[3]]
                at = [x_end] + [_with_eps(x_end, e) for e in grid]
                fits = list(pool.map(pfit, at))
                costs = [_rms(f.residual) for f in fits]
                i_best = int(np.argmin(costs))
                if i_best > 0 and costs[0] > _PLATEAU_FACTOR * stop_cost_nm:
                    p_end = fits[0].parameters
                    rescan = (math.radians(float(x_end[3])), math.radians(float(at[i_best][3])))
                    queue.insert(qi, _Rescan(at[i_best], lo, hi,
                                             p_end.B_l / max(p_end.B_m + p_end.B_l, 1e-300)))
                    scans_left = 0
                    continue
            # consensus: two starts that end at the same cost and ε settle it
            if len(entries) >= 2 and consensus_rtol > 0:
                a, b = sorted(entries, key=lambda r: r[0])[:2]
                if (a[1] is not None and b[1] is not None
                        and abs(a[0] - b[0]) <= consensus_rtol * a[0]
                        and abs(a[1].x[3] - b[1].x[3]) <= max(1e-4, consensus_rtol * abs(a[1].x[3]))):
                    break
        best_cost = min(e[0] for e in entries)
        for i, e in enumerate(entries):
            if e[1] is None:
                try:
                    e[1] = e[2].finish() if e[0] <= _RESUME_FACTOR * best_cost else e[2].abandon()
                except BaseException:
                    for f in entries[i + 1:]:
                        if f[1] is None:
                            f[2].abandon()
                    raise
                e[0] = _rms(e[1].fun)
        results = [(e[0], e[1], e[3], e[4], e[5], e[6]) for e in entries]
        results.sort(key=lambda r: r[0])
        _, sol, _, _, lo, hi = results[0]
        th = sol.x
        # drop chaotic bursts (see burst_mask) and refit until the kept set is stable
        dropped = 0.0 if mask[0] is None else 1.0 - float(mask[0].mean())
        for _ in range(trim_rounds):
            r_full = fun(th)
            if stop_cost_nm > 0.0 and _rms(r_full) <= stop_cost_nm:
                break  # at the noise floor: there are no bursts worth a refit
            r_now = r_full[:n_motor]
            keep = burst_mask(r_now, rate, threshold=trim_threshold)
            if mask[0] is not None:
                keep &= mask[0]
            if keep.all() or (mask[0] is not None and np.array_equal(keep, mask[0])):
                break
            if keep.mean() < 0.6:  # more than 40 % "bursts": the model is wrong, not chaotic
                break
            mask[0] = keep
            dropped = 1.0 - float(keep.mean())

            jac2 = new_jacobian(hi)
            sol = _least_squares(primary(hi, jac2), np.clip(th, lo, hi), jac2, lo, hi, max_nfev)
            th = sol.x
        pf = pfit(th)
        counter.n += 1
        r, params = pf.residual, pf.parameters
        _, eps, q, lag = unpack(th)
        fcm = pf.coulomb_motor_nm
        fcl = 0.0 if q is None else q * params.J_l
        # covariance in (ln J_m, ln J_l, ln B_m, ln B_l, ln K, ln D, ε[deg], [F_cm], [F_cl], [T_c µs])
        # from the full residual
        n_x = 7 + int(tm.coulomb_motor) + int(tm.coulomb_load) + int(tm.current_loop)
        j_cm = 7 if tm.coulomb_motor else -1
        j_cl = 7 + int(tm.coulomb_motor) if tm.coulomb_load else -1
        j_lag = n_x - 1 if tm.current_loop else -1

        full_sims: dict[bytes, tuple[object, NDArray[np.float64]]] = {}

        def full(tx: NDArray[np.float64]) -> NDArray[np.float64]:
            counter.n += 1
            jm, jl, bm, bl, k, d = np.exp(tx[:6])
            fl = float(tx[j_cl]) if j_cl >= 0 else None
            # the simulation does not depend on J_m, B_m, F_cm nor T_c: reuse it across those
            skey = np.asarray([tx[1], tx[3], tx[4], tx[5], tx[6], fl or 0.0], dtype=np.float64).tobytes()
            hit = full_sims.get(skey)
            if hit is None:
                sim = simulate_load(problem, jl, bl, k, d, math.radians(tx[6]), fl)
                ts_f = _filtfilt_decimate(problem.sos, problem.zi, sim.shaft_torque, problem.padlen,
                                          problem.decimation)
                hit = (sim, ts_f)
                _remember(full_sims, skey, hit, 4)
            sim, ts_f = hit
            lg = float(tx[j_lag]) * 1e-6 if j_lag >= 0 else 0.0
            tgt = targets.get(lg)
            if tgt is None:
                tgt = problem.lagged_torque_f(lg)
                _remember(targets, lg, tgt, 16)
            v = jm * problem.acceleration_f + bm * problem.velocity_f + ts_f - tgt
            if j_cm >= 0 and problem.coulomb_f is not None:
                v = v + float(tx[j_cm]) * problem.coulomb_f
            if mask[0] is not None:
                v = np.where(mask[0], v, 0.0)
            if problem.load_position is not None and w > 0.0:
                v = np.concatenate((v, w * (sim.load_position - problem.load_position)[1:-1:problem.decimation]))
            return v

        pa = params.as_array()
        extras = ([fcm] if tm.coulomb_motor else []) + ([fcl] if tm.coulomb_load else []) \
            + ([lag * 1e6] if tm.current_loop else [])
        if np.all(pa > 0.0):
            tx = np.concatenate((np.log(pa), [th[3]], extras))
            fx = full(tx)
            # J_m, B_m and F_cm columns are analytic (linear terms); the others by finite differences
            cols = [1, 3, 4, 5, 6] + [j for j in (j_cl, j_lag) if j >= 0]
            fd_steps = np.array([_FD_LOG_STEP] * 4 + [_FD_EPS_STEP_DEG]
                                + ([1e-7] if j_cl >= 0 else []) + ([1e-3] if j_lag >= 0 else []))
            Jp = _fd_jacobian(lambda sub: full(_embed(tx, cols, sub)), tx[cols], fx,
                              fd_steps, np.full(len(cols), np.inf), pool)
            JX = np.zeros((fx.size, n_x))
            JX[:, cols] = Jp
            JX[:n_motor, 0] = params.J_m * problem.acceleration_f
            JX[:n_motor, 2] = params.B_m * problem.velocity_f
            if j_cm >= 0 and problem.coulomb_f is not None:
                JX[:n_motor, j_cm] = problem.coulomb_f
            if mask[0] is not None:
                JX[:n_motor][~mask[0]] = 0.0
            n_used = fx.size - (0 if mask[0] is None else int((~mask[0]).sum()))
            dof = max(n_used - n_x, 1)
            s2 = float(np.sum(fx * fx)) / dof
            try:
                sd = np.sqrt(np.clip(np.diag(np.linalg.inv(JX.T @ JX)) * s2, 0.0, None))
            except np.linalg.LinAlgError:
                sd = np.full(n_x, np.inf)
        else:
            dof = max(r.size - n_x, 1)
            sd = np.full(n_x, np.inf)
    sd_eps = math.radians(float(sd[6]))
    rel = {name: float(sd[i]) for i, name in enumerate(_PARAM_NAMES)}
    interval = (max(0.0, eps - 1.96 * sd_eps), eps + 1.96 * sd_eps)
    extra_sd = {}
    if j_cm >= 0:
        extra_sd["coulomb_motor_nm"] = float(sd[j_cm])
    if j_cl >= 0:
        extra_sd["coulomb_load_nm"] = float(sd[j_cl])
    if j_lag >= 0:
        extra_sd["lag_s"] = float(sd[j_lag]) * 1e-6
    return JointFit(
        parameters=params, epsilon_rad=eps, cost=_rms(r), epsilon_stderr_rad=sd_eps,
        epsilon_interval_rad=interval, relative_stderr=rel, dof=dof, evaluations=counter.n,
        starts=tuple((float(e0), float(p0), float(c), math.radians(float(s.x[3])))
                     for c, s, e0, p0, _, _ in results),
        seconds=time.perf_counter() - t0, success=bool(sol.success), message=str(sol.message),
        residual=r, dropped_fraction=dropped, terms=tm, coulomb_motor_nm=fcm, coulomb_load_nm=fcl,
        lag_s=lag, term_stderr=extra_sd, mask=mask[0], n_used=int(n_used if np.all(pa > 0.0) else r.size),
        robust_loss=scale_now > 0.0, rescan_epsilon_rad=rescan,
    )


@dataclass(frozen=True)
class _Rescan:
    """A joint-fit start at a point of a previous start with ε from a scan."""

    theta: NDArray[np.float64]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    phi: float


def _with_eps(th: NDArray[np.float64], eps_deg: float) -> NDArray[np.float64]:
    t = th.copy()
    t[3] = eps_deg
    return t


def _embed(t7: NDArray[np.float64], cols: list[int], sub: NDArray[np.float64]) -> NDArray[np.float64]:
    t = t7.copy()
    t[cols] = sub
    return t
