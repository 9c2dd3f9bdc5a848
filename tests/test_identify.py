"""The hybrid identifier on plants whose parameters the test chose (sim_drive's plant plays the machine).

Each plant is simulated and identified once (module cache). Outcomes with stated tolerances:
what a user reads in result.json, never a stage's path. Tolerances: those of the issue
(ε within 0.01° or 2 %, J_m, J_l, K within 2 %, resonance and anti-resonance within 0.5 %) on
plants the model describes; on plants it cannot follow, the result is flagged approximate with
its reasons, and its intervals hold the truth.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from commission.config import ExcitationConfig
from commission.excitation import chirp
from commission.ident.hybrid import Identification, IdentificationOptions, identify
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters, modes
from commission.recording import Recording
from sim_drive.plant import Plant, PlantParameters

from conftest import two_mass_plant

FS = 8000.0


LIGHTLY_DAMPED = TwoMassParameters(**{**REFERENCE_PLANT.as_dict(), "D": 0.0045})
CASES: dict[str, tuple[TwoMassParameters, dict]] = {
    "reference": (REFERENCE_PLANT, dict(epsilon_deg=0.40)),
    "no_backlash": (REFERENCE_PLANT, dict(epsilon_deg=0.0)),
    "lightly_damped": (LIGHTLY_DAMPED, dict(epsilon_deg=0.25)),
    "lightly_damped_seed9": (LIGHTLY_DAMPED, dict(epsilon_deg=0.25, seed=9)),
    "friction": (REFERENCE_PLANT, dict(epsilon_deg=0.40, coulomb_motor_nm=0.01, coulomb_load_nm=0.01)),
    "current_loop": (REFERENCE_PLANT, dict(epsilon_deg=0.40, current_loop_bandwidth_hz=1000.0, torque_noise_nm=1e-3)),
    # impact-rich: at the true parameters the load simulated open loop leaves 28 % of τ_ref
    "impact_rich_100hz": (two_mass_plant(1.0, 100.0, 0.05, B_l=0.53e-2 * math.sqrt(2.5)), dict(epsilon_deg=0.20, seed=3)),
    "heavy_60hz": (two_mass_plant(2.0, 60.0, 0.07, B_l=0.53e-2 * math.sqrt(5.0)), dict(epsilon_deg=0.30, seed=7)),
    "soft_heavy": (two_mass_plant(4.0, 25.0, 0.17, B_l=1.5e-2), dict(epsilon_deg=0.60)),
    "wide_backlash": (REFERENCE_PLANT, dict(epsilon_deg=1.5)),
    # J_l/J_m 0.2, 200 Hz, ζ 0.11: 645 impacts in 10 s (bench_identify's "stiff light 200Hz")
    "stiff_light_200hz": (two_mass_plant(0.2, 200.0, 0.11, B_l=0.3e-2), dict(epsilon_deg=0.25)),
    "coarse_encoder": (LIGHTLY_DAMPED, dict(epsilon_deg=0.25, seed=5, encoder_bits_motor=17)),
    "noisy": (REFERENCE_PLANT, dict(epsilon_deg=0.40, torque_noise_nm=3e-3, seed=5)),
    # ~2000 impacts in 10 s of a load the excitation throws around the gap: not followed
    "chaotic_300hz": (two_mass_plant(2.0, 300.0, 0.15, B_l=0.53e-2 * math.sqrt(5.0)), dict(epsilon_deg=0.50, seed=7)),
}
_cache: dict[tuple, Identification] = {}


def _recording(name: str, *, load: bool = False, position: bool = True, duration_s: float = 10.0) -> Recording:
    params, extra = CASES[name]
    kw = dict(torque_noise_nm=1e-4, seed=11)
    kw.update(extra)
    tau = chirp(ExcitationConfig(duration_s=duration_s)).samples
    r = Plant(PlantParameters(**params.as_dict(), **kw), FS).run_torque(tau)
    sig = {"motor_position": r.motor_position} if position else {}
    if load:
        sig["load_position"] = r.load_position
    return Recording.uniform(FS, r.torque_ref, r.motor_velocity, **sig)


def _identified(name: str, **rec: object) -> Identification:
    key = (name, tuple(sorted(rec.items())))
    if key not in _cache:
        _cache[key] = identify(_recording(name, **rec))  # type: ignore[arg-type]
    return _cache[key]


def _within(res: Identification, name: str, scale: float = 1.0) -> None:
    """The issue's tolerances (× ``scale``)."""
    true, extra = CASES[name]
    eps = extra["epsilon_deg"]
    assert abs(res.epsilon_deg - eps) <= scale * max(0.01, 0.02 * eps), res.epsilon_deg
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(true, p), rel=0.02 * scale), p
    mt, mi = modes(true), res.modes
    assert mi.f_resonance_hz == pytest.approx(mt.f_resonance_hz, rel=0.005 * scale)
    assert mi.f_antiresonance_hz == pytest.approx(mt.f_antiresonance_hz, rel=0.005 * scale)


def _covers(res: Identification, name: str) -> None:
    """The 95 % intervals hold the truth."""
    true, extra = CASES[name]
    lo, hi = res.epsilon_interval_rad
    assert lo <= math.radians(extra["epsilon_deg"]) <= hi
    for p, (a, b) in (res.parameter_interval or {}).items():
        if p in ("J_m", "J_l", "K"):
            assert a <= getattr(true, p) <= b, p


@pytest.mark.parametrize("name", ["reference", "lightly_damped", "lightly_damped_seed9", "impact_rich_100hz",
                                  "heavy_60hz", "soft_heavy", "noisy", "coarse_encoder",
                                  # the gap softens the spring the FRD sees: a start too soft for the fit's basin
                                  "wide_backlash"])
def test_plants_the_model_describes_are_identified_within_the_tolerances(name: str) -> None:
    res = _identified(name)
    _within(res, name)
    _covers(res, name)
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons


def test_the_reference_plant_keeps_no_extra_term_and_reports_a_tight_fit() -> None:
    res = _identified("reference")
    d = json.loads(json.dumps(res.to_dict()))
    assert "friction" not in d and "current_loop" not in d
    assert not any(t["kept"] for t in d["model_selection"].values())
    assert d["fit"]["residual_ratio"] < 1e-3 and d["fit"]["approximate"] is False and d["fit"]["reasons"] == []
    lo, hi = d["backlash"]["epsilon_interval_deg"]
    assert hi - lo < 0.02
    assert d["measured_band_hz"][1] > 300.0


def test_no_backlash_is_reported_as_such() -> None:
    res = _identified("no_backlash")
    assert not res.backlash_detected and res.epsilon_deg <= 0.01
    _within(res, "no_backlash")


def test_coulomb_friction_is_kept_with_values_that_hold_the_truth() -> None:
    res = _identified("friction")
    _within(res, "friction")
    f = res.to_dict()["friction"]
    for side in ("motor", "load"):
        assert f[f"{side}_nm"] == pytest.approx(0.01, rel=0.1)
        lo, hi = f[f"{side}_interval_nm"]
        assert lo <= f[f"{side}_nm"] <= hi


def test_a_current_loop_is_kept_with_its_bandwidth() -> None:
    res = _identified("current_loop")
    _within(res, "current_loop")
    c = res.to_dict()["current_loop"]
    assert c["bandwidth_hz"] == pytest.approx(1000.0, rel=0.05)
    lo, hi = c["bandwidth_interval_hz"]
    assert lo <= c["bandwidth_hz"] <= hi
    assert "friction" not in res.to_dict()


def test_a_coarse_motor_encoder_is_the_predictors_measurement_noise() -> None:
    # 17 bits: the quantization (step²/12) is what the Kalman predictor expects of the encoder, so its
    # normalized prediction errors stay white with unit variance and nothing is flagged
    res = _identified("coarse_encoder")
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons
    assert res.fit.innovation_rms is not None and 0.8 < res.fit.innovation_rms < 1.3
    assert res.fit.noise_limited


#: Plants at the edge of what one chirp record shows, and their records; the one the model cannot follow on
#: 3 s of the chirp (a thousand impacts already, at a third of the cost).
_EDGE: dict[str, dict] = {"wide_backlash": {}, "stiff_light_200hz": {}, "chaotic_300hz": dict(duration_s=3.0)}


@pytest.mark.parametrize("name", list(_EDGE))
def test_a_result_outside_the_tolerances_is_flagged_never_silent(name: str) -> None:
    # plants at the edge of what one chirp record shows (a 1.5° gap on a light load, hundreds of
    # impacts of a stiff light load, thousands at 300 Hz): within the tolerances, or flagged
    # approximate with its reasons — and every number of result.json finite either way
    res = _identified(name, **_EDGE[name])
    d = json.loads(json.dumps(res.to_dict()))
    assert all(math.isfinite(v) for v in d["two_mass"].values())
    try:
        _within(res, name)
    except AssertionError:
        assert d["fit"]["approximate"] is True and d["fit"]["reasons"], "outside the tolerances, not flagged"


def test_velocity_only_and_load_encoder_records() -> None:
    v_only = _identified("lightly_damped", position=False)
    _within(v_only, "lightly_damped")
    assert any("rebuilt from the velocity" in n for n in v_only.notes)
    both = _identified("lightly_damped", load=True)
    _within(both, "lightly_damped")
    assert both.stage("start").detail["load_encoder"] is True


def test_a_five_second_record_is_identified_at_the_resolution_it_supports() -> None:
    res = _identified("reference", duration_s=5.0)
    assert any("resolution" in n for n in res.notes)
    _within(res, "reference")


def test_a_plant_the_model_cannot_follow_is_flagged_with_its_reasons_not_refused() -> None:
    res = _identified("chaotic_300hz", **_EDGE["chaotic_300hz"])
    d = json.loads(json.dumps(res.to_dict()))
    assert d["fit"]["approximate"] is True and d["fit"]["reasons"]
    assert any(n.startswith("approximate result") for n in d["notes"])
    assert all(math.isfinite(v) for v in d["two_mass"].values())


def test_the_answer_does_not_depend_on_the_thread_count_or_on_perturbations_far_below_the_noise() -> None:
    rec = _recording("lightly_damped")
    one = identify(rec, IdentificationOptions(threads=1))
    base = _identified("lightly_damped")
    assert one.epsilon_rad == base.epsilon_rad and one.parameters == base.parameters
    scale = 1.0 + 1e-9 * np.random.default_rng(0).standard_normal(len(rec))
    moved = identify(rec.replace(torque_ref=rec.torque_ref * scale))
    assert abs(moved.epsilon_deg - base.epsilon_deg) <= 0.001
    for p in ("J_m", "J_l", "K"):
        assert getattr(moved.parameters, p) == pytest.approx(getattr(base.parameters, p), rel=1e-4), p


def test_a_fit_that_explains_nothing_claims_no_precision() -> None:
    # the curvature at a point where the predictions miss by 100× their predicted size says nothing
    # about where the plant is: the intervals are then unbounded, never a tight one around noise
    from commission.ident.assess import assess
    from commission.ident.estimator import ModelTerms, PemFit
    from commission.ident.kalman import Innovations

    rng = np.random.default_rng(1)
    names = ("ln J_m", "ln J_l", "ln B_m", "ln B_l", "ln K", "ln D", "eps_deg")

    def fit_with(size: float, disturbance_nm: float = 1e-4) -> PemFit:
        nu = size * rng.standard_normal((4000, 1))
        inn = Innovations(error=nu, normalized=nu, log_variance=np.zeros_like(nu), events=0)
        return PemFit(parameters=REFERENCE_PLANT, epsilon_rad=math.radians(0.4), coulomb_motor_nm=0.0,
                      coulomb_load_nm=0.0, lag_s=0.0, terms=ModelTerms(), residual=nu[:, 0], cost_nm=size,
                      names=names, covariance=np.eye(7) * 1e-10, n_effective=4000.0, evaluations=10,
                      converged=True, message="", process_noise_nm=disturbance_nm, innovations=inn)

    # a fit without the parameters' coordinates bounds none of them: said in words, never as "±nan %"
    bare = assess(replace(fit_with(1.0), names=("eps_deg",), covariance=np.eye(1) * 1e-10), torque_rms_nm=0.1,
                  sample_rate_hz=8000.0)
    assert bare.approximate and not any("±nan" in r or "±inf" in r for r in bare.reasons)
    assert any("does not determine J_m or J_l or K" in r for r in bare.reasons), bare.reasons
    assert any("does not determine the resonance frequency" in r for r in bare.reasons), bare.reasons
    lost = assess(fit_with(300.0), torque_rms_nm=0.1, sample_rate_hz=8000.0)
    assert not lost.determined and lost.approximate
    assert any("unbounded" in r for r in lost.reasons)
    fine = assess(fit_with(1.0), torque_rms_nm=0.1, sample_rate_hz=8000.0)
    assert fine.determined and not fine.approximate and fine.noise_limited
    # errors that look like noise only because the noise model took a tenth of the torque as disturbance
    absorbed = assess(fit_with(1.0, disturbance_nm=0.02), torque_rms_nm=0.1, sample_rate_hz=8000.0)
    assert absorbed.approximate and absorbed.model_error
    assert any("unexplained" in r for r in absorbed.reasons)
    # 2.5 % of RMS τ_ref: more than a drive's noise, flagged, the intervals kept; 1.5 %: a noisy drive's
    suspect = assess(fit_with(1.0, disturbance_nm=0.0025), torque_rms_nm=0.1, sample_rate_hz=8000.0)
    assert suspect.approximate and suspect.model_error and suspect.determined
    assert any("may bias" in r for r in suspect.reasons)
    noisy = assess(fit_with(1.0, disturbance_nm=0.0015), torque_rms_nm=0.1, sample_rate_hz=8000.0)
    assert not noisy.approximate and noisy.determined
    # what a new record needs is said for a record without a load encoder that leaves model error, and only then
    assert not suspect.remedies and not fine.remedies
    side = dict(torque_rms_nm=0.1, sample_rate_hz=8000.0, load_encoder=False)
    assert any("load encoder" in r for r in assess(fit_with(1.0, disturbance_nm=0.02), **side).remedies)
    assert assess(fit_with(1.0, disturbance_nm=0.0025), **side).remedies
    assert not assess(fit_with(1.0), **side).remedies and not assess(fit_with(300.0), **side).remedies
    # the chirp's end is named where the record's band stops below 2.4× the estimate's resonance, at 3.5× it
    resonance_hz = modes(REFERENCE_PLANT).f_resonance_hz
    end_hz = 3.5 * resonance_hz
    short = assess(fit_with(1.0, disturbance_nm=0.02), **side, band_top_hz=2.1 * resonance_hz).remedies
    assert any("load encoder" in r for r in short)
    assert any(f"end the chirp at {end_hz:.0f} Hz or more" in r and "sample rate of" not in r for r in short), short
    # a band past 2.4× it gets the load encoder alone (a longer chirp rescued none of the family's such records)
    for top in (2.5, 4.2):
        reached = assess(fit_with(1.0, disturbance_nm=0.02), **side, band_top_hz=top * resonance_hz).remedies
        assert len(reached) == 1 and "load encoder" in reached[0], reached
    # where the estimate puts the resonance beyond the band (the record does not show it) or the band is unknown,
    # a chirp past the resonance, unnamed
    beyond = assess(fit_with(1.0, disturbance_nm=0.02), **side, band_top_hz=0.7 * resonance_hz).remedies
    assert beyond == assess(fit_with(1.0, disturbance_nm=0.02), **side).remedies
    assert not any(f"{end_hz:.0f} Hz" in r for r in beyond) and any("3.5× the resonance" in r for r in beyond)
    # beyond the band a record at this sample rate can fit: the sample rate that reaches it is named too
    slow = assess(fit_with(1.0, disturbance_nm=0.02), torque_rms_nm=0.1, sample_rate_hz=400.0, load_encoder=False,
                  band_top_hz=150.0).remedies
    assert any(f"sample rate of {end_hz / 0.45:.0f} Hz or more" in r for r in slow), slow


def test_a_gap_whose_likelihood_is_flat_past_the_polished_span_is_flagged_not_reported_as_known() -> None:
    # 22:151 on an AMD CPU: ε 0.045° for 0.058°, the curvature's interval ±0.0005°, the likelihood ratio's
    # open up to the searched 2°: the estimate must say it does not know, not pass as within its tolerance
    from commission.ident.assess import assess
    from commission.ident.estimator import ModelTerms, PemFit
    from commission.ident.kalman import Innovations

    nu = np.random.default_rng(2).standard_normal((4000, 1))
    inn = Innovations(error=nu, normalized=nu, log_variance=np.zeros_like(nu), events=0)
    names = ("ln J_m", "ln J_l", "ln B_m", "ln B_l", "ln K", "ln D", "eps_deg")
    cov = np.eye(7) * 1e-10
    cov[6, 6] = (0.0005 / 1.96) ** 2

    def fit_with(profile_deg: tuple[float, float]) -> PemFit:
        return PemFit(parameters=REFERENCE_PLANT, epsilon_rad=math.radians(0.045), coulomb_motor_nm=0.0,
                      coulomb_load_nm=0.0, lag_s=0.0, terms=ModelTerms(), residual=nu[:, 0], cost_nm=1.0,
                      names=names, covariance=cov, n_effective=4000.0, evaluations=10, converged=True,
                      message="", process_noise_nm=1e-4, innovations=inn, epsilon_profile_deg=profile_deg)

    open_ended = assess(fit_with((0.0444, 2.0)), torque_rms_nm=0.1, sample_rate_hz=4000.0)
    assert open_ended.approximate and any("bounds ε only to [0.0444°, 2°]" in r for r in open_ended.reasons)
    bounded = assess(fit_with((0.0440, 0.0460)), torque_rms_nm=0.1, sample_rate_hz=4000.0)
    assert not bounded.approximate, bounded.reasons


def test_a_load_encoder_gives_the_start_where_the_gap_pulls_the_frequency_response_low() -> None:
    # 1.5° of gap on the reference plant: the gap softens the spring the FRD sees; both encoders'
    # equations of motion give the start, and the record is identified within the tolerances
    res = _identified("wide_backlash", load=True)
    _within(res, "wide_backlash")
    _covers(res, "wide_backlash")


def test_a_record_whose_fit_at_the_drives_delay_sits_beside_the_gap_is_identified_within_the_tolerances() -> None:
    # family member 22:151 (4 kHz, 19-bit motor encoder, 518 Hz current loop, ε 0.058°): on an AMD CPU the
    # fit ended at ε 0.045° behind an open likelihood interval (flagged); the fit with the torque a sample
    # later reached the gap's basin, and from there the record is likelier at the drive's own delay
    from sim_drive.family import member

    m = member(22, 151)
    res = identify(m.simulate())
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons
    assert abs(res.epsilon_deg - m.epsilon_deg) <= max(0.01, 0.02 * m.epsilon_deg), res.epsilon_deg
    lo, hi = res.epsilon_interval_rad
    assert lo <= math.radians(m.epsilon_deg) <= hi
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(m.two_mass, p), rel=0.02), p
