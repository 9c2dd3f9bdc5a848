"""Family records (sim_drive.family) the identifier once got wrong or flagged, identified end to end (or, where
its start went wrong, started): each test names the member and what went wrong. Apart from test_hybrid.py so
that ``--dist loadfile`` runs them on another worker."""

from __future__ import annotations

from typing import Any

import pytest

from commission.ident.hybrid import identify


def test_motor_friction_the_first_fits_left_out_is_taken_back_where_the_record_asks_for_it() -> None:
    # family member 23:036: a load encoder, load Coulomb friction of 9 mN·m and motor friction of a tenth of
    # it. The torque-residual fit's term selection dropped the motor's; without it the estimate needed 0.8 %
    # of the torque as a disturbance (a drive's noise, not flagged) and came out J_l +3 %, K +2 %
    from sim_drive.family import Sensors, member

    m = member(23, 36)
    assert m.sensors is Sensors.LOAD_ENCODER and 0.05 < m.coulomb_motor_nm / m.coulomb_load_nm < 0.2
    res = identify(m.simulate())
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(m.two_mass, p), rel=0.01), p
    assert res.friction is not None and res.friction.get("motor_nm") == pytest.approx(m.coulomb_motor_nm, rel=0.2)


def test_a_fast_current_loop_the_fit_held_at_zero_is_found_from_a_drives_typical_one() -> None:
    # family member 25:002 recorded for 4 s: a load encoder at 2 kHz and a 2.9 kHz current loop (55 µs, a
    # tenth of a sample). The fits left the loop out and held its lag at 0, where the estimate (K +4 %) needed
    # a 16 % disturbance; without the lag the truth itself needs 10 %, with it 1 %
    import dataclasses

    from sim_drive.family import Sensors, member

    m = member(25, 2)
    m = dataclasses.replace(m, excitation=m.excitation.model_copy(update={"duration_s": 4.0}))
    assert m.sensors is Sensors.LOAD_ENCODER and m.current_loop_bandwidth_hz > m.sample_rate_hz
    res = identify(m.simulate())
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(m.two_mass, p), rel=0.01), p
    assert res.epsilon_deg == pytest.approx(m.epsilon_deg, rel=0.01)
    loop = res.to_dict().get("current_loop")
    assert loop is not None and loop["bandwidth_hz"] == pytest.approx(m.current_loop_bandwidth_hz, rel=0.2)


def test_a_load_encoders_stick_slip_is_a_disturbance_on_the_load_not_a_model_error() -> None:
    # family member 22:180: a load encoder, load Coulomb friction of 10 % of the peak torque. Where the load
    # sticks the model's smooth friction is not the simulator's: the truth is likeliest with a disturbance of
    # 0.3 % of RMS τ_ref on the motor and 3× that on the load; a noise model with at most 0.3× on the load put
    # 2.1 % on the motor and flagged an estimate within 0.1 %
    from sim_drive.family import Sensors, member

    m = member(22, 180)
    assert m.sensors is Sensors.LOAD_ENCODER and m.coulomb_load_nm > 10.0 * m.coulomb_motor_nm
    res = identify(m.simulate())
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons
    assert res.fit.process_noise_ratio is not None and res.fit.process_noise_ratio < 0.02
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(m.two_mass, p), rel=0.005), p


def test_coulomb_friction_split_wrongly_between_motor_and_load_is_split_again() -> None:
    # family member 22:186: velocity only, motor Coulomb friction of 24 mN·m and the load's of an eighth of
    # it. The sum is what the record determines; the fit ended with a third of it on the load, needed a
    # disturbance of 4.3 % of RMS τ_ref there and was flagged, J and K within 0.1 %
    from sim_drive.family import Sensors, member

    m = member(22, 186)
    assert m.sensors is Sensors.VELOCITY_ONLY and 0.1 < m.coulomb_load_nm / m.coulomb_motor_nm < 0.2
    res = identify(m.simulate())
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons
    assert res.fit.process_noise_ratio is not None and res.fit.process_noise_ratio < 0.01
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(m.two_mass, p), rel=0.01), p
    assert res.friction is not None
    assert res.friction.get("motor_nm") == pytest.approx(m.coulomb_motor_nm, rel=0.1)
    assert res.friction.get("load_nm") == pytest.approx(m.coulomb_load_nm, rel=0.3)


def _encoders_start(seed: int, index: int) -> tuple[Any, Any]:
    """The member and the encoders' start on the residual problem the hybrid pipeline prepares first."""
    import math

    from commission.ident.options import IdentificationOptions
    from commission.ident.residual import prepare_residual
    from commission.ident.start import load_encoder_start
    from sim_drive.family import Sensors, member

    m = member(seed, index)
    assert m.sensors is Sensors.LOAD_ENCODER
    rec, opt = m.simulate(), IdentificationOptions()
    problem = prepare_residual(rec.torque_ref, rec.sample_rate_hz, motor_position=rec.motor_position,
                               cutoff_hz=min(opt.residual_cutoff_hz, 0.4 * rec.sample_rate_hz),
                               load_position=rec.load_position,
                               velocity_scale_rad_s=opt.coulomb_velocity_scale_rad_s)
    return m, load_encoder_start(problem, math.radians(16.0), current_loop=True)


@pytest.mark.parametrize("seed, index", [(24, 44), (22, 2)])
def test_the_encoders_start_takes_a_current_loop_only_where_the_record_shows_one(seed: int, index: int) -> None:
    # 24:044: a 419 Hz loop under a 714 Hz chirp. Read as an ideal one, no gap gave positive K and J_l: no start,
    # the scan's J_l ×1e-3 took 1,420 s of fit, flagged. 22:002: an ideal loop and a 1.7° gap, where a lag at the
    # grid's top (3 ms) stood in for the rigid body's J/B and the start came out at ε = 0, K ×1e-3
    import math

    m, start = _encoders_start(seed, index)
    assert start is not None
    lag_s = 1.0 / (2.0 * math.pi * m.current_loop_bandwidth_hz) if m.current_loop_bandwidth_hz else 0.0
    # measured: 24:044 ε +0.001°, J_m +2 %, J_l −15 %, K −10 %, T_c −4 %; 22:002 ε +0.002°, J_m −8 %, J_l −11 %,
    # K −7 %, T_c 0
    assert math.degrees(start.epsilon_rad) == pytest.approx(m.epsilon_deg, abs=0.01)
    for p in ("J_m", "J_l", "K"):
        assert getattr(start.parameters, p) == pytest.approx(getattr(m.two_mass, p), rel=0.25), p
    assert start.lag_s == pytest.approx(lag_s, rel=0.1, abs=5e-6)
