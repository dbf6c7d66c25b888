"""The ``[record]`` section of a robot config: what a recording keeps and how it is written.

Kept apart from the recorder so that validating a config never imports mcap.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import AfterValidator, Field, ValidationInfo

from ..hal import Options

#: the per-tick channels; ``decimate`` keys
TICK_CHANNELS = ("joint_state", "joint_command", "imu", "force_torque", "hand", "device_faults", "timing", "safety")
Channel = Literal["joint_state", "joint_command", "imu", "force_torque", "hand", "device_faults", "timing", "safety"]


def _relative_to_config(value: Path | None, info: ValidationInfo) -> Path | None:
    base = (info.context or {}).get("base_dir")
    if value is not None and base is not None and not value.is_absolute():
        return (Path(base) / value).resolve()
    return value


class RecordSection(Options):
    path: Annotated[Path | None, AfterValidator(_relative_to_config)] = Field(
        None,
        description="Record every run of this config to this MCAP file, or to this rosbag2 directory if the "
        "name does not end in .mcap (the CLI's --record overrides it).",
    )
    decimate: dict[Channel, Annotated[int, Field(ge=1, le=1_000_000)]] = Field(
        default_factory=dict,
        description="Keep every n-th tick of a channel (default 1: every tick), e.g. { imu = 10 }.",
    )
    flush_ms: float = Field(
        250.0,
        ge=10,
        le=10_000,
        description="Close the chunk in progress and write it to the file at least this often: how "
        "far behind the file can be when the process is killed.",
    )
    buffer_ticks: int = Field(
        4096,
        ge=64,
        le=1 << 20,
        description="Ticks the ring buffer between the tick and the writer holds (a power of 2 is used); "
        "when the writer is that far behind, ticks are dropped and counted.",
    )
    compression: Literal["zstd", "lz4", "none"] = Field("zstd", description="Compression of the chunks.")
    health_hz: float = Field(
        10.0, gt=0, le=100, description="How often drivers' health and the controller's metrics are recorded."
    )
    live_decimate: int = Field(
        10,
        ge=1,
        le=1_000_000,
        description="With --foxglove: send every n-th tick of each channel live (default: 100 Hz at 1 kHz).",
    )
