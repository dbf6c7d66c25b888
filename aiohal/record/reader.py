"""Reading a recording back into numpy arrays, and its summary (``aiohal info``).

Reads the file from the start with mcap's stream reader, so a file whose writer was killed
(no summary section at its end) reads up to its last complete chunk; ``truncated`` says so.
A rosbag2 directory is read through its MCAP files. Messages are decoded by rosbags
(:mod:`aiohal.ros2`); a channel whose messages all have one fixed layout (every per-tick
channel aiohal writes) is decoded in one ``frombuffer`` per field instead of per message.
"""

from __future__ import annotations

import json
import struct
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import ros2
from ..core.tick_timing import PHASES, percentiles_us
from ..files import open_regular
from ..safety import SafetyLevel

#: a recording is loaded whole into memory: larger ones are refused, not read until it runs out
MAX_RECORDING_BYTES = 4 << 30
LEVELS = tuple(level.name.lower() for level in sorted(SafetyLevel))  # by value: the recorded number


@dataclass
class Series:
    """One channel's messages: ``log_time_ns`` (Unix ns), ``t`` (s since the recording's first
    message), ``tick`` and its number fields by dotted path, as arrays with one row per message
    (``series["position"]``, ``series.position``, ``series["orientation.w"]``); a channel
    without a fixed layout (diagnostics, events) has only ``tick``. ``messages``: every message
    decoded as an object (by rosbags, on first use)."""

    topic: str
    schema: str
    log_time_ns: np.ndarray
    t: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    raw: list[bytes] = field(default_factory=list, repr=False)  # the CDR messages
    _decoded: list[Any] | None = field(default=None, repr=False)

    @property
    def messages(self) -> list[Any]:
        if self._decoded is None:
            self._decoded = [ros2.deserialize(m, self.schema) for m in self.raw]
        return self._decoded

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
    """A recording loaded into memory: ``rec["/joint_states"].position`` is ``(ticks, joints)``."""

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
        """The run's description (robot, rate, clock, joint and device names) from ``/robot``,
        and the decimation from the file's metadata."""
        out = {k: json.loads(v) for k, v in self.metadata.get("aiohal", {}).items()}
        robot = self.series.get("/robot")
        if robot is not None and robot.messages:
            msg = robot.messages[0]
            out.update(robot=msg.name, rate_hz=msg.rate_hz, clock=msg.clock, joint_names=list(msg.joint_names))
            out["devices"] = {k: list(getattr(msg, f"{k}_names")) for k in ("imu", "force_torque", "hand")}
            out["description"] = msg.description
        return out

    @property
    def joint_names(self) -> list[str]:
        return list(self.info.get("joint_names", []))

    @property
    def faults(self) -> list[dict]:
        """Every fault: tick, source, phase, error (from ``/faults``' diagnostics)."""
        out = []
        for msg in self.series["/faults"].messages if "/faults" in self.series else []:
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                tick = values.get("tick", "-1")
                out.append(
                    {
                        "tick": int(tick),
                        "source": status.name,
                        "phase": values.get("phase", ""),
                        "error": status.message,
                    }
                )
        return out

    def summary(self) -> dict[str, Any]:
        """What ``aiohal info`` prints: ticks per channel, gaps, timing, safety, faults."""
        info = self.info
        out: dict[str, Any] = {
            "path": str(self.path),
            "robot": info.get("robot"),
            "rate_hz": info.get("rate_hz"),
            "truncated": self.truncated,
        }
        state = self.series.get("/joint_states")
        if state is not None and len(state):
            ticks = state.tick
            steps = np.diff(ticks)
            every = int(info.get("decimate", {}).get("joint_state", steps.min() if len(steps) else 1))
            expected = (int(ticks[-1]) - int(ticks[0])) // every + 1
            out.update(
                ticks=len(state),
                first_tick=int(ticks[0]),
                last_tick=int(ticks[-1]),
                # from tick 1: tick 0 is the activation's read, stamped before the run started
                duration_s=round(float(state.t[-1] - state.t[1 if ticks[0] == 0 and len(ticks) > 1 else 0]), 4),
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
    """Load every channel of a recording: an MCAP file, or a rosbag2 directory of MCAP files."""
    path = Path(path)
    files = sorted(path.glob("*.mcap")) if path.is_dir() else [path]
    if not files:
        raise ValueError(f"{path}: a directory without an MCAP file (a rosbag2 directory holds one)")
    raw = _RawRecording()
    for file in files:
        raw.read(file)
    starts = [t[0] for t in raw.times.values() if t]
    start = min(starts) if starts else 0
    series: dict[str, Series] = {}
    for cid, channel in raw.channels.items():
        stamps = np.array(raw.times.get(cid, []), dtype=np.int64)
        schema = raw.schemas.get(channel.schema_id)
        s = Series(channel.topic, schema.name if schema else "", stamps, (stamps - start) / 1e9)
        messages = raw.data.get(cid, [])
        if channel.message_encoding == "cdr" and schema is not None and messages:
            s.raw = messages
            _decode(s, np.array(raw.sequences[cid], dtype=np.int64))
        series[channel.topic] = s
    return Recording(path, series, raw.metadata, raw.truncated, start)


class _RawRecording:
    """The records of one or more MCAP files, as the stream reader gives them."""

    def __init__(self) -> None:
        self.schemas: dict[int, Any] = {}
        self.channels: dict[int, Any] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.data: dict[int, list[bytes]] = defaultdict(list)
        self.times: dict[int, list[int]] = defaultdict(list)
        self.sequences: dict[int, list[int]] = defaultdict(list)
        self.truncated = False

    def read(self, path: Path) -> None:
        from mcap.exceptions import McapError
        from mcap.records import Channel, Message, Metadata, Schema
        from mcap.stream_reader import StreamReader

        with open_regular(path, "recording", limit=MAX_RECORDING_BYTES) as f:
            try:
                for record in StreamReader(f).records:
                    if isinstance(record, Message):
                        self.data[record.channel_id].append(record.data)
                        self.times[record.channel_id].append(record.log_time)
                        self.sequences[record.channel_id].append(record.sequence)
                    elif isinstance(record, Schema):
                        self.schemas[record.id] = record
                    elif isinstance(record, Channel):
                        self.channels[record.id] = record
                    elif isinstance(record, Metadata):
                        self.metadata[record.name] = dict(record.metadata)
            except (McapError, EOFError, struct.error, ValueError, OSError) as exc:
                # the end of a file whose writer was killed: a chunk or record cut short
                self.truncated = True
                if not self.data and not self.channels:
                    raise ValueError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from exc


def _decode(series: Series, sequences: np.ndarray) -> None:
    """Number fields by path when every message of ``series`` has one fixed layout. ``tick``:
    the message's field, else the MCAP sequence (the recorder writes the tick there)."""
    from ..ros2.fixed import FixedLayout

    messages = series.raw
    try:
        first = ros2.deserialize(messages[0], series.schema)
    except KeyError:  # a type that is neither Jazzy's nor aiohal's: left undecoded
        return
    except Exception as exc:  # rosbags' SerdeError, or whatever its generated decoder met
        raise ValueError(
            f"{series.topic}: its messages do not decode as {series.schema} ({type(exc).__name__}: {exc})"
        ) from None
    size = len(messages[0])
    if all(len(m) == size for m in messages):
        try:
            layout = FixedLayout(first)
        except ValueError:  # a sequence of messages (diagnostics)
            layout = None
        raw = np.frombuffer(b"".join(messages), dtype=np.uint8).reshape(len(messages), size)
        if layout is not None and layout.matches(raw):
            series.fields = layout.decode(raw)
            series.fields.setdefault("tick", sequences)
            return
    series.fields["tick"] = np.array([getattr(m, "tick", s) for m, s in zip(series.messages, sequences, strict=True)])


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


def info_main(argv: list[str]) -> int:
    """``aiohal info FILE``: print a recording's summary (``--json`` for JSON)."""
    import argparse

    p = argparse.ArgumentParser(
        prog="python -m aiohal info", description="Summarise a recording (an MCAP file or a rosbag2 directory)."
    )
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
