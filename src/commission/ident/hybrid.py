"""The identification pipelines: ``hybrid`` (default, accurate) and ``paper`` (faithful).

``hybrid``, stage by stage:

1. ``start`` — FRD of τ_ref → v_m over the band the torque excites, at the resolution the record's
   length allows, its 2/3 fit and the physical start (:mod:`commission.ident.start`); the
   residual's low-pass for this record (the band, the resonance, the encoder's quantization).
2. ``scan``  — (ε, damping split) cells on the projected torque residual, J_m, B_m, J_l and the
   motor-side columns solved linearly in each (:mod:`commission.ident.scan`).
3. ``fit``   — one prediction-error least squares of every parameter and the candidate terms from
   the best cell, on the residual with the load-state observer; terms kept by their Wald
   statistic (:mod:`commission.ident.estimator`).
4. ``assess`` — residual, whiteness, intervals: approximate and why (:mod:`commission.ident.assess`).
5. ``check`` — the paper's step 5 for the start and the result: the dead-zone model simulated
   open loop, its FRD against the measured one (:func:`commission.ident.paper.frd_error`).

A record whose samples are not uniform (host-streamed) is brought to its nominal grid first
(:mod:`commission.ident.resample`). ``paper`` wraps :func:`commission.ident.paper.paper_identify`
(Bayesian search of ε on max|v_m − v̂_m|, steps 5–6 iterated) into the same result.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from ..exceptions import IdentificationError
from ..recording import Recording
from .estimator import ModelTerms, PemFit, fit, select_terms
from .options import IdentificationOptions, Method, options_from_mapping
from .result import FitQuality, Identification, StageResult
from .twomass import TwoMassParameters, modes

__all__ = ["FitQuality", "Identification", "IdentificationOptions", "Method", "StageResult", "identify",
           "options_from_mapping"]

Progress = Callable[[str, float], None]
#: Load Coulomb friction is fitted when the scan's friction column exceeds this × RMS τ_ref (its
#: simulation takes sub-steps wherever the load nearly stops: 2–3× the cost of one without).
_FRICTION_SCREEN = 0.02
#: The hybrid scan's ε step, in the configured resolutions.
_SCAN_STEP = 5
#: Quantization floor the residual's low-pass is lowered to, in good-fit levels.
_QUANTIZATION_TARGET = 2.5
#: Scans at the fitted linear parameters at most (each followed by a fit when its best ε differs).
_RESCANS = 2


class _Stages:
    def __init__(self, progress: Progress | None) -> None:
        self.items: list[StageResult] = []
        self.progress = progress
        self._t = 0.0

    def start(self, name: str, fraction: float) -> None:
        if self.progress is not None:
            self.progress(name, fraction)
        self._t = time.perf_counter()

    def done(self, name: str, **detail: Any) -> None:
        self.items.append(StageResult(name, time.perf_counter() - self._t, detail))


def _check_recording(rec: Recording, opt: IdentificationOptions) -> None:
    fs = rec.sample_rate_hz
    if opt.band_hz is not None and opt.band_hz[1] > fs / 2:
        raise IdentificationError(f"band upper edge {opt.band_hz[1]:g} Hz is above Nyquist ({fs / 2:g} Hz)")
    if np.ptp(rec.torque_ref) == 0.0:
        raise IdentificationError("torque_ref is constant: the axis was not excited")
    if np.ptp(rec.motor_velocity) == 0.0:
        raise IdentificationError("motor_velocity is constant: the motor did not move")
    n = len(rec)
    if n < 64:
        raise IdentificationError(f"a recording of {n} samples is too short to identify anything")
    for name, x in (("torque_ref", rec.torque_ref), ("motor_velocity", rec.motor_velocity)):
        top = np.flatnonzero(x == x.max())
        if top.size >= max(10, n // 100) and np.sum(np.diff(top) == 1) >= max(10, n // 100) - 1:
            raise IdentificationError(f"{name} sits at its extreme value for many consecutive samples: "
                                      "saturated or clipped")


def _band(rec: Recording, opt: IdentificationOptions, notes: list[str]) -> tuple[tuple[float, float], float]:
    """The FRD's band and resolution for this record: the configured band (default: up to the top
    of the band the torque excites), at the resolution the record's length allows."""
    from .start import excited_band_hz

    fs = rec.sample_rate_hz
    resolution = max(opt.resolution_hz, fs / len(rec))
    if resolution > opt.resolution_hz * (1 + 1e-9):
        notes.append(f"a {len(rec) / fs:g} s record: FRD at {resolution:.3g} Hz resolution "
                     f"(the configured {opt.resolution_hz:g} Hz needs {1 / opt.resolution_hz:g} s)")
    if opt.band_hz is not None:
        lo, hi = opt.band_hz
    else:
        lo, hi = 0.0, min(excited_band_hz(rec.torque_ref, fs), 0.45 * fs)
    lo = max(lo, resolution)
    if hi <= lo + 4 * resolution:
        raise IdentificationError(f"the torque excites no band to identify (up to {hi:.3g} Hz at "
                                  f"{resolution:.3g} Hz resolution)")
    return (lo, hi), resolution


def identify(recording: Recording, options: IdentificationOptions | None = None,
             progress: Progress | None = None) -> Identification:
    """Identify the two-mass model and the backlash from one chirp experiment.

    :param recording: torque_ref, motor_velocity (and motor_position, optional load encoder).
    :param options: see :class:`IdentificationOptions` (default: hybrid).
    :param progress: called as progress(stage, fraction ∈ [0, 1]) when a stage starts.
    :raises IdentificationError: the record cannot give a model at all (one-line reason); a model
        that fits it poorly is returned, flagged approximate with the reasons.
    """
    opt = options if options is not None else IdentificationOptions()
    notes: list[str] = []
    if not recording.is_uniform:
        # host-streamed runs carry the real sample times: identify on the nominal grid
        from .resample import to_uniform

        recording, rs = to_uniform(recording)
        notes.append(f"resampled from jittered sample times (period jitter rms {rs.jitter_rms_s * 1e6:.0f} µs, "
                     f"max {rs.jitter_max_s * 1e6:.0f} µs) to a uniform {recording.sample_rate_hz:g} Hz grid")
    _check_recording(recording, opt)
    band, resolution = _band(recording, opt, notes)
    # one BLAS thread: the LAPACK calls are small and run from several threads at once
    with threadpool_limits(limits=1, user_api="blas"):
        if opt.method is Method.PAPER:
            result = _identify_paper(recording, opt, _Stages(progress), band, resolution)
        else:
            result = _identify_hybrid(recording, opt, _Stages(progress), band, resolution)
    result.notes[:0] = notes
    if progress is not None:
        progress("done", 1.0)
    return result


def _identify_hybrid(rec: Recording, opt: IdentificationOptions, st: _Stages, band: tuple[float, float],
                     resolution: float) -> Identification:
    from .assess import assess
    from .frd import estimate_frd
    from .residual import Observer, prepare_residual
    from .scan import EPSILON_EXTEND_MAX_DEG, Scan, ScanCell, scan
    from .start import Start, frequency_start, load_encoder_start, measured_band_hz, residual_cutoff

    notes: list[str] = []
    fs = rec.sample_rate_hz
    use_load = bool(opt.use_load_encoder and rec.load_position is not None)

    lost = rec.lost_mask
    if lost.any():
        notes.append(f"{int(lost.sum())} samples the link lost are interpolated in the record and left out of "
                     "the time-domain fit")

    def prepared(cutoff_hz: float, interpolation: str = opt.motor_interpolation) -> Any:
        return prepare_residual(rec.torque_ref, fs, motor_position=rec.motor_position,
                                motor_velocity=rec.motor_velocity, cutoff_hz=cutoff_hz,
                                load_position=rec.load_position if use_load else None,
                                velocity_scale_rad_s=opt.coulomb_velocity_scale_rad_s,
                                interpolation=interpolation, lost=lost if lost.any() else None)

    st.start("start", 0.0)
    candidates = ModelTerms(**{name: True for name in opt.model_terms})
    problem = prepared(min(opt.residual_cutoff_hz, 0.4 * fs))
    try:
        start: Start | None = frequency_start(rec, problem, band_hz=band, resolution_hz=resolution,
                                              quality_threshold=opt.quality_threshold,
                                              fit_delay=candidates.current_loop, notes=notes)
    except IdentificationError as err:
        if not use_load:
            raise
        start = None
        notes.append(f"frequency-domain start failed ({err}); the load encoder's start is used")
    enc = load_encoder_start(problem, math.radians(EPSILON_EXTEND_MAX_DEG)) if use_load else None
    if start is None and enc is None:
        raise IdentificationError("neither the frequency response nor the encoders give a two-mass plant")
    base = start.parameters if start is not None else enc.parameters  # type: ignore[union-attr]
    ref = float(np.sqrt(np.mean(problem.torque_f ** 2)))
    cut = residual_cutoff(rec, base, band[1], opt.residual_cutoff_hz, ref, _QUANTIZATION_TARGET * opt.good_fit_ratio)
    if cut["cutoff_hz"] != problem.cutoff_hz:
        problem = prepared(cut["cutoff_hz"])
        ref = float(np.sqrt(np.mean(problem.torque_f ** 2)))
        if use_load:
            enc = load_encoder_start(problem, math.radians(EPSILON_EXTEND_MAX_DEG)) or enc
    if cut.get("unlowered_cutoff_hz"):
        notes.append(f"the motor encoder's step ({cut['position_step_rad']:.3g} rad) would leave much of the "
                     f"torque as noise in the residual; low-passed at {cut['cutoff_hz']:.0f} Hz instead of "
                     f"{cut['unlowered_cutoff_hz']:.0f} Hz — a finer encoder would let the fit see more")
    if rec.motor_position is None:
        notes.append("motor position rebuilt from the velocity (x[k] = x[k−1] + Ts·v[k])")
    if use_load:
        notes.append("load encoder used: the start from both encoders' equations of motion, the initial twist "
                     "from the encoders, and a load-position block K̂·(x_l,sim − x_l,meas) in the residual")
    w_load = float(base.K) if use_load else 0.0
    lag0 = max(start.delay_s - 1.0 / fs, 0.0) if candidates.current_loop and start is not None else 0.0
    st.done("start", parameters=base.as_dict(), how=start.how if start else "load encoder",
            delay_s=start.delay_s if start else 1.0 / fs, band_hz=list(band),
            band_low_hz=start.band_low_hz if start else band[0], resolution_hz=resolution, residual=cut,
            load_encoder=use_load)

    st.start("scan", 0.2)
    friction_rescan = None
    if enc is not None:
        # both encoders: the equation-error start is the cell (no load simulation needed to find it)
        cell = ScanCell(enc.epsilon_rad, math.nan, enc.cost_nm, enc.parameters,
                        enc.coulomb_motor_nm + enc.coulomb_load_nm)
        if candidates.coulomb_load and enc.coulomb_load_nm > _FRICTION_SCREEN * ref:
            friction_rescan = {"coulomb_nm": enc.coulomb_motor_nm + enc.coulomb_load_nm,
                               "load_nm": enc.coulomb_load_nm}
        sc = Scan((cell,), None)
    else:
        step = _SCAN_STEP * opt.epsilon_resolution_deg
        sc = scan(problem, base, opt.epsilon_bounds_deg, step, opt.damping_splits,
                  coulomb=candidates.coulomb_motor or candidates.coulomb_load, lag_s=lag0,
                  load_weight_nm_per_rad=w_load, threads=opt.threads)
        cell = _best_cell(sc)
        if candidates.coulomb_load and cell is not None and cell.coulomb_nm > _FRICTION_SCREEN * ref:
            # friction: the motor column stood in for both sides; scan again with half of it simulated
            # on the load side, where it shapes the load's motion through the gap
            friction_rescan = {"coulomb_nm": cell.coulomb_nm, "first_epsilon_deg": math.degrees(cell.epsilon_rad)}
            sc = scan(problem, base, opt.epsilon_bounds_deg, step, opt.damping_splits, coulomb=True,
                      lag_s=lag0, load_weight_nm_per_rad=w_load, coulomb_load_nm=0.5 * cell.coulomb_nm,
                      threads=opt.threads)
            cell = _best_cell(sc) or cell
    if cell is None:
        # no projection gives positive inertias (the record holds more than a two-mass plant's response):
        # the fit starts from the frequency-domain start itself, and its quality will say so
        cell = ScanCell(0.0, math.nan, math.inf, base)
        notes.append("no cell of the start scan gave positive inertias: the fit starts from the frequency-domain "
                     "start")
    top_deg = sc.extended_to_deg or scan_top_deg(opt)
    if sc.extended_to_deg:
        notes.append(f"ε scan extended to {sc.extended_to_deg:g}°: its best cell lay at the top of the "
                     f"configured range (up to {opt.epsilon_bounds_deg[1]:g}°)")
    st.done("scan", evaluations=sc.evaluations, extended_to_deg=sc.extended_to_deg, lag_s=lag0,
            friction_rescan=friction_rescan, load_encoder_start=enc is not None,
            history=[{"epsilon_deg": math.degrees(c.epsilon_rad), "phi": c.phi, "cost_nm": c.cost_nm}
                     for c in (sc.history or sc.cells)])

    st.start("fit", 0.35)
    terms = ModelTerms(coulomb_motor=candidates.coulomb_motor, coulomb_load=friction_rescan is not None,
                       current_loop=candidates.current_loop)
    p0 = cell.parameters
    assert p0 is not None
    floor = 1e-3 * (base.B_m + base.B_l)
    p0 = TwoMassParameters(J_m=p0.J_m, J_l=p0.J_l, B_m=max(p0.B_m, floor), B_l=max(p0.B_l, floor), K=p0.K,
                           D=max(p0.D, 1e-6 * p0.K))
    fc = problem.cutoff_hz
    observer = Observer.design(fs, opt.observer_bandwidth_factor * fc, 2.0 * fc, p0.K, p0.D, load_encoder=use_load)
    friction = max(friction_rescan["coulomb_nm"] if friction_rescan else cell.coulomb_nm, 0.0)
    eps_max = math.radians(2.0 * max(top_deg, math.degrees(cell.epsilon_rad)))
    f_load = (friction_rescan or {}).get("load_nm", 0.5 * friction)
    # the same residual discretized otherwise: its motor position a global spline, its observer half
    # as fast (the estimate's sensitivity to them is part of its uncertainty)
    other = prepared(fc, "spline" if opt.motor_interpolation == "local" else "local")
    alternates = ((other, observer),
                  (problem, Observer.design(fs, 0.5 * opt.observer_bandwidth_factor * fc, 2.0 * fc, p0.K, p0.D,
                                            load_encoder=use_load)))
    # continuation in the observer's gain: a slow observer first (the cost's basin in the linear
    # parameters is wide), then the configured one from there (it follows impact-rich loads)
    slow = alternates[1][1]
    pem = fit(problem, p0, cell.epsilon_rad, terms, slow,
              coulomb_motor_nm=friction - f_load if terms.coulomb_load else friction,
              coulomb_load_nm=f_load, lag_s=lag0, epsilon_max_rad=eps_max,
              load_weight_nm_per_rad=w_load, threads=opt.threads, max_nfev=opt.max_fit_evaluations)
    fast = fit(problem, pem.parameters, pem.epsilon_rad, terms, observer, alternates=alternates,
               coulomb_motor_nm=pem.coulomb_motor_nm, coulomb_load_nm=pem.coulomb_load_nm, lag_s=pem.lag_s,
               epsilon_max_rad=eps_max, load_weight_nm_per_rad=w_load, threads=opt.threads,
               max_nfev=opt.max_fit_evaluations, hold_epsilon=False)
    pem = replace(fast, evaluations=fast.evaluations + pem.evaluations)
    # the scan again at the fit's linear parameters (which moved toward the plant's even where its ε
    # did not): block-coordinate descent, a global step in ε between local fits, until the scan's best
    # cell is the fit's own
    rounds = 0
    while enc is None and rounds < _RESCANS and math.isfinite(pem.cost_nm):
        bounds = (opt.epsilon_bounds_deg[0], max(opt.epsilon_bounds_deg[1], 2.0 * math.degrees(pem.epsilon_rad)))
        again = scan(problem, pem.parameters, bounds, step, opt.damping_splits,
                     coulomb=candidates.coulomb_motor or candidates.coulomb_load, lag_s=pem.lag_s,
                     load_weight_nm_per_rad=w_load, threads=opt.threads, phi_around=True)
        best = _best_cell(again)
        rounds += 1
        if best is None or abs(best.epsilon_rad - pem.epsilon_rad) <= 2.5 * math.radians(step):
            break
        other = fit(problem, best.parameters, best.epsilon_rad, terms, observer, alternates=alternates,
                    coulomb_motor_nm=pem.coulomb_motor_nm, coulomb_load_nm=pem.coulomb_load_nm, lag_s=pem.lag_s,
                    epsilon_max_rad=eps_max, load_weight_nm_per_rad=w_load, threads=opt.threads,
                    max_nfev=opt.max_fit_evaluations)
        calls = pem.evaluations + other.evaluations + again.evaluations
        pem = replace(other if other.cost_nm < pem.cost_nm else pem, evaluations=calls)
        if other.cost_nm >= pem.cost_nm and other is not pem:
            break
    if terms.any:
        pem = select_terms(problem, pem, observer, epsilon_max_rad=eps_max, load_weight_nm_per_rad=w_load,
                           threads=opt.threads, keep_all=opt.term_selection == "keep_all", alternates=alternates)
    st.done("fit", evaluations=pem.evaluations, converged=pem.converged, message=pem.message,
            start_epsilon_deg=math.degrees(cell.epsilon_rad), start_phi=cell.phi, rescans=rounds,
            observer_gain_rad_per_nm=observer.gain_rad_per_nm, terms=list(pem.terms.names()))

    st.start("check", 0.9)
    quality = assess(pem, torque_rms_nm=ref, motor_samples=problem.acceleration_f.size,
                     decimated_rate_hz=fs / problem.decimation, good_fit_ratio=opt.good_fit_ratio,
                     noise_floor_ratio=float(cut["quantization_floor_ratio"]), cutoff_hz=fc,
                     observer_bandwidth_hz=observer.bandwidth_hz, sample_rate_hz=fs,
                     resonance_hz=_resonance_hz(pem.parameters))
    notes += [f"approximate result: {r}" for r in quality.reasons]
    if quality.noise_limited:
        notes.append(f"the model leaves {100 * quality.residual_ratio:.2f} % of the torque unexplained, but as "
                     "white, stationary noise: the record's noise, not model error")
    iterations = []
    frd = start.frd if start is not None else estimate_frd(rec.torque_ref, rec.motor_velocity, fs, band_hz=band,
                                                           resolution_hz=resolution, quality=False)
    for label, p, e, lag in (("start", base, cell.epsilon_rad, 0.0),
                             ("result", pem.parameters, pem.epsilon_rad, pem.lag_s)):
        if not 0.0 < _resonance_hz(p) < 0.25 * fs:  # an open-loop simulation could not resolve it
            notes.append(f"step 5 on the {label} skipped: its resonance is not below fs/4")
            continue
        try:
            iterations.append({"frd_error": _step5(rec, frd, p, e, lag), "epsilon_deg": math.degrees(e)})
        except IdentificationError as err:  # an open-loop simulation of a poor start may diverge
            notes.append(f"step 5 on the {label} failed: {err}")
    st.done("check", fit=quality.to_dict())

    eps = pem.epsilon_rad
    detected = math.degrees(eps) > opt.no_backlash_threshold_deg
    if not detected:
        notes.append(f"no backlash detected: ε̂ = {math.degrees(eps):.4f}° ≤ {opt.no_backlash_threshold_deg}°")
    params = pem.parameters
    num, den = params.velocity_tf()
    return Identification(
        method=Method.HYBRID, parameters=params, epsilon_rad=eps,
        epsilon_interval_rad=_epsilon_interval(pem, float(cut["position_step_rad"])),
        evaluations=sc.evaluations + pem.evaluations, modes=modes(params), num=num, den=den, delay_s=1.0 / fs,
        iterations=iterations, stages=st.items, source_samples=len(rec), sample_rate_hz=fs,
        backlash_detected=detected, notes=notes, fit=quality, parameter_stderr=pem.relative_stderr,
        parameter_interval=_intervals(pem), friction=_friction(pem, opt), current_loop=_current_loop(pem),
        selection=pem.selection or None, measured_band_hz=measured_band_hz(frd) if start is not None else band)


def _resonance_hz(p: TwoMassParameters) -> float:
    try:
        return float(modes(p).f_resonance_hz)
    except IdentificationError:  # no complex pole pair: nothing resonates
        return 0.0


def scan_top_deg(opt: IdentificationOptions) -> float:
    """Top of the ε range the start looks in first [deg]."""
    return opt.epsilon_bounds_deg[1]


def _best_cell(sc: Any) -> Any:
    """The scan's best cell that gives a plant with positive inertias (None: none does)."""
    return next((c for c in sc.cells if c.parameters is not None and math.isfinite(c.cost_nm)), None)


#: Relative resolution of the parameters: the identifier's model (exact contact maps, the motor
#: position interpolated between samples) and an independent integration of the same plant
#: (sim_drive's RK4) differ by up to this much on noise-free records.
_RELATIVE_RESOLUTION = 5e-4


def _epsilon_interval(pem: PemFit, position_step_rad: float) -> tuple[float, float]:
    """ε's 95 % interval [rad], at least ± the motor encoder's step (what the record resolves)."""
    half = max(1.96 * pem.epsilon_stderr_rad, position_step_rad)
    if not math.isfinite(half):
        half = math.inf
    return max(pem.epsilon_rad - half, 0.0), pem.epsilon_rad + half


def _intervals(pem: PemFit) -> dict[str, tuple[float, float]]:
    out = {}
    for name, rel in pem.relative_stderr.items():
        v = float(getattr(pem.parameters, name))
        half = min(max(1.96 * rel, _RELATIVE_RESOLUTION), 50.0) if math.isfinite(rel) else 50.0  # e^50: unbounded
        out[name] = (v * math.exp(-half), v * math.exp(half))
    return out


def _friction(pem: PemFit, opt: IdentificationOptions) -> dict[str, Any] | None:
    sides = [(side, name, value) for side, name, value, on in
             (("motor", "F_cm", pem.coulomb_motor_nm, pem.terms.coulomb_motor),
              ("load", "F_cl", pem.coulomb_load_nm, pem.terms.coulomb_load)) if on]
    if not sides:
        return None
    out: dict[str, Any] = {"velocity_scale_rad_s": opt.coulomb_velocity_scale_rad_s}
    for side, name, value in sides:
        half = 1.96 * pem.stderr(name)
        out[f"{side}_nm"] = float(value)
        out[f"{side}_interval_nm"] = [float(max(value - half, 0.0)), float(value + half)]
    return out


def _current_loop(pem: PemFit) -> dict[str, Any] | None:
    if not pem.terms.current_loop or pem.lag_s <= 0:
        return None
    tc, half = pem.lag_s, 1.96e-6 * pem.stderr("T_c_us")
    lo_t, hi_t = max(tc - half, 0.0), tc + half
    return {"bandwidth_hz": 1.0 / (2.0 * math.pi * tc),
            "bandwidth_interval_hz": [1.0 / (2.0 * math.pi * hi_t), 1.0 / (2.0 * math.pi * lo_t) if lo_t > 0 else math.inf],
            "time_constant_s": tc}


def _step5(rec: Recording, frd: Any, params: TwoMassParameters, eps: float, lag_s: float = 0.0) -> float:
    """Paper step 5: FRD of the open-loop dead-zone simulation vs the measured FRD (a kept current
    loop's lag enters as its exact mean over each held sample)."""
    from scipy.signal import lfilter

    from .backlash import simulate_deadzone
    from .frd import estimate_frd
    from .paper import frd_error

    torque = rec.torque_ref
    if lag_s > 0.0:
        ts = 1.0 / rec.sample_rate_hz
        a = math.exp(-ts / lag_s)
        state = lfilter([0.0, 1.0 - a], [1.0, -a], torque)  # τ at each tick, from rest
        torque = torque + (state - torque) * (lag_s / ts) * (1.0 - a)
    sim = simulate_deadzone(params, eps, torque, rec.sample_rate_hz, delay_samples=1)
    lo, hi = float(frd.frequency_hz[0]), float(frd.frequency_hz[-1])
    g = estimate_frd(rec.torque_ref, sim.motor_velocity, rec.sample_rate_hz, band_hz=(lo, hi),
                     resolution_hz=frd.resolution_hz, quality=False)
    return frd_error(frd, g, (max(1.0, lo), hi))


def _identify_paper(rec: Recording, opt: IdentificationOptions, st: _Stages, band: tuple[float, float],
                    resolution: float) -> Identification:
    from .frd import estimate_frd
    from .paper import paper_identify
    from .start import linear_start
    from .tffit import fit_transfer_function

    notes: list[str] = []
    fs = rec.sample_rate_hz
    st.start("frd", 0.0)
    frd = estimate_frd(rec.torque_ref, rec.motor_velocity, fs, band_hz=band, resolution_hz=resolution)
    fit_ = fit_transfer_function(frd)
    st.done("frd", bins=int(frd.frequency_hz.size), resolution_hz=float(frd.resolution_hz))
    st.start("paper", 0.3)
    bounds = (math.radians(opt.epsilon_bounds_deg[0]), math.radians(opt.epsilon_bounds_deg[1]))
    # the paper's FRDs over this record's band and resolution
    frd_of = functools.partial(estimate_frd, band_hz=band, resolution_hz=resolution, quality=False)
    kw = dict(search="bayes", bounds_rad=bounds, resolution_rad=math.radians(opt.epsilon_resolution_deg),
              max_iterations=opt.max_iterations, seed=opt.seed, frd_band_hz=(max(1.0, band[0]), band[1]),
              estimate_frd=frd_of)
    try:
        res = paper_identify(rec.torque_ref, rec.motor_velocity, fs, fit_, **kw)
    except IdentificationError as err:
        start, _ = linear_start(fit_.num, fit_.den)
        notes.append(f"paper: the fit maps to no physical plant ({err}); started from the modes with an even "
                     "damping split instead")
        res = paper_identify(rec.torque_ref, rec.motor_velocity, fs, start, **kw)
    st.done("paper", stop_reason=res.stop_reason, timings_s=dict(res.timings_s), passes=len(res.iterations),
            searches=[[{"epsilon_deg": math.degrees(e), "loss": float(v)} for e, v in it.search.history]
                      for it in res.iterations if getattr(it.search, "history", None) is not None])
    chosen = min(res.iterations, key=lambda r: r.frd_error)
    params = res.params
    num, den = params.velocity_tf()
    if not res.backlash_detected:
        notes.append("paper: L(0) is as good as the best ε of the grid: no backlash detected")
    notes.append(f"paper: stopped by '{res.stop_reason}'")
    interval = tuple(chosen.search.interval_rad) if res.backlash_detected else (0.0, bounds[0])
    return Identification(
        method=Method.PAPER, parameters=params, epsilon_rad=res.epsilon_rad,
        epsilon_interval_rad=(float(interval[0]), float(interval[1])),
        evaluations=int(sum(it.search.evaluations for it in res.iterations)), modes=modes(params), num=num,
        den=den, delay_s=float(res.delay_s),
        iterations=[{"frd_error": float(it.frd_error), "epsilon_deg": math.degrees(it.epsilon_rad)}
                    for it in res.iterations],
        stages=st.items, source_samples=len(rec), sample_rate_hz=fs, backlash_detected=bool(res.backlash_detected),
        notes=notes)
