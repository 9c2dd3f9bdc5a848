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
from typing import Any

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
    run = _GridSearch(fun, g, log_loss, stop_when, int(min(max(max_evaluations, n_initial), n)), ei_tol, xi,
                      repeat_limit, min_iterations)
    space = [Real(0.0, float(n - 1), name="index")]
    run.x0 = [[float(i)] for i in np.unique(np.round(np.linspace(0, n - 1, n_initial)).astype(int))]
    budget = max(3 * run.max_evaluations, len(run.x0) + 5)
    with threadpool_limits(1), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp_minimize(run.objective, space, x0=run.x0, n_initial_points=0, n_calls=budget, acq_func="EI", xi=xi,
                    acq_optimizer=acq_optimizer, n_points=n_points, random_state=int(seed),
                    callback=[run.callback])
    if run.stopped_by == "exhausted" and len(run.cache) < n and run.calls >= budget:
        run.stopped_by = "budget"
    if "local_min" in stop_when:
        run.descend()

    cache = run.cache
    ib = min(cache, key=cache.__getitem__)
    fb = cache[ib]
    lower = _optimistic_bounds(run.model, run.grid_pts, n, log_loss)

    def loss_at(i: int) -> tuple[float, float]:
        if i in cache:
            return cache[i], 1.0
        return (lower[i] if lower is not None else -math.inf), 0.0

    from commission.ident.backlash import epsilon_interval

    interval = epsilon_interval(g, loss_at, ib, fb, rel_tol)
    return GridMinimization(x=float(g[ib]), fun=float(fb), index=int(ib), evaluations=len(cache),
                            history=run.history, interval=interval, stopped_by=run.stopped_by,
                            optimizer_calls=run.calls)


class _GridSearch:
    """One :func:`minimize_on_grid`: the losses met (``cache`` by grid index, ``history`` in call order),
    the objective and the stop rules ``gp_minimize`` calls back, and why it stopped."""

    def __init__(self, fun: Callable[[float], float], g: NDArray[np.float64], log_loss: bool,
                 stop_when: Sequence[str], max_evaluations: int, ei_tol: float, xi: float, repeat_limit: int,
                 min_iterations: int) -> None:
        self.fun, self.g, self.n, self.log_loss = fun, g, g.size, log_loss
        self.stop_when, self.max_evaluations, self.ei_tol, self.xi = stop_when, max_evaluations, ei_tol, xi
        self.repeat_limit, self.min_iterations = repeat_limit, min_iterations
        self.cache: dict[int, float] = {}
        self.history: list[tuple[float, float]] = []
        self.calls = self.repeats = 0
        self.stopped_by = "exhausted"
        self.model: Any = None
        self.x0: list[list[float]] = []
        self.grid_pts = np.arange(self.n, dtype=float).reshape(-1, 1)

    def evaluate(self, i: int) -> float:
        if i not in self.cache:
            v = float(self.fun(float(self.g[i])))
            if not math.isfinite(v) or (self.log_loss and v <= 0.0):
                if self.log_loss and v == 0.0:
                    v = _TINY
                else:
                    raise IdentificationError(f"loss at grid[{i}] = {self.g[i]!r} is {v!r}")
            self.cache[i] = v
            self.history.append((float(self.g[i]), v))
        return self.cache[i]

    def to_model(self, v: float) -> float:
        return math.log(max(v, _TINY)) if self.log_loss else v

    def objective(self, x: list[float]) -> float:
        i = int(np.clip(round(float(x[0])), 0, self.n - 1))
        self.calls += 1
        self.repeats = self.repeats + 1 if i in self.cache else 0
        return self.to_model(self.evaluate(i))

    def callback(self, res: Any) -> bool:
        """True (stop) by the rules of ``stop_when`` (module docstring), the budget, or a grid used up."""
        cache = self.cache
        if len(cache) >= self.max_evaluations:
            self.stopped_by = "max_evaluations"
            return True
        if "repeat" in self.stop_when and self.repeats >= self.repeat_limit:
            self.stopped_by = "repeat"
            return True
        if res.models:
            model = res.models[-1]
            self.model = (model, res.space)
            if "ei" in self.stop_when and len(res.x_iters) >= len(self.x0) + self.min_iterations:
                todo = np.array([i for i in range(self.n) if i not in cache])
                if todo.size == 0:
                    self.stopped_by = "exhausted"
                    return True
                mu, sd = model.predict(res.space.transform(self.grid_pts[todo].tolist()), return_std=True)
                f_min = min(self.to_model(v) for v in cache.values())
                if float(np.max(_expected_improvement(mu, sd, f_min, self.xi))) < self.ei_tol:
                    self.stopped_by = "ei"
                    return True
        if len(cache) >= self.n:
            self.stopped_by = "exhausted"
            return True
        return False

    def descend(self) -> None:
        """The "local_min" rule: the best's unevaluated neighbours evaluated until it is a local minimum."""
        cache, n = self.cache, self.n
        while True:
            ib = min(cache, key=cache.__getitem__)
            moved = False
            for j in (ib - 1, ib + 1):
                if 0 <= j < n and j not in cache and len(cache) < n:
                    self.evaluate(j)
                    if cache[j] < cache[ib]:
                        moved = True
                        break
            if not moved:
                break


def _optimistic_bounds(model_space, grid_pts: NDArray[np.float64], n: int, log_loss: bool) -> NDArray[np.float64] | None:
    """GP lower bound μ − 2σ on every grid point, in loss units; None without a model."""
    if model_space is None:
        return None
    model, space = model_space
    mu, sd = model.predict(space.transform(grid_pts.tolist()), return_std=True)
    lo = mu - 2.0 * sd
    return np.exp(lo) if log_loss else lo
