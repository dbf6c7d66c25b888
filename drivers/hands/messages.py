"""The two messages between the ``nrt_hand`` driver and the hand service (fixed layouts)."""

from __future__ import annotations

from aiohal.pipe import Message


class HandCommandMsg(Message):
    """Fast side -> hand: grasp target and limits, each 0..1."""

    TYPE = 10
    FIELDS = (("grasp", "d"), ("speed", "d"), ("force", "d"))
    # the fields' values, set per instance by Message
    grasp: float
    speed: float
    force: float


class HandStateMsg(Message):
    """Hand -> fast side: the measured state and the seq of the command it acts on
    (``command_seq``, 0xFFFFFFFF before the first)."""

    TYPE = 11
    FIELDS = (
        ("position", "d"),
        ("effort", "d"),
        ("object_detected", "?"),
        ("ready", "?"),
        ("fault", "H"),
        ("command_seq", "I"),
    )
    position: float
    effort: float
    object_detected: bool
    ready: bool
    fault: int
    command_seq: int
