"""``hold``: keep every joint where its command is, braking to rest within the limits.

It is also the fallback the loop switches to when a driver or controller fails, so it
starts from the last command sent (position and rate) and never jumps: a joint that was
moving decelerates at its acceleration limit (instantly where none is configured).
"""

from __future__ import annotations

import numpy as np

from aiohal.hal import Controller, Options
from aiohal.robot import CommandRow, Mode


class HoldParams(Options):
    pass


class HoldController(Controller):
    Params = HoldParams

    def start(self, t: float) -> None:
        cmd = self.robot.command
        accel = self.robot.acceleration_limit
        self.t0 = t
        self.x0 = cmd.position.copy()
        v0 = np.where(np.isfinite(cmd.velocity), cmd.velocity, 0.0)
        braking = np.isfinite(accel) & (v0 != 0.0)
        self.v0 = np.where(braking, v0, 0.0)
        self.decel = np.where(braking, -np.sign(v0) * np.where(np.isfinite(accel), accel, 0.0), 0.0)
        self.t_stop = np.where(braking, np.abs(v0) / np.where(np.isfinite(accel), accel, 1.0), 0.0)
        self.t_settled = float(self.t_stop.max(initial=0.0))
        self._tau = np.empty_like(self.x0)
        cmd.mode[:] = Mode.POSITION
        cmd.effort[:] = 0.0
        cmd.feedforward[:] = 0.0
        self._braking = self.t_settled > 0.0
        # At rest, one copy per tick writes the position and velocity rows, adjacent in the
        # command block: [where each joint comes to rest, 0]. A byte copy between memoryviews,
        # because on the real clock's cold caches np.copyto costs several µs more per tick
        # (docs/performance.md, "Why the compiled kernels are kept"); memoryview.cast()
        # refuses any block that is not C-contiguous.
        rows = cmd.block[CommandRow.POSITION : CommandRow.VELOCITY + 1]
        if rows.shape[0] != 2:
            raise RuntimeError("hold writes position and velocity as adjacent rows of the command block")
        rest = np.array([self.x0 + 0.5 * self.v0 * self.t_stop, np.zeros_like(self.x0)])
        self._rest = rest.data.cast("B")
        self._position_velocity = rows.data.cast("B")
        self._write(0.0)

    def _write(self, elapsed: float) -> None:
        cmd = self.robot.command
        tau = np.minimum(self.t_stop, elapsed, out=self._tau)
        # x = x0 + v0·τ + ½·a·τ², v = v0 + a·τ  (a opposes v0; τ stops at t_stop)
        np.multiply(self.decel, tau, out=cmd.velocity)
        cmd.velocity += self.v0
        np.add(self.v0, cmd.velocity, out=cmd.position)
        cmd.position *= 0.5
        cmd.position *= tau
        cmd.position += self.x0

    def update(self, t: float, dt: float) -> None:
        if self._braking:
            elapsed = t - self.t0
            self._write(elapsed)
            self._braking = elapsed < self.t_settled
        else:
            self._position_velocity[:] = self._rest

    def metrics(self) -> dict:
        return {"braking_s": round(self.t_settled, 4)}
