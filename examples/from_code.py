"""A robot built in code, with no TOML file: joints and limits, a driver, a controller.

``ControlLoop.from_parts`` takes what a config file holds as Python values and validates them
the same way (a mistake raises ``ConfigError`` naming the key, e.g. ``driver[0].joints``).
A driver is given by its plugin name or its class, with its joints and options: it is built
by the loop, which hands it the view of its rows. A controller may be an instance.

    python examples/from_code.py
"""

from __future__ import annotations

import asyncio

from aiohal import ControlLoop
from aiohal.controllers.sine import SineController
from aiohal.drivers.mock import MockDriver

#: three joints of ±1 rad, 2 rad/s, 20 rad/s² (what [joints.<name>] tables say in a file)
JOINTS = {name: {"position": [-1.0, 1.0], "velocity": 2.0, "acceleration": 20.0} for name in ("j1", "j2", "j3")}


def build() -> ControlLoop:
    return ControlLoop.from_parts(
        robot="code_bot",
        joints=JOINTS,
        drivers=[(MockDriver, {"joints": ["j*"], "options": {"dynamics": "first_order", "time_constant": 0.01}})],
        controller=SineController(),
        params={"amplitude": {"j1": 0.3, "j2": 0.2}, "frequency": 0.5},
        rate_hz=1000,
        clock="virtual",  # as fast as the CPU allows, deterministic
    )


async def main() -> dict:
    loop = build()
    async with loop:
        report = await loop.run(duration=2.0)
        print("joint positions after 2 s:", loop.robot.state.position.round(3))
    print(f"{report['ticks']} ticks on the {report['clock']} clock, controller {report['controller']}")
    return report


if __name__ == "__main__":
    asyncio.run(main())
