"""Property tests of the command limiter: whatever a controller writes, what reaches a driver
is finite and within the joint limits (hypothesis explores the inputs)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.core.limits import CommandLimiter
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


@st.composite
def robots_some_unlimited(draw):
    """Like ``robots``, but any limit may be absent (inf), as a config may leave it."""
    specs = []
    for i in range(draw(st.integers(1, 3))):
        lo = draw(st.floats(-10, 10) | st.just(-math.inf))
        hi = draw(st.just(math.inf) | st.floats(0.01, 10).map(lambda d, lo=lo: (0.0 if math.isinf(lo) else lo) + d))
        def limit(low, high):
            return st.floats(low, high) | st.just(math.inf)

        specs.append(JointSpec(f"j{i}", i, lo, hi, draw(limit(0.1, 10)), draw(limit(0.1, 100)), draw(limit(0.1, 100))))
    return Robot("r", specs)


any_float = st.one_of(st.floats(-1e6, 1e6), st.floats())  # includes NaN, inf, huge


# hypothesis' usual 100 random robots: drawing each one's arrays element by element is most
# of this test's time (300 took 15 s)
@settings(max_examples=100, deadline=None)
@given(robot=robots() | robots_some_unlimited(), data=st.data())
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


class NumpyLimiter:
    """The limiter's rules written as vectorised numpy (its earlier implementation): an
    independent formulation that the compiled kernel must match bit for bit."""

    def __init__(self, robot: Robot, start: np.ndarray) -> None:
        self.robot = robot
        n = robot.dof
        eff, vel = robot.effort_limit, robot.velocity_limit
        self.lower = np.array([robot.position_min, -vel, -eff, np.zeros(n), np.zeros(n), -eff])
        self.upper = np.array([robot.position_max, vel, eff, np.full(n, 1e12), np.full(n, 1e12), eff])
        self.fixed_lower, self.fixed_upper = self.lower[:2].copy(), self.upper[:2].copy()
        self.step = np.vstack([vel * DT, robot.acceleration_limit * DT])
        self.last = np.vstack([start, np.zeros(n)])
        self.outside = bool(((start < robot.position_min) | (start > robot.position_max)).any())

    def apply(self, block: np.ndarray, mode: np.ndarray, position: np.ndarray) -> bool:
        r = self.robot
        lower, upper = self.lower, self.upper
        moving_lower, moving_upper = self.last - self.step, self.last + self.step
        if self.outside:
            moving_lower = np.maximum(moving_lower, np.minimum(self.fixed_lower, moving_upper))
            moving_upper = np.minimum(moving_upper, np.maximum(self.fixed_upper, moving_lower))
        else:
            moving_lower = np.maximum(moving_lower, self.fixed_lower)
            moving_upper = np.minimum(moving_upper, self.fixed_upper)
        lower[:2], upper[:2] = moving_lower, moving_upper
        velocity_rows = mode == Mode.VELOCITY
        upper[1] = np.where(velocity_rows & ~(position < r.position_max), np.minimum(upper[1], 0.0), upper[1])
        lower[1] = np.where(velocity_rows & ~(position > r.position_min), np.maximum(lower[1], 0.0), lower[1])
        clamped = np.minimum(np.maximum(block, lower), upper)
        finite = np.isfinite(clamped)
        clamped[:2] = np.where(finite[:2], clamped[:2], self.last)
        clamped[2:] = np.where(finite[2:], clamped[2:], 0.0)
        block[:] = np.minimum(np.maximum(clamped, lower), upper)
        self.last = block[:2].copy()
        self.outside = bool(((block[0] < r.position_min) | (block[0] > r.position_max)).any())
        return bool(finite.all())


# hypothesis' usual 100 random robots, each limited by both formulations: drawing their arrays
# element by element is most of the time (300 took 22 s)
@settings(max_examples=100, deadline=None)
@given(robot=robots() | robots_some_unlimited(), data=st.data())
def test_the_compiled_limiter_matches_the_numpy_formulation(robot, data):
    n = robot.dof
    start = np.array([data.draw(st.floats(-30, 30) | st.just(math.nan)) for _ in range(n)])  # often outside the range; NaN: bounds NaN
    limiter = CommandLimiter(robot, DT)
    limiter.reset(start)
    reference = NumpyLimiter(robot, start)
    cmd = robot.command
    for _ in range(data.draw(st.integers(1, 20))):
        commands = np.array(data.draw(st.lists(any_float, min_size=6 * n, max_size=6 * n))).reshape(6, n)
        cmd.mode[:] = data.draw(st.lists(st.sampled_from(list(Mode)), min_size=n, max_size=n))
        robot.state.position[:] = data.draw(st.lists(st.floats(-30, 30) | st.just(math.nan), min_size=n, max_size=n))
        expected = commands.copy()
        expected_ok = reference.apply(expected, cmd.mode, robot.state.position)
        cmd.block[:] = commands
        assert limiter.apply() is expected_ok
        np.testing.assert_array_equal(cmd.block, expected)
        np.testing.assert_array_equal(limiter.last, expected[:2])
