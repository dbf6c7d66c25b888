"""The canopen driver's CPU per cycle against bare python-can doing the same frames, side by side.

Two virtual CAN channels in this process, each with six simulated CiA 402 drives and the
simulated sensor gateway (an IMU and an F/T sensor): on one, the ``canopen`` driver (opened
as the loop opens it, with the arm config's nodes and sensors); on the other, bare
python-can: the same six RPDOs and SYNC sent from prebuilt messages, the TPDOs and sensor
frames taken by a ``can.Notifier`` listener into a buffer, and each TPDO unpacked with one
``struct`` call per drive (the least a master can do with them). Cycles alternate between the
two, so both see the same host.

Per cycle: the CPU time of the master's own thread (``time.thread_time_ns``) in its write
(RPDOs + SYNC) and, once the drives answered, in its read (the driver: decode, state
machines, sensors; bare: the unpack); the receiving threads' work is not in either figure
(both receive in a notifier thread). And the latency from SYNC sent to the last TPDO of the
cycle received (the drives answer from canopen's notifier thread of the simulated bus).

    python -m benchmarks.canopen [--cycles 5000] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import struct
import time
from pathlib import Path

import can
import numpy as np

from aiohal.config import parse_config
from aiohal.drivers.canopen.sim import SimBus

CONFIG = "configs/canopen_arm_sim.toml"
NODES = range(1, 7)
PERIOD_NS = 2_000_000


def arm_raw(channel: str) -> dict:
    import tomllib

    with open(CONFIG, "rb") as f:
        raw = tomllib.load(f)
    options = raw["driver"][0]["options"]
    options.update(channel=channel, simulate=False)
    raw["driver"][0]["every"] = 1
    raw["loop"]["rate_hz"] = 500
    return raw


class Bare:
    """Bare python-can: the same frames, the least work."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.rpdos = [can.Message(arbitration_id=0x200 + n, data=bytearray(7), is_extended_id=False) for n in NODES]
        self.sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
        self.frames: dict[int, bytes] = {}
        self.tpdos = 0
        self.last_tpdo_s = 0.0
        self.unpack = struct.Struct("<Hih").unpack_from
        self.state = np.zeros((3, len(NODES)))
        tpdo_ids = {0x180 + n for n in NODES}

        bare = self

        class Listener(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                bare.frames[msg.arbitration_id] = msg.data
                if msg.arbitration_id in tpdo_ids:
                    bare.tpdos += 1
                    bare.last_tpdo_s = time.perf_counter()

        self.notifier = can.Notifier(self.bus, [Listener()], timeout=0.05)

    def write(self) -> None:
        send = self.bus.send
        for msg in self.rpdos:
            msg.data[0] = 0x0F
            send(msg, 0)
        send(self.sync, 0)

    def read(self) -> None:
        frames, unpack, state = self.frames, self.unpack, self.state
        for i, n in enumerate(NODES):
            data = frames.get(0x180 + n)
            if data is not None:
                status, position, torque = unpack(data)
                state[0, i] = position
                state[1, i] = torque
                state[2, i] = status

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


def enable_bare(bare: Bare, sim: SimBus) -> None:
    """NMT start, then walk the simulated drives to Operation enabled (0x06, 0x07, 0x0F)."""
    start = can.Message(arbitration_id=0, data=bytes([0x01, 0]), is_extended_id=False)
    bare.bus.send(start)
    time.sleep(0.05)
    for word in (0x06, 0x07, 0x0F):
        for msg in bare.rpdos:
            msg.data[:] = struct.pack("<Hib", word, 0, 8)
            bare.bus.send(msg)
        bare.bus.send(bare.sync)
        time.sleep(0.01)


async def one_cycle(write, read, received, last_tpdo, deadline_s: float = 0.02) -> tuple[int, float, bool]:
    """One master's cycle: its write, the six TPDOs awaited (outside the figure), its read.
    (thread CPU ns of write + read, SYNC to last TPDO in s, whether a TPDO was missing)."""
    cpu_now = time.thread_time_ns
    seen = received()
    c0 = cpu_now()
    await write()
    c1 = cpu_now()
    sent = time.perf_counter()
    until = sent + deadline_s
    while received() - seen < 6 and time.perf_counter() < until:
        time.sleep(50e-6)
    missing = received() - seen < 6
    latency = last_tpdo() - sent
    c2 = cpu_now()
    await read()
    return (cpu_now() - c2) + (c1 - c0), latency, missing


async def run(cycles: int) -> dict:
    pid = os.getpid()
    ch_driver, ch_bare = f"bench-canopen-driver-{pid}", f"bench-canopen-bare-{pid}"
    sim_driver = SimBus("virtual", ch_driver, list(NODES), sensors={"imu": 0.004, "force_torque": 0.004})
    sim_bare = SimBus("virtual", ch_bare, list(NODES), sensors={"imu": 0.004, "force_torque": 0.004})
    config = parse_config(arm_raw(ch_driver), base_dir=Path(CONFIG).parent)
    robot = config.build_robot()
    dc = config.drivers[0]
    view = robot.driver_view(dc.joints, dc.devices)
    driver = dc.cls(dc.name, view, dc.options)
    await driver.open()
    bare = Bare(ch_bare)
    enable_bare(bare, sim_bare)
    tpdo_times: list[float] = []
    for node in driver.remotes:
        driver.network.subscribe(0x180 + node.id, lambda *_: tpdo_times.append(time.perf_counter()))
    cpu = np.zeros((2, cycles), dtype=np.int64)  # driver, bare: write + read, thread CPU ns
    latency = np.zeros((2, cycles))
    clock = robot.clock
    late = [0, 0]

    async def driver_write() -> None:
        await driver.write()

    async def driver_read() -> None:
        await driver.read()

    async def bare_write() -> None:
        bare.write()

    async def bare_read() -> None:
        bare.read()

    sides = ((driver_write, driver_read, lambda: driver.rx_tpdos, lambda: tpdo_times[-1] if tpdo_times else np.nan),
             (bare_write, bare_read, lambda: bare.tpdos, lambda: bare.last_tpdo_s))
    try:
        for k in range(cycles):
            clock.tick, clock.now_ns = k, time.monotonic_ns()
            for i, (write, read, received, last_tpdo) in enumerate(sides):  # the driver, then bare python-can
                cpu[i, k], latency[i, k], missing = await one_cycle(write, read, received, last_tpdo)
                late[i] += missing
    finally:
        health = driver.health()
        await driver.close()
        bare.close()
        sim_driver.close()
        sim_bare.close()
    skip = min(100, cycles // 10)  # warm-up
    out = {"cycles": cycles, "late": {"driver": late[0], "bare": late[1]}, "driver_health": health}
    for i, name in enumerate(("driver", "bare")):
        c = cpu[i, skip:] / 1e3
        lat = latency[i, skip:] * 1e6
        lat = lat[np.isfinite(lat) & (lat > 0)]
        out[name] = {"cpu_us": {p: round(float(np.percentile(c, q)), 1) for p, q in (("p50", 50), ("p99", 99))},
                     "sync_to_last_tpdo_us": {p: round(float(np.percentile(lat, q)), 1)
                                              for p, q in (("p50", 50), ("p99", 99))}}
    out["ratio_p50"] = round(out["driver"]["cpu_us"]["p50"] / out["bare"]["cpu_us"]["p50"], 2)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=5000)
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args(argv)
    result = asyncio.run(run(args.cycles))
    print(f"canopen driver vs bare python-can, 6 drives + IMU + F/T, {result['cycles']} cycles side by side")
    print(f"  {'':8} {'CPU/cycle p50':>14} {'p99':>8}   {'SYNC->last TPDO p50':>20} {'p99':>8}")
    for name in ("driver", "bare"):
        r = result[name]
        print(f"  {name:8} {r['cpu_us']['p50']:>11.1f} µs {r['cpu_us']['p99']:>6.1f} µs   "
              f"{r['sync_to_last_tpdo_us']['p50']:>17.1f} µs {r['sync_to_last_tpdo_us']['p99']:>6.1f} µs")
    print(f"  driver / bare CPU p50: {result['ratio_p50']}   late cycles: {result['late']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
