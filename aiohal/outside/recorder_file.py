"""Where a recording goes: one MCAP file, or a rosbag2 directory (that MCAP file + metadata.yaml).

The MCAP file is what ROS 2's own MCAP storage writes: profile ``ros2``, one ``ros2msg``
schema per type (the text with its dependencies, from :mod:`aiohal.ros2`), ``cdr`` channels
whose metadata carry the offered QoS (YAML) and the RIHS01 type hash. A path ending in
``.mcap`` is a file; any other path is a rosbag2 directory, created, holding
``<name>_0.mcap`` and, once the recording is finished, ``metadata.yaml`` (bag format 9), so
that ``ros2 bag info/play`` and rosbags open it. mcap's writer closes a chunk and writes it
every ``flush_ms`` (the recorder calls :meth:`flush`), so a killed run keeps what was flushed.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from .. import ros2

log = logging.getLogger(__name__)

#: rosbag2's spelling of an infinite duration in a QoS profile
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


def qos_profile(latched: bool) -> dict[str, Any]:
    """The QoS a topic is offered with, as rosbag2 writes it: reliable; a latched topic
    transient-local with its last message kept, so that ``ros2 bag play`` latches it too."""
    return {
        "history": "keep_last",
        "depth": 1 if latched else 10,
        "reliability": "reliable",
        "durability": "transient_local" if latched else "volatile",
        "deadline": _INFINITE,
        "lifespan": _INFINITE,
        "liveliness": "automatic",
        "liveliness_lease_duration": _INFINITE,
        "avoid_ros_namespace_conventions": False,
    }


def is_bag_path(path: Path) -> bool:
    """A path not ending in ``.mcap`` names a rosbag2 directory."""
    return path.suffix != ".mcap"


class RecordingFile:
    """An MCAP file being written, in a rosbag2 directory when ``path`` is not a ``.mcap`` file."""

    def __init__(self, path: Path, compression: str) -> None:
        from mcap.writer import CompressionType, Writer  # the extra 'record'

        self.path = path
        self.bag_dir: Path | None = None
        if is_bag_path(path):
            path.mkdir()  # a new directory: an existing one is refused
            self.bag_dir = path
            self.mcap_path = path / f"{path.name}_0.mcap"
        else:
            self.mcap_path = path
        self._file = open(self.mcap_path, "wb")  # noqa: SIM115 - open until finish()
        # chunks are closed by time (the recorder's flush), not by size: the size bound is a backstop
        self._writer = Writer(
            self._file,
            chunk_size=64 << 20,
            compression={"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[
                compression
            ],
        )
        self._writer.start(profile="ros2", library="aiohal")
        self._schemas: dict[str, int] = {}
        #: channel id -> (topic, type, latched)
        self._channels: dict[int, tuple[str, str, bool]] = {}
        self._counts: dict[int, int] = {}
        self._first_ns: int | None = None
        self._last_ns = 0
        self.custom_data: dict[str, str] = {}

    def add_channel(self, topic: str, msgtype: str, latched: bool = False) -> int:
        """Register a topic of ROS 2 type ``msgtype``; returns its channel id."""
        schema = self._schemas.get(msgtype)
        if schema is None:
            schema = self._writer.register_schema(msgtype, "ros2msg", ros2.schema_text(msgtype).encode())
            self._schemas[msgtype] = schema
        metadata = {
            "offered_qos_profiles": json.dumps([qos_profile(latched)]),  # YAML flow style
            "topic_type_hash": ros2.type_hash(msgtype),
        }
        cid = int(self._writer.register_channel(topic, "cdr", schema, metadata))
        self._channels[cid] = (topic, msgtype, latched)
        self._counts[cid] = 0
        return cid

    def add_message(self, channel: int, log_time_ns: int, data: bytes, sequence: int = 0) -> None:
        self._writer.add_message(channel, log_time_ns, data, log_time_ns, sequence & 0xFFFFFFFF)
        self._counts[channel] += 1
        if self._first_ns is None:
            self._first_ns = log_time_ns
        self._first_ns = min(self._first_ns, log_time_ns)
        self._last_ns = max(self._last_ns, log_time_ns)

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        """A metadata record in the MCAP file, and the bag's ``custom_data`` in a rosbag2 directory."""
        self._writer.add_metadata(name, values)
        self.custom_data.update({f"{name}.{k}": v for k, v in values.items()})

    def flush(self) -> None:
        """Close the chunk in progress and write it to the file."""
        self._writer.flush()
        self._file.flush()

    def finish(self, complete: bool = True) -> None:
        """Write the MCAP summary (when ``complete``), close the file, and write the bag's metadata."""
        try:
            if complete:
                self._writer.finish()
        finally:
            self._file.close()
        if self.bag_dir is not None:
            (self.bag_dir / "metadata.yaml").write_text(self._bag_metadata(), encoding="utf-8")

    @property
    def size(self) -> int:
        return sum(f.stat().st_size for f in (self.mcap_path,) if f.exists())

    def _bag_metadata(self) -> str:
        """rosbag2's metadata.yaml (bag format 9), as JSON: YAML reads it as its flow style."""
        start = self._first_ns or 0
        duration = max(0, self._last_ns - start)
        count = sum(self._counts.values())
        topics = [
            {
                "topic_metadata": {
                    "name": topic,
                    "type": msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": [qos_profile(latched)],
                    "type_description_hash": ros2.type_hash(msgtype),
                },
                "message_count": self._counts[cid],
            }
            for cid, (topic, msgtype, latched) in self._channels.items()
        ]
        info = {
            "version": 9,
            "storage_identifier": "mcap",
            "relative_file_paths": [self.mcap_path.name],
            "starting_time": {"nanoseconds_since_epoch": start},
            "duration": {"nanoseconds": duration},
            "message_count": count,
            "topics_with_message_count": topics,
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": self.mcap_path.name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": {"nanoseconds": duration},
                    "message_count": count,
                }
            ],
            "custom_data": self.custom_data,
            "ros_distro": "jazzy",
        }
        return json.dumps({"rosbag2_bagfile_information": info}, indent=2) + "\n"
