"""The examples run and do what they say (they are documentation that must not rot)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from aiohal import plugins
from conftest import ROOT


def load(name):
    spec = importlib.util.spec_from_file_location(f"example_{name}", ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
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
async def test_custom_driver_example(monkeypatch):
    module = load("custom_driver")
    monkeypatch.setitem(plugins.BUILTIN["driver"], "echo", (f"{module.__name__}:EchoDriver", None))
    import sys

    sys.modules[module.__name__] = module
    try:
        plugins.load.cache_clear()
        report = await module.main()
    finally:
        del sys.modules[module.__name__]
        plugins.load.cache_clear()
    assert report["controller"]["reached"] is True
    assert report["controller"]["final_error_max"] < 1e-9
