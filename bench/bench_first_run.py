"""What a first run pays for numba's compilation, and what `commission --warm-cache` moves out of it.

Run as ``python bench/bench_first_run.py`` (``REPEATS=N`` for more than 3). Each figure is the
median wall time of a `commission` process over REPEATS trials, each with a fresh, empty numba
cache (``$NUMBA_CACHE_DIR``):

- ``--sim`` cold: the first run after an install (it compiles every kernel it calls);
- ``--warm-cache`` cold: the warm-up alone (what `make run`'s install step and the image add);
- ``--sim`` after the warm-up: what `make run` then costs;
- ``--sim`` warm: a later run (the cache already full).

The difference of the first and the last is the compilation a fresh machine pays once. Each row also
gives the process's peak memory (numba's compilation of a large inlined function takes gigabytes).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPEATS = int(os.environ.get("REPEATS", "3"))
COMMISSION = [sys.executable, "-m", "commission.cli"]


def timed(argv: list[str], cache: Path, cwd: Path) -> tuple[float, float]:
    """(wall time [s], peak resident memory [MB]) of one `commission` process."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    start = time.perf_counter()
    proc = subprocess.Popen([*COMMISSION, *argv], cwd=cwd, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise subprocess.CalledProcessError(proc.returncode, proc.args)
    return time.perf_counter() - start, usage.ru_maxrss / 1024.0  # (ru_maxrss: KiB on Linux)


def main() -> None:
    rows: dict[str, list[tuple[float, float]]] = {"--sim, cold cache": [], "--warm-cache, cold cache": [],
                                                  "--sim after --warm-cache": [], "--sim, warm cache": []}
    for _ in range(REPEATS):
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            rows["--sim, cold cache"].append(timed(["--sim", "--out", "a"], work / "cold", work))
            rows["--warm-cache, cold cache"].append(timed(["--warm-cache"], work / "warm", work))
            rows["--sim after --warm-cache"].append(timed(["--sim", "--out", "b"], work / "warm", work))
            rows["--sim, warm cache"].append(timed(["--sim", "--out", "c"], work / "warm", work))
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"commission wall time and peak memory, median of {REPEATS} (fresh numba cache per trial; {cpus} CPUs)")
    medians = {}
    for name, trials in rows.items():
        seconds = [t for t, _ in trials]
        medians[name] = statistics.median(seconds)
        print(f"  {name:<28} {medians[name]:6.1f} s   (min {min(seconds):.1f}, max {max(seconds):.1f})   "
              f"{statistics.median(m for _, m in trials):6.0f} MB peak")
    compile_s = medians["--sim, cold cache"] - medians["--sim, warm cache"]
    print(f"  {'compilation paid once':<28} {compile_s:6.1f} s")


if __name__ == "__main__":
    main()
