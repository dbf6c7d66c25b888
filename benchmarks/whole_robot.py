"""The whole robot at 2 kHz: configs/walkman_whole_sim.toml through the shipped CLI, beside a
bare timerfd loop measured in the same run.

The config has every kind of part at once: 15 CiA 402 drives (WALK-MAN's legs and waist) on
one EtherCAT line (real SOEM against ``python -m aiohal.drivers.ethercat.sim`` behind a veth
pair in a network namespace of its own, made here and gone with the simulator), an IMU and a
force/torque sensor on CAN, the hand behind the NRT pipe (a subprocess), recording to MCAP and
the Zenoh bridge (peer on loopback). The bus runs at 2 kHz, the controller at 1 kHz with
extrapolated targets in between.

The CAN sensor gateway is simulated in a process of its own (``--can-sim process``, the
default), as a real gateway is another device: the robot runs in a second network namespace
made here (the master's veth end moved in, loopback up with a multicast route) and the
gateway (``python -m aiohal.drivers.canopen.sim --sensors``) talks to the CANopen driver over
python-can's ``udp_multicast`` on that loopback only (needs ``msgpack``, the ``bench`` extra).
``--can-sim thread`` keeps the shipped config's simulated gateway on a ``virtual`` bus in the
robot's process, whose threads then take the tick's GIL whenever a pysoem call releases it.

Each round runs, for ``--seconds`` each: the bare loop (timerfd at 2 kHz, no work, in its own
process) and then the robot, both with the loop's thread at SCHED_FIFO 80 on CPU 0 with memory
locked (the config's ``[realtime]`` plus ``cpus = [0]``); the simulator runs on CPU 1 at
SCHED_FIFO 70 (``--sim-priority``: hardware answers whatever else the host does; at normal
priority a loaded host delays its replies by hundreds of µs), and everything else of the
robot's process (recorder, bridge, CAN threads) and the hand may run on either CPU. How
calm the machine was is in each row: the bare loop's own missed deadlines, the 1-minute load
average before and after, the share of both CPUs busy and the share the hypervisor took
(steal), each over the case.

The floor the robot is judged by: lateness p99 at most ``--ratio`` (1.2) times the bare loop's
in the same round, and 0 working-counter errors. The rows also give lateness p50, missed
deadlines, work per phase (p50/p99), each driver's time, the recorder's and the bridge's
dropped counts and what every part produced (cycles, sensor frames, hand states, messages).
``--without can hand record bridge`` leaves parts out, to see what each costs.

    sudo python -m benchmarks.whole_robot [--seconds 60] [--rounds 1] [--ratio 1.2] [--json PATH]
        [--without can hand record bridge] [--can-sim process|thread]
"""

from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

from .breakdown import bare_spec, spawn, timeout_for
from .common import ROOT, StealMeter, run_cli, table, write_json

CONFIG = ROOT / "configs" / "walkman_whole_sim.toml"
SLAVES = "drive*15"
LOOP_CPU, SIM_CPU = 0, 1
PRIORITY = 80
RATE_HZ = 2000.0
CAN_PRIORITY = 60  # the CAN gateway answers as a device would, after the EtherCAT segment (70)
CAN_GROUP = "239.74.163.2"  # python-can's IPv4 group, routed to the namespace's loopback only


class HostMeter:
    """The host's load over a case: the 1-minute load average before and after, the share of
    all CPUs busy (anything but idle and iowait) and the hypervisor's steal, in %."""

    def __init__(self) -> None:
        self.load0 = os.getloadavg()[0]
        self.cpu0 = self._cpu()
        self.steal = StealMeter()

    @staticmethod
    def _cpu() -> tuple[int, int]:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
        idle = fields[3] + fields[4]
        return sum(fields[:8]) - idle, sum(fields[:8])

    def result(self) -> dict:
        busy0, total0 = self.cpu0
        busy1, total1 = self._cpu()
        busy = 100 * (busy1 - busy0) / max(1, total1 - total0)
        return {"load1_before": round(self.load0, 2), "load1_after": round(os.getloadavg()[0], 2),
                "cpu_busy_percent": round(busy, 1), "steal_percent": round(self.steal.percent(), 2)}


PARTS = ("can", "hand", "record", "bridge")


def toml_text(raw: dict) -> str:
    """A parsed config written back as TOML (tables, arrays of tables, inline arrays)."""

    def value(v: object) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{json.dumps(k)} = {value(x)}" for k, x in v.items()) + " }"
        raise TypeError(f"no TOML for {v!r}")

    def tables(path: str, table: dict, header: str) -> list[str]:
        lines = [header] if header else []
        nested = []
        for k, v in table.items():
            if isinstance(v, dict):
                nested.append((k, v, False))
            elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
                nested.append((k, v, True))
            else:
                lines.append(f"{json.dumps(k)} = {value(v)}")
        for k, v, many in nested:
            sub = f"{path}.{json.dumps(k)}" if path else json.dumps(k)
            for item in v if many else [v]:
                lines += tables(sub, item, f"[[{sub}]]" if many else f"[{sub}]")
        return lines

    return "\n".join(tables("", raw, "")) + "\n"


def config_raw(ifname: str, without: tuple[str, ...] = (), can_process: bool = False) -> dict:
    """The shipped config with the veth pair's master end, the loop's thread on LOOP_CPU, the
    CAN gateway in its own process (``can_process``) and without the parts named (to see what
    each costs)."""
    raw = tomllib.loads(CONFIG.read_text())
    (legs,) = [d for d in raw["driver"] if d["type"] == "ethercat"]
    legs["options"]["interface"] = ifname
    raw["realtime"]["cpus"] = [LOOP_CPU]
    if can_process and "can" not in without:
        (can,) = [d for d in raw["driver"] if d["type"] == "canopen"]
        can["options"].update(interface="udp_multicast", channel=CAN_GROUP, simulate=False)
    drop = {"can": "canopen", "hand": "nrt_hand"}
    for part in without:
        if part in drop:
            (driver,) = [d for d in raw["driver"] if d["type"] == drop[part]]
            raw["driver"].remove(driver)
            for name in driver.get("devices", []):
                del raw["devices"][name]
            for name in driver.get("joints", []):
                del raw["joints"][name]
                raw["controller"]["params"]["amplitude"].pop(name, None)
        elif part == "record":
            del raw["record"]
        elif part == "bridge":
            del raw["bridge"]
    return raw


def pin(pid: int, cpu: int, priority: int) -> None:
    """Every thread of ``pid`` on ``cpu`` at SCHED_FIFO ``priority`` (a process's threads do not
    follow a change made to its first one)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        os.sched_setaffinity(int(tid), {cpu})
        os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=10)


class RobotNamespace:
    """A network namespace of this benchmark's own for the robot's process: the master's veth
    end moved in, loopback up with a multicast route, and the CAN sensor gateway simulated in
    a process of its own on python-can's ``udp_multicast`` there. Gone at exit (the veth pair
    with it)."""

    def __init__(self, ifname: str, with_can: bool) -> None:
        self.name = f"aiohal-whole-{os.getpid()}"
        self.ifname = ifname
        self.with_can = with_can
        self.can_sim: subprocess.Popen | None = None
        self.prefix = ("ip", "netns", "exec", self.name)

    def __enter__(self) -> RobotNamespace:
        _ip("netns", "add", self.name)
        try:
            _ip("link", "set", self.ifname, "netns", self.name)
            _ip("-n", self.name, "link", "set", "lo", "up")
            _ip("-n", self.name, "link", "set", self.ifname, "up")
            _ip("-n", self.name, "route", "add", "224.0.0.0/4", "dev", "lo")
            if self.with_can:
                self._start_can_sim()
        except BaseException:
            self.__exit__()
            raise
        return self

    def _start_can_sim(self) -> None:
        cmd = [*self.prefix, sys.executable, "-m", "aiohal.drivers.canopen.sim", "--interface", "udp_multicast",
               "--channel", CAN_GROUP, "--sensors", "--sensor-period-ms", "4"]
        self.can_sim = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        ready, _, _ = select.select([self.can_sim.stdout], [], [], 30.0)
        line = self.can_sim.stdout.readline() if ready else ""
        if not line.startswith("simulating"):
            raise RuntimeError(f"the CAN gateway simulator did not start: {line!r} {self.can_sim.stderr.read()[-500:]}")
        # `ip netns exec` runs the simulator as its child: pin the process that has the threads
        (sim_pid,) = [int(p) for p in subprocess.run(["pgrep", "-P", str(self.can_sim.pid)], capture_output=True,
                                                     text=True, timeout=10).stdout.split()] or [self.can_sim.pid]
        pin(sim_pid, SIM_CPU, CAN_PRIORITY)

    def __exit__(self, *exc: object) -> None:
        if self.can_sim is not None:
            self.can_sim.terminate()
            try:
                self.can_sim.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                self.can_sim.kill()
                self.can_sim.communicate()
        subprocess.run(["ip", "netns", "del", self.name], capture_output=True, timeout=10, check=False)


def run_bare(seconds: float, loop: str) -> dict:
    """A timerfd loop at the robot's rate with no work, the same [realtime] settings, its own process."""
    host = HostMeter()
    realtime = {"priority": PRIORITY, "lock_memory": True, "cpus": [LOOP_CPU]}
    bare = spawn("benchmarks.breakdown", bare_spec(realtime, RATE_HZ, seconds, loop), timeout_for(seconds))
    return {**bare, **host.result()}


def _p(d: dict | None, key: str = "p50") -> float | None:
    return None if not d else d.get(key)


def run_whole(seconds: float, loop: str, without: tuple[str, ...] = (), sim_priority: int = 0,
              can_process: bool = True) -> dict:
    """The shipped config through the CLI against a fresh simulated segment; the figures of one run."""
    from aiohal.drivers.ethercat.sim.fixture import SimulatedSegment

    with SimulatedSegment(SLAVES, watchdog_ms=100) as sim, tempfile.TemporaryDirectory() as tmp:
        os.sched_setaffinity(sim.pid, {SIM_CPU})
        if sim_priority:  # the slaves answer as hardware would: before the helpers of the robot's process
            os.sched_setscheduler(sim.pid, os.SCHED_FIFO, os.sched_param(sim_priority))
        config = Path(tmp) / CONFIG.name
        config.write_text(toml_text(config_raw(sim.ifname, without, can_process)))
        record = () if "record" in without else ("--record", str(Path(tmp) / "whole.mcap"))
        with RobotNamespace(sim.ifname, with_can=can_process and "can" not in without) as netns:
            host = HostMeter()
            report = run_cli(config, "--duration", str(seconds), "--loop", loop, *record, prefix=netns.prefix,
                             timeout=seconds + 180)
            calm = host.result()
    drivers = report["drivers"]
    legs, can, hand = drivers.get("legs", {}), drivers.get("can_sensors", {}), drivers.get("hand", {})
    record = report.get("record") or {}
    bridge = (report.get("bridge") or {}).get("zenoh") or {}
    phases = {name: {"p50": v["p50"], "p99": v["p99"]} for name, v in report["phases_us"].items()}
    return {
        "ticks": report["ticks"], "missed": report["missed_ticks"], "rate_hz_achieved": report["rate_hz_achieved"],
        "lateness_p50_us": report["lateness_us"]["p50"], "lateness_p99_us": report["lateness_us"]["p99"],
        "lateness_max_us": report["lateness_us"].get("max"),
        "work_p50_us": report["work_us"]["p50"], "work_p99_us": report["work_us"]["p99"], "phases_us": phases,
        "drivers_us": {name: {k: d[k] for k in ("read_us_mean", "write_us_mean", "read_us_max", "write_us_max") if k in d}
                       for name, d in drivers.items()},
        "ecat_cpu_us": legs.get("cpu_us"),
        "wkc_errors": legs.get("wkc_errors"), "frames_lost": legs.get("frames_lost"), "ecat_cycles": legs.get("cycles"),
        "ecat_receive_wait_p50_us": _p(legs.get("receive_wait_us")),
        "can_sensors": {k: v for k, v in can.items() if "sensor" in k or "frames" in k or k in ("late_cycles", "malformed")},
        "hand": {k: hand.get(k) for k in ("hand", "alive", "pipe") if k in hand},
        "record_dropped_ticks": record.get("dropped_ticks"), "record_ticks": record.get("ticks"),
        "record_messages": record.get("messages"),
        "bridge_state_lost": bridge.get("state_lost"), "bridge_state_sent": bridge.get("state_sent"),
        "controller": report["controller"], "faults": report["faults"], "safety_worst": report["safety_worst"],
        "cpu_percent": report.get("cpu_percent"), "exit_code": report["exit_code"], **calm,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0, help="seconds of each case (bare loop, robot)")
    p.add_argument("--rounds", type=int, default=1, help="rounds of bare loop + robot")
    p.add_argument("--ratio", type=float, default=1.2, help="the floor: robot lateness p99 / bare lateness p99")
    p.add_argument("--loop", choices=("asyncio", "uvloop"), default="uvloop", help="event loop of both cases")
    p.add_argument("--without", nargs="+", choices=PARTS, default=[],
                   help="leave these parts out of the robot (what each costs)")
    p.add_argument("--sim-priority", type=int, default=70,
                   help="SCHED_FIFO priority of the simulator on its CPU (default 70; 0: normal scheduling)")
    p.add_argument("--can-sim", choices=("process", "thread"), default="process",
                   help="the CAN gateway simulated in its own process (default) or in the robot's")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    if os.geteuid() != 0:
        print("benchmarks.whole_robot needs root (veth pair, network namespace, raw socket)", file=sys.stderr)
        return 2
    if args.can_sim == "process" and "can" not in args.without:
        try:
            import msgpack  # noqa: F401  python-can's udp_multicast needs it
        except ImportError:
            print("--can-sim process needs python-can's udp_multicast: pip install -e '.[bench]' "
                  "(or --can-sim thread)", file=sys.stderr)
            return 2
    if (os.cpu_count() or 1) < 2:
        print("benchmarks.whole_robot needs 2 CPUs (the loop on one, the simulator on the other)", file=sys.stderr)
        return 2
    started = time.monotonic()
    rounds = []
    for r in range(1, args.rounds + 1):
        bare = run_bare(args.seconds, args.loop)
        print(json.dumps({"round": r, "bare": bare}), flush=True)
        whole = run_whole(args.seconds, args.loop, tuple(args.without), args.sim_priority, args.can_sim == "process")
        ratio = None  # a robot that did not run (a failed bring-up: its faults say why) has none
        if whole["lateness_p99_us"] is not None and bare["lateness_p99_us"]:
            ratio = round(whole["lateness_p99_us"] / bare["lateness_p99_us"], 3)
        met = ratio is not None and ratio <= args.ratio and whole["wkc_errors"] == 0 and whole["exit_code"] == 0
        rounds.append({"round": r, "bare": bare, "whole": whole, "lateness_p99_ratio": ratio, "floor_met": met})
        print(json.dumps({"round": r, "whole": whole, "lateness_p99_ratio": ratio, "floor_met": met}), flush=True)
        for fault in whole["faults"]:
            print(f"round {r}: FAULT {fault['source']} in {fault['phase']} at tick {fault['tick']}: {fault['error']}",
                  flush=True)
    rows = []
    for rnd in rounds:
        for case in ("bare", "whole"):
            d = rnd[case]
            rows.append({
                "round": rnd["round"], "case": "bare timerfd loop" if case == "bare" else "whole robot",
                "ticks": d["ticks"], "missed": d["missed"], "p50": d["lateness_p50_us"], "p99": d["lateness_p99_us"],
                "work_p50": d.get("work_p50_us", "–"), "work_p99": d.get("work_p99_us", "–"),
                "wkc": d.get("wkc_errors", "–"), "rec_drop": d.get("record_dropped_ticks", "–"),
                "br_drop": d.get("bridge_state_lost", "–"), "load": f"{d['load1_before']}→{d['load1_after']}",
                "busy": d["cpu_busy_percent"], "steal": d["steal_percent"],
                "ratio": (rnd["lateness_p99_ratio"] or "–") if case == "whole" else "", "met": (
                    "yes" if rnd["floor_met"] else "no") if case == "whole" else "",
            })
    print()
    print(f"{CONFIG.relative_to(ROOT)} at {RATE_HZ:g} Hz (controller at 1 kHz), {args.seconds:g} s per case:")
    print(table(rows, [
        ("round", "round"), ("case", "case"), ("ticks", "ticks"), ("missed", "missed"),
        ("p50", "lateness p50 µs"), ("p99", "lateness p99 µs"), ("work_p50", "work p50 µs"), ("work_p99", "work p99 µs"),
        ("wkc", "WKC errors"), ("rec_drop", "record dropped"), ("br_drop", "bridge dropped"),
        ("load", "load avg 1 min"), ("busy", "CPUs busy %"), ("steal", "steal %"),
        ("ratio", f"p99 / bare (≤ {args.ratio:g})"), ("met", "floor met"),
    ]))
    last = rounds[-1]["whole"]
    print("\nwork per phase in the last round, p50 / p99 µs: "
          + ", ".join(f"{k} {v['p50']} / {v['p99']}" for k, v in last["phases_us"].items()))
    print("drivers' time per tick, mean µs: " + ", ".join(
        f"{name} read {d.get('read_us_mean')} write {d.get('write_us_mean')}" for name, d in last["drivers_us"].items()))
    elapsed = round(time.monotonic() - started, 1)
    write_json(args.json, {"benchmark": "whole_robot", "config": str(CONFIG.relative_to(ROOT)), "rate_hz": RATE_HZ,
                           "seconds": args.seconds, "loop": args.loop, "can_sim": args.can_sim,
                           "ratio_floor": args.ratio, "elapsed_s": elapsed,
                           "rounds": rounds, "floor_met_rounds": sum(r["floor_met"] for r in rounds)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
