"""The mock driver's simulated joints, one step per tick, compiled with numba.

Why compiled: the mock is what the HAL's own cost is measured with (``benchmarks.scaling``,
``benchmarks.breakdown``: mock driver, ``hold``, 33 joints), and as numpy its step was 6-9
calls and its stamps 2 more. On the real clock each tick starts cold after the wait, where a
numpy call costs several times what it costs back to back; one small compiled call suffers
less. The arithmetic is numpy's, in the same order (``tests/test_mock_driver.py`` compares
the two bit for bit). Module globals are frozen into numba's on-disk cache, which only
notices changes to this file: the rows and modes are literals here, checked at import.
"""

from __future__ import annotations

from numba import njit, types

from aiohal.robot import JOINT_COMMAND_FIELDS, JOINT_STATE_FIELDS, Mode

# rows of the simulated joints (the first three rows of the state block) and of the command
POSITION, VELOCITY, EFFORT = 0, 1, 2
C_POSITION, C_VELOCITY, C_EFFORT, C_FEEDFORWARD = 0, 1, 2, 5
VELOCITY_MODE, EFFORT_MODE = 2, 3

if (JOINT_STATE_FIELDS[:3] != ("position", "velocity", "effort")
        or tuple(JOINT_COMMAND_FIELDS[i] for i in (0, 1, 2, 5)) != ("position", "velocity", "effort", "feedforward")
        or (int(Mode.VELOCITY), int(Mode.EFFORT)) != (VELOCITY_MODE, EFFORT_MODE)):
    raise ImportError("drivers/mock_kernels.py: its literal rows or modes no longer match aiohal.robot")

_RO_BLOCK = types.Array(types.float64, 2, "A", readonly=True)
_BLOCK = types.Array(types.float64, 2, "A")
_MODE = types.Array(types.int8, 1, "A", readonly=True)
_STAMPS = types.Array(types.int64, 1, "A")


@njit(types.void(_RO_BLOCK, _MODE, _BLOCK, types.float64, types.boolean, types.float64, types.float64,
                 types.boolean, _STAMPS, _STAMPS, types.int64, types.int64), cache=True, nogil=True)
def step_joints(command, mode, sim, dt, first_order, alpha, inv_dt, stamp, updated_tick, stamp_ns, tick, now_ns):
    """Move each simulated joint toward its target by ``dt``: the position command, or the
    position plus velocity × dt in velocity mode, or where it is in effort mode; all the way
    (mirror) or by ``alpha`` of the way (first order). The step over dt is the velocity, the
    commanded effort plus feed-forward the effort. ``stamp``: the rows are the state's, so
    they are stamped with this tick too."""
    for j in range(sim.shape[1]):
        position = sim[POSITION, j]
        m = mode[j]
        if m == VELOCITY_MODE:
            target = command[C_VELOCITY, j] * dt
            target += position
        elif m == EFFORT_MODE:
            target = position
        else:
            target = command[C_POSITION, j]
        motion = target - position
        if first_order:
            motion *= alpha
        sim[POSITION, j] = position + motion
        sim[VELOCITY, j] = motion * inv_dt
        sim[EFFORT, j] = command[C_EFFORT, j] + command[C_FEEDFORWARD, j]
        if stamp:
            updated_tick[j] = tick
            stamp_ns[j] = now_ns


_HAND = types.Array(types.float64, 1, "A")
_RO_HAND = types.Array(types.float64, 1, "A", readonly=True)


@njit(types.void(_RO_HAND, _RO_HAND, _RO_HAND, _HAND, _HAND, types.float64, types.float64), cache=True, nogil=True)
def step_hands(grasp, speed, force, position, effort, hand_speed, period_s):
    """Move each simulated hand toward its ``grasp`` by at most ``hand_speed × speed`` per
    second over one period; it pushes with its ``force`` while not fully open (the position
    before the step decides, as the numpy version did)."""
    for i in range(position.shape[0]):
        step = hand_speed * speed[i] * period_s
        before = position[i]
        # min(max(grasp, before - step), before + step), with Python's min/max on NaN
        low = before - step
        target = low if low > grasp[i] else grasp[i]
        high = before + step
        position[i] = high if high < target else target
        effort[i] = force[i] if before > 0.0 else 0.0
