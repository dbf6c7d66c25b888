"""A controller slower than the bus: targets extrapolated on the ticks in between (LOLA).

With ``[controller] every = n`` the controller runs on every n-th tick only, and the drivers
still exchange data on every tick. On the ticks in between, the command is the one the
controller left, with each position target moved on along a line with its last target
velocity: ``q*(k) = q*(k₀) + v*(k₀)·(k − k₀)·T``. The drives then get a ramp at the bus rate
instead of a staircase at the controller's rate, which is what lets a slow planner drive a
fast servo loop without exciting it at the controller's frequency.

Only joints commanded in position or impedance mode are extrapolated; velocity, effort,
stiffness, damping and feed-forward are held as the controller left them. The command limits
still apply on every tick, to the extrapolated targets: an extrapolation cannot leave the range
or go faster than the velocity limit. A controller that sets no target velocity gets a
zero-order hold.
"""

from __future__ import annotations

import numpy as np

from .robot import CommandRow, JointCommand, Mode

POS, VEL = CommandRow.POSITION, CommandRow.VELOCITY


class TargetExtrapolator:
    """Decides which ticks run the controller, and fills the command on the others."""

    def __init__(self, command: JointCommand, period_s: float, every: int, extrapolate: bool = True) -> None:
        if every < 1:
            raise ValueError(f"every must be >= 1, not {every}")
        self.command = command
        self.period_s = period_s
        self.every = every
        self.extrapolate = extrapolate
        self._anchor = np.zeros_like(command.block)  # the command as the controller left it
        self._anchor_k = 0
        self._due = True
        self._step = np.zeros(command.block.shape[-1])
        self._moving = np.zeros(command.block.shape[-1], dtype=bool)  # rows in position / impedance mode
        self._any_moving = False
        self._modes = b""
        self.updates = 0  # controller updates since the start

    def due(self, k: int) -> bool:
        """The controller runs at tick ``k``: ``every`` ticks after its last update (or more,
        when ticks were skipped), or at once after :meth:`force`."""
        return self._due or k - self._anchor_k >= self.every

    def force(self) -> None:
        """Run the controller on the next tick (the command was changed under it: a resync)."""
        self._due = True

    def capture(self, k: int) -> None:
        """The controller has just updated the command at tick ``k`` (before the limits)."""
        cmd = self.command
        np.copyto(self._anchor, cmd.block)
        self._anchor_k = k
        self._due = False
        self.updates += 1
        modes = cmd.mode.tobytes()
        if modes != self._modes:
            self._modes = modes
            np.equal(cmd.mode, Mode.POSITION, out=self._moving)
            self._moving |= cmd.mode == Mode.IMPEDANCE
            self._any_moving = bool(self._moving.any())

    def fill(self, k: int) -> None:
        """A tick without the controller: its last command, position targets moved on."""
        block = self.command.block
        np.copyto(block, self._anchor)
        if self.extrapolate and self._any_moving:
            np.multiply(self._anchor[VEL], (k - self._anchor_k) * self.period_s, out=self._step)
            np.add(block[POS], self._step, out=block[POS], where=self._moving)
