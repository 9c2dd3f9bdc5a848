"""Run benchmark scripts and append what they print to ``bench/results/RESULTS.md``, dated.

    python bench/record.py bench/bench_*.py        # what `make bench` runs
    python bench/record.py bench/bench_first_run.py
    python bench/record.py bench/bench_streamed.py --slcan-runs 20   # options go to the script before them

Each script's output is shown as it runs and then kept, under a heading with the date, the
commit, the machine (CPUs, Python, numba), so that figures quoted anywhere can be traced to a
run. Nothing is asserted; a script that fails ends the run with its exit code after its
output has been recorded.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "RESULTS.md"


def _commit() -> str:
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT, capture_output=True, text=True,
                             check=True)
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return out.stdout.strip()


def _versions() -> str:
    found = []
    for name in ("numpy", "scipy", "numba"):
        try:
            found.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            pass
    return ", ".join(found)


def heading() -> str:
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return (f"## {now} · commit {_commit()}\n\n{platform.node()}: {cpus} CPUs, "
            f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, {_versions()}\n")


def run(script: Path, options: list[str]) -> tuple[int, str, float]:
    """Run one script with this interpreter, echoing its output; returns (exit code, output, seconds)."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, str(script), *options], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines = []
    assert proc.stdout is not None
    for line in proc.stdout:
        sys.stdout.write(line)
        lines.append(line)
    return proc.wait(), "".join(lines), time.perf_counter() - start


def main(argv: list[str]) -> int:
    scripts: list[tuple[Path, list[str]]] = []
    for a in argv:
        if a.startswith("-") and scripts:
            scripts[-1][1].append(a)
        elif scripts and scripts[-1][1] and not a.endswith(".py"):
            scripts[-1][1].append(a)  # an option's value
        else:
            scripts.append((Path(a), []))
    scripts = scripts or [(p, []) for p in sorted((ROOT / "bench").glob("bench_*.py"))]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    if not RESULTS.exists():
        RESULTS.write_text("# Benchmark results\n\nAppended by `make bench` (bench/record.py), newest last.\n",
                           encoding="utf-8")
    sections = [heading()]
    code = 0
    for script, options in scripts:
        print(f"== {script} {' '.join(options)}".rstrip(), flush=True)
        code, output, seconds = run(script, options)
        rel = script.resolve().relative_to(ROOT) if script.resolve().is_relative_to(ROOT) else script
        rel = f"{rel} {' '.join(options)}".rstrip()
        status = "" if code == 0 else f", exit code {code}"
        sections.append(f"### {rel} ({seconds:.0f} s{status})\n\n```\n{output.rstrip()}\n```\n")
        if code != 0:
            break
    with RESULTS.open("a", encoding="utf-8") as f:
        f.write("\n" + "\n".join(sections))
    print(f"recorded in {RESULTS.relative_to(ROOT)}")
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
