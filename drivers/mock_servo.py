"""The mock's ``dynamics = "servo"``: each joint behind a simulated servo drive
(:mod:`aiohal.simulation.servo`, LOLA's cascade with the motor and the load).

The drive gets, at each write, the command's target position, its target velocity as velocity
feed-forward and its effort plus feed-forward as torque feed-forward, as a CiA 402 drive in
cyclic synchronous position mode gets them (0x607A, 0x60B1, 0x60B2); the next read runs the
drive over the time since and measures position, velocity and motor torque. A joint commanded
in another mode than position or impedance holds where it stands (the drive's position loop
on its own position, no feed-forward).
"""

from __future__ import annotations

import numpy as np

from aiohal.robot import DriverView, Mode
from aiohal.simulation.servo import ServoBank, ServoParams


class MockServo:
    def __init__(self, view: DriverView, params: ServoParams, sim: np.ndarray) -> None:
        self.command = view.command
        self.sim = sim  # rows: position, velocity, effort (the state's, or the driver's own)
        self.bank = ServoBank(params, sim[0])
        n = view.dof
        self._target = np.zeros(n)
        self._velocity = np.zeros(n)
        self._torque = np.zeros(n)
        self._tracks = np.zeros(n, dtype=bool)
        self._impedance = np.zeros(n, dtype=bool)

    def write(self) -> None:
        """The command to the drives (in place, no allocation)."""
        cmd = self.command
        np.equal(cmd.mode, Mode.POSITION, out=self._tracks)
        np.equal(cmd.mode, Mode.IMPEDANCE, out=self._impedance)
        np.logical_or(self._tracks, self._impedance, out=self._tracks)
        np.copyto(self._target, self.sim[0])
        np.copyto(self._target, cmd.position, where=self._tracks)
        self._velocity.fill(0.0)
        np.copyto(self._velocity, cmd.velocity, where=self._tracks)
        self._torque.fill(0.0)
        np.add(cmd.effort, cmd.feedforward, out=self._torque, where=self._tracks)
        self.bank.command(self._target, self._velocity, self._torque)

    def step(self, dt: float) -> None:
        self.bank.step(dt)
        self.bank.measure(self.sim[0], self.sim[1], self.sim[2])
