"""The mock driver: mirroring, first-order dynamics, modes, devices, injected faults."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from helpers import arm_raw, virtual_loop
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.core import compiled_entry
from aiohal.drivers import mock_kernels
from aiohal.hal import Controller
from aiohal.robot import JOINT_COMMAND_FIELDS, JOINT_STATE_FIELDS, CommandRow, Mode, StateRow


class Fixed(Controller):
    """Commands fixed values per mode, set by the test."""

    def __init__(self, mode=Mode.POSITION, position=0.0, velocity=0.0, effort=0.0):
        self.mode, self.p, self.v, self.e = mode, position, velocity, effort

    def update(self, t, dt):
        cmd = self.robot.command
        cmd.mode[:] = self.mode
        cmd.position[:] = self.p
        cmd.velocity[:] = self.v
        cmd.effort[:] = self.e


def raw_with(options, n=2):
    raw = arm_raw(n)
    raw["joints"] = {f"j{i}": {"position": [-10.0, 10.0], "velocity": 1e4, "effort": 50.0} for i in range(n)}
    raw["driver"][0]["options"] = options
    return raw


@pytest.mark.asyncio
async def test_mirror_follows_the_command_one_tick_later():
    loop = virtual_loop(raw_with({"dynamics": "mirror"}), controller=Fixed(position=0.05, effort=3.0))
    async with loop:
        await loop.run(ticks=2)  # commanded at tick 1, measured at tick 2
        state = loop.robot.state
        assert np.allclose(state.position, 0.05)
        assert np.allclose(state.velocity, 0.05 / 0.001)
        await loop.run(ticks=1)
    assert np.allclose(state.position, 0.05)
    assert np.allclose(state.effort, 3.0)
    assert np.allclose(state.velocity, 0.0)  # no motion between the last two ticks


@pytest.mark.asyncio
async def test_first_order_reaches_63_percent_after_one_time_constant():
    tau = 0.05
    loop = virtual_loop(raw_with({"dynamics": "first_order", "time_constant": tau}), controller=Fixed(position=1.0))
    async with loop:
        await loop.run(ticks=51)  # the command of tick 1 is applied from tick 2 on: 50 ticks = τ
    assert loop.robot.state.position[0] == pytest.approx(1 - math.exp(-1), rel=1e-9)
    assert loop.robot.state.velocity[0] > 0


@pytest.mark.asyncio
async def test_velocity_mode_integrates_and_effort_mode_holds_position():
    loop = virtual_loop(raw_with({"initial_position": 0.5}), controller=Fixed(mode=Mode.VELOCITY, velocity=2.0))
    async with loop:
        await loop.run(ticks=101)
    assert loop.robot.state.position[0] == pytest.approx(0.5 + 2.0 * 0.1, rel=1e-9)
    assert loop.robot.state.velocity[0] == pytest.approx(2.0)

    loop = virtual_loop(raw_with({"initial_position": 0.5}), controller=Fixed(mode=Mode.EFFORT, position=9.0, effort=4.0))
    async with loop:
        await loop.run(ticks=50)
    assert np.allclose(loop.robot.state.position, 0.5)
    assert np.allclose(loop.robot.state.effort, 4.0)


@pytest.mark.asyncio
async def test_initial_position_is_clipped_to_the_range():
    raw = arm_raw(2)  # range [-2, 2]
    raw["driver"][0]["options"] = {"initial_position": {"j0": 5.0, "j1": -0.25}}
    loop = virtual_loop(raw)
    async with loop:
        assert list(loop.robot.state.position) == [2.0, -0.25]


@pytest.mark.asyncio
async def test_feedback_delay_shows_the_past():
    loop = virtual_loop(raw_with({"feedback_delay_ticks": 10}), controller=Fixed(position=1.0))
    async with loop:
        await loop.run(ticks=11)
        assert np.allclose(loop.robot.state.position, 0.0)  # the step is applied at tick 2
    loop2 = virtual_loop(raw_with({"feedback_delay_ticks": 10}), controller=Fixed(position=1.0))
    async with loop2:
        await loop2.run(ticks=12)
        assert np.allclose(loop2.robot.state.position, 1.0)


@pytest.mark.asyncio
async def test_read_latency_is_spent_inside_read():
    loop = virtual_loop(raw_with({"read_latency_us": 2000}))
    async with loop:
        t0 = time.monotonic()
        report = await loop.run(ticks=20)
        elapsed = time.monotonic() - t0
    assert elapsed >= 20 * 0.002
    assert report["phases_us"]["read"]["p50"] >= 2000


@pytest.mark.asyncio
async def test_devices_read_gravity_wrench_and_hand_motion():
    raw = arm_raw(3)
    raw["devices"] = {
        "imu": {"type": "imu"},
        "ft": {"type": "force_torque"},
        "gripper": {"type": "hand", "joint": "j2"},
    }
    raw["driver"][0]["devices"] = ["imu", "ft", "gripper"]
    raw["driver"][0]["options"] = {"force": [1.0, 2.0, 30.0], "hand_speed": 2.0}
    loop = virtual_loop(raw)
    async with loop:
        robot = loop.robot
        hand = robot.hand_for_joint("j2")
        assert hand.name == "gripper"
        hand.grasp[...] = 1.0
        await loop.run(ticks=100)  # 0.1 s at 2 /s: half closed
        assert float(hand.position) == pytest.approx(0.2, abs=1e-9)
        await loop.run(ticks=500)
        assert float(hand.position) == pytest.approx(1.0)
        assert hand.updated_tick == robot.clock.tick
    imu, ft = robot.imu["imu"], robot.force_torque["ft"]
    assert list(imu.quaternion) == [1.0, 0.0, 0.0, 0.0]
    assert list(imu.linear_acceleration) == [0.0, 0.0, 9.81]
    assert list(ft.force) == [1.0, 2.0, 30.0]
    assert robot.imu.updated_tick[0] == robot.clock.tick


@pytest.mark.asyncio
async def test_each_driver_steps_and_stamps_only_its_own_devices_in_runs_of_rows():
    raw = arm_raw(4)
    raw["devices"] = {name: {"type": "hand", "joint": joint} for name, joint in
                      (("h0", "j0"), ("h1", "j2"), ("h2", "j1"))}  # group rows: h0, h1, h2
    raw["devices"]["ft"] = {"type": "force_torque"}
    raw["driver"] = [
        {"type": "mock", "name": "a", "joints": ["j0", "j1"], "devices": ["h2", "ft", "h0"], "options": {"hand_speed": 2.0}},
        {"type": "mock", "name": "b", "joints": ["j2", "j3"], "devices": ["h1"], "options": {"hand_speed": 2.0}},
    ]
    loop = virtual_loop(raw)
    async with loop:
        robot = loop.robot
        a_view = loop.slots[0].driver.view
        runs = [(group.kind, rows) for group, rows in a_view.device_runs()]
        # rows 0 and 2 of the hand group are a's, row 1 is b's: two runs, never one across it
        assert sorted(runs, key=str) == sorted([("hand", slice(0, 1)), ("hand", slice(2, 3)),
                                                ("force_torque", slice(0, 1))], key=str)
        robot.hand.grasp[:] = 1.0
        await loop.run(ticks=100)  # 0.1 s at 2 /s: each hand stepped once per tick, so 0.2
        np.testing.assert_allclose(robot.hand.position, [0.2, 0.2, 0.2], atol=1e-9)
        assert (robot.hand.updated_tick == robot.clock.tick).all()
        assert robot.force_torque.updated_tick[0] == robot.clock.tick


@pytest.mark.asyncio
async def test_estop_freezes_the_simulated_joints():
    loop = virtual_loop(raw_with({}), controller=Fixed(mode=Mode.VELOCITY, velocity=1.0))
    async with loop:
        await loop.run(ticks=10)
        mock = loop.slots[0].driver
        before = loop.robot.state.position.copy()
        mock.estop()
        mock.estop()  # idempotent
        await loop.run(ticks=10)
        assert np.array_equal(loop.robot.state.position, before)
        assert mock.estops == 2


def test_views_write_in_place():
    from aiohal.config import parse_config

    raw = arm_raw(4)
    raw["driver"] = [
        {"type": "mock", "name": "a", "joints": ["j0", "j1"]},
        {"type": "mock", "name": "b", "joints": ["j2", "j3"]},
    ]
    robot = parse_config(raw).build_robot()
    view = robot.driver_view(["j2", "j3"])
    view.state.position[:] = [7.0, 8.0]
    view.mark_fresh()
    assert list(robot.state.position) == [0.0, 0.0, 7.0, 8.0]
    assert np.shares_memory(view.state.block, robot.state.block)
    assert np.shares_memory(view.command.position, robot.command.position)
    ro = robot.controller_view()
    with pytest.raises(ValueError):
        ro.state.position[0] = 1.0  # controllers read state, they do not write it
    ro.command.position[0] = 1.0
    assert robot.command.position[0] == 1.0


def numpy_step(command, mode, sim, dt, alpha):
    """The mock's step in plain numpy, the reference the compiled step must match (alpha None:
    mirror; ``sim`` has the state block's rows)."""
    position, motion, effort = sim[StateRow.POSITION], sim[StateRow.VELOCITY], sim[StateRow.EFFORT]
    command = {row: command[row] for row in CommandRow}
    velocity_rows, effort_rows = mode == Mode.VELOCITY, mode == Mode.EFFORT
    with np.errstate(all="ignore"):
        target = command[CommandRow.POSITION].copy()
        tmp = np.multiply(command[CommandRow.VELOCITY], dt)
        tmp += position
        np.copyto(target, tmp, where=velocity_rows)
        np.copyto(target, position, where=effort_rows)
        np.subtract(target, position, out=motion)
        if alpha is not None:
            motion *= alpha
        position += motion
        motion *= 1.0 / dt
        np.add(command[CommandRow.EFFORT], command[CommandRow.FEEDFORWARD], out=effort)


FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64) | st.floats(-10.0, 10.0)


@settings(max_examples=100, deadline=None)  # hypothesis' usual count (300 took 11 s, drawing most of it)
@given(data=st.data(), n=st.integers(1, 10), dt=st.sampled_from([0.001, 0.0005, 0.003]),
       first_order=st.booleans())
def test_the_compiled_step_matches_the_numpy_formulation(data, n, dt, first_order):
    vectors = st.lists(FLOATS, min_size=n, max_size=n)
    command = np.array([data.draw(vectors) for _ in JOINT_COMMAND_FIELDS])
    mode = np.array(data.draw(st.lists(st.sampled_from(list(Mode)), min_size=n, max_size=n)), dtype=np.int8)
    sim = np.array([data.draw(vectors) for _ in JOINT_STATE_FIELDS])
    alpha = 1.0 - math.exp(-dt / 0.02) if first_order else 1.0
    expected = sim.copy()
    numpy_step(command, mode, expected, dt, alpha if first_order else None)

    ticks, stamps = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    args = (command, mode, sim, dt, first_order, alpha, 1.0 / dt, True, ticks, stamps, 5, 77)
    compiled_entry.compiled_for(mock_kernels.step_joints, args)(*args)
    nan = np.isnan(expected)  # equal bits elsewhere (0.0 is not -0.0), NaN where NaN
    np.testing.assert_array_equal(np.isnan(sim), nan)
    np.testing.assert_array_equal(sim[~nan].view(np.uint64), expected[~nan].view(np.uint64))
    assert (ticks == 5).all() and (stamps == 77).all()


@pytest.mark.parametrize("dynamics", ["mirror", "first_order"])
def test_the_mock_type_moves_the_joints_as_the_plain_driver(dynamics):
    """FastMockDriver (the ``mock`` type) against MockDriver, on the same commands in every mode."""
    import asyncio

    from aiohal import plugins
    from aiohal.drivers.mock import MockDriver
    from aiohal.drivers.mock_fast import FastMockDriver

    rng = np.random.default_rng(7)
    commands = [(rng.integers(1, 4, 6), rng.uniform(-2, 2, 6), rng.uniform(-2, 2, 6), rng.uniform(-5, 5, 6))
                for _ in range(40)]

    class Replay(Controller):
        def start(self, t):
            self.k = 0

        def update(self, t, dt):
            mode, position, velocity, effort = commands[self.k % len(commands)]
            self.k += 1
            cmd = self.robot.command
            cmd.mode[:], cmd.position[:], cmd.velocity[:], cmd.effort[:] = mode, position, velocity, effort

    async def run(driver_type):
        raw = raw_with({"dynamics": dynamics}, n=6)
        raw["driver"][0]["type"] = driver_type
        loop = virtual_loop(raw, controller=Replay())
        async with loop:
            await loop.run(ticks=len(commands))
            return type(loop.slots[0].driver), loop.robot.state.block[:3].copy()

    plugins.register("driver", "plain_mock", MockDriver)
    try:
        plain_type, plain = asyncio.run(run("plain_mock"))
    finally:
        plugins.unregister("driver", "plain_mock")
    fast_type, fast = asyncio.run(run("mock"))
    assert (plain_type, fast_type) == (MockDriver, FastMockDriver)
    np.testing.assert_allclose(fast, plain, rtol=1e-12, atol=1e-12)


@pytest.mark.asyncio
@pytest.mark.parametrize("options", [{}, {"feedback_delay_ticks": 3}])
async def test_every_read_stamps_the_joints_with_its_tick(options):
    loop = virtual_loop(raw_with(options), controller=Fixed(position=0.5))
    async with loop:
        for _ in range(3):
            await loop.run(ticks=4)
            state, clock = loop.robot.state, loop.robot.clock
            assert (state.updated_tick == clock.tick).all() and (state.stamp_ns == clock.now_ns).all()


@pytest.mark.asyncio
async def test_lost_feedback_leaves_the_stamps_of_the_last_measurement():
    raw = raw_with({"faults": {"feedback_lost_at_tick": 5, "feedback_lost_for": 3}})
    loop = virtual_loop(raw, controller=Fixed(position=0.5))
    async with loop:
        await loop.run(ticks=7)  # ticks 1..7, the feedback of 5, 6 and 7 lost
        state = loop.robot.state
        assert loop.robot.clock.tick == 7 and (state.updated_tick == 4).all()
        stamp_of_4 = state.stamp_ns.copy()
        await loop.run(ticks=2)  # tick 8 measures again
        assert (state.updated_tick == 9).all() and (state.stamp_ns > stamp_of_4).all()
