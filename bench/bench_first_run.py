"""What a first run pays for numba's compilation, and what `commission --warm-cache` moves out of it.

Run as ``python bench/bench_first_run.py`` (``REPEATS=N`` for more than 3). Each figure is the
median wall time of a `commission` process over REPEATS trials, each with a fresh, empty numba
cache (``$NUMBA_CACHE_DIR``):

- ``--sim`` cold: the first run after an install (it compiles every kernel it calls);
- ``--warm-cache`` cold: the warm-up alone (what `make run`'s install step and the image add);
- ``--sim`` after the warm-up: what `make run` then costs;
- ``--sim`` warm: a later run (the cache already full).

The difference of the first and the last is the compilation a fresh machine pays once.
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


def timed(argv: list[str], cache: Path, cwd: Path) -> float:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    start = time.perf_counter()
    subprocess.run([*COMMISSION, *argv], cwd=cwd, env=env, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> None:
    rows: dict[str, list[float]] = {"--sim, cold cache": [], "--warm-cache, cold cache": [],
                                     "--sim after --warm-cache": [], "--sim, warm cache": []}
    for _ in range(REPEATS):
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            rows["--sim, cold cache"].append(timed(["--sim", "--out", "a"], work / "cold", work))
            rows["--warm-cache, cold cache"].append(timed(["--warm-cache"], work / "warm", work))
            rows["--sim after --warm-cache"].append(timed(["--sim", "--out", "b"], work / "warm", work))
            rows["--sim, warm cache"].append(timed(["--sim", "--out", "c"], work / "warm", work))
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"commission wall time, median of {REPEATS} (fresh numba cache per trial; {cpus} CPUs)")
    for name, values in rows.items():
        print(f"  {name:<28} {statistics.median(values):6.1f} s   (min {min(values):.1f}, max {max(values):.1f})")
    compile_s = statistics.median(rows["--sim, cold cache"]) - statistics.median(rows["--sim, warm cache"])
    print(f"  {'compilation paid once':<28} {compile_s:6.1f} s")


if __name__ == "__main__":
    main()
