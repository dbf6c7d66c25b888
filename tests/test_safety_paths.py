"""What the loop does when things go wrong: nothing non-finite or jumping reaches a driver."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from helpers import arm_raw, register_driver, virtual_loop

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.errors import ConfigError, DriverError
from aiohal.hal import Controller, Driver
from aiohal.robot import Mode


def spy_writes(loop):
    """Record the command block every driver is given, at each write."""
    sent = []
    for slot in loop.slots:
        driver = slot.driver
        original = driver.write

        async def write(original=original, driver=driver):
            sent.append(driver.view.command.block.copy())
            await original()

        driver.write = write
    return sent


class NanDamping(Controller):
    def update(self, t, dt):
        if self.robot.clock.tick >= 30:
            self.robot.command.damping[:] = np.nan


@pytest.mark.asyncio
async def test_persisting_nan_is_never_sent_and_is_one_fault():
    loop = virtual_loop(arm_raw(2), controller=NanDamping())
    async with loop:
        sent = spy_writes(loop)
        report = await loop.run(ticks=1000)
    assert all(np.isfinite(block).all() for block in sent)
    assert [f["phase"] for f in report["faults"]] == ["limits"]
    assert report["safety_level"] == "hold"


class VelocityThenCrash(Controller):
    def start(self, t):
        self.robot.command.mode[:] = Mode.VELOCITY

    def update(self, t, dt):
        if t >= 0.6:
            raise RuntimeError("bug")
        self.robot.command.velocity[:] = 1.0


@pytest.mark.asyncio
async def test_hold_after_a_velocity_controller_starts_where_the_joint_is():
    raw = arm_raw(1)
    raw["joints"]["j0"]["acceleration"] = 1e3  # reach 1 rad/s within the first ticks
    loop = virtual_loop(raw, controller=VelocityThenCrash())
    measured, commanded = [], []
    loop.add_publisher(lambda lp: (measured.append(lp.robot.state.position[0]), commanded.append(lp.robot.command.position[0])))
    async with loop:
        await loop.run(ticks=800)
    fault_tick = 600
    # the first hold command continues from the measured position, it does not jump to 0
    assert abs(commanded[fault_tick - 1] - measured[fault_tick - 1]) < 2.5e-3
    assert np.abs(np.diff(commanded[fault_tick - 1 :])).max() <= 1e-3 + 1e-12


class Mover(Controller):
    def start(self, t):
        self.q0 = self.robot.state.position.copy()

    def update(self, t, dt):
        if self.robot.clock.tick == 300:
            raise RuntimeError("bug")
        self.robot.command.position[:] = self.q0 + 1.5 * t  # 1.5 rad/s


@pytest.mark.asyncio
async def test_switch_to_hold_neither_jumps_nor_stalls():
    loop = virtual_loop(arm_raw(1), controller=Mover())
    sent = []
    loop.add_publisher(lambda lp: sent.append(lp.limiter.last_position[0]))
    async with loop:
        await loop.run(ticks=600)
    steps = np.diff(sent) / 1e-3  # rate of the position command, rad/s
    around = steps[295:310]
    # no stalled tick: the rate goes down by at most 0.02 rad/s per tick (20 rad/s²), never to 0
    assert around.min() > 1.5 - 15 * 0.02 - 1e-9
    assert (np.diff(around) <= 1e-9).all() and (np.diff(around) >= -0.02 - 1e-9).all()
    assert np.abs(np.diff(steps[:400])).max() <= 20.0 * 1e-3 + 1e-9  # acceleration within limit
    assert steps[-50:].max() == 0.0  # then at rest
    assert loop.robot.command.velocity[0] == 0.0  # at rest, the velocity command too
    assert loop.robot.command.position[0] == sent[-1]


class Homing(Controller):
    def start(self, t):
        self.q0 = self.robot.state.position.copy()

    def update(self, t, dt):
        s = min(t / 0.5, 1.0)
        self.robot.command.position[:] = self.q0 + s * 1.0


@pytest.mark.asyncio
async def test_controller_time_continues_across_runs():
    loop = virtual_loop(arm_raw(1), controller=Homing())
    async with loop:
        await loop.run(ticks=600)
        first = loop.robot.command.position[0]
        await loop.run(ticks=200)
        second = loop.robot.command.position[0]
    assert first == second == pytest.approx(1.0)


@pytest.mark.asyncio
async def test_estop_stops_commanding_but_keeps_reading():
    loop = virtual_loop(arm_raw(1, type="sine", params={"amplitude": 0.5, "frequency": 0.5}))
    async with loop:
        sent = spy_writes(loop)
        loop.add_publisher(lambda lp: lp.estop() if lp.robot.clock.tick == 100 else None)
        report = await loop.run(ticks=300)
        mock = loop.slots[0].driver
    assert len(sent) == 100  # nothing written after the emergency stop
    assert mock.reads == 301
    assert report["safety_level"] == "estop"


class Stuck(Driver):
    async def read(self):
        if self.view.clock.tick >= 50:
            await asyncio.get_running_loop().create_future()  # never completes
        self.view.mark_fresh()

    async def write(self):
        pass

    def estop(self):
        self.estopped = getattr(self, "estopped", 0) + 1


@pytest.mark.asyncio
async def test_a_read_that_never_returns_trips_the_watchdog(monkeypatch):
    register_driver(monkeypatch, "stuck", f"{__name__}:Stuck")
    raw = arm_raw(1)
    raw["driver"][0]["type"] = "stuck"
    raw["loop"] = {"rate_hz": 1000, "clock": "timerfd", "stall_timeout_ms": 100}
    loop = ControlLoop(parse_config(raw))
    async with loop:
        report = await asyncio.wait_for(loop.run(ticks=10_000), timeout=10)
    assert report["stop_reason"] == "stalled"
    assert loop.slots[0].driver.estopped >= 1
    assert any(f["phase"] == "tick" and "no tick for 100 ms" in f["error"] for f in report["faults"])


@pytest.mark.asyncio
async def test_publisher_that_raises_is_dropped_and_reported():
    loop = virtual_loop(arm_raw(1))
    calls = []

    def bad(lp):
        calls.append(1)
        raise ValueError("oops")

    loop.add_publisher(bad)
    async with loop:
        report = await loop.run(ticks=50)
    assert report["ticks"] == 50 and calls == [1]
    assert report["faults"][0]["source"].startswith("publisher:") and "oops" in report["faults"][0]["error"]


@pytest.mark.asyncio
async def test_when_every_driver_failed_the_loop_estops_and_stops():
    raw = arm_raw(2)
    raw["driver"][0]["options"] = {"faults": {"read_error_at_tick": 10}}
    async with virtual_loop(raw) as loop:
        report = await loop.run(ticks=1000)
    assert report["stop_reason"] == "no driver left"
    assert report["safety_level"] == "estop"
    assert report["ticks"] < 20


@pytest.mark.asyncio
async def test_deactivate_during_run_waits_for_the_tick_to_finish():
    loop = virtual_loop(arm_raw(1))
    await loop.activate()
    mock = loop.slots[0].driver
    task = asyncio.create_task(loop.run())
    while loop.robot.clock.tick < 20:
        await asyncio.sleep(0)
    await loop.deactivate()
    await task
    writes = mock.writes
    assert mock.closed and loop.state == "closed"
    await asyncio.sleep(0)
    assert mock.writes == writes  # nothing written after close


class NanAtStart(Driver):
    async def read(self):
        self.view.state.position[:] = np.nan
        self.view.mark_fresh()

    async def write(self):
        pass


@pytest.mark.asyncio
async def test_non_finite_feedback_at_activation_fails_the_driver(monkeypatch):
    register_driver(monkeypatch, "nanbus", f"{__name__}:NanAtStart")
    raw = arm_raw(1)
    raw["driver"][0]["type"] = "nanbus"
    loop = virtual_loop(raw)
    with pytest.raises(DriverError, match="not finite"):
        await loop.activate()
    assert loop.state == "closed"


def test_non_finite_per_joint_values_are_config_errors():
    raw = arm_raw(1, type="sine", params={"amplitude": float("nan")})
    raw["driver"][0]["options"] = {"initial_position": float("inf")}
    with pytest.raises(ConfigError) as info:
        parse_config(raw)
    paths = sorted(i.path for i in info.value.issues)
    assert any(p.startswith("controller.params.amplitude") for p in paths)
    assert any(p.startswith("driver[0].options.initial_position") for p in paths)
