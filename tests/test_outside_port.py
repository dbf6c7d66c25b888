"""The loop's port: what everything outside the tick reads of a loop, and asks of it."""

from __future__ import annotations

import os
import time

import pytest
from conftest import NOT_HUNG_S
from helpers import arm_raw, virtual_loop

from aiohal.outside.event_feed import EventFeed
from aiohal.outside.terminal_status import StatusFigures, render
from aiohal.outside.tick_door import make_ring
from aiohal.outside.tick_ring import TickReader
from aiohal.safety import SafetyLevel, SafetyRequestExpired, SafetyRequestRefused


@pytest.mark.asyncio
async def test_at_tick_end_sees_each_tick_once_with_what_it_left():
    loop = virtual_loop(arm_raw(type="sine", params={"amplitude": 0.2}))
    port = loop.port
    seen = []

    def publish(_: object) -> None:
        seen.append((port.tick, port.running, port.level, float(port.robot.command.position[0])))

    async with loop:
        port.at_tick_end(publish)
        await loop.run(ticks=50)
        assert not port.running
        ticks = [s[0] for s in seen]
        assert ticks == list(range(ticks[0], ticks[0] + 50)) and ticks[-1] == port.tick
        assert all(running and level == SafetyLevel.RUN for _, running, level, _ in seen)
        assert len({round(p, 9) for *_, p in seen}) > 10  # the sine's commands, tick by tick
        assert port.timing.count == 50 and port.missed_ticks == 0
        assert port.clock_kind == "virtual" and port.period_ns == 1_000_000

        port.stop_calling(publish)
        await loop.run(ticks=10)
        assert len(seen) == 50


@pytest.mark.asyncio
async def test_health_is_the_drivers_and_the_controllers_as_the_report_gives_them():
    loop = virtual_loop(arm_raw(type="sine", params={"amplitude": 0.2}))
    async with loop:
        await loop.run(ticks=20)
        health = loop.port.health()
        report = loop.report()
    assert health.level == SafetyLevel.RUN and health.tick == loop.robot.clock.tick
    assert health.drivers["arm"]["status"] == report["drivers"]["arm"]["status"] == "open"
    assert health.controller["type"] == "sine"
    assert health.as_dict()["safety_level"] == "run"


@pytest.mark.asyncio
async def test_requests_act_or_are_refused_with_the_loops_reasons():
    loop = virtual_loop(arm_raw())
    port = loop.port
    async with loop:
        await loop.run(ticks=20)
        port.hold("a test")
        assert port.level == SafetyLevel.HOLD
        with pytest.raises(SafetyRequestRefused, match="only from run"):
            port.hold("again")
        port.estop("a test", source="test")
        assert port.level == SafetyLevel.ESTOP
        with pytest.raises(SafetyRequestRefused, match="reset_faults\\(\\) first"):
            port.rearm(source="test", act_by_ns=None)
        # a request whose last moment to act passed a moment ago is not acted on, whatever the level
        gone = time.monotonic_ns() - 1_000_000
        with pytest.raises(SafetyRequestExpired, match="too late to answer its caller"):
            port.reset_faults(source="test", act_by_ns=gone)
        assert port.level == SafetyLevel.ESTOP  # a reset would have released the stop
        port.reset_faults(source="test", act_by_ns=time.monotonic_ns() + 1_000_000_000)
        assert port.level == SafetyLevel.DISABLED
        with pytest.raises(SafetyRequestExpired):
            port.rearm(source="test", act_by_ns=gone)
        assert port.level == SafetyLevel.DISABLED
        port.rearm(source="test", act_by_ns=None)
        assert port.level == SafetyLevel.RUN
        fault = port.record_fault("test:door", "open", "refused by a test")
        assert port.faults[-1] is fault and loop.report()["faults"][-1]["source"] == "test:door"


@pytest.mark.asyncio
async def test_the_terminal_status_shows_the_run_through_the_port():
    """The panel's figures from the tick ring and the event feed, as its process gets them."""
    loop = virtual_loop(arm_raw())
    async with loop:
        ring = make_ring(loop.port, 64)
        reader = TickReader("test_arm", pid=os.getpid())
        status = StatusFigures("test_arm")
        publish = ring.publisher(loop.port)
        loop.port.at_tick_end(publish)
        await loop.run(ticks=30)
        loop.port.stop_calling(publish)
        del publish
        status.add_rows(reader.meta(reader.read(64)))
        for event in EventFeed(loop.port, 10.0).collect(health=True):
            status.message(event)
        figures = status.figures()
        reader.close()
        ring.close()
    assert figures["robot"] == "test_arm" and figures["ticks"] == 30 and figures["missed_ticks"] == 0
    assert figures["safety_level"] == "run" and figures["fault_count"] == 0
    assert figures["drivers"]["arm"]["status"] == "open" and figures["controller"]["type"] == "hold"
    assert render(figures) is not None


class _Sink:
    """What an output process's socket would get, kept here."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def send_bytes(self, data: bytes) -> bool:
        self.sent.append(data)
        return True


@pytest.mark.asyncio
async def test_the_feed_samples_the_health_right_after_a_tick_or_a_period_without_one():
    """The health (hundreds of µs with many drives) is sampled when a tick has just ended, in
    that tick's idle time; between runs, where no tick comes, a period later anyway."""
    import asyncio
    import pickle

    loop = virtual_loop(arm_raw())
    async with loop:
        port = loop.port
        hooks: list = []
        real_at_tick_end = port.at_tick_end
        port.at_tick_end = lambda fn: (hooks.append(fn), real_at_tick_end(fn))  # type: ignore[method-assign]
        feed = EventFeed(port, 0.5)  # a sample every 2 s: far longer than this test's steps
        sink = _Sink()
        feed.sinks.append(sink)
        feed.start()
        try:
            for _ in range(int(NOT_HUNG_S / 0.01)):  # the period passes; then the feed waits for a tick's end
                if hooks:
                    break
                await asyncio.sleep(0.01)
            assert hooks and sink.sent == []  # not sampled before a tick ended
            await loop.run(ticks=1)  # a tick: its end wakes the feed, which samples at once
            for _ in range(10):
                await asyncio.sleep(0)
            topics = [pickle.loads(data)[1] for data in sink.sent]
            assert "/diagnostics" in topics and hooks[0] not in loop._publishers  # the hook taken out
            sink.sent.clear()
            feed.period_s = 0.1
            for _ in range(int(NOT_HUNG_S / 0.01)):  # no tick now: a period after the wait began
                if sink.sent:
                    break
                await asyncio.sleep(0.01)
            assert "/diagnostics" in [pickle.loads(data)[1] for data in sink.sent]
        finally:
            feed.stop()
