"""Where a loop's deadlines fall against the kernel's periodic tick, and what that costs.

Linux fires its scheduler tick at whole multiples of 1e9 / HZ ns of CLOCK_MONOTONIC: whole
milliseconds for HZ = 100, 250 and 1000. A deadline there shares the CPU with the tick's
interrupt. This runs aiohal's timerfd tick source (asyncio, the IdleWait path; with
``--guard`` in precision mode, waking that much early and spinning) with its deadlines at
fixed phases past whole milliseconds, at a phase left to chance (how the Ticker started before
it placed its deadlines itself), and where the Ticker places them (:func:`aiohal.core.ticker.
off_the_kernel_tick`). The cases run in rounds, in an order that alternates, so a change of
the host's speed falls on every case alike. Per case: the share of ticks later than 5 µs and
the lateness percentiles over all rounds, and the range of the rounds' p99.

    python -m benchmarks.tick_phase [--rate 1000] [--guard 200] [--phases 0 100 250 500 750]
        [--rounds 4] [--ticks 2000] [--fifo] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import gzip
import os
import platform
import time

import numpy as np

from aiohal.core.ticker import KERNEL_TICK_GRID_NS, TimerfdTickSource, at_phase, off_the_kernel_tick

from .common import StealMeter, table, write_json

CHANCE, AIOHAL = "any", "aiohal"


def kernel_hz() -> str:
    """CONFIG_HZ of the running kernel, from /proc/config.gz or /boot if it has one, else '?'."""
    for path, opener in (("/proc/config.gz", gzip.open), (f"/boot/config-{platform.release()}", open)):
        try:
            with opener(path, "rt") as f:
                for line in f:
                    if line.startswith("CONFIG_HZ="):
                        return line.split("=", 1)[1].strip()
        except OSError:
            pass
    return "?"


def first_deadline(case: str | int, period_ns: int) -> int:
    """t0 of a round: the first deadline is one period from now, moved to the case's phase."""
    t = time.monotonic_ns() + period_ns
    if case == CHANCE:
        return t
    if case == AIOHAL:
        return off_the_kernel_tick(t, period_ns)
    return at_phase(t, int(case) * 1000)  # that many µs past a whole ms


async def one_round(t0: int, period_ns: int, guard_ns: int, ticks: int) -> tuple[np.ndarray, int]:
    """Lateness (ns) of ``ticks`` wakes of the source, and how many deadlines it skipped."""
    source = TimerfdTickSource(guard_ns)
    source.start(t0, period_ns)
    mono = time.monotonic_ns
    lateness = np.empty(ticks, dtype=np.int64)
    k = missed = 0
    try:
        for i in range(ticks):
            n = await source.wait()
            k += n
            missed += n - 1
            lateness[i] = mono() - (t0 + k * period_ns)
    finally:
        source.close()
    return lateness, missed


def phase_of(t0: int) -> float:
    return (t0 % KERNEL_TICK_GRID_NS) / 1e3


async def measure(cases: list, period_ns: int, guard_ns: int, rounds: int, ticks: int) -> dict:
    results = {case: {"lateness": [], "p99": [], "missed": 0, "phases": []} for case in cases}
    for r in range(rounds):
        for case in cases if r % 2 == 0 else cases[::-1]:
            t0 = first_deadline(case, period_ns)
            lateness, missed = await one_round(t0, period_ns, guard_ns, ticks)
            res = results[case]
            res["lateness"].append(lateness)
            res["p99"].append(float(np.percentile(lateness, 99)) / 1e3)
            res["missed"] += missed
            res["phases"].append(phase_of(t0))
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rate", type=float, default=1000.0, help="tick rate, Hz (default 1000)")
    p.add_argument("--guard", type=float, default=200.0, help="precision mode's spin guard, µs (0: plain timerfd wake)")
    p.add_argument("--phases", type=int, nargs="*", default=[0, 100, 250, 500, 750],
                   help="fixed phases to try, µs past a whole millisecond")
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--ticks", type=int, default=2000, help="ticks per case per round")
    p.add_argument("--fifo", action="store_true", help="run at SCHED_FIFO 80, as the shipped configs ask (root)")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    period_ns = round(1e9 / args.rate)
    guard_ns = round(args.guard * 1e3)
    if guard_ns * 2 > period_ns:
        p.error(f"--guard {args.guard:g} µs is more than half the period")
    if args.fifo:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
        except PermissionError:
            p.error("--fifo needs root (CAP_SYS_NICE)")
    cases = [CHANCE, *args.phases, AIOHAL]
    steal = StealMeter()
    gc.collect()
    gc.disable()  # each round allocates its array before its first tick, nothing after
    started = time.monotonic()
    try:
        results = asyncio.run(measure(cases, period_ns, guard_ns, max(1, args.rounds), args.ticks))
    finally:
        gc.enable()
    elapsed = time.monotonic() - started
    rows = []
    for case, res in results.items():
        lat = np.concatenate(res["lateness"]) / 1e3
        phases = sorted(round(x) for x in res["phases"])
        where = "any (as started)" if case == CHANCE else (f"{phases[0]} (aiohal's)" if case == AIOHAL else f"{case}")
        rows.append({
            "case": str(case), "phase": where, "ticks": int(lat.size),
            "late5": round(100 * float(np.mean(lat > 5.0)), 2),
            "p50": round(float(np.percentile(lat, 50)), 2), "p99": round(float(np.percentile(lat, 99)), 2),
            "p999": round(float(np.percentile(lat, 99.9)), 1),
            "p99_rounds": f"{min(res['p99']):.1f}–{max(res['p99']):.1f}", "missed": res["missed"],
            "round_phases_us": [round(x, 1) for x in res["phases"]],
        })
    mode = f"precision mode, spin guard {args.guard:g} µs" if guard_ns else "timerfd wake, no spin"
    print(f"{args.rate:g} Hz, {mode}, asyncio{', SCHED_FIFO 80' if args.fifo else ''}; kernel HZ {kernel_hz()}; "
          f"{args.rounds} rounds x {args.ticks} ticks per case, {elapsed:.0f} s, host steal {steal.percent():.1f} %")
    print(table(rows, [("phase", "deadlines, µs past a whole ms"), ("ticks", "ticks"), ("late5", "late > 5 µs %"),
                       ("p50", "lateness p50 µs"), ("p99", "p99 µs"), ("p999", "p99.9 µs"),
                       ("p99_rounds", "p99 of the rounds, µs"), ("missed", "deadlines skipped")]))
    write_json(args.json, {"benchmark": "tick_phase", "rate_hz": args.rate, "guard_us": args.guard,
                           "fifo": args.fifo, "kernel_hz": kernel_hz(), "rounds": args.rounds, "ticks": args.ticks,
                           "steal_percent": round(steal.percent(), 2), "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
