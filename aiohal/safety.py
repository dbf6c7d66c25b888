"""Safety levels (ordered, as in EEROS) and the record of a fault.

The full safety layer (limits on inputs, watchdog process, re-arm) grows here; the control
loop already enforces the rule that matters most: any fault drops the robot to ``HOLD``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from enum import IntEnum


class SafetyLevel(IntEnum):
    OFF = 0  # drivers closed, nothing commanded
    ESTOP = 1  # every driver's emergency stop was triggered
    HOLD = 2  # controller replaced by hold: joints keep the last commanded position
    RUN = 3  # the configured controller is in charge


@dataclass(frozen=True)
class FaultRecord:
    """Who failed, where, at which tick, and why."""

    source: str  # "driver:<name>", "controller:<type>" or "feedback"
    phase: str  # open, read, write, close, update, start, stop, check
    tick: int
    error: str

    def as_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        return f"{self.source} failed in {self.phase} at tick {self.tick}: {self.error}"
