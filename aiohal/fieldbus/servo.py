"""A joint servo model for simulated bus devices (joint boards, a KUKA controller).

No physics engine: each joint's position servo tracks a target that moves on with the
commanded velocity, and the tracking error decays with a time constant. The step is exact
for any time step (error × exp(-dt/τ)), so a simulator can advance whenever a datagram comes
and stays stable however late it is. Every joint in one set of array operations.
"""

from __future__ import annotations

import numpy as np

from aiohal.robot import Mode


class ServoModel:
    """``n`` joints: ``position``, ``velocity``, ``effort`` measured; targets set by ``command``."""

    def __init__(self, n: int, time_constant: float = 0.005, initial: np.ndarray | None = None) -> None:
        self.n = n
        self.time_constant = time_constant
        self.position = np.zeros(n) if initial is None else np.array(initial, dtype=np.float64)
        self.velocity = np.zeros(n)
        self.effort = np.zeros(n)
        self.target = self.position.copy()  # where the servo wants the joint now
        self.target_velocity = np.zeros(n)
        self.command_effort = np.zeros(n)
        self.stiffness = np.zeros(n)
        self.damping = np.zeros(n)
        self.mode = np.zeros(n, dtype=np.uint8)  # Mode values; NONE holds where it stands
        self._previous = np.zeros(n)

    def command(self, rows: slice | np.ndarray, mode, position, velocity, effort, stiffness=0.0, damping=0.0) -> None:
        """New targets for ``rows``: a position target restarts from the commanded position."""
        self.mode[rows] = mode
        self.target[rows] = np.where(self._tracks(mode), position, self.position[rows])
        self.target_velocity[rows] = np.where(np.asarray(mode) == Mode.EFFORT, 0.0, velocity)
        self.command_effort[rows] = effort
        self.stiffness[rows] = stiffness
        self.damping[rows] = damping

    @staticmethod
    def _tracks(mode) -> np.ndarray:
        mode = np.asarray(mode)
        return (mode == Mode.POSITION) | (mode == Mode.IMPEDANCE)

    def stop(self, rows: slice | np.ndarray = slice(None)) -> None:
        """Brake where the joints stand (mode NONE)."""
        self.mode[rows] = Mode.NONE
        self.target[rows] = self.position[rows]
        self.target_velocity[rows] = 0.0

    def step(self, dt: float) -> None:
        """Advance every joint by ``dt`` seconds."""
        if dt <= 0.0:
            return
        moving = (self.mode != Mode.NONE) & (self.mode != Mode.EFFORT)
        np.copyto(self._previous, self.position)
        # the error to the target decays while the target moves on with the commanded velocity
        error = (self.position - self.target) * np.exp(-dt / self.time_constant)
        self.target += np.where(moving, self.target_velocity, 0.0) * dt
        velocity_mode = self.mode == Mode.VELOCITY
        self.position = np.where(velocity_mode, self.target, np.where(moving, self.target + error, self.position))
        self.target = np.where(moving, self.target, self.position)
        np.subtract(self.position, self._previous, out=self.velocity)
        self.velocity /= dt
        self.effort = (
            self.command_effort + self.stiffness * (self.target - self.position) - self.damping * self.velocity
        )
