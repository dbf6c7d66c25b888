"""CPU per tick of the udp driver against bare asyncio sending and receiving the same
datagrams, side by side: COMAN's 29 boards (one joint each) on simulated boards, 1 kHz.

Both variants talk to the same simulated boards (one subprocess) in alternating blocks of
``--block`` ticks, so that the host's moods fall on both alike. CPU per tick is the ticking
thread's CPU time (``thread_time_ns``) from one deadline to the next: it includes the
replies taken between the ticks (asyncio's callbacks for the bare variant).

- ``driver``: ``UdpDriver.read()`` (drain, check, take, publish, stamp) and ``write()``
  (fill the records, header, CRC, ``sendmsg``) on a timerfd ticker.
- ``bare``: an asyncio datagram endpoint; each tick puts the sequence number and CRC into
  29 prebuilt command datagrams and sends them; ``datagram_received`` keeps each reply's
  bytes. Nothing is checked, nothing reaches a robot array. With ``--key`` it seals each
  datagram with the MAC too (the boards take nothing else), but checks no reply's.

    python -m benchmarks.udp [--seconds 10] [--block 500] [--key] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import struct
import subprocess
import sys
import time
import zlib

import numpy as np

from aiohal.core import realtime
from aiohal.core.ticker import Ticker, TimerfdTickSource
from aiohal.drivers.udp.driver import UdpDriver, UdpOptions
from aiohal.drivers.udp.protocol import COMMAND_RECORD, Kind, encode, seal
from aiohal.robot import JointSpec, Mode, Robot

from .common import machine, table, write_json

BOARDS = 29
KEY = "00112233445566778899aabbccddeeff"


class _Bare(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.replies: dict[tuple, bytes] = {}
        self.count = 0

    def datagram_received(self, data: bytes, addr) -> None:
        self.replies[addr] = data
        self.count += 1


async def _run(ports: list[int], seconds: float, block: int, keyed: bool) -> dict:
    loop = asyncio.get_running_loop()
    robot = Robot("coman", [JointSpec(f"j{i}", i, -3, 3, 5, 50, 50) for i in range(BOARDS)])
    names = list(robot.joint_names)
    boards = [{"id": i + 1, "joints": [names[i]], "address": "127.0.0.1", "port": p} for i, p in enumerate(ports)]
    options = UdpOptions.model_validate({"boards": boards, "bind_address": "127.0.0.1", "silent_ticks": 1000,
                                         **({"key": KEY} if keyed else {})})
    driver = UdpDriver("boards", robot.driver_view(names), options)
    await driver.open()
    robot.command.mode[:] = Mode.POSITION
    transport, bare = await loop.create_datagram_endpoint(_Bare, local_addr=("127.0.0.1", 0))
    addresses = [("127.0.0.1", p) for p in ports]
    key = bytes.fromhex(KEY) if keyed else None
    datagrams = [encode(Kind.COMMAND, i + 1, 0, 0, np.zeros(1, dtype=COMMAND_RECORD), key) for i in range(BOARDS)]
    seq_at, crc_at = struct.Struct("<I"), struct.Struct("<I")

    ticks = int(seconds * 1000)
    cpu = {"driver": [], "bare": []}
    ticker = Ticker(TimerfdTickSource(), 1_000_000)
    ticker.start(1_000_000)
    clock = robot.clock
    thread_time = time.thread_time_ns
    previous = thread_time()
    variant = "driver"
    try:
        for n in range(2 * ticks):
            k = await ticker.next()
            now = thread_time()
            if n:
                cpu[variant].append(now - previous)
            previous = now
            variant = "driver" if (n // block) % 2 == 0 else "bare"
            if variant == "driver":
                clock.tick, clock.now_ns = k, time.monotonic_ns()
                await driver.read()
                robot.command.position[:] = 0.1 * np.sin(k * 1e-3)
                await driver.write()
            else:
                # one sequence for both variants: a board takes only commands newer than its last
                seq = driver._seq = driver._seq + 1
                for data, addr in zip(datagrams, addresses, strict=True):
                    seq_at.pack_into(data, 16, seq)
                    if key is None:
                        crc_at.pack_into(data, 4, zlib.crc32(memoryview(data)[8:]))
                    else:  # the boards take only authenticated datagrams: the same MAC as the driver's
                        seal(data, len(data), key)
                    transport.sendto(data, addr)
    finally:
        ticker.close()
        transport.close()
        health = driver.health()
        await driver.close()
    # the first tick of each block carries the other variant's leftovers: drop it
    out = {}
    for name, values in cpu.items():
        trimmed = [v for i, v in enumerate(values) if i % block != 0]
        a = np.array(trimmed) / 1e3
        out[name] = {"ticks": len(a), "p50": round(float(np.percentile(a, 50)), 1),
                     "p99": round(float(np.percentile(a, 99)), 1), "mean": round(float(a.mean()), 1)}
    out["bare"]["replies"] = bare.count
    out["driver"]["health"] = health
    out["missed"] = ticker.missed
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="per variant")
    p.add_argument("--block", type=int, default=500)
    p.add_argument("--key", action="store_true", help="every datagram carries an HMAC (both variants seal theirs)")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    argv = [sys.executable, "-m", "aiohal.drivers.udp.sim", "--boards", str(BOARDS), "--priority", "70",
            "--watchdog-ms", "100000"]
    if args.key:
        argv += ["--key", KEY]
    sim = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ports = json.loads(sim.stdout.readline())["ports"]
        state = realtime.apply(realtime.RealtimeSection(priority=80))  # as the demo configs run
        try:
            result = asyncio.run(_run(ports, args.seconds, args.block, args.key))
        finally:
            realtime.restore(state)
    finally:
        sim.terminate()
        sim.wait(5)
    d, b = result["driver"], result["bare"]
    rows = [{"variant": name, **{k: result[name][k] for k in ("ticks", "p50", "p99", "mean")}} for name in ("driver", "bare")]
    print(table(rows, [("variant", "variant"), ("ticks", "ticks"), ("p50", "CPU/tick p50 µs"), ("p99", "p99 µs"), ("mean", "mean µs")]))
    ratio = d["p50"] / b["p50"]
    h = d["health"]
    print(f"driver/bare p50: {ratio:.3f}   driver: received {h['received']}, lost {h['lost']}, late {h['late']}; "
          f"bare replies {b['replies']}; missed deadlines {result['missed']}")
    write_json(args.json, {"machine": machine(), "seconds": args.seconds, "block": args.block, "key": args.key,
                           "ratio_p50": round(ratio, 3), **result})


if __name__ == "__main__":
    main()
