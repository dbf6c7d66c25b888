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
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.tick_timing import PHASES
from ..record.cdr import Layout
from ..record.options import Channel, RecordSection
from . import recorder_ring as R
from .port import LoopPort, TickEnd

if TYPE_CHECKING:
    from .foxglove_server import FoxgloveServer

log = logging.getLogger(__name__)

SCHEMA_PACKAGE = "aiohal/msg/"
#: JSON channels: events and slow samples, encoding "json" with a JSON Schema
FAULT_SCHEMA = {
    "type": "object",
    "properties": {
        "tick": {"type": "integer"},
        "source": {"type": "string"},
        "phase": {"type": "string"},
        "error": {"type": "string"},
        "condition": {"type": "boolean"},
    },
}
HEALTH_SCHEMA = {
    "type": "object",
    "properties": {
        "tick": {"type": "integer"},
        "safety_level": {"type": "string"},
        "drivers": {"type": "object"},
        "controller": {"type": "object"},
    },
}
ROBOT_SCHEMA = {
    "type": "object",
    "properties": {
        "robot": {"type": "string"},
        "rate_hz": {"type": "number"},
        "joint_names": {"type": "array", "items": {"type": "string"}},
        "devices": {"type": "object"},
        "clock": {"type": "string"},
    },
}


@dataclass
class TickChannel:
    """A per-tick channel: its topic, layout, decimation and how its fields come from ring rows."""

    topic: str
    key: Channel  # the [record] decimate key
    layout: Layout
    fields: Callable[[np.ndarray, np.ndarray], dict[str, np.ndarray]]  # (meta rows, data rows) -> values
    timing: bool = False  # its rows are the previous tick's (timing is complete one tick later)
    channel_id: int = 0
    live: Any = None  # the live server's channel


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


class Recorder:
    """Records a loop, through its :class:`~aiohal.outside.port.LoopPort`, to an MCAP file.

    ``attach()`` (before ``run``) adds the tick's publisher and starts the writer; ``close()``
    (after the run) drains the ring, writes the summary and closes the file. ``live`` is an
    optional :class:`~aiohal.outside.foxglove_server.FoxgloveServer` that gets the same messages, decimated.
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
    ) -> None:
        from mcap.writer import CompressionType, Writer  # the extra 'record'

        self.port = port
        self.options = options or RecordSection()
        self.path = None if path is None else Path(path)
        self.live = live
        robot, stats = port.robot, port.timing
        self._arrays: list[np.ndarray] = []
        self.channels: list[TickChannel] = []
        self._build_channels(robot)
        self.ring = R.TickRing(
            self._arrays, self.options.buffer_ticks, [stats.lateness, stats.work, *stats.phases], stats.mask
        )
        from ..core import compiled_entry

        self._kernel = compiled_entry.compiled_for(
            R.record_tick, (self.ring.data, self.ring.sources, self.ring.state, 0, 0, 0, 0)
        )
        self._file = None
        self._writer = None
        if self.path is not None:
            self._file = open(self.path, "wb")  # noqa: SIM115 - open for the recorder's life, closed in close()
            compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[
                self.options.compression
            ]
            # chunks are closed by time (flush_ms), not by size: the size bound is only a backstop
            self._writer = Writer(self._file, chunk_size=64 << 20, compression=compression)
            self._writer.start(profile="aiohal", library="aiohal")
        self._register()
        self._events: collections.deque[tuple[str, int, dict]] = collections.deque()
        self._faults_seen = 0
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

    def _build_channels(self, robot: Any) -> None:
        n = robot.dof
        ring = lambda: self.ring  # noqa: E731  (the ring is built after the channels name their arrays)
        state, command = robot.state, robot.command
        i_state, i_sfault = self._add_array(state.block), self._add_array(state.fault)
        i_cmd, i_mode = self._add_array(command.block), self._add_array(command.mode)
        tick_field = [("tick", np.int64, None)]

        state_layout = Layout(
            SCHEMA_PACKAGE + "JointState",
            tick_field
            + [
                (f, np.float64, n)
                for f in ("position", "velocity", "effort", "motor_position", "motor_velocity", "temperature")
            ]
            + [("fault", np.uint32, n)],
        )

        def state_fields(meta, data):
            block = ring().field(data, i_state)
            out = {
                f: block[:, r]
                for r, f in enumerate(
                    ("position", "velocity", "effort", "motor_position", "motor_velocity", "temperature")
                )
            }
            out["fault"] = ring().field(data, i_sfault)
            return out

        self.channels.append(TickChannel("/joint_state", "joint_state", state_layout, state_fields))

        command_layout = Layout(
            SCHEMA_PACKAGE + "JointCommand",
            tick_field
            + [(f, np.float64, n) for f in ("position", "velocity", "effort", "stiffness", "damping", "feedforward")]
            + [("mode", np.int8, n)],
        )

        def command_fields(meta, data):
            block = ring().field(data, i_cmd)
            out = {
                f: block[:, r]
                for r, f in enumerate(("position", "velocity", "effort", "stiffness", "damping", "feedforward"))
            }
            out["mode"] = ring().field(data, i_mode)
            return out

        self.channels.append(TickChannel("/joint_command", "joint_command", command_layout, command_fields))

        for kind, group in robot.device_groups.items():
            if not len(group):
                continue
            i_fault = self._add_array(group.fault)
            if group.values is not None:
                i_values = self._add_array(group.values)
                field_arrays = None
            else:
                i_values = None
                field_arrays = {f: self._add_array(getattr(group, f)) for f in group.fields}
            fields = []
            for f in group.fields:
                shape, dtype = group.shapes[f]
                fields.append((f, dtype, shape[0] if shape else None))
            layout = Layout(
                SCHEMA_PACKAGE + {"imu": "Imu", "force_torque": "ForceTorque", "hand": "Hand"}[kind],
                tick_field + fields + [("fault", np.uint32, None)],
            )
            for d, name in enumerate(group.names):

                def device_fields(
                    meta, data, d=d, group=group, i_fault=i_fault, i_values=i_values, field_arrays=field_arrays
                ):
                    if i_values is not None:
                        values = ring().field(data, i_values)[:, d]
                        out = {f: values[:, cols] for f, cols in group.columns.items()}
                    else:
                        out = {f: ring().field(data, i)[:, d] for f, i in field_arrays.items()}
                    out["fault"] = ring().field(data, i_fault)[:, d]
                    return out

                self.channels.append(TickChannel(f"/{kind}/{name}", kind, layout, device_fields))

        timing_layout = Layout(
            SCHEMA_PACKAGE + "TickTiming",
            tick_field
            + [("lateness_ns", np.int64, None), ("work_ns", np.int64, None)]
            + [(f"{p}_ns", np.int64, None) for p in PHASES],
        )

        def timing_fields(meta, data):
            out = {"lateness_ns": meta[:, R.TIMING], "work_ns": meta[:, R.TIMING + 1]}
            for i, p in enumerate(PHASES):
                out[f"{p}_ns"] = meta[:, R.TIMING + 2 + i]
            return out

        self.channels.append(TickChannel("/timing", "timing", timing_layout, timing_fields, timing=True))

        safety_layout = Layout(SCHEMA_PACKAGE + "Safety", [*tick_field, ("level", np.uint8, None)])
        self.channels.append(
            TickChannel("/safety", "safety", safety_layout, lambda meta, data: {"level": meta[:, R.LEVEL]})
        )

    def _register(self) -> None:
        writer, live = self._writer, self.live
        for ch in self.channels:
            if writer is not None:
                schema = writer.register_schema(ch.layout.name, "ros2msg", ch.layout.schema.encode())
                ch.channel_id = writer.register_channel(ch.topic, "cdr", schema)
            if live is not None:
                ch.live = live.channel(ch.topic, ch.layout.name, "ros2msg", ch.layout.schema.encode(), "cdr")
        self._json_channels: dict[str, tuple[int, Any]] = {}
        for topic, name, schema in (
            ("/faults", "aiohal.Fault", FAULT_SCHEMA),
            ("/health", "aiohal.Health", HEALTH_SCHEMA),
            ("/robot", "aiohal.Robot", ROBOT_SCHEMA),
        ):
            data = json.dumps(schema).encode()
            cid = 0
            if writer is not None:
                sid = writer.register_schema(name, "jsonschema", data)
                cid = writer.register_channel(topic, "json", sid)
            lch = live.channel(topic, name, "jsonschema", data, "json") if live is not None else None
            self._json_channels[topic] = (cid, lch)

    # ------------------------------------------------------------ lifecycle

    def attach(self) -> None:
        """Start recording: the writer thread, the health sampler (if an event loop runs) and the
        tick's publisher. Call before ``control.run()``."""
        if self._attached:
            return
        port = self.port
        robot = port.robot
        self._attached = True
        devices = {kind: list(group.names) for kind, group in robot.device_groups.items() if len(group)}
        info = {
            "robot": robot.name,
            "rate_hz": 1e9 / port.period_ns,
            "joint_names": list(robot.joint_names),
            "devices": devices,
            "clock": port.clock_kind,
            "decimate": {k: self.options.decimate.get(k, 1) for k in sorted({c.key for c in self.channels})},
        }
        if self._writer is not None:
            self._writer.add_metadata("aiohal", {k: json.dumps(v) for k, v in info.items()})
        self._events.append(("/robot", port.now_ns(), info))
        self._thread = threading.Thread(target=self._write_loop, name="aiohal-recorder", daemon=True)
        self._thread.start()
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            loop = None
        if loop is not None:
            self._health_task = loop.create_task(self._sample_health())
        self._publisher = self.publisher()
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
            self._events.append(("/health", self.port.robot.clock.now_ns, self.port.health().as_dict()))

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
        if self._writer is not None:
            try:
                if self.error is None:
                    self._writer.finish()
            except Exception as exc:
                self.error = f"{type(exc).__name__}: {exc}"
                log.error("recording not finished: %s", self.error)
            finally:
                if self._file is not None:  # opened with the writer
                    self._file.close()
        return self.summary()

    def _health_event(self) -> None:
        self._events.append(("/health", self.port.robot.clock.now_ns, self.port.health().as_dict()))

    def summary(self) -> dict[str, Any]:
        return {
            "path": None if self.path is None else str(self.path),
            "ticks": self.ticks_written,
            "dropped_ticks": self.ring.dropped,
            "messages": self.messages,
            "live_messages": self.live_messages,
            "bytes": self.path.stat().st_size if self.path is not None and self.path.exists() else 0,
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

    def _work(self) -> Iterator[bool]:
        """The writer's work in small steps; yields True when it has nothing left to do."""
        ring = self.ring
        options = self.options
        flush_ns = int(options.flush_ms * 1e6)
        decimate = [options.decimate.get(ch.key, 1) for ch in self.channels]
        live_every = options.live_decimate
        writer, live = self._writer, self.live
        offset = self._offset_ns
        while True:
            head = ring.head
            if head == ring.tail:
                self._write_events()
                if writer is not None and time.monotonic_ns() - self._last_flush >= flush_ns:
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
                if ch.timing:
                    keep = valid & (meta[:, R.PREV_TICK] % every == 0)
                    chan_ticks, stamps = meta[keep, R.PREV_TICK], meta[keep, R.PREV_NOW]
                else:
                    keep = ticks % every == 0 if every > 1 else slice(None)
                    chan_ticks, stamps = ticks[keep], meta[keep, R.NOW]
                count = len(chan_ticks)
                if not count:
                    continue
                values = ch.fields(meta[keep], data[keep])
                values["tick"] = chan_ticks
                blob = ch.layout.encode(values, count).tobytes()
                size = ch.layout.size
                times = (stamps + offset).tolist()
                tick_list = chan_ticks.tolist()
                for i in range(count):
                    msg = blob[i * size : (i + 1) * size]
                    if writer is not None:
                        writer.add_message(ch.channel_id, times[i], msg, times[i], tick_list[i] & 0xFFFFFFFF)
                    if live is not None and ch.live is not None and tick_list[i] % live_every == 0:
                        live.log(ch.live, msg, times[i])
                        self.live_messages += 1
                    if i % self.STRIDE == self.STRIDE - 1:
                        yield False
                self.messages += count
                yield False
            ring.tail += n
            self.ticks_written += n
            if writer is not None and time.monotonic_ns() - self._last_flush >= flush_ns:
                self._flush()
                yield False

    def _flush(self) -> None:
        writer, file = self._writer, self._file
        if writer is None or file is None:  # not recording to a file
            return
        writer.flush()  # closes the chunk in progress and writes it
        file.flush()
        self._last_flush = time.monotonic_ns()

    def _write_events(self) -> None:
        faults = self.port.faults
        while self._faults_seen < len(faults):
            f = faults[self._faults_seen]
            self._faults_seen += 1
            self._events.append(("/faults", self.port.robot.clock.now_ns, f.as_dict()))
        while self._events:
            topic, stamp, body = self._events.popleft()
            data = json.dumps(_jsonable(body)).encode()
            cid, live_channel = self._json_channels[topic]
            t = stamp + self._offset_ns
            if self._writer is not None:
                self._writer.add_message(cid, t, data, t, 0)
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
        ch = next(c for c in self.channels if c.timing)
        values = {
            "tick": np.array([ring.state[R.LAST_TICK]]),
            "lateness_ns": stats.lateness[j : j + 1],
            "work_ns": stats.work[j : j + 1],
        }
        for i, p in enumerate(PHASES):
            values[f"{p}_ns"] = stats.phases[i, j : j + 1]
        every = self.options.decimate.get("timing", 1)
        if int(values["tick"][0]) % every:
            return
        msg = ch.layout.encode(values, 1).tobytes()
        t = int(ring.state[R.LAST_NOW]) + self._offset_ns
        if self._writer is not None:
            self._writer.add_message(ch.channel_id, t, msg, t, int(values["tick"][0]) & 0xFFFFFFFF)
        self.messages += 1
