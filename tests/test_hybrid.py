"""End-to-end identification on sim_drive's plant (motor-side data, 24-bit encoders, torque noise).

Done criteria of the issue: reference plant ε ±0.01°, J_m, J_l, K ±1 %, modes ±0.5 %;
a plant without backlash reported at ≤ 0.02°; the same within 3× on a stiff light load
(J_l/J_m = 0.2, resonance 150 Hz) and a soft heavy load (J_l/J_m = 4, resonance 25 Hz).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from commission.config import ExcitationConfig
from commission.exceptions import IdentificationError
from commission.excitation import chirp
from commission.ident.hybrid import Identification, IdentificationOptions, Method, identify
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters, modes
from commission.recording import Recording
from sim_drive.plant import Plant, PlantParameters

FS = 8000.0
J_M = 4.78e-4
PLANTS: dict[str, tuple[TwoMassParameters, float]] = {
    "reference": (REFERENCE_PLANT, 0.40),
    "no_backlash": (REFERENCE_PLANT, 0.0),
    # J_l/J_m = 0.2, K for a 150 Hz resonance (anti-resonance 137 Hz), ζ_r ≈ 0.33
    "stiff_light": (TwoMassParameters(J_m=J_M, J_l=0.2 * J_M, B_m=0.84e-2, B_l=1.0e-2,
                                      K=(2 * math.pi * 150) ** 2 * 0.2 * J_M / 1.2, D=5.0e-2), 0.25),
    # J_l/J_m = 4, K for a 25 Hz resonance (anti-resonance 11 Hz), ζ_r ≈ 0.17
    "soft_heavy": (TwoMassParameters(J_m=J_M, J_l=4 * J_M, B_m=0.84e-2, B_l=1.5e-2,
                                     K=(2 * math.pi * 25) ** 2 * 4 * J_M / 5, D=1.5e-2), 0.60),
}


def _record(params: TwoMassParameters, eps_deg: float, *, load: bool = False, position: bool = True,
            noise: float = 1e-4, duration_s: float = 10.0) -> Recording:
    tau = chirp(ExcitationConfig(duration_s=duration_s)).samples
    r = Plant(PlantParameters(**params.as_dict(), epsilon_deg=eps_deg, torque_noise_nm=noise, seed=11),
              FS).run_torque(tau)
    extra = {"motor_position": r.motor_position} if position else {}
    if load:
        extra["load_position"] = r.load_position
    return Recording.uniform(FS, r.torque_ref, r.motor_velocity, **extra)


_cache: dict[str, Identification] = {}


def _identified(name: str) -> Identification:
    if name not in _cache:
        params, eps = PLANTS[name]
        _cache[name] = identify(_record(params, eps))
    return _cache[name]


def _check(res: Identification, true: TwoMassParameters, eps_deg: float, scale: float) -> None:
    assert abs(res.epsilon_deg - eps_deg) <= max(0.01, 0.02 * eps_deg) * scale
    for name in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, name) == pytest.approx(getattr(true, name), rel=0.01 * scale), name
    mt, mi = modes(true), res.modes
    assert mi.f_resonance_hz == pytest.approx(mt.f_resonance_hz, rel=0.005 * scale)
    assert mi.f_antiresonance_hz == pytest.approx(mt.f_antiresonance_hz, rel=0.005 * scale)


@pytest.mark.parametrize("name, scale", [("stiff_light", 1.0), ("soft_heavy", 1.0)])
def test_accuracy(name: str, scale: float) -> None:
    true, eps = PLANTS[name]
    res = _identified(name)
    _check(res, true, eps, scale)
    assert res.backlash_detected
    lo, hi = res.epsilon_interval_rad
    assert lo <= math.radians(eps) <= hi


def test_a_backlash_far_beyond_the_configured_range_is_looked_for_beyond_it() -> None:
    # ε = 3° (a worn gearbox), the default scan range up to 1°: the scan's best cell lies at the
    # top and its range is doubled; the result is within the tolerances or says it is approximate
    res = identify(_record(REFERENCE_PLANT, 3.0))
    assert res.stage("scan").detail["extended_to_deg"] >= 2.0
    assert any("ε scan extended" in n for n in res.notes)
    assert res.epsilon_deg > 1.0
    try:
        _check(res, REFERENCE_PLANT, 3.0, 1.0)
    except AssertionError:
        assert res.fit is not None and res.fit.approximate
    assert _identified("reference").stage("scan").detail["extended_to_deg"] is None


def test_iterations_show_step5_getting_better() -> None:
    res = _identified("reference")
    assert len(res.iterations) == 2  # the frequency-domain start with the scan's ε, the result
    assert res.iterations[1]["frd_error"] < res.iterations[0]["frd_error"]
    assert res.iterations[1]["frd_error"] < 0.01
    assert [s.name for s in res.stages] == ["start", "scan", "fit", "kalman", "check"]
    assert all(s.seconds >= 0 for s in res.stages)


def test_result_json_has_exactly_the_documented_keys() -> None:
    res = _identified("reference")
    d = json.loads(json.dumps(res.to_dict("run.mcap")))
    assert set(d["backlash"]) >= {"epsilon_deg", "epsilon_interval_deg", "evaluations", "method"}
    assert d["backlash"]["method"] == "hybrid"
    assert isinstance(d["backlash"]["evaluations"], int)
    assert set(d["two_mass"]) == {"J_m", "J_l", "B_m", "B_l", "K", "D"}
    assert set(d["modes"]) == {"f_resonance_hz", "zeta_resonance", "f_antiresonance_hz", "zeta_antiresonance"}
    assert len(d["transfer_function"]["num"]) == 3 and len(d["transfer_function"]["den"]) == 4
    assert all(set(it) == {"frd_error", "epsilon_deg"} for it in d["iterations"])
    assert d["source"] == {"file": "run.mcap", "sample_rate_hz": FS, "samples": 80000}
    assert set(d["fit"]) == {"residual_ratio", "noise_floor_ratio", "spectral_flatness", "window_rms_p90_over_median",
                             "noise_limited", "approximate", "reasons", "cutoff_hz", "observer_bandwidth_hz",
                             "effective_samples", "converged", "interval_scale", "determined", "model_error",
                             "innovation_rms", "process_noise_ratio", "remedies"}
    assert set(d["two_mass_interval"]) == set(d["two_mass"]) == set(d["two_mass_relative_stderr"])
    lo, hi = d["measured_band_hz"]
    assert 0 < lo < 1.0 and 300.0 < hi <= 420.0  # the chirp's 0.1–400 Hz, to the bins' edge


def test_a_load_encoder_the_options_turn_off_is_not_used() -> None:
    # (velocity-only and load-encoder records are identified within the tolerances: test_identify)
    true, eps = PLANTS["reference"]
    ignored = identify(_record(true, eps, load=True), IdentificationOptions(use_load_encoder=False))
    assert not any("load encoder" in n for n in ignored.notes)
    assert ignored.stage("start").detail["load_encoder"] is False
    _check(ignored, true, eps, 1.0)


def test_the_encoders_start_reads_the_plant_off_both_encoders_with_any_number_of_threads() -> None:
    from commission.ident.residual import prepare_residual
    from commission.ident.start import load_encoder_start

    true, eps = PLANTS["reference"]
    rec = _record(true, eps, load=True)
    problem = prepare_residual(rec.torque_ref, FS, motor_position=rec.motor_position, cutoff_hz=1000.0,
                               load_position=rec.load_position)
    one, two = (load_encoder_start(problem, math.radians(3.0), threads=n) for n in (1, 2))
    assert one is not None and one == two
    # a start (noise in the twist biases the dampings), but on this clean record ε, the inertias and the
    # stiffness within the family's tolerances (measured: −0.003°, −0.02 %, −0.07 %, −0.18 %)
    assert math.degrees(one.epsilon_rad) == pytest.approx(eps, abs=0.01)
    for name in ("J_m", "J_l", "K"):
        assert getattr(one.parameters, name) == pytest.approx(getattr(true, name), rel=0.01), name


@pytest.mark.parametrize("loop_hz", [150.0, None])
def test_the_encoders_start_reads_a_slow_current_loop_with_the_plant(loop_hz: float | None) -> None:
    # τ_ref stands in for τ only behind an ideal loop: at 150 Hz, read as one, the start's J_l and K came out
    # 38 % and 28 % low (on 24:044, a 419 Hz loop under a 714 Hz chirp, negative: no start, a 1,700 s fit)
    from commission.ident.residual import prepare_residual
    from commission.ident.start import load_encoder_start

    true, eps = PLANTS["reference"]
    tau = chirp(ExcitationConfig(duration_s=5.0)).samples
    r = Plant(PlantParameters(**true.as_dict(), epsilon_deg=eps, torque_noise_nm=1e-4, seed=11,
                              current_loop_bandwidth_hz=loop_hz), FS).run_torque(tau)
    problem = prepare_residual(r.torque_ref, FS, motor_position=r.motor_position, cutoff_hz=1000.0,
                               load_position=r.load_position)
    start = load_encoder_start(problem, math.radians(3.0), current_loop=True)
    assert start is not None
    # measured: ε −0.003°, J_m, J_l, K within 1.4 %, T_c +2 % (150 Hz) and 0 (ideal)
    assert math.degrees(start.epsilon_rad) == pytest.approx(eps, abs=0.01)
    for name in ("J_m", "J_l", "K"):
        assert getattr(start.parameters, name) == pytest.approx(getattr(true, name), rel=0.03), name
    lag_s = 1.0 / (2.0 * math.pi * loop_hz) if loop_hz else 0.0
    assert start.lag_s == pytest.approx(lag_s, rel=0.05, abs=5e-6)


@pytest.mark.parametrize("offset_rad", [0.0, math.radians(0.05), -math.radians(0.3), 5.0])
def test_the_load_encoders_own_origin_is_found_from_both_encoders(offset_rad: float) -> None:
    # a load encoder's zero is its own: the twist the model reads is x_m − x_l from a common origin, the
    # gap's middle; the simulator's encoders share that origin, a real axis's do not
    from commission.ident.residual import prepare_residual
    from commission.ident.start import load_encoder_start, load_origin_rad

    true, eps = PLANTS["reference"]
    rec = _record(true, eps, load=True, duration_s=3.0)
    problem = prepare_residual(rec.torque_ref, FS, motor_position=rec.motor_position, cutoff_hz=300.0,
                               load_position=rec.load_position + offset_rad)
    shift = load_origin_rad(problem, load_encoder_start(problem, math.radians(16.0)))
    if offset_rad == 0.0:
        assert shift == 0.0  # a centred gap is left as it is
    else:
        assert math.degrees(shift + offset_rad) == pytest.approx(0.0, abs=1e-4)


def test_a_load_encoder_with_its_own_zero_replays_to_the_plant(tmp_path) -> None:
    # 286° between the encoders' zeros: the start found no plant and the fit ran for minutes
    from commission.cli import main
    from commission.csvlog import write_csv

    true, eps = PLANTS["reference"]
    rec = _record(true, eps, load=True, duration_s=3.0)
    write_csv(tmp_path / "dual.csv", rec.replace(load_position=rec.load_position + 5.0))
    assert main(["--replay", str(tmp_path / "dual.csv"), "--out", str(tmp_path / "o"), "--no-tune"]) == 0
    doc = json.loads((tmp_path / "o" / "result.json").read_text())
    assert any(n.startswith("the load encoder's origin lies 286.479° from the motor's") for n in doc["notes"])
    assert doc["fit"]["approximate"] is False
    assert doc["backlash"]["epsilon_deg"] == pytest.approx(eps, abs=0.01)
    for name in ("J_m", "J_l", "K"):
        assert doc["two_mass"][name] == pytest.approx(getattr(true, name), rel=0.02), name


def test_paper_method_runs_end_to_end() -> None:
    true, eps = PLANTS["reference"]
    res = identify(_record(true, eps), IdentificationOptions(method=Method.PAPER, max_iterations=2))
    assert res.method is Method.PAPER
    d = res.to_dict()
    assert d["backlash"]["method"] == "paper"
    assert 1 <= len(d["iterations"]) <= 2
    assert 0.0 <= res.epsilon_deg <= 1.0


# --------------------------------------------------------------------------- bad input
def _ref_arrays():
    true, eps = PLANTS["reference"]
    return _record(true, eps)


def test_a_record_with_nothing_to_identify_is_one_clear_error() -> None:
    rec = _ref_arrays().head(50)
    with pytest.raises(IdentificationError, match="too short"):
        identify(rec)


def test_band_above_nyquist() -> None:
    with pytest.raises(IdentificationError, match="Nyquist"):
        identify(_ref_arrays(), IdentificationOptions(band_hz=(0.1, 5000.0)))


def test_flat_signals() -> None:
    rec = _ref_arrays()
    with pytest.raises(IdentificationError, match="constant"):
        identify(rec.replace(torque_ref=np.zeros(len(rec))))
    with pytest.raises(IdentificationError, match="constant|did not move"):
        identify(rec.replace(motor_velocity=np.zeros(len(rec)), motor_position=np.zeros(len(rec))))


def test_saturated_velocity() -> None:
    rec = _ref_arrays()
    v = np.clip(rec.motor_velocity, -5.0, 5.0)
    with pytest.raises(IdentificationError, match="saturated|clipped"):
        identify(rec.replace(motor_velocity=v, motor_position=None))


def test_likelihood_ratios_past_a_floats_range_are_written_as_powers_of_ten() -> None:
    """A record no model explains (a random-walk velocity beside a drive with 3 samples of delay) moved its
    likelihood by ~1500 e-folds per sample between two delays: the note's exp() overflowed and the whole
    identification ended in OverflowError instead of a flagged result."""
    from commission.ident.hybrid import _likelier

    assert _likelier(11439.6, 9573.4) == "10^405"
    assert _likelier(2.0, 1.0) == f"{math.exp(0.5):.3g}"
    assert _likelier(math.inf, 1.0) == "∞"


def test_options_are_validated() -> None:
    with pytest.raises(ValueError):
        IdentificationOptions(band_hz=(400.0, 0.1))
    with pytest.raises(ValueError):
        IdentificationOptions(epsilon_bounds_deg=(1.0, 0.5))
    with pytest.raises(ValueError):
        IdentificationOptions(unknown=1)  # type: ignore[call-arg]
    with pytest.raises(ValueError):
        IdentificationOptions(resolution_hz=0.0)


def _heavy_friction(f_nm: float, duration_s: float = 10.0) -> Recording:
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.40, torque_noise_nm=1e-4, seed=3,
                              coulomb_motor_nm=f_nm, coulomb_load_nm=f_nm),
              FS).run_torque(chirp(ExcitationConfig(duration_s=duration_s)).samples)
    return Recording.uniform(FS, r.torque_ref, r.motor_velocity, motor_position=r.motor_position)


def test_heavy_friction_gives_a_physical_start_without_overflow():
    # 0.05 N·m of Coulomb friction per side (17 % of the chirp's peak torque): the physical refit
    # of the whole band used to drive its log-parameters to overflow (inf, then NaN into LAPACK and
    # "no physical refit"); RuntimeWarnings are errors here
    import warnings

    from commission.ident.residual import prepare_residual
    from commission.ident.start import frequency_start

    rec = _heavy_friction(0.05)
    notes: list[str] = []
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        problem = prepare_residual(rec.torque_ref, FS, motor_position=rec.motor_position, cutoff_hz=400.0)
        start = frequency_start(rec, problem, band_hz=(0.1, 400.0), resolution_hz=0.1, quality_threshold=0.9,
                                fit_delay=True, notes=notes).parameters
    # a rough but physical start; the estimator takes it from there
    assert min(start.as_array()) > 0
    assert 1 / 3 < start.J_m / REFERENCE_PLANT.J_m < 3 and 1 / 3 < start.K / REFERENCE_PLANT.K < 3


def test_friction_of_a_quarter_of_the_peak_torque_gives_a_result_in_one_piece():
    # 0.08 N·m per side, a quarter of the peak torque: a result, every number finite. On 2 s of the chirp the
    # friction holds the motor in the lowest band, whose apparent inertia is then negative, and no rational fit
    # gives a plant: the start is read off the top of the band, and the result is flagged (it used to be an
    # error with nothing written). On 10 s it is identified within the tolerances, not flagged
    res = identify(_heavy_friction(0.08, duration_s=2.0))
    assert res.fit is not None and res.fit.approximate
    assert any("never crosses the gap" in r for r in res.fit.reasons), res.fit.reasons
    d = json.loads(json.dumps(res.to_dict()))
    assert all(math.isfinite(v) for v in d["two_mass"].values())
    assert isinstance(d["fit"]["approximate"], bool)


def test_the_load_friction_a_load_encoder_shows_is_fitted() -> None:
    # family member 22:171: a light load (J_l/J_m 0.11) with Coulomb friction of 0.8 % of the peak torque
    # on its side, a 17-bit load encoder. The encoders' start shows the friction; left out of the fits it
    # biased ε by +0.023° (7 %) behind a tight interval that missed the truth, not flagged
    from sim_drive.family import DEFAULT_SEED, Sensors, member

    m = member(DEFAULT_SEED, 171)
    assert m.sensors is Sensors.LOAD_ENCODER and m.coulomb_load_nm > 0.005 * m.peak_torque_nm
    res = identify(m.simulate())
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons if res.fit else None
    assert abs(res.epsilon_deg - m.epsilon_deg) <= 0.01
    lo, hi = (math.degrees(x) for x in res.epsilon_interval_rad)
    assert lo <= m.epsilon_deg <= hi
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(m.two_mass, p), rel=0.02), p
    assert res.friction is not None and res.friction["load_nm"] == pytest.approx(m.coulomb_load_nm, rel=0.25)


@pytest.mark.parametrize(("ratio", "f_r"), [(0.1, 30.0), (1.0, 150.0), (10.0, 350.0)])
def test_the_last_start_reads_a_two_mass_plant_off_its_apparent_inertia(ratio: float, f_r: float) -> None:
    # the start for an FRD no rational fit and no peak/dip pair place: on the analytic FRD of a plant
    # whose parameters were chosen, inertias within 25 % and the resonance within 15 %
    from commission.ident.frd import FRD
    from commission.ident.start import inertia_start
    from conftest import two_mass_plant

    p = two_mass_plant(ratio, f_r, 0.08)
    f = np.arange(1, int(2.5 * f_r / 0.1) + 1) * 0.1
    num, den = p.velocity_tf()
    g = np.polyval(num, 2j * np.pi * f) / np.polyval(den, 2j * np.pi * f)
    q = inertia_start(FRD(f, g, np.ones(f.size), np.ones(f.size, complex), g, 8000.0, 0.1), 2000.0)
    assert q is not None
    assert q.J_m == pytest.approx(p.J_m, rel=0.25)
    assert q.J_l == pytest.approx(p.J_l, rel=0.25)
    assert modes(q).f_resonance_hz == pytest.approx(f_r, rel=0.15)
    # friction that holds the motor in the lowest band turns its apparent inertia negative there: the top's
    # inertia is taken for each side, a physical start with the resonance in the band
    held = g.copy()
    held[: f.size // 20] = np.conj(g[: f.size // 20])
    q = inertia_start(FRD(f, held, np.ones(f.size), np.ones(f.size, complex), held, 8000.0, 0.1), 2000.0)
    assert q is not None and min(q.as_array()) > 0
    assert q.J_m == pytest.approx(p.J_m, rel=0.25) and q.J_l == q.J_m
    assert f[0] < modes(q).f_resonance_hz < f[-1]
    # a response with no inertia in it (a pure damper) gives no start
    flat = np.full(f.size, 2.0 + 0j)
    assert inertia_start(FRD(f, flat, np.ones(f.size), np.ones(f.size, complex), flat, 8000.0, 0.1), 2000.0) is None


def test_a_start_the_gap_softened_is_made_stiffer_until_the_record_is_likeliest() -> None:
    # family member 22:022: a 0.85° gap on a heavy load (J_l/J_m 3.1), Coulomb friction of 5 % of the peak
    # torque, velocity only. The gap softens the spring the frequency response sees: the start's stiffness
    # is half the plant's, outside the Kalman fit's basin; from a stiffer start the plant is found
    from sim_drive.family import DEFAULT_SEED, member

    m = member(DEFAULT_SEED, 22)
    res = identify(m.simulate())
    start_k = res.stage("start").detail["parameters"]["K"]
    assert start_k < 0.7 * m.two_mass.K
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons if res.fit else None
    assert res.epsilon_deg == pytest.approx(m.epsilon_deg, rel=0.02)
    lo, hi = (math.degrees(x) for x in res.epsilon_interval_rad)
    assert lo <= m.epsilon_deg <= hi
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(m.two_mass, p), rel=0.02), p
