"""Bayesian optimisation on the ε grid: same argmin as the exhaustive grid, fewer evaluations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from commission.exceptions import IdentificationError
from commission.ident.backlash import search_epsilon_bayes, search_epsilon_grid
from commission.ident.bayesopt import minimize_on_grid


def _deg(e: float) -> float:
    return math.degrees(e)


# Synthetic loss profiles over ε [rad] (shapes seen on real ε profiles, METHOD.md)
PROFILES = {
    # the paper loss with true linear parameters: 0.55 at 0.01°, sharp minimum at 0.40°
    "sharp": lambda e: 0.017 + 1.3 * abs(_deg(e) - 0.40),
    "paper-like": lambda e: 0.017
    + 0.533 * min(1.0, abs(_deg(e) - 0.40) / 0.39) ** 0.7
    + 0.3 * max(0.0, _deg(e) - 0.40),
    # with biased linear parameters: the loss rises monotonically, answer 0.01°
    "monotonic up": lambda e: 0.2 + _deg(e),
    "monotonic down": lambda e: 2.0 - _deg(e) ** 2,
    "flat bowl": lambda e: 1.0 + 0.02 * (_deg(e) - 0.63) ** 2,
    "ripple": lambda e: 0.5 + 0.3 * math.sin(9 * _deg(e)) ** 2 + 0.5 * (_deg(e) - 0.7) ** 2,
}


@pytest.mark.parametrize("name", list(PROFILES))
def test_bayes_finds_the_grid_argmin_with_fewer_evaluations(name):
    f = PROFILES[name]
    grid = search_epsilon_grid(f)
    calls: list[float] = []

    def counted(e: float) -> float:
        calls.append(e)
        return f(e)

    bo = search_epsilon_bayes(counted, seed=0)
    assert bo.method == "bayes"
    assert bo.epsilon_rad == pytest.approx(grid.epsilon_rad, abs=1e-12), name
    assert bo.loss == pytest.approx(grid.loss, rel=1e-12)
    # every distinct evaluation is one loss call (repeats are cached)
    assert bo.evaluations == len(calls) == len(set(calls)) == len(bo.history)
    # measured: 6–20 evaluations (flat bowl 20) against 100
    assert bo.evaluations <= 25, (name, bo.evaluations)
    assert bo.evaluations < grid.evaluations
    lo, hi = bo.interval_rad
    assert lo <= bo.epsilon_rad <= hi


def test_reproducible_with_a_seed():
    f = PROFILES["ripple"]
    a = search_epsilon_bayes(f, seed=3)
    b = search_epsilon_bayes(f, seed=3)
    assert a.history == b.history


def test_interval_is_wide_for_a_flat_loss_and_tight_for_a_sharp_one():
    flat = search_epsilon_bayes(PROFILES["flat bowl"])
    sharp = search_epsilon_bayes(PROFILES["sharp"])
    assert _deg(flat.interval_rad[1] - flat.interval_rad[0]) > 0.5
    assert _deg(sharp.interval_rad[1] - sharp.interval_rad[0]) < 0.015


def test_max_evaluations_is_a_hard_cap():
    grid = np.linspace(0.0, 1.0, 100)
    # no stopping rule but the cap
    res = minimize_on_grid(lambda x: 1.0 + math.sin(40 * x) ** 2 + x, grid, max_evaluations=8,
                           stop_when=())
    assert res.evaluations == 8
    assert res.stopped_by == "max_evaluations"


def test_bad_arguments_raise():
    with pytest.raises(IdentificationError):
        minimize_on_grid(lambda x: 1.0, [1.0])
    with pytest.raises(IdentificationError):
        minimize_on_grid(lambda x: 1.0, [0.0, 1.0, 2.0], stop_when=("never",))
    with pytest.raises(IdentificationError):
        minimize_on_grid(lambda x: float("nan"), np.linspace(0, 1, 10))
