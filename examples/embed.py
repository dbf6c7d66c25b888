"""Embed aiohal in an async application: run the mock arm for one second, then read its report.

    python examples/embed.py
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from aiohal import ControlLoop, load_config

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "mock_arm.toml"


async def main() -> dict:
    config = load_config(CONFIG).with_loop(clock="virtual")  # as fast as possible, deterministic
    async with ControlLoop(config) as loop:
        report = await loop.run(duration=1.0)
        print("joint positions after 1 s:", loop.robot.state.position.round(3))
    print(f"{report['ticks']} ticks, work p50 {report['work_us']['p50']} µs, controller {report['controller']}")
    return report


if __name__ == "__main__":
    asyncio.run(main())
