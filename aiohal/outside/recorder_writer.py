"""The recorder's writer, in an output process of its own: tick ring rows into MCAP (and live).

It reads the tick ring (:mod:`.tick_ring`) at its own pace, encodes batches of ticks
(fixed-layout CDR, one numpy fill per field, :mod:`aiohal.ros2.fixed`), writes the MCAP
records, compresses and flushes, and hands the same messages to a Foxglove server it runs
(``live_port``), every ``live_decimate``-th tick. Health, faults and safety changes come from
the loop as messages (:mod:`.output_process`). A writer that falls a whole ring behind loses
the oldest rows and counts them (``dropped_ticks``); the tick never knows.

The file is usable at any time up to its last written chunk: the writer closes the chunk in
progress and flushes the file every ``flush_ms`` (docs/recording.md).
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import ros2
from ..core.tick_timing import PHASES
from ..record.options import RecordSection
from ..ros2.fixed import FixedLayout, with_values
from ..safety import SafetyLevel
from . import recorder_topics as T
from . import tick_ring as R
from .recorder_file import RecordingFile

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


def topics_for(robot: Any, ring: R.TickReader) -> list[T.TickTopic]:
    """The robot's per-tick topics, their arrays found in ``ring`` (checked against its layout)."""
    arrays = R.ring_arrays(robot)
    names = [n for n, _ in arrays]
    if names != ring.names:
        raise ValueError(f"the tick ring holds {ring.names}, the robot has {names}")
    index = {(a.ctypes.data, a.nbytes): i for i, (_, a) in enumerate(arrays)}
    return T.tick_topics(robot, lambda a: index[(a.ctypes.data, a.nbytes)], lambda: ring)


class RecorderWriter:
    """The writer of one recording (a file, a live server, or both) from the tick ring.

    ``spec`` (from :class:`~aiohal.outside.recorder.Recorder`): ``robot`` (a copy of the loop's
    :class:`~aiohal.robot.Robot`, for names and shapes), ``path``, ``options``
    (:class:`~aiohal.record.RecordSection`), ``live_port``, ``plain``, ``period_ns``, ``clock``,
    ``config_text``, ``offset_ns`` (the loop's clock to Unix time), ``start`` and ``line`` (the
    ring position and the reader line the loop gave this writer).
    """

    #: ticks encoded at once
    BATCH = 64
    #: the process's wait for a message when it has caught up (a couple of ticks accumulate)
    IDLE_S = 0.002

    def __init__(self, spec: dict[str, Any]) -> None:
        robot = spec["robot"]
        self.options: RecordSection = spec["options"] or RecordSection()
        self.path = None if spec["path"] is None else Path(spec["path"])
        self.plain = bool(spec.get("plain", False))
        self._offset_ns = int(spec["offset_ns"])
        self.ring = R.TickReader(robot.name, pid=spec["pid"], start=spec["start"], line=spec["line"])
        self.live = None
        try:
            self.channels = [self._channel(topic) for topic in topics_for(robot, self.ring)]
            if spec.get("live_port") is not None:
                from .foxglove_server import FoxgloveServer

                self.live = FoxgloveServer(spec["live_port"])
        except BaseException:
            self.ring.close()
            raise
        self._file = None if self.path is None else RecordingFile(self.path, self.options.compression)
        self._register()
        self._events: collections.deque[tuple[str, int, Any]] = collections.deque()
        self.messages = 0
        self.ticks_written = 0
        self.live_messages = 0
        self.error: str | None = None
        self._last_flush = time.monotonic_ns()
        self._start_file(robot, spec)
        self._work_steps = self._work()

    def info(self) -> dict[str, Any]:
        return {"live_port": None if self.live is None else self.live.port}

    # ------------------------------------------------------------ channels

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

    def _start_file(self, robot: Any, spec: dict[str, Any]) -> None:
        """The run's metadata and the robot's description (latched)."""
        rate_hz = 1e9 / spec["period_ns"]
        decimate = {k: self.options.decimate.get(k, 1) for k in sorted({c.topic.key for c in self.channels})}
        if self._file is not None:
            import json

            info = {"robot": robot.name, "rate_hz": rate_hz, "clock": spec["clock"], "decimate": decimate}
            self._file.add_metadata("aiohal", {k: json.dumps(v) for k, v in info.items()})
        description = T.robot_message(robot, rate_hz, spec["clock"], spec["config_text"])
        data = ros2.serialize(description)
        t = int(spec["now_ns"]) + self._offset_ns
        cid, lch = self._event_channels["/robot"]
        if self._file is not None:
            self._file.add_message(cid, t, data)
        if self.live is not None and lch is not None:
            self.live.latch(lch, data, t)
        self.messages += 1

    # ------------------------------------------------------------ the process's calls

    def step(self) -> bool:
        """Some work; True when nothing was left to do."""
        if self.error is not None:
            return True
        try:
            return next(self._work_steps)
        except Exception as exc:  # a full disk, a closed server: the recording stops, the run goes on
            self.error = f"{type(exc).__name__}: {exc}"
            log.error("recording stopped: %s", self.error)
            return True

    def message(self, message: tuple) -> None:
        """An event from the loop: ``("event", topic, stamp_ns, body)``."""
        if message[0] == "event" and message[1] in T.EVENT_TOPICS:
            _, topic, stamp, body = message
            self._events.append((topic, stamp, body))

    def finish(self, final: dict[str, Any] | None) -> dict[str, Any]:
        """Drain the ring up to the loop's last tick, write the last events and timing, close
        the file; the summary. ``final`` None: the loop is gone, keep what is there."""
        if final is not None:
            for event in final.get("events", []):
                self.message(event)
        if self.error is None:
            try:
                for _ in range(1 << 20):
                    if self.ring.tail >= self.ring.head:
                        break
                    next(self._work_steps)
                self._write_events()
                if final is not None and final.get("last_timing") is not None:
                    self._last_timing(final["last_timing"])
            except Exception as exc:
                self.error = f"{type(exc).__name__}: {exc}"
                log.error("recording stopped: %s", self.error)
        if self._file is not None:
            try:
                self._file.finish(complete=self.error is None and final is not None)
            except Exception as exc:
                self.error = f"{type(exc).__name__}: {exc}"
                log.error("recording not finished: %s", self.error)
        if self.live is not None:
            self.live.close()
        summary = self.summary()
        self.ring.close()
        return summary

    def summary(self) -> dict[str, Any]:
        return {
            "path": None if self.path is None else str(self.path),
            "ticks": self.ticks_written,
            "dropped_ticks": self.ring.lost,
            "messages": self.messages,
            "live_messages": self.live_messages,
            "bytes": self._file.size if self._file is not None else 0,
            **({"error": self.error} if self.error else {}),
        }

    # ------------------------------------------------------------ encoding

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
        """The writer's work a batch at a time; yields True when it has nothing left to do."""
        ring = self.ring
        options = self.options
        flush_ns = int(options.flush_ms * 1e6)
        decimate = [options.decimate.get(ch.topic.key, 1) for ch in self.channels]
        live_every = options.live_decimate
        file, live = self._file, self.live
        offset = self._offset_ns
        while True:
            data = ring.read(self.BATCH)
            if not len(data):
                self._write_events()
                if file is not None and time.monotonic_ns() - self._last_flush >= flush_ns:
                    self._flush()
                yield True
                continue
            self.ticks_written += len(data)
            meta = ring.meta(data)
            if file is None:  # live only: encode only the ticks that go out
                sent = (meta[:, R.TICK] % live_every == 0) | (meta[:, R.PREV_TICK] % live_every == 0)
                data, meta = data[sent], meta[sent]
            ticks = meta[:, R.TICK]
            valid = meta[:, R.TIMING_VALID] != 0
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
                self.messages += count
            if file is not None and time.monotonic_ns() - self._last_flush >= flush_ns:
                self._flush()
            yield False

    def _flush(self) -> None:
        if self._file is not None:
            self._file.flush()
        self._last_flush = time.monotonic_ns()

    def _write_events(self) -> None:
        """Faults, safety events and diagnostics the loop sent since the last call."""
        while self._events:
            topic, stamp, body = self._events.popleft()
            t = stamp + self._offset_ns
            if topic == "/diagnostics":
                body = T.diagnostics_message(t, body)
            elif topic == "/faults":
                body = T.faults_message(t, [body])
            elif topic == "/safety/events":
                body = T.safety_event_message(t, body, LEVEL_NUMBERS)
            data = ros2.serialize(body)
            cid, live_channel = self._event_channels[topic]
            if self._file is not None:
                self._file.add_message(cid, t, data)
            if live_channel is not None and self.live is not None:
                self.live.log(live_channel, data, t)
            self.messages += 1

    def _last_timing(self, last: dict[str, Any]) -> None:
        """The run's last tick: its timing was stored after its publisher ran (the loop sends it)."""
        tick = int(last["tick"])
        if tick % self.options.decimate.get("timing", 1):
            return
        ch = next(c for c in self.channels if c.topic.timing)
        values = {
            "lateness_ns": np.array([last["lateness_ns"]]),
            "work_ns": np.array([last["work_ns"]]),
            "tick": np.array([tick]),
        }
        for p, v in zip(PHASES, last["phases_ns"], strict=True):
            values[f"{p}_ns"] = np.array([v])
        t = int(last["now_ns"]) + self._offset_ns
        values[T.STAMP[0]], values[T.STAMP[1]] = np.divmod(np.array([t]), 1_000_000_000)
        msg = next(self._encode(ch, values, 1))
        if self._file is not None:
            self._file.add_message(ch.channel_id, t, msg, tick)
        self.messages += 1
