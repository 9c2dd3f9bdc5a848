"""The estimator: prediction-error least squares of every parameter on the observed torque residual.

One objective: the low-passed, decimated motor-equation residual of
:func:`commission.ident.residual.residual_vector` with the load-state observer (a fixed-gain
predictor, :class:`commission.ident.residual.Observer`), minimised by
``scipy.optimize.least_squares`` (trf, bounds) over

    ln J_m, ln J_l, ln B_m, ln B_l, ln K, ln D, ε [deg]   and the kept terms   F_cm, F_cl [N·m], T_c [µs]

from one start cell of the scan: first with ε held at the cell's (the linear parameters move to
where that ε explains the record), then everything. Finite-difference columns run on threads (the
compiled simulation releases the GIL); each column is computed alone, so the result does not
depend on the number of threads. No accept/reject rule chooses between paths: the answer is a
smooth function of the data.

Optional terms (:class:`ModelTerms`): motor Coulomb friction F_cm·tanh(ẋ_m/v_s) in the motor
equation; load Coulomb friction F_cl·tanh(ẋ_l/v_s) in the load simulation; a first-order current
loop T_c·τ̇ = τ_ref − τ. A term is kept when its Wald statistic (value/σ)² exceeds ln n_eff (the
BIC's price of a parameter, :func:`significant_terms`).

Uncertainty. The Newey–West (HAC) covariance at the optimum: the residual of a model that is not
exact is correlated with itself and with the Jacobian, which s²·(JᵀJ)⁻¹ ignores. n_eff, the
residual's independent samples from its autocorrelation, prices a term in the selection.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .residual import Observer, ResidualProblem, motor_part, simulate_load
from .twomass import TwoMassParameters

__all__ = ["ModelTerms", "PemFit", "fit", "significant_terms"]

PARAMETER_NAMES = ("J_m", "J_l", "B_m", "B_l", "K", "D")
#: Decimated residual samples left out at each end: the zero-phase low-pass's edge transients.
EDGE_SAMPLES = 4
#: Iterations of the first least squares, ε held at the start cell's.
_HELD_EPSILON_NFEV = 6
#: Relative finite-difference step in the log-parameters (as scipy's diff_step).
_DIFF_STEP = 1e-6
#: Largest lag of the autocorrelation behind n_eff.
_ACF_LAGS = 20
#: The log-parameters are bounded to ×/÷ this around the start: a fit that would leave the range is
#: lost, and the bound keeps its simulation finite and fast.
_LOG_RANGE = math.log(30.0)
#: Upper bound of the current loop's time constant [µs] (a 32 Hz loop).
_LAG_MAX_US = 5000.0


@dataclass(frozen=True)
class ModelTerms:
    """Optional terms of the model beyond the two-mass + dead zone (each off by default)."""

    coulomb_motor: bool = False
    coulomb_load: bool = False
    current_loop: bool = False

    @property
    def any(self) -> bool:
        return self.coulomb_motor or self.coulomb_load or self.current_loop

    def names(self) -> tuple[str, ...]:
        return tuple(n for n in ("coulomb_motor", "coulomb_load", "current_loop") if getattr(self, n))


@dataclass(frozen=True)
class PemFit:
    """Result of :func:`fit`."""

    parameters: TwoMassParameters
    epsilon_rad: float
    """Backlash half-width [rad] (≥ 0)."""
    coulomb_motor_nm: float
    coulomb_load_nm: float
    lag_s: float
    """Current-loop time constant T_c [s] (0 when not modelled)."""
    terms: ModelTerms
    residual: NDArray[np.float64]
    """Decimated residual at the optimum, edges trimmed [N·m] (motor block, then load block)."""
    cost_nm: float
    """RMS of ``residual`` [N·m]."""
    names: tuple[str, ...]
    """Coordinates of ``covariance``: ln J_m … ln D, eps_deg, then the terms (F_cm, F_cl [N·m], T_c [µs])."""
    covariance: NDArray[np.float64]
    """Covariance of the coordinates at the optimum (inflated for correlated residuals)."""
    n_effective: float
    """Independent residual samples implied by the residual's autocorrelation."""
    evaluations: int
    """Residual evaluations (Jacobian columns included)."""
    converged: bool
    message: str
    selection: dict[str, dict[str, float | bool]] = field(default_factory=dict)
    """Per candidate term: its Wald z², the threshold ln n_eff, kept."""
    discretization: dict[str, float] = field(default_factory=dict)
    """Per coordinate: how far the estimate moves under the alternate discretizations (in
    ``covariance`` already)."""

    def stderr(self, name: str) -> float:
        """Standard error of a coordinate (NaN when not in the fit)."""
        if name not in self.names:
            return math.nan
        i = self.names.index(name)
        return float(math.sqrt(max(self.covariance[i, i], 0.0)))

    @property
    def epsilon_stderr_rad(self) -> float:
        return math.radians(self.stderr("eps_deg"))

    @property
    def epsilon_interval_rad(self) -> tuple[float, float]:
        """ε ± 1.96σ [rad], the lower end clipped at 0."""
        se = self.epsilon_stderr_rad
        return max(self.epsilon_rad - 1.96 * se, 0.0), self.epsilon_rad + 1.96 * se

    @property
    def relative_stderr(self) -> dict[str, float]:
        """Relative standard errors of J_m … D (the log-coordinates' standard errors) [-]."""
        return {n: self.stderr("ln " + n) for n in PARAMETER_NAMES}


class _Objective:
    """The residual as a function of the fit's coordinates (see the module docstring)."""

    def __init__(self, problem: ResidualProblem, observer: Observer, terms: ModelTerms,
                 load_weight_nm_per_rad: float) -> None:
        self.problem, self.observer, self.terms = problem, observer, terms
        self.load_weight = load_weight_nm_per_rad
        self.names = tuple(f"ln {n}" for n in PARAMETER_NAMES) + ("eps_deg",) + tuple(
            n for n, on in (("F_cm", terms.coulomb_motor), ("F_cl", terms.coulomb_load),
                            ("T_c_us", terms.current_loop)) if on)
        self.calls = 0
        self.bad = 1.0

    def unpack(self, z: NDArray[np.float64]) -> tuple[TwoMassParameters, float, dict[str, float]]:
        J_m, J_l, B_m, B_l, K, D = (float(v) for v in np.exp(z[:6]))
        extra = dict(zip(self.names[7:], (float(v) for v in z[7:])))
        return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=B_m, B_l=B_l, K=K, D=D), math.radians(float(z[6])), extra

    def __call__(self, z: NDArray[np.float64]) -> NDArray[np.float64]:
        self.calls += 1
        p, eps, extra = self.unpack(z)
        pr = self.problem
        motor = motor_part(pr, p.J_m, p.B_m, coulomb_motor_nm=extra.get("F_cm", 0.0),
                           lag_s=1e-6 * extra.get("T_c_us", 0.0))
        sim = simulate_load(pr, p.J_l, p.B_l, p.K, p.D, eps,
                            extra.get("F_cl", 0.0) if self.terms.coulomb_load else None,
                            motor=motor, observer=self.observer)
        v = pr.lowpass(sim.residual)
        if pr.keep is not None:  # samples a streamed link lost are no evidence
            v = v * pr.keep
        v = v[EDGE_SAMPLES:-EDGE_SAMPLES]
        if pr.load_position is not None:
            w = self.load_weight * sim.load_error[1:-1:pr.decimation]
            v = np.concatenate((v, w[EDGE_SAMPLES:-EDGE_SAMPLES]))
        # a diverged simulation — non-finite, or a sample past the flat residual's level (a torque residual
        # 10× the RMS torque is no plant's; finite but huge, its differences overflowed the Jacobian): a
        # large, flat residual the fit steps back from, never above it
        if not (np.all(np.isfinite(v)) and float(np.max(np.abs(v), initial=0.0)) <= self.bad):
            return np.full(v.shape, self.bad)
        return v


def _least_squares(obj: _Objective, z0: NDArray[np.float64], free: NDArray[np.bool_], lo: NDArray[np.float64],
                   hi: NDArray[np.float64], scale: NDArray[np.float64], steps: NDArray[np.float64],
                   pool: ThreadPoolExecutor, max_nfev: int) -> tuple[NDArray[np.float64], object]:
    """least_squares over the ``free`` coordinates of ``z0`` (the others held)."""
    idx = np.flatnonzero(free)
    last: dict[bytes, NDArray[np.float64]] = {}

    def full(y: NDArray[np.float64]) -> NDArray[np.float64]:
        z = z0.copy()
        z[idx] = y
        return z

    def fun(y: NDArray[np.float64]) -> NDArray[np.float64]:
        r = obj(full(y))
        last.clear()
        last[y.tobytes()] = r
        return r

    def jac(y: NDArray[np.float64]) -> NDArray[np.float64]:
        f0 = last.get(y.tobytes())
        if f0 is None:
            f0 = fun(y)
        h = steps[idx]

        def column(i: int) -> NDArray[np.float64]:
            dy = y.copy()
            # a forward step, backward at an upper bound
            dy[i] += h[i] if y[i] + h[i] <= hi[idx][i] else -h[i]
            return (obj(full(dy)) - f0) / (dy[i] - y[i])

        return np.stack(list(pool.map(column, range(y.size))), axis=1)

    res = least_squares(fun, np.clip(z0[idx], lo[idx], hi[idx]), jac=jac, bounds=(lo[idx], hi[idx]),
                        method="trf", x_scale=scale[idx], max_nfev=max_nfev, ftol=1e-8, xtol=1e-8)
    return full(res.x), res


def _n_effective(r: NDArray[np.float64]) -> float:
    """Independent samples of a residual from its autocorrelation (Bartlett weights)."""
    n = r.size
    x = r - r.mean()
    var = float(x @ x)
    if var <= 0.0 or n < 4 * _ACF_LAGS:
        return float(n)
    rho = np.array([float(x[:-k] @ x[k:]) / var for k in range(1, _ACF_LAGS + 1)])
    w = 1.0 - np.arange(1, _ACF_LAGS + 1) / (_ACF_LAGS + 1.0)
    return float(n / max(1.0, 1.0 + 2.0 * float(np.sum(w * rho))))


def _covariance(J: NDArray[np.float64], r: NDArray[np.float64]) -> NDArray[np.float64]:
    """Heteroscedasticity- and autocorrelation-consistent covariance of a least-squares estimate
    (Newey–West: H⁻¹·S·H⁻¹, H = JᵀJ, S the Bartlett-weighted sum of the score products J_t·r_t over
    lags up to ``_ACF_LAGS``). What a fit leaves of a model error is correlated with the Jacobian's
    columns; s²·H⁻¹ assumes it is not, and its intervals came out too narrow."""
    G = J * r[:, None]
    S = G.T @ G
    for k in range(1, min(_ACF_LAGS, r.size - 1) + 1):
        C = G[k:].T @ G[:-k]
        S += (1.0 - k / (_ACF_LAGS + 1.0)) * (C + C.T)
    Hinv = np.linalg.pinv(J.T @ J)
    n, p = J.shape
    return (n / max(n - p, 1)) * Hinv @ S @ Hinv


def fit(problem: ResidualProblem, start: TwoMassParameters, epsilon_rad: float, terms: ModelTerms,
        observer: Observer, *, coulomb_motor_nm: float = 0.0, coulomb_load_nm: float = 0.0, lag_s: float = 0.0,
        epsilon_max_rad: float,
        load_weight_nm_per_rad: float = 0.0, threads: int = 2, max_nfev: int = 40,
        hold_epsilon: bool = True, alternates: Sequence[tuple[ResidualProblem, Observer]] = ()) -> PemFit:
    """Least squares of every parameter from ``start`` and ``epsilon_rad`` (see the module docstring).

    :param coulomb_motor_nm: start of F_cm [N·m]; ``coulomb_load_nm``: of F_cl [N·m].
    :param lag_s: start of T_c [s].
    :param epsilon_max_rad: upper bound of ε [rad].
    :param hold_epsilon: first fit the others with ε held (a start from a scan cell).
    :param alternates: other discretizations of the same residual (another motor interpolation,
        another observer bandwidth; the same samples): the Gauss–Newton step each would take from
        the optimum is the estimate's sensitivity to how the model is discretized, added to its
        covariance as a systematic error (:attr:`PemFit.discretization`).
    """
    obj = _Objective(problem, observer, terms, load_weight_nm_per_rad)
    ref = float(np.sqrt(np.mean(problem.torque_f ** 2)))
    z0 = [math.log(max(getattr(start, n), 1e-12 * max(start.B_m + start.B_l, 1e-12))) for n in PARAMETER_NAMES]
    z0 += [math.degrees(epsilon_rad)]
    lo = [z - _LOG_RANGE for z in z0[:6]] + [0.0]
    hi = [z + _LOG_RANGE for z in z0[:6]] + [math.degrees(epsilon_max_rad)]
    scale = [0.1] * 6 + [0.05]
    steps = [_DIFF_STEP * max(abs(z), 1.0) for z in z0[:6]] + [1e-5]
    f_scale = max(ref, 1e-12)
    for name in obj.names[7:]:
        if name == "T_c_us":
            z0.append(max(1e6 * lag_s, 0.0))
            lo.append(0.0), hi.append(_LAG_MAX_US), scale.append(50.0), steps.append(1e-3)
        else:
            z0.append(max(coulomb_motor_nm if name == "F_cm" else coulomb_load_nm, 0.0))
            lo.append(0.0), hi.append(10.0 * f_scale), scale.append(0.01 * f_scale), steps.append(1e-6 * f_scale)
    z = np.clip(np.array(z0), lo, hi)
    # the plateau lies above the start's own residual: a poor start whose residual peaks past 10× the torque
    # is still a point the fit can move from, not a flat plateau it would stop on at once
    obj.bad = math.inf
    v0 = obj(z)
    obj.bad = 10.0 * ref
    if np.all(np.isfinite(v0)):
        obj.bad = max(obj.bad, 2.0 * float(np.max(np.abs(v0), initial=0.0)))
    lo_a, hi_a, scale_a, steps_a = (np.array(v, dtype=float) for v in (lo, hi, scale, steps))
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        if hold_epsilon:
            held = np.ones(z.size, dtype=bool)
            held[6] = False
            z, _ = _least_squares(obj, z, held, lo_a, hi_a, scale_a, steps_a, pool, _HELD_EPSILON_NFEV)
        z, res = _least_squares(obj, z, np.ones(z.size, dtype=bool), lo_a, hi_a, scale_a, steps_a, pool, max_nfev)
    r = np.asarray(res.fun)  # type: ignore[attr-defined]
    J = np.asarray(res.jac)  # type: ignore[attr-defined]
    n, k = r.size, z.size
    n_eff = _n_effective(r[:problem.acceleration_f.size - 2 * EDGE_SAMPLES])
    try:
        cov = _covariance(J, r)
        Jp = np.linalg.pinv(J)
    except np.linalg.LinAlgError:
        cov, Jp = np.full((k, k), math.nan), None
    shifts = []
    for alt_problem, alt_observer in alternates:
        alt = _Objective(alt_problem, alt_observer, terms, load_weight_nm_per_rad)
        alt.bad = obj.bad
        ra = alt(z)
        if Jp is not None and ra.shape == r.shape and np.all(np.isfinite(ra)):
            shifts.append(-(Jp @ (ra - r)))
    for d in shifts:
        cov = cov + np.outer(d, d)
    p, eps, extra = obj.unpack(z)
    return PemFit(parameters=p, epsilon_rad=eps, coulomb_motor_nm=extra.get("F_cm", 0.0),
                  coulomb_load_nm=extra.get("F_cl", 0.0), lag_s=1e-6 * extra.get("T_c_us", 0.0), terms=terms,
                  residual=r, cost_nm=float(np.sqrt(np.mean(r * r))), names=obj.names, covariance=cov,
                  n_effective=n_eff, evaluations=obj.calls + len(shifts), converged=bool(res.status > 0) and not np.all(r == obj.bad),  # type: ignore[attr-defined]
                  message=str(res.message),  # type: ignore[attr-defined]
                  discretization={n: float(np.sqrt(sum(d[i] ** 2 for d in shifts))) for i, n in enumerate(obj.names)})


_TERM_COORDINATE = {"coulomb_motor": "F_cm", "coulomb_load": "F_cl", "current_loop": "T_c_us"}


def significant_terms(result: PemFit, *, keep_all: bool = False) -> tuple[ModelTerms, dict[str, dict[str, Any]]]:
    """The terms of a fit whose Wald statistic z² = (value/σ)² exceeds ln n_eff (the BIC's price of a
    parameter), and per candidate its z², the threshold and whether it is kept."""
    threshold = math.log(max(result.n_effective, 2.0))
    selection: dict[str, dict[str, Any]] = {}
    kept = {}
    for term in result.terms.names():
        name = _TERM_COORDINATE[term]
        se = result.stderr(name)
        value = float({"F_cm": result.coulomb_motor_nm, "F_cl": result.coulomb_load_nm,
                       "T_c_us": 1e6 * result.lag_s}[name])
        z2 = (value / se) ** 2 if se > 0 else (math.inf if value > 0 else 0.0)
        kept[term] = bool(keep_all or z2 > threshold)
        selection[term] = {"z2": float(z2), "threshold": threshold, "kept": kept[term]}
    return ModelTerms(**{t: kept.get(t, False) for t in ("coulomb_motor", "coulomb_load", "current_loop")}), selection
