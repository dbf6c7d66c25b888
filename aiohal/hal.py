"""The HAL protocol: what a driver and a controller are.

A driver moves data between hardware and its rows of the robot arrays (R-HAL's
``init/recvFromSlave/sendToSlave``); a controller turns state into commands inside the tick.
Both declare typed options (a pydantic model) that the configuration is validated against
before anything starts.

Concurrency: the loop calls every method of a driver and a controller on its own thread, one
at a time, except ``Driver.estop``, which the stall watchdog thread may call while the loop's
thread is stuck. ``read`` and ``write`` are coroutines awaited in turn inside the tick: they
must not block, nor await anything slow (a coroutine that never awaits is the normal case).
Blocking bring-up runs in a thread (``asyncio.to_thread`` or an executor); a library's own
thread (python-can's notifier, a keep-alive thread) hands data to ``read`` through a buffer
made once and a counter, or a ``deque`` for events, and never touches the robot's arrays.
docs/architecture.md ("The concurrency model") says what each shipped driver does.

Trouble, one way per kind: a failure a driver cannot go on from is an exception raised from
``read``/``write`` (the loop isolates the driver, e-stops it, holds the robot); a condition of
its hardware is ``view.fault(reason)`` (recorded, and the robot held; ``hold=False`` for what
the run survives), with the ``Fault`` bits of the joints or devices it concerns set while it
lasts. A driver's configuration is checked in one place beyond its options' own fields:
:meth:`Driver.check_config` (and :meth:`Driver.check_rate` for what depends on the rate).
"""

from __future__ import annotations

import abc
import difflib
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Annotated, Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field, field_validator

from .robot import DriverView, JointSpec, Mode, RobotView

#: A finite number (NaN and inf are refused at validation).
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]

#: A per-joint value in options: one number for every joint, or a {joint name: number} table.
JointValues = FiniteFloat | dict[str, FiniteFloat]

#: Every command mode a joint can be given (``Mode.NONE`` is no command at all).
ALL_MODES: frozenset[Mode] = frozenset({Mode.POSITION, Mode.VELOCITY, Mode.EFFORT, Mode.IMPEDANCE})


class Options(BaseModel):
    """Base of every driver's options and controller's parameters: unknown keys are errors,
    and so is NaN in any number field (it would pass or fail a bound by accident)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @field_validator("*", mode="before")
    @classmethod
    def _no_nan(cls, value: Any) -> Any:
        if isinstance(value, float) and math.isnan(value):
            raise ValueError("must be a finite number (got nan)")
        return value


#: The base class under another name, for annotations inside Driver, whose ``Options`` is
#: the driver's own options class.
AnyOptions = Options


class NoOptions(Options):
    pass


def did_you_mean(name: str, choices: Iterable[str]) -> str:
    """`` (did you mean "a3"?)`` for the known name closest to ``name`` (same letters in
    another case first), or an empty string."""
    choices = list(choices)
    same_case = [c for c in choices if c.casefold() == name.casefold()]
    if same_case:
        return f' (did you mean "{same_case[0]}"?)'
    close = difflib.get_close_matches(name, choices, n=1)
    # short names: one character off (a8 -> a3) is below difflib's cutoff; the first declared
    typo = [c for c in choices if len(c) == len(name) and sum(a != b for a, b in zip(c, name, strict=True)) == 1]
    best = close or typo
    return f' (did you mean "{best[0]}"?)' if best else ""


def unknown_joint_issues(path: str, mapping: Any, allowed: Iterable[str]) -> list[tuple[str, str]]:
    """Issues for keys of a {joint: value} table that are not among ``allowed`` joints."""
    if not isinstance(mapping, Mapping):
        return []
    allowed = list(allowed)
    known = set(allowed)
    return [
        (f"{path}.{key}", f'unknown joint "{key}"{did_you_mean(key, allowed)}') for key in mapping if key not in known
    ]


class Driver(abc.ABC):
    """A backend that owns some joints and devices.

    ``read`` and ``write`` run inside the tick: they must not block (no blocking syscalls, no
    long computation). Bring-up that blocks belongs in ``open`` (e.g. ``asyncio.to_thread``).
    ``estop`` is synchronous and idempotent: it may be called from a signal handler, a watchdog
    or after the driver itself failed, and must leave the hardware safe.
    """

    Options: ClassVar[type[Options]] = NoOptions
    device_kinds: ClassVar[frozenset[str]] = frozenset()
    """Device kinds ("imu", "force_torque", "hand") this driver can serve."""
    command_modes: ClassVar[frozenset[Mode]] = ALL_MODES
    """The command modes this driver applies to its joints (ros2_control's command
    interfaces): a controller that commands another mode is refused before anything starts."""

    def __init__(self, name: str, view: DriverView, options: AnyOptions) -> None:
        self.name = name
        self.view = view
        self.options = options

    @classmethod
    def check_config(
        cls, options: AnyOptions, joints: list[str], devices: dict[str, str], robot: Any
    ) -> list[tuple[str, str]]:
        """Extra checks of options against the joints and devices given to this driver and
        the ``[robot]`` section (its ``model`` path, resolved).

        Returns (path relative to the driver's entry, e.g. ``options.kp`` or ``joints``,
        message) pairs; empty when all is well. A path that starts with ``/`` names a key
        from the top of the file (``/robot.model``): where the user wrote the value.
        """
        return []

    @classmethod
    def check_rate(cls, options: AnyOptions, cycle_hz: float, every: int) -> list[tuple[str, str]]:
        """Checks at the rate this driver will be cycled at: the loop's rate divided by the
        ``[[driver]] every`` given (e.g. whether a bus carries the frames). Same pairs as
        :meth:`check_config`."""
        return []

    @classmethod
    def supported_modes(cls, options: AnyOptions) -> frozenset[Mode]:
        """The command modes with these options: ``command_modes`` unless the options narrow
        them (the KUKA's position strategy takes no impedance)."""
        return cls.command_modes

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

    def reset_faults(self) -> object:
        """Clear the hardware's latched faults (e.g. a drive's), on the user's request. The
        loop has just cleared the joints' fault bits: a driver whose fault persists sets its
        joints' bits again here, so that ``rearm()`` is refused until it is gone."""
        return None

    def release_estop(self) -> bool:
        """Leave the emergency stop, hardware disabled but ready to be commanded again (the
        loop re-arms it). False: this driver cannot without being opened again."""
        return False

    def safe_actions(self) -> list:
        """What the watchdog process does for this driver when the tick stops
        (:mod:`aiohal.safety.watchdog` actions: plain data, run outside this process)."""
        return []

    def health(self) -> dict[str, Any]:
        """Driver-specific counters for the report (e.g. frames lost)."""
        return {}


class Controller(abc.ABC):
    """Turns state into commands. ``update`` is synchronous, runs in the tick, must not block."""

    Params: ClassVar[type[Options]] = NoOptions
    command_modes: ClassVar[frozenset[Mode]] = frozenset({Mode.POSITION})
    """The command modes this controller writes to ``command.mode``."""

    robot: RobotView

    @classmethod
    def check_config(cls, params: Options, joints: Sequence[JointSpec], robot: Any) -> list[tuple[str, str]]:
        """Extra checks of params against the robot's joints, limits and ``[robot]`` section;
        (path relative to ``[controller]``, e.g. ``params.pose``, or from the top of the file
        when it starts with ``/``, message) pairs."""
        return []

    @classmethod
    def commanded_modes(cls, params: Options) -> frozenset[Mode]:
        """The command modes with these params: ``command_modes`` unless a parameter chooses
        (a ``mode`` parameter: config errors then name ``controller.params.mode``)."""
        return cls.command_modes

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
