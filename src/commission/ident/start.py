"""The frequency-domain start (paper steps 2–3) and the residual's low-pass for a record.

The FRD of the whole record, at the resolution its length allows, over the band its torque
actually excites, is fitted with a 2/3 rational model (transient term, delay, converged
Sanathanan–Koerner; :mod:`commission.ident.tffit`), and the fit mapped to physical parameters.
Friction and impacts distort the low frequencies: bins whose local-polynomial quality is low are
left out, and fits from raised low band edges are candidates too; the time domain (the projected
torque residual at ε = 0) picks among them.
"""

from __future__ import annotations

import dataclasses
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.signal import butter, sosfreqz

from ..exceptions import IdentificationError
from ..recording import Recording
from .frd import FRD, estimate_frd
from .residual import ResidualProblem, motor_position_samples
from .scan import cell_rates, projected_cell
from .tffit import TransferFunctionFit, fit_transfer_function
from .twomass import TwoMassParameters, from_velocity_tf, modes

__all__ = ["Start", "cutoff_note", "excited_band_hz", "frequency_start", "linear_start", "quantization_floor_nm",
           "residual_cutoff"]

#: Raised low band edges of the frequency-domain start [Hz], tried when the whole band's fit is
#: distorted (masked bins, or no physical plant).
_RAISED_EDGES_HZ = (1.0, 5.0, 10.0)
#: A further edge, tried when the FRD's resonance peak lies at ≥ 3× it (both modes stay in band).
_HIGH_EDGE_HZ = 20.0
#: The chirp's band ends where its smoothed spectrum falls below this fraction of its median.
_BAND_EDGE_LEVEL = 0.1
#: The top of the band the identifier fits, as a share of the sample rate.
BAND_TOP_PER_SAMPLE_RATE = 0.45


@dataclass(frozen=True)
class Start:
    """The frequency-domain start."""

    frd: FRD
    fit: TransferFunctionFit | None
    """The fit of the whole band (None when it failed)."""
    parameters: TwoMassParameters
    how: str
    """"exact" (the fit maps to a physical plant) or "modes" (split from the modes)."""
    delay_s: float
    """Delay of the chosen fit [s] (one sample, plus a current loop's lag when fitted)."""
    band_low_hz: float
    """Low band edge the chosen fit used [Hz]."""


def excited_band_hz(torque_ref: NDArray[np.float64], sample_rate_hz: float) -> float:
    """Upper edge of the band the torque excites [Hz]: where its spectrum, averaged over
    log-spaced bands, falls for good below ``_BAND_EDGE_LEVEL`` × its median above 1 Hz
    (a chirp's amplitude spectrum is flat over its sweep)."""
    u = np.asarray(torque_ref, dtype=float)
    fs = float(sample_rate_hz)
    p = np.abs(np.fft.rfft(u - u.mean())) ** 2
    f = np.fft.rfftfreq(u.size, 1.0 / fs)
    edges = np.geomspace(1.0, 0.5 * fs, 121)
    idx = np.searchsorted(f, edges)
    power = np.array([p[a:b].mean() if b > a else 0.0 for a, b in zip(idx[:-1], idx[1:])])
    level = float(np.median(power[power > 0])) if np.any(power > 0) else 0.0
    above = np.flatnonzero(power >= _BAND_EDGE_LEVEL * level)
    return float(edges[above[-1] + 1]) if above.size else 0.5 * fs


def linear_start(num: NDArray[np.float64], den: NDArray[np.float64],
                 phi: float = 0.5) -> tuple[TwoMassParameters, str]:
    """Physical parameters from a fitted V_m/T_ref = num/den, robust to a bad damping split.

    Exact inversion (:func:`commission.ident.twomass.from_velocity_tf`) when it gives a physical
    plant; otherwise (typical on backlash data: B_m or B_l comes out negative) the well-conditioned
    quantities are kept — J_m = 1/b2, B_m + B_l = a0/b0, ω_a² = b0/b2 = K/J_l, the resonance
    ω_r² ≈ K·(1/J_m + 1/J_l), D + B_l = b1·J_m·J_l — and the friction is split with ``phi``.
    Returns the parameters and how they were obtained ("exact" or "modes").
    """
    num = np.asarray(num, dtype=float) / float(den[0])
    den = np.asarray(den, dtype=float) / float(den[0])
    try:
        return from_velocity_tf(num, den), "exact"
    except IdentificationError:
        pass
    b2, b1, b0 = num
    a0 = den[3]
    if not (b2 > 0 and b0 > 0 and a0 > 0):
        raise IdentificationError("the fitted transfer function is not that of a two-mass plant "
                                  f"(b2={b2:.3g}, b0={b0:.3g}, a0={a0:.3g} must be positive)")
    J_m, S, wa2 = 1.0 / b2, a0 / b0, b0 / b2
    poles = np.roots(den)
    cplx = poles[np.abs(poles.imag) > 1e-9 * np.abs(poles)]
    if cplx.size == 0:
        raise IdentificationError("the fitted transfer function has no resonance (no complex poles)")
    wr2 = float(np.max(np.abs(cplx)) ** 2)
    if wr2 <= wa2:
        raise IdentificationError("the fitted anti-resonance lies above the resonance: not a two-mass plant")
    J_l = J_m * (wr2 / wa2 - 1.0)
    K = wa2 * J_l
    B_l = phi * S
    X = max(b1 * J_m * J_l, 0.0)
    D = max(X - B_l, 0.05 * X, 1e-6 * K / math.sqrt(wr2))
    return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=(1.0 - phi) * S, B_l=B_l, K=K, D=D), "modes"


def _bins(frd: FRD, keep: NDArray[np.bool_]) -> FRD:
    """``frd`` restricted to the bins ``keep`` (the DFTs and the quality are per bin)."""
    return dataclasses.replace(frd, frequency_hz=frd.frequency_hz[keep], response=frd.response[keep],
                               quality=frd.quality[keep], input_dft=frd.input_dft[keep],
                               output_dft=frd.output_dft[keep])


def _masked_fit(frd: FRD, quality_threshold: float, fit_delay: bool) -> tuple[TransferFunctionFit, int]:
    """The 2/3 fit without the bins of low quality (when some, but at most half, are); a current
    loop's lag fitted as extra delay. Returns (fit, bins left out)."""
    good = frd.quality >= quality_threshold
    masked = not good.all() and good.sum() >= 0.5 * good.size
    return fit_transfer_function(_bins(frd, good) if masked else frd, fit_delay=fit_delay), \
        int((~good).sum()) if masked else 0


def frequency_start(rec: Recording, problem: ResidualProblem, *, band_hz: tuple[float, float],
                    resolution_hz: float, quality_threshold: float, fit_delay: bool,
                    notes: list[str], raise_edges: bool = True) -> Start:
    """The FRD, its fit, and the physical start (see the module docstring). ``raise_edges`` False: the
    whole band's fit only, no search over raised low band edges (a load encoder's record, whose start
    comes from the encoders: of the FRD's start only the delay is used, and the search was most of the
    start's time)."""
    fs = rec.sample_rate_hz
    frd = estimate_frd(rec.torque_ref, rec.motor_velocity, fs, band_hz=band_hz, resolution_hz=resolution_hz)
    fits: list[tuple[float, TransferFunctionFit]] = []
    whole: TransferFunctionFit | None = None
    masked = 0
    try:
        whole, masked = _masked_fit(frd, quality_threshold, fit_delay)
        fits.append((band_hz[0], whole))
    except IdentificationError as err:
        notes.append(f"frequency-domain fit of the whole band failed ({err})"
                     + ("; low band edges raised" if raise_edges else ""))
    if masked:
        notes.append(f"frequency-domain start: {masked} of {frd.frequency_hz.size} FRD bins left out "
                     f"(quality < {quality_threshold:g})")
    # a start whose resonance lies beyond fs/4 is no start (the load simulation's one step per
    # sample does not resolve it), nor one whose anti-resonance lies below the band it came from
    f_max = 0.25 * fs

    def usable(p: TwoMassParameters, f_lo: float) -> bool:
        try:
            m = modes(p)
        except IdentificationError:  # no resonance at all
            return False
        return min(p.K, p.J_l, p.J_m) > 0 and m.f_resonance_hz < f_max and m.f_antiresonance_hz > f_lo

    if whole is not None and not masked:
        try:
            p, how = linear_start(whole.num, whole.den)
            if how == "exact" and usable(p, band_hz[0]):
                return Start(frd, whole, p, how, float(whole.delay_s), band_hz[0])
        except IdentificationError:
            pass
    above = frd.frequency_hz >= 5.0
    f_peak = (float(frd.frequency_hz[above][np.argmax(np.abs(frd.response[above]) * frd.frequency_hz[above])])
              if above.any() else 0.0)
    edges = (_RAISED_EDGES_HZ + ((_HIGH_EDGE_HZ,) if f_peak >= 3.0 * _HIGH_EDGE_HZ else ())) if raise_edges else ()
    for f_lo in (f for f in edges if band_hz[0] < f < 0.1 * band_hz[1]):
        try:
            fits.append((f_lo, _masked_fit(_bins(frd, frd.frequency_hz >= f_lo - 1e-9 * frd.resolution_hz),
                                           quality_threshold, fit_delay)[0]))
        except IdentificationError:
            continue
    scored: list[tuple[float, float, TwoMassParameters, str, float]] = []
    for f_lo, fit in fits:
        try:
            p, how = linear_start(fit.num, fit.den)
        except IdentificationError:
            continue
        if usable(p, f_lo):
            cost = projected_cell(problem, cell_rates(p, 0.5), 0.0, coulomb=True).cost_nm
            scored.append((cost, f_lo, p, how, float(fit.delay_s)))
    if not scored:
        p, how = _shape_start(frd, f_max), "shape"
        if p is None:
            p, how = inertia_start(frd, f_max), "inertia"
        if p is None:
            raise IdentificationError("the frequency response is not that of a two-mass plant with its resonance "
                                      f"below fs/4 = {f_max:.0f} Hz, from any low band edge up to "
                                      f"{max(edges, default=band_hz[0]):g} Hz, nor shows an inertia")
        what = ("its shape" if how == "shape" else "its apparent inertia (no resonance shows; the fit's quality will "
                "say whether the record determines one)")
        notes.append("no rational fit of the frequency response gave a two-mass plant (friction or impacts distort "
                     f"it); the start is read off {what}: resonance {modes(p).f_resonance_hz:.1f} Hz, "
                     f"anti-resonance {modes(p).f_antiresonance_hz:.1f} Hz")
        return Start(frd, whole, p, how, 1.0 / fs, band_hz[0])
    cost, f_lo, p, how, delay = min(scored, key=lambda c: (c[0], c[1]))
    if f_lo > band_hz[0]:
        notes.append(f"frequency-domain start fitted from {f_lo:g} Hz up (chosen by the torque residual "
                     "among low band edges; the low band is distorted)")
    return Start(frd, whole, p, how, delay, f_lo)


def _shape_start(frd: FRD, f_max: float) -> TwoMassParameters | None:
    """A start read off the FRD's shape when no rational fit gives a two-mass plant: the resonance at the
    peak of the apparent inertia's inverse ω·|G| above 5 Hz, the anti-resonance at its dip just below, J_m
    from the high-frequency asymptote |G| → 1/(J_m·ω), ζ 0.05 and a mechanical corner at 1 Hz
    (both refined by the fit). None when the shape shows no such pair."""
    f = frd.frequency_hz
    band = (f >= 5.0) & (f < f_max)
    if band.sum() < 20:
        return None
    # ω·|G| smoothed over ±5 % in frequency (its median): the bins of one record are noisy
    wg = 2.0 * np.pi * f * np.abs(frd.response)
    lo = np.searchsorted(f, 0.95 * f)
    hi = np.searchsorted(f, 1.05 * f, side="right")
    smooth = np.array([np.median(wg[a:max(b, a + 1)]) for a, b in zip(lo, hi)])
    idx = np.flatnonzero(band)
    r = idx[int(np.argmax(smooth[idx]))]
    # the dip just below it: a two-mass plant's anti-resonance lies above f_r/√(1 + J_l/J_m), f_r/3.5 for
    # the loads drives carry (friction bends the low band down, so not the band's global minimum)
    below = idx[(idx < r) & (f[idx] > f[r] / 3.5)]
    high = idx[f[idx] > 1.5 * f[r]]
    if below.size < 5 or high.size < 5:
        return None
    a = below[int(np.argmin(smooth[below]))]
    f_r, f_a = float(f[r]), float(f[a])
    if not f_a < f_r:
        return None
    J_m = float(np.median(1.0 / smooth[high]))
    J_l = J_m * ((f_r / f_a) ** 2 - 1.0)
    K = (2.0 * np.pi * f_a) ** 2 * J_l
    B = 2.0 * np.pi * 1.0 * (J_m + J_l)
    D = 2.0 * 0.05 * 2.0 * np.pi * f_r / (1.0 / J_m + 1.0 / J_l)
    return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=0.5 * B, B_l=0.5 * B, K=K, D=D)


def inertia_start(frd: FRD, f_max: float) -> TwoMassParameters | None:
    """The last start, for an FRD that shows no resonance a fit or its shape can place: from the apparent
    inertia Im(1/G)/ω (a viscous term goes to the real part) — its median over the band's lowest 2 %
    (at least 5 bins) is J_m + J_l, over its top 20 % below ``f_max`` J_m (above a resonance the motor
    moves alone) — and the anti-resonance where it falls half way between the two (past the
    anti-resonance the load moves against the motor; J_m + J_l split evenly when the two do not differ),
    ζ 0.05, a mechanical corner at 1 Hz. Where friction holds the motor in the lowest band, which then shows
    no positive inertia, the top's is taken for each side and the anti-resonance at the band's geometric
    middle. None when the top shows no positive inertia either."""
    f = frd.frequency_hz
    with np.errstate(divide="ignore", invalid="ignore"):
        j = (1.0 / frd.response).imag / (2.0 * np.pi * f)
    inside = np.isfinite(j) & (f < f_max)
    f, j = f[inside], j[inside]
    if f.size < 20:
        return None
    total = float(np.median(j[:max(5, f.size // 50)]))
    top = float(np.median(j[-max(5, f.size // 5):]))
    held = not total > 0.0
    if held:
        if not top > 0.0:
            return None
        total = 2.0 * top
    J_m = top if 0.0 < top < 0.9 * total else 0.5 * total
    J_l = total - J_m
    # the first fall below half way above the low band, in its running median over ±25 bins (at most
    # 2,000 points of it)
    step = max(1, f.size // 2000)
    at = np.arange(max(5, f.size // 50), f.size, step)
    smooth = np.array([np.median(j[max(0, i - 25):i + 26]) for i in at])
    below = np.flatnonzero(smooth < 0.5 * (total + J_m))
    f_a = float(f[at[below[0]]]) if below.size and not held else float(np.sqrt(f[0] * f[-1]))
    K = (2.0 * np.pi * f_a) ** 2 * J_l
    w_r = math.sqrt(K * total / (J_m * J_l))
    B = 2.0 * np.pi * 1.0 * total
    D = 2.0 * 0.05 * w_r / (1.0 / J_m + 1.0 / J_l)
    return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=0.5 * B, B_l=0.5 * B, K=K, D=D)


def quantization_floor_nm(step_rad: float, J_m: float, sample_rate_hz: float, cutoff_hz: float) -> float:
    """RMS torque residual [N·m] that a motor position quantized in steps of ``step_rad`` leaves
    through J_m·ẍ_m: uniform quantization noise (variance step²/12, white) through the second
    difference (|H|² = 16·sin⁴(ω/2)) times fs², and the residual's zero-phase low-pass (the 4th-order
    Butterworth of :func:`commission.ident.residual.prepare_residual`, applied twice: |H|⁴)."""
    sos = butter(4, min(cutoff_hz, 0.49 * sample_rate_hz), fs=sample_rate_hz, output="sos")
    w, h = sosfreqz(sos, worN=4096)
    power = 16.0 * np.sin(0.5 * w) ** 4 * np.abs(h) ** 4
    var = step_rad * step_rad / 12.0 * float(np.sum(0.5 * (power[1:] + power[:-1]) * np.diff(w))) / math.pi
    return J_m * sample_rate_hz ** 2 * math.sqrt(max(var, 0.0))


def position_step_rad(rec: Recording) -> float:
    """The motor encoder's step [rad]: the smallest position change in the record between samples the link
    did not lose (0: none)."""
    from .kalman import position_step_rad as step_of

    return step_of(motor_position_samples(rec.motor_position, rec.motor_velocity, rec.sample_rate_hz),
                   ~rec.lost_mask)


def residual_cutoff(rec: Recording, start: TwoMassParameters, band_high_hz: float, configured_hz: float,
                    torque_rms_nm: float, target_ratio: float) -> dict[str, Any]:
    """The residual's low-pass for this record [Hz], with the quantization floor it leaves.

    At least the configured cut-off and twice the start's resonance, at most the excited band and
    0.4·fs; then lowered (not below twice the resonance) until the encoder's quantization, through
    the second difference, leaves at most ``target_ratio`` of RMS τ_ref: a coarse encoder's
    acceleration noise rises as f².
    """
    fs = rec.sample_rate_hz
    f_res = modes(start).f_resonance_hz
    top = min(band_high_hz, 0.4 * fs)
    fc = min(max(configured_hz, 2.0 * f_res), top)
    step = position_step_rad(rec)
    ref = max(torque_rms_nm, 1e-300)

    def floor(f_hz: float) -> float:
        return quantization_floor_nm(step, start.J_m, fs, f_hz) / ref

    out: dict[str, Any] = {"cutoff_hz": fc, "position_step_rad": step, "quantization_floor_ratio": floor(fc)}
    if out["quantization_floor_ratio"] > target_ratio:
        lowest = min(fc, 2.0 * f_res)
        new = max(lowest, brentq(lambda f: floor(f) - target_ratio, 1e-3 * fc, fc)) if floor(lowest) < target_ratio \
            else lowest
        out.update(cutoff_hz=new, quantization_floor_ratio=floor(new), unlowered_cutoff_hz=fc)
    return out


def cutoff_note(cutoff: dict[str, Any]) -> str | None:
    """The note on a :func:`residual_cutoff` the encoder's quantization lowered, or could not lower further
    (twice the start's resonance is its floor); None where the encoder left the cut-off alone."""
    if not cutoff.get("unlowered_cutoff_hz"):
        return None
    cut, unlowered = cutoff["cutoff_hz"], cutoff["unlowered_cutoff_hz"]
    where = (f"low-passed at {cut:.0f} Hz instead of {unlowered:.0f} Hz" if cut < 0.99 * unlowered else
             f"it leaves {100 * cutoff['quantization_floor_ratio']:.2g} % of RMS τ_ref even low-passed at {cut:.0f} Hz, "
             "as low as twice the start's resonance allows")
    return (f"the motor encoder's step ({cutoff['position_step_rad']:.3g} rad) would leave much of the torque as noise "
            f"in the residual; {where} — a finer encoder would let the fit see more")


@dataclass(frozen=True)
class EncoderStart:
    """The start from a load encoder (:func:`load_encoder_start`)."""

    parameters: TwoMassParameters
    epsilon_rad: float
    coulomb_motor_nm: float
    coulomb_load_nm: float
    cost_nm: float
    """RMS of the motor equation's residual at the best ε [N·m]."""
    lag_s: float = 0.0
    """The current loop's time constant T_c the equations fit best [s] (0 when not searched)."""


#: The load encoder's origin is searched for when a shift of the twist by this much [°] either way fits the
#: encoders' equations better than none.
_ORIGIN_PROBE_DEG = 0.002


#: Current-loop time constants T_c [s] the encoders' start scans (loops of ~50 Hz to ~16 kHz), after 0.
_LAG_GRID_S = np.geomspace(10e-6, 3e-3, 25)


def _deadzone(z: NDArray[np.float64], eps: float) -> NDArray[np.float64]:
    return np.where(z > eps, z - eps, np.where(z < -eps, z + eps, 0.0))


def load_encoder_start(problem: ResidualProblem, epsilon_top_rad: float, threads: int = 1,
                       current_loop: bool = False) -> EncoderStart | None:
    """Every parameter and ε from both encoders by linear least squares, no simulation.

    With the load's position measured, the shaft torque is K·y + D·ẏ of the measured twist
    y = dz(x_m − x_l; ε), and both equations of motion,

        J_m·ẍ_m + B_m·ẋ_m + F_cm·sgn ẋ_m + K·y + D·ẏ = τ        J_l·ẍ_l + B_l·ẋ_l + F_cl·sgn ẋ_l = K·y + D·ẏ,

    are linear in the parameters for a given ε (equation error, the same low-pass as the residual):
    ε is scanned (log-spaced, then refined around the best), each ε one small least-squares
    problem. With ``current_loop`` τ is τ_ref behind a first-order loop whose time constant T_c is
    scanned with ε (:data:`_LAG_GRID_S`, then refined; each T_c one more right-hand side of the same
    problem): a loop near the band's top leaves τ_ref a poor stand-in for τ, and the stiffness and load
    inertia that would explain the difference come out negative. T_c is the likeliest local minimum
    below the grid's top (:func:`_loop_index`): a cost still falling there mimics a rigid body's J/B.
    Noise in the measured twist biases the damping (errors in variables), so this is the estimator's
    start, not its answer. None when no (ε, T_c) gives positive inertias and stiffness. The ε are shared
    out over ``threads`` (each its own problem: the same answer with any number).
    """
    if problem.load_position is None:
        return None
    loop = current_loop and problem.torque_ref is not None
    lags = np.concatenate(([0.0], _LAG_GRID_S)) if loop else np.zeros(1)
    grid = np.concatenate(([0.0], np.geomspace(math.radians(0.005), max(epsilon_top_rad, math.radians(0.01)), 40)))
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        solved = list(pool.map(_encoder_equations(problem, lags), grid))
        j = _loop_index(np.array([c for c, _ in solved]).min(axis=0))
        best = _best_of([(c[j:j + 1], th[j:j + 1]) for c, th in solved])
        if best is None:
            return None
        i = best[1]
        fine = np.linspace(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)], 11)
        fine_lags = (np.linspace(lags[max(j - 1, 0)], lags[min(j + 1, lags.size - 1)], 11) if lags.size > 1
                     else lags)
        refined = _best_of(list(pool.map(_encoder_equations(problem, fine_lags), fine)))
    (cost, th), eps, lag = ((refined[0], fine[refined[1]], fine_lags[refined[2]])
                            if refined is not None and refined[0][0] <= best[0][0]
                            else (best[0], grid[i], lags[j]))
    J_m, B_m, J_l, B_l, K, D, F_m, F_l = (float(v) for v in th)
    S = max(abs(B_m) + abs(B_l), 1e-9)
    p = TwoMassParameters(J_m=J_m, J_l=J_l, B_m=max(B_m, 1e-3 * S), B_l=max(B_l, 1e-3 * S), K=K,
                          D=max(D, 1e-6 * K))
    return EncoderStart(p, float(eps), max(F_m, 0.0), max(F_l, 0.0), cost, float(lag))


def _loop_index(cost: NDArray[np.float64]) -> int:
    """The index of the current loop's time constant in the lag grid from the least cost at each (n_lags,):
    the lowest local minimum below the grid's top, 0 where there is none. A cost still falling at the top is
    a rigid body's J/B (the lag standing in for the inertia, the twist's terms dropped), not a loop's."""
    n = cost.size
    minima = [j for j in range(n - 1) if math.isfinite(cost[j]) and cost[j] <= cost[j + 1]
              and (j == 0 or cost[j] <= cost[j - 1])]
    return min(minima, key=lambda j: cost[j]) if minima else 0


def _best_of(solved: list[tuple[NDArray[np.float64], NDArray[np.float64]]]
             ) -> tuple[tuple[float, NDArray[np.float64]], int, int] | None:
    """((cost [N·m], parameters), ε index, T_c index) of the least cost over ``solved`` (per ε: the costs
    (n_lags,) and parameters (n_lags, 8) of :func:`_encoder_equations`); None when every cost is infinite."""
    costs = np.array([c for c, _ in solved])
    i, j = np.unravel_index(int(np.argmin(costs)), costs.shape)
    if not math.isfinite(costs[i, j]):
        return None
    return (float(costs[i, j]), solved[i][1][j]), int(i), int(j)


def load_origin_rad(problem: ResidualProblem, start: EncoderStart | None) -> float:
    """How far the load encoder's origin lies from the motor's [rad]: the shift of the measured twist that
    centres the gap (0 when centred). A load encoder's zero is its own; the twist the model reads is
    x_m − x_l measured from a common origin, the gap's middle. The encoders' equations of motion
    (:func:`load_encoder_start`) fit far better at the right shift (0.01° off on the reference plant: 10×
    the residual), so the shift and ε are fitted together on them (Nelder–Mead from the middle of the
    twist's range) when the centred gap is not already the best within ±``_ORIGIN_PROBE_DEG``, or the
    twist never crosses 0; the shift is kept when it halves the residual of the centred gap (at the
    start's ε and at the one found), else 0 (with no ``start``, whenever the fit has positive inertias
    and stiffness: the centred gap gave none)."""
    from scipy.optimize import minimize

    solve = _scalar(_encoder_equations(problem, np.array([start.lag_s if start is not None else 0.0])))
    h = math.radians(_ORIGIN_PROBE_DEG)
    c = problem.spline
    z = np.concatenate((c[:, 3], [c[-1].sum()])) - problem.load_position
    middle, half = 0.5 * float(np.max(z) + np.min(z)), 0.5 * float(np.ptp(z))
    # (far from the right shift the residual is flat: a twist that never crosses 0 is searched anyway)
    if (start is not None and abs(middle) <= half
            and min(solve(start.epsilon_rad, d)[0] for d in (-h, h)) >= start.cost_nm):
        return 0.0
    # (ε within the twist's range: a start that read the offset as a gap has ε beyond it, and no stiffness)
    eps0 = max(min(start.epsilon_rad, 0.9 * half) if start is not None else 0.5 * half, h)
    before = start.cost_nm if start is not None else math.inf

    def cost(v: NDArray[np.float64]) -> float:
        c = solve(abs(float(v[1])), float(v[0]))[0]
        return c if math.isfinite(c) else 1e300

    first = cost(np.array([middle, eps0]))
    res = minimize(cost, np.array([middle, eps0]), method="Nelder-Mead",
                   options={"initial_simplex": np.array([[middle, eps0], [middle + 0.1 * half + h, eps0],
                                                         [middle, 0.5 * eps0]]),
                            "xatol": 1e-7, "fatol": 1e-6 * min(before, first), "maxfev": 400})
    # against the centred gap at the ε found (the start's ε is a grid's)
    centred = min(before, cost(np.array([0.0, float(res.x[1])])))
    return float(res.x[0]) if float(res.fun) < 0.5 * centred else 0.0


def _encoder_equations(problem: ResidualProblem, lags_s: NDArray[np.float64]) -> Any:
    """``solve(ε, shift=0)``: the encoders' equations of motion at gap ε [rad] with the measured twist
    shifted by ``shift`` [rad], τ_ref behind a current loop of each time constant in ``lags_s`` [s]
    (:func:`load_encoder_start`): (RMS residuals [N·m] (n_lags,), inf where an inertia or the stiffness is
    not positive; the parameters (J_m, B_m, J_l, B_l, K, D, F_m, F_l) (n_lags, 8))."""
    fs = problem.sample_rate_hz
    c = problem.spline
    x = np.concatenate((c[:, 3], [c[-1].sum()]))
    xl = problem.load_position
    z = x - xl
    lp = problem.lowpass
    al = lp(np.ascontiguousarray((xl[2:] - 2.0 * xl[1:-1] + xl[:-2]) * fs * fs))
    vl_raw = (xl[2:] - xl[:-2]) * (0.5 * fs)
    vl = lp(np.ascontiguousarray(vl_raw))
    sl = lp(np.ascontiguousarray(np.tanh(vl_raw / problem.velocity_scale_rad_s)))
    am, vm = problem.acceleration_f, problem.velocity_f
    sm = problem.coulomb_f if problem.coulomb_f is not None else np.zeros_like(am)
    n = am.size
    inner = slice(4, n - 4)
    zero = np.zeros(n)
    # the motor block's right-hand sides, one per time constant (the load block's are zero)
    b = np.stack([problem.lagged_torque_f(float(t))[inner] for t in lags_s], axis=1)

    def solve(eps: float, shift: float = 0.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        y = _deadzone(z - shift if shift else z, eps)
        Y = lp(np.ascontiguousarray((y[:-2] + 4.0 * y[1:-1] + y[2:]) / 6.0))
        Yd = lp(np.ascontiguousarray((y[2:] - y[:-2]) * (0.5 * fs)))
        A = np.vstack((np.stack((am, vm, zero, zero, Y, Yd, sm, zero), axis=1)[inner],
                       np.stack((zero, zero, -al, -vl, Y, Yd, zero, -sl), axis=1)[inner]))
        sc = np.sqrt(np.sum(A * A, axis=0))
        sc[sc == 0.0] = 1.0
        A /= sc
        # the normal equations of the unit columns, one solve for every right-hand side (least squares: a
        # column of zeros, ε beyond the twist's range, gets 0); a start needs no more than their accuracy
        th = np.linalg.lstsq(A.T @ A, A[: n - 8].T @ b, rcond=None)[0]
        r = A[: n - 8] @ th - b
        th /= sc[:, None]
        ok = (th[0] > 0) & (th[2] > 0) & (th[4] > 0)
        return np.where(ok, np.sqrt(np.mean(r * r, axis=0)), math.inf), th.T

    return solve


def _scalar(solve: Any) -> Any:
    """One time constant's ``solve`` of :func:`_encoder_equations`: (cost [N·m], parameters (8,))."""
    def one(eps: float, shift: float = 0.0) -> tuple[float, NDArray[np.float64]]:
        costs, th = solve(eps, shift)
        return float(costs[0]), th[0]
    return one


def measured_band_hz(frd: FRD, level: float = 0.5) -> tuple[float, float]:
    """The band the record measured with good signal [Hz]: from the FRD's first bin up to the last
    frequency where its quality, averaged over ±5 % of the frequency, is at least ``level``."""
    f, q = frd.frequency_hz, frd.quality
    if not np.all(np.isfinite(q)):
        return float(f[0]), float(f[-1])
    c = np.concatenate(([0.0], np.cumsum(q)))
    lo = np.searchsorted(f, 0.95 * f)
    hi = np.searchsorted(f, 1.05 * f, side="right")
    smooth = (c[hi] - c[lo]) / np.maximum(hi - lo, 1)
    good = np.flatnonzero(smooth >= level)
    return float(f[0]), float(f[good[-1]]) if good.size else float(f[0])
