"""A controller slower than the bus: targets extrapolated on the ticks in between (LOLA).

With ``[controller] every = n`` the controller runs on every n-th tick only, and the drivers
still exchange data on every tick. On the ticks in between, the command is the one the
controller left, moved on along its own motion: the target velocity's rate of change over the
controller's last two updates, ``a* = (v*(k₀) − v*(k₋₁)) / ((k₀ − k₋₁)·T)``, carries both
targets on, ``q*(k) = q*(k₀) + v*(k₀)·τ + a*·τ²/2`` and ``v*(k) = v*(k₀) + a*·τ`` with
``τ = (k − k₀)·T``. The drives then get a ramp at the bus rate instead of a staircase at the
controller's rate, which is what lets a slow planner drive a fast servo loop without exciting
it at the controller's frequency; and since a drive takes the target velocity as its velocity
feed-forward, that has to move on too: held, it lags the motion by a*·τ, which a servo with a
tuned feed-forward turns straight into tracking error (docs/experiments.md).

Only joints commanded in position or impedance mode are extrapolated; effort, stiffness,
damping and the torque feed-forward are held as the controller left them, and so is everything
of the joints in other modes. Until the controller has updated twice in the same modes (after
the start, a mode change or a resync) the acceleration is taken as zero: the position moves on
with the last target velocity alone. The command limits still apply on every tick, to the
extrapolated targets: an extrapolation cannot leave the range or go faster than the velocity
limit. A controller that sets no target velocity gets a zero-order hold.
"""

from __future__ import annotations

import numpy as np

from ..robot import CommandRow, JointCommand, Mode

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
        n = command.block.shape[-1]
        self._accel = np.zeros(n)  # the target velocity's rate of change between the last two updates
        self._step = np.zeros(n)
        self._moving = np.zeros(n, dtype=bool)  # rows in position / impedance mode
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
        modes = cmd.mode.tobytes()
        # two updates of the same motion: not the first, not after a resync, not across a mode change
        if self.updates and not self._due and modes == self._modes and k > self._anchor_k:
            np.subtract(cmd.velocity, self._anchor[VEL], out=self._accel)
            self._accel /= (k - self._anchor_k) * self.period_s
        else:
            self._accel.fill(0.0)
        np.copyto(self._anchor, cmd.block)
        self._anchor_k = k
        self._due = False
        self.updates += 1
        if modes != self._modes:
            self._modes = modes
            np.equal(cmd.mode, Mode.POSITION, out=self._moving)
            self._moving |= cmd.mode == Mode.IMPEDANCE
            self._any_moving = bool(self._moving.any())

    def fill(self, k: int) -> None:
        """A tick without the controller: its last command, position and velocity targets moved on."""
        block = self.command.block
        np.copyto(block, self._anchor)
        if self.extrapolate and self._any_moving:
            tau = (k - self._anchor_k) * self.period_s
            step = self._step
            np.multiply(self._accel, 0.5 * tau, out=step)  # (v* + a*·τ/2)·τ, in place
            step += self._anchor[VEL]
            step *= tau
            np.add(block[POS], step, out=block[POS], where=self._moving)
            np.multiply(self._accel, tau, out=step)
            np.add(block[VEL], step, out=block[VEL], where=self._moving)
