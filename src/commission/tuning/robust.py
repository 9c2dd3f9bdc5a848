"""Margins over an uncertainty set: the preset's PM/GM must hold on every member, not only on
the design model.

A member is the design model with the current-loop bandwidth scaled (×0.5–2 by default), the
loop delay lengthened (+0 or +1 sample), J_l and K scaled (±20 %), and the gears in contact
or — when ε > 0 for any ε factor — apart (the motor alone). ε's size does not enter a linear
margin; it enters the closed-loop runs of :mod:`.verify`. Every member is evaluated on the
frequency grid of :mod:`.loop` (no simulation): the search of :mod:`.design` asks
:class:`MemberResponses` whether a candidate gain meets the margins on a few members, the
reported worst case (:func:`robust_margins`) locates the crossings of the worst members
exactly (:func:`.loop.margins_of`) and checks every member's closed-loop poles.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from ..ident.twomass import TwoMassParameters
from .loop import (
    SEARCH_POINTS,
    LoopTransfer,
    Poly,
    _controller_z,
    _eval,
    _freq_grid,
    _grid_crossings,
    _plant_z,
    _polymul,
    _stable,
    margins_of,
)
from .settings import (
    ControllerSettings,
    LoopMargins,
    RobustMargins,
    TuningOptions,
    UncertaintyMember,
    UncertaintySet,
)

__all__ = ["MemberResponses", "member_loop", "member_plant", "member_settings", "members", "robust_margins"]

#: Members whose crossings are located exactly for the reported worst case (the lowest on the grid).
_EXACT_WORST = 3


def members(uncertainty: UncertaintySet, backlash: bool, ideal_current_loop: bool) -> list[UncertaintyMember]:
    """Every member of the set: contact members over all factors, then (with backlash) the gap
    members over the drive's factors (the motor alone has no J_l or K)."""
    cl = (1.0,) if ideal_current_loop else tuple(dict.fromkeys(uncertainty.current_loop_factors))
    delays = tuple(dict.fromkeys(uncertainty.extra_delay_samples))
    out = [UncertaintyMember(c, d, j, k, False) for c, d, j, k in itertools.product(
        cl, delays, dict.fromkeys(uncertainty.load_inertia_factors), dict.fromkeys(uncertainty.stiffness_factors))]
    if backlash and any(f > 0.0 for f in uncertainty.backlash_factors):
        out += [UncertaintyMember(c, d, 1.0, 1.0, True) for c, d in itertools.product(cl, delays)]
    return out


def member_plant(p: TwoMassParameters, m: UncertaintyMember) -> TwoMassParameters:
    """The two-mass model of member ``m`` (J_l and K scaled; the damping coefficients kept)."""
    if m.load_inertia_factor == 1.0 and m.stiffness_factor == 1.0:
        return p
    return replace(p, J_l=p.J_l * m.load_inertia_factor, K=p.K * m.stiffness_factor)


def member_settings(settings: ControllerSettings, m: UncertaintyMember) -> ControllerSettings:
    """``settings`` as the loop model sees them on member ``m`` (its current loop and delay)."""
    cl = settings.current_loop_bandwidth_hz
    return replace(settings, current_loop_bandwidth_hz=None if cl is None else cl * m.current_loop_factor,
                   loop_delay_samples=settings.loop_delay_samples + m.extra_delay_samples)


def _member_plant_z(p: TwoMassParameters, m: UncertaintyMember, current_loop_hz: float | None,
                    delay_samples: float, Ts: float) -> tuple[Poly, Poly]:
    """The member's discrete plant (torque samples → velocity samples): a whole-sample extra
    delay multiplies the nominal delay's plant by z⁻¹ (one discretisation serves both)."""
    if m.gap:
        num, den = np.array([1.0 / p.J_m]), np.array([1.0, p.B_m / p.J_m])
    else:
        num, den = member_plant(p, m).velocity_tf()
    cl = None if current_loop_hz is None else current_loop_hz * m.current_loop_factor
    extra = m.extra_delay_samples
    if extra == int(extra):
        pn, pd = _plant_z(num, den, Ts, cl, delay_samples)
        return pn, np.polymul(pd, np.r_[1.0, np.zeros(int(extra))])
    return _plant_z(num, den, Ts, cl, delay_samples + extra)


def member_loop(settings: ControllerSettings, p: TwoMassParameters, m: UncertaintyMember) -> LoopTransfer:
    """The velocity loop of ``settings`` on member ``m`` (the loop of :func:`.loop.loop_transfer`)."""
    Ts = 1.0 / settings.sample_rate_hz
    pn, pd = _member_plant_z(p, m, settings.current_loop_bandwidth_hz, settings.loop_delay_samples, Ts)
    cn, cd = _controller_z(settings.velocity_gain, settings.velocity_integral_time_s,
                           settings.torque_filter_time_constant_s, settings.notches, Ts)
    return LoopTransfer(_polymul(cn, pn), _polymul(cd, pd), Ts)


def _worst_first(ms: list[UncertaintyMember]) -> list[UncertaintyMember]:
    """Members most likely to break a margin first (slow current loop, long delay), so that the
    search rejects a gain after one or two of them."""
    return sorted(ms, key=lambda m: (m.current_loop_factor, -m.extra_delay_samples, m.gap,
                                     abs(m.load_inertia_factor - 1.0) + abs(m.stiffness_factor - 1.0) == 0.0))


@dataclass
class _Response:
    member: UncertaintyMember
    num: Poly
    den: Poly
    P: NDArray[np.complex128]


class MemberResponses:
    """The members' plants, discretised once and evaluated on the design's frequency grid."""

    def __init__(self, p: TwoMassParameters, ms: list[UncertaintyMember], current_loop_hz: float | None,
                 delay_samples: float, Ts: float, w: NDArray[np.float64]) -> None:
        self.Ts, self.w = Ts, w
        self.items: list[_Response] = []
        for m in _worst_first(ms):
            pn, pd = _member_plant_z(p, m, current_loop_hz, delay_samples, Ts)
            self.items.append(_Response(m, pn, pd, _eval(pn, pd, w, Ts)))

    def first_failure(self, C: NDArray[np.complex128], cn: Poly, cd: Poly, pm: float, gm: float,
                      which: list[int] | None = None) -> int | None:
        """Index of the first member (of ``which``, default all) on which the controller
        (``C`` on the grid, ``cn/cd``) misses PM ≥ pm or GM ≥ gm or is unstable; None: none.
        The margins of all are read before any closed-loop poles are computed (those cost more)."""
        idx = list(range(len(self.items))) if which is None else which
        for i in idx:
            pm_i, gm_i, _, _ = _grid_crossings(C * self.items[i].P, self.w)
            if pm_i < pm or gm_i < gm:
                return i
        for i in idx:
            r = self.items[i]
            if not _stable(_polymul(cn, r.num), _polymul(cd, r.den)):
                return i
        return None

    def failures(self, C: NDArray[np.complex128], cn: Poly, cd: Poly, pm: float, gm: float) -> list[int]:
        """Every member that misses the margins (the worst phase margin first)."""
        bad: list[tuple[float, int]] = []
        for i, r in enumerate(self.items):
            pm_i, gm_i, _, _ = _grid_crossings(C * r.P, self.w)
            if pm_i < pm or gm_i < gm or not _stable(_polymul(cn, r.num), _polymul(cd, r.den)):
                bad.append((min(pm_i - pm, 5.0 * (gm_i - gm)), i))
        return [i for _, i in sorted(bad)]


def robust_margins(settings: ControllerSettings, p: TwoMassParameters, options: TuningOptions,
                   backlash: bool, responses: MemberResponses | None = None) -> RobustMargins:
    """The worst phase and gain margins of ``settings`` over the uncertainty set of ``options``
    around ``p`` and the settings' own drive model, with the members that set them.

    Every member's margins are read on the frequency grid and its closed-loop poles checked;
    the few lowest are then located exactly on the loop (:func:`.loop.margins_of`).
    ``responses``: the same members already discretised (the design's), to save the work."""
    with threadpool_limits(1):  # small matrices: BLAS threads only cost
        return _robust_margins(settings, p, options, backlash, responses)


def _robust_margins(settings: ControllerSettings, p: TwoMassParameters, options: TuningOptions,
                    backlash: bool, responses: MemberResponses | None) -> RobustMargins:
    pm_req, gm_req = settings.required_phase_margin_deg, settings.required_gain_margin_db
    ms = members(options.uncertainty, backlash, settings.current_loop_bandwidth_hz is None)
    Ts = 1.0 / settings.sample_rate_hz
    cn, cd = _controller_z(settings.velocity_gain, settings.velocity_integral_time_s,
                           settings.torque_filter_time_constant_s, settings.notches, Ts)
    if responses is None or responses.Ts != Ts or {r.member for r in responses.items} != set(ms):
        responses = MemberResponses(p, ms, settings.current_loop_bandwidth_hz, settings.loop_delay_samples, Ts,
                                    _freq_grid(settings.sample_rate_hz, points=SEARCH_POINTS))
    C = _eval(cn, cd, responses.w, Ts)
    grid: list[tuple[UncertaintyMember, float, float, bool]] = []
    for r in responses.items:
        pm_i, gm_i, _, _ = _grid_crossings(C * r.P, responses.w)
        grid.append((r.member, pm_i, gm_i, _stable(_polymul(cn, r.num), _polymul(cd, r.den))))
    exact: dict[UncertaintyMember, LoopMargins] = {}
    for key in (1, 2):
        for m, *_ in sorted(grid, key=lambda g: g[key])[:_EXACT_WORST]:
            if m not in exact:
                exact[m] = margins_of(member_loop(settings, p, m))
    pms = [(exact[m].phase_margin_deg if m in exact else pm_i, m) for m, pm_i, _, _ in grid]
    gms = [(exact[m].gain_margin_db if m in exact else gm_i, m) for m, _, gm_i, _ in grid]
    pm_w, pm_m = min(pms, key=lambda x: x[0])
    gm_w, gm_m = min(gms, key=lambda x: x[0])
    unstable = tuple(m for m, _, _, st in grid if not st)
    return RobustMargins(phase_margin_deg=float(pm_w), phase_member=pm_m, gain_margin_db=float(gm_w),
                         gain_member=gm_m, stable=not unstable, unstable=unstable, members=len(ms),
                         required_phase_margin_deg=pm_req, required_gain_margin_db=gm_req,
                         uncertainty=options.uncertainty, current_loop_hz=settings.current_loop_bandwidth_hz)
