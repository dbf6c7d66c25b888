"""The fault matrix: every fault aiohal knows, injected, with the safety level it reaches and
how soon. docs/safety.md shows the same table; a bus that lands joins both.

In-process faults are injected at a known tick on the virtual clock (the tick the level
changes is exact); the stall of the event loop and the frozen process run on the real clock,
where the bound is the watchdog's time (a frozen process: ``watchdog_ms`` + 5 ms, measured by
the simulated hardware: the UDP board of the mock driver, the simulated UDP joint boards and
the simulated EtherCAT slaves).
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
from conftest import CONFIGS, HOST_UNFIT, ROOT, HostReference, require_root
from helpers import Reported, arm_raw, register_driver, virtual_loop
from test_canopen_driver import SINE, channel, driver_of
from test_canopen_driver import raw_config as can_config
from test_ethercat_driver import At, in_thread, raw_config, segment, sim  # noqa: F401  (fixtures)
from test_fri import Krc
from test_hand import FaultWatch, hand_raw
from test_safety_paths import Stuck
from test_udp_driver import KEY, KEY_HEX
from test_udp_driver import _config as udp_config
from test_watchdog import SLACK_MS, WATCHDOG_MS, Board, board, start_robot  # noqa: F401  (board: fixture)
from udp_helpers import wait_for

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.drivers.fri.protocol import State
from aiohal.errors import DriverError
from aiohal.hal import Controller
from aiohal.robot import Fault

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
    assert (stopped - seen[-1]) / 1e6 >= 100
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


@pytest.mark.realtime  # the keep-alive thread must get its cycles in within the stall: run alone
@pytest.mark.asyncio
async def test_ethercat_wkc_errors_in_a_stall_count_in_the_health(segment):
    """The tick stalls (100 ms, five times keepalive_after_ms) right after the segment was told
    to answer its next 3 frames short: the keep-alive cycles the bus meanwhile and meets them,
    and they count as the tick's own would."""
    raw = raw_config(segment.ifname, wkc_error_limit=5)

    def stall(lp) -> None:
        segment.control({"cmd": "wkc", "count": 3})
        time.sleep(0.1)

    async with ControlLoop(parse_config(raw)) as loop:
        loop.add_publisher(At((200, stall)))  # from tick 200: a stall of the host may skip it
        report = await loop.run(ticks=400)
    health = report["drivers"]["bus"]
    assert health["keepalive_cycles"] >= 3, health
    assert health["wkc_errors"] >= 3 and report["faults"] == [] and report["safety_level"] == "run", health


@pytest.mark.realtime
def test_a_frozen_process_is_stopped_by_the_watchdog_process_within_its_time(tmp_path, board):
    require_root("SCHED_FIFO for the robot, its watchdog process and the simulated board")
    proc, report_path, _ = start_robot(tmp_path, board)
    host = HostReference(SLACK_MS, priority=90)  # the watchdog process's priority
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
        proc.send_signal(signal.SIGCONT)
        proc.send_signal(signal.SIGINT)
        _out, _err = proc.communicate(timeout=30)
        host.require_fit()
        assert took_ms <= WATCHDOG_MS + SLACK_MS, took_ms
    finally:
        host.stop()
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    report = json.loads(report_path.read_text())
    # back from the freeze, the robot knows the hardware was stopped: estop, by the watchdog
    assert [t["event"] for t in report["safety"]][-2:] == ["watchdog", "deactivate"], report["safety"]
    assert any(f["source"] == "watchdog" for f in report["faults"])
    assert proc.returncode == 1




# ---------------------------------------------------------------- CANopen (virtual bus, in process)


class TickTimes:
    """A publisher: each tick run and the CLOCK_MONOTONIC time its publishers ran (after its read)."""

    def __init__(self) -> None:
        self.ticks: list[int] = []
        self.times: list[float] = []

    def __call__(self, loop) -> None:
        self.ticks.append(loop.robot.clock.tick)
        self.times.append(time.monotonic())

    def at(self, tick: int) -> float:
        return self.times[self.ticks.index(tick)]


@pytest.mark.realtime  # its bound is the heartbeat's timing: run apart from the parallel tests
@pytest.mark.asyncio
async def test_can_heartbeat_loss_fails_the_driver_within_its_timeout():
    timeout_ms, heartbeat_ms, at = 100.0, 10, 50
    raw = can_config(channel(), SINE, heartbeat_ms=heartbeat_ms, heartbeat_timeout_ms=timeout_ms)
    async with ControlLoop(parse_config(raw)) as loop:
        driver = driver_of(loop)
        times = TickTimes()
        loop.add_publisher(times)
        silenced: list[int] = []  # the tick it was silenced at: a stall of the host may skip ``at``

        def silence(lp):
            driver.sim.drives[3].go_silent()
            silenced.append(lp.robot.clock.tick)

        loop.add_publisher(At((at, silence)))
        report = await loop.run(ticks=1500)
    if len(report["safety"]) > 1 and report["safety"][1]["source"] == "feedback":
        # a stall of this host delayed the heartbeat's verdict (silence while the process was
        # stalled is not the node's) and the loop's stale-feedback check held the robot first:
        # safe; the heartbeat's timing is not this run's to judge
        pytest.skip(f"{HOST_UNFIT}: the stale-feedback check came first ({report['safety'][1:3]})")
    assert any("heartbeat lost" in f["error"] for f in report["faults"]), report["faults"]
    # the driver fails (hold), and with no driver left the loop stops everything, same tick
    change = level_change(report, "hold")
    assert [(t["source"], t["after"], t["tick"]) for t in report["safety"][1:3]] == [
        ("driver:bus", "hold", change["tick"]), ("loop", "estop", change["tick"])]
    assert "heartbeat lost" in report["faults"][0]["error"] and report["safety_level"] == "estop"
    # detection time: the node's last heartbeat + the timeout, checked every tenth of it. Not
    # before (its last heartbeat came at most heartbeat_ms after the node was silenced), and
    # the tick before the failing one read no later than one check and one tick past it
    due = float(driver._heard[2]) + timeout_ms / 1e3
    period = 1 / raw["loop"]["rate_hz"]
    assert (change["tick"] - silenced[0]) * period >= (timeout_ms - heartbeat_ms) / 1e3 - period
    before = max(k for k in times.ticks if k < change["tick"])
    print(f"heartbeat loss: failed at tick {change['tick']}, {change['tick'] - silenced[0]} ticks of "
          f"{1e3 * period:g} ms after the node went silent (timeout {timeout_ms:g} ms)")
    assert times.at(before) < due + timeout_ms / 1e4 + period


@pytest.mark.asyncio
async def test_can_emcy_drive_fault_holds_the_robot_on_the_next_tick():
    at = 50
    async with ControlLoop(parse_config(can_config(channel(), SINE))) as loop:
        driver = driver_of(loop)
        pending: list[int] = []  # ticks after whose read the EMCY had arrived, not yet handled
        injected: list[int] = []

        def watch(lp):
            tick = lp.robot.clock.tick
            if tick >= at and not injected:  # a stall of the host may skip tick ``at`` itself
                injected.append(tick)
                driver.sim.drives[2].inject_fault(0x2310)
            if driver._emcy and not pending:
                pending.append(tick)
            if lp.level.name != "RUN" and tick > at + 5:
                lp.request_stop("held")

        loop.add_publisher(watch)
        report = await loop.run(ticks=1000)
    change = level_change(report, "hold")
    assert report["safety_level"] == "hold" and change["source"] == "driver:bus"
    assert change["tick"] >= injected[0]
    # read by the notifier thread between two ticks: handled by the next tick's read (the
    # drive's statusword may show the fault first, in the same or an earlier tick)
    assert not pending or change["tick"] <= pending[0] + 1, (change, pending)
    assert any("0x2310" in f["error"] for f in report["faults"])


# ---------------------------------------------------------------- UDP joint boards (simulated, loopback)


@pytest.mark.asyncio
async def test_udp_board_silence_fails_the_driver_after_silent_ticks():
    silent = 25
    raw = udp_config(3, silent_ticks=silent, simulation={"die_board": 2, "die_after_s": 0.1})
    loop = ControlLoop(parse_config(raw))
    ran: list[int] = []
    loop.add_publisher(lambda lp: ran.append(lp.robot.clock.tick))
    async with loop:
        report = await loop.run(duration=1.0)
    change = level_change(report, "hold")
    assert [(t["source"], t["after"], t["tick"]) for t in report["safety"][1:3]] == [
        ("driver:boards", "hold", change["tick"]), ("loop", "estop", change["tick"])]
    last = int(loop.slots[0].driver.board_tick[1])  # board 2's last answer
    # the first tick run more than silent_ticks after it
    assert change["tick"] == min(k for k in [*ran, change["tick"]] if k - last > silent), (last, change)
    assert "board(s) [2] silent" in report["faults"][0]["error"]


@pytest.mark.asyncio
async def test_udp_forgery_moves_nothing_is_counted_and_the_robot_runs_on():
    import socket

    from aiohal.drivers.udp.protocol import COMMAND_RECORD, STATE_RECORD, Kind, encode

    raw = udp_config(3, key=KEY_HEX, silent_ticks=200)  # the boards' process at its priority (where allowed)
    loop = ControlLoop(parse_config(raw))
    reach = [0.0]
    forged = []
    forger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    forger.bind(("127.0.0.1", 0))

    def forge(lp):
        reach[0] = max(reach[0], float(np.abs(lp.robot.state.position).max()))
        if lp.robot.clock.tick < AT or forged:  # once, at the first tick run from AT (a stall skips ticks)
            return
        forged.append(lp.robot.clock.tick)
        driver = lp.slots[0].driver
        state = np.zeros(1, dtype=STATE_RECORD)
        state["position"] = 1.5
        command = np.zeros(1, dtype=COMMAND_RECORD)
        command["mode"], command["position"] = 1, 1.5
        for board_id, address in zip(driver.board_ids, driver.addresses, strict=True):
            # to the driver: states with the right key from a stranger, with a wrong key
            forger.sendto(bytes(encode(Kind.STATE, board_id, 1 << 30, driver._seq, state, KEY)), driver.sock.getsockname())
            forger.sendto(bytes(encode(Kind.STATE, board_id, 1 << 30, driver._seq, state, bytes(16))), driver.sock.getsockname())
            # to the board: a command with the right key from a stranger
            forger.sendto(bytes(encode(Kind.COMMAND, board_id, 1 << 30, 0, command, KEY)), address)

    loop.add_publisher(forge)
    try:
        async with loop:
            report = await loop.run(ticks=AT + 200)
    finally:
        forger.close()
    health = loop.report()["drivers"]["boards"]
    assert report["safety_level"] == "run" and report["faults"] == []
    assert health["unauthenticated"] == 2 * 3 and health["simulated_boards"]["unauthenticated"] == 3
    assert reach[0] < 0.5  # the sine's 0.2 rad: no joint went toward the forged 1.5


@pytest.mark.realtime
def test_a_frozen_process_gets_the_udp_boards_e_stopped_by_the_watchdog_process():
    """The boards take datagrams only from the master's address and with its key: the
    watchdog process sends the ESTOP from the driver's own socket, with the MAC."""
    import socket
    import threading

    from aiohal.drivers.udp.sim import BoardSimulator

    require_root("SCHED_FIFO for the robot, its watchdog process and the simulated boards")
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    master = probe.getsockname()
    probe.close()  # the driver binds this port next
    sim = BoardSimulator([2, 2, 2], key=KEY, master=master, watchdog_ms=1000.0)

    def serve():
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(95))  # the boards do not stall
        sim.serve()

    sim._thread = threading.Thread(target=serve, daemon=True)
    sim._thread.start()
    raw = udp_config(6, seconds_rate=1000, key=KEY_HEX, silent_ticks=200)
    raw["driver"][0]["options"].update(
        simulate=False, bind_address=master[0], bind_port=master[1],
        boards=[{"id": b.id, "joints": [f"j{2 * i}", f"j{2 * i + 1}"], "port": b.sock.getsockname()[1]}
                for i, b in enumerate(sim.boards)])
    raw["loop"].update(max_feedback_age=5000, stall_timeout_ms=5000)
    raw["realtime"] = {"priority": 80}
    raw["safety"] = {"watchdog_ms": WATCHDOG_MS, "watchdog_priority": 90}
    proc = subprocess.Popen([sys.executable, "-c", ROBOT_SCRIPT, json.dumps(raw)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    host = None
    try:
        import select

        ready, _, _ = select.select([proc.stdout], [], [], 60)
        if (proc.stdout.readline().strip() if ready else "") != "ticking":
            proc.kill()
            pytest.fail(f"the robot did not tick: {proc.communicate(timeout=10)[1][-3000:]}")
        assert all(b.estops_at == [] and b.counters["commands"] > 100 for b in sim.boards)
        host = HostReference(SLACK_MS, priority=90)  # the watchdog process's priority
        frozen = time.monotonic()
        proc.send_signal(signal.SIGSTOP)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not all(b.estops_at for b in sim.boards):  # bounded
            time.sleep(0.005)
        host.require_fit()
        for b in sim.boards:
            assert b.estops_at, f"board {b.id} got no e-stop datagram ({b.counters})"
            arrived, last_command = b.estops_at[0]
            since_command_ms, since_freeze_ms = (arrived - last_command) * 1e3, (arrived - frozen) * 1e3
            print(f"board {b.id}: ESTOP {since_command_ms:.2f} ms after its last command, "
                  f"{since_freeze_ms:.2f} ms after SIGSTOP")
            assert last_command >= frozen - 0.002  # this freeze's last command
            assert since_command_ms <= WATCHDOG_MS + SLACK_MS and since_freeze_ms <= WATCHDOG_MS + SLACK_MS
            assert b.estopped
        assert sum(b.counters["unauthenticated"] + b.counters["malformed"] for b in sim.boards) == 0
    finally:
        if host is not None:
            host.stop()
        proc.kill()
        proc.wait(10)
        sim.stop()


# ---------------------------------------------------------------- FRI (simulated KRC, loopback)


@pytest.mark.realtime  # the KRC must reach command mode first: run apart, as tests/test_fri.py
@pytest.mark.host_reference(1.0, 60)  # as tests/test_fri.py: the KRC grades every answer
@pytest.mark.usefixtures("answers_at_fifo")
@pytest.mark.asyncio
async def test_fri_quality_drop_holds_the_robot_on_the_tick_it_is_measured():
    krc = Krc()
    await krc.open()
    d = krc.driver
    reported = Reported(d.view)
    d.view.attach(reported)
    try:
        krc.robot.command.position[:] = 0.1
        await krc.ticks(3)
        krc.sim.options.drop_answers = 0.6  # most answers lost: the KRC's statistics fall
        first_bad = None
        for _ in range(400):
            await krc.ticks(1)
            msr = d.msr
            if first_bad is None and (msr["quality"] < d.min_quality or msr["state"] != State.CMD):
                first_bad = d.view.clock.tick
                break
        assert first_bad is not None and reported.holds == [first_bad]  # the read that took it held the robot
        await wait_for(lambda: krc.sim.state == State.MON, timeout=5.0)  # the KRC's own drop to monitor mode
    finally:
        await krc.close()


ROBOT_SCRIPT = """
import asyncio, json, sys
from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop

async def main():
    loop = ControlLoop(parse_config(json.loads(sys.argv[1])))
    async with loop:
        # once, from tick 200 (a stall of the host may skip tick 200 itself): the drives are
        # enabled and the loop ticks
        said = []
        loop.add_publisher(lambda lp: None if said or lp.robot.clock.tick < 200
                           else (said.append(1), print("ticking", flush=True)))
        await loop.run(30.0)

asyncio.run(main())
"""


@pytest.mark.realtime
def test_a_frozen_robot_process_leaves_the_simulated_drives_safe_within_the_watchdog_time(tmp_path):
    import tomllib

    from conftest import start_segment

    sim = start_segment("drive*7,imu,ft", watchdog_ms=1000)
    proc = host = start = None
    try:
        os.sched_setscheduler(sim.pid, os.SCHED_FIFO, os.sched_param(95))  # the hardware does not stall
        raw = tomllib.loads((CONFIGS / "ethercat_sim.toml").read_text())
        raw["loop"].update(max_feedback_age=5000, stall_timeout_ms=5000)
        raw["safety"] = {"watchdog_ms": WATCHDOG_MS}
        raw["driver"][0]["options"].update(interface=sim.ifname, sm_watchdog_ms=WATCHDOG_MS,
                                           receive_timeout_us=2000, frame_timeout_us=50_000,
                                           keepalive_after_ms=5.0)
        # the bring-up's keep-alive must cycle the bus within the drives' short SM watchdog
        # time: a host that stalls the robot process longer trips them before the first tick
        start = HostReference(WATCHDOG_MS, priority=95)
        proc = subprocess.Popen([sys.executable, "-c", ROBOT_SCRIPT, json.dumps(raw)], cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        import select

        ready, _, _ = select.select([proc.stdout], [], [], 60)
        line = proc.stdout.readline().strip() if ready else ""
        if line != "ticking":
            proc.kill()
            _, err = proc.communicate(timeout=10)
            start.require_fit()
            pytest.fail(f"the robot did not tick: {err[-3000:]}")
        start.stop()
        slaves = sim.status()["slaves"]
        drives = [s for s in slaves if s["kind"] == "drive"]
        assert len(drives) == 7
        assert all(d["device"]["state"] == "operation_enabled" and d["watchdog_ms"] == WATCHDOG_MS for d in drives)
        host = HostReference(SLACK_MS, priority=95)  # the simulated segment's priority
        frozen = time.monotonic_ns()
        proc.send_signal(signal.SIGSTOP)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:  # bounded: until every drive's slave has tripped
            drives = [s for s in sim.status()["slaves"] if s["position"] in {d["position"] for d in drives}]
            if all(d["watchdog_trip"] for d in drives):
                break
            time.sleep(0.01)
        host.require_fit()
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
        for reference in (start, host):
            if reference is not None:
                reference.stop()
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        sim.stop()
