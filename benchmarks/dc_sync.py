"""Distributed clocks (LOLA's Fig. 8): each slave's SYNC0 error against the reference clock.

The ``ethercat`` driver brings up 7 drives on the simulated segment
(needs root), whose slaves' clocks drift apart by ``--drift-ppm`` (the first slave, the
reference clock, at -ppm/2, the last at +ppm/2, the others in between, from ``--seed``), with
SYNC0 on every drive, and runs the loop at 1 kHz for ``--seconds``. Twice: with the ESCs' drift
compensation (the driver's static compensation before SAFEOP, then the reference clock's time
in every cycle's frame), and with the ESCs' time control loops off (only config_dc's offsets
and delays). The errors come from the simulated clocks (``dc_trace``), sampled at each cycle's
frame: they do not depend on when the host ran the simulator.

    sudo python -m benchmarks.dc_sync [--seconds 10] [--drift-ppm 100] [--out /tmp/aiohal-dc-sync]

Writes ``dc_sync.json`` and ``dc_sync.png`` into ``--out``; prints, per case, the largest
error of any slave after lock (from the end of the bring-up on).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
import tomllib
from pathlib import Path

from benchmarks.common import machine
from benchmarks.ethercat import LINES, config_text

SLAVES = 7  # drive*7
PLOT_STEP = 10  # every 10th sample (about 10 ms) in the plot and the JSON


def run_case(seconds: float, drift_ppm: float, seed: int, compensation: bool) -> dict:
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop
    from aiohal.drivers.ethercat.sim.fixture import SimulatedSegment

    inject = [] if compensation else ["--inject", json.dumps({"cmd": "dc", "compensation": False})]
    args = ["--drift-ppm", str(drift_ppm), "--seed", str(seed), *inject]
    with SimulatedSegment(LINES[SLAVES], watchdog_ms=1000, extra_args=args) as sim:
        text = config_text(SLAVES, sim.ifname, 1000, "split").replace(
            "[driver.options]\n", "[driver.options]\nsync0 = true\ndc_lock = true\n"
        )
        raw = tomllib.loads(text)
        # a stall of this shared machine must not end the run: the errors are in the simulated
        # clocks' time, the loop's own stall and stale-feedback checks are not what is measured
        raw["loop"].update(stall_timeout_ms=5000, max_feedback_age=5000)
        raw.setdefault("safety", {})["max_tick_gap_ms"] = 5000

        async def run() -> tuple[int, dict]:
            async with ControlLoop(parse_config(raw)) as loop:
                locked = time.monotonic_ns()  # the bring-up (static compensation included) is done
                report = await loop.run(duration=seconds)
            return locked, report

        locked, report = asyncio.run(run())
        trace = sim.control({"cmd": "dc_trace", "step": PLOT_STEP}, timeout_s=30)
        after = sim.control({"cmd": "dc_trace", "since_ns": locked, "step": 1 << 30}, timeout_s=30)
        drifts = sim.control({"cmd": "status"})["slaves"]
    t0 = trace["t_ns"][0]
    worst = [w for w in after["worst_ns"] if w is not None]
    return {
        "compensation": compensation,
        "drift_ppm": [s["drift_ppm"] for s in drifts],
        "locked_s": (locked - t0) / 1e9,
        "worst_after_lock_ns": after["worst_ns"],
        "max_abs_after_lock_us": max(abs(w) for w in worst) / 1e3,
        "samples_after_lock": after["samples"],
        "ticks": report["ticks"],
        "wkc_errors": report["drivers"]["bus"].get("wkc_errors"),
        "faults": [str(f)[:300] for f in report["faults"]],
        "master_phase_error_us": report["drivers"]["bus"].get("dc_lock_error_us"),
        "t_s": [(t - t0) / 1e9 for t in trace["t_ns"]],
        "errors_ns": trace["errors_ns"],
    }


def plot(cases: list[dict], path: Path, drift_ppm: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, case in zip(axes, cases, strict=True):
        for k in range(1, SLAVES):
            series = [(t, e[k] / 1e3) for t, e in zip(case["t_s"], case["errors_ns"], strict=True) if e[k] is not None]
            if series:
                ax.plot(*zip(*series, strict=True), lw=0.8, label=f"slave {k} ({case['drift_ppm'][k]:+.0f} ppm)")
        ax.axvline(case["locked_s"], color="grey", ls=":", lw=0.8)
        what = "with drift compensation" if case["compensation"] else "without drift compensation"
        ax.set_title(f"{what}: after lock max |error| {case['max_abs_after_lock_us']:.3g} µs", fontsize=9)
        ax.set_xlabel("time (s); dotted: bring-up done")
        ax.set_ylabel("SYNC0 error against the reference clock (µs)")
        if case["compensation"]:
            ax.set_ylim(-2, 2)
            ax.axhspan(-1, 1, color="green", alpha=0.08)
    axes[1].legend(fontsize=7)
    fig.suptitle(
        f"Simulated segment, slaves' clocks {drift_ppm:g} ppm apart (reference: slave 0, {cases[0]['drift_ppm'][0]:+.0f} ppm)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--drift-ppm", type=float, default=100.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path("/tmp/aiohal-dc-sync"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cases = [run_case(args.seconds, args.drift_ppm, args.seed, compensation) for compensation in (True, False)]
    for case in cases:
        what = "with" if case["compensation"] else "without"
        print(
            f"{what:>7} drift compensation: max |SYNC0 error| after lock {case['max_abs_after_lock_us']:.3f} µs "
            f"(worst per slave, ns: {case['worst_after_lock_ns']}), {case['samples_after_lock']} samples, "
            f"{case['ticks']} ticks, {case['wkc_errors']} working-counter errors; the loop's deadlines against "
            f"the reference clock (dc_lock), |phase error| µs: {case['master_phase_error_us']}"
        )
    (args.out / "dc_sync.json").write_text(
        json.dumps({"machine": machine(), "args": {k: str(v) for k, v in vars(args).items()}, "cases": cases}) + "\n"
    )
    plot(cases, args.out / "dc_sync.png", args.drift_ppm)
    print(f"wrote {args.out / 'dc_sync.json'} and {args.out / 'dc_sync.png'}")


if __name__ == "__main__":
    main()
