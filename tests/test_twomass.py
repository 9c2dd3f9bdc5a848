"""Two-mass model: coefficients <-> parameters (exact inverse) and modes."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from commission.exceptions import IdentificationError
from commission.ident.twomass import (
    REFERENCE_PLANT,
    Modes,
    TwoMassParameters,
    from_velocity_tf,
    modes,
    modes_from_tf,
)


def _random_plant(rng: np.random.Generator, load_share: float) -> TwoMassParameters:
    """Inertia ratio 0.1–10, resonance 20–300 Hz, anti-resonance ζ 0.01–0.9;
    ``load_share`` = B_l/(B_l + D) of the anti-resonance damping, B_m from 0.01× to 100× B_l."""
    J_m = 10 ** rng.uniform(-5, -2)
    J_l = J_m * 10 ** rng.uniform(-1, 1)
    f_r = 10 ** rng.uniform(np.log10(20), np.log10(300))
    K = (2 * np.pi * f_r) ** 2 * J_m * J_l / (J_m + J_l)
    zeta_a = 10 ** rng.uniform(-2, np.log10(0.9))
    X = 2 * zeta_a * np.sqrt(K * J_l)                       # D + B_l
    B_l = X * load_share
    D = X - B_l
    B_m = max(B_l, 1e-4 * X) * 10 ** rng.uniform(-2, 2)
    return TwoMassParameters(J_m, J_l, B_m, B_l, K, D)


@pytest.mark.parametrize("load_share", [0.001, 0.05, 0.5, 0.95])
def test_round_trip_random_plants(load_share: float) -> None:
    rng = np.random.default_rng(int(load_share * 1000))
    for _ in range(300):
        p = _random_plant(rng, load_share)
        q = from_velocity_tf(*p.velocity_tf())
        assert_allclose(q.as_array(), p.as_array(), rtol=1e-10)


def test_round_trip_extreme_damping_splits() -> None:
    base = REFERENCE_PLANT
    for B_m, B_l in [(1e-4, 1e-1), (1e-1, 1e-4), (5e-2, 5e-2)]:
        p = TwoMassParameters(base.J_m, base.J_l, B_m, B_l, base.K, base.D)
        assert_allclose(from_velocity_tf(*p.velocity_tf()).as_array(), p.as_array(), rtol=1e-10)


def test_reference_plant_modes_match_method_md() -> None:
    m = modes(REFERENCE_PLANT)
    assert isinstance(m, Modes)
    assert m.f_resonance_hz == pytest.approx(65.35, abs=0.01)
    assert m.zeta_resonance == pytest.approx(0.167, abs=0.001)
    assert m.f_antiresonance_hz == pytest.approx(55.20, abs=0.01)
    assert m.zeta_antiresonance == pytest.approx(0.155, abs=0.001)
    assert m.real_pole_rad_s == pytest.approx(-20.45, abs=0.01)


def test_modes_reproduce_the_denominator() -> None:
    num, den = REFERENCE_PLANT.velocity_tf()
    m = modes_from_tf(num, den)
    w_r = 2 * np.pi * m.f_resonance_hz
    rebuilt = np.polymul([1.0, -m.real_pole_rad_s], [1.0, 2 * m.zeta_resonance * w_r, w_r**2])
    assert_allclose(rebuilt, den, rtol=1e-12)
    w_a = 2 * np.pi * m.f_antiresonance_hz
    assert_allclose(num / num[0], [1.0, 2 * m.zeta_antiresonance * w_a, w_a**2], rtol=1e-12)


def test_unnormalised_denominator_is_accepted() -> None:
    num, den = REFERENCE_PLANT.velocity_tf()
    q = from_velocity_tf(3.0 * num, 3.0 * den)
    assert_allclose(q.as_array(), REFERENCE_PLANT.as_array(), rtol=1e-12)


def test_refuses_negative_high_frequency_gain() -> None:
    num, den = REFERENCE_PLANT.velocity_tf()
    with pytest.raises(IdentificationError, match="J_m"):
        from_velocity_tf(-num, den)


def test_refuses_antiresonance_above_resonance() -> None:
    # swap the roles: zeros above the pole pair is no two-mass plant (J_l < 0)
    num, den = REFERENCE_PLANT.velocity_tf()
    num2 = num.copy()
    num2[2] = num[2] * 2.0  # anti-resonance at 55·√2 = 78 Hz > 65 Hz
    with pytest.raises(IdentificationError, match="J_l|B_m|B_l|D"):
        from_velocity_tf(num2, den)


def test_refuses_negative_friction_naming_the_parameter() -> None:
    p = TwoMassParameters(4.78e-4, 1.92e-4, -0.002, 0.0053, 23.1, 0.0154)
    with pytest.raises(IdentificationError, match=r"B_m = -"):
        from_velocity_tf(*p.velocity_tf())


def test_refuses_unstable_dc() -> None:
    num, den = REFERENCE_PLANT.velocity_tf()
    den2 = den.copy()
    den2[3] = -den[3]
    with pytest.raises(IdentificationError, match="B_m \\+ B_l"):
        from_velocity_tf(num, den2)


def test_refuses_bad_shapes_and_nan() -> None:
    num, den = REFERENCE_PLANT.velocity_tf()
    with pytest.raises(IdentificationError, match="shape"):
        from_velocity_tf(num[:2], den)
    with pytest.raises(IdentificationError, match="finite"):
        from_velocity_tf(num, np.array([1.0, np.nan, 1.0, 1.0]))


def test_overdamped_antiresonance_is_unique_or_refused() -> None:
    """ζ_a > 1: the quadratic in J_l may have two positive roots; either the answer
    is the original plant or the call refuses with 'ambiguous' — never a wrong plant."""
    rng = np.random.default_rng(7)
    outcomes = {"same": 0, "ambiguous": 0}
    for _ in range(300):
        J_m = 10 ** rng.uniform(-5, -2)
        J_l = J_m * 10 ** rng.uniform(-1, 1)
        K = (2 * np.pi * 60) ** 2 * J_m * J_l / (J_m + J_l)
        X = 2 * rng.uniform(1.1, 3.0) * np.sqrt(K * J_l)
        B_l = X * rng.uniform(0.0, 0.5)
        p = TwoMassParameters(J_m, J_l, X * 0.1 * rng.uniform(), B_l, K, X - B_l)
        try:
            q = from_velocity_tf(*p.velocity_tf())
        except IdentificationError as err:
            assert "ambiguous" in str(err)
            outcomes["ambiguous"] += 1
        else:
            assert_allclose(q.as_array(), p.as_array(), rtol=1e-8)
            outcomes["same"] += 1
    assert outcomes["same"] > 0
