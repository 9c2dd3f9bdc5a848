"""Speed and size of the MCAP log (commission.mcaplog) for a 10 s, 8 kHz, 5-signal run.

Run as ``python bench/bench_mcaplog.py``; prints medians over a few runs:
write and read time and file size against samples per message and chunk size,
the most a crash can lose (samples per chunk), and the time to recover a cut file.
"""

from __future__ import annotations

import statistics
import tempfile
import time
import warnings
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from commission.mcaplog import TruncatedLogWarning, read_recording, write_recording
from commission.recording import DriveInfo, Recording

FS_HZ = 8000.0
N = 80_000


def drive_like_recording(seed: int = 0) -> Recording:
    """Signals shaped like a drive trace: chirp torque in 0.1 % of rated torque,
    20-bit encoder positions, velocities from differenced positions (noisy)."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) / FS_HZ
    f = 1.0 + (2000.0 - 1.0) * t / t[-1]
    phase = 2 * np.pi * np.cumsum(f) / FS_HZ
    rated = 1.27
    torque = np.round(300 * np.sin(phase)) / 1000 * rated
    counts_per_rad = 2**20 / (2 * np.pi)
    motor_rad = np.cumsum(0.05 * np.sin(phase - 0.3) + 0.01) / FS_HZ * 50
    load_rad = np.cumsum(0.04 * np.sin(phase - 0.9) + 0.01) / FS_HZ * 50
    motor_pos = np.round(motor_rad * counts_per_rad) / counts_per_rad
    load_pos = np.round(load_rad * counts_per_rad) / counts_per_rad
    motor_vel = np.gradient(motor_pos, t) + rng.normal(0, 0.01, N)
    load_vel = np.gradient(load_pos, t) + rng.normal(0, 0.01, N)
    return Recording(
        t=t, sample_rate_hz=FS_HZ, torque_ref=torque, motor_velocity=motor_vel,
        motor_position=motor_pos, load_position=load_pos, load_velocity=load_vel,
        start_time=datetime(2025, 1, 1, tzinfo=timezone.utc),
        drive=DriveInfo(backend="sim", rated_torque_nm=rated),
    )


def median_time(fn: Callable[[], object], runs: int) -> tuple[float, float]:
    """Median wall-clock and CPU time [s] of ``fn`` (CPU time is the steadier figure
    on a busy machine)."""
    wall, cpu = [], []
    for _ in range(runs):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def ms(times: tuple[float, float]) -> str:
    return f"{times[0] * 1e3:.0f} ({times[1] * 1e3:.0f})"


def chunk_count(path: Path) -> int:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    return summary.statistics.chunk_count


def main(runs: int = 5) -> None:
    rec = drive_like_recording()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "run.mcap"
        print(f"MCAP log of {N:,} samples x 5 signals ({N / FS_HZ:.0f} s at {FS_HZ:.0f} Hz), "
              f"median of {runs} runs\n")
        print("write / read: wall-clock ms (CPU ms); max loss: samples per chunk, what a crash loses")
        header = (f"{'samples/msg':>11} {'chunk KiB':>9} {'write ms':>12} {'read ms':>12} "
                  f"{'size KB':>8} {'B/sample':>8} {'chunks':>6} {'max loss':>16}")
        print(header)
        print("-" * len(header))
        cases = [(1, 64), (80, 64), (800, 64), (80, 16), (80, 256), (80, 1024)]
        for spm, chunk_kib in cases:
            kw = {"samples_per_message": spm, "chunk_size": chunk_kib * 1024}
            n_runs = 3 if spm == 1 else runs  # 400,000 messages: slow
            t_write = median_time(lambda: write_recording(path, rec, **kw), n_runs)
            t_read = median_time(lambda: read_recording(path), n_runs)
            assert read_recording(path).equals(rec)
            size = path.stat().st_size
            chunks = chunk_count(path)
            loss = N / chunks  # samples per chunk: what a crash loses at most
            print(f"{spm:>11} {chunk_kib:>9} {ms(t_write):>12} {ms(t_read):>12} "
                  f"{size / 1e3:>8.0f} {size / N:>8.1f} {chunks:>6} "
                  f"{loss:>5.0f} sa = {loss / FS_HZ * 1e3:.0f} ms")

        write_recording(path, rec)
        data = path.read_bytes()
        print("\nrecovery of a cut file (defaults: 80 samples/msg, 64 KiB chunks)")
        for frac in (0.1, 0.5, 0.9):
            cut = Path(tmp) / f"cut{frac}.mcap"
            cut.write_bytes(data[: int(len(data) * frac)])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", TruncatedLogWarning)
                t_rec = median_time(lambda: read_recording(cut), runs)
                n = len(read_recording(cut))
            print(f"  cut at {frac:>4.0%} of {len(data) / 1e3:.0f} KB: {ms(t_rec):>12}, "
                  f"{n:,} samples back ({n / N:.1%})")


if __name__ == "__main__":
    main()
