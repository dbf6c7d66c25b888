"""The lifecycle's words and steps: the loop's states, each driver's status, the slot that holds
a driver with its status and timing counters (shared by the loop and the safety supervisor),
building the drivers and controllers a config names, and bringing the drivers up and down."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from enum import StrEnum
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from .. import plugins
from ..config import mode_issues
from ..errors import ConfigError, ControllerError, DriverError
from ..hal import Controller, Driver

if TYPE_CHECKING:
    from ..config import Config
    from ..robot import DriverEvents, Robot

#: ``record_fault(source, phase, error)``: the loop's (its supervisor's) record of faults
RecordFault = Callable[[str, str, Any], object]


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

    def report(self, ticks: int) -> dict:
        """This driver's part of the run report: status, timing and its own health."""
        try:
            health = self.driver.health()
        except Exception as exc:
            health = {"health_error": str(exc)}
        return {
            "type": self.type,
            "status": self.status.value,
            "joints": len(self.driver.view.joint_names),
            "read_us_mean": round(self.read_ns / ticks / 1e3, 2) if ticks else None,
            "write_us_mean": round(self.write_ns / ticks / 1e3, 2) if ticks else None,
            "read_us_max": round(self.max_read_ns / 1e3, 2),
            "write_us_max": round(self.max_write_ns / 1e3, 2),
            **health,
        }


def build_slots(config: Config, robot: Robot, events_of: Callable[[str, slice], DriverEvents]) -> list[DriverSlot]:
    """One slot per configured driver, built on a view of its joints and devices whose events
    go to ``events_of(name, rows)``; a constructor that raises is a :class:`DriverError`."""
    slots = []
    for dc in config.drivers:
        view = robot.driver_view(dc.joints, dc.devices)
        view.attach(events_of(dc.name, view.rows))
        view.every = dc.every
        try:
            driver = dc.cls(dc.name, view, dc.options)
        except Exception as exc:
            raise DriverError(dc.name, "configure", f"{type(exc).__name__}: {exc}") from exc
        slots.append(DriverSlot(driver, dc.type, dc.every, config.loop.max_feedback_age * dc.every))
    return slots


def check_given_controller(config: Config, given: Controller | None, given_params: Any = None) -> None:
    """A controller given in code, checked as the config checked its own: its command modes
    against the drivers' (a :class:`ConfigError`, before any driver is built)."""
    if given is None:
        return
    params = given_params if given_params is not None else type(given).Params()
    issues = mode_issues(type(given), params, config.drivers)
    if issues:
        raise ConfigError(issues, str(config.path) if config.path else None)


def build_controllers(
    config: Config, robot: Robot, given: Controller | None = None, given_params: Any = None
) -> tuple[Controller, str, Controller]:
    """The controller (``given``, or the configured one) and ``hold``, configured on the
    robot's controller view: ``(controller, its type name, hold)``."""
    view = robot.controller_view()
    hold_cls = cast(type[Controller], plugins.load("controller", "hold"))
    hold = hold_cls()
    hold.configure(view, hold_cls.Params())
    controller: Controller
    if given is not None:
        controller, controller_type = given, type(given).__name__
        params = given_params if given_params is not None else type(given).Params()
    else:
        controller, controller_type = config.controller.cls(), config.controller.type
        params = config.controller.params
    try:
        controller.configure(view, params)
    except Exception as exc:
        raise ControllerError(controller_type, "configure", f"{type(exc).__name__}: {exc}") from exc
    return controller, controller_type, hold


async def open_drivers(slots: list[DriverSlot], record_fault: RecordFault) -> None:
    """Open every driver, then read each once; the first that raises, or whose first reading
    of position, velocity or effort is not finite, is recorded, marked failed and raised
    again as a :class:`DriverError` naming it and the phase."""
    for phase in ("open", "read"):
        for slot in slots:
            step = slot.driver.open if phase == "open" else slot.driver.read
            try:
                await step()
                view = slot.driver.view
                if phase == "read" and not np.isfinite(view.state.block[:3]).all():
                    raise ValueError("measured position, velocity or effort is not finite after the first read")
            except Exception as exc:
                record_fault(f"driver:{slot.name}", phase, exc)
                slot.status = DriverStatus.FAILED
                raise DriverError(slot.name, phase, f"{type(exc).__name__}: {exc}") from exc
            if phase == "open":
                slot.status = DriverStatus.OPEN


async def close_drivers(slots: list[DriverSlot], timeout_s: float, record_fault: RecordFault) -> None:
    """Close every driver not yet closed, the last opened first, also the failed ones. A
    close() that raises or hangs past ``timeout_s`` is recorded and e-stopped; one that hangs
    is abandoned (its thread may never finish)."""
    for slot in reversed(slots):
        if slot.status in (DriverStatus.CLOSED, DriverStatus.ABANDONED):
            continue
        try:
            await asyncio.wait_for(slot.driver.close(), timeout_s)
        except Exception as exc:  # includes TimeoutError: a close() that hangs
            if isinstance(exc, TimeoutError):
                exc = TimeoutError(f"close() did not return within {timeout_s:g} s")
            record_fault(f"driver:{slot.name}", "close", exc)
            try:
                slot.driver.estop()
            except Exception:
                pass
            slot.status = DriverStatus.ABANDONED if isinstance(exc, TimeoutError) else slot.status
        if slot.status not in (DriverStatus.FAILED, DriverStatus.ABANDONED):
            slot.status = DriverStatus.CLOSED
