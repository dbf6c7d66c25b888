"""The end-of-run timing report as text for people (the JSON form is the loop's report dict)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        if 0 < abs(value) < 0.1:
            return f"{value:.3g}"
        return f"{value:,.2f}" if abs(value) < 1e6 else f"{value:.3g}"
    return str(value)


# the loop's own per-driver figures; anything else a driver's health() added is printed after them
_DRIVER_KEYS = {"type", "status", "joints", "read_us_mean", "write_us_mean", "read_us_max", "write_us_max"}


def format_report(report: dict[str, Any]) -> str:
    lat, work = report["lateness_us"], report["work_us"]
    target, achieved = report["rate_hz_target"], report["rate_hz_achieved"]
    error_pct = (achieved - target) / target * 100 if target and not math.isnan(achieved) else float("nan")
    lines = [
        f"aiohal run report: {report['robot']} ({report['joints']} joints, clock {report['clock']}, "
        f"overrun policy {report['overrun_policy']})",
        f"  rate         target {_fmt(target)} Hz, achieved {achieved:.3f} Hz ({error_pct:+.4f} %)",
        f"  ticks        {report['ticks']} in {_fmt(report['duration_s'])} s, missed {report['missed_ticks']}, "
        f"overruns {report['overruns']}",
        f"  lateness µs  p50 {_fmt(lat['p50'])}  p99 {_fmt(lat['p99'])}  p99.9 {_fmt(lat['p999'])}  "
        f"max {_fmt(lat['max'])}",
        f"  drift        {_fmt(report['drift_us'])} µs",
        f"  work µs      p50 {_fmt(work['p50'])}  p99 {_fmt(work['p99'])}  max {_fmt(work['max'])}",
        "  phases µs    "
        + "  ".join(f"{name} {_fmt(p['p50'])}/{_fmt(p['p99'])}" for name, p in report["phases_us"].items())
        + "  (p50/p99)",
        f"  cpu          {_fmt(report['cpu_percent'])} % of one core",
        "  realtime     "
        + (", ".join(f"{k} {v}" for k, v in report.get("realtime", {}).items() if k != "warnings") or "none")
        + "".join(f"\n  WARNING      {w}" for w in report.get("realtime", {}).get("warnings", [])),
        f"  safety       {report['safety_level']}  (stop: {report['stop_reason']})",
    ]
    for name, d in report["drivers"].items():
        lines.append(
            f"  driver       {name} [{d['type']}] {d['status']}, {d['joints']} joints, "
            f"read {_fmt(d['read_us_mean'])} µs, write {_fmt(d['write_us_mean'])} µs (mean)"
        )
        health = [f"{k} {_fmt(v)}" for k, v in d.items() if k not in _DRIVER_KEYS and not isinstance(v, (dict, list))]
        if health:
            lines.append("               " + ", ".join(health))
    ctrl = report["controller"]
    extra = ", ".join(f"{k} {_fmt(v)}" for k, v in ctrl.items() if k != "type")
    lines.append(f"  controller   {ctrl['type']}" + (f": {extra}" if extra else ""))
    rec = report.get("record")
    if rec:
        lines.append(f"  record       {rec['path'] or 'live only'}: {rec['ticks']} ticks, {rec['dropped_ticks']} dropped, "
                     f"{rec['messages']} messages" + (f", ERROR {rec['error']}" if rec.get("error") else ""))
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


def write_json(report: dict[str, Any], path: str | Path) -> None:
    """Write the report as strict JSON (NaN becomes null), atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_json_safe(report), indent=2, allow_nan=False) + "\n")
    tmp.replace(path)
