"""Command line: run a simulated EtherCAT segment on one network interface.

    python -m aiohal.drivers.ethercat.sim --ifname ecs0 --slaves 'drive*7,imu,ft,dio' \\
        [--control /run/ecsim.sock] [--watchdog-ms 100] [--seed 0] [--inject JSON ...]

It prints ``waiting <ifname> pid=<pid>`` (flushed) as soon as it runs, waits (bounded, see
``--wait-s``) until the interface exists in its network namespace, brings it up, binds, then
prints ``ready``. Meant to run inside ``unshare --net``: see docs/ethercat.md.

``--bench N`` does not touch the network: it brings the segment to OP in-process and prints
the time ``handle_frame`` takes for an LRW + FRMW frame.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import signal
import sys

from . import control
from .net import Runner, disable_ipv6, set_up, wait_for_interface
from .segment import Segment

IFNAMSIZ = 16  # Linux: an interface name is at most 15 bytes and a NUL


def _ifname(text: str) -> str:
    """Refused at once rather than after the wait for an interface that cannot exist."""
    if not text or len(text.encode()) >= IFNAMSIZ or "/" in text or text.strip() != text or text in (".", ".."):
        raise argparse.ArgumentTypeError(f"{text!r} is not a Linux interface name (1..15 bytes, no '/' or spaces)")
    return text


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m aiohal.drivers.ethercat.sim", description="Simulated EtherCAT slave segment on one interface."
    )
    p.add_argument("--ifname", type=_ifname, help="interface to answer on (only this one is opened)")
    p.add_argument(
        "--slaves", default="drive", help="bus order, e.g. 'drive*7,imu,ft,dio' (dioN: I/O terminal with N channels)"
    )
    p.add_argument("--control", metavar="PATH", help="UNIX socket path for JSON control commands")
    p.add_argument(
        "--watchdog-ms", type=float, default=100.0, help="SM (process data) watchdog time, 0 = off (default 100)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed for noise and random frame drops")
    p.add_argument(
        "--drift-ppm",
        type=float,
        default=0.0,
        help="spread of the slaves' clock drifts: the first at -ppm/2, the last at +ppm/2 (default 0)",
    )
    p.add_argument("--wait-s", type=float, default=10.0, help="how long to wait for the interface")
    p.add_argument(
        "--inject",
        action="append",
        default=[],
        metavar="JSON",
        help='a control command to apply at start, e.g. \'{"cmd":"drop","prob":0.01}\' (repeatable)',
    )
    p.add_argument(
        "--dynamics",
        choices=("motor", "servo"),
        help="every drive's dynamics: servo is aiohal.simulation.servo's cascade (a hip-like joint behind a gear)",
    )
    p.add_argument(
        "--servo-json",
        metavar="JSON",
        type=json.loads,
        help="with --dynamics servo: aiohal.simulation.servo.ServoParams fields",
    )
    p.add_argument("--drop-prob", type=float, help="shortcut for --inject drop prob")
    p.add_argument("--delay-ms", type=float, help="shortcut for --inject delay ms")
    p.add_argument("--duration-s", type=float, help="stop after this time (default: until killed)")
    p.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="stop when the parent process goes away (used by the test fixture)",
    )
    p.add_argument("--stats", action="store_true", help="print the status as JSON at exit")
    p.add_argument(
        "--bench", type=int, metavar="FRAMES", help="measure handle_frame for an LRW+FRMW frame in-process, no network"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    parent = os.getppid()
    try:
        segment = Segment(args.slaves, watchdog_ms=args.watchdog_ms, seed=args.seed, drift_ppm=args.drift_ppm)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    commands = [json.loads(c) for c in args.inject]
    if args.dynamics is not None or args.servo_json is not None:
        setting = {"dynamics": args.dynamics or "servo"}
        if args.servo_json is not None:
            setting["servo"] = args.servo_json
        drives = [k for k, esc in enumerate(segment.slaves) if esc.device.kind == "drive"]
        commands[:0] = [{"cmd": "device", "slave": k, **setting} for k in drives]
    if args.drop_prob is not None:
        commands.append({"cmd": "drop", "prob": args.drop_prob})
    if args.delay_ms is not None:
        commands.append({"cmd": "delay", "ms": args.delay_ms})
    for c in commands:
        answer = control.apply(segment, c)
        if not answer.get("ok"):
            print(f"error: --inject {c}: {answer.get('error')}", file=sys.stderr)
            return 2

    if args.bench:
        from .bench import measure

        print(json.dumps(measure(segment, args.bench)))
        return 0
    if not args.ifname:
        print("error: --ifname is required", file=sys.stderr)
        return 2

    def stop(signum, frame):
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    print(f"waiting {args.ifname} pid={os.getpid()}", flush=True)
    try:
        wait_for_interface(args.ifname, args.wait_s)
        disable_ipv6(args.ifname)
        set_up(args.ifname)
    except (OSError, TimeoutError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    runner = Runner(segment, args.ifname, args.control, parent_pid=parent if args.exit_with_parent else None)
    try:
        runner.open()
    except OSError as exc:
        print(f"error: cannot open {args.ifname}: {exc}", file=sys.stderr)
        return 1
    gc.collect()
    gc.freeze()  # the models' long-lived objects leave the collector's view: shorter pauses
    print("ready", flush=True)
    try:
        runner.serve(args.duration_s)
    finally:
        runner.close()
        if args.stats:
            print(json.dumps(segment.status()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
