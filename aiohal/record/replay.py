"""``aiohal replay FILE --config CONFIG``: run a config's controller on a recorded run, compare.

The config's drivers are replaced by one ``replay`` driver (``drivers/replay.py``) that feeds
the loop, in lockstep, the state measured on each recorded tick; the config's controller,
limits and safety run as they would on the robot. The commands of every tick are compared bit
for bit with the recorded ones (``/joint_commands`` and ``/joint_commands/extra``): a
deterministic controller on the same config gives the same bits, and the first tick that
differs says where a change of controller or parameters first shows.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import AiohalError, ConfigError, ConfigIssue
from .reader import Recording, load

#: the compared command fields and the recorded topic of each
COMMAND_FIELDS = (
    ("position", "/joint_commands"),
    ("velocity", "/joint_commands"),
    ("effort", "/joint_commands"),
    ("stiffness", "/joint_commands/extra"),
    ("damping", "/joint_commands/extra"),
    ("feedforward", "/joint_commands/extra"),
    ("mode", "/joint_commands/extra"),
)
#: sections that start something beside the loop: a replay runs none of them
OUTSIDE = ("record", "bridge", "client", "realtime")


@dataclass
class ReplayResult:
    ticks: int
    differing: list[int] = field(default_factory=list)  # ticks whose commands differ
    first: list[dict[str, Any]] = field(default_factory=list)  # the first such tick's differences
    missing: int = 0  # recorded ticks the replay could not feed (gaps in the recording)

    def as_dict(self) -> dict[str, Any]:
        return {
            "ticks": self.ticks,
            "differing_ticks": len(self.differing),
            "first_differing_tick": self.differing[0] if self.differing else None,
            "differences": self.first,
            "missing_ticks": self.missing,
        }


def replay_config(config_path: Path, recording: Path, rec: Recording) -> Any:
    """The config with its drivers replaced by one ``replay`` driver, on the virtual clock."""
    from ..config import parse_config
    from ..files import FileRefused, read_regular_text

    try:
        raw = tomllib.loads(read_regular_text(config_path, limit=1 << 20))
    except (FileRefused, OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError([ConfigIssue("", f"cannot read the file: {exc}")], str(config_path)) from None
    for key in OUTSIDE:
        raw.pop(key, None)
    raw.setdefault("loop", {})["clock"] = "virtual"
    raw["driver"] = [
        {
            "type": "replay",
            "name": "replay",
            "joints": ["*"],
            "devices": list(raw.get("devices", {})),
            "options": {"recording": str(recording.resolve())},
        }
    ]
    config = parse_config(raw, base_dir=config_path.resolve().parent, path=config_path)
    rate = rec.info.get("rate_hz")
    if rate is not None and abs(float(rate) - config.loop.rate_hz) > 1e-9:
        raise ConfigError(
            [ConfigIssue("loop.rate_hz", f"{config.loop.rate_hz:g} Hz, but the recording ran at {float(rate):g} Hz")],
            str(config_path),
        )
    return config


async def run_replay(config: Any, rec: Recording) -> ReplayResult:
    """Run the controller on the recorded state for every recorded tick and compare commands."""
    from ..core.loop import ControlLoop
    from ..core.ticker import VirtualTickSource

    recorded = rec["/joint_commands"]
    extra = rec.series.get("/joint_commands/extra")
    ticks = np.asarray(recorded.tick, dtype=np.int64)
    last = int(ticks[-1])
    loop = ControlLoop(config, tick_source=VirtualTickSource())
    robot = loop.robot
    rows = {name: getattr(robot.command, name) for name, _ in COMMAND_FIELDS}
    replayed = {name: np.zeros((last + 1, robot.dof), dtype=row.dtype) for name, row in rows.items()}

    def capture(_: object) -> None:  # at the end of each tick, as the recorder copied them
        k = robot.clock.tick
        for name, row in rows.items():
            replayed[name][k] = row

    await loop.activate()
    try:
        capture(None)  # tick 0: the commands activation left, as the recorder's tick 0
        loop.add_publisher(capture)
        await loop.run(ticks=last)
    finally:
        await loop.deactivate()
    names = list(rec.joint_names) or list(recorded.messages[0].name)
    columns = [names.index(j) for j in robot.joint_names]
    differ = np.zeros(len(ticks), dtype=bool)
    compared: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, topic in COMMAND_FIELDS:
        series = recorded if topic == "/joint_commands" else extra
        if series is None or len(series) != len(ticks):
            continue
        want = np.ascontiguousarray(series[name][:, columns], dtype=replayed[name].dtype)
        got = replayed[name][ticks]
        compared[name] = (want, got)
        differ |= (want.view(np.uint8) != got.view(np.uint8)).reshape(len(ticks), -1).any(axis=1)
    result = ReplayResult(len(ticks), [int(t) for t in ticks[differ]])
    if result.differing:
        i = int(np.flatnonzero(differ)[0])
        for name, (want, got) in compared.items():
            for j in range(robot.dof):
                if want[i, j].tobytes() != got[i, j].tobytes():
                    result.first.append(
                        {
                            "field": name,
                            "joint": robot.joint_names[j],
                            "recorded": want[i, j].item(),
                            "replayed": got[i, j].item(),
                        }
                    )
    result.missing = int(getattr(loop.slots[0].driver, "missing", 0))
    return result


def format_result(path: Path, config: Path, result: ReplayResult) -> str:
    lines = [f"replay {path} with {config}: {result.ticks} ticks compared"]
    if result.missing:
        lines.append(f"  {result.missing} ticks missing from the recording: the state of the tick before was kept")
    if not result.differing:
        lines.append("  0 ticks differ: the commands are bit-identical")
        return "\n".join(lines)
    lines.append(f"  {len(result.differing)} ticks differ; the first is tick {result.differing[0]}:")
    for d in result.first[:12]:
        lines.append(f"    {d['field']:<12} {d['joint']:<20} recorded {d['recorded']!r:<24} replayed {d['replayed']!r}")
    if len(result.first) > 12:
        lines.append(f"    ... and {len(result.first) - 12} more")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    """Exit status: 0 every tick's commands equal, 1 some differ, 2 bad usage, file or config."""
    p = argparse.ArgumentParser(
        prog="python -m aiohal replay",
        description="Run a config's controller in lockstep on a recording's measured state and compare its "
        "commands with the recorded ones, tick by tick.",
    )
    p.add_argument("recording", type=Path, help="an MCAP file or a rosbag2 directory")
    p.add_argument("--config", type=Path, required=True, help="the robot config whose controller to run")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    args = p.parse_args(argv)
    try:
        rec = load(args.recording)
        if "/joint_commands" not in rec or not len(rec["/joint_commands"]):
            raise ValueError(f"{args.recording}: no /joint_commands recorded")
        config = replay_config(args.config, args.recording, rec)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (OSError, ValueError, ImportError, AiohalError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = asyncio.run(run_replay(config, rec))
    print(json.dumps(result.as_dict(), indent=2) if args.json else format_result(args.recording, args.config, result))
    return 1 if result.differing else 0
