"""The joint-board wire format: layouts at the documented offsets, round trips, and a parser
that refuses every malformed datagram with ProtocolError (fuzzed with hypothesis)."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.drivers.udp.protocol import (
    COMMAND_RECORD,
    HEADER_SIZE,
    MAGIC,
    STATE_RECORD,
    Kind,
    ProtocolError,
    decode,
    encode,
    seq_newer,
)

KEY = bytes(range(16))


def test_header_fields_sit_at_the_documented_offsets():
    rec = np.zeros(2, dtype=COMMAND_RECORD)
    data = bytes(encode(Kind.COMMAND, 0x1234, 0xA1B2C3D4, 0x01020304, rec, KEY))
    assert len(data) == 40 + 2 * 24
    assert data[0:4] == b"AHJB"
    assert struct.unpack_from("<I", data, 4)[0] == zlib.crc32(data[8:])
    assert (data[8], data[9], data[10], data[11]) == (1, Kind.COMMAND, 2, 1)
    assert struct.unpack_from("<HHII", data, 12) == (0x1234, 0, 0xA1B2C3D4, 0x01020304)
    assert data[24:40] != bytes(16)  # the MAC


def test_record_layouts_are_the_documented_ones():
    assert COMMAND_RECORD.itemsize == 24 and STATE_RECORD.itemsize == 20
    assert [COMMAND_RECORD.fields[f][1] for f in ("mode", "position", "velocity", "effort", "stiffness", "damping")] == [0, 4, 8, 12, 16, 20]
    assert [STATE_RECORD.fields[f][1] for f in ("fault", "mode", "position", "velocity", "effort", "temperature")] == [0, 2, 4, 8, 12, 16]
    rec = np.zeros(1, dtype=STATE_RECORD)
    rec["position"], rec["fault"] = 1.5, 0x11
    data = bytes(encode(Kind.STATE, 1, 1, 1, rec))
    assert struct.unpack_from("<HBBffff", data, HEADER_SIZE)[:4] == (0x11, 0, 0, 1.5)


finite = st.floats(-1e6, 1e6, allow_nan=False, width=32)


@settings(max_examples=200, deadline=None)
@given(kind=st.sampled_from([Kind.COMMAND, Kind.STATE]), n=st.integers(0, 48), board=st.integers(0, 0xFFFF),
       seq=st.integers(0, 0xFFFFFFFF), ack=st.integers(0, 0xFFFFFFFF), keyed=st.booleans(), data=st.data())
def test_round_trip(kind, n, board, seq, ack, keyed, data):
    dtype = COMMAND_RECORD if kind == Kind.COMMAND else STATE_RECORD
    rec = np.zeros(n, dtype=dtype)
    for field in ("position", "velocity", "effort"):
        rec[field] = data.draw(st.lists(finite, min_size=n, max_size=n))
    key = KEY if keyed else None
    head, out = decode(encode(kind, board, seq, ack, rec, key), key)
    assert (head.kind, head.count, head.board, head.seq, head.ack) == (kind, n, board, seq, ack)
    assert out.tobytes() == rec.tobytes()


@settings(max_examples=500, deadline=None)
@given(blob=st.binary(max_size=400), keyed=st.booleans())
def test_any_bytes_are_parsed_or_refused_with_protocol_error(blob, keyed):
    try:
        decode(blob, KEY if keyed else None)
    except ProtocolError as exc:
        assert exc.reason in ("malformed", "unauthenticated")


@settings(max_examples=500, deadline=None)
@given(position=st.integers(0, 40 + 3 * 20 - 1), value=st.integers(1, 255), keyed=st.booleans())
def test_any_changed_byte_is_refused(position, value, keyed):
    key = KEY if keyed else None
    data = bytearray(encode(Kind.STATE, 3, 10, 9, np.zeros(3, dtype=STATE_RECORD), key))
    data[position] ^= value
    with pytest.raises(ProtocolError) as info:
        decode(data, key)
    assert info.value.reason == "malformed"  # the CRC catches a changed byte before the MAC is looked at


@settings(max_examples=300, deadline=None)
@given(prefix=st.integers(0, 40 + 2 * 24 - 1))
def test_a_truncated_datagram_is_malformed(prefix):
    data = bytes(encode(Kind.COMMAND, 1, 1, 1, np.zeros(2, dtype=COMMAND_RECORD)))
    with pytest.raises(ProtocolError, match="malformed"):
        decode(data[:prefix])


def test_a_mac_is_required_and_checked_with_a_key():
    data = bytes(encode(Kind.STATE, 1, 1, 1, np.zeros(1, dtype=STATE_RECORD)))
    with pytest.raises(ProtocolError, match="unauthenticated: no MAC"):
        decode(data, KEY)
    forged = bytes(encode(Kind.STATE, 1, 1, 1, np.zeros(1, dtype=STATE_RECORD), bytes(16)))
    with pytest.raises(ProtocolError, match="unauthenticated: wrong MAC"):
        decode(forged, KEY)
    with pytest.raises(ProtocolError, match="unauthenticated"):
        decode(forged, None)


def test_sequence_numbers_compare_across_the_wrap():
    assert seq_newer(0, 0xFFFFFFFF) == 1
    assert seq_newer(0xFFFFFFFF, 0) == -1
    assert seq_newer(5, 5) == 0
    assert MAGIC.to_bytes(4, "little") == b"AHJB"
