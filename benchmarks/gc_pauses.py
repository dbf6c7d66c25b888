"""Garbage-collector pauses inside the tick, with ``[loop] gc = "default"`` against ``"freeze"``.

A collection that runs inside a tick delays it: a full collection of a process that has
loaded MuJoCo and pydantic scans tens of thousands of objects. ``freeze`` (the default)
collects once and freezes the start-up heap before the drivers open (then, with the drivers
open, only the young generations before the first tick), so later collections scan only what
the run itself allocated. Each run is a fresh process at 1 kHz on the real clock
with the config's [realtime] settings; gc callbacks time every collection during the run.

    python -m benchmarks.gc_pauses [--seconds 10] [--json PATH]
"""

from __future__ import annotations

import argparse
import gc
import time

from .breakdown import _runner, load_raw, loop_spec, spawn, timeout_for
from .common import ROOT, table, write_json

CONFIGS = ["mock_humanoid", "walkman_sim"]


async def _run(spec: dict) -> dict:
    from pathlib import Path

    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop

    control = ControlLoop(parse_config(spec["raw"], base_dir=Path(spec["base_dir"])))
    pauses: list[tuple[int, float]] = []  # collections once ticking has begun
    before_open_ms: list[float] = []  # freeze's full collection, in activate() before open()
    before_tick_ms: list[float] = []  # run()'s young collection, with the drivers open
    started: list[tuple[int, str]] = []
    stage = "before_open"

    def on_gc(phase: str, info: dict) -> None:
        if phase == "start":
            started.append((time.perf_counter_ns(), "ticking" if control.stats.count > 0 else stage))
        elif started:
            t0, when = started.pop()
            us = (time.perf_counter_ns() - t0) / 1e3
            if when == "ticking":
                pauses.append((info["generation"], us))
            else:
                (before_open_ms if when == "before_open" else before_tick_ms).append(us / 1e3)

    control.configure()
    driver = control.slots[0].driver
    opened = driver.open

    async def open_and_mark() -> None:
        nonlocal stage
        stage = "drivers_open"
        await opened()

    driver.open = open_and_mark
    gc.callbacks.append(on_gc)
    try:
        await control.activate()
        report = await control.run(ticks=spec["ticks"])
    finally:
        gc.callbacks.remove(on_gc)
        await control.deactivate()
    return {
        "freeze_collect_ms": round(sum(before_open_ms), 1),
        "open_collect_ms": round(sum(before_tick_ms), 2),
        "collections": [sum(1 for g, _ in pauses if g == gen) for gen in range(3)],
        "pause_max_us": round(max((d for _, d in pauses), default=0.0), 1),
        "pause_total_ms": round(sum(d for _, d in pauses) / 1e3, 2),
        "missed": report["missed_ticks"],
        "rate": report["rate_hz_achieved"],
        "lateness_p999": report["lateness_us"]["p999"],
        "lateness_max": report["lateness_us"]["max"],
        "work_max": report["work_us"]["max"],
    }


def worker(spec: dict) -> dict:
    with _runner("asyncio") as runner:
        return runner.run(_run(spec))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--json", default=None)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        from .breakdown import worker_main

        worker_main(worker)
        return
    rows = []
    for name in CONFIGS:
        raw = load_raw(ROOT / "configs" / f"{name}.toml")
        for mode in ("default", "freeze"):
            raw.setdefault("loop", {})["gc"] = mode
            spec = loop_spec(raw, base_dir=ROOT / "configs", clock="timerfd", rate_hz=1000.0,
                             seconds=args.seconds, warmup=0.0)
            result = spawn("benchmarks.gc_pauses", spec, timeout_for(args.seconds))
            rows.append({"config": name, "gc": mode, **result})
            print(f"{name} gc={mode}: done", flush=True)
    print(table(rows, [
        ("config", "config"), ("gc", "gc"), ("freeze_collect_ms", "freeze collect ms"),
        ("open_collect_ms", "drivers open collect ms"),
        ("collections", "collections gen0/1/2"),
        ("pause_max_us", "longest pause µs"), ("pause_total_ms", "total ms"), ("missed", "missed ticks"),
        ("rate", "rate Hz"), ("lateness_p999", "lateness p99.9 µs"), ("lateness_max", "max µs"), ("work_max", "work max µs"),
    ]))
    write_json(args.json, {"seconds": args.seconds, "rows": rows})


if __name__ == "__main__":
    main()
