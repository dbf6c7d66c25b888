"""The drives' per-cycle conversions, compiled with numba: process image ↔ robot arrays.

Why compiled: in CPython each drive costs a struct call and about twenty interpreted
operations each way. A numba kernel loops over the drives in machine code, and its fixed cost
(the call, the arguments' types) is paid once per cycle, whatever the number of drives
(figures: docs/performance.md, "Why the compiled kernels are kept"). numba does this better
than a hand-written C extension would here: no compiler at install time, the kernels stay
readable Python, and they are cached on disk after the first compilation.

Arguments are few on purpose: each adds to the cost of a call, so each drive's byte offsets
and row are one row of ``layout`` (int64: the input variables' offsets in
:data:`~.drives.DRIVE_INPUTS` order, the outputs' in
:data:`~.drives.DRIVE_OUTPUTS` order, then the joint's row), its unit constants one row of
``constants`` (float64, columns below) and its integer state one row of ``ints`` (int64,
columns below). Values are little-endian, as on the bus.

Everything else a kernel reads is a constant of this module, taken from :mod:`aiohal.robot`
and :mod:`aiohal.fieldbus.cia402` (see ``CommandRow`` in aiohal.robot about numba's cache).
"""

from __future__ import annotations

import numpy as np
from numba import njit, types

from aiohal.fieldbus.cia402 import CSP as _CSP
from aiohal.fieldbus.cia402 import CST as _CST
from aiohal.fieldbus.cia402 import CSV as _CSV
from aiohal.robot import CommandRow, Mode, StateRow

# layout columns: 5 input offsets, 5 output offsets, the 2 feed-forward offsets (-1: not
# mapped), the joint's row
IN, OUT, OFFSETS, ROW = 0, 5, 10, 12
# constants columns (float64)
RAD_PER_COUNT, MOTOR_RAD_PER_COUNT, NM_PER_PER_MILLE, POSITION_OFFSET, COUNTS_PER_RAD, PER_MILLE_PER_NM = range(6)
# ints columns (int64): VALID says the drive's position was read once (so it can be unwrapped)
STATUSWORD, ERROR_CODE, RAW_POSITION, COUNTS, CONTROLWORD, HOLD, VALID = range(7)
# rows of the joints' state and command blocks (aiohal.robot), and the CiA 402 modes
S_POSITION, S_VELOCITY = int(StateRow.POSITION), int(StateRow.VELOCITY)
S_EFFORT, S_MOTOR_POSITION = int(StateRow.EFFORT), int(StateRow.MOTOR_POSITION)
C_POSITION, C_VELOCITY = int(CommandRow.POSITION), int(CommandRow.VELOCITY)
C_EFFORT, C_FEEDFORWARD = int(CommandRow.EFFORT), int(CommandRow.FEEDFORWARD)
CSP, CSV, CST = int(_CSP), int(_CSV), int(_CST)
#: joint command mode → CiA 402 mode of operation (impedance runs as CSP: the drive's own loop)
MODE_OF_OPERATION = np.full(max(Mode) + 1, CSP, dtype=np.int64)
MODE_OF_OPERATION[Mode.VELOCITY] = CSV
MODE_OF_OPERATION[Mode.EFFORT] = CST


@njit(cache=True, nogil=True, inline="always")
def _u16(buf, o):
    return np.int64(buf[o]) | (np.int64(buf[o + 1]) << 8)


@njit(cache=True, nogil=True, inline="always")
def _i16(buf, o):
    v = np.int64(buf[o]) | (np.int64(buf[o + 1]) << 8)
    return v - 65536 if v >= 32768 else v


@njit(cache=True, nogil=True, inline="always")
def _i32(buf, o):
    v = np.int64(buf[o]) | (np.int64(buf[o + 1]) << 8) | (np.int64(buf[o + 2]) << 16) | (np.int64(buf[o + 3]) << 24)
    return v - 4294967296 if v >= 2147483648 else v


@njit(cache=True, nogil=True, inline="always")
def _put(buf, o, value, nbytes):
    """``value``'s low ``nbytes`` bytes, little-endian (two's complement for negatives)."""
    v = value & ((np.int64(1) << (8 * nbytes)) - 1)
    for b in range(nbytes):
        buf[o + b] = (v >> (8 * b)) & 0xFF


@njit(cache=True, nogil=True, inline="always")
def _clamp(value, low, high):
    return low if value < low else (high if value > high else value)


# Explicit signatures (any layout, "A"): compiled once, at import (or loaded from the cache),
# and never again. A lazily compiled kernel would compile again, on the tick, for the first
# strided array it meets (a driver's columns of the robot's state): seconds without a cycle.
# Arguments a kernel only reads are typed read-only: numba then takes writable and read-only
# arrays alike (a read-only view of the command would otherwise not match).
_U8, _I64_2D, _F64_2D = (
    types.Array(types.uint8, 1, "A"),
    types.Array(types.int64, 2, "A"),
    types.Array(types.float64, 2, "A"),
)
_RO_U8, _RO_I64_2D, _RO_F64_2D = (types.Array(t.dtype, t.ndim, "A", readonly=True) for t in (_U8, _I64_2D, _F64_2D))
_RO_I8 = types.Array(types.int8, 1, "A", readonly=True)
_I64_1D = types.Array(types.int64, 1, "A")
_DECODE = types.boolean(_RO_U8, _RO_I64_2D, _RO_F64_2D, _I64_2D, _F64_2D, _I64_1D, _I64_1D, types.int64, types.int64)
_ENCODE = types.void(_U8, _RO_I64_2D, _RO_F64_2D, _I64_2D, _RO_F64_2D, _RO_I8, types.boolean)


@njit(_DECODE, cache=True, nogil=True)
def decode_drives(inputs, layout, constants, ints, state, ticks, stamps, tick, now_ns):
    """Every drive's inputs → statusword, error code, unwrapped counts (``ints``) and SI
    values into its column of ``state`` (rows: position, velocity, effort, motor position),
    its joint stamped fresh (``ticks``, ``stamps``: the state's ``updated_tick`` and
    ``stamp_ns``; two numpy calls fewer per cycle than stamping afterwards).
    Returns True when a statusword or error code changed."""
    changed = False
    for i in range(layout.shape[0]):
        o = layout[i]
        status, raw, speed, torque, error = (
            _u16(inputs, o[IN]),
            _i32(inputs, o[IN + 1]),
            _i32(inputs, o[IN + 2]),
            _i16(inputs, o[IN + 3]),
            _u16(inputs, o[IN + 4]),
        )
        if status != ints[i, STATUSWORD] or error != ints[i, ERROR_CODE]:
            changed = True
        ints[i, STATUSWORD] = status
        ints[i, ERROR_CODE] = error
        if ints[i, VALID]:  # the int32 counter wraps: add the difference since the last cycle, wrapped
            counts = ints[i, COUNTS] + ((raw - ints[i, RAW_POSITION] + 2147483648) & 0xFFFFFFFF) - 2147483648
        else:
            counts = raw
            ints[i, VALID] = 1
        ints[i, COUNTS] = counts
        ints[i, RAW_POSITION] = raw
        k = constants[i]
        row = o[ROW]
        state[S_POSITION, row] = counts * k[RAD_PER_COUNT] + k[POSITION_OFFSET]
        state[S_MOTOR_POSITION, row] = counts * k[MOTOR_RAD_PER_COUNT]
        state[S_VELOCITY, row] = speed * k[RAD_PER_COUNT]
        state[S_EFFORT, row] = torque * k[NM_PER_PER_MILLE]
        ticks[row] = tick
        stamps[row] = now_ns
    return changed


@njit(_ENCODE, cache=True, nogil=True)
def encode_drives(outputs, layout, constants, ints, command, mode, hold_all):
    """Commands (``command``: the joints' command block, ``mode``: their modes) → every
    drive's outputs. A drive in hold (every drive with ``hold_all``) gets target = actual in
    CSP; the others their mode's targets. In CSP the target velocity and the effort plus
    feed-forward go to the velocity and torque offsets (0x60B1, 0x60B2) of a drive that maps
    them (its layout's offset is not -1), in the units of the target velocity and torque. Velocity and torque targets are clamped to their
    int32 / int16 range, the position target wraps. The loop's limits make every command
    finite and bounded before a driver sees it; should one not be, a non-finite position is
    held and a non-finite velocity or torque is sent as 0 (and a position beyond ±2⁶³ counts
    has no defined target)."""
    for i in range(layout.shape[0]):
        o = layout[i]
        row = o[ROW]
        k = constants[i]
        cia_mode = CSP
        target = ints[i, RAW_POSITION]
        speed = 0
        torque = 0
        speed_offset = 0
        torque_offset = 0
        p = command[C_POSITION, row]
        if not hold_all and not ints[i, HOLD] and np.isfinite(p):
            m = np.int64(mode[row])
            cia_mode = MODE_OF_OPERATION[m] if 0 <= m < MODE_OF_OPERATION.shape[0] else CSP
            target = np.int64(np.rint((p - k[POSITION_OFFSET]) * k[COUNTS_PER_RAD]))
            v = command[C_VELOCITY, row] * k[COUNTS_PER_RAD]
            t = (command[C_EFFORT, row] + command[C_FEEDFORWARD, row]) * k[PER_MILLE_PER_NM]
            v = np.int64(np.rint(_clamp(v, -2147483648.0, 2147483647.0))) if np.isfinite(v) else 0
            t = np.int64(np.rint(_clamp(t, -32768.0, 32767.0))) if np.isfinite(t) else 0
            if cia_mode == CSP:  # the feed-forward, where the drive maps its offsets
                speed_offset, torque_offset = v, t
            else:
                speed, torque = v, t
        _put(outputs, o[OUT], ints[i, CONTROLWORD], 2)
        _put(outputs, o[OUT + 1], target, 4)
        _put(outputs, o[OUT + 2], speed, 4)
        _put(outputs, o[OUT + 3], torque, 2)
        _put(outputs, o[OUT + 4], cia_mode, 1)
        if o[OFFSETS] >= 0:
            _put(outputs, o[OFFSETS], speed_offset, 4)
        if o[OFFSETS + 1] >= 0:
            _put(outputs, o[OFFSETS + 1], torque_offset, 2)
