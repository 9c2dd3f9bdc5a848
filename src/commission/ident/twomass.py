"""Two-mass model: physical parameters <-> transfer-function coefficients, and modes.

Plant (METHOD.md): J_m·ẍ_m = τ − B_m·ẋ_m − τ_s,  J_l·ẍ_l = τ_s − B_l·ẋ_l,
τ_s = K·y + D·ẏ. Without backlash, from torque to motor velocity:

    V_m/T = (b2 s² + b1 s + b0) / (s³ + a2 s² + a1 s + a0)
"""

from __future__ import annotations

from dataclasses import dataclass, asdict

import numpy as np
from numpy.typing import NDArray

from commission.exceptions import IdentificationError


@dataclass(frozen=True)
class TwoMassParameters:
    """Physical parameters of the linear two-mass model (SI units)."""

    J_m: float  # motor-side inertia [kg·m²]
    J_l: float  # load-side inertia [kg·m²]
    B_m: float  # motor-side viscous friction [N·m·s/rad]
    B_l: float  # load-side viscous friction [N·m·s/rad]
    K: float  # shaft stiffness [N·m/rad]
    D: float  # shaft damping [N·m·s/rad]

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}

    def as_array(self) -> NDArray[np.float64]:
        """(J_m, J_l, B_m, B_l, K, D) as an array of shape (6,)."""
        return np.array([self.J_m, self.J_l, self.B_m, self.B_l, self.K, self.D])

    def velocity_tf(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(num, den) of V_m/T_ref in descending powers of s; num shape (3,), den shape (4,), den[0] = 1."""
        J_m, J_l, B_m, B_l, K, D = self.as_array()
        jj = J_m * J_l
        num = np.array([1.0 / J_m, (D + B_l) / jj, K / jj])
        den = np.array([
            1.0,
            ((D + B_l) * J_m + (D + B_m) * J_l) / jj,
            ((J_m + J_l) * K + (B_m + B_l) * D + B_l * B_m) / jj,
            (B_m + B_l) * K / jj,
        ])
        return num, den

    def velocity_response(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """V_m/T_ref(j·2π·f) [rad/s per N·m], shape of ``f_hz``."""
        num, den = self.velocity_tf()
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        return np.polyval(num, s) / np.polyval(den, s)


#: The paper's torsion test machine (Table 3), the simulator's default plant.
REFERENCE_PLANT = TwoMassParameters(
    J_m=4.78e-4, J_l=1.92e-4, B_m=0.84e-2, B_l=0.53e-2, K=23.10, D=1.54e-2
)


# --- coefficients -> parameters ---------------------------------------------
# With J_m = 1/b2 and the unknown J_l = x (so J_m·J_l = J_m·x):
#
#     S := B_m + B_l = a0/b0                          (DC gain; reliable)
#     X := D + B_l   = b1·J_m·x      = c·x,  c = b1·J_m
#     Y := D + B_m   = J_m·(a2 − b1·J_m)              (does not depend on x)
#     K              = b0·J_m·x
#
# hence D = (X + Y − S)/2, B_l = (X − Y + S)/2, B_m = (Y − X + S)/2, all linear
# in x. Substituting into a1·J_m·x = (J_m + x)·K + S·D + B_l·B_m and
# multiplying by 4 gives
#
#     α·x² + β·x + γ = 0,   α = 4·b0·J_m − c²,
#                           β = 4·b0·J_m² + 2·c·(S + Y) − 4·a1·J_m,
#                           γ = −(S − Y)² = −(B_l − D)²  ≤ 0.
#
# α > 0  ⇔  4·b0·b2 > b1²  ⇔  the anti-resonance zeros are complex. Then the
# roots have opposite signs (α·γ ≤ 0) and the positive one is J_l: unique.
# With real (over-damped) zeros both roots may be positive: two different
# plants give the same transfer function, and we refuse to guess.
# (The paper's eq. 15–17 are garbled in the source and are not used.)

_PARAM_UNITS = {
    "J_m": "kg·m²", "J_l": "kg·m²", "B_m": "N·m·s/rad",
    "B_l": "N·m·s/rad", "K": "N·m/rad", "D": "N·m·s/rad",
}


def _check_coefficients(num: NDArray[np.float64], den: NDArray[np.float64]) -> None:
    if num.shape != (3,) or den.shape != (4,):
        raise IdentificationError(
            f"expected num of shape (3,) and den of shape (4,), got {num.shape} and {den.shape}"
        )
    if not (np.all(np.isfinite(num)) and np.all(np.isfinite(den))):
        raise IdentificationError("transfer-function coefficients are not finite")
    if den[0] == 0.0:
        raise IdentificationError("den[0] is zero: the denominator is not of order 3")


def _candidate(J_m: float, x: float, S: float, Y: float, c: float, b0: float) -> TwoMassParameters:
    X = c * x
    return TwoMassParameters(
        J_m=J_m, J_l=x,
        B_m=0.5 * (Y - X + S), B_l=0.5 * (X - Y + S),
        K=b0 * J_m * x, D=0.5 * (X + Y - S),
    )


def _first_unphysical(p: TwoMassParameters) -> str | None:
    """Name and value of the first parameter that is not physical, or None.

    Inertias and stiffness must be > 0; friction and damping ≥ 0 (a tiny
    negative value from rounding, below 1e-12 of the largest damping, is
    reported as well: nothing is clipped).
    """
    for name in ("J_m", "J_l", "K"):
        v = getattr(p, name)
        if not v > 0.0:
            return f"{name} = {v:.3e} {_PARAM_UNITS[name]} is not positive"
    for name in ("B_m", "B_l", "D"):
        v = getattr(p, name)
        if v < 0.0:
            return f"{name} = {v:.3e} {_PARAM_UNITS[name]} is negative"
    return None


def from_velocity_tf(num: NDArray[np.float64], den: NDArray[np.float64]) -> TwoMassParameters:
    """Exact inverse of :meth:`TwoMassParameters.velocity_tf`.

    ``num`` = (b2, b1, b0) and ``den`` = (1, a2, a1, a0) in descending powers
    of s (a ``den`` with den[0] ≠ 1 is normalised first). The derivation is in
    the comment above this function: J_m = 1/b2, B_m + B_l = a0/b0, and J_l is
    the physical root of one quadratic equation.

    Conditioning: J_m, K, J_l and B_m + B_l follow well from the coefficients; the
    split B_m/B_l (and D) rests on Y = J_m·(a2 − b1·J_m), a small difference of similar
    numbers, so from a fitted transfer function it is the weak part.

    :raises IdentificationError: when the coefficients belong to no physical
        two-mass plant (a negative inertia, stiffness, friction or damping,
        no real J_l) or to two of them (over-damped anti-resonance with two
        physical roots). The message names the parameter and why. Nothing is
        clipped.
    """
    num = np.asarray(num, dtype=float).reshape(-1)
    den = np.asarray(den, dtype=float).reshape(-1)
    _check_coefficients(num, den)
    num = num / den[0]
    den = den / den[0]
    b2, b1, b0 = num
    _, a2, a1, a0 = den
    if not b2 > 0.0:
        raise IdentificationError(
            f"J_m = 1/b2 = {('inf' if b2 == 0 else f'{1.0 / b2:.3e}')} kg·m² is not positive: "
            f"the high-frequency gain b2 = {b2:.3e} must be > 0"
        )
    if not b0 > 0.0:
        raise IdentificationError(
            f"K = b0·J_m·J_l has the sign of b0 = {b0:.3e}: the stiffness would not be positive"
        )
    if not a0 > 0.0:
        raise IdentificationError(
            f"B_m + B_l = a0/b0 = {a0 / b0:.3e} N·m·s/rad is not positive: "
            "the plant would have no viscous friction or an unstable pole"
        )
    J_m = 1.0 / b2
    S = a0 / b0
    c = b1 * J_m
    Y = J_m * (a2 - b1 * J_m)
    alpha = 4.0 * b0 * J_m - c * c
    beta = 4.0 * b0 * J_m * J_m + 2.0 * c * (S + Y) - 4.0 * a1 * J_m
    gamma = -((S - Y) ** 2)

    roots: list[float]
    if alpha == 0.0:
        roots = [] if beta == 0.0 else [-gamma / beta]
    else:
        disc = beta * beta - 4.0 * alpha * gamma
        if disc < 0.0:
            raise IdentificationError(
                f"J_l has no real solution (discriminant {disc:.3e} < 0): "
                "the coefficients are not those of a two-mass plant"
            )
        sq = np.sqrt(disc)
        q = -0.5 * (beta + (sq if beta >= 0.0 else -sq))  # no cancellation
        roots = [q / alpha] + ([gamma / q] if q != 0.0 else [])
    positive = sorted({r for r in roots if r > 0.0})
    if not positive:
        r = max(roots) if roots else float("nan")
        raise IdentificationError(
            f"J_l = {r:.3e} kg·m² is not positive: the coefficients are not those of a "
            "two-mass plant (e.g. anti-resonance above the resonance)"
        )
    candidates = [_candidate(J_m, x, S, Y, c, b0) for x in positive]
    physical = [p for p in candidates if _first_unphysical(p) is None]
    if not physical:
        raise IdentificationError(_first_unphysical(candidates[0]) + ": the coefficients are "
                                  "not those of a physical two-mass plant")  # type: ignore[operator]
    if len(physical) > 1:
        raise IdentificationError(
            f"J_l is ambiguous ({physical[0].J_l:.3e} or {physical[1].J_l:.3e} kg·m²): "
            "with an over-damped anti-resonance two plants share this transfer function"
        )
    return physical[0]


# --- modes ------------------------------------------------------------------
@dataclass(frozen=True)
class Modes:
    """Modal description of V_m/T_ref.

    The resonance is the complex pole pair of the denominator, the
    anti-resonance the zero pair of the numerator (frequency √(b0/b2),
    ζ = b1/(2√(b0·b2)), so an over-damped pair has ζ > 1), and the real pole
    the remaining real root of the denominator (negative for a stable plant;
    with three real poles, the one of smallest magnitude).
    """

    f_resonance_hz: float  # undamped natural frequency of the resonance [Hz]
    zeta_resonance: float  # its damping ratio [-]
    f_antiresonance_hz: float  # undamped natural frequency of the anti-resonance [Hz]
    zeta_antiresonance: float  # its damping ratio [-]
    real_pole_rad_s: float  # the real pole [rad/s] (−20.45 on the reference plant)


def modes_from_tf(num: NDArray[np.float64], den: NDArray[np.float64]) -> Modes:
    """:class:`Modes` of (b2 s² + b1 s + b0)/(s³ + a2 s² + a1 s + a0)."""
    num = np.asarray(num, dtype=float).reshape(-1)
    den = np.asarray(den, dtype=float).reshape(-1)
    _check_coefficients(num, den)
    num, den = num / den[0], den / den[0]
    b2, b1, b0 = num
    if not (b2 != 0.0 and b0 / b2 > 0.0):
        raise IdentificationError(f"no anti-resonance: b0/b2 = {b0 / b2 if b2 else float('inf'):.3e} is not positive")
    w_a = np.sqrt(b0 / b2)
    zeta_a = b1 / (2.0 * np.sqrt(b0 * b2)) if b2 > 0 else -b1 / (2.0 * np.sqrt(b0 * b2))
    poles = np.roots(den)
    real_idx = np.flatnonzero(np.abs(poles.imag) <= 1e-9 * np.abs(poles))
    if real_idx.size == 0:
        raise IdentificationError("the denominator has no real root")
    r = real_idx[np.argmin(np.abs(poles[real_idx]))]
    p_real = float(poles[r].real)
    # deflate: den = (s − p)(s² + 2ζω s + ω²)
    q = np.polydiv(den, np.array([1.0, -p_real]))[0]
    if q[2] <= 0.0:
        raise IdentificationError(f"no resonance: ω² = {q[2]:.3e} (rad/s)² of the pole pair is not positive")
    w_r = np.sqrt(q[2])
    zeta_r = q[1] / (2.0 * w_r)
    return Modes(
        f_resonance_hz=float(w_r / (2 * np.pi)), zeta_resonance=float(zeta_r),
        f_antiresonance_hz=float(w_a / (2 * np.pi)), zeta_antiresonance=float(zeta_a),
        real_pole_rad_s=p_real,
    )


def modes(params: TwoMassParameters) -> Modes:
    """:class:`Modes` of the plant's V_m/T_ref."""
    return modes_from_tf(*params.velocity_tf())
