"""LOLA's Table III, Fig. 6 and Fig. 9 in simulation: the hip flexion joint's tracking error
while walking, without and with the learned velocity feed-forward, and with a 2 kHz bus.

``configs/lola_hip_sim.toml``: the ``gait`` controller (a hip flexion at 2.7 km/h, a stride of
1.2 s; target position, target velocity and model torque feed-forward) on the mock driver's
simulated servo drive (``aiohal.simulation.servo``), in lockstep, through the HAL's real path (read,
controller, extrapolation, feed-forward, limits, write). Runs:

* ``ref``: controller and bus at 1 kHz, k_e = 0 (k_vel,ff = 1: the target velocity as is);
* ``ff``: the same with k_e learned by LOLA's policy at 1 kHz (``aiohal.learn_feedforward``);
* ``ff_2khz``: loop and bus at 2 kHz, the controller at 1 kHz (``[controller] every = 2``,
  targets extrapolated in between), k_e learned by the same policy in that configuration.

The error is the target position of a tick against the position measured at that tick, RMS
over 3 strides after a ramp-in and a settling stride. Fig. 6 is the cost (that RMS) over a
sweep of k_e, with the points the policy visited; Fig. 9 the three error traces.

With ``--ethercat`` (root) the same three runs and learnings go through real SOEM to the
simulated EtherCAT segment (a veth pair in a namespace of its own), its one drive running the
same servo model (``--dynamics servo`` with the config's parameters) behind RxPDO 0x1602, so
the target velocity and torque feed-forward travel as 0x60B1/0x60B2 in the drive's units.
That runs on the real clock (about a minute; no sweep, Fig. 6 shows the policy's windows).

    python -m benchmarks.lola_tracking [--json out.json] [--figures DIR] [--ethercat]
"""

from __future__ import annotations

import argparse
import asyncio
import time
from dataclasses import replace

import numpy as np

from .common import ROOT, write_json

CONFIG = ROOT / "configs" / "lola_hip_sim.toml"
STRIDES = 3  # measured strides per run


class EthercatBus:
    """The simulated segment with one servo drive, and the config that drives it through SOEM."""

    COUNTS_PER_REV = 131072

    def __init__(self) -> None:
        import json
        import tomllib

        from aiohal.drivers.ethercat.sim.fixture import SimulatedSegment

        self.raw = tomllib.loads(CONFIG.read_text())
        self.servo = self.raw["driver"][0]["options"]["servo"]
        self.start = float(self.raw["driver"][0]["options"]["initial_position"])
        self.segment = SimulatedSegment(
            "drive", watchdog_ms=100, extra_args=["--dynamics", "servo", "--servo-json", json.dumps(self.servo)]
        )

    def __enter__(self) -> EthercatBus:
        self.segment.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.segment.__exit__(*exc)

    def power_cycle(self) -> None:
        """Each run starts as the lockstep one does: the drive disabled, the joint at rest at
        the config's initial position."""
        counts = self.start * self.servo["gear_ratio"] * self.COUNTS_PER_REV / (2 * np.pi)
        self.segment.control({"cmd": "power_cycle"})
        self.segment.control({"cmd": "device", "slave": 0, "position": counts})

    def config(self, rate_hz: float):
        from aiohal.config import parse_config

        raw = {key: value for key, value in self.raw.items() if key != "driver"}
        raw["loop"] = {**raw["loop"], "rate_hz": rate_hz}
        raw["loop"].pop("clock", None)
        raw["realtime"] = {"priority": 80, "lock_memory": True}
        raw["driver"] = [{
            "type": "ethercat",
            "name": "bus",
            "joints": ["hip_flexion"],
            "options": {
                "interface": self.segment.ifname,
                "drive_defaults": {"counts_per_rev": self.COUNTS_PER_REV, "gear_ratio": self.servo["gear_ratio"],
                                   "rated_torque": 1.0},
                "slaves": [{"name": "hip", "kind": "cia402", "joint": "hip_flexion", "rx_pdos": {"0x1602": []}}],
            },
        }]
        return parse_config(raw, base_dir=CONFIG.parent)


def configure(rate_hz: float, every: int, k_e: float | None, bus: EthercatBus | None = None):
    from aiohal.config import load_config
    from aiohal.core.feedforward import FeedforwardSection

    if bus is None:
        config = load_config(CONFIG).with_loop(rate_hz=rate_hz, clock="virtual")
    else:
        bus.power_cycle()
        config = bus.config(rate_hz)
    config = replace(config, controller=replace(config.controller, every=every))
    section = config.feedforward.model_copy(update={"k_e": k_e, "gains": None}) if k_e is not None else \
        FeedforwardSection(**{**config.feedforward.model_dump(), "k_e": None, "gains": None})
    return replace(config, feedforward=section)


async def tracking_run(rate_hz: float, every: int, k_e: float | None, bus: EthercatBus | None = None) -> dict:
    """One run: the error of every tick after the settling time, and its RMS."""
    from aiohal import ControlLoop

    config = configure(rate_hz, every, k_e, bus)
    loop = ControlLoop(config)
    period = config.controller.params.period
    settle = config.controller.params.ramp + period
    ticks = round((settle + STRIDES * period) * rate_hz)
    times = np.zeros(ticks + 1)
    measured = np.zeros(ticks + 1)
    count = [0]

    def record(control) -> None:
        i = count[0]
        if i < len(times):
            times[i] = control.robot.clock.tick * control.period_s
            measured[i] = control.robot.state.position[0]
            count[0] = i + 1

    async with loop:
        loop.add_publisher(record)
        report = await loop.run(duration=ticks / rate_hz)
        # the controller's time is the tick's since activation (tick 0 at t = 0)
        target, _ = loop.controller.reference(times[: count[0]])
    t = times[: count[0]]
    error = target[:, 0] - measured[: count[0]]
    keep = t >= settle
    # the target of a tick against the position read one tick later (on a bus whose slaves
    # answer with the inputs of the cycle before, that is the position at the target's time)
    next_tick = (np.round(np.diff(t) * rate_hz) == 1) & keep[:-1]
    error_next = target[:-1, 0][next_tick] - measured[1 : count[0]][next_tick]
    return {"t": t[keep] - settle, "error": error[keep], "rms": float(np.sqrt(np.mean(error[keep] ** 2))),
            "rms_one_tick_later": float(np.sqrt(np.mean(error_next**2))),
            "faults": report["faults"], "refused": report["commands_refused"],
            "missed_ticks": report["missed_ticks"], "controller_rms": report["controller"].get("tracking_rms_rad")}


async def learn_gain(rate_hz: float, every: int, bus: EthercatBus | None = None):
    from aiohal.learn_feedforward import learn

    learner, report = await learn(configure(rate_hz, every, None, bus))
    if report["faults"] or learner.best is None:
        raise RuntimeError(f"learning failed: {report['faults']}")
    return learner


def figures(out_dir, runs: dict, sweeps: dict, learners: dict, suffix: str = "") -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    fig, ax = plt.subplots(figsize=(8, 3.6))
    for name, label in (("ref", "1 kHz, k_e = 0"), ("ff", "1 kHz, learned k_e"),
                        ("ff_2khz", "2 kHz bus, 1 kHz controller, learned k_e")):
        run = runs[name]
        ax.plot(run["t"], run["error"] * 1e3, lw=0.9, label=f"{label}: RMS {run['rms'] * 1e3:.3f} mrad")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("hip flexion error (mrad)")
    ax.set_title("Tracking error while walking (cf. LOLA Fig. 9)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    paths.append(str(out_dir / f"lola_fig9_tracking{suffix}.png"))
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for key, label, style in (("1khz", "1 kHz", "C0"), ("2khz", "2 kHz bus", "C2")):
        if sweeps:
            k, rms = zip(*sweeps[key], strict=True)
            ax.plot(k, np.array(rms) * 1e3, "-", color=style, label=f"{label}: sweep")
        lk, lr = zip(*learners[key].costs, strict=True)
        ax.plot(lk, np.array(lr) * 1e3, "o", color=style, mfc="none", label=f"{label}: windows of the policy")
    ax.set_xlabel("k_e  (k_vel,ff = 1 + k_e)")
    ax.set_ylabel("RMS error (mrad)")
    ax.set_title("Cost against k_e (cf. LOLA Fig. 6)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    paths.append(str(out_dir / f"lola_fig6_cost{suffix}.png"))
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


async def main_async(args, bus: EthercatBus | None = None) -> dict:
    start = time.perf_counter()
    learners = {"1khz": await learn_gain(1000.0, 1, bus), "2khz": await learn_gain(2000.0, 2, bus)}
    k_e, k_e_2khz = learners["1khz"].best[0], learners["2khz"].best[0]
    runs = {"ref": await tracking_run(1000.0, 1, 0.0, bus),
            "ff": await tracking_run(1000.0, 1, k_e, bus),
            "ff_2khz": await tracking_run(2000.0, 2, k_e_2khz, bus)}
    sweeps = {}
    if bus is None:  # on the real clock a sweep would take minutes
        sweep_k = np.round(np.arange(0.0, args.sweep_max + 1e-9, args.sweep_step), 6)
        sweeps = {"1khz": [(float(k), (await tracking_run(1000.0, 1, float(k)))["rms"]) for k in sweep_k],
                  "2khz": [(float(k), (await tracking_run(2000.0, 2, float(k)))["rms"]) for k in sweep_k]}
    result = {
        "path": "ethercat" if bus is not None else "mock, lockstep",
        "rms_ref_rad": runs["ref"]["rms"],
        "rms_ff_rad": runs["ff"]["rms"],
        "rms_ff_2khz_rad": runs["ff_2khz"]["rms"],
        "rms_one_tick_later_rad": {name: run["rms_one_tick_later"] for name, run in runs.items()},
        "k_e": k_e,
        "k_e_2khz": k_e_2khz,
        "reduction_ff": 1.0 - runs["ff"]["rms"] / runs["ref"]["rms"],
        "reduction_ff_2khz": 1.0 - runs["ff_2khz"]["rms"] / runs["ref"]["rms"],
        "learning_windows": {key: learner.costs for key, learner in learners.items()},
        "learning_windows_repeated": {key: learner.repeated for key, learner in learners.items()},
        "sweep": sweeps,
        "faults": {name: run["faults"] for name, run in runs.items()},
        "commands_refused": {name: run["refused"] for name, run in runs.items()},
        "missed_ticks": {name: run["missed_ticks"] for name, run in runs.items()},
        "lola_table3_rad": {"ref": 0.0047, "ff": 0.0004, "ff_2khz": 0.0003},
    }
    if not args.no_figures:
        from pathlib import Path

        suffix = "_ethercat" if bus is not None else ""
        result["figures"] = figures(Path(args.figures), runs, sweeps, learners, suffix)
    result["seconds"] = round(time.perf_counter() - start, 1)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--figures", default=str(ROOT / "docs" / "img"), help="folder of the PNGs")
    parser.add_argument("--no-figures", action="store_true")
    parser.add_argument("--sweep-max", type=float, default=0.5)
    parser.add_argument("--sweep-step", type=float, default=0.05)
    parser.add_argument("--ethercat", action="store_true", help="through real SOEM and the simulated segment (root)")
    args = parser.parse_args()
    if args.ethercat:
        with EthercatBus() as bus:
            result = asyncio.run(main_async(args, bus))
    else:
        result = asyncio.run(main_async(args))
    ref, ff, ff2 = result["rms_ref_rad"], result["rms_ff_rad"], result["rms_ff_2khz_rad"]
    print(f"RMS error, hip flexion: ref {ref:.3g} rad, learned ff {ff:.3g} rad ({result['reduction_ff']:.1%} lower), "
          f"2 kHz {ff2:.3g} rad ({result['reduction_ff_2khz']:.1%} lower); k_e {result['k_e']:g} "
          f"(2 kHz: {result['k_e_2khz']:g}); {result['seconds']} s")
    for path in result.get("figures", []):
        print("figure:", path)
    write_json(args.json, result)


if __name__ == "__main__":
    main()
