"""The same tick code timed alone and inside the loop: why the number of calls matters.

One mock driver, the hold controller, 33 joints. Each part (driver read, hold update,
limiter) is timed in a tight loop of 20 000 calls, then the same parts are read from the
loop's per-phase statistics on the virtual clock (back to back: no waiting, only the event
loop's own work between ticks). The ratio is what the rest of the loop costs the tick's code.

    python -m benchmarks.isolated [--joints 33] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import time

from aiohal.config import parse_config
from aiohal.loop import ControlLoop

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


def _run_coroutine(factory):
    def call():
        coro = factory()
        try:
            coro.send(None)
        except StopIteration:
            pass
    return call


async def measure(joints: int) -> list[dict]:
    loop = ControlLoop(parse_config(arm(joints)))
    async with loop:
        report = await loop.run(ticks=5000)
        driver, clock = loop.slots[0].driver, loop.robot.clock

        def read_one_tick():  # advance the tick so the mock steps its dynamics, as in the loop
            clock.tick += 1
            _run_coroutine(driver.read)()

        alone = {
            "read": _time_us(read_one_tick),
            "control": _time_us(lambda: loop.controller.update(1.0, 0.001)),
            "limits": _time_us(loop.limiter.apply),
            "write": _time_us(_run_coroutine(driver.write)),
        }
    phases = report["phases_us"]
    return [{"part": part, "alone_us": round(us, 2), "in_loop_us": phases[part]["p50"],
             "ratio": round(phases[part]["p50"] / us, 2)} for part, us in alone.items()]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--joints", type=int, default=33)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    rows = asyncio.run(measure(args.joints))
    print(table(rows, [("part", "part"), ("alone_us", "alone µs (mean of 20 000)"),
                       ("in_loop_us", "in the loop µs (p50, virtual clock)"), ("ratio", "ratio")]))
    write_json(args.json, {"joints": args.joints, "rows": rows})


if __name__ == "__main__":
    main()
