"""Direct calls of the compiled kernels: the same results as numba's dispatch, and the checks
that stand in for the dispatch's (what the entry point itself would let through)."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit, types

from aiohal.core import compiled_entry
from aiohal.core import limit_kernel as lk
from aiohal.core.limits import CommandLimiter
from aiohal.robot import JointSpec, Robot


@njit(types.float64(types.Array(types.float64, 1, "C"), types.Array(types.int64, 2, "A", readonly=True)))
def _scale_first(out, rows):
    out[0] *= rows[0, 0]
    return out[0]


def test_a_direct_call_computes_what_the_dispatched_call_does():
    a, b = np.array([1.5, 2.0]), np.array([1.5, 2.0])
    rows = np.full((2, 2), 3, dtype=np.int64)
    direct = compiled_entry.compiled_for(_scale_first, (a, rows))
    assert direct(a, rows) == _scale_first(b, rows) == 4.5
    assert np.array_equal(a, b)


@pytest.mark.parametrize(("out", "rows", "why"), [
    (np.zeros(3, dtype=np.float32), np.zeros((1, 1), dtype=np.int64), "argument 0: a 1-d float32 array"),
    # the same item size: the entry point itself would take these and misread them
    (np.zeros(3, dtype=np.int64), np.zeros((1, 1), dtype=np.int64), "argument 0: a 1-d int64 array"),
    (np.zeros(3), np.zeros((1, 1), dtype=np.uint64), "argument 1: a 2-d uint64 array"),
    (np.zeros(3), np.zeros((1, 1), dtype=">i8"), "argument 1: a 2-d >i8 array"),
    (np.zeros(6)[::2], np.zeros((1, 1), dtype=np.int64), "argument 0: not C-contiguous"),
    (np.zeros(3), np.zeros(1, dtype=np.int64), "argument 1: a 1-d int64 array"),
    ([0.0, 1.0], np.zeros((1, 1), dtype=np.int64), "argument 0: list is not a numpy array"),
])
def test_check_refuses_an_array_numbas_dispatch_would_refuse(out, rows, why):
    with pytest.raises(TypeError, match=why):
        compiled_entry.check(_scale_first, (out, rows))


def test_check_refuses_a_read_only_array_the_kernel_writes_and_takes_one_it_only_reads():
    read_only = np.zeros(3)
    read_only.flags.writeable = False
    rows = np.zeros((1, 1), dtype=np.int64)
    with pytest.raises(TypeError, match="argument 0: read-only, and the kernel writes it"):
        compiled_entry.check(_scale_first, (read_only, rows))
    rows.flags.writeable = False
    compiled_entry.check(_scale_first, (np.zeros(3), rows))
    compiled_entry.check(_scale_first, (np.zeros(3), np.zeros((4, 4), dtype=np.int64)[::2, ::2]))  # strided: "A"


def test_the_entry_point_is_given_only_for_checked_arrays_and_one_signature():
    with pytest.raises(TypeError, match="argument 0: not C-contiguous"):
        compiled_entry.compiled_for(_scale_first, (np.zeros(6)[::2], np.zeros((1, 1), dtype=np.int64)))
    with pytest.raises(TypeError, match="takes 2 arguments, got 1"):
        compiled_entry.check(_scale_first, (np.zeros(3),))

    @njit(["float64(float64)", "int64(int64)"])
    def twice(x):
        return 2 * x

    with pytest.raises(TypeError, match=r"one explicit signature is needed.*it has 2"):
        compiled_entry.compiled_for(twice, (1.0,))


def _robot(n=3):
    return Robot("r", [JointSpec(f"j{i}", i, -1, 1, 1.0, 10.0, 5.0) for i in range(n)])


def test_the_limiter_checks_the_robots_arrays_before_it_calls_its_kernel_directly():
    robot = _robot()
    robot.command.mode = robot.command.mode.astype(np.int16)  # not the kernel's int8
    with pytest.raises(TypeError, match=f"{lk.limit_commands.py_func.__qualname__}, argument 1: a 1-d int16 array"):
        CommandLimiter(robot, 0.001)


def test_the_limiter_checks_an_array_of_the_robot_replaced_after_it_was_built():
    robot = _robot()
    limiter = CommandLimiter(robot, 0.001)
    limiter.reset(np.zeros(3))
    robot.command.position[:] = 5.0
    assert limiter.apply() and np.all(robot.command.position <= 1.0)
    robot.command.mode = np.zeros(3, dtype=np.uint8)  # the same item size as int8: misread if not checked
    with pytest.raises(TypeError, match="argument 1: a 1-d uint8 array"):
        limiter.apply()
    robot.command.mode = np.zeros(3, dtype=np.int8)
    robot.command.block = np.full((robot.command.block.shape[0], 3), 5.0)  # another block, well typed
    assert limiter.apply() and np.all(robot.command.block[0] <= 1.0)  # the new block is the one clamped
    robot.command.block = np.zeros((robot.command.block.shape[0], 2))
    with pytest.raises(ValueError, match=r"got \(6, 2\)"):
        limiter.apply()
