"""Learned velocity feed-forward: LOLA's policy, the gains applied by the HAL, the gains file,
the learning command, and the mock's servo drive in the loop."""

from __future__ import annotations

import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers import arm_raw, virtual_loop

from aiohal.config import load_config, parse_config
from aiohal.core.feedforward import GainLearner, LearningFeedforward, VelocityFeedforward, read_gains, write_gains
from aiohal.core.loop import ControlLoop
from aiohal.errors import ConfigError
from aiohal.hal import Controller
from aiohal.learn_feedforward import main as learn_main
from aiohal.robot import JointCommand, JointState, Mode

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "lola_hip_sim.toml"


# ---------------------------------------------------------------- the policy

def test_the_policy_raises_while_the_error_falls_and_keeps_the_last_that_lowered_it():
    learner = GainLearner(step=0.1)
    cost = lambda k: abs(k - 0.33)  # noqa: E731  a V with its bottom between grid points
    k = learner.k_e
    assert k == 0.0
    while not learner.done:
        k = learner.window(cost(k))
    assert k == pytest.approx(0.3)
    assert [c[0] for c in learner.costs] == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])
    assert learner.best == (pytest.approx(0.3), pytest.approx(0.03))


def test_the_policy_stays_at_zero_when_the_first_raise_makes_it_worse():
    learner = GainLearner(step=0.1)
    learner.window(1.0)
    assert learner.window(1.5) == 0.0 and learner.done
    assert learner.window(0.1) == 0.0  # done: later windows change nothing


def test_the_policy_stops_after_max_steps():
    learner = GainLearner(step=0.1, max_steps=3)
    k = 0.0
    while not learner.done:
        k = learner.window(10.0 - k)
    assert k == pytest.approx(0.3) and len(learner.costs) == 4


def test_a_window_with_a_missed_deadline_is_measured_again():
    """A skipped tick spoils its window (a spike of error that says nothing about k_e): the
    window is measured again, at most MAX_REPEATS times in a row."""

    class Clock:
        tick = 0

    clock, learner = Clock(), GainLearner(step=0.1)
    command, state = JointCommand(1), JointState(1)
    command.mode[:] = Mode.POSITION
    learning = LearningFeedforward(command, state, learner, window=10, settle=5, clock=clock)
    skips = {3, 17}  # ticks after which one is missed (3: while settling)

    def run(ticks):
        for _ in range(ticks):
            clock.tick += 2 if clock.tick in skips else 1
            command.position[:] = 0.01 * clock.tick  # an error that grows: the policy would stop
            learning.apply()

    run(15)  # settling (its miss does not count), then a clean window
    assert learner.costs == [(0.0, pytest.approx(0.01 * np.sqrt(np.mean(np.arange(7, 17) ** 2)), rel=1e-6))]
    run(10)  # a miss at 17: measured again
    assert len(learner.costs) == 1 and learner.repeated == 1
    run(10)
    assert len(learner.costs) == 2 and learner.done  # clean, and worse: the policy stopped
    learner2 = GainLearner(step=0.1)
    learning2 = LearningFeedforward(command, state, learner2, window=10, settle=0, clock=clock)
    skips.update(range(clock.tick, clock.tick + 100, 5))  # a miss in every window
    for _ in range(4 * 10):
        clock.tick += 2 if clock.tick in skips else 1
        learning2.apply()
    assert learner2.repeated == LearningFeedforward.MAX_REPEATS and len(learner2.costs) == 1


# ---------------------------------------------------------------- applied by the HAL

def test_the_gain_scales_the_target_velocity_of_position_and_impedance_joints_only():
    cmd = JointCommand(4)
    cmd.mode[:] = [Mode.POSITION, Mode.IMPEDANCE, Mode.VELOCITY, Mode.EFFORT]
    cmd.velocity[:] = 2.0
    ff = VelocityFeedforward(cmd, np.array([0.2, 0.5, 0.5, 0.5]))
    ff.apply()
    assert cmd.velocity.tolist() == pytest.approx([2.4, 3.0, 2.0, 2.0])


class Ramp(Controller):
    def update(self, t, dt):
        cmd = self.robot.command
        cmd.mode[:] = Mode.POSITION
        cmd.position[:] = 0.1 * t
        cmd.velocity[:] = 0.1


@pytest.mark.asyncio
@pytest.mark.parametrize("every", [1, 2])
async def test_configured_gains_reach_the_driver_on_every_tick(tmp_path, every):
    write_gains(tmp_path / "gains.toml", {"j0": 0.3, "j1": 0.1})
    raw = arm_raw(3)
    for joint in raw["joints"].values():
        joint["acceleration"] = 1e4  # the velocity's rate limit out of the way
    raw["feedforward"] = {"gains": str(tmp_path / "gains.toml"), "k_e": {"j2": 0.2}}
    raw["controller"]["every"] = every
    loop = virtual_loop(raw, controller=Ramp())
    sent = []
    loop.add_publisher(lambda lp: sent.append(lp.robot.command.velocity.copy()))
    async with loop:
        await loop.run(ticks=6)
    assert np.array(sent[1:]) == pytest.approx(np.tile([0.13, 0.11, 0.12], (len(sent) - 1, 1)))


@pytest.mark.asyncio
async def test_without_a_feedforward_section_the_velocity_is_sent_as_commanded():
    raw = arm_raw(2)
    for joint in raw["joints"].values():
        joint["acceleration"] = 1e4
    loop = virtual_loop(raw, controller=Ramp())
    sent = []
    loop.add_publisher(lambda lp: sent.append(lp.robot.command.velocity.copy()))
    async with loop:
        await loop.run(ticks=3)
    assert loop.feedforward is None
    assert np.array(sent[1:]) == pytest.approx(0.1)


def test_a_gains_file_naming_an_unknown_joint_is_a_config_error(tmp_path):
    write_gains(tmp_path / "gains.toml", {"hip": 0.2})
    raw = arm_raw(2)
    raw["feedforward"] = {"gains": str(tmp_path / "gains.toml")}
    with pytest.raises(ConfigError, match=r"feedforward.gains"):
        parse_config(raw)
    raw["feedforward"] = {"gains": str(tmp_path / "missing.toml")}
    with pytest.raises(ConfigError, match=r"feedforward.gains"):
        parse_config(raw)
    raw["feedforward"] = {"k_e": {"j9": 0.1}}
    with pytest.raises(ConfigError, match=r"feedforward.k_e.j9"):
        parse_config(raw)


# ---------------------------------------------------------------- learning on the servo drive

def test_the_learning_command_writes_gains_a_config_loads(tmp_path, capsys):
    out = tmp_path / "gains.toml"
    assert learn_main([str(CONFIG), "--out", str(out)]) == 0
    gains = read_gains(out)
    assert set(gains) == {"hip_flexion"}
    assert gains["hip_flexion"] > 0.0  # the joint lags its target: a positive k_e lowers the error
    text = out.read_text()
    assert "RMS per window" in text
    tomllib.loads(text)
    config = load_config(CONFIG)
    section = config.feedforward.model_copy(update={"gains": out})
    loop_config = replace(config, feedforward=section)
    assert ControlLoop(loop_config).feedforward.k_e.tolist() == [gains["hip_flexion"]]


@pytest.mark.asyncio
async def test_the_learned_gain_lowers_the_tracking_error_on_the_servo_drive():
    """The gait on the mock's servo drive, in lockstep: with k_e = 0 the joint lags its
    target; with a gain the policy finds, the RMS error is much lower."""
    config = load_config(CONFIG)

    async def rms(k_e):
        section = config.feedforward.model_copy(update={"k_e": k_e})
        loop = ControlLoop(replace(config, feedforward=section))
        async with loop:
            report = await loop.run(duration=3.6)
        assert not report["faults"]
        return report["controller"]["tracking_rms_rad"]

    ref, learned = await rms(0.0), await rms(0.4)
    assert ref > 2e-3  # about v·2T: the drive's latch and its interpolation, a cycle each
    assert learned < 0.1 * ref
