"""The live terminal status of a run: a rich panel refreshed a few times a second.

Rendered on the event loop between ticks (never in the tick, and not from rich's own refresh
thread, whose Python work would take the GIL from the tick at any moment); it reads the tick's
timing and the drivers' health through the loop's port, as the report reads them.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np

from .port import LoopPort


def panel_figures(port: LoopPort, window: int = 1000) -> dict[str, Any]:
    """The figures the panel shows, over the last ``window`` ticks."""
    stats = port.timing
    n = stats.count
    last = min(n, window, stats.mask + 1)
    idx = (n - 1 - np.arange(last)) & stats.mask
    lateness = stats.lateness[idx]
    span_s = (stats.last_tick_ns - stats.first_tick_ns) / 1e9
    health = port.health()
    faults = port.faults
    return {
        "robot": port.robot.name,
        "ticks": n,
        "rate_hz": (n - 1) / span_s if n > 1 and span_s > 0 else float("nan"),
        "lateness_p99_us": float(np.percentile(lateness, 99)) / 1e3 if last else float("nan"),
        "work_p50_us": float(np.median(stats.work[idx])) / 1e3 if last else float("nan"),
        "missed_ticks": port.missed_ticks,
        "safety_level": health.level.name.lower(),
        "faults": [str(f) for f in faults[-3:]],
        "fault_count": len(faults),
        "drivers": health.drivers,
        "controller": health.controller,
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


class StatusPanel:
    """Shows the panel from :meth:`start` to :meth:`stop`, on the running event loop."""

    def __init__(self, port: LoopPort, refresh_hz: float = 4.0, console: Any = None) -> None:
        self.port = port
        self.period = 1.0 / refresh_hz
        self.console = console
        self._task: asyncio.Task | None = None
        self._live: Any = None
        self.refreshes = 0
        self.draw_ns = 0
        self.max_draw_ns = 0

    def start(self) -> None:
        from rich.console import Console
        from rich.live import Live

        self._live = Live(
            render(panel_figures(self.port)), console=self.console or Console(), auto_refresh=False, transient=True
        )
        self._live.start()
        self._task = asyncio.get_running_loop().create_task(self._refresh())

    async def _refresh(self) -> None:
        while True:
            await asyncio.sleep(self.period)
            start = time.perf_counter_ns()
            self._live.update(render(panel_figures(self.port)), refresh=True)
            spent = time.perf_counter_ns() - start
            self.refreshes += 1
            self.draw_ns += spent
            self.max_draw_ns = max(self.max_draw_ns, spent)

    def cost(self) -> dict[str, Any]:
        """What drawing took on the event loop's thread (between ticks, but a tick due while it
        draws waits for it): refreshes, mean and longest draw."""
        return {
            "refreshes": self.refreshes,
            "draw_ms_mean": round(self.draw_ns / self.refreshes / 1e6, 3) if self.refreshes else None,
            "draw_ms_max": round(self.max_draw_ns / 1e6, 3),
        }

    def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
        if self._live is not None:
            self._live.stop()
