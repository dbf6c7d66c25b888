"""What numba's dispatch costs the tick's kernels: each called through its dispatcher and
directly (:mod:`aiohal.core.compiled_entry`), on the arrays aiohal gives them, alternating rounds in
one process. Warm: calls back to back. After a sleep: one call after each 0.9 ms sleep, as
on the real clock, where a tick starts with cold caches.

    python -m benchmarks.kernel_call [--drives 7] [--joints 33] [--rounds 20] [--json PATH]
"""

from __future__ import annotations

import argparse
import statistics
import time

from aiohal.core import compiled_entry

from .common import StealMeter, table, write_json


def _limiter_case(joints: int):
    from aiohal.core import limit_kernel as lk
    from aiohal.core.limits import CommandLimiter
    from aiohal.robot import JointSpec, Robot

    robot = Robot("bench", [JointSpec(f"j{i}", i, -2.0, 2.0, 2.0, 20.0, 50.0) for i in range(joints)])
    limiter = CommandLimiter(robot, 0.001)
    limiter.reset(robot.state.position)
    args = (*limiter._args, False)
    return f"limiter, {joints} joints", lk.limit_commands, args


def _decode_case(drives: int):
    from aiohal.drivers.ethercat.devices import DriveGroup, DriveSpec
    from aiohal.fieldbus import drive_kernels as kernels
    from aiohal.fieldbus.busvar import PdoLayout, ProcessImage, encode_mapping
    from aiohal.fieldbus.cia402 import DriveUnits
    from aiohal.robot import JointState

    rx = [(0x6040, 16), (0x607A, 32), (0x60FF, 32), (0x6071, 16), (0x6060, 8)]
    tx = [(0x6041, 16), (0x6064, 32), (0x606C, 32), (0x6077, 16), (0x6061, 8), (0x603F, 16)]
    layout = PdoLayout.from_coe([0x1600], [0x1A00], {0x1600: [encode_mapping(i, 0, b) for i, b in rx],
                                                     0x1A00: [encode_mapping(i, 0, b) for i, b in tx]})
    image = ProcessImage([(f"d{i}", layout) for i in range(drives)])
    group = DriveGroup(image, [DriveSpec(f"d{i}", f"j{i}", i, DriveUnits()) for i in range(drives)], stuck_after=100)
    state = JointState(drives)
    group.bind_state(state)
    args = (group._inputs, group._layout, group._constants, group.ints, state.block, state.updated_tick,
            state.stamp_ns, 1, 2)
    return f"EtherCAT decode, {drives} drives", kernels.decode_drives, args


def _warm_us(fn, args, calls: int = 2000) -> float:
    t0 = time.perf_counter_ns()
    for _ in range(calls):
        fn(*args)
    return (time.perf_counter_ns() - t0) / calls / 1e3


def _after_sleep_us(fn, args, calls: int = 200) -> float:
    times = []
    for _ in range(calls):
        time.sleep(0.0009)
        t0 = time.perf_counter_ns()
        fn(*args)
        times.append(time.perf_counter_ns() - t0)
    return statistics.median(times) / 1e3


def measure(name: str, kernel, args: tuple, rounds: int) -> dict:
    ways = {"dispatch": kernel, "direct": compiled_entry.compiled_for(kernel, args)}
    samples: dict[str, list[float]] = {f"{way}_{when}": [] for way in ways for when in ("warm", "after_sleep")}
    for _ in range(rounds):
        for way, fn in ways.items():
            samples[f"{way}_warm"].append(_warm_us(fn, args))
            samples[f"{way}_after_sleep"].append(_after_sleep_us(fn, args))
    row = {"kernel": name, **{k: round(statistics.median(v), 2) for k, v in samples.items()}}
    for when in ("warm", "after_sleep"):
        pairs = [a - b for a, b in zip(samples[f"dispatch_{when}"], samples[f"direct_{when}"], strict=True)]
        row[f"saved_{when}"] = round(statistics.median(pairs), 2)
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--drives", type=int, default=7)
    p.add_argument("--joints", type=int, default=33)
    p.add_argument("--rounds", type=int, default=20)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    steal = StealMeter()
    rows = [measure(*_decode_case(args.drives), args.rounds), measure(*_limiter_case(args.joints), args.rounds)]
    steal_percent = round(steal.percent(), 1)
    print(table(rows, [("kernel", "kernel"), ("dispatch_warm", "dispatch µs"), ("direct_warm", "direct µs"),
                       ("saved_warm", "saved µs"), ("dispatch_after_sleep", "dispatch after sleep µs"),
                       ("direct_after_sleep", "direct after sleep µs"), ("saved_after_sleep", "saved µs")]))
    print(f"medians of {args.rounds} alternating rounds; steal {steal_percent} %")
    write_json(args.json, {"benchmark": "kernel_call", "rounds": args.rounds, "steal_percent": steal_percent,
                           "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
