"""Run simulated CANopen nodes until stopped: CiA 402 drives and the DBC sensor gateway.

    python -m aiohal.drivers.canopen.sim --interface socketcan --channel vcan0 --drives 1-6 --sensors
    python -m aiohal.drivers.canopen.sim --interface udp_multicast --channel 239.74.163.2 --drives 1-6
    python -m aiohal.drivers.canopen.sim --interface socketcan --channel vcan0 --drives 1-6 --rpdo-type 255 \
        --sensors --no-orientation --status-ok 0

``udp_multicast`` needs python-can's ``multicast`` extra, and every process on the group sees
the others' frames: isolate it (a network namespace with only ``lo`` up and a route
``224.0.0.0/4 dev lo``). The drives answer SYNC from whichever master runs the bus; the
master's config names their node ids (aiohal's EDS, ``drivers/canopen/data/aiohal_drive.eds``).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

from . import SimBus


def node_ids(text: str) -> list[int]:
    """``'1-6'`` or ``'1,3,5'`` (or both) → node ids, each 1..127."""
    ids: list[int] = []
    for part in text.split(","):
        low, _, high = part.strip().partition("-")
        try:
            ids += list(range(int(low), int(high or low) + 1))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: node ids like 1-6 or 1,3,5") from None
    if not ids or not all(1 <= i <= 127 for i in ids) or len(set(ids)) != len(ids):
        raise argparse.ArgumentTypeError(f"{text!r}: distinct node ids 1..127")
    return ids


def rpdo_type(text: str) -> int:
    """An RPDO's transmission type: 0..240 (synchronous), 254 or 255 (event-driven)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not (0 <= value <= 240 or value in (254, 255)):
        raise argparse.ArgumentTypeError(f"{text!r}: an RPDO's transmission type is 0..240, 254 or 255")
    return value


def main(
    argv: list[str] | None = None, stop: threading.Event | None = None, ready: threading.Event | None = None
) -> int:
    """Run until ``stop`` is set (or a signal, or ``--duration``); ``ready`` is set once the
    nodes are on the bus."""
    parser = argparse.ArgumentParser(prog="python -m aiohal.drivers.canopen.sim", description=__doc__.split("\n\n")[0])
    parser.add_argument("--interface", required=True, help="python-can interface (socketcan, udp_multicast, ...)")
    parser.add_argument("--channel", required=True)
    parser.add_argument("--bitrate", type=int, default=1_000_000)
    parser.add_argument("--drives", type=node_ids, default=[], help="node ids of the drives, e.g. 1-6")
    parser.add_argument("--sensors", action="store_true", help="also the IMU + F/T gateway (aiohal_sensors.dbc)")
    parser.add_argument("--sensor-period-ms", type=float, default=4.0)
    parser.add_argument(
        "--rpdo-type",
        type=rpdo_type,
        default=None,
        help="the drives' RPDO transmission type at start (default: the EDS's, 1); 255: event-driven",
    )
    parser.add_argument(
        "--no-orientation", action="store_true", help="the IMU sends no orientation frame (IMU_Orientation)"
    )
    parser.add_argument(
        "--status-ok",
        type=int,
        choices=(0, 1),
        default=1,
        help="the sensors' Status value that means OK (default 1; 0: a gateway whose 0 means OK)",
    )
    parser.add_argument(
        "--dynamics",
        choices=("motor", "servo"),
        default="motor",
        help="servo: aiohal.simulation.servo's cascade per drive",
    )
    parser.add_argument(
        "--servo-json", type=json.loads, default=None, help="with --dynamics servo: ServoParams as JSON"
    )
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    args = parser.parse_args(argv)
    if not args.drives and not args.sensors:
        parser.error("nothing to simulate: give --drives and/or --sensors")
    period = args.sensor_period_ms * 1e-3
    try:
        sim = SimBus(
            args.interface,
            args.channel,
            args.drives,
            bitrate=args.bitrate,
            sensors={"imu": period, "force_torque": period} if args.sensors else None,
            rpdo_transmission_type=args.rpdo_type,
            imu_orientation=not args.no_orientation,
            status_ok=args.status_ok,
        )
    except Exception as exc:  # python-can raises several kinds for a bus it cannot open
        print(f"cannot open {args.interface}:{args.channel}: {exc}", file=sys.stderr)
        return 1
    settings = {"dynamics": args.dynamics, **({"servo": args.servo_json} if args.servo_json is not None else {})}
    try:
        for drive in sim.drives.values():
            drive.configure(**settings)
    except ValueError as exc:
        sim.close()
        print(f"error: {exc}", file=sys.stderr)
        return 2
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    if ready is not None:
        ready.set()
    print(
        f"simulating drives {args.drives}{' and sensors' if args.sensors else ''} on {args.interface}:{args.channel}",
        flush=True,
    )
    try:
        stop.wait(args.duration)
    finally:
        sim.close()
    for node_id, drive in sim.drives.items():
        print(f"  node {node_id}: {drive.status()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
