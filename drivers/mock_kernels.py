"""The mock driver's simulated joints, one step per tick, compiled with numba.

Why compiled: the mock is what the HAL's own cost is measured with (``benchmarks.scaling``:
mock driver, ``hold``, 33 joints, work per tick p50 ≤ 25 µs at 1 kHz). As numpy the step is
half a dozen calls, and on the real clock each tick starts on cold caches, where each numpy
call costs several µs; one compiled call pays that once (docs/performance.md, "Why the
compiled kernels are kept"). ``tests/test_mock_driver.py`` holds the numpy formulation it
must match. The rows and modes come from :mod:`aiohal.robot` (see ``CommandRow`` there about
numba's cache).
"""

from __future__ import annotations

from numba import njit, types

from aiohal.robot import CommandRow, Mode, StateRow

POSITION, VELOCITY, EFFORT = int(StateRow.POSITION), int(StateRow.VELOCITY), int(StateRow.EFFORT)
C_POSITION, C_VELOCITY = int(CommandRow.POSITION), int(CommandRow.VELOCITY)
C_EFFORT, C_FEEDFORWARD = int(CommandRow.EFFORT), int(CommandRow.FEEDFORWARD)
VELOCITY_MODE, EFFORT_MODE = int(Mode.VELOCITY), int(Mode.EFFORT)

_RO_BLOCK = types.Array(types.float64, 2, "A", readonly=True)
_BLOCK = types.Array(types.float64, 2, "A")
_MODE = types.Array(types.int8, 1, "A", readonly=True)
_STAMPS = types.Array(types.int64, 1, "A")


@njit(
    types.void(
        _RO_BLOCK,
        _MODE,
        _BLOCK,
        types.float64,
        types.boolean,
        types.float64,
        types.float64,
        types.boolean,
        _STAMPS,
        _STAMPS,
        types.int64,
        types.int64,
    ),
    cache=True,
    nogil=True,
)
def step_joints(command, mode, sim, dt, first_order, alpha, inv_dt, stamp, updated_tick, stamp_ns, tick, now_ns):
    """Move each simulated joint (``sim``: rows as in the state block) toward its target by
    ``dt``: the position command, or the position plus velocity × dt in velocity mode, or
    where it is in effort mode; all the way (mirror) or by ``alpha`` of the way (first
    order). The step over dt is the velocity, the commanded effort plus feed-forward the
    effort. ``stamp``: the rows are the state's, so they are stamped with this tick too."""
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
