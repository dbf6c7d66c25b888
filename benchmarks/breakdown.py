"""Where the time of a tick goes (LOLA, Fig. 7): wake latency, read, check, control, limits,
write and publish, p50/p99, for the mock 33-joint humanoid at 1 kHz.

Configs: ``configs/mock_humanoid.toml`` (33 joints, 4 mock drivers with first-order dynamics,
IMU, 4 F/T sensors, 2 hands) with its controller replaced by ``hold``, and with its own
``sine``. Each is run twice, each run in a fresh process:

* real time: 1 kHz on the timerfd clock with the config's ``[realtime]`` settings (SCHED_FIFO
  80 + mlockall when permitted), for ``--seconds``. A bare timerfd loop (no work, same
  ``[realtime]`` settings) runs just before, in its own process, for as long: it is what the
  machine allows at that moment (host stalls on a shared VM) and its lateness is the floor of
  the wake latency;
* virtual clock: the same number of ticks back to back (warm caches, no waiting). Wake latency
  is 0 by construction there; instead the table gives the time spent between two ticks' work
  (ticker, the stats stores, the asyncio round trip), as wall time per tick minus mean work.

Both are measured after a warm-up run of ``--warmup`` seconds in the same process (first-tick
costs, and the sine's 1 s ramp-in, are left out). The per-phase times are what the loop itself
records (``ControlLoop.stats.phases``, rows in ``aiohal.core.tick_timing.PHASES`` order); "work" is the
whole tick from wake-up to the end of publish, which also holds the loop's own bookkeeping
between phases.

    python -m benchmarks.breakdown [--seconds 10] [--warmup 1] [--loop asyncio|uvloop] [--json PATH]

This module also holds the worker the other benchmarks start (``--worker`` reads a JSON spec
on stdin and prints one JSON result line): a ControlLoop built from a config dict, or a bare
timerfd loop.
"""

from __future__ import annotations

import argparse
import asyncio
import copy
import json
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

from .common import ROOT, table, write_json

HUMANOID = ROOT / "configs" / "mock_humanoid.toml"


# ---------------------------------------------------------------- shared: workers in fresh processes


def spawn(module: str, spec: dict, timeout: float) -> dict:
    """Run ``python -m MODULE --worker`` with ``spec`` (JSON on stdin) in a fresh process."""
    cmd = [sys.executable, "-m", module, "--worker"]
    proc = subprocess.run(cmd, cwd=ROOT, input=json.dumps(spec), capture_output=True, text=True, timeout=timeout)
    lines = proc.stdout.strip().splitlines()
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"{' '.join(cmd)} ({spec.get('kind')}) failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(lines[-1])


def load_raw(path: Path) -> dict:
    return tomllib.loads(path.read_text())


def loop_spec(raw: dict, *, base_dir: Path, clock: str, rate_hz: float, seconds: float, warmup: float,
              loop: str = "asyncio", controller: dict | None = None) -> dict:
    """A worker spec: run the config ``raw`` (a parsed TOML dict) with these overrides."""
    raw = copy.deepcopy(raw)
    raw.setdefault("loop", {})
    raw["loop"]["clock"] = clock
    raw["loop"]["rate_hz"] = rate_hz
    if controller is not None:
        raw["controller"] = controller
    return {
        "kind": "loop",
        "raw": raw,
        "base_dir": str(base_dir),
        "warmup_ticks": round(warmup * rate_hz),
        "ticks": max(1, round(seconds * rate_hz)),
        "loop": loop,
    }


def bare_spec(realtime: dict, rate_hz: float, seconds: float, loop: str = "asyncio") -> dict:
    return {"kind": "bare", "realtime": realtime, "rate_hz": rate_hz, "ticks": max(1, round(seconds * rate_hz)), "loop": loop}


def _runner(loop: str) -> asyncio.Runner:
    if loop == "uvloop":
        import uvloop

        return asyncio.Runner(loop_factory=uvloop.new_event_loop)
    return asyncio.Runner(loop_factory=asyncio.new_event_loop)


async def _run_loop(spec: dict) -> dict:
    import numpy as np

    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop
    from aiohal.core.tick_timing import PHASES

    config = parse_config(spec["raw"], base_dir=Path(spec["base_dir"]))
    control = ControlLoop(config)
    await control.activate()
    try:
        if spec.get("warmup_ticks"):
            await control.run(ticks=spec["warmup_ticks"])
        report = await control.run(ticks=spec["ticks"])
        stats = control.stats
        n = min(stats.count, stats.mask + 1)
        wall_ns = stats.stopped_wall_ns - stats.started_wall_ns
        work_mean = float(stats.work[:n].mean()) / 1e3 if n else float("nan")
        extra = {
            "wall_s": wall_ns / 1e9,
            # rusage over the ticks only (stats.begin/end): the gc.collect before the first tick is outside
            "cpu_s": report["cpu_percent"] / 100.0 * wall_ns / 1e9,
            "work_mean_us": round(work_mean, 3),
            "phase_mean_us": {name: round(float(stats.phases[i, :n].mean()) / 1e3, 3) for i, name in enumerate(PHASES)},
            "between_ticks_us": round(wall_ns / 1e3 / max(stats.count, 1) - work_mean, 3),
            "final_position": [float(x) for x in np.asarray(control.robot.state.position)],
        }
    finally:
        await control.deactivate()
    return {"report": report, **extra}


async def _run_bare(spec: dict) -> dict:
    """A timerfd loop with no work under the given [realtime] settings: lateness and missed deadlines."""
    import numpy as np

    from aiohal.core import realtime
    from aiohal.core.ticker import Ticker, TimerfdTickSource

    period = round(1e9 / spec["rate_hz"])
    n = spec["ticks"]
    lateness = np.full(n, 0, dtype=np.int64)  # written now: no page fault during the run
    state = realtime.apply(realtime.RealtimeSection(**spec.get("realtime", {})))
    ticker = Ticker(TimerfdTickSource(), period)
    mono = time.monotonic_ns
    i = 0
    try:
        ticker.start(period)
        while ticker.k < n:  # bounded by deadlines, like run(ticks=n)
            await ticker.next()
            lateness[i] = mono() - ticker.deadline_ns
            i += 1
    finally:
        ticker.close()
        realtime.restore(state)
    p50, p99 = np.percentile(lateness[:i], (50, 99)) / 1e3
    return {
        "ticks": i,
        "missed": ticker.missed,
        "lateness_p50_us": round(float(p50), 2),
        "lateness_p99_us": round(float(p99), 2),
        "lateness_max_us": round(float(lateness[:i].max()) / 1e3, 2),
        "realtime_warnings": state.warnings,
    }


def worker(spec: dict) -> dict:
    """Run one measurement described by ``spec`` in this (fresh) process."""
    kind = spec["kind"]
    with _runner(spec.get("loop", "asyncio")) as runner:
        if kind == "loop":
            return runner.run(_run_loop(spec))
        if kind == "bare":
            return runner.run(_run_bare(spec))
    raise ValueError(f"unknown worker kind {kind!r}")


def worker_main(fn=worker) -> None:
    print(json.dumps(fn(json.loads(sys.stdin.read()))), flush=True)


def timeout_for(seconds: float) -> float:
    return 120.0 + 5.0 * seconds


def r1(x: Any) -> Any:
    return round(x, 1) if isinstance(x, float) else x


# ---------------------------------------------------------------- the benchmark


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="measured seconds per run (default 10)")
    p.add_argument("--warmup", type=float, default=1.0, help="warm-up seconds before each measured run")
    p.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio")
    p.add_argument("--json", default=None)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        worker_main()
        return

    from aiohal.core.tick_timing import PHASES

    base = load_raw(HUMANOID)
    started = time.monotonic()
    runs = []
    for controller in ("hold", "sine"):
        ctrl = {"type": "hold"} if controller == "hold" else base["controller"]
        for clock in ("timerfd", "virtual"):
            bare = None
            if clock == "timerfd":
                bare = spawn("benchmarks.breakdown", bare_spec(base.get("realtime", {}), 1000.0, args.seconds, args.loop),
                             timeout_for(args.seconds))
            spec = loop_spec(base, base_dir=HUMANOID.parent, clock=clock, rate_hz=1000.0, seconds=args.seconds,
                             warmup=args.warmup, loop=args.loop, controller=ctrl)
            res = spawn("benchmarks.breakdown", spec, timeout_for(args.seconds))
            res["controller"], res["clock"], res["bare"] = controller, clock, bare
            runs.append(res)
            print(f"{controller} / {clock}: done", flush=True)
    elapsed = time.monotonic() - started

    # phases as rows, runs as columns (p50 | p99)
    cols = [("phase", "phase")]
    for i, run in enumerate(runs):
        tag = f"{run['controller']} {'real' if run['clock'] == 'timerfd' else 'virtual'}"
        cols += [(f"p50_{i}", f"{tag} p50 µs"), (f"p99_{i}", "p99 µs")]
    rows: list[dict] = []

    def add(label: str, get) -> None:
        row = {"phase": label}
        for i, run in enumerate(runs):
            p50, p99 = get(run)
            row[f"p50_{i}"], row[f"p99_{i}"] = r1(p50), r1(p99)
        rows.append(row)

    add("wake (lateness)", lambda r: (r["report"]["lateness_us"]["p50"], r["report"]["lateness_us"]["p99"])
        if r["clock"] == "timerfd" else ("–", "–"))
    add("wake, bare timerfd loop", lambda r: (r["bare"]["lateness_p50_us"], r["bare"]["lateness_p99_us"])
        if r["bare"] else ("–", "–"))
    for name in PHASES:
        add(name, lambda r, name=name: (r["report"]["phases_us"][name]["p50"], r["report"]["phases_us"][name]["p99"]))
    add("sum of the phases (p50s)", lambda r: (sum(r["report"]["phases_us"][n]["p50"] for n in PHASES), "–"))
    add("work (whole tick)", lambda r: (r["report"]["work_us"]["p50"], r["report"]["work_us"]["p99"]))
    add("between ticks, mean (virtual)", lambda r: (r["between_ticks_us"], "–") if r["clock"] == "virtual" else ("–", "–"))
    print()
    print("Per phase, mock humanoid (33 joints, 4 mock drivers) at 1 kHz:")
    print(table(rows, cols))

    summary = []
    for run in runs:
        rep, bare = run["report"], run["bare"] or {}
        summary.append({
            "controller": run["controller"], "clock": run["clock"], "ticks": rep["ticks"],
            "rate": rep["rate_hz_achieved"] if run["clock"] == "timerfd" else "–",
            "missed": rep["missed_ticks"], "bare_missed": bare.get("missed", "–"),
            "overruns": rep["overruns"], "work_mean": r1(run["work_mean_us"]), "cpu": rep["cpu_percent"],
            "faults": len(rep["faults"]),
            "rt": ", ".join(f"{k}={v}" for k, v in rep["realtime"].items() if k != "warnings") or "–",
        })
    print()
    print(table(summary, [
        ("controller", "controller"), ("clock", "clock"), ("ticks", "ticks"), ("rate", "rate Hz"),
        ("missed", "missed"), ("bare_missed", "bare loop missed"), ("overruns", "overruns"),
        ("work_mean", "work mean µs"), ("cpu", "CPU %"), ("faults", "faults"), ("rt", "realtime applied"),
    ]))

    drivers = []
    for name in runs[0]["report"]["drivers"]:
        row = {"driver": name, "joints": runs[0]["report"]["drivers"][name]["joints"]}
        for i, run in enumerate(runs):
            d = run["report"]["drivers"][name]
            row[f"r{i}"] = f"{d['read_us_mean']} / {d['write_us_mean']}"
        drivers.append(row)
    print()
    print("Driver read / write, mean µs per tick:")
    print(table(drivers, [("driver", "driver"), ("joints", "joints")] + [
        (f"r{i}", f"{run['controller']} {'real' if run['clock'] == 'timerfd' else 'virtual'}") for i, run in enumerate(runs)
    ]))
    print(f"\n{len(runs)} runs + {sum(1 for r in runs if r['bare'])} bare loops in {elapsed:.1f} s")
    for run in runs:
        run.pop("final_position", None)
    write_json(args.json, {"seconds": args.seconds, "warmup": args.warmup, "loop": args.loop,
                           "elapsed_s": round(elapsed, 1), "table": rows, "summary": summary, "runs": runs})


if __name__ == "__main__":
    main()
