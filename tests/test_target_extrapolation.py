"""A controller slower than the bus: ``[controller] every = n`` and the targets extrapolated
on the ticks in between (aiohal.core.target_extrapolation), in the loop and on their own."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import arm_raw, virtual_loop

from aiohal.config import parse_config
from aiohal.core.target_extrapolation import TargetExtrapolator
from aiohal.errors import ConfigError
from aiohal.hal import Controller
from aiohal.robot import JointCommand, Mode

PERIOD = 1e-3


class Motion(Controller):
    """Joint 0 from where it stands: q = q0 + v0·t + a·t²/2 with its target velocity; the
    ticks it ran at are recorded; it raises from ``fail_at`` on."""

    def __init__(self, v0: float, a: float = 0.0, fail_at: int | None = None):
        self.v0, self.a, self.fail_at = v0, a, fail_at
        self.ran: list[int] = []

    def start(self, t):
        self.q0 = self.robot.state.position.copy()

    def update(self, t, dt):
        k = self.robot.clock.tick
        if self.fail_at is not None and k >= self.fail_at:
            raise RuntimeError("controller bug")
        self.ran.append(k)
        cmd = self.robot.command
        cmd.position[:] = self.q0
        cmd.position[0] = self.q0[0] + self.v0 * t + 0.5 * self.a * t * t
        cmd.velocity[:] = 0.0
        cmd.velocity[0] = self.v0 + self.a * t


def raw_with(every: int, extrapolate: bool = True) -> dict:
    raw = arm_raw(2)
    raw["controller"]["every"] = every
    raw["controller"]["extrapolate"] = extrapolate
    return raw


async def run_sent(raw: dict, controller: Controller, ticks: int):
    """The position sent each tick (after the limits) and the tick's time since activation."""
    loop = virtual_loop(raw, controller=controller)
    sent, times = [], []
    loop.add_publisher(lambda lp: (sent.append(lp.limiter.last_position[0]),
                                   times.append(lp.robot.clock.tick * PERIOD)))
    async with loop:
        report = await loop.run(ticks=ticks)
    return np.array(sent), np.array(times), report, loop


@pytest.mark.asyncio
async def test_the_controller_runs_every_nth_tick_and_a_ramp_stays_a_ramp():
    ramp = Motion(v0=0.2)
    sent, times, report, _loop = await run_sent(raw_with(every=5), ramp, ticks=200)
    assert np.diff(ramp.ran).tolist() == [5] * (len(ramp.ran) - 1)
    assert report["controller"]["every"] == 5 and report["controller"]["updates"] == len(ramp.ran) == 40
    # on every tick, the controller's or not, the target is on the line: nothing but a ramp
    np.testing.assert_allclose(sent, ramp.q0[0] + 0.2 * times, rtol=0, atol=1e-12)

    held = Motion(v0=0.2)
    sent, times, report, _ = await run_sent(raw_with(every=5, extrapolate=False), held, ticks=200)
    steps = np.diff(sent)
    # without extrapolation the last command is held: a staircase of 1 mrad steps every 5 ticks
    assert np.count_nonzero(steps) == len(held.ran) - 1
    assert steps.max() == pytest.approx(0.2 * 5 * PERIOD, abs=1e-12)
    assert report["controller"]["extrapolate"] is False


@pytest.mark.asyncio
async def test_an_accelerating_target_is_extrapolated_within_the_second_order_term():
    every, a = 4, 5.0  # 1.5 rad/s after 0.3 s: within the 2 rad/s limit
    sent, times, _, _ = await run_sent(raw_with(every), Motion(v0=0.0, a=a), ticks=300)
    exact = sent[0] + 0.5 * a * (times**2 - times[0] ** 2)
    error = np.abs(sent - exact)
    # between updates the line misses a·(jT)²/2 at most (j < every ticks since the update)
    bound = 0.5 * a * ((every - 1) * PERIOD) ** 2
    assert 0.0 < error.max() <= bound + 1e-12
    sent_held, _, _, _ = await run_sent(raw_with(every, extrapolate=False), Motion(v0=0.0, a=a), ticks=300)
    assert np.abs(sent_held - exact).max() > 10 * bound  # holding lags by v·(every-1)·T


@pytest.mark.asyncio
async def test_the_target_velocity_moves_on_with_its_rate_of_change():
    every, a = 4, 5.0  # within the 20 rad/s² the limits allow
    motion = Motion(v0=0.0, a=a)
    loop = virtual_loop(raw_with(every), controller=motion)
    sent = []  # (tick, position, velocity) as the driver gets them, after the limits
    loop.add_publisher(lambda lp: sent.append((lp.robot.clock.tick, lp.robot.command.position[0],
                                               lp.robot.command.velocity[0])))
    async with loop:
        await loop.run(ticks=200)
    k, position, velocity = np.array(sent).T
    t = k * PERIOD
    second = k > motion.ran[1]  # from the second update on, the acceleration is known
    q0 = position[0] - 0.5 * a * t[0] ** 2
    # a constant acceleration is carried exactly: no lag in the velocity the drives take as
    # feed-forward (held, it would lag by a·3T = 15 mrad/s), none in the position
    np.testing.assert_allclose(velocity[second], a * t[second], rtol=0, atol=1e-12)
    np.testing.assert_allclose(position[second], q0 + 0.5 * a * t[second] ** 2, rtol=0, atol=1e-12)
    # before it, the first update's velocity alone: held velocity, a line in position
    first = (k > motion.ran[0]) & ~second & (k < motion.ran[1])
    assert np.all(velocity[first] == velocity[k == motion.ran[0]])


@pytest.mark.asyncio
async def test_the_limits_apply_to_extrapolated_targets():
    class NearTheEnd(Controller):
        def update(self, t, dt):
            self.robot.command.position[0] = 1.99
            self.robot.command.velocity[0] = 1.5  # within the 2 rad/s limit, towards the end at 2.0

    raw = raw_with(every=50)
    raw["driver"][0]["options"] = {"initial_position": {"j0": 1.99}}
    sent, _, _, _ = await run_sent(raw, NearTheEnd(), ticks=200)
    assert sent.max() == 2.0  # the line went on past the range; the command stopped at its end
    assert np.abs(np.diff(sent)).max() <= 2.0 * PERIOD + 1e-12


@pytest.mark.asyncio
async def test_hold_runs_on_every_tick_after_a_controller_failure():
    failing = Motion(v0=0.5, fail_at=101)
    sent, _, report, _loop = await run_sent(raw_with(every=4), failing, ticks=400)
    assert report["controller"]["type"] == "hold" and report["faults"][0]["tick"] == 101
    assert failing.ran[-1] == 97
    # from the failure on, hold updated the command on each of the 300 ticks left
    assert report["controller"]["updates"] == len(failing.ran) + 300
    steps = np.abs(np.diff(sent))
    assert steps.max() <= 0.5 * PERIOD + 20.0 * PERIOD**2 + 1e-12  # braked within the acceleration limit
    assert steps[-20:].max() == 0.0


@pytest.mark.asyncio
async def test_a_resync_runs_the_controller_on_the_next_tick():
    ramp = Motion(v0=0.1)
    loop = virtual_loop(raw_with(every=4), controller=ramp)

    def resync_at_21(lp):
        if lp.robot.clock.tick == 21:
            lp.resync_joints(slice(0, 2), np.array([True, False]))
    loop.add_publisher(resync_at_21)
    async with loop:
        await loop.run(ticks=40)
    assert ramp.ran[:8] == [1, 5, 9, 13, 17, 21, 22, 26]


def test_extrapolation_moves_only_position_and_impedance_targets():
    cmd = JointCommand(4)
    cmd.mode[:] = [Mode.POSITION, Mode.VELOCITY, Mode.IMPEDANCE, Mode.EFFORT]
    cmd.position[:] = [1.0, 2.0, 3.0, 4.0]
    cmd.velocity[:] = [1.0, 2.0, 3.0, 4.0]
    cmd.effort[:] = [0.5, 0.5, 0.5, 0.5]
    x = TargetExtrapolator(cmd, period_s=0.01, every=10)
    assert x.due(0)
    x.capture(10)
    assert not x.due(19) and x.due(20)
    cmd.block[:] = -7.0  # what the limits did to the command since: forgotten
    x.fill(12)
    np.testing.assert_allclose(cmd.position, [1.02, 2.0, 3.06, 4.0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(cmd.velocity, [1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(cmd.effort, [0.5, 0.5, 0.5, 0.5])
    x.extrapolate = False
    x.fill(15)
    np.testing.assert_array_equal(cmd.position, [1.0, 2.0, 3.0, 4.0])
    with pytest.raises(ValueError, match="every"):
        TargetExtrapolator(cmd, period_s=0.01, every=0)


def test_the_acceleration_comes_from_two_updates_of_the_same_motion():
    cmd = JointCommand(3)
    cmd.mode[:] = [Mode.POSITION, Mode.IMPEDANCE, Mode.VELOCITY]
    cmd.feedforward[:] = 4.0
    x = TargetExtrapolator(cmd, period_s=0.01, every=2)

    def update(k, position, velocity):
        cmd.position[:] = position
        cmd.velocity[:] = velocity
        x.capture(k)

    update(10, 1.0, 2.0)
    x.fill(11)  # one update: no acceleration yet
    np.testing.assert_allclose(cmd.position, [1.02, 1.02, 1.0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(cmd.velocity, [2.0, 2.0, 2.0])
    update(12, 1.0, [3.0, 1.0, 5.0])  # 50, -50 rad/s² on the moving joints; velocity mode held
    x.fill(13)
    np.testing.assert_allclose(cmd.position, [1.0 + 0.03 + 0.0025, 1.0 + 0.01 - 0.0025, 1.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(cmd.velocity, [3.5, 0.5, 5.0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(cmd.feedforward, [4.0, 4.0, 4.0])  # the torque feed-forward is held
    x.force()  # a resync: the command changed under the controller, its last two updates are no motion
    update(13, 1.0, 0.0)
    x.fill(14)
    np.testing.assert_array_equal(cmd.velocity, [0.0, 0.0, 0.0])
    update(15, 1.0, 1.0)
    cmd.mode[0] = Mode.VELOCITY  # a mode change: no acceleration across it
    update(17, 1.0, 3.0)
    x.fill(18)
    np.testing.assert_array_equal(cmd.velocity, [3.0, 3.0, 3.0])


@pytest.mark.parametrize("value", [0, 2.5, 1001])
def test_a_bad_every_names_its_key(value):
    raw = arm_raw(2)
    raw["controller"]["every"] = value
    with pytest.raises(ConfigError) as info:
        parse_config(raw)
    assert "controller.every" in str(info.value)
