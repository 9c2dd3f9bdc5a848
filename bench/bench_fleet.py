"""Fleet mode's throughput on Dask (commission.fleet): logs per minute with 1 and 2 local workers,
with each identification on 1 or 2 threads, and the memory of a worker.

Run as ``python bench/bench_fleet.py [--logs N] [--repeat R] [--config NAME]``. It simulates N logs
(default 16 of the shipped default recipe's 10 s chirp, the reference plant with its coupling
softened by up to 20 % and ε from 0.2° to 0.7°) into a temporary folder, starts a local Dask cluster per
variant, lets every worker identify one log first (imports and numba's cache loaded: what a long
batch amortises), then times the batch R times (median). Cluster start-up is printed apart: it is
paid once per batch, not per log. Memory: each worker's peak resident set (ru_maxrss) after the
batches, and its resident set when it started.
"""

from __future__ import annotations

import argparse
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


def measure(logs: list[tuple[str, str]], options: dict, workers: int, threads: int, repeat: int) -> dict:
    start = time.perf_counter()
    with connect(None, workers) as (client, info):
        started = time.perf_counter() - start
        rss_start = client.run(_rss_kb)
        opts = {**options, "threads": threads}
        # one log per worker first: imports, numba's cache, the first allocation
        warm = [client.submit(identify_log, *logs[i % len(logs)], options=opts, workers=[w], pure=False)
                for i, w in enumerate(client.scheduler_info()["workers"])]
        client.gather(warm)
        times, failed = [], 0
        for _ in range(repeat):
            rows: list[dict] = []
            t0 = time.perf_counter()
            identify_all(client, logs, opts, identify_log, rows.append)
            times.append(time.perf_counter() - t0)
            failed += sum(r["status"] != "ok" for r in rows)
        rss_end = client.run(_rss_kb)
    wall = statistics.median(times)
    return {"workers": info.workers, "threads": threads, "start_s": started, "wall_s": wall,
            "per_min": 60.0 * len(logs) / wall, "failed": failed,
            "rss_start_mb": max(v[0] for v in rss_start.values()) / 1024,
            "rss_peak_mb": max(v[1] for v in rss_end.values()) / 1024}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--config", default="default", help="recipe of the simulated logs and their identification")
    args = ap.parse_args()
    cfg = load_config(args.config)
    options = cfg.identification.model_dump(mode="json")
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
        t0 = time.perf_counter()
        logs = make_logs(Path(tmp), args.logs, args.config)
        made = time.perf_counter() - t0
        size_mb = sum(os.path.getsize(p) for p, _ in logs) / len(logs) / 1e6
        print(f"fleet throughput: {args.logs} simulated logs of the '{args.config}' recipe "
              f"({cfg.excitation.duration_s:g} s, {size_mb:.2f} MB each, made in {made:.1f} s), "
              f"median of {args.repeat} batches; {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}")
        results = []
        for workers, threads in ((1, 1), (1, 2), (2, 1), (2, 2)):
            r = measure(logs, options, workers, threads, args.repeat)
            results.append(r)
            print(f"  {r['workers']} worker(s), identify on {r['threads']} thread(s): {r['per_min']:6.1f} logs/min "
                  f"(batch {r['wall_s']:.1f} s, {r['wall_s'] / args.logs:.2f} s/log; cluster start {r['start_s']:.1f} s)"
                  f"  worker memory: {r['rss_start_mb']:.0f} MB at start, peak {r['rss_peak_mb']:.0f} MB"
                  + (f"  FAILED ROWS {r['failed']}" if r["failed"] else ""))
        best = {w: max((r for r in results if r["workers"] == w), key=lambda r: r["per_min"]) for w in (1, 2)}
        ratio = best[2]["per_min"] / best[1]["per_min"]
        same = {t: next(r for r in results if r["workers"] == 2 and r["threads"] == t)["per_min"]
                / next(r for r in results if r["workers"] == 1 and r["threads"] == t)["per_min"] for t in (1, 2)}
        print(f"  throughput ratio 2 workers / 1 worker: {ratio:.2f} (best of each; "
              f"identify on 1 thread: {same[1]:.2f}, on 2 threads: {same[2]:.2f})")
        print(f"  per log on one worker: {60.0 / best[1]['per_min']:.2f} s; peak worker memory "
              f"{max(r['rss_peak_mb'] for r in results):.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
