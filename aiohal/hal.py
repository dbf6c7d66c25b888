"""The HAL protocol: what a driver and a controller are.

A driver moves data between hardware and its rows of the robot arrays (R-HAL's
``init/recvFromSlave/sendToSlave``); a controller turns state into commands inside the tick.
Both declare typed options (a pydantic model) that the configuration is validated against
before anything starts.
"""

from __future__ import annotations

import abc
from collections.abc import Iterable, Mapping, Sequence
from typing import Annotated, Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field

from .robot import DriverView, JointSpec, RobotView

#: A finite number (NaN and inf are refused at validation).
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]

#: A per-joint value in options: one number for every joint, or a {joint name: number} table.
JointValues = FiniteFloat | dict[str, FiniteFloat]


class Options(BaseModel):
    """Base of every driver's options and controller's parameters: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class NoOptions(Options):
    pass


def unknown_joint_issues(path: str, mapping: Any, allowed: Iterable[str]) -> list[tuple[str, str]]:
    """Issues for keys of a {joint: value} table that are not among ``allowed`` joints."""
    if not isinstance(mapping, Mapping):
        return []
    allowed = set(allowed)
    return [(f"{path}.{key}", f'unknown joint "{key}"') for key in mapping if key not in allowed]


class Driver(abc.ABC):
    """A backend that owns some joints and devices.

    ``read`` and ``write`` run inside the tick: they must not block (no blocking syscalls, no
    long computation). Bring-up that blocks belongs in ``open`` (e.g. ``asyncio.to_thread``).
    ``estop`` is synchronous and idempotent: it may be called from a signal handler, a watchdog
    or after the driver itself failed, and must leave the hardware safe.
    """

    Options: ClassVar[type[Options]] = NoOptions
    #: Device kinds ("imu", "force_torque", "hand") this driver can serve.
    device_kinds: ClassVar[frozenset[str]] = frozenset()

    def __init__(self, name: str, view: DriverView, options: Options) -> None:
        self.name = name
        self.view = view
        self.options = options

    @classmethod
    def check_config(
        cls, options: Options, joints: list[str], devices: dict[str, str], robot: Any
    ) -> list[tuple[str, str]]:
        """Extra checks of options against the joints and devices given to this driver and
        the ``[robot]`` section (its ``model`` path, resolved).

        Returns (path relative to the driver's entry, e.g. ``options.kp`` or ``joints``,
        message) pairs; empty when all is well.
        """
        return []

    @classmethod
    def check_rate(cls, options: Options, cycle_hz: float, every: int) -> list[tuple[str, str]]:
        """Checks at the rate this driver will be cycled at: the loop's rate divided by the
        ``[[driver]] every`` given (e.g. whether a bus carries the frames). Same pairs as
        :meth:`check_config`."""
        return []

    async def open(self) -> None:
        """Bring the hardware up; may take long, runs before the first tick."""

    @abc.abstractmethod
    async def read(self) -> None:
        """Fill this driver's state rows (and ``view.mark_fresh()`` when data arrived)."""

    @abc.abstractmethod
    async def write(self) -> None:
        """Send this driver's command rows to the hardware."""

    async def close(self) -> None:
        """Leave the hardware safe and release it. Called once, also after a failure."""

    def estop(self) -> None:
        """Emergency stop: synchronous, idempotent, never raises on purpose."""

    def health(self) -> dict[str, Any]:
        """Driver-specific counters for the report (e.g. frames lost)."""
        return {}


class Controller(abc.ABC):
    """Turns state into commands. ``update`` is synchronous, runs in the tick, must not block."""

    Params: ClassVar[type[Options]] = NoOptions

    robot: RobotView

    @classmethod
    def check_config(cls, params: Options, joints: Sequence[JointSpec], robot: Any) -> list[tuple[str, str]]:
        """Extra checks of params against the robot's joints, limits and ``[robot]`` section;
        (path relative to ``[controller]``, e.g. ``params.pose``, message) pairs."""
        return []

    def configure(self, robot: RobotView, params: Options) -> None:
        self.robot = robot
        self.params = params

    def start(self, t: float) -> None:
        """Called once before the first update, with the measured state filled in."""

    @abc.abstractmethod
    def update(self, t: float, dt: float) -> None:
        """Write ``self.robot.command`` from ``self.robot.state``; ``t`` in s since start."""

    def stop(self) -> None:
        """Called once when the controller is switched off."""

    def metrics(self) -> dict[str, Any]:
        """The controller's own figures, reported under ``controller`` in the run report."""
        return {}
