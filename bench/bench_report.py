"""Time to build report.html (commission.report) for a 10 s, 8 kHz simulated run with tuning.

Run as ``python bench/bench_report.py``; prints medians over a few runs: the whole
``write_report`` (verdict, settings, verification and identification sections), the
recomputation (FRDs, dead-zone simulations, ε profile) and each figure's SVG time and size,
the page size, and the time /samples (Foxglove) and ``append_result`` add to the MCAP log.
"""

from __future__ import annotations

import contextlib
import io
import statistics
import tempfile
import time
from pathlib import Path

from commission import report as rp
from commission.cli import main
from commission.ident.hybrid import identify
from commission.mcaplog import append_result, read_config, read_recording, write_recording
from commission.sequencer import simulated_plant, tune_and_export
from commission.tuning import TuningOptions

REPEATS = 5


def median_time(fn, repeats: int = REPEATS) -> str:  # type: ignore[no-untyped-def]
    """Median wall and CPU time of ``fn()``, as text (the CPU time is what counts on a busy
    machine: the wall time grows with whatever else runs on its 2 cores)."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return f"{statistics.median(wall):6.3f} s wall {statistics.median(cpu):6.3f} s CPU"


def main_bench() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["--sim", "--out", str(out), "--json", "--no-identify"]) == 0
        log = out / "run.mcap"
        rec, cfg = read_recording(log), read_config(log)
        ident = identify(rec)
        tp = simulated_plant(rec, cfg)
        tuning = tune_and_export(out, ident, TuningOptions(), None, tp)

        def whole() -> None:
            rp.write_report(out, rec, ident, config=cfg, source_file=log, tuning=tuning, true_plant=tp)

        total = median_time(whole)
        size = (out / rp.REPORT_NAME).stat().st_size
        print(f"write_report (whole page)          {total}   {size / 1e6:.2f} MB")
        curves = rp._curves(rec, ident, cfg, tp)
        print(f"  recompute (FRDs, sims, ε profile) {median_time(lambda: rp._curves(rec, ident, cfg, tp))}")
        window = rp._zoom_window(rec, curves, ident.epsilon_rad)
        history = rp.search_history(ident)
        v = tuning.verification
        figures = {
            "openloop": lambda: rp._fig_open_loop(tuning.settings, ident.parameters),
            "step": lambda: rp._fig_steps(v),
            "move": lambda: rp._fig_move(v, "position_move", "fig-move", "move"),
            "reversal": lambda: rp._fig_move(v, "reversal", "fig-reversal", "reversal"),
            "bode": lambda: rp._fig_bode(ident, curves),
            "time": lambda: rp._fig_time(rec, ident, curves),
            "zoom": lambda: rp._fig_zoom(rec, ident, curves, window),
            "search": lambda: rp._fig_search(ident, curves, history),
            "iterations": lambda: rp._fig_iterations(ident),
        }
        for name, fn in figures.items():
            svg = fn() or ""
            print(f"  figure {name:<27} {median_time(fn)}   {len(svg) / 1e3:6.0f} kB SVG")

        plain = median_time(lambda: write_recording(out / "plain.mcap", rec, config=cfg), 3)
        plotted = median_time(lambda: write_recording(out / "plot.mcap", rec, config=cfg, plot_every=8), 3)
        s0, s1 = (out / "plain.mcap").stat().st_size, (out / "plot.mcap").stat().st_size
        print(f"write_recording                    {plain}   {s0 / 1e6:.2f} MB")
        print(f"write_recording(plot_every=8)      {plotted}   {s1 / 1e6:.2f} MB (+/samples at 1 kHz)")
        payload = ident.to_dict(str(log))
        print(f"append_result(/identification)     "
              f"{median_time(lambda: append_result(out / 'plot.mcap', '/identification', payload), 3)}")


if __name__ == "__main__":
    main_bench()
