"""What every NRT hand backend offers: blocking calls, run by the hand service's slow loop."""

from __future__ import annotations

import abc
from dataclasses import dataclass

from aiohal.errors import AiohalError

#: Fault codes shared by every backend (a backend's own codes are given above 0x100).
FAULT_NONE = 0
FAULT_NOT_READY = 1  # not activated / still activating
FAULT_COMMUNICATION = 2  # the link to the hand failed (timeout, connection lost)
FAULT_BACKEND = 3  # the backend raised something else
VENDOR_FAULT_BASE = 0x100  # + the hand's own fault code (e.g. Robotiq gFLT)

FAULT_MEANINGS = {
    FAULT_NONE: "no fault",
    FAULT_NOT_READY: "not activated, or still activating",
    FAULT_COMMUNICATION: "the link to the hand failed",
    FAULT_BACKEND: "the hand's backend failed",
}

#: Robotiq 2F grippers' gFLT (the fault nibble of the status registers), as its manual lists them
ROBOTIQ_GFLT = {
    0x5: "action delayed: the activation must complete first",
    0x7: "the activation bit must be set first",
    0x8: "above its maximum operating temperature",
    0x9: "no communication for at least 1 s",
    0xA: "below its minimum operating voltage",
    0xB: "automatic release in progress",
    0xC: "internal processor fault",
    0xD: "activation fault: check for interference",
    0xE: "overcurrent",
    0xF: "automatic release completed",
}


def describe_fault(code: int, backend: str | None = None) -> str:
    """A fault code with what it means, e.g. ``0x10e (Robotiq gFLT 0xE: overcurrent)``."""
    if code in FAULT_MEANINGS:
        meaning = FAULT_MEANINGS[code]
    elif code >= VENDOR_FAULT_BASE:
        vendor = code - VENDOR_FAULT_BASE
        if backend == "robotiq" and vendor in ROBOTIQ_GFLT:
            meaning = f"Robotiq gFLT {vendor:#X}: {ROBOTIQ_GFLT[vendor]}".replace("0X", "0x")
        else:
            meaning = f"the hand's own fault {vendor:#x}"
    else:
        meaning = "unknown code"
    return f"{code:#x} ({meaning})"


class HandError(AiohalError):
    """A hand backend could not do what was asked; ``code`` is one of the FAULT_* values."""

    def __init__(self, reason: str, code: int = FAULT_BACKEND) -> None:
        super().__init__(reason)
        self.reason = reason
        self.code = code


@dataclass
class HandStatus:
    """A hand's measured state, normalised: 0 = open, 1 = closed; effort 0..1 of its maximum."""

    position: float = 0.0
    effort: float = 0.0
    object_detected: bool = False
    fault: int = FAULT_NONE
    ready: bool = False  # activated and accepting motion commands


class HandBackend(abc.ABC):
    """A gripper reached by blocking I/O. Every call may block; none is ever called on the tick.

    ``command`` takes values already clamped to 0..1: grasp (0 open, 1 closed), speed and
    force as fractions of the hand's maximum.
    """

    @abc.abstractmethod
    def open(self) -> None:
        """Connect and activate; raises ``HandError`` with a reason on failure."""

    @abc.abstractmethod
    def command(self, grasp: float, speed: float, force: float) -> None:
        """Send a grasp target."""

    @abc.abstractmethod
    def read(self) -> HandStatus:
        """Read the hand's state now."""

    def close(self) -> None:
        """Leave the hand safe (stop motion) and release the connection."""
