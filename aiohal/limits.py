"""Clamp commands to the configured joint limits before any driver writes them.

Vectorised over all joints with preallocated bounds, so a tick costs a handful of numpy calls
whatever the number of joints. The bounds are two arrays shaped like the command block (one
row per command quantity): fixed rows for velocity, effort, stiffness, damping (>= 0) and
feed-forward, and rows recomputed each tick where a limit depends on the last command sent.

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

import math

import numpy as np

from .robot import JOINT_COMMAND_FIELDS, Mode, Robot

_ROW = {name: i for i, name in enumerate(JOINT_COMMAND_FIELDS)}
POS, VEL = _ROW["position"], _ROW["velocity"]
assert (POS, VEL) == (0, 1)  # the two rows whose bounds move are adjacent: one slice
#: Stiffness and damping have no configured limit; this cap keeps every sum finite.
GAIN_CAP = 1e12


class CommandLimiter:
    """Per tick: 2 calls move the bounds of position and velocity, 2 intersect them with the
    fixed limits, 2 clamp the whole command block, 1 checks it is finite, 1 remembers it."""

    def __init__(self, robot: Robot, period_s: float) -> None:
        self.cmd = robot.command
        self.state = robot.state
        n = robot.dof
        self.period_s = period_s
        self.position_min = robot.position_min
        self.position_max = robot.position_max
        self.velocity_limit = robot.velocity_limit
        lower = np.empty((len(JOINT_COMMAND_FIELDS), n))
        upper = np.empty_like(lower)
        for name, i in _ROW.items():
            if name in ("effort", "feedforward"):
                lower[i], upper[i] = -robot.effort_limit, robot.effort_limit
            elif name == "velocity":
                lower[i], upper[i] = -robot.velocity_limit, robot.velocity_limit
            elif name == "position":
                lower[i], upper[i] = robot.position_min, robot.position_max
            else:  # stiffness, damping
                lower[i], upper[i] = 0.0, GAIN_CAP
        self.fixed_lower, self.fixed_upper = lower[:2].copy(), upper[:2].copy()
        self.lower, self.upper = lower, upper
        self._moving_lower, self._moving_upper = lower[:2], upper[:2]  # views, made once
        # rows [position, velocity]: how far each may move from the last command in one tick
        self.step = np.vstack([robot.velocity_limit * period_s, robot.acceleration_limit * period_s])
        self.last = np.zeros((2, n))  # [position, velocity] sent last tick
        self._before = np.zeros((2, n))  # the same, one tick earlier (the buffers swap)
        self._outside = False  # a joint's last command lies outside its range
        self._finite = np.zeros(lower.shape, dtype=bool)
        self._modes = b""
        self._velocity_rows = np.zeros(n, dtype=bool)
        self._any_velocity_mode = False
        self._inside = np.zeros(n, dtype=bool)
        self.refused = 0  # ticks whose command was not finite

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
        self._outside = bool(((position < self.position_min) | (position > self.position_max)).any())

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
        self._outside = bool(((self.last[0] < self.position_min) | (self.last[0] > self.position_max)).any())

    def apply(self) -> bool:
        """Clamp the command in place. False if some entry was not finite (it was replaced, see
        the module's docstring, then clamped)."""
        cmd = self.cmd
        block = cmd.block
        lower, upper, last = self.lower, self.upper, self.last
        moving_lower, moving_upper = self._moving_lower, self._moving_upper
        # position within a rate step of the last one, velocity within an acceleration step
        np.subtract(last, self.step, out=moving_lower)
        np.add(last, self.step, out=moving_upper)
        if self._outside:  # the rate limit wins: move back into the range at the allowed rate
            np.maximum(moving_lower, np.minimum(self.fixed_lower, moving_upper), out=moving_lower)
            np.minimum(moving_upper, np.maximum(self.fixed_upper, moving_lower), out=moving_upper)
        else:
            np.maximum(moving_lower, self.fixed_lower, out=moving_lower)
            np.minimum(moving_upper, self.fixed_upper, out=moving_upper)
        modes = cmd.mode.tobytes()
        if modes != self._modes:
            self._modes = modes
            np.equal(cmd.mode, Mode.VELOCITY, out=self._velocity_rows)
            self._any_velocity_mode = bool(self._velocity_rows.any())
        if self._any_velocity_mode:  # no velocity out of the range at its ends
            position, rows, inside = self.state.position, self._velocity_rows, self._inside
            np.less(position, self.position_max, out=inside)
            np.minimum(upper[VEL], 0.0, out=upper[VEL], where=rows & ~inside)
            np.greater(position, self.position_min, out=inside)
            np.maximum(lower[VEL], 0.0, out=lower[VEL], where=rows & ~inside)
        # NaN passes through maximum/minimum; ±inf does not (every bound is finite)
        np.maximum(block, lower, out=block)
        np.minimum(block, upper, out=block)
        refused = not math.isfinite(np.add.reduce(block, axis=None))
        if refused:  # rare: position and velocity fall back to what was sent, the rest to 0
            finite = np.isfinite(block, out=self._finite)
            np.copyto(block[:2], last, where=~finite[:2])
            np.copyto(block[2:], 0.0, where=~finite[2:])
            np.maximum(block, lower, out=block)
            np.minimum(block, upper, out=block)
            self.refused += 1
        self._before, self.last = last, self._before  # swap: no copy of the history
        np.copyto(self.last, block[:2])
        if self._outside:
            p = cmd.position
            self._outside = bool(((p < self.position_min) | (p > self.position_max)).any())
        return not refused
