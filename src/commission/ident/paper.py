"""The paper's own procedure (steps 4–6 on top of an FRD fit), as a reproducible mode.

Reading of the paper (Fig. 5) implemented here:

* **Step 4**: the paper's eqs. 21–24 feed a shaft torque into the *whole* plant P̂, which is
  inconsistent with it; instead P̂ is mapped to physical parameters
  (:func:`commission.ident.twomass.from_velocity_tf`) and the two-mass model with the dead zone
  between the masses is simulated (:func:`commission.ident.backlash.simulate_deadzone`), driven
  by the measured T_ref with the fit's delay (``delay_samples = round(delay_s·fs)``). Loss: eq.
  31, L(ε) = max_t |v_m − v̂_m|, searched on the paper's grid [0.01°, 1°] step 0.01° by
  Bayesian optimisation (or exhaustively).
* **No backlash**: the range cannot say "none", so L(0) is evaluated too; if
  L(0) ≤ (1 + rel_tol)·L(ε*) the pass reports ε = 0 and ``backlash_detected = False``.
* **Step 5**: the FRD of the simulated output against the measured one, both by the same
  estimator from the same torque so that their common biases (leakage, delay) cancel:
  ``frd_error`` = sqrt(mean_k |Ĝ_sim − G_meas|² / |G_meas|²) over ``frd_band_hz`` (each decade
  counts alike). Done when ``frd_error ≤ frd_tol``.
* **Step 6**: remove the backlash's effect and refit (step 3). ``correction="output"``
  (default): v_lin = v_m − (v̂_m(ε*) − v̂_m(0)), exact in the model if P̂ and ε* are right.
  ``"input"``: the paper's eqs. 25–26, T̂_input = T_ref + n̂ with n̂ the internal backlash
  torque (:func:`commission.ident.backlash.nonlinear_torque`), approximate because n̂ also acts
  on the load. ``"input_filtered"``: T̂_input = T_ref + F(s)·n̂, F = (J_l s² + B_l s)/(J_l s² +
  (B_l + D) s + K) = 1 − G_ml/G_mm, which accounts for that reaction.
  Passes repeat while ``frd_error`` decreases, at most ``max_iterations``; the result is the
  pass with the smallest ``frd_error``.

The procedure is only as good as the linear fit it starts from (METHOD.md): with a biased fit
the loss grows monotonically with ε and the search returns 0.01°.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from commission.exceptions import IdentificationError
from commission.ident.backlash import (
    EPSILON_BOUNDS_RAD,
    EPSILON_RESOLUTION_RAD,
    EpsilonSearch,
    max_output_error,
    nonlinear_torque,
    search_epsilon_bayes,
    search_epsilon_grid,
    simulate_deadzone,
    simulate_motor_velocity,
)
from commission.ident.twomass import TwoMassParameters

__all__ = ["PaperIteration", "PaperIdentification", "frd_error", "paper_identify"]


class _FRDLike(Protocol):
    frequency_hz: NDArray[np.float64]
    response: NDArray[np.complex128]


class _FitLike(Protocol):
    num: NDArray[np.float64]
    den: NDArray[np.float64]
    delay_s: float


LinearFit = tuple[ArrayLike, ArrayLike, float] | TwoMassParameters | _FitLike


@dataclass(frozen=True)
class PaperIteration:
    """One pass of steps 4–5 (and the refit of step 6 that produced ``params``)."""

    index: int  # 0 = the linear fit given to paper_identify
    params: TwoMassParameters  # linear two-mass parameters of this pass
    delay_s: float  # delay of the linear fit [s] (simulated as round(delay_s·fs) samples)
    epsilon_rad: float  # ε of step 4 [rad] (0 if L(0) is as good, see backlash_detected)
    backlash_detected: bool  # False if ε = 0 explains the data as well as the grid's best ε
    loss: float  # paper loss (eq. 31) at epsilon_rad [rad/s]
    frd_error: float  # step-5 FRD mismatch (module docstring) [-]
    search: EpsilonSearch  # the ε search of this pass

    @property
    def epsilon_deg(self) -> float:
        return math.degrees(self.epsilon_rad)


@dataclass(frozen=True)
class PaperIdentification:
    """Result of :func:`paper_identify`; the chosen pass is the one with the least ``frd_error``."""

    params: TwoMassParameters
    epsilon_rad: float
    delay_s: float
    frd_error: float
    backlash_detected: bool
    iterations: tuple[PaperIteration, ...]
    #: "frd_tol" (close enough), "frd_error increased", "max_iterations", "no backlash detected"
    #: (step 6 has nothing to remove) or "refit failed: …" (step 6 gave no physical plant).
    stop_reason: str
    #: Wall time [s] of "search" (step 4), "frd" (steps 2/5/6), "fit" (step 3 refits), "simulate"
    #: (steps 5/6) and "total".
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def epsilon_deg(self) -> float:
        return math.degrees(self.epsilon_rad)


def frd_error(reference: _FRDLike, other: _FRDLike, band_hz: tuple[float, float] = (1.0, 400.0)) -> float:
    """sqrt(mean_k |G_other − G_ref|² / |G_ref|²) over the common bins inside ``band_hz``.

    :raises IdentificationError: the FRDs are on different bins, or no bin in the band.
    """
    f = np.asarray(reference.frequency_hz, dtype=float)
    if f.shape != np.shape(other.frequency_hz) or not np.allclose(f, other.frequency_hz):
        raise IdentificationError("the two FRDs are not on the same frequency bins")
    m = (f >= band_hz[0]) & (f <= band_hz[1])
    if not np.any(m):
        raise IdentificationError(f"no FRD bin inside {band_hz} Hz")
    g0 = np.asarray(reference.response)[m]
    g1 = np.asarray(other.response)[m]
    return float(np.sqrt(np.mean(np.abs(g1 - g0) ** 2 / np.abs(g0) ** 2)))


def _linear_parameters(linear_fit: Any, sample_rate_hz: float,
                       to_params: Callable[[Any, Any], TwoMassParameters]) -> tuple[TwoMassParameters, float]:
    if isinstance(linear_fit, TwoMassParameters):
        return linear_fit, 1.0 / sample_rate_hz
    if isinstance(linear_fit, tuple):
        num, den, delay = linear_fit
    else:
        num, den, delay = linear_fit.num, linear_fit.den, linear_fit.delay_s
    return to_params(np.asarray(num, float), np.asarray(den, float)), float(delay)


def _load_reaction_filter(params: TwoMassParameters, n: NDArray[np.float64], fs: float) -> NDArray[np.float64]:
    """F(s)·n, F = (J_l s² + B_l s)/(J_l s² + (B_l + D)s + K): the part of the internal
    torque pair (+n on the motor, −n on the load) seen at the motor velocity,
    as an equivalent motor torque."""
    from scipy.signal import lsim

    t = np.arange(n.size) / fs
    num = [params.J_l, params.B_l, 0.0]
    den = [params.J_l, params.B_l + params.D, params.K]
    _, y, _ = lsim((num, den), n, t)
    return np.asarray(y, dtype=float)


def paper_identify(
    torque_ref: ArrayLike, motor_velocity: ArrayLike, sample_rate_hz: float, linear_fit: LinearFit, *,
    search: Literal["bayes", "grid"] = "bayes", bounds_rad: tuple[float, float] = EPSILON_BOUNDS_RAD,
    resolution_rad: float = EPSILON_RESOLUTION_RAD,
    correction: Literal["output", "input", "input_filtered"] = "output", max_iterations: int = 5,
    frd_tol: float = 0.01, frd_band_hz: tuple[float, float] = (1.0, 400.0), rel_tol: float = 0.05,
    seed: int = 0, bayes_kwargs: dict[str, Any] | None = None, fixed_epsilon_rad: float | None = None,
    estimate_frd: Callable[..., Any] | None = None, fit_transfer_function: Callable[..., Any] | None = None,
    from_velocity_tf: Callable[[Any, Any], TwoMassParameters] | None = None,
) -> PaperIdentification:
    """The paper's steps 4–6 given a linear fit (step 3), iterated (module docstring).

    :param torque_ref: torque reference [N·m], shape (N,).
    :param motor_velocity: measured motor velocity [rad/s], shape (N,), drive convention.
    :param sample_rate_hz: [Hz].
    :param linear_fit: ``(num, den, delay_s)`` of V_m/T_ref, an object with ``num``/``den``/``delay_s``
        (a ``TransferFunctionFit``), or ``TwoMassParameters`` (delay: one sample).
    :param search: "bayes" (paper) or "grid" (exhaustive).
    :param correction: step-6 reading, "output", "input" or "input_filtered" (module docstring).
    :param max_iterations: passes of steps 4–5 at most (≥ 1); step 6 runs between passes.
    :param frd_tol: step-5 "close enough" threshold on ``frd_error``.
    :param fixed_epsilon_rad: skip step 4 and use this ε in every pass (to study
        step 6 on its own, e.g. with the true ε).
    :param estimate_frd, fit_transfer_function, from_velocity_tf: steps 2, 3 and the
        coefficient → parameter map; default: the package's own.
    :raises IdentificationError: bad inputs, or the initial fit is not a physical plant.
    """
    t_total = time.perf_counter()
    estimate_frd, fit_transfer_function, from_velocity_tf = _steps(estimate_frd, fit_transfer_function,
                                                                   from_velocity_tf)
    tau = np.asarray(torque_ref, dtype=float)
    v_m = np.asarray(motor_velocity, dtype=float)
    if tau.shape != v_m.shape or tau.ndim != 1:
        raise IdentificationError(f"torque_ref {tau.shape} and motor_velocity {v_m.shape} differ")
    fs = float(sample_rate_hz)
    if max_iterations < 1:
        raise IdentificationError("max_iterations must be >= 1")
    timings = {"search": 0.0, "frd": 0.0, "fit": 0.0, "simulate": 0.0}
    params, delay_s = _linear_parameters(linear_fit, fs, from_velocity_tf)
    with _timed(timings, "frd"):
        frd_meas = estimate_frd(tau, v_m, fs)

    iterations: list[PaperIteration] = []
    stop_reason = "max_iterations"
    for it in range(max_iterations):
        d = max(0, int(round(delay_s * fs)))

        def loss(eps: float, _p: TwoMassParameters = params, _d: int = d) -> float:
            return max_output_error(v_m, simulate_motor_velocity(_p, eps, tau, fs, delay_samples=_d))

        with _timed(timings, "search"):  # step 4
            res = _epsilon_search(loss, fixed_epsilon_rad, search, bounds_rad, resolution_rad, rel_tol, seed,
                                  bayes_kwargs)
            loss0 = loss(0.0)
        detected = fixed_epsilon_rad is not None or not (loss0 <= (1.0 + rel_tol) * res.loss)
        eps = res.epsilon_rad if detected else 0.0
        err, sim, sim0 = _compare(params, eps, tau, fs, d, frd_meas, estimate_frd, frd_band_hz, timings)  # step 5
        iterations.append(PaperIteration(
            index=it, params=params, delay_s=delay_s, epsilon_rad=eps, backlash_detected=detected,
            loss=res.loss if detected else loss0, frd_error=err, search=res,
        ))
        if (stop := _stop_reason(iterations, frd_tol, it == max_iterations - 1)) is not None:
            stop_reason = stop
            break
        with _timed(timings, "frd"):  # step 6: remove the backlash's effect, refit
            frd_new = _corrected_frd(estimate_frd, correction, tau, v_m, fs, params, eps, d, sim, sim0)
        with _timed(timings, "fit"):
            try:
                fit = fit_transfer_function(frd_new)
                params = from_velocity_tf(np.asarray(fit.num, float), np.asarray(fit.den, float))
                delay_s = float(fit.delay_s)
            except IdentificationError as err_fit:
                stop_reason = f"refit failed: {err_fit}"
                break

    best = min(iterations, key=lambda r: r.frd_error)
    timings["total"] = time.perf_counter() - t_total
    return PaperIdentification(params=best.params, epsilon_rad=best.epsilon_rad, delay_s=best.delay_s,
                               frd_error=best.frd_error, backlash_detected=best.backlash_detected,
                               iterations=tuple(iterations), stop_reason=stop_reason, timings_s=timings)


def _compare(params: TwoMassParameters, eps: float, tau: NDArray[np.float64], fs: float, d: int, frd_meas: Any,
             estimate_frd: Callable[..., Any], frd_band_hz: tuple[float, float],
             timings: dict[str, float]) -> tuple[float, Any, Any]:
    """Step 5: the model's FRD error against the measured one, and its simulations with ε and without it
    (step 6 reads both)."""
    with _timed(timings, "simulate"):
        sim = simulate_deadzone(params, eps, tau, fs, delay_samples=d)
        sim0 = simulate_deadzone(params, 0.0, tau, fs, delay_samples=d) if eps > 0 else sim
    with _timed(timings, "frd"):
        err = frd_error(frd_meas, estimate_frd(tau, sim.motor_velocity, fs), frd_band_hz)
    return err, sim, sim0


def _steps(estimate_frd: Callable[..., Any] | None, fit_transfer_function: Callable[..., Any] | None,
           from_velocity_tf: Callable[[Any, Any], TwoMassParameters] | None) -> tuple[
               Callable[..., Any], Callable[..., Any], Callable[[Any, Any], TwoMassParameters]]:
    """Steps 2, 3 and the coefficient → parameter map: the package's own where not given."""
    if estimate_frd is None:
        from commission.ident.frd import estimate_frd as _est

        # the method never reads the quality indicator: skip it (most of an FRD's time)
        estimate_frd = functools.partial(_est, quality=False)
    if fit_transfer_function is None:
        from commission.ident.tffit import fit_transfer_function
    if from_velocity_tf is None:
        from commission.ident.twomass import from_velocity_tf
    return estimate_frd, fit_transfer_function, from_velocity_tf


def _corrected_frd(estimate_frd: Callable[..., Any], correction: str, tau: NDArray[np.float64],
                   v_m: NDArray[np.float64], fs: float, params: TwoMassParameters, eps: float, d: int,
                   sim: Any, sim0: Any) -> Any:
    """Step 6: the FRD with the backlash's effect removed, by ``correction`` (module docstring); ``sim``,
    ``sim0`` the dead-zone simulations at ε and at 0, ``d`` the delay [samples]."""
    if correction == "output":
        return estimate_frd(tau, v_m - (sim.motor_velocity - sim0.motor_velocity), fs)
    if correction not in ("input", "input_filtered"):
        raise IdentificationError(f"unknown correction {correction!r}")
    n_hat = nonlinear_torque(params, eps, sim.twist, sim.motor_velocity_instant - sim.load_velocity_instant)
    # the torque acting over [k, k+1) is tau[k − d + 1]: align n̂ with it
    shift = d - 1
    n_al = np.zeros_like(n_hat)
    if shift >= 0:
        n_al[: n_hat.size - shift] = n_hat[shift:]
    else:
        n_al[1:] = n_hat[:-1]
    if correction == "input_filtered":
        n_al = _load_reaction_filter(params, n_al, fs)
    return estimate_frd(tau + n_al, v_m, fs)


def _stop_reason(iterations: list[PaperIteration], frd_tol: float, last: bool) -> str | None:
    """Why the passes stop after the latest of ``iterations`` (``last``: no pass is left), or None."""
    r = iterations[-1]
    if r.frd_error <= frd_tol:
        return "frd_tol"
    if len(iterations) > 1 and r.frd_error >= iterations[-2].frd_error:
        return "frd_error increased"
    if last:
        return "max_iterations"
    if not r.backlash_detected or r.epsilon_rad == 0.0:
        return "no backlash detected"
    return None


@contextmanager
def _timed(timings: dict[str, float], key: str) -> Iterator[None]:
    """Adds the block's wall time [s] to ``timings[key]``."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[key] += time.perf_counter() - t0


def _epsilon_search(loss: Callable[[float], float], fixed_epsilon_rad: float | None, search: str,
                    bounds_rad: tuple[float, float], resolution_rad: float, rel_tol: float, seed: int,
                    bayes_kwargs: dict[str, Any] | None) -> EpsilonSearch:
    """Step 4: ε of the smallest ``loss`` by ``search`` ("bayes" or "grid"), or ``fixed_epsilon_rad``."""
    if fixed_epsilon_rad is not None:
        fe = float(fixed_epsilon_rad)
        return EpsilonSearch(epsilon_rad=fe, loss=loss(fe), evaluations=1, history=[], interval_rad=(fe, fe),
                             method="grid")
    if search == "bayes":
        return search_epsilon_bayes(loss, bounds_rad, resolution_rad,
                                    **{"seed": seed, "rel_tol": rel_tol, **(bayes_kwargs or {})})
    return search_epsilon_grid(loss, bounds_rad, resolution_rad, rel_tol=rel_tol)
