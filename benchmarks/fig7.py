"""R-HAL's Fig. 7 on the robots' own buses: the same ``circle`` on four robots, each through
the bus it really uses, all simulated: WALK-MAN and CENTAURO on the EtherCAT simulator (real
SOEM, needs root), COMAN on UDP joint boards (1 kHz), the KUKA LWR over FRI at 200 Hz.

For each robot, in a fresh process: the control period's mean and standard deviation (from
the wake-ups of successive ticks), missed ticks, the HAL process's CPU % of one core (R-HAL's
Table I figure; the simulators' own processes are not counted), the circle's RMS error, and
the run's faults. Without root the EtherCAT robots are skipped (said in the table).

    python -m benchmarks.fig7 [--seconds 10] [--json PATH] [--only coman_udp kuka_fri ...] [--figure PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tomllib

import numpy as np

from .common import ROOT, machine, table, write_json

COUNTS_PER_RAD = 131072 / (2 * 3.141592653589793)  # the drives' encoders, no gearbox
ROBOTS = {  # name: (config, bus)
    "walkman_ethercat": ("walkman_sim.toml", "EtherCAT (sim)"),
    "centauro_ethercat": ("centauro_upper_sim.toml", "EtherCAT (sim)"),
    "coman_udp": ("coman_udp_sim.toml", "UDP boards (sim)"),
    "kuka_fri": ("kuka_fri_sim.toml", "FRI 200 Hz (sim)"),
}


def ethercat_raw(config: str, ifname: str) -> dict:
    """A MuJoCo robot config turned into the same robot on an EtherCAT line of CiA 402 drives."""
    raw = tomllib.loads((ROOT / "configs" / config).read_text())
    raw["robot"]["model"] = str(ROOT / "configs" / raw["robot"]["model"])
    raw.pop("devices", None)
    joints = list(raw["joints"])
    slaves = [{"name": f"drive{i + 1}", "kind": "cia402", "joint": j, "product_code": 0x402} for i, j in enumerate(joints)]
    # the simulated drives have no gearbox and a 1 N·m motor: their effort limit is theirs
    for table_ in raw["joints"].values():
        table_["effort"] = 1.0
    raw["driver"] = [{"type": "ethercat", "name": "bus", "joints": joints,
                      "options": {"interface": ifname, "exchange": "split", "sync0": True, "slaves": slaves,
                                  "drive_defaults": {"counts_per_rev": 131072, "gear_ratio": 1.0, "rated_torque": 1.0}}}]
    return raw


async def _run(raw_or_path, seconds: float) -> dict:
    from aiohal import ControlLoop, load_config
    from aiohal.config import parse_config

    config = parse_config(raw_or_path) if isinstance(raw_or_path, dict) else load_config(raw_or_path)
    loop = ControlLoop(config)
    async with loop:
        report = await loop.run(duration=seconds)
        n = loop.stats.count
        window = min(n, loop.stats.lateness.size)
        lateness = np.roll(loop.stats.lateness, -(n % loop.stats.lateness.size))[-window:] if n > window else loop.stats.lateness[:n]
    period_ns = loop.period_ns
    periods = period_ns + np.diff(lateness.astype(np.float64))  # wake-up to wake-up of successive ticks
    final = loop.report()
    return {"report": report, "drivers": final["drivers"], "period_mean_us": round(float(periods.mean()) / 1e3, 3),
            "period_std_us": round(float(periods.std()) / 1e3, 3)}


def one(name: str, seconds: float) -> dict:
    config, bus = ROBOTS[name]
    if bus.startswith("EtherCAT"):
        from aiohal.drivers.ethercat.sim.fixture import SimulatedSegment

        mujoco_raw = tomllib.loads((ROOT / "configs" / config).read_text())
        joints = list(mujoco_raw["joints"])
        start = mujoco_raw["driver"][0]["options"].get("initial_position", {})
        with SimulatedSegment(f"drive*{len(joints)}", watchdog_ms=100) as sim:
            # the drives stand where the MuJoCo run starts (its "home" pose), in encoder counts
            for i, joint in enumerate(joints):
                sim.control({"cmd": "device", "slave": i, "position": round(start.get(joint, 0.0) * COUNTS_PER_RAD)})
            result = asyncio.run(_run(ethercat_raw(config, sim.ifname), seconds))
    else:
        result = asyncio.run(_run(ROOT / "configs" / config, seconds))
    report = result.pop("report")
    drivers = result.pop("drivers")
    driver = next(iter(drivers.values()))
    keep = ("sent", "received", "lost", "late", "malformed", "unauthenticated", "refused", "round_trip_us_p50",
            "krc_quality", "krc_answer_rate", "wkc_errors", "frames_lost", "cycles")
    return {"robot": name, "bus": bus, "joints": report["joints"], "rate_hz": report["rate_hz_target"], **result,
            "missed": report["missed_ticks"], "ticks": report["ticks"], "cpu_percent": report["cpu_percent"],
            "rms_error_mm": None if report["controller"].get("rms_error_m") is None else round(report["controller"]["rms_error_m"] * 1e3, 4),
            "faults": len(report["faults"]), "fault_list": [f"{f['source']}: {f['error']}" for f in report["faults"]][:3],
            "driver": {k: driver[k] for k in keep if k in driver}}


def figure(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ran = [r for r in rows if "period_mean_us" in r]
    names = [r["robot"].replace("_", "\n") for r in ran]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    axes[0].bar(names, [r["period_std_us"] for r in ran])
    axes[0].set_ylabel("control period std (µs)")
    axes[1].bar(names, [r["cpu_percent"] for r in ran])
    axes[1].set_ylabel("CPU % of one core")
    axes[2].bar(names, [r["rms_error_mm"] for r in ran])
    axes[2].set_ylabel("circle RMS error (mm)")
    for ax in axes:
        ax.tick_params(axis="x", labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--only", nargs="*", default=None)
    p.add_argument("--json", default=None)
    p.add_argument("--figure", default=None, help="write the figure here (needs the plot extra)")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)  # a single robot, in this process
    args = p.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.seconds)))
        return
    rows = []
    for name in args.only or list(ROBOTS):
        if ROBOTS[name][1].startswith("EtherCAT") and os.geteuid() != 0:
            rows.append({"robot": name, "bus": ROBOTS[name][1], "skipped": "needs root"})
            continue
        proc = subprocess.run([sys.executable, "-m", "benchmarks.fig7", "--one", name, "--seconds", str(args.seconds)],
                              cwd=ROOT, capture_output=True, text=True, timeout=args.seconds + 180)
        try:
            rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        except (IndexError, ValueError):
            rows.append({"robot": name, "bus": ROBOTS[name][1], "skipped": f"failed: {proc.stderr[-400:]}"})
        print(f"{name}: done", flush=True)
    print(table(rows, [("robot", "robot"), ("bus", "bus"), ("joints", "joints"), ("rate_hz", "Hz"),
                       ("period_mean_us", "period mean µs"), ("period_std_us", "std µs"), ("missed", "missed"),
                       ("cpu_percent", "CPU %"), ("rms_error_mm", "RMS err mm"), ("faults", "faults"), ("skipped", "note")]))
    write_json(args.json, {"machine": machine(), "seconds": args.seconds, "rows": rows})
    if args.figure:
        figure(rows, args.figure)


if __name__ == "__main__":
    main()
