"""Controller settings over the identifier bench's spread of plants (issue #6).

For each plant (bench/bench_identify.py's cases: J_l/J_m 0.2–5, resonance 20–300 Hz,
ε 0–0.9°, with Coulomb friction and current-loop lag as unmodelled extras) the chirp is
simulated, identified (hybrid), the controller designed on the identification and verified
on the TRUE plant (sim_drive parameters, backlash included). Printed: the velocity-loop gain
K_v, the −3 dB bandwidth on the identified model and the crossover on the true plant, the
margins on the true plant (contact and gap = motor alone; posGM: the position loop's gain
margin around the closed velocity loop), the velocity step's overshoot, and —
with/without backlash compensation (with it: the offset 2ε and the position-reference filter that
makes moves end with the load on the driving flank) — the position step's overshoot, settling
time and load error, the load error after a smooth move from the centred gap, the lost motion of out-back-out moves and the
largest load limit-cycle amplitude ("comp": the direction the design chose, "off" when the
compensation did not help on the identified model, so on = off).

    python bench/bench_tuning.py            # identify, design, verify
    python bench/bench_tuning.py --true     # design on the true parameters (no identification)
    python bench/bench_tuning.py --quick    # a subset
    python bench/bench_tuning.py --drive-lag 1000 --delay 1   # design for a 1 kHz current loop + 1 sample
    python bench/bench_tuning.py --drive yaskawa-sigma7       # the drive description's loop
    python bench/bench_tuning.py --timing [RUNS]              # only the design's time (medians)

The design is told the plant's current-loop bandwidth when it has one (a drive datum, entered
in the config as tuning.current_loop_bandwidth_hz); otherwise it assumes an unknown drive's
(2 kHz, one sample of computation delay) and holds the margins over the uncertainty set
around it. "light 300Hz r5" is designed for a drive with a 1 kHz current loop and one sample
of computation delay, where its resonance lies above the loop. The verification adds a 1 kHz
current loop and 2 samples of delay to a plant whose drive is ideal.

Timing (printed first, medians over RUNS repeats on the reference plant's identification, one
process, warm): the whole design (search over the uncertainty set's members, the exact worst
case, the backlash direction's three closed-loop runs), the design without the uncertainty set,
the worst-case evaluation alone (60 members on the frequency grid, the lowest located exactly),
and the verification.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

from commission.config import ExcitationConfig
from commission.exceptions import CommissionError
from commission.excitation import chirp
from commission.ident.hybrid import identify
from commission.recording import Recording
from commission.tuning import TuningOptions, UncertaintySet, design, robust_margins, verify
from commission.tuning.loop import _plant_z_cached
from sim_drive.plant import Plant, PlantParameters

FS = 8000.0

# One definition of the plant spread: the identifier bench's (this script runs from bench/,
# which is then on sys.path).
from bench_identify import FULL as _IDENT_FULL  # noqa: E402
from bench_identify import Case  # noqa: E402


def truth(case: Case) -> PlantParameters:
    """The simulator's plant of a case (backlash, Coulomb friction and lag included)."""
    return PlantParameters(**case.params().as_dict(), epsilon_deg=case.eps_deg,
                           coulomb_motor_nm=case.coulomb_nm, coulomb_load_nm=case.coulomb_nm,
                           current_loop_bandwidth_hz=case.lag_hz, encoder_bits_motor=case.encoder_bits)


FULL = [c for c in _IDENT_FULL if not c.name.startswith("ref zeta")] + [
    Case("light 300Hz r5", 5.0, 300, 0.05, 0.30),  # resonance above a slow drive's loop: notch
]
QUICK = {"reference", "reference eps=0", "stiff light 150Hz", "soft heavy 25Hz", "reference +lag1k"}


def _identify(case: Case):
    tau = chirp(ExcitationConfig()).samples
    pp = truth(case).model_copy(update={"torque_noise_nm": case.noise_nm, "seed": 11})
    r = Plant(pp, FS).run_torque(tau)
    return identify(Recording.uniform(FS, r.torque_ref, r.motor_velocity, motor_position=r.motor_position))


def _fmt(x: float | None, scale: float = 1.0, nd: int = 1) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x * scale:.{nd}f}"


def timing(runs: int, description: object | None) -> None:
    """Medians of the design's stages on the reference plant's identification (module docstring)."""
    ident = _identify(next(c for c in FULL if c.name == "reference"))
    band = (0.1, ExcitationConfig().f_end_hz)
    opt = TuningOptions()
    none = TuningOptions(uncertainty=UncertaintySet.none())

    def timed(fn) -> tuple[float, float]:  # type: ignore[no-untyped-def]
        """(median wall time, median CPU time of this process) [s]: the machine is shared."""
        wall, cpu = [], []
        for _ in range(runs):
            _plant_z_cached.cache_clear()  # a fresh process discretises every plant once
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        return statistics.median(wall), statistics.median(cpu)

    s = design(ident, opt, description=description, excitation_band_hz=band)  # warm-up (numba cache, imports)
    rows = [
        ("design (with the uncertainty set)", timed(lambda: design(ident, opt, description=description,
                                                                   excitation_band_hz=band))),
        ("design (nominal model only)", timed(lambda: design(ident, none, description=description,
                                                             excitation_band_hz=band))),
        ("worst case over the set alone", timed(lambda: robust_margins(s, ident.parameters, opt, backlash=True))),
        ("verification (true plant + 1 kHz, 2 samples)", timed(lambda: verify(s, truth(FULL[0]), opt))),
    ]
    print(f"design time, reference plant, median of {runs} (members: {s.robust.members if s.robust else 0}); "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    for name, (wall, cpu) in rows:
        print(f"  {name:46s} {1e3 * wall:7.1f} ms wall {1e3 * cpu:7.1f} ms CPU")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--timing", nargs="?", type=int, const=9, default=None, metavar="RUNS",
                    help="only the design's time: medians over RUNS (default 9)")
    ap.add_argument("--drive", default=None, help="design with this drive description's loop")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--true", action="store_true", help="design on the true parameters")
    ap.add_argument("--drive-lag", type=float, default=None, help="drive current-loop bandwidth [Hz] for the design")
    ap.add_argument("--delay", type=float, default=None, help="computation delay [samples] for the design "
                    "(default: the description's, else assumed)")
    ap.add_argument("--preset", default="standard")
    args = ap.parse_args()
    description = None
    if args.drive:
        from commission.drive.description import load_description

        description = load_description(args.drive)
    timing(args.timing or 5, description)
    if args.timing is not None:
        return
    cases = [c for c in FULL if not args.quick or c.name in QUICK]
    print(f"design on: {'true parameters' if args.true else 'hybrid identification'}; preset {args.preset}; "
          f"verification on the true plant (backlash, friction, lag included; an ideal drive given 1 kHz + 2 samples); "
          f"wPM/wGM: worst case over the uncertainty set; limit: what limited the bandwidth")
    head = (f"{'plant':20s} {'ε°':>4s} {'notch':>5s} {'Kv Hz':>6s} {'bw Hz':>5s} {'wc Hz':>5s} {'PM°':>5s} {'GM dB':>5s} "
            f"{'gapPM':>5s} {'gapGM':>5s} {'posGM':>5s} {'vstep ov%':>9s} {'step ov% on/off':>15s} {'step ts ms on/off':>17s} "
            f"{'step err µrad on/off':>20s} {'move err µrad on/off':>20s} {'lost motion µrad on/off':>23s} {'cycle µrad on/off':>17s} "
            f"{'comp':>4s} {'wPM°':>5s} {'wGM':>5s} {'limit':>12s} {'ready':>5s} {'s':>4s}")
    print(head)
    for c in cases:
        t0 = time.perf_counter()
        try:
            opt_kw = {"preset": args.preset}
            # the drive's current loop is a drive datum the technician enters (the identifier has no term for it)
            extra = {"current_loop_bandwidth_hz": args.drive_lag if args.drive_lag is not None else c.lag_hz,
                     "computation_delay_samples": args.delay}
            extra = {k: v for k, v in extra.items() if v is not None}
            if c.name == "light 300Hz r5" and args.drive_lag is None:
                extra = {"current_loop_bandwidth_hz": 1000.0, "computation_delay_samples": 1}
            opt = TuningOptions(**opt_kw, **extra)
            band = (0.1, ExcitationConfig().f_end_hz)
            if args.true:
                s = design(c.params(), opt, epsilon_rad=math.radians(c.eps_deg), description=description,
                           excitation_band_hz=band)
            else:
                s = design(_identify(c), opt, description=description, excitation_band_hz=band)
            v = verify(s, truth(c), opt)
        except CommissionError as err:
            print(f"{c.name:20s} failed: {err}")
            continue
        on = v.runs["proposed"]
        off = v.runs.get("without_backlash_compensation", on)
        gap = v.margins_gap
        notch = f"{s.notches[0].frequency_hz:.0f}" if s.notches else "-"

        def pair(key: str, attr: str, scale: float, nd: int = 0) -> str:
            return f"{_fmt(getattr(on[key], attr), scale, nd)}/{_fmt(getattr(off[key], attr), scale, nd)}"

        cyc_on = max(on[k].limit_cycle_amplitude for k in ("position_step", "position_move", "reversal"))
        cyc_off = max(off[k].limit_cycle_amplitude for k in ("position_step", "position_move", "reversal"))
        comp = s.backlash.direction[:3] if s.backlash.enabled else "off"
        print(f"{c.name:20s} {c.eps_deg:4.2f} {notch:>5s} {s.velocity_loop_gain_hz:6.1f} {s.velocity_bandwidth_hz:5.0f} "
              f"{v.margins.crossover_hz:5.0f} {v.margins.phase_margin_deg:5.1f} {v.margins.gain_margin_db:5.1f} "
              f"{_fmt(gap.phase_margin_deg if gap else None):>5s} {_fmt(gap.gain_margin_db if gap else None):>5s} "
              f"{_fmt(v.position_margins.gain_margin_db):>5s} "
              f"{on['velocity_step'].overshoot_pct:9.1f} {pair('position_step', 'overshoot_pct', 1, 1):>15s} "
              f"{pair('position_step', 'settling_time_s', 1e3, 1):>17s} "
              f"{pair('position_step', 'load_error_rad', 1e6):>20s} {pair('position_move', 'load_error_rad', 1e6):>20s} {pair('reversal', 'lost_motion_rad', 1e6):>23s} "
              f"{_fmt(cyc_on, 1e6, 0) + '/' + _fmt(cyc_off, 1e6, 0):>17s} "
              f"{comp:>4s} {_fmt(s.robust.phase_margin_deg if s.robust else None):>5s} "
              f"{_fmt(s.robust.gain_margin_db if s.robust else None):>5s} "
              f"{s.limit.factor.value if s.limit else '-':>12s} {str(v.ready and s.meets_margins):>5s} "
              f"{time.perf_counter() - t0:4.1f}")
        if not (v.ready and s.meets_margins):
            print(f"{'':20s} not ready: {'; '.join([*v.reasons, *(s.robust.reasons() if s.robust else [])])}")


if __name__ == "__main__":
    main()
