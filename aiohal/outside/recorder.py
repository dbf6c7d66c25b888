"""The recorder: every tick into an MCAP file, written by a thread in the tick's idle time.

On the tick: one compiled copy of the robot's arrays into a ring slot (:mod:`.ring`). In the
writer thread: encoding (fixed-layout CDR, one numpy fill per field for a batch of ticks,
:mod:`.cdr`), the MCAP records, compression and the file. The thread shares the GIL with the
tick, so it works in slices placed between the end of one tick's work and the next deadline,
and sleeps through the ticks: a slice that held the GIL when the timer fired would make the
tick late. Drivers' health and the controller's metrics are sampled on the event loop (not in
the tick, and not from the thread: drivers are not thread-safe) at ``health_hz``.

The file is usable at any time up to its last written chunk: the writer closes the chunk in
progress and flushes the file every ``flush_ms`` (docs/recording.md).
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import ros2
from ..core.tick_timing import PHASES
from ..record.options import RecordSection
from ..ros2.fixed import FixedLayout, with_values
from ..safety import SafetyLevel
from . import recorder_ring as R
from . import recorder_topics as T
from .port import LoopPort, TickEnd
from .recorder_file import RecordingFile

if TYPE_CHECKING:
    from .foxglove_server import FoxgloveServer

log = logging.getLogger(__name__)

LEVEL_NUMBERS = {level.name.lower(): int(level) for level in SafetyLevel}


@dataclass
class TickChannel:
    """A per-tick topic as written: its layout (the fast path) and where it goes."""

    topic: T.TickTopic
    layout: FixedLayout
    channel_id: int = 0
    live: Any = None  # the live server's channel
    extra: list[str] = field(default_factory=list)  # the paths the writer fills besides the topic's fields


class Recorder:
    """Records a loop, through its :class:`~aiohal.outside.port.LoopPort`, to an MCAP file or a
    rosbag2 directory (a path not ending in ``.mcap``; :mod:`.recorder_file`).

    ``attach()`` (before ``run``) adds the tick's publisher and starts the writer; ``close()``
    (after the run) drains the ring, writes the summary and closes the file. ``live`` is an
    optional :class:`~aiohal.outside.foxglove_server.FoxgloveServer` that gets the same messages,
    decimated. ``plain``: serialize every message with rosbags, one at a time (the reference
    for the batch path, which writes the same bytes; ``python -m benchmarks.record --plain``).
    """

    #: ticks encoded at once by the writer
    BATCH = 64
    #: messages added between two looks at the clock
    STRIDE = 4
    #: the writer's sleep when it has caught up (a couple of ticks accumulate meanwhile)
    IDLE_S = 0.002

    def __init__(
        self,
        port: LoopPort,
        path: str | Path | None,
        options: RecordSection | None = None,
        *,
        live: FoxgloveServer | None = None,
        plain: bool = False,
    ) -> None:
        self.port = port
        self.options = options or RecordSection()
        self.path = None if path is None else Path(path)
        self.live = live
        self.plain = plain
        robot, stats = port.robot, port.timing
        self._arrays: list[np.ndarray] = []
        topics = T.tick_topics(robot, self._add_array, lambda: self.ring)
        self.ring = R.TickRing(
            self._arrays, self.options.buffer_ticks, [stats.lateness, stats.work, *stats.phases], stats.mask
        )
        from ..core import compiled_entry

        self._kernel = compiled_entry.compiled_for(
            R.record_tick, (self.ring.data, self.ring.sources, self.ring.state, 0, 0, 0, 0)
        )
        self.channels = [self._channel(topic) for topic in topics]
        self._file = None if self.path is None else RecordingFile(self.path, self.options.compression)
        self._register()
        self._events: collections.deque[tuple[str, int, Any]] = collections.deque()
        self._faults_seen = 0
        self._transitions_seen = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._health_task: asyncio.Task | None = None
        self._offset_ns = time.time_ns() - port.now_ns()  # tick clock -> Unix time
        self.messages = 0
        self.ticks_written = 0
        self.live_messages = 0
        self.error: str | None = None
        self._attached = False
        self._closed = False
        self._publisher: TickEnd | None = None
        self._busy_ns = port.period_ns // 2  # the ticks' recent lateness + work: the writer waits them out
        self._last_flush = time.monotonic_ns()

    # ------------------------------------------------------------ channels

    def _add_array(self, array: np.ndarray) -> int:
        self._arrays.append(array)
        return len(self._arrays) - 1

    def _channel(self, topic: T.TickTopic) -> TickChannel:
        """The topic's layout: the stamp, its tick (where the type has one) and its fields."""
        empty = self.ring.data[:0]
        extra = [*T.STAMP, *(["tick"] if hasattr(topic.sample, "tick") else [])]
        paths = extra + list(topic.fields(self.ring.meta(empty), empty))
        return TickChannel(topic, FixedLayout(topic.sample, paths), extra=extra)

    def _register(self) -> None:
        file, live = self._file, self.live
        for ch in self.channels:
            if file is not None:
                ch.channel_id = file.add_channel(ch.topic.topic, ch.topic.msgtype)
            if live is not None:
                ch.live = self._live_channel(ch.topic.topic, ch.topic.msgtype)
        self._event_channels: dict[str, tuple[int, Any]] = {}
        for topic, msgtype in T.EVENT_TOPICS.items():
            latched = topic in T.LATCHED
            cid = file.add_channel(topic, msgtype, latched) if file is not None else 0
            lch = self._live_channel(topic, msgtype) if live is not None else None
            self._event_channels[topic] = (cid, lch)

    def _live_channel(self, topic: str, msgtype: str) -> Any:
        assert self.live is not None
        return self.live.channel(topic, msgtype, "ros2msg", ros2.schema_text(msgtype).encode(), "cdr")

    # ------------------------------------------------------------ lifecycle

    def attach(self) -> None:
        """Start recording: the robot's description (latched), tick 0 (the state the activation
        read, when called between ``activate()`` and ``run()``), the writer thread, the health
        sampler (if an event loop runs) and the tick's publisher."""
        if self._attached:
            return
        port = self.port
        robot = port.robot
        self._attached = True
        rate_hz = 1e9 / port.period_ns
        decimate = {k: self.options.decimate.get(k, 1) for k in sorted({c.topic.key for c in self.channels})}
        if self._file is not None:
            info = {"robot": robot.name, "rate_hz": rate_hz, "clock": port.clock_kind, "decimate": decimate}
            self._file.add_metadata("aiohal", {k: json.dumps(v) for k, v in info.items()})
        description = T.robot_message(robot, rate_hz, port.clock_kind, _config_text(port))
        data = ros2.serialize(description)
        t = port.now_ns() + self._offset_ns
        cid, lch = self._event_channels["/robot"]
        if self._file is not None:
            self._file.add_message(cid, t, data)
        if self.live is not None and lch is not None:
            self.live.latch(lch, data, t)
        self.messages += 1
        self._thread = threading.Thread(target=self._write_loop, name="aiohal-recorder", daemon=True)
        self._thread.start()
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            loop = None
        if loop is not None:
            self._health_task = loop.create_task(self._sample_health())
        self._publisher = self.publisher()
        if not port.running and port.tick == 0:
            self._publisher(None)  # tick 0: the state read at activation, where the controller started
        port.at_tick_end(self._publisher)

    def publisher(self) -> TickEnd:
        """The tick's part: one kernel call into the next free slot, or a drop counted."""
        kernel, stats, port = self._kernel, self.port.timing, self.port
        clock = port.robot.clock
        data, sources, state = self.ring.data, self.ring.sources, self.ring.state

        def record_tick(_: object) -> None:
            kernel(data, sources, state, stats.count, clock.tick, clock.now_ns, port.level)

        return record_tick

    async def _sample_health(self) -> None:
        period = 1.0 / self.options.health_hz
        while True:
            await asyncio.sleep(period)
            self._health_event()

    def close(self) -> dict[str, Any]:
        """Drain what the tick left, write the last events and the summary; returns the figures."""
        if self._closed:
            return self.summary()
        self._closed = True
        if self._health_task is not None:
            self._health_task.cancel()
        if self._publisher is not None:
            self.port.stop_calling(self._publisher)
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.error is None:
            self._health_event()
            self._last_timing()
            self._write_events()
        if self._file is not None:
            try:
                self._file.finish(complete=self.error is None)
            except Exception as exc:
                self.error = f"{type(exc).__name__}: {exc}"
                log.error("recording not finished: %s", self.error)
        return self.summary()

    def _health_event(self) -> None:
        health = self.port.health()
        self._events.append(("/diagnostics", self.port.robot.clock.now_ns, health))

    def summary(self) -> dict[str, Any]:
        return {
            "path": None if self.path is None else str(self.path),
            "ticks": self.ticks_written,
            "dropped_ticks": self.ring.dropped,
            "messages": self.messages,
            "live_messages": self.live_messages,
            "bytes": self._file.size if self._file is not None else 0,
            **({"error": self.error} if self.error else {}),
        }

    # ------------------------------------------------------------ the writer thread

    def _write_loop(self) -> None:
        priority = self.port.config.realtime.priority
        if priority is not None:
            # just below the tick: a writer preempted by another process while it holds the GIL
            # would keep the tick waiting for as long as it is off the CPU
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(1, priority - 1)))
            except OSError as exc:
                log.warning("recorder thread: SCHED_FIFO %d not set: %s", max(1, priority - 1), exc)
        work = self._work()
        try:
            while True:
                stopping = self._stop.is_set()  # read before draining: no tick runs after it is set
                end = self._window(stopping)
                while True:
                    if next(work):  # nothing left
                        if stopping:
                            return
                        time.sleep(self.IDLE_S)
                        break
                    if time.monotonic_ns() >= end:
                        break
        except Exception as exc:  # a full disk, a closed server: the run goes on, the recording stops
            self.error = f"{type(exc).__name__}: {exc}"
            log.error("recording stopped: %s", self.error)
            self.ring.state[R.MASK] = -1  # the tick now drops every copy (and counts it)

    def _window(self, stopping: bool) -> int:
        """Sleep until the tick's idle time; return when the slice must end (monotonic ns).

        The idle time of a period runs from the ticks' recent lateness + work past a deadline to
        a margin before the next deadline. A virtual clock has no idle time: short slices."""
        port = self.port
        period = port.period_ns
        now = time.monotonic_ns()
        if stopping or not port.running or port.clock_kind == "virtual":
            return now + 200_000
        margin = max(200_000, period // 5)
        start = min(self._busy_ns, period - 2 * margin)
        phase = (now - port.deadlines_origin_ns) % period
        if not start <= phase < period - margin:
            time.sleep(((start - phase) % period) / 1e9)
            now = time.monotonic_ns()
            phase = (now - port.deadlines_origin_ns) % period
        return now + max(0, period - margin - phase)

    def _encode(self, ch: TickChannel, values: dict[str, np.ndarray], count: int) -> Iterator[bytes]:
        """The batch's messages: one numpy fill per field, or (``plain``) rosbags per message."""
        if self.plain:
            sample = ch.topic.sample
            for i in range(count):
                yield ros2.serialize(with_values(sample, {p: v[i] for p, v in values.items()}))
            return
        blob = ch.layout.encode(values, count).tobytes()
        size = ch.layout.size
        for i in range(count):
            yield blob[i * size : (i + 1) * size]

    def _values(self, ch: TickChannel, meta: np.ndarray, data: np.ndarray, ticks: np.ndarray, times: np.ndarray):
        values = ch.topic.fields(meta, data)
        values[T.STAMP[0]], values[T.STAMP[1]] = np.divmod(times, 1_000_000_000)
        if "tick" in ch.extra:
            values["tick"] = ticks
        return values

    def _work(self) -> Iterator[bool]:
        """The writer's work in small steps; yields True when it has nothing left to do."""
        ring = self.ring
        options = self.options
        flush_ns = int(options.flush_ms * 1e6)
        decimate = [options.decimate.get(ch.topic.key, 1) for ch in self.channels]
        live_every = options.live_decimate
        file, live = self._file, self.live
        offset = self._offset_ns
        while True:
            head = ring.head
            if head == ring.tail:
                self._write_events()
                if file is not None and time.monotonic_ns() - self._last_flush >= flush_ns:
                    self._flush()
                yield True
                continue
            a = ring.tail & ring.mask
            n = min(head - ring.tail, self.BATCH, ring.slots - a)
            data = ring.data[a : a + n]
            meta = ring.meta(data)
            ticks = meta[:, R.TICK]
            recent = meta[:, R.TIMING] + meta[:, R.TIMING + 1]
            valid = meta[:, R.TIMING_VALID] != 0
            if valid.any():
                self._busy_ns = int(np.percentile(recent[valid], 90)) + 50_000
            yield False
            for ch, every in zip(self.channels, decimate, strict=True):
                if ch.topic.timing:
                    keep = valid & (meta[:, R.PREV_TICK] % every == 0)
                    chan_ticks, stamps = meta[keep, R.PREV_TICK], meta[keep, R.PREV_NOW]
                else:
                    keep = ticks % every == 0 if every > 1 else slice(None)
                    chan_ticks, stamps = ticks[keep], meta[keep, R.NOW]
                count = len(chan_ticks)
                if not count:
                    continue
                times = stamps + offset
                values = self._values(ch, meta[keep], data[keep], chan_ticks, times)
                time_list, tick_list = times.tolist(), chan_ticks.tolist()
                for i, msg in enumerate(self._encode(ch, values, count)):
                    if file is not None:
                        file.add_message(ch.channel_id, time_list[i], msg, tick_list[i])
                    if live is not None and ch.live is not None and tick_list[i] % live_every == 0:
                        live.log(ch.live, msg, time_list[i])
                        self.live_messages += 1
                    if i % self.STRIDE == self.STRIDE - 1:
                        yield False
                self.messages += count
                yield False
            ring.tail += n
            self.ticks_written += n
            if file is not None and time.monotonic_ns() - self._last_flush >= flush_ns:
                self._flush()
                yield False

    def _flush(self) -> None:
        if self._file is not None:
            self._file.flush()
        self._last_flush = time.monotonic_ns()

    def _write_events(self) -> None:
        """Faults, safety events and diagnostics that happened since the last call."""
        port = self.port
        now = port.robot.clock.now_ns
        faults = port.faults
        while self._faults_seen < len(faults):
            self._events.append(("/faults", now, T.faults_message(now + self._offset_ns, [faults[self._faults_seen]])))
            self._faults_seen += 1
        transitions = port.transitions
        while self._transitions_seen < len(transitions):
            change = transitions[self._transitions_seen]
            self._events.append(
                ("/safety/events", now, T.safety_event_message(now + self._offset_ns, change, LEVEL_NUMBERS))
            )
            self._transitions_seen += 1
        while self._events:
            topic, stamp, body = self._events.popleft()
            t = stamp + self._offset_ns
            if topic == "/diagnostics":
                body = T.diagnostics_message(t, body)
            data = ros2.serialize(body)
            cid, live_channel = self._event_channels[topic]
            if self._file is not None:
                self._file.add_message(cid, t, data)
            if live_channel is not None and self.live is not None:
                self.live.log(live_channel, data, t)
            self.messages += 1

    def _last_timing(self) -> None:
        """The run's last tick: its timing was stored after its publisher ran."""
        ring, stats = self.ring, self.port.timing
        count = stats.count
        if count == 0 or ring.state[R.LAST_COUNT] != count - 1:
            return
        j = (count - 1) & stats.mask
        ch = next(c for c in self.channels if c.topic.timing)
        tick = int(ring.state[R.LAST_TICK])
        if tick % self.options.decimate.get("timing", 1):
            return
        values = {"lateness_ns": stats.lateness[j : j + 1], "work_ns": stats.work[j : j + 1], "tick": np.array([tick])}
        for i, p in enumerate(PHASES):
            values[f"{p}_ns"] = stats.phases[i, j : j + 1]
        t = int(ring.state[R.LAST_NOW]) + self._offset_ns
        values[T.STAMP[0]], values[T.STAMP[1]] = np.divmod(np.array([t]), 1_000_000_000)
        msg = next(self._encode(ch, values, 1))
        if self._file is not None:
            self._file.add_message(ch.channel_id, t, msg, tick)
        self.messages += 1


def _config_text(port: LoopPort) -> str:
    """The configuration file's text, for ``/robot``'s description ("" for a config built in code)."""
    path = port.config.path
    if path is None:
        return ""
    from ..files import FileRefused, read_regular_text

    try:
        return read_regular_text(Path(path), limit=1 << 20)
    except (FileRefused, OSError) as exc:
        log.warning("recording: the config's text is not in /robot: %s", exc)
        return ""
