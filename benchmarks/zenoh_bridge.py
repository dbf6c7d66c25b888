"""What the Zenoh bridge adds to the tick: work per tick with the bridge off and on, side by side.

Each round runs both cases in this process on the real clock (timerfd; SCHED_FIFO 80 and locked
memory where permitted), 7 mock joints under ``hold`` at 1 kHz. ``on``: ``[bridge.zenoh]`` at
100 Hz on loopback (listen on a free 127.0.0.1 port, multicast scouting off) with a ROS 2-style
subscriber in another process (``examples/zenoh_monitor.py``) so that every put goes out. The figure that
matters is work p50 (the tick's own time, wake to end of publish) and its publish phase.

    python -m benchmarks.zenoh_bridge [--seconds 5] [--rounds 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import statistics
import subprocess
import sys
import time
import uuid

from .common import ROOT, StealMeter, table, write_json
from .shm_client import config_raw


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def run_case(bridge: bool, seconds: float) -> dict:
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop

    name = f"zbench_{uuid.uuid4().hex[:6]}"
    raw = config_raw(name)  # the same 7-joint mock arm, under hold, without the shared-memory door
    raw["controller"] = {"type": "hold"}
    del raw["client"]
    monitor = None
    if bridge:
        port = free_port()
        raw["bridge"] = {"zenoh": {"listen": [f"tcp/127.0.0.1:{port}"], "connect": []}}
        monitor = subprocess.Popen([sys.executable, str(ROOT / "examples" / "zenoh_monitor.py"),
                                    "--connect", f"tcp/127.0.0.1:{port}", "--listen", f"tcp/127.0.0.1:{free_port()}",
                                    "--seconds", str(seconds + 3), "--wait", "30"], cwd=ROOT,
                                   stdout=subprocess.PIPE, text=True)
    loop = ControlLoop(parse_config(raw))
    steal = StealMeter()
    async with loop:
        await loop.run(duration=2.0)  # the monitor connects meanwhile
        report = await loop.run(duration=seconds)
        bridge = loop.doors.zenoh
    sent = bridge.counters["state_sent"] if bridge is not None else None  # its process's figure, at close
    if monitor is not None:
        monitor.kill()
        monitor.wait()
    return {"case": "on" if bridge else "off", "ticks": report["ticks"], "missed": report["missed_ticks"],
            "work_p50_us": report["work_us"]["p50"], "work_p99_us": report["work_us"]["p99"],
            "publish_p50_us": report["phases_us"]["publish"]["p50"],
            "publish_p99_us": report["phases_us"]["publish"]["p99"],
            "lateness_p99_us": report["lateness_us"]["p99"], "state_sent": sent,
            "steal_percent": round(steal.percent(), 2)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    rows = []
    for r in range(args.rounds):
        for bridge in (False, True):
            row = asyncio.run(run_case(bridge, args.seconds))
            row["round"] = r + 1
            rows.append(row)
            print(row, flush=True)
            time.sleep(0.5)
    print(table(rows, [("round", "round"), ("case", "bridge"), ("ticks", "ticks"), ("missed", "missed"),
                       ("work_p50_us", "work p50 µs"), ("work_p99_us", "work p99 µs"),
                       ("publish_p50_us", "publish p50 µs"), ("publish_p99_us", "publish p99 µs"),
                       ("lateness_p99_us", "lateness p99 µs"), ("state_sent", "states sent"),
                       ("steal_percent", "steal %")]))
    diffs = [on["work_p50_us"] - off["work_p50_us"]
             for off, on in zip(rows[0::2], rows[1::2], strict=True)]
    print(f"work p50 added by the bridge per round: {[round(d, 2) for d in diffs]} µs; "
          f"median {statistics.median(diffs):.2f} µs")
    write_json(args.json, {"rows": rows, "work_p50_added_us": [round(d, 2) for d in diffs]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
