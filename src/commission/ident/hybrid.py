"""The identification pipelines: ``hybrid`` (default, accurate) and ``paper`` (faithful).

``hybrid`` (METHOD.md, "What works"), stage by stage:

1. ``frd``     — FRD of τ_ref → v_m (:func:`commission.ident.frd.estimate_frd`).
2. ``tffit``   — 2/3 rational fit with transient term and one-sample delay
   (:func:`commission.ident.tffit.fit_transfer_function`), leaving out FRD bins whose
   quality indicator is below ``quality_threshold`` (friction distorts the low band); when
   the current-loop lag is a candidate, an extra delay is fitted too (``fit_delay``: a loop
   acts on the FRD like about its time constant of delay, and left to the damping it spoils
   the start's B_m/B_l split). ``start`` maps it to a physical start
   (:func:`commission.ident.jointfit.linear_start`, robust to an unphysical damping split);
   when the whole-band fit is not exactly physical or bins were left out, fits from raised
   low edges (1, 5, 10 Hz; 20 Hz on plants resonating above 60 Hz) compete and the one
   leaving the smallest drift-free torque residual is taken (:func:`_robust_start`); a
   start resonating beyond fs/4, or whose anti-resonance lies below its band, is refused.
3. ``search``  — (ε, φ = B_l/(B_m+B_l), ω_a scale) cells on the drift-free torque residual
   (:mod:`commission.ident.residual`), J_m, B_m, J_l projected out in every evaluation —
   and, for the candidate terms, a motor Coulomb column and the lag: the fitted extra delay
   simulated as T_c, else a first-order lag column. When the Coulomb column is large
   (friction), the search is repeated with half of it simulated on the load side.
4. ``joint``   — least squares of all seven parameters and the candidate terms from the
   best cells (:func:`commission.ident.jointfit.joint_fit`), chaotic bursts dropped, ε ≥ 0;
   when bursts had to be dropped, a second pass searches ε again from that fit's parameters
   and, unless that search confirms the first pass's ε, fits the whole record
   (:func:`_second_pass`). Then **model selection**
   (:func:`_select_terms`): a candidate term is kept when it lowers the BIC (Wald z² > ln n),
   and the model is refitted with the kept terms only. Load Coulomb friction is fitted at all
   only when the search's Coulomb column found friction, or when the fit keeps a motor Coulomb
   term (``model_selection.screened_by_search`` says which).
   A result the approximate rules flag (the fit cannot follow the record: lightly damped,
   impact-rich plants whose load, re-simulated open loop from the motor position,
   decorrelates from the real one) goes to stage ``predictor``: ε scanned and all seven
   parameters refitted on :func:`commission.ident.residual.predictor_residual`, whose
   simulated load is corrected from the motor equation after every sample; taken when it
   reaches ``good_fit_ratio`` (:func:`_predictor_refit`), result.json ``fit.refined_by_predictor``.
   So does a result without extra terms that the rules pass but that leaves more than 5× the
   good-fit level over all samples, the dropped ones included (``_REFINE_ALL_SAMPLES_FACTOR``);
   the stage's ``trigger`` says which.
5. ``check``   — the paper's step 5 for the result: simulate the dead-zone model open loop
   (:func:`commission.ident.backlash.simulate_deadzone`), FRD of the simulation vs the
   measured FRD (:func:`commission.ident.paper.frd_error`); then the paper's step 6 once
   (backlash effect removed from v_m with the result, FRD refitted, step 5 again). Reported
   as iterations: the frequency-domain start (with the search's best ε), the joint-fit
   result, and its step-6 refit.

Terms beyond the paper's model (issue 8), each a candidate in ``model_terms``: Coulomb
friction F·tanh(v/v_s) on the motor side (a linear column of the residual) and on the
load side (inside the load simulation), and a first-order current-loop lag
T_c·τ̇ = τ_ref − τ (T_c nonlinear; the torque regressor is refiltered exactly). They are
written from the equations in :mod:`commission.ident.residual`, independently of
sim_drive's integrator (which uses the same physics but RK4 sub-steps, its own v_s and its
own lag update). Kept terms appear in result.json as ``friction`` / ``current_loop`` with
values and ±1.96σ intervals; ``model_selection`` lists every candidate's z² and decision.

No backlash: ε is fitted on [0, 2·upper bound]; ``backlash_detected`` is
ε̂ > ``no_backlash_threshold_deg`` and ``epsilon_deg`` is the estimate either way.

Load encoder (``use_load_encoder`` and the recording has ``load_position``): the
initial twist comes from the encoders instead of "centred, at rest", and the joint
fit gets a second residual block K̂·(x_l,sim − x_l,meas) [N·m], which ties the
simulated load to the measured one (the gap shows directly in the twist).

``paper`` wraps :func:`commission.ident.paper.paper_identify` (Bayesian search of ε on
max|v_m − v̂_m|, steps 5–6 iterated) into the same :class:`Identification`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..exceptions import IdentificationError
from ..recording import Recording
from .twomass import Modes, TwoMassParameters, modes

__all__ = [
    "Method",
    "SearchMethod",
    "IdentificationOptions",
    "StageResult",
    "Identification",
    "identify",
]


class Method(str, Enum):
    """Identification pipeline."""

    HYBRID = "hybrid"
    PAPER = "paper"


class SearchMethod(str, Enum):
    """How the hybrid pipeline searches its (ε, φ, ω_a-scale) starts."""

    COARSE = "coarse"
    """Exhaustive on a grid 5× coarser in ε than the resolution (the joint fit refines ε)."""
    GRID = "grid"
    """Exhaustive at the full ε resolution."""
    BAYES = "bayes"
    """Gaussian-process Bayesian optimisation over ε per (φ, scale) pair, full resolution."""


class IdentificationOptions(BaseModel):
    """Options of :func:`identify` (validated; units in the names and descriptions)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    method: Method = Field(Method.HYBRID, description="Pipeline: 'hybrid' (default) or 'paper'.")
    band_hz: tuple[float, float] = Field(
        (0.1, 400.0), description="Frequency band of the FRD and its fit [Hz], (low, high).")
    resolution_hz: float = Field(
        0.1, gt=0, description="FRD resolution [Hz]; the record must last ≥ 1/resolution_hz s.")
    epsilon_bounds_deg: tuple[float, float] = Field(
        (0.01, 1.0), description="Search range of the backlash half-width ε [deg] (paper Table 2). "
        "The hybrid grid search doubles the upper bound (up to 16°) while its best cell lies at the "
        "top; the joint fit may go down to 0 and up to twice the (extended) upper bound.")
    epsilon_resolution_deg: float = Field(
        0.01, gt=0, description="Resolution of the ε search grid [deg].")
    max_iterations: int = Field(
        5, ge=1, le=50, description="Paper method: passes of steps 4–6 at most. "
        "Hybrid: not used (its joint fit stops on convergence, see max_fit_evaluations).")
    max_fit_evaluations: int = Field(
        40, ge=5, le=500, description="Hybrid: least-squares function evaluations per start.")
    seed: int = Field(0, ge=0, description="Seed of the Bayesian optimiser.")
    residual_cutoff_hz: float = Field(
        400.0, gt=0, description="Zero-phase low-pass of the torque residual [Hz].")
    use_load_encoder: bool = Field(
        True, description="Use the load-side encoder when the recording has one.")
    no_backlash_threshold_deg: float = Field(
        0.01, ge=0, description="ε̂ at or below this [deg] is reported as 'no backlash detected'.")
    search: SearchMethod = Field(
        SearchMethod.COARSE, description="Hybrid: search of the joint fit's starts.")
    compare_searches: bool = Field(
        False, description="Hybrid: also run the full-resolution grid and the Bayesian search and "
        "report their evaluation counts and best cells (slower; for benchmarks).")
    damping_splits: tuple[float, ...] = Field(
        (0.2, 0.5, 0.8), description="Hybrid: candidates of φ = B_l/(B_m + B_l) [-] in the search.")
    omega_scales: tuple[float, ...] = Field(
        (1.0,), description="Hybrid: factors on the fitted anti-resonance frequency in the "
        "search, e.g. (1.0, 1.15) when backlash biases the FRD's modes low [-]. One factor "
        "sufficed on every plant of bench/bench_identify.py the model describes (and halves "
        "the search time).")
    starts: int = Field(3, ge=1, le=10, description="Hybrid: joint-fit starts from the best cells.")
    good_fit_ratio: float = Field(
        1e-3, ge=0, description="Hybrid: a joint-fit start whose RMS residual is below this "
        "fraction of RMS(low-passed τ_ref) ends the multi-start (measured noise floor with 24-bit "
        "encoders and 1e-4 N·m torque noise: 3e-4) [-].")
    robust_loss_ratio: float = Field(
        3e-3, ge=0, description="Hybrid: when the first joint-fit start ends on a plateau far above "
        "the noise floor with impact bursts in its residual, that start and the next ones minimise "
        "the Cauchy loss ln(1 + (r/c)²) with c = this × RMS(low-passed τ_ref) (0: least squares "
        "throughout); the burst trimming after them is least squares. Measured when introduced, on "
        "bench/bench_identify.py plants, noise seeds 1–6, mean wall time: ζ = 0.07 4.9 → 4.1 s, Coulomb "
        "4.7 → 3.7 s, 1 kHz lag 3.4 → 2.7 s; ε within 0.02° on the ζ = 0.07 plant for seeds 1–15 "
        "(least squares throughout: 14 of 15); plants whose first start converges are unchanged [-].")
    max_residual_ratio: float = Field(
        0.05, gt=0, description="Hybrid: fail when RMS(residual)/RMS(low-passed τ_ref) exceeds this [-].")
    threads: int = Field(2, ge=1, le=64, description="Threads for residual evaluations.")
    jacobian: Literal["broyden", "finite_difference"] = Field(
        "finite_difference", description="Hybrid: Jacobian of the joint fit's least squares — "
        "'finite_difference' (at every accepted point; 1 + n_parameters evaluations per step) or "
        "'broyden' (rank-one updates from the residuals already evaluated; finite differences at "
        "the first point, every few points, after poor steps and to confirm convergence). Broyden "
        "is faster but not as robust on lightly damped plants: measured on the ζ = 0.07 bench plant over "
        "noise seeds 1–15, ε off by 0.01–0.05° on 6 seeds (finite differences: 0.04° on 1).")
    model_terms: tuple[Literal["coulomb_motor", "coulomb_load", "current_loop"], ...] = Field(
        ("coulomb_motor", "coulomb_load", "current_loop"),
        description="Hybrid: candidate terms beyond the two-mass + dead-zone model — Coulomb "
        "friction F·tanh(v/v_s) on the motor and on the load side, a first-order current-loop "
        "lag (bandwidth identified). Each is kept only when the data support it (term_selection).")
    term_selection: Literal["bic", "keep_all"] = Field(
        "bic", description="Hybrid: 'bic' keeps a candidate term when it lowers the Bayesian "
        "information criterion n·ln(SSR) + k·ln(n) of the torque residual (n: kept residual "
        "samples after decimation, ≈ independent); 'keep_all' keeps every candidate.")
    coulomb_velocity_scale_rad_s: float = Field(
        2e-3, gt=0, description="Hybrid: velocity scale v_s of the Coulomb terms' smooth sign "
        "tanh(v/v_s) [rad/s], on both sides as stated (the load simulation takes sub-steps where the "
        "smooth sign is stiff).")
    quality_threshold: float = Field(
        0.9, ge=0, lt=1, description="Hybrid: FRD bins whose local-polynomial quality is below "
        "this are left out of the frequency-domain start (friction distorts the low frequencies) [-].")
    second_pass_dropped_fraction: float = Field(
        0.01, ge=0, le=1, description="Hybrid: when the joint fit drops more than this fraction "
        "of the residual as bursts, ε is searched again from its parameters and the record "
        "refitted whole; the second pass is kept when it drops under 0.9× as many samples at ≤ 1.5× "
        "the RMS residual, or explains the samples both keep clearly better [-].")
    motor_interpolation: Literal["local", "spline"] = Field(
        "local", description="Hybrid: motor position between samples for the load simulation: "
        "'local' (Catmull–Rom, a kink at an impact stays local) or 'spline' (global C² cubic "
        "spline, spreads impacts' kinks; see commission.ident.residual.motor_interpolant).")
    step6_check: bool = Field(
        True, description="Hybrid: also run the paper's step 6 (backlash effect removed from v_m, "
        "FRD refitted, step 5 again) on the result and report it as the last iteration.")
    predictor_refit: bool = Field(
        True, description="Hybrid: refit a result the approximate rules flag on the residual with a "
        "load-state predictor (the simulated load corrected from the motor equation after every "
        "sample; lightly damped, impact-rich plants), taken when it reaches good_fit_ratio.")

    @model_validator(mode="after")
    def _check(self) -> IdentificationOptions:
        lo, hi = self.band_hz
        if not (0 <= lo < hi):
            raise ValueError(f"band_hz must satisfy 0 ≤ low < high, got {self.band_hz}")
        elo, ehi = self.epsilon_bounds_deg
        if not (0 <= elo < ehi < 90):
            raise ValueError(f"epsilon_bounds_deg must satisfy 0 ≤ low < high < 90, got {self.epsilon_bounds_deg}")
        if self.epsilon_resolution_deg > ehi - elo:
            raise ValueError("epsilon_resolution_deg is larger than the search range")
        if not all(0 < p < 1 for p in self.damping_splits) or not self.damping_splits:
            raise ValueError("damping_splits must be in (0, 1)")
        if not all(s > 0 for s in self.omega_scales) or not self.omega_scales:
            raise ValueError("omega_scales must be positive")
        return self


@dataclass(frozen=True)
class StageResult:
    """One stage of a pipeline: its name, wall time and what it found."""

    name: str
    seconds: float
    """Wall time [s]."""
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Identification:
    """Result of :func:`identify` (SI units unless the name says otherwise)."""

    method: Method
    parameters: TwoMassParameters
    epsilon_rad: float
    """Backlash half-width ε [rad] (the estimate, also when no backlash is detected)."""
    epsilon_interval_rad: tuple[float, float]
    """Interval of ε [rad]: hybrid, ε̂ ± 1.96σ from the Jacobian; paper, the search's interval."""
    evaluations: int
    """Loss/residual evaluations of the ε search (hybrid: the search stage)."""
    modes: Modes
    num: NDArray[np.float64]
    """V_m/T_ref numerator, descending powers of s (from ``parameters``)."""
    den: NDArray[np.float64]
    """V_m/T_ref denominator, descending powers of s, den[0] = 1."""
    delay_s: float
    """Pure delay of the data [s] (one sample: the drive convention)."""
    iterations: list[dict[str, float]]
    """Step-5 checks: {"frd_error", "epsilon_deg"} per iteration."""
    stages: list[StageResult]
    source_samples: int
    sample_rate_hz: float
    backlash_detected: bool
    notes: list[str] = field(default_factory=list)
    evaluations_grid: int | None = None
    """Evaluations the full-resolution grid search took (when computed)."""
    evaluations_joint: int | None = None
    """Residual evaluations of the joint least-squares fits (hybrid: both passes and the
    refit after model selection)."""
    parameter_stderr: dict[str, float] | None = None
    """Relative standard errors of J_m … D (hybrid, from the Jacobian) [-]."""
    friction: dict[str, Any] | None = None
    """Kept Coulomb terms (hybrid): velocity_scale_rad_s and, per kept side, motor_nm /
    load_nm [N·m] with motor_interval_nm / load_interval_nm (±1.96σ); None when none kept."""
    current_loop: dict[str, Any] | None = None
    """Kept current-loop lag (hybrid): bandwidth_hz, bandwidth_interval_hz, time_constant_s;
    None when not kept."""
    selection: dict[str, Any] | None = None
    """Model selection (hybrid): per candidate term its Wald z², the BIC threshold ln(n), kept."""

    @property
    def epsilon_deg(self) -> float:
        return math.degrees(self.epsilon_rad)

    def stage(self, name: str) -> StageResult:
        """The stage called ``name``."""
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(name)

    def to_dict(self, source_file: str | None = None) -> dict[str, Any]:
        """The result.json document."""
        lo, hi = self.epsilon_interval_rad
        m = self.modes
        out: dict[str, Any] = {
            "backlash": {
                "epsilon_deg": math.degrees(self.epsilon_rad),
                "epsilon_interval_deg": [math.degrees(lo), math.degrees(hi)],
                "evaluations": int(self.evaluations),
                "method": self.method.value,
                "detected": bool(self.backlash_detected),
            },
            "two_mass": self.parameters.as_dict(),
            "modes": {
                "f_resonance_hz": float(m.f_resonance_hz),
                "zeta_resonance": float(m.zeta_resonance),
                "f_antiresonance_hz": float(m.f_antiresonance_hz),
                "zeta_antiresonance": float(m.zeta_antiresonance),
            },
            "transfer_function": {"num": [float(v) for v in self.num],
                                  "den": [float(v) for v in self.den],
                                  "delay_s": float(self.delay_s)},
            "iterations": [{"frd_error": float(it["frd_error"]), "epsilon_deg": float(it["epsilon_deg"])}
                           for it in self.iterations],
            "source": {"file": source_file, "sample_rate_hz": float(self.sample_rate_hz),
                       "samples": int(self.source_samples)},
            "stages": [{"name": s.name, "seconds": float(s.seconds)} for s in self.stages],
            "notes": list(self.notes),
        }
        joint = next((s.detail for s in self.stages if s.name == "joint"), None)
        if joint is not None and "residual_ratio" in joint:
            # how well the model reproduces the record: the number to read before trusting it
            out["fit"] = {"residual_ratio": float(joint["residual_ratio"]),
                          "residual_ratio_all_samples": float(joint.get("residual_ratio_all_samples",
                                                                        joint["residual_ratio"])),
                          "approximate": bool(joint.get("approximate", False)),
                          "dropped_fraction": float(joint.get("dropped_fraction", 0.0)),
                          "robust_loss": bool(joint.get("robust_loss", False)),
                          "refined_by_predictor": bool(joint.get("refined_by_predictor", False)),
                          "noise_limited": bool(joint.get("noise_limited", False))}
        if self.evaluations_grid is not None:
            out["backlash"]["evaluations_grid"] = int(self.evaluations_grid)
        if self.parameter_stderr is not None:
            out["two_mass_relative_stderr"] = {k: float(v) for k, v in self.parameter_stderr.items()}
        if self.friction is not None:
            out["friction"] = dict(self.friction)
        if self.current_loop is not None:
            out["current_loop"] = dict(self.current_loop)
        if self.selection is not None:
            out["model_selection"] = dict(self.selection)
        return out


# ----------------------------------------------------------------------------
# input checks
# ----------------------------------------------------------------------------
def _check_recording(rec: Recording, opt: IdentificationOptions) -> None:
    fs = rec.sample_rate_hz
    need = int(round(fs / opt.resolution_hz))
    if len(rec) < need:
        raise IdentificationError(
            f"recording of {len(rec) / fs:.3f} s is too short for a {opt.resolution_hz:g} Hz "
            f"resolution (needs {need / fs:.3f} s)")
    if opt.band_hz[1] > fs / 2:
        raise IdentificationError(
            f"band upper edge {opt.band_hz[1]:g} Hz is above Nyquist ({fs / 2:g} Hz)")
    if opt.residual_cutoff_hz >= fs / 2:
        raise IdentificationError(
            f"residual cut-off {opt.residual_cutoff_hz:g} Hz is above Nyquist ({fs / 2:g} Hz)")
    tau = rec.torque_ref
    if np.ptp(tau) == 0.0:
        raise IdentificationError("torque_ref is constant: the axis was not excited")
    v = rec.motor_velocity
    if np.ptp(v) == 0.0:
        raise IdentificationError("motor_velocity is constant: the motor did not move")
    n = len(rec)
    for name, x in (("torque_ref", tau), ("motor_velocity", v)):
        top = np.flatnonzero(x == x.max())
        if top.size >= max(10, n // 100):
            runs = np.diff(top)
            if np.sum(runs == 1) >= max(10, n // 100) - 1:
                raise IdentificationError(f"{name} sits at its extreme value for many consecutive "
                                          "samples: saturated or clipped")


# ----------------------------------------------------------------------------
# pipelines
# ----------------------------------------------------------------------------
Progress = Callable[[str, float], None]


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


def identify(recording: Recording, options: IdentificationOptions | None = None,
             progress: Progress | None = None) -> Identification:
    """Identify the two-mass model and the backlash from one chirp experiment.

    :param recording: torque_ref, motor_velocity (and motor_position, optional load encoder).
    :param options: see :class:`IdentificationOptions` (default: hybrid).
    :param progress: called as progress(stage, fraction ∈ [0, 1]) when a stage starts.
    :raises IdentificationError: the data cannot give a trustworthy model (one-line reason).
    """
    opt = options if options is not None else IdentificationOptions()
    note = None
    if not recording.is_uniform:
        # host-streamed runs carry the real SYNC times: identify on the nominal grid
        from .resample import to_uniform

        recording, rs = to_uniform(recording)
        note = (f"resampled from jittered sample times (period jitter rms {rs.jitter_rms_s * 1e6:.0f} µs, "
                f"max {rs.jitter_max_s * 1e6:.0f} µs) to a uniform {recording.sample_rate_hz:g} Hz grid")
    _check_recording(recording, opt)
    if opt.method is Method.PAPER:
        result = _identify_paper(recording, opt, _Stages(progress))
    else:
        from threadpoolctl import threadpool_limits

        # one BLAS thread: the pipeline's LAPACK calls are small and run from two threads at
        # once (see commission.ident.jointfit._one_blas_thread)
        with threadpool_limits(limits=1, user_api="blas"):
            result = _identify_hybrid(recording, opt, _Stages(progress))
    if note is not None:
        result.notes.insert(0, note)
    if progress is not None:
        progress("done", 1.0)
    return result


def _frd_and_fit(rec: Recording, opt: IdentificationOptions, st: _Stages,
                 notes: list[str] | None = None) -> tuple[Any, Any]:
    """FRD and its 2/3 fit. With ``notes`` (hybrid) the fit leaves out the bins whose quality
    indicator is below ``opt.quality_threshold`` (friction, impacts) and says so."""
    from .frd import estimate_frd
    from .tffit import fit_transfer_function

    st.start("frd", 0.0)
    frd = estimate_frd(rec.torque_ref, rec.motor_velocity, rec.sample_rate_hz,
                       band_hz=opt.band_hz, resolution_hz=opt.resolution_hz)
    st.done("frd", bins=int(frd.frequency_hz.size), resolution_hz=float(frd.resolution_hz))
    st.start("tffit", 0.1)
    if notes is None:
        fit = fit_transfer_function(frd)
    else:
        try:
            fit = _masked_fit(frd, opt, notes)
        except IdentificationError as err:
            # heavy friction can leave no physical fit of the whole band: the hybrid start then
            # tries raised low edges (_robust_start)
            notes.append(f"frequency-domain fit of the whole band failed ({err}); low band edges raised")
            st.done("tffit", failed=str(err))
            return frd, None
        if fit.delay_s > 1.0001 / rec.sample_rate_hz:
            notes.append(f"transfer-function fit: {1e6 * (fit.delay_s - 1.0 / rec.sample_rate_hz):.0f} µs "
                         "of delay fitted beyond the sample's (a current-loop lag acts like one on the FRD)")
    st.done("tffit", num=[float(v) for v in fit.num], den=[float(v) for v in fit.den],
            delay_s=float(fit.delay_s), fit_error=float(fit.fit_error),
            sk_iterations=int(fit.iterations), converged=bool(fit.converged))
    return frd, fit


def _bins(frd: Any, keep: NDArray[np.bool_]) -> Any:
    """``frd`` restricted to the bins ``keep`` (the DFTs and the quality are per bin)."""
    import dataclasses

    return dataclasses.replace(frd, frequency_hz=frd.frequency_hz[keep], response=frd.response[keep],
                               quality=frd.quality[keep], input_dft=frd.input_dft[keep],
                               output_dft=frd.output_dft[keep])


def _quality_mask(frd: Any, opt: IdentificationOptions) -> NDArray[np.bool_] | None:
    """Bins of quality ≥ ``opt.quality_threshold`` when some are below it and at least half
    remain; None when the fit takes every bin."""
    good = frd.quality >= opt.quality_threshold
    return good if (not good.all() and good.sum() >= 0.5 * good.size) else None


def _masked_fit(frd: Any, opt: IdentificationOptions, notes: list[str]) -> Any:
    """The hybrid start's 2/3 fit: bins of low quality left out (said in ``notes``); a candidate
    current-loop lag fitted as extra delay (see tffit._DELAY_GAIN; the joint fit then identifies
    T_c itself). Raises IdentificationError when no fit is found."""
    from .tffit import fit_transfer_function

    sel = frd
    good = _quality_mask(frd, opt)
    if good is not None:
        sel = _bins(frd, good)
        bad_f = frd.frequency_hz[~good]
        notes.append(f"frequency-domain start: {int((~good).sum())} of {good.size} FRD bins left out "
                     f"(quality < {opt.quality_threshold:g}; {bad_f.min():.1f}–{bad_f.max():.1f} Hz)")
    return fit_transfer_function(sel, fit_delay="current_loop" in opt.model_terms)


def _step5(rec: Recording, frd: Any, params: TwoMassParameters, eps: float, delay_s: float,
           opt: IdentificationOptions, lag_s: float = 0.0) -> float:
    """Paper step 5: FRD of the open-loop dead-zone simulation vs the measured FRD.

    ``lag_s``: a kept current-loop time constant T_c [s]; the simulation, which holds its torque
    over each sample, then gets the lag's exact mean over the sample (state τ_k at the tick,
    u_k held: τ̄_k = u_k + (τ_k − u_k)·(T_c/Ts)·(1 − e^{−Ts/T_c})). Coulomb friction is not in this
    simulation (it is exact per linear mode); the result says so when friction was kept.
    """
    from scipy.signal import lfilter

    from .backlash import simulate_deadzone
    from .frd import estimate_frd
    from .paper import frd_error

    d = max(0, int(round(delay_s * rec.sample_rate_hz)))
    torque = rec.torque_ref
    if lag_s > 0.0:
        ts = 1.0 / rec.sample_rate_hz
        a = math.exp(-ts / lag_s)
        state = lfilter([0.0, 1.0 - a], [1.0, -a], torque)  # τ at each tick, from rest
        torque = torque + (state - torque) * (lag_s / ts) * (1.0 - a)
    sim = simulate_deadzone(params, eps, torque, rec.sample_rate_hz, delay_samples=d)
    g = estimate_frd(rec.torque_ref, sim.motor_velocity, rec.sample_rate_hz,
                     band_hz=opt.band_hz, resolution_hz=opt.resolution_hz, quality=False)
    lo = max(1.0, opt.band_hz[0])
    return frd_error(frd, g, (lo, opt.band_hz[1]))


def _epsilon_candidates(opt: IdentificationOptions, coarse: bool,
                        bounds_deg: tuple[float, float] | None = None) -> NDArray[np.float64]:
    """ε grid [rad] over ``bounds_deg`` (default: the options' search range) and 0."""
    lo, hi = bounds_deg or opt.epsilon_bounds_deg
    step = opt.epsilon_resolution_deg * (5 if coarse else 1)
    n = int(math.floor((hi - lo) / step + 1e-9))
    grid = lo + step * np.arange(n + 1)
    if grid[-1] < hi - 1e-12:
        grid = np.append(grid, hi)
    return np.radians(np.unique(np.concatenate(([0.0], grid))))


#: The grid search's range is extended (its upper bound doubled, at most to this [deg]) while its
#: best cell lies within 2.5 grid steps of the top. Measured (reference plant, ε = 1.5°, the
#: default range up to 1°): best cell 0.96°, the fit ended at 0.83° (the gap crossings dropped as
#: "bursts", residual 0.09 % on the rest, nothing flagged); searched up to 2°: ε = 1.5000° in 1.9 s.
_EPSILON_EXTEND_MAX_DEG = 16.0
#: Ratio of the second pass's ε cells beyond the range (up to ``_EPSILON_EXTEND_MAX_DEG``), searched
#: when the first pass leaves more than ``_APPROXIMATE_ALL_SAMPLES`` over all samples: ~57 more
#: cells from 1°, 0.1–0.2 s (0.3–0.4 s with load friction simulated, whose second pass, run for
#: the stick windows it drops, does not need them: first pass at 0.1–0.6 %). Measured (reference
#: plant, range up to 1°): ε = 2, 3, 5, 8° ended at 0.22, 0.74, 1.69, 0.19° (the start's search
#: stops in a local minimum, or extends only to 2°); the first pass's linear parameters are right
#: nevertheless, and from them the wide cells find each ε exactly. ζ = 0.07 seeds 1–30 and 40
#: swept plants: no other result changed.
_WIDE_RATIO = 1.05


def _extend_upward(search: Any, eps_cands: NDArray[np.float64], hi_deg: float, opt: IdentificationOptions,
                   search_more: Any) -> tuple[Any, NDArray[np.float64], float]:
    """Double the upper bound of an ε grid search (to at most ``_EPSILON_EXTEND_MAX_DEG``) while its
    best cell lies within 2.5 grid steps of the top; ``search_more(ε [rad])`` searches the new
    cells. Returns (the combined search, all its ε cells [rad], the final upper bound [deg])."""
    from .jointfit import combine_searches

    step = math.radians(opt.epsilon_resolution_deg * (5 if opt.search is SearchMethod.COARSE else 1))
    while hi_deg < _EPSILON_EXTEND_MAX_DEG and search.best[0].epsilon_rad >= float(np.max(eps_cands)) - 2.5 * step:
        more = _epsilon_candidates(opt, coarse=opt.search is SearchMethod.COARSE, bounds_deg=(hi_deg, 2.0 * hi_deg))
        more = more[more > np.max(eps_cands) + 1e-12]
        eps_cands = np.concatenate((eps_cands, more))
        search = combine_searches((search, search_more(more)), eps_cands, opt.starts)
        hi_deg *= 2.0
    return search, eps_cands, hi_deg


def _identify_hybrid(rec: Recording, opt: IdentificationOptions, st: _Stages) -> Identification:
    from .jointfit import ModelTerms, combine_searches, joint_fit, search_starts
    from .residual import PREDICTOR_GAIN, prepare_residual

    notes: list[str] = []
    fs = rec.sample_rate_hz
    frd, fit = _frd_and_fit(rec, opt, st, notes)

    st.start("start", 0.25)
    use_load = bool(opt.use_load_encoder and rec.load_position is not None)

    def prepared(cutoff_hz: float) -> Any:
        return prepare_residual(
            rec.torque_ref, fs, motor_position=rec.motor_position, motor_velocity=rec.motor_velocity,
            cutoff_hz=cutoff_hz, load_position=rec.load_position if use_load else None,
            velocity_scale_rad_s=opt.coulomb_velocity_scale_rad_s, interpolation=opt.motor_interpolation)

    problem = prepared(opt.residual_cutoff_hz)
    candidates = ModelTerms(**{name: True for name in opt.model_terms})
    start, how, start_info = _robust_start(rec, opt, frd, fit, problem, candidates, notes)
    if how != "exact":
        notes.append("the fitted transfer function maps to no physical plant (damping split); "
                     "the start keeps J_m, B_m + B_l and the modes and searches the split")
    if rec.motor_position is None:
        notes.append("motor position rebuilt from the velocity (x[k] = x[k−1] + Ts·v[k])")
    if use_load:
        notes.append("load encoder used: initial twist from the encoders and a load-position "
                     "residual block K̂·(x_l,sim − x_l,meas)")
    w_load = float(start.K) if use_load else 0.0
    cutoff = _residual_cutoff(rec, opt, start, problem, notes)
    if cutoff["cutoff_hz"] < opt.residual_cutoff_hz:
        problem = prepared(cutoff["cutoff_hz"])
    st.done("start", parameters=start.as_dict(), how=how, load_encoder=use_load, residual=cutoff, **start_info)

    st.start("search", 0.3)
    eps_coarse = _epsilon_candidates(opt, coarse=opt.search is SearchMethod.COARSE)
    method = "grid" if opt.search in (SearchMethod.COARSE, SearchMethod.GRID) else "bayes"
    eps_cands = eps_coarse if method == "grid" else _epsilon_candidates(opt, coarse=False)
    # a delay fitted beyond the sample's (the start's transfer-function fit) is the current loop's
    # T_c to first order: the search simulates it exactly instead of its linear column. Measured
    # (seed 3): 500 Hz loop 3.6 → 1.0 s (the linear column left every start on a plateau, 9 % of
    # the record dropped), mid 100 Hz + friction + 1 kHz loop 2.6 → 2.1 s; others within noise.
    lag0 = start_info.get("delay_s", 1.0 / fs) - 1.0 / fs
    fixed0 = (None, lag0) if candidates.current_loop and lag0 > 0.0 else None
    ref = float(np.sqrt(np.mean(problem.torque_f ** 2)))

    def searched(phis: tuple[float, ...], fixed: Any, eps: Any = None) -> Any:
        return search_starts(problem, start, eps_cands if eps is None else eps, phis, opt.omega_scales,
                             method=method, n_best=opt.starts, seed=opt.seed, threads=opt.threads,
                             load_weight_nm_per_rad=w_load, terms=candidates, fixed_terms=fixed)

    splits = tuple(opt.damping_splits)
    if method == "grid" and candidates.coulomb_load and len(splits) > 1:
        # the middle split first: when its cells show friction the search is repeated with it
        # simulated (below) and the other splits need not be searched without it; otherwise
        # they are, and the cells are those of one search over all splits
        mid = splits[len(splits) // 2]
        search = searched((mid,), fixed0)
        if search.best[0].coulomb_motor_nm <= _FRICTION_SEARCH_RATIO * ref:
            rest = searched(tuple(p for p in splits if p != mid), fixed0)
            search = combine_searches((search, rest), eps_cands, opt.starts)
    else:
        search = searched(splits, fixed0)
    best = search.best[0]
    evaluations = search.evaluations
    fixed_now = fixed0
    friction_search: dict[str, Any] | None = None
    if candidates.coulomb_load and best.coulomb_motor_nm > _FRICTION_SEARCH_RATIO * ref:
        # friction: search again with the load's share in the load simulation (see the constant)
        first = best
        fixed_now = (0.5 * first.coulomb_motor_nm, first.lag_s)
        search = searched(splits, fixed_now)
        best = search.best[0]
        evaluations += search.evaluations
        friction_search = {"coulomb_nm": first.coulomb_motor_nm, "first_epsilon_deg": math.degrees(first.epsilon_rad),
                           "epsilon_deg": math.degrees(best.epsilon_rad)}
        notes.append(f"start search repeated with half of its Coulomb friction ({first.coulomb_motor_nm:.3g} N·m "
                     "in all) on the load side of the simulation")
    # a best cell at the top of the range: the backlash may be wider than the range (see the constant)
    eps_hi = opt.epsilon_bounds_deg[1]
    extended_deg: float | None = None
    if method == "grid":
        n0 = search.evaluations
        search, eps_cands, eps_hi = _extend_upward(search, eps_cands, eps_hi, opt,
                                                   lambda more: searched(splits, fixed_now, more))
        best = search.best[0]
        evaluations += search.evaluations - n0
    if eps_hi > opt.epsilon_bounds_deg[1]:
        extended_deg = eps_hi
        eps_coarse = eps_cands
        notes.append(f"ε search range extended to {extended_deg:g}°: the best cell of the configured range "
                     f"(up to {opt.epsilon_bounds_deg[1]:g}°) lay at its top")
    st.done("search", method=opt.search.value, evaluations=evaluations, friction_search=friction_search,
            extended_to_deg=extended_deg, lag_s=None if fixed0 is None else lag0,
            best=[{"epsilon_deg": math.degrees(c.epsilon_rad), "phi": c.phi,
                   "omega_scale": c.omega_scale, "cost_nm": c.cost} for c in search.best])
    evaluations_grid: int | None = None
    if opt.compare_searches:
        st.start("search_compare", 0.4)
        full = _epsilon_candidates(opt, coarse=False)
        g = search_starts(problem, start, full, opt.damping_splits, opt.omega_scales,
                          method="grid", n_best=1, threads=opt.threads, load_weight_nm_per_rad=w_load,
                          terms=candidates)
        b = search_starts(problem, start, full, opt.damping_splits, opt.omega_scales,
                          method="bayes", n_best=1, seed=opt.seed, load_weight_nm_per_rad=w_load,
                          terms=candidates)
        evaluations_grid = g.evaluations
        cell = lambda c: {"epsilon_deg": math.degrees(c.epsilon_rad), "phi": c.phi,  # noqa: E731
                          "omega_scale": c.omega_scale, "cost_nm": c.cost}
        st.done("search_compare", grid_evaluations=g.evaluations, grid_best=cell(g.best[0]),
                grid_seconds=g.seconds, bayes_evaluations=b.evaluations, bayes_best=cell(b.best[0]),
                bayes_seconds=b.seconds, coarse_evaluations=evaluations if opt.search is SearchMethod.COARSE else None)

    if ref <= 0 or best.cost > 10 * opt.max_residual_ratio * ref:
        raise IdentificationError(
            f"the model cannot explain the data: even the best start leaves "
            f"{100 * best.cost / max(ref, 1e-300):.0f} % of the torque unexplained")

    st.start("joint", 0.5)
    eps_max = math.radians(2.0 * eps_hi)
    # load Coulomb friction is a candidate of the joint fit only when the search's Coulomb column
    # found friction (see _FRICTION_SEARCH_RATIO): it is the one candidate inside the load
    # simulation, whose friction path (RK4, smooth sign) costs 2.5× the frictionless one, and
    # without friction its value only wanders (on ζ = 0.07 it was even kept, spuriously, on one
    # seed). Measured (bench_seeds.py, paired): ζ = 0.07 seeds 1–30 4.8 → 3.0 s mean, 29 of 30
    # within tolerance before and after (with the second pass's starts, see _second_pass); 1 kHz
    # lag 0.84 → 0.62 s; bench_identify.py: every frictionless plant faster (reference 0.92 →
    # 0.76 s, soft heavy 25 Hz 2.3 → 1.7 s), the same results on those the model describes
    fit_terms = candidates
    screened: dict[str, Any] | None = None
    if candidates.coulomb_load and friction_search is None:
        fit_terms = replace(candidates, coulomb_load=False)
        screened = {"coulomb_load": {"search_coulomb_nm": best.coulomb_motor_nm,
                                     "limit_nm": _FRICTION_SEARCH_RATIO * ref}}
    # pass 1 drops chaotic bursts; when it had to, pass 2 searches ε again from its parameters
    # (see _second_pass for the measurements behind this)
    jf = joint_fit(problem, start, search.best, epsilon_max_rad=eps_max,
                   max_nfev=opt.max_fit_evaluations, threads=opt.threads,
                   load_weight_nm_per_rad=w_load, stop_cost_nm=opt.good_fit_ratio * ref,
                   terms=fit_terms, jacobian=opt.jacobian,
                   robust_scale_nm=opt.robust_loss_ratio * ref, rescan_epsilons_rad=eps_coarse)
    joint_evaluations = jf.evaluations
    robust_loss = jf.robust_loss
    rescan = jf.rescan_epsilon_rad
    if robust_loss:
        notes.append("the first joint-fit start ended on a plateau far above the noise floor with "
                     "impact bursts in its residual; the starts were refitted with a Cauchy loss "
                     f"(scale {opt.robust_loss_ratio:g} × RMS τ_ref), then least squares without the bursts")
    if rescan is not None:
        e_end, e_cell = (math.degrees(e) for e in rescan)
        notes.append(f"a Cauchy-loss start ended at ε = {e_end:.3f}° on a plateau; ε scanned at its "
                     f"other parameters, the next start took the {e_cell:.2f}° cell")
    second_pass: dict[str, Any] | None = None
    if jf.dropped_fraction > opt.second_pass_dropped_fraction:
        jf, second_pass, eps_max = _second_pass(problem, jf, eps_coarse, opt, eps_max, w_load, ref, notes)
        joint_evaluations += int(second_pass["evaluations"])
    selection: dict[str, Any] | None = None
    if fit_terms.any:
        jf, selection = _select_terms(problem, jf, fit_terms, opt, eps_max, w_load, notes)
        joint_evaluations += int(selection.get("refit_evaluations", 0))
    if screened and jf.terms.coulomb_motor:
        # friction after all: the fit keeps a motor Coulomb term that the search's column did not
        # show above its limit — small friction, possibly the load's (measured: 0.001–0.002 N·m on
        # the load only came out as motor friction, ε 0.007° and J, K 0.2 % off): refit with the
        # load term from half of it, select again
        both = replace(jf.terms, coulomb_load=True)
        j2 = _refit_at(problem, jf, both, opt, eps_max, w_load, initial_mask=jf.mask,
                       load_friction_start_nm=0.5 * jf.coulomb_motor_nm)
        joint_evaluations += j2.evaluations
        jf, selection = _select_terms(problem, j2, both, opt, eps_max, w_load, notes)
        joint_evaluations += int(selection.get("refit_evaluations", 0))
        screened["coulomb_load"]["reconsidered"] = True
        notes.append("load Coulomb friction, screened out by the ε search, fitted after all: the fit kept a "
                     "motor Coulomb term")
    if screened:
        selection = dict(selection or {}, screened_by_search=screened)
    params = jf.parameters
    st.done("joint", second_pass=second_pass, robust_loss=robust_loss,
            rescan_epsilon_deg=None if rescan is None else [math.degrees(e) for e in rescan],
            evaluations=joint_evaluations, cost_nm=jf.cost, success=jf.success,
            message=jf.message, dropped_fraction=jf.dropped_fraction, dof=jf.dof,
            epsilon_stderr_deg=math.degrees(jf.epsilon_stderr_rad),
            relative_stderr=jf.relative_stderr, terms=list(jf.terms.names()),
            coulomb_motor_nm=jf.coulomb_motor_nm, coulomb_load_nm=jf.coulomb_load_nm, lag_s=jf.lag_s,
            selection=selection,
            starts=[{"epsilon_start_deg": math.degrees(a), "phi_start": b, "cost_nm": c,
                     "epsilon_deg": math.degrees(e)} for a, b, c, e in jf.starts])
    # written after the predictor stage, which may replace this fit by one that drops nothing
    dropped_note = None if jf.dropped_fraction <= 0 else (
        f"{100 * jf.dropped_fraction:.1f} % of the residual dropped (down-weighted to "
        "zero) as windows the model cannot reproduce — chaotic impacts while the load "
        "floats in the gap, stick at velocity reversals: " + _windows(jf.mask, fs / problem.decimation))
    ratio = jf.cost / ref
    st.items[-1].detail["residual_ratio"] = ratio
    # the same residual on every sample, the dropped windows included (= ratio when none were)
    ratio_all = _ratio_all_samples(problem, jf, w_load, ref) if math.isfinite(ratio) else ratio
    st.items[-1].detail["residual_ratio_all_samples"] = ratio_all
    if not math.isfinite(ratio):
        raise IdentificationError("the joint fit did not converge to finite parameters")
    if ratio > opt.max_residual_ratio:
        raise IdentificationError(
            f"the model cannot explain the data: residual is {100 * ratio:.1f} % of the torque "
            f"(limit {100 * opt.max_residual_ratio:.1f} %)")
    # a residual over the good-fit level that is white, stationary noise is the record's torque
    # noise, not model error (see the constants)
    noise_limited = False
    if ratio > _APPROXIMATE_FACTOR * opt.good_fit_ratio:
        white = _residual_whiteness(_inner_motor_block(problem, _all_samples_residual(problem, jf, w_load)),
                                    fs / problem.decimation)
        st.items[-1].detail["residual_whiteness"] = white
        noise_limited = (white["spectral_flatness"] >= _WHITE_FLATNESS
                         and white["window_rms_p90_over_median"] <= _WHITE_STATIONARY)
    st.items[-1].detail["noise_limited"] = noise_limited
    if noise_limited:
        notes.append(f"the model leaves {100 * ratio:.2f} % of the torque unexplained, "
                     f"{ratio / max(opt.good_fit_ratio, 1e-300):.0f}× the good-fit level, but that residual is "
                     f"white (spectral flatness {white['spectral_flatness']:.3f}) and stationary (window RMS "
                     f"p90/median {white['window_rms_p90_over_median']:.2f}): the record's torque noise, not "
                     "model error — not flagged approximate")
    # Measured (bench/bench_identify.py): plants the model describes end at 0.03–0.1 % of τ_ref;
    # the impact-rich stiff plants at 2–17 %, with K 28–72 % off. Past 5× the good-fit level
    # (0.5 % by default, the tuning's backlash-compensation gate) the result is said approximate.
    why: str | None = None  # the approximate rule that holds, as a note's text
    if ratio > _APPROXIMATE_FACTOR * opt.good_fit_ratio and not noise_limited:
        why = (f"the model leaves {100 * ratio:.2f} % of the torque unexplained, "
               f"{ratio / max(opt.good_fit_ratio, 1e-300):.0f}× the good-fit level — the axis has "
               "dynamics the model does not reproduce (e.g. chaotic impacts of a light, stiff, "
               "lightly damped load); the parameters, ε included, may be biased by tens of percent")
    elif jf.dropped_fraction > _APPROXIMATE_DROPPED:
        why = (f"the model reproduces the record only with "
               f"{100 * jf.dropped_fraction:.0f} % of it dropped (more than "
               f"{100 * _APPROXIMATE_DROPPED:.0f} %) — e.g. a lightly damped load whose impacts it "
               "cannot follow; ε may be off by tenths of a degree")
    elif ratio_all > _APPROXIMATE_ALL_SAMPLES:
        why = (f"the model explains the samples it kept ({100 * ratio:.2f} % of the "
               f"torque left) but not the {100 * jf.dropped_fraction:.0f} % it dropped: "
               f"{100 * ratio_all:.1f} % left over the whole record (more than "
               f"{100 * _APPROXIMATE_ALL_SAMPLES:.1f} %) — e.g. a lightly damped load whose impacts it "
               "cannot follow; ε may be off by tenths of a degree")
    approximate = why is not None
    st.items[-1].detail["approximate"] = approximate
    refined = None
    pdetail: dict[str, Any] = {}
    # why the predictor refit runs, as a note's text (None: it does not). A fit that ended with a
    # negative damping (the projection has no sign constraint) is no result either: the refit
    # starts it from the damping floor (measured: J_l/J_m = 2, 60 Hz, ζ 0.07, seed 7: B_m −8e-4,
    # refined to ε within 0.001°). A fit without extra terms that the rules pass but that leaves
    # more over all samples than they allow on the kept ones is refined too (see the constant).
    trigger: str | None = None
    if approximate:
        trigger = "the fit left the record unexplained (the approximate rules above)"
    elif not _physical(params):
        trigger = "the fit ended on no physical plant (a negative damping)"
    elif not jf.terms.any and ratio_all > max(_REFINE_ALL_SAMPLES_FACTOR * opt.good_fit_ratio, 2.0 * ratio):
        trigger = (f"the fit explained the samples it kept but left {100 * ratio_all:.2f} % of the "
                   "torque over the whole record")
    if trigger is not None and opt.predictor_refit and min(params.J_m, params.J_l, params.K) > 0:
        joint_detail = st.items[-1].detail
        st.start("predictor", 0.85)
        refined, pdetail = _predictor_refit(problem, jf, eps_coarse, eps_max, opt, ref, use_load)
        joint_evaluations += int(pdetail.get("evaluations", 0))
        pdetail["gain"] = PREDICTOR_GAIN
        if refined is None and (approximate or not _physical(params)) and "residual_ratio" in pdetail:
            # not followed closely enough at the default gain: a stronger correction (see the constant)
            refined, high = _predictor_refit(problem, jf, eps_coarse, eps_max, opt, ref, use_load,
                                             gain=_PREDICTOR_HIGH_GAIN,
                                             accept_ratio=_PREDICTOR_HIGH_GAIN_ACCEPT * opt.good_fit_ratio,
                                             second_start=True)
            joint_evaluations += int(high.get("evaluations", 0))
            pdetail = dict(high, gain=_PREDICTOR_HIGH_GAIN,
                           default_gain={k: v for k, v in pdetail.items() if k != "parameters"})
        st.done("predictor", trigger=trigger, **pdetail)
        if refined is not None:
            jf, params, approximate = refined, refined.parameters, False
            # the joint stage's figures are those of the result (the plain fit's stay in its other fields)
            joint_detail.update(approximate=False, refined_by_predictor=True, terms=list(refined.terms.names()),
                                residual_ratio=pdetail["residual_ratio"],
                                residual_ratio_all_samples=pdetail["residual_ratio"], dropped_fraction=0.0)
    # once refined, the dropped windows and the rule speak of the plain fit, no longer the result
    if dropped_note is not None:
        notes.append(("plain fit (before the predictor refit): " if refined is not None else "") + dropped_note)
    if why is not None:
        notes.append(("plain fit (before the predictor refit) approximate: " if refined is not None
                      else "approximate result: ") + why)
    if refined is not None:
        notes.append(f"result refined with a load-state predictor: {trigger}; its load re-simulated from "
                     "the motor position drifts from the real one across the impacts; with the simulated "
                     f"load corrected from the motor equation after every sample (gain {pdetail['gain']:g}) "
                     "the fit leaves "
                     f"{100 * pdetail['residual_ratio']:.3f} % of the torque (ε {pdetail['epsilon_deg']:.4f}°, "
                     f"was {pdetail['plain_epsilon_deg']:.4f}°)"
                     + (f"; without the terms it had kept ({', '.join(pdetail['terms_dropped'])})"
                        if pdetail["terms_dropped"] else ""))
    elif "default_gain" in pdetail:
        notes.append(f"a load-state predictor refit left {100 * pdetail['default_gain']['residual_ratio']:.2f} % "
                     f"of the torque (more than the good-fit level {100 * opt.good_fit_ratio:.2f} %), and "
                     f"{100 * pdetail['residual_ratio']:.2f} % with the gain {_PREDICTOR_HIGH_GAIN:g} (more than "
                     f"{100 * _PREDICTOR_HIGH_GAIN_ACCEPT * opt.good_fit_ratio:.2f} %): not taken")
    elif "residual_ratio" in pdetail:
        notes.append(f"a load-state predictor refit left {100 * pdetail['residual_ratio']:.2f} % of the "
                     f"torque (more than the good-fit level {100 * opt.good_fit_ratio:.2f} %): not taken")
    elif "error" in pdetail:
        notes.append(f"the load-state predictor refit failed ({pdetail['error']}): not taken")
    if not _physical(params):
        bad = ", ".join(f"{n} = {getattr(params, n):.3g}" for n in ("J_m", "J_l", "B_m", "B_l", "K", "D")
                        if getattr(params, n) < 0 or (n in ("J_m", "J_l", "K") and getattr(params, n) == 0))
        # seen with a backlash of degrees on a soft heavy (4°) or stiff light (2°) load: the load is
        # decoupled for most of the chirp, the FRD shows little of it and the start is 10–1000× off
        raise IdentificationError(
            f"the joint fit found no physical plant ({bad}; SI units): the record shows no two-mass "
            "plant the fit could reach from its frequency-domain start — e.g. a backlash of degrees "
            "that leaves the load decoupled for most of the excitation")

    st.start("check", 0.9)
    iterations: list[dict[str, float]] = []
    try:
        e0 = _step5(rec, frd, start, best.epsilon_rad, 1.0 / fs if fit is None else fit.delay_s, opt)
        iterations.append({"frd_error": e0, "epsilon_deg": math.degrees(best.epsilon_rad)})
    except IdentificationError as err:  # the start may be unphysical; not fatal
        notes.append(f"step 5 on the frequency-domain start failed: {err}")
    e1 = _step5(rec, frd, params, jf.epsilon_rad, 1.0 / fs, opt, lag_s=jf.lag_s if jf.terms.current_loop else 0.0)
    iterations.append({"frd_error": e1, "epsilon_deg": math.degrees(jf.epsilon_rad)})
    if jf.terms.coulomb_motor or jf.terms.coulomb_load:
        notes.append("step 5's open-loop simulation has no Coulomb friction: its frd_error includes the "
                     "friction's effect on the FRD")
    step6: dict[str, Any] = {}
    if opt.step6_check and jf.epsilon_rad > 0 and jf.terms.any:
        notes.append("step 6 check skipped: its frequency-domain refit has no friction or current-loop "
                     f"terms, and this result kept {', '.join(jf.terms.names())}")
    elif opt.step6_check and jf.epsilon_rad > 0:
        # the paper's step 6 applied to the hybrid result: remove the backlash's effect from
        # v_m with (parameters, ε̂), refit the FRD, step 5 again — shows whether the
        # frequency-domain refit would move the model (it should not when the model is right)
        from .paper import paper_identify

        try:
            pr = paper_identify(rec.torque_ref, rec.motor_velocity, fs, params,
                                fixed_epsilon_rad=jf.epsilon_rad, max_iterations=2, frd_tol=0.0,
                                frd_band_hz=(max(1.0, opt.band_hz[0]), opt.band_hz[1]))
            if len(pr.iterations) > 1:
                it = pr.iterations[1]
                iterations.append({"frd_error": float(it.frd_error), "epsilon_deg": math.degrees(it.epsilon_rad)})
                step6 = {"refit_parameters": it.params.as_dict(), "stop_reason": pr.stop_reason}
        except IdentificationError as err:
            notes.append(f"step 6 check on the hybrid result failed: {err}")
    st.done("check", frd_error=e1, **step6)

    eps = jf.epsilon_rad
    detected = math.degrees(eps) > opt.no_backlash_threshold_deg
    if not detected:
        notes.append(f"no backlash detected: ε̂ = {math.degrees(eps):.4f}° ≤ "
                     f"{opt.no_backlash_threshold_deg}°")
    num, den = params.velocity_tf()
    return Identification(
        method=Method.HYBRID, parameters=params, epsilon_rad=eps,
        epsilon_interval_rad=jf.epsilon_interval_rad, evaluations=evaluations,
        modes=modes(params), num=num, den=den, delay_s=1.0 / fs, iterations=iterations,
        stages=st.items, source_samples=len(rec), sample_rate_hz=fs, backlash_detected=detected,
        notes=notes, evaluations_grid=evaluations_grid, evaluations_joint=joint_evaluations,
        parameter_stderr=jf.relative_stderr, friction=_friction_section(jf, opt),
        current_loop=_current_loop_section(jf), selection=selection,
    )


#: A result whose residual exceeds this × good_fit_ratio is reported as approximate.
_APPROXIMATE_FACTOR = 5.0
#: ... and so is one that had to drop more than this fraction of the record. Measured (seed 3):
#: lightly damped plants the model cannot follow through their impacts — at their *true*
#: parameters the residual is 17 % (J_l/J_m = 2, 60 Hz, ζ 0.07) and 29 % (100 Hz, ζ 0.05) of
#: τ_ref — ended with a small residual on the rest, 23 % and 29 % dropped, and ε 0.26–0.27° too
#: high; accurate results dropped 0–15 % (0.03 N·m friction: its stick windows), except a
#: J_l/J_m = 2, 60 Hz plant with friction and lag: 21 %, ε within 0.003° (flagged all the same).
_APPROXIMATE_DROPPED = 0.2
#: ... and so is one whose residual over every sample, the dropped windows included, exceeds this
#: fraction of RMS τ_ref. Measured (bench_identify's plants, seed 7, and 24 unseen ones): results
#: within the issue's tolerances leave 0.03–0.7 % (1.2 % on a ζ 0.07 seed 0.015° off; 2.2 % with
#: 0.05 N·m of friction, flagged by the dropped fraction); wrong ones that the other two rules
#: let pass leave 5.2 % (100 Hz, ζ 0.1, ε 0.15°: ε 0.41°, 14 % dropped; since the second ε scan
#: of the joint fit ε 0.16° with 4.0 % left) and 5.9 % (ε 3°, beyond the extended search: ε 0.74°).
_APPROXIMATE_ALL_SAMPLES = 0.025
#: A result without extra terms that the approximate rules pass is still refined by the predictor
#: (:func:`_predictor_refit`) when its residual over every sample exceeds this × good_fit_ratio —
#: the level the first rule sets for the kept samples — and 2× the residual on the kept ones, so
#: that what is left lies in the dropped windows, not in the noise of a noisy record. Measured
#: (ζ 0.07, ε 0.25°, seeds 1–30, bench/bench_seeds.py): the seeds whose second pass could not
#: get back the windows it dropped left 1.0–1.2 % over all samples and ε 0.015–0.024° too low
#: (seed 30 beyond the issue's ±0.02°); refined, all four within 0.0003°, 30 of 30 within
#: tolerance instead of 29, at +1 s each (median 2.10 → 2.12 s, mean 2.57 → 2.80 s); ζ 0.07
#: with ε 0.15°: 0.0154° → 0.0002°. Unchanged: the other 39 plants of a 40-plant sweep and
#: bench_identify's (seed 7), where results without terms leave 0.03 % and those with friction
#: or a lag (not refined: the predictor models neither) up to 0.6 %. Not taken (+1.5 s): a stiff light 150 Hz, ζ 0.07 plant (1.1 %).
_REFINE_ALL_SAMPLES_FACTOR = 5.0
#: The first approximate rule (residual over 5× the good-fit level) does not flag a result whose
#: residual on every sample is white (spectral flatness ≥ this) and stationary (window RMS
#: p90/median ≤ ``_WHITE_STATIONARY``, :func:`_residual_whiteness`): that is the record's torque
#: noise. Measured (seed 5): accurate results on records with 3e-3 and 1e-2 N·m of torque noise
#: (residual 0.52 % and 1.75 %; reference, heavy 40 Hz, soft heavy 25 Hz, ζ 0.07, with friction,
#: with a lag: ε within 0.001°, J, K 0.1 %), all flagged before, give flatness 0.991–0.992 and
#: p90/median 1.05–1.08; the wrong results of impact-rich plants give 0.20–0.89 and 1.76–260
#: (stiff light 200 Hz, also under 3e-3 and 1e-2 N·m of noise; stiff 300 Hz: 0.83–0.89, 1.76–2.3;
#: J_l/J_m = 0.1 at 250 Hz: 0.73, 2.7; 100 Hz ζ 0.05), the accurate ones at 1e-4 N·m 0.86 and 1.07.
_WHITE_FLATNESS = 0.95
_WHITE_STATIONARY = 1.3
#: The residual's low-pass is lowered from ``residual_cutoff_hz`` when the motor encoder's
#: quantization alone would leave more than this × good_fit_ratio of τ_ref at the start's
#: J_m (:func:`_quantization_floor_nm`; it grows as cut-off^2.5: the acceleration of a quantized
#: position), to the cut-off where it leaves that much, but not below
#: ``_CUTOFF_RESONANCE_FACTOR`` × the start's resonance. Measured (seed 5, 400 Hz): with a 17-bit
#: encoder the quantization leaves 3.0 % of τ_ref at the true parameters (3.1 % predicted), with
#: 16 bits 6.2 %, with 20 bits 0.38 %, with 24 bits 0.03 % (with the torque noise); at 17 bits the
#: reference plant's result was flagged approximate (J, K 1.2 % off), the ζ 0.07 plant's wrong
#: (ε +0.10°, J, K 8 % off), and at 16 bits the run failed on the 5 % limit. With the low-pass at
#: 150 or 200 Hz the reference, ζ 0.07, soft heavy 25 Hz and 0.01 N·m plants at 17 bits ended
#: within 0.001° and 0.1 %.
_QUANTIZATION_TARGET_FACTOR = 2.5
#: ... see ``_QUANTIZATION_TARGET_FACTOR`` (stiff light 150 Hz at 17 bits, low-pass 150 Hz: K 2 % off).
_CUTOFF_RESONANCE_FACTOR = 2.0

#: The start search is repeated with half its Coulomb friction in the load simulation when its
#: motor column found more than this fraction of the RMS torque reference. Its first run stands
#: the motor column in for both frictions, and on friction plants its best cells sit far below the
#: true ε (0.0–0.11° for 0.40°, seed 7); with the load's share simulated they sit at 0.36–0.41°,
#: and the joint fit needs no Cauchy restart. Measured on the bench plants: 0.10–0.31 with
#: 0.01–0.03 N·m per side, below 0.002 in absolute value without friction.
#: bench/bench_seeds.py, seeds 1–9, mean wall time when introduced (with the start's fitted delay,
#: same session): Coulomb 0.01 N·m 4.8 → 3.7 s, 0.03 N·m 8.5 → 7.0 s; all within tolerance before
#: and after. (Today's times, after later changes: README, "Known limits".)
_FRICTION_SEARCH_RATIO = 0.02


def _windows(mask: Any, rate_hz: float, most: int = 6) -> str:
    """The dropped windows of a keep-mask as "a–b s" text (the longest ``most``)."""
    if mask is None:
        return "none"
    bad = np.concatenate(([False], ~np.asarray(mask, dtype=bool), [False]))
    d = np.diff(bad.astype(np.int8))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    order = np.argsort(ends - starts)[::-1][:most]
    parts = [f"{starts[i] / rate_hz:.2f}–{ends[i] / rate_hz:.2f} s" for i in sorted(order)]
    more = len(starts) - len(parts)
    return ", ".join(parts) + (f" and {more} shorter" if more > 0 else "")


#: Raised low band edges of the frequency-domain start [Hz]. 2 Hz was one too, and never chosen
#: (bench plants on seeds 3, 5, 7; 40 swept plants: no result changed without it); each edge is
#: a 2/3 fit of 0.1–0.4 s (stiff light 200 Hz: 4.0 → 3.3 s).
_RAISED_EDGES_HZ = (1.0, 5.0, 10.0)
#: A further edge, tried when the FRD's resonance peak (max of |V/T|·f above 5 Hz; measured at
#: 1.0–1.4× the true resonance on the bench plants) lies at ≥ 3× it, so that both modes stay in
#: the band. Measured: with 0.01 N·m of Coulomb friction per side on a light, stiff load
#: (J_l/J_m = 0.2, 150 Hz) every fit from 10 Hz down came out with K ≈ 0.3–0.8 (71 N·m/rad), fit
#: error 0.17–0.19, and the identification ended with K off ×100 (35 s); from 15 Hz up K within
#: 3 % (15 % with a 1 kHz current loop too), fit error 0.04. On soft plants (modes below 30 Hz) the
#: edge would cut a mode and costs 0.3–0.6 s of fitting: not tried there.
_HIGH_EDGE_HZ = 20.0


def _robust_start(rec: Recording, opt: IdentificationOptions, frd: Any, fit: Any, problem: Any,
                  candidates: Any, notes: list[str]) -> tuple[Any, str, dict[str, Any]]:
    """The frequency-domain start, made safe against distorted low frequencies.

    The fit of the whole band (quality-masked) is taken when it maps exactly to a physical
    plant and no FRD bin was masked: nothing changes on plants the model describes. Otherwise
    (friction, lag) fits from raised low edges (``_RAISED_EDGES_HZ``, ``_HIGH_EDGE_HZ``; quality-masked) are candidates
    too, and the one whose start leaves the smallest drift-free torque residual (projected, at
    ε = 0 and an even damping split, with the candidate terms' linear columns) is taken: the
    time domain judges, with friction in the model. Measured on 0.01 N·m of Coulomb friction
    per side: the whole band gave no resonance (seed 11) or a start with K ≈ 0 (seed 7);
    from 1 Hz up, J_m, J_l and K within 2 %.
    """
    from .jointfit import _cell_cost, linear_start

    masked = _quality_mask(frd, opt) is not None
    fits: list[tuple[float, Any]] = [] if fit is None else [(opt.band_hz[0], fit)]
    # a start whose resonance lies beyond fs/4 is no start: the load simulation's RK4 (one
    # step per sample, taken with load friction) diverges near fs/2.2. Seen with an unmodelled 1 kHz lag on a light
    # 150 Hz plant: an "exact" start with K/J_l = 1.9e16 s⁻², NaN in every search cell.
    f_max = 0.25 * rec.sample_rate_hz

    def usable(p: TwoMassParameters, f_lo: float) -> bool:
        # ... and one whose anti-resonance lies below the band it was fitted from was not fitted
        # to a mode the data show (friction on a light load: from 5–10 Hz up, K ≈ 0.5 for 71)
        try:
            m = modes(p)
            return p.K > 0 and p.J_l > 0 and p.J_m > 0 and m.f_resonance_hz < f_max and m.f_antiresonance_hz > f_lo
        except IdentificationError:  # no resonance at all
            return False

    try:
        if fit is not None:
            start, how = linear_start(fit.num, fit.den)
            if how == "exact" and not masked and usable(start, opt.band_hz[0]):
                return start, how, {"delay_s": float(fit.delay_s)}
    except IdentificationError:
        pass
    def raised(f_lo: float) -> Any:
        # the FRD's bins are independent DFT bins: those from f_lo up are the FRD of that band
        try:
            return _masked_fit(_bins(frd, frd.frequency_hz >= f_lo - 1e-9 * frd.resolution_hz), opt, [])
        except IdentificationError:
            return None

    above = frd.frequency_hz >= 5.0
    f_peak = (float(frd.frequency_hz[above][np.argmax(np.abs(frd.response[above]) * frd.frequency_hz[above])])
              if above.any() else 0.0)
    edges = _RAISED_EDGES_HZ + ((_HIGH_EDGE_HZ,) if f_peak >= 3.0 * _HIGH_EDGE_HZ else ())
    edges = tuple(f for f in edges if opt.band_hz[0] < f < 0.1 * opt.band_hz[1])
    # one after the other: on two threads the fits (small numpy operations, GIL-bound) took
    # longer than in turn (measured, soft heavy 25 Hz: 0.68–0.88 s against ~0.45 s)
    for f_lo in edges:
        f2 = raised(f_lo)
        if f2 is not None:
            fits.append((f_lo, f2))
    scored: list[tuple[float, float, Any, str]] = []
    for f_lo, f in fits:
        try:
            st_, hw = linear_start(f.num, f.den)
        except IdentificationError:
            continue
        if not usable(st_, f_lo):
            continue
        cost = _cell_cost(problem, st_, 0.0, 0.5, 1.0, 0.0, candidates).cost
        scored.append((cost, f_lo, st_, hw, float(f.delay_s)))
    if not scored:
        raise IdentificationError("the fitted transfer function is not that of a two-mass plant "
                                  f"(resonance below fs/4 = {f_max:.0f} Hz) from any low band edge up to {max(edges, default=opt.band_hz[0]):g} Hz")
    scored.sort(key=lambda c: c[0])
    cost, f_lo, start, how, delay = scored[0]
    if f_lo > opt.band_hz[0]:
        notes.append(f"frequency-domain start fitted from {f_lo:g} Hz up (chosen by the torque "
                     "residual among low band edges; the low band is distorted)")
    return start, how, {"delay_s": delay, "band_low_hz": f_lo, "candidates": [{"band_low_hz": c[1], "cost_nm": c[0]}
                                                            for c in scored]}


#: Second pass taken also when, on the samples both passes keep, its RMS residual is below this
#: fraction of the first pass's while it drops about as much (≤ 1.5× + 0.5 % of the record).
#: Measured (Coulomb plant, noise seed 3): first pass ε 0.168° at 1.9× the noise floor dropping
#: 3.6 %, second pass ε 0.400° at the noise floor dropping 4.0 % — the old rule (fewer dropped)
#: kept the first.
_CLEARLY_BETTER = 0.75
#: ... or when it drops fewer than this fraction of the first pass's dropped samples (a margin:
#: the burst mask's extent varies by a few % of itself between nearby fits). Measured: a
#: J_l/J_m = 2, 60 Hz plant with friction and lag, first pass ε 0.303° (true 0.30°) dropping
#: 21.3 %, second pass 0.360° dropping 20.0 % and no better on the samples both keep — taken
#: by "fewer dropped" alone.
_FEWER_DROPPED = 0.9


def _physical(p: TwoMassParameters) -> bool:
    """Positive inertias and stiffness, non-negative dampings."""
    return min(p.J_m, p.J_l, p.K) > 0 and min(p.B_m, p.B_l, p.D) >= 0


#: Gain of the predictor's second refit (x_l += gain·e/K after every sample), run when the first,
#: at ``residual.PREDICTOR_GAIN``, does not reach the good-fit level on an approximate (or
#: unphysical) result; taken when it leaves at most ``_PREDICTOR_HIGH_GAIN_ACCEPT`` ×
#: good_fit_ratio. The stronger correction keeps the simulated load on the real one through the
#: impacts of a stiff, light load, as multiple shooting does for a chaotic system, at the price of
#: a less sharp ε. Measured (stiff light 200 Hz, J_l/J_m 0.2, ζ 0.11, seeds 1, 3, 7): the plain fit
#: ends with K 28 % low, the gain-0.1 refit at 1.3–1.7 %; at 0.5 it leaves 0.07–0.16 % with ε
#: within 0.003°, J, K within 0.65 %, the modes within 0.5 %; seeds 1–10: 9 within the issue's
#: tolerances. The tenth (seed 2) ends at 0.26 % with J, K 4.5 % off: not taken at 2.5×, taken
#: (wrongly) at 3.5×; the wrong ends seen otherwise leave 0.54–5 %. Not rescued (5 % left, not
#: taken): stiff 300 Hz and light 300 Hz J_l/J_m 5, at +1.5–3 s.
_PREDICTOR_HIGH_GAIN = 0.5
_PREDICTOR_HIGH_GAIN_ACCEPT = 2.5
#: The high-gain refit starts a second time from the widest ε cell whose scan cost is within this
#: fraction of the best's. At the plain fit's parameters the scan can be flat: stiff light 200 Hz,
#: seed 11 (plain ε 0.01° for 0.25°): 0.74–0.80 % of τ_ref from 0.02° to 0.3°, best 0.04°, from
#: which the refit ends at ε 0.053°, 0.54 %; from 0.15°, 0.25° or 0.4° it ends at 0.243–0.245°,
#: 0.13–0.15 %, J, K within 2 % — the narrow minimum shows only near the true rates.
_PREDICTOR_SCAN_NEAR = 0.1
#: Iterations cap of the predictor refit's least squares (converged in 15–29 on the plants it helps).
_PREDICTOR_MAX_NFEV = 40
#: Relative forward-difference step of the predictor refit's Jacobian (as scipy's diff_step).
_PREDICTOR_DIFF_STEP = 1e-6


def _predictor_refit(problem: Any, jf: Any, eps_cells: Any, eps_max: float, opt: IdentificationOptions,
                     ref: float, use_load: bool, gain: float | None = None,
                     accept_ratio: float | None = None, second_start: bool = False) -> tuple[Any, dict[str, Any]]:
    """Refit a result on :func:`residual.predictor_residual` (the simulated load corrected from
    the motor equation after every sample), taken when it reaches the good-fit level: an
    approximate one, one on no physical plant, or one that leaves much of the record it dropped
    unexplained (the caller decides). Returns (the refined fit or None, the stage's detail).

    Measured (bench/bench_predictor.py; noise seed 3): the lightly damped plants whose impacts the
    plain residual cannot follow (at the true parameters it leaves 17 % and 32 % of τ_ref) ended
    with ε 0.26–0.28° too high, flagged; their linear parameters were right (J, K within 0.7 %).
    From them, an ε scan on the predictor residual (best cells 0.14° for 0.20° and 0.23° for
    0.30°) and a least-squares fit of all seven parameters reach ε within 0.0001° and J, K within
    0.03 % at the noise floor (100 Hz ζ 0.05; J_l/J_m = 2, 60 Hz, ζ 0.07). On the stiff light 200 Hz
    plant it ends at 1.5 % of τ_ref at the default gain: not taken; the caller then refits at
    ``gain`` = ``_PREDICTOR_HIGH_GAIN`` with ``accept_ratio`` and ``second_start`` (a second start
    from the widest near-best ε cell when the first is not taken). The predictor models no friction
    or current-loop terms: terms the approximate fit kept (spuriously, e.g. a lag on the 60 Hz
    plant) are dropped when the refit reaches the good-fit level without them, and a plant that
    needs them does not reach it. Skipped with a load encoder (no load-position block).
    """
    from concurrent.futures import ThreadPoolExecutor

    from scipy.optimize import least_squares

    from .jointfit import ModelTerms
    from .residual import predictor_residual

    if use_load:
        return None, {"skipped": "a load encoder is used: the predictor has no load-position block"}
    if jf.terms.coulomb_motor or jf.terms.coulomb_load:
        # measured: 0.05 N·m per side (flagged for the 27 % it drops) — 11 s of refit, not taken
        return None, {"skipped": "the fit kept Coulomb friction, which the predictor does not model"}
    p = jf.parameters
    floor = 1e-9 * max(p.B_m + p.B_l, p.D, 1e-12)

    def unpack(z: NDArray[np.float64]) -> tuple[TwoMassParameters, float]:
        J_m, J_l, B_m, B_l, K, D = np.exp(z[:6])
        return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=B_m, B_l=B_l, K=K, D=D), math.radians(z[6])

    calls = [0]
    last: dict[bytes, NDArray[np.float64]] = {}  # the latest point's residual: its Jacobian's base

    def residual_at(z: NDArray[np.float64]) -> NDArray[np.float64]:
        q, e = unpack(z)
        return predictor_residual(problem, q.J_m, q.J_l, q.B_m, q.B_l, q.K, q.D, e,
                                  **({} if gain is None else {"gain": gain}))

    def fun(z: NDArray[np.float64]) -> NDArray[np.float64]:
        calls[0] += 1
        r = residual_at(z)
        last.clear()
        last[z.tobytes()] = r
        return r

    def jac(z: NDArray[np.float64]) -> NDArray[np.float64]:
        # forward differences from the point least_squares has just evaluated, the columns on
        # opt.threads threads (the simulation releases the GIL)
        f0 = last.get(z.tobytes())
        if f0 is None:
            f0 = fun(z)
        steps = _PREDICTOR_DIFF_STEP * np.maximum(np.abs(z), 1.0)

        def column(i: int) -> NDArray[np.float64]:
            dz = z.copy()
            dz[i] += steps[i]
            return (residual_at(dz) - f0) / steps[i]

        calls[0] += z.size
        return np.stack(list(pool.map(column, range(z.size))), axis=1)

    def scan_cost(e_rad: float) -> float:
        z = z0.copy()
        z[6] = math.degrees(e_rad)
        r = residual_at(z)
        return float(np.sqrt(np.mean(r * r)))

    z0 = np.array([math.log(max(v, floor)) for v in (p.J_m, p.J_l, p.B_m, p.B_l, p.K, p.D)]
                  + [math.degrees(jf.epsilon_rad)])
    cells = np.asarray(eps_cells, dtype=float)
    lo = np.array([-np.inf] * 6 + [0.0])
    hi = np.array([np.inf] * 6 + [math.degrees(eps_max)])
    with ThreadPoolExecutor(max_workers=opt.threads) as pool:
        # ε scanned first with the other parameters held: the plain fit's ε is the wrong one
        scan = np.array(list(pool.map(scan_cost, cells)))
        calls[0] += len(scan)
        # starts: the scan's best cell; when a refit from it is not taken, also the widest cell
        # within _PREDICTOR_SCAN_NEAR of the best (see the constant)
        best = float(cells[int(np.argmin(scan))])
        widest = float(np.max(cells[scan <= (1.0 + _PREDICTOR_SCAN_NEAR) * np.min(scan)]))
        starts = [best] + ([widest] if second_start and widest > best else [])
        accept = opt.good_fit_ratio if accept_ratio is None else accept_ratio
        fit = None
        for e_start in starts:
            z = z0.copy()
            z[6] = math.degrees(e_start)
            try:
                f = least_squares(fun, np.clip(z, lo, hi), jac=jac, bounds=(lo, hi), method="trf",
                                  x_scale=np.array([0.1] * 6 + [0.05]), max_nfev=_PREDICTOR_MAX_NFEV)
            except (ValueError, np.linalg.LinAlgError) as err:  # a non-finite simulation
                if fit is None:
                    return None, {"evaluations": calls[0], "error": str(err)}
                break
            if fit is None or f.cost < fit.cost:
                fit, z0[6] = f, z[6]
            if np.sqrt(2.0 * fit.cost / fit.fun.size) <= accept * ref:
                break
    q, eps = unpack(fit.x)
    r = fit.fun
    n = r.size
    rms = float(np.sqrt(np.mean(r * r)))
    evaluations = calls[0]
    detail: dict[str, Any] = {"evaluations": evaluations, "residual_ratio": rms / ref,
                              "epsilon_deg": math.degrees(eps), "plain_epsilon_deg": math.degrees(jf.epsilon_rad),
                              "start_epsilon_deg": float(z0[6]), "parameters": q.as_dict(),
                              "terms_dropped": list(jf.terms.names()), "taken": False}
    if not (rms <= accept * ref and np.all(np.isfinite(fit.x))):
        return None, detail
    # interval as the joint fit's: cov = s²·(JᵀJ)⁻¹ in (ln J_m … ln D, ε [deg]), n ≈ independent samples
    s2 = float(r @ r) / max(n - 7, 1)
    try:
        cov = s2 * np.linalg.inv(fit.jac.T @ fit.jac)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        sd = np.full(7, math.nan)
    se = math.radians(float(sd[6]))
    detail["taken"] = True
    refined = replace(jf, parameters=q, epsilon_rad=eps, cost=rms, epsilon_stderr_rad=se,
                      epsilon_interval_rad=(max(eps - 1.96 * se, 0.0), eps + 1.96 * se),
                      relative_stderr={k: float(v) for k, v in zip(("J_m", "J_l", "B_m", "B_l", "K", "D"), sd[:6])},
                      dof=max(n - 7, 1), evaluations=jf.evaluations + evaluations, residual=r,
                      dropped_fraction=0.0, mask=None, n_used=n, terms=ModelTerms(), coulomb_motor_nm=0.0,
                      coulomb_load_nm=0.0, lag_s=0.0, term_stderr={})
    return refined, detail


def _all_samples_residual(problem: Any, jf: Any, w_load: float) -> NDArray[np.float64]:
    """The residual vector of the fit ``jf`` on every sample, the dropped ones included [N·m]
    (as :func:`residual.residual_vector`: the low-passed, decimated motor block first)."""
    if jf.dropped_fraction <= 0:
        return np.asarray(jf.residual, dtype=float)
    from .residual import residual_vector

    p = jf.parameters
    return residual_vector(problem, p.J_m, p.J_l, p.B_m, p.B_l, p.K, p.D, jf.epsilon_rad, load_weight_nm_per_rad=w_load,
                           coulomb_motor_nm=jf.coulomb_motor_nm if jf.terms.coulomb_motor else 0.0,
                           coulomb_load_nm=jf.coulomb_load_nm if jf.terms.coulomb_load else None,
                           lag_s=jf.lag_s if jf.terms.current_loop else 0.0)


#: Decimated residual samples at each end of the record left out of the all-samples residual's
#: RMS: the zero-phase low-pass's edge transients (a 4th-order Butterworth settles in ~2/f_c,
#: 4 samples after decimation to 2·f_c). Filter artefacts, not data: the odd padding anchors on
#: the last (noisy) sample. Measured at the true parameters, last sample / RMS of the others:
#: 24-bit encoder 10×; 17 bits, low-pass 142 Hz, 35×; 16 bits, 131 Hz, 472× — the fit drops
#: it as a burst, and it alone made the all-samples residual 3.3 % instead of 0.3 %.
_EDGE_SAMPLES = 4


def _ratio_all_samples(problem: Any, jf: Any, w_load: float, ref: float) -> float:
    """RMS residual of the fit ``jf`` over every sample, the dropped ones included but the
    low-pass's edge transients not (``_EDGE_SAMPLES``), / ``ref``."""
    if jf.dropped_fraction <= 0:
        return float(jf.cost / ref)
    v = _all_samples_residual(problem, jf, w_load)
    v = np.concatenate((_inner_motor_block(problem, v), v[problem.acceleration_f.shape[0]:]))
    return float(np.sqrt(np.mean(v * v))) / ref


def _inner_motor_block(problem: Any, v: NDArray[np.float64]) -> NDArray[np.float64]:
    """The motor block of a residual vector without the low-pass's edge transients (``_EDGE_SAMPLES``)."""
    n = problem.acceleration_f.shape[0]
    return v[:n][_EDGE_SAMPLES:n - _EDGE_SAMPLES] if n > 4 * _EDGE_SAMPLES else v[:n]


def _residual_cutoff(rec: Recording, opt: IdentificationOptions, start: TwoMassParameters, problem: Any,
                     notes: list[str]) -> dict[str, float]:
    """The residual's low-pass [Hz] for this record (see ``_QUANTIZATION_TARGET_FACTOR``) and the
    quantization floor (:func:`_quantization_floor_nm`) at the start's J_m, as the start stage's detail."""
    from scipy.optimize import brentq

    from .residual import motor_position_samples

    ref = max(float(np.sqrt(np.mean(problem.torque_f ** 2))), 1e-300)
    fs, fc = rec.sample_rate_hz, opt.residual_cutoff_hz
    steps = np.abs(np.diff(motor_position_samples(rec.motor_position, rec.motor_velocity, fs)))
    steps = steps[steps > 0]
    count = float(np.min(steps)) if steps.size else 0.0

    def floor(f_hz: float) -> float:
        return _quantization_floor_nm(count, start.J_m, fs, f_hz) / ref

    target = _QUANTIZATION_TARGET_FACTOR * opt.good_fit_ratio
    out = {"cutoff_hz": fc, "quantization_floor_ratio": floor(fc), "position_step_rad": count}
    if out["quantization_floor_ratio"] <= target:
        return out
    f_res = modes(start).f_resonance_hz
    lowest = min(fc, _CUTOFF_RESONANCE_FACTOR * f_res)
    new = max(lowest, brentq(lambda f: floor(f) - target, 1e-3 * fc, fc)) if floor(lowest) < target else lowest
    out.update(cutoff_hz=new, configured_cutoff_hz=fc, quantization_floor_ratio=floor(new),
               quantization_floor_ratio_configured=floor(fc))
    notes.append(f"the motor encoder's step ({count:.3g} rad) would leave {100 * floor(fc):.2f} % of the torque "
                 f"as noise in the residual low-passed at {fc:g} Hz; low-passed at {new:.0f} Hz instead "
                 f"({100 * floor(new):.2f} %; the start's resonance {f_res:.0f} Hz) — a finer encoder would let "
                 "the fit see more")
    return out


def _quantization_floor_nm(step_rad: float, J_m: float, sample_rate_hz: float, cutoff_hz: float) -> float:
    """RMS torque residual [N·m] that a motor position quantized in steps of ``step_rad`` leaves
    through J_m·ẍ_m: uniform quantization noise (variance step²/12, white) through the second
    difference (|H|² = 16·sin⁴(ω/2)) times fs², and the residual's zero-phase low-pass (the 4th-order
    Butterworth of :func:`residual.prepare_residual`, applied twice: |H|⁴).

    Measured: within 3 % of such noise through ``prepare_residual`` (tests); 3.1 % of τ_ref for a
    17-bit encoder on the reference plant at 400 Hz, where the true parameters leave 3.0 %.
    """
    from scipy.signal import butter, sosfreqz

    sos = butter(4, min(cutoff_hz, 0.49 * sample_rate_hz), fs=sample_rate_hz, output="sos")
    w, h = sosfreqz(sos, worN=4096)
    power = 16.0 * np.sin(0.5 * w) ** 4 * np.abs(h) ** 4
    var = step_rad * step_rad / 12.0 * float(np.sum(0.5 * (power[1:] + power[:-1]) * np.diff(w))) / math.pi
    return J_m * sample_rate_hz ** 2 * math.sqrt(max(var, 0.0))


def _residual_whiteness(v: NDArray[np.float64], rate_hz: float) -> dict[str, float]:
    """How much a residual (shape (n,), sampled at ``rate_hz``) looks like white, stationary noise.

    ``spectral_flatness``: geometric / arithmetic mean of its Welch PSD (256-sample segments)
    from 5 Hz to 0.8 × Nyquist — near 1 for white noise, lower when the power sits in bands.
    ``window_rms_p90_over_median``: the 90th percentile / median of its RMS over 50 equal
    windows — near 1 when stationary, large when bursts (impacts) carry it.
    """
    from scipy.signal import welch

    f, P = welch(v, fs=rate_hz, nperseg=min(256, v.size))
    band = (f > 5.0) & (f < 0.4 * rate_hz) & (P > 0)
    flat = float(np.exp(np.mean(np.log(P[band]))) / np.mean(P[band])) if band.any() else 0.0
    w = np.array([np.sqrt(np.mean(x * x)) for x in np.array_split(v, 50) if x.size])
    med = float(np.median(w))
    return {"spectral_flatness": flat,
            "window_rms_p90_over_median": float(np.percentile(w, 90)) / med if med > 0 else math.inf}


def _second_pass(problem: Any, jf: Any, eps_cands: Any, opt: IdentificationOptions,
                 eps_max: float, w_load: float, ref: float, notes: list[str]) -> tuple[Any, dict[str, Any], float]:
    """Search ε again around the first joint fit, then fit again on the whole record.

    Returns (the fit taken, the pass's detail, the ε bound [rad] for later refits: raised when
    the search's range was extended).

    Measured (1 kHz current loop, reference plant): from the frequency-domain start, which the
    lag biases, the first fit stalls at 80× the noise floor; the burst mask then drops the
    windows where the gears cross the gap (11 %), and the refit finds every linear parameter
    and T_c exactly but ε = 0.11° instead of 0.40° — the data that fix ε were dropped. The
    linear parameters of a stalled fit are nevertheless a good start: a new ε search from
    them (F_cl and T_c held at the fit's values, exactly), then a joint fit on the whole
    record, recovers ε (also on 0.01 N·m Coulomb friction, where the first pass ended at
    ε = 0.105°, and on the ζ = 0.07 plant, 0.38° → 0.25°). The pass that drops fewer samples
    at no more than 1.5× the RMS residual is taken, and so is one that explains the samples both
    passes keep clearly better (``_CLEARLY_BETTER``) while dropping about as many. Measured, too: running pass 1 without
    dropping bursts and comparing whole-record residuals instead fails on the ζ = 0.07 plant
    (pass 1 then ends with D −65 %, and pass 2 from there at ε = 0.30°): the dropped windows
    are what lets pass 1 get the linear parameters right, the kept ones what fixes ε.

    The refit runs all its starts (no consensus stop) unless one reaches the noise floor: this
    pass exists because the first ended on impact bursts, and two starts that agree on such a
    plateau are what it must get past. Measured (ζ = 0.07, seeds 1–30, load friction screened
    out): the first two starts of seeds 12 and 18 agreed on ε = 0.226° (true 0.25°) at 9× the stop
    cost, dropping 13.5 %; the third, from the 0.31° cell, reached 0.250° at the noise floor
    (27 → 29 of 30 within tolerance).

    When the new search's best cell is the grid cell nearest the first pass's ε, the search
    confirms it and the refit is skipped. Measured (bench/bench_seeds.py, seeds 1–9): the friction
    plants' first pass ends at the noise floor at the right ε and drops its stick windows; the
    refit, which always came back to the same ε and was never taken, cost 0.5–1 s (Coulomb
    3.7 → 2.6 s, Coulomb + lag 2.8 → 2.0 s mean). On the ζ = 0.07 plant the searches that
    disagree with a wrong first pass (0.245°, 0.313°, 0.405°: best cells 0.21°, 0.26°) still refit.
    """
    from .jointfit import joint_fit, search_starts

    p = jf.parameters
    phi = p.B_l / max(p.B_m + p.B_l, 1e-300)

    def searched(eps: Any) -> Any:
        return search_starts(problem, p, eps, (phi,), (1.0,), method="grid", n_best=opt.starts,
                             threads=opt.threads, load_weight_nm_per_rad=w_load, terms=jf.terms,
                             fixed_terms=(jf.coulomb_load_nm, jf.lag_s))

    # from the first pass's parameters the ε search can see a backlash wider than the range the
    # start's search saw: when the first pass leaves the record unexplained (the approximate
    # rule on all samples), its cells go on geometrically (_WIDE_RATIO) up to _EPSILON_EXTEND_MAX_DEG
    hi_deg = 0.5 * math.degrees(eps_max)
    eps_cands = np.asarray(eps_cands, dtype=float)
    wide = np.zeros(0)
    if _ratio_all_samples(problem, jf, w_load, ref) > _APPROXIMATE_ALL_SAMPLES:
        n_wide = int(math.log(_EPSILON_EXTEND_MAX_DEG / hi_deg) / math.log(_WIDE_RATIO))
        wide = np.radians(hi_deg * _WIDE_RATIO ** np.arange(1, n_wide + 1))
        wide = wide[wide > np.max(eps_cands) + 1e-12]
    s = searched(np.concatenate((eps_cands, wide)))
    searched_to = math.degrees(float(np.max(wide))) if wide.size else hi_deg
    if s.best[0].epsilon_rad > math.radians(hi_deg):
        eps_max = max(eps_max, 2.0 * s.best[0].epsilon_rad)
        notes.append(f"second pass: ε searched up to {searched_to:.3g}° from the first fit's parameters; "
                     f"its best cell {math.degrees(s.best[0].epsilon_rad):.2f}° lies beyond the range the "
                     f"start's search covered (up to {hi_deg:g}°)")
    # the search confirms the first pass when its best cell is the grid cell nearest the first
    # pass's ε: the refit would start where the first pass ended (measured: see the docstring)
    grid = np.unique(eps_cands)
    if s.best[0].epsilon_rad == grid[np.argmin(np.abs(grid - jf.epsilon_rad))]:
        notes.append(f"second pass: ε searched again from the first fit's parameters confirms "
                     f"{math.degrees(jf.epsilon_rad):.3f}° (best cell {math.degrees(s.best[0].epsilon_rad):.2f}°); "
                     "no refit")
        return jf, {"evaluations": s.evaluations, "epsilon_deg": math.degrees(jf.epsilon_rad), "taken": False,
                    "confirmed": True, "first_epsilon_deg": math.degrees(jf.epsilon_rad),
                    "first_dropped_fraction": jf.dropped_fraction, "searched_to_deg": searched_to}, eps_max
    j2 = joint_fit(problem, p, s.best, epsilon_max_rad=eps_max, max_nfev=opt.max_fit_evaluations,
                   threads=opt.threads, load_weight_nm_per_rad=w_load, terms=jf.terms,
                   stop_cost_nm=opt.good_fit_ratio * ref, jacobian=opt.jacobian, consensus_rtol=0.0)
    # on the samples both passes keep, the residual of each (dropped samples are zeros in both)
    n = problem.acceleration_f.shape[0]
    both = np.ones(n, dtype=bool)
    for m in (jf.mask, j2.mask):
        if m is not None:
            both &= m
    rms1, rms2 = (float(np.sqrt(np.mean(f.residual[:n][both] ** 2))) if both.any() else math.inf
                  for f in (jf, j2))
    take = ((j2.dropped_fraction < _FEWER_DROPPED * jf.dropped_fraction and j2.cost <= 1.5 * jf.cost)
            or (rms2 < _CLEARLY_BETTER * rms1
                and j2.dropped_fraction <= 1.5 * jf.dropped_fraction + 0.005))
    info = {"evaluations": s.evaluations + j2.evaluations, "epsilon_deg": math.degrees(j2.epsilon_rad),
            "common_rms_nm": [rms1, rms2],
            "dropped_fraction": j2.dropped_fraction, "cost_nm": j2.cost, "taken": bool(take),
            "first_epsilon_deg": math.degrees(jf.epsilon_rad), "first_dropped_fraction": jf.dropped_fraction,
            "searched_to_deg": searched_to}
    if take:
        notes.append(f"second pass (ε searched again from the first fit's parameters) taken: it "
                     f"explains {100 * (1 - j2.dropped_fraction):.1f} % of the record instead of "
                     f"{100 * (1 - jf.dropped_fraction):.1f} % (first pass ε̂ = "
                     f"{math.degrees(jf.epsilon_rad):.3f}°)")
        return j2, info, eps_max
    return jf, info, eps_max


def _refit_at(problem: Any, jf: Any, terms: Any, opt: IdentificationOptions, eps_max: float,
              w_load: float, *, trim_rounds: int = 0, initial_mask: Any = None,
              load_friction_start_nm: float | None = None) -> Any:
    """Joint fit started at a previous solution ``jf`` (with ``terms``); F_cl starts at
    ``load_friction_start_nm`` when given, else at the solution's."""
    from .jointfit import SearchCell, joint_fit

    p = jf.parameters
    phi = p.B_l / max(p.B_m + p.B_l, 1e-300)
    fcl = jf.coulomb_load_nm if load_friction_start_nm is None else load_friction_start_nm
    # a cell at the solution: cell_rates(start = solution, φ of the solution) gives back its
    # rates; joint_fit starts F_cl/J_l at half the cell's motor Coulomb value (its search
    # convention), hence 2·F_cl
    cell = SearchCell(jf.epsilon_rad, phi, 1.0, jf.cost, coulomb_motor_nm=2.0 * fcl, lag_s=jf.lag_s)
    return joint_fit(problem, p, [cell], epsilon_max_rad=eps_max, max_nfev=opt.max_fit_evaluations,
                     threads=opt.threads, load_weight_nm_per_rad=w_load, terms=terms,
                     initial_mask=initial_mask, trim_rounds=trim_rounds, jacobian=opt.jacobian)


def _select_terms(problem: Any, jf: Any, candidates: Any, opt: IdentificationOptions,
                  eps_max: float, w_load: float, notes: list[str]) -> tuple[Any, dict[str, Any]]:
    """Keep the candidate terms the data support (BIC), refit without the others.

    BIC = n·ln(SSR) + k·ln(n) with n the kept residual samples (decimated to ≈ independent).
    Removing one term from the fitted full model raises SSR by ≈ (θ/σ_θ)²·s² (its Wald
    statistic z², σ_θ from the Jacobian, s² = SSR/(n − k)), so the term lowers the BIC when
    z² > ln(n). A Coulomb level must also be positive (the motor one is projected unbounded).
    """
    from .jointfit import ModelTerms

    n = max(int(jf.n_used), 2)
    thr = math.log(n)
    values = {"coulomb_motor": jf.coulomb_motor_nm, "coulomb_load": jf.coulomb_load_nm,
              "current_loop": jf.lag_s}
    sds = {"coulomb_motor": jf.term_stderr.get("coulomb_motor_nm", math.inf),
           "coulomb_load": jf.term_stderr.get("coulomb_load_nm", math.inf),
           "current_loop": jf.term_stderr.get("lag_s", math.inf)}
    table: dict[str, Any] = {"criterion": opt.term_selection, "n": n, "threshold_ln_n": thr, "terms": {}}
    kept: dict[str, bool] = {}
    for name in candidates.names():
        v, sd = values[name], sds[name]
        z2 = (v / sd) ** 2 if sd > 0 and math.isfinite(sd) else (math.inf if v != 0 else 0.0)
        keep = opt.term_selection == "keep_all" or (v > 1.96 * sd and z2 > thr)
        kept[name] = keep
        table["terms"][name] = {"value": float(v), "stderr": float(sd), "wald_z2": float(z2), "kept": bool(keep)}
    chosen = ModelTerms(**kept)
    if chosen == candidates:
        return jf, table
    ref = _refit_at(problem, jf, chosen, opt, eps_max, w_load, initial_mask=jf.mask)
    table["refit_evaluations"] = int(ref.evaluations)
    dropped = [k for k in candidates.names() if not kept[k]]
    if dropped:
        table["dropped"] = dropped
    return ref, table


def _friction_section(jf: Any, opt: IdentificationOptions) -> dict[str, Any] | None:
    t = jf.terms
    if not (t.coulomb_motor or t.coulomb_load):
        return None
    out: dict[str, Any] = {"model": "F·tanh(v/v_s)", "velocity_scale_rad_s": opt.coulomb_velocity_scale_rad_s}
    for side, on, key in (("motor", t.coulomb_motor, "coulomb_motor_nm"), ("load", t.coulomb_load, "coulomb_load_nm")):
        if on:
            v = float(getattr(jf, key))
            sd = float(jf.term_stderr.get(key, math.inf))
            out[f"{side}_nm"] = v
            out[f"{side}_interval_nm"] = [max(0.0, v - 1.96 * sd), v + 1.96 * sd]
    return out


def _current_loop_section(jf: Any) -> dict[str, Any] | None:
    if not jf.terms.current_loop or jf.lag_s <= 0.0:
        return None
    tc = float(jf.lag_s)
    sd = float(jf.term_stderr.get("lag_s", math.inf))
    lo_t, hi_t = max(tc - 1.96 * sd, 0.0), tc + 1.96 * sd
    bw = 1.0 / (2.0 * math.pi * tc)
    return {"model": "first-order lag T_c·dτ/dt = τ_ref − τ", "bandwidth_hz": bw,
            "bandwidth_interval_hz": [1.0 / (2.0 * math.pi * hi_t) if math.isfinite(hi_t) else 0.0,
                                      1.0 / (2.0 * math.pi * lo_t) if lo_t > 0 else math.inf],
            "time_constant_s": tc}


def _identify_paper(rec: Recording, opt: IdentificationOptions, st: _Stages) -> Identification:
    from .jointfit import linear_start
    from .paper import paper_identify

    notes: list[str] = []
    fs = rec.sample_rate_hz
    frd, fit = _frd_and_fit(rec, opt, st)
    st.start("paper", 0.3)
    bounds = (math.radians(opt.epsilon_bounds_deg[0]), math.radians(opt.epsilon_bounds_deg[1]))
    kw = dict(search="bayes", bounds_rad=bounds, resolution_rad=math.radians(opt.epsilon_resolution_deg),
              max_iterations=opt.max_iterations, seed=opt.seed)
    try:
        res = paper_identify(rec.torque_ref, rec.motor_velocity, fs, fit, **kw)
    except IdentificationError as err:
        start, _ = linear_start(fit.num, fit.den)
        notes.append(f"paper: the fit maps to no physical plant ({err}); started from the "
                     "modes with an even damping split instead")
        res = paper_identify(rec.torque_ref, rec.motor_velocity, fs, start, **kw)
    st.done("paper", stop_reason=res.stop_reason, timings_s=dict(res.timings_s),
            passes=len(res.iterations))
    chosen = min(res.iterations, key=lambda r: r.frd_error)
    params = res.params
    num, den = params.velocity_tf()
    if not res.backlash_detected:
        notes.append("paper: L(0) is as good as the best ε of the grid: no backlash detected")
    notes.append(f"paper: stopped by '{res.stop_reason}'")
    iterations = [{"frd_error": float(it.frd_error), "epsilon_deg": math.degrees(it.epsilon_rad)}
                  for it in res.iterations]
    interval = tuple(chosen.search.interval_rad) if res.backlash_detected else (0.0, bounds[0])
    return Identification(
        method=Method.PAPER, parameters=params, epsilon_rad=res.epsilon_rad,
        epsilon_interval_rad=(float(interval[0]), float(interval[1])),
        evaluations=int(sum(it.search.evaluations for it in res.iterations)),
        modes=modes(params), num=num, den=den, delay_s=float(res.delay_s), iterations=iterations,
        stages=st.items, source_samples=len(rec), sample_rate_hz=fs,
        backlash_detected=bool(res.backlash_detected), notes=notes,
    )


def options_from_mapping(data: dict[str, Any]) -> IdentificationOptions:
    """Validated options from a plain mapping (config files); errors as IdentificationError."""
    try:
        return IdentificationOptions.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        loc = ".".join(str(p) for p in first.get("loc", ()))
        raise IdentificationError(f"invalid identification option {loc}: {first.get('msg')}") from err
