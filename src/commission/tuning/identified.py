"""What the tuning reads from an identification: one place, so that the identifier's result
can change shape without the design noticing.

The design needs the two-mass parameters, the backlash ε and whether it was detected, the
current-loop lag the identifier kept (if any), the record's sample rate, how well the model
fits (approximate, residual ratio, noise-limited), the Coulomb friction it kept and the band
the record measured with good signal. :func:`read_identification` takes them from a
:class:`~commission.ident.hybrid.Identification` (``.fit``, ``.measured_band_hz`` when it has
them, else a stated fallback), or from bare
:class:`~commission.ident.twomass.TwoMassParameters` with ``epsilon_rad``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ..ident.twomass import TwoMassParameters
from .settings import TuningError

__all__ = ["FitFacts", "IdentifiedModel", "read_identification"]

#: Fraction of the record's Nyquist frequency taken as its measured band when nothing says more.
NYQUIST_FRACTION = 0.8


@dataclass(frozen=True)
class FitFacts:
    """How well the identified model reproduces the record (unknown: not approximate, ratio None)."""

    approximate: bool = False
    residual_ratio: float | None = None
    """RMS residual / RMS torque [-]."""
    noise_limited: bool = False
    """The residual over the good-fit level is white, stationary torque noise."""


@dataclass(frozen=True)
class IdentifiedModel:
    """The identification as the design reads it (SI units)."""

    parameters: TwoMassParameters
    epsilon_rad: float
    backlash_detected: bool
    current_loop_hz: float | None
    """The current-loop bandwidth the identifier kept [Hz] (None: none kept)."""
    delay_s: float | None
    """The whole-sample delay the identifier kept beyond the hold's sample, from the torque reference to the
    encoders' response (computation and encoder delay together) [s] (None: none kept)."""
    sample_rate_hz: float | None
    """The record's sample rate [Hz] (None: no record)."""
    fit: FitFacts
    measured_band_hz: tuple[float, float] | None
    """The band the record excited with good signal [Hz] (None: no record and no band given)."""
    band_source: str
    friction: dict[str, Any] | None
    source: Any
    """What was read (an Identification, or the parameters): the verification's plant on a real axis."""


def read_identification(model: Any, *, epsilon_rad: float | None = None,
                        excitation_band_hz: tuple[float, float] | None = None) -> IdentifiedModel:
    """The facts the design needs from ``model`` (an Identification, or TwoMassParameters with
    ``epsilon_rad``); ``excitation_band_hz``: the band the experiment's excitation swept, the
    measured band's fallback when the identification does not state one.

    :raises TuningError: ``model`` is neither.
    """
    if isinstance(model, TwoMassParameters):
        eps = float(epsilon_rad or 0.0)
        band, why = _band(None, None, excitation_band_hz)
        return IdentifiedModel(model, eps, eps > 0.0, None, None, None, FitFacts(), band, why, None, model)
    params = getattr(model, "parameters", None)
    if not isinstance(params, TwoMassParameters):
        raise TuningError(f"the design needs an Identification or TwoMassParameters, got {type(model).__name__}")
    eps = float(model.epsilon_rad if epsilon_rad is None else epsilon_rad)
    loop = getattr(model, "current_loop", None) or {}
    cl = loop.get("bandwidth_hz")
    fs = getattr(model, "sample_rate_hz", None)
    fs = float(fs) if isinstance(fs, (int, float)) and fs > 0 else None
    kept = int(loop.get("delay_samples") or 0)
    band, why = _band(getattr(model, "measured_band_hz", None), fs, excitation_band_hz)
    return IdentifiedModel(params, eps, bool(getattr(model, "backlash_detected", True)),
                           float(cl) if cl else None, kept / fs if kept > 0 and fs else None, fs, _fit(model), band, why,
                           getattr(model, "friction", None) or None, model)


def _band(stated: Any, fs: float | None, excitation: tuple[float, float] | None
          ) -> tuple[tuple[float, float] | None, str]:
    if stated is not None:
        lo, hi = (float(x) for x in stated)
        return (lo, hi), "the frequency response's quality (identification)"
    if excitation is not None:
        lo, hi = (float(x) for x in excitation)
        if fs is not None:
            hi = min(hi, NYQUIST_FRACTION * fs / 2.0)
        return (lo, hi), "the excitation's band (the identification states none)"
    if fs is not None:
        return (0.0, NYQUIST_FRACTION * fs / 2.0), (f"{NYQUIST_FRACTION:g} × the record's Nyquist frequency "
                                                     "(neither the identification nor the run states a band)")
    return None, "no record"


def _fit(model: Any) -> FitFacts:
    """``model.fit`` (a FitQuality) when the identification has one (unknown otherwise)."""
    fit = getattr(model, "fit", None)
    if fit is None or not hasattr(fit, "approximate"):
        return FitFacts()
    ratio = getattr(fit, "residual_ratio", None)
    ratio = None if ratio is None or not math.isfinite(float(ratio)) else float(ratio)
    return FitFacts(bool(fit.approximate), ratio, bool(getattr(fit, "noise_limited", False)))