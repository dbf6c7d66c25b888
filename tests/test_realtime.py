"""Real-time settings: applied to the ticking thread and restored; failures become warnings."""

from __future__ import annotations

import os

import pytest
from conftest import require_root
from helpers import arm_raw, virtual_loop

from aiohal.config import parse_config
from aiohal.core import realtime
from aiohal.core.loop import ControlLoop
from aiohal.errors import ConfigError


def test_fifo_is_applied_and_restored():
    require_root("SCHED_FIFO needs root or CAP_SYS_NICE")
    before = os.sched_getscheduler(0)
    state = realtime.apply(realtime.RealtimeSection(priority=10, timer_slack_ns=1))
    try:
        assert os.sched_getscheduler(0) == os.SCHED_FIFO
        assert os.sched_getparam(0).sched_priority == 10
        assert realtime.timer_slack_ns() in (0, 1)  # an RT task has no slack at all
        assert state.applied["sched_fifo_priority"] == 10 and state.warnings == []
    finally:
        realtime.restore(state)
    assert os.sched_getscheduler(0) == before
    assert realtime.timer_slack_ns() == state._slack != 1


def test_each_failure_becomes_one_warning(monkeypatch, caplog):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "sched_setaffinity", refuse)
    monkeypatch.setattr(realtime, "_libc_call", refuse)
    settings = realtime.RealtimeSection(priority=80, lock_memory=True, cpus=[0], timer_slack_ns=1)
    state = realtime.apply(settings)
    assert state.applied == {}
    assert len(state.warnings) == 4
    assert any("SCHED_FIFO priority 80" in w and "Operation not permitted" in w for w in state.warnings)
    assert any("mlockall" in w for w in state.warnings)
    assert len([r for r in caplog.records if r.levelname == "WARNING"]) == 4
    realtime.restore(state)  # nothing to undo: no error


@pytest.mark.asyncio
async def test_run_reports_realtime_and_keeps_going_without_permission(monkeypatch):
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: (_ for _ in ()).throw(PermissionError(1, "nope")))
    raw = arm_raw(2)
    raw["realtime"] = {"priority": 50}
    raw["loop"]["clock"] = "auto"  # a real clock: the virtual one never applies these settings
    async with ControlLoop(parse_config(raw)) as loop:
        report = await loop.run(ticks=10)
    assert report["ticks"] + report["missed_ticks"] == 10  # a real clock: deadlines served or counted
    assert report["realtime"]["warnings"] and "nope" in report["realtime"]["warnings"][0]


def test_spin_guard_above_half_the_period_is_a_config_error():
    raw = arm_raw(2)
    raw["realtime"] = {"spin_guard_us": 600}
    with pytest.raises(ConfigError) as info:
        parse_config(raw)
    [issue] = info.value.issues
    assert issue.path == "realtime.spin_guard_us"
    assert "more than half the period (500 µs)" in issue.message
    raw["realtime"] = {"spin_guard_us": 200}
    config = parse_config(raw)
    with pytest.raises(ValueError):
        config.with_loop(rate_hz=4000)  # 200 µs is more than half of 250 µs


@pytest.mark.asyncio
async def test_virtual_clock_never_applies_realtime_settings(monkeypatch):
    calls = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: calls.append(a))
    raw = arm_raw(2)
    raw["realtime"] = {"priority": 50, "lock_memory": True}
    async with virtual_loop(raw) as loop:
        report = await loop.run(ticks=10)
    assert calls == []  # a flat-out virtual loop under SCHED_FIFO would starve the machine
    # chosen, so not a warning: a note of what was not applied
    assert report["realtime"] == {"not_applied": "priority, lock_memory (virtual clock)", "warnings": []}


@pytest.mark.asyncio
async def test_virtual_clock_warns_nothing_when_nothing_was_asked():
    async with virtual_loop(arm_raw(2)) as loop:
        report = await loop.run(ticks=10)
    assert report["realtime"]["warnings"] == []
