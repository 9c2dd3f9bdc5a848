"""The record's signals checked against each other before anything is fitted: a position in other units
than its velocity, one that counts the other way, one that wraps, a torque whose sign is reversed.

Positions that wrap: a single-turn encoder or a counter exported as it stands jumps by one period
where the axis crossed it, and no model explains such a record (the fits then spend minutes on it).
A sample-to-sample step of a position is at most the largest velocity times the sample period (the
drive's velocity is that difference); a step far beyond it is a jump. When every jump is a whole
multiple of one period (within ``PERIOD_RTOL``) and the position stays within a period, it is unwrapped
and the note says so; other jumps are glitches, and the position is left out (the identification uses
the velocity, or the motor side alone), with a note that says where it jumped.

Scale and direction: the median ratio of a position's steps to the motion the velocity says (over the
samples where the axis moves well) is 1 when both are in rad and rad/s and count the same way. About
0: the position was not recorded (left out); about −1: it counts the other way (reversed); anything else
is a unit error no one can undo from the record (an error that names the ratio). A position in whole
encoder counts agrees with a velocity in counts/s; it steps by 1, which no encoder does in rad, and is an
error that says so. A passive machine
absorbs the work the torque does on it: mean(τ·v) > 0. A record where it is clearly negative has its
torque's sign reversed against the encoder: identified with the torque reversed, and said so.

A velocity without a position: the drive's velocity is the difference of its encoder's counts over a
sample (v[k] = (x[k] − x[k−1])/Ts), so Ts·v lies on a lattice of whole counts, and the position is its
running sum. A velocity off any such lattice is a signal sampled at the sample instants (a simulator's
state, an observer's estimate, a filter's output): its running sum would put the position half a sample
early, a lead no delay or lag of the model can explain; such a velocity is averaged over each sample
period ((v[k−1] + v[k])/2, the trapezoid's step) before the position is rebuilt from it.

Where the record starts (:class:`InitialMotion`): every experiment this tool runs starts at rest, but a
record cut from a longer log may start in motion; the predictor and the load simulation then start at the
speed and acceleration of its first millisecond.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..exceptions import IdentificationError
from ..recording import LOST_SAMPLES_KEY, Recording, encode_samples

__all__ = ["InitialMotion", "initial_motion", "rebuilt_position_noise_rad", "reconcile", "unwrap_positions"]

#: A step beyond this many times the largest motion a sample allows is a jump (a 2π wrap is told
#: from motion up to ~0.5 rad per sample, 4,000 rad/s at 8 kHz).
JUMP_FACTOR = 10.0
#: ... and beyond this [rad] in any case: an encoder's quantization step is never a jump.
JUMP_FLOOR_RAD = 0.05
#: The jumps are one period's multiples when each is within this share of a period of one.
PERIOD_RTOL = 0.01
#: A position agrees with its velocity when its steps are this range's multiples of the velocity's
#: motion (a velocity the drive filters or estimates lags a little at the chirp's top) ...
SCALE_RANGE = (0.7, 1.4)
#: ... and was not recorded when they are below this share of it.
SCALE_STILL = 0.05
#: Samples whose motion is above this share of the largest are the ones the scale is read on.
SCALE_MOVING = 0.3
#: Correlation of torque and velocity below which the torque's sign is reversed (a passive plant's is
#: positive; bench/results/RESULTS.md has the family's lowest).
REVERSED_POWER = -0.02
#: A velocity is a difference of counts when this share of its samples' motions lie within
#: ``LATTICE_TOLERANCE`` counts of a whole number of counts (one count: the smallest motion, or a
#: whole fraction of it up to ``LATTICE_DIVISORS``: a record may never move by just one count) ...
LATTICE_SHARE = 0.99
LATTICE_TOLERANCE = 0.01
LATTICE_DIVISORS = 4
#: A load position whose displacement correlates less than this with the motor's does not follow it (another
#: axis's, or a motor record that is not the load's): it is left out rather than judged for its scale.
LOAD_FOLLOWS = 0.9
#: A position that jumps and jumps back within this many samples has glitched there (an encoder's
#: misread, a corrupted frame), not wrapped or been reset.
GLITCH_SAMPLES = 16
#: A velocity sample disagrees with its position's step when it is off by more than this many times the
#: 99th percentile of the disagreement (a drive's filter lags a little everywhere; a glitch is one sample)
#: ... and by more than two encoder steps per sample.
GLITCH_FACTOR = 10.0


def reconcile(rec: Recording) -> tuple[Recording, list[str]]:
    """``rec`` with its positions and torque made to agree with its velocity, and the notes on what was
    changed (module docstring).

    :raises IdentificationError: a position whose units are not its velocity's (or a load position not
        on the motor's scale), which the record cannot say how to undo.
    """
    notes: list[str] = []
    _not_counts(rec)
    rec = _judged(rec, "motor_position", _step_ratio(rec.motor_position, _motion(rec.motor_velocity, rec.t)), notes)
    interpolated = rec.lost_mask  # by the link or the log, before any glitch is
    rec, wraps = unwrap_positions(rec)
    notes += wraps
    rec = _velocity_glitches(rec, notes, interpolated)
    if rec.load_position is None and rec.load_velocity is not None:
        rec = _load_from_velocity(rec, notes)
    if rec.load_position is not None and rec.load_velocity is not None:
        rec = _judged(rec, "load_position", _step_ratio(rec.load_position, _motion(rec.load_velocity, rec.t)), notes,
                      against="load_velocity's")
    if rec.load_position is not None:
        rec = _load_on_motor_scale(rec, notes)
    if rec.motor_position is None and not _on_a_lattice(rec.motor_velocity, rec.lost_mask):
        v = rec.motor_velocity
        notes.append("the motor velocity is no difference of encoder counts (it lies on no lattice of whole "
                     "counts): taken as sampled at the sample instants, and averaged over each sample period "
                     "before the position is rebuilt from it")
        rec = rec.replace(motor_velocity=np.concatenate((v[:1], 0.5 * (v[1:] + v[:-1]))))
    v = rec.motor_velocity
    power = float(np.mean(rec.torque_ref * v) / max(float(np.std(rec.torque_ref) * np.std(v)), 1e-300))
    if power < REVERSED_POWER:
        notes.append(f"the motor turns against torque_ref (correlation of torque and velocity {power:.2f}): "
                     "the torque's sign is reversed against the encoder's, and it is identified reversed; "
                     "check the drive's direction settings before closing a loop on it")
        rec = rec.replace(torque_ref=-rec.torque_ref)
    return rec, notes


def _not_counts(rec: Recording) -> None:
    """An error when the motor's position, or without one its velocity, is in encoder counts: whole numbers
    that step by 1 (no encoder's step is 1 rad). With both in counts the two agree, and the record would
    be identified in counts: J and K off by the square of the counts per rad, after minutes of fitting."""
    x = rec.motor_position
    if x is not None:
        steps = np.abs(np.diff(x))
        if np.array_equal(x, np.round(x)) and steps.any() and float(np.min(steps[steps > 0])) == 1.0:
            raise IdentificationError(
                "motor_position holds whole encoder counts (it steps by 1), not rad: convert the positions "
                "(rad = counts × 2π / counts per turn) and the velocities (rad/s) before replaying")
        return
    d = np.abs(_motion(rec.motor_velocity, rec.t))
    d = d[d > 0]
    if d.size >= 20 and np.all(np.abs(d - np.round(d)) < 1e-6) and abs(float(d.min()) - 1.0) < 1e-6:
        raise IdentificationError(
            "motor_velocity is whole encoder counts per sample (counts/s), not rad/s: convert it "
            "(rad/s = counts/s × 2π / counts per turn) before replaying")


def _motion(v: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.float64]:
    """The step from sample k to k+1 the velocity says [rad], shape (N − 1,) (the drive's convention:
    v[k+1] = (x[k+1] − x[k])/Ts)."""
    return v[1:] * np.diff(t)


def _step_ratio(x: NDArray[np.float64] | None, motion: NDArray[np.float64]) -> float | None:
    """The median ratio of ``x``'s steps to ``motion`` (shape (N − 1,), [rad]) where the axis moves well
    (a wrap's few steps do not move a median); None without a position or motion."""
    if x is None:
        return None
    moving = np.abs(motion) > SCALE_MOVING * float(np.max(np.abs(motion)))
    if np.count_nonzero(moving) < 20:
        return None
    return float(np.median(np.diff(x)[moving] / motion[moving]))


def rebuilt_position_noise_rad(rec: Recording) -> float:
    """The error of the motor position rebuilt from a sampled velocity by the trapezoid [rad], standard
    deviation (0 for a record with a position, or whose velocity is a difference of counts, rebuilt
    exactly): the trapezoid misses Ts³/12·v̈ per sample, which sums to Ts²/12 times the change of the
    acceleration within the samples since the record's start (the shaft's share of it); taken as twice
    Ts²/12 times the acceleration's RMS, that change being a difference of two accelerations."""
    if rec.motor_position is not None or _on_a_lattice(rec.motor_velocity, rec.lost_mask):
        return 0.0
    ts = 1.0 / rec.sample_rate_hz
    return ts / 6.0 * float(np.sqrt(np.mean(np.diff(rec.motor_velocity) ** 2)))


def _on_a_lattice(velocity: NDArray[np.float64], lost: NDArray[np.bool_]) -> bool:
    """Whether each sample of ``velocity`` (shape (N,), [rad/s]) is a whole number of one encoder count per
    sample period (True also when too few samples move to tell); the samples a link lost (``lost``),
    interpolated, are left out. (The velocity's own values: a streamed record's sample times jitter, the
    drive's period does not.)"""
    d = np.abs(velocity[~lost])
    d = d[d > 1e-12 * float(np.max(d, initial=0.0))]
    if d.size < 20:
        return True
    for divisor in range(1, LATTICE_DIVISORS + 1):
        counts = d * (divisor / float(np.min(d)))
        if np.mean(np.abs(counts - np.round(counts)) <= LATTICE_TOLERANCE) >= LATTICE_SHARE:
            return True
    return False


def _displacement_ratio(x: NDArray[np.float64], reference: NDArray[np.float64]) -> float | None:
    """The least-squares slope of ``x``'s displacement on ``reference``'s (both shape (N,), [rad])."""
    a, b = x - x[0], reference - reference[0]
    bb = float(np.dot(b, b))
    return float(np.dot(a, b) / bb) if bb > 0.0 else None


def _load_from_velocity(rec: Recording, notes: list[str]) -> Recording:
    """``rec`` with the load position summed from its load velocity when it has no load position (the
    drive's convention, x[k] = x[k−1] + Ts·v[k]), from the motor's first position (the identification
    fits the shift between the two encoders' zeros: ``start.load_origin_rad``); a load velocity that is
    no difference of counts (a filter's, an observer's) is left unused, with a note."""
    if not _on_a_lattice(rec.load_velocity, rec.lost_mask):
        notes.append("load_velocity is no difference of encoder counts and the record has no load_position: "
                     "the load is not used")
        return rec
    x0 = float(rec.motor_position[0]) if rec.motor_position is not None else 0.0
    notes.append("load position rebuilt from load_velocity (x[k] = x[k−1] + Ts·v[k])")
    return rec.replace(load_position=x0 + np.concatenate(([0.0], np.cumsum(_motion(rec.load_velocity, rec.t)))))


def _load_on_motor_scale(rec: Recording, notes: list[str]) -> Recording:
    """``rec`` with its load encoder judged against the motor's: above the resonance the load hardly moves
    while the motor does, so the two are compared by their whole displacement (the slow bias's), which the
    load follows but for the twist. A load encoder mounted the other way round counts the other way with
    its own velocity too, so both are reversed."""
    motor = (rec.motor_position if rec.motor_position is not None
             else np.concatenate(([0.0], np.cumsum(_motion(rec.motor_velocity, rec.t)))))
    a, b = rec.load_position - rec.load_position[0], motor - motor[0]
    follows = abs(float(np.dot(a, b))) / max(float(np.sqrt(np.dot(a, a) * np.dot(b, b))), 1e-300)
    if follows < LOAD_FOLLOWS:
        notes.append(f"load_position does not follow the motor (correlation of their displacements {follows:.2f}): "
                     "left out of the identification")
        return rec.replace(load_position=None)
    judged = _judged(rec, "load_position", _displacement_ratio(rec.load_position, motor), notes,
                     against="the motor's")
    if judged.load_position is None or rec.load_velocity is None or judged.load_position is rec.load_position:
        return judged
    notes[-1] += " (and load_velocity's)"
    return judged.replace(load_velocity=-rec.load_velocity)


def _judged(rec: Recording, name: str, ratio: float | None, notes: list[str],
            against: str = "the velocity's") -> Recording:
    """``rec`` with position ``name`` left out when it does not move (``ratio`` of its motion to what it
    should be near 0), reversed when it counts the other way (near −1); an error at any other ratio
    outside ``SCALE_RANGE``."""
    lo, hi = SCALE_RANGE
    if ratio is None or lo <= ratio <= hi:
        return rec
    if abs(ratio) < SCALE_STILL:
        notes.append(f"{name} moves {ratio:.2g}× as far as it should by the velocity: not recorded, left out "
                     "of the identification")
        return rec.replace(**{name: None})
    if -hi <= ratio <= -lo:
        notes.append(f"{name} counts the other way than {against} motion: its sign is reversed")
        return rec.replace(**{name: -getattr(rec, name)})
    raise IdentificationError(
        f"{name} moves {ratio:.3g}× as far as {against} motion says: its units are not rad on the motor's "
        "scale (degrees, revolutions, counts, a gear ratio; or a velocity in rpm?), and the record cannot "
        "say which signal to rescale")


def unwrap_positions(rec: Recording) -> tuple[Recording, list[str]]:
    """``rec`` with its wrapped positions unwrapped, its glitches interpolated (and marked lost), and a
    position that jumps and stays left out; the notes say which.

    The bound on a sample's motion comes from the motor velocity (and the load velocity, when the
    record has one, for the load position; ``_top_speed``), over the longest sample period of the record."""
    notes: list[str] = []
    dt = np.diff(rec.t)
    v_max = _top_speed(rec.motor_velocity)
    if rec.load_velocity is not None:
        v_max = max(v_max, _top_speed(rec.load_velocity))
    changes: dict[str, NDArray[np.float64] | None] = {}
    glitched = np.zeros(len(rec), dtype=np.bool_)
    for name, v in (("motor_position", rec.motor_velocity), ("load_position", rec.load_velocity)):
        x = getattr(rec, name)
        if x is None:
            continue
        # the step from sample k to k+1 the velocity says (the drive's convention: v[k+1] = Δx/Ts)
        motion = v[1:] * dt if v is not None else np.zeros_like(dt)
        fixed, note, bad = _unwrapped(x, motion, v_max * float(np.max(dt)), name, rec.t)
        if note:
            changes[name] = fixed
            notes.append(note)
            glitched |= bad
    return (_with_lost(rec.replace(**changes), glitched) if changes else rec), notes


def _top_speed(v: NDArray[np.float64]) -> float:
    """The largest speed of a velocity [rad/s] that a glitch does not set: twice its 99.9th percentile
    (a drive's velocity is its encoder's difference, and spikes with it)."""
    return 2.0 * float(np.percentile(np.abs(v), 99.9))


def _with_lost(rec: Recording, lost: NDArray[np.bool_]) -> Recording:
    """``rec`` with the samples ``lost`` (shape (N,)) added to those it marks lost."""
    if not lost.any():
        return rec
    return rec.replace(metadata={**rec.metadata, LOST_SAMPLES_KEY: encode_samples(rec.lost_mask | lost)})


def _interpolated(x: NDArray[np.float64], bad: NDArray[np.bool_]) -> NDArray[np.float64]:
    """``x`` (shape (N,)) on the line between its good neighbours at the samples ``bad``."""
    k = np.arange(x.size)
    return np.where(bad, np.interp(k, k[~bad], x[~bad]), x)


def _velocity_glitches(rec: Recording, notes: list[str], interpolated: NDArray[np.bool_]) -> Recording:
    """``rec`` with the velocity samples that disagree with their position's step by far more than any
    other does (a glitch; ``GLITCH_FACTOR``), or without a position that spike, interpolated and marked
    lost, and a note on where. ``interpolated`` (shape (N,)): the samples a link or a logger lost, and the
    record interpolated: no evidence of a glitch there, nor at the sample after (its step is from one)."""
    dt = np.diff(rec.t)
    bad = np.zeros(len(rec), dtype=np.bool_)
    known = ~(interpolated | np.concatenate(([False], interpolated[:-1])))
    changes = {}
    for pos, vel in (("motor_position", "motor_velocity"), ("load_position", "load_velocity")):
        x, v = getattr(rec, pos), getattr(rec, vel)
        if x is None or v is None:
            continue
        off = np.abs(v[1:] - np.diff(x) / dt)
        steps = np.abs(np.diff(x))
        step = float(np.min(steps[steps > 0])) if steps.any() else 0.0
        limit = max(GLITCH_FACTOR * float(np.percentile(off, 99)), 2.0 * step / float(np.max(dt)))
        glitch = np.concatenate(([False], off > limit)) & known
        if glitch.any() and glitch.mean() < 0.01:
            k = int(np.argmax(glitch))
            notes.append(f"{vel} disagrees with {pos}'s step at {int(glitch.sum())} sample"
                         f"{'s' if glitch.sum() > 1 else ''} (first at t = {rec.t[k]:.4g} s, by {off[k - 1]:.3g} "
                         f"rad/s): glitches, interpolated there and left out of the time-domain fit")
            changes[vel] = _interpolated(v, glitch)
            bad |= glitch
    if rec.motor_position is None:
        v = rec.motor_velocity
        # without a position, a glitch is a spike: away from both neighbours in one direction (an encoder's
        # misread count makes one up and one down), by more than nearly any speed of the record (an impact
        # at a turning point is a spike too, but a small one)
        dv = np.diff(v)
        off = np.where(dv[:-1] * dv[1:] < 0.0, np.minimum(np.abs(dv[:-1]), np.abs(dv[1:])), 0.0)
        limit = max(GLITCH_FACTOR * float(np.percentile(off, 99)), 0.5 * _top_speed(v))
        glitch = np.concatenate(([False], off > limit, [False])) & known
        if glitch.any() and glitch.mean() < 0.01:
            k = int(np.argmax(glitch))
            notes.append(f"motor_velocity glitches at {int(glitch.sum())} sample{'s' if glitch.sum() > 1 else ''} "
                         f"(first at t = {rec.t[k]:.4g} s, a spike of {off[k - 1]:.3g} rad/s): interpolated there "
                         "and left out of the time-domain fit")
            changes["motor_velocity"] = _interpolated(v, glitch)
            bad |= glitch
    return _with_lost(rec.replace(**changes), bad) if changes else rec


def _unwrapped(x: NDArray[np.float64], motion: NDArray[np.float64], bound_rad: float, name: str,
               t: NDArray[np.float64]) -> tuple[NDArray[np.float64] | None, str, NDArray[np.bool_]]:
    """(the position unwrapped, or with its glitches interpolated, or None when its jumps are neither;
    the note; the glitched samples), or (x, "", none) without jumps.

    :param x: the position [rad], shape (N,).
    :param motion: each step's motion by the velocity [rad], shape (N − 1,) (zeros when unknown).
    :param bound_rad: the largest motion a sample allows [rad].
    """
    step = np.diff(x)
    none = np.zeros(x.size, dtype=np.bool_)
    jumps = np.flatnonzero(np.abs(step) > max(JUMP_FACTOR * bound_rad, JUMP_FLOOR_RAD))
    if jumps.size == 0:
        return x, "", none
    excess = step[jumps] - motion[jumps]
    unit = float(np.min(np.abs(excess)))  # a wrap jumps by one period at least
    if unit > bound_rad:  # (a glitch the velocity repeats has no excess over the motion)
        turns = np.round(excess / unit)
        period = float(np.median(np.abs(excess) / np.abs(turns)))
        if abs(period - 2.0 * math.pi) <= PERIOD_RTOL * 2.0 * math.pi:
            period = 2.0 * math.pi  # a single-turn position in rad: its period exactly
        # a wrapped position stays within one period; a spike and back jumps by equal steps too, but not that
        within = float(np.ptp(x)) <= (1.0 + PERIOD_RTOL) * period + bound_rad
        if within and np.all(np.abs(excess - turns * period) <= PERIOD_RTOL * period + bound_rad):
            correction = np.zeros_like(x)
            correction[jumps + 1] = -turns * period
            return x + np.cumsum(correction), (
                f"{name} wraps {jumps.size} times at a period of {period:.6g} rad (a single-turn or counter "
                "position): unwrapped"), none
    k = int(jumps[0])
    glitched = _spikes(x, jumps, bound_rad)
    if glitched is not None:
        return _interpolated(x, glitched), (
            f"{name} glitches at {int(glitched.sum())} sample{'s' if glitched.sum() > 1 else ''} (first at "
            f"t = {t[k + 1]:.4g} s, by {step[k]:.3g} rad, and back): interpolated there and left out of the "
            "time-domain fit"), glitched
    return None, (f"{name} jumps by {step[k]:.3g} rad at sample {k + 1} (t = {t[k + 1]:.4g} s) where the "
                  f"velocity moves it by at most {bound_rad:.2g} rad, and does not come back "
                  f"({jumps.size} jump{'s' if jumps.size > 1 else ''}, no wrap of one period: a reset or a "
                  "slipping encoder): left out of the identification"), none


def _spikes(x: NDArray[np.float64], jumps: NDArray[np.intp], bound_rad: float) -> NDArray[np.bool_] | None:
    """The samples of a position ``x`` (shape (N,)) that jumped away and came back within ``GLITCH_SAMPLES``:
    back within two samples' motion (``bound_rad`` each) of the line its last two good samples set (not
    of the velocity's motion: a drive's velocity is the difference of the glitched counts), shape (N,);
    None when a jump does not come back."""
    bad = np.zeros(x.size, dtype=np.bool_)
    for k in jumps:
        if bad[k]:
            continue  # the way back of a glitch already found
        end = min(x.size - 1, int(k) + GLITCH_SAMPLES)
        slope = x[k] - x[k - 1] if k > 0 else 0.0
        line = x[k] + slope * np.arange(1, end - k + 1)
        back = np.flatnonzero(np.abs(x[k + 1:end + 1] - line) <= 2.0 * bound_rad + 1e-9 * abs(x[k]))
        back = back[back > 0]
        if back.size == 0:
            return None
        bad[k + 1:k + 1 + int(back[0])] = True
    return bad


#: A record starts in motion when its speed over its first ``_START_WINDOW_S`` is above this share of its
#: largest (an experiment from rest shows its encoder's quantization alone there).
_START_MOVING = 0.05
_START_WINDOW_S = 1e-3


@dataclass(frozen=True)
class InitialMotion:
    """How the axis moves at sample 0 (both 0 for a record that starts at rest: every experiment this tool
    runs; a record cut from a longer one may start in motion)."""

    speed_rad_s: float = 0.0
    acceleration_rad_s2: float = 0.0

    @property
    def moving(self) -> bool:
        return self.speed_rad_s != 0.0

    def twist_rad(self, J_l: float, B_l: float, K: float, epsilon_rad: float) -> float:
        """x_m − x_l at sample 0 of a load that moves with the motor [rad]: on the flank the shaft torque
        J_l·a + B_l·v pushes it against, twisted by that torque over K; 0 (the gap's middle) at rest."""
        if not self.moving:
            return 0.0
        shaft = J_l * self.acceleration_rad_s2 + B_l * self.speed_rad_s
        return math.copysign(epsilon_rad, shaft) + shaft / K if shaft != 0.0 else 0.0


def initial_motion(position: NDArray[np.float64], sample_rate_hz: float) -> InitialMotion:
    """The motion at sample 0 of a record that starts moving (a parabola through ``position`` [rad],
    shape (N,), over its first millisecond, at least 8 samples); none for one that starts at rest."""
    n = max(8, int(round(_START_WINDOW_S * sample_rate_hz)))
    if position.size < 4 * n:
        return InitialMotion()
    t = np.arange(n) / sample_rate_hz
    c = np.polyfit(t, position[:n], 2)
    top = float(np.max(np.abs(np.diff(position)))) * sample_rate_hz
    return InitialMotion(float(c[1]), float(2.0 * c[0])) if abs(c[1]) > _START_MOVING * top else InitialMotion()
