"""Bayesian optimisation of a 1-D loss on a grid: a small interface over ``skopt.gp_minimize``.

Only :func:`minimize_on_grid` is public, so that the optimiser behind it could be swapped.

* The GP works on a ``Real`` grid *index* in [0, n − 1], rounded to the nearest grid point, with
  repeated points served from a cache: an ``Integer`` space silently replaces re-evaluated
  points by random ones (wasted evaluations). ``evaluations`` counts distinct loss calls.
* One BLAS thread (``threadpool_limits(1)``): the GP refit is several times faster so.
* Initial design: ``n_initial`` evenly spaced grid points, both ends included (deterministic; a
  monotonic profile has its minimum at an end).
* The GP models log(loss) (``log_loss``, losses > 0): error norms span decades and a sharp
  minimum is much smoother in log scale. Acquisition: expected improvement (the paper's
  eqs. 28–30), ``xi`` in the GP's units.
* Stopping (any of ``stop_when``): ``"ei"``, the largest EI over the unevaluated grid points is
  below ``ei_tol`` (log units: 1e-3 ≈ an expected 0.1 % improvement), from the
  ``min_iterations``-th GP-proposed point on; ``"repeat"``, ``repeat_limit`` already evaluated
  points proposed in a row; always, ``max_evaluations`` distinct evaluations.
* ``"local_min"``: after the GP stage, walk the grid downhill from the incumbent until both
  neighbours are evaluated and not better, so that the result is a local minimum on the grid.
* Interval: the connected run of grid points around the argmin whose loss could be within
  ``rel_tol`` of the minimum: evaluated points by their loss, the others by the GP's
  optimistic bound exp(μ − 2σ).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import norm

from commission.exceptions import IdentificationError

__all__ = ["GridMinimization", "minimize_on_grid"]

_TINY = 1e-300


@dataclass(frozen=True)
class GridMinimization:
    """Result of :func:`minimize_on_grid`."""

    x: float  # best grid value
    fun: float  # loss at x
    index: int  # index of x in the grid
    evaluations: int  # distinct loss evaluations
    history: list[tuple[float, float]] = field(default_factory=list)  # (x, loss), in order
    interval: tuple[float, float] = (math.nan, math.nan)  # grid values compatible with the minimum
    stopped_by: str = ""  # rule that ended the GP stage: "ei", "repeat", "max_evaluations", …
    optimizer_calls: int = 0  # calls the GP optimiser made, cached repeats included


def _expected_improvement(mu: NDArray[np.float64], sd: NDArray[np.float64], f_min: float, xi: float) -> NDArray[np.float64]:
    sd = np.maximum(sd, 1e-12)
    imp = f_min - mu - xi
    z = imp / sd
    return imp * norm.cdf(z) + sd * norm.pdf(z)


def minimize_on_grid(fun: Callable[[float], float], grid: ArrayLike, *, n_initial: int = 5,
                     max_evaluations: int = 40, seed: int = 0, stop_when: Sequence[str] = ("ei", "local_min"),
                     ei_tol: float = 1e-3, xi: float = 0.01, repeat_limit: int = 3, rel_tol: float = 0.05,
                     log_loss: bool = True, min_iterations: int = 2, acq_optimizer: str = "lbfgs",
                     n_points: int = 10000) -> GridMinimization:
    """Minimise ``fun`` over the values of ``grid`` (sorted, 1-D) with GP + EI.

    :param fun: loss, called with a grid value (Python float).
    :param grid: candidate values, shape (n,), n ≥ 2.
    :param n_initial: evenly spaced initial points (both ends included), ≥ 2.
    :param max_evaluations: cap on distinct evaluations (≤ n makes sense).
    :param seed: random state of the GP optimiser (results are reproducible).
    :param stop_when: subset of {"ei", "repeat", "local_min"} (module docstring).
    :param ei_tol: threshold of the "ei" rule, in the GP's units (log loss if ``log_loss``).
    :param xi: EI exploration margin, same units.
    :param min_iterations: GP-proposed calls before the "ei" rule may stop
        (a GP fitted on the initial design alone can be over-confident).
    :param rel_tol: relative tolerance defining ``interval``.
    :param log_loss: model log(loss) (requires loss > 0).
    :param acq_optimizer, n_points: passed to ``gp_minimize`` (the GP refit, not the
        acquisition's optimiser, dominates each call).
    :raises IdentificationError: bad arguments or a non-finite loss.
    """
    from skopt import gp_minimize
    from skopt.space import Real
    from threadpoolctl import threadpool_limits

    g = np.asarray(grid, dtype=float)
    n = g.size
    if g.ndim != 1 or n < 2 or not np.all(np.diff(g) > 0):
        raise IdentificationError("grid must be a sorted 1-D array of at least 2 values")
    unknown = set(stop_when) - {"ei", "repeat", "local_min"}
    if unknown:
        raise IdentificationError(f"unknown stop_when rules: {sorted(unknown)}")
    n_initial = int(min(max(n_initial, 2), n))
    max_evaluations = int(min(max(max_evaluations, n_initial), n))

    cache: dict[int, float] = {}
    history: list[tuple[float, float]] = []

    def evaluate(i: int) -> float:
        if i not in cache:
            v = float(fun(float(g[i])))
            if not math.isfinite(v) or (log_loss and v <= 0.0):
                if log_loss and v == 0.0:
                    v = _TINY
                else:
                    raise IdentificationError(f"loss at grid[{i}] = {g[i]!r} is {v!r}")
            cache[i] = v
            history.append((float(g[i]), v))
        return cache[i]

    def to_model(v: float) -> float:
        return math.log(max(v, _TINY)) if log_loss else v

    state = {"calls": 0, "repeats": 0, "stopped_by": "exhausted", "model": None}

    def objective(x: list[float]) -> float:
        i = int(np.clip(round(float(x[0])), 0, n - 1))
        state["calls"] += 1
        if i in cache:
            state["repeats"] += 1
        else:
            state["repeats"] = 0
        return to_model(evaluate(i))

    space = [Real(0.0, float(n - 1), name="index")]
    init_idx = np.unique(np.round(np.linspace(0, n - 1, n_initial)).astype(int))
    x0 = [[float(i)] for i in init_idx]
    grid_pts = np.arange(n, dtype=float).reshape(-1, 1)

    def callback(res) -> bool:
        if len(cache) >= max_evaluations:
            state["stopped_by"] = "max_evaluations"
            return True
        if "repeat" in stop_when and state["repeats"] >= repeat_limit:
            state["stopped_by"] = "repeat"
            return True
        if res.models:
            model = res.models[-1]
            state["model"] = (model, res.space)
            if "ei" in stop_when and len(res.x_iters) >= len(x0) + min_iterations:
                todo = np.array([i for i in range(n) if i not in cache])
                if todo.size == 0:
                    state["stopped_by"] = "exhausted"
                    return True
                mu, sd = model.predict(res.space.transform(grid_pts[todo].tolist()), return_std=True)
                f_min = min(to_model(v) for v in cache.values())
                if float(np.max(_expected_improvement(mu, sd, f_min, xi))) < ei_tol:
                    state["stopped_by"] = "ei"
                    return True
        if len(cache) >= n:
            state["stopped_by"] = "exhausted"
            return True
        return False

    budget = max(3 * max_evaluations, len(x0) + 5)
    with threadpool_limits(1), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp_minimize(objective, space, x0=x0, n_initial_points=0, n_calls=budget, acq_func="EI", xi=xi,
                    acq_optimizer=acq_optimizer, n_points=n_points, random_state=int(seed),
                    callback=[callback])
    if state["stopped_by"] == "exhausted" and len(cache) < n and state["calls"] >= budget:
        state["stopped_by"] = "budget"

    if "local_min" in stop_when:
        while True:
            ib = min(cache, key=cache.__getitem__)
            moved = False
            for j in (ib - 1, ib + 1):
                if 0 <= j < n and j not in cache and len(cache) < n:
                    evaluate(j)
                    if cache[j] < cache[ib]:
                        moved = True
                        break
            if not moved:
                break

    ib = min(cache, key=cache.__getitem__)
    fb = cache[ib]
    lower = _optimistic_bounds(state["model"], grid_pts, n, log_loss)

    def loss_at(i: int) -> tuple[float, float]:
        if i in cache:
            return cache[i], 1.0
        return (lower[i] if lower is not None else -math.inf), 0.0

    from commission.ident.backlash import epsilon_interval

    interval = epsilon_interval(g, loss_at, ib, fb, rel_tol)
    return GridMinimization(x=float(g[ib]), fun=float(fb), index=int(ib), evaluations=len(cache),
                            history=history, interval=interval, stopped_by=str(state["stopped_by"]),
                            optimizer_calls=int(state["calls"]))


def _optimistic_bounds(model_space, grid_pts: NDArray[np.float64], n: int, log_loss: bool) -> NDArray[np.float64] | None:
    """GP lower bound μ − 2σ on every grid point, in loss units; None without a model."""
    if model_space is None:
        return None
    model, space = model_space
    mu, sd = model.predict(space.transform(grid_pts.tolist()), return_std=True)
    lo = mu - 2.0 * sd
    return np.exp(lo) if log_loss else lo
