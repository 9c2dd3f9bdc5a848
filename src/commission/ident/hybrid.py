"""The identification pipelines: ``hybrid`` (default, accurate) and ``paper`` (faithful).

``hybrid``, stage by stage:

1. ``start`` — FRD of τ_ref → v_m over the band the torque excites, at the resolution the record's
   length allows, its 2/3 fit and the physical start (:mod:`commission.ident.start`); the
   residual's low-pass for this record (the band, the resonance, the encoder's quantization).
2. ``scan``  — (ε, damping split) cells on the projected torque residual, J_m, B_m, J_l and the
   motor-side columns solved linearly in each (:mod:`commission.ident.scan`).
3. ``fit``   — the start's refinement: prediction-error least squares of every parameter and the
   candidate terms from the best cell, on the torque residual with a load-state observer
   (:func:`commission.ident.estimator.fit`).
4. ``kalman`` — **the estimate**: prediction errors of the Kalman predictor of the whole state, its
   noise model chosen by likelihood (:func:`commission.ident.estimator.kalman_fit`); terms kept by
   their Wald statistic on it. When its noise model needs more than 1 % of the torque, again from it
   with every configured term, kept if the BIC prefers it.
5. ``restarts`` — only when the estimate leaves model error: stages 2–4 again from a stiffer start,
   the more likely estimate kept.
6. ``check`` — prediction errors, intervals: approximate and why
   (:func:`commission.ident.assess.assess`); the paper's step 5 for the start and the
   result: the dead-zone model simulated open loop, its FRD against the measured one
   (:func:`commission.ident.paper.frd_error`).

A record whose samples are not uniform (host-streamed) is brought to its nominal grid first
(:mod:`commission.ident.resample`). ``paper`` wraps :func:`commission.ident.paper.paper_identify`
(Bayesian search of ε on max|v_m − v̂_m|, steps 5–6 iterated) into the same result.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.signal import sosfiltfilt
from threadpoolctl import threadpool_limits

from ..exceptions import IdentificationError
from ..recording import Recording
from .estimator import EPSILON_ZERO_DEG, Hedge, ModelTerms, PemFit, fit, significant_terms
from .kalman import KalmanProblem
from .options import IdentificationOptions, Method, options_from_mapping
from .result import FitQuality, Identification, StageResult
from .twomass import Modes, TwoMassParameters, modes

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
#: Torque disturbance (relative to RMS τ_ref) of the estimate's noise model above which the stiffer starts
#: are tried too: the most likely estimate is kept, so a noisy record only pays their time.
_RESTART_DISTURBANCE = 0.01
#: Stiffness factors of the further starts when the first fit leaves model error (:func:`_stiffer_starts`).
#: One: a second, ×3, never decided a verdict where it ran (20 of 168 family records; bench/results/family.md).
_STIFFER_STARTS = (1.7,)
#: Torque disturbance (relative to RMS τ_ref) of the estimate's noise model above which its residual is searched
#: for a torque periodic in the motor's position (:func:`_cogging_stage`).
_COGGING_DISTURBANCE = 0.003
#: The residual's observer there, as a share of the configured one's bandwidth.
_COGGING_OBSERVER = 0.1
#: Largest whole-sample torque delay tried beyond the hold's own (:func:`_delay_stage`).
_MAX_DELAY_SAMPLES = 4
#: Current-loop time constant [s] :func:`_lag_stage` starts the loop at: a 1 kHz loop, mid-range of servo
#: drives' (300 Hz–3 kHz).
_LAG_STAGE_START_S = 1.0 / (2.0 * math.pi * 1000.0)
#: :func:`_friction_stage` weighs each pair of these factors on the motor's and the load's Coulomb friction
#: (each side at least a third of their sum), and these shares of one side's moved to the other.
_FRICTION_FACTORS = (1.0 / 3.0, 1.0, 3.0)
_FRICTION_TRANSFERS = (1.0 / 3.0, 2.0 / 3.0)
#: :func:`_gap_stage` weighs ε at these factors of the estimate's: ½–2×, 1.5 % apart (the likelihood's dip at the
#: gap, with the rest of the estimate held, is a few % of ε wide).
_GAP_FACTORS = tuple(float(f) for f in np.exp(np.linspace(-math.log(2.0), math.log(2.0), 93)) if abs(f - 1.0) > 1e-9)


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
    from .start import BAND_TOP_PER_SAMPLE_RATE, excited_band_hz

    fs = rec.sample_rate_hz
    resolution = max(opt.resolution_hz, fs / len(rec))
    if resolution > opt.resolution_hz * (1 + 1e-3):  # (not for a record a few samples short)
        notes.append(f"a {len(rec) / fs:g} s record: FRD at {resolution:.3g} Hz resolution "
                     f"(the configured {opt.resolution_hz:g} Hz needs {1 / opt.resolution_hz:g} s)")
    if opt.band_hz is not None:
        lo, hi = opt.band_hz
    else:
        lo, hi = 0.0, min(excited_band_hz(rec.torque_ref, fs), BAND_TOP_PER_SAMPLE_RATE * fs)
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
    from .consistency import reconcile

    opt = options if options is not None else IdentificationOptions()
    _check_recording(recording, opt)  # (first: a clipped velocity would also look like a unit error)
    recording, notes = reconcile(recording)  # (before resampling: a spline through a wrap rings)
    if not recording.is_uniform:
        # host-streamed runs carry the real sample times: identify on the nominal grid
        from .resample import to_uniform

        recording, rs = to_uniform(recording)
        notes.append(f"resampled from jittered sample times (period jitter rms {rs.jitter_rms_s * 1e6:.0f} µs, "
                     f"max {rs.jitter_max_s * 1e6:.0f} µs) to a uniform {recording.sample_rate_hz:g} Hz grid")
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


@dataclass
class _Run:
    """What the hybrid stages share: the record, the options, and what the earlier stages found."""

    rec: Recording
    opt: IdentificationOptions
    band: tuple[float, float]
    resolution: float
    notes: list[str]
    use_load: bool
    lost: NDArray[np.bool_]
    problem: Any = None
    """The residual problem (commission.ident.residual.ResidualProblem) at the chosen low-pass."""
    start: Any = None
    """The frequency-domain start (commission.ident.start.Start), None when only the encoders gave one."""
    encoders: Any = None
    """The start from both encoders (commission.ident.start.EncoderStart), None without a load encoder."""
    base: TwoMassParameters | None = None
    """The start's parameters (the frequency-domain one's, else the encoders')."""
    cutoff: dict[str, Any] = field(default_factory=dict)
    torque_rms_nm: float = 0.0
    lag_s: float = 0.0
    """The start's current-loop time constant (delay fitted beyond the sample's) [s]."""
    epsilon_max_rad: float = math.inf
    """Upper bound of ε in the fit [rad]."""
    epsilon_searched_rad: float = 0.0
    """Upper bound of ε over every Kalman fit [rad]: a result the record does not determine says ε lies
    somewhere up to it (or up to the largest gap the scan considers)."""
    delay_samples: float = 0
    """Whole samples the torque acts after its reference beyond the hold's own; negative (−½ or −1): the
    encoders latched that long after the torque (:func:`_delay_stage`)."""
    kalman: Any = None
    """The Kalman predictor's problem (commission.ident.kalman.KalmanProblem) at ``delay_samples``, built by
    the first Kalman fit."""
    cogging: Any = None
    """The torque periodic in the motor's position taken out of ``rec``'s torque (commission.ident.cogging.Cogging)."""

    @property
    def fs(self) -> float:
        return self.rec.sample_rate_hz

    @property
    def load_weight(self) -> float:
        return float(self.base.K) if self.use_load and self.base is not None else 0.0

    def prepared(self, cutoff_hz: float, interpolation: str | None = None) -> Any:
        from .residual import prepare_residual

        rec, opt = self.rec, self.opt
        return prepare_residual(rec.torque_ref, self.fs, motor_position=rec.motor_position,
                                motor_velocity=rec.motor_velocity, cutoff_hz=cutoff_hz,
                                load_position=rec.load_position if self.use_load else None,
                                velocity_scale_rad_s=opt.coulomb_velocity_scale_rad_s,
                                interpolation=interpolation or opt.motor_interpolation,
                                lost=self.lost if self.lost.any() else None)


def _identify_hybrid(rec: Recording, opt: IdentificationOptions, st: _Stages, band: tuple[float, float],
                     resolution: float) -> Identification:
    run = _Run(rec, opt, band, resolution, [], bool(opt.use_load_encoder and rec.load_position is not None),
               rec.lost_mask)
    if run.lost.any():
        run.notes.append(f"in all, {int(run.lost.sum())} samples lost or glitched are interpolated in the record "
                         "and left out of the time-domain fit")
    st.start("start", 0.0)
    _start_stage(run)
    st.done("start", parameters=run.base.as_dict(), how=run.start.how if run.start else "load encoder",  # type: ignore[union-attr]
            delay_s=run.start.delay_s if run.start else 1.0 / run.fs, band_hz=list(band),
            band_low_hz=run.start.band_low_hz if run.start else band[0], resolution_hz=resolution,
            residual=run.cutoff, load_encoder=run.use_load)
    st.start("scan", 0.2)
    cell, scan_detail = _scan_stage(run)
    st.done("scan", **scan_detail)
    st.start("fit", 0.35)
    pem, _, fit_detail = _fit_stage(run, cell, scan_detail)
    st.done("fit", **fit_detail)
    st.start("kalman", 0.55)
    start = pem
    pem = _kalman_stage(run, pem)
    st.done("kalman", process_noise_nm=pem.process_noise_nm, load_share=pem.load_share, evaluations=pem.evaluations,
            converged=pem.converged, events=pem.innovations.events if pem.innovations is not None else 0)
    if pem.disturbance_nm > _COGGING_DISTURBANCE * _torque_rms(run):
        st.start("cogging", 0.6)
        run, pem = _cogging_stage(run, pem)
        st.done("cogging", **(run.cogging.to_dict() if run.cogging is not None else {}))
    first = run
    if _delay_candidates(run, pem):
        st.start("delay", 0.65)
        pem, tried = _delay_stage(run, pem)
        st.done("delay", delay_samples=run.delay_samples, tried=tried)
    # (the gap softens the spring the frequency response sees only where the load crosses it)
    if run.encoders is None and _model_error(run, pem) and not _keeps_one_flank(run, pem):
        st.start("restarts", 0.7)
        run, cell, pem, restarts = _stiffer_starts(run, cell, pem)
        st.done("restarts", starts=restarts)
    from .assess import DISTURBANCE_MISFIT, INNOVATION_UNDETERMINED

    # (a record the model cannot follow at all, its predictions 100× off, has no gap's basin to find; a
    # motor-side record was rescued by it on none of the 96 run's members it ran on, whether its Kalman
    # stage was hedged (17) or its start had no gap (6): bench/results/family.md)
    level = pem.innovations.rms if pem.innovations is not None else math.inf
    if (first.encoders is not None and start.epsilon_rad > 0.0
            and pem.disturbance_nm >= DISTURBANCE_MISFIT * _torque_rms(run) and level < INNOVATION_UNDETERMINED):
        st.start("hedged", 0.8)
        run, pem = _hedged_stage(first, start, run, pem)
        st.done("hedged", process_noise_nm=pem.process_noise_nm, evaluations=pem.evaluations)
    if "current_loop" in opt.model_terms and not pem.terms.current_loop and _needs_disturbance(run, pem):
        st.start("lag", 0.85)
        pem, kept = _lag_stage(run, pem)
        st.done("lag", kept=kept, evaluations=pem.evaluations)
    if run.encoders is None and math.degrees(pem.epsilon_rad) >= EPSILON_ZERO_DEG and _needs_disturbance(run, pem):
        st.start("gap", 0.86)
        pem, kept = _gap_stage(run, pem)
        st.done("gap", kept=kept, evaluations=pem.evaluations)
    if (pem.terms.coulomb_motor or pem.terms.coulomb_load) and _needs_disturbance(run, pem):
        st.start("friction", 0.87)
        pem, kept = _friction_stage(run, pem)
        st.done("friction", kept=kept, evaluations=pem.evaluations)
    st.start("check", 0.9)
    quality, iterations = _check_stage(run, cell, pem)
    st.done("check", fit=quality.to_dict())
    return _identification(run, pem, quality, iterations, st.items, scan_detail["evaluations"])


def _start_stage(run: _Run) -> None:
    """The frequency-domain start (or the encoders'), the residual's low-pass, and the notes on them."""
    from .scan import EPSILON_EXTEND_MAX_DEG
    from .start import cutoff_note, frequency_start, load_encoder_start, load_origin_rad, residual_cutoff

    opt, fs = run.opt, run.fs
    run.problem = run.prepared(min(opt.residual_cutoff_hz, 0.4 * fs))
    try:
        run.start = frequency_start(run.rec, run.problem, band_hz=run.band, resolution_hz=run.resolution,
                                    quality_threshold=opt.quality_threshold,
                                    fit_delay="current_loop" in opt.model_terms, notes=run.notes,
                                    raise_edges=not run.use_load)
    except IdentificationError as err:
        if not run.use_load:
            raise
        run.notes.append(f"frequency-domain start failed ({err}); the load encoder's start is used")
    top = math.radians(EPSILON_EXTEND_MAX_DEG)
    first = run.problem

    def encoders(problem: Any) -> Any:
        return load_encoder_start(problem, top, threads=opt.threads,
                                  current_loop="current_loop" in opt.model_terms)

    # with a load encoder, the encoders' start (no simulation, no FRD) at the first low-pass is the start: the
    # FRD's resonance is pulled low by the gap on backlash-rich records, and the low-pass chosen from a low
    # resonance would cut the real one off
    run.encoders = encoders(first) if run.use_load else None
    if run.use_load:
        shift = load_origin_rad(first, run.encoders)
        if shift:
            run.notes.append(f"the load encoder's origin lies {math.degrees(-shift):.6g}° from the motor's (with "
                             "the gap's middle as the common origin): its position is shifted by that")
            run.rec = run.rec.replace(load_position=run.rec.load_position + shift)
            first = run.problem = run.prepared(first.cutoff_hz)
            run.encoders = encoders(first)
    if run.start is None and run.encoders is None:
        raise IdentificationError("neither the frequency response nor the encoders give a two-mass plant")
    run.base = run.encoders.parameters if run.encoders is not None else run.start.parameters
    ref = float(np.sqrt(np.mean(run.problem.torque_f ** 2)))
    run.cutoff = residual_cutoff(run.rec, run.base, run.band[1], opt.residual_cutoff_hz, ref,
                                 _QUANTIZATION_TARGET * opt.good_fit_ratio)
    if run.cutoff["cutoff_hz"] != run.problem.cutoff_hz:
        run.problem = run.prepared(run.cutoff["cutoff_hz"])
        ref = float(np.sqrt(np.mean(run.problem.torque_f ** 2)))
        if run.use_load:
            run.encoders = encoders(run.problem) or run.encoders
    run.torque_rms_nm = ref
    if run.encoders is not None:
        run.lag_s = run.encoders.lag_s  # fitted in the residual's own equation, not read off a delay
    elif run.start is not None and "current_loop" in opt.model_terms:
        run.lag_s = max(run.start.delay_s - 1.0 / fs, 0.0)
    note = cutoff_note(run.cutoff)
    if note is not None:
        run.notes.append(note)
    if run.rec.motor_position is None:
        run.notes.append("motor position rebuilt from the velocity (x[k] = x[k−1] + Ts·v[k])")
    if run.use_load:
        run.notes.append("load encoder used: the start from both encoders' equations of motion, the initial twist "
                         "from the encoders, and a load-position block K̂·(x_l,sim − x_l,meas) in the residual")


def _scan_stage(run: _Run) -> tuple[Any, dict[str, Any]]:
    """The start cell: the encoders' start, else the best cell of the (ε, damping split) scan (scanned again
    with friction on the load side when its friction column shows friction)."""
    from .scan import Scan, ScanCell, scan

    opt, ref = run.opt, run.torque_rms_nm
    coulomb_load = "coulomb_load" in opt.model_terms
    friction: dict[str, float] | None = None
    enc = run.encoders
    if enc is not None:
        cell = ScanCell(enc.epsilon_rad, math.nan, enc.cost_nm, enc.parameters,
                        enc.coulomb_motor_nm + enc.coulomb_load_nm)
        if coulomb_load and enc.coulomb_load_nm > _FRICTION_SCREEN * ref:
            friction = {"coulomb_nm": cell.coulomb_nm, "load_nm": enc.coulomb_load_nm}
        sc = Scan((cell,), None)
    else:
        sc = _scan_at(run, run.base, opt.epsilon_bounds_deg)  # type: ignore[arg-type]
        cell = _best_cell(sc)
        if coulomb_load and cell is not None and cell.coulomb_nm > _FRICTION_SCREEN * ref:
            # the motor column stood in for both sides: again with half of it simulated on the load side,
            # where it shapes the load's motion through the gap
            friction = {"coulomb_nm": cell.coulomb_nm, "load_nm": 0.5 * cell.coulomb_nm}
            sc = scan(run.problem, run.base, opt.epsilon_bounds_deg, _SCAN_STEP * opt.epsilon_resolution_deg,
                      opt.damping_splits, coulomb=True, lag_s=run.lag_s, load_weight_nm_per_rad=run.load_weight,
                      coulomb_load_nm=friction["load_nm"], threads=opt.threads)
            cell = _best_cell(sc) or cell
    if cell is None:
        # no projection gives positive inertias (the record holds more than a two-mass plant's response):
        # the fit starts from the start itself, and its quality will say so
        cell = ScanCell(0.0, math.nan, math.inf, run.base)
        run.notes.append("no cell of the start scan gave positive inertias: the fit starts from the "
                         "frequency-domain start")
    if sc.extended_to_deg:
        run.notes.append(f"ε scan extended to {sc.extended_to_deg:g}°: its best cell lay at the top of the "
                         f"configured range (up to {opt.epsilon_bounds_deg[1]:g}°)")
    return cell, {"evaluations": sc.evaluations, "extended_to_deg": sc.extended_to_deg, "lag_s": run.lag_s,
                  "friction": friction, "load_encoder_start": enc is not None,
                  "history": [{"epsilon_deg": math.degrees(c.epsilon_rad), "phi": c.phi, "cost_nm": c.cost_nm}
                              for c in (sc.history or sc.cells)]}


def _scan_at(run: _Run, around: TwoMassParameters, bounds_deg: tuple[float, float], own_split: bool = False) -> Any:
    from .scan import scan

    opt = run.opt
    return scan(run.problem, around, bounds_deg, _SCAN_STEP * opt.epsilon_resolution_deg, opt.damping_splits,
                coulomb=bool({"coulomb_motor", "coulomb_load"} & set(opt.model_terms)), lag_s=run.lag_s,
                load_weight_nm_per_rad=run.load_weight, threads=opt.threads, phi_around=own_split)


def _fit_stage(run: _Run, cell: Any, scan_detail: dict[str, Any]) -> tuple[PemFit, Any, dict[str, Any]]:
    """The prediction-error fit from the start cell: with a slow observer and every candidate term, then
    with the configured observer and the terms the first fit found significant; then a scan at the fit's
    linear parameters, and a fit from its best cell when that lies at another ε (the lower cost taken)."""
    from .residual import Observer

    opt, fs, base = run.opt, run.fs, run.base
    assert base is not None and cell.parameters is not None
    p = cell.parameters
    floor = 1e-3 * (base.B_m + base.B_l)
    p0 = TwoMassParameters(J_m=p.J_m, J_l=p.J_l, B_m=max(p.B_m, floor), B_l=max(p.B_l, floor), K=p.K,
                           D=max(p.D, 1e-6 * p.K))
    fc = run.problem.cutoff_hz

    def observer(factor: float, at: TwoMassParameters) -> Observer:
        return Observer.design(fs, factor * opt.observer_bandwidth_factor * fc, 2.0 * fc, at.K, at.D,
                               load_encoder=run.use_load)

    slow = observer(0.5, p0)
    friction = scan_detail["friction"]
    f_total = max(friction["coulomb_nm"] if friction else cell.coulomb_nm, 0.0)
    f_load = friction["load_nm"] if friction else 0.0
    # motor Coulomb friction is a candidate when the start shows it (the scan cell's column significant: its
    # Wald statistic over ln n; the encoders' start has no such statistic)
    n = run.problem.acceleration_f.size
    candidates = ModelTerms(coulomb_motor="coulomb_motor" in opt.model_terms
                            and (friction is not None or run.encoders is not None or cell.coulomb_z2 > math.log(n)),
                            coulomb_load=friction is not None, current_loop="current_loop" in opt.model_terms)
    top = scan_detail["extended_to_deg"] or opt.epsilon_bounds_deg[1]
    eps_max = run.epsilon_max_rad = math.radians(2.0 * max(top, math.degrees(cell.epsilon_rad)))
    common = dict(epsilon_max_rad=eps_max, load_weight_nm_per_rad=run.load_weight, threads=opt.threads,
                  max_nfev=opt.max_fit_evaluations)
    # continuation in the observer's gain: the slow one's basin in the linear parameters is wide, the
    # configured one follows impact-rich loads
    first = fit(run.problem, p0, cell.epsilon_rad, candidates, slow, coulomb_motor_nm=f_total - f_load,
                coulomb_load_nm=f_load, lag_s=run.lag_s, **common)
    terms, selection = significant_terms(first, keep_all=opt.term_selection == "keep_all")
    # the configured observer, designed at the start; its gain removes a fraction α of a twist error per sample
    # at the start's K + D·fs, α·(K + D·fs)/(K₀ + D₀·fs) at the first fit's: past the whole error (> 1) the
    # correction overshoots and the predictor diverges, so then it is designed at the first fit's stiffness
    fast = observer(1.0, p0)
    at = first.parameters
    if fast.gain_rad_per_nm * (at.K + at.D * fs) > 1.0:
        fast = observer(1.0, at)
    else:
        at = p0
    def refit(p: TwoMassParameters, eps: float, hold: bool) -> PemFit:
        return fit(run.problem, p, eps, terms, fast, coulomb_motor_nm=first.coulomb_motor_nm,
                   coulomb_load_nm=first.coulomb_load_nm, lag_s=first.lag_s, hold_epsilon=hold, **common)

    pem = refit(first.parameters, first.epsilon_rad, False)
    calls = first.evaluations + pem.evaluations
    rescans = 0
    if run.encoders is None and math.isfinite(pem.cost_nm):
        # a global step in ε between local fits: the scan at the fit's linear parameters (which moved
        # toward the plant's even where its ε did not)
        bounds = (opt.epsilon_bounds_deg[0], max(opt.epsilon_bounds_deg[1], 2.0 * math.degrees(pem.epsilon_rad)))
        again = _scan_at(run, pem.parameters, bounds, own_split=True)
        best, rescans = _best_cell(again), 1
        calls += again.evaluations
        if best is not None and abs(best.epsilon_rad - pem.epsilon_rad) > 2.5 * math.radians(
                _SCAN_STEP * opt.epsilon_resolution_deg):
            other = refit(best.parameters, best.epsilon_rad, True)
            calls += other.evaluations
            pem = other if other.cost_nm < pem.cost_nm else pem
    final = significant_terms(pem, keep_all=True)[1]
    selection = {t: {**v, **({"z2": final[t]["z2"]} if t in final else {})} for t, v in selection.items()}
    for term in opt.model_terms:  # the candidates the start did not show
        if term not in selection:
            selection[term] = {"kept": False, "screened": "coulomb column of the start cell" if term == "coulomb_motor"
                               else "no friction in the start scan",
                               **({"z2": cell.coulomb_z2, "threshold": math.log(n)} if term == "coulomb_motor" else {})}
    pem = replace(pem, evaluations=calls, selection=selection)
    detail = {"evaluations": calls, "converged": pem.converged, "message": pem.message,
              "start_epsilon_deg": math.degrees(cell.epsilon_rad), "start_phi": cell.phi, "rescans": rescans,
              "observer_gain_rad_per_nm": fast.gain_rad_per_nm, "terms": list(pem.terms.names())}
    return pem, fast, detail


def _model_error(run: _Run, pem: PemFit) -> bool:
    """The estimate may leave model error: the assessment says so, or its noise model needs a torque
    disturbance above ``_RESTART_DISTURBANCE`` (a noisy drive's, or a wrong basin's)."""
    from .assess import assess

    q = assess(pem, torque_rms_nm=_torque_rms(run), sample_rate_hz=run.fs)
    return q.model_error or _needs_disturbance(run, pem)


def _configured_terms(opt: IdentificationOptions) -> ModelTerms:
    """Every model term the options allow."""
    return ModelTerms(**{f.name: f.name in opt.model_terms for f in fields(ModelTerms)})


def _kalman_options(run: _Run, epsilon_max_rad: float) -> dict[str, Any]:
    """The keyword arguments of a Kalman fit (:func:`~commission.ident.estimator.kalman_fit`) the options set."""
    return dict(epsilon_max_rad=epsilon_max_rad, threads=run.opt.threads, max_nfev=run.opt.max_fit_evaluations,
                keep_all=run.opt.term_selection == "keep_all")


def _needs_disturbance(run: _Run, pem: PemFit) -> bool:
    return pem.disturbance_nm > _RESTART_DISTURBANCE * _torque_rms(run)


def _kept_note(run: _Run, pem: PemFit, other: PemFit, at: str, how: str) -> str:
    """The note of a stage that kept ``other`` over ``pem``, an estimate that needed a disturbance: what ``pem``
    was ``at``, ``how`` the stage found ``other``, and how much likelier the record is there."""
    return (f"the estimate needed a disturbance of {100 * pem.disturbance_nm / _torque_rms(run):.2g} % of RMS τ_ref"
            f"{at}; {how} makes the record {_likelier(_likelihood_cost(pem), _likelihood_cost(other))}× as likely "
            "per prediction error and is kept")


def _torque_rms(run: _Run) -> float:
    return float(np.sqrt(np.mean(run.rec.torque_ref ** 2)))


def _pays_for(kp: KalmanProblem, pem: PemFit, other: PemFit, added: int) -> bool:
    """Whether ``other`` makes the record of Kalman problem ``kp`` more likely than ``pem`` by more than the
    BIC's price of its ``added`` parameters (½·ln n_eff each)."""
    gain = (_likelihood_cost(pem) - _likelihood_cost(other)) * (len(kp.motor_position) - 1) * kp.outputs
    return gain > 0.5 * added * math.log(other.n_effective)


def _likelihood_cost(pem: PemFit) -> float:
    """The estimate's negative log-likelihood per prediction error: comparable across starts and noise models."""
    return pem.innovations.negative_log_likelihood() if pem.innovations is not None else math.inf


def _likelier(nll_before: float, nll_after: float) -> str:
    """How many times as likely per prediction error the record is at ``nll_after`` than at ``nll_before``
    (negative log-likelihoods per prediction error), for a note: a power of ten past a float's range (a
    record no model explains moves its likelihood by thousands of e-folds)."""
    log_ratio = 0.5 * (nll_before - nll_after)
    if log_ratio < 700.0:
        return f"{math.exp(log_ratio):.3g}"
    if not math.isfinite(log_ratio):  # a likelihood that could not be computed (nan: neither could)
        return "∞" if log_ratio > 0 else "?"
    return f"10^{log_ratio / math.log(10.0):.0f}"


def _stiffer_starts(run: _Run, cell: Any, pem: PemFit) -> tuple[_Run, Any, PemFit, list[dict[str, float]]]:
    """The scan, the fit and the estimate again from the start with its stiffness raised by each of
    ``_STIFFER_STARTS`` in turn (the damping by its square root, ζ kept), while each makes the record
    more likely than the one before; the estimate of the largest likelihood is kept.

    The gap softens the spring the FRD sees (its describing function), so on backlash-rich records the
    frequency-domain start's resonance is low, often beyond the fit's basin; the inertias, from the
    FRD's asymptotes, hold.
    """
    best = (run, cell, pem)
    tried = [{"stiffness_factor": 1.0, "negative_log_likelihood": _likelihood_cost(pem)}]
    spent = pem.evaluations
    assert run.base is not None
    for factor in _STIFFER_STARTS:
        base = replace(run.base, K=factor * run.base.K, D=math.sqrt(factor) * run.base.D)
        if not 0.0 < _resonance_hz(base) < 0.25 * run.fs:
            continue
        other = replace(run, base=base, notes=[])
        try:
            c, detail = _scan_stage(other)
            p = _kalman_stage(other, _fit_stage(other, c, detail)[0])
        except (IdentificationError, ValueError, np.linalg.LinAlgError) as err:
            # a start this far off may leave the simulation no finite point to start from: not a start then
            tried.append({"stiffness_factor": factor, "negative_log_likelihood": math.inf, "failed": str(err)})
            continue
        spent += detail["evaluations"] + p.evaluations
        tried.append({"stiffness_factor": factor, "negative_log_likelihood": _likelihood_cost(p)})
        if not _likelihood_cost(p) < _likelihood_cost(best[2]):
            break  # the ladder is climbed while each start makes the record more likely
        best = (other, c, p)
    chosen, c, p = best
    p = replace(p, evaluations=spent)
    if chosen is not run:
        factor = chosen.base.K / run.base.K  # type: ignore[union-attr]
        run.notes.append(f"the estimate from the frequency-domain start left model error; from its stiffness "
                         f"×{factor:.2g} the record is {_likelier(tried[0]['negative_log_likelihood'], _likelihood_cost(p))}× "
                         "as likely per prediction error and it is kept (the gap softens the spring the frequency "
                         "response sees)")
        chosen = replace(chosen, notes=run.notes + chosen.notes)
    else:
        factors = ", ×".join(f"{t['stiffness_factor']:g}" for t in tried[1:])
        starts = "a stiffer start" if len(tried) == 2 else "stiffer starts"
        run.notes.append(f"the estimate left model error; {starts} (×{factors} K) did not explain the record better"
                         if factors else "the estimate left model error; no stiffer start keeps the resonance below a "
                         "quarter of the sample rate")
    return chosen, c, p, tried


def _delay_candidates(run: _Run, pem: PemFit) -> Sequence[float]:
    """The whole-sample torque delays worth trying: where the estimate needs a disturbance and its current
    loop's lag spans whole samples (a delay the first-order lag stands in for); or, where it has no lag
    to speak of, half a sample and a sample less than the hold's own (the encoders latched that long after
    the torque: motion the model's lag cannot put before its torque)."""
    if not _needs_disturbance(run, pem):
        return range(0)
    lag = pem.lag_s * run.fs if pem.terms.current_loop else 0.0
    if lag < 0.5:
        return _LEADS
    return range(1, min(_MAX_DELAY_SAMPLES, int(lag)) + 1)


#: The encoders' latching after the torque tried, in samples (a mid-cycle encoder latch, a log a sample off).
_LEADS = (-0.5, -1.0)


def _delay_stage(run: _Run, pem: PemFit) -> tuple[PemFit, list[dict[str, float]]]:
    """The estimate again with the torque acting 1, 2, … samples after its reference (the current loop's
    lag shortened by as much), while each makes the record more likely by more than a parameter's price
    (the BIC's ½·ln n_eff); the most likely delay is kept in ``run.delay_samples``.

    A drive's computation and transport delay is a pure delay, which a first-order current loop only
    stands in for at low frequency: on the simulated drive with a 1 kHz loop and 2 samples of delay the
    estimate without it needed a torque disturbance of 11 % of RMS τ_ref (flagged, ε 0.374° for 0.4°);
    with it 0.01 % (the drive's own noise), the loop's time constant exact, ε 0.4000°. The estimate of the
    first delay that does not pay for itself seeds one more fit at the kept delay (:func:`_seeded_by_delay`).
    Each trial is the plain fit from the estimate, which the Kalman stage already brought into the gap's basin
    (hedged trials gave the same verdict on all 27 members of the 96 run the stage ran on, in 3.6× the time:
    bench/results/family.md).

    With no lag to shorten, the torque a sample earlier (delay −1): a log that puts each torque beside the
    next sample's position, whose motion leads its torque; half a sample first (an encoder latched mid-cycle,
    the torque interpolated). Kept only when the record then needs no disturbance: on the reference plant
    logged a sample late the estimate was flagged (K +10 %) after 84 s, latched half a sample late (K +9 %)
    after 74 s; with the torque that much earlier both are exact."""
    tried = [{"delay_samples": 0, "negative_log_likelihood": _likelihood_cost(pem)}]
    best, best_d, spent = pem, 0, pem.evaluations
    rejected: tuple[int, PemFit] | None = None
    for d in _delay_candidates(run, pem):
        run.delay_samples = d
        try:  # (the terms as the first estimate chose them, every configured one tried there)
            other = _kalman_stage(run, replace(best, lag_s=max(pem.lag_s - max(d, 0) / run.fs, 0.0)),
                                  retry=False, hedge=Hedge.NONE)
        except (IdentificationError, ValueError, np.linalg.LinAlgError) as err:
            tried.append({"delay_samples": d, "negative_log_likelihood": math.inf, "failed": str(err)})
            break
        spent += other.evaluations
        tried.append({"delay_samples": d, "negative_log_likelihood": _likelihood_cost(other)})
        if not _pays_for(run.kalman, best, other, 1):
            rejected = (d, other)
            break  # the delays are tried while each makes the record more likely
        best, best_d = other, d
    # (a torque earlier than logged is kept only when it explains the record: a misaligned log, not a basin)
    if best_d < 0 and _needs_disturbance(run, best):
        best, best_d = pem, 0
    run.delay_samples = best_d
    if rejected is not None and rejected[0] > 0:
        best, seeded = _seeded_by_delay(run, best, *rejected, tried)
        spent += seeded
    if best_d < 0:
        when, how = (("half a sample", "mid-cycle") if best_d == -0.5 else
                     ("a sample", "each torque logged beside the next sample's position"))
        run.notes.append(f"the encoders are latched {when} after the torque they answer ({how}): the torque is taken "
                         f"{when} earlier, and the record is "
                         f"{_likelier(tried[0]['negative_log_likelihood'], _likelihood_cost(best))}× as likely per "
                         "sample")
    elif best_d:
        run.notes.append(f"the torque acts {best_d} sample{'s' if best_d > 1 else ''} after its reference beyond the "
                         "hold's own (the drive's computation and encoder delays): the record is "
                         f"{_likelier(tried[0]['negative_log_likelihood'], _likelihood_cost(best))}× as "
                         "likely per sample as with the current loop's lag alone")
    return replace(best, evaluations=spent), tried


def _seeded_by_delay(run: _Run, best: PemFit, d: int, other: PemFit,
                     tried: list[dict[str, float]]) -> tuple[PemFit, int]:
    """The estimate at ``run.delay_samples`` again, from the one the delay ``d`` that did not pay for itself
    reached (its delay given back to the current loop's lag): the shifted torque moves the fit out of a
    basin a disturbance holds it in, and the likelier of the two is kept (22:151: ε 0.045° at a 0.7 %
    disturbance with the drive's delay, 0.058° (the truth) a sample later). Returns (it, evaluations)."""
    at = run.delay_samples
    start = replace(other, lag_s=other.lag_s + (d - at) / run.fs)
    try:
        seeded = _kalman_stage(run, start, retry=False, hedge=Hedge.NONE)
    except (IdentificationError, ValueError, np.linalg.LinAlgError) as err:
        tried.append({"delay_samples": at, "seeded_by_delay": d, "negative_log_likelihood": math.inf, "failed": str(err)})
        return best, 0
    nll, nll_best = _likelihood_cost(seeded), _likelihood_cost(best)
    tried.append({"delay_samples": at, "seeded_by_delay": d, "negative_log_likelihood": nll})
    if not nll < nll_best:
        return best, seeded.evaluations
    run.notes.append(f"from the estimate with the torque {d - at} sample{'s' if d - at > 1 else ''} later, the fit "
                     f"makes the record {_likelier(nll_best, nll)}× as likely per prediction error and is kept")
    return seeded, seeded.evaluations


def _hedged_stage(first: _Run, start: PemFit, run: _Run, pem: PemFit) -> tuple[_Run, PemFit]:
    """A load-encoder estimate (whose Kalman stage is not hedged) that needs a disturbance the assessment
    flags, tried again: the hedged Kalman fit
    (:attr:`~commission.ident.estimator.Hedge.GLOBAL`) from the torque-residual fit's ``start`` on the ``first``
    run finds the gap's basin, the Kalman fit from there the estimate (the hedged predictor's own optimum can
    sit a few % off ε behind narrow intervals: 22:095); the more likely of the two estimates is kept. On
    impact-rich records the plain likelihood is a needle around the gap and a start outside it moves nowhere
    (bench/results/family.md)."""
    hedged = _kalman_stage(first, start, hedge=Hedge.GLOBAL)
    other = _kalman_stage(first, hedged)
    spent = pem.evaluations + hedged.evaluations + other.evaluations
    if not _likelihood_cost(other) < _likelihood_cost(pem):
        run.notes.append("the estimate needs a large disturbance; the fit hedging the gap's contacts (sigma points "
                         "across the twist) did not explain the record better")
        return run, replace(pem, evaluations=spent)
    first.notes.append(_kept_note(run, pem, other, "", "from the fit hedging the gap's contacts (sigma points "
                                  "across the twist), the estimate"))
    return first, replace(other, evaluations=spent)


def _lag_stage(run: _Run, pem: PemFit) -> tuple[PemFit, bool]:
    """An estimate without a current loop that needs a disturbance, fitted again with the loop started at
    ``_LAG_STAGE_START_S``, kept when the record is likelier by more than the BIC's price of the terms added. From 0
    the loop's lag is within a standard error of it while the rest is a few % off, and the fit holds it there:
    25:002 (a 2.9 kHz loop recorded at 2 kHz) stayed at a 30 % disturbance with J_m +3 %, K +5 %, and went to
    the truth (1 % disturbance) from 50 or 125 µs."""
    other, kept = _refit(run, pem, replace(pem, terms=_configured_terms(run.opt), lag_s=_LAG_STAGE_START_S))
    if kept:
        run.notes.append(_kept_note(run, pem, other, " without a current loop",
                                    f"with one (started at {_LAG_STAGE_START_S * 1e6:.0f} µs) it"))
    return other, kept


def _refit(run: _Run, pem: PemFit, start: PemFit) -> tuple[PemFit, bool]:
    """The Kalman fit from ``start`` (``pem`` with other terms or their values), and whether it is kept: the record
    likelier than at ``pem`` by more than the BIC's price of the terms it adds; else ``pem`` (either with the
    evaluations of both)."""
    from .estimator import kalman_fit

    eps_max = max(run.epsilon_searched_rad, 2.0 * pem.epsilon_rad)
    other = kalman_fit(run.kalman, start, **_kalman_options(run, eps_max))
    spent = pem.evaluations + other.evaluations
    if not _pays_for(run.kalman, pem, other, len(start.terms.names()) - len(pem.terms.names())):
        return replace(pem, evaluations=spent), False
    return replace(other, evaluations=spent), True


def _cost_at(run: _Run, pem: PemFit, *, epsilon_rad: float | None = None,
             friction: tuple[float, float] | None = None) -> float:
    """The record's negative log-likelihood per prediction error at ``pem`` (its noise model) with ε [rad] or the
    Coulomb friction (motor, load) [N·m] replaced: one predictor pass."""
    from .kalman import innovations

    fm, fl = friction if friction is not None else (pem.coulomb_motor_nm if pem.terms.coulomb_motor else 0.0,
                                                     pem.coulomb_load_nm if pem.terms.coulomb_load else 0.0)
    inn = innovations(run.kalman, pem.parameters, pem.epsilon_rad if epsilon_rad is None else epsilon_rad,
                      coulomb_motor_nm=fm, coulomb_load_nm=fl, lag_s=pem.lag_s if pem.terms.current_loop else 0.0,
                      process_noise_nm=pem.process_noise_nm, load_share=pem.load_share)
    return inn.negative_log_likelihood() if inn is not None else math.inf


def _gap_stage(run: _Run, pem: PemFit) -> tuple[PemFit, bool]:
    """A motor-side estimate with a gap that needs a disturbance, fitted again from the likeliest ε of
    ``_GAP_FACTORS`` (weighed at the estimate's noise model, the rest held) where that one is likelier than the
    estimate's; the refit kept when the record is likelier. With the rest of the plant right the likelihood still
    dips sharply at the true gap, which the fit does not see from a start a third off: 22:191 (a 2.7° gap on a
    light load, J and K within 0.7 %) ended at ε 3.6° needing 14 %, and from ×0.75 went to the truth (1.2 %)."""
    from concurrent.futures import ThreadPoolExecutor

    base = _cost_at(run, pem)
    with ThreadPoolExecutor(max_workers=max(1, run.opt.threads)) as pool:  # (the predictor releases the GIL)
        costs = list(pool.map(lambda f: _cost_at(run, pem, epsilon_rad=f * pem.epsilon_rad), _GAP_FACTORS))
    if not min(costs) < base:
        return pem, False
    eps = _GAP_FACTORS[int(np.argmin(costs))] * pem.epsilon_rad
    other, kept = _refit(run, pem, replace(pem, epsilon_rad=eps))
    if kept:
        run.notes.append(_kept_note(run, pem, other, f" at ε {math.degrees(pem.epsilon_rad):.4g}°",
                                    f"from {math.degrees(eps):.4g}° it"))
    return other, kept


def _friction_stage(run: _Run, pem: PemFit) -> tuple[PemFit, bool]:
    """An estimate with Coulomb friction that needs a disturbance, fitted again from the likeliest of other
    values of its motor's and load's friction (each pair of ``_FRICTION_FACTORS`` on them, and
    ``_FRICTION_TRANSFERS`` of one side's moved to the other; weighed at the estimate's noise model, the rest
    held) where that one is likelier than the estimate; the refit kept when the record is likelier by more than
    the BIC's price of any term added. Below the resonance both sides slide together and the record
    determines the sum far better than the split: the fit can end with the split wrong and not move. 25:006
    stayed at a 5 % disturbance with the load's friction at 0; 22:049 at 5.5 % and 22:186 at 4.3 % with a
    fifth and a third of the sum on the load, not a fourteenth and an eighth (J, K within 0.3 %); from the
    values chosen each went to the truth (0.1–0.4 %)."""
    terms = _configured_terms(run.opt)
    on = (terms.coulomb_motor, terms.coulomb_load)
    base = (pem.coulomb_motor_nm if pem.terms.coulomb_motor else 0.0,
            pem.coulomb_load_nm if pem.terms.coulomb_load else 0.0)
    floor = sum(base) / 3.0
    if floor <= 0.0:
        return pem, False

    (m0, l0), sides = base, [[f * max(b, floor) for f in _FRICTION_FACTORS] if o else [0.0]
                             for b, o in zip(base, on)]
    moved = [(m0 + f * l0, (1.0 - f) * l0) for f in _FRICTION_TRANSFERS] + [
        ((1.0 - f) * m0, l0 + f * m0) for f in _FRICTION_TRANSFERS]
    pairs = [p for p in [(m, ld) for m in sides[0] for ld in sides[1]] + moved
             if p != base and all(o or v == 0.0 for v, o in zip(p, on))]
    costs = [_cost_at(run, pem, friction=p) for p in pairs]
    if not pairs or not min(costs) < _cost_at(run, pem):
        return pem, False
    fm, fl = pairs[int(np.argmin(costs))]
    other, kept = _refit(run, pem, replace(pem, terms=terms, coulomb_motor_nm=fm, coulomb_load_nm=fl))
    if kept:
        run.notes.append(_kept_note(run, pem, other, f" with Coulomb friction of {m0:.3g} N·m on the motor and "
                                    f"{l0:.3g} N·m on the load", f"from {fm:.3g} and {fl:.3g} N·m it"))
    return other, kept


def _cogging_stage(run: _Run, pem: PemFit) -> tuple[_Run, PemFit]:
    """A torque periodic in the motor's position (cogging, ripple) in the residual at the estimate: taken out of
    the record's torque and the estimate fitted again from there (once more where a tenth of it was left), kept
    when the record is then likelier by more than the BIC's price of the series' coefficients."""
    x = run.kalman.motor_position  # (the motor position as the Kalman stage read the record, rebuilt if need be)
    found = _cogging_in(run, pem, x)
    if found is None:
        return run, pem
    other, again, spent = run, pem, pem.evaluations
    for refined in (False, True):
        # (a delay the stage after this one finds delays τ_c with τ_ref: a sample, a few degrees of its period)
        other = replace(run, rec=run.rec.replace(torque_ref=run.rec.torque_ref + found.interval_torque(x)),
                        kalman=None, notes=[], cogging=found)
        other.problem = other.prepared(run.problem.cutoff_hz)
        again = _kalman_stage(other, again)
        spent += again.evaluations
        # the observer follows a share of a cogging as the load's motion (17 % on a 4 s record): what it left
        # is fitted again at the new estimate, on the record without what was found
        rest = None if refined else _cogging_in(other, again, x, found.harmonics)
        if rest is None or rest.peak_nm < 0.1 * found.peak_nm:
            break
        found = replace(found, cos_nm=tuple(float(a) for a in np.add(found.cos_nm, rest.cos_nm)),
                        sin_nm=tuple(float(b) for b in np.add(found.sin_nm, rest.sin_nm)))
    what = (f"a torque periodic in the motor's position (cogging or ripple: {', '.join(map(str, found.harmonics))} "
            f"per revolution, {1e3 * found.peak_nm:.3g} mN·m peak, {100 * found.explained:.0f} % of the residual)")
    if not _pays_for(other.kalman, pem, again, 2 * len(found.harmonics)):
        run.notes.append(f"the residual holds {what}; taken out of the torque, the record was not likelier: not kept")
        return run, replace(pem, evaluations=spent)
    other.notes = run.notes + [f"the residual held {what}: it is added to τ_ref, and the record is "
                               f"{_likelier(_likelihood_cost(pem), _likelihood_cost(again))}× as likely per "
                               "prediction error"]
    return other, replace(again, evaluations=spent)


def _cogging_in(run: _Run, pem: PemFit, x: NDArray[np.float64], harmonics: tuple[int, ...] | None = None) -> Any:
    """The cogging (commission.ident.cogging.Cogging) in the torque residual at ``pem``, None if none; ``x`` the
    motor's position [rad], shape (N,); ``harmonics``: these fitted, without a search."""
    from .cogging import find_cogging
    from .residual import Observer, torque_residual

    # a tenth of the configured observer's bandwidth: the configured one follows much of a cogging torque as the
    # load's motion (at the reference plant's truth it leaves 63 % of it in the residual, a tenth 95 %)
    p, fc = pem.parameters, run.problem.cutoff_hz
    observer = Observer.design(run.fs, _COGGING_OBSERVER * run.opt.observer_bandwidth_factor * fc, 2.0 * fc, p.K,
                               p.D, load_encoder=run.use_load)
    res = torque_residual(run.problem, p.J_m, p.J_l, p.B_m, p.B_l, p.K, p.D, pem.epsilon_rad,
                          coulomb_motor_nm=pem.coulomb_motor_nm,
                          coulomb_load_nm=pem.coulomb_load_nm if pem.terms.coulomb_load else None, lag_s=pem.lag_s,
                          observer=observer)
    return find_cogging(res.residual, x[1:-1], lowpass=functools.partial(sosfiltfilt, run.problem.sos),
                        decimation=run.problem.decimation, harmonics=harmonics)


def _kalman_stage(run: _Run, start: PemFit, *, hedge: Hedge | None = None, retry: bool = True) -> PemFit:
    """The estimate: prediction errors of the Kalman predictor of the whole state, from the torque-residual fit
    (``hedge``: how the fit hedges the gap's contacts, by default as :func:`_hedge` chooses from ``start``;
    :attr:`~commission.ident.estimator.Hedge.NONE` for a start already in the gap's basin), again with every
    configured term when it needs a disturbance or a term it leaves out scores above its price (``retry``)."""
    from .consistency import rebuilt_position_noise_rad
    from .estimator import kalman_fit, kalman_resettled
    from .kalman import kalman_problem
    from .residual import motor_position_samples

    rec = run.rec
    if run.kalman is None or run.kalman.delay_samples != run.delay_samples:
        run.kalman = kalman_problem(
            rec.torque_ref, motor_position_samples(rec.motor_position, rec.motor_velocity, run.fs), run.fs,
            load_position=rec.load_position if run.use_load else None,
            velocity_scale_rad_s=run.opt.coulomb_velocity_scale_rad_s, lost=run.lost if run.lost.any() else None,
            delay_samples=run.delay_samples, motor_noise_rad=rebuilt_position_noise_rad(rec))
    kp = run.kalman
    if run.delay_samples > 0 and start.process_noise_nm == 0.0:
        # a torque-residual fit's current loop stands in for the delay too
        start = replace(start, lag_s=max(start.lag_s - run.delay_samples / run.fs, 0.0))
    eps_max = max(run.epsilon_max_rad, 2.0 * start.epsilon_rad)
    if not math.isfinite(eps_max):
        eps_max = math.radians(2.0 * run.opt.epsilon_bounds_deg[1])
    run.epsilon_searched_rad = max(run.epsilon_searched_rad, eps_max)
    kw = _kalman_options(run, eps_max)
    if hedge is None:
        hedge = _hedge(run, start)
    memo: dict[str, Any] = {}
    pem = kalman_fit(kp, start, hedge=Hedge.START if hedge is Hedge.NEAR else hedge, memo=memo, **kw)
    if hedge is Hedge.NEAR and _needs_disturbance(run, pem):
        # the hedged fit's start alone brings most records into the gap's basin; where the estimate from
        # there needs a disturbance, the whole hedged fit (from the same hedged start: ``memo``), then the
        # plain one from its optimum (the hedged likelihood flattens above the gap: 24:000), the likelier
        # kept (22:015, 23:021 need it)
        full = kalman_fit(kp, start, hedge=hedge, memo=memo, **kw)
        plain = kalman_fit(kp, full, **kw)
        spent = pem.evaluations + full.evaluations + plain.evaluations
        pem = replace(plain if _likelihood_cost(plain) < _likelihood_cost(pem) else pem, evaluations=spent)
    # the torque-residual fit's term selection can miss friction the Kalman fit then needs a large
    # disturbance for (22:038, 22:049): from this estimate again with every configured term, kept when the
    # likelihood gain pays for the parameters added (the BIC)
    candidates = _configured_terms(run.opt)
    # so can the screen on the load's friction where the encoders measured the load's own equation of motion
    # and show friction the estimate lacks: left out, 0.8 % of τ_ref on a light load biased ε by 7 % behind an
    # interval that missed the truth (22:171); fitted from the start instead, it led 22:188 astray
    unfitted = (run.encoders is not None and run.encoders.coulomb_load_nm > 0.0 and candidates.coulomb_load
                and not pem.terms.coulomb_load)
    if not retry or candidates.names() == pem.terms.names() or not (
            _needs_disturbance(run, pem) or unfitted or _omits_a_term(run, pem, candidates, kw["epsilon_max_rad"])):
        return pem
    again = replace(pem, terms=candidates)
    if unfitted:
        again = replace(again, coulomb_load_nm=run.encoders.coulomb_load_nm)  # type: ignore[union-attr]
    other = kalman_fit(kp, again, **kw)
    if unfitted:
        # started at the encoders' friction, its noise model was chosen far from where it ended
        other = kalman_resettled(kp, other, epsilon_max_rad=eps_max, threads=run.opt.threads,
                                 max_nfev=run.opt.max_fit_evaluations)
    added = len(candidates.names()) - len(pem.terms.names())
    best = other if _pays_for(kp, pem, other, added) else pem
    return replace(best, evaluations=pem.evaluations + other.evaluations)


def _omits_a_term(run: _Run, pem: PemFit, candidates: ModelTerms, epsilon_max_rad: float) -> bool:
    """Whether a term of ``candidates`` the estimate leaves out would make the record likelier by more than the
    BIC's price of a parameter (ln n_eff in −2·ln L), by its score statistic at the estimate
    (:func:`~commission.ident.estimator.omitted_term_scores`): the torque-residual fit's selection dropped
    motor friction of 10 % of the load's on 23:036, whose estimate then needed only 0.8 % of the torque as a
    disturbance and came out J_l +3 %, K +2 %, not flagged."""
    from .estimator import omitted_term_scores

    scores = omitted_term_scores(run.kalman, pem, candidates, epsilon_max_rad=epsilon_max_rad)
    return any(v > math.log(max(pem.n_effective, 2.0)) for v in scores.values())


def _hedge(run: _Run, start: PemFit) -> Hedge:
    """The Kalman fit's :class:`~commission.ident.estimator.Hedge` from ``start``: without a load encoder every
    fit with a gap is hedged near its start (there the plain likelihood is a needle around the gap that a start
    a few % off does not leave; the hedged one recovers from ±5–10 %: bench/results/family.md); with one, none
    (:func:`_hedged_stage` hedges over ε's global grid where the estimate needs it). A start with no gap to
    speak of (ε below :data:`~commission.ident.estimator.EPSILON_ZERO_DEG`) is not hedged: the random walk is
    relative to ε, so that fit would be the plain one at 2–4× the cost (22:019: 47 → 11 s)."""
    if run.encoders is None and math.degrees(start.epsilon_rad) >= EPSILON_ZERO_DEG:
        return Hedge.NEAR
    return Hedge.NONE


def _check_stage(run: _Run, cell: Any, pem: PemFit) -> tuple[FitQuality, list[dict[str, float]]]:
    """The estimate's quality, and the paper's step 5 for the start and the result."""
    from .assess import assess
    from .frd import estimate_frd
    from .start import excited_band_hz

    rec, fs = run.rec, run.fs
    quality = assess(pem, torque_rms_nm=_torque_rms(run), sample_rate_hz=fs, load_encoder=run.use_load,
                     band_top_hz=excited_band_hz(rec.torque_ref, fs))
    if not _crosses_the_gap(run, pem):
        quality = replace(quality, approximate=True, reasons=(*quality.reasons, NO_CROSSING),
                          remedies=(*quality.remedies, "record a run in which the motor reverses (the excitation's "
                                    "bias changes sign), so that the load crosses the gap"))
    run.notes.extend(f"approximate result: {r}" for r in quality.reasons)
    if quality.noise_limited:
        run.notes.append(f"the model leaves {100 * quality.residual_ratio:.2f} % of the torque unexplained, but as "
                         "white, stationary noise: the record's noise, not model error")
    frd = run.start.frd if run.start is not None else estimate_frd(
        rec.torque_ref, rec.motor_velocity, fs, band_hz=run.band, resolution_hz=run.resolution, quality=False)
    iterations = []
    for label, p, e, lag, d in (("start", run.base, cell.epsilon_rad, 0.0, 0),
                                ("result", pem.parameters, pem.epsilon_rad, pem.lag_s, run.delay_samples)):
        if not 0.0 < _resonance_hz(p) < 0.25 * fs:  # an open-loop simulation could not resolve it
            run.notes.append(f"step 5 on the {label} skipped: its resonance is not below fs/4")
            continue
        try:
            iterations.append({"frd_error": _step5(rec, frd, p, e, lag, d), "epsilon_deg": math.degrees(e)})
        except IdentificationError as err:  # an open-loop simulation of a poor start may diverge
            run.notes.append(f"step 5 on the {label} failed: {err}")
    return quality, iterations


#: Why ε is not determined when the load never leaves one flank.
NO_CROSSING = ("the load never crosses the gap in this record (the shaft's torque keeps its sign: the motor "
               "never reverses), so the record does not determine ε")


def _crosses_the_gap(run: _Run, pem: PemFit) -> bool:
    """Whether the shaft's torque changes sign in the estimate's load simulation (so the load crosses the
    gap, whatever its width): if not, every ε explains the record alike (a record cut from a run before the
    motor reverses). Without a torque-residual problem (none was built), assumed so."""
    above, below = _flank_samples(run, pem)
    return above >= _CROSSING_SAMPLES and below >= _CROSSING_SAMPLES


def _keeps_one_flank(run: _Run, pem: PemFit) -> bool:
    """Whether the estimate's shaft torque presses on one flank only (not: never on either, an estimate whose
    gap the load never closes)."""
    above, below = _flank_samples(run, pem)
    return (above >= _CROSSING_SAMPLES) != (below >= _CROSSING_SAMPLES)


def _flank_samples(run: _Run, pem: PemFit) -> tuple[int, int]:
    """The samples of the estimate's load simulation whose shaft torque lies above, and below, ±
    ``_CROSSING_LEVEL`` of its largest magnitude (both ``_CROSSING_SAMPLES`` without a torque-residual
    problem: none was built)."""
    from .residual import simulate_load

    if run.problem is None:
        return _CROSSING_SAMPLES, _CROSSING_SAMPLES
    p = pem.parameters
    shaft = simulate_load(run.problem, p.J_l, p.B_l, p.K, p.D, pem.epsilon_rad,
                          pem.coulomb_load_nm if pem.terms.coulomb_load else None).shaft_torque
    level = _CROSSING_LEVEL * float(np.max(np.abs(shaft)))
    return int(np.count_nonzero(shaft > level)), int(np.count_nonzero(shaft < -level))


#: The shaft's torque changes sign when at least this many samples lie beyond this share of its largest
#: magnitude on each side.
_CROSSING_LEVEL = 0.01
_CROSSING_SAMPLES = 10


def _identification(run: _Run, pem: PemFit, quality: FitQuality, iterations: list[dict[str, float]],
                    stages: list[StageResult], scan_evaluations: int) -> Identification:
    from .scan import EPSILON_EXTEND_MAX_DEG
    from .start import measured_band_hz

    eps = pem.epsilon_rad
    if quality.interval_scale > 1.0:  # the intervals as the assessment widened them
        pem = replace(pem, covariance=pem.covariance * quality.interval_scale ** 2)
    determined = quality.determined and NO_CROSSING not in quality.reasons
    detected = math.degrees(eps) > run.opt.no_backlash_threshold_deg
    if not detected and determined:
        run.notes.append(f"no backlash detected: ε̂ = {math.degrees(eps):.4f}° ≤ {run.opt.no_backlash_threshold_deg}°")
    params = pem.parameters
    num, den = params.velocity_tf()
    try:
        plant_modes = modes(params)
    except IdentificationError as err:  # an estimate with no resonance: a result all the same, saying so
        plant_modes = Modes(math.nan, math.nan, math.nan, math.nan, math.nan)
        quality = replace(quality, approximate=True,
                          reasons=(*quality.reasons, f"the estimate has no two-mass modes to report ({err})"))
        run.notes.append(f"approximate result: {quality.reasons[-1]}")
    return Identification(
        method=Method.HYBRID, parameters=params, epsilon_rad=eps,
        epsilon_interval_rad=(_epsilon_interval(pem, float(run.cutoff["position_step_rad"])) if determined
                              else (0.0, max(run.epsilon_searched_rad, math.radians(EPSILON_EXTEND_MAX_DEG), eps))),
        epsilon_determined=determined,
        evaluations=scan_evaluations + pem.evaluations, modes=plant_modes, num=num, den=den,
        delay_s=(1 + run.delay_samples) / run.fs, iterations=iterations, stages=stages, source_samples=len(run.rec),
        sample_rate_hz=run.fs, backlash_detected=detected, notes=run.notes, fit=quality,
        parameter_stderr=pem.relative_stderr, parameter_interval=_intervals(pem, quality.determined), friction=_friction(pem, run.opt),
        current_loop=_current_loop(pem, run.delay_samples), selection=pem.selection or None,
        cogging=run.cogging.to_dict() if run.cogging is not None else None,
        measured_band_hz=measured_band_hz(run.start.frd) if run.start is not None else run.band)


def _resonance_hz(p: TwoMassParameters) -> float:
    try:
        return float(modes(p).f_resonance_hz)
    except IdentificationError:  # no complex pole pair: nothing resonates
        return 0.0


def _best_cell(sc: Any) -> Any:
    """The scan's best cell that gives a plant with positive inertias (None: none does)."""
    return next((c for c in sc.cells if c.parameters is not None and math.isfinite(c.cost_nm)), None)


#: Relative resolution of the parameters: a coarse encoder's quantization error is not white where the
#: motor moves slowly (it keeps its sign over many samples), which the prediction errors' statistics
#: do not fully show; estimates of noise-free 17-bit records move by up to about this much.
_RELATIVE_RESOLUTION = 1e-3


def _epsilon_interval(pem: PemFit, position_step_rad: float) -> tuple[float, float]:
    """ε's 95 % interval [rad], at least ± the motor encoder's step (what the record resolves) and the
    model's relative resolution."""
    half = max(1.96 * pem.epsilon_stderr_rad, position_step_rad, _RELATIVE_RESOLUTION * pem.epsilon_rad)
    if not math.isfinite(half):
        half = math.inf
    lo, hi = max(pem.epsilon_rad - half, 0.0), pem.epsilon_rad + half
    if pem.epsilon_profile_deg is not None:  # and at least the likelihood ratio's on ε's rugged profile
        lo, hi = min(lo, math.radians(pem.epsilon_profile_deg[0])), max(hi, math.radians(pem.epsilon_profile_deg[1]))
    return lo, hi


def _intervals(pem: PemFit, determined: bool = True) -> dict[str, tuple[float, float]]:
    out = {}
    for name, rel in pem.relative_stderr.items():
        v = float(getattr(pem.parameters, name))
        half = min(max(1.96 * rel, _RELATIVE_RESOLUTION), 50.0) if math.isfinite(rel) and determined else 50.0  # e^50: unbounded
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


def _current_loop(pem: PemFit, delay_samples: float = 0) -> dict[str, Any] | None:
    if not pem.terms.current_loop or pem.lag_s <= 0:
        return {"delay_samples": delay_samples} if delay_samples else None
    tc, half = pem.lag_s, 1.96e-6 * pem.stderr("T_c_us")
    lo_t, hi_t = max(tc - half, 0.0), tc + half
    return {"bandwidth_hz": 1.0 / (2.0 * math.pi * tc),
            "bandwidth_interval_hz": [1.0 / (2.0 * math.pi * hi_t), 1.0 / (2.0 * math.pi * lo_t) if lo_t > 0 else math.inf],
            "time_constant_s": tc, "delay_samples": delay_samples}


def _step5(rec: Recording, frd: Any, params: TwoMassParameters, eps: float, lag_s: float = 0.0,
           delay_samples: float = 0) -> float:
    """Paper step 5: FRD of the open-loop dead-zone simulation vs the measured FRD (a kept current
    loop's lag enters as its exact mean over each held sample, a torque delay in whole samples)."""
    from scipy.signal import lfilter

    from .backlash import simulate_deadzone
    from .frd import estimate_frd
    from .paper import frd_error

    torque = rec.torque_ref
    if delay_samples < 0:  # a lead: the torque itself taken earlier (as the predictor took it)
        from .kalman import delayed_torque

        torque, delay_samples = delayed_torque(torque, delay_samples), 0
    if lag_s > 0.0:
        ts = 1.0 / rec.sample_rate_hz
        a = math.exp(-ts / lag_s)
        state = lfilter([0.0, 1.0 - a], [1.0, -a], torque)  # τ at each tick, from rest
        torque = torque + (state - torque) * (lag_s / ts) * (1.0 - a)
    sim = simulate_deadzone(params, eps, torque, rec.sample_rate_hz, delay_samples=1 + int(delay_samples))
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
