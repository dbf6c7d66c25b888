"""The live terminal status of a run: a rich panel refreshed a few times a second, drawn by
an output process of its own.

The process reads the tick's timing from the tick ring (:mod:`.tick_ring`: each row carries
the previous tick's lateness and work) and the drivers' health, the faults and the missed
ticks from the loop's messages (:mod:`.event_feed`); the loop's process spends
nothing on drawing. Its cost (refreshes, mean and longest draw) comes back in the report.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from . import tick_ring as R
from .event_feed import EventFeed, join_feed, leave_feed
from .output_process import OutputProcess
from .port import LoopPort
from .tick_door import TickDoor, close_door, open_door


class StatusFigures:
    """What the panel shows, from ring rows (:meth:`add_rows`) and the loop's messages
    (:meth:`message`), over the last ``window`` ticks."""

    def __init__(self, robot: str, window: int = 1000) -> None:
        self.robot = robot
        self.lateness = np.zeros(window, dtype=np.int64)
        self.work = np.zeros(window, dtype=np.int64)
        self.timed = 0  # ticks whose timing was seen
        self.ticks = 0
        self.first: tuple[int, int] | None = None  # (count, now_ns) of the first row
        self.last: tuple[int, int] | None = None
        self.health: Any = None
        self.loop: dict[str, Any] = {"missed_ticks": 0}
        self.faults: list[str] = []
        self.fault_count = 0

    def add_rows(self, meta: np.ndarray) -> None:
        if not len(meta):
            return
        if self.first is None:
            self.first = (int(meta[0, R.COUNT]), int(meta[0, R.NOW]))
        self.last = (int(meta[-1, R.COUNT]), int(meta[-1, R.NOW]))
        self.ticks = self.last[0] + 1
        timed = meta[meta[:, R.TIMING_VALID] != 0]
        w = len(self.lateness)
        for row in timed[-w:]:
            i = self.timed % w
            self.lateness[i], self.work[i] = row[R.TIMING], row[R.TIMING + 1]
            self.timed += 1

    def message(self, message: tuple) -> None:
        if message[0] != "event":
            return
        _, topic, _, body = message
        if topic == "/diagnostics":
            self.health = body
        elif topic == "/loop":
            self.loop = body
        elif topic == "/faults":
            self.fault_count += 1
            self.faults = [*self.faults[-2:], str(body)]

    def figures(self) -> dict[str, Any]:
        n = min(self.timed, len(self.lateness))
        rate = float("nan")
        if self.first is not None and self.last is not None and self.last[1] > self.first[1]:
            rate = (self.last[0] - self.first[0]) / ((self.last[1] - self.first[1]) / 1e9)
        health = self.health
        return {
            "robot": self.robot,
            "ticks": self.ticks,
            "rate_hz": rate,
            "lateness_p99_us": float(np.percentile(self.lateness[:n], 99)) / 1e3 if n else float("nan"),
            "work_p50_us": float(np.median(self.work[:n])) / 1e3 if n else float("nan"),
            "missed_ticks": self.loop.get("missed_ticks", 0),
            "safety_level": health.level.name.lower() if health is not None else "?",
            "faults": self.faults,
            "fault_count": self.fault_count,
            "drivers": health.drivers if health is not None else {},
            "controller": health.controller if health is not None else {},
        }


def render(figures: dict[str, Any]) -> Any:
    from rich.table import Table

    level = figures["safety_level"]
    colour = {"run": "green", "hold": "yellow"}.get(level, "red")
    table = Table.grid(padding=(0, 2))
    table.add_column(style="bold")
    table.add_column()
    table.add_row("robot", f"{figures['robot']}  ticks {figures['ticks']}")
    table.add_row("rate", f"{figures['rate_hz']:.1f} Hz")
    table.add_row(
        "lateness",
        f"p99 {figures['lateness_p99_us']:.1f} µs (last 1000 ticks)  work p50 {figures['work_p50_us']:.1f} µs",
    )
    table.add_row("missed", str(figures["missed_ticks"]))
    table.add_row("safety", f"[{colour}]{level}[/]")
    table.add_row("faults", str(figures["fault_count"]) + "".join(f"\n[red]{f}[/]" for f in figures["faults"]))
    for name, d in figures["drivers"].items():
        extra = ", ".join(f"{k} {_short(v)}" for k, v in d.items() if k != "status" and not isinstance(v, (dict, list)))
        table.add_row(f"driver {name}", d["status"] + (f"  {extra}" if extra else ""))
    ctrl = figures["controller"]
    table.add_row(
        "controller",
        ctrl.get("type", "?")
        + "  "
        + ", ".join(f"{k} {_short(v)}" for k, v in ctrl.items() if k != "type" and not isinstance(v, (dict, list))),
    )
    from rich.panel import Panel

    return Panel(table, title="aiohal", expand=False)


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


class StatusOutput:
    """The panel's process: draws from the ring and the loop's messages every ``refresh_s``."""

    IDLE_S = 0.02

    def __init__(self, spec: dict[str, Any], console: Any = None) -> None:
        from rich.console import Console
        from rich.live import Live

        self.ring = R.TickReader(spec["robot_name"], pid=spec["pid"], start=spec["start"], line=spec["line"])
        self.state = StatusFigures(spec["robot_name"])
        self.period_ns = int(1e9 / spec.get("refresh_hz", 4.0))
        self.refreshes = 0
        self.draw_ns = 0
        self.max_draw_ns = 0
        if console is None and spec.get("terminal") is not None:  # another terminal (or a file)
            self._out = open(spec["terminal"], "w")  # noqa: SIM115 - closed in finish()
            console = Console(file=self._out, force_terminal=True, width=100)
        self._live = Live(
            render(self.state.figures()), console=console or Console(), auto_refresh=False, transient=True
        )
        self._live.start()
        self._next = time.monotonic_ns() + self.period_ns

    def info(self) -> dict[str, Any]:
        return {}

    def step(self) -> bool:
        rows = self.ring.read(self.ring.slots)
        self.state.add_rows(self.ring.meta(rows))
        now = time.monotonic_ns()
        if now >= self._next:
            self._next = now + self.period_ns
            self._live.update(render(self.state.figures()), refresh=True)
            spent = time.monotonic_ns() - now
            self.refreshes += 1
            self.draw_ns += spent
            self.max_draw_ns = max(self.max_draw_ns, spent)
        return not len(rows)

    def message(self, message: tuple) -> None:
        self.state.message(message)

    def finish(self, final: Any) -> dict[str, Any]:
        """Stop drawing; what drawing took in this process (refreshes, mean and longest draw)."""
        self._live.stop()
        if getattr(self, "_out", None) is not None:
            self._out.close()
        self.ring.close()
        return {
            "refreshes": self.refreshes,
            "draw_ms_mean": round(self.draw_ns / self.refreshes / 1e6, 3) if self.refreshes else None,
            "draw_ms_max": round(self.max_draw_ns / 1e6, 3),
        }


class StatusPanel:
    """The loop's side: starts the panel's process reading the loop's tick ring; the loop's
    event feed (:mod:`.event_feed`) sends it the health and faults."""

    def __init__(
        self,
        port: LoopPort,
        buffer_ticks: int = 4096,
        refresh_hz: float = 4.0,
        terminal: str | None = None,
        health_hz: float = 10.0,
    ) -> None:
        self.port = port
        self.buffer_ticks = buffer_ticks
        self.door: TickDoor | None = None
        self.feed: EventFeed | None = None
        self.health_hz = health_hz
        self.refresh_hz = refresh_hz
        self.terminal = terminal
        self.process: OutputProcess | None = None
        self._cost: dict[str, Any] | None = None

    def start(self, timeout_s: float = 60.0) -> OutputProcess:
        self.door = door = open_door(self.port, self.buffer_ticks)
        start = door.start_index()
        line = door.ring.claim_reader(start)
        spec = {
            "robot_name": self.port.robot.name,
            "start": start,
            "pid": os.getpid(),
            "line": line,
            "refresh_hz": self.refresh_hz,
            "terminal": self.terminal,
        }
        self.process = OutputProcess(
            "status", spec, f"status panel of {self.port.robot.name}", avoid_cpus=self.port.config.realtime.cpus
        )
        self.process.wait_ready(timeout_s)
        self.feed = join_feed(self.port, self.health_hz, self.process)
        return self.process

    def stop(self) -> None:
        if self.feed is not None and self.process is not None:
            leave_feed(self.feed, self.process)
            self.feed = None
        if self.process is not None:
            self._cost = self.process.stop(None, 30.0)
            self.process = None
        if self.door is not None:
            close_door(self.door)
            self.door = None

    def cost(self) -> dict[str, Any]:
        """What drawing took in the panel's process: refreshes, mean and longest draw."""
        return self._cost or {"refreshes": 0, "draw_ms_mean": None, "draw_ms_max": 0.0}
