"""ROS 2 messages without ROS 2: the Jazzy type store, aiohal's own ``aiohal_msgs``, and CDR.

Recordings, the live view and the Zenoh bridge speak standard ROS 2 messages
(``sensor_msgs/msg/JointState``, ``sensor_msgs/msg/Imu``, ...) wherever one fits, and
``aiohal_msgs`` (the ``.msg`` files in ``msg/``) where none does. The type store, the CDR
encoding, the schema texts and the RIHS01 type hashes all come from ``rosbags`` (pure
Python), so what aiohal writes is what ROS 2 tools read. Needs the extra ``record``,
``foxglove`` or ``zenoh`` (each installs rosbags).
"""

from __future__ import annotations

from .messages import (
    PACKAGE,
    deserialize,
    header,
    message_type,
    schema_text,
    serialize,
    stamp,
    type_hash,
    typestore,
)

__all__ = [
    "PACKAGE",
    "deserialize",
    "header",
    "message_type",
    "schema_text",
    "serialize",
    "stamp",
    "type_hash",
    "typestore",
]
