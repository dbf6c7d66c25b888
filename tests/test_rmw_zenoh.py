"""rmw_zenoh's names and wire formats, against the examples of rmw_zenoh's design document
(ros2/rmw_zenoh, docs/design.md, the demo_nodes_cpp talker and add_two_ints server)."""

from __future__ import annotations

import pytest
from conftest import require_module

from aiohal.outside import rmw_zenoh as rmw

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_key_expressions_and_tokens_are_those_of_the_design_document():
    assert rmw.data_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    talker = rmw.Node(2, "8b20917502ee955ac4476e0266340d5c", "/", "talker")
    assert talker.token() == "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%/talker"
    token = talker.endpoint_token(10, rmw.PUBLISHER, "/chatter", "std_msgs/msg/String", STRING_HASH, rmw.Qos(depth=7))
    assert token == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
    )
    assert rmw.dds_type("example_interfaces/srv/AddTwoInts") == "example_interfaces::srv::dds_::AddTwoInts_"
    arm = rmw.Node(0, "ab", "/lab/arm", "aiohal")
    assert arm.qualify("joint_states") == "/lab/arm/joint_states" and arm.qualify("/diagnostics") == "/diagnostics"
    assert arm.token().endswith("/NN/%/%lab%arm/aiohal")


def test_qos_fields_left_empty_where_they_are_rmw_zenohs_default():
    assert rmw.VOLATILE.token_text() == "::,10:,:,:,,"  # reliable, volatile, keep last 10
    assert rmw.LATCHED.token_text() == ":1:,1:,:,:,,"  # transient local, depth 1
    assert rmw.Qos(reliable=False, depth=rmw.DEFAULT_DEPTH).token_text() == "2::,:,:,:,,"


def test_attachment_round_trip_and_malformed_ones_refused():
    gid = bytes(range(16))
    data = rmw.attachment(7, 1_700_000_000_000_000_000, gid)
    assert len(data) == 33 and data[16] == 16  # seq, time, GID length, GID
    assert rmw.read_attachment(data) == (7, 1_700_000_000_000_000_000, gid)
    with pytest.raises(ValueError):
        rmw.read_attachment(data[:-1])
    with pytest.raises(ValueError):
        rmw.read_attachment(data[:16] + b"\x08" + data[17:])


def test_gid_is_16_bytes_of_the_token_hash():
    require_module("xxhash")
    token = "@ros2_lv/0/ab/0/0/NN/%/%/n"
    assert len(rmw.gid(token)) == 16 and rmw.gid(token) == rmw.gid(token) != rmw.gid(token + "x")
