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
            noise: float = 1e-4) -> Recording:
    tau = chirp(ExcitationConfig()).samples
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
    assert abs(res.epsilon_deg - eps_deg) <= 0.01 * scale
    for name in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, name) == pytest.approx(getattr(true, name), rel=0.01 * scale), name
    mt, mi = modes(true), res.modes
    assert mi.f_resonance_hz == pytest.approx(mt.f_resonance_hz, rel=0.005 * scale)
    assert mi.f_antiresonance_hz == pytest.approx(mt.f_antiresonance_hz, rel=0.005 * scale)


@pytest.mark.parametrize("name, scale", [("reference", 1.0), ("stiff_light", 3.0), ("soft_heavy", 3.0)])
def test_accuracy(name: str, scale: float) -> None:
    true, eps = PLANTS[name]
    res = _identified(name)
    _check(res, true, eps, scale)
    assert res.backlash_detected
    lo, hi = res.epsilon_interval_rad
    assert lo <= res.epsilon_rad <= hi


def test_a_backlash_beyond_the_search_range_extends_the_range() -> None:
    # ε = 1.5° on the reference plant, the default range up to 1°: the best cell lies at the top,
    # the range is doubled and ε found (it used to end at 0.83°, nothing flagged); the plants whose
    # best cell lies inside the range are not searched further (the reference plant: 0.40°)
    res = identify(_record(REFERENCE_PLANT, 1.5))
    assert abs(res.epsilon_deg - 1.5) <= 0.01
    assert res.stage("search").detail["extended_to_deg"] == 2.0
    assert any("ε search range extended to 2°" in n for n in res.notes)
    assert _identified("reference").stage("search").detail["extended_to_deg"] is None


def test_a_backlash_far_beyond_the_range_is_found_by_the_second_pass() -> None:
    # ε = 3° (a worn gearbox), the default range up to 1°: the start's search stops at a local
    # minimum (extended to 2°, the first pass ends near 1.7° dropping 4.5 %); from the first
    # pass's parameters, which are right, the second pass's cells beyond the range find it.
    # It used to end at 0.74°, flagged approximate
    res = identify(_record(REFERENCE_PLANT, 3.0))
    assert abs(res.epsilon_deg - 3.0) <= 0.01
    _check(res, REFERENCE_PLANT, 3.0, 1.0)
    joint = res.stage("joint").detail
    assert joint["second_pass"]["taken"] and joint["dropped_fraction"] == 0.0
    assert joint["second_pass"]["searched_to_deg"] > 15.0
    assert not joint["approximate"]
    assert any("lies beyond the range" in n for n in res.notes)


def test_no_backlash_is_reported_as_such() -> None:
    res = _identified("no_backlash")
    assert res.epsilon_deg <= 0.02
    assert not res.backlash_detected
    _check(res, REFERENCE_PLANT, 0.0, 1.0)


def test_iterations_show_step5_getting_better() -> None:
    res = _identified("reference")
    assert len(res.iterations) == 3  # FRD start, joint fit, step-6 refit of the joint fit
    assert res.iterations[1]["frd_error"] < res.iterations[0]["frd_error"]
    assert res.iterations[1]["frd_error"] < 0.01
    # step 6 from a right model does not move it
    assert res.iterations[2]["frd_error"] < 1.5 * res.iterations[1]["frd_error"]
    names = [s.name for s in res.stages]
    assert names == ["frd", "tffit", "start", "search", "joint", "check"]
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


def test_velocity_only_and_load_encoder_recordings() -> None:
    true, eps = PLANTS["reference"]
    v_only = identify(_record(true, eps, position=False))
    _check(v_only, true, eps, 1.0)
    with_load = identify(_record(true, eps, load=True))
    _check(with_load, true, eps, 1.0)
    assert any("load encoder" in n for n in with_load.notes)
    ignored = identify(_record(true, eps, load=True), IdentificationOptions(use_load_encoder=False))
    assert not any("load encoder" in n for n in ignored.notes)


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


def test_too_short_for_the_resolution() -> None:
    rec = _ref_arrays().head(40_000)
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


def test_data_the_model_cannot_explain() -> None:
    rec = _ref_arrays()
    # a 3 Hz, 10 rad/s motion that the torque did not cause (an external disturbance)
    v = rec.motor_velocity + 10.0 * np.sin(2 * np.pi * 3.0 * rec.t)
    with pytest.raises(IdentificationError, match="cannot explain"):
        identify(rec.replace(motor_velocity=v, motor_position=None))


def test_options_are_validated() -> None:
    with pytest.raises(ValueError):
        IdentificationOptions(band_hz=(400.0, 0.1))
    with pytest.raises(ValueError):
        IdentificationOptions(epsilon_bounds_deg=(1.0, 0.5))
    with pytest.raises(ValueError):
        IdentificationOptions(unknown=1)  # type: ignore[call-arg]
    with pytest.raises(ValueError):
        IdentificationOptions(resolution_hz=0.0)


def _heavy_friction(f_nm: float) -> Recording:
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.40, torque_noise_nm=1e-4, seed=3,
                              coulomb_motor_nm=f_nm, coulomb_load_nm=f_nm), FS).run_torque(chirp(ExcitationConfig()).samples)
    return Recording.uniform(FS, r.torque_ref, r.motor_velocity, motor_position=r.motor_position)


def test_heavy_friction_gives_a_physical_start_without_overflow():
    # 0.05 N·m of Coulomb friction per side (17 % of the chirp's peak torque): the physical refit
    # of the whole band used to drive its log-parameters to overflow (inf, then NaN into LAPACK and
    # "no physical refit"); RuntimeWarnings are errors here
    import warnings

    from commission.ident.hybrid import _frd_and_fit, _robust_start, _Stages
    from commission.ident.jointfit import ModelTerms
    from commission.ident.residual import prepare_residual

    rec = _heavy_friction(0.05)
    opt = IdentificationOptions()
    notes: list[str] = []
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        frd, fit = _frd_and_fit(rec, opt, _Stages(None), notes)
        problem = prepare_residual(rec.torque_ref, FS, motor_position=rec.motor_position, cutoff_hz=400.0)
        start, _, _ = _robust_start(rec, opt, frd, fit, problem, ModelTerms(True, True, True), notes)
    assert fit is not None
    # a rough but physical start (measured: J_m +48 %, K ×2.3); the joint fit takes it from there
    # (identify: ε within 0.004°, J and K within 0.1 % on this record — 20 s, too slow to repeat here)
    assert min(start.as_array()) > 0
    assert 1 / 3 < start.J_m / REFERENCE_PLANT.J_m < 3 and 1 / 3 < start.K / REFERENCE_PLANT.K < 3


def test_friction_no_band_can_fit_is_one_clear_error():
    # 0.08 N·m per side (a quarter of the peak torque): no 2/3 fit from 10 Hz down is a physical
    # plant; from the 20 Hz edge one is, but the model then leaves 6.3 % of the torque unexplained
    # — the identifier says so in one line instead of failing inside
    with pytest.raises(IdentificationError, match="cannot explain the data|from any low band edge") as err:
        identify(_heavy_friction(0.08))
    assert "\n" not in str(err.value)
