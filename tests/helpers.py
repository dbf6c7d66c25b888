"""Small builders shared by tests: configs as dicts, loops on the virtual clock."""

from __future__ import annotations

import copy
from typing import Any

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.core.ticker import VirtualTickSource


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


def record(loop):
    """Per tick run: the tick, the position sent and the measured position; and per update of
    the loop's controller, what it wrote itself, before the limits."""

    sent, measured, own = [], [], []
    controller = loop.controller
    update = controller.update

    def spied(t, dt):
        update(t, dt)
        own.append((loop.robot.clock.tick, loop.robot.command.position.copy()))

    controller.update = spied
    loop.add_publisher(lambda lp: (sent.append((lp.robot.clock.tick, lp.limiter.last_position.copy())),
                                   measured.append(lp.robot.state.position.copy())))
    return sent, measured, own


def at(tick, action):
    """A publisher doing ``action(loop)`` at one tick."""
    return lambda lp: action(lp) if lp.robot.clock.tick == tick else None


def assert_bumpless(loop, sent, measured, own, rearm_tick, since=0):
    """No step of the position sent larger than one tick of the velocity limit per tick run,
    and the restarted controller's own first command within one such step of the last
    command sent and of the measured position (it does not start elsewhere and catch up).
    ``since``: the first tick checked (a joint resynchronised before it may jump, by design)."""
    import numpy as np

    step = loop.robot.velocity_limit * loop.period_s
    ticks = np.array([k for k, _ in sent])
    positions = np.array([q for _, q in sent])
    gaps = np.diff(ticks)[:, None]
    bad = (np.abs(np.diff(positions, axis=0)) > gaps * step + 1e-12).any(axis=1) & (ticks[1:] >= since)
    assert not bad.any(), f"steps larger than the velocity limit at ticks {ticks[1:][bad][:10]}"
    i = int(np.flatnonzero(ticks == rearm_tick)[0])
    first = [q for k, q in own if k > rearm_tick]
    assert first, "the controller did not run after the re-arm"
    assert (np.abs(first[0] - positions[i]) <= step).all(), (first[0], positions[i])
    assert (np.abs(first[0] - measured[i]) <= step + 1e-9).all(), (first[0], measured[i])


def assert_rearmed_from_disabled(loop, sent, measured, own, rearm_tick, held, held_within, moving_after):
    """After a re-arm from ``disabled`` (an emergency stop released), where nothing was sent:
    the joints stood where the drives held them (``held``, within ``held_within``), the
    controller's first command lies within one step of the velocity limit of the measured
    position, every step after it is bumpless, and the first joint moves again (more than
    0.05 rad peak to peak) ``moving_after`` ticks on."""
    import numpy as np

    i = [k for k, _ in sent].index(rearm_tick)
    assert np.abs(measured[i] - held).max() < held_within
    step = loop.robot.velocity_limit * loop.period_s
    first = next(q for k, q in own if k > rearm_tick)
    assert (np.abs(first - measured[i]) <= step + 1e-9).all(), (first, measured[i])
    assert_bumpless(loop, sent[i + 1 :], measured[i + 1 :], own, sent[i + 1][0])
    assert np.ptp(np.array([q for k, q in sent if k > rearm_tick + moving_after])[:, 0]) > 0.05


class Reported:
    """A driver view's events kept for a test (``view.attach(Reported(view))``): every fault
    as (tick, reason, hold), and the masks of every resync."""

    def __init__(self, view) -> None:
        self.clock = view.clock
        self.faults: list[tuple[int, str, bool]] = []
        self.resyncs: list = []

    def fault(self, phase: str, reason: str, hold: bool) -> None:
        self.faults.append((self.clock.tick, reason, hold))

    def resync(self, mask) -> None:
        self.resyncs.append(mask.copy())

    @property
    def reasons(self) -> list[str]:
        return [reason for _, reason, _ in self.faults]

    @property
    def holds(self) -> list[int]:
        """The ticks of the faults that asked for a hold."""
        return [tick for tick, _, hold in self.faults if hold]
