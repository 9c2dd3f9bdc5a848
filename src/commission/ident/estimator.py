"""The estimators: prediction-error least squares of every parameter.

:func:`kalman_fit` — **the estimate**. The one-step prediction errors of the Kalman predictor of the
whole state (:mod:`commission.ident.kalman`: exact per-mode discretization, located contact events,
noise model from the encoders' quantization and an estimated torque disturbance), minimised by
``scipy.optimize.least_squares`` (trf, bounds) over

    ln J_m, ln J_l, ln B_m, ln B_l, ln K, ln D, ε [deg]   and the kept terms   F_cm, F_cl [N·m], T_c [µs]

:func:`fit` — its start: the low-passed, decimated motor-equation residual of
:func:`commission.ident.residual.residual_vector` with a fixed-gain load-state observer, from one
cell of the scan (first with ε held at the cell's, then everything); its Wald statistics select the
optional terms (:func:`significant_terms`).

Every least squares stops once its Gauss–Newton step moves no coordinate by more than a tenth of its
standard error (:func:`_within_a_step`): what is left is below the record's own uncertainty.

Finite-difference columns run on threads (the compiled kernels release the GIL); each column is
computed alone, so the result does not depend on the number of threads. With two or more, a point's
first column is started beside the point's own evaluation (whose core would idle otherwise); where the
step is rejected it is wasted and not counted, so the evaluations do not depend on the threads either.
No accept/reject rule chooses between paths: the answer is a smooth function of the data.

Optional terms (:class:`ModelTerms`): motor Coulomb friction F_cm·tanh(ẋ_m/v_s); load Coulomb
friction F_cl·tanh(ẋ_l/v_s); a first-order current loop T_c·τ̇ = τ_ref − τ. A term is kept when its
Wald statistic (value/σ)² exceeds ln n_eff (the BIC's price of a parameter).

Uncertainty. The Newey–West (HAC) covariance at the optimum: prediction errors that are not quite
white (a coarse encoder's quantization at low speed, model error) are correlated with themselves and
with the Jacobian, which s²·(JᵀJ)⁻¹ ignores.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .kalman import Innovations, KalmanProblem, innovations
from .residual import Observer, ResidualProblem, motor_part, simulate_load
from .twomass import TwoMassParameters

__all__ = ["Hedge", "ModelTerms", "PemFit", "fit", "kalman_fit", "kalman_resettled", "significant_terms"]

PARAMETER_NAMES = ("J_m", "J_l", "B_m", "B_l", "K", "D")
#: Decimated residual samples left out at each end: the zero-phase low-pass's edge transients.
EDGE_SAMPLES = 4
#: Iterations of the first least squares, ε held at the start cell's.
_HELD_EPSILON_NFEV = 6
#: Relative finite-difference step in the log-parameters (as scipy's diff_step).
_DIFF_STEP = 1e-6
#: The divergence plateau at most (a residual or prediction error the objectives return where the model
#: diverges): its sum of squares over a million samples, and its finite differences, stay finite.
_PLATEAU_MAX = 1e100
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
    process_noise_nm: float = 0.0
    """Kalman fit: the torque disturbance per sample its predictor assumes, chosen by likelihood [N·m]
    (0: the torque-residual fit)."""
    load_share: float = 0.0
    """Kalman fit: the share of that disturbance on the load, chosen with it [-]."""
    innovations: Innovations | None = None
    """Kalman fit: the predictor's prediction errors at the optimum."""
    epsilon_profile_deg: tuple[float, float] | None = None
    """Kalman fit: ε's 95 % likelihood-ratio interval on its closing profile [deg] (None: ε at 0)."""

    @property
    def disturbance_nm(self) -> float:
        """Kalman fit: the larger of the motor's and the load's torque disturbance per sample [N·m]."""
        return self.process_noise_nm * max(1.0, self.load_share)

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
        self._last: tuple[bytes, Any] | None = None

    def _remembered(self, z: NDArray[np.float64], compute: Callable[[NDArray[np.float64]], Any],
                    remember: bool) -> Any:
        """``compute(z)``, or its value when ``z`` is the last point kept (the same bits: the evaluation is
        deterministic); ``z`` kept if ``remember``. A least squares starts where :func:`_armed` set the
        plateau, and its optimum is evaluated again by what follows (likelihood, ε polish, result); its
        finite-difference columns and the grids are not kept."""
        key, last = z.tobytes(), self._last  # (read once: another thread may replace it meanwhile)
        if last is not None and last[0] == key:
            return last[1]
        value = compute(z)
        if remember:
            self._last = (key, value)
        return value

    def unpack(self, z: NDArray[np.float64]) -> tuple[TwoMassParameters, float, dict[str, float]]:
        J_m, J_l, B_m, B_l, K, D = (float(v) for v in np.exp(z[:6]))
        extra = dict(zip(self.names[7:], (float(v) for v in z[7:])))
        return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=B_m, B_l=B_l, K=K, D=D), math.radians(float(z[6])), extra

    def __call__(self, z: NDArray[np.float64], remember: bool = True) -> NDArray[np.float64]:
        v = self._remembered(z, self._residual, remember)
        # a diverged simulation — non-finite, or a sample past the flat residual's level (a torque residual
        # 10× the RMS torque is no plant's; finite but huge, its differences overflowed the Jacobian): a
        # large, flat residual the fit steps back from, never above it
        if not (np.all(np.isfinite(v)) and float(np.max(np.abs(v), initial=0.0)) <= self.bad):
            return np.full(v.shape, self.bad)
        return v

    def _residual(self, z: NDArray[np.float64]) -> NDArray[np.float64]:
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
        v.flags.writeable = False  # kept: read, never changed
        return v


class _Workers(ThreadPoolExecutor):
    """The fits' threads (the compiled predictor and load simulation release the GIL)."""

    def __init__(self, threads: int) -> None:
        self.threads = max(1, threads)
        super().__init__(max_workers=self.threads)


def _least_squares(obj: _Objective, z0: NDArray[np.float64], free: NDArray[np.bool_], lo: NDArray[np.float64],
                   hi: NDArray[np.float64], scale: NDArray[np.float64], steps: NDArray[np.float64],
                   pool: _Workers, max_nfev: int, tol: float = 1e-8,
                   pair: tuple[int, int] | None = None) -> tuple[NDArray[np.float64], object]:
    """least_squares over the ``free`` coordinates of ``z0`` (the others held). ``pair``: two free log-coordinates
    (ln a, ln b) taken as ln(a + b) and ln(b/a) inside (:func:`_pair_coordinates`); the result (its ``x`` and
    ``jac`` too) is in ``z0``'s coordinates."""
    idx = np.flatnonzero(free)
    paired = pair is not None and bool(free[pair[0]] and free[pair[1]])
    w0, lo_w, hi_w = _pair_coordinates(z0, lo, hi, pair) if paired else (z0, lo, hi)  # type: ignore[arg-type]
    h, top = steps[idx], hi_w[idx]
    last: dict[bytes, NDArray[np.float64]] = {}
    jacobian: dict[bytes, NDArray[np.float64]] = {}
    ahead: dict[bytes, Future[NDArray[np.float64]]] = {}  # the first column's pass, started beside fun's
    started: list[Future[NDArray[np.float64]]] = []
    used = 0

    def full(y: NDArray[np.float64]) -> NDArray[np.float64]:
        z = w0.copy()
        z[idx] = y
        return _unpaired(z, lo, hi, pair) if paired else z  # type: ignore[arg-type]

    def stepped(y: NDArray[np.float64], i: int) -> NDArray[np.float64]:
        dy = y.copy()
        # a forward step, backward at an upper bound
        dy[i] += h[i] if y[i] + h[i] <= top[i] else -h[i]
        return dy

    def fun(y: NDArray[np.float64]) -> NDArray[np.float64]:
        ahead.clear()
        if pool.threads > 1:
            ahead[y.tobytes()] = pool.submit(obj, full(stepped(y, 0)), False)
            started.append(ahead[y.tobytes()])
        r = obj(full(y))
        last.clear()
        last[y.tobytes()] = r
        return r

    def jac(y: NDArray[np.float64]) -> NDArray[np.float64]:
        nonlocal used
        f0 = last.get(y.tobytes())
        if f0 is None:
            f0 = fun(y)
        first = ahead.pop(y.tobytes(), None)
        used += first is not None

        def column(i: int, r: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
            dy = stepped(y, i)
            return ((obj(full(dy), remember=False) if r is None else r) - f0) / (dy[i] - y[i])

        columns = pool.map(column, range(0 if first is None else 1, y.size))
        J = np.stack(([] if first is None else [column(0, first.result())]) + list(columns), axis=1)
        jacobian.clear()
        jacobian[y.tobytes()] = J
        return J

    def settled(intermediate_result: Any) -> None:  # (scipy passes the state by this parameter's name)
        # an iterate whose Gauss–Newton step moves no coordinate by more than a tenth of its standard
        # error is the estimate: the iterations after it only crawl below the record's own uncertainty
        # (taken, not read: after a rejected step scipy calls back at the same point, already tested)
        state = intermediate_result
        J = jacobian.pop(state.x.tobytes(), None)
        if J is not None and _within_a_step(J, np.asarray(state.fun)):
            raise StopIteration

    # xtol stays tight whatever ``tol``: it is relative to ‖z‖, which T_c_us (hundreds of µs) dominates; at
    # 1e-4 it stopped a continuation after two evaluations, its steps in the log-parameters "small"
    res = least_squares(fun, np.clip(w0[idx], lo_w[idx], hi_w[idx]), jac=jac, bounds=(lo_w[idx], hi_w[idx]),
                        method="trf", x_scale=scale[idx], max_nfev=max_nfev, ftol=tol, xtol=_KALMAN_TOL,
                        callback=settled)
    wait(started)  # (a pass still running on a rejected point: done before its count is taken back)
    obj.calls -= len(started) - used
    if res.status == _STOPPED_BY_CALLBACK:
        res.status, res.message = _SETTLED, "the Gauss–Newton step is within a tenth of a standard error"
    z = full(res.x)
    if paired:
        _unpaired_result(res, z, idx, pair)  # type: ignore[arg-type]
    return z, res


def _unpaired_result(res: Any, z: NDArray[np.float64], idx: NDArray[np.intp], pair: tuple[int, int]) -> None:
    """A least squares' result in :func:`_pair_coordinates` (``res.x``, ``res.jac``) put in ``z``'s
    coordinates: ∂r/∂z = ∂r/∂y·∂y/∂z, y = ln(a + b) moving with a's and b's shares of the sum, ln(b/a)
    with −1 and +1."""
    a, b = pair
    dy = np.eye(z.size)
    wa = 1.0 / (1.0 + math.exp(z[b] - z[a]))
    dy[a, a], dy[a, b], dy[b, a], dy[b, b] = wa, 1.0 - wa, -1.0, 1.0
    res.jac = np.asarray(res.jac) @ dy[np.ix_(idx, idx)]
    res.x = z[idx]


def _pair_coordinates(z: NDArray[np.float64], lo: NDArray[np.float64], hi: NDArray[np.float64],
                      pair: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``z``, ``lo`` and ``hi`` with the log-coordinates ``pair`` = (ln a, ln b) replaced by ln(a + b) and ln(b/a)
    (the bounds: a box holding the original one). A record that determines a + b tightly and the split loosely
    (the motor's and the load's viscous damping) has a curved valley in (ln a, ln b): a least squares there
    crawls (23:054: 200 evaluations for a third of the way), and along a straight one in these it does not."""
    a, b = pair
    w, lo_w, hi_w = z.copy(), lo.copy(), hi.copy()
    w[a], w[b] = np.logaddexp(z[a], z[b]), z[b] - z[a]
    lo_w[a], hi_w[a] = np.logaddexp(lo[a], lo[b]), np.logaddexp(hi[a], hi[b])
    lo_w[b], hi_w[b] = lo[b] - hi[a], hi[b] - lo[a]
    return w, lo_w, hi_w


def _unpaired(w: NDArray[np.float64], lo: NDArray[np.float64], hi: NDArray[np.float64],
              pair: tuple[int, int]) -> NDArray[np.float64]:
    """The coordinates of :func:`_pair_coordinates`'s ``w``, within ``lo`` and ``hi``."""
    a, b = pair
    z = w.copy()
    z[a] = w[a] - np.logaddexp(0.0, w[b])
    z[b] = z[a] + w[b]
    z[a], z[b] = np.clip(z[a], lo[a], hi[a]), np.clip(z[b], lo[b], hi[b])
    return z


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


def _held_covariance(res: Any, free: NDArray[np.bool_]) -> NDArray[np.float64]:
    """The Newey–West covariance of a least squares over the ``free`` coordinates, in the full coordinates
    (a held one has no variance of its own; NaN where the Jacobian is singular)."""
    cov = np.zeros((free.size, free.size))
    try:
        cov[np.ix_(free, free)] = _covariance(np.asarray(res.jac), np.asarray(res.fun))
    except np.linalg.LinAlgError:
        cov[np.ix_(free, free)] = math.nan
    return cov


def fit(problem: ResidualProblem, start: TwoMassParameters, epsilon_rad: float, terms: ModelTerms,
        observer: Observer, *, coulomb_motor_nm: float = 0.0, coulomb_load_nm: float = 0.0, lag_s: float = 0.0,
        epsilon_max_rad: float,
        load_weight_nm_per_rad: float = 0.0, threads: int = 2, max_nfev: int = 40,
        hold_epsilon: bool = True) -> PemFit:
    """Least squares of every parameter from ``start`` and ``epsilon_rad`` (see the module docstring).

    :param coulomb_motor_nm: start of F_cm [N·m]; ``coulomb_load_nm``: of F_cl [N·m].
    :param lag_s: start of T_c [s].
    :param epsilon_max_rad: upper bound of ε [rad].
    :param hold_epsilon: first fit the others with ε held (a start from a scan cell).
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
        # (a diverged start can be finite at 1e288: a plateau there overflows the least squares' sums, 22:185)
        obj.bad = min(max(obj.bad, 2.0 * float(np.max(np.abs(v0), initial=0.0))), _PLATEAU_MAX)
    lo_a, hi_a, scale_a, steps_a = (np.array(v, dtype=float) for v in (lo, hi, scale, steps))
    with _Workers(threads) as pool:
        if hold_epsilon:
            held = np.ones(z.size, dtype=bool)
            held[6] = False
            z, _ = _least_squares(obj, z, held, lo_a, hi_a, scale_a, steps_a, pool, _HELD_EPSILON_NFEV)
        z, res = _least_squares(obj, z, np.ones(z.size, dtype=bool), lo_a, hi_a, scale_a, steps_a, pool, max_nfev)
    r = np.asarray(res.fun)  # type: ignore[attr-defined]
    return _result(obj, z, res, _n_effective(r[:problem.acceleration_f.size - 2 * EDGE_SAMPLES]), obj.calls)


def _result(obj: _Objective, z: NDArray[np.float64], res: Any, n_effective: float, evaluations: int,
            free: NDArray[np.bool_] | None = None, cov: NDArray[np.float64] | None = None, **fields: Any) -> PemFit:
    """The :class:`PemFit` of a least squares' optimum ``z`` over its ``free`` coordinates (default: all;
    its Newey–West covariance ``cov``, computed from ``res`` when not given)."""
    r = np.asarray(res.fun)
    free = np.ones(z.size, dtype=bool) if free is None else free
    cov = _held_covariance(res, free) if cov is None else cov
    p, eps, extra = obj.unpack(z)
    return PemFit(parameters=p, epsilon_rad=eps, coulomb_motor_nm=extra.get("F_cm", 0.0),
                  coulomb_load_nm=extra.get("F_cl", 0.0), lag_s=1e-6 * extra.get("T_c_us", 0.0), terms=obj.terms,
                  residual=r, cost_nm=float(np.sqrt(np.mean(r * r))), names=obj.names, covariance=cov,
                  n_effective=n_effective, evaluations=evaluations,
                  converged=bool(res.status > 0 or _within_a_step(np.asarray(res.jac), r, cov[np.ix_(free, free)])) and not np.all(r == obj.bad),
                  message=str(res.message), **fields)


#: A least squares stopped at its evaluation limit has converged all the same when its Gauss–Newton step
#: from there moves no coordinate by more than this share of its standard error: on a likelihood rugged
#: at the difference step's scale the cost keeps falling by more than ftol in ever smaller steps.
_CONVERGED_STEP = 0.1


#: scipy's status of a least squares its callback stopped, and the status it is given here (converged).
_STOPPED_BY_CALLBACK, _SETTLED = -2, 5


def _within_a_step(J: NDArray[np.float64], r: NDArray[np.float64], cov: NDArray[np.float64] | None = None) -> bool:
    """Whether the Gauss–Newton step −(JᵀJ)⁻¹Jᵀr (J: n × p, r: n) is within ``_CONVERGED_STEP`` standard
    errors in every coordinate: those of ``cov`` (p × p), by default the Newey–West covariance, computed
    only when the plain s²·(JᵀJ)⁻¹ does not already rule the step out (it costs ~20 products of J)."""
    with np.errstate(all="ignore"):  # differences across a divergence plateau: no step to speak of
        try:
            Hinv = np.linalg.pinv(J.T @ J)
            step = np.abs(Hinv @ (J.T @ r))
            if cov is None:
                plain = float(r @ r) / max(r.size - J.shape[1], 1) * np.diag(Hinv)
                if not np.all(step <= _CONVERGED_STEP * np.sqrt(plain)):
                    return False
                cov = _covariance(J, r)
        except np.linalg.LinAlgError:
            return False
        return bool(np.all(step <= _CONVERGED_STEP * np.sqrt(np.diag(cov))))


_TERM_COORDINATE = {"coulomb_motor": "F_cm", "coulomb_load": "F_cl", "current_loop": "T_c_us"}
_TERM_FIELD = {"coulomb_motor": "coulomb_motor_nm", "coulomb_load": "coulomb_load_nm", "current_loop": "lag_s"}
#: The dampings' coordinates (B_m, B_l, D): logarithms, held where they stand when not determined.
_DAMPINGS = (2, 3, 5)


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


# --- the estimator: prediction errors of the Kalman predictor -------------------------------------
#: Torque disturbances per sample, relative to RMS τ_ref, of the Kalman fits before the noise model is
#: chosen: a predictor that follows the record closely has a wide basin, one that trusts the model a
#: sharp minimum.
_CONTINUATION = (1e-2, 1e-3)
#: The continuation's least squares on the Cauchy likelihood (:meth:`_KalmanObjective._cauchy`): its
#: basin around the truth is wide where the Gaussian one is a needle; the final fit is Gaussian.
_ROBUST_CONTINUATION = True
#: Torque disturbance (relative to RMS τ_ref) of the final noise model above which the fit is sharpened
#: again from its estimate, at most this many rounds: above a drive's own torque noise, below what the
#: family's wrong basins needed (both measured in bench/results/family.md).
_SHARPEN_ABOVE = 2e-2
_SHARPEN_ROUNDS = 2
#: ... and the levels the noise model is chosen among by likelihood at the first fit's optimum.
_PROCESS_NOISE_GRID = (1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 3e-1)
#: Further rounds of ``max_nfev`` iterations the final least squares gets when it stops at its evaluation
#: limit (a round restarts the trust region too). Where the valley is long the rounds needed differ between
#: machines (floating-point paths): 2 sufficed on one, 3 on another for the same fit; 4 leaves a margin.
_LIMIT_ROUNDS = 4
#: ... in which the viscous dampings (ln B_m, ln B_l) are fitted as their sum and ratio.
_VISCOUS_PAIR = (2, 3)
#: The Kalman fit's log-parameters are bounded to ×/÷ this around its start: its predictor stays finite
#: far from the plant, and a start's damping can be off by more than ``_LOG_RANGE``.
_KALMAN_LOG_RANGE = math.log(1e3)
#: ln of the smallest damping rate B/J [1/s] at the start's inertia: a time constant of years, which no
#: record tells from none, and with J ×1000 still clear of coincident poles (cond(V) ≈ 2·J/B < 1e12).
_DAMPING_RATE_FLOOR = math.log(1e-8)
#: ε's closing profile: ± this share of the estimate, on this many points; its best local minima start
#: the final fit again.
_POLISH_SPAN = 0.08
_POLISH_POINTS = 17
_POLISH_STARTS = 3
_PROFILE_FIRST = True
#: Iterations of each continuation fit at most, and its relative tolerance in cost (they only bring the
#: estimate into the final fit's basin; the first 50 of the family end the same with 8 as with 20).
_CONTINUATION_NFEV = 8
_CONTINUATION_TOL = 1e-4
_KALMAN_TOL = 1e-8
#: Shares of the disturbance on the load the noise model is chosen among: none (a drive's torque noise
#: acts on the motor), or enough for the predictor to follow a load thrown around the gap; with a load
#: encoder, mostly on the load too: there the encoder shows where the load's stick-slip departs from the
#: model's smooth friction (22:180's truth: 0.3 % on the motor, 3× that on the load, the likeliest; from
#: the first two alone 2.1 % on the motor, flagged).
_LOAD_SHARES = (0.0, 0.3)
_LOAD_ENCODER_SHARES = (*_LOAD_SHARES, 3.0)
#: ε factors tried at the chosen noise level before the second fit (then ± half and a quarter of a step
#: around the best): a predictor that trusts the model sees ε sharply, with local minima ±10 % around
#: the optimum.
_EPSILON_FACTORS = tuple(float(f) for f in np.geomspace(0.5, 2.0, 13))
#: ε below which the continuation's estimate is taken as no gap at all [deg]: a fifth of the smallest
#: backlash reported as one (``no_backlash_threshold_deg``'s default).
EPSILON_ZERO_DEG = 0.002
#: The hedged fit (``kalman_fit(hedge=...)``): a random walk of the twist per sample, relative to ε, in
#: every predictor; its sigma points take the modes the twist's uncertainty reaches, so the likelihood has a
#: basin around the gap where the plain predictor's is a needle, and loses little at the truth (22:079:
#: NLL per sample 1.80 → 1.88).
_HEDGE_TWIST_NOISE = 1e-4
#: ... and before it, Gaussian least squares at a disturbance of 1 % with the twist's random walk taken
#: down over these multiples of the start's ε per sample, the first after ε's grid (:class:`Hedge`).
_HEDGE_CONTINUATION = (1e-2, 1e-3, 1e-4)
_HEDGE_NFEV = 40
_HEDGE_GRID_POINTS = 40
_HEDGE_GRID_FROM_DEG = 0.02


class Hedge(Enum):
    """The predictor :func:`kalman_fit` hedges the gap's contacts with, and where its ε starts."""

    NONE = "none"
    """The plain predictor: sharp at the optimum, a needle around the gap on impact-rich records."""
    NEAR = "near"
    """Sigma points across the twist, ε started at the best of ``_EPSILON_FACTORS`` × the start's: a start
    a few % off, such as the torque-residual fit's (the plain fit moves from ±2 % only, this one from ±5–10 %)."""
    START = "start"
    """:attr:`NEAR`'s start only (ε's grid, the random walk taken down), the plain predictor from there: what
    brings ε into the gap's basin, at half the cost of the whole hedged fit (bench/results/family.md)."""
    GLOBAL = "global"
    """Sigma points, ε started at the best of its global grid: a start whose ε basin is unknown."""


class _KalmanObjective(_Objective):
    """The prediction errors of :func:`commission.ident.kalman.innovations`, over each encoder's noise."""

    def __init__(self, problem: KalmanProblem, terms: ModelTerms, process_noise_nm: float, load_share: float,
                 robust: bool = False, twist_noise: float = 0.0, twist_noise_rad: float = 0.0) -> None:
        self.kp, self.terms, self.process_noise_nm, self.load_share = problem, terms, process_noise_nm, load_share
        self.robust = robust
        self.twist_noise, self.twist_noise_rad = twist_noise, twist_noise_rad
        """A random walk of the twist per sample, relative to ε, or in rad (0, 0: none); with it the predictor's
        sigma points take the gap's modes the twist's uncertainty reaches
        (:func:`commission.ident.kalman.innovations`)."""
        self.names = tuple(f"ln {n}" for n in PARAMETER_NAMES) + ("eps_deg",) + tuple(
            n for n, on in (("F_cm", terms.coulomb_motor), ("F_cl", terms.coulomb_load),
                            ("T_c_us", terms.current_loop)) if on)
        self.calls = 0
        self.bad = math.inf
        self.size = (problem.motor_position.size - 1) * problem.outputs
        self._last = None

    def innovations(self, z: NDArray[np.float64], remember: bool = True) -> Innovations | None:
        return self._remembered(z, self._innovations, remember)  # type: ignore[no-any-return]

    def _innovations(self, z: NDArray[np.float64]) -> Innovations | None:
        self.calls += 1
        p, eps, extra = self.unpack(z)
        return innovations(self.kp, p, eps, coulomb_motor_nm=extra.get("F_cm", 0.0),
                           coulomb_load_nm=extra.get("F_cl", 0.0), lag_s=1e-6 * extra.get("T_c_us", 0.0),
                           process_noise_nm=self.process_noise_nm, load_share=self.load_share,
                           twist_noise_rad=self.twist_noise_rad or self.twist_noise * eps,
                           sigma_points=self.twist_noise_rad > 0.0 or self.twist_noise > 0.0)

    def __call__(self, z: NDArray[np.float64], remember: bool = True) -> NDArray[np.float64]:
        """e_k/√S_k · ⁿ√(Π S): its sum of squares is the likelihood with the noise's scale concentrated out,
        exp(−2·ln L/N) up to a constant. The prediction errors alone (Σe²) reward a model that makes the
        filter trust the encoders (a tiny J_m turns the torque disturbance into a huge acceleration
        noise): a wrong basin the variances' term closes."""
        inn = self.innovations(z, remember)
        if inn is None:
            v = np.full(self.size + self.robust, math.inf)
        elif self.robust:
            v = self._cauchy(inn)
        else:
            v = (inn.normalized * math.exp(0.5 * float(np.mean(inn.log_variance)))).ravel()
        if not (np.all(np.isfinite(v)) and float(np.max(np.abs(v), initial=0.0)) <= self.bad):
            return np.full(v.shape, self.bad)
        return v

    @staticmethod
    def _cauchy(inn: Innovations) -> NDArray[np.float64]:
        """Residuals whose sum of squares is the Cauchy (Student-t, one degree of freedom) negative
        log-likelihood Σ ln(1 + ν²) + ½·Σ ln S: each prediction error's ±√ln(1 + ν²) (≈ ν near 0), and one
        element for the variances. On an impact-rich record a model a few % off loses the contact timing
        for a few samples, errors of hundreds of σ that make the Gaussian likelihood a needle at the
        truth; their logarithm leaves a valley around it."""
        nu = inn.normalized.ravel()
        return np.concatenate((np.sign(nu) * np.sqrt(np.log1p(nu * nu)),
                               [math.sqrt(0.5 * max(float(np.sum(inn.log_variance)), 0.0))]))


def _coordinates(start: PemFit, obj: _Objective, epsilon_max_rad: float, torque_rms_nm: float) -> tuple[
        NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(z, lo, hi, x_scale, diff steps) of a fit from ``start``'s estimate (its terms' values included)."""
    p = start.parameters
    z = [math.log(getattr(p, n)) for n in PARAMETER_NAMES] + [math.degrees(start.epsilon_rad)]
    lo = [v - _KALMAN_LOG_RANGE for v in z[:6]] + [0.0]
    hi = [v + _KALMAN_LOG_RANGE for v in z[:6]] + [math.degrees(epsilon_max_rad)]
    for b, j in ((2, 0), (3, 1)):  # B_m over J_m, B_l over J_l
        # a damping near 0 makes its mass's two poles in the gap coincide, where the predictor has no eigen
        # decomposition and a fit started there cannot move (a torque-residual fit's on a record no model explains)
        floor = z[j] + _DAMPING_RATE_FLOOR
        if lo[b] < floor:  # (bounds left as they were otherwise: the least squares' path depends on them)
            lo[b], hi[b], z[b] = floor, max(hi[b], floor + 2.0 * _KALMAN_LOG_RANGE), max(z[b], floor)
    scale = [0.1] * 6 + [0.05]
    steps = [_DIFF_STEP * max(abs(v), 1.0) for v in z[:6]] + [1e-5]
    f = max(torque_rms_nm, 1e-12)
    for name in obj.names[7:]:
        if name == "T_c_us":
            z.append(1e6 * start.lag_s)
            lo.append(0.0), hi.append(_LAG_MAX_US), scale.append(50.0), steps.append(1e-3)
        else:
            z.append(start.coulomb_motor_nm if name == "F_cm" else start.coulomb_load_nm)
            lo.append(0.0), hi.append(10.0 * f), scale.append(0.01 * f), steps.append(1e-6 * f)
    lo_a, hi_a = np.array(lo), np.array(hi)
    return np.clip(np.array(z), lo_a, hi_a), lo_a, hi_a, np.array(scale), np.array(steps)


def _epsilon_profile(obj: _KalmanObjective, z: NDArray[np.float64], top_deg: float,
                     pool: ThreadPoolExecutor) -> NDArray[np.float64]:
    """``z`` with ε moved to the lowest cost of the profile (the other coordinates held) over
    ``_EPSILON_FACTORS`` of it, refined around the best."""
    def at(eps_deg: float) -> NDArray[np.float64]:
        return np.concatenate((z[:6], [min(eps_deg, top_deg)], z[7:]))

    def best(values: list[float]) -> float:
        costs = list(pool.map(lambda e: float(np.sum(obj(at(e), remember=False) ** 2)), values))
        return values[int(np.argmin(costs))]

    e = best([z[6] * f for f in _EPSILON_FACTORS])
    step = _EPSILON_FACTORS[1] / _EPSILON_FACTORS[0]
    e = best([e * step ** a for a in (-0.5, -0.25, 0.0, 0.25, 0.5)])
    return at(e)


def _nll(obj: _KalmanObjective, z: NDArray[np.float64]) -> float:
    """The negative log-likelihood per prediction error at ``z`` under ``obj``'s noise model."""
    inn = obj.innovations(z)
    return inn.negative_log_likelihood() if inn is not None else math.inf


def _hold(obj: _KalmanObjective, z: NDArray[np.float64], res: Any, free: NDArray[np.bool_], sample_rate_hz: float,
          keep_all: bool) -> None:
    """Hold at 0, in place, what the continuation's optimum does not support: a term within a standard
    error of 0 (a spurious term absorbs what a slightly wrong basin leaves and moves ε with it; every
    term stays with ``keep_all``), and a gap below ``EPSILON_ZERO_DEG`` (a free ε near 0 switches mode
    at every zero crossing of the twist and the fit crawls there)."""
    cov = _held_covariance(res, free)
    selection = _term_selection(obj, z, res, cov, free, sample_rate_hz, _TERM_HOLD)
    _hold_dampings(cov, free)
    for term, sel in selection.items():
        if not (sel["kept"] or keep_all):
            i = obj.names.index(_TERM_COORDINATE[term])
            z[i], free[i] = 0.0, False
    if z[6] < EPSILON_ZERO_DEG:
        z[6], free[6] = 0.0, False


def _hold_dampings(cov: NDArray[np.float64], free: NDArray[np.bool_]) -> bool:
    """Hold, in place, a damping within a standard error of 0 where it stands (B/σ_B = 1/σ of ln B, so
    σ(ln B) > 1): on its log scale the fit would crawl toward 0 without end (a light load's B_l trades
    with B_m). Returns whether one was held; ``cov`` is the covariance of the least squares over ``free``
    as it was (:func:`_held_covariance`)."""
    held = False
    for i in _DAMPINGS:
        if free[i] and not cov[i, i] <= _TERM_HOLD:
            free[i], held = False, True
    return held


def _polished(obj: _KalmanObjective, z: NDArray[np.float64], res: Any, top_deg: float,
              ls: Callable[[_KalmanObjective, NDArray[np.float64], int], tuple[NDArray[np.float64], Any]],
              max_nfev: int, pool: ThreadPoolExecutor) -> tuple[NDArray[np.float64], Any, tuple[float, float]]:
    """ε's likelihood is rugged at this scale (grazing contacts come and go): the best of a fine profile
    around the optimum, and the interval the likelihood ratio gives on it; the profile's local minima
    start the final fit again, the lowest cost kept. Returns (z, its least squares, the interval [deg])."""
    starts, interval = _epsilon_polish(obj, z, top_deg, pool)
    for s in starts:
        if s[6] != z[6]:
            zs, rs = ls(obj, s, max_nfev)
            if float(np.sum(np.asarray(rs.fun) ** 2)) < float(np.sum(np.asarray(res.fun) ** 2)):
                z, res = zs, rs
    return z, res, interval


def _armed(obj: _KalmanObjective, z: NDArray[np.float64]) -> _KalmanObjective:
    """``obj`` with its divergence plateau set far above its residual at ``z`` (and far below where its sum of
    squares would overflow: a predictor that diverges can return finite values of 1e200)."""
    v0 = obj(z)
    obj.bad = min(1e3 * max(1.0, float(np.max(np.abs(v0)))), _PLATEAU_MAX) if np.all(np.isfinite(v0)) else 1e12
    return obj


def _noise_level(at: Callable[[float, float], Innovations | None], pool: ThreadPoolExecutor,
                 shares: tuple[float, ...] = _LOAD_SHARES) -> tuple[float, float]:
    """The noise model of the largest likelihood: (torque disturbance relative to RMS τ_ref, the load's
    share of it) over ``_PROCESS_NOISE_GRID`` × ``shares``, the level then refined to the vertex of
    the parabola in ln q through the best and its neighbours."""
    grid = np.array(_PROCESS_NOISE_GRID)
    cells = [(float(q), share) for share in shares for q in grid]
    nll = np.array(list(pool.map(lambda c: (lambda i: i.negative_log_likelihood() if i is not None else math.inf)(
        at(*c)), cells))).reshape(len(shares), grid.size)
    nll[~np.isfinite(nll)] = math.inf  # (argmin would take a NaN for the least)
    j, i = np.unravel_index(int(np.argmin(nll)), nll.shape)
    share, row = shares[int(j)], nll[int(j)]
    if 0 < i < grid.size - 1 and np.all(np.isfinite(row[i - 1:i + 2])):
        x = np.log(grid[i - 1:i + 2])
        c = np.polyfit(x, row[i - 1:i + 2], 2)
        if c[0] > 0:
            return float(np.exp(np.clip(-c[1] / (2 * c[0]), x[0], x[2]))), share
    return float(grid[i]), share


def _epsilon_polish(obj: _KalmanObjective, z: NDArray[np.float64], top_deg: float,
                    pool: ThreadPoolExecutor) -> tuple[list[NDArray[np.float64]], tuple[float, float]]:
    """ε over ±``_POLISH_SPAN`` of the estimate (the other coordinates held): the profile's local minima,
    most likely first (at most ``_POLISH_STARTS``), and the range of grid points within the 95 %
    likelihood-ratio threshold (χ²₁: 3.84) of the best — ends stretched to the next grid point, where
    the ratio is known to be past it [deg]."""
    grid = [min(z[6] * (1.0 + _POLISH_SPAN * f), top_deg) for f in np.linspace(-1.0, 1.0, _POLISH_POINTS)]

    def nll(eps_deg: float) -> float:
        inn = obj.innovations(np.concatenate((z[:6], [eps_deg], z[7:])), remember=False)
        return inn.negative_log_likelihood() * inn.normalized.size if inn is not None else math.inf

    costs = np.array(list(pool.map(nll, grid)))
    costs[~np.isfinite(costs)] = math.inf  # a predictor that broke down there: no minimum
    if not np.isfinite(costs).any():  # ... nor anywhere on the profile: nothing to polish, nothing bounded
        return [], (0.0, top_deg)
    padded = np.concatenate(([math.inf], costs, [math.inf]))
    minima = [i for i in range(len(grid)) if padded[i + 1] <= padded[i] and padded[i + 1] <= padded[i + 2]]
    minima = sorted(minima, key=lambda i: costs[i])[:_POLISH_STARTS]
    i = minima[0]
    inside = np.flatnonzero(costs <= costs[i] + 3.84)
    a, b = int(inside.min()), int(inside.max())
    lo_deg = grid[max(a - 1, 0)] if a > 0 else 0.0
    hi_deg = grid[min(b + 1, len(grid) - 1)] if b < len(grid) - 1 else top_deg
    return [np.concatenate((z[:6], [grid[j]], z[7:])) for j in minima], (lo_deg, hi_deg)


def kalman_fit(problem: KalmanProblem, start: PemFit, *, epsilon_max_rad: float, threads: int = 2,
               max_nfev: int = 30, keep_all: bool = False, hedge: Hedge = Hedge.NONE,
               memo: dict[str, Any] | None = None) -> PemFit:
    """The prediction-error estimate with the Kalman predictor of the whole state, from ``start``
    (its parameters, ε, terms and their values).

    1. continuation (``_CONTINUATION``): the Cauchy likelihood's least squares with a predictor that
       assumes a large torque disturbance (wide basin; ε profiled there), then one that trusts the model;
    2. the noise model chosen by likelihood there (encoders' quantization known; the torque disturbance
       and its share on the load estimated), and the least squares of the Gaussian likelihood, the
       noise's scale concentrated out (:meth:`_KalmanObjective.__call__`), sharpened again while its
       noise model needs more than ``_SHARPEN_ABOVE``; intervals: its Newey–West covariance.

    Terms: each of ``start.terms`` is a coordinate; after the continuation one within a standard error of
    0 is held there (none with ``keep_all``); the result keeps a term by its Wald statistic on the final
    fit (``terms`` and ``selection`` say which). Deterministic: fixed starts and grids, Jacobian columns
    computed one by one (threads only share them out): a smooth function of the record.

    ``hedge`` (not :attr:`Hedge.NONE`): every predictor with the twist's random walk ``_HEDGE_TWIST_NOISE``
    (sigma points across the gap), the continuation started by :func:`_hedge` (ε's grid, the random walk
    taken down), and the noise model chosen again where the sharpening and the polish end: for a start
    outside the needle the plain likelihood has around the gap. :attr:`Hedge.START`: that start, then the
    plain fit. ``memo``: a dict shared by fits of the same ``problem``: the hedged start one of them computed
    is taken by the next from the same coordinates (a :attr:`Hedge.START` fit, then the :attr:`Hedge.NEAR`
    fit from the same start, repeats none of it).
    """
    with _Workers(threads) as pool:
        run = _KalmanFit(problem, start, epsilon_max_rad, pool, max_nfev, hedge)
        obj, z, res = run.continuation(keep_all, memo)
        obj, z, res = run.sharpened(obj, z, res)
        for _ in range(_LIMIT_ROUNDS):
            if res.status > 0:
                break
            # stopped at the evaluation limit: a damping crawling toward 0 is held, and a fit still
            # descending a long valley from a start far off in a pair the record ties together (23:012's
            # B_m and B_l beside 9 % Coulomb friction) goes on, along the valley (:func:`_pair_coordinates`)
            _hold_dampings(_held_covariance(res, run.free), run.free)
            z, res = run.ls(obj, z, max_nfev, pair=_VISCOUS_PAIR)
        interval = None
        if z[6] > 0:
            obj, z, res, interval = run.polished(obj, z, res)
        run.calls += obj.calls
    return _kalman_result(obj, z, res, run.free, run.calls, start.selection, keep_all, interval)


def kalman_resettled(problem: KalmanProblem, estimate: PemFit, *, epsilon_max_rad: float, threads: int = 2,
                     max_nfev: int = 30) -> PemFit:
    """``estimate`` (a :func:`kalman_fit` result) with the noise model chosen again at it and the least
    squares with that model, when the record is then more likely; else ``estimate`` itself.

    :func:`kalman_fit` chooses the noise model where its continuation ends: a fit started far from its
    estimate (a term added at another fit's value) can end where another noise model explains the record
    much better, and is then judged against other fits at a disadvantage (22:171: 1.35 → 1.08 per
    prediction error)."""
    before = _likelihood(estimate)
    with _Workers(threads) as pool:
        run = _KalmanFit(problem, estimate, epsilon_max_rad, pool, max_nfev, Hedge.NONE)
        if run.z[6] < EPSILON_ZERO_DEG:
            run.z[6], run.free[6] = 0.0, False
        obj, z, res = run.settle(run.z)
        if not _nll(obj, z) < before:
            return replace(estimate, evaluations=estimate.evaluations + run.calls + obj.calls)
        interval = None
        if z[6] > 0:
            obj, z, res, interval = run.polished(obj, z, res)
        run.calls += obj.calls
    again = _kalman_result(obj, z, res, run.free, run.calls, estimate.selection, False, interval)
    if not _likelihood(again) < before:  # the term selection dropped what the likelihood needed
        return replace(estimate, evaluations=estimate.evaluations + run.calls)
    return replace(again, evaluations=estimate.evaluations + again.evaluations)


def omitted_term_scores(problem: KalmanProblem, estimate: PemFit, candidates: ModelTerms, *,
                        epsilon_max_rad: float) -> dict[str, float]:
    """The score (Lagrange multiplier) statistic at a :func:`kalman_fit` ``estimate`` of each of ``candidates``
    it leaves out, the term at 0 and its noise model held: the drop in −2·ln L a Gauss–Newton step on that
    term alone would give (0 where the step points below the term's bound of 0). One predictor pass at the
    estimate and one per term; the other coordinates do not move, so a term they stand in for scores less
    than it would gain in a fit."""
    omitted = [n for n in candidates.names() if not getattr(estimate.terms, n)]
    if not omitted:
        return {}
    # every omitted term switched on at 0: the same predictor as the estimate's, with a coordinate for each
    terms = replace(estimate.terms, **{n: True for n in omitted})
    at = replace(estimate, terms=terms, **{_TERM_FIELD[n]: 0.0 for n in omitted})
    obj = _KalmanObjective(problem, terms, estimate.process_noise_nm, estimate.load_share)
    z, _, _, _, steps = _coordinates(at, obj, epsilon_max_rad, problem.torque_rms_nm)
    r0 = obj(z, remember=False)
    s = float(r0 @ r0)
    out: dict[str, float] = {}
    for name in omitted:
        i = obj.names.index(_TERM_COORDINATE[name])
        dz = z.copy()
        dz[i] += steps[i]
        column = (obj(dz, remember=False) - r0) / steps[i]
        g, h = float(column @ r0), float(column @ column)
        # the sum of squares is the likelihood's generalized variance: −2·ln L = N·ln(S/N) + const
        out[name] = r0.size * -math.log1p(-g * g / (h * s)) if g < 0.0 and h > 0.0 and s > 0.0 else 0.0
    return out


def _likelihood(estimate: PemFit) -> float:
    """A Kalman fit's negative log-likelihood per prediction error (inf without its prediction errors)."""
    return estimate.innovations.negative_log_likelihood() if estimate.innovations is not None else math.inf


class _KalmanFit:
    """One :func:`kalman_fit`: the coordinates' start, bounds and scales, the coordinates held, the
    thread pool, and the predictor evaluations spent (``calls``)."""

    def __init__(self, problem: KalmanProblem, start: PemFit, epsilon_max_rad: float, pool: _Workers,
                 max_nfev: int, hedge: Hedge) -> None:
        self.problem, self.terms, self.ref = problem, start.terms, problem.torque_rms_nm
        self.pool, self.max_nfev, self.hedge = pool, max_nfev, hedge
        self.hedged = hedge is not Hedge.NONE
        self.twist = _HEDGE_TWIST_NOISE if self.hedged else 0.0
        self.z, self.lo, self.hi, self.scale, self.steps = _coordinates(
            start, self.objective(_CONTINUATION[0]), epsilon_max_rad, self.ref)
        self.top_deg = float(self.hi[6])
        self.free = np.ones(self.z.size, dtype=bool)
        self.calls = 0

    def objective(self, level: float, share: float = _LOAD_SHARES[-1], robust: bool = False) -> _KalmanObjective:
        """The predictor with a torque disturbance of ``level`` × RMS τ_ref, ``share`` of it on the load."""
        return _KalmanObjective(self.problem, self.terms, level * self.ref, share, robust, self.twist)

    def ls(self, o: _KalmanObjective, z0: NDArray[np.float64], nfev: int, tol: float = _KALMAN_TOL,
           pair: tuple[int, int] | None = None) -> tuple[NDArray[np.float64], Any]:
        return _least_squares(o, z0, self.free, self.lo, self.hi, self.scale, self.steps, self.pool, nfev, tol,
                              pair)

    def settle(self, z0: NDArray[np.float64]) -> tuple[_KalmanObjective, NDArray[np.float64], Any]:
        """The noise model of the largest likelihood at ``z0``, and the least squares with it."""
        shares = _LOAD_SHARES if self.problem.load_position is None else _LOAD_ENCODER_SHARES
        level, share = _noise_level(lambda lv, sh: self.objective(lv, sh).innovations(z0), self.pool, shares)
        self.calls += len(_PROCESS_NOISE_GRID) * len(shares)
        o = _armed(self.objective(level, share), z0)
        return (o, *self.ls(o, z0, self.max_nfev))

    def continuation(self, keep_all: bool,
                     memo: dict[str, Any] | None = None) -> tuple[_KalmanObjective, NDArray[np.float64], Any]:
        """Step 1 (the hedged fit started by :func:`_hedge`, or taken from ``memo``), the terms within a
        standard error of 0 held, and the noise model settled where it ends."""
        z, profiled = self.z, False
        if self.hedged and z[6] > 0:
            # the hedged start is a deterministic function of these: an equal key is the same start
            key = (z.tobytes(), self.lo.tobytes(), self.hi.tobytes(), self.terms, self.hedge is Hedge.GLOBAL)
            if memo is not None and memo.get("key") == key:
                z = memo["z"].copy()
            else:
                z, spent = _hedge(lambda noise_rad: _KalmanObjective(
                    self.problem, self.terms, _CONTINUATION[0] * self.ref, _LOAD_SHARES[-1],
                    twist_noise_rad=noise_rad), z, self.top_deg, self.ls, self.pool, self.hedge)
                self.calls += spent
                if memo is not None:
                    memo.update(key=key, z=z.copy())
            profiled = True
            if self.hedge is Hedge.START:
                self.hedged, self.twist, profiled = False, 0.0, False
        # a predictor that follows the record (wide basin, where ε is profiled), then one that trusts the
        # model (sharp minimum; a profile there could jump to a neighbouring valley)
        for level in _CONTINUATION:
            obj = _armed(self.objective(level, robust=_ROBUST_CONTINUATION), z)
            if level == _CONTINUATION[0] and z[6] > 0 and _PROFILE_FIRST and not profiled:
                z = _epsilon_profile(obj, z, self.top_deg, self.pool)
            z, res = self.ls(obj, z, _CONTINUATION_NFEV, _CONTINUATION_TOL)
            self.calls += obj.calls
        _hold(obj, z, res, self.free, self.problem.sample_rate_hz, keep_all)
        return self.settle(z)

    def sharpened(self, obj: _KalmanObjective, z: NDArray[np.float64],
                  res: Any) -> tuple[_KalmanObjective, NDArray[np.float64], Any]:
        """A noise model that needs a large disturbance flattens the likelihood: the fit may have stopped in
        a neighbouring basin; sharpened again from there (the Cauchy likelihood at the smallest
        continuation level), the noise model chosen again, kept if the record is more likely."""
        nll = math.nan  # the current estimate's, computed once and carried from round to round
        share = obj.load_share
        for _ in range(_SHARPEN_ROUNDS):
            if obj.process_noise_nm <= _SHARPEN_ABOVE * self.ref:
                break
            nll = _nll(obj, z) if math.isnan(nll) else nll
            if self.hedged:
                # the noise model was chosen where the least squares started: chosen again where it ended
                obj2, z2, res2 = self.settle(z)
                nll2 = _nll(obj2, z2)
                if nll2 < nll and obj2.process_noise_nm < obj.process_noise_nm:
                    self.calls += obj.calls
                    obj, z, res, nll = obj2, z2, res2, nll2
                    continue
                self.calls += obj2.calls
            sharp = _armed(self.objective(_CONTINUATION[-1], share, robust=True), z)
            z2 = self.ls(sharp, z, _CONTINUATION_NFEV, _CONTINUATION_TOL)[0]
            self.calls += sharp.calls
            obj2, z2, res2 = self.settle(z2)
            nll2 = _nll(obj2, z2)
            if not nll2 < nll:
                self.calls += obj2.calls
                break
            self.calls += obj.calls
            obj, z, res, nll = obj2, z2, res2, nll2
        return obj, z, res

    def polished(self, obj: _KalmanObjective, z: NDArray[np.float64], res: Any) -> tuple[
            _KalmanObjective, NDArray[np.float64], Any, tuple[float, float] | None]:
        """ε polished (:func:`_polished`), and its 95 % likelihood-ratio interval [deg]."""
        z, res, interval = _polished(obj, z, res, self.top_deg, self.ls, self.max_nfev, self.pool)
        if self.hedged and obj.process_noise_nm > _SHARPEN_ABOVE * self.ref:
            # the polish moved ε into the gap's basin: the noise model chosen again there (22:079:
            # 12 % → 0.2 % of RMS τ_ref), and polished again if the record is more likely
            obj2, z2, res2 = self.settle(z)
            if _nll(obj2, z2) < _nll(obj, z):
                self.calls += obj.calls
                obj, z, res = obj2, z2, res2
                z, res, interval = _polished(obj, z, res, self.top_deg, self.ls, self.max_nfev, self.pool)
            else:
                self.calls += obj2.calls
        return obj, z, res, interval


def _hedge(objective: Callable[[float], _KalmanObjective], z: NDArray[np.float64], top_deg: float,
           ls: Callable[..., tuple[NDArray[np.float64], Any]], pool: ThreadPoolExecutor,
           hedge: Hedge) -> tuple[NDArray[np.float64], int]:
    """The hedged fit's start: ε moved to the best of its grid (:attr:`Hedge.NEAR`: ``_EPSILON_FACTORS`` × ε;
    :attr:`Hedge.GLOBAL`: ``_HEDGE_GRID_POINTS``, geometric from ``_HEDGE_GRID_FROM_DEG`` to ``top_deg``),
    then Gaussian least squares with the twist's random walk ``objective(noise_rad)`` taken down over
    ``_HEDGE_CONTINUATION`` × ε per sample. With the random walk the likelihood has a basin across ε where
    the plain one is flat away from a needle at the truth (22:008, 22:079). Returns the coordinates and the
    evaluations spent."""
    calls = 0
    for i, level in enumerate(_HEDGE_CONTINUATION):
        obj = _armed(objective(level * math.radians(z[6])), z)
        if i == 0:
            grid = (np.minimum(z[6] * np.array(_EPSILON_FACTORS), top_deg) if hedge is not Hedge.GLOBAL
                    else np.geomspace(_HEDGE_GRID_FROM_DEG, top_deg, _HEDGE_GRID_POINTS))

            def cost(eps_deg: float) -> float:
                return float(np.sum(obj(np.concatenate((z[:6], [eps_deg], z[7:])), remember=False) ** 2))

            z = np.concatenate((z[:6], [grid[int(np.argmin(list(pool.map(cost, grid))))]], z[7:]))
        z = ls(obj, z, _HEDGE_NFEV, _CONTINUATION_TOL)[0]
        calls += obj.calls
    return z, calls


def _kalman_result(obj: _KalmanObjective, z: NDArray[np.float64], res: Any, free: NDArray[np.bool_], calls: int,
                   start_selection: dict[str, Any], keep_all: bool, interval: tuple[float, float] | None) -> PemFit:
    """The Kalman fit's :class:`PemFit` at ``z``: its prediction errors, and the terms kept by their Wald
    statistic (every free one with ``keep_all``)."""
    inn = obj.innovations(z)
    n_eff = _n_effective(inn.normalized[:, 0]) if inn is not None else float(np.asarray(res.fun).size)
    cov = _held_covariance(res, free)
    selection = _term_selection(obj, z, res, cov, free, obj.kp.sample_rate_hz)
    if keep_all:
        selection = {t: {**v, "kept": bool(free[obj.names.index(_TERM_COORDINATE[t])])} for t, v in selection.items()}
    fit_ = _result(obj, z, res, n_eff, calls, free, cov, selection={**start_selection, **selection}, process_noise_nm=obj.process_noise_nm,
                   load_share=obj.load_share, innovations=inn, epsilon_profile_deg=interval)
    return replace(fit_, terms=ModelTerms(**{t: bool(selection.get(t, {}).get("kept", False))
                                             for t in _TERM_COORDINATE}))


#: A current-loop time constant below this share of the sample period is none (no record resolves it).
_LAG_NEGLIGIBLE = 0.1
#: Wald statistic below which a term is held at 0 after the continuation (within a standard error of it);
#: the final fit's terms are then kept by the BIC's threshold, ln n_eff.
_TERM_HOLD = 1.0


def _term_selection(obj: _KalmanObjective, z: NDArray[np.float64], res: Any, cov: NDArray[np.float64],
                    free: NDArray[np.bool_], sample_rate_hz: float,
                    threshold: float | None = None) -> dict[str, dict[str, Any]]:
    """Per candidate term of a least squares over the ``free`` coordinates (``cov`` its covariance): its
    Wald statistic z² = (value/σ)², the threshold (default ln n_eff, the BIC's price of a parameter) and
    whether it is kept (free, above it, and a current loop slower than ``_LAG_NEGLIGIBLE`` of a sample)."""
    r = np.asarray(res.fun)
    if threshold is None:
        threshold = math.log(max(_n_effective(r[::obj.kp.outputs]), 2.0))
    out: dict[str, dict[str, Any]] = {}
    for term, name in _TERM_COORDINATE.items():
        if name not in obj.names:
            continue
        i = obj.names.index(name)
        v, se = float(z[i]), math.sqrt(max(float(cov[i, i]), 0.0)) if math.isfinite(cov[i, i]) else math.inf
        z2 = (v / se) ** 2 if se > 0 else (math.inf if v > 0 else 0.0)
        seen = not (name == "T_c_us" and v < _LAG_NEGLIGIBLE * 1e6 / sample_rate_hz)
        out[term] = {"z2": float(z2), "threshold": threshold, "kept": bool(free[i] and z2 > threshold and seen)}
    return out
