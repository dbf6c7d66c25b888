"""Safety: the levels and their table (:mod:`.levels`), the supervisor that keeps the robot
within them (:mod:`.supervisor`), the watchdog process outside the control process
(:mod:`.watchdog`), the stall thread (:mod:`.stall`) and workspace limits (:mod:`.workspace`).

The names most code needs are here; the supervisor is imported from its module by the loop.
"""

from .levels import (
    TRANSITIONS,
    BoxSection,
    FaultRecord,
    SafetyEvent,
    SafetyLevel,
    SafetyMachine,
    SafetyRequestExpired,
    SafetyRequestRefused,
    SafetySection,
    SphereSection,
    Transition,
    WorkspaceSection,
)

__all__ = [
    "TRANSITIONS",
    "BoxSection",
    "FaultRecord",
    "SafetyEvent",
    "SafetyLevel",
    "SafetyMachine",
    "SafetyRequestExpired",
    "SafetyRequestRefused",
    "SafetySection",
    "SphereSection",
    "Transition",
    "WorkspaceSection",
]
