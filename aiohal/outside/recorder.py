"""The recorder: every tick into an MCAP file, written by a process of its own.

On the tick: one compiled copy of the robot's arrays into the tick ring in shared memory
(:mod:`.tick_ring`), shared by every output. In the recorder's process
(:mod:`.recorder_writer`): encoding, the MCAP records, compression, the file, and the live
Foxglove server when one is asked for. The loop's process keeps only the tick's thread: the
drivers' health and the controller's metrics are sampled on the event loop (drivers are not
thread-safe) at ``health_hz`` and sent with the faults and safety changes as small messages
(:mod:`.output_process`), never waited for. A writer that falls behind, stops or dies loses its
own rows, counted in the summary; the tick never waits for it.

The file is usable at any time up to its last written chunk: the writer closes the chunk in
progress and flushes the file every ``flush_ms`` (docs/recording.md).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any

from ..core.tick_timing import PHASES
from ..record.options import RecordSection
from . import tick_ring as R
from .event_feed import EventFeed, join_feed, leave_feed
from .output_process import OutputProcess
from .port import LoopPort
from .tick_door import TickDoor, close_door, open_door

log = logging.getLogger(__name__)

#: how long the writer's process may take to start (imports, the file, the server's port)
START_TIMEOUT_S = 60.0
#: how long it may take to drain the ring and close the file at the end
STOP_TIMEOUT_S = 60.0


class Recorder:
    """Records a loop, through its :class:`~aiohal.outside.port.LoopPort`, to an MCAP file or a
    rosbag2 directory (a path not ending in ``.mcap``; :mod:`.recorder_file`), and/or serves
    it live to Foxglove on ``live_port`` (0: any free port; :attr:`live_port` says which).

    ``attach()`` (before ``run``) opens the loop's tick door (:mod:`.tick_door`) and starts the
    writer's process; ``close()`` (after the run) lets it drain the ring, write the summary and
    close the file. ``plain``: serialize every message
    with rosbags, one at a time (the reference for the batch path, which writes the same bytes;
    ``python -m benchmarks.record --plain``).
    """

    def __init__(
        self,
        port: LoopPort,
        path: str | Path | None,
        options: RecordSection | None = None,
        *,
        live_port: int | None = None,
        plain: bool = False,
    ) -> None:
        self.port = port
        self.options = options or RecordSection()
        self.path = None if path is None else Path(path)
        self.live_port = live_port
        self.plain = plain
        self.door: TickDoor | None = None
        self.ring: R.TickRing | None = None
        self.process: OutputProcess | None = None
        self.feed: EventFeed | None = None
        self.error: str | None = None
        self._line = -1
        self._attached = False
        self._closed = False
        self._summary: dict[str, Any] | None = None
        self._offset_ns = time.time_ns() - port.now_ns()  # tick clock -> Unix time

    def start_process(self) -> None:
        """Start the writer's process and wait until it runs (before the robot starts, this
        refuses a live port in use before anything moves): RuntimeError with its reason."""
        if self.process is not None:
            return
        port = self.port
        self.door = open_door(port, self.options.buffer_ticks)
        self.ring = self.door.ring
        start = self.door.start_index()
        self._line = self.ring.claim_reader(start)
        spec = {
            "robot": port.robot,
            "path": None if self.path is None else str(self.path),
            "options": self.options,
            "live_port": self.live_port,
            "plain": self.plain,
            "period_ns": port.period_ns,
            "clock": port.clock_kind,
            "config_text": _config_text(port),
            "offset_ns": self._offset_ns,
            "now_ns": port.now_ns(),
            "start": start,
            "pid": os.getpid(),
            "line": self._line,
        }
        what = "recorder" if self.path is not None else "live view"
        self.process = OutputProcess(
            "recorder", spec, f"{what} of {port.robot.name}", avoid_cpus=port.config.realtime.cpus
        )
        info = self.process.wait_ready(START_TIMEOUT_S)
        if self.live_port is not None:
            self.live_port = info["live_port"]

    def attach(self) -> None:
        """Start recording: the writer's process (the robot's description, latched), tick 0 (the
        state the activation read, when called between ``activate()`` and ``run()``), the health
        sampler (if an event loop runs) and the tick's publisher."""
        if self._attached:
            return
        self._attached = True
        try:
            self.start_process()
        except (RuntimeError, OSError) as exc:
            self.error = str(exc)
            log.error("recording not started: %s", self.error)
            return
        assert self.process is not None
        self.feed = join_feed(self.port, self.options.health_hz, self.process)

    @property
    def pid(self) -> int | None:
        """The writer process's id (None before it starts)."""
        return None if self.process is None else self.process.pid

    def close(self) -> dict[str, Any]:
        """Let the writer drain what the tick left, write the last events and the summary; returns
        the figures."""
        if self._closed:
            return self.summary()
        self._closed = True
        if self.feed is not None and self.process is not None:
            leave_feed(self.feed, self.process)  # the last health and events go first
            self.feed = None
        if self.process is not None:
            final = {"last_timing": self._last_timing()}
            self._summary = self.process.stop(final, STOP_TIMEOUT_S)
            if self._summary is None:
                self.error = self.process.error
                log.error("%s: %s", self.process.name, self.error)
        summary = self.summary()
        if self.door is not None:
            close_door(self.door)
            self.door = None
        return summary

    def summary(self) -> dict[str, Any]:
        if self._summary is not None:
            out = dict(self._summary)
        else:  # no word from the writer: what its reader line says
            ring = self.ring
            seen = R.reader_figures(ring, self._line) if ring is not None and ring.readers is not None else {}
            out = {
                "path": None if self.path is None else str(self.path),
                "ticks": seen.get("kept", 0),
                "dropped_ticks": seen.get("not_kept", 0),
                "messages": 0,
                "live_messages": 0,
                "bytes": self.path.stat().st_size if self.path is not None and self.path.is_file() else 0,
            }
        if self.error:
            out["error"] = self.error
        if self.process is not None and self.process.dropped_messages:
            out["dropped_events"] = self.process.dropped_messages
        return out

    def _last_timing(self) -> dict[str, Any] | None:
        """The run's last tick's timing (stored after its publisher ran), when it was recorded."""
        assert self.ring is not None
        last = self.ring.last_tick()
        stats = self.port.timing
        count = stats.count
        if last is None or count == 0 or last[0] != count - 1:
            return None
        j = (count - 1) & stats.mask
        return {
            "tick": last[1],
            "now_ns": last[2],
            "lateness_ns": int(stats.lateness[j]),
            "work_ns": int(stats.work[j]),
            "phases_ns": [int(stats.phases[i, j]) for i in range(len(PHASES))],
        }


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
