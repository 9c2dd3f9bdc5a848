"""The drive's own loop as the design models it: current loop, loop clocks, delays, gain ranges.

A record shows the current loop only when it is sampled fast enough (the 8 kHz trace shows a
1 kHz loop; a 1–2 kHz streamed record cannot), and a delay only in whole samples of its own rate,
the computation and encoder delays together. Each figure is therefore taken from the first of:

1. the config (``tuning.current_loop_bandwidth_hz``, ``computation_delay_samples``,
   ``encoder_delay_samples``, a ``sample_rate_hz`` that was set): the technician's entry;
2. the identification (the current-loop lag and the whole-sample delay the identifier kept; the record
   shows the computation and encoder delays only as their sum, so the encoder's is taken off it);
3. the drive description's ``loop:`` block, with its stated source;
4. a stated conservative assumption (``assumed_*``).

``tuning.ideal_drive`` replaces all of it by an ideal current loop and no delay (only to
compare). The gain ranges are the description's parameter map (``parameters:``) in SI units.
"""

from __future__ import annotations

import math
from typing import Any

from .identified import IdentifiedModel
from .settings import DriveDynamics, Source, Sourced, TuningOptions

__all__ = ["resolve_dynamics"]

#: Units the parameter map may give a gain range in, to SI.
_TO_SI = {"Hz": 1.0, "1/s": 1.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "N·m·s/rad": 1.0}
#: description parameter -> (gain range key, SI kind)
_RANGES = {"speed_loop_gain": "velocity_gain_hz", "velocity_kp": "velocity_gain",
           "speed_loop_integral_time": "velocity_integral_time_s", "position_loop_gain": "position_gain_per_s"}


def _from_description(spec: Any, scale: float = 1.0) -> Sourced | None:
    if spec is None:
        return None
    return Sourced(float(spec.value) * scale, Source.DESCRIPTION, spec.source, bool(spec.confirm))


def resolve_dynamics(model: IdentifiedModel, options: TuningOptions, description: Any | None) -> DriveDynamics:
    """The drive's loop for the design, each figure with its source (module docstring)."""
    loop = getattr(description, "loop", None)
    name = getattr(description, "name", None)
    where = f"drivers/{name}/description.yaml" if name else "the drive description"

    def described(attr: str, scale: float = 1.0) -> Sourced | None:
        sv = _from_description(getattr(loop, attr, None) if loop is not None else None, scale)
        if sv is None:
            return None
        return Sourced(sv.value, sv.how, f"{where}: {sv.source}", sv.confirm)

    # the velocity loop's clock
    if "sample_rate_hz" in options.model_fields_set:
        fs = Sourced(options.sample_rate_hz, Source.CONFIG, "tuning.sample_rate_hz")
    else:
        period = described("velocity_loop_period_s")
        if period is not None and period.value:
            fs = Sourced(1.0 / period.value, period.how, period.source, period.confirm)
        else:
            fs = Sourced(options.sample_rate_hz, Source.ASSUMED, "tuning.sample_rate_hz's default")
    Ts = 1.0 / float(fs.value or options.sample_rate_hz)
    pos = described("position_loop_period_s") or Sourced(Ts, Source.ASSUMED, "the velocity loop's")

    if options.ideal_drive:
        why = "tuning.ideal_drive: true (a comparison; no real drive is like that)"
        return DriveDynamics(fs, pos, Sourced(None, Source.IDEAL, why), Sourced(0.0, Source.IDEAL, why),
                             Sourced(0.0, Source.IDEAL, why), *_gain_limits(description, where))

    # the current loop
    record = (f"the record ({model.sample_rate_hz:g} Hz)" if model.sample_rate_hz else "the record")
    if options.current_loop_bandwidth_hz is not None:
        cl = Sourced(options.current_loop_bandwidth_hz, Source.CONFIG, "tuning.current_loop_bandwidth_hz")
    elif model.current_loop_hz is not None:
        cl = Sourced(model.current_loop_hz, Source.IDENTIFIED, f"identified from {record}")
    else:
        cl = described("current_loop_bandwidth_hz") or Sourced(
            options.assumed_current_loop_bandwidth_hz, Source.ASSUMED,
            f"tuning.assumed_current_loop_bandwidth_hz: nothing known ({record} shows no current-loop lag, the "
            "drive description gives none)", True)
    if cl.how is Source.DESCRIPTION and model.sample_rate_hz and model.sample_rate_hz < 2.0 * float(cl.value or 0):
        cl = Sourced(cl.value, cl.how, cl.source + f" (above {record}'s Nyquist frequency: it cannot show it)",
                     cl.confirm)

    # the delays, in velocity-loop samples
    def delay(option: float | None, key: str, attr: str, assumed: float) -> Sourced:
        if option is not None:
            return Sourced(float(option), Source.CONFIG, f"tuning.{key}")
        d = described(attr, 1.0 / Ts)
        if d is not None:
            return d
        return Sourced(assumed, Source.ASSUMED, f"tuning.assumed_{key}: nothing known about this drive", True)

    enc = delay(options.encoder_delay_samples, "encoder_delay_samples", "encoder_delay_s",
                options.assumed_encoder_delay_samples)
    if options.computation_delay_samples is None and model.delay_s is not None:
        comp = _identified_computation_delay(model.delay_s / Ts, Ts, enc, record)
    else:
        comp = delay(options.computation_delay_samples, "computation_delay_samples", "computation_delay_s",
                     options.assumed_computation_delay_samples)
    return DriveDynamics(fs, pos, cl, comp, enc, *_gain_limits(description, where))


def _identified_computation_delay(total: float, Ts: float, enc: Sourced, record: str) -> Sourced:
    """The computation delay a record shows [velocity-loop samples]: the record sees the torque's delay and
    the encoder's together (``total``, beyond the hold's sample), so the encoder's is taken off once."""
    enc_samples = float(enc.value or 0.0)
    less = f", less the encoder delay ({enc_samples:g}, {enc.how.value})" if enc_samples else ""
    return Sourced(max(total - enc_samples, 0.0), Source.IDENTIFIED,
                   f"identified from {record}: {total * Ts * 1e6:.0f} µs ({total:g} velocity-loop samples) from the "
                   f"torque reference to the encoders' response{less}")


def _gain_limits(description: Any | None, where: str) -> tuple[dict[str, tuple[float, float]], str]:
    """SI ranges of the gains from the description's parameter map (min/max × scale, unit → SI)."""
    params = getattr(description, "parameters", None) or {}
    out: dict[str, tuple[float, float]] = {}
    used = []
    for pname, key in _RANGES.items():
        spec = params.get(pname)
        if spec is None or spec.unit.strip() not in _TO_SI or (spec.min is None and spec.max is None):
            continue
        k = _TO_SI[spec.unit.strip()] * spec.scale
        lo = -math.inf if spec.min is None else spec.min * k
        hi = math.inf if spec.max is None else spec.max * k
        out[key] = (max(lo, 0.0), hi)
        used.append(pname)
    return out, (f"{where}: parameters {', '.join(used)} (min/max)" if used else "")
