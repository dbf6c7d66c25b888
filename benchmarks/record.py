"""What the outputs cost the tick: outputs on and off side by side in one run.

One process, one ControlLoop on the real clock (configs/walkman_sim.toml: MuJoCo, 33 joints,
5 devices, the circle controller, SCHED_FIFO as configured), run for 2 × ``--seconds``: every
``--block`` seconds the tick ring's publisher (the tick's whole share of every output) and the
event feeds (health sampled on the event loop) are attached or detached between ticks, so the
ticks with and without outputs alternate and a change of the host's speed enters both sides
alike. The output processes live through the whole run and read the ring at their own pace;
the ticks of the "on" blocks are all in the file (checked by reading it back).

Outputs on: the recording (``--out``). With ``--all``, also the live Foxglove server with a
WebSocket client subscribed to every channel (another process), the terminal panel (drawn
into /dev/null) and the Zenoh bridge with a ROS 2-style subscriber (examples/zenoh_monitor.py).
Printed: the tick's work p50/p99, lateness p99 (over all ticks of a side, and the median over
blocks of each block's p99) and missed deadlines of each side.

With ``--plain`` the writer serializes every message with rosbags, one at a time, instead of
filling a batch (the recorder's plain path, for comparison).

With ``--toggle ring`` (or ``feed``) the blocks switch only the ring's publisher (or only the
event feed) and the other stays off for the whole run: what each costs the tick on its own.
Each side's work is also given per phase of the tick (p50, p99).

With ``--neighbour`` no output runs: the blocks toggle a plain busy loop (``while True: pass``,
nice 5, on the CPUs the outputs would use) between stopped and running. It measures what any
work beside the tick costs it on this machine (shared caches, memory, the hypervisor's
scheduling of the vCPUs), to compare with what the outputs cost.

    python -m benchmarks.record [--config configs/walkman_sim.toml] [--seconds 10] [--block 0.5]
        [--out /tmp/walkman.mcap] [--all] [--plain] [--neighbour] [--toggle both|ring|feed] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from aiohal import ControlLoop, load_config
from aiohal.core.tick_timing import PHASES
from aiohal.outside.recorder import Recorder
from aiohal.outside.terminal_status import StatusPanel
from aiohal.record import load

from .common import ROOT, table, write_json


def side_figures(stats, mask: np.ndarray, blocks: list[tuple[int, int]]) -> dict:
    n = len(mask)
    work, lateness = stats.work[:n] / 1e3, stats.lateness[:n] / 1e3
    phases = {name: stats.phases[i, :n][mask] / 1e3 for i, name in enumerate(PHASES)}
    block_p99 = [float(np.percentile(lateness[a:b][mask[a:b]], 99)) for a, b in blocks if mask[a:b].any()]
    block_work = [float(np.percentile(work[a:b][mask[a:b]], 99)) for a, b in blocks if mask[a:b].any()]
    return {
        "ticks": int(mask.sum()),
        "work_p50_us": round(float(np.median(work[mask])), 2),
        "work_p99_us": round(float(np.percentile(work[mask], 99)), 2),
        "lateness_p99_us": round(float(np.percentile(lateness[mask], 99)), 2),
        "block_lateness_p99_median_us": round(float(np.median(block_p99)), 2),
        "block_work_p99_median_us": round(float(np.median(block_work)), 2),
        "publish_p50_us": round(float(np.median(phases["publish"])), 2),
        "phase_p50_us": {name: round(float(np.median(v)), 2) for name, v in phases.items()},
        "phase_p99_us": {name: round(float(np.percentile(v, 99)), 2) for name, v in phases.items()},
    }


def start_neighbour(avoid_cpus: list[int] | None) -> subprocess.Popen:
    """A stopped busy loop where the output processes would run (off the tick's CPUs, nice 5)."""
    others = sorted(set(os.sched_getaffinity(0)) - set(avoid_cpus or [])) or sorted(os.sched_getaffinity(0))
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"],
                           preexec_fn=lambda: (os.sched_setaffinity(0, others), os.nice(5)))
    hog.send_signal(signal.SIGSTOP)
    return hog


async def measure(config_path: Path, seconds: float, block_s: float, out: Path, plain: bool = False,
                  every: bool = False, cpus: list[int] | None = None, neighbour: bool = False,
                  switched: str = "both") -> dict:
    config = load_config(config_path)
    if cpus:  # the tick on these CPUs, the output processes on the others
        config = dataclasses.replace(config, realtime=config.realtime.model_copy(update={"cpus": cpus}))
    if every:
        from aiohal.outside.options import BridgeSection, ZenohBridgeSection

        from .zenoh_bridge import free_port

        zport = free_port()
        config = dataclasses.replace(config, bridge=BridgeSection(
            zenoh=ZenohBridgeSection(listen=[f"tcp/127.0.0.1:{zport}"], connect=[])))
    control = ControlLoop(config)
    await control.activate()
    port = control.port
    hog = start_neighbour(config.realtime.cpus) if neighbour else None
    recorder = None if neighbour else Recorder(port, out, config.record, plain=plain)
    if recorder is not None:
        recorder.attach()
    live = status = client = monitor = None
    if every:
        live = Recorder(port, None, config.record, live_port=0)
        live.attach()
        status = StatusPanel(port, config.record.buffer_ticks, terminal="/dev/null")
        status.start()
        client = subprocess.Popen([sys.executable, "-m", "benchmarks.record", "--foxglove-client", str(live.live_port),
                                   "--seconds", str(2 * seconds + 30)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
        monitor = subprocess.Popen([sys.executable, str(ROOT / "examples" / "zenoh_monitor.py"),
                                    "--connect", f"tcp/127.0.0.1:{zport}", "--listen", f"tcp/127.0.0.1:{free_port()}",
                                    "--seconds", str(2 * seconds), "--wait", "30"], cwd=ROOT,
                                   stdout=subprocess.PIPE, text=True)
    bridge = control.doors.zenoh if control.doors is not None else None
    if hog is None:
        publish = port.tick_door.publish  # the tick's whole share of every output
        feed = port.event_feed  # one for every output process: health sampled on the event loop
        feed.stop()
        control.remove_publisher(publish)  # the run starts with the outputs off
    rate = 1e9 / control.period_ns
    blocks_per_side = round(seconds / block_s)
    ticks_per_block = round(block_s * rate)
    bounds: list[tuple[int, bool]] = []  # (stats index where a block starts, outputs on)
    missed = {"off": 0, "on": 0}  # deadlines missed in each side's blocks

    def switch(on: bool) -> None:
        if hog is not None:
            hog.send_signal(signal.SIGCONT if on else signal.SIGSTOP)
            return
        if switched != "feed":
            control.add_publisher(publish) if on else control.remove_publisher(publish)
        if switched != "ring":
            feed.start() if on else feed.stop()

    async def toggle() -> None:
        on = False
        await asyncio.sleep(3.0 if every else 0.5)  # clients connect, caches warm
        for _ in range(2 * blocks_per_side):
            while control.state != "running":
                await asyncio.sleep(0.001)
            bounds.append((control.stats.count, on))
            before = control.missed_ticks
            target = control.stats.count + ticks_per_block
            while control.stats.count < target:
                await asyncio.sleep(0.0005)
            missed["on" if on else "off"] += control.missed_ticks - before
            on = not on
            switch(on)
        control.request_stop("benchmark done")

    toggler = asyncio.get_running_loop().create_task(toggle())
    try:
        report = await control.run(2 * seconds + 30)
        await toggler
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    publish = None  # its views of the ring go before the ring's segment closes
    await control.deactivate()
    summary = recorder.close() if recorder is not None else {"dropped_ticks": 0, "bytes": 0}
    extra: dict = {}
    if every:
        extra["live"] = live.close()
        status.stop()
        extra["status_panel"] = status.cost()
        for name, proc in (("foxglove_client", client), ("zenoh_monitor", monitor)):
            if name == "foxglove_client":
                proc.terminate()
            try:
                text, _ = proc.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                text, _ = proc.communicate()
            extra[name] = text.strip().splitlines()[-1] if text.strip() else ""
        if bridge is not None:
            extra["zenoh_bridge"] = dict(bridge.counters)  # given by its process at close
    stats = control.stats
    n = stats.count
    on_mask = np.zeros(n, dtype=bool)
    edges = [b for b, _ in bounds] + [n]
    for (start, on), end in zip(bounds, edges[1:], strict=True):
        # the first tick of a block runs with the previous setting (the switch lands between ticks)
        on_mask[start + 1: end + 1] = on
    on_mask = on_mask[:n]
    off_mask = ~on_mask
    off_mask[: edges[0] + 1] = False  # the warm-up before the first block
    blocks = list(itertools.pairwise(edges))
    side = {name: {**side_figures(stats, mask, blocks), "missed": missed[name]}
            for name, mask in (("off", off_mask), ("on", on_mask))}
    rec = load(out) if recorder is not None else None
    outputs = "recording, Foxglove + client, panel, Zenoh bridge + subscriber" if every else "recording"
    return {
        "config": str(config_path.relative_to(ROOT) if config_path.is_relative_to(ROOT) else config_path),
        "outputs": "none; a busy loop beside the tick" if hog is not None else outputs,
        "rate_hz": rate, "cpus": cpus, "block_s": block_s, "seconds_per_side": seconds, "plain": plain,
        "toggled": "a busy loop" if hog is not None else {"both": "ring and feed", "ring": "ring only (feed off)",
                                                          "feed": "feed only (ring off)"}[switched],
        "sides": side,
        "work_p50_added_us": round(side["on"]["work_p50_us"] - side["off"]["work_p50_us"], 2),
        "missed_ticks_run": report["missed_ticks"],
        "recorded_ticks_per_channel": {t: len(s) for t, s in rec.series.items() if len(s) > 10} if rec else {},
        "dropped_ticks": summary["dropped_ticks"],
        "file_bytes": summary["bytes"],
        **extra,
    }


def foxglove_client(port: int, seconds: float) -> None:
    """Subscribe to every channel of the live server; print how many messages came."""
    import websockets

    async def main() -> int:
        got = 0
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
            end = time.monotonic() + seconds
            subscribed: set[int] = set()
            while time.monotonic() < end:
                try:
                    frame = await asyncio.wait_for(ws.recv(), 1.0)
                except TimeoutError:
                    continue
                if isinstance(frame, bytes):
                    got += 1
                    if got % 1000 == 0:
                        print(f"foxglove client: {got} messages on {len(subscribed)} channels", flush=True)
                    continue
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    new = [c["id"] for c in msg["channels"] if c["id"] not in subscribed]
                    subscribed.update(new)
                    await ws.send(json.dumps({"op": "subscribe",
                                              "subscriptions": [{"id": i, "channelId": i} for i in new]}))
                print(f"foxglove client: {got} messages on {len(subscribed)} channels", flush=True)
        return got

    try:
        asyncio.run(main())
    except (KeyboardInterrupt, Exception):
        pass


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=ROOT / "configs" / "walkman_sim.toml")
    p.add_argument("--seconds", type=float, default=10.0, help="seconds with outputs on (and as many off)")
    p.add_argument("--block", type=float, default=0.5, help="seconds per on or off block")
    p.add_argument("--out", type=Path, default=Path("/tmp/aiohal-record-bench.mcap"))
    p.add_argument("--all", action="store_true", help="every output on: recording, Foxglove, panel, Zenoh")
    p.add_argument("--cpus", type=lambda v: [int(c) for c in v.split(",") if c], default=[1],
                   help="pin the tick to these CPUs ([realtime] cpus; the outputs keep off them); '' for none")
    p.add_argument("--plain", action="store_true", help="serialize each message with rosbags (the plain path)")
    p.add_argument("--neighbour", action="store_true",
                   help="no outputs: toggle a busy loop on the outputs' CPUs instead (what any neighbour costs)")
    p.add_argument("--toggle", choices=("both", "ring", "feed"), default="both",
                   help="what the blocks switch: the tick ring's publisher and the event feed (both), or one of "
                        "them with the other off for the whole run (what each costs)")
    p.add_argument("--foxglove-client", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    if args.foxglove_client is not None:
        foxglove_client(args.foxglove_client, args.seconds)
        return
    t = time.monotonic()
    result = asyncio.run(measure(args.config.resolve(), args.seconds, args.block, args.out, args.plain, args.all,
                                 args.cpus, args.neighbour, args.toggle))
    rows = [{"side": k, **v} for k, v in result["sides"].items()]
    print(f"outputs: {result['outputs']}; toggled: {result['toggled']}")
    print(table(rows, [("side", "outputs"), ("ticks", "ticks"), ("work_p50_us", "work p50 µs"),
                       ("work_p99_us", "work p99 µs"), ("block_work_p99_median_us", "work p99 µs (block median)"),
                       ("publish_p50_us", "publish p50 µs"), ("lateness_p99_us", "lateness p99 µs"),
                       ("block_lateness_p99_median_us", "lateness p99 µs (block median)"),
                       ("missed", "missed deadlines")]))
    print(table([{"side": k, **{f"{name}": f"{v['phase_p50_us'][name]:.1f} / {v['phase_p99_us'][name]:.1f}"
                                for name in PHASES}} for k, v in result["sides"].items()],
                [("side", "outputs")] + [(name, f"{name} p50 / p99 µs") for name in PHASES]))
    cause = "the busy neighbour" if args.neighbour else "the outputs"
    print(f"work p50 added by {cause}: {result['work_p50_added_us']} µs; missed deadlines in the run: "
          f"{result['missed_ticks_run']}; recorder dropped: {result['dropped_ticks']}")
    print("ticks per channel in the file:", result["recorded_ticks_per_channel"])
    for key in ("live", "status_panel", "foxglove_client", "zenoh_monitor", "zenoh_bridge"):
        if key in result:
            print(f"{key}: {result[key]}")
    print(f"file: {args.out} ({result['file_bytes'] / 1e6:.1f} MB); {time.monotonic() - t:.0f} s")
    write_json(args.json, result)


if __name__ == "__main__":
    main()
