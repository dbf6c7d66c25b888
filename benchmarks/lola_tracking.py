"""LOLA's Table III, Figs. 6 and 9 in simulation: the hip flexion joint's tracking error
while walking, without and with the learned velocity feed-forward, and with a 2 kHz bus.

``configs/lola_hip_sim.toml``: the ``gait`` controller (a hip flexion at 2.7 km/h, a stride of
1.2 s; target position, target velocity and model torque feed-forward) on the mock driver's
simulated servo drive (``aiohal.simulation.servo``: an elastic harmonic drive, motor and link
encoders, the drive's velocity estimate, noise), in lockstep, through the HAL's real path
(read, controller, extrapolation, feed-forward, limits, write). Runs:

* ``ref``: controller and bus at 1 kHz, k_e = 0 (k_vel,ff = 1: the target velocity as is);
* ``ff``: the same with k_e learned by LOLA's policy at 1 kHz (``aiohal.learn_feedforward``);
* ``ff_2khz``: loop and bus at 2 kHz, the controller at 1 kHz (``[controller] every = 2``,
  targets extrapolated in between), k_e learned by the same policy in that configuration;
* ``reduction_by_kp``: ``ref`` and ``ff`` again (learning included) for each position gain.

The error is LOLA's (``aiohal.core.tracking_error``): the desired position against the link
position measured at the same instant, RMS over 3 strides after a ramp-in and a settling
stride. Fig. 6 is the error over time while the policy raises k_e, Fig. 9 the three runs.

With ``--ethercat`` (root) the same three runs and learnings go through real SOEM to the
simulated EtherCAT segment (a veth pair in a namespace of its own), its one drive running the
same servo model (``--dynamics servo`` with the config's parameters) behind RxPDO 0x1602, so
the target velocity and torque feed-forward travel as 0x60B1/0x60B2 in the drive's units.
That runs on the real clock (about a minute; no gain sweep). A reading there was measured one
cycle before it is read, which the error definition takes into account.

Figures go to ``--out`` (default ``bench-results/lola``, ignored by git).

    python -m benchmarks.lola_tracking [--json out.json] [--out DIR] [--no-figures] [--ethercat]
                                       [--servo '{"sync_latch": false}']
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from aiohal.core.tracking_error import tracking_error

from .common import ROOT, write_json

CONFIG = ROOT / "configs" / "lola_hip_sim.toml"
STRIDES = 3  # measured strides per run
GAINS = (100.0, 150.0, 200.0, 250.0, 300.0)  # position gains of reduction_by_kp (1/s)
MEASUREMENT_DELAY = 1  # ticks between an EtherCAT slave's reading and the master's


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
        # the slave answers with the inputs it latched in the cycle before
        raw["feedforward"] = {**raw.get("feedforward", {}), "measurement_delay_ticks": MEASUREMENT_DELAY}
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


SERVO: dict = {}  # changes to the config's servo parameters (--servo), lockstep runs only


def configure(rate_hz: float, every: int, k_e: float | None, bus: EthercatBus | None = None,
              position_gain: float | None = None):
    from aiohal.config import load_config
    from aiohal.core.feedforward import FeedforwardSection

    if bus is None:
        config = load_config(CONFIG).with_loop(rate_hz=rate_hz, clock="virtual")
        changes = {**SERVO, **({"position_gain": position_gain} if position_gain is not None else {})}
        if changes:
            driver = config.drivers[0]
            servo = type(driver.options.servo).model_validate({**driver.options.servo.model_dump(), **changes})
            options = driver.options.model_copy(update={"servo": servo})
            config = replace(config, drivers=(replace(driver, options=options),))
    else:
        bus.power_cycle()
        config = bus.config(rate_hz)
    config = replace(config, controller=replace(config.controller, every=every))
    section = config.feedforward.model_copy(update={"k_e": k_e, "gains": None}) if k_e is not None else \
        FeedforwardSection(**{**config.feedforward.model_dump(), "k_e": None, "gains": None})
    return replace(config, feedforward=section)


class Recorder:
    """Each tick's time (s since activation), measured position and k_e, for ``ticks`` ticks."""

    def __init__(self, ticks: int) -> None:
        self.times, self.measured, self.k_e = np.zeros(ticks), np.zeros(ticks), np.zeros(ticks)
        self.count = 0

    def __call__(self, control) -> None:
        i = self.count
        if i < len(self.times):
            self.times[i] = control.robot.clock.tick * control.period_s
            self.measured[i] = control.robot.state.position[0]
            feedforward = control.feedforward
            self.k_e[i] = feedforward.k_e[0] if feedforward is not None else 0.0
            self.count = i + 1

    def error(self, controller, delay: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """LOLA's error of every tick that has one: times, errors, k_e."""
        n = self.count
        t = self.times[:n]
        desired, _ = controller.reference(t)  # the controller's time is the tick's since activation
        error = tracking_error(desired[:, 0], self.measured[:n], delay)
        return t[delay:], error, self.k_e[delay:n]


async def tracking_run(rate_hz: float, every: int, k_e: float | None, bus: EthercatBus | None = None,
                       position_gain: float | None = None) -> dict:
    """One run: the error of every tick after the settling time, and its RMS."""
    from aiohal import ControlLoop

    config = configure(rate_hz, every, k_e, bus, position_gain)
    loop = ControlLoop(config)
    period = config.controller.params.period
    settle = config.controller.params.ramp + period
    ticks = round((settle + STRIDES * period) * rate_hz)
    recorder = Recorder(ticks + 1)
    async with loop:
        loop.add_publisher(recorder)
        report = await loop.run(duration=ticks / rate_hz)
        t, error, _ = recorder.error(loop.controller, config.feedforward.measurement_delay_ticks)
    keep = t >= settle
    return {"t": t[keep] - settle, "error": error[keep], "rms": float(np.sqrt(np.mean(error[keep] ** 2))),
            "faults": report["faults"], "refused": report["commands_refused"],
            "missed_ticks": report["missed_ticks"]}


async def learn_gain(rate_hz: float, every: int, bus: EthercatBus | None = None,
                     position_gain: float | None = None):
    """LOLA's policy in one run: the learner, and the run's error and k_e over time (Fig. 6)."""
    from aiohal.learn_feedforward import learn

    config = configure(rate_hz, every, None, bus, position_gain)
    section = config.feedforward
    windows = (section.max_steps + 2) * 4  # as learn() bounds it
    recorder = Recorder(round((section.settle_s + section.window_s * windows) * rate_hz) + 1)
    controller = []
    recorder_tick = recorder.__call__

    def on_tick(control) -> None:
        if not controller:
            controller.append(control.controller)
        recorder_tick(control)

    learner, report = await learn(config, on_tick=on_tick)
    if report["faults"] or learner.best is None:
        raise RuntimeError(f"learning failed: {report['faults']}")
    t, error, k_e = recorder.error(controller[0], section.measurement_delay_ticks)
    return learner, {"t": t, "error": error, "k_e": k_e}


def figures(out_dir: Path, runs: dict, learning: dict, suffix: str = "") -> list[str]:
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

    fig, axes = plt.subplots(len(learning), 1, figsize=(8, 2.6 * len(learning)), sharex=True, squeeze=False)
    for ax, (key, label) in zip(axes[:, 0], (("1khz", "1 kHz"), ("2khz", "2 kHz bus")), strict=False):
        trace = learning[key]
        ax.plot(trace["t"], trace["error"] * 1e3, lw=0.6, color="C0")
        ax.set_ylabel(f"{label}: error (mrad)")
        gain = ax.twinx()
        gain.step(trace["t"], trace["k_e"], where="post", color="C3", lw=1.2)
        gain.set_ylabel("k_e", color="C3")
        ax.grid(alpha=0.3)
    axes[0, 0].set_title("Error while the policy raises k_e (cf. LOLA Fig. 6)")
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    paths.append(str(out_dir / f"lola_fig6_learning{suffix}.png"))
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


async def reduction_by_kp() -> dict:
    """For each position gain: the gain learned, the RMS without and with it, the reduction."""
    result = {}
    for kp in GAINS:
        learner, _ = await learn_gain(1000.0, 1, position_gain=kp)
        k_e = learner.best[0]
        ref = (await tracking_run(1000.0, 1, 0.0, position_gain=kp))["rms"]
        ff = (await tracking_run(1000.0, 1, k_e, position_gain=kp))["rms"]
        result[f"{kp:g}"] = {"k_e": k_e, "rms_ref_rad": ref, "rms_ff_rad": ff, "reduction": 1.0 - ff / ref,
                             "k_e_over_kp_ms": 1e3 * k_e / kp}
    return result


async def main_async(args, bus: EthercatBus | None = None) -> dict:
    start = time.perf_counter()
    learned = {"1khz": await learn_gain(1000.0, 1, bus), "2khz": await learn_gain(2000.0, 2, bus)}
    learners = {key: learner for key, (learner, _) in learned.items()}
    k_e, k_e_2khz = learners["1khz"].best[0], learners["2khz"].best[0]
    runs = {"ref": await tracking_run(1000.0, 1, 0.0, bus),
            "ff": await tracking_run(1000.0, 1, k_e, bus),
            "ff_2khz": await tracking_run(2000.0, 2, k_e_2khz, bus)}
    result = {
        "path": "ethercat" if bus is not None else "mock, lockstep",
        "rms_ref_rad": runs["ref"]["rms"],
        "rms_ff_rad": runs["ff"]["rms"],
        "rms_ff_2khz_rad": runs["ff_2khz"]["rms"],
        "k_e": k_e,
        "k_e_2khz": k_e_2khz,
        "reduction_ff": 1.0 - runs["ff"]["rms"] / runs["ref"]["rms"],
        "reduction_ff_2khz": 1.0 - runs["ff_2khz"]["rms"] / runs["ref"]["rms"],
        "learning_windows": {key: learner.costs for key, learner in learners.items()},
        "learning_windows_repeated": {key: learner.repeated for key, learner in learners.items()},
        "faults": {name: run["faults"] for name, run in runs.items()},
        "commands_refused": {name: run["refused"] for name, run in runs.items()},
        "missed_ticks": {name: run["missed_ticks"] for name, run in runs.items()},
        "lola_table3_rad": {"ref": 0.0047, "ff": 0.0004, "ff_2khz": 0.0003},
    }
    if bus is None:  # on the real clock five more learnings would take minutes
        by_kp = await reduction_by_kp()
        reductions = [entry["reduction"] for entry in by_kp.values()]
        result["reduction_by_kp"] = {kp: entry["reduction"] for kp, entry in by_kp.items()}
        result["by_kp"] = by_kp
        result["reduction_spread_points"] = 100.0 * (max(reductions) - min(reductions))
    if not args.no_figures:
        suffix = "_ethercat" if bus is not None else ""
        result["figures"] = figures(Path(args.out), runs, {key: trace for key, (_, trace) in learned.items()}, suffix)
    result["seconds"] = round(time.perf_counter() - start, 1)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--out", default=str(ROOT / "bench-results" / "lola"), help="folder of the PNGs")
    parser.add_argument("--no-figures", action="store_true")
    parser.add_argument("--ethercat", action="store_true", help="through real SOEM and the simulated segment (root)")
    parser.add_argument("--servo", default="{}", help='servo parameters changed, JSON (e.g. \'{"sync_latch": false}\')')
    args = parser.parse_args()
    SERVO.update(json.loads(args.servo))
    if SERVO and args.ethercat:
        parser.error("--servo: lockstep runs only")
    if args.ethercat:
        with EthercatBus() as bus:
            result = asyncio.run(main_async(args, bus))
    else:
        result = asyncio.run(main_async(args))
    ref, ff, ff2 = result["rms_ref_rad"], result["rms_ff_rad"], result["rms_ff_2khz_rad"]
    print(f"RMS error, hip flexion: ref {ref:.3g} rad, learned ff {ff:.3g} rad ({result['reduction_ff']:.1%} lower), "
          f"2 kHz {ff2:.3g} rad ({result['reduction_ff_2khz']:.1%} lower); k_e {result['k_e']:g} "
          f"(2 kHz: {result['k_e_2khz']:g}); {result['seconds']} s")
    for kp, entry in result.get("by_kp", {}).items():
        print(f"  K_p {kp}: k_e {entry['k_e']:g}, ref {entry['rms_ref_rad']:.3g}, learned {entry['rms_ff_rad']:.3g} rad, "
              f"{entry['reduction']:.1%} lower")
    for path in result.get("figures", []):
        print("figure:", path)
    write_json(args.json, result)


if __name__ == "__main__":
    main()
