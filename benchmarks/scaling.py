"""How the tick scales: work per tick against the number of joints and of drivers, and the
highest tick rate the mock 33-joint humanoid sustains.

1. Joints: 7, 33, 100, 300, 1000 joints on one mock driver (mirror dynamics), controller
   ``hold``, every joint with position, velocity, acceleration and effort limits (the config
   is built in-process like ``tests/helpers.arm_raw``). Work per tick p50/p99 (the report's
   ``work_us``) on the virtual clock (pure work, back to back) and on the real clock at 1 kHz
   (timerfd) for ``--rt-seconds``. Virtual runs are repeated ``--repeat`` times (fresh
   processes) and the medians shown: on a shared VM one run's p50 can be 1.5× another's. The
   ratio work(1000 joints)/work(7 joints) is measured side by side: every joint count's loop
   in one process, run in turn ``--chunk`` ticks at a time for ``--rounds`` rounds (the order
   alternating), so each round's ratio compares ticks measured milliseconds apart and a change
   of the host's speed between runs does not enter it; the median over the rounds is shown.
2. Drivers: 1, 2, 4, 8 mock drivers sharing 32 joints (32, 16, 8, 4 joints each), same setup.
3. Highest rate: ``configs/mock_humanoid.toml`` (33 joints, 4 mock drivers, devices) with
   ``hold``, on the timerfd clock at 1, 2, 4, 5, 8, 10, 16, 20 kHz for ``--sweep-seconds``
   each: achieved rate, missed ticks, lateness p99, work p99. A rate is *sustained* when the
   missed ticks are at most 0.1 % of the deadlines and lateness p99 + work p99 < the period.
   A bare timerfd loop (no work, same ``[realtime]`` settings) runs before each rate in its
   own process, for the same time: what the machine allows at that moment.

Every run is a fresh process, measured after a warm-up run of ``--warmup`` seconds in the
same process. Real-time runs use SCHED_FIFO ``--priority`` (default 80, like the shipped
configs) and mlockall where permitted; ``--priority 0`` runs at normal priority. Near and past
saturation (work ≥ period) a SCHED_FIFO loop runs flat out: the kernel's RT throttling then
stops it for 50 ms of every second, which the figures of those rates include; each run is
bounded by its deadline count, and the stall watchdog ends a run after 500 ms without a tick.

    python -m benchmarks.scaling [--seconds 5] [--rt-seconds 3] [--sweep-seconds 3]
        [--repeat 3] [--rounds 40] [--chunk 500] [--rates 1000 2000 ...] [--no-bare] [--priority 80]
        [--loop asyncio|uvloop] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import time

import numpy as np

from .breakdown import HUMANOID, bare_spec, load_raw, loop_spec, r1, spawn, timeout_for, worker, worker_main
from .common import ROOT, table, write_json

JOINTS = (7, 33, 100, 300, 1000)
DRIVERS = (1, 2, 4, 8)
RATES = (1000, 2000, 4000, 5000, 8000, 10_000, 16_000, 20_000)
MODULE = "benchmarks.scaling"


def robot_raw(joints: int, drivers: int = 1, priority: int = 0) -> dict:
    """``joints`` joints with limits, split evenly over ``drivers`` mock drivers, controller hold."""
    if joints % drivers:
        raise ValueError(f"{joints} joints do not split over {drivers} drivers")
    names = [f"j{i}" for i in range(joints)]
    per = joints // drivers
    raw: dict = {
        "robot": {"name": f"scale_{joints}j_{drivers}d"},
        "loop": {"rate_hz": 1000},
        "joints": {n: {"position": [-2.0, 2.0], "velocity": 2.0, "acceleration": 20.0, "effort": 50.0} for n in names},
        "driver": [{"type": "mock", "name": f"bus{k}", "joints": names[k * per:(k + 1) * per]} for k in range(drivers)],
        "controller": {"type": "hold"},
    }
    if priority:
        raw["realtime"] = {"priority": priority, "lock_memory": True}
    return raw


def _median_report(runs: list[dict]) -> dict:
    """The figures the tables use, each the median over repeated virtual runs."""
    reps = [r["report"] for r in runs]
    med = statistics.median
    return {
        "work_us": {k: med(r["work_us"][k] for r in reps) for k in ("p50", "p99")},
        "phases_us": {ph: {"p50": med(r["phases_us"][ph]["p50"] for r in reps)} for ph in reps[0]["phases_us"]},
        "faults": [f for r in reps for f in r["faults"]],
        "work_p50_runs": [r["work_us"]["p50"] for r in reps],
    }


def _pair(raw: dict, args: argparse.Namespace) -> tuple[dict, dict]:
    """(virtual, real-time 1 kHz) results for one built config; virtual: medians of --repeat runs."""
    virtual = [spawn(MODULE, loop_spec(raw, base_dir=ROOT, clock="virtual", rate_hz=1000.0, seconds=args.seconds,
                                       warmup=args.warmup, loop=args.loop), timeout_for(args.seconds))
               for _ in range(max(1, args.repeat))]
    real = spawn(MODULE, loop_spec(raw, base_dir=ROOT, clock="timerfd", rate_hz=1000.0, seconds=args.rt_seconds,
                                   warmup=args.warmup, loop=args.loop), timeout_for(args.rt_seconds))
    return {"report": _median_report(virtual)}, real


async def _side_by_side(spec: dict) -> dict:
    """Work p50 per round of every joint count's loop, all in this process on the virtual
    clock, run in turn ``chunk`` ticks at a time (the order alternating each round)."""
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop
    from aiohal.core.ticker import VirtualTickSource

    loops = {n: ControlLoop(parse_config(robot_raw(n)), tick_source=VirtualTickSource()) for n in spec["joints"]}
    work = {n: [] for n in loops}
    try:
        for control in loops.values():
            await control.activate()
            await control.run(ticks=spec["warmup_ticks"])
        order = list(loops)
        for r in range(spec["rounds"]):
            for n in order if r % 2 == 0 else order[::-1]:
                report = await loops[n].run(ticks=spec["chunk"])  # its statistics are this run's ticks
                work[n].append(report["work_us"]["p50"])
    finally:
        for control in loops.values():
            await control.deactivate()
    return {"work_p50_rounds": {str(n): w for n, w in work.items()}}


def scaling_worker(spec: dict) -> dict:
    if spec["kind"] == "side_by_side":
        return asyncio.run(_side_by_side(spec))
    return worker(spec)


def side_by_side_ratio(args: argparse.Namespace) -> dict:
    """work(1000)/work(7) per round of a side-by-side run: median and quartiles over the rounds."""
    spec = {"kind": "side_by_side", "joints": list(JOINTS), "rounds": max(2, args.rounds), "chunk": args.chunk,
            "warmup_ticks": round(args.warmup * 1000)}
    rounds = spawn(MODULE, spec, timeout_for(len(JOINTS) * args.rounds * args.chunk / 1000))["work_p50_rounds"]
    ratios = np.array(rounds[str(JOINTS[-1])]) / np.array(rounds[str(JOINTS[0])])
    q25, q50, q75 = (round(float(np.percentile(ratios, q)), 2) for q in (25, 50, 75))
    return {"ratio": q50, "p25": q25, "p75": q75, "rounds": len(ratios), "chunk": args.chunk,
            "work_p50": {n: round(statistics.median(w), 2) for n, w in rounds.items()}}


def _check(result: dict, what: str) -> None:
    faults = result["report"]["faults"]
    if faults:
        print(f"warning: {what}: {len(faults)} fault(s): {faults[0]}", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=5.0, help="virtual-clock ticks, in seconds at 1 kHz (default 5)")
    p.add_argument("--rt-seconds", type=float, default=3.0, help="real-time seconds per joints/drivers run (default 3)")
    p.add_argument("--sweep-seconds", type=float, default=3.0, help="seconds per rate of the sweep (default 3)")
    p.add_argument("--warmup", type=float, default=0.5, help="warm-up seconds before each measured run")
    p.add_argument("--repeat", type=int, default=3, help="virtual-clock runs per config; medians are shown (default 3)")
    p.add_argument("--rounds", type=int, default=40, help="rounds of the side-by-side ratio (default 40)")
    p.add_argument("--chunk", type=int, default=500, help="ticks per loop per round of the side-by-side ratio (default 500)")
    p.add_argument("--rates", type=float, nargs="*", default=list(RATES))
    p.add_argument("--no-bare", action="store_true", help="skip the bare timerfd loop beside each rate")
    p.add_argument("--priority", type=int, default=80, help="SCHED_FIFO priority of real-time runs (0: normal)")
    p.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio")
    p.add_argument("--json", default=None)
    p.add_argument("--worker", action="store_true", help="(internal) run one measurement: JSON spec on stdin")
    args = p.parse_args()
    if args.worker:
        worker_main(scaling_worker)
        return
    started = time.monotonic()

    # 1. joints
    joint_rows = []
    for n in JOINTS:
        virtual, real = _pair(robot_raw(n, 1, args.priority), args)
        _check(virtual, f"{n} joints virtual")
        _check(real, f"{n} joints real")
        v, r = virtual["report"], real["report"]
        joint_rows.append({
            "joints": n,
            "v_p50": v["work_us"]["p50"], "v_p99": v["work_us"]["p99"],
            "v_read": v["phases_us"]["read"]["p50"], "v_control": v["phases_us"]["control"]["p50"],
            "v_limits": v["phases_us"]["limits"]["p50"], "v_write": v["phases_us"]["write"]["p50"],
            "ns_per_joint": round(v["work_us"]["p50"] * 1e3 / n), "v_runs": v["work_p50_runs"],
            "r_p50": r["work_us"]["p50"], "r_p99": r["work_us"]["p99"],
            "r_lat_p99": r["lateness_us"]["p99"], "r_missed": r["missed_ticks"], "r_rate": r["rate_hz_achieved"],
        })
        print(f"{n} joints: done", flush=True)
    side = side_by_side_ratio(args)

    # 2. drivers
    driver_rows = []
    for k in DRIVERS:
        virtual, real = _pair(robot_raw(32, k, args.priority), args)
        _check(virtual, f"{k} drivers virtual")
        _check(real, f"{k} drivers real")
        v, r = virtual["report"], real["report"]
        driver_rows.append({
            "drivers": k, "per": 32 // k,
            "v_p50": v["work_us"]["p50"], "v_p99": v["work_us"]["p99"],
            "v_read": v["phases_us"]["read"]["p50"], "v_write": v["phases_us"]["write"]["p50"],
            "r_p50": r["work_us"]["p50"], "r_p99": r["work_us"]["p99"],
            "r_lat_p99": r["lateness_us"]["p99"], "r_missed": r["missed_ticks"],
        })
        print(f"{k} drivers: done", flush=True)

    # 3. highest sustained rate
    humanoid = load_raw(HUMANOID)
    rt = dict(humanoid.get("realtime", {}))
    if args.priority:
        rt["priority"] = args.priority
    else:
        rt.pop("priority", None)
    humanoid["realtime"] = rt
    rate_rows = []
    for rate in args.rates:
        bare = None
        if not args.no_bare:
            bare = spawn(MODULE, bare_spec(rt, rate, args.sweep_seconds, args.loop), timeout_for(args.sweep_seconds))
        res = spawn(MODULE, loop_spec(humanoid, base_dir=HUMANOID.parent, clock="timerfd", rate_hz=rate,
                                      seconds=args.sweep_seconds, warmup=min(args.warmup, 0.2), loop=args.loop,
                                      controller={"type": "hold"}), timeout_for(args.sweep_seconds))
        _check(res, f"{rate:g} Hz")
        rep = res["report"]
        period_us = 1e6 / rate
        deadlines = round(args.sweep_seconds * rate)
        missed_pct = 100.0 * rep["missed_ticks"] / deadlines
        budget = rep["lateness_us"]["p99"] + rep["work_us"]["p99"]
        sustained = missed_pct <= 0.1 and budget < period_us and not rep["faults"]
        rate_rows.append({
            "rate": int(rate), "period": r1(period_us), "achieved": rep["rate_hz_achieved"],
            "ticks": rep["ticks"], "missed": rep["missed_ticks"], "missed_pct": round(missed_pct, 3),
            "lat_p99": rep["lateness_us"]["p99"], "work_p50": rep["work_us"]["p50"], "work_p99": rep["work_us"]["p99"],
            "budget": r1(budget), "cpu": rep["cpu_percent"],
            "bare_missed": bare["missed"] if bare else "–", "bare_lat_p99": bare["lateness_p99_us"] if bare else "–",
            "bare_ok": ("yes" if 100.0 * bare["missed"] / deadlines <= 0.1 else "no") if bare else "–",
            "sustained": "yes" if sustained else "no",
        })
        print(f"{rate:g} Hz: {'sustained' if sustained else 'not sustained'}", flush=True)
    elapsed = time.monotonic() - started

    print()
    print(f"Work per tick against joints (one mock driver, hold), µs; virtual: median of {args.repeat} runs:")
    print(table(joint_rows, [
        ("joints", "joints"), ("v_p50", "virtual work p50"), ("v_p99", "p99"), ("v_read", "read p50"),
        ("v_control", "control p50"), ("v_limits", "limits p50"), ("v_write", "write p50"),
        ("ns_per_joint", "ns/joint (p50)"),
        ("r_p50", "1 kHz work p50"), ("r_p99", "p99"), ("r_lat_p99", "lateness p99"), ("r_missed", "missed"),
    ]))
    by_n = {row["joints"]: row for row in joint_rows}
    ratio_v = round(by_n[1000]["v_p50"] / by_n[7]["v_p50"], 2)
    ratio_r = round(by_n[1000]["r_p50"] / by_n[7]["r_p50"], 2)
    print(f"\nwork(1000 joints) / work(7 joints), p50: side by side in one process {side['ratio']} "
          f"(p25–p75 {side['p25']}–{side['p75']} over {side['rounds']} rounds of {side['chunk']} ticks; work p50 "
          + ", ".join(f"{n} joints {w} µs" for n, w in side["work_p50"].items())
          + f"); from the separate runs above: virtual {ratio_v}, 1 kHz {ratio_r}")

    print()
    print(f"Work per tick against drivers (32 joints, hold), µs; virtual: median of {args.repeat} runs:")
    print(table(driver_rows, [
        ("drivers", "drivers"), ("per", "joints each"), ("v_p50", "virtual work p50"), ("v_p99", "p99"),
        ("v_read", "read p50"), ("v_write", "write p50"),
        ("r_p50", "1 kHz work p50"), ("r_p99", "p99"), ("r_lat_p99", "lateness p99"), ("r_missed", "missed"),
    ]))
    slope = None
    if len(driver_rows) > 1:
        first, last = driver_rows[0], driver_rows[-1]
        slope = round((last["v_p50"] - first["v_p50"]) / (last["drivers"] - first["drivers"]), 2)
        print(f"\nvirtual work p50 per extra driver: {slope} µs")

    print()
    print(f"Mock humanoid (33 joints, 4 drivers, hold) on timerfd, {args.sweep_seconds:g} s per rate:")
    print(table(rate_rows, [
        ("rate", "rate Hz"), ("period", "period µs"), ("achieved", "achieved Hz"), ("ticks", "ticks"),
        ("missed", "missed"), ("missed_pct", "missed %"), ("lat_p99", "lateness p99 µs"),
        ("work_p50", "work p50 µs"), ("work_p99", "work p99 µs"), ("budget", "lateness+work p99 µs"),
        ("cpu", "CPU %"), ("bare_missed", "bare loop missed"), ("bare_lat_p99", "bare lateness p99 µs"),
        ("bare_ok", "bare loop ≤ 0.1 % missed"), ("sustained", "sustained"),
    ]))
    best = max((row["rate"] for row in rate_rows if row["sustained"] == "yes"), default=None)
    print(f"\nhighest sustained rate: {best if best is not None else 'none'} Hz"
          " (missed ≤ 0.1 % and lateness p99 + work p99 < period)")
    print(f"elapsed {elapsed:.1f} s")
    write_json(args.json, {
        "seconds": args.seconds, "rt_seconds": args.rt_seconds, "sweep_seconds": args.sweep_seconds,
        "warmup": args.warmup, "repeat": args.repeat, "priority": args.priority, "loop": args.loop, "elapsed_s": round(elapsed, 1),
        "joints": joint_rows,
        "work_ratio_1000_over_7": {"side_by_side": side, "virtual": ratio_v, "realtime": ratio_r},
        "drivers": driver_rows, "virtual_us_per_extra_driver": slope,
        "rates": rate_rows, "highest_sustained_hz": best,
    })


if __name__ == "__main__":
    main()
