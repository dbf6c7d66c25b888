"""Property tests of the command limiter: whatever a controller writes, what reaches a driver
is finite and within the joint limits (hypothesis explores the inputs)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.limits import CommandLimiter
from aiohal.robot import JointSpec, Mode, Robot

DT = 0.001
EPS = 1e-9


@st.composite
def robots(draw):
    specs = []
    for i in range(draw(st.integers(1, 3))):
        lo = draw(st.floats(-10, 10))
        hi = lo + draw(st.floats(0.01, 10))
        specs.append(JointSpec(
            f"j{i}", i, lo, hi,
            draw(st.floats(0.1, 10)),
            draw(st.one_of(st.just(math.inf), st.floats(0.1, 100))),
            draw(st.floats(0.1, 100)),
        ))
    return Robot("r", specs)


any_float = st.one_of(st.floats(-1e6, 1e6), st.floats())  # includes NaN, inf, huge


@settings(max_examples=300, deadline=None)
@given(robot=robots(), data=st.data())
def test_limited_commands_are_finite_and_within_limits(robot, data):
    n = robot.dof
    limiter = CommandLimiter(robot, DT)
    start = np.array([data.draw(st.floats(-30, 30)) for _ in range(n)])
    robot.state.position[:] = start
    robot.command.position[:] = start
    limiter.reset(start)
    cmd = robot.command
    prev_p, prev_v = start.copy(), np.zeros(n)
    for _ in range(data.draw(st.integers(1, 20))):
        cmd.block[:] = np.array(data.draw(st.lists(any_float, min_size=6 * n, max_size=6 * n))).reshape(6, n)
        cmd.mode[:] = data.draw(st.sampled_from([Mode.POSITION, Mode.VELOCITY, Mode.IMPEDANCE]))
        limiter.apply()
        p, v = cmd.position, cmd.velocity
        assert np.isfinite(cmd.block).all()
        assert (np.abs(p - prev_p) <= robot.velocity_limit * DT + EPS).all()  # rate
        was_inside = (prev_p >= robot.position_min) & (prev_p <= robot.position_max)
        inside = (p >= robot.position_min) & (p <= robot.position_max)
        assert (inside | ~was_inside).all()  # once in range, stays in range
        assert ((p >= prev_p) | ~(prev_p < robot.position_min)).all()  # outside: only back in
        assert ((p <= prev_p) | ~(prev_p > robot.position_max)).all()
        assert (np.abs(v) <= robot.velocity_limit + EPS).all()
        accel_ok = np.abs(v - prev_v) <= robot.acceleration_limit * DT + EPS
        # a velocity-mode joint at the end of its range is stopped there, whatever it costs
        at_end = (cmd.mode == Mode.VELOCITY) & (
            (robot.state.position >= robot.position_max) | (robot.state.position <= robot.position_min)
        )
        assert (accel_ok | ~np.isfinite(robot.acceleration_limit) | at_end).all()
        assert (np.abs(cmd.effort) <= robot.effort_limit).all()
        assert (np.abs(cmd.feedforward) <= robot.effort_limit).all()
        assert (cmd.stiffness >= 0).all() and (cmd.damping >= 0).all()
        prev_p, prev_v = p.copy(), v.copy()


@settings(max_examples=200, deadline=None)
@given(robot=robots(), data=st.data())
def test_velocity_mode_never_pushes_out_of_range(robot, data):
    n = robot.dof
    limiter = CommandLimiter(robot, DT)
    at_max = robot.position_max.copy()
    robot.state.position[:] = at_max  # every joint measured at the top of its range
    limiter.reset(at_max)
    robot.command.mode[:] = Mode.VELOCITY
    robot.command.velocity[:] = [data.draw(st.floats(-100, 100)) for _ in range(n)]
    limiter.apply()
    assert (robot.command.velocity <= 0.0).all()


def test_finite_but_huge_commands_are_clamped_not_refused():
    robot = Robot("r", [JointSpec("a", 0, -1, 1, 1.0, math.inf, 5.0), JointSpec("b", 1, -1, 1, 1.0, math.inf, 5.0)])
    limiter = CommandLimiter(robot, DT)
    limiter.reset(np.zeros(2))
    robot.command.stiffness[:] = 1e308  # the sum overflows, yet every entry is finite
    assert limiter.apply() is True
    assert limiter.refused == 0
