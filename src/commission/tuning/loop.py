"""The velocity and position loops of given settings on a given plant, exactly as the drive runs them.

One loop model for everything that reports on a loop: the design's search, the margins in
controller.json, the open-loop Bode plot of the report and the verification's margins all
come from here. The loop is discrete at the drive's clock Ts: the plant is the ZOH
discretisation of V_m/T·(1/s) (with the current-loop lag and the computation delay)
followed by the drive's backward-difference velocity (1 − z⁻¹)/Ts, and the PI, the torque
low-pass and the notches are the very difference equations the drive (and
:mod:`.closedloop`) runs.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.linalg
import scipy.signal
from numpy.typing import NDArray

from ..ident.twomass import TwoMassParameters
from .settings import ControllerSettings, LoopMargins, Notch

__all__ = ["LoopTransfer", "loop_margins", "loop_transfer", "margins_of", "notch_coefficients", "open_loop",
           "velocity_closed_loop"]


# discrete-time loop pieces: (num, den) in descending powers of z
Poly = NDArray[np.float64]


def _plant_z(num_s: Poly, den_s: Poly, Ts: float, current_loop_hz: float | None,
             delay_samples: float) -> tuple[Poly, Poly]:
    """Torque samples → velocity samples: (1 − z⁻¹)/Ts·(the ZOH of lag(s)·P(s)/s with its input
    delayed by ``delay_samples`` (≥ 0, fractional allowed) beyond the hold's own sample).

    The design, the verification and the report discretise the same few plants: each is
    computed once (scipy's matrix exponential costs milliseconds when BLAS threads wake up).
    """
    num, den = _plant_z_cached(tuple(np.asarray(num_s, dtype=float).tolist()),
                               tuple(np.asarray(den_s, dtype=float).tolist()), Ts, current_loop_hz,
                               float(delay_samples))
    return num.copy(), den.copy()


def _zoh_integrals(A: NDArray[np.float64], B: NDArray[np.float64], t: float
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(e^{A·t}, ∫₀ᵗ e^{A·σ} dσ·B), from one matrix exponential."""
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A * t
    M[:n, n] = B[:, 0] * t
    E = scipy.linalg.expm(M)
    return E[:n, :n], E[:n, n:]


@functools.lru_cache(maxsize=512)
def _plant_z_cached(num_s: tuple[float, ...], den_s: tuple[float, ...], Ts: float, current_loop_hz: float | None,
                    delay_samples: float) -> tuple[Poly, Poly]:
    num = np.asarray(num_s, dtype=float)
    den = np.polymul(np.asarray(den_s, dtype=float), [1.0, 0.0])
    if current_loop_hz is not None:
        wc = 2.0 * math.pi * current_loop_hz
        num = num * wc
        den = np.polymul(den, [1.0, wc])
    # the delay: m whole samples, then a fraction f of one (the input switches at f·Ts into
    # the sample): x[k+1] = Φ·x[k] + Γ0·u[k] + Γ1·u[k−1] (the modified z-transform)
    m = int(math.floor(delay_samples + 1e-12))
    f = max(0.0, delay_samples - m)
    A, B, C, _ = scipy.signal.tf2ss(num, den)
    Phi, G = _zoh_integrals(A, B, Ts)
    if f < 1e-12:
        g0, g1 = G, G
    else:
        E1, g0 = _zoh_integrals(A, B, (1.0 - f) * Ts)
        _, G2 = _zoh_integrals(A, B, f * Ts)
        g1 = E1 @ G2
    n0, dz = scipy.signal.ss2tf(Phi, g0, C, np.zeros((1, 1)))
    if f < 1e-12:
        nd, dd = np.trim_zeros(n0[0], "f"), np.asarray(dz, dtype=float)
    else:
        # C(zI − Φ)⁻¹(Γ0·z + Γ1)·z⁻¹: numerator n0·z + n1 over det·z
        n1, _ = scipy.signal.ss2tf(Phi, g1, C, np.zeros((1, 1)))
        nd = np.trim_zeros(np.polyadd(np.polymul(n0[0], [1.0, 0.0]), n1[0]), "f")
        dd = np.polymul(dz, [1.0, 0.0])
    # (z − 1)/(Ts·z) and z^{-m}
    nd = np.convolve(nd, [1.0 / Ts, -1.0 / Ts])
    dd = np.convolve(dd, np.r_[1.0, np.zeros(1 + m)])
    # cancel the common (z − 1): the plant has no integrator, ZOH{P/s} has its pole at z = 1
    q_n, r_n = _over_z_minus_1(nd)
    q_d, r_d = _over_z_minus_1(dd)
    if abs(r_n) < 1e-9 * max(np.max(np.abs(nd)), 1e-300) and abs(r_d) < 1e-9 * max(np.max(np.abs(dd)), 1e-300):
        nd, dd = q_n, q_d
    return nd, dd


def _over_z_minus_1(a: Poly) -> tuple[Poly, float]:
    """(quotient, remainder) of a(z)/(z − 1), descending powers (synthetic division)."""
    q = np.cumsum(a)
    return q[:-1], float(q[-1])


def _polymul(a: Poly, b: Poly) -> Poly:
    """np.polymul without its poly1d round trip (the same numbers when neither has a leading zero)."""
    if a.size and b.size and a[0] != 0.0 and b[0] != 0.0:
        return np.convolve(a, b)
    return np.polymul(a, b)


def _pi_z(kp: float, Ti: float, Ts: float) -> tuple[Poly, Poly]:
    """u = k_p·e + k_i·T_s·Σe (the sum including e[k]): ((k_p + k_i T_s) z − k_p)/(z − 1)."""
    ki = kp / Ti
    return np.array([kp + ki * Ts, -kp]), np.array([1.0, -1.0])


def _lowpass_alpha(tf_s: float, Ts: float) -> float:
    return 1.0 if tf_s <= 0.0 else 1.0 - math.exp(-Ts / tf_s)


def _lowpass_z(tf_s: float, Ts: float) -> tuple[Poly, Poly]:
    """y += α(x − y): α z/(z − (1 − α))."""
    a = _lowpass_alpha(tf_s, Ts)
    return np.array([a, 0.0]), np.array([1.0, -(1.0 - a)])


def notch_coefficients(n: Notch, Ts: float) -> tuple[Poly, Poly]:
    """Tustin discretisation, prewarped at the centre: (b0, b1, b2), (1, a1, a2)."""
    w = 2.0 * math.pi * n.frequency_hz
    zeta = 1.0 / (2.0 * n.q)
    c = w / math.tan(w * Ts / 2.0)  # prewarped bilinear constant
    # H(s) = (s² + 2dζω s + ω²)/(s² + 2ζω s + ω²), s = c (z − 1)/(z + 1)
    def _quad(two_z_w: float) -> Poly:
        return np.array([c * c + two_z_w * c + w * w, 2.0 * (w * w - c * c), c * c - two_z_w * c + w * w])
    b = _quad(2.0 * n.depth * zeta * w)
    a = _quad(2.0 * zeta * w)
    return b / a[0], a / a[0]


def _controller_z(kp: float, Ti: float, tf_s: float, notches: tuple[Notch, ...], Ts: float) -> tuple[Poly, Poly]:
    num, den = _pi_z(kp, Ti, Ts)
    n2, d2 = _lowpass_z(tf_s, Ts)
    num, den = _polymul(num, n2), _polymul(den, d2)
    for n in notches:
        b, a = notch_coefficients(n, Ts)
        num, den = _polymul(num, b), _polymul(den, a)
    return num, den


def _freq_grid(fs: float, f_low: float = 0.05, points: int = 6000) -> NDArray[np.float64]:
    """Angular frequencies [rad/s] from f_low to just below Nyquist."""
    return 2.0 * math.pi * np.geomspace(f_low, 0.4999 * fs, points)


#: Points of the search's grid: its crossings are interpolated to well under 0.1° and 0.1 dB
#: (0.6 % between points), and the reported margins are located exactly anyway.
SEARCH_POINTS = 2000


def _eval(num: Poly, den: Poly, w: NDArray[np.float64], Ts: float) -> NDArray[np.complex128]:
    z = np.exp(1j * w * Ts)
    return np.polyval(num, z) / np.polyval(den, z)


def _grid_crossings(L: NDArray[np.complex128], w: NDArray[np.float64]) -> tuple[float, float, float, float]:
    """(PM [deg], GM [dB], highest gain crossover [rad/s], phase crossover of the GM [rad/s]) of a dense
    frequency response, crossings interpolated linearly (inf / nan where there is none)."""
    mag = np.abs(L)
    lm = np.log(mag)
    idx = np.flatnonzero(np.sign(lm[:-1]) != np.sign(lm[1:]))
    pms = []
    wgc = []
    for i in idx:
        t = lm[i] / (lm[i] - lm[i + 1])
        wc = w[i] + t * (w[i + 1] - w[i])
        Lc = L[i] + t * (L[i + 1] - L[i])
        pms.append(abs(math.degrees(np.angle(-Lc))))
        wgc.append(wc)
    im = L.imag
    jdx = np.flatnonzero((np.sign(im[:-1]) != np.sign(im[1:])))
    gms = []
    wpc = []
    for i in jdx:
        t = im[i] / (im[i] - im[i + 1])
        Lp = L[i] + t * (L[i + 1] - L[i])
        if Lp.real < 0 and abs(Lp.real) < 1.0:
            gms.append(-20.0 * math.log10(abs(Lp.real)))
            wpc.append(w[i] + t * (w[i + 1] - w[i]))
    pm = min(pms) if pms else math.inf
    if gms:
        j = int(np.argmin(gms))
        gm, wp = gms[j], wpc[j]
    else:
        gm, wp = math.inf, math.nan
    return float(pm), float(gm), float(max(wgc)) if wgc else math.nan, float(wp)


def _grid_margins(L: NDArray[np.complex128], w: NDArray[np.float64], num: Poly, den: Poly) -> LoopMargins:
    """Margins from a dense frequency response (crossings interpolated linearly)."""
    pm, gm, wc, wp = _grid_crossings(L, w)
    return LoopMargins(phase_margin_deg=pm, gain_margin_db=gm, crossover_hz=wc / (2 * math.pi),
                       phase_crossover_hz=wp / (2 * math.pi), stability_margin=float(np.min(np.abs(L + 1.0))),
                       stable=_stable(num, den))


def _grid_meets(L: NDArray[np.complex128], w: NDArray[np.float64], num: Poly, den: Poly, pm_req: float,
                gm_req: float) -> bool:
    """``_grid_margins(...).meets(pm_req, gm_req)``, the closed-loop poles only computed when needed."""
    pm, gm, _, _ = _grid_crossings(L, w)
    return pm >= pm_req and gm >= gm_req and _stable(num, den)


def _stable(num: Poly, den: Poly) -> bool:
    char = np.polyadd(den, num)
    roots = np.roots(char)
    return bool(np.all(np.abs(roots) < 1.0 - 1e-9))


def _bandwidth_hz(L: NDArray[np.complex128], w: NDArray[np.float64]) -> float:
    """−3 dB bandwidth of T = L/(1 + L) [Hz]: the lowest frequency from which |T| stays below
    −3 dB for an octave. A lightly damped anti-resonance inside the loop (a zero pair of the
    plant) notches |T| below −3 dB over a few percent of frequency; that dip is not where the loop
    stops following (measured: 100 Hz, ζ 0.05 plant, notch at 71 Hz read as the bandwidth of a
    loop whose gain crosses 0 dB at 716 Hz)."""
    T = np.abs(L / (1.0 + L))
    low = T < 1.0 / math.sqrt(2.0)
    # the grid is geometric: an octave is a fixed number of points
    octave = max(1, int(round(math.log(2.0) / math.log(w[1] / w[0])))) if w.size > 1 else 1
    for i in np.flatnonzero(low):
        if low[i:i + octave + 1].all() or i + octave >= w.size:
            return float(w[i] / (2 * math.pi))
    return float(w[-1] / (2 * math.pi))


# analysis of given settings on a given plant
@dataclass(frozen=True)
class LoopTransfer:
    """A discrete-time open loop L(z) = num(z)/den(z) (descending powers of z) at the drive's clock."""

    num: Poly
    den: Poly
    sample_time_s: float

    def response(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """L(e^{j2πf·Ts}) at f_hz [Hz]."""
        return _eval(self.num, self.den, 2.0 * math.pi * np.asarray(f_hz, dtype=float), self.sample_time_s)


def loop_transfer(settings: ControllerSettings, plant: TwoMassParameters, *, gap: bool = False,
                  notches: bool = True, loop: Literal["velocity", "position"] = "velocity") -> LoopTransfer:
    """The open loop of ``settings`` around ``plant``, exactly as the drive runs it.

    Velocity loop: the controller (PI, torque low-pass, notches) times the plant (ZOH, current
    loop, the loop delay (computation + encoder, fractional samples allowed), backward-difference
    velocity); ``gap=True``: the motor alone (gears
    apart). Position loop (around the closed velocity loop, contact): the drive's velocity is the
    backward difference of the position it measures, so x̂_m = Ts·z/(z − 1)·v̂_m and
    L_pos = K_p·Ts·z/(z − 1)·T_v(z), T_v = L_v/(1 + L_v).
    """
    Ts = 1.0 / settings.sample_rate_hz
    p = plant
    if gap and loop == "velocity":
        pnum, pden = np.array([1.0 / p.J_m]), np.array([1.0, p.B_m / p.J_m])
    else:
        pnum, pden = p.velocity_tf()
    pn, pd = _plant_z(pnum, pden, Ts, settings.current_loop_bandwidth_hz, settings.loop_delay_samples)
    cn, cd = _controller_z(settings.velocity_gain, settings.velocity_integral_time_s,
                           settings.torque_filter_time_constant_s, settings.notches if notches else (), Ts)
    num, den = _polymul(cn, pn), _polymul(cd, pd)
    if loop == "position":
        closed = np.polyadd(den, num)
        num = settings.position_gain_per_s * Ts * np.polymul([1.0, 0.0], num)
        # the position loop's slower clock: its samples of the reference and of x̂_m arrive late
        den = np.polymul(np.polymul([1.0, -1.0], closed), np.r_[1.0, np.zeros(settings.position_loop_delay_samples)])
    return LoopTransfer(num, den, Ts)


def open_loop(settings: ControllerSettings, plant: TwoMassParameters, f_hz: NDArray[np.float64], *,
              gap: bool = False, notches: bool = True,
              loop: Literal["velocity", "position"] = "velocity") -> NDArray[np.complex128]:
    """Open-loop response L(e^{j2πf·Ts}) at f_hz [Hz] of the loop :func:`loop_margins` analyses
    (same arguments): what a Bode plot of the settings' margins must show."""
    return loop_transfer(settings, plant, gap=gap, notches=notches, loop=loop).response(f_hz)


def _refine(g: Any, a: float, b: float) -> float:
    """The root of g in [a, b] (a sign change of g), to 1e-12 relative."""
    from scipy.optimize import brentq

    ga, gb = g(a), g(b)
    if ga == 0.0:
        return a
    if gb == 0.0 or ga * gb > 0.0:
        return b
    return float(brentq(g, a, b, xtol=1e-12 * b))


def margins_of(lt: LoopTransfer) -> LoopMargins:
    """Margins of the open loop ``lt``: every gain and phase crossover is found on a dense grid
    (the design's) and then located exactly on L(e^{jωTs}); the phase margin is the smallest
    over all gain crossovers, the gain margin the smallest over the phase crossovers with
    |L| < 1; stability from the closed-loop poles (roots of den + num)."""
    Ts = lt.sample_time_s
    w = _freq_grid(1.0 / Ts)
    L = _eval(lt.num, lt.den, w, Ts)

    def at(x: float) -> complex:
        z = complex(math.cos(x * Ts), math.sin(x * Ts))
        return complex(np.polyval(lt.num, z) / np.polyval(lt.den, z))

    lm = np.log(np.abs(L))
    pms, wgc = [], []
    for i in np.flatnonzero(np.sign(lm[:-1]) != np.sign(lm[1:])):
        wc = _refine(lambda x: math.log(abs(at(x))), float(w[i]), float(w[i + 1]))
        pms.append(abs(math.degrees(np.angle(-at(wc)))))
        wgc.append(wc)
    gms, wpc = [], []
    im = L.imag
    for i in np.flatnonzero(np.sign(im[:-1]) != np.sign(im[1:])):
        wp = _refine(lambda x: at(x).imag, float(w[i]), float(w[i + 1]))
        re = at(wp).real
        if re < 0.0 and abs(re) < 1.0:
            gms.append(-20.0 * math.log10(abs(re)))
            wpc.append(wp)
    if gms:
        j = int(np.argmin(gms))
        gm, fpc = gms[j], wpc[j] / (2 * math.pi)
    else:
        gm, fpc = math.inf, math.nan
    return LoopMargins(phase_margin_deg=float(min(pms)) if pms else math.inf, gain_margin_db=float(gm),
                       crossover_hz=float(max(wgc) / (2 * math.pi)) if wgc else math.nan,
                       phase_crossover_hz=float(fpc), stability_margin=float(np.min(np.abs(L + 1.0))),
                       stable=_stable(lt.num, lt.den))


def loop_margins(settings: ControllerSettings, plant: TwoMassParameters, *, gap: bool = False,
                 notches: bool = True, loop: Literal["velocity", "position"] = "velocity") -> LoopMargins:
    """Margins of the velocity loop (or, ``loop="position"``, of the position loop around the
    closed velocity loop) of ``settings`` around ``plant``: :func:`margins_of` the
    :func:`loop_transfer` (``gap=True``: the motor alone, gears apart)."""
    return margins_of(loop_transfer(settings, plant, gap=gap, notches=notches, loop=loop))


def velocity_closed_loop(settings: ControllerSettings, plant: TwoMassParameters, f_hz: NDArray[np.float64], *,
                         notches: bool = True, output: Literal["motor", "load"] = "motor") -> NDArray[np.complex128]:
    """Closed-loop response v/v* at f_hz (contact, linear): motor velocity, or load velocity
    (motor closed loop × the shaft's load/motor velocity ratio (D s + K)/(J_l s² + (D + B_l) s + K))."""
    lt = loop_transfer(settings, plant, notches=notches)
    L = lt.response(f_hz)
    out = L / (1.0 + L)
    if output == "load":
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        p = plant
        out = out * (p.D * s + p.K) / (p.J_l * s * s + (p.D + p.B_l) * s + p.K)
    return out
