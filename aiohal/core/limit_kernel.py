"""The command limiter's per-tick work, compiled with numba (see :mod:`aiohal.core.limits`).

Why compiled: as numpy the limiter's rules are 9 calls per tick, and on the real clock every
tick starts with the caches and branch predictors cold after the wait, where each call costs
several times its warm price; one call of a kernel that loops over the joints pays that once
(figures: docs/performance.md, "Why the compiled kernels are kept"; the numpy formulation it
must match: ``tests/test_limits.py``). It is imported only when a limiter is built, so
``import aiohal`` and the processes of NRT drivers do not load numba.

Everything the kernel needs besides the command is one float64 table (rows below): each
argument adds to the cost of a call. The rows and modes come from :mod:`aiohal.robot`
(see ``CommandRow`` there about numba's cache).
"""

from __future__ import annotations

import math

from numba import njit, types

from ..robot import CommandRow, Mode

# table rows: the [position, velocity] sent last tick, the same one tick earlier, how far each
# may move in one tick (velocity and acceleration limit × period), then the fixed lower and
# upper bounds of every command row (one per row of the command block, in its order)
LAST, BEFORE, STEP, LOWER = 0, 2, 4, 6
UPPER = LOWER + len(CommandRow)
ROWS = UPPER + len(CommandRow)
POSITION_ROW, VELOCITY_ROW = int(CommandRow.POSITION), int(CommandRow.VELOCITY)
VELOCITY_MODE = int(Mode.VELOCITY)
#: bits of the kernel's result
REFUSED, OUTSIDE = 1, 2


@njit(cache=True, nogil=True, inline="always")
def _clamp(x, lo, hi):
    """``minimum(maximum(x, lo), hi)`` as numpy does it for bounds that are not NaN: a NaN
    ``x`` passes through, and ``hi`` wins when the bounds cross (a joint more than one rate
    step below its range)."""
    x = lo if x < lo else x
    return hi if x > hi else x


# C-contiguous: the robot's command and state blocks, and the table, are made so; the kernel
# then reads each row as one stream (a signature of any layout ran 5x slower at 1000 joints)
_BLOCK = types.Array(types.float64, 2, "C")
_MODE = types.Array(types.int8, 1, "C", readonly=True)
_POSITION = types.Array(types.float64, 1, "C", readonly=True)
_TABLE = types.Array(types.float64, 2, "C")


@njit(types.int64(_BLOCK, _MODE, _POSITION, _TABLE, types.boolean), cache=True, nogil=True)
def limit_commands(block, mode, position, table, outside):
    """Clamp ``block`` (command rows × joints) in place; move LAST to BEFORE and the limited
    position and velocity to LAST. ``outside``: some joint's last position command lies
    outside its range (its rate limit then wins over the range). Returns REFUSED if an entry
    was not finite after clamping (replaced as in :mod:`aiohal.core.limits`), OUTSIDE if a limited
    position still lies outside its range."""
    rows, n = block.shape
    refused = False
    still_outside = False
    p_min = table[LOWER + POSITION_ROW]
    p_max = table[UPPER + POSITION_ROW]
    for i in range(2):  # position within a rate step of the last, velocity an acceleration step
        velocity = i == 1
        r = VELOCITY_ROW if velocity else POSITION_ROW
        x_row, last_row, before_row, step = block[r], table[LAST + i], table[BEFORE + i], table[STEP + i]
        fixed_lo, fixed_hi = table[LOWER + r], table[UPPER + r]
        for j in range(n):
            last = last_row[j]
            lo = last - step[j]
            hi = last + step[j]
            if outside:  # the rate limit wins: back into the range at the allowed rate
                lo = max(lo, min(fixed_lo[j], hi))
                hi = min(hi, max(fixed_hi[j], lo))
            else:
                lo = max(lo, fixed_lo[j])
                hi = min(hi, fixed_hi[j])
            if velocity and mode[j] == VELOCITY_MODE:  # no velocity out of the range at its ends
                if not position[j] < p_max[j]:
                    hi = min(hi, 0.0)
                if not position[j] > p_min[j]:
                    lo = max(lo, 0.0)
            # selects, not branches, from here (about twice as fast at 1000 joints):
            nan_bound = lo != lo or hi != hi  # a NaN last command: numpy's clamp gives NaN
            x = _clamp(x_row[j], lo, hi)  # ±inf is clamped like any other value
            bad = not math.isfinite(x)  # NaN, or ±inf where a bound is infinite: what was sent last
            x = _clamp(last, lo, hi) if bad else x
            x = math.nan if nan_bound else x
            refused |= nan_bound or bad
            x_row[j] = x
            before_row[j] = last
            last_row[j] = x
            if not velocity:
                still_outside |= x < p_min[j] or x > p_max[j]
    for r in range(rows):  # the other rows: fixed bounds, never NaN (the config refuses NaN limits)
        if r == POSITION_ROW or r == VELOCITY_ROW:  # noqa: SIM109 - numba kernel: two integer tests
            continue
        x_row, lower, upper = block[r], table[LOWER + r], table[UPPER + r]
        for j in range(n):
            lo, hi = lower[j], upper[j]
            x = _clamp(x_row[j], lo, hi)
            bad = not math.isfinite(x)  # NaN, or ±inf where a bound is infinite: no effort, feed-forward or gain
            x_row[j] = _clamp(0.0, lo, hi) if bad else x
            refused |= bad
    return (REFUSED if refused else 0) | (OUTSIDE if still_outside else 0)
