"""Fit a continuous-time rational model V_m/T_ref = B(s)/A(s) to one record's DFTs (step 3).

Model (Pintelon & Schoukens), at each bin k of the band, s_k = j·2π·f_k, Ts = 1/fs::

    Y(k) = H(s_k)·B(s_k)/A(s_k)·U(k) + F(s_k)·I(s_k)/A(s_k)

* ``B/A``: the continuous plant, deg B = num_order, A monic of degree den_order.
* ``H(s) = exp(−s·delay_s)·sinc²(ω·Ts/2)``: the sampling operator. A zero-order-hold torque
  and a backward-difference velocity give exactly ``exp(−s·Ts)·sinc²(ωTs/2)`` times the
  continuous response, up to aliasing of relative size (f/fs)³. A 2/3 model absorbs neither
  the delay nor the sinc², and either one left out biases J_m, J_l and D. A drive's current
  loop adds about its time constant to the delay; ``fit_delay`` fits that excess.
* ``I/A``: the transient (leakage) term. The record is not periodic (the motor starts at rest
  and ends moving), so Y carries a term that U does not; I is a real polynomial of degree
  den_order and F(s) = exp(+s·Ts/2)/sinc(ωTs/2) maps the continuous transient onto the
  sampled one. Without it the plain ratio Y/U is biased by a few percent.

Continuous rather than discrete: a discrete model fits as well, but converting it back to the
six continuous coefficients is badly conditioned at fs/f_max = 20.

Algorithm: Sanathanan–Koerner iterations (linear least squares in the coefficients of A, B, I
for the equation error A·Y − H·B·U − F·I, divided by |A_prev|), iterated to convergence
(Levy's first iteration alone is far off), then a Gauss–Newton polish of the true output
error Y − Ŷ, whose minimum differs from SK's fixed point when the data are not exactly of the
model (backlash). The frequency axis is scaled by the band's top frequency.

Weighting of the output error per bin: ``"balanced"`` (default) 1/√(|Y|·median|Y|), the
geometric mean of ``"uniform"`` (maximum likelihood for white encoder noise, dominated by the
large low-frequency bins) and ``"relative"`` 1/|Y| (every decade counts alike): with backlash
it had the smallest worst-case error, relative weighting chasing the distorted resonance and
uniform weighting the DC bins (bench/bench_linear.py).

Physical constraint (2/3 models, ``physical=True``): when the free optimum maps to no physical
two-mass plant (typical with backlash, where the B_m/B_l split is ill-conditioned), the fit is
redone in the physical parameters (J_m, J_l, K > 0; B_m, B_l, D ≥ 1e-6·(B_m + B_l)) with the
transient by variable projection, so that :func:`commission.ident.twomass.from_velocity_tf`
always succeeds on the result.

What to trust: B_m + B_l (the DC gain), J_m (the high-frequency gain) and the modal
frequencies; the split of the friction between B_m, B_l and D is ill-conditioned. With
backlash the fit is the best linear approximation of a nonlinear plant: a start for the
time-domain estimator (:mod:`commission.ident.estimator`), not the answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from threadpoolctl import threadpool_limits

from commission.exceptions import IdentificationError
from commission.ident.frd import FRD
from commission.ident.twomass import TwoMassParameters, from_velocity_tf

Weighting = Literal["balanced", "relative", "uniform"]

#: Lower bound of B_m, B_l and D in the physical refit, relative to B_m + B_l.
_DAMPING_FLOOR = 1e-6


@dataclass(frozen=True)
class TransferFunctionFit:
    """A continuous rational model of V_m/T_ref fitted to FRD, plus the modelled delay."""

    num: NDArray[np.float64]  # descending powers of s (continuous V_m/T_ref, without the delay)
    den: NDArray[np.float64]  # descending powers of s, den[0] == 1
    delay_s: float  # pure delay modelled [s] (one sample, 1/fs, by default)
    #: Relative RMS error of the modelled output DFT over the band, sqrt(mean_k |Y − Ŷ|² / |Y|²),
    #: Ŷ = H·B/A·U + F·I/A (plant and transient).
    fit_error: float
    iterations: int  # Sanathanan–Koerner iterations done (the polish not counted)
    converged: bool  # the SK iterations met tol within max_iterations
    sample_rate_hz: float = 0.0  # of the data [Hz]; > 0 adds the hold's sinc² in response()
    constrained: bool = False  # the free optimum was not physical and the physical refit was used

    def response(self, f_hz: ArrayLike) -> NDArray[np.complex128]:
        """Modelled sampled response at ``f_hz`` [rad/s per N·m], *including* the delay (and the
        sinc²(f/fs) of zero-order hold + backward difference when the fit modelled the sampling)."""
        f = np.asarray(f_hz, dtype=float)
        s = 2j * np.pi * f
        h = np.exp(-s * self.delay_s)
        if self.sample_rate_hz > 0.0:
            h = h * np.sinc(f / self.sample_rate_hz) ** 2
        return h * np.polyval(self.num, s) / np.polyval(self.den, s)

    def plant_response(self, f_hz: ArrayLike) -> NDArray[np.complex128]:
        """Continuous plant num/den at ``f_hz``, without the delay and the hold."""
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        return np.polyval(self.num, s) / np.polyval(self.den, s)


def fit_transfer_function(frd: FRD, *, num_order: int = 2, den_order: int = 3, delay_s: float | None = None,
                          transient: bool = True, max_iterations: int = 100, tol: float = 1e-9,
                          weighting: Weighting = "balanced", polish: bool = True, physical: bool = True,
                          fit_delay: bool = False) -> TransferFunctionFit:
    """Fit B(s)/A(s) (order num_order/den_order) to ``frd``'s raw DFTs (see the module docstring).

    :param delay_s: pure delay to model [s]. ``None`` = one sample (1/fs), the drive convention,
        with the hold's sinc²; an explicit value models that delay and the sinc²; 0.0 neither.
    :param transient: model the transient term I/A (``False`` with ``delay_s=0.0``: the naive
        fit of the plain ratio Y/U).
    :param max_iterations, tol: SK stops after ``max_iterations`` or when the relative change of
        the coefficient vector falls below ``tol``.
    :param weighting: "balanced" (default), "relative" or "uniform".
    :param polish: Gauss–Newton on the true output error after SK.
    :param physical: for 2/3 models, refit in physical parameters when the free optimum is not
        a physical two-mass plant.
    :param fit_delay: also fit an extra delay δ ≥ 0 beyond ``delay_s`` in the polish (a current
        loop acts on the FRD like a delay of about its time constant), kept when it removes enough
        of the output error (``_DELAY_GAIN``); ``delay_s`` of the result then includes it.
    :raises IdentificationError: bad orders or delay, too few bins, an output DFT that is zero,
        or a singular/non-finite least-squares problem.
    """
    # small dense problems: one BLAS thread is several times faster than many on a loaded machine
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit(frd, num_order, den_order, delay_s, transient, max_iterations, tol,
                    weighting, polish, physical, fit_delay)


def _fit(frd: FRD, num_order: int, den_order: int, delay_s: float | None, transient: bool,
         max_iterations: int, tol: float, weighting: Weighting, polish: bool,
         physical: bool, fit_delay: bool = False) -> TransferFunctionFit:
    b = _basis(frd, num_order, den_order, delay_s, transient, weighting)
    theta, it, converged = _sanathanan_koerner(b, max_iterations, tol)
    if polish:
        try:
            th_p, _, ssq = _polished(b, theta, False)
            if ssq <= float(np.sum(b.resid(theta) ** 2)):
                theta = th_p
        except (ValueError, np.linalg.LinAlgError):
            pass  # keep the SK result
    if fit_delay:
        try:
            th_d, extra, ssq = _polished(b, theta, True)
        except (ValueError, np.linalg.LinAlgError):
            extra, ssq = 0.0, math.inf
        # kept only when it explains much of the error (see _DELAY_GAIN); H then carries it
        # (the physical refit below and fit_error use the new H through model())
        if extra > 0.0 and ssq <= _DELAY_GAIN ** 2 * float(np.sum(b.resid(theta) ** 2)):
            theta, b = th_d, replace(b, td=b.td + extra, H=b.H * np.exp(-b.s * extra))

    num, den = _unscale(theta, b.na, num_order, b.w_scale)
    constrained = False
    if physical and (num_order, den_order) == (2, 3):
        try:
            from_velocity_tf(num, den)
        except IdentificationError:
            phys = _physical_fit(theta, b)
            if phys is None:
                raise IdentificationError(
                    "the 2/3 fit is not a physical two-mass plant and no physical refit "
                    "could be started from it (no anti-resonance below a resonance)"
                ) from None
            theta, constrained = phys, True
            num, den = _unscale(theta, b.na, num_order, b.w_scale)

    fit_error = float(np.sqrt(np.mean(np.abs(b.Y - b.model(theta)[1]) ** 2 / np.abs(b.Y) ** 2)))
    return TransferFunctionFit(
        num=num, den=den, delay_s=b.td, fit_error=fit_error, iterations=it,
        converged=converged, sample_rate_hz=b.fs if b.hold else 0.0, constrained=constrained,
    )


@dataclass(frozen=True, eq=False)
class _Basis:
    """One fit's data and regressors over the band's M bins: the scaled Laplace variable x = s/ω_s, the
    DFTs U, Y, the sampling operator H, the transient's map F, the weights w, and the powers of x
    (columns x^n … x^0) of A (``Xa``), B (``Xb``) and I (``Xi``, none without the transient). θ is
    [a_{na−1}..a_0, b_{nb−1}..b_0, i…] in x, A monic in x."""

    fs: float
    td: float  # delay modelled [s]
    hold: bool  # the hold's sinc² modelled
    s: NDArray[np.complex128]  # j·2π·f [rad/s], shape (M,)
    w_scale: float  # ω_s [rad/s]
    U: NDArray[np.complex128]
    Y: NDArray[np.complex128]
    H: NDArray[np.complex128]
    F: NDArray[np.complex128]
    w: NDArray[np.float64]
    Xa: NDArray[np.complex128]  # (M, na + 1)
    Xb: NDArray[np.complex128]  # (M, nb)
    Xi: NDArray[np.complex128]  # (M, den_order + 1) or (M, 0)

    @property
    def na(self) -> int:
        return self.Xa.shape[1] - 1

    @property
    def nb(self) -> int:
        return self.Xb.shape[1]

    def model(self, th: NDArray[np.float64]) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """(A(x), Ŷ = (H·B·U + F·I)/A) at θ."""
        na, nb = self.na, self.nb
        Ax = self.Xa[:, 0] + self.Xa[:, 1:] @ th[:na]
        return Ax, (self.H * (self.Xb @ th[na:na + nb]) * self.U + self.F * (self.Xi @ th[na + nb:])) / Ax

    def resid(self, th: NDArray[np.float64]) -> NDArray[np.float64]:
        """The weighted output error (Y − Ŷ)·w, real parts then imaginary."""
        e = (self.Y - self.model(th)[1]) * self.w
        return np.concatenate([e.real, e.imag])


def _basis(frd: FRD, num_order: int, den_order: int, delay_s: float | None, transient: bool,
           weighting: Weighting) -> _Basis:
    """The fit's :class:`_Basis`, its arguments checked."""
    if num_order < 0 or den_order < 1 or num_order > den_order:
        raise IdentificationError(
            f"orders num {num_order} / den {den_order} are not a proper model "
            "(need 0 ≤ num ≤ den, den ≥ 1)"
        )
    if weighting not in ("balanced", "relative", "uniform"):
        raise IdentificationError(f"unknown weighting {weighting!r}")
    fs = float(frd.sample_rate_hz)
    Ts = 1.0 / fs
    td = Ts if delay_s is None else float(delay_s)
    if not (np.isfinite(td) and td >= 0.0):
        raise IdentificationError(f"delay {delay_s!r} s is not a non-negative number")
    hold = td > 0.0 or delay_s is None
    f = np.asarray(frd.frequency_hz, dtype=float)
    U = np.asarray(frd.input_dft, dtype=complex)
    Y = np.asarray(frd.output_dft, dtype=complex)
    M = f.size
    n_i = den_order if transient else -1
    n_unknown = den_order + num_order + 1 + (n_i + 1)
    if M < n_unknown:
        raise IdentificationError(f"{M} frequency bins are too few for {n_unknown} unknown coefficients")
    absY = np.abs(Y)
    if np.any(absY == 0.0) or not (np.all(np.isfinite(Y)) and np.all(np.isfinite(U))):
        raise IdentificationError("the output DFT is zero or not finite at some bin: cannot fit")

    s = 2j * np.pi * f
    w_scale = 2.0 * np.pi * float(f.max())
    x = s / w_scale

    def powers(n: int) -> NDArray[np.complex128]:
        return x[:, None] ** np.arange(n, -1, -1)[None, :]

    ymed = float(np.median(absY))
    w = {
        "balanced": 1.0 / np.sqrt(absY * ymed),
        "relative": 1.0 / absY,
        "uniform": np.full(M, 1.0 / ymed),
    }[weighting]
    return _Basis(
        fs=fs, td=td, hold=hold, s=s, w_scale=w_scale, U=U, Y=Y,
        H=np.exp(-s * td) * (np.sinc(f / fs) ** 2 if hold else 1.0),
        F=np.exp(s * Ts / 2.0) / np.sinc(f / fs) if hold else np.ones(M, complex), w=w,
        Xa=powers(den_order), Xb=powers(num_order), Xi=powers(n_i) if transient else np.zeros((M, 0), complex))


def _sanathanan_koerner(b: _Basis, max_iterations: int, tol: float) -> tuple[NDArray[np.float64], int, bool]:
    """θ of the iterations on the equation error A·Y − H·B·U − F·I (= cols·θ − rhs) divided by |A_prev|,
    the iterations done, and whether the relative change of θ fell below ``tol``."""
    Xa, na = b.Xa, b.na
    cols = np.concatenate([Xa[:, 1:] * b.Y[:, None], -(b.H * b.U)[:, None] * b.Xb, -b.F[:, None] * b.Xi], axis=1)
    rhs = -Xa[:, 0] * b.Y
    A_prev = np.ones(b.Y.size, complex)
    theta = np.zeros(cols.shape[1])
    it = 0
    for it in range(1, max_iterations + 1):
        rw = b.w / np.abs(A_prev)
        Mr = np.concatenate([(cols * rw[:, None]).real, (cols * rw[:, None]).imag])
        rr = np.concatenate([(rhs * rw).real, (rhs * rw).imag])
        cn = np.linalg.norm(Mr, axis=0)
        if np.any(cn == 0.0) or not np.all(np.isfinite(Mr)):
            raise IdentificationError("the least-squares problem is singular (a column is zero or not finite)")
        new = np.linalg.lstsq(Mr / cn, rr, rcond=None)[0] / cn
        if not np.all(np.isfinite(new)):
            raise IdentificationError("Sanathanan–Koerner iteration produced non-finite coefficients")
        change = np.linalg.norm(new - theta) / max(np.linalg.norm(new), 1e-300)
        theta = new
        A_prev = Xa[:, 0] + Xa[:, 1:] @ theta[:na]
        if it > 1 and change < tol:
            return theta, it, True
    return theta, it, False


def _polished(b: _Basis, th0: NDArray[np.float64], delay: bool) -> tuple[NDArray[np.float64], float, float]:
    """Gauss–Newton on the output error from th0; with ``delay`` also an extra delay δ [s]
    (H·e^(−sδ)). Returns (θ, δ, sum of squared weighted errors)."""
    na, nb, n_th, Ts = b.na, b.nb, th0.size, 1.0 / b.fs
    Xa, Xb, Xi, s, w = b.Xa, b.Xb, b.Xi, b.s, b.w
    sc = np.maximum(np.abs(th0), 1e-300)

    def parts(z: NDArray[np.float64]):  # type: ignore[no-untyped-def]
        th = z[:n_th] * sc
        Ax = Xa[:, 0] + Xa[:, 1:] @ th[:na]
        Hd = b.H * np.exp(-s * (z[n_th] * Ts)) if delay else b.H
        HBU = Hd * (Xb @ th[na:na + nb]) * b.U
        return Ax, Hd, HBU, (HBU + b.F * (Xi @ th[na + nb:])) / Ax

    def fun(z: NDArray[np.float64]) -> NDArray[np.float64]:
        e = (b.Y - parts(z)[3]) * w
        return np.concatenate([e.real, e.imag])

    def jac(z: NDArray[np.float64]) -> NDArray[np.float64]:
        Ax, Hd, HBU, Yh = parts(z)
        cols = [(Yh / Ax)[:, None] * Xa[:, 1:], -(Hd * b.U / Ax)[:, None] * Xb, -(b.F / Ax)[:, None] * Xi]
        if delay:  # ∂e/∂δ = +s·H·e^(−sδ)·B·U/A (δ in samples)
            cols.append((s * Ts * HBU / Ax)[:, None])
        J = np.concatenate(cols, axis=1) * w[:, None]
        J[:, :n_th] *= sc
        return np.concatenate([J.real, J.imag])

    z0 = np.concatenate([np.ones(n_th), [0.0] if delay else []])
    res = least_squares(fun, z0, jac=jac, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=200)
    if not np.all(np.isfinite(res.x)):
        raise ValueError("the polish diverged")
    return res.x[:n_th] * sc, (float(res.x[n_th]) * Ts if delay else 0.0), 2.0 * float(res.cost)


def _unscale(theta: NDArray[np.float64], na: int, num_order: int,
             w_scale: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Coefficients in x = s/ω_s → in s, den monic: coefficient of s^j gets ω_s^(na−j)."""
    den_x = np.concatenate([[1.0], theta[:na]])
    num_x = theta[na:na + num_order + 1]
    den = den_x / w_scale ** np.arange(na, -1, -1) * w_scale ** na
    num = num_x / w_scale ** np.arange(num_order, -1, -1) * w_scale ** na
    return num, den


def _scaled_coefficients(p: TwoMassParameters, w_scale: float) -> NDArray[np.float64]:
    """(a2, a1, a0, b2, b1, b0) of the plant in x = s/ω_s (the inverse of :func:`_unscale`)."""
    num, den = p.velocity_tf()
    return np.concatenate([den[1:] / w_scale ** np.arange(1, 4), num / w_scale ** np.arange(1, 4)])


def _start_parameters(theta: NDArray[np.float64], w_scale: float) -> TwoMassParameters | None:
    """A physical start from a non-physical 2/3 fit: J_m = 1/b2, J_l and K from the
    undamped two-mass relations ω_a² = K/J_l, ω_r² = ω_a²·(1 + J_l/J_m), B_m + B_l
    from the DC gain split evenly, D from the anti-resonance damping."""
    num, den = _unscale(theta, 3, 2, w_scale)
    b2, b1, b0 = num
    if not (b2 > 0.0 and b0 > 0.0):
        return None
    J_m = 1.0 / b2
    wa2 = b0 / b2
    poles = np.roots(den)
    cplx = poles[np.abs(poles.imag) > 1e-9 * np.abs(poles)]
    wr2 = float(np.abs(cplx[0]) ** 2) if cplx.size else float(np.max(np.abs(poles)) ** 2)
    wr2 = max(wr2, 1.2 * wa2)
    J_l = J_m * (wr2 / wa2 - 1.0)
    K = J_l * wa2
    S = den[3] / b0 if den[3] / b0 > 0.0 else 1e-3 * np.sqrt(K * J_m)
    zeta_a = max(b1 / (2.0 * np.sqrt(b0 * b2)), 0.02)
    D = max(2.0 * zeta_a * np.sqrt(wa2) * J_l - 0.5 * S, 0.05 * np.sqrt(K * J_l))
    return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=0.5 * S, B_l=0.5 * S, K=K, D=D)


_PHYSICAL_MAX_NFEV = 60

#: An extra delay (``fit_delay``) is kept when the weighted output error falls below this factor:
#: a current-loop lag removes far more than that, an ideal loop a few percent at most
#: (measured: see bench/results/RESULTS.md).
_DELAY_GAIN = 0.8


#: Bound on the physical refit's log-parameters (ln J_m, ln J_l, ln K relative to its start).
_LOG_SPAN = 20.0


def _physical_fit(theta: NDArray[np.float64], b: _Basis) -> NDArray[np.float64] | None:
    """Refit in physical parameters with bounds, transient by variable projection.

    Parameters z = (ln J_m, ln J_l, ln K relative to the start, B_m/S0, B_l/S0,
    D/D0). Returns θ (scaled coefficients + transient) of the optimum, or None
    when no physical start exists.
    """
    Xa, Xb, w_scale = b.Xa, b.Xb, b.w_scale
    p0 = _start_parameters(theta, w_scale)
    if p0 is None:
        return None
    S0 = p0.B_m + p0.B_l
    D0 = max(p0.D, 1e-3 * S0)
    Fw = (b.F * b.w)[:, None] * b.Xi
    Yw = b.Y * b.w
    HUw = b.H * b.U * b.w

    def unpack(z: NDArray[np.float64]) -> TwoMassParameters:
        return TwoMassParameters(
            J_m=p0.J_m * np.exp(z[0]), J_l=p0.J_l * np.exp(z[1]), K=p0.K * np.exp(z[2]),
            B_m=S0 * z[3], B_l=S0 * z[4], D=D0 * z[5],
        )

    def parts(z: NDArray[np.float64]):  # type: ignore[no-untyped-def]
        c = _scaled_coefficients(unpack(z), w_scale)
        Ax = Xa[:, 0] + Xa[:, 1:] @ c[:3]
        e = Yw - HUw * (Xb @ c[3:]) / Ax
        Mc = Fw / Ax[:, None]
        Mr = np.concatenate([Mc.real, Mc.imag])
        er = np.concatenate([e.real, e.imag])
        if Mr.shape[1]:
            Q = np.linalg.qr(Mr)[0]
            ci = np.linalg.lstsq(Mr, er, rcond=None)[0]
        else:
            Q, ci = np.zeros((er.size, 0)), np.zeros(0)
        return c, Ax, Q, ci, er

    def fun(z: NDArray[np.float64]) -> NDArray[np.float64]:
        _, _, Q, _, er = parts(z)
        return er - Q @ (Q.T @ er)

    def jac(z: NDArray[np.float64]) -> NDArray[np.float64]:
        # Kaufman's variable-projection Jacobian: P⊥ · ∂r/∂c · ∂c/∂z (c fixed transient)
        c, Ax, Q, ci, _ = parts(z)
        num_full = HUw * (Xb @ c[3:]) + Fw @ ci
        dr_dc = np.concatenate([(num_full / Ax ** 2)[:, None] * Xa[:, 1:],
                                -(HUw / Ax)[:, None] * Xb], axis=1)
        dr_dc = np.concatenate([dr_dc.real, dr_dc.imag])
        h = 1e-7
        dc_dz = np.empty((6, 6))
        for k in range(6):
            dz = np.zeros(6)
            dz[k] = h * max(1.0, abs(z[k]))
            dc_dz[:, k] = (_scaled_coefficients(unpack(z + dz), w_scale)
                           - _scaled_coefficients(unpack(z - dz), w_scale)) / (2.0 * dz[k])
        J = dr_dc @ dc_dz
        return J - Q @ (Q.T @ J)

    # log-parameters bounded to e^±20 of the start: a band distorted by Coulomb friction
    # otherwise drives them to overflow (inf coefficients, NaN into LAPACK)
    lo = np.array([-_LOG_SPAN, -_LOG_SPAN, -_LOG_SPAN, _DAMPING_FLOOR, _DAMPING_FLOOR,
                   _DAMPING_FLOOR * S0 / D0])
    z0 = np.array([0.0, 0.0, 0.0, p0.B_m / S0, p0.B_l / S0, p0.D / D0])
    z0[3:] = np.maximum(z0[3:], 2.0 * lo[3:])
    try:
        # capped: it converges well within the cap wherever it can, and on a band distorted by
        # Coulomb friction the start is taken from a raised band edge anyway
        r = least_squares(fun, z0, jac=jac, bounds=(lo, np.array([_LOG_SPAN] * 3 + [np.inf] * 3)),
                          method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=_PHYSICAL_MAX_NFEV)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(r.x)):
        return None
    c, _, _, ci, _ = parts(r.x)
    return np.concatenate([c, ci])
