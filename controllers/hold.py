"""``hold``: keep every joint where its command is, braking to rest within the limits.

It is also the fallback the loop switches to when a driver or controller fails, so it
starts from the last command sent (position and rate) and never jumps: a joint that was
moving decelerates at its acceleration limit (instantly where none is configured).
"""

from __future__ import annotations

import numpy as np

from aiohal.hal import Controller, Options
from aiohal.robot import Mode


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
        self.rest = self.x0 + 0.5 * self.v0 * self.t_stop  # where each joint comes to rest
        cmd.mode[:] = Mode.POSITION
        cmd.effort[:] = 0.0
        cmd.feedforward[:] = 0.0
        self.update(t, 0.0)

    def update(self, t: float, dt: float) -> None:
        cmd = self.robot.command
        elapsed = t - self.t0
        if elapsed < self.t_settled:
            # x = x0 + v0·τ + ½·a·τ², v = v0 + a·τ  (a opposes v0; τ stops at t_stop)
            tau = np.minimum(self.t_stop, elapsed)
            cmd.velocity[:] = self.v0 + self.decel * tau
            cmd.position[:] = self.x0 + 0.5 * (self.v0 + cmd.velocity) * tau
        else:
            cmd.position[:] = self.rest
            cmd.velocity[:] = 0.0

    def metrics(self) -> dict:
        return {"braking_s": round(self.t_settled, 4)}
