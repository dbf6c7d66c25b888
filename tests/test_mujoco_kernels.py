"""The MuJoCo driver's compiled joint work gives the numpy formulation's values, bit for bit
(hypothesis explores modes, gains, NaN and infinite commands, absent torque bounds), and its
read gathers the right addresses."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.core import compiled_entry
from aiohal.drivers import mujoco_kernels as kernels
from aiohal.robot import JOINT_COMMAND_FIELDS, JOINT_STATE_FIELDS, Mode

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64) | st.floats(-1e3, 1e3)


def numpy_torque(command, mode, state, kp, kd, tau_min, tau_max, bias_of_joint, compensate):
    """The torque law as the driver wrote it with numpy before the kernel."""
    with np.errstate(all="ignore"):  # inf - inf, 0 × inf: NaN, as on the robot
        return _numpy_torque(command, mode, state, kp, kd, tau_min, tau_max, bias_of_joint, compensate)


def _numpy_torque(command, mode, state, kp, kd, tau_min, tau_max, bias_of_joint, compensate):
    position = mode == Mode.POSITION
    impedance = mode == Mode.IMPEDANCE
    kp_eff = np.multiply(kp, position)
    kd_eff = np.multiply(kd, position | (mode == Mode.VELOCITY))
    np.copyto(kp_eff, command[3], where=impedance)
    np.copyto(kd_eff, command[4], where=impedance)
    tau = np.subtract(command[0], state[0])
    tau *= kp_eff
    tmp = np.subtract(command[1], state[1])
    tmp *= kd_eff
    tau += tmp
    tau += command[2]
    tau += command[5]
    if compensate:
        tau += bias_of_joint
    np.minimum(tau, tau_max, out=tau)
    np.maximum(tau, tau_min, out=tau)
    return tau


def assert_same_bits(actual, expected):
    """Equal bit for bit (so 0.0 is not -0.0), NaN where NaN whatever its sign bit: LLVM may
    swap an addition's operands, and which NaN's sign survives depends on that order."""
    nan = np.isnan(expected)
    np.testing.assert_array_equal(np.isnan(actual), nan)
    np.testing.assert_array_equal(actual[~nan].view(np.uint64), expected[~nan].view(np.uint64))


@st.composite
def cases(draw):
    n = draw(st.integers(1, 12))
    vectors = st.lists(FLOATS, min_size=n, max_size=n)
    command = np.array([draw(vectors) for _ in JOINT_COMMAND_FIELDS])
    state = np.array([draw(vectors) for _ in JOINT_STATE_FIELDS])
    mode = np.array(draw(st.lists(st.sampled_from(list(Mode)), min_size=n, max_size=n)), dtype=np.int8)
    gains = st.lists(st.floats(0.0, 1e4), min_size=n, max_size=n)
    kp, kd = np.array(draw(gains)), np.array(draw(gains))
    bound = st.floats(0.0, 500.0) | st.just(np.inf)
    tau_max = np.array(draw(st.lists(bound, min_size=n, max_size=n)))
    tau_min = -np.array(draw(st.lists(bound, min_size=n, max_size=n)))
    nv = n + draw(st.integers(0, 4))
    bias = np.array(draw(st.lists(FLOATS, min_size=nv, max_size=nv)))
    permutation = draw(st.permutations(range(nv)))
    return command, mode, state, kp, kd, tau_min, tau_max, bias, np.array(permutation[:n]), draw(st.booleans())


@settings(max_examples=100, deadline=None)  # hypothesis' usual count (300 took 10 s, drawing most of it)
@given(case=cases())
def test_the_compiled_torque_law_matches_the_numpy_formulation(case):
    command, mode, state, kp, kd, tau_min, tau_max, bias, dof, compensate = case
    n = len(mode)
    actuators = dof[::-1].copy()  # any other scatter than the gather
    index = np.array([np.arange(n), dof, actuators], dtype=np.intp)
    table = np.array([kp, kd, tau_min, tau_max])
    tau, ctrl = np.zeros(n), np.full(len(bias), 7.0)
    args = (command, mode, state, table, index, bias, compensate, tau, ctrl)
    compiled_entry.compiled_for(kernels.drive_torque, args)(*args)

    expected = numpy_torque(command, mode, state, kp, kd, tau_min, tau_max, bias[dof], compensate)
    assert_same_bits(tau, expected)
    assert_same_bits(ctrl[actuators], expected)
    untouched = np.setdiff1d(np.arange(len(bias)), actuators)
    assert (ctrl[untouched] == 7.0).all()


def test_the_compiled_read_gathers_and_stamps_a_drivers_columns():
    qpos, qvel = np.arange(10.0), np.arange(10.0) * -1.0
    index = np.array([[9, 2, 5], [1, 8, 3], [0, 0, 0]], dtype=np.intp)
    tau = np.array([0.5, 1.5, 2.5])
    robot_state = np.full((len(JOINT_STATE_FIELDS), 5), np.nan)  # the driver owns columns 1..3
    ticks, stamps = np.full(5, -1, dtype=np.int64), np.zeros(5, dtype=np.int64)
    args = (qpos, qvel, index, tau, robot_state[:, 1:4], ticks[1:4], stamps[1:4], 42, 123_456)
    compiled_entry.compiled_for(kernels.read_joints, args)(*args)

    np.testing.assert_array_equal(robot_state[:3, 1:4], [[9.0, 2.0, 5.0], [-1.0, -8.0, -3.0], tau])
    assert np.isnan(robot_state[:, [0, 4]]).all() and np.isnan(robot_state[3:]).all()
    assert ticks.tolist() == [-1, 42, 42, 42, -1] and stamps.tolist() == [0, 123_456, 123_456, 123_456, 0]


def test_the_compiled_sensor_read_fills_and_stamps_adjacent_rows():
    sensordata = np.arange(20.0) / 10.0
    values = np.full((4, 3), np.nan)  # a group of 4 devices; this driver's run is rows 1..2
    index = np.array([[5, 6, 7], [19, 0, 3]], dtype=np.intp)
    ticks, stamps = np.full(4, -1, dtype=np.int64), np.zeros(4, dtype=np.int64)
    args = (sensordata, index, values[1:3], ticks[1:3], stamps[1:3], 7, 99)
    compiled_entry.compiled_for(kernels.read_sensors, args)(*args)

    np.testing.assert_array_equal(values[1:3], [[0.5, 0.6, 0.7], [1.9, 0.0, 0.3]])
    assert np.isnan(values[[0, 3]]).all()
    assert ticks.tolist() == [-1, 7, 7, -1] and stamps.tolist() == [0, 99, 99, 0]
