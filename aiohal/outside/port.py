"""The loop's one port to everything outside the tick.

The doors, the recorder and the terminal status get a :class:`LoopPort`, never the loop: what
they may read of it (the robot's arrays, the safety level, the faults, the tick's timing, the
drivers' health) and what they may ask of it (estop, hold, reset_faults, rearm), typed, with
nothing private of the loop behind it. A reader that copies the robot's arrays does it in a
function the tick calls at its end (:meth:`LoopPort.at_tick_end`): the only moment they hold
one tick's values, and the only code of theirs that runs in the tick.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from ..core.lifecycle import LoopState
from ..safety import SafetyRequestExpired

if TYPE_CHECKING:
    from ..config import Config
    from ..core.lifecycle import DriverSlot
    from ..core.tick_timing import TickStats
    from ..core.ticker import Ticker, TickSource
    from ..robot import Robot
    from ..safety import FaultRecord, SafetyLevel, Transition
    from ..safety.supervisor import Supervisor

#: Called at the end of every tick with one argument, which it ignores (the loop's own
#: publishers get the loop there). It must not block, log or allocate on the common path.
TickEnd = Callable[[object], None]


class Loop(Protocol):
    """What the port uses of :class:`aiohal.core.loop.ControlLoop`: its public face only."""

    config: Config
    robot: Robot
    period_ns: int
    source: TickSource
    ticker: Ticker
    stats: TickStats
    state: LoopState
    slots: list[DriverSlot]
    supervisor: Supervisor

    @property
    def missed_ticks(self) -> int: ...

    def add_publisher(self, publish: TickEnd) -> None: ...

    def remove_publisher(self, publish: TickEnd) -> None: ...


@dataclass(frozen=True)
class Health:
    """The drivers' status and health and the controller's metrics, as the report gives them."""

    tick: int
    level: SafetyLevel
    #: per driver: ``status`` and what its ``health()`` returned (or ``health_error``)
    drivers: dict[str, dict[str, Any]]
    #: ``type`` and what the controller's ``metrics()`` returned (or ``metrics_error``)
    controller: dict[str, Any]

    def as_dict(self) -> dict[str, Any]:
        """The JSON form the recorder's ``/health`` channel carries."""
        return {
            "tick": self.tick,
            "safety_level": self.level.name.lower(),
            "drivers": self.drivers,
            "controller": self.controller,
        }


class LoopPort:
    """What everything outside the tick reads of one loop, and asks of it.

    Reads are cheap attribute reads (a door reads :attr:`level` on every tick) or, for
    :meth:`health`, calls into drivers: that one only on the event loop, between ticks.
    Requests act at once and raise :class:`~aiohal.safety.SafetyRequestRefused` with the
    reason when the loop refuses them; call them on the loop's thread (from another thread,
    through its event loop's ``call_soon_threadsafe``).
    """

    def __init__(self, loop: Loop) -> None:
        self._loop = loop
        self._supervisor = loop.supervisor
        #: the loop's configuration (read only)
        self.config = loop.config
        #: the robot whose arrays the tick fills: read them in a :meth:`at_tick_end` function
        #: (or copy them there for later); never write them
        self.robot = loop.robot
        self.period_ns = loop.period_ns
        #: the loop's tick ring while an output reads it (:mod:`.tick_door`)
        self.tick_door: Any = None  # a TickDoor (that module imports this one)
        #: the loop's health and fault feed while an output process gets it (:mod:`.event_feed`)
        self.event_feed: Any = None  # an EventFeed

    # ------------------------------------------------------------ what to read

    @property
    def clock_kind(self) -> str:
        """``timerfd``, ``sleep`` or ``virtual``: the clock the ticks follow."""
        return self._loop.source.kind

    def now_ns(self) -> int:
        """The time on the loop's clock (CLOCK_MONOTONIC, or the virtual clock)."""
        return self._loop.source.now_ns()

    @property
    def tick(self) -> int:
        """The number of the last tick."""
        return self.robot.clock.tick

    @property
    def running(self) -> bool:
        """Whether the loop is ticking now (inside ``run()``)."""
        return self._loop.state == LoopState.RUNNING

    @property
    def active(self) -> bool:
        """Whether the loop is active and not ticking: its state is what the activation read
        (before the first ``run()``) or what the last tick left."""
        return self._loop.state == LoopState.ACTIVE

    @property
    def deadlines_origin_ns(self) -> int:
        """The run's deadlines are this plus whole periods (on the loop's clock)."""
        return self._loop.ticker.t0_ns

    @property
    def level(self) -> SafetyLevel:
        """The safety level now."""
        return self._supervisor.level

    @property
    def faults(self) -> Sequence[FaultRecord]:
        """Every fault recorded since the loop was made, oldest first; it only grows, so a
        reader keeps how many it has seen."""
        return self._supervisor.faults

    @property
    def transitions(self) -> Sequence[Transition]:
        """Every change of safety level since the loop was made, oldest first; it only grows."""
        return self._supervisor.machine.transitions

    @property
    def controller_type(self) -> str:
        """The controller commanding now (``hold`` after a failure or a hold request)."""
        return self._supervisor.controller_type

    @property
    def timing(self) -> TickStats:
        """The tick's timing store: lateness, work and each phase's time per tick (read only)."""
        return self._loop.stats

    @property
    def missed_ticks(self) -> int:
        """Deadlines missed in this run."""
        return self._loop.missed_ticks

    def health(self) -> Health:
        """Sample the drivers' health and the controller's metrics (on the event loop only:
        drivers are not thread-safe)."""
        drivers: dict[str, dict[str, Any]] = {}
        for slot in self._loop.slots:
            try:
                health = slot.driver.health()
            except Exception as exc:
                health = {"health_error": str(exc)}
            drivers[slot.name] = {"status": slot.status.value, **health}
        controller = self._supervisor.controller
        try:
            metrics = controller.metrics() if controller is not None else {}
        except Exception as exc:
            metrics = {"metrics_error": str(exc)}
        return Health(self.tick, self.level, drivers, {"type": self.controller_type, **metrics})

    # ------------------------------------------------------------ called by the tick

    def at_tick_end(self, publish: TickEnd) -> None:
        """Call ``publish`` at the end of every tick, after the drivers' writes. One that
        raises is recorded as a fault and not called again."""
        self._loop.add_publisher(publish)

    def stop_calling(self, publish: TickEnd) -> None:
        """No longer call ``publish`` (from the next tick)."""
        self._loop.remove_publisher(publish)

    # ------------------------------------------------------------ what to send

    def estop(self, cause: str, *, source: str) -> None:
        """Emergency-stop every driver now; never refused."""
        self._supervisor.estop(cause, source=source)

    def hold(self, cause: str) -> None:
        """Replace the controller by ``hold`` (braking to rest); only from ``run``."""
        self._supervisor.hold(cause)

    def reset_faults(self, source: str, *, act_by_ns: int | None) -> list[str]:
        """Clear the latched faults (and release an emergency stop); what was cleared.

        ``act_by_ns`` (CLOCK_MONOTONIC) is the last moment the loop may act on the request:
        its caller's wait for the answer, less the time the answer needs to get back (None
        for a caller that waits as long as it takes); read later, the request is refused with
        :class:`~aiohal.safety.SafetyRequestExpired`. Every door passes it: one whose caller
        gives up must not have the loop act behind its back."""
        _check_awaited("reset_faults", act_by_ns)
        return self._supervisor.reset_faults(source)

    def rearm(self, source: str, *, act_by_ns: int | None) -> None:
        """Return to ``run`` without a jump; refused while a fault is active, and after
        ``act_by_ns`` as :meth:`reset_faults` is."""
        _check_awaited("rearm", act_by_ns)
        self._supervisor.rearm(source)

    def record_fault(self, source: str, phase: str, exc: BaseException | str) -> FaultRecord:
        """Record a fault of a door or an output (it appears in the report; the CLI exits 1)."""
        return self._supervisor.record_fault(source, phase, exc)


def _check_awaited(what: str, act_by_ns: int | None) -> None:
    late_s = 0.0 if act_by_ns is None else (time.monotonic_ns() - act_by_ns) / 1e9
    if late_s > 0:
        raise SafetyRequestExpired(
            f"{what} read {late_s:.3f} s too late to answer its caller in time (the loop was not running): ask again"
        )
