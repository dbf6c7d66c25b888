"""The safety state machine: ordered levels (as in EEROS), named events, a recorded history.

A level says how far the robot may move; higher is more able to move. Every change of level
is caused by a named event and recorded with the tick, the event, its source and its cause,
so that the report says why the robot stopped and who let it go again.

===============  =============================  ==============================================
event            from                           to
===============  =============================  ==============================================
``activate``     off                            run (drivers open, controller started)
``fault``        run, hold, disabled            the fault's level (``[safety] fault_level``,
                                                hold by default) when lower than the current;
                                                never raises the level
``hold``         run                            hold (a user's request)
``estop``        disabled, hold, run            estop (a user's request, or the loop's own
                                                when nothing is left to command)
``watchdog``     disabled, hold, run            estop (the stall watchdog, or the watchdog
                                                process acted on the hardware)
``reset_faults`` estop                          disabled, when every driver released its stop
                                                (it stays in estop otherwise)
``reset_faults`` disabled, hold                 unchanged: the latched faults are cleared
``rearm``        disabled, hold                 run, when no fault is active (bumpless: the
                                                controller restarts from the measured state)
``deactivate``   any                            off (drivers closed)
===============  =============================  ==============================================

An event the table has no row for is refused: a user's request raises
:class:`SafetyRequestRefused` with the reason, a fault or watchdog event changes nothing (the
fault itself is still recorded by the loop).

What each level means in the tick: ``run`` and ``hold`` command the drivers (``hold`` with
the HAL's hold controller, braking to rest); ``disabled`` and ``estop`` read the drivers and
command nothing; ``off`` has no driver open.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from enum import Enum, IntEnum
from typing import Literal

from pydantic import Field, model_validator

from ..hal import FiniteFloat, Options


class SafetyLevel(IntEnum):
    OFF = 0  # drivers closed, nothing commanded
    ESTOP = 1  # every driver's emergency stop was triggered
    DISABLED = 2  # the emergency stop released, nothing commanded until rearm()
    HOLD = 3  # controller replaced by hold: joints keep the last commanded position
    RUN = 4  # the configured controller is in charge


class SafetyEvent(str, Enum):  # noqa: UP042 - StrEnum would change str() of a member
    ACTIVATE = "activate"
    FAULT = "fault"
    HOLD = "hold"
    ESTOP = "estop"
    WATCHDOG = "watchdog"
    RESET_FAULTS = "reset_faults"
    REARM = "rearm"
    DEACTIVATE = "deactivate"


L, E = SafetyLevel, SafetyEvent
_MOVING = (L.DISABLED, L.HOLD, L.RUN)
#: (event, from) -> to. ``fault`` is resolved against the fault's own level (see the module).
TRANSITIONS: dict[tuple[SafetyEvent, SafetyLevel], SafetyLevel] = {
    (E.ACTIVATE, L.OFF): L.RUN,
    **{(E.FAULT, level): L.HOLD for level in _MOVING},
    (E.HOLD, L.RUN): L.HOLD,
    **{(E.ESTOP, level): L.ESTOP for level in (L.ESTOP, *_MOVING)},
    **{(E.WATCHDOG, level): L.ESTOP for level in (L.ESTOP, *_MOVING)},
    (E.RESET_FAULTS, L.ESTOP): L.DISABLED,
    (E.RESET_FAULTS, L.DISABLED): L.DISABLED,
    (E.RESET_FAULTS, L.HOLD): L.HOLD,
    (E.REARM, L.DISABLED): L.RUN,
    (E.REARM, L.HOLD): L.RUN,
    **{(E.DEACTIVATE, level): L.OFF for level in L},
}
del L, E


class SafetyRequestRefused(RuntimeError):
    """A user's safety request (hold, reset_faults, rearm) cannot be granted now; says why."""


class SafetyRequestExpired(SafetyRequestRefused):
    """A reset or rearm reached the loop too late to answer its caller within its wait (the
    loop was frozen or stopped meanwhile): the caller is told, or was told, that it went
    unanswered and may have walked up to the robot, so it is not acted on."""


@dataclass(frozen=True)
class Transition:
    """One change of level (or a request granted at the same level), and why."""

    tick: int
    event: str
    source: str  # "user", "loop", "driver:<name>", "controller:<type>", "watchdog", ...
    cause: str
    before: str
    after: str

    def as_dict(self) -> dict:
        return asdict(self)


class SafetyMachine:
    """The current level and the transitions that led there. Not thread-safe by itself: the
    loop calls it from its own thread, and the watchdog thread only through ``estop``, whose
    worst race is recording the emergency stop twice."""

    def __init__(self, fault_level: SafetyLevel = SafetyLevel.HOLD) -> None:
        self.level = SafetyLevel.OFF
        self.fault_level = fault_level
        self.transitions: list[Transition] = []

    def target(self, event: SafetyEvent, level: SafetyLevel | None = None) -> SafetyLevel | None:
        """Where ``event`` leads from the current level; None when the table refuses it.
        ``level``: a fault's own level (default ``fault_level``)."""
        to = TRANSITIONS.get((event, self.level))
        if to is not None and event is SafetyEvent.FAULT:
            wanted = self.fault_level if level is None else level
            to = wanted if wanted < self.level else None
        return to

    def fire(self, event: SafetyEvent, tick: int, source: str, cause: str, level: SafetyLevel | None = None) -> bool:
        """Apply ``event``; record it when the table has a row for it. False if refused."""
        to = self.target(event, level)
        if to is None:
            return False
        if to == self.level == SafetyLevel.ESTOP:
            return True  # a repeated emergency stop changes nothing worth a record
        self.transitions.append(Transition(tick, event.value, source, cause, self.level.name.lower(), to.name.lower()))
        self.level = to
        return True


Vector3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


class BoxSection(Options):
    min: Vector3
    max: Vector3

    @model_validator(mode="after")
    def _ordered(self) -> BoxSection:
        if not all(lo < hi for lo, hi in zip(self.min, self.max, strict=True)):
            raise ValueError(f"min must be below max on every axis (got {list(self.min)}, {list(self.max)})")
        return self


class SphereSection(Options):
    center: Vector3
    radius: float = Field(gt=0)


class WorkspaceSection(Options):
    """``[[safety.workspace]]``: a site of the robot's model must stay in a box or a sphere,
    given in the frame of a body of the model (``world``: the model's own)."""

    site: str = Field(min_length=1, description="A site of the [robot] model (e.g. the end effector's).")
    frame: str = Field("world", min_length=1, description="The body whose frame the box or sphere is given in.")
    box: BoxSection | None = None
    sphere: SphereSection | None = None
    level: Literal["hold", "estop"] = Field("hold", description="Where leaving it takes the robot.")

    @model_validator(mode="after")
    def _one_shape(self) -> WorkspaceSection:
        if (self.box is None) == (self.sphere is None):
            raise ValueError("give exactly one of box or sphere")
        return self


class SafetySection(Options):
    """``[safety]``: how faults are handled, the watchdog process and the workspace."""

    fault_level: Literal["hold", "estop"] = Field(
        "hold", description="Where a fault (driver, controller, stale feedback, refused command) takes the robot."
    )
    watchdog: bool = Field(
        True,
        description="Start the watchdog process when some driver declares an out-of-process safe action "
        "(and the clock is real): it runs them when the tick's heartbeat stops.",
    )
    watchdog_ms: float = Field(
        20.0, gt=0, le=10_000, description="The heartbeat is stale after this long (ms): the watchdog process acts."
    )
    workspace: list[WorkspaceSection] = Field(
        default_factory=list, description="Sites that must stay inside a box or sphere (needs [robot] model)."
    )
    watchdog_priority: int | None = Field(
        None,
        ge=0,
        le=99,
        description="SCHED_FIFO priority of the watchdog process (0: normal scheduling; default: one "
        "above [realtime] priority when the loop has one, else normal scheduling).",
    )
    max_tick_gap_ms: float | None = Field(
        None,
        gt=0,
        le=10_000,
        description="A tick that starts longer than this after the one before it (a frozen process, a "
        "stalled host) is a stall: the robot holds where it stands, with a fault, before anything is "
        "written (default: watchdog_ms, at least three periods).",
    )


@dataclass(frozen=True)
class FaultRecord:
    """Who failed, where, at which tick, and why."""

    source: str  # "driver:<name>", "controller:<type>" or "feedback"
    phase: str  # open, read, write, close, update, start, stop, check
    tick: int
    error: str
    # a condition of the hardware its driver reported (DriverView.fault: a drive's emergency, a
    # stale sensor), not a failure of the software
    condition: bool = False

    def as_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        if self.condition:
            return f"{self.source} at tick {self.tick}: {self.error}"
        return f"{self.source} failed in {self.phase} at tick {self.tick}: {self.error}"
