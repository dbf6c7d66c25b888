"""Small builders shared by tests: configs as dicts, loops on the virtual clock."""

from __future__ import annotations

import copy
from typing import Any

from aiohal.config import parse_config
from aiohal.loop import ControlLoop
from aiohal.ticker import VirtualTickSource


def arm_raw(n: int = 3, **controller: Any) -> dict[str, Any]:
    """A minimal n-joint robot on one mock driver, as a parsed-TOML dict."""
    raw: dict[str, Any] = {
        "robot": {"name": "test_arm"},
        "loop": {"rate_hz": 1000, "clock": "virtual"},
        "joints": {
            f"j{i}": {"position": [-2.0, 2.0], "velocity": 2.0, "acceleration": 20.0, "effort": 50.0}
            for i in range(n)
        },
        "driver": [{"type": "mock", "name": "arm", "joints": [f"j{i}" for i in range(n)]}],
        "controller": controller or {"type": "hold"},
    }
    return raw


def with_changes(raw: dict[str, Any], fn) -> dict[str, Any]:
    out = copy.deepcopy(raw)
    fn(out)
    return out


def virtual_loop(raw: dict[str, Any], **kwargs: Any) -> ControlLoop:
    config = parse_config(raw)
    return ControlLoop(config, tick_source=VirtualTickSource(), **kwargs)


def register_driver(monkeypatch, name: str, target: str) -> None:
    """Make ``target`` ("module:Class") loadable as driver ``name`` for one test only: the
    table entry and a fresh plugin cache are both undone by monkeypatch at teardown."""
    import functools

    from aiohal import plugins

    monkeypatch.setitem(plugins.BUILTIN["driver"], name, (target, None))
    monkeypatch.setattr(plugins, "load", functools.lru_cache(maxsize=None)(plugins.load.__wrapped__))
