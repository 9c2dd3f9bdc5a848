"""Time of a whole ``commission --sim`` run, warm, stage by stage.

Run as ``python bench/bench_run.py [RUNS] [-- extra commission options]``; prints, as medians
over RUNS runs (default 5) after one warm-up run, how long each stage of the run takes:

* imports — every module the run loads (the list is taken from the warm-up run and imported
  first, so that an import done lazily inside a stage is counted here, not in that stage);
* experiment — the simulated drive plays the chirp (enable, play, trace, stop);
* log (run.mcap) — the log is written, and rewritten with the identification in it;
* identification, tuning design, verification, report — the functions of those stages;
* other — the rest inside ``main()`` (result and controller files, summary, ...);
* total — the wall time of the whole process, from the parent's side: what a user waits.

Each run is a fresh process (``python -c``) so that imports cost what they cost a user; "warm"
means numba's on-disk cache and the OS file cache are filled by the warm-up run. The machine
is shared: the CPU time of the process is printed beside the wall time.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

RUNS = 5

#: The child: time the imports, wrap the stage functions, run commission's main().
CHILD = r"""
import json, sys, time
t_start = time.perf_counter()
modules = json.loads(sys.argv[1])
for name in modules:
    try:
        __import__(name)
    except Exception:
        pass
t_imports = time.perf_counter() - t_start
import commission.cli, commission.sequencer, commission.tuning, commission.ident.hybrid

stages = {}
stack = []  # [name, time spent in stages nested inside it]
def timed(name, fn):
    def wrapper(*args, **kwargs):
        stack.append([name, 0.0])
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            elapsed = time.perf_counter() - t0
            _, inner = stack.pop()
            stages[name] = stages.get(name, 0.0) + elapsed - inner
            if stack:
                stack[-1][1] += elapsed
    return wrapper

seq = commission.sequencer
seq.Sequencer._experiment = timed("experiment", seq.Sequencer._experiment)
seq.write_recording = timed("log (run.mcap)", seq.write_recording)
seq.append_result = timed("log (run.mcap)", seq.append_result)
seq.write_run_report = timed("report", seq.write_run_report)
commission.ident.hybrid.identify = timed("identification", commission.ident.hybrid.identify)
commission.tuning.design = timed("tuning design", commission.tuning.design)
commission.tuning.verify = timed("verification", commission.tuning.verify)
t0 = time.perf_counter()
code = commission.cli.main(sys.argv[2:])
t_main = time.perf_counter() - t0
stages["imports"] = t_imports
stages["other"] = t_main - sum(v for k, v in stages.items() if k != "imports")
stages["code"] = code
stages["modules"] = sorted(m for m in sys.modules if "__main__" not in m)
print("BENCH" + json.dumps(stages))
"""

STAGES = ["imports", "experiment", "log (run.mcap)", "identification", "tuning design", "verification", "report",
          "other"]


def run_once(modules: list[str], extra: list[str], out: str) -> tuple[dict, float, float]:
    """(stage times, process wall time, process CPU time) of one `commission --sim` run."""
    args = [sys.executable, "-c", CHILD, json.dumps(modules), "--sim", "--out", out, "--json", *extra]
    t0 = time.perf_counter()
    before = os.times()
    done = subprocess.run(args, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = os.times()
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    line = next((ln for ln in done.stdout.splitlines() if ln.startswith("BENCH")), None)
    if done.returncode != 0 or line is None:
        raise SystemExit(f"commission failed ({done.returncode}): {done.stderr[-2000:]}")
    stages = json.loads(line[len("BENCH"):])
    if stages["code"] != 0:
        raise SystemExit(f"commission exited with {stages['code']}: {done.stderr[-2000:]}")
    return stages, wall, cpu


def main() -> None:
    argv = sys.argv[1:]
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    runs = int(argv[0]) if argv else RUNS
    with tempfile.TemporaryDirectory() as tmp:
        warm, _, _ = run_once([], extra, os.path.join(tmp, "warm-up"))
        modules = warm["modules"]
        results = [run_once(modules, extra, os.path.join(tmp, f"run{i}")) for i in range(runs)]
    print(f"commission --sim {' '.join(extra)}".rstrip() + f": median of {runs} warm runs "
          f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
    total = statistics.median(r[1] for r in results)
    for name in STAGES:
        t = statistics.median(r[0].get(name, 0.0) for r in results)
        print(f"  {name:<16} {t:6.2f} s  {100 * t / total:4.0f} %")
    inside = statistics.median(sum(r[0].get(n, 0.0) for n in STAGES) for r in results)
    print(f"  {'start and exit':<16} {total - inside:6.2f} s  {100 * (total - inside) / total:4.0f} %")
    print(f"  {'total':<16} {total:6.2f} s wall, {statistics.median(r[2] for r in results):.2f} s CPU")


if __name__ == "__main__":
    main()
