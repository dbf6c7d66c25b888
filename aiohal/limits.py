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
entries of a command are refused: each is replaced by the value sent last tick, and the result
is clamped like any other command.
"""

from __future__ import annotations

import math

import numpy as np

from .robot import JOINT_COMMAND_FIELDS, Mode, Robot

_ROW = {name: i for i, name in enumerate(JOINT_COMMAND_FIELDS)}
POS, VEL = _ROW["position"], _ROW["velocity"]


class CommandLimiter:
    def __init__(self, robot: Robot, period_s: float) -> None:
        self.cmd = robot.command
        self.state = robot.state
        n = robot.dof
        self.period_s = period_s
        self.position_min = robot.position_min
        self.position_max = robot.position_max
        self.max_step = robot.velocity_limit * period_s
        self.max_velocity_change = robot.acceleration_limit * period_s
        self.velocity_limit = robot.velocity_limit
        self.limit_acceleration = bool(np.isfinite(robot.acceleration_limit).any())
        lower = np.empty((len(JOINT_COMMAND_FIELDS), n))
        upper = np.empty_like(lower)
        for name, i in _ROW.items():
            if name in ("effort", "feedforward"):
                lower[i], upper[i] = -robot.effort_limit, robot.effort_limit
            elif name == "velocity":
                lower[i], upper[i] = -robot.velocity_limit, robot.velocity_limit
            else:  # position (recomputed each tick), stiffness, damping
                lower[i], upper[i] = 0.0, np.inf
        self.lower, self.upper = lower, upper
        self.last_position = np.zeros(n)
        self.previous_position = np.zeros(n)
        self.last_velocity = np.zeros(n)
        self._outside = False  # a joint's last command lies outside its range
        self.sent = np.zeros_like(lower)  # the command block sent last tick
        self._finite = np.zeros(lower.shape, dtype=bool)
        self._modes = b""
        self._velocity_rows = np.zeros(n, dtype=bool)
        self._any_velocity_mode = False
        self._inside = np.zeros(n, dtype=bool)
        self.refused = 0  # ticks whose command was not finite

    def reset(self, position: np.ndarray) -> None:
        """Start limiting from a known position at rest (activation, re-arm)."""
        np.copyto(self.last_position, position)
        np.copyto(self.previous_position, position)
        self.last_velocity[:] = 0.0
        np.copyto(self.sent, self.cmd.block)
        self._outside = bool(((position < self.position_min) | (position > self.position_max)).any())

    def last_rate(self, out: np.ndarray) -> np.ndarray:
        """The rate of the last position command sent (per second)."""
        np.subtract(self.last_position, self.previous_position, out=out)
        out /= self.period_s
        return out

    def hold_last(self) -> None:
        """Replace the command with the last position sent, moving at its last rate, no effort.

        ``hold`` starts from this and brakes to rest within the acceleration limits.
        """
        cmd = self.cmd
        np.copyto(cmd.position, self.last_position)
        self.last_rate(cmd.velocity)
        cmd.effort[:] = 0.0
        cmd.feedforward[:] = 0.0

    def follow_measured(self, rows: np.ndarray, velocity: np.ndarray) -> None:
        """Make ``rows`` continue from their measured position at ``velocity`` (a switch from a
        velocity- or effort-mode controller, whose position command meant nothing)."""
        measured = self.state.position
        ok = rows & np.isfinite(measured)
        np.copyto(self.last_position, measured, where=ok)
        np.copyto(self.previous_position, measured - velocity * self.period_s, where=ok)

    def apply(self) -> bool:
        """Clamp the command in place. False if some entry was not finite (it was replaced by
        the value sent last tick before clamping)."""
        cmd = self.cmd
        block = cmd.block
        refused = False
        with np.errstate(over="ignore", invalid="ignore"):  # inf - inf, overflow: checked below
            total = np.add.reduce(block, axis=None)
        if not math.isfinite(total):  # rare: find which entries
            finite = np.isfinite(block, out=self._finite)
            if not finite.all():
                np.copyto(block, self.sent, where=~finite)
                self.refused += 1
                refused = True
        lower, upper = self.lower, self.upper
        last = self.last_position
        lo, hi = lower[POS], upper[POS]
        np.subtract(last, self.max_step, out=lo)
        np.add(last, self.max_step, out=hi)
        if self._outside:  # window ∩ range, or the window's edge nearest the range
            np.maximum(lo, np.minimum(self.position_min, hi), out=lo)
            np.minimum(hi, np.maximum(self.position_max, lo), out=hi)
        else:
            np.maximum(lo, self.position_min, out=lo)
            np.minimum(hi, self.position_max, out=hi)
        if self.limit_acceleration:
            last_v = self.last_velocity
            np.subtract(last_v, self.max_velocity_change, out=lower[VEL])
            np.maximum(lower[VEL], -self.velocity_limit, out=lower[VEL])
            np.add(last_v, self.max_velocity_change, out=upper[VEL])
            np.minimum(upper[VEL], self.velocity_limit, out=upper[VEL])
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
        np.maximum(block, lower, out=block)
        np.minimum(block, upper, out=block)
        np.copyto(self.sent, block)
        if self.limit_acceleration:
            np.copyto(self.last_velocity, cmd.velocity)
        # the previous buffer becomes the last one: no copy of the history
        self.previous_position, self.last_position = last, self.previous_position
        np.copyto(self.last_position, cmd.position)
        if self._outside:
            self._outside = bool(
                ((cmd.position < self.position_min) | (cmd.position > self.position_max)).any()
            )
        if self._any_velocity_mode and not self.limit_acceleration:
            # the velocity rows' bounds were narrowed for this tick only: restore them
            np.copyto(lower[VEL], -self.velocity_limit)
            np.copyto(upper[VEL], self.velocity_limit)
        return not refused
