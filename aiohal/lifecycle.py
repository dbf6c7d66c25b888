"""The lifecycle's words: the loop's states, each driver's status, and the slot that holds a
driver with its status and timing counters (shared by the loop and the safety supervisor)."""

from __future__ import annotations

from enum import StrEnum

from .hal import Driver


class LoopState(StrEnum):
    """The loop's lifecycle: ``created`` -> ``configured`` (drivers and controller built) ->
    ``active`` (drivers open, controller started) <-> ``running`` (inside :meth:`ControlLoop.run`)
    -> ``closed``. The values are the words the report and the errors use."""

    CREATED = "created"
    CONFIGURED = "configured"
    ACTIVE = "active"
    RUNNING = "running"
    CLOSED = "closed"


class DriverStatus(StrEnum):
    """A driver's lifecycle in the loop: ``created`` -> ``open`` -> ``closed``; ``failed``
    once it raised (isolated, never read or written again); ``abandoned`` when its
    ``close()`` did not return in time (after its estop)."""

    CREATED = "created"
    OPEN = "open"
    FAILED = "failed"
    CLOSED = "closed"
    ABANDONED = "abandoned"


class DriverSlot:
    """A driver with its status and timing counters."""

    __slots__ = (
        "driver",
        "name",
        "type",
        "status",
        "read_ns",
        "write_ns",
        "max_read_ns",
        "max_write_ns",
        "every",
        "max_age",
    )

    def __init__(self, driver: Driver, type_name: str, every: int = 1, max_age: int = 0) -> None:
        self.driver = driver
        self.every = every  # read and written on every n-th tick ([[driver]] every)
        self.max_age = max_age  # feedback older than this (ticks) is stale: max_feedback_age at its rate
        self.name = driver.name
        self.type = type_name
        self.status = DriverStatus.CREATED
        self.read_ns = 0
        self.write_ns = 0
        self.max_read_ns = 0
        self.max_write_ns = 0
