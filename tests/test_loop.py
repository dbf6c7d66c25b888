"""The control loop: lifecycle, the tick pipeline, fault isolation, limits before writes."""

from __future__ import annotations

import asyncio
import sys

import numpy as np
import pytest
from helpers import arm_raw, virtual_loop

from aiohal.errors import DriverError, LifecycleError
from aiohal.hal import Controller
from aiohal.robot import Fault, Mode
from aiohal.safety import SafetyLevel


def two_driver_raw(**faults_b):
    raw = arm_raw(4)
    raw["driver"] = [
        {"type": "mock", "name": "left", "joints": ["j0", "j1"]},
        {"type": "mock", "name": "right", "joints": ["j2", "j3"], "options": {"faults": faults_b}},
    ]
    return raw


@pytest.mark.asyncio
async def test_lifecycle_order_and_states():
    loop = virtual_loop(arm_raw(3))
    assert loop.state == "created"
    loop.configure()
    assert loop.state == "configured"
    mock = loop.slots[0].driver
    await loop.activate()
    assert loop.state == "active" and loop.level == SafetyLevel.RUN
    assert loop.slots[0].status == "open"
    report = await loop.run(ticks=250)
    assert report["ticks"] == 250 and loop.state == "active"
    assert mock.reads == 251  # one read at activation, one per tick
    assert mock.writes == 250
    await loop.deactivate()
    assert loop.state == "closed" and mock.closed and loop.level == SafetyLevel.OFF
    with pytest.raises(LifecycleError):
        await loop.run(ticks=1)


@pytest.mark.asyncio
async def test_activation_starts_from_measured_state_without_a_jump():
    raw = arm_raw(3)
    raw["driver"][0]["options"] = {"initial_position": {"j0": 0.3, "j1": -0.4, "j2": 1.0}}
    async with virtual_loop(raw) as loop:
        cmd = loop.robot.command
        assert np.allclose(cmd.position, [0.3, -0.4, 1.0])
        assert np.all(cmd.mode == Mode.POSITION)
        await loop.run(ticks=10)
        assert np.allclose(loop.robot.state.position, [0.3, -0.4, 1.0])


@pytest.mark.asyncio
async def test_run_stops_on_request_from_another_task():
    import asyncio

    async with virtual_loop(arm_raw(2)) as loop:
        async def stopper():
            while loop.robot.clock.tick < 42:
                await asyncio.sleep(0)
            loop.request_stop("test")

        task = asyncio.create_task(stopper())
        report = await loop.run()  # no duration: runs until the request
        await task
    assert report["stop_reason"] == "test"
    # the other task runs when the virtual clock yields (at least every ms of wall time)
    assert 42 <= report["ticks"] < 42 + 1000


@pytest.mark.asyncio
async def test_driver_read_failure_is_isolated_and_robot_holds():
    loop = virtual_loop(two_driver_raw(read_error_at_tick=100))
    async with loop:
        left, right = (s.driver for s in loop.slots)
        report = await loop.run(ticks=300)
    assert report["ticks"] == 300  # the loop went on
    assert report["safety_level"] == "hold"
    assert report["controller"]["type"] == "hold"
    [fault] = report["faults"]
    assert fault["source"] == "driver:right" and fault["phase"] == "read" and fault["tick"] == 100
    assert "injected read error" in fault["error"]
    assert report["drivers"]["right"]["status"] == "failed"
    assert report["drivers"]["left"]["status"] == "open"
    final = loop.report()  # after deactivation
    assert final["drivers"]["left"]["status"] == "closed" and final["drivers"]["right"]["status"] == "failed"
    assert right.estops == 1 and right.reads == 100  # not read again after failing
    assert left.reads == 301 and left.estops == 0
    assert np.all(loop.robot.state.fault[2:] & Fault.DRIVER)
    assert not np.any(loop.robot.state.fault[:2] & Fault.DRIVER)


@pytest.mark.asyncio
async def test_driver_write_failure_and_failing_estop_do_not_escape():
    loop = virtual_loop(two_driver_raw(write_error_at_tick=5, estop_error=True))
    async with loop:
        report = await loop.run(ticks=20)
    sources = [(f["source"], f["phase"]) for f in report["faults"]]
    assert ("driver:right", "write") in sources and ("driver:right", "estop") in sources
    assert report["ticks"] == 20 and report["safety_level"] == "hold"


@pytest.mark.asyncio
async def test_driver_that_fails_to_open_stops_bring_up_and_closes_the_others():
    raw = two_driver_raw(open_error=True)
    loop = virtual_loop(raw)
    with pytest.raises(DriverError) as info:
        await loop.activate()
    assert info.value.driver == "right" and info.value.phase == "open"
    assert isinstance(info.value, RuntimeError)
    left = loop.slots[0].driver
    assert left.closed and left.estops == 1 and loop.state == "closed"


class Exploding(Controller):
    """Moves joint 0 at constant speed, then raises at a given tick."""

    def __init__(self, at_tick: int, nan: bool = False):
        self.at_tick, self.nan = at_tick, nan

    def start(self, t):
        self.q0 = self.robot.state.position.copy()

    def update(self, t, dt):
        if self.robot.clock.tick >= self.at_tick:
            if self.nan:
                self.robot.command.position[0] = np.nan
                return
            raise ZeroDivisionError("controller bug")
        self.robot.command.position[:] = self.q0
        self.robot.command.position[0] = self.q0[0] + 1.0 * t  # 1 rad/s


@pytest.mark.parametrize("nan", [False, True], ids=["raises", "writes-nan"])
@pytest.mark.asyncio
async def test_controller_failure_switches_to_hold_without_a_jump(nan):
    loop = virtual_loop(arm_raw(2), controller=Exploding(at_tick=200, nan=nan))
    sent = []
    loop.add_publisher(lambda lp: sent.append(lp.limiter.last_position[0]))
    async with loop:
        report = await loop.run(ticks=600)
    assert report["controller"]["type"] == "hold"
    assert report["faults"][0]["tick"] == 200
    assert report["faults"][0]["phase"] == ("limits" if nan else "update")
    assert all(np.isfinite(sent))
    steps = np.abs(np.diff(sent))
    # before the fault the command moved 1 mrad per tick; after, it brakes at 20 rad/s²:
    # no step is larger than the last one plus one acceleration step
    assert steps.max() <= 1e-3 + 20.0 * 1e-6 + 1e-12
    # it comes to rest within the braking distance v²/2a = 25 mm past the fault position
    assert steps[-50:].max() == 0.0
    assert sent[-1] - sent[198] <= 1.0 / (2 * 20.0) + 1e-3


@pytest.mark.asyncio
async def test_commands_are_clamped_before_any_write():
    seen = []

    class Greedy(Controller):
        def update(self, t, dt):
            cmd = self.robot.command
            cmd.position[:] = 100.0  # far beyond the range, as a step
            cmd.velocity[:] = -50.0
            cmd.effort[:] = 1e6

    loop = virtual_loop(arm_raw(2), controller=Greedy())
    async with loop:
        mock = loop.slots[0].driver
        original_write = mock.write

        async def spy():
            seen.append(mock.view.command.block.copy())
            await original_write()

        mock.write = spy
        await loop.run(ticks=3000)
    first, last = seen[0], seen[-1]
    assert first[0, 0] == pytest.approx(2.0 * 1e-3)  # one tick at the 2 rad/s rate limit
    assert last[0, 0] == 2.0  # reached the position limit and stays there
    assert np.all(np.array([s[0] for s in seen]) <= 2.0)
    assert np.all(np.array([s[1] for s in seen]) >= -2.0)  # velocity limit
    assert np.all(np.array([s[2] for s in seen]) <= 50.0)  # effort limit
    # velocity command changes at most acceleration·dt = 0.02 per tick
    assert np.abs(np.diff([s[1, 0] for s in seen])).max() <= 0.02 + 1e-12


@pytest.mark.asyncio
async def test_lost_feedback_makes_the_robot_hold():
    raw = arm_raw(2, type="sine", params={"amplitude": 0.1, "frequency": 1.0})
    raw["loop"]["max_feedback_age"] = 20
    raw["driver"][0]["options"] = {"faults": {"feedback_lost_at_tick": 50, "feedback_lost_for": 100}}
    async with virtual_loop(raw) as loop:
        report = await loop.run(ticks=300)
    [fault] = report["faults"]
    assert fault["source"] == "driver:arm" and fault["phase"] == "check"
    assert fault["tick"] == 50 + 20  # last fresh at tick 49, stale when older than 20 ticks
    assert report["safety_level"] == "hold"
    assert report["drivers"]["arm"]["status"] == "open"  # not isolated: it may come back
    assert report["drivers"]["arm"]["feedback_lost_ticks"] == 100


@pytest.mark.asyncio
async def test_skipped_ticks_give_controller_the_real_dt():
    dts = []

    class Recorder(Controller):
        def update(self, t, dt):
            dts.append((self.robot.clock.tick, round(t, 9), round(dt, 9)))

    loop = virtual_loop(arm_raw(1), controller=Recorder())
    async with loop:
        loop.add_publisher(lambda lp: lp.source.stall(2) if lp.robot.clock.tick == 3 else None)
        report = await loop.run(ticks=8)
    assert [d[0] for d in dts] == [1, 2, 3, 6, 7, 8]
    assert dts[3] == (6, 0.006, 0.003)  # t counts from activation (tick 0)
    assert report["missed_ticks"] == 2
    assert report["ticks"] == 6


@pytest.mark.asyncio
async def test_a_stall_past_the_last_deadline_counts_only_the_runs_own_deadlines():
    import time

    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop

    raw = arm_raw(2)
    raw["loop"]["clock"] = "auto"  # a real clock, where a stall skips deadlines
    stalled = []

    def stall_once(loop):
        if not stalled:
            stalled.append(loop.robot.clock.tick)
            time.sleep(0.03)  # 30 periods at 1 kHz: past the end of a 10-tick run

    async with ControlLoop(parse_config(raw)) as loop:
        loop.add_publisher(stall_once)
        report = await loop.run(ticks=10)
    assert report["ticks"] + report["missed_ticks"] == 10  # every deadline of the run, no more
    assert report["missed_ticks"] >= 1


@pytest.mark.asyncio
@pytest.mark.parametrize("idle_wait", [True, False])
async def test_the_report_counts_how_the_real_clock_waited(idle_wait):
    """On asyncio's epoll loop the ticks wait on the timer itself unless ``idle_wait = false``;
    on uvloop they always go round the event loop. The report says which."""
    if not sys.platform.startswith("linux"):
        pytest.skip("timerfd is Linux only")
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop

    raw = arm_raw(2)
    raw["loop"].update(clock="timerfd", idle_wait=idle_wait)
    asyncio_epoll = isinstance(asyncio.get_running_loop(), asyncio.SelectorEventLoop)
    async with ControlLoop(parse_config(raw)) as loop:
        report = await loop.run(ticks=30)
    waits = report["waits"]
    assert report["ticks"] + report["missed_ticks"] == 30
    assert waits["on_timer"] + waits["through_loop"] >= 1
    if idle_wait and asyncio_epoll:
        assert waits["on_timer"] > 0
    else:
        assert waits["on_timer"] == 0 and waits["through_loop"] > 0


@pytest.mark.asyncio
async def test_the_deadlines_sit_where_the_config_puts_them():
    """``[loop] phase_us`` places a real clock's deadlines; without it they sit between the
    kernel's ticks (500 µs past a whole millisecond at 1 kHz)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("timerfd is Linux only")
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop

    for phase_us, expected_ns in ((None, 500_000), (250.0, 250_000), (0.0, 0)):
        raw = arm_raw(2)
        raw["loop"]["clock"] = "timerfd"
        if phase_us is not None:
            raw["loop"]["phase_us"] = phase_us
        async with ControlLoop(parse_config(raw)) as loop:
            report = await loop.run(ticks=5)
            ticker = loop.ticker
        assert report["ticks"] + report["missed_ticks"] == 5
        assert ticker.t0_ns % 1_000_000 == expected_ns
        assert ticker.deadline_ns % 1_000_000 == expected_ns and ticker.deadline_ns == ticker.t0_ns + ticker.k * 1_000_000


class _Collections:
    """Every collection from here on, in order with marks; automatic collection is off, so
    each one seen is an explicit ``gc.collect`` somebody made."""

    def __init__(self):
        self.events: list[tuple[str, int]] = []

    def __call__(self, phase, info):
        if phase == "start":
            self.events.append(("collect", info["generation"]))

    def __enter__(self):
        import gc

        self._was_enabled = gc.isenabled()
        gc.disable()
        gc.callbacks.append(self)
        return self

    def __exit__(self, *exc):
        import gc

        gc.callbacks.remove(self)
        if self._was_enabled:
            gc.enable()

    def after(self, mark):
        return self.events[self.events.index(mark) + 1 :]


@pytest.mark.asyncio
async def test_the_full_collection_runs_before_any_driver_opens():
    """A full collection holds the GIL for tens of milliseconds in a MuJoCo process: a driver's
    keep-alive thread (EtherCAT feeds the bus until the first tick) must not wait it out. Once
    a driver is open, the loop collects only the young generations."""
    import gc

    from aiohal.core import realtime

    holders = realtime._freeze_holders
    loop = virtual_loop(arm_raw(3))
    loop.configure()
    driver = loop.slots[0].driver
    opened = driver.open

    with _Collections() as seen:

        async def open_and_mark():
            seen.events.append(("open", 0))
            await opened()

        driver.open = open_and_mark
        frozen_while_ticking = []
        await loop.activate()
        loop.add_publisher(lambda _loop: frozen_while_ticking.append(gc.get_freeze_count() > 0))
        await loop.run(ticks=20)
        await loop.run(ticks=20)
        await loop.deactivate()

    assert ("collect", 2) in seen.events[: seen.events.index(("open", 0))]
    after_open = seen.after(("open", 0))
    assert after_open, "run() no longer freezes what open() allocated"
    assert all(gen < 2 for _, gen in after_open), seen.events
    assert frozen_while_ticking == [True] * 40
    assert realtime._freeze_holders == holders
    if holders == 0:
        assert gc.get_freeze_count() == 0


@pytest.mark.asyncio
async def test_the_heap_thaws_when_the_last_loop_closes():
    """The freeze is process-wide: one loop closing must not thaw another one's run."""
    import gc

    from aiohal.core import realtime

    holders = realtime._freeze_holders
    first, second = virtual_loop(arm_raw(2)), virtual_loop(arm_raw(2))
    await first.activate()
    await second.activate()
    await first.deactivate()
    assert realtime._freeze_holders == holders + 1 and gc.get_freeze_count() > 0
    await second.run(ticks=5)
    await second.deactivate()
    assert realtime._freeze_holders == holders


@pytest.mark.asyncio
async def test_a_failed_activation_thaws_the_heap():
    from aiohal.core import realtime

    holders = realtime._freeze_holders
    raw = arm_raw(2)
    raw["driver"][0]["options"] = {"faults": {"open_error": True}}
    loop = virtual_loop(raw)
    with pytest.raises(DriverError):
        await loop.activate()
    assert loop.state == "closed" and realtime._freeze_holders == holders


@pytest.mark.asyncio
async def test_gc_default_leaves_the_collector_alone():
    raw = arm_raw(2)
    raw["loop"]["gc"] = "default"
    with _Collections() as seen:
        async with virtual_loop(raw) as loop:
            await loop.run(ticks=5)
    assert seen.events == []


@pytest.mark.parametrize("duration", [float("nan"), float("inf"), 1e300, 0.0, -1.0])
@pytest.mark.asyncio
async def test_run_refuses_a_duration_that_is_not_a_finite_positive_time(duration):
    loop = virtual_loop(arm_raw(2))
    async with loop:
        with pytest.raises(ValueError, match="duration must be a finite number of seconds"):
            await loop.run(duration)
        report = await loop.run(ticks=10)  # nothing was broken by the refusal
    assert report["ticks"] == 10 and report["faults"] == []
