"""The fault matrix: every fault aiohal knows, injected, with the safety level it reaches and
how soon. docs/safety.md shows the same table; a bus that lands joins both.

In-process faults are injected at a known tick on the virtual clock (the tick the level
changes is exact); the stall of the event loop and the frozen process run on the real clock,
where the bound is the watchdog's time (a frozen process: ``watchdog_ms`` + 5 ms, measured by
the simulated hardware: the UDP board of the mock driver, and the simulated EtherCAT slaves).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import CONFIGS, ROOT, require_root
from test_hand import FaultWatch, hand_raw
from test_safety_paths import Stuck
from test_ethercat_driver import At, in_thread, raw_config, segment, sim  # noqa: F401  (fixtures)
from test_watchdog import WATCHDOG_MS, SLACK_MS, Board, board, start_robot  # noqa: F401  (board: fixture)

from aiohal.config import parse_config
from aiohal.errors import DriverError
from aiohal.hal import Controller
from aiohal.loop import ControlLoop
from aiohal.robot import Fault
from helpers import arm_raw, register_driver, virtual_loop

AT = 200  # the tick a fault is injected at
MAX_AGE = 20  # loop.max_feedback_age of these runs


def two_drivers(**right_faults) -> dict:
    """Joints j0, j1 on driver "left", j2, j3 on "right" (the one that fails)."""
    raw = arm_raw(4)
    raw["loop"]["max_feedback_age"] = MAX_AGE
    raw["driver"] = [{"type": "mock", "name": "left", "joints": ["j0", "j1"]},
                     {"type": "mock", "name": "right", "joints": ["j2", "j3"],
                      "options": {"faults": right_faults}}]
    raw["controller"] = {"type": "sine", "params": {"amplitude": 0.2, "frequency": 0.5}}
    return raw


class FailsAt(Controller):
    """A sine-like move that fails at tick AT: raising, or writing NaN."""

    def __init__(self, how: str) -> None:
        self.how = how

    def start(self, t):
        self.q0 = self.robot.state.position.copy()

    def update(self, t, dt):
        if self.robot.clock.tick >= AT:
            if self.how == "raise":
                raise RuntimeError("controller bug")
            self.robot.command.position[:] = np.nan
            return
        self.robot.command.position[:] = self.q0 + 0.1 * np.sin(t)


def level_change(report: dict, level: str) -> dict:
    return next(t for t in report["safety"] if t["after"] == level)


# fault, how it is injected, the level reached, the tick it is reached at, the fault's source
IN_PROCESS = [
    ("driver raises in read", dict(raw=two_drivers(read_error_at_tick=AT)), "hold", AT, "driver:right"),
    ("driver raises in write", dict(raw=two_drivers(write_error_at_tick=AT)), "hold", AT, "driver:right"),
    ("stale feedback", dict(raw=two_drivers(feedback_lost_at_tick=AT)), "hold", AT + MAX_AGE, "driver:right"),
    ("NaN command", dict(raw=two_drivers(), controller="nan"), "hold", AT, "controller:FailsAt"),
    ("controller raises", dict(raw=two_drivers(), controller="raise"), "hold", AT, "controller:FailsAt"),
    ("every driver failed", dict(raw=arm_raw(2) | {"driver": [{"type": "mock", "name": "arm", "joints": ["j0", "j1"],
                                                               "options": {"faults": {"read_error_at_tick": AT}}}]}),
     "estop", AT, "driver:arm"),
]


@pytest.mark.asyncio
@pytest.mark.parametrize("fault, inject, level, tick, source", IN_PROCESS, ids=[row[0] for row in IN_PROCESS])
async def test_in_process_faults_reach_their_level_on_the_tick_they_are_seen(fault, inject, level, tick, source):
    controller = FailsAt(inject["controller"]) if "controller" in inject else None
    loop = virtual_loop(inject["raw"], controller=controller)
    sent = []
    loop.add_publisher(lambda lp: sent.append(lp.robot.command.block.copy()))
    async with loop:
        report = await loop.run(ticks=AT + 200)
    assert report["safety_level"] == level
    change = level_change(report, level)
    assert change["tick"] == tick, change
    assert report["faults"][0]["source"] == source and report["faults"][0]["tick"] == tick
    assert all(np.isfinite(block).all() for block in sent)  # nothing non-finite reached a driver


@pytest.mark.asyncio
async def test_driver_raises_in_open_nothing_starts_and_the_others_are_stopped():
    loop = virtual_loop(two_drivers() | {"driver": [two_drivers()["driver"][0],
                                                    {**two_drivers()["driver"][1],
                                                     "options": {"faults": {"open_error": True}}}]})
    with pytest.raises(DriverError, match="open"):
        await loop.activate()
    assert loop.level.name == "OFF" and loop.state == "closed"
    assert loop.slots[0].driver.estops == 1 and loop.slots[0].driver.closed


@pytest.mark.asyncio
async def test_a_read_that_never_returns_estops_within_the_stall_timeout(monkeypatch):
    register_driver(monkeypatch, "stuck", f"{Stuck.__module__}:Stuck")
    raw = arm_raw(1)
    raw["driver"][0]["type"] = "stuck"
    raw["loop"] = {"rate_hz": 1000, "clock": "timerfd", "stall_timeout_ms": 100}
    loop = ControlLoop(parse_config(raw))
    seen = []
    loop.add_publisher(lambda lp: seen.append(time.monotonic_ns()))
    async with loop:
        report = await asyncio.wait_for(loop.run(ticks=10_000), timeout=10)
        stopped = time.monotonic_ns()
    assert report["safety_level"] == "estop" and level_change(report, "estop")["event"] == "watchdog"
    # the stall watchdog checks every timeout / 4: estop between 100 and 125 ms after the last tick
    # (plus the time the event loop takes to run the cancellation, measured up to `stopped`)
    assert 100 <= (stopped - seen[-1]) / 1e6
    assert loop.slots[0].driver.estopped >= 1


@pytest.mark.asyncio
async def test_a_site_leaving_its_workspace_holds_on_that_tick():
    from test_workspace import test_leaving_a_sphere_holds_the_robot_on_that_tick_with_site_and_distance as check

    await check()


@pytest.mark.asyncio
async def test_hand_process_death_faults_the_hand_and_the_arm_runs_on():
    raw = hand_raw(steps=[{"pose": {"j0": 0.5}, "duration": 0.5}])
    watch = FaultWatch(at_tick=150, action=lambda loop: loop.slots[1].driver.peer.kill())
    async with ControlLoop(parse_config(raw)) as loop:
        loop.add_publisher(watch)
        loop.add_publisher(lambda lp: lp.request_stop("seen") if Fault.HARDWARE in watch.first_ran else None)
        report = await loop.run(ticks=5000)
    assert report["safety_level"] == "run" and report["faults"][0]["source"] == "driver:hand"
    assert 0 < watch.first_ran[Fault.HARDWARE] - watch.acted_ran <= 150  # EOF of its pipe, within 150 ticks run


# ---------------------------------------------------------------- EtherCAT (simulated segment, root)


@pytest.mark.asyncio
@pytest.mark.parametrize("fault, command, level", [
    ("working-counter error, fewer than wkc_error_limit cycles", {"cmd": "wkc", "count": 3}, "run"),
    ("slave loss (cable break before drive 5)", {"cmd": "break", "slave": 4}, "estop"),
], ids=["wkc error", "slave loss"])
async def test_ethercat_faults_reach_their_level_within_the_error_limit(segment, fault, command, level):
    line = segment

    limit = 5
    raw = raw_config(line.ifname, wkc_error_limit=limit)
    at = At((800, in_thread(line.control, command)))
    ran = []
    loop = ControlLoop(parse_config(raw))
    loop.add_publisher(lambda lp: ran.append(lp.robot.clock.tick))
    loop.add_publisher(at)
    async with loop:
        report = await loop.run(ticks=2000)
        await asyncio.gather(*at.tasks)
    assert report["safety_level"] == level
    if level == "run":
        assert report["drivers"]["bus"]["wkc_errors"] >= 3 and report["faults"] == []
    else:
        change = level_change(report, level)
        # the break lands between two frames, sent from a thread: the bad cycles start at the
        # first tick after it; wkc_error_limit of them, then the slaves' states are read
        injected = next(k for k in ran if k >= 800)
        ticks_run = sum(1 for k in ran if injected <= k <= change["tick"])
        assert ticks_run <= limit + 50, (injected, change)  # + the thread's latency on this host
        # the driver fails (hold), and with no driver left the loop stops everything, same tick
        assert [(t["source"], t["after"], t["tick"]) for t in report["safety"][1:3]] == [
            ("driver:bus", "hold", change["tick"]), ("loop", "estop", change["tick"])]


def test_a_frozen_process_is_stopped_by_the_watchdog_process_within_its_time(tmp_path, board):
    require_root("SCHED_FIFO for the robot, its watchdog process and the simulated board")
    proc, report_path, _ = start_robot(tmp_path, board)
    try:
        time.sleep(0.3)  # let it tick a while; nothing is sent while it does
        assert board.received == []
        frozen = time.monotonic_ns()
        proc.send_signal(signal.SIGSTOP)
        assert board.arrived.wait(2.0), "no e-stop datagram from the watchdog process"
        arrived, payload = board.received[0]
        took_ms = (arrived - frozen) / 1e6
        assert payload == b"ESTOP arm"
        print(f"e-stop datagram {took_ms:.2f} ms after SIGSTOP")
        assert took_ms <= WATCHDOG_MS + SLACK_MS, took_ms
        proc.send_signal(signal.SIGCONT)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    report = json.loads(report_path.read_text())
    # back from the freeze, the robot knows the hardware was stopped: estop, by the watchdog
    assert [t["event"] for t in report["safety"]][-2:] == ["watchdog", "deactivate"], report["safety"]
    assert any(f["source"] == "watchdog" for f in report["faults"])
    assert proc.returncode == 1




ROBOT_SCRIPT = """
import asyncio, json, sys
from aiohal.config import parse_config
from aiohal.loop import ControlLoop

async def main():
    loop = ControlLoop(parse_config(json.loads(sys.argv[1])))
    async with loop:
        # once: the drives are enabled and the loop ticks
        loop.add_publisher(lambda lp: print("ticking", flush=True) if lp.robot.clock.tick == 200 else None)
        await loop.run(30.0)

asyncio.run(main())
"""


def test_a_frozen_robot_process_leaves_the_simulated_drives_safe_within_the_watchdog_time(tmp_path):
    import tomllib

    from conftest import start_segment

    sim = start_segment("drive*7,imu,ft", watchdog_ms=1000)
    proc = None
    try:
        os.sched_setscheduler(sim.pid, os.SCHED_FIFO, os.sched_param(95))  # the hardware does not stall
        raw = tomllib.loads((CONFIGS / "ethercat_sim.toml").read_text())
        raw["loop"].update(max_feedback_age=5000, stall_timeout_ms=5000)
        raw["safety"] = {"watchdog_ms": WATCHDOG_MS}
        raw["driver"][0]["options"].update(interface=sim.ifname, sm_watchdog_ms=WATCHDOG_MS,
                                           receive_timeout_us=2000, frame_timeout_us=50_000,
                                           keepalive_after_ms=5.0)
        proc = subprocess.Popen([sys.executable, "-c", ROBOT_SCRIPT, json.dumps(raw)], cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        import select

        ready, _, _ = select.select([proc.stdout], [], [], 60)
        line = proc.stdout.readline().strip() if ready else ""
        if line != "ticking":
            proc.kill()
            pytest.fail(f"the robot did not tick: {proc.communicate(timeout=10)[1][-3000:]}")
        slaves = sim.status()["slaves"]
        drives = [s for s in slaves if s["kind"] == "drive"]
        assert len(drives) == 7
        assert all(d["device"]["state"] == "operation_enabled" and d["watchdog_ms"] == WATCHDOG_MS for d in drives)
        frozen = time.monotonic_ns()
        proc.send_signal(signal.SIGSTOP)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:  # bounded: until every drive's slave has tripped
            drives = [s for s in sim.status()["slaves"] if s["position"] in {d["position"] for d in drives}]
            if all(d["watchdog_trip"] for d in drives):
                break
            time.sleep(0.01)
        for d in drives:
            trip, device = d["watchdog_trip"], d["device"]
            assert trip is not None, d
            # measured by the simulated slave: from its last outputs to its drive's safe state
            since_outputs_ms = (trip["tripped_ns"] - trip["last_output_ns"]) / 1e6
            since_freeze_ms = (device["outputs_lost_ns"] - frozen) / 1e6
            print(f"{d['name']}: safe {since_outputs_ms:.2f} ms after its last outputs, "
                  f"{since_freeze_ms:.2f} ms after SIGSTOP")
            assert trip["last_output_ns"] >= frozen - 2_000_000  # this freeze's, not an earlier trip
            assert since_outputs_ms <= WATCHDOG_MS + SLACK_MS
            assert since_freeze_ms <= WATCHDOG_MS + SLACK_MS
            assert device["state"] in ("switch_on_disabled", "quick_stop_active", "fault"), device["state"]
            assert d["state"] == "SAFEOP" and d["al_status_code"] == 0x001B
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        sim.stop()
