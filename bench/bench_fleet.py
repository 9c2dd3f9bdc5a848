"""Fleet mode's throughput on Dask (commission.fleet): logs per minute with 1 and 2 local workers,
with each identification on 1 or 2 threads, and the memory of a worker.

Run as ``python bench/bench_fleet.py [--logs N] [--repeat R] [--config NAME]``. It simulates N logs
(default 16 of the shipped default recipe's 10 s chirp, the reference plant with its coupling
softened by up to 20 % and ε from 0.2° to 0.7°) into a temporary folder, starts a local Dask cluster
of 1 worker and one of 2 (one thread each), lets every worker identify one log first (imports and numba's cache loaded: what a long
batch amortises), then times the batch R times per variant, the variants interleaved (median; the
workers' CPU time per log beside it, the steadier figure on a shared machine). Cluster start-up is
printed apart: it is paid once per batch, not per log. Memory: each worker's peak resident set
(ru_maxrss) after the batches, and its resident set when it started.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import statistics
import sys
import tempfile
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from commission.config import load_config
from commission.excitation import chirp
from commission.fleet import identify_log
from commission.fleet.cluster import connect, identify_all
from commission.fleet.table import content_hash
from commission.mcaplog import write_recording
from commission.plant import Plant, PlantParameters
from commission.recording import DriveInfo, Recording

FS_HZ = 8000.0


def make_logs(folder: Path, n: int, config_name: str) -> list[tuple[str, str]]:
    cfg = load_config(config_name)
    tau = chirp(cfg.excitation).samples
    rng = np.random.default_rng(23)
    logs = []
    for i in range(n):
        # the reference plant as it wears: the coupling softens (K, with D keeping its damping ratio)
        # and the gear's play grows
        soften = float(rng.uniform(0.8, 1.05))
        ref = PlantParameters()
        plant = ref.model_copy(update={"K": ref.K * soften, "D": ref.D * math.sqrt(soften),
                                       "epsilon_deg": float(rng.uniform(0.2, 0.7)), "torque_noise_nm": 1e-4,
                                       "seed": i})
        r = Plant(plant, FS_HZ).run_torque(tau)
        rec = Recording.uniform(FS_HZ, r.torque_ref, r.motor_velocity, motor_position=r.motor_position,
                                start_time=datetime(2026, 1, 1, tzinfo=timezone.utc) + timedelta(days=i),
                                drive=DriveInfo(backend="sim", vendor="bench", product="axis",
                                                serial_number=f"B{i % 4}"))
        path = folder / f"axis-{i:03d}.mcap"
        write_recording(path, rec)
        logs.append((str(path), content_hash(path)))
    return logs


def _rss_kb() -> tuple[int, int]:
    """(current, peak) resident set of this process [kB] (runs on a worker)."""
    import resource

    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") // 1024, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def _cpu_s() -> float:
    """CPU time of this process, all threads [s] (runs on a worker)."""
    return time.process_time()


def batch(client: object, logs: list[tuple[str, str]], options: dict) -> tuple[float, float, int]:
    """(wall [s], workers' CPU [s], rows not ok) of one batch."""
    cpu0 = client.run(_cpu_s)  # type: ignore[attr-defined]
    rows: list[dict] = []
    t0 = time.perf_counter()
    identify_all(client, logs, options, identify_log, rows.append)
    wall = time.perf_counter() - t0
    cpu1 = client.run(_cpu_s)  # type: ignore[attr-defined]
    return wall, sum(cpu1[w] - cpu0[w] for w in cpu1 if w in cpu0), sum(r["status"] != "ok" for r in rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--config", default="default", help="recipe of the simulated logs and their identification")
    args = ap.parse_args()
    cfg = load_config(args.config)
    options = cfg.identification.model_dump(mode="json")
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp, contextlib.ExitStack() as stack:
        t0 = time.perf_counter()
        logs = make_logs(Path(tmp), args.logs, args.config)
        made = time.perf_counter() - t0
        size_mb = sum(os.path.getsize(p) for p, _ in logs) / len(logs) / 1e6
        print(f"fleet throughput: {args.logs} simulated logs of the '{args.config}' recipe "
              f"({cfg.excitation.duration_s:g} s, {size_mb:.2f} MB each, made in {made:.1f} s); "
              f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f} at start")
        # both clusters at once, and the variants' batches interleaved round by round: the load of
        # a shared machine drifts over minutes and must not favour one variant
        clusters = {}
        for workers in (1, 2):
            t0 = time.perf_counter()
            client, info = stack.enter_context(connect(None, workers))
            started = time.perf_counter() - t0
            rss_start = client.run(_rss_kb)
            # one log per worker first: imports, numba's cache, the first allocation
            client.gather([client.submit(identify_log, *logs[i % len(logs)], options=options, workers=[w], pure=False)
                           for i, w in enumerate(client.scheduler_info()["workers"])])
            clusters[workers] = (client, started, rss_start)
        variants = [(w, t) for w in (1, 2) for t in (1, 2)]
        walls: dict[tuple[int, int], list[float]] = {v: [] for v in variants}
        cpus: dict[tuple[int, int], list[float]] = {v: [] for v in variants}
        failed = 0
        for _ in range(args.repeat):
            for w, t in variants:
                wall, cpu, bad = batch(clusters[w][0], logs, {**options, "threads": t})
                walls[(w, t)].append(wall)
                cpus[(w, t)].append(cpu)
                failed += bad
        print(f"  median of {args.repeat} batches per variant, interleaved; load {os.getloadavg()[0]:.1f} at the end"
              + (f"; {failed} ROWS NOT OK" if failed else ""))
        rate = {v: 60.0 * len(logs) / statistics.median(walls[v]) for v in variants}
        for w, t in variants:
            client, started, rss_start = clusters[w]
            peak = max(v[1] for v in client.run(_rss_kb).values()) / 1024
            print(f"  {w} worker(s), identify on {t} thread(s): {rate[(w, t)]:6.1f} logs/min "
                  f"(batch {statistics.median(walls[(w, t)]):.1f} s; worker CPU "
                  f"{statistics.median(cpus[(w, t)]) / len(logs):.2f} s/log)  cluster start {started:.1f} s, "
                  f"worker memory {max(v[0] for v in rss_start.values()) / 1024:.0f} MB at start, peak {peak:.0f} MB")
        for t in (1, 2):
            print(f"  throughput ratio 2 workers / 1 worker, identify on {t} thread(s): "
                  f"{rate[(2, t)] / rate[(1, t)]:.2f}")
        best = max(variants, key=lambda v: rate[v])
        print(f"  best: {best[0]} worker(s) x {best[1]} thread(s), {rate[best]:.1f} logs/min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
