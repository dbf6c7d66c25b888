"""What the output processes need that is not in the tick ring, sampled on the event loop
between ticks: the drivers' health and the controller's metrics (drivers are not thread-safe),
the missed ticks, new faults and safety changes. One feed per loop, however many outputs read
it: each event is sampled and pickled once and sent to every output's process as
``("event", topic, stamp_ns, body)``, never waited for (:mod:`.output_process`)."""

from __future__ import annotations

import asyncio
import pickle

from .output_process import OutputProcess
from .port import LoopPort


class EventFeed:
    """Sends to ``sinks`` every ``1/hz`` s while it runs, and on :meth:`flush`."""

    def __init__(self, port: LoopPort, hz: float) -> None:
        self.port = port
        self.period_s = 1.0 / hz
        self.sinks: list[OutputProcess] = []
        self._faults_seen = 0
        self._transitions_seen = 0
        self._task: asyncio.Task | None = None

    def start(self) -> None:
        """Run on the running event loop (none: only :meth:`flush` sends)."""
        if self._task is not None:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        self._task = loop.create_task(self._run())

    def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            self._task = None

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(self.period_s)
            await self._next_tick_end()
            self.flush(health=True)

    async def _next_tick_end(self) -> None:
        """Until a tick has just ended (at most a period: between runs no tick comes). The
        drivers' health takes hundreds of µs with many drives (15 EtherCAT drives: 0.2 ms);
        sampled right after a tick it uses that tick's idle time, where at a random moment it
        would often make the next tick late (at 2 kHz, one deadline missed in a hundred)."""
        loop = asyncio.get_running_loop()
        ended = loop.create_future()

        def done(*_: object) -> None:
            if not ended.done():
                ended.set_result(None)

        self.port.at_tick_end(done)
        timer = loop.call_later(self.period_s, done)
        try:
            await ended
        finally:
            timer.cancel()
            self.port.stop_calling(done)

    def flush(self, *, health: bool = True) -> None:
        """Send what happened since the last call (and the health now) to every sink."""
        if not self.sinks:
            return
        for event in self.collect(health=health):
            data = pickle.dumps(event, protocol=pickle.HIGHEST_PROTOCOL)
            for sink in self.sinks:
                sink.send_bytes(data)

    def collect(self, *, health: bool) -> list[tuple]:
        port = self.port
        now = port.robot.clock.now_ns
        events: list[tuple] = []
        faults = port.faults
        while self._faults_seen < len(faults):
            events.append(("event", "/faults", now, faults[self._faults_seen]))
            self._faults_seen += 1
        transitions = port.transitions
        while self._transitions_seen < len(transitions):
            events.append(("event", "/safety/events", now, transitions[self._transitions_seen]))
            self._transitions_seen += 1
        if health:
            events.append(("event", "/diagnostics", now, port.health()))
            events.append(("event", "/loop", now, {"missed_ticks": port.missed_ticks, "ticks": port.timing.count}))
        return events


def join_feed(port: LoopPort, hz: float, sink: OutputProcess) -> EventFeed:
    """The loop's feed (made and started by its first sink, at ``hz``), with ``sink`` in it;
    the newcomer first gets every fault and safety change since the loop was made."""
    feed = port.event_feed
    if feed is None:
        feed = port.event_feed = EventFeed(port, hz)
        feed.start()
    feed.flush(health=False)  # those already in get what happened until now
    for event in EventFeed(port, hz).collect(health=False):
        sink.send(event)
    feed._faults_seen, feed._transitions_seen = len(port.faults), len(port.transitions)
    feed.sinks.append(sink)
    return feed


def leave_feed(feed: EventFeed, sink: OutputProcess) -> None:
    """Send ``sink`` what happened until now, then take it out; the last one stops the feed."""
    if sink in feed.sinks:
        feed.flush(health=True)
        feed.sinks.remove(sink)
    if not feed.sinks:
        feed.stop()
        if feed.port.event_feed is feed:
            feed.port.event_feed = None
