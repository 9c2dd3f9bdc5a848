"""``python -m sim_drive``: run the simulated drive behind a fieldbus until Ctrl-C.

    python -m sim_drive --canopen --interface socketcan --channel vcan0 [--node-id 1]

One option per link (``--canopen`` now; the serial-adapter issue adds ``--slcan`` and
``--modbus`` to the same group); the plant and drive options are shared by all links.
python-can's ``virtual`` interface does not cross processes: run a commissioning
against this node over SocketCAN (``ip link add dev vcan0 type vcan``) or a real adapter.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from collections.abc import Sequence

from .device import SimulatedDevice
from .plant import PlantParameters


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m sim_drive",
        description="Run the simulated drive (two-mass + backlash plant, CiA 402) behind a fieldbus until Ctrl-C.",
    )
    link = p.add_argument_group("link (choose one)")
    which = link.add_mutually_exclusive_group(required=True)
    which.add_argument("--canopen", action="store_true", help="a CiA 402 node on a python-can bus")
    can_opts = p.add_argument_group("CAN options (with --canopen)")
    can_opts.add_argument("--interface", default="socketcan", help="python-can interface (default: socketcan)")
    can_opts.add_argument("--channel", default="vcan0", help="CAN channel (default: vcan0)")
    can_opts.add_argument("--bitrate", type=int, help="bit rate for adapters that need one")
    can_opts.add_argument("--node-id", type=int, default=1, help="CANopen node id (default: 1)")
    drive = p.add_argument_group("drive and plant")
    drive.add_argument("--seed", type=int, default=0, help="seed of the plant's torque noise")
    drive.add_argument("--pace", type=float, default=1.0,
                       help="waveform playback speed as a multiple of real time (default 1; 0: as fast as possible)")
    drive.add_argument("--run-for", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    device = SimulatedDevice(PlantParameters(seed=args.seed))
    if args.canopen:
        from .canopen_slave import CanopenSlave

        options = {"bitrate": args.bitrate} if args.bitrate else {}
        node = CanopenSlave(device, node_id=args.node_id, channel=args.channel, interface=args.interface,
                            pace=args.pace or None, **options)
    else:  # pragma: no cover - argparse requires one link
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        node.start()
    except Exception as err:  # a missing interface is the usual cause: one line, no traceback
        print(f"sim_drive: cannot start on {args.interface}:{args.channel}: {err}", file=sys.stderr)
        return 1
    print(f"sim_drive: CiA 402 node {args.node_id} on {args.interface}:{args.channel} "
          f"(heartbeat {node.node.sdo[0x1017].raw} ms); Ctrl-C stops", file=sys.stderr)
    deadline = None if args.run_for is None else time.monotonic() + args.run_for
    try:
        while not stop.wait(0.1):
            if deadline is not None and time.monotonic() > deadline:
                break
    finally:
        node.close()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
