"""The type store (Jazzy + ``aiohal_msgs``) and what is asked of it: types, schemas, hashes, CDR.

One store per process, built on first use: rosbags parses the ``.msg`` files of
``aiohal_msgs`` once and registers them beside the standard types.
"""

from __future__ import annotations

import functools
import logging
from importlib import resources
from typing import Any

from ..errors import MissingDependencyError

log = logging.getLogger(__name__)

#: the package of aiohal's own message types (their ``.msg`` files are in ``aiohal/ros2/msg``)
PACKAGE = "aiohal_msgs"


@functools.cache
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy type store with the ``aiohal_msgs`` types registered."""
    try:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError as exc:
        raise MissingDependencyError(f"ROS 2 messages need rosbags: pip install 'aiohal[record]' ({exc})") from None
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for entry in sorted(resources.files(__package__).joinpath("msg").iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".msg"):
            name = f"{PACKAGE}/msg/{entry.name.removesuffix('.msg')}"
            types.update(get_types_from_msg(entry.read_text(encoding="utf-8"), name))
    store.register(types)
    log.debug("ROS 2 type store: Jazzy and %d %s types", len(types), PACKAGE)
    return store


def message_type(name: str) -> Any:
    """The message class of ``name`` (e.g. ``"sensor_msgs/msg/JointState"``); its fields are
    keyword arguments, sequences of numbers numpy arrays."""
    try:
        return typestore().types[name]
    except KeyError:
        raise KeyError(f"unknown ROS 2 message type {name!r}") from None


def schema_text(name: str) -> str:
    """The ``ros2msg`` schema of ``name`` as MCAP and Foxglove want it: its definition, then each
    type it uses after a ``MSG: package/Type`` separator line."""
    text, _ = typestore().generate_msgdef(name, ros_version=2)
    return str(text)


def type_hash(name: str) -> str:
    """The RIHS01 type hash of ``name`` (``RIHS01_<64 hex>``), as ROS 2 Jazzy computes it."""
    return str(typestore().hash_rihs01(name))


def serialize(msg: Any) -> bytes:
    """``msg`` in little-endian CDR, with its 4-byte encapsulation header."""
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def deserialize(data: bytes | memoryview, name: str) -> Any:
    """A CDR message of type ``name`` back into its message class."""
    return typestore().deserialize_cdr(data, name)


def stamp(ns: int) -> Any:
    """A ``builtin_interfaces/msg/Time`` for a time in ns."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return message_type("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def header(ns: int, frame_id: str = "") -> Any:
    """A ``std_msgs/msg/Header`` stamped ``ns``."""
    return message_type("std_msgs/msg/Header")(stamp=stamp(ns), frame_id=frame_id)
