"""The record's signals are checked against each other before the identification (ident.consistency).

Positions that wrap (a single-turn encoder, a counter exported as it stands) are unwrapped; positions that
jump by no period, or do not move, are left out; a position or torque that counts the other way is
reversed; units that disagree are one clear error. Each with a note. A wrapped record used to run for
more than 10 minutes and end with nothing; a constant position column gave J_m 1e6× off, not flagged;
a reversed torque ended flagged with ε at the top of its range."""

import json
import math

import numpy as np
import pytest

from commission.cli import main
from commission.csvlog import write_csv
from commission.excitation import chirp
from commission.config import ExcitationConfig
from commission.ident.twomass import REFERENCE_PLANT
from commission.exceptions import IdentificationError
from commission.ident.consistency import reconcile, unwrap_positions
from commission.recording import Recording
from sim_drive.plant import Plant, PlantParameters

FS = 8000.0


def _run(duration_s: float, load: bool = False) -> Recording:
    r = Plant(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.40, torque_noise_nm=1e-4, seed=5),
              FS).run_torque(chirp(ExcitationConfig(duration_s=duration_s)).samples)
    extra = {"load_position": r.load_position, "load_velocity": r.load_velocity} if load else {}
    return Recording.uniform(FS, r.torque_ref, r.motor_velocity, motor_position=r.motor_position, **extra)


def _wrapped(x: np.ndarray, period: float) -> np.ndarray:
    return np.mod(x + 0.5 * period, period) - 0.5 * period


def _crossings(x: np.ndarray, period: float) -> int:
    """How often ``x`` crosses an odd multiple of half the period: where ``_wrapped`` jumps."""
    return int(np.count_nonzero(np.diff(np.floor(x / period + 0.5))))


@pytest.fixture(scope="module")
def run() -> Recording:
    return _run(10.0, load=True)


@pytest.mark.parametrize("period", [2 * math.pi, 0.5])
def test_a_wrapped_position_is_unwrapped_to_the_one_recorded(run: Recording, period: float) -> None:
    # 2π: a single-turn position in rad; 0.5 rad: a counter of some other length
    x = run.motor_position
    assert _crossings(x, period) > 5
    got, notes = unwrap_positions(run.replace(motor_position=_wrapped(x, period)))
    # the same motion (the wrap's offset to the record's first sample aside), to rounding
    assert np.max(np.abs((got.motor_position - got.motor_position[0]) - (x - x[0]))) < 1e-9
    assert notes == [f"motor_position wraps {_crossings(x, period)} times at a period of {period:.6g} rad "
                     "(a single-turn or counter position): unwrapped"]


def test_the_load_position_is_unwrapped_on_its_own(run: Recording) -> None:
    got, notes = unwrap_positions(run.replace(load_position=_wrapped(run.load_position, 2 * math.pi)))
    assert np.array_equal(got.motor_position, run.motor_position)
    assert np.max(np.abs((got.load_position - got.load_position[0]) - (run.load_position - run.load_position[0]))) < 1e-9
    assert len(notes) == 1 and notes[0].startswith("load_position wraps")


def test_a_record_without_jumps_is_left_as_it_is(run: Recording) -> None:
    got, notes = unwrap_positions(run)
    assert got is run and notes == []


def test_a_glitch_is_interpolated_marked_lost_and_said_where(run: Recording) -> None:
    x = run.motor_position.copy()
    x[30_000:30_003] += 1.234  # three samples off by a value no wrap has, then back
    got, notes = unwrap_positions(run.replace(motor_position=x))
    assert np.flatnonzero(got.lost_mask).tolist() == [30_000, 30_001, 30_002]
    # on the line between the good neighbours: within the motion of 4 samples of the true position
    assert np.max(np.abs(got.motor_position - run.motor_position)) < 4 * np.max(np.abs(np.diff(run.motor_position)))
    assert np.array_equal(got.motor_velocity, run.motor_velocity)
    jump = x[30_000] - x[29_999]
    assert notes == [f"motor_position glitches at 3 samples (first at t = 3.75 s, by {jump:.3g} rad, and back): "
                     "interpolated there and left out of the time-domain fit"]


def test_an_encoder_glitch_replays_to_the_plant(tmp_path) -> None:
    # one sample of the encoder misread by 0.05 rad, and the drive's velocity its difference (a spike up
    # and down): identified as 136 s of fitting to J_m -93 % (flagged) when the glitch was a reset
    rec = _run(3.0)
    x = rec.motor_position.copy()
    x[12_000] += 0.05
    _replays_to_the_plant(tmp_path, rec.replace(motor_position=x, motor_velocity=np.diff(x, prepend=0.0) * FS),
                          "motor_position glitches at 1 sample (first at t = 1.5 s",
                          "motor_velocity disagrees with motor_position's step at 2 samples")


def _replays_to_the_plant(tmp_path, rec: Recording, *notes: str) -> None:
    """``rec`` written as a CSV and replayed: within the tolerances, not flagged, with notes that start so."""
    write_csv(tmp_path / "axis.csv", rec)
    assert main(["--replay", str(tmp_path / "axis.csv"), "--out", str(tmp_path / "o"), "--no-tune"]) == 0
    doc = json.loads((tmp_path / "o" / "result.json").read_text())
    for start in notes:
        assert any(n.startswith(start) for n in doc["notes"]), start
    assert doc["fit"]["approximate"] is False
    assert doc["backlash"]["epsilon_deg"] == pytest.approx(0.40, abs=0.01)
    for p in ("J_m", "J_l", "K"):
        assert doc["two_mass"][p] == pytest.approx(getattr(REFERENCE_PLANT, p), rel=0.02), p


def test_a_load_encoders_glitch_is_interpolated_and_marked_lost(run: Recording) -> None:
    xl = run.load_position.copy()
    xl[40_000] += 0.05  # the load encoder misread once, its velocity the difference
    got, notes = reconcile(run.replace(load_position=xl, load_velocity=np.diff(xl, prepend=xl[0]) * FS))
    assert np.flatnonzero(got.lost_mask).tolist() == [40_000, 40_001]
    assert np.max(np.abs(got.load_position - run.load_position)) < 2 * np.max(np.abs(np.diff(run.load_position)))
    assert [n.split(" (")[0] for n in notes] == ["load_position glitches at 1 sample",
                                                 "load_velocity disagrees with load_position's step at 2 samples"]


def test_samples_a_logger_lost_are_no_glitch(run: Recording) -> None:
    # rows a logger dropped come back interpolated and marked lost: the velocity after each disagrees with
    # the interpolated step, which is no glitch (12 rows of a CSV once gave 12 such notes' samples more)
    from commission.recording import LOST_SAMPLES_KEY, encode_samples

    lost = np.zeros(len(run), dtype=bool)
    lost[1000:80_000:7_000] = True
    k = np.arange(len(run))
    filled = {name: np.interp(k, k[~lost], getattr(run, name)[~lost])
              for name in ("motor_position", "motor_velocity", "load_position", "load_velocity")}
    rec = run.replace(**filled, metadata={LOST_SAMPLES_KEY: encode_samples(lost)})
    got, notes = reconcile(rec)
    assert notes == [] and np.array_equal(got.lost_mask, lost)


def test_a_position_that_jumps_and_stays_is_left_out_and_said_where(run: Recording) -> None:
    x = run.motor_position.copy()
    x[30_000:] += 1.234  # reset by a value no wrap has
    got, notes = unwrap_positions(run.replace(motor_position=x))
    assert got.motor_position is None and np.array_equal(got.motor_velocity, run.motor_velocity)
    jump = x[30_000] - x[29_999]
    assert len(notes) == 1 and f"motor_position jumps by {jump:.3g} rad at sample 30000 (t = 3.75 s)" in notes[0]
    assert "does not come back (1 jump, no wrap of one period: a reset" in notes[0] and "left out" in notes[0]


@pytest.mark.parametrize("kind", ["difference of counts", "filtered by the drive", "velocity only"])
def test_a_velocity_glitch_is_interpolated_and_marked_lost(run: Recording, kind: str) -> None:
    # a velocity that is its position's step but for one sample: a corrupted value; with a drive's filtered
    # velocity the same glitch stands out from the filter's lag, and without a position from its neighbours
    v = run.motor_velocity.copy()
    if kind == "filtered by the drive":
        from scipy.signal import lfilter
        a = math.exp(-2 * math.pi * 500.0 / FS)
        v = lfilter([1 - a], [1, -a], v)
    clean = run.replace(motor_velocity=v.copy(), **({"motor_position": None} if kind == "velocity only" else {}))
    v[40_000] += 50.0
    got, notes = reconcile(clean.replace(motor_velocity=v))
    assert np.flatnonzero(got.lost_mask).tolist() == [40_000]
    assert got.motor_velocity[40_000] == pytest.approx(0.5 * (v[39_999] + v[40_001]))
    start = ("motor_velocity glitches at 1 sample (first at t = 5 s, a spike of 50" if kind == "velocity only" else
             "motor_velocity disagrees with motor_position's step at 1 sample (first at t = 5 s, by 50")
    assert len(notes) == 1 and notes[0].startswith(start), notes
    # and the record without it is left as it is
    assert reconcile(clean) == (clean, [])


def test_a_position_in_other_units_than_its_velocity_is_one_clear_error(run: Recording) -> None:
    # degrees for rad, or a velocity in rpm: the record cannot say which of the two to rescale
    with pytest.raises(IdentificationError, match=r"motor_position moves 57\.3× as far as the velocity's"):
        reconcile(run.replace(motor_position=np.degrees(run.motor_position)))
    with pytest.raises(IdentificationError, match=r"moves 0\.105× .*rpm"):
        reconcile(run.replace(motor_velocity=run.motor_velocity * 60.0 / (2.0 * math.pi)))
    # a load encoder behind a gear (1:10) is not on the motor's scale
    with pytest.raises(IdentificationError, match=r"load_position moves 0\.1× as far as the motor's.*gear ratio"):
        reconcile(run.replace(load_position=0.1 * run.load_position, load_velocity=None))


@pytest.mark.parametrize("velocity_only", [False, True])
def test_a_record_in_encoder_counts_is_one_clear_error(run: Recording, velocity_only: bool) -> None:
    # position and velocity both in counts agree with each other: identified, J and K were 1e-10 off after
    # 108-128 s of fitting (flagged, with no word on units)
    cpr = 2**24 / (2 * math.pi)  # the simulator's 24-bit encoder
    rec = run.replace(motor_position=None if velocity_only else np.round(run.motor_position * cpr),
                      motor_velocity=run.motor_velocity * cpr, load_position=None, load_velocity=None)
    what = "motor_velocity is whole encoder counts per sample" if velocity_only else "motor_position holds whole"
    with pytest.raises(IdentificationError, match=what):
        reconcile(rec)


def test_a_position_that_does_not_move_is_left_out(run: Recording) -> None:
    # a position column exported though no encoder fed it: identified from the velocity instead
    got, notes = reconcile(run.replace(motor_position=np.zeros(len(run))))
    assert got.motor_position is None and len(notes) == 1
    assert notes[0].startswith("motor_position moves 0× as far as it should") and "left out" in notes[0]


def test_positions_that_count_the_other_way_are_reversed(run: Recording) -> None:
    got, notes = reconcile(run.replace(motor_position=-run.motor_position, load_position=-run.load_position,
                                       load_velocity=None))
    assert np.array_equal(got.motor_position, run.motor_position)
    assert np.array_equal(got.load_position, run.load_position)
    assert notes == ["motor_position counts the other way than the velocity's motion: its sign is reversed",
                     "load_position counts the other way than the motor's motion: its sign is reversed"]


def test_a_load_encoder_mounted_the_other_way_round_is_reversed(run: Recording) -> None:
    # its position agrees with its own velocity, both against the motor's: both are reversed
    got, notes = reconcile(run.replace(load_position=-run.load_position, load_velocity=-run.load_velocity))
    assert np.array_equal(got.load_position, run.load_position)
    assert np.array_equal(got.load_velocity, run.load_velocity)
    assert notes == ["load_position counts the other way than the motor's motion: its sign is reversed "
                     "(and load_velocity's)"]


def test_a_load_position_that_does_not_follow_the_motor_is_left_out(run: Recording) -> None:
    # another axis's encoder in the load column: no scale to judge, so no units error either
    other = np.cumsum(np.random.default_rng(1).standard_normal(len(run))) * 1e-3
    got, notes = reconcile(run.replace(load_position=other, load_velocity=None))
    assert got.load_position is None and len(notes) == 1
    assert notes[0].startswith("load_position does not follow the motor (correlation of their displacements 0.")


def test_a_load_velocity_alone_is_summed_to_its_position(run: Recording) -> None:
    # a dual-loop drive's log may hold the load's velocity but not its position
    got, notes = reconcile(run.replace(load_position=None))
    assert notes == ["load position rebuilt from load_velocity (x[k] = x[k−1] + Ts·v[k])"]
    assert np.max(np.abs(got.load_position - run.load_position)) < 1e-9
    # a filtered one is no difference of counts: summed, it would lead by half a sample
    from scipy.signal import lfilter
    a = math.exp(-2 * math.pi * 500.0 / FS)
    got, notes = reconcile(run.replace(load_position=None, load_velocity=lfilter([1 - a], [1, -a], run.load_velocity)))
    assert got.load_position is None and len(notes) == 1 and notes[0].endswith("the load is not used")


def test_a_load_encoder_behind_a_gear_is_an_error_with_its_velocity_too(run: Recording) -> None:
    with pytest.raises(IdentificationError, match=r"load_position moves 0\.1× as far as the motor's.*gear ratio"):
        reconcile(run.replace(load_position=0.1 * run.load_position, load_velocity=0.1 * run.load_velocity))


def test_a_torque_of_the_other_sign_is_reversed_and_said_so(run: Recording) -> None:
    # a passive machine absorbs the torque's work: against the velocity, the torque's sign is reversed
    got, notes = reconcile(run.replace(torque_ref=-run.torque_ref))
    assert np.array_equal(got.torque_ref, run.torque_ref)
    assert len(notes) == 1 and notes[0].startswith("the motor turns against torque_ref (correlation")
    assert "check the drive's direction settings" in notes[0]


def test_a_wrapped_reversed_csv_replays_to_the_plant(tmp_path) -> None:
    # the user's way in: a CSV whose position column is single-turn and whose torque counts the other way;
    # 3 s of the chirp turn the motor 2 times
    rec = _run(3.0)
    assert _crossings(rec.motor_position, 2 * math.pi) >= 2
    _replays_to_the_plant(tmp_path, rec.replace(motor_position=_wrapped(rec.motor_position, 2 * math.pi),
                                                torque_ref=-rec.torque_ref),
                          "motor_position wraps", "the motor turns against torque_ref")


def test_units_that_disagree_are_a_one_line_error_of_the_command(tmp_path, capsys) -> None:
    rec = _run(1.0)
    write_csv(tmp_path / "deg.csv", rec.replace(motor_position=np.degrees(rec.motor_position)))
    assert main(["--replay", str(tmp_path / "deg.csv"), "--out", str(tmp_path / "o")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert any("motor_position moves 57.3× as far as the velocity's motion says" in line for line in err)
    assert "Traceback" not in "\n".join(err)


def _cut(run: Recording, start_s: float, duration_s: float) -> Recording:
    """``run`` from ``start_s`` on, as a CSV cut from a longer log has it: motor side only, times from 0."""
    a = int(start_s * FS)
    b = a + int(duration_s * FS)
    return Recording.uniform(FS, run.torque_ref[a:b], run.motor_velocity[a:b], motor_position=run.motor_position[a:b])


def test_a_record_cut_from_a_running_axis_is_identified_from_its_first_samples_motion(run: Recording) -> None:
    # 3.5-6.5 s of the reference run: it starts at ~14 rad/s, and the motor reverses once inside it. Started
    # at rest, the predictor and the load simulation explained 13 % of the torque (J_m 10× off, flagged)
    from commission.ident.hybrid import identify

    cut = _cut(run, 3.5, 3.0)
    assert abs(cut.motor_velocity[0]) > 10.0 and cut.motor_velocity.min() < 0.0 < cut.motor_velocity.max()
    res = identify(cut)
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons
    assert res.epsilon_determined and res.epsilon_deg == pytest.approx(0.40, abs=0.01)
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(REFERENCE_PLANT, p), rel=0.02), p


def test_a_record_in_which_the_load_never_crosses_the_gap_says_it_does_not_determine_e(run: Recording) -> None:
    # 1-4 s: the motor turns at 9-17 rad/s throughout and the load stays on one flank (its twist is
    # 0.42-0.75° against ε 0.4°): every ε explains the record alike. The plant is still identified; ε is
    # not, and the result says so instead of "no backlash detected" with an interval that missed the truth
    from commission.ident.hybrid import NO_CROSSING, identify

    cut = _cut(run, 1.0, 3.0)
    twist = (run.motor_position - run.load_position)[int(FS):int(4 * FS)]
    assert twist.min() > math.radians(0.40)  # (the simulator's own load: on the positive flank throughout)
    res = identify(cut)
    assert res.fit is not None and res.fit.approximate and NO_CROSSING in res.fit.reasons
    assert not res.epsilon_determined
    lo, hi = res.epsilon_interval_rad
    assert lo == 0.0 and math.degrees(hi) >= 16.0
    assert res.to_dict()["backlash"]["determined"] is False
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(REFERENCE_PLANT, p), rel=0.02), p


@pytest.fixture(scope="module")
def sampled() -> tuple[Recording, np.ndarray]:
    """The reference run with a velocity sampled at the sample instants (no difference of counts), velocity
    only; and the motor position at the sample instants [rad]."""
    from sim_drive.sampled import sampled_motor_velocity

    tau = chirp(ExcitationConfig()).samples
    v, x = sampled_motor_velocity(PlantParameters(**REFERENCE_PLANT.as_dict(), epsilon_deg=0.40,
                                                  torque_noise_nm=1e-4, seed=5), tau, FS)
    return Recording.uniform(FS, tau, v), x


def test_a_velocity_that_is_a_difference_of_counts_is_left_as_it_is(run: Recording) -> None:
    from commission.ident.consistency import rebuilt_position_noise_rad

    rec = run.replace(motor_position=None, load_position=None, load_velocity=None)
    got, notes = reconcile(rec)
    assert got is rec and notes == []
    assert rebuilt_position_noise_rad(rec) == 0.0


def test_a_sampled_velocity_is_averaged_over_each_sample(sampled: tuple[Recording, np.ndarray]) -> None:
    # summed as it stands it puts the position half a sample early; averaged, the sum is the trapezoid's
    rec, x = sampled
    got, notes = reconcile(rec)
    assert len(notes) == 1 and "no difference of encoder counts" in notes[0]
    v = rec.motor_velocity
    np.testing.assert_array_equal(got.motor_velocity[1:], 0.5 * (v[1:] + v[:-1]))
    truth = x - x[0]
    summed = np.concatenate(([0.0], np.cumsum(v[1:]) / FS))
    rebuilt = np.concatenate(([0.0], np.cumsum(got.motor_velocity[1:]) / FS))
    assert np.max(np.abs(rebuilt - truth)) < 0.02 * np.max(np.abs(summed - truth))


@pytest.mark.parametrize("kind", ["sampled", "filtered by the drive"])
def test_a_velocity_only_record_of_no_counts_is_identified(kind: str, run: Recording,
                                                           sampled: tuple[Recording, np.ndarray]) -> None:
    # both were flagged (K +7 %, J_m +8 %) after 73-94 s: the summed position led the torque by half a
    # sample, which no delay or lag of the model can explain; "filtered": the drive's velocity through a
    # first-order 500 Hz low-pass, as many drives report it
    from scipy.signal import lfilter

    from commission.ident.hybrid import identify

    if kind == "sampled":
        rec = sampled[0]
    else:
        a = math.exp(-2 * math.pi * 500.0 / FS)
        rec = Recording.uniform(FS, run.torque_ref, lfilter([1 - a], [1, -a], run.motor_velocity))
    res = identify(rec)
    assert res.fit is not None and not res.fit.approximate, res.fit.reasons
    assert res.epsilon_deg == pytest.approx(0.40, abs=0.01)
    for p in ("J_m", "J_l", "K"):
        assert getattr(res.parameters, p) == pytest.approx(getattr(REFERENCE_PLANT, p), rel=0.02), p
