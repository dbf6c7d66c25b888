"""aiohal.ros2: the Jazzy store with aiohal_msgs, schemas, RIHS01 hashes, CDR both ways."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest
from conftest import require_module

require_module("rosbags")
mcap_ros2_dynamic = require_module("mcap_ros2._dynamic")

from aiohal import ros2

AIOHAL_TYPES = sorted(
    f"aiohal_msgs/msg/{e.name.removesuffix('.msg')}"
    for e in resources.files("aiohal.ros2").joinpath("msg").iterdir()
    if e.name.endswith(".msg")
)


def test_every_shipped_msg_file_is_a_registered_type():
    assert len(AIOHAL_TYPES) >= 8
    for name in AIOHAL_TYPES:
        assert ros2.message_type(name).__msgtype__ == name
        assert ros2.type_hash(name).startswith("RIHS01_")


def test_joint_state_hash_is_the_one_ros2_jazzy_publishes():
    # the hash `ros2 topic info /joint_states --verbose` prints on Jazzy
    assert ros2.type_hash("sensor_msgs/msg/JointState") == (
        "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
    )


def test_schema_text_carries_the_types_it_uses():
    text = ros2.schema_text("sensor_msgs/msg/JointState")
    assert text.splitlines()[0] == "std_msgs/Header header"
    assert "MSG: std_msgs/Header" in text and "MSG: builtin_interfaces/Time" in text


def test_cdr_round_trip_and_another_decoder_agree():
    msg = ros2.message_type("sensor_msgs/msg/JointState")(
        header=ros2.header(1_700_000_000_123_456_789, "base"),
        name=["a", "bc"],
        position=np.array([0.5, -1.0]),
        velocity=np.array([1.0, 2.0]),
        effort=np.array([3.0, 4.0]),
    )
    data = ros2.serialize(msg)
    assert data[:4] == b"\x00\x01\x00\x00"  # little-endian CDR
    back = ros2.deserialize(data, "sensor_msgs/msg/JointState")
    assert back.name == ["a", "bc"] and back.position.tolist() == [0.5, -1.0]
    assert (back.header.stamp.sec, back.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    decode = mcap_ros2_dynamic.generate_dynamic(
        "sensor_msgs/msg/JointState", ros2.schema_text("sensor_msgs/msg/JointState")
    )["sensor_msgs/msg/JointState"]
    other = decode(data)
    assert other.name == ["a", "bc"] and list(other.effort) == [3.0, 4.0]
    assert other.header.frame_id == "base"


@pytest.mark.parametrize("name", AIOHAL_TYPES)
def test_aiohal_types_decode_with_another_decoder(name):
    msg_class = ros2.message_type(name)
    defaults = {"header": ros2.header(42)} if "header" in msg_class.__dataclass_fields__ else {}
    fields = {}
    for field in msg_class.__dataclass_fields__:
        if field == "__msgtype__" or field in defaults or field.isupper():
            continue
        fields[field] = _zero(name, field)
    data = ros2.serialize(msg_class(**defaults, **fields))
    decode = mcap_ros2_dynamic.generate_dynamic(name, ros2.schema_text(name))[name]
    decoded = decode(data)
    if defaults:
        assert decoded.header.stamp.nanosec == 42


def _zero(name: str, field: str):
    """A zero value of the field's type, from the store's own field definitions."""
    store = ros2.typestore()
    _, fields = store.fielddefs[name]
    (kind, detail) = dict(fields)[field]
    from rosbags.interfaces import Nodetype

    if kind == Nodetype.BASE:
        return "" if detail[0] == "string" else (False if detail[0] == "bool" else 0)
    if kind == Nodetype.SEQUENCE:
        inner = detail[0]
        if inner[1][0] == "string":
            return ["x"]
        dtype = {"float64": np.float64, "uint32": np.uint32, "int8": np.int8}[inner[1][0]]
        return np.zeros(1, dtype=dtype)
    raise AssertionError(f"{name}.{field}: no zero for {kind}")


def test_unknown_type_is_named():
    with pytest.raises(KeyError, match="no_pkg/msg/Nope"):
        ros2.message_type("no_pkg/msg/Nope")
