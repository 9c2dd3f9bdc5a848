"""The CANopen path: what the technician waits for, measured on the virtual bus and computed for a real one.

1. Primary path, the paper's 10 s chirp at 8 kHz on the simulated node: SDO block
   download of the waveform and block upload of the five trace channels over
   python-can's in-process ``virtual`` bus — wall time, throughput, frame counts — and
   the bus time those frames take on a real 1 Mbit/s bus (nominal 111 bit per 8-byte
   frame without stuffing, worst case 135 bit with it), plus the 10 s playback.
2. Streamed fallback: the bus budget per bit rate and through an slcan UART, and a
   2 s streamed run on the virtual bus on the drive's clock (lost cycles, late
   setpoints, SYNC arrival jitter, host response; the host and the simulated node
   share one Python process, so this measures this machine, not a real bus).
Run: python bench/bench_canopen.py
"""

from __future__ import annotations

import time

from commission.config import Config
from commission.drive.canopen import frame_bits, open_simulated, plan_cycle
from commission.drive.canopen.pdo import STREAM_FRAMES, slcan_line_bytes
from commission.excitation import chirp

NOMINAL_8_BYTE_FRAME_BITS = 111  # 11-bit id, 8 data bytes, no stuff bits, 3 bit interframe space
BITRATE = 1_000_000


def primary_path() -> None:
    wave = chirp(Config().excitation)
    drive = open_simulated(channel="bench-canopen-trace")
    try:
        drive.set_limits(0.5, 50.0, 200.0)
        drive.enable()
        t0 = time.perf_counter()
        drive.run_excitation(wave.samples, wave.sample_rate_hz)
        total = time.perf_counter() - t0
        transfers = list(drive.transfers)
    finally:
        drive.close()
    print("primary path: waveform download + trace upload by SDO block transfer (10 s chirp, 80,000 samples, INT32)")
    print(f"  {'object':<10} {'dir':<9} {'bytes':>8} {'virtual s':>9} {'kB/s':>7} {'frames':>7}"
          f" {'1 Mbit/s: nominal s':>19} {'worst s':>8}")
    frames_total = bytes_total = 0
    wall_total = 0.0
    for t in transfers:
        nominal = t.frames * NOMINAL_8_BYTE_FRAME_BITS / BITRATE
        worst = t.frames * frame_bits(8) / BITRATE
        print(f"  {t.object:<10} {t.direction:<9} {t.n_bytes:>8} {t.seconds:>9.2f} {t.throughput_bps / 1e3:>7.0f}"
              f" {t.frames:>7} {nominal:>19.2f} {worst:>8.2f}")
        frames_total += t.frames
        bytes_total += t.n_bytes
        wall_total += t.seconds
    nominal = frames_total * NOMINAL_8_BYTE_FRAME_BITS / BITRATE
    worst = frames_total * frame_bits(8) / BITRATE
    print(f"  {'total':<10} {'':<9} {bytes_total:>8} {wall_total:>9.2f} {bytes_total / wall_total / 1e3:>7.0f}"
          f" {frames_total:>7} {nominal:>19.2f} {worst:>8.2f}")
    print(f"  whole excitation on the virtual bus (download, playback as fast as the plant runs, polls, upload):"
          f" {total:.2f} s")
    print(f"  on a real 1 Mbit/s bus the technician waits about {nominal:.0f}-{worst:.0f} s of transfers"
          f" + {wave.samples.size / wave.sample_rate_hz:.0f} s of playback"
          f" (≈ {nominal + 10:.0f}-{worst + 10:.0f} s), plus the adapter's turnaround on each of the"
          f" {sum(-(-t.n_bytes // 7 // 127) for t in transfers)} sub-block acks;")
    print(f"  SDO block transfer carries 7 payload bytes per 8-byte frame:"
          f" ≤ {7 * BITRATE / NOMINAL_8_BYTE_FRAME_BITS / 1e3:.0f} kB/s at 1 Mbit/s"
          f" ({7 * BITRATE / frame_bits(8) / 1e3:.0f} kB/s with worst-case stuffing)")


def streamed_fallback() -> None:
    print("\nstreamed fallback: bus budget (SYNC 1 B counter + RPDO 2 B + TPDO 8 B, worst-case stuffing, "
          "≤ 80 % load, two heartbeats every 100 ms)")
    line = slcan_line_bytes(STREAM_FRAMES[0]) + slcan_line_bytes(STREAM_FRAMES[2]) + 2
    for bitrate in (125_000, 250_000, 500_000, 1_000_000):
        budget = plan_cycle(bitrate, STREAM_FRAMES, 1 / 8000, max_load=0.8, background_bps=2 * frame_bits(1) / 0.1)
        print(f"  {bitrate / 1e3:>6.0f} kbit/s: {budget.describe()}")
    for line_bps in (115_200, 1_000_000):
        budget = plan_cycle(1_000_000, STREAM_FRAMES, 1 / 8000, max_load=0.8, background_bps=2 * frame_bits(1) / 0.1,
                            line_bps=line_bps, line_bytes_per_cycle=line)
        print(f"  slcan UART {line_bps / 1e3:g} kbit/s: {budget.describe()}")
    cfg = Config(excitation={"duration_s": 2.0, "bias_frequency_hz": 0.5})
    wave = chirp(cfg.excitation)
    drive = open_simulated(channel="bench-canopen-stream", drive="generic-cia402")
    try:
        drive.set_limits(0.5, 50.0, 200.0)
        drive.enable()
        rec = drive.run_excitation(wave.samples, wave.sample_rate_hz)
        report = drive.stream_report
        slips = drive.simulator.clock_slips
    finally:
        drive.close()
    assert report is not None
    print(f"  virtual bus, 2 s chirp, host and node in one process (bench_streamed.py: beside a CPU hog): "
          f"{report.describe()}; the simulated clock slipped {slips} times")
    print(f"  recorded {len(rec)} samples on the drive's cycle grid, {int(rec.lost_mask.sum())} lost")


def main() -> None:
    primary_path()
    streamed_fallback()


if __name__ == "__main__":
    main()
