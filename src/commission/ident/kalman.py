"""The Kalman predictor of the whole two-mass + dead-zone state: the estimator's prediction errors.

State (per sample, SI units)::

    x = (x_m, v_m, s, v_l [, τ])      s = x_m − x_l (the twist), τ the current loop's output

Between two samples τ_ref is held (the drive's zero-order hold), so each mode of the plant — in
contact on either side, τ_s = K·(s ∓ ε) + D·ṡ, or in the gap, τ_s = 0 — is a linear system whose
exact discretization (Φ, Γ) is computed once per parameter set: the predictor needs no interpolated
motor position and no differentiated encoder, and is exact at any sample rate. A sample whose
twist changes mode is propagated exactly with the switch located inside it (the modes' eigen
decompositions, bisection on the twist; interior points catch grazes).

Friction: the motor's Coulomb term F_cm·tanh(v/v_s) takes the measured mean speed of the interval
(an input, as in an equation-error model) where the encoder moved; where it did not (a motor slower
than one step per sample: its speed's sign unknown) it is, as the load's always is, the set-valued
sign at the interval's end (backward Euler: the friction never reverses the mass within one sample,
and holds it when it can), the limit of the smooth sign the plant uses.

Noise model (Ljung, *System Identification*, ch. 4): each encoder measures its position with its
quantization noise, variance step²/12 (the step read from the record); a white torque disturbance
of standard deviation ``process_noise_nm`` per sample acts on the motor (a share of it on the load), and
at a sample a streamed link lost, the spread of the torques the drive may have applied there. The
time-varying Kalman filter (covariance propagated through the sample's mode, so that the load's
uncertainty grows in the gap and is corrected at the next contact) gives one-step prediction
errors e_k and their variances S_k: at the true parameters and noise levels e_k/√S_k is white with
unit variance. The prediction errors themselves, e_k/σ_encoder, are the estimator's residual.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.linalg import expm

from .compiled import inlined, per_sample, read_only
from .consistency import InitialMotion, initial_motion
from .twomass import TwoMassParameters

__all__ = ["KalmanProblem", "Innovations", "delayed_torque", "innovations", "kalman_problem", "position_step_rad"]


@dataclass(frozen=True, eq=False)
class KalmanProblem:
    """One record as the Kalman predictor reads it; arrays are indexed by sample k = 0 … N−1."""

    sample_rate_hz: float
    torque_ref: NDArray[np.float64]
    """Torque acting over [k·Ts, (k+1)·Ts): the reference ``delay_samples`` before, 0 before the record
    [N·m], shape (N,)."""
    motor_position: NDArray[np.float64]
    """Motor encoder at k·Ts [rad], shape (N,)."""
    load_position: NDArray[np.float64] | None
    """Load encoder at k·Ts [rad], shape (N,); None without one."""
    motor_friction: NDArray[np.float64]
    """tanh(v̄/v_s) of the measured mean motor speed over [k·Ts, (k+1)·Ts) [-], shape (N,); exactly 0
    where the encoder did not move (the predictor then takes the friction from its state)."""
    measurement_noise_rad: NDArray[np.float64]
    """Standard deviation of each encoder's quantization, step/√12 [rad], shape (outputs,)."""
    measured: NDArray[np.bool_]
    """False at samples a streamed link lost (interpolated in the record: no evidence), shape (N,)."""
    torque_variance: NDArray[np.float64]
    """Variance of the torque acting over [k·Ts, (k+1)·Ts) [N·m²], shape (N,): 0 where the drive reported
    it; where the link lost its cycle, the spread of the torques the drive may have applied (the one
    the host meant, or a neighbour's: a setpoint late or lost is held)."""
    torque_rms_nm: float
    """RMS of τ_ref [N·m]: the scale of the torque disturbance."""
    velocity_scale_rad_s: float
    delay_samples: float = 0
    """Whole samples between a torque reference and the current loop beyond the hold's own (a drive's
    computation and transport delay); negative, also a fraction: the encoders latched that long after the
    torque (a log's alignment)."""
    start: InitialMotion = InitialMotion()
    """How the axis moves at sample 0: at rest for every experiment this tool runs; read off the first
    samples of a record cut from a longer one."""

    @property
    def outputs(self) -> int:
        return 1 if self.load_position is None else 2


def position_step_rad(position: NDArray[np.float64], measured: NDArray[np.bool_] | None = None) -> float:
    """An encoder's step [rad]: the smallest position change between samples (0: it never moved), among
    samples ``measured`` (an interpolated one a link lost may sit anywhere between two steps); divided by
    the whole number of steps it holds where the axis never stops (a record cut from a running one), which
    the smallest change of a move between samples counts (a change below 1e-8 of the largest move is a
    float's rounding, not a step)."""
    x = np.asarray(position, dtype=np.float64)
    ok = np.ones(x.size, dtype=np.bool_) if measured is None else np.asarray(measured, dtype=np.bool_)
    d1 = np.diff(x)
    d2 = np.abs(np.diff(d1)[ok[2:] & ok[1:-1] & ok[:-2]])
    d1 = np.abs(d1[ok[1:] & ok[:-1]])
    d1 = d1[d1 > 0]
    if not d1.size:
        return 0.0
    smallest = float(d1.min())
    d2 = d2[d2 > 1e-8 * float(d1.max())]
    # the smallest move as a whole number of the smallest change of a move (1 when the axis ever moved by
    # one step: that move itself, to the last bit)
    return smallest / max(round(smallest / float(d2.min())), 1) if d2.size else smallest


def kalman_problem(torque_ref: NDArray[np.float64], motor_position: NDArray[np.float64], sample_rate_hz: float, *,
                   load_position: NDArray[np.float64] | None = None, velocity_scale_rad_s: float = 2e-3,
                   lost: NDArray[np.bool_] | None = None, delay_samples: float = 0,
                   motor_noise_rad: float = 0.0) -> KalmanProblem:
    """The predictor's view of a record (see :class:`KalmanProblem`); ``torque_ref`` [N·m], shape (N,), the
    reference as logged, acting ``delay_samples`` later; ``motor_noise_rad``: the motor position's error
    beside its quantization (standard deviation [rad]: a position rebuilt from a sampled velocity)."""
    fs = float(sample_rate_hz)
    y = np.ascontiguousarray(motor_position, dtype=np.float64)
    speed = np.diff(y) * fs
    measured = np.ones(y.size, dtype=np.bool_) if lost is None else ~np.asarray(lost, dtype=np.bool_)
    steps = [position_step_rad(y, measured)] + ([position_step_rad(load_position, measured)]
                                                if load_position is not None else [])
    # a record that never moves by one step has no quantization to speak of: a floor far below any encoder's
    noise = np.array([max(s, 1e-9) / math.sqrt(12.0) for s in steps])
    noise[0] = max(noise[0], motor_noise_rad)
    tau = np.ascontiguousarray(torque_ref, dtype=np.float64)
    d = float(delay_samples)
    if not (-tau.size < d < tau.size and (d <= 0 or d == int(d))):
        raise ValueError(f"delay of {delay_samples} samples on a record of {tau.size} (whole samples, or a lead)")
    return KalmanProblem(fs, delayed_torque(tau, d), y, None if load_position is None else np.ascontiguousarray(load_position, dtype=np.float64),
                         np.concatenate((np.tanh(speed / velocity_scale_rad_s), [0.0])), noise,
                         np.ascontiguousarray(measured), delayed_torque(_lost_torque_variance(tau, ~measured), d),
                         float(np.sqrt(np.mean(tau * tau))),
                         velocity_scale_rad_s, d, initial_motion(y, fs))


def delayed_torque(x: NDArray[np.float64], d: float) -> NDArray[np.float64]:
    """``x`` acting ``d`` samples later, 0 before the record (shape kept; ``d`` whole when positive); ``d`` < 0:
    earlier (sensors latched after the torque's sample), interpolated between whole samples (a smooth
    torque's hold a fraction of a sample earlier), its last value held past the record."""
    if d < 0:
        n, w = int(math.floor(-d)), -d - math.floor(-d)

        def early(m: int) -> NDArray[np.float64]:
            return np.concatenate((x[m:], np.full(m, x[-1]))) if m else x

        return early(n) if w == 0.0 else (1.0 - w) * early(n) + w * early(n + 1)
    d = int(d)
    return np.concatenate((np.zeros(d), x[:x.size - d])) if d else x


def _lost_torque_variance(tau: NDArray[np.float64], lost: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Per sample, the variance of the torque the drive applied [N·m²]: 0 where the record has it; at a lost
    cycle the mean square of its differences to its neighbours (whether a busy host's setpoint came in time
    there, or the drive held the one before, the record cannot say)."""
    var = np.zeros(tau.size)
    if lost.any() and tau.size > 1:
        step = np.diff(np.concatenate(([tau[0]], tau, [tau[-1]])))
        var = 0.5 * (step[:-1] ** 2 + step[1:] ** 2)
        var[~lost] = 0.0
    return np.ascontiguousarray(var)


@dataclass(frozen=True, eq=False)
class Innovations:
    """The predictor's one-step prediction errors over samples 1 … N−1."""

    error: NDArray[np.float64]
    """Prediction error over each encoder's noise, e_k/σ [-], shape (N−1, outputs); 0 at lost samples."""
    normalized: NDArray[np.float64]
    """e_k/√S_k: unit variance and white at the true parameters and noise levels [-], shape (N−1, outputs)."""
    log_variance: NDArray[np.float64]
    """ln(S_k/σ²) [-], shape (N−1, outputs)."""
    events: int
    """Contact and separation events located inside samples."""

    def negative_log_likelihood(self) -> float:
        """Mean of ν² + ln S (Gaussian prediction errors, up to a constant) [-]."""
        return float(np.mean(self.normalized ** 2 + self.log_variance))

    @property
    def rms(self) -> float:
        """RMS of ``normalized`` [-]: 1 at the true parameters and noise levels."""
        return float(np.sqrt(np.mean(self.normalized ** 2)))


# --- the model's matrices ------------------------------------------------------------------------
def _continuous(p: TwoMassParameters, lag_s: float, contact: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(A, B) of one mode; inputs u = (τ_ref, ±ε (the contact side's offset), F_cm·f_m, F_cl·f_l)."""
    n = 5 if lag_s > 0 else 4
    A = np.zeros((n, n))
    B = np.zeros((n, 4))
    A[0, 1] = 1.0
    A[1, 1] = -p.B_m / p.J_m
    A[2, 1], A[2, 3] = 1.0, -1.0
    A[3, 3] = -p.B_l / p.J_l
    if contact:  # τ_s = K·s − K·(±ε) + D·(v_m − v_l)
        A[1, 1] -= p.D / p.J_m
        A[1, 2] -= p.K / p.J_m
        A[1, 3] += p.D / p.J_m
        A[3, 1] += p.D / p.J_l
        A[3, 2] += p.K / p.J_l
        A[3, 3] -= p.D / p.J_l
        B[1, 1], B[3, 1] = p.K / p.J_m, -p.K / p.J_l
    if lag_s > 0:
        A[1, 4] = 1.0 / p.J_m
        A[4, 4] = -1.0 / lag_s
        B[4, 0] = 1.0 / lag_s
    else:
        B[1, 0] = 1.0 / p.J_m
    B[1, 2] = -1.0 / p.J_m
    B[3, 3] = -1.0 / p.J_l
    return A, B


def _discretize(A: NDArray[np.float64], B: NDArray[np.float64], t: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Exact zero-order-hold discretization over t: (e^{At}, ∫₀ᵗ e^{As} ds·B)."""
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, B
    E = expm(M * t)
    return E[:n, :n], E[:n, n:]


@dataclass(frozen=True, eq=False)
class _Model:
    """Per mode (0: gap, 1: contact): full- and half-sample maps, eigen decomposition, B, process noise."""

    Phi: NDArray[np.float64]
    Gam: NDArray[np.float64]
    PhiH: NDArray[np.float64]
    GamH: NDArray[np.float64]
    V: NDArray[np.complex128]
    lam: NDArray[np.complex128]
    Vi: NDArray[np.complex128]
    B: NDArray[np.float64]
    Q: NDArray[np.float64]


def _model(p: TwoMassParameters, lag_s: float, Ts: float, process_noise_nm: float, load_share: float) -> _Model | None:
    mats = [_continuous(p, lag_s, c) for c in (False, True)]
    n = mats[0][0].shape[0]
    out = {k: np.empty((2, n, n)) for k in ("Phi", "PhiH", "Q")}
    out.update(Gam=np.empty((2, n, 4)), GamH=np.empty((2, n, 4)), B=np.empty((2, n, 4)))
    V = np.empty((2, n, n), dtype=np.complex128)
    lam = np.empty((2, n), dtype=np.complex128)
    Vi = np.empty((2, n, n), dtype=np.complex128)
    for m, (A, B) in enumerate(mats):
        out["Phi"][m], out["Gam"][m] = _discretize(A, B, Ts)
        out["PhiH"][m], out["GamH"][m] = _discretize(A, B, 0.5 * Ts)
        lam[m], V[m] = np.linalg.eig(A)
        if not np.all(np.isfinite(V[m])) or np.linalg.cond(V[m]) > 1e12:
            return None  # a defective mode (coincident poles): no parameter set a fit would end at
        Vi[m] = np.linalg.inv(V[m])
        out["B"][m] = B
        # a white torque disturbance held over the sample on the motor (through τ_ref's column: the
        # current loop filters it as it filters τ_ref), and a share of it on the load (F_cl's column)
        g_m, g_l = out["Gam"][m][:, 0], out["Gam"][m][:, 3]
        out["Q"][m] = (np.outer(g_m, g_m) + load_share ** 2 * np.outer(g_l, g_l)) * process_noise_nm ** 2
    return _Model(V=V, lam=lam, Vi=Vi, **out)


# --- compiled core ---------------------------------------------------------------------------------
#: Relative change of the covariance over a contact interval below which it is taken as steady (its
#: gains then reused until the mode changes): far below what moves an estimate.
_STEADY = 1e-12
#: Points inside a switching sample where the twist is checked for the first crossing.
_INTERIOR = 4

@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _region(s: float, eps: float) -> int:
    """+1 / −1: in contact on that side; 0: in the gap (no backlash: always in contact)."""
    if eps <= 0.0 or s > eps:
        return 1
    if s < -eps:
        return -1
    return 0


@per_sample
def _twist_at(V: NDArray[np.complex128], lam: NDArray[np.complex128], m: int, z0: NDArray[np.complex128],
              c: NDArray[np.complex128], t: float) -> float:
    """The twist [rad] at time t [s] into a segment of mode ``m`` (x(t) = V·(e^{λt}·z₀ + φ(λ,t)·c))."""
    acc = 0.0
    for i in range(lam.shape[1]):
        a = lam[m, i] * t
        ea = np.exp(a)
        ph = t * (1.0 + 0.5 * a) if abs(a) < 1e-8 else (ea - 1.0) / lam[m, i]
        acc += (V[m, 2, i] * (ea * z0[i] + ph * c[i])).real
    return acc


@per_sample
def _crossing(V: NDArray[np.complex128], lam: NDArray[np.complex128], m: int, z0: NDArray[np.complex128],
              c: NDArray[np.complex128], b: float, t0: float, g0: float, t1: float, g1: float, reg: int,
              eps: float) -> float:
    """The first time in (t0, t1] the twist leaves mode ``reg`` through the boundary b (g = s − b changes
    sign on the bracket): Illinois regula falsi (an end's value halved only when the end is kept twice in
    a row: halving it every time makes the steps alternate sides and converge no faster than bisection);
    the returned time lies in the new mode."""
    kept = 0  # the end kept by the last step: −1 t0, +1 t1
    for _ in range(60):
        if t1 - t0 <= 1e-14 * max(t1, 1e-300):
            break
        t = t1 - g1 * (t1 - t0) / (g1 - g0) if g1 != g0 else 0.5 * (t0 + t1)
        if not t0 < t < t1:
            t = 0.5 * (t0 + t1)
        st = _twist_at(V, lam, m, z0, c, t)
        g = st - b
        if _region(st, eps) != reg:
            t1, g1 = t, g
            if kept < 0:
                g0 *= 0.5
            kept = -1
        else:
            t0, g0 = t, g
            if kept > 0:
                g1 *= 0.5
            kept = 1
    return t1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _flow(V: NDArray[np.complex128], ek: NDArray[np.complex128], Vi: NDArray[np.complex128],
          Ve: NDArray[np.complex128], out: NDArray[np.float64]) -> None:
    """out ← Φ(t) = Re(V·e^{Λt}·V⁻¹), ``ek`` = e^{λt} (Ve: scratch; the products associate as written)."""
    n = out.shape[0]
    for i in range(n):
        for k in range(n):
            Ve[i, k] = V[i, k] * ek[k]
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += (Ve[i, k] * Vi[k, j]).real
            out[i, j] = acc


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _product(A: NDArray[np.float64], B: NDArray[np.float64], out: NDArray[np.float64]) -> None:
    """out ← A·B for small square matrices (summed in a fixed order: the same bits on every machine)."""
    n = out.shape[0]
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += A[i, k] * B[k, j]
            out[i, j] = acc


@per_sample
def _switching_step(x0: NDArray[np.float64], x: NDArray[np.float64], u: NDArray[np.float64], eps: float, Ts: float,
                    V: NDArray[np.complex128], lam: NDArray[np.complex128], Vi: NDArray[np.complex128],
                    Bc: NDArray[np.float64], jump: NDArray[np.float64], M: NDArray[np.float64],
                    cw: NDArray[np.complex128], rw: NDArray[np.float64]) -> int:
    """Propagate ``x0`` over Ts into ``x``, locating each mode switch (x(t) = V·(e^{λt}·z₀ + φ(λ,t)·c));
    returns the number of switches. ``M`` (n × n) becomes the flow's linearization over the sample: each
    mode's transition matrix over its part, and at each switch the saltation matrix I ± jump·e_sᵀ (the
    damper's force jumps at contact, so a twist error moves the switch time and the velocities with it).
    ``cw`` ((4 + n) × n, complex) and ``rw`` ((1 + 2n) × n) are scratch."""
    n = x.size
    for i in range(n):
        x[i] = x0[i]
    t_left = Ts
    events = 0
    z0, c, ek, phk, Ve = cw[0], cw[1], cw[2], cw[3], cw[4:]
    bu, W, W2 = rw[0], rw[1:n + 1], rw[n + 1:]
    for i in range(n):
        for j in range(n):
            M[i, j] = 1.0 if i == j else 0.0
    for _ in range(16):
        reg = _region(x[2], eps)
        m = 0 if reg == 0 else 1
        u[1] = reg * eps
        for j in range(n):
            acc = 0.0
            for q in range(4):
                acc += Bc[m, j, q] * u[q]
            bu[j] = acc
        for i in range(n):
            a0 = 0j
            a1 = 0j
            for j in range(n):
                a0 += Vi[m, i, j] * x[j]
                a1 += Vi[m, i, j] * bu[j]
            z0[i] = a0
            c[i] = a1
        tc = -1.0
        t_prev, s_prev = 0.0, x[2]
        for j in range(1, _INTERIOR + 1):  # interior points catch a graze that leaves the end in the same mode
            tj = t_left * j / _INTERIOR
            sj = _twist_at(V, lam, m, z0, c, tj)
            side = _region(sj, eps)
            if side != reg:
                # the boundary crossed: ε or −ε (out of the gap toward ``side``, out of contact toward the gap)
                b = eps * (side if reg == 0 else reg)
                tc = _crossing(V, lam, m, z0, c, b, t_prev, s_prev - b, tj, sj - b, reg, eps)
                break
            t_prev, s_prev = tj, sj
        t = t_left if tc < 0 else tc
        for k in range(n):  # e^{λt} and φ(λ,t) once per segment: the state and the flow map share them
            a = lam[m, k] * t
            ek[k] = np.exp(a)
            phk[k] = t * (1.0 + 0.5 * a) if abs(a) < 1e-8 else (ek[k] - 1.0) / lam[m, k]
        for i in range(n):
            acc = 0.0
            for k in range(n):
                acc += (V[m, i, k] * (ek[k] * z0[k] + phk[k] * c[k])).real
            x[i] = acc
        # M ← Φ_m(t)·M
        _flow(V[m], ek, Vi[m], Ve, W)
        _product(W, M, W2)
        for i in range(n):
            for j in range(n):
                M[i, j] = W2[i, j]
        if tc < 0:
            break
        # saltation: into contact +jump·e_sᵀ, out of it −jump·e_sᵀ (the spring's force is continuous there)
        sign = 1.0 if reg == 0 else -1.0
        for i in range(n):
            if jump[i] != 0.0:
                for j in range(n):
                    M[i, j] += sign * jump[i] * M[2, j]
        events += 1
        t_left -= tc
        if t_left <= 1e-12 * Ts:
            break
    return events


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _set_valued_friction(xe: NDArray[np.float64], Gam: NDArray[np.float64], m: int, velocity: int, column: int,
                         F: float) -> float:
    """The Coulomb force [N·m] of the set-valued sign at the interval's end velocity ``xe[velocity]``
    (backward Euler: it never reverses the mass within the sample, and holds it when it can), added to
    the predicted state ``xe`` through the friction's column of mode ``m``'s Γ."""
    f = min(max(xe[velocity] / (-Gam[m, velocity, column] * F), -1.0), 1.0) * F
    for i in range(xe.size):
        xe[i] += Gam[m, i, column] * f
    return f


@inlined
def _predict(x: NDArray[np.float64], tk: float, fmk: float, Fcm: float, Fcl: float, eps: float, Ts: float,
             Phi: NDArray[np.float64], Gam: NDArray[np.float64], PhiH: NDArray[np.float64], GamH: NDArray[np.float64],
             u: NDArray[np.float64], xe: NDArray[np.float64]) -> tuple[int, bool]:
    """One sample's prediction of ``x`` into ``xe`` within the mode it starts in, and the inputs ``u`` of the
    sample; returns (that mode, whether the twist leaves it within the sample: then ``xe`` is to be
    replaced by :func:`_switching_step`'s, which the loop calls)."""
    n = x.size
    reg = _region(x[2], eps)
    m = 0 if reg == 0 else 1
    u[0] = tk
    u[1] = reg * eps
    u[2] = Fcm * fmk
    u[3] = 0.0
    for i in range(n):
        a = 0.0
        for j in range(n):
            a += Phi[m, i, j] * x[j]
        for q in range(3):
            a += Gam[m, i, q] * u[q]
        xe[i] = a
    if Fcm > 0.0 and fmk == 0.0:
        # the encoder did not move: the motor's friction as the load's, set-valued at the end velocity
        u[2] = _set_valued_friction(xe, Gam, m, 1, 2, Fcm)
    if Fcl > 0.0:
        u[3] = _set_valued_friction(xe, Gam, m, 3, 3, Fcl)
    switch = False
    if eps > 0.0:
        switch = _region(xe[2], eps) != reg
        # a graze (out of the mode and back within the sample) is possible only near a boundary
        reach = 2.0 * Ts * (abs(x[1] - x[3]) + abs(xe[1] - xe[3]))
        near = min(abs(abs(x[2]) - eps), abs(abs(xe[2]) - eps)) < reach
        if not switch and near:
            xh2 = 0.0
            for j in range(n):
                xh2 += PhiH[m, 2, j] * x[j]
            for q in range(4):
                xh2 += GamH[m, 2, q] * u[q]
            switch = _region(xh2, eps) != reg
    return m, switch


#: Sigma points along the twist (Gauss–Hermite, 3 points: offsets 0, ±√3·σ_s, weights 2/3, 1/6, 1/6).
_SIGMA = math.sqrt(3.0)
_SIGMA_OFFSET = np.array([0.0, _SIGMA, -_SIGMA])
_SIGMA_WEIGHT = np.array([2.0 / 3.0, 1.0 / 6.0, 1.0 / 6.0])


@njit(cache=True, nogil=True, error_model="numpy")
def _filter(tau: NDArray[np.float64], tvar: NDArray[np.float64], y: NDArray[np.float64], yl: NDArray[np.float64],
            fm: NDArray[np.float64], measured: NDArray[np.bool_], Fcm: float, Fcl: float, eps: float, Ts: float,
            Phi: NDArray[np.float64], Gam: NDArray[np.float64], PhiH: NDArray[np.float64], GamH: NDArray[np.float64],
            V: NDArray[np.complex128], lam: NDArray[np.complex128], Vi: NDArray[np.complex128],
            Bc: NDArray[np.float64], jump: NDArray[np.float64], Q: NDArray[np.float64], R: NDArray[np.float64],
            x0: NDArray[np.float64], P0: NDArray[np.float64], e: NDArray[np.float64], S_out: NDArray[np.float64],
            sigma_points: bool) -> int:
    """The predictor over the record from (``x0``, ``P0``): prediction errors into ``e``, their variances
    into ``S_out`` (both (N−1, outputs)); returns the contact events located inside samples. Allocates the
    state and scratch; the loop is :func:`_loop`'s."""
    n = x0.size
    nout = e.shape[1]
    x = x0.copy()
    P = P0.copy()
    T = np.empty((n, n))
    Msw = np.empty((n, n))
    xe = np.empty(n)
    u = np.zeros(4)
    g = np.empty(n)
    P_last = np.zeros((n, n))
    G_st = np.zeros((nout, n))
    S_st = np.ones(nout)
    xs = np.empty((3, n))
    xes = np.empty((3, n))
    Fs = np.empty((3, n, n))
    Pc = np.empty((n, n))
    col = np.empty(n)
    cw = np.empty((4 + n, n), dtype=np.complex128)
    rw = np.empty((1 + 2 * n, n))
    return _loop(tau, tvar, y, yl, fm, measured, Fcm, Fcl, eps, Ts, Phi, Gam, PhiH, GamH, V, lam, Vi, Bc, jump, Q, R,
                 e, S_out, sigma_points, x, P, T, Msw, xe, u, g, P_last, G_st, S_st, xs, xes, Fs, Pc, col, cw, rw)


@per_sample  # (the per-sample steps inlined into it: one function, no calls, no reference counts)
def _loop(tau: NDArray[np.float64], tvar: NDArray[np.float64], y: NDArray[np.float64], yl: NDArray[np.float64],
          fm: NDArray[np.float64], measured: NDArray[np.bool_], Fcm: float, Fcl: float, eps: float, Ts: float,
          Phi: NDArray[np.float64], Gam: NDArray[np.float64], PhiH: NDArray[np.float64], GamH: NDArray[np.float64],
          V: NDArray[np.complex128], lam: NDArray[np.complex128], Vi: NDArray[np.complex128],
          Bc: NDArray[np.float64], jump: NDArray[np.float64], Q: NDArray[np.float64], R: NDArray[np.float64],
          e: NDArray[np.float64], S_out: NDArray[np.float64], sigma_points: bool, x: NDArray[np.float64],
          P: NDArray[np.float64], T: NDArray[np.float64], Msw: NDArray[np.float64], xe: NDArray[np.float64],
          u: NDArray[np.float64], g: NDArray[np.float64], P_last: NDArray[np.float64], G_st: NDArray[np.float64],
          S_st: NDArray[np.float64], xs: NDArray[np.float64], xes: NDArray[np.float64], Fs: NDArray[np.float64],
          Pc: NDArray[np.float64], col: NDArray[np.float64], cw: NDArray[np.complex128],
          rw: NDArray[np.float64]) -> int:
    """:func:`_filter`'s loop over the samples (the state ``x`` and covariance ``P`` from their start; the
    other arrays after ``x``: its scratch); returns the contact events located inside samples."""
    N = y.size
    n = x.size
    nout = e.shape[1]
    steady = False
    events = 0
    for k in range(N - 1):
        spread = False
        if sigma_points and eps > 0.0 and P[2, 2] > 0.0:
            # the twist's uncertainty reaches a boundary: its sigma points may take different modes
            h = _SIGMA * math.sqrt(P[2, 2])
            spread = h > 1e-6 * eps and abs(abs(x[2]) - eps) < 4.0 * Ts * abs(x[1] - x[3]) + h
        if not spread:
            m, switch = _predict(x, tau[k], fm[k], Fcm, Fcl, eps, Ts, Phi, Gam, PhiH, GamH, u, xe)
            if switch:  # (the load friction as the plain prediction set it in u: continuous across the switch)
                events += _switching_step(x, xe, u, eps, Ts, V, lam, Vi, Bc, jump, Msw, cw, rw)
            for i in range(n):
                x[i] = xe[i]
            if steady and m == 1 and not switch and measured[k + 1] and tvar[k] == 0.0:
                # in contact, the covariance has reached its steady state: the stored gains
                for o in range(nout):
                    innov = y[k + 1] - x[0] if o == 0 else yl[k + 1] - (x[0] - x[2])
                    e[k, o] = innov
                    S_out[k, o] = S_st[o]
                    for i in range(n):
                        x[i] += G_st[o, i] * innov
                continue
            # P ← F P Fᵀ + Q: F the interval's mode's Φ, or across a switch the saltated flow's linearization
            _propagate(Phi, Msw, switch, m, P, Q, T)
            if tvar[k] > 0.0:
                _torque_noise(P, Gam, m, tvar[k])
        else:
            m, ev = _sigma_predict(x, P, tau[k], fm[k], Fcm, Fcl, eps, Ts, Phi, Gam, PhiH, GamH, V, lam, Vi, Bc, jump,
                                   Q, u, Msw, xs, xes, Fs, Pc, col, T, cw, rw)
            events += ev
            switch = True  # never a steady sample
            if tvar[k] > 0.0:
                _torque_noise(P, Gam, m, tvar[k])
        if not measured[k + 1]:
            steady = False
            for o in range(nout):
                e[k, o] = 0.0
                S_out[k, o] = R[o]
            continue
        # (yl is empty without a load encoder: not read past its end)
        _update(x, P, y[k + 1], yl[k + 1] if nout > 1 else 0.0, R, e, S_out, k, S_st, G_st, g)
        # steady once a contact interval leaves the covariance where the last one did (to ~1e-12)
        steady = _settled(P, P_last) and m == 1 and not switch
    return events


@inlined
def _torque_noise(P: NDArray[np.float64], Gam: NDArray[np.float64], m: int, var: float) -> None:
    """P ← P + var·g·gᵀ: a torque reference of variance ``var`` [N·m²] held over the sample (g: mode ``m``'s Γ's
    τ_ref column)."""
    n = P.shape[0]
    for i in range(n):
        for j in range(n):
            P[i, j] += var * Gam[m, i, 0] * Gam[m, j, 0]


@inlined
def _propagate(Phi: NDArray[np.float64], Msw: NDArray[np.float64], switch: bool, m: int, P: NDArray[np.float64],
               Q: NDArray[np.float64], T: NDArray[np.float64]) -> None:
    """P ← F·P·Fᵀ + Q_m, symmetric, F the saltated flow ``Msw`` across a switch, else mode ``m``'s Φ (T:
    scratch; the mode picked here by index: a view made in the filter's loop costs its reference counts)."""
    n = P.shape[0]
    F = Msw if switch else Phi[m]
    _product(F, P, T)
    for i in range(n):
        for j in range(i, n):
            acc = Q[m, i, j]
            for l in range(n):
                acc += T[i, l] * F[j, l]
            P[i, j] = acc
            P[j, i] = acc


@per_sample
def _sigma_predict(x: NDArray[np.float64], P: NDArray[np.float64], tk: float, fmk: float, Fcm: float, Fcl: float,
                   eps: float, Ts: float, Phi: NDArray[np.float64], Gam: NDArray[np.float64], PhiH: NDArray[np.float64],
                   GamH: NDArray[np.float64], V: NDArray[np.complex128], lam: NDArray[np.complex128],
                   Vi: NDArray[np.complex128], Bc: NDArray[np.float64], jump: NDArray[np.float64],
                   Q: NDArray[np.float64], u: NDArray[np.float64], Msw: NDArray[np.float64], xs: NDArray[np.float64],
                   xes: NDArray[np.float64], Fs: NDArray[np.float64], Pc: NDArray[np.float64],
                   col: NDArray[np.float64], T: NDArray[np.float64], cw: NDArray[np.complex128],
                   rw: NDArray[np.float64]) -> tuple[int, int]:
    """One sample's prediction of ``x`` and ``P`` by three points along the twist's direction in the state
    (x ± √3·P[:,2]/σ_s), each through its own modes; the rest of the covariance (given the twist) through
    each point's flow. Returns (the mean point's mode at the start, its contact events)."""
    n = x.size
    sd = math.sqrt(P[2, 2])
    for i in range(n):
        col[i] = P[i, 2] / sd
    for i in range(n):
        for j in range(n):
            Pc[i, j] = P[i, j] - col[i] * col[j]
    m0 = 0
    events = 0
    for p in range(3):
        for i in range(n):
            xs[p, i] = x[i] + _SIGMA_OFFSET[p] * col[i]
        mp, sw = _predict(xs[p], tk, fmk, Fcm, Fcl, eps, Ts, Phi, Gam, PhiH, GamH, u, xes[p])
        ev = _switching_step(xs[p], xes[p], u, eps, Ts, V, lam, Vi, Bc, jump, Msw, cw, rw) if sw else 0
        if p == 0:
            m0, events = mp, ev
        for i in range(n):
            for j in range(n):
                Fs[p, i, j] = Msw[i, j] if sw else Phi[mp, i, j]
    for i in range(n):
        acc = 0.0
        for p in range(3):
            acc += _SIGMA_WEIGHT[p] * xes[p, i]
        x[i] = acc
    for i in range(n):
        for j in range(i, n):
            acc = Q[m0, i, j]
            for p in range(3):
                acc += _SIGMA_WEIGHT[p] * (xes[p, i] - x[i]) * (xes[p, j] - x[j])
            P[i, j] = acc
    for p in range(3):
        _product(Fs[p], Pc, T)
        for i in range(n):
            for j in range(i, n):
                acc = 0.0
                for l in range(n):
                    acc += T[i, l] * Fs[p, j, l]
                P[i, j] += _SIGMA_WEIGHT[p] * acc
    for i in range(n):
        for j in range(i + 1, n):
            P[j, i] = P[i, j]
    return m0, events


@inlined
def _update(x: NDArray[np.float64], P: NDArray[np.float64], y1: float, yl1: float, R: NDArray[np.float64],
            e: NDArray[np.float64], S_out: NDArray[np.float64], k: int, S_st: NDArray[np.float64],
            G_st: NDArray[np.float64], g: NDArray[np.float64]) -> None:
    """The measurement update at one sample, by sequential scalar updates (independent encoders): the motor
    position ``y1``, then (with two outputs) the load's ``yl1``. Writes the innovations into ``e[k]`` and
    their variances into ``S_out[k]``, and keeps the gains (``G_st``, ``S_st``) for the steady state."""
    n = x.size
    for o in range(e.shape[1]):
        if o == 0:
            innov = y1 - x[0]
            for i in range(n):
                g[i] = P[i, 0]
            S = R[0] + g[0]
        else:
            innov = yl1 - (x[0] - x[2])
            for i in range(n):
                g[i] = P[i, 0] - P[i, 2]
            S = R[1] + g[0] - g[2]
        e[k, o] = innov
        S_out[k, o] = S
        S_st[o] = S
        for i in range(n):
            G_st[o, i] = g[i] / S
            x[i] += g[i] / S * innov
        for i in range(n):
            for j in range(n):
                P[i, j] -= g[i] * g[j] / S


@inlined
def _settled(P: NDArray[np.float64], P_last: NDArray[np.float64]) -> bool:
    """Whether ``P`` is where ``P_last`` was, to ``_STEADY`` of its size; ``P_last`` ← ``P``."""
    n = P.shape[0]
    change = 0.0
    size = 0.0
    for i in range(n):
        for j in range(n):
            change = max(change, abs(P[i, j] - P_last[i, j]))
            size = max(size, abs(P[i, j]))
            P_last[i, j] = P[i, j]
    return change <= _STEADY * size


def innovations(problem: KalmanProblem, params: TwoMassParameters, epsilon_rad: float, *,
                coulomb_motor_nm: float = 0.0, coulomb_load_nm: float = 0.0, lag_s: float = 0.0,
                process_noise_nm: float, load_share: float = 0.0, twist_noise_rad: float = 0.0,
                sigma_points: bool = False) -> Innovations | None:
    """The Kalman predictor's prediction errors at these parameters (None: the model has a defective
    mode, where no eigen decomposition describes it).

    :param process_noise_nm: standard deviation of the torque disturbance on the motor, per sample [N·m].
    :param load_share: the load's disturbance as a share of it (0: a drive's torque noise alone; more
        lets the predictor follow a load the model does not quite reproduce) [-].
    """
    pr = problem
    Ts = 1.0 / pr.sample_rate_hz
    model = _model(params, lag_s, Ts, process_noise_nm, load_share)
    if model is None:
        return None
    n = model.Phi.shape[1]
    Qm = model.Q
    if twist_noise_rad > 0.0:  # a random walk of the twist: the gap's edges known only to this
        Qm = model.Q.copy()
        Qm[:, 2, 2] += twist_noise_rad ** 2
    R = pr.measurement_noise_rad ** 2
    x0 = np.zeros(n)
    x0[0] = pr.motor_position[0]
    P0 = np.zeros((n, n))
    P0[0, 0] = R[0]
    # the record starts at rest, the twist anywhere in the gap (measured with a load encoder); or moving
    # at its first samples' speed (known to a fifth), on the flank the shaft's torque presses
    P0[2, 2] = epsilon_rad ** 2 + R[0]
    if pr.start.moving:
        x0[1] = x0[3] = pr.start.speed_rad_s
        P0[1, 1] = P0[3, 3] = (0.2 * pr.start.speed_rad_s) ** 2
        if pr.load_position is None:
            x0[2] = pr.start.twist_rad(params.J_l, params.B_l, params.K, epsilon_rad)
    yl = np.zeros(0) if pr.load_position is None else pr.load_position
    if pr.load_position is not None:
        x0[2] = pr.motor_position[0] - pr.load_position[0]
        P0[2, 2] = R[0] + R[1]
    # the damper's force D·(v_m − v_l) per twist rate, on each velocity: what jumps at contact
    jump = np.zeros(n)
    jump[1], jump[3] = -params.D / params.J_m, params.D / params.J_l
    e = np.zeros((pr.motor_position.size - 1, pr.outputs))
    S = np.ones_like(e)
    tau, tvar, y, yl, fm = (read_only(a) for a in (pr.torque_ref, pr.torque_variance, pr.motor_position, yl,
                                                   pr.motor_friction))
    events = _filter(tau, tvar, y, yl, fm, read_only(pr.measured, np.bool_), float(coulomb_motor_nm),
                     float(coulomb_load_nm), float(epsilon_rad), Ts, model.Phi, model.Gam,
                     model.PhiH, model.GamH, model.V, model.lam, model.Vi, model.B, jump, Qm, R, x0, P0, e, S,
                     sigma_points)
    S = S / R[None, :]
    error = e / np.sqrt(R)[None, :]
    return Innovations(error=error, normalized=error / np.sqrt(S), log_variance=np.log(S), events=int(events))
