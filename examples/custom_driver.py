"""A custom driver: joints that answer over a (simulated) non-blocking link.

A driver owns a contiguous run of joints and gets views of their rows: ``read()`` fills
``self.view.state`` in place and calls ``self.view.mark_fresh()``; ``write()`` sends
``self.view.command``. Neither may block: bring-up that blocks belongs in ``open()``
(``asyncio.to_thread``). ``estop()`` is synchronous and idempotent.

Register it in your package's pyproject:

    [project.entry-points."aiohal.drivers"]
    echo = "mypackage.driver:EchoDriver"

Here it is registered in this process (``aiohal.plugins.register``) so that a config can
name it; ``ControlLoop.from_parts`` also takes the class itself (examples/from_code.py).

    python examples/custom_driver.py
"""

from __future__ import annotations

import asyncio

import numpy as np
from pydantic import Field

from aiohal import ControlLoop, Driver, Options, parse_config, plugins


class EchoOptions(Options):
    gain: float = Field(1.0, gt=0, le=1.0, description="Fraction of the command the joint reaches.")


class EchoDriver(Driver):
    """Reports each command back, scaled: stands in for a bus whose frames come back next tick."""

    Options = EchoOptions

    async def open(self) -> None:
        self._last = np.zeros(self.view.dof)  # what the "bus" returns on the next read

    async def read(self) -> None:
        np.multiply(self._last, self.options.gain, out=self.view.state.position)
        self.view.mark_fresh()

    async def write(self) -> None:
        np.copyto(self._last, self.view.command.position)

    def estop(self) -> None:
        pass  # a real driver would disable the drives here


CONFIG = {
    "robot": {"name": "echo_bot"},
    "loop": {"rate_hz": 500, "clock": "virtual"},
    "joints": {"q1": {"position": [-1, 1], "velocity": 1.0}, "q2": {"position": [-1, 1], "velocity": 1.0}},
    "driver": [{"type": "echo", "joints": ["q1", "q2"], "options": {"gain": 1.0}}],
    "controller": {"type": "homing", "params": {"pose": {"q1": 0.5, "q2": -0.25}, "duration": 1.0}},
}


async def main() -> dict:
    plugins.register("driver", "echo", EchoDriver)
    async with ControlLoop(parse_config(CONFIG)) as loop:
        report = await loop.run(duration=1.5)
    print("measured:", loop.robot.state.position, "controller:", report["controller"])
    return report


if __name__ == "__main__":
    asyncio.run(main())
