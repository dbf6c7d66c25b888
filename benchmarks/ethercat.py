"""EtherCAT cycles through the ``ethercat`` driver and real SOEM against the simulated segment.

For 1, 7 and 25 slaves (a drive; 7 drives; 23 drives + IMU + F/T, LOLA's count) at 1 and
2 kHz, the shipped CLI runs a config like configs/ethercat_sim.toml (sine on every joint,
SCHED_FIFO 80, memory locked) against ``python -m aiohal.drivers.ethercat.sim`` behind a veth
pair (needs root), each in a fresh process (on uvloop, or each of ``--loops``):

* ``exchange = "immediate"`` gives the round trip: send, then wait for the frame in the tick
  (``rtt_us`` = from the send's return to the receive's);
* ``exchange = "split"`` (the default) is the production setting: the frame sent at the end of
  a tick is received at the start of the next; ``receive_wait_us`` is what was left to wait.

Per case: working-counter errors, missed ticks, loop lateness, and the driver's CPU per cycle:
the time inside its read() and write() minus the time inside pysoem's receive call (the wait
for the frame, which is a busy poll inside SOEM). The loop runs on CPU 0, the simulator on
CPU 1 (2-core machine: they would otherwise share one). "steal" is the CPU time the hypervisor
took from this VM during the case, in % of both CPUs (from /proc/stat).

    sudo python -m benchmarks.ethercat [--seconds 10] [--soak 60] [--json PATH]
    sudo python -m benchmarks.ethercat --breakdown 7 [--seconds 5] [--exchange immediate]  # where the driver's time goes
    sudo python -m benchmarks.ethercat --bare 7 [--rounds 3]          # pysoem's own floor beside it
    sudo python -m benchmarks.ethercat --send-after-work 7 [--rounds 3]  # the send after the tick's work

``--soak`` runs 25 slaves at 1 kHz (split) for that long at the end (0 = skip).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import StealMeter, run_cli, table, write_json

LINES = {1: "drive", 7: "drive*7", 25: "drive*23,imu,ft"}
LOOP_CPU, SIM_CPU = 0, 1


def config_text(n_slaves: int, ifname: str, rate_hz: int, exchange: str, spin_guard_us: float = 0.0) -> str:
    drives = n_slaves if n_slaves < 25 else 23
    joints = [f"j{i}" for i in range(1, drives + 1)]
    slaves = [f'{{ name = "drive{i}", kind = "cia402", joint = "j{i}" }}' for i in range(1, drives + 1)]
    devices = ""
    device_names: list[str] = []
    if n_slaves == 25:
        slaves += ['{ name = "imu", kind = "imu", device = "imu" }', '{ name = "ft", kind = "force_torque", device = "ft" }']
        devices = '[devices.imu]\ntype = "imu"\n[devices.ft]\ntype = "force_torque"\n'
        device_names = ["imu", "ft"]
    joint_tables = "\n".join(f"[joints.{j}]" for j in joints)
    return f"""[robot]
name = "ethercat_bench_{n_slaves}"
[loop]
rate_hz = {rate_hz}
[realtime]
priority = 80
lock_memory = true
spin_guard_us = {spin_guard_us}
[joint_defaults]
position = [-2.5, 2.5]
velocity = 2.0
acceleration = 20.0
effort = 1.0
{joint_tables}
{devices}
[[driver]]
type = "ethercat"
name = "bus"
joints = {json.dumps(joints)}
devices = {json.dumps(device_names)}
[driver.options]
interface = "{ifname}"
exchange = "{exchange}"
receive_timeout_us = {500 if exchange == "immediate" else 200}
slaves = [{", ".join(slaves)}]
[controller]
type = "sine"
[controller.params]
amplitude = 0.3
frequency = 0.5
ramp = 0.5
"""


def run_case(n_slaves: int, rate_hz: int, exchange: str, seconds: float, spin_guard_us: float = 0.0,
             loop: str = "uvloop") -> dict:
    from aiohal.drivers.ethercat.sim.fixture import SimulatedSegment

    with SimulatedSegment(LINES[n_slaves], watchdog_ms=100) as sim, tempfile.TemporaryDirectory() as tmp:
        os.sched_setaffinity(sim.pid, {SIM_CPU})
        config = Path(tmp) / "bench.toml"
        config.write_text(config_text(n_slaves, sim.ifname, rate_hz, exchange, spin_guard_us))
        steal = StealMeter()
        report = run_cli(config, "--duration", str(seconds), "--loop", loop, prefix=("taskset", "-c", str(LOOP_CPU)),
                         timeout=seconds + 120)
        steal_percent = steal.percent()
    bus = report["drivers"]["bus"]
    cpu_p50, cpu_p99 = (bus.get("cpu_us") or {}).get("p50"), (bus.get("cpu_us") or {}).get("p99")
    key = "rtt_us" if exchange == "immediate" else "receive_wait_us"
    wait_p50, wait_p99 = bus.get(key, {}).get("p50"), bus.get(key, {}).get("p99")
    return {
        "slaves": n_slaves, "loop": loop, "rate_hz": rate_hz, "exchange": exchange, "seconds": seconds, "spin_guard_us": spin_guard_us,
        "process_data_bytes": bus.get("process_data_bytes"), "ticks": report["ticks"], "missed": report["missed_ticks"],
        "cycles": bus.get("cycles"), "wkc_errors": bus.get("wkc_errors"), "frames_lost": bus.get("frames_lost"),
        "faults": len(report["faults"]), "lateness_p99_us": report["lateness_us"]["p99"],
        "cpu_p50_us": cpu_p50, "cpu_p99_us": cpu_p99, "steal_percent": round(steal_percent, 1),
        "exit_code": report["exit_code"], f"{key}_p50": wait_p50, f"{key}_p99": wait_p99,
    }


ETHERCAT = "aiohal.drivers.ethercat"
# methods timed where they are defined; the driver's own pysoem calls are timed on the driver (below)
PHASES = ((f"{ETHERCAT}.devices", "DriveGroup", "decode"), (f"{ETHERCAT}.devices", "DriveGroup", "update_machines"),
          (f"{ETHERCAT}.devices", "DriveGroup", "write"))


def breakdown(n_slaves: int, ticks: int, exchange: str = "split") -> dict:
    """Where the driver's time goes, in the loop (each phase wrapped with a timer, ~0.3 µs
    added per phase), then the same decode run back to back (warm) and after a 0.9 ms sleep
    each (cold, as in the loop): on this VM a tick after sleeping runs several times slower."""
    import asyncio
    import functools
    import importlib
    import tomllib

    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop
    from aiohal.drivers.ethercat.sim.fixture import SimulatedSegment

    spent: dict[str, int] = {}

    def timed_call(fn, name):
        @functools.wraps(fn)
        def timed(*a, **k):
            t = time.perf_counter_ns()
            try:
                return fn(*a, **k)
            finally:
                spent[name] = spent.get(name, 0) + time.perf_counter_ns() - t
        return timed

    for module, cls_name, name in PHASES:
        cls = getattr(importlib.import_module(module), cls_name)
        setattr(cls, name, timed_call(getattr(cls, name), name))

    async def run(ifname: str) -> dict:
        raw = tomllib.loads(config_text(n_slaves, ifname, 1000, exchange))
        async with ControlLoop(parse_config(raw)) as loop:
            driver = loop.slots[0].driver
            with driver._lock:  # pysoem's calls as bound on the driver at bring-up
                driver._send_now = timed_call(driver._send_now, "send")
                driver._receive_now = timed_call(driver._receive_now, "receive")
                driver._in_getters = [timed_call(get, "slave_inputs") for get in driver._in_getters]
                driver._out_parts = [(timed_call(put, "slave_outputs"), start, end) for put, start, end in driver._out_parts]
            await loop.run(ticks=500)
            spent.clear()
            report = await loop.run(ticks=ticks)
            out = {f"{k}_us": round(v / report["ticks"] / 1e3, 1) for k, v in spent.items()}
            out["cpu_us_p50"] = report["drivers"]["bus"]["cpu_us"]["p50"]
        # the decode alone, once the driver is closed: nothing else (the keep-alive thread)
        # cycles the bus on this CPU between the samples; the decode only reads the image
        for label, pause in (("warm", 0.0), ("after_sleep", 0.0009)):
            total = 0
            for _ in range(2000):
                if pause:
                    time.sleep(pause)
                t = time.perf_counter_ns()
                driver.drives.decode(0, 0)
                total += time.perf_counter_ns() - t
            out[f"decode_{label}_us"] = round(total / 2000 / 1e3, 2)
        return out

    os.sched_setaffinity(0, {LOOP_CPU})
    with SimulatedSegment(LINES[n_slaves], watchdog_ms=250) as sim:
        os.sched_setaffinity(sim.pid, {SIM_CPU})
        return {"slaves": n_slaves, "exchange": exchange, **asyncio.run(run(sim.ifname))}


@contextlib.contextmanager
def bare_master(n_slaves: int):
    """A plain pysoem master in OP against the simulated segment (loop on LOOP_CPU, simulator on
    SIM_CPU): yields (master, the slaves' input getters, (output setter, bytes) per slave)."""
    import pysoem

    from aiohal.drivers.ethercat.bus import reach_op, reach_safeop
    from aiohal.drivers.ethercat.sim.fixture import SimulatedSegment

    with SimulatedSegment(LINES[n_slaves], watchdog_ms=100) as sim:
        os.sched_setaffinity(sim.pid, {SIM_CPU})
        os.sched_setaffinity(0, {LOOP_CPU})
        m = pysoem.Master()
        m.open(sim.ifname)
        try:
            if m.config_init() != n_slaves:
                raise RuntimeError("config_init did not find the simulated slaves")
            m.config_map()
            m.config_dc()
            slaves = list(m.slaves)
            getters = [s._get_input for s in slaves if len(s.input)]
            setters = [(s._set_output, bytes(len(s.output))) for s in slaves if len(s.output)]

            def exchange() -> None:
                m.send_processdata()
                m.receive_processdata(50_000)

            # the driver's own waits: each asks again after a frame lost in a stall of the host
            if not (reach_safeop(m, 2.0) and reach_op(m, exchange, 2.0, 0.001)):
                raise RuntimeError("the simulated slaves did not reach OP: "
                                   + ", ".join(hex(s.state) for s in m.slaves))
            yield m, getters, setters
        finally:
            m.close()


@contextlib.contextmanager
def fifo_no_gc():
    """SCHED_FIFO 80 and no garbage collector, for a timed bare loop; both undone after."""
    import gc

    gc.collect()
    gc.disable()
    saved = os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
    try:
        yield
    finally:
        os.sched_setscheduler(0, saved[0], saved[1])
        gc.enable()


def bare_case(n_slaves: int, seconds: float) -> dict:
    """The least any driver on pysoem does per cycle, timed like the driver's CPU figure: a
    plain loop (SCHED_FIFO 80, sleeping to absolute 1 ms deadlines, as the aiohal loop does)
    that receives the frame sent at the end of the previous cycle (the wait is excluded), reads
    every slave's ``input``, writes every slave's ``output`` (bytes made once), sends. No
    decoding, no state machine: what is left of 50 µs after this is the budget for the rest."""
    cycles = round(seconds * 1000)
    with bare_master(n_slaves) as (m, getters, setters):
        expected = m.expected_wkc
        parts = np.zeros((cycles, 3), dtype=np.int64)  # inputs, outputs, send (the receive's wait left out)
        bad = 0
        with fifo_no_gc():
            steal = StealMeter()
            m.send_processdata()
            deadline = time.monotonic() + 0.001
            for i in range(cycles):
                wkc = m.receive_processdata(2000)
                t1 = time.perf_counter_ns()
                bad += wkc != expected
                for get in getters:
                    get()
                t2 = time.perf_counter_ns()
                for set_output, data in setters:
                    set_output(data)
                t3 = time.perf_counter_ns()
                m.send_processdata()
                t4 = time.perf_counter_ns()
                parts[i] = (t2 - t1, t3 - t2, t4 - t3)
                left = deadline - time.monotonic()
                if left > 0:
                    time.sleep(left)
                deadline += 0.001
            m.receive_processdata(2000)
            steal_percent = steal.percent()
    spent = parts.sum(axis=1)
    med = np.median(parts, axis=0)
    return {"loop": "bare pysoem", "slaves": n_slaves, "cycles": cycles, "wkc_errors": int(bad),
            "cpu_p50_us": round(float(np.median(spent)) / 1e3, 1),
            "cpu_p99_us": round(float(np.percentile(spent, 99)) / 1e3, 1),
            "inputs_p50_us": round(med[0] / 1e3, 1), "outputs_p50_us": round(med[1] / 1e3, 1),
            "send_p50_us": round(med[2] / 1e3, 1), "steal_percent": round(steal_percent, 1)}


def send_after_work(n_slaves: int, rounds: int, block: int = 500) -> list[dict]:
    """Why pysoem's send costs more inside the driver than in the bare loop: the bare loop with
    work put between its receive and its send, in blocks of ``block`` cycles alternating in one
    run: none; a pure-Python spin of 30 µs (time, no memory); numpy over 64 KB and over 512 KB
    (memory, as a tick's work touches it). The send's own time is compared."""
    small, small_out = np.ones(8192), np.empty(8192)
    large, large_out = np.ones(65536), np.empty(65536)

    def spin() -> None:
        until = time.perf_counter_ns() + 30_000
        while time.perf_counter_ns() < until:
            pass

    def touch(a: np.ndarray, out: np.ndarray) -> None:
        np.multiply(a, 1.0001, out=out)
        np.add(out, a, out=out)

    kinds = {"none": lambda: None, "spin 30 µs": spin, "numpy over 64 KB": lambda: touch(small, small_out),
             "numpy over 512 KB": lambda: touch(large, large_out)}
    sends: dict[str, list[int]] = {kind: [] for kind in kinds}
    work: dict[str, list[int]] = {kind: [] for kind in kinds}
    with bare_master(n_slaves) as (m, getters, setters), fifo_no_gc():
        steal = StealMeter()
        m.send_processdata()
        deadline = time.monotonic() + 0.001
        for kind in list(kinds) * rounds:
            between = kinds[kind]
            for _ in range(block):
                m.receive_processdata(2000)
                for get in getters:
                    get()
                t0 = time.perf_counter_ns()
                between()
                t1 = time.perf_counter_ns()
                for set_output, data in setters:
                    set_output(data)
                t2 = time.perf_counter_ns()
                m.send_processdata()
                t3 = time.perf_counter_ns()
                sends[kind].append(t3 - t2)
                work[kind].append(t1 - t0)
                left = deadline - time.monotonic()
                if left > 0:
                    time.sleep(left)
                deadline += 0.001
        m.receive_processdata(2000)
        steal_percent = round(steal.percent(), 1)
    return [{"between": kind, "cycles": len(sends[kind]),
             "work_p50_us": round(float(np.median(work[kind])) / 1e3, 1),
             "send_p50_us": round(float(np.median(sends[kind])) / 1e3, 1),
             "send_p90_us": round(float(np.percentile(sends[kind], 90)) / 1e3, 1),
             "steal_percent": steal_percent} for kind in kinds]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--soak", type=float, default=60.0, help="25 slaves at 1 kHz for this long (0: skip)")
    p.add_argument("--slaves", type=int, nargs="+", choices=sorted(LINES), default=[1, 7, 25])
    p.add_argument("--rates", type=int, nargs="+", default=[1000, 2000])
    p.add_argument("--loops", nargs="+", choices=("uvloop", "asyncio"), default=["uvloop"],
                   help="event loop(s) of the runs, each case on each (default uvloop)")
    p.add_argument("--json", default=None)
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--breakdown", type=int, choices=sorted(LINES), default=None,
                      help="instead: the driver's time per phase in the loop with this many slaves")
    mode.add_argument("--bare", type=int, choices=sorted(LINES), default=None,
                      help="instead: a bare pysoem loop against the driver (1 kHz, split), alternately, "
                           "--rounds times each with this many slaves")
    mode.add_argument("--send-after-work", type=int, choices=sorted(LINES), default=None,
                      help="instead: the bare loop's send after none, spin or memory work, alternating")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--exchange", choices=("split", "immediate"), default="split",
                   help="with --breakdown: the driver's exchange (default split)")
    p.add_argument("--spin-guard-us", type=float, default=0.0,
                   help="[realtime] spin_guard_us of the runs (wake early and spin to the deadline)")
    args = p.parse_args(argv)
    if os.geteuid() != 0:
        print("benchmarks.ethercat needs root (veth pair, network namespace, raw socket)", file=sys.stderr)
        return 2
    if args.breakdown:
        result = breakdown(args.breakdown, round(args.seconds * 1000), args.exchange)
        print(json.dumps(result))
        write_json(args.json, {"benchmark": "ethercat_breakdown", **result})
        return 0
    if args.send_after_work:
        rows = send_after_work(args.send_after_work, args.rounds)
        print(table(rows, [("between", "between receive and send"), ("cycles", "cycles"),
                           ("work_p50_us", "work p50 µs"), ("send_p50_us", "send p50 µs"),
                           ("send_p90_us", "send p90 µs"), ("steal_percent", "steal %")]))
        write_json(args.json, {"benchmark": "ethercat_send_after_work", "rows": rows})
        return 0
    if args.bare:
        pairs = []
        for _ in range(args.rounds):
            pairs.append(bare_case(args.bare, args.seconds))
            print(json.dumps(pairs[-1]), flush=True)
            pairs.append({"loop": "aiohal driver", **run_case(args.bare, 1000, "split", args.seconds,
                                                                       args.spin_guard_us)})
            print(json.dumps(pairs[-1]), flush=True)
        print(table(pairs, [("loop", "loop"), ("slaves", "slaves"), ("wkc_errors", "WKC errors"),
                            ("exit_code", "exit"), ("faults", "faults"),
                            ("cpu_p50_us", "CPU p50 µs"), ("cpu_p99_us", "CPU p99 µs"),
                            ("inputs_p50_us", "inputs µs"), ("outputs_p50_us", "outputs µs"),
                            ("send_p50_us", "send µs"), ("steal_percent", "steal %")]))
        write_json(args.json, {"benchmark": "ethercat_bare", "rows": pairs})
        return 0
    rows = []
    for n in args.slaves:
        for rate in args.rates:
            for exchange in ("immediate", "split"):
                for loop in args.loops:
                    rows.append(run_case(n, rate, exchange, args.seconds, args.spin_guard_us, loop))
                    print(json.dumps(rows[-1]), flush=True)
    if args.soak:
        rows.append(run_case(25, 1000, "split", args.soak, args.spin_guard_us, args.loops[0]))
        print(json.dumps(rows[-1]), flush=True)
    columns = [("slaves", "slaves"), ("loop", "loop"), ("process_data_bytes", "PD bytes"), ("rate_hz", "Hz"), ("exchange", "exchange"),
               ("seconds", "s"), ("ticks", "ticks"), ("missed", "missed"), ("wkc_errors", "WKC errors"), ("frames_lost", "of which lost"),
               ("rtt_us_p50", "RTT p50 µs"), ("rtt_us_p99", "RTT p99 µs"),
               ("receive_wait_us_p50", "wait p50 µs"), ("receive_wait_us_p99", "wait p99 µs"),
               ("cpu_p50_us", "driver CPU p50 µs"), ("cpu_p99_us", "CPU p99 µs"),
               ("lateness_p99_us", "lateness p99 µs"), ("faults", "faults"), ("exit_code", "exit"),
               ("steal_percent", "steal %")]
    print(table(rows, columns))
    write_json(args.json, {"benchmark": "ethercat", "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
