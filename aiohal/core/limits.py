"""Clamp commands to the configured joint limits before any driver writes them.

One compiled call per tick (:mod:`aiohal.core.limit_kernel`) over all joints, whatever their
number. The bounds are fixed for every command quantity (range, velocity, effort, stiffness and
damping >= 0, feed-forward) and, for position and velocity, also move with the last command
sent.

Position commands are limited in range and, relative to the last command sent, in rate (the
velocity limit), so a jump in a target becomes a ramp that stops exactly at the target. If a
joint starts outside its range, the rate limit wins: the command moves back into range at the
allowed rate instead of jumping. Velocity commands are limited in magnitude and in change per
tick (the acceleration limit). Position commands are not acceleration-clamped: a clamp that
cannot see where a target stops turns a step into an overshooting oscillation; smooth position
references are the controller's job, and ``hold`` brakes within the limit. Joints in velocity
mode are stopped at the ends of their range (no velocity pushing further out). Non-finite
entries of a command are refused: a position or velocity is replaced by the value sent last
tick, an effort, feed-forward, stiffness or damping by 0, and the result is clamped like any
other command.
"""

from __future__ import annotations

import numpy as np

from ..robot import CommandRow, Robot
from . import compiled_entry

#: Stiffness and damping have no configured limit; this cap keeps every sum finite.
GAIN_CAP = 1e12


class CommandLimiter:
    """Per tick, one compiled call (:mod:`aiohal.core.limit_kernel`) clamps the command block to the
    bounds: fixed ones, and for position and velocity a step from the last command sent."""

    def __init__(self, robot: Robot, period_s: float) -> None:
        from . import limit_kernel as lk  # numba: loaded when a loop is built, not on import aiohal

        self._refused_bit, self._outside_bit = lk.REFUSED, lk.OUTSIDE
        self.cmd = robot.command
        self.state = robot.state
        n = robot.dof
        self.period_s = period_s
        self.position_min = robot.position_min
        self.position_max = robot.position_max
        table = np.zeros((lk.ROWS, n))
        for row in CommandRow:
            lower, upper = table[lk.LOWER + row], table[lk.UPPER + row]
            if row in (CommandRow.EFFORT, CommandRow.FEEDFORWARD):
                lower[:], upper[:] = -robot.effort_limit, robot.effort_limit
            elif row == CommandRow.VELOCITY:
                lower[:], upper[:] = -robot.velocity_limit, robot.velocity_limit
            elif row == CommandRow.POSITION:
                lower[:], upper[:] = robot.position_min, robot.position_max
            else:  # stiffness, damping
                lower[:], upper[:] = 0.0, GAIN_CAP
        # rows [position, velocity]: how far each may move from the last command in one tick
        table[lk.STEP] = robot.velocity_limit * period_s
        table[lk.STEP + 1] = robot.acceleration_limit * period_s
        self._table = table
        self.last = table[lk.LAST : lk.LAST + 2]  # [position, velocity] sent last tick (views)
        self._before = table[lk.BEFORE : lk.BEFORE + 2]  # the same, one tick earlier
        self._outside = False  # a joint's last command lies outside its range
        self.refused = 0  # ticks whose command was not finite
        self._dispatcher = lk.limit_commands
        self._rebind()

    def _rebind(self) -> None:
        """Check the robot's arrays for the kernel, which is called directly (no numba dispatch)."""
        args = (self.cmd.block, self.cmd.mode, self.state.position, self._table)
        self._kernel = compiled_entry.compiled_for(self._dispatcher, (*args, False))
        n = self._table.shape[1]
        if args[0].shape != (len(CommandRow), n) or args[1].shape != (n,) or args[2].shape != (n,):
            raise ValueError(
                f"the limiter's kernel needs the robot's command block {(len(CommandRow), n)}, modes and "
                f"positions ({n},): got {args[0].shape}, {args[1].shape}, {args[2].shape}"
            )
        self._args = args

    @property
    def last_position(self) -> np.ndarray:
        return self.last[0]

    @property
    def previous_position(self) -> np.ndarray:
        return self._before[0]

    def reset(self, position: np.ndarray) -> None:
        """Start limiting from a known position at rest (activation, re-arm)."""
        np.copyto(self.last[0], position)
        np.copyto(self.previous_position, position)
        self.last[1] = 0.0
        self._outside = self._out_of_range(position)

    def _out_of_range(self, position: np.ndarray) -> bool:
        return bool(((position < self.position_min) | (position > self.position_max)).any())

    def last_rate(self, out: np.ndarray) -> np.ndarray:
        """The rate of the last position command sent (per second)."""
        np.subtract(self.last[0], self.previous_position, out=out)
        out /= self.period_s
        return out

    def hold_last(self) -> None:
        """Replace the command with the last position sent, moving at its last rate, no effort.

        ``hold`` starts from this and brakes to rest within the acceleration limits.
        """
        cmd = self.cmd
        np.copyto(cmd.position, self.last[0])
        self.last_rate(cmd.velocity)
        cmd.effort[:] = 0.0
        cmd.feedforward[:] = 0.0

    def follow_measured(self, rows: np.ndarray, velocity: np.ndarray) -> None:
        """Make ``rows`` continue from their measured position at ``velocity`` (a switch from a
        velocity- or effort-mode controller, whose position command meant nothing)."""
        measured = self.state.position
        ok = rows & np.isfinite(measured)
        np.copyto(self.last[0], measured, where=ok)
        np.copyto(self.previous_position, measured - velocity * self.period_s, where=ok)
        self._outside = self._out_of_range(self.last[0])

    def apply(self) -> bool:
        """Clamp the command in place. False if some entry was not finite (it was replaced, see
        the module's docstring, then clamped)."""
        block, mode, position, table = self._args
        if self.cmd.block is not block or self.cmd.mode is not mode or self.state.position is not position:
            self._rebind()  # an array of the robot was replaced: the kernel checks nothing itself
            block, mode, position, table = self._args
        result = self._kernel(block, mode, position, table, self._outside)
        self._outside = bool(result & self._outside_bit)
        if result & self._refused_bit:  # rare
            self.refused += 1
            return False
        return True
