"""Reading a recording back into numpy arrays, and its summary (``aiohal replay``).

Reads the file from the start with mcap's stream reader, so a file whose writer was killed
(no summary section at its end) reads up to its last complete chunk; ``truncated`` says so.
"""

from __future__ import annotations

import json
import struct
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.tick_timing import PHASES, percentiles_us
from ..files import open_regular
from ..safety import SafetyLevel
from .cdr import Layout

#: a recording is loaded whole into memory: larger ones are refused, not read until it runs out
MAX_RECORDING_BYTES = 4 << 30
LEVELS = tuple(level.name.lower() for level in sorted(SafetyLevel))  # by value: the recorded number


@dataclass
class Series:
    """One channel's messages: ``log_time_ns`` (Unix ns), ``t`` (s since the recording's first
    message) and its fields, as arrays with one row per message (``series["position"]`` or
    ``series.position``)."""

    topic: str
    schema: str
    log_time_ns: np.ndarray
    t: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    messages: list[Any] = field(default_factory=list)  # JSON channels: the decoded messages

    def __getitem__(self, name: str) -> np.ndarray:
        return self.fields[name]

    def __getattr__(self, name: str) -> np.ndarray:
        fields = self.__dict__.get("fields", {})
        if name in fields:
            return fields[name]
        raise AttributeError(name)

    def __len__(self) -> int:
        return len(self.log_time_ns)


@dataclass
class Recording:
    """A recording loaded into memory: ``rec["/joint_state"].position`` is ``(ticks, joints)``."""

    path: Path
    series: dict[str, Series]
    metadata: dict[str, dict[str, str]]
    truncated: bool
    start_ns: int

    def __getitem__(self, topic: str) -> Series:
        return self.series[topic]

    def __contains__(self, topic: str) -> bool:
        return topic in self.series

    @property
    def info(self) -> dict[str, Any]:
        """The run's description (robot, rate, joint and device names), from the file's metadata."""
        raw = self.metadata.get("aiohal", {})
        return {k: json.loads(v) for k, v in raw.items()}

    @property
    def joint_names(self) -> list[str]:
        return list(self.info.get("joint_names", []))

    @property
    def faults(self) -> list[dict]:
        return list(self.series["/faults"].messages) if "/faults" in self.series else []

    def summary(self) -> dict[str, Any]:
        """What ``aiohal replay`` prints: ticks per channel, gaps, timing, safety, faults."""
        info = self.info
        out: dict[str, Any] = {
            "path": str(self.path),
            "robot": info.get("robot"),
            "rate_hz": info.get("rate_hz"),
            "truncated": self.truncated,
        }
        state = self.series.get("/joint_state")
        if state is not None and len(state):
            ticks = state.tick
            every = int(info.get("decimate", {}).get("joint_state", 1))
            expected = (int(ticks[-1]) - int(ticks[0])) // every + 1
            out.update(
                ticks=len(state),
                first_tick=int(ticks[0]),
                last_tick=int(ticks[-1]),
                duration_s=round(float(state.t[-1] - state.t[0]), 4),
                missing_ticks=expected - len(state),
            )
        out["channels"] = {topic: len(s) for topic, s in sorted(self.series.items())}
        timing = self.series.get("/timing")
        if timing is not None and len(timing):
            out["lateness_us"] = percentiles_us(timing.lateness_ns)
            out["work_us"] = percentiles_us(timing.work_ns)
            out["phases_us_p50"] = {p: round(float(np.median(timing[f"{p}_ns"])) / 1e3, 2) for p in PHASES}
        safety = self.series.get("/safety")
        if safety is not None and len(safety):
            levels, counts = np.unique(safety.level, return_counts=True)
            out["safety_ticks"] = {
                LEVELS[int(v)] if v < len(LEVELS) else str(v): int(c) for v, c in zip(levels, counts, strict=True)
            }
            out["safety_last"] = LEVELS[int(safety.level[-1])]
        out["faults"] = self.faults
        return out


def load(path: str | Path) -> Recording:
    """Load every channel of an aiohal recording (or any MCAP file with ros2msg/cdr and json channels)."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    path = Path(path)
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    metadata: dict[str, dict[str, str]] = {}
    data: dict[int, list[bytes]] = defaultdict(list)
    times: dict[int, list[int]] = defaultdict(list)
    truncated = False
    with open_regular(path, "recording", limit=MAX_RECORDING_BYTES) as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Message):
                    data[record.channel_id].append(record.data)
                    times[record.channel_id].append(record.log_time)
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Metadata):
                    metadata[record.name] = dict(record.metadata)
        except (McapError, EOFError, struct.error, ValueError, OSError) as exc:
            # the end of a file whose writer was killed: a chunk or record cut short
            truncated = True
            if not data and not channels:
                raise ValueError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from exc
    starts = [t[0] for t in times.values() if t]
    start = min(starts) if starts else 0
    series: dict[str, Series] = {}
    for cid, channel in channels.items():
        stamps = np.array(times.get(cid, []), dtype=np.int64)
        schema = schemas.get(channel.schema_id)
        s = Series(channel.topic, schema.name if schema else "", stamps, (stamps - start) / 1e9)
        messages = data.get(cid, [])
        if channel.message_encoding == "cdr" and schema is not None and schema.encoding == "ros2msg" and messages:
            layout = Layout.from_schema(schema.name, schema.data.decode(), messages[0])
            if all(len(m) == layout.size for m in messages):
                raw = np.frombuffer(b"".join(messages), dtype=np.uint8).reshape(len(messages), layout.size)
                s.fields = layout.decode(raw)
            else:  # sequence lengths changed within the channel: one message at a time
                rows = [
                    Layout.from_schema(schema.name, schema.data.decode(), m).decode(
                        np.frombuffer(m, dtype=np.uint8)[None, :]
                    )
                    for m in messages
                ]
                s.fields = {k: np.array([r[k][0] for r in rows], dtype=object) for k in rows[0]}
        elif channel.message_encoding == "json":
            s.messages = [json.loads(m) for m in messages]
        series[channel.topic] = s
    return Recording(path, series, metadata, truncated, start)


def format_summary(summary: dict[str, Any]) -> str:
    """The summary as text for people."""
    lines = [
        f"recording {summary['path']}: robot {summary.get('robot')} at {summary.get('rate_hz')} Hz"
        + (
            "  (TRUNCATED: the writer did not finish; read up to its last complete chunk)"
            if summary["truncated"]
            else ""
        )
    ]
    if "ticks" in summary:
        lines.append(
            f"  ticks        {summary['ticks']} ({summary['first_tick']}..{summary['last_tick']}) in "
            f"{summary['duration_s']} s, missing {summary['missing_ticks']}"
        )
    for key, label in (("lateness_us", "lateness µs"), ("work_us", "work µs")):
        if key in summary:
            p = summary[key]
            lines.append(f"  {label:<12} p50 {p['p50']}  p99 {p['p99']}  max {p['max']}")
    if "phases_us_p50" in summary:
        lines.append("  phases µs    " + "  ".join(f"{k} {v}" for k, v in summary["phases_us_p50"].items()) + "  (p50)")
    if "safety_ticks" in summary:
        lines.append(
            f"  safety       last {summary['safety_last']}; ticks per level "
            + ", ".join(f"{k} {v}" for k, v in summary["safety_ticks"].items())
        )
    lines.append("  channels     " + ", ".join(f"{k} {v}" for k, v in summary["channels"].items()))
    for fault in summary["faults"]:
        lines.append(f"  FAULT        {fault['source']} in {fault['phase']} at tick {fault['tick']}: {fault['error']}")
    return "\n".join(lines)


def replay_main(argv: list[str]) -> int:
    """``aiohal replay FILE``: print a recording's summary (``--json`` for JSON)."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m aiohal replay", description="Summarise a recording (MCAP).")
    p.add_argument("recording", type=Path)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    args = p.parse_args(argv)
    try:
        summary = load(args.recording).summary()
    except (OSError, ValueError, ImportError) as exc:
        print(f"error: {exc}", file=__import__("sys").stderr)
        return 2
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
    else:
        print(format_summary(summary))
    return 0
