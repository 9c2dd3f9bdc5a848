"""``python -m sim_drive``: run the simulated drive behind a fieldbus until Ctrl-C.

    python -m sim_drive --canopen --interface socketcan --channel vcan0 [--node-id 1]
    python -m sim_drive --slcan  [--config FILE] [--seed N]   # prints the pty's path first
    python -m sim_drive --modbus [--config FILE] [--seed N]   # prints the pty's path first
    python -m sim_drive --slcan --line-rate 1000000 --frame-loss 0.001 --bus-load 0.2 --identity generic

One option per link; the plant and drive options are shared by all links. ``--slcan``
and ``--modbus`` open a pty and print its path as the first line on stdout: point
``commission --port PATH --interface slcan`` or ``--protocol modbus`` at it.
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m sim_drive",
        description="Run the simulated drive (two-mass + backlash plant, CiA 402) behind a fieldbus until Ctrl-C.",
    )
    link = p.add_argument_group("link (choose one)")
    which = link.add_mutually_exclusive_group(required=True)
    which.add_argument("--canopen", action="store_true", help="a CiA 402 node on a python-can bus")
    which.add_argument("--slcan", action="store_true",
                       help="an slcan (Lawicel) serial CAN adapter on a pty, the CiA 402 node behind it")
    which.add_argument("--modbus", action="store_true", help="the drive's Modbus RTU service port on a pty")
    can_opts = p.add_argument_group("CAN options (with --canopen)")
    can_opts.add_argument("--interface", default="socketcan", help="python-can interface (default: socketcan)")
    can_opts.add_argument("--channel", default="vcan0", help="CAN channel (default: vcan0)")
    can_opts.add_argument("--bitrate", type=int, help="bit rate for adapters that need one")
    can_opts.add_argument("--node-id", type=int, default=1, help="CANopen node id (default: 1)")
    serial_opts = p.add_argument_group("serial options (with --slcan / --modbus)")
    serial_opts.add_argument("--line-rate", type=float, metavar="BIT/S",
                             help="model a UART at this bit rate (8N1, half duplex); default: pty speed, not modelled")
    serial_opts.add_argument("--inject", action="append", default=[], metavar="FAULT",
                             help="link fault: garble|truncate|crc|mute|hangup[@N[+]] (N: answer number, for "
                                  "hangup the playback sample; +: and every later one); repeatable")
    serial_opts.add_argument("--watchdog", type=float, default=1.0, metavar="S",
                             help="--modbus: fault the drive when the host is silent this long while enabled (0: off)")
    bus = p.add_argument_group("bus and drive identity (with --canopen / --slcan)")
    bus.add_argument("--frame-loss", type=float, default=0.0, metavar="P",
                     help="probability that a cyclic frame (SYNC, TPDO, RPDO) is lost (default 0)")
    bus.add_argument("--bus-load", type=float, default=0.0, metavar="FRACTION",
                     help="other nodes' traffic on the bus, as a fraction of 1 Mbit/s (default 0)")
    bus.add_argument("--identity", metavar="NAME|VENDOR:PRODUCT",
                     help="report another drive's 0x1018: a description name (yaskawa-sigma7), 'generic' "
                          "(vendor 0, a drive no description claims) or hex VENDOR:PRODUCT")
    drive = p.add_argument_group("drive and plant")
    drive.add_argument("--config", metavar="FILE",
                       help="commissioning recipe whose 'sim' section is the plant (as commission --sim --config)")
    drive.add_argument("--seed", type=int, help="seed of the plant's torque noise (overrides sim.seed; default 0)")
    drive.add_argument("--trace-capacity", type=int, metavar="N", help="samples the trace buffer holds")
    drive.add_argument("--pace", type=float, default=1.0,
                       help="waveform playback speed as a multiple of real time (default 1; 0: as fast as possible)")
    drive.add_argument("--run-for", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    return p


def _identity(text: str | None) -> tuple[int, int, str] | None:
    """``--identity``: (vendor id, product code, device name) to report, or None for the simulator's own."""
    if text is None:
        return None
    if text == "generic":
        return 0, 0, "CiA 402 servo drive"
    if ":" in text:
        vendor, product = (int(part, 16) for part in text.split(":", 1))
        return vendor, product, "CiA 402 servo drive"
    from commission.drive.description import load_description

    desc = load_description(text)
    if desc.identity is None:
        raise ValueError(f"drive description '{text}' has no identity to pose as")
    codes = desc.identity.product_codes or (0,)
    return desc.identity.vendor_id, codes[0], desc.summary or desc.name


def _node_options(args: argparse.Namespace) -> dict[str, object]:
    options: dict[str, object] = {"frame_loss": args.frame_loss, "bus_load": args.bus_load}
    identity = _identity(args.identity)
    if identity is not None:
        options["identity"] = identity
    if args.seed is not None:
        options["seed"] = args.seed
    return options


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        device = _device(args)
        node_options = _node_options(args)
    except Exception as err:  # a bad config, plant or option: one line
        print(f"sim_drive: {err}", file=sys.stderr)
        return 2
    if args.slcan or args.modbus:
        return _serve_pty(args, device, node_options)
    if args.canopen:
        from .canopen_slave import CanopenSlave

        options = {"bitrate": args.bitrate} if args.bitrate else {}
        try:
            node = CanopenSlave(device, node_id=args.node_id, channel=args.channel, interface=args.interface,
                                pace=args.pace or None, **node_options, **options)
        except ValueError as err:
            print(f"sim_drive: {err}", file=sys.stderr)
            return 2
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


def _device(args: argparse.Namespace) -> SimulatedDevice:
    """The simulated drive with the plant ``commission --sim`` would use for the same config and seed."""
    from commission.config import load_config
    from commission.drive.sim import plant_from_options

    plant = dict(load_config(args.config).sim)
    if args.seed is not None:
        plant["seed"] = args.seed
    options = {"trace_capacity": args.trace_capacity} if args.trace_capacity else {}
    return SimulatedDevice(plant_from_options(plant), **options)


def _serve_pty(args: argparse.Namespace, device: SimulatedDevice, node_options: dict[str, object]) -> int:
    from .serial_slave import ModbusRtuServer, SlcanAdapter, parse_fault

    try:
        faults = tuple(parse_fault(f) for f in args.inject)
    except ValueError as err:
        print(f"sim_drive: {err}", file=sys.stderr)
        return 2
    pace = args.pace or None
    server: SlcanAdapter | ModbusRtuServer
    if args.slcan:
        try:
            server = SlcanAdapter(device, node_id=args.node_id, pace=pace, faults=faults, line_rate_bps=args.line_rate,
                                  node_options=node_options)
        except ValueError as err:
            print(f"sim_drive: {err}", file=sys.stderr)
            return 2
    else:
        server = ModbusRtuServer(device, pace=pace, faults=faults, line_rate_bps=args.line_rate,
                                 watchdog_s=args.watchdog)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    server.start()
    print(server.path, flush=True)  # the first line on stdout: the host's --port
    link = "slcan adapter, CANopen node %d" % args.node_id if args.slcan else "Modbus RTU device 1"
    rate = f"line modelled at {args.line_rate:g} bit/s" if args.line_rate else "pty speed (line rate not modelled)"
    print(f"sim_drive: {link} on {server.path} ({rate}); Ctrl-C stops", file=sys.stderr, flush=True)
    deadline = None if args.run_for is None else time.monotonic() + args.run_for
    try:
        while not stop.wait(0.1):
            if deadline is not None and time.monotonic() > deadline:
                break
    finally:
        server.close()
        if isinstance(server, SlcanAdapter):
            node = server.node
            print(f"sim_drive: {server.frames_from_host} frames from the host, {server.frames_to_host} to it, "
                  f"{server.overruns} dropped by the line, {server.bad_lines} malformed lines "
                  f"{server.last_bad_line!r}; {node.cycles_produced} cycles on the drive's clock, "
                  f"{node.held_cycles} with a late setpoint, {node.frames_dropped} frames lost on the bus",
                  file=sys.stderr)
        else:
            print(f"sim_drive: {server.requests} requests, {server.responses} responses, "
                  f"{server.crc_errors} with a bad CRC", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
