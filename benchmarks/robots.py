"""Every shipped robot config at 1 kHz: the mock arm and humanoid, and the four simulated robots
of the R-HAL experiment: tick work, simulation speed, real-time rate, lateness, missed ticks.

For each config: a lockstep run (virtual clock, as fast as possible) gives the work per tick
and MuJoCo steps per second without waiting; a real-time run at 1 kHz (timerfd, the config's
[realtime] settings) gives the achieved rate, lateness and missed ticks. A bare timerfd loop
with no work (same SCHED_FIFO priority) runs before each real-time run, side by side, to show
what the machine itself allows at that moment (host stalls on a shared VM).

    python -m benchmarks.robots [--seconds 10] [--json PATH] [--only NAME ...]
"""

from __future__ import annotations

import argparse
import asyncio

from aiohal.core import realtime
from aiohal.core.ticker import Ticker, TimerfdTickSource

from .common import ROOT, run_cli, table, write_json

ROBOTS = ["mock_arm", "mock_humanoid", "kuka_lwr_sim", "centauro_upper_sim", "coman_sim", "walkman_sim"]


async def _bare(seconds: float) -> int:
    """Missed deadlines of a timerfd loop doing nothing, with the same SCHED_FIFO priority."""
    state = realtime.apply(realtime.RealtimeSection(priority=80))
    ticker = Ticker(TimerfdTickSource(), 1_000_000)
    ticker.start(1_000_000)
    try:
        while ticker.k < seconds * 1000:
            await ticker.next()
    finally:
        ticker.close()
        realtime.restore(state)
    return ticker.missed


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--json", default=None)
    p.add_argument("--only", nargs="*", default=None, help="config names to run (default: all)")
    args = p.parse_args()
    rows = []
    for name in args.only or ROBOTS:
        config = ROOT / "configs" / f"{name}.toml"
        lock = run_cli(config, "--duration", str(args.seconds), "--clock", "virtual")
        bare_missed = asyncio.run(_bare(args.seconds))
        real = run_cli(config, "--duration", str(args.seconds))
        sim = lock["drivers"].get("sim", {})
        rms = lock["controller"].get("rms_error_m")
        rt_rms = real["controller"].get("rms_error_m")
        rows.append({
            "robot": name,
            "joints": lock["joints"],
            "work_p50": lock["work_us"]["p50"],
            "work_p99": lock["work_us"]["p99"],
            "steps_per_s": sim.get("sim_steps_per_s", "-"),
            "rms_mm": round(rms * 1e3, 3) if rms is not None else "-",
            "rt_rate": real["rate_hz_achieved"],
            "rt_missed": real["missed_ticks"],
            "bare_missed": bare_missed,
            "rt_lat_p50": real["lateness_us"]["p50"],
            "rt_lat_p99": real["lateness_us"]["p99"],
            "rt_work_p50": real["work_us"]["p50"],
            "rt_work_p99": real["work_us"]["p99"],
            "rt_rms_mm": round(rt_rms * 1e3, 3) if rt_rms is not None else "-",
            "rt_cpu": real["cpu_percent"],
        })
        print(f"{name}: done", flush=True)
    print(table(rows, [
        ("robot", "robot"), ("joints", "joints"),
        ("work_p50", "lockstep work p50 µs"), ("work_p99", "p99 µs"), ("steps_per_s", "mj steps/s"),
        ("rms_mm", "RMS err mm"),
        ("rt_rate", "real-time rate Hz"), ("rt_missed", "missed"), ("bare_missed", "bare timerfd missed"),
        ("rt_lat_p50", "lateness p50 µs"), ("rt_lat_p99", "p99 µs"),
        ("rt_work_p50", "work p50 µs"), ("rt_work_p99", "p99 µs"), ("rt_rms_mm", "RMS err mm"), ("rt_cpu", "CPU %"),
    ]))
    write_json(args.json, {"seconds": args.seconds, "rows": rows})


if __name__ == "__main__":
    main()
