"""The examples run and do what they say (they are documentation that must not rot)."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest
from conftest import ROOT

from aiohal import plugins


def load(name):
    spec = importlib.util.spec_from_file_location(f"example_{name}", ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    # in sys.modules as an imported module is: pydantic resolves the string annotations of an
    # example's option models (``from __future__ import annotations``) in its namespace
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.mark.asyncio
async def test_embed_example():
    report = await load("embed").main()
    assert report["ticks"] == 1000 and report["controller"]["type"] == "sine"


@pytest.mark.asyncio
async def test_custom_controller_example_pulls_joints_to_zero():
    position = await load("custom_controller").main()
    assert np.allclose(position, 0.0, atol=1e-12)


@pytest.mark.asyncio
async def test_custom_driver_example():
    module = load("custom_driver")
    try:
        report = await module.main()
        assert plugins.available("driver")["echo"].source == "registered"
    finally:
        plugins.unregister("driver", "echo")
    assert "echo" not in plugins.available("driver")
    assert report["controller"]["reached"] is True
    assert report["controller"]["final_error_max"] < 1e-9
    assert report["drivers"]["echo"]["type"] == "echo"


@pytest.mark.asyncio
async def test_from_code_example_runs_a_loop_without_a_config_file():
    module = load("from_code")
    loop = module.build()
    assert loop.config.path is None
    swing = np.zeros(3)

    def largest(control):
        np.maximum(swing, np.abs(control.robot.state.position), out=swing)

    loop.add_publisher(largest)
    async with loop:
        report = await loop.run(duration=2.0)
    assert report["ticks"] == 2000 and report["faults"] == []
    assert report["robot"] == "code_bot" and report["drivers"]["MockDriver"]["joints"] == 3
    assert report["controller"]["type"] == "SineController"
    # j1 swings 0.3 rad once ramped in (its peak at t = 1.5 s, lagged by the first-order
    # dynamics), j2 0.2 rad, and j3, with no amplitude, never leaves 0
    assert 0.25 < swing[0] <= 0.3 and 0.15 < swing[1] <= 0.2 and swing[2] == 0.0
    assert (await load("from_code").main())["ticks"] == 2000  # and main() itself runs
