"""The run report: built from the loop (:func:`build`, the JSON form) and written as text for
people (:func:`format_report`)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ..files import write_atomically
from .ticker import TimerfdTickSource

if TYPE_CHECKING:
    from ..config import Config
    from ..hal import Controller
    from ..outside.doorkeeper import Doorkeeper
    from ..robot import Robot
    from ..safety import FaultRecord, SafetyLevel
    from ..safety.supervisor import Supervisor
    from .lifecycle import DriverSlot
    from .limits import CommandLimiter
    from .realtime import RealtimeState
    from .target_extrapolation import TargetExtrapolator
    from .tick_timing import TickStats
    from .ticker import TickSource


class ReportedLoop(Protocol):
    """What the report reads of the loop (:class:`aiohal.core.loop.ControlLoop`)."""

    config: Config
    robot: Robot
    source: TickSource
    stats: TickStats
    period_ns: int
    slots: list[DriverSlot]
    limiter: CommandLimiter
    extrapolator: TargetExtrapolator | None
    supervisor: Supervisor
    realtime: RealtimeState | None
    doors: Doorkeeper | None
    event_loop: str
    stop_reason: str

    @property
    def missed_ticks(self) -> int: ...
    @property
    def level(self) -> SafetyLevel: ...
    @property
    def worst_level(self) -> SafetyLevel: ...
    @property
    def faults(self) -> list[FaultRecord]: ...
    @property
    def controller(self) -> Controller | None: ...
    @property
    def controller_type(self) -> str: ...


def build(loop: ReportedLoop) -> dict[str, Any]:
    """Timing, faults, drivers and the controller's own metrics of the run so far."""
    stats = loop.stats
    n = stats.count
    span = (stats.last_tick_ns - stats.first_tick_ns) / 1e9
    achieved = (n - 1) / span if n > 1 and span > 0 else float("nan")
    metrics: dict[str, Any] = {"type": loop.controller_type}
    configured = loop.supervisor.configured_type
    if configured != loop.controller_type:
        metrics["configured"] = configured
    if loop.extrapolator is not None:
        metrics.update(
            every=loop.extrapolator.every, extrapolate=loop.extrapolator.extrapolate, updates=loop.extrapolator.updates
        )
    if loop.controller is not None:
        try:
            metrics.update(loop.controller.metrics())
        except Exception as exc:
            metrics["metrics_error"] = f"{type(exc).__name__}: {exc}"
    source = loop.source  # a timerfd's waits: blocked on the timer, or round the event loop
    waits = (
        {"waits": {"on_timer": source.idle_waits, "through_loop": source.loop_waits}}
        if isinstance(source, TimerfdTickSource)
        else {}
    )
    bridges = loop.doors.report() if loop.doors is not None else {}
    return {
        "robot": loop.robot.name,
        "joints": loop.robot.dof,
        "clock": loop.source.kind,
        "event_loop": loop.event_loop,
        **waits,
        "overrun_policy": loop.config.loop.overrun,
        "realtime": loop.realtime.report() if loop.realtime else {},
        "rate_hz_target": round(1e9 / loop.period_ns, 3),
        "rate_hz_achieved": round(achieved, 3),
        "ticks": n,
        "missed_ticks": loop.missed_ticks,
        "duration_s": round(span, 4),
        **stats.summary(),
        "safety_level": loop.level.name.lower(),
        "safety_worst": loop.worst_level.name.lower(),
        "safety": [t.as_dict() for t in loop.supervisor.machine.transitions],
        "stop_reason": loop.stop_reason,
        "commands_refused": loop.limiter.refused,
        "faults": [f.as_dict() for f in loop.faults],
        "drivers": {slot.name: slot.report(n) for slot in loop.slots},
        "controller": metrics,
        **({"bridge": bridges} if bridges else {}),
    }


def _fmt(value: Any) -> str:
    """A value as a person reads it: no Python reprs (None, [], {...}, True)."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        if 0 < abs(value) < 0.1:
            return f"{value:.3g}"
        return f"{value:,.2f}" if abs(value) < 1e6 else f"{value:.3g}"
    if isinstance(value, dict):
        return "(" + ", ".join(_item(k, v) for k, v in value.items()) + ")" if value else "none"
    if isinstance(value, (list, tuple)):
        return "; ".join(_fmt(v) for v in value) if value else "none"
    return str(value)


#: key suffixes that carry a unit: ``sim_time_s`` reads "sim time 1.00 s"
_UNITS = (
    ("_per_s", "/s"),
    ("_percent", " %"),
    ("_us", " µs"),
    ("_ms", " ms"),
    ("_ns", " ns"),
    ("_hz", " Hz"),
    ("_rad", " rad"),
    ("_s", " s"),
    ("_m", " m"),
)


def _item(key: str, value: Any) -> str:
    unit = suffix = ""
    for ending, name in _UNITS:
        if key.endswith(ending) and len(key) > len(ending):
            key, unit, suffix = key[: -len(ending)], name, ending
            break
    if unit and isinstance(value, dict) and value:  # each figure with its unit: "rtt (p50 6.1 µs, p99 153.7 µs)"
        shown = "(" + ", ".join(_item(f"{k}{suffix}", v) for k, v in value.items()) + ")"
        return f"{key.replace('_', ' ')} {shown}"
    if unit and isinstance(value, (list, tuple)) and value:
        return f"{key.replace('_', ' ')} " + "; ".join(f"{_fmt(v)}{unit}" for v in value)
    shown = _fmt(value)
    return f"{key.replace('_', ' ')} {shown}{unit if shown != '-' else ''}"


def counted(n: int, noun: str) -> str:
    """``1 joint``, ``7 joints``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


# the loop's own per-driver figures; anything else a driver's health() added is printed after them
_DRIVER_KEYS = {"type", "status", "joints", "read_us_mean", "write_us_mean", "read_us_max", "write_us_max"}

# what each safety level means, said as what happened to the robot
_WORST = {"run": "ran normally", "hold": "went to hold", "estop": "EMERGENCY-STOPPED", "off": "never ran"}
_FINAL = {"off": "drivers closed", "estop": "drivers emergency-stopped", "hold": "holding", "run": "still running"}


def _safety(report: dict[str, Any]) -> str:
    worst = report.get("safety_worst", report["safety_level"])
    final = report["safety_level"]
    return f"{_WORST.get(worst, worst)}; at the end: {_FINAL.get(final, final)}"


def format_report(report: dict[str, Any]) -> str:
    lat, work = report["lateness_us"], report["work_us"]
    target, achieved = report["rate_hz_target"], report["rate_hz_achieved"]
    error_pct = (achieved - target) / target * 100 if target and not math.isnan(achieved) else float("nan")
    achieved_text = "-" if math.isnan(achieved) else f"{achieved:.3f} Hz ({error_pct:+.4f} %)"
    event_loop = f" on {report['event_loop']}" if report.get("event_loop") else ""
    realtime = report.get("realtime", {})
    lines = [
        f"aiohal run report: {report['robot']} ({counted(report['joints'], 'joint')}, clock {report['clock']}"
        f"{event_loop}, overrun policy {report['overrun_policy']})",
        f"  rate         target {_fmt(target)} Hz, achieved {achieved_text}",
        f"  ticks        {report['ticks']} in {_fmt(report['duration_s'])} s; deadlines missed "
        f"{report['missed_ticks']} (passed while a tick was late), ticks over the period {report['overruns']} "
        "(work longer than one period)",
        f"  lateness µs  p50 {_fmt(lat['p50'])}  p99 {_fmt(lat['p99'])}  p99.9 {_fmt(lat['p999'])}  "
        f"max {_fmt(lat['max'])}",
        f"  drift        {_fmt(report['drift_us'])} µs",
        f"  work µs      p50 {_fmt(work['p50'])}  p99 {_fmt(work['p99'])}  max {_fmt(work['max'])}",
        "  phases µs    "
        + "  ".join(f"{name} {_fmt(p['p50'])}/{_fmt(p['p99'])}" for name, p in report["phases_us"].items())
        + "  (p50/p99)",
        f"  cpu          {_fmt(report['cpu_percent'])} % of one core",
        "  realtime     "
        + (", ".join(_item(k, v) for k, v in realtime.items() if k != "warnings") or "none")
        + "".join(f"\n  WARNING      {w}" for w in realtime.get("warnings", [])),
        f"  safety       {_safety(report)}  (stop: {report['stop_reason'] or '-'})",
    ]
    for name, d in report["drivers"].items():
        lines.append(
            f"  driver       {name} [{d['type']}] {d['status']}, {counted(d['joints'], 'joint')}, "
            f"read {_fmt(d['read_us_mean'])} µs, write {_fmt(d['write_us_mean'])} µs (mean)"
        )
        health = [_item(k, v) for k, v in d.items() if k not in _DRIVER_KEYS]
        if health:
            lines.append("               " + ", ".join(health))
    ctrl = report["controller"]
    extra = ", ".join(_item(k, v) for k, v in ctrl.items() if k != "type")
    lines.append(f"  controller   {ctrl['type']}" + (f": {extra}" if extra else ""))
    rec = report.get("record")
    if rec:
        lines.append(
            f"  record       {rec['path'] or 'live only'}: {rec['ticks']} ticks, {rec['dropped_ticks']} dropped, "
            f"{rec['messages']} messages" + (f", ERROR {rec['error']}" if rec.get("error") else "")
        )
    for name, counters in report.get("bridge", {}).items():
        lines.append(
            f"  bridge       {name}: {counters.get('state_sent', 0)} states sent, {counters.get('state_lost', 0)} lost, "
            f"{counters.get('refused', 0)} commands refused"
        )
    panel = report.get("status_panel")
    if panel and panel["refreshes"]:
        lines.append(
            f"  panel        {panel['refreshes']} refreshes, drawing {panel['draw_ms_mean']:.2f} ms mean, "
            f"{panel['draw_ms_max']:.2f} ms longest (a tick due meanwhile waits; --no-panel turns it off)"
        )
    for fault in report["faults"]:
        lines.append(f"  FAULT        {fault['source']} in {fault['phase']} at tick {fault['tick']}: {fault['error']}")
    return "\n".join(lines)


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def write_json(report: dict[str, Any], path: str | Path, *, protect: tuple[Path, ...] = ()) -> None:
    """Write the report as strict JSON (NaN becomes null), atomically
    (:func:`aiohal.files.write_atomically`: only ever over a regular file, never ``protect``)."""
    text = json.dumps(_json_safe(report), indent=2, allow_nan=False) + "\n"
    write_atomically(path, text.encode(), protect=protect)
