"""Replay inputs are read with bounded memory (issue 21): time and peak memory of ``commission --replay``
on CSV files of a 10 s run and of one longer than any run (refused once 4.8 million rows are read).

Run as ``python bench/bench_replay_limits.py``; each figure is the median of a few runs of the command in
a fresh process (peak resident memory of that process, wall time), with ``--no-identify``.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RUNS = 3
STEP_S = 1.0 / 8000.0


def write_csv(path: Path, rows: int) -> None:
    with open(path, "w") as f:
        f.write("t,torque_ref,motor_velocity,motor_position\n")
        for start in range(0, rows, 100_000):
            f.write("".join(f"{i * STEP_S!r},0.123456789012,-1.23456789012,0.000123456789\n"
                            for i in range(start, min(rows, start + 100_000))))


def measure(path: Path, out: Path) -> tuple[float, float, int]:
    """(seconds, peak MiB, exit code) of one replay in a new process."""
    script = ("import resource, sys; from commission.cli import main; code = main(sys.argv[1:]); "
              "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr); sys.exit(code)")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", script, "--replay", str(path), "--no-identify", "--out", str(out)],
                          capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    peak_kib = int(proc.stderr.strip().splitlines()[-1])
    return seconds, peak_kib / 1024, proc.returncode


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="bench-replay-") as tmp:
        root = Path(tmp)
        for label, rows in (("10 s run, 80,000 rows", 80_000), ("over the limit, 6,000,000 rows", 6_000_000)):
            path = root / f"{rows}.csv"
            write_csv(path, rows)
            size_mb = path.stat().st_size / 1e6
            runs = [measure(path, root / "out") for _ in range(RUNS)]
            codes = {r[2] for r in runs}
            print(f"{label} ({size_mb:.0f} MB): exit {sorted(codes)}, "
                  f"median {statistics.median(r[0] for r in runs):.2f} s, "
                  f"peak memory median {statistics.median(r[1] for r in runs):.0f} MiB (whole process)")
            path.unlink()


if __name__ == "__main__":
    main()
