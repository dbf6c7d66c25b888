"""The MuJoCo driver's per-tick work, compiled with numba: MjData ↔ robot arrays.

Why compiled: as numpy calls the driver's read is 3 gathers and 2 stamp fills, plus a gather
and 2 fills per run of sensors, and its torque law 12 calls (gains by mode, PD terms,
compensation, clamp, scatter into ``ctrl``); called in turn with the controller and
``mj_step``, as in the tick, each call runs on caches the step left cold. One call per joint
read, per sensor run and for the torque does the same arithmetic in the same order, so the
torques are bit for bit those of the numpy formulation, but for the sign bit of a NaN
(``tests/test_mujoco_kernels.py``; figures: docs/performance.md, "Why the compiled kernels
are kept").

Arguments are few (each adds to the cost of a call, even a direct one):
the joints' MjData addresses are one int array (rows below), the per-joint gains and torque
bounds one float table (rows below). The state and command rows and the modes come from
:mod:`aiohal.robot` (see ``CommandRow`` there about numba's cache).
"""

from __future__ import annotations

from numba import njit, types

from aiohal.robot import CommandRow, Mode, StateRow

# rows of ``index`` (intp): qpos address, dof address, actuator of each joint
QPOS, DOF, ACTUATOR = 0, 1, 2
# rows of ``table`` (float64): position gain, velocity gain, lower and upper torque bound
KP, KD, TAU_MIN, TAU_MAX = 0, 1, 2, 3
# rows of the robot's state and command blocks, and the command modes (see aiohal.robot)
S_POSITION, S_VELOCITY, S_EFFORT = int(StateRow.POSITION), int(StateRow.VELOCITY), int(StateRow.EFFORT)
C_POSITION, C_VELOCITY, C_EFFORT = int(CommandRow.POSITION), int(CommandRow.VELOCITY), int(CommandRow.EFFORT)
C_STIFFNESS, C_DAMPING, C_FEEDFORWARD = int(CommandRow.STIFFNESS), int(CommandRow.DAMPING), int(CommandRow.FEEDFORWARD)
POSITION, VELOCITY, IMPEDANCE = int(Mode.POSITION), int(Mode.VELOCITY), int(Mode.IMPEDANCE)

_VECTOR = types.Array(types.float64, 1, "C")  # MjData's arrays, the driver's own torque
_RO_VECTOR = types.Array(types.float64, 1, "C", readonly=True)
_INDEX = types.Array(types.intp, 2, "C", readonly=True)
_TABLE = types.Array(types.float64, 2, "C", readonly=True)
_BLOCK = types.Array(types.float64, 2, "A")  # a driver's columns of the robot's block
_RO_BLOCK = types.Array(types.float64, 2, "A", readonly=True)
_MODE = types.Array(types.int8, 1, "A", readonly=True)
_STAMPS = types.Array(types.int64, 1, "A")


@njit(
    types.void(_RO_VECTOR, _RO_VECTOR, _INDEX, _RO_VECTOR, _BLOCK, _STAMPS, _STAMPS, types.int64, types.int64),
    cache=True,
    nogil=True,
)
def read_joints(qpos, qvel, index, tau, state, updated_tick, stamp_ns, tick, now_ns):
    """Measured position and velocity from MjData, effort = the torque applied last tick;
    every joint stamped with this tick."""
    for j in range(index.shape[1]):
        state[S_POSITION, j] = qpos[index[QPOS, j]]
        state[S_VELOCITY, j] = qvel[index[DOF, j]]
        state[S_EFFORT, j] = tau[j]
        updated_tick[j] = tick
        stamp_ns[j] = now_ns


@njit(
    types.void(_RO_BLOCK, _MODE, _RO_BLOCK, _TABLE, _INDEX, _RO_VECTOR, types.boolean, _VECTOR, _VECTOR),
    cache=True,
    nogil=True,
)
def drive_torque(command, mode, state, table, index, bias, compensate, tau, ctrl):
    """``tau = kp·(q* − q) + kd·(v* − v) + effort* + feed-forward (+ qfrc_bias)``, clamped to
    the actuator's range and written to ``ctrl``. The gains by mode: position kp and kd,
    velocity kd only, impedance the command's stiffness and damping, effort and none neither.
    The operations are numpy's, in its order: the same values bit for bit, a NaN's sign bit
    aside (LLVM may swap the operands of an addition, which numpy's NaN keeps)."""
    for j in range(index.shape[1]):
        m = mode[j]
        if m == IMPEDANCE:
            kp, kd = command[C_STIFFNESS, j], command[C_DAMPING, j]
        else:
            # a gain times 1.0 or 0.0, as numpy's gain × mode mask
            kp = table[KP, j] * (1.0 if m == POSITION else 0.0)
            kd = table[KD, j] * (1.0 if m == POSITION or m == VELOCITY else 0.0)  # noqa: SIM109 - numba kernel
        t = (command[C_POSITION, j] - state[S_POSITION, j]) * kp
        t += (command[C_VELOCITY, j] - state[S_VELOCITY, j]) * kd
        t += command[C_EFFORT, j]
        t += command[C_FEEDFORWARD, j]
        if compensate:
            t += bias[index[DOF, j]]
        # numpy's minimum then maximum: a NaN passes; at a tie the bound is taken (its sign of zero)
        t = t if t < table[TAU_MAX, j] or t != t else table[TAU_MAX, j]
        t = t if t > table[TAU_MIN, j] or t != t else table[TAU_MIN, j]
        tau[j] = t
        ctrl[index[ACTUATOR, j]] = t


_SENSOR_INDEX = types.Array(types.intp, 2, "C", readonly=True)
_ROWS = types.Array(types.float64, 2, "C")
_ROW_STAMPS = types.Array(types.int64, 1, "C")


@njit(
    types.void(_RO_VECTOR, _SENSOR_INDEX, _ROWS, _ROW_STAMPS, _ROW_STAMPS, types.int64, types.int64),
    cache=True,
    nogil=True,
)
def read_sensors(sensordata, index, rows, updated_tick, stamp_ns, tick, now_ns):
    """Adjacent rows of a device group (IMUs, force/torque sensors) from ``sensordata``:
    ``rows[r, c] = sensordata[index[r, c]]``, each row stamped with this tick."""
    for r in range(index.shape[0]):
        for c in range(index.shape[1]):
            rows[r, c] = sensordata[index[r, c]]
        updated_tick[r] = tick
        stamp_ns[r] = now_ns
