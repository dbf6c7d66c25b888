"""A driver of your own: joints on a link that answers one cycle late (docs/writing-a-driver.md).

``EchoLink`` stands in for the library of a real bus: connecting blocks, sending and
receiving do not. ``EchoDriver`` puts it behind the HAL: ``open()`` brings the link up off
the loop's thread, ``read()`` fills the driver's state rows in place, ``write()`` sends its
command rows, ``estop()`` disables the joints at once.

Register it in your package's pyproject:

    [project.entry-points."aiohal.drivers"]
    echo = "mypackage.driver:EchoDriver"

Here it is registered in this process (``aiohal.plugins.register``) so that a config can
name it; ``ControlLoop.from_parts`` also takes the class itself.

    python examples/custom_driver.py
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
from pydantic import Field

from aiohal import ControlLoop, Driver, JointValues, Mode, Options, parse_config, plugins
from aiohal.hal import unknown_joint_issues


class EchoLink:
    """The hardware: each enabled joint moves a fraction ``gain`` of the way to its target per
    cycle; a disabled joint stays where it is."""

    def __init__(self, gain: np.ndarray) -> None:
        self.gain = gain
        self.position = np.zeros(len(gain))
        self.target = np.zeros(len(gain))
        self.enabled = False

    def connect(self) -> None:
        time.sleep(0.05)  # bring-up blocks, as a real bus's does
        self.enabled = True

    def send(self, target: np.ndarray) -> None:
        np.copyto(self.target, target)

    def receive(self) -> np.ndarray:
        if self.enabled:
            self.position += self.gain * (self.target - self.position)
        return self.position


class EchoOptions(Options):
    gain: JointValues = Field(1.0, description="Fraction of the way to its target a joint moves per cycle, in (0, 1].")


class EchoDriver(Driver):
    """Position-controlled joints on an :class:`EchoLink`."""

    Options = EchoOptions
    options: EchoOptions  # what __init__ receives, typed as this driver's
    command_modes = frozenset({Mode.POSITION})

    @classmethod
    def check_config(cls, options, joints, devices, robot):
        issues = unknown_joint_issues("options.gain", options.gain, joints)
        gains = options.gain.values() if isinstance(options.gain, dict) else [options.gain]
        if not all(0.0 < gain <= 1.0 for gain in gains):
            issues.append(("options.gain", "every gain must be in (0, 1]"))
        return issues

    def __init__(self, name, view, options) -> None:
        super().__init__(name, view, options)
        self.link = EchoLink(view.per_joint(options.gain, default=1.0))
        self.cycles = 0

    async def open(self) -> None:
        await asyncio.to_thread(self.link.connect)  # blocking: never on the loop's thread

    async def read(self) -> None:
        np.copyto(self.view.state.position, self.link.receive())
        self.view.mark_fresh()

    async def write(self) -> None:
        self.link.send(self.view.command.position)
        self.cycles += 1

    def estop(self) -> None:
        self.link.enabled = False

    def release_estop(self) -> bool:
        self.link.send(self.link.position)  # enabled again where the joints stand
        self.link.enabled = True
        return True

    async def close(self) -> None:
        self.link.enabled = False

    def health(self) -> dict:
        return {"cycles": self.cycles}


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
