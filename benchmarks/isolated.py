"""The same tick code timed alone and inside the loop: why the number of calls matters.

One mock driver, the hold controller, 33 joints (or a shipped config with ``--config``, e.g.
``configs/walkman_sim.toml``: its first driver and its controller, on the virtual clock). Each part (driver read, hold update,
limiter) is timed in a tight loop of 20 000 calls, then the same parts are read from the
loop's per-phase statistics on the virtual clock (back to back: no waiting, only the event
loop's own work between ticks). The ratio is what the rest of the loop costs the tick's code.
Each part is also timed once after each of ``--sleep-calls`` sleeps of 0.9 ms (p50): what a
call costs on the real clock, where a tick starts with the caches cold after the wait.

    python -m benchmarks.isolated [--joints 33 | --config PATH] [--sleep-calls 2000] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import time
import tomllib
from pathlib import Path

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop

from .common import table, write_json


def arm(n: int) -> dict:
    return {
        "robot": {"name": f"mock{n}"},
        "loop": {"rate_hz": 1000, "clock": "virtual"},
        "joints": {f"j{i}": {"position": [-2.0, 2.0], "velocity": 2.0, "acceleration": 20.0, "effort": 50.0}
                   for i in range(n)},
        "driver": [{"type": "mock", "name": "arm", "joints": [f"j{i}" for i in range(n)]}],
        "controller": {"type": "hold"},
    }


def _time_us(fn, n: int = 20_000) -> float:
    t0 = time.perf_counter_ns()
    for _ in range(n):
        fn()
    return (time.perf_counter_ns() - t0) / n / 1e3


def _after_sleep_us(fn, n: int) -> float:
    """p50 of one call made after a 0.9 ms sleep, ``n`` times."""
    times = []
    for _ in range(n):
        time.sleep(0.0009)
        t0 = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t0)
    return statistics.median(times) / 1e3 if times else float("nan")


def _run_coroutine(factory):
    def call():
        coro = factory()
        try:
            coro.send(None)
        except StopIteration:
            pass
    return call


def from_config(path: str) -> tuple[dict, Path]:
    """A config as shipped, on the virtual clock and without its [realtime] settings."""
    raw = tomllib.loads(Path(path).read_text())
    raw.pop("realtime", None)
    raw.setdefault("loop", {})["clock"] = "virtual"
    return raw, Path(path).resolve().parent


async def measure(joints: int, sleep_calls: int = 2000, config: str | None = None) -> list[dict]:
    raw, base = from_config(config) if config else (arm(joints), None)
    loop = ControlLoop(parse_config(raw, base_dir=base))
    async with loop:
        report = await loop.run(ticks=5000)
        driver, clock = loop.slots[0].driver, loop.robot.clock

        def read_one_tick():  # advance the tick so the mock steps its dynamics, as in the loop
            clock.tick += 1
            _run_coroutine(driver.read)()

        parts = {
            "read": read_one_tick,
            "control": lambda: loop.controller.update(1.0, 0.001),
            "limits": loop.limiter.apply,
            "write": _run_coroutine(driver.write),
        }
        alone = {part: _time_us(fn) for part, fn in parts.items()}
        cold = {part: _after_sleep_us(fn, sleep_calls) for part, fn in parts.items()}
    phases = report["phases_us"]
    return [{"part": part, "alone_us": round(us, 2), "in_loop_us": phases[part]["p50"],
             "ratio": round(phases[part]["p50"] / us, 2), "after_sleep_us": round(cold[part], 2)}
            for part, us in alone.items()]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--joints", type=int, default=33)
    p.add_argument("--config", default=None, help="a robot config instead of the mock arm (first driver)")
    p.add_argument("--sleep-calls", type=int, default=2000, help="calls timed after a 0.9 ms sleep, per part")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    rows = asyncio.run(measure(args.joints, args.sleep_calls, args.config))
    print(table(rows, [("part", "part"), ("alone_us", "alone µs (mean of 20 000)"),
                       ("in_loop_us", "in the loop µs (p50, virtual clock)"), ("ratio", "ratio"),
                       ("after_sleep_us", "after a 0.9 ms sleep µs (p50)")]))
    write_json(args.json, {"joints": args.joints, "config": args.config, "rows": rows})


if __name__ == "__main__":
    main()
