"""A planner process streaming setpoints at 1 kHz into a running 1 kHz loop through the
shared-memory door: what it costs the loop, and how long a setpoint takes to reach a command.

Each round runs two cases side by side in this process, on the real clock (timerfd; SCHED_FIFO 80
and locked memory where permitted), 7 mock joints, the ``stream`` controller, ``[client] shm``:

- ``without``: nobody attached (the door still publishes every tick);
- ``with``: a client in another process (``--client`` mode of this module) sends one
  as-soon-as-possible setpoint per millisecond on its own absolute deadlines.

Each case ticks ``--warmup`` s (the client starts and streams) then ``--seconds`` s measured.
Lateness p99 is the loop's (wake − deadline) over the measured run; latency is client write
(``time.monotonic_ns()`` just before the ring's head moves) to the wake of the tick that took the
point, in µs and in periods.

    python -m benchmarks.shm_client [--seconds 10] [--warmup 2] [--rounds 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import subprocess
import sys
import time
import uuid

import numpy as np

from .common import ROOT, StealMeter, table, write_json

PERIOD_NS = 1_000_000


def config_raw(name: str) -> dict:
    return {
        "robot": {"name": name},
        "loop": {"rate_hz": 1000},
        "realtime": {"priority": 80, "lock_memory": True},
        "joint_defaults": {"acceleration": 10.0, "velocity": 2.0},
        "joints": {f"a{i}": {"position": [-2.9, 2.9]} for i in range(7)},
        "driver": [{"type": "mock", "name": "arm", "joints": ["*"], "options": {"dynamics": "first_order"}}],
        "controller": {"type": "stream", "params": {"dry_after_s": 60.0}},
        "client": {"shm": True},
    }


async def run_case(with_client: bool, seconds: float, warmup: float) -> dict:
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop

    name = f"bench_{uuid.uuid4().hex[:8]}"
    loop = ControlLoop(parse_config(config_raw(name)))
    client = None
    steal = StealMeter()
    async with loop:
        if with_client:
            client = subprocess.Popen([sys.executable, "-m", "benchmarks.shm_client", "--client", name,
                                       "--client-seconds", str(warmup + seconds + 5)], cwd=ROOT,
                                      stdout=subprocess.PIPE, text=True)
        await loop.run(duration=warmup)
        controller = loop.controller
        applied0 = getattr(controller, "applied", 0)
        report = await loop.run(duration=seconds)
        latencies = controller.latencies_ns(applied0) if hasattr(controller, "latencies_ns") else np.zeros(0)
    if client is not None:
        client.terminate()
        client.wait(timeout=10)
    row = {
        "case": "with" if with_client else "without",
        "ticks": report["ticks"],
        "missed": report["missed_ticks"],
        "lateness_p50_us": report["lateness_us"]["p50"],
        "lateness_p99_us": report["lateness_us"]["p99"],
        "work_p50_us": report["work_us"]["p50"],
        "publish_p50_us": report["phases_us"]["publish"]["p50"],
        "steal_percent": round(steal.percent(), 2),
        "faults": len(report["faults"]),
    }
    if with_client:
        lat = latencies / 1e3
        row.update(points=int(lat.size),
                   latency_p50_us=round(float(np.percentile(lat, 50)), 1) if lat.size else None,
                   latency_p99_us=round(float(np.percentile(lat, 99)), 1) if lat.size else None,
                   latency_p99_ticks=round(float(np.percentile(lat, 99)) * 1e3 / PERIOD_NS, 3) if lat.size else None,
                   latency_max_us=round(float(lat.max()), 1) if lat.size else None)
    return row


def client_main(name: str, seconds: float) -> None:
    """The planner: one as-soon-as-possible setpoint per millisecond, a slow sine about the start."""
    from aiohal.client import RobotClient, RobotNotRunning

    deadline = time.monotonic() + 10
    while True:
        try:
            client = RobotClient(name, command=True)
            break
        except RobotNotRunning:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.01)
    q0 = client.read().position.copy()
    start = time.monotonic_ns()
    end = start + int(seconds * 1e9)
    k, sent = 0, 0
    while True:
        k += 1
        due = start + k * PERIOD_NS
        if due > end:
            break
        wait = due - time.monotonic_ns()
        if wait > 0:
            time.sleep(wait / 1e9)
        try:
            client.send(q0 + 0.05 * np.sin(2e-9 * np.pi * 0.5 * (due - start)), timeout_s=0.01)
        except RobotNotRunning:  # the measured run is over and the loop closed
            break
        sent += 1
    print(f"sent {sent}", flush=True)
    client.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--warmup", type=float, default=2.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--json", default=None)
    p.add_argument("--client", default=None, help=argparse.SUPPRESS)
    p.add_argument("--client-seconds", type=float, default=10.0, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.client:
        client_main(args.client, args.client_seconds)
        return 0
    rows = []
    for r in range(args.rounds):
        for with_client in (False, True):
            row = asyncio.run(run_case(with_client, args.seconds, args.warmup))
            row["round"] = r + 1
            rows.append(row)
            print(row, flush=True)
    cols = [("round", "round"), ("case", "client"), ("ticks", "ticks"), ("missed", "missed"),
            ("lateness_p50_us", "lateness p50 µs"), ("lateness_p99_us", "lateness p99 µs"),
            ("publish_p50_us", "publish p50 µs"), ("work_p50_us", "work p50 µs"), ("points", "points"),
            ("latency_p50_us", "latency p50 µs"), ("latency_p99_us", "latency p99 µs"),
            ("latency_p99_ticks", "latency p99 ticks"), ("steal_percent", "steal %")]
    print(table(rows, cols))
    without = [row["lateness_p99_us"] for row in rows if row["case"] == "without"]
    with_ = [row["lateness_p99_us"] for row in rows if row["case"] == "with"]
    ratio = statistics.median(with_) / statistics.median(without)
    worst = max(row["latency_p99_ticks"] or 0 for row in rows if row["case"] == "with")
    print(f"lateness p99, median of rounds: {statistics.median(without):.1f} µs without, "
          f"{statistics.median(with_):.1f} µs with the client (x{ratio:.3f}); latency p99 worst round {worst} ticks")
    write_json(args.json, {"rows": rows, "lateness_p99_ratio": round(ratio, 4), "latency_p99_ticks_worst": worst})
    return 0


if __name__ == "__main__":
    sys.exit(main())
