"""Serial paths: how long the trace upload of the paper's 10 s chirp takes, on the pty and on real lines.

For each serial path (CANopen through an slcan adapter; Modbus RTU) the simulated drive runs in a second
process (``python -m sim_drive --slcan|--modbus``) behind a pty; this process runs the real host stack
(python-can's slcan client + canopen; pymodbus's serial client) and plays the 10 s chirp (80,000 samples,
five INT32 trace channels = 1.6 MB of trace).

Figures:
1. measured on the pty (no line rate: the cost of the two Python stacks and the simulated drive);
2. modelled for a real link, from the bytes and frames that crossed the pty:
   - slcan, three links in series: the serial side at 115200 8N1 (an adapter behind a real UART; ASCII
     lines of 22 bytes per 8-byte frame), the USB CDC side (full speed, ~1 MB/s: not the limit), and the
     1 Mbit/s CAN bus (111 bit per 8-byte frame nominal, 135 worst case with stuffing);
   - Modbus RTU at 115200 8N1: every request and answer byte + 3.5 characters of silence after each
     (the drive's own reaction time per request is extra and not modelled);
3. a check of the model: a 0.1 s chirp with the pty paced to 115200 bit/s (``--line-rate``), measured
   against the model's figure for the same bytes.
Run: python bench/bench_serial.py
"""

from __future__ import annotations

import contextlib
import select
import subprocess
import sys
import time
from collections.abc import Iterator

from commission.config import Config
from commission.drive import open_drive
from commission.drive.canopen import frame_bits
from commission.excitation import chirp

BAUD = 115_200
CAN_BITRATE = 1_000_000
NOMINAL_8_BYTE_FRAME_BITS = 111
SLCAN_LINE_BYTES = 22  # "t581" + "8" + 16 hex + CR
USB_CDC_BYTES_PER_S = 1.0e6  # full-speed bulk, practical


@contextlib.contextmanager
def sim_drive(link: str, *args: str) -> Iterator[str]:
    proc = subprocess.Popen([sys.executable, "-m", "sim_drive", f"--{link}", "--pace", "0", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 60)
        if not ready:
            raise RuntimeError("sim_drive printed no pty path")
        yield proc.stdout.readline().strip()
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def run(link: str, duration_s: float, *sim_args: str) -> tuple[list, float]:
    wave = chirp(Config(excitation={"duration_s": duration_s, "bias_frequency_hz": 0.1}).excitation)
    with sim_drive(link, *sim_args) as port:
        options = {"interface": "slcan", "drive": "sim"} if link == "slcan" else {"protocol": "modbus"}
        drive = open_drive(port=port, **options)
        try:
            drive.set_limits(0.5, 50.0, 200.0)
            drive.enable()
            t0 = time.perf_counter()
            drive.run_excitation(wave.samples, wave.sample_rate_hz)
            total = time.perf_counter() - t0
            transfers = list(drive.transfers)
        finally:
            drive.close()
    return transfers, total


def slcan_model(frames: int) -> dict[str, float]:
    return {
        "uart": frames * SLCAN_LINE_BYTES * 10 / BAUD,
        "usb": frames * SLCAN_LINE_BYTES / USB_CDC_BYTES_PER_S,
        "can_nominal": frames * NOMINAL_8_BYTE_FRAME_BITS / CAN_BITRATE,
        "can_worst": frames * frame_bits(8) / CAN_BITRATE,
    }


def slcan() -> None:
    transfers, total = run("slcan", 10.0)
    uploads = [t for t in transfers if t.direction == "upload"]
    print("slcan adapter (CANopen SDO block upload of 5 trace channels, 10 s chirp)")
    print(f"  {'object':<10} {'bytes':>8} {'frames':>7} {'pty s':>7} {'UART 115200 s':>13} {'USB CDC s':>9}"
          f" {'CAN 1M s':>12}")
    sums = {"pty": 0.0, "uart": 0.0, "usb": 0.0, "can_nominal": 0.0, "can_worst": 0.0, "bytes": 0, "frames": 0}
    for t in uploads:
        m = slcan_model(t.frames)
        print(f"  {t.object:<10} {t.n_bytes:>8} {t.frames:>7} {t.seconds:>7.2f} {m['uart']:>13.1f} {m['usb']:>9.2f}"
              f" {m['can_nominal']:>5.1f}-{m['can_worst']:<6.1f}")
        sums["pty"] += t.seconds
        sums["bytes"] += t.n_bytes
        sums["frames"] += t.frames
        for k in ("uart", "usb", "can_nominal", "can_worst"):
            sums[k] += m[k]
    print(f"  {'trace':<10} {sums['bytes']:>8} {sums['frames']:>7} {sums['pty']:>7.2f} {sums['uart']:>13.1f}"
          f" {sums['usb']:>9.2f} {sums['can_nominal']:>5.1f}-{sums['can_worst']:<6.1f}")
    download = next(t for t in transfers if t.direction == "download")
    print(f"  (waveform download {download.n_bytes} B: {download.seconds:.2f} s on the pty; whole excitation"
          f" {total:.1f} s on the pty)")
    print(f"  trace upload on the pty: {sums['pty']:.1f} s ({sums['bytes'] / sums['pty'] / 1e3:.0f} kB/s: python-can's"
          " slcan client + canopen + the simulated node, two Python processes)")
    print(f"  modelled: behind a 115200-baud UART the ASCII lines take {sums['uart']:.0f} s (the UART is the"
          f" bottleneck, {BAUD / 10 / SLCAN_LINE_BYTES:.0f} frames/s);")
    print(f"  a USB CDC adapter (no real baud rate) moves the lines in ~{sums['usb']:.1f} s, so there the 1 Mbit/s"
          f" CAN bus is the bottleneck: {sums['can_nominal']:.0f}-{sums['can_worst']:.0f} s"
          f" (≤ {CAN_BITRATE / NOMINAL_8_BYTE_FRAME_BITS:.0f} frames/s), plus one USB round trip per"
          f" {127}-frame sub-block ack ({sum(-(-t.frames // 128) for t in uploads)} acks, ~1-2 ms each)")


def modbus() -> None:
    transfers, total = run("modbus", 10.0)
    uploads = [t for t in transfers if t.direction == "upload"]
    print("\nModbus RTU (FC 23 trace window, 62 INT32 samples per request, 10 s chirp)")
    print(f"  {'channel':<22} {'bytes':>8} {'requests':>8} {'line bytes':>10} {'pty s':>7} {'115200 8N1 s':>12}")
    pty = model = 0.0
    for t in uploads:
        m = t.modelled_seconds(BAUD)
        print(f"  {t.what:<22} {t.n_bytes:>8} {t.requests:>8} {t.line_bytes:>10} {t.seconds:>7.2f} {m:>12.1f}")
        pty += t.seconds
        model += m
    print(f"  {'trace':<22} {sum(t.n_bytes for t in uploads):>8} {sum(t.requests for t in uploads):>8}"
          f" {sum(t.line_bytes for t in uploads):>10} {pty:>7.2f} {model:>12.1f}")
    download = next(t for t in transfers if t.direction == "download")
    print(f"  (waveform download: {download.seconds:.2f} s on the pty, {download.modelled_seconds(BAUD):.1f} s modelled"
          f" at 115200; whole excitation {total:.1f} s on the pty)")
    print(f"  modelled at 115200 8N1 the line is the bottleneck: {model:.0f} s for the trace"
          f" ({sum(t.n_bytes for t in uploads) / model / 1e3:.1f} kB/s of payload), plus the drive's reaction"
          f" time per request ({sum(t.requests for t in uploads)} requests × its latency)")


def model_check() -> None:
    print("\nmodel check: 0.1 s chirp with the pty paced to 115200 bit/s (sim_drive --line-rate 115200)")
    transfers, _ = run("modbus", 0.1, "--line-rate", str(BAUD))
    ups = [t for t in transfers if t.direction == "upload"]
    measured, modelled = sum(t.seconds for t in ups), sum(t.modelled_seconds(BAUD) for t in ups)
    print(f"  Modbus trace upload: paced pty {measured:.2f} s, model {modelled:.2f} s")
    transfers, _ = run("slcan", 0.1, "--line-rate", str(BAUD))
    ups = [t for t in transfers if t.direction == "upload"]
    measured = sum(t.seconds for t in ups)
    modelled = sum(slcan_model(t.frames)["uart"] for t in ups)
    print(f"  slcan trace upload: paced pty {measured:.2f} s, model (UART only) {modelled:.2f} s")


def main() -> None:
    slcan()
    modbus()
    model_check()


if __name__ == "__main__":
    main()
