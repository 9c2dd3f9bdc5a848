"""The default (hybrid) identifier on machines that are not the paper's ideal model (issue 8).

sim_drive's plant plays the machine (its own smooth-sign Coulomb friction, its own current-loop
lag, its own event location); the identifier's terms are written independently in
commission.ident.residual / jointfit. Motor-side data only, 24-bit encoders, torque noise.
Done criteria: ε within ±0.02°, J_m, J_l, K within 3 %, resonance and anti-resonance within
1 %; on the ideal plant no extra term is kept. Each plant is simulated and identified once.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from commission.config import ExcitationConfig
from commission.excitation import chirp
from commission.ident.hybrid import Identification, IdentificationOptions, identify
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters, modes
from commission.recording import Recording
from sim_drive.plant import Plant, PlantParameters

FS = 8000.0
#: reference inertias and stiffness, shaft damping lowered to ζ_r = 0.070
LIGHTLY_DAMPED = TwoMassParameters(**{**REFERENCE_PLANT.as_dict(), "D": 0.0045})
CASES: dict[str, tuple[TwoMassParameters, dict]] = {
    "ideal": (REFERENCE_PLANT, dict(epsilon_deg=0.40)),
    "coulomb": (REFERENCE_PLANT, dict(epsilon_deg=0.40, coulomb_motor_nm=0.01, coulomb_load_nm=0.01)),
    "current_loop": (REFERENCE_PLANT, dict(epsilon_deg=0.40, current_loop_bandwidth_hz=1000.0,
                                           torque_noise_nm=1e-3)),
    "lightly_damped": (LIGHTLY_DAMPED, dict(epsilon_deg=0.25)),
    # the noise seed on which least squares throughout ended 0.041° off (issue 8, session notes)
    "lightly_damped_seed9": (LIGHTLY_DAMPED, dict(epsilon_deg=0.25, seed=9)),
    # a seed on which the first pass ends at a wrong ε, the ε scans after its Cauchy-loss starts
    # included, and the second pass is taken
    "lightly_damped_seed8": (LIGHTLY_DAMPED, dict(epsilon_deg=0.25, seed=8)),
    # 3× the friction: the load simulation's smooth sign is then 33× stiffer than the
    # sample rate (widening v_s instead had biased ε by 0.025°)
    "coulomb_strong": (REFERENCE_PLANT, dict(epsilon_deg=0.40, coulomb_motor_nm=0.03, coulomb_load_nm=0.03)),
    # bench/bench_identify.py "stiff light 200Hz": J_l/J_m = 0.2, 200 Hz, ζ 0.12 — chaotic impacts
    # the model does not reproduce (K comes out ~30 % low)
    # bench "stiff light 150Hz" with a 1 kHz current loop: the fixed-delay frequency-domain fit
    # gave an "exact" start with K/J_l = 1.9e16 s⁻² and NaN reached LAPACK (LinAlgError)
    "light_current_loop": (TwoMassParameters(J_m=4.78e-4, J_l=0.956e-4, B_m=0.84e-2, B_l=1.0e-2,
                                             K=70.77, D=0.04956),
                           dict(epsilon_deg=0.25, current_loop_bandwidth_hz=1000.0)),
    # the same light, stiff load with 0.01 N·m of Coulomb friction per side: every frequency-domain
    # fit from 10 Hz down gave K ≈ 0.3–0.8 for 71 and the result was K off ×100 (the 20 Hz edge)
    "light_coulomb": (TwoMassParameters(J_m=4.78e-4, J_l=0.956e-4, B_m=0.84e-2, B_l=1.0e-2, K=70.77,
                                        D=0.04956),
                      dict(epsilon_deg=0.25, coulomb_motor_nm=0.01, coulomb_load_nm=0.01)),
    # 100 Hz, J_l = J_m, ζ 0.05 (K, D, B_l exactly as bench_identify.py derives them): at the true
    # parameters the residual is 29 % of τ_ref (the load re-simulated through its impacts
    # decorrelates); the fit explains the rest by dropping 29 %. The outcome on such a plant
    # depends on the fit's path: with B_l, K, D rounded to 4 digits it drops 18.5 % instead
    "lightly_damped_100hz": (TwoMassParameters(J_m=4.78e-4, J_l=4.78e-4, B_m=0.84e-2,
                                               B_l=0.53e-2 * math.sqrt(2.5),
                                               K=(2 * math.pi * 100) ** 2 * 4.78e-4 / 2,
                                               D=0.05 * 2 * math.pi * 100 * 4.78e-4),
                             dict(epsilon_deg=0.20, seed=3)),
    # 100 Hz, J_l = J_m, ζ 0.1, ε 0.15° (bench_identify's derivation): at the true parameters 0.65 %
    # of τ_ref is left; the fit explains the 83 % it keeps at the noise floor but leaves 4 % over
    # all samples (its ε: 0.16°, 0.41° on another path — the impacts make it a matter of luck)
    "lightly_damped_100hz_zeta01": (TwoMassParameters(J_m=4.78e-4, J_l=4.78e-4, B_m=0.84e-2,
                                                      B_l=0.53e-2 * math.sqrt(2.5),
                                                      K=(2 * math.pi * 100) ** 2 * 4.78e-4 / 2,
                                                      D=0.1 * 2 * math.pi * 100 * 4.78e-4),
                                    dict(epsilon_deg=0.15, seed=5)),
    # J_l/J_m = 2, 60 Hz, ζ 0.07 (bench_identify's derivation): at the true parameters the plain
    # residual leaves 17 % of τ_ref; on this seed the plain fit ends with B_m < 0
    "lightly_damped_60hz_ratio2": (TwoMassParameters(J_m=4.78e-4, J_l=2 * 4.78e-4, B_m=0.84e-2,
                                                     B_l=0.53e-2 * math.sqrt(5.0),
                                                     K=(2 * math.pi * 60) ** 2 * 2 * 4.78e-4 / 3,
                                                     D=2 * 0.07 * 2 * math.pi * 60 / (1 / 4.78e-4 + 1 / (2 * 4.78e-4))),
                                   dict(epsilon_deg=0.30, seed=7)),
    # 30× the torque noise of the other cases: the residual at the true parameters is 0.5 % of
    # τ_ref, over the approximate rule's level, and it is white noise
    "noisy": (REFERENCE_PLANT, dict(epsilon_deg=0.40, torque_noise_nm=3e-3, seed=5)),
    # a 17-bit motor encoder (the 24-bit default elsewhere): at the 400 Hz low-pass its
    # quantization leaves 3 % of τ_ref, and the ζ 0.07 plant's fit ended with ε +0.10°, J, K 8 % off
    "coarse_encoder": (LIGHTLY_DAMPED, dict(epsilon_deg=0.25, seed=5, encoder_bits_motor=17)),
    # bench "stiff 300Hz" (J_l/J_m 2, ζ 0.15): chaotic impacts no predictor gain follows
    "stiff_300hz": (TwoMassParameters(J_m=4.78e-4, J_l=2 * 4.78e-4, B_m=0.84e-2, B_l=0.53e-2 * math.sqrt(5.0),
                                      K=(2 * math.pi * 300) ** 2 * 2 * 4.78e-4 / 3,
                                      D=2 * 0.15 * 2 * math.pi * 300 / (1 / 4.78e-4 + 1 / (2 * 4.78e-4))),
                    dict(epsilon_deg=0.50, seed=7)),
    # small friction on the load only: below the search's Coulomb limit, so screened at first
    "small_load_coulomb": (REFERENCE_PLANT, dict(epsilon_deg=0.40, coulomb_load_nm=0.002)),
    "impact_rich": (TwoMassParameters(J_m=4.78e-4, J_l=0.956e-4, B_m=0.84e-2, B_l=0.3e-2, K=125.8,
                                      D=0.0220), dict(epsilon_deg=0.25)),
}
_cache: dict[tuple[str, bool], Identification] = {}


def _recording(name: str) -> Recording:
    params, extra = CASES[name]
    kw = dict(torque_noise_nm=1e-4, seed=11)
    kw.update(extra)
    r = Plant(PlantParameters(**params.as_dict(), **kw), FS).run_torque(chirp(ExcitationConfig()).samples)
    return Recording.uniform(FS, r.torque_ref, r.motor_velocity, motor_position=r.motor_position)


def _identified(name: str, predictor: bool = True) -> Identification:
    """The plant identified with the default options (``predictor``: the predictor refit of
    approximate results; off to see the approximate rules themselves)."""
    if (name, predictor) not in _cache:
        _cache[name, predictor] = identify(_recording(name), IdentificationOptions(predictor_refit=predictor))
    return _cache[name, predictor]


def test_lightly_damped_plant_has_the_stated_damping() -> None:
    assert modes(LIGHTLY_DAMPED).zeta_resonance == pytest.approx(0.07, abs=0.002)
    m = modes(CASES["impact_rich"][0])
    assert m.f_resonance_hz == pytest.approx(200.0, rel=0.01)
    assert m.zeta_resonance == pytest.approx(0.12, abs=0.01)  # D for 0.11, B_m and B_l add the rest


@pytest.mark.parametrize("name", ["coulomb", "current_loop", "lightly_damped", "lightly_damped_seed9",
                                  "lightly_damped_seed8", "coulomb_strong", "light_current_loop",
                                  "light_coulomb"])
def test_accuracy_under_unideal_effects(name: str) -> None:
    _assert_done_criteria(_identified(name), name)


def _model_fit_row(identification: dict) -> str:
    """The CLI summary's "model fit" row for a result.json identification section."""
    from commission.cli import _rows

    rec = {"samples": 80000, "sample_rate_hz": FS, "duration_s": 10.0, "signals": ["torque_ref"],
           "peak_torque_nm": 0.3, "peak_motor_velocity_rad_s": 17.0, "status": "complete"}
    return dict(_rows({"files": [], "source": "sim", "recording": rec, "identification": identification}))["model fit"]


def _assert_done_criteria(res: Identification, name: str) -> None:
    """The issue's tolerances: ε ±0.02°, J_m, J_l, K 3 %, resonance and anti-resonance 1 %."""
    true, extra = CASES[name]
    assert abs(res.epsilon_deg - extra["epsilon_deg"]) <= 0.02
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(true, p), rel=0.03), p
    mt, mi = modes(true), res.modes
    assert mi.f_resonance_hz == pytest.approx(mt.f_resonance_hz, rel=0.01)
    assert mi.f_antiresonance_hz == pytest.approx(mt.f_antiresonance_hz, rel=0.01)


def test_coulomb_friction_is_kept_with_values_and_intervals() -> None:
    d = json.loads(json.dumps(_identified("coulomb").to_dict()))
    f = d["friction"]
    assert f["velocity_scale_rad_s"] > 0
    for side in ("motor", "load"):
        assert f[f"{side}_nm"] == pytest.approx(0.01, rel=0.1)
        lo, hi = f[f"{side}_interval_nm"]
        assert lo <= f[f"{side}_nm"] <= hi
    assert "current_loop" not in d
    assert d["model_selection"]["terms"]["coulomb_motor"]["kept"]


def test_load_friction_is_fitted_only_when_the_search_finds_friction() -> None:
    # ideal plant: the search's Coulomb column is far below its limit, so the load term is not a
    # candidate of the joint fit (and said so); with friction it is fitted and kept
    sel = _identified("ideal").to_dict()["model_selection"]
    s = sel["screened_by_search"]["coulomb_load"]
    assert abs(s["search_coulomb_nm"]) < 0.2 * s["limit_nm"]
    assert "coulomb_load" not in sel["terms"]
    sel = _identified("coulomb").to_dict()["model_selection"]
    assert "screened_by_search" not in sel
    assert sel["terms"]["coulomb_load"]["kept"]


def test_small_load_friction_screened_by_the_search_is_fitted_on_its_side() -> None:
    # 0.002 N·m on the load only: the search's column stays under its limit, the fit then keeps
    # a motor Coulomb term, and the load term is reconsidered (without: reported as motor
    # friction, ε 0.003–0.007° and J, K 0.2 % off)
    res = _identified("small_load_coulomb")
    d = res.to_dict()
    assert d["model_selection"]["screened_by_search"]["coulomb_load"]["reconsidered"] is True
    assert d["friction"]["load_nm"] == pytest.approx(0.002, rel=0.05) and "motor_nm" not in d["friction"]
    assert abs(res.epsilon_deg - 0.40) <= 0.002
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(REFERENCE_PLANT, p), rel=0.002), p


def test_current_loop_is_kept_with_its_bandwidth() -> None:
    d = _identified("current_loop").to_dict()
    c = d["current_loop"]
    assert c["bandwidth_hz"] == pytest.approx(1000.0, rel=0.05)
    lo, hi = c["bandwidth_interval_hz"]
    assert lo <= c["bandwidth_hz"] <= hi
    assert "friction" not in d


def test_step5_check_models_the_kept_current_loop() -> None:
    """Step 5's open-loop simulation gets the kept lag: its FRD matches the measured one as well
    as on the ideal plant (within noise), instead of the lag's phase showing as model error;
    the frequency-domain step 6 (which has no lag term) is skipped, and said to be."""
    res = _identified("current_loop")
    assert res.iterations[-1]["frd_error"] < 0.02
    assert res.iterations[-1]["frd_error"] < 0.2 * res.iterations[0]["frd_error"]
    assert any("step 6 check skipped" in n for n in res.notes)


def test_ideal_plant_keeps_no_extra_term() -> None:
    res = _identified("ideal")
    d = res.to_dict()
    assert "friction" not in d and "current_loop" not in d
    assert not any(t["kept"] for t in d["model_selection"]["terms"].values())
    assert abs(res.epsilon_deg - 0.40) <= 0.01
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(REFERENCE_PLANT, p), rel=0.01), p


def test_windows_the_model_cannot_reproduce_are_said_in_the_notes() -> None:
    res = _identified("coulomb")
    dropped = res.stage("joint").detail["dropped_fraction"]
    if dropped > 0:
        assert any("dropped" in n for n in res.notes)
    assert math.isfinite(res.stage("joint").detail["residual_ratio"])


def test_a_start_stuck_on_an_impact_plateau_is_refitted_with_a_robust_loss_and_said() -> None:
    # the lightly damped plant's first least-squares start ends ~20× above the stop cost with
    # chaotic bursts in its residual; the ideal plant's converges and stays least squares
    res = _identified("lightly_damped")
    assert res.stage("joint").detail["robust_loss"] is True
    assert any("Cauchy loss" in n for n in res.notes)
    ideal = _identified("ideal")
    assert ideal.stage("joint").detail["robust_loss"] is False
    assert not any("Cauchy loss" in n for n in ideal.notes)


def test_an_epsilon_left_in_a_neighbouring_minimum_by_the_robust_start_is_scanned_again() -> None:
    # on this noise seed the first Cauchy-loss start gets the load rates right but ends at
    # ε ≈ 0.33°; the ε scan at its other parameters ranks the true ε's cell first, and the next
    # start reaches ε without a second pass
    res = _identified("lightly_damped")
    d = res.stage("joint").detail
    e_end, e_cell = d["rescan_epsilon_deg"]
    assert abs(e_end - 0.25) > 0.05
    assert abs(e_cell - 0.25) <= 0.025
    assert d["second_pass"] is None and d["dropped_fraction"] == 0.0
    assert abs(res.epsilon_deg - 0.25) <= 0.002
    assert any("ε scanned at its other parameters" in n for n in res.notes)
    assert _identified("ideal").stage("joint").detail["rescan_epsilon_deg"] is None


def test_an_impact_rich_plant_is_reported_as_approximate() -> None:
    # the plain fit's rules (the predictor refit, on by default, refines this plant: below)
    d = _identified("impact_rich", predictor=False).to_dict()
    assert d["fit"]["residual_ratio"] > 0.005 and d["fit"]["approximate"] is True
    assert any(n.startswith("approximate result") for n in d["notes"])
    ideal = _identified("ideal").to_dict()
    assert ideal["fit"]["residual_ratio"] < 0.001 and ideal["fit"]["approximate"] is False
    assert not any(n.startswith("approximate result") for n in ideal["notes"])
    assert all(s.name != "predictor" for s in _identified("ideal").stages)  # only for approximate results


def test_a_stiff_light_impact_rich_plant_is_refined_with_the_higher_predictor_gain() -> None:
    # J_l/J_m 0.2, 200 Hz: the plain fit ends with K ~29 % low and ε 0.01° for 0.25°; at the default
    # gain the predictor refit leaves 1.3 %, at the higher gain (from the widest near-best ε cell,
    # the scan at the plain rates being flat) 0.15 %
    res = _identified("impact_rich")
    _assert_done_criteria(res, "impact_rich")
    pred = res.stage("predictor").detail
    assert pred["taken"] is True and pred["gain"] > pred["default_gain"]["gain"]
    assert pred["default_gain"]["taken"] is False and pred["default_gain"]["residual_ratio"] > 0.005
    fit = res.to_dict()["fit"]
    assert fit["refined_by_predictor"] is True and fit["approximate"] is False and fit["residual_ratio"] < 0.0025
    assert any("(gain 0.5)" in n for n in res.notes)


def test_a_plant_the_predictor_cannot_follow_stays_approximate() -> None:
    # J_l/J_m 2, 300 Hz: ~2000 impacts in 10 s; neither gain reaches its level. The plain fit
    # leaves 17 %: over the default limit (an error), so the limit is raised to see the result
    res = identify(_recording("stiff_300hz"), IdentificationOptions(max_residual_ratio=0.5))
    pred = res.stage("predictor").detail
    assert pred["taken"] is False and pred["default_gain"]["taken"] is False
    assert pred["residual_ratio"] > 0.0025 and pred["default_gain"]["residual_ratio"] > 0.001
    fit = res.to_dict()["fit"]
    assert fit["approximate"] is True and fit["refined_by_predictor"] is False
    assert any(n.startswith("approximate result") for n in res.notes)
    assert any("with the gain 0.5" in n and "not taken" in n for n in res.notes)


@pytest.mark.parametrize("name", ["lightly_damped_100hz", "lightly_damped_100hz_zeta01"])
def test_a_load_state_predictor_refines_lightly_damped_plants_the_plain_fit_cannot_follow(name: str) -> None:
    # 100 Hz, J_l = J_m, ζ 0.05 / 0.1: the plain fit ends with ε 0.26° / 0.01–0.26° off, flagged
    # approximate (the tests above); corrected from the motor equation after every sample, the
    # simulated load follows the real one through the impacts and the refit ends at the noise floor
    plain, res = _identified(name, predictor=False), _identified(name)
    assert plain.to_dict()["fit"]["approximate"] is True
    _assert_done_criteria(res, name)
    fit = res.to_dict()["fit"]
    assert fit["approximate"] is False and fit["refined_by_predictor"] is True
    assert fit["residual_ratio"] < 0.001 and fit["dropped_fraction"] == 0.0
    assert res.stage("predictor").detail["taken"] is True
    assert any(n.startswith("result refined with a load-state predictor") for n in res.notes)
    assert not any(n.startswith("approximate result") for n in res.notes)
    assert any(n.startswith("plain fit (before the predictor refit) approximate") for n in res.notes)
    lo, hi = res.epsilon_interval_rad
    assert lo <= res.epsilon_rad <= hi and hi - lo < math.radians(0.02)


def test_a_plain_fit_that_ends_on_no_physical_plant_is_refined_by_the_predictor() -> None:
    from commission.exceptions import IdentificationError

    with pytest.raises(IdentificationError, match="no physical plant"):
        _identified("lightly_damped_60hz_ratio2", predictor=False)
    res = _identified("lightly_damped_60hz_ratio2")
    _assert_done_criteria(res, "lightly_damped_60hz_ratio2")
    assert min(res.parameters.B_m, res.parameters.B_l, res.parameters.D) > 0
    assert res.to_dict()["fit"]["refined_by_predictor"] is True


def test_a_fit_that_leaves_its_dropped_windows_unexplained_is_refined_though_not_flagged() -> None:
    # ζ 0.07, seed 9: the plain fit keeps 84 % of the record at the noise floor and passes the
    # approximate rules, but leaves ~1.2 % over all samples and ε ~0.015° low
    res = _identified("lightly_damped_seed9")
    stage = res.stage("predictor").detail
    assert stage["trigger"].startswith("the fit explained the samples it kept but left")
    assert stage["taken"] is True and abs(stage["plain_epsilon_deg"] - 0.25) > 0.005
    fit = res.to_dict()["fit"]
    assert fit["refined_by_predictor"] is True and fit["dropped_fraction"] == 0.0
    assert abs(res.epsilon_deg - 0.25) < 0.002
    _assert_done_criteria(res, "lightly_damped_seed9")
    # the plain fit's dropped windows are said as the plain fit's
    assert any(n.startswith("plain fit (before the predictor refit): ") and "dropped" in n for n in res.notes)
    # results with friction terms are not refined this way (the predictor models none)
    assert all(s.name != "predictor" for s in _identified("coulomb").stages)


def test_a_residual_that_is_white_noise_does_not_make_the_result_approximate() -> None:
    from commission.tuning.design import TuningOptions, design

    res = _identified("noisy")
    _assert_done_criteria(res, "noisy")
    fit = res.to_dict()["fit"]
    # over 5× the good-fit level (0.1 %), which alone would flag it
    assert fit["residual_ratio"] > 5 * IdentificationOptions().good_fit_ratio
    assert fit["approximate"] is False and fit["noise_limited"] is True
    white = res.stage("joint").detail["residual_whiteness"]
    assert white["spectral_flatness"] > 0.95 and white["window_rms_p90_over_median"] < 1.3
    assert any("white" in n and "not flagged approximate" in n for n in res.notes)
    assert all(s.name != "predictor" for s in res.stages)
    row = _model_fit_row(res.to_dict())
    assert "white torque noise" in row and "APPROXIMATE" not in row
    # ... and the tuning trusts its ε although the residual is over its own gate (0.5 %)
    assert fit["residual_ratio"] > TuningOptions().backlash_max_residual_ratio
    s = design(res, TuningOptions())
    assert s.backlash.enabled and s.backlash.amount_rad == pytest.approx(2 * res.epsilon_rad)
    assert any("white torque noise" in n for n in s.notes)
    # the impact-rich plant's plain residual is neither: it is flagged
    bursts = _identified("impact_rich", predictor=False)
    w = bursts.stage("joint").detail["residual_whiteness"]
    assert w["spectral_flatness"] < 0.95 and w["window_rms_p90_over_median"] > 1.3
    assert bursts.to_dict()["fit"]["noise_limited"] is False


def test_the_quantization_floor_matches_quantization_noise_through_the_residual() -> None:
    from commission.ident.hybrid import _quantization_floor_nm
    from commission.ident.residual import prepare_residual

    step = 2 * math.pi / 2 ** 17
    noise = np.random.default_rng(1).uniform(-step / 2, step / 2, 80000)
    for fc in (400.0, 150.0):
        pr = prepare_residual(np.zeros(noise.size), FS, motor_position=noise, cutoff_hz=fc)
        measured = REFERENCE_PLANT.J_m * float(np.sqrt(np.mean(pr.acceleration_f[4:-4] ** 2)))
        assert _quantization_floor_nm(step, REFERENCE_PLANT.J_m, FS, fc) == pytest.approx(measured, rel=0.04)


def test_a_coarse_motor_encoder_lowers_the_residual_low_pass() -> None:
    res = _identified("coarse_encoder")
    _assert_done_criteria(res, "coarse_encoder")
    cut = res.stage("start").detail["residual"]
    assert cut["position_step_rad"] == pytest.approx(2 * math.pi / 2 ** 17)
    assert cut["quantization_floor_ratio_configured"] > 0.02  # 3 % at 400 Hz
    assert cut["cutoff_hz"] < 200.0 and cut["quantization_floor_ratio"] < 0.003
    assert abs(res.epsilon_deg - 0.25) < 0.005 and res.to_dict()["fit"]["approximate"] is False
    assert any("encoder's step" in n for n in res.notes)
    # a 24-bit encoder leaves the configured low-pass alone
    ideal = _identified("ideal").stage("start").detail["residual"]
    assert ideal["cutoff_hz"] == IdentificationOptions().residual_cutoff_hz and ideal["quantization_floor_ratio"] < 1e-3


def test_a_result_that_cannot_explain_the_windows_it_dropped_is_reported_as_approximate() -> None:
    # the plain fit's rules (the predictor refit, on by default, would refine this plant)
    d = _identified("lightly_damped_100hz_zeta01", predictor=False).to_dict()
    fit = d["fit"]
    # the other two rules let it pass: small residual on the kept samples, < 20 % dropped
    assert fit["residual_ratio"] < 0.005 and 0 < fit["dropped_fraction"] < 0.2
    assert fit["residual_ratio_all_samples"] > 0.025 and fit["approximate"] is True
    assert any(n.startswith("approximate result") and "over the whole record" in n for n in d["notes"])
    # results within the tolerances: every sample explained about as well as the kept ones
    for name in ("ideal", "coulomb", "lightly_damped_seed9"):
        f = _identified(name).to_dict()["fit"]
        assert f["residual_ratio_all_samples"] < 0.015 and f["approximate"] is False, name
    assert _identified("ideal").to_dict()["fit"]["residual_ratio_all_samples"] == \
        _identified("ideal").to_dict()["fit"]["residual_ratio"]
    # the CLI's summary says both when samples were dropped
    row = _model_fit_row(d)
    assert "dropped" in row and "over all of it" in row and "APPROXIMATE" in row


def test_a_result_that_drops_a_fifth_of_the_record_is_reported_as_approximate() -> None:
    # the plain fit's rules (the predictor refit, on by default, would refine this plant)
    d = _identified("lightly_damped_100hz", predictor=False).to_dict()
    assert d["fit"]["dropped_fraction"] > 0.2 and d["fit"]["residual_ratio"] < 0.005
    assert d["fit"]["approximate"] is True
    assert any(n.startswith("approximate result") and "dropped" in n for n in d["notes"])
    # ... and the tuning does not compensate a backlash it cannot trust
    from commission.tuning.design import TuningOptions, design

    s = design(_identified("lightly_damped_100hz", predictor=False), TuningOptions())
    assert not s.backlash.enabled and any("approximate" in n for n in s.notes)
    for name in ("ideal", "coulomb"):  # the friction plant drops its stick windows, < 20 %
        f = _identified(name).to_dict()["fit"]
        assert f["dropped_fraction"] < 0.2 and f["approximate"] is False


def test_a_current_loop_lag_is_fitted_as_delay_for_the_start() -> None:
    # the 1 kHz loop (T_c = 159 µs) acts on the FRD like ~T_c of extra delay; fitted, the start
    # splits the viscous friction right (with the sample's delay alone B_m came out ~0)
    res = _identified("current_loop")
    extra = res.stage("tffit").detail["delay_s"] - 1 / FS
    assert extra == pytest.approx(1 / (2 * math.pi * 1000.0), rel=0.25)
    assert any("of delay fitted" in n for n in res.notes)
    start = res.stage("start").detail["parameters"]
    assert start["B_m"] == pytest.approx(REFERENCE_PLANT.B_m, rel=0.3)
    # ... and the ε search simulates that delay as the loop's T_c
    assert res.stage("search").detail["lag_s"] == pytest.approx(extra)
    assert _identified("ideal").stage("search").detail["lag_s"] is None
    ideal = _identified("ideal")
    assert ideal.stage("tffit").detail["delay_s"] == 1 / FS
    assert not any("of delay fitted" in n for n in ideal.notes)


def test_friction_repeats_the_start_search_with_the_load_share_simulated() -> None:
    res = _identified("coulomb")
    fs_ = res.stage("search").detail["friction_search"]
    assert fs_ is not None and fs_["coulomb_nm"] == pytest.approx(0.02, rel=0.5)
    assert abs(res.stage("search").detail["best"][0]["epsilon_deg"] - 0.40) <= 0.1
    assert any("start search repeated" in n for n in res.notes)
    assert _identified("ideal").stage("search").detail["friction_search"] is None


def test_a_second_pass_whose_search_confirms_the_first_is_not_refitted() -> None:
    # the friction plant's first pass drops its stick windows (≥ 1 %: a second pass is due) and
    # ends at the right ε; the new search's best cell is the grid cell nearest it: no refit
    res = _identified("coulomb")
    sp = res.stage("joint").detail["second_pass"]
    assert sp is not None and sp["confirmed"] is True and sp["taken"] is False
    assert abs(sp["first_epsilon_deg"] - 0.40) <= 0.02
    assert any("confirms" in n for n in res.notes)
    # a first pass that explains the whole record is not searched for a wider ε (the default range)
    assert sp["searched_to_deg"] == 1.0
    # this lightly damped plant's first pass ends at a wrong ε (0.33°): its search disagrees and
    # the refit is made — and taken
    sp = _identified("lightly_damped_seed8").stage("joint").detail["second_pass"]
    assert "confirmed" not in sp and sp["taken"] is True
    assert abs(sp["first_epsilon_deg"] - 0.25) > 0.03 and abs(sp["epsilon_deg"] - 0.25) <= 0.02


def test_a_light_stiff_load_with_friction_starts_from_the_high_edge() -> None:
    d = _identified("light_coulomb").stage("start").detail
    assert d["band_low_hz"] == 20.0
    assert d["parameters"]["K"] == pytest.approx(70.77, rel=0.1)


def test_the_search_in_two_parts_finds_the_cells_of_one_search() -> None:
    # the middle damping split is searched first (friction shows there); without friction the
    # other splits follow and the best cells must be those of one search over all splits
    from commission.ident.hybrid import IdentificationOptions, _epsilon_candidates
    from commission.ident.jointfit import ModelTerms, search_starts
    from commission.ident.residual import prepare_residual

    res = _identified("ideal")
    d = res.stage("search").detail
    assert d["friction_search"] is None and d["evaluations"] == 66
    opt = IdentificationOptions()
    rec = _recording("ideal")
    problem = prepare_residual(rec.torque_ref, FS, motor_position=rec.motor_position,
                               motor_velocity=rec.motor_velocity, cutoff_hz=opt.residual_cutoff_hz,
                               velocity_scale_rad_s=opt.coulomb_velocity_scale_rad_s,
                               interpolation=opt.motor_interpolation)
    start = TwoMassParameters(**res.stage("start").detail["parameters"])
    one = search_starts(problem, start, _epsilon_candidates(opt, coarse=True), opt.damping_splits,
                        opt.omega_scales, n_best=opt.starts, terms=ModelTerms(True, True, True))
    assert [(math.degrees(c.epsilon_rad), c.phi, c.cost) for c in one.best] == \
        [(b["epsilon_deg"], b["phi"], b["cost_nm"]) for b in d["best"]]
    # with friction only the middle split is searched before the friction search
    assert _identified("coulomb").stage("search").detail["evaluations"] == 22 + 66
