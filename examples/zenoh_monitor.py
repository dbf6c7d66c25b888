"""Watch robots in a ROS 2 graph over rmw_zenoh, as a ROS 2 tool would: nodes, rates, gaps, diagnostics.

    python examples/zenoh_monitor.py --connect tcp/127.0.0.1:7447 --seconds 10   # through the local router
    python examples/zenoh_monitor.py --connect tcp/192.168.1.10:7447 --domain 3

Needs only eclipse-zenoh and rosbags (no aiohal, no ROS 2). It reads the graph from rmw_zenoh's
liveliness tokens (``@ros2_lv/<domain>/...``), takes every publisher of a ``.../joint_states``
topic of type ``sensor_msgs/msg/JointState`` whose type hash is the one rosbags computes for
Jazzy, subscribes to its key expression and decodes the CDR messages; ``/diagnostics`` alike.
For ``--seconds`` from each robot's first message it counts messages per robot, the rate (as
they arrived, and by their header stamps: the publisher's own), the longest gap, the attachments' sequence numbers, and prints one JSON line: per robot (its
namespace) those figures, the joint names and the last diagnostics, and the nodes seen.
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import threading
import time

JOINT_STATE = "sensor_msgs/msg/JointState"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
ATTACHMENT = struct.Struct("<qqB16s")  # sequence number, source time ns, GID length, GID


def dds_name(ros_type: str) -> str:
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def session_config(args: argparse.Namespace):
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(args.mode))
    config.insert_json5("listen/endpoints", json.dumps(args.listen))
    config.insert_json5("connect/endpoints", json.dumps(args.connect))
    config.insert_json5("scouting/multicast/enabled", json.dumps(args.scouting))
    if args.user:  # a bridge with user/password authentication lets in only those it knows
        config.insert_json5("transport/auth/usrpwd", json.dumps({"user": args.user, "password": args.password}))
    return config


def monitor(args: argparse.Namespace) -> dict:
    import zenoh
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    hashes = {t: store.hash_rihs01(t) for t in (JOINT_STATE, DIAGNOSTICS)}
    lock = threading.Lock()
    robots: dict[str, dict] = {}
    nodes: set[str] = set()
    publishers: dict[str, dict] = {}
    subscribed: set[str] = set()
    diagnostics: dict[str, dict] = {}
    session = zenoh.open(session_config(args))
    subs: list = []

    def on_state(robot: str, sample) -> None:
        now = time.monotonic()
        msg = store.deserialize_cdr(sample.payload.to_bytes(), JOINT_STATE)
        seq = ATTACHMENT.unpack(sample.attachment.to_bytes())[0] if sample.attachment else None
        with lock:
            r = robots.setdefault(robot, {"first": now, "last": now, "count": 0, "max_gap_ms": 0.0, "seq_gaps": 0})
            if now - r["first"] > args.seconds:
                return
            r["max_gap_ms"] = max(r["max_gap_ms"], (now - r["last"]) * 1e3)
            if seq is not None and r.get("seq") is not None and seq != r["seq"] + 1:
                r["seq_gaps"] += 1
            r.update(last=now, seq=seq, names=list(msg.name), position=[float(x) for x in msg.position])
            r["stamp_ns"] = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            r.setdefault("first_stamp_ns", r["stamp_ns"])
            r["count"] += 1

    def on_diagnostics(sample) -> None:
        msg = store.deserialize_cdr(sample.payload.to_bytes(), DIAGNOSTICS)
        first: dict[str, dict] = {}  # a robot's own status comes first, then one per new fault
        for status in msg.status:
            first.setdefault(status.hardware_id, {"name": status.name, "level": int(status.level),
                                                  "message": status.message})
        with lock:
            diagnostics.update(first)

    def subscribe(key: str, handler) -> None:
        if key not in subscribed:
            subscribed.add(key)
            subs.append(session.declare_subscriber(key, handler))

    def on_token(sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        parts = str(sample.key_expr).split("/")
        # @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]
        kind, namespace, node = parts[5], parts[7].replace("%", "/"), parts[8]
        with lock:
            nodes.add(f"{namespace.rstrip('/')}/{node}")
        if kind != "MP" or len(parts) < 13:
            return
        topic, dds_type, type_hash = parts[9].replace("%", "/"), parts[10], parts[11]
        with lock:
            publishers[topic] = {"type": dds_type, "hash": type_hash, "node": f"{namespace.rstrip('/')}/{node}"}
        key = f"{args.domain}/{topic.strip('/')}/{dds_type}/{type_hash}"
        if topic.endswith("/joint_states") and dds_type == dds_name(JOINT_STATE) and type_hash == hashes[JOINT_STATE]:
            robot = topic.removesuffix("/joint_states")
            subscribe(key, lambda s: on_state(robot, s))
        elif topic == "/diagnostics" and dds_type == dds_name(DIAGNOSTICS) and type_hash == hashes[DIAGNOSTICS]:
            subscribe(key, on_diagnostics)

    try:
        subs.append(session.liveliness().declare_subscriber(f"@ros2_lv/{args.domain}/**", on_token, history=True))
        deadline = time.monotonic() + args.wait
        while True:
            time.sleep(0.05)
            with lock:
                firsts = [r["first"] for r in robots.values()]
            if len(firsts) >= args.robots and time.monotonic() > max(firsts) + args.seconds:
                break
            if time.monotonic() > deadline + args.seconds:
                break
        for sub in subs:
            sub.undeclare()
    finally:
        session.close()
    out: dict = {"nodes": sorted(nodes), "publishers": publishers, "joint_state_hash": hashes[JOINT_STATE],
                 "robots": {}}
    for robot, r in sorted(robots.items()):
        span = r["last"] - r["first"]
        stamped_s = (r["stamp_ns"] - r["first_stamp_ns"]) / 1e9  # the publisher's clock: no delivery delays
        out["robots"][robot] = {
            "messages": r["count"], "rate_hz": round((r["count"] - 1) / span, 2) if span > 0 else None,
            "stamped_rate_hz": round((r["count"] - 1) / stamped_s, 2) if stamped_s > 0 else None,
            "span_s": round(span, 3), "max_gap_ms": round(r["max_gap_ms"], 2), "seq_gaps": r["seq_gaps"],
            "names": r["names"], "position": r["position"], "stamp_ns": r["stamp_ns"],
            "diagnostics": diagnostics.get(robot.strip("/"))}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--connect", action="append", default=[], help="endpoint of a robot's bridge or a router")
    p.add_argument("--listen", action="append", default=[], help="endpoint to listen on")
    p.add_argument("--scouting", action="store_true", help="find peers by UDP multicast too")
    p.add_argument("--mode", choices=("peer", "client"), default="peer")
    p.add_argument("--user", default=None, help="user name, where the bridge asks for a password")
    p.add_argument("--password", default=None)
    p.add_argument("--domain", type=int, default=0, help="ROS_DOMAIN_ID")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to count, from each robot's first message")
    p.add_argument("--robots", type=int, default=1, help="wait for this many robots")
    p.add_argument("--wait", type=float, default=10.0, help="how long to wait for the robots to appear")
    args = p.parse_args(argv)
    print(json.dumps(monitor(args)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
