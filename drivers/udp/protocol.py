"""The joint-board wire format (docs/udp.md): one datagram per board per tick each way.

Every datagram is a 40-byte header and a fixed array of per-joint records, little-endian:

    off size field
      0   4  magic     b"AHJB"
      4   4  crc32     zlib.crc32 of bytes [8, end)
      8   1  version   1
      9   1  kind      COMMAND, STATE, ESTOP, RESET
     10   1  count     joint records that follow
     11   1  flags     bit 0: ``mac`` holds an HMAC
     12   2  board     board id
     14   2  reserved  0
     16   4  seq       the sender's sequence number, +1 per datagram sent, wraps
     20   4  ack       the last ``seq`` received from the other side (the command a state answers)
     24  16  mac       HMAC-SHA256 of bytes [8, end) with this field zeroed, first 16 bytes; else 0
     40   .  records   COMMAND: 24 bytes per joint; STATE: 20 bytes per joint; ESTOP, RESET: none

The records are numpy structured dtypes, so both ends fill and read a whole board (or every
board, through a 2-D array of datagrams) with array operations instead of a loop per joint.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
import zlib
from enum import IntEnum
from typing import NamedTuple

import numpy as np

MAGIC = int.from_bytes(b"AHJB", "little")
VERSION = 1
HEADER = struct.Struct("<IIBBBBHHII16s")
HEADER_SIZE = HEADER.size  # 40
MAC_OFFSET, MAC_SIZE = 24, 16
CRC_START = 8  # the CRC and the MAC cover everything after magic and crc
FLAG_MAC = 0x01
MAX_JOINTS = 48  # per board: 40 + 48·24 = 1192 bytes, one datagram within a 1500-byte MTU
ZERO_MAC = bytes(MAC_SIZE)


class Kind(IntEnum):
    COMMAND = 1  # master -> board: one command record per joint
    STATE = 2  # board -> master: one state record per joint, ``ack`` = the command it answers
    ESTOP = 3  # master -> board: stop now, latched until RESET; the board answers with STATE
    RESET = 4  # master -> board: clear the e-stop and the faults; the board answers with STATE


class BoardFault(IntEnum):
    """Bits of a joint's ``fault`` in a STATE record."""

    ESTOP = 1 << 0  # the board is e-stopped (latched until RESET)
    WATCHDOG = 1 << 1  # no command for the board's watchdog time: it stopped the joint
    OVER_TEMPERATURE = 1 << 2
    POSITION_LIMIT = 1 << 3
    DRIVE = 1 << 4  # the power stage reports a fault


#: Joint command record: the mode (aiohal.robot.Mode values), the targets and the gains.
COMMAND_RECORD = np.dtype(
    [
        ("mode", "<u1"),
        ("reserved", "<u1", (3,)),
        ("position", "<f4"),
        ("velocity", "<f4"),
        ("effort", "<f4"),
        ("stiffness", "<f4"),
        ("damping", "<f4"),
    ]
)
#: Joint state record: the fault bits, the mode the board applies, the measurements.
STATE_RECORD = np.dtype(
    [
        ("fault", "<u2"),
        ("mode", "<u1"),
        ("reserved", "<u1"),
        ("position", "<f4"),
        ("velocity", "<f4"),
        ("effort", "<f4"),
        ("temperature", "<f4"),
    ]
)
RECORD_SIZE = {Kind.COMMAND: COMMAND_RECORD.itemsize, Kind.STATE: STATE_RECORD.itemsize, Kind.ESTOP: 0, Kind.RESET: 0}
assert COMMAND_RECORD.itemsize == 24 and STATE_RECORD.itemsize == 20 and HEADER_SIZE == 40


class ProtocolError(ValueError):
    """A datagram that is not a valid one of this protocol; ``reason`` names the class."""

    def __init__(self, reason: str, detail: str = "") -> None:
        self.reason = reason
        super().__init__(f"{reason}: {detail}" if detail else reason)


class Header(NamedTuple):
    kind: int
    count: int  # type: ignore[assignment]  # the field shadows tuple.count, which no caller uses
    flags: int
    board: int
    seq: int
    ack: int


def datagram_size(kind: int, count: int) -> int:
    return HEADER_SIZE + RECORD_SIZE[Kind(kind)] * count


def seal(buf, size: int, key: bytes | None) -> None:
    """Write the MAC (with a key) and the CRC of the datagram in ``buf[:size]``, in place.

    The header's flags must already say whether a MAC is present."""
    mv = memoryview(buf)
    seal_parts(mv[:HEADER_SIZE], mv[HEADER_SIZE:size], key)


def seal_parts(head, body, key: bytes | None) -> None:
    """``seal`` for a datagram sent as two buffers (a board's header, its run of records in
    the driver's array of every record): the CRC and the MAC run over both, nothing is joined."""
    if key is not None:
        head[MAC_OFFSET : MAC_OFFSET + MAC_SIZE] = ZERO_MAC
        mac = hmac.new(key, head[CRC_START:], "sha256")
        mac.update(body)
        head[MAC_OFFSET : MAC_OFFSET + MAC_SIZE] = mac.digest()[:MAC_SIZE]
    struct.pack_into("<I", head, 4, zlib.crc32(body, zlib.crc32(head[CRC_START:])))


def encode(
    kind: int, board: int, seq: int, ack: int, records: np.ndarray | None = None, key: bytes | None = None
) -> bytearray:
    """One whole datagram (allocates: for tests, tools and the simulator's set-up)."""
    count = 0 if records is None else len(records)
    size = datagram_size(kind, count)
    buf = bytearray(size)
    HEADER.pack_into(
        buf,
        0,
        MAGIC,
        0,
        VERSION,
        kind,
        count,
        FLAG_MAC if key is not None else 0,
        board,
        0,
        seq & 0xFFFFFFFF,
        ack & 0xFFFFFFFF,
        ZERO_MAC,
    )
    if records is not None and count:
        buf[HEADER_SIZE:] = records.tobytes()
    seal(buf, size, key)
    return buf


def check(data, size: int, key: bytes | None) -> Header:
    """The header of a valid datagram ``data[:size]``, or ProtocolError naming what is wrong.

    Order: size, magic, CRC, version, kind, record count against the size, then the MAC
    (``unauthenticated``): a corrupted datagram is ``malformed``, a well-formed one without
    the right MAC is ``unauthenticated``."""
    if size < HEADER_SIZE:
        raise ProtocolError("malformed", f"{size} bytes, shorter than the {HEADER_SIZE}-byte header")
    magic, crc, version, kind, count, flags, board, _reserved, seq, ack, mac = HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise ProtocolError("malformed", f"magic 0x{magic:08x}")
    mv = memoryview(data)[:size]
    if zlib.crc32(mv[CRC_START:]) != crc:
        raise ProtocolError("malformed", "CRC mismatch")
    if version != VERSION:
        raise ProtocolError("malformed", f"version {version}")
    if kind not in RECORD_SIZE:
        raise ProtocolError("malformed", f"kind {kind}")
    if size != HEADER_SIZE + RECORD_SIZE[kind] * count:
        raise ProtocolError("malformed", f"{size} bytes for {count} records of kind {kind}")
    if key is not None:
        if not flags & FLAG_MAC:
            raise ProtocolError("unauthenticated", "no MAC")
        scratch = bytearray(mv[CRC_START:])
        scratch[MAC_OFFSET - CRC_START : MAC_OFFSET - CRC_START + MAC_SIZE] = ZERO_MAC
        expected = hmac.digest(key, scratch, "sha256")[:MAC_SIZE]
        if not hmac.compare_digest(expected, mac):
            raise ProtocolError("unauthenticated", "wrong MAC")
    elif flags & FLAG_MAC:
        raise ProtocolError("unauthenticated", "a MAC, but no key is configured")
    return Header(kind, count, flags, board, seq, ack)


def decode(data, key: bytes | None = None) -> tuple[Header, np.ndarray | None]:
    """Header and records (a copy) of a whole datagram, or ProtocolError."""
    size = len(data)
    head = check(data, size, key)
    if head.kind in (Kind.COMMAND, Kind.STATE):
        dtype = COMMAND_RECORD if head.kind == Kind.COMMAND else STATE_RECORD
        return head, np.frombuffer(bytes(data), dtype=dtype, count=head.count, offset=HEADER_SIZE).copy()
    return head, None


def seq_newer(a: int, b: int) -> int:
    """a - b of two 32-bit sequence numbers across the wrap (positive: a is newer)."""
    d = (a - b) & 0xFFFFFFFF
    return d - (1 << 32) if d >= 1 << 31 else d


def key_bytes(key: str | None) -> bytes | None:
    """The shared key of a config (hex, at least 16 bytes) as bytes."""
    if key is None:
        return None
    return bytes.fromhex(key)


def key_digest(key: bytes) -> str:
    """A short fingerprint of a key for logs and reports (never the key)."""
    return hashlib.sha256(key).hexdigest()[:8]
