"""Watch robots over Zenoh from another machine (or process): state rates, gaps, safety, faults.

    python examples/zenoh_monitor.py --connect tcp/192.168.1.10:7447 --seconds 10
    python examples/zenoh_monitor.py --seconds 10          # peers found by multicast scouting

Subscribes to ``<prefix>/*/state``, ``safety`` and ``faults`` (every robot on the network),
counts state messages per robot from its first one for ``--seconds``, and prints one JSON line:
per robot the messages, the rate and the longest gap between two messages, the last tick and
the safety changes and faults seen. Needs only eclipse-zenoh and numpy, not the robot's loop.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

from aiohal.outside.options import ZenohBridgeSection
from aiohal.outside.zenoh import decode_state, zenoh_config


def monitor(section: ZenohBridgeSection, seconds: float, robots: int, wait_s: float) -> dict:
    import zenoh

    lock = threading.Lock()
    seen: dict[str, dict] = {}

    def on_state(sample) -> None:
        now = time.monotonic()
        robot = str(sample.key_expr).split("/")[-2]
        state = decode_state(sample.payload.to_bytes())
        with lock:
            r = seen.setdefault(robot, {"first": now, "last": now, "count": 0, "max_gap_ms": 0.0,
                                        "safety": [], "faults": []})
            if now - r["first"] > seconds:
                return
            r["max_gap_ms"] = max(r["max_gap_ms"], (now - r["last"]) * 1e3)
            r["last"] = now
            r["count"] += 1
            r["tick"] = state["tick"]
            r["level"] = state["level"]

    def on_event(sample) -> None:
        robot, kind = str(sample.key_expr).split("/")[-2:]
        with lock:
            if robot in seen:
                seen[robot][kind].append(json.loads(sample.payload.to_bytes()))

    session = zenoh.open(zenoh_config(section))
    try:
        subs = [session.declare_subscriber(f"{section.prefix}/*/state", on_state),
                session.declare_subscriber(f"{section.prefix}/*/safety", on_event),
                session.declare_subscriber(f"{section.prefix}/*/faults", on_event)]
        deadline = time.monotonic() + wait_s
        while True:
            time.sleep(0.05)
            with lock:
                firsts = [r["first"] for r in seen.values()]
            if len(firsts) >= robots and time.monotonic() > max(firsts) + seconds:
                break
            if time.monotonic() > deadline + seconds:
                break
        for sub in subs:
            sub.undeclare()
    finally:
        session.close()
    out = {}
    for robot, r in sorted(seen.items()):
        span = r["last"] - r["first"]
        out[robot] = {"messages": r["count"], "rate_hz": round((r["count"] - 1) / span, 2) if span > 0 else None,
                      "span_s": round(span, 3), "max_gap_ms": round(r["max_gap_ms"], 2), "tick": r.get("tick"),
                      "level": r.get("level"), "safety": r["safety"], "faults": r["faults"]}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--connect", action="append", default=[], help="endpoint of a robot's bridge or a router")
    p.add_argument("--listen", action="append", default=[], help="endpoint to listen on")
    p.add_argument("--no-scouting", action="store_true", help="no multicast scouting (endpoints only)")
    p.add_argument("--mode", choices=("peer", "client"), default="peer")
    p.add_argument("--prefix", default="aiohal")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to count, from each robot's first message")
    p.add_argument("--robots", type=int, default=1, help="wait for this many robots")
    p.add_argument("--wait", type=float, default=10.0, help="how long to wait for the robots to appear")
    args = p.parse_args(argv)
    section = ZenohBridgeSection(prefix=args.prefix, mode=args.mode, listen=args.listen, connect=args.connect,
                                 multicast_scouting=not args.no_scouting)
    print(json.dumps(monitor(section, args.seconds, args.robots, args.wait)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
