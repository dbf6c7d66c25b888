"""What recording costs the tick: recording on and off side by side in one run.

One process, one ControlLoop on the real clock (configs/walkman_sim.toml: MuJoCo, 33 joints,
5 devices, the circle controller, SCHED_FIFO as configured), run for 2 × ``--seconds``: every
``--block`` seconds the recorder's publisher is attached or detached (between ticks), so the
ticks with and without recording alternate and a change of the host's speed enters both
sides alike. The recorder (thread, ring, file) lives through the whole run; the ticks of the
"on" blocks are all in the file (checked by reading it back: ``--seconds`` × rate ticks per
channel, none dropped). Printed: the tick's work p50/p99, lateness p99 and missed deadlines
of each side, and work p50 on − off.

With ``--plain`` the writer serializes every message with rosbags, one at a time, instead of
filling a batch (the recorder's plain path, for comparison).

    python -m benchmarks.record [--config configs/walkman_sim.toml] [--seconds 10] [--block 0.5]
        [--out /tmp/walkman.mcap] [--plain] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import time
from pathlib import Path

import numpy as np

from aiohal import ControlLoop, load_config
from aiohal.outside.recorder import Recorder
from aiohal.record import load

from .common import ROOT, table, write_json


async def measure(config_path: Path, seconds: float, block_s: float, out: Path, plain: bool = False) -> dict:
    config = load_config(config_path)
    control = ControlLoop(config)
    await control.activate()
    recorder = Recorder(control.port, out, config.record, plain=plain)
    recorder.attach()
    publish = recorder._publisher
    control.remove_publisher(publish)  # the run starts with recording off
    rate = 1e9 / control.period_ns
    blocks_per_side = round(seconds / block_s)
    ticks_per_block = round(block_s * rate)
    bounds: list[tuple[int, bool]] = []  # (stats index where a block starts, recording on)

    async def toggle() -> None:
        on = False
        for _ in range(2 * blocks_per_side):
            while control.state != "running":
                await asyncio.sleep(0.001)
            bounds.append((control.stats.count, on))
            target = control.stats.count + ticks_per_block
            while control.stats.count < target:
                await asyncio.sleep(0.0005)
            on = not on
            if on:
                control.add_publisher(publish)
            else:
                control.remove_publisher(publish)
        control.request_stop("benchmark done")

    toggler = asyncio.get_running_loop().create_task(toggle())
    report = await control.run(2 * seconds + 5)
    await toggler
    await control.deactivate()
    summary = recorder.close()
    stats = control.stats
    n = stats.count
    on_mask = np.zeros(n, dtype=bool)
    edges = [b for b, _ in bounds] + [n]
    for (start, on), end in zip(bounds, edges[1:], strict=True):
        # the first tick of a block runs with the previous setting (the toggle lands between ticks)
        on_mask[start + 1: end + 1] = on
    on_mask = on_mask[:n]
    off_mask = ~on_mask
    off_mask[: edges[0] + 1] = False  # the warm-up before the first block
    work, lateness = stats.work[:n] / 1e3, stats.lateness[:n] / 1e3
    rec = load(out)
    side = {}
    for name, mask in (("off", off_mask), ("on", on_mask)):
        side[name] = {"ticks": int(mask.sum()),
                      "work_p50_us": round(float(np.median(work[mask])), 2),
                      "work_p99_us": round(float(np.percentile(work[mask], 99)), 2),
                      "lateness_p99_us": round(float(np.percentile(lateness[mask], 99)), 2),
                      "publish_p50_us": round(float(np.median(stats.phases[5, :n][mask])) / 1e3, 2)}
    return {
        "config": str(config_path.relative_to(ROOT) if config_path.is_relative_to(ROOT) else config_path),
        "rate_hz": rate, "block_s": block_s, "seconds_per_side": seconds, "plain": plain,
        "sides": side,
        "work_p50_added_us": round(side["on"]["work_p50_us"] - side["off"]["work_p50_us"], 2),
        "missed_ticks_run": report["missed_ticks"],
        "recorded_ticks_per_channel": {t: len(s) for t, s in rec.series.items() if len(s) > 10},
        "dropped_ticks": summary["dropped_ticks"],
        "file_bytes": summary["bytes"],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=ROOT / "configs" / "walkman_sim.toml")
    p.add_argument("--seconds", type=float, default=10.0, help="recorded seconds (and as many unrecorded)")
    p.add_argument("--block", type=float, default=0.5, help="seconds per on or off block")
    p.add_argument("--out", type=Path, default=Path("/tmp/aiohal-record-bench.mcap"))
    p.add_argument("--plain", action="store_true", help="serialize each message with rosbags (the plain path)")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    t = time.monotonic()
    result = asyncio.run(measure(args.config.resolve(), args.seconds, args.block, args.out, args.plain))
    rows = [{"side": k, **v} for k, v in result["sides"].items()]
    print(table(rows, [("side", "recording"), ("ticks", "ticks"), ("work_p50_us", "work p50 µs"),
                       ("work_p99_us", "work p99 µs"), ("publish_p50_us", "publish p50 µs"),
                       ("lateness_p99_us", "lateness p99 µs")]))
    print(f"work p50 added by recording: {result['work_p50_added_us']} µs; missed deadlines in the run: "
          f"{result['missed_ticks_run']}; dropped: {result['dropped_ticks']}")
    print("ticks per channel in the file:", result["recorded_ticks_per_channel"])
    print(f"file: {args.out} ({result['file_bytes'] / 1e6:.1f} MB); {time.monotonic() - t:.0f} s")
    write_json(args.json, result)


if __name__ == "__main__":
    main()
