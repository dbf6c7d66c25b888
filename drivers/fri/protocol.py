"""FRI 1.x datagrams as numpy structured dtypes at their byte offsets (docs/fri.md).

The KRC sends a 916-byte measurement (id 0x2006) every cycle; the remote answers each with a
376-byte command (id 0x1005). Little-endian, 32-bit floats, no implicit padding. A field is
read or written in place through the dtype (``msr["msr_jnt_pos"]``), so nothing is packed
by hand and the offsets are checked once (tests/test_fri_protocol.py) against the reference.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

JOINTS = 7  # LBR_MNJ
USER_SIZE = 16  # FRI_USER_SIZE: KRL values per type
MSR_SIZE, CMD_SIZE = 916, 376
MSR_ID, CMD_ID = 0x2006, 0x1005
DEFAULT_PORT = 49938
#: The largest move of the joint set point (rad) one command may ask for, per KRC cycle. A
#: larger step is an "interpolation error": the KRC brakes and falls back to monitor mode.
#: KUKA publishes no figure; this is the simulator's limit and the driver's default
#: (docs/fri.md, "Disturbances").
MAX_STEP = 0.004


#: One field of a datagram: name, numpy format (a scalar, or ``(scalar, count)`` for an
#: array) and byte offset.
_Field = tuple[str, str | tuple[str, int], int]


def _struct(fields: list[_Field], size: int) -> np.dtype:
    names, formats, offsets = zip(*fields, strict=True)
    return np.dtype({"names": list(names), "formats": list(formats), "offsets": list(offsets), "itemsize": size})


_HEAD_AND_KRL: list[_Field] = [
    ("send_seq", "<u2", 0),
    ("refl_seq", "<u2", 2),
    ("packet_size", "<u2", 4),
    ("datagram_id", "<u2", 6),
    ("krl_real", ("<f4", USER_SIZE), 8),
    ("krl_int", ("<i4", USER_SIZE), 72),
    ("krl_bool", "<u2", 136),
    ("krl_fill", "<u2", 138),
]

#: tFriMsrData, KRC -> remote.
MSR = _struct(
    [
        *_HEAD_AND_KRL,
        ("timestamp", "<f4", 140),
        ("state", "<u2", 144),
        ("quality", "<u2", 146),
        ("desired_msr_sample_time", "<f4", 148),
        ("desired_cmd_sample_time", "<f4", 152),
        ("safety_limits", "<f4", 156),
        ("answer_rate", "<f4", 160),
        ("latency", "<f4", 164),
        ("jitter", "<f4", 168),
        ("miss_rate", "<f4", 172),
        ("miss_counter", "<u4", 176),
        ("power", "<u2", 180),
        ("control", "<u2", 182),
        ("error", "<u2", 184),
        ("warning", "<u2", 186),
        ("temperature", ("<f4", JOINTS), 188),
        ("msr_jnt_pos", ("<f4", JOINTS), 216),
        ("msr_cart_pos", ("<f4", 12), 244),
        ("cmd_jnt_pos", ("<f4", JOINTS), 292),
        ("cmd_jnt_pos_fri_offset", ("<f4", JOINTS), 320),
        ("cmd_cart_pos", ("<f4", 12), 348),
        ("cmd_cart_pos_fri_offset", ("<f4", 12), 396),
        ("msr_jnt_trq", ("<f4", JOINTS), 444),
        ("est_ext_jnt_trq", ("<f4", JOINTS), 472),
        ("est_ext_tcp_ft", ("<f4", 6), 500),
        ("jacobian", ("<f4", 42), 524),
        ("mass_matrix", ("<f4", 49), 692),
        ("gravity", ("<f4", JOINTS), 888),
    ],
    MSR_SIZE,
)

#: tFriCmdData, remote -> KRC.
CMD = _struct(
    [
        *_HEAD_AND_KRL,
        ("cmd_flags", "<u4", 140),
        ("jnt_pos", ("<f4", JOINTS), 144),
        ("cart_pos", ("<f4", 12), 172),
        ("add_jnt_trq", ("<f4", JOINTS), 220),
        ("add_tcp_ft", ("<f4", 6), 248),
        ("jnt_stiffness", ("<f4", JOINTS), 272),
        ("jnt_damping", ("<f4", JOINTS), 300),
        ("cart_stiffness", ("<f4", 6), 328),
        ("cart_damping", ("<f4", 6), 352),
    ],
    CMD_SIZE,
)


class State(IntEnum):
    OFF = 0
    MON = 1
    CMD = 2


class Quality(IntEnum):
    UNACCEPTABLE = 0
    BAD = 1
    OK = 2
    PERFECT = 3


class Control(IntEnum):
    OTHER = 0
    POSITION = 1
    CART_IMP = 2
    JNT_IMP = 3


#: KRL ``$stiffness.strategy`` for each control strategy.
STRATEGY = {Control.POSITION: 10, Control.CART_IMP: 20, Control.JNT_IMP: 30}
CONTROL_OF_STRATEGY = {v: k for k, v in STRATEGY.items()}


class Flags:
    JNTPOS = 0x0001
    JNTTRQ = 0x0004
    JNTSTIFF = 0x0010
    JNTDAMP = 0x0020
    CARTPOS = 0x0100
    TCPFT = 0x0400
    CARTSTIFF = 0x1000
    CARTDAMP = 0x2000


#: The command fields each strategy takes (the flag sets the public clients use).
FLAGS = {
    Control.POSITION: Flags.JNTPOS,
    Control.JNT_IMP: Flags.JNTPOS | Flags.JNTTRQ | Flags.JNTSTIFF | Flags.JNTDAMP,
    Control.CART_IMP: Flags.CARTPOS | Flags.TCPFT | Flags.CARTSTIFF | Flags.CARTDAMP,
}


class FriError(ValueError):
    """A datagram that is not the expected FRI datagram: ``reason`` is its class."""

    def __init__(self, reason: str, detail: str) -> None:
        self.reason = reason
        super().__init__(f"{reason}: {detail}")


def check(data, size: int, expected_size: int, expected_id: int) -> None:
    """Size, the header's own size and the datagram id: anything else is ``malformed``."""
    if size != expected_size:
        raise FriError("malformed", f"{size} bytes, expected {expected_size}")
    packet_size = int.from_bytes(data[4:6], "little")
    datagram_id = int.from_bytes(data[6:8], "little")
    if packet_size != expected_size or datagram_id != expected_id:
        raise FriError("malformed", f"packetSize {packet_size}, datagramId 0x{datagram_id:04x}")


def new_msr() -> np.ndarray:
    msr = np.zeros((), dtype=MSR)
    msr["packet_size"], msr["datagram_id"] = MSR_SIZE, MSR_ID
    return msr


def new_cmd() -> np.ndarray:
    cmd = np.zeros((), dtype=CMD)
    cmd["packet_size"], cmd["datagram_id"] = CMD_SIZE, CMD_ID
    return cmd


def seq16_newer(a: int, b: int) -> int:
    """a - b of two 16-bit counters across the wrap (positive: a is newer)."""
    d = (a - b) & 0xFFFF
    return d - 0x10000 if d >= 0x8000 else d
