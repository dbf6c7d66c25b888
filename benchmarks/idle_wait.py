"""What waiting on the timer itself saves: aiohal's loop with ``[loop] idle_wait`` on and off,
side by side in one process.

One ``ControlLoop`` on the real clock (timerfd, 1 kHz; or in lockstep with ``--clock virtual``,
where ``idle_wait`` decides whether the virtual clock's periodic yield skips an idle loop)
runs ``--rounds`` rounds of ``--ticks`` ticks, switching its tick source's ``idle_wait`` between
rounds (which goes first alternates),
so each pair of rounds is measured a few hundred milliseconds apart and a change of the
host's speed between processes does not enter the comparison. Per round: CPU per tick
(process CPU over the round, the wait included), lateness and work p50 from the loop's own
statistics, and how the waits went. The config's ``[realtime]`` section is dropped unless
``--realtime`` (then SCHED_FIFO and mlockall need root).

    python -m benchmarks.idle_wait [--config configs/mock_humanoid.toml] [--controller hold]
        [--rounds 10] [--ticks 1000] [--loop asyncio] [--clock timerfd|virtual] [--realtime] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tomllib
from pathlib import Path

from .common import ROOT, table, write_json


async def _rounds(config, rounds: int, ticks: int) -> list[dict]:
    from aiohal.core.loop import ControlLoop

    rows = []
    async with ControlLoop(config) as control:
        await control.run(ticks=ticks // 2)  # warm-up
        for r in range(rounds):
            for idle_wait in ((True, False) if r % 2 == 0 else (False, True)):
                control.source.idle_wait = idle_wait
                report = await control.run(ticks=ticks)
                stats = control.stats
                wall_s = (stats.stopped_wall_ns - stats.started_wall_ns) / 1e9
                rows.append({
                    "round": r, "idle_wait": idle_wait,
                    "cpu_us": report["cpu_percent"] / 100 * wall_s / report["ticks"] * 1e6,
                    "lateness_p50": report["lateness_us"]["p50"], "lateness_p99": report["lateness_us"]["p99"],
                    "work_p50": report["work_us"]["p50"], "missed": report["missed_ticks"],
                    **report.get("waits", {}),
                })
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=ROOT / "configs" / "mock_humanoid.toml")
    p.add_argument("--controller", default="hold", help="controller type to run (default hold; 'config' keeps the config's)")
    p.add_argument("--rounds", type=int, default=10)
    p.add_argument("--ticks", type=int, default=1000, help="ticks per round and setting")
    p.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio")
    p.add_argument("--clock", choices=("timerfd", "virtual"), default="timerfd")
    p.add_argument("--realtime", action="store_true", help="keep the config's [realtime] settings")
    p.add_argument("--json", default=None)
    args = p.parse_args()

    from aiohal.config import parse_config

    raw = tomllib.loads(args.config.read_text())
    raw.setdefault("loop", {}).update(clock=args.clock, rate_hz=1000.0)
    if args.controller != "config":
        raw["controller"] = {"type": args.controller}
    if not args.realtime:
        raw.pop("realtime", None)
    config = parse_config(raw, base_dir=args.config.parent, path=args.config)
    if args.loop == "uvloop":
        import uvloop

        rows = uvloop.run(_rounds(config, args.rounds, args.ticks))
    else:
        rows = asyncio.run(_rounds(config, args.rounds, args.ticks))

    summary = []
    for idle_wait in (True, False):
        mine = [r for r in rows if r["idle_wait"] is idle_wait]
        summary.append({
            "setting": f"idle_wait = {str(idle_wait).lower()}",
            **{key: round(statistics.median(r[key] for r in mine), 1)
               for key in ("cpu_us", "lateness_p50", "lateness_p99", "work_p50")},
            "missed": sum(r["missed"] for r in mine),
            "on_timer": sum(r.get("on_timer", 0) for r in mine), "through_loop": sum(r.get("through_loop", 0) for r in mine),
        })
    by_round = {(r["round"], r["idle_wait"]): r["cpu_us"] for r in rows}
    saved = sorted(by_round[r, False] - by_round[r, True] for r in range(args.rounds))
    print(f"{args.config.name}, controller {args.controller}, {args.loop}, {args.clock} clock, 1 kHz, "
          f"{args.rounds} rounds of {args.ticks} ticks per setting, alternating; medians over the rounds:")
    print(table(summary, [("setting", "setting"), ("cpu_us", "CPU µs/tick"), ("lateness_p50", "lateness p50 µs"),
                          ("lateness_p99", "p99 µs"), ("work_p50", "work p50 µs"), ("missed", "missed"),
                          ("on_timer", "waits on the timer"), ("through_loop", "waits round the loop")]))
    print(f"\nCPU saved per tick, pair by pair: median {statistics.median(saved):.1f} µs "
          f"(min {saved[0]:.1f}, max {saved[-1]:.1f})")
    write_json(args.json, {"config": str(args.config), "controller": args.controller, "loop": args.loop, "clock": args.clock,
                           "rounds": rows, "summary": summary})


if __name__ == "__main__":
    main()
