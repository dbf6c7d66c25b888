"""The NRT hand: the simulated backend, its service behind the pipe, the ``nrt_hand`` driver in
the fast loop (subprocess and thread), a hand process killed or stalled mid-run, and the
``sequence`` controller that moves, grasps and moves again."""

from __future__ import annotations

import asyncio
import re
import time

import numpy as np
import pytest
from conftest import host_stalls_tolerated, require_module
from helpers import arm_raw

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.core.run_report import format_report
from aiohal.drivers.hands.base import FAULT_BACKEND, HandError
from aiohal.drivers.hands.messages import HandCommandMsg, HandStateMsg
from aiohal.drivers.hands.sim import SimHand
from aiohal.errors import ConfigError, DriverError
from aiohal.pipe import NrtPeer
from aiohal.robot import Fault

SERVICE = "aiohal.drivers.hands.service:serve"


def _wait_for(condition, timeout_s: float, poll_s: float = 0.005):
    """Poll ``condition`` until it returns something truthy, at most ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(poll_s)
    return condition()


def test_sim_hand_closes_on_an_object_and_opens_again():
    hand = SimHand(stroke_time_s=0.2, object_at=0.6, io_time_s=(0.0, 0.0), activation_s=0.0)
    hand.open()
    hand.command(1.0, 1.0, 0.5)
    status = _wait_for(lambda: (s := hand.read()).object_detected and s, 2.0)
    assert status.ready and status.position == pytest.approx(0.6)
    assert status.effort == pytest.approx(0.5)
    hand.command(0.0, 1.0, 0.5)
    status = _wait_for(lambda: (s := hand.read()).position < 1e-9 and s, 2.0)
    assert not status.object_detected and status.effort == 0.0


def test_sim_hand_speed_sets_the_closing_rate():
    hand = SimHand(stroke_time_s=1.0, io_time_s=(0.0, 0.0), activation_s=0.0)
    hand.open()
    c0 = time.monotonic()
    hand.command(1.0, 0.5, 1.0)
    c1 = time.monotonic()
    time.sleep(0.2)
    r0 = time.monotonic()
    moved = hand.read().position
    r1 = time.monotonic()
    # half speed: half a stroke per second, between the earliest and latest the calls can have run
    assert 0.5 * (r0 - c1) - 1e-6 <= moved <= 0.5 * (r1 - c0) + 1e-6
    assert moved > 0.05


def test_sim_hand_activation_failure_is_a_hand_error():
    with pytest.raises(HandError) as info:
        SimHand(fail_open=True).open()
    assert info.value.code == FAULT_BACKEND and "activation" in info.value.reason


@pytest.mark.parametrize("mode", ["thread", "subprocess"])
def test_service_answers_commands_through_the_pipe(mode):
    options = {"backend_options": {"object_at": 0.4, "stroke_time_s": 0.2}, "rate_hz": 100}
    peer = NrtPeer.start(SERVICE, options, mode=mode)
    try:
        fast = peer.fast
        assert _wait_for(lambda: isinstance(fast.receive_latest(), HandStateMsg), 5.0)
        command = HandCommandMsg(grasp=1.0, speed=1.0, force=0.7)
        assert fast.send(command)

        def grasped():
            msg = fast.receive_latest()
            return isinstance(msg, HandStateMsg) and msg.object_detected and msg

        state = _wait_for(grasped, 3.0)
        assert state, "the hand never reported the object"
        assert state.position == pytest.approx(0.4) and state.effort == pytest.approx(0.7)
        assert state.command_seq == command.seq and state.ready and state.fault == 0
        # about 100 Hz, a slow loop and not a busy one: the median interval between the states'
        # own send stamps (a stall of this shared VM delays some, not the median)
        stamps: list[int] = []

        def collect() -> bool:
            stamps.extend(m.stamp_ns for m in fast.receive_all() if isinstance(m, HandStateMsg))
            return len(stamps) >= 21

        assert _wait_for(collect, 5.0), f"only {len(stamps)} states in 5 s"
        interval_ms = float(np.median(np.diff(stamps))) / 1e6
        assert 5.0 <= interval_ms <= 50.0, interval_ms  # (10 ms asked; a starved host slows the hand's process)
    finally:
        peer.stop(2.0)
    assert not peer.alive()


# ---------------------------------------------------------------- in the fast loop


def hand_raw(mode: str = "subprocess", steps=None, **options) -> dict:
    """A 2-joint mock arm plus a hand joint served by ``nrt_hand``, on the real clock."""
    raw = arm_raw(2)
    # the loop's stall watchdog at 5 s: a stall of this whole shared VM (1.3 s seen) would trip
    # the default 500 ms; the watchdog is tested elsewhere
    raw["loop"] = {"rate_hz": 500, "clock": "auto", "max_feedback_age": 20, "stall_timeout_ms": 5000}
    raw["joints"]["gripper"] = {"position": [0.0, 1.0], "velocity": 2.0, "effort": 1.0}
    raw["devices"] = {"gripper": {"type": "hand", "joint": "gripper"}}
    hand_options = {
        "mode": mode,
        "rate_hz": 100,
        "backend_options": {"object_at": 0.5, "stroke_time_s": 0.2, "io_time_s": [0.001, 0.004]},
        # generous: this shared host stalls the hand's process for 150-200 ms at times (seen in
        # CI); the stalled-hand test sets the thresholds it measures
        "stale_after_ms": 500,
        "dead_after_ms": 1500,
        "start_timeout_s": 20.0,  # the hand's subprocess imports numpy: seconds on a loaded host
        **options,
    }
    raw["driver"].append(
        {"type": "nrt_hand", "name": "hand", "joints": ["gripper"], "devices": ["gripper"], "options": hand_options}
    )
    raw["controller"] = {
        "type": "sequence",
        "params": {
            "steps": steps
            or [
                {"pose": {"j0": 0.3}, "duration": 0.2},
                {"hand": "gripper", "grasp": 1.0, "speed": 1.0, "force": 0.6, "timeout": 2.0},
                {"pose": {"j1": -0.3}, "duration": 0.2},
            ]
        },
    }
    return raw


class FaultWatch:
    """A publisher that records, per tick, the hand's fault bits (and can act at a tick).

    It also counts the ticks it ran: a stall of the host (seen up to a second in CI) adds
    clock ticks that never ran, so "how soon" is counted in ticks run."""

    def __init__(self, at_tick: int | None = None, action=None) -> None:
        self.at_tick, self.action = at_tick, action
        self.acted_tick = None
        self.ran = 0  # ticks this publisher ran
        self.acted_ran = None
        self.first = {}  # fault bit -> first tick seen
        self.first_ran = {}  # fault bit -> ticks run when first seen
        # every time the bit was newly set: (when the tick before ran, when this one ran)
        self.rises_ns = {Fault.STALE: [], Fault.HARDWARE: []}
        self._bits = 0
        self._last_ns = 0

    def __call__(self, loop: ControlLoop) -> None:
        tick = loop.robot.clock.tick
        self.ran += 1
        if self.at_tick is not None and self.acted_tick is None and tick >= self.at_tick:
            self.action(loop)
            self.acted_tick, self.acted_ran = tick, self.ran
        bits = int(loop.robot.hand.fault[0])
        now = time.monotonic_ns()
        for bit in (Fault.STALE, Fault.HARDWARE):
            if bits & bit and bit not in self.first:
                self.first[bit] = tick
                self.first_ran[bit] = self.ran
            if bits & bit and not self._bits & bit:
                self.rises_ns[bit].append((self._last_ns, now))
        self._bits, self._last_ns = bits, now

    def first_since(self, bit: int, since_ns: int) -> tuple[int, int]:
        """(tick before, tick) when ``bit`` was first newly set at or after ``since_ns``."""
        return next(rise for rise in self.rises_ns[bit] if rise[1] >= since_ns)


@pytest.mark.asyncio
@pytest.mark.parametrize("mode", ["subprocess", "thread"])
async def test_arm_moves_grasps_and_moves_again(mode):
    def until_done(loop):
        """Ends the run when the sequence is through (about 0.6 s of steps) and the arm stands
        at its last pose (the limits may hold the command back after a stall), within a bound
        of 20 s: a fixed 1.6 s window failed once in a full-suite run on a stalling host."""
        position = loop.robot.state.position
        if loop.controller.index >= 3 and abs(position[0] - 0.3) < 1e-9 and abs(position[1] + 0.3) < 1e-9:
            loop.request_stop("done")

    async with ControlLoop(parse_config(hand_raw(mode))) as loop:
        loop.add_publisher(until_done)
        report = await loop.run(ticks=10_000)
    assert report["stop_reason"] == "done"
    ctrl = report["controller"]
    assert ctrl["steps_done"] == 3, ctrl
    (grasp,) = ctrl["hand_steps"]
    assert grasp["outcome"] == "object" and grasp["position"] == pytest.approx(0.5, abs=0.02)
    assert report["faults"] == [] and report["safety_level"] == "run"
    assert report["drivers"]["hand"]["hand"] == "ok" and report["drivers"]["hand"]["mode"] == mode
    state = loop.robot.state
    assert state.position[0] == pytest.approx(0.3) and state.position[1] == pytest.approx(-0.3)
    assert state.position[2] == pytest.approx(0.5, abs=0.02)  # the hand joint shows the hand


@pytest.mark.asyncio
async def test_killing_the_hand_process_faults_the_hand_and_the_run_goes_on():
    raw = hand_raw(steps=[{"pose": {"j0": 0.5}, "duration": 0.5}])  # done well before the end
    watch = FaultWatch(at_tick=150, action=lambda loop: loop.slots[1].driver.peer.kill())

    def until_done(loop):
        """Ends the run once the hand's fault is seen and the arm stands at the end of its move
        (bounded by the run's ticks: a stall of the host skips ticks, so a fixed window could
        end first, and the limits then let the command catch up with the move at their rate)."""
        if (Fault.HARDWARE in watch.first and loop.controller.index >= 1
                and abs(loop.robot.state.position[0] - 0.5) < 1e-6):
            loop.request_stop("done")

    async with ControlLoop(parse_config(raw)) as loop:
        loop.add_publisher(watch)
        loop.add_publisher(until_done)
        report = await loop.run(ticks=10_000)
        level_during = loop.level
    assert report["stop_reason"] == "done"  # the run went on after the hand's death
    assert level_during.name == "RUN"  # the arm was not held for its hand
    assert loop.robot.state.position[0] == pytest.approx(0.5, abs=1e-6)  # and finished its move
    # peer death is seen at once (EOF), not when the state is dead_after_ms old (1.5 s = 750 ticks
    # here): within 150 ticks run (300 ms: the killed process must still get a CPU to exit,
    # and this shared host takes up to half of them at times)
    assert 0 < watch.first_ran[Fault.HARDWARE] - watch.acted_ran <= 150
    (fault,) = report["faults"]
    assert fault["source"] == "driver:hand"
    # EOF can come before the kernel has made the killed process a zombie: then the reason
    # says the pipe closed, and the exit code shows in the driver's health line below
    assert re.search(r"hand subprocess (exited \(code -9\)|closed its end of the pipe)", fault["error"])
    assert report["drivers"]["hand"]["hand"].startswith("lost:")
    assert report["drivers"]["hand"]["exitcode"] == -9


@pytest.mark.asyncio
async def test_a_stalled_hand_goes_stale_then_faulted_in_the_configured_time():
    raw = hand_raw(steps=[{"pose": {"j0": 0.2}, "duration": 0.5}], stall_after_s=0.3, stale_after_ms=60,
                   dead_after_ms=150)
    watch = FaultWatch()

    def until_dead(loop):
        """Ends the run once the hand was declared dead after its last state (bounded: a stall
        of the host skips ticks, so a fixed number of deadlines could end before it)."""
        rises = watch.rises_ns[Fault.HARDWARE]
        if (loop.robot.clock.tick >= 300 and rises  # the hand stalls 0.3 s in
                and rises[-1][1] >= loop.slots[1].driver.pipe.last_receive_ns):
            loop.request_stop("hand dead")

    async with ControlLoop(parse_config(raw)) as loop:
        loop.add_publisher(watch)
        loop.add_publisher(until_dead)
        report = await loop.run(ticks=10_000)
        driver = loop.slots[1].driver
        last_state_ns = driver.pipe.last_receive_ns
    # ages count from the last state received: never early, and seen by the first tick that
    # runs after the age is reached. So the tick before it ran in time; a stall of the host
    # between the two (seen up to a second in CI) only delays the tick that sees it. The 100 ms
    # are for the time inside that tick before (the read comes before this publisher).
    # A stall of the host before the hand's own stall can make it briefly stale (seen in CI):
    # what counts is the first time after its last state.
    for bit, age_ms in ((Fault.STALE, 60), (Fault.HARDWARE, 150)):
        before_ns, seen_ns = watch.first_since(bit, last_state_ns)
        assert seen_ns - last_state_ns >= age_ms * 1e6, (bit, seen_ns - last_state_ns)
        assert before_ns - last_state_ns <= (age_ms + 100) * 1e6, (bit, before_ns - last_state_ns)
    assert report["stop_reason"] == "hand dead"  # the run went on until then
    # (a stall of the host before the hand's own can add one such fault: the hand came back)
    assert report["faults"] and all("no state from the hand" in f["error"] for f in report["faults"])


@pytest.mark.asyncio
async def test_a_hand_that_cannot_start_fails_open_with_its_reason():
    raw = hand_raw(mode="thread", backend="no_such_module:Hand", start_timeout_s=2.0)
    loop = ControlLoop(parse_config(raw))
    loop.configure()
    with pytest.raises(DriverError) as info:
        await loop.activate()
    assert "did not start" in str(info.value) and "no_such_module" in str(info.value)
    await loop.deactivate()


@pytest.mark.asyncio
async def test_a_non_finite_grasp_is_never_sent():
    steps = [{"hand": "gripper", "grasp": 0.8, "timeout": 0.5}]
    async with ControlLoop(parse_config(hand_raw(mode="thread", steps=steps))) as loop:
        hand = loop.robot.hand["gripper"]
        driver = loop.slots[1].driver

        def poison(loop):
            hand.grasp[...] = np.nan

        watch = FaultWatch(at_tick=50, action=poison)
        loop.add_publisher(watch)
        await loop.run(ticks=150)
    assert driver._sent[0] == pytest.approx(0.8)


@pytest.mark.parametrize(
    "change, path",
    [
        (lambda raw: raw["driver"][1].update(devices=[]), "driver[1].devices"),
        (lambda raw: raw["driver"][1]["options"].update(dead_after_ms=10), "driver[1].options.dead_after_ms"),
        (lambda raw: raw["controller"]["params"]["steps"][0].pop("duration"), "controller.params.steps[0]"),
        (lambda raw: raw["controller"]["params"]["steps"][1].update(hand="j9"), "controller.params.steps[1].hand"),
    ],
)
def test_bad_hand_configs_name_the_key(change, path):
    raw = hand_raw()
    change(raw)
    with pytest.raises(ConfigError) as info:
        parse_config(raw)
    assert path in [issue.path for issue in info.value.issues], info.value.issues


# ---------------------------------------------------------------- the Modbus gripper in the loop


@pytest.mark.asyncio
async def test_robotiq_gripper_in_the_loop_grasps_then_reports_a_fault_and_a_lost_link():
    require_module("pymodbus")
    from aiohal.drivers.hands.robotiq_sim import running_in_process

    # the server in its own process: in a thread it would take the test loop's GIL per request
    with running_in_process(host="127.0.0.1", port=0, activation_time_s=0.05, object_position=0.5) as server:
        steps = [{"hand": "gripper", "grasp": 1.0, "speed": 1.0, "force": 0.5, "timeout": 2.0}]
        raw = hand_raw(
            mode="subprocess",
            steps=steps,
            backend="robotiq",
            backend_options={"host": "127.0.0.1", "port": server.port, "timeout_s": 0.5},
            stale_after_ms=100,
            dead_after_ms=1500,  # (the lost link is reported by the service, code 0x2)
        )
        watch = FaultWatch()

        async def break_things(loop):
            """After 600 ticks run the gripper faults; after 900 its server goes away (off
            the tick: the server's calls block). Ticks run, not clock ticks: a stall of the
            host skips ticks."""
            for at_tick, call in ((600, lambda: server.inject_fault(0xE)), (900, server.stop)):
                while watch.ran < at_tick:
                    await asyncio.sleep(0.005)
                await asyncio.to_thread(call)

        def until_link_lost(loop):
            if any("reports fault code 0x2" in f.error for f in loop.faults):
                loop.request_stop("link loss reported")

        async with ControlLoop(parse_config(raw)) as loop:
            loop.add_publisher(watch)
            loop.add_publisher(until_link_lost)
            breaker = asyncio.create_task(break_things(loop))
            report = await loop.run(ticks=20000)  # (bounded: 40 s)
            await asyncio.wait_for(breaker, 5.0)
            final_fault = loop.robot.hand["gripper"].fault
    (grasp,) = report["controller"]["hand_steps"]
    assert grasp["outcome"] == "object" and grasp["position"] == pytest.approx(0.5, abs=0.01)
    errors = [f["error"] for f in report["faults"]]
    # VENDOR_FAULT_BASE + 0xE, with what it means
    assert any("reports fault code 0x10e (Robotiq gFLT 0xE: overcurrent)" in e for e in errors), errors
    (hand_health,) = [d for d in report["drivers"].values() if d["type"] == "nrt_hand"]
    assert "faulted: 0x10e (Robotiq gFLT 0xE: overcurrent)" in hand_health["hand"]  # never "ok" after a fault
    assert "hand ok" not in format_report(report)
    assert any("reports fault code 0x2" in e for e in errors), errors  # FAULT_COMMUNICATION: link lost
    assert final_fault & Fault.HARDWARE
    assert watch.first_ran[Fault.HARDWARE] >= 600  # no fault before the injected one
    assert report["stop_reason"] == "link loss reported"  # the run went on through the gripper's fault


def test_shipped_arm_and_hand_config_moves_grasps_and_moves_again(tmp_path):
    """configs/kuka_lwr_hand_sim.toml as a user runs it: MuJoCo arm in the loop, hand in a subprocess
    (its steps take about 5.4 s; 9 s leaves room for a hand step that waits up to its timeout)."""
    import json
    import subprocess
    import sys

    from conftest import CONFIGS

    require_module("mujoco")
    report_path = tmp_path / "report.json"
    # as shipped, but for the hand's stale/dead ages: this shared host stalls the hand's
    # process for longer than 300 ms at times (the ages are tested with the pipe); and the
    # robot's process, for 26 ms once, beside the parallel tests on a quiet host
    text = (CONFIGS / "kuka_lwr_hand_sim.toml").read_text()
    config = tmp_path / "kuka_lwr_hand_sim.toml"
    config.write_text(host_stalls_tolerated(text.replace("stale_after_ms = 100", "stale_after_ms = 500")
                                            .replace("dead_after_ms = 300", "dead_after_ms = 2000")
                                            .replace('model = "models/', f'model = "{CONFIGS}/models/')))
    assert "dead_after_ms = 2000" in config.read_text() and str(CONFIGS) in config.read_text()
    proc = subprocess.run(
        [sys.executable, "-m", "aiohal", str(config), "--duration", "9",
         "--quiet", "--report-json", str(report_path)],
        capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads(report_path.read_text())
    ctrl = report["controller"]
    assert ctrl["steps_done"] == 3, ctrl
    (grasp,) = ctrl["hand_steps"]
    assert grasp["outcome"] == "object" and grasp["position"] == pytest.approx(0.6, abs=0.02)
    assert report["faults"] == [] and report["drivers"]["hand"]["hand"] == "ok"


def test_hand_for_joint_finds_the_hand_each_joint_carries():
    from aiohal.robot import JointSpec, Robot

    joints = [JointSpec(name, i, -1.0, 1.0, 1.0, 10.0, 10.0) for i, name in enumerate(("l_wrist", "r_wrist", "neck"))]
    robot = Robot("two_hands", joints, devices=[("left", "hand", "l_wrist"), ("right", "hand", "r_wrist")])
    view = robot.controller_view()
    for finder in (robot.hand_for_joint, view.hand_for_joint):
        assert finder("l_wrist") is robot.hand["left"]
        assert finder("r_wrist") is robot.hand["right"]
        with pytest.raises(KeyError, match="no hand is carried by joint 'neck'"):
            finder("neck")
