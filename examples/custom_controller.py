"""A custom controller: a PD-like pull of every joint toward zero, bounded in speed.

Controllers implement a synchronous ``update(t, dt)`` that writes ``self.robot.command`` from
``self.robot.state``, with numpy operations on whole arrays (no per-joint Python loop).
Register it in your package's pyproject under ``[project.entry-points."aiohal.controllers"]``
to use it from a config by name; here it is passed to the loop directly.

    python examples/custom_controller.py
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
from pydantic import Field

from aiohal import Controller, ControlLoop, Options, load_config
from aiohal.robot import Mode

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "mock_arm.toml"


class ToZeroParams(Options):
    speed: float = Field(0.5, gt=0, description="Speed toward zero (rad/s).")


class ToZero(Controller):
    Params = ToZeroParams

    def configure(self, robot, params):
        super().configure(robot, params)
        self._step = np.empty(robot.dof)

    def start(self, t):
        self.robot.command.mode[:] = Mode.POSITION

    def update(self, t, dt):
        cmd = self.robot.command
        # move the command toward zero by at most speed·dt per tick
        np.clip(cmd.position, -self.params.speed * dt, self.params.speed * dt, out=self._step)
        cmd.position -= self._step


async def main() -> np.ndarray:
    config = load_config(CONFIG).with_loop(clock="virtual")
    loop = ControlLoop(config, controller=ToZero(), controller_params=ToZeroParams(speed=1.0))
    async with loop:
        await loop.run(duration=2.0)
    print("positions after 2 s:", loop.robot.state.position.round(4))
    return loop.robot.state.position.copy()


if __name__ == "__main__":
    asyncio.run(main())
