"""The control loop: lifecycle and the tick.

One tick, in order::

    wake (absolute deadline k) -> read every driver -> check feedback -> controller.update
    (or, with ``[controller] every = n``, on the ticks between two updates: the last command
    with its position targets extrapolated, see :mod:`aiohal.multirate`)
    -> clamp commands to limits -> write every driver -> publish -> statistics

Lifecycle: ``configure`` (build drivers and controller, nothing touches hardware) ->
``activate`` (open drivers, first read, command := measured state, controller start) ->
``run`` (ticks until a duration, a tick count or :meth:`ControlLoop.request_stop`) ->
``deactivate`` (controller stop, drivers closed). ``async with ControlLoop(config)`` does the
first two and the last. A driver or controller that raises never ends the process: the driver
is isolated and emergency-stopped, the controller is replaced by ``hold`` without a jump, and
the fault is recorded with its name.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import subprocess
import threading
import time
from collections.abc import Callable
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from . import plugins
from .config import Config, mode_issues
from .config import from_parts as config_from_parts
from .doors import Doors
from .errors import ConfigError, ControllerError, DriverError, LifecycleError
from .feedforward import VelocityFeedforward, gains_of
from .hal import Controller, Driver
from .limits import CommandLimiter
from .logutil import RateLimitedLogger
from .multirate import TargetExtrapolator
from .realtime import RealtimeState, freeze_heap, freeze_young, thaw_heap
from .realtime import apply as apply_realtime
from .realtime import restore as restore_realtime
from .robot import Fault, Mode
from .safety import FaultRecord, SafetyEvent, SafetyLevel, SafetyMachine, SafetyRequestRefused
from .stats import TickStats
from .ticker import Ticker, TickSource, TimerfdTickSource, make_source
from .watchdog import FIRED, STAMP, TICK, WORDS, WatchdogProcess

if TYPE_CHECKING:
    from .workspace import WorkspaceMonitor

assert (TICK, STAMP, FIRED) == (0, 1, 3)  # the tick stores heartbeat[0], [1] and reads [3]

log = logging.getLogger(__name__)


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


class ControlLoop:
    """Runs one robot: its drivers, its controller and the tick."""

    def __init__(
        self,
        config: Config,
        *,
        tick_source: TickSource | None = None,
        controller: Controller | None = None,
        controller_params: Any = None,
    ) -> None:
        """``controller`` replaces the configured one (with ``controller_params``, or its
        ``Params`` defaults); ``tick_source`` replaces the configured clock (tests, lockstep)."""
        self.config = config
        self.robot = config.build_robot()
        self.period_ns = config.period_ns
        self.period_s = self.period_ns / 1e9
        guard_ns = int(config.realtime.spin_guard_us * 1e3)
        self.source = tick_source or make_source(config.loop.clock, guard_ns, config.loop.idle_wait)
        self.realtime: RealtimeState | None = None
        phase = config.loop.phase_us
        self.ticker = Ticker(
            self.source, self.period_ns, config.loop.overrun, None if phase is None else round(phase * 1e3)
        )
        self.stats = TickStats(config.loop.stats_window)
        self.limiter = CommandLimiter(self.robot, self.period_s)
        every = config.controller.every
        #: a controller slower than the bus (None: it runs on every tick)
        self.multirate = (
            TargetExtrapolator(self.robot.command, self.period_s, every, config.controller.extrapolate)
            if every > 1
            else None
        )
        #: learned velocity feed-forward, applied after the controller (None: not configured)
        self.feedforward = (
            VelocityFeedforward(self.robot.command, gains_of(config.feedforward, list(self.robot.joint_names)))
            if config.feedforward.active
            else None
        )
        #: the safety state machine (:mod:`aiohal.safety`); ``level`` mirrors its level for the tick
        self.safety = SafetyMachine(SafetyLevel[config.safety.fault_level.upper()])
        self.level = SafetyLevel.OFF
        #: the most severe level since activate(): the report's "safety_worst"
        self.worst_level = SafetyLevel.OFF
        self.faults: list[FaultRecord] = []
        self._faults_reset_at = 0  # faults recorded before this index were cleared by reset_faults()
        self.watchdog: WatchdogProcess | None = None
        #: a tick that starts longer than this after the one before is a stall (hold, a fault)
        gap_ms = config.safety.max_tick_gap_ms
        if gap_ms is None:
            gap_ms = max(config.safety.watchdog_ms, 3 * self.period_ns / 1e6)
        self.max_tick_gap_ns = round(gap_ms * 1e6)
        # the tick's heartbeat: two int64 stores per tick; shared with the watchdog process
        # when one runs, else a private page nobody reads
        self._heartbeat = memoryview(bytearray(WORDS * 8)).cast("q")
        #: workspace limits, only when configured (nothing of it in the tick otherwise)
        self.workspace: WorkspaceMonitor | None = None
        if config.safety.workspace:
            from .workspace import WorkspaceMonitor

            # the config refuses workspace limits without [robot] model
            self.workspace = WorkspaceMonitor(
                cast(Path, config.robot.model),
                list(self.robot.joint_names),
                self.robot.state.position,
                list(config.safety.workspace),
            )
        self._outside = False  # a site is outside its workspace (recorded once per excursion)
        self.slots: list[DriverSlot] = []
        self._active: list[DriverSlot] = []
        self._given_controller = controller
        self._given_params = controller_params
        self.controller: Controller | None = None
        self.controller_type = config.controller.type
        self._configured: tuple[Controller, str] | None = None  # what rearm() restarts
        self._hold: Controller | None = None
        self._publishers: list[Callable[[ControlLoop], None]] = []
        self._stop = False
        self.stop_reason = ""
        self.state = LoopState.CREATED
        self._k_start = 0
        self._last_update_k = 0
        self._stale_drivers: set[str] = set()
        self._refusing = False
        self._run_finished = asyncio.Event()
        self._missed_before = 0
        self._warn = RateLimitedLogger(log)
        self._heap_frozen = False
        self.doors: Doors | None = None
        self.event_loop = ""  # the event loop's implementation, set by run()

    @classmethod
    def from_parts(
        cls,
        *,
        controller: Controller | str | type | dict[str, Any] = "hold",
        params: Any = None,
        tick_source: TickSource | None = None,
        **parts: Any,
    ) -> ControlLoop:
        """A loop built from code, with no config file: joints, drivers, ``rate_hz``, ``clock``
        and the other sections as :func:`aiohal.config.from_parts` takes them, validated as a
        file is (:class:`~aiohal.errors.ConfigError` with key paths). ``controller`` may also be
        an instance, whose ``params`` are validated and checked like a configured one's::

            loop = ControlLoop.from_parts(
                joints={"q1": {"position": [-1, 1], "velocity": 1.0}},
                drivers=[("mock", {"joints": ["q1"]})],
                controller=SineController(), params={"amplitude": 0.2},
                rate_hz=1000, clock="virtual",
            )
        """
        instance: Controller | None
        spec: str | type | dict[str, Any]
        if isinstance(controller, Controller):
            instance, spec = controller, type(controller)
        else:
            instance, spec = None, controller
        config = config_from_parts(controller=spec, params=params, **parts)
        return cls(
            config,
            tick_source=tick_source,
            controller=instance,
            controller_params=config.controller.params if instance else None,
        )

    # ------------------------------------------------------------ lifecycle

    def configure(self) -> None:
        """Instantiate drivers and controllers from the config; touches no hardware."""
        if self.state != LoopState.CREATED:
            raise LifecycleError(f"configure() in state {self.state.value!r}")
        if self._given_controller is not None:  # the config checked its own controller, not this one
            given = type(self._given_controller)
            params = self._given_params if self._given_params is not None else given.Params()
            issues = mode_issues(given, params, self.config.drivers)
            if issues:
                raise ConfigError(issues, str(self.config.path) if self.config.path else None)
        for dc in self.config.drivers:
            view = self.robot.driver_view(dc.joints, dc.devices)
            view.report_fault = functools.partial(self.record_fault, f"driver:{dc.name}")
            view.request_hold = functools.partial(self._hold_for_driver, dc.name)
            view.resync = functools.partial(self.resync_joints, view.rows)
            view.every = dc.every
            try:
                driver = dc.cls(dc.name, view, dc.options)
            except Exception as exc:
                raise DriverError(dc.name, "configure", f"{type(exc).__name__}: {exc}") from exc
            self.slots.append(DriverSlot(driver, dc.type, dc.every, self.config.loop.max_feedback_age * dc.every))
        controller_view = self.robot.controller_view()
        hold_cls = cast(type[Controller], plugins.load("controller", "hold"))
        self._hold = hold_cls()
        self._hold.configure(controller_view, hold_cls.Params())
        if self._given_controller is not None:
            self.controller = self._given_controller
            self.controller_type = type(self.controller).__name__
            params = self._given_params if self._given_params is not None else type(self.controller).Params()
        else:
            self.controller = self.config.controller.cls()
            params = self.config.controller.params
        try:
            self.controller.configure(controller_view, params)
        except Exception as exc:
            raise ControllerError(self.controller_type, "configure", f"{type(exc).__name__}: {exc}") from exc
        self.doors = Doors(self)  # shared memory and bridges, as configured (aiohal.doors)
        self._configured = (self.controller, self.controller_type)
        self.state = LoopState.CONFIGURED

    async def activate(self) -> None:
        """Open every driver, read once, start from the measured state, start the controller."""
        if self.state == LoopState.CREATED:
            self.configure()
        if self.state != LoopState.CONFIGURED:
            raise LifecycleError(f"activate() in state {self.state.value!r}")
        clock = self.robot.clock
        clock.kind = self.source.kind
        clock.tick = 0
        clock.now_ns = self.source.now_ns()
        if self.config.loop.gc == "freeze":
            freeze_heap()  # the one full collection, before any driver has a thread to feed
            self._heap_frozen = True
        try:
            for slot in self.slots:
                await self._bring_up(slot, "open", slot.driver.open)
            for slot in self.slots:
                await self._bring_up(slot, "read", slot.driver.read)
            self._start_watchdog()
        except BaseException:
            self.estop("bring-up failed", source="loop")
            await self._close_drivers()
            self.state = LoopState.CLOSED
            raise
        state = self.robot.state
        for slot in self.slots:
            rows = slot.driver.view.rows
            if not np.isfinite(state.block[:3, rows]).all():
                reason = "measured position, velocity or effort is not finite after the first read"
                self.record_fault(f"driver:{slot.name}", "read", reason)
                self.estop(reason, source=f"driver:{slot.name}")
                await self._close_drivers()
                self.state = LoopState.CLOSED
                raise DriverError(slot.name, "read", reason)
        self._active = list(self.slots)
        cmd = self.robot.command
        np.copyto(cmd.position, state.position)
        cmd.velocity[:] = 0.0
        cmd.effort[:] = 0.0
        cmd.feedforward[:] = 0.0
        cmd.mode[cmd.mode == Mode.NONE] = Mode.POSITION
        self.limiter.reset(state.position)
        self._event(SafetyEvent.ACTIVATE, "loop", "drivers open, controller started")
        self.state = LoopState.ACTIVE
        self._k_start = 0  # controller time counts from activation, across run() calls
        self._last_update_k = 0
        if self.multirate is not None:
            self.multirate.force()
        try:
            cast(Controller, self.controller).start(0.0)  # set by configure()
        except Exception as exc:
            self._controller_failed("start", exc)
        cast(Doors, self.doors).activate()

    async def _bring_up(self, slot: DriverSlot, phase: str, step: Callable) -> None:
        try:
            await step()
        except Exception as exc:
            self.record_fault(f"driver:{slot.name}", phase, exc)
            slot.status = DriverStatus.FAILED
            raise DriverError(slot.name, phase, f"{type(exc).__name__}: {exc}") from exc
        if phase == "open":
            slot.status = DriverStatus.OPEN

    async def deactivate(self) -> None:
        """Stop the controller and close every driver (also the failed ones)."""
        if self.state in (LoopState.CLOSED, LoopState.CREATED, LoopState.CONFIGURED):
            self.state = LoopState.CLOSED
            return
        if self.state == LoopState.RUNNING:  # finish the tick in progress before closing anything
            self.request_stop("deactivated")
            await self._run_finished.wait()
        controller = self.controller
        try:
            if controller is not None:
                controller.stop()
        except Exception as exc:
            self.record_fault(f"controller:{self.controller_type}", "stop", exc)
        await self._close_drivers()
        self._event(SafetyEvent.DEACTIVATE, "loop", "drivers closed")
        self.state = LoopState.CLOSED

    def _start_watchdog(self) -> None:
        """The watchdog process, when some driver declares a safe action and time is real."""
        safety = self.config.safety
        actions = [(f"driver:{slot.name}", action) for slot in self.slots for action in slot.driver.safe_actions()]
        if not (safety.watchdog and actions) or self.source.kind == "virtual":
            return
        priority = safety.watchdog_priority
        if priority is None:  # above the loop's own, so that it runs when the loop does not
            loop_priority = self.config.realtime.priority
            priority = min(99, loop_priority + 1) if loop_priority else 0
        watchdog = WatchdogProcess(actions, safety.watchdog_ms, priority)
        watchdog.start()
        self.watchdog = watchdog
        self._heartbeat = cast(memoryview, watchdog.heartbeat)  # mapped by start()

    def _stop_watchdog(self) -> None:
        watchdog, self.watchdog = self.watchdog, None
        if watchdog is not None:
            self._heartbeat = memoryview(bytearray(WORDS * 8)).cast("q")
            watchdog.stop()

    async def _close_drivers(self) -> None:
        self._stop_watchdog()
        timeout = self.config.loop.close_timeout_ms / 1e3
        for slot in reversed(self.slots):
            if slot.status in (DriverStatus.CLOSED, DriverStatus.ABANDONED):
                continue
            try:
                await asyncio.wait_for(slot.driver.close(), timeout)
            except Exception as exc:  # includes TimeoutError: a close() that hangs
                if isinstance(exc, TimeoutError):
                    exc = TimeoutError(f"close() did not return within {timeout:g} s")
                self.record_fault(f"driver:{slot.name}", "close", exc)
                try:
                    slot.driver.estop()
                except Exception:
                    pass
                slot.status = DriverStatus.ABANDONED if isinstance(exc, TimeoutError) else slot.status
            if slot.status not in (DriverStatus.FAILED, DriverStatus.ABANDONED):
                slot.status = DriverStatus.CLOSED
        if self._heap_frozen:  # every path that closes the drivers ends the loop's freeze
            thaw_heap()
            self._heap_frozen = False
        if self.doors is not None:  # and closes the doors to other processes
            self.doors.close()

    async def __aenter__(self) -> ControlLoop:
        await self.activate()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.deactivate()

    def request_stop(self, reason: str = "requested") -> None:
        """Ask the loop to finish the current tick and return from :meth:`run`."""
        if not self._stop:
            self.stop_reason = reason
        self._stop = True

    @property
    def stop_requested(self) -> bool:
        return self._stop

    # ------------------------------------------------------------ safety events

    def _event(self, event: SafetyEvent, source: str, cause: str, level: SafetyLevel | None = None) -> bool:
        """Fire ``event`` on the safety machine; the tick reads the level from ``self.level``."""
        changed = self.safety.fire(event, self.robot.clock.tick, source, cause, level)
        self.level = self.safety.level
        if self.level != SafetyLevel.OFF and (self.worst_level == SafetyLevel.OFF or self.level < self.worst_level):
            self.worst_level = self.level  # the lowest level reached while running, for the exit status
        return changed

    def estop(self, cause: str = "requested", *, source: str = "user", event: SafetyEvent = SafetyEvent.ESTOP) -> None:
        """Trigger every driver's emergency stop now (synchronous; safe to call twice, and from
        another thread or a signal handler). The drivers are still read; nothing is commanded
        until :meth:`reset_faults` and :meth:`rearm`."""
        for slot in self.slots:
            try:
                slot.driver.estop()
            except Exception as exc:
                self.record_fault(f"driver:{slot.name}", "estop", exc)
        if self.level > SafetyLevel.OFF:
            self._event(event, source, cause, SafetyLevel.ESTOP if event is SafetyEvent.FAULT else None)

    def hold(self, cause: str = "requested") -> None:
        """A user's request: replace the controller by ``hold`` (braking to rest, no jump)."""
        if self.safety.target(SafetyEvent.HOLD) is None:
            raise SafetyRequestRefused(f"hold from {self.level.name.lower()}: only from run")
        self.enter_hold(cause, source="user", event=SafetyEvent.HOLD)

    def reset_faults(self, source: str = "user") -> list[str]:
        """Clear latched faults: every driver's own (:meth:`Driver.reset_faults`), the joints'
        fault bits and the loop's record of faults since the last reset. After an emergency
        stop, every driver must release it (:meth:`Driver.release_estop`): the robot is then
        ``disabled``, read but not commanded, until :meth:`rearm`. Returns what a driver
        reported resetting (e.g. EtherCAT drive names). Raises
        :class:`SafetyRequestRefused` with the reason when it cannot."""
        if self.state not in ("active", "running"):
            raise SafetyRequestRefused(f"reset_faults() with the loop {self.state}")
        if self.safety.target(SafetyEvent.RESET_FAULTS) is None:
            raise SafetyRequestRefused(f"reset_faults() from {self.level.name.lower()}")
        reset: list[str] = []
        for slot in self._active:
            try:
                names = slot.driver.reset_faults()
            except Exception as exc:
                self.record_fault(f"driver:{slot.name}", "reset_faults", exc)
                continue
            if isinstance(names, (list, tuple)):
                reset += [str(n) for n in names]
        if self.level == SafetyLevel.ESTOP:
            kept = []
            for slot in self._active:
                try:
                    if not slot.driver.release_estop():
                        kept.append(slot.name)
                except Exception as exc:
                    self.record_fault(f"driver:{slot.name}", "release_estop", exc)
                    kept.append(slot.name)
            if kept:
                raise SafetyRequestRefused(
                    f"driver(s) {', '.join(kept)} cannot leave the emergency stop without a restart"
                )
        for slot in self._active:
            self.robot.state.fault[slot.driver.view.rows] = 0
        watchdog = self.watchdog
        if watchdog is not None and self.state == LoopState.RUNNING and not watchdog.trouble():
            watchdog.arm()  # after it fired (it disarms itself then): watching again
        self._stale_drivers.clear()
        self._refusing = False
        cleared = len(self.faults) - self._faults_reset_at
        self._faults_reset_at = len(self.faults)
        self._event(SafetyEvent.RESET_FAULTS, source, f"{cleared} fault(s) cleared")
        log.info("robot %s: %d fault(s) cleared, level %s", self.robot.name, cleared, self.level.name.lower())
        return reset

    def active_faults(self) -> list[str]:
        """Why :meth:`rearm` would be refused now (empty: it would not)."""
        reasons = []
        failed = [s.name for s in self.slots if s.status in (DriverStatus.FAILED, DriverStatus.ABANDONED)]
        if failed:
            reasons.append(f"driver(s) {', '.join(failed)} failed (isolated until the loop is started again)")
        if len(self.faults) > self._faults_reset_at:
            reasons.append(f"{len(self.faults) - self._faults_reset_at} fault(s) since the last reset_faults()")
        k, max_age = self.robot.clock.tick, self.config.loop.max_feedback_age
        stale = [s.name for s in self._active if k - s.driver.view.fresh_tick > max_age]
        if stale:
            reasons.append(f"feedback is stale from {', '.join(stale)}")
        faulted = np.flatnonzero(self.robot.state.fault)
        if faulted.size:
            names = [self.robot.joint_names[i] for i in faulted[:5]]
            reasons.append(f"joint(s) {', '.join(names)}{' ...' if faulted.size > 5 else ''} report a fault")
        trouble = self.watchdog_trouble()
        if trouble:
            reasons.append(trouble)
        if self.workspace is not None and not self.workspace.check():
            reasons.append(f"site {self.workspace.entries[self.workspace.outside].site} is outside its workspace")
        if self.level == SafetyLevel.HOLD:
            rate = self.limiter.last_rate(np.empty(self.robot.dof))
            if np.any(rate != 0.0):
                reasons.append("hold is still braking")
        return reasons

    def rearm(self, source: str = "user") -> None:
        """Return to ``run`` from ``hold`` or ``disabled`` when no fault is active, without a
        jump: the configured controller starts again (``start``) from the measured state, and
        the command continues from the last one sent (from ``hold``) or from the measured
        position (from ``disabled``, where nothing was sent). Raises
        :class:`SafetyRequestRefused` with the reasons when it cannot."""
        if self.state not in ("active", "running"):
            raise SafetyRequestRefused(f"rearm() with the loop {self.state}")
        if self.safety.target(SafetyEvent.REARM) is None:
            hint = ": reset_faults() first" if self.level == SafetyLevel.ESTOP else ""
            raise SafetyRequestRefused(f"rearm() from {self.level.name.lower()}{hint}")
        reasons = self.active_faults()
        if reasons:
            raise SafetyRequestRefused("rearm() refused: " + "; ".join(reasons))
        if self._configured is None:
            raise SafetyRequestRefused("rearm() before configure()")
        cmd, measured = self.robot.command, self.robot.state.position
        if self.level == SafetyLevel.DISABLED:
            np.copyto(cmd.position, measured)
            cmd.velocity[:] = 0.0
            cmd.effort[:] = 0.0
            cmd.feedforward[:] = 0.0
            self.limiter.reset(measured)
        controller, controller_type = self._configured
        self.controller, self.controller_type = controller, controller_type
        self._event(SafetyEvent.REARM, source, f"{controller_type} restarted from the measured state")
        log.info("robot %s re-armed: %s restarted from the measured state", self.robot.name, controller_type)
        k = self.robot.clock.tick
        self._last_update_k = k
        if self.multirate is not None:
            self.multirate.force()
        try:
            controller.start((k - self._k_start) * self.period_s)
        except Exception as exc:
            self._controller_failed("start", exc)

    def add_publisher(self, publish: Callable[[ControlLoop], None]) -> None:
        """Call ``publish(loop)`` at the end of every tick; it must not block."""
        self._publishers.append(publish)

    # ------------------------------------------------------------ faults

    def record_fault(self, source: str, phase: str, exc: BaseException | str) -> FaultRecord:
        """Record and log a fault; it appears in the report and makes the CLI exit 1."""
        error = exc if isinstance(exc, str) else f"{type(exc).__name__}: {exc}"
        record = FaultRecord(source, phase, self.robot.clock.tick, error)
        self.faults.append(record)
        log.error("%s", record)
        return record

    def _driver_failed(self, slot: DriverSlot, phase: str, exc: BaseException) -> None:
        self.record_fault(f"driver:{slot.name}", phase, exc)
        slot.status = DriverStatus.FAILED
        try:
            slot.driver.estop()
        except Exception as estop_exc:
            self.record_fault(f"driver:{slot.name}", "estop", estop_exc)
        self.robot.state.fault[slot.driver.view.rows] |= np.uint32(Fault.DRIVER)
        self._active = [s for s in self._active if s is not slot]
        self.enter_hold(f"driver {slot.name} failed in {phase}", source=f"driver:{slot.name}")

    def _controller_failed(self, phase: str, exc: BaseException | str) -> None:
        """The controller raised or wrote a non-finite command: hold, and command this tick."""
        source = f"controller:{self.controller_type}"
        self.record_fault(source, phase, exc)
        self.enter_hold(f"controller {self.controller_type} failed in {phase}", source=source)
        if self.level < SafetyLevel.HOLD:
            return
        t = (self.robot.clock.tick - self._k_start) * self.period_s
        try:
            cast(Controller, self._hold).update(t, self.period_s)  # set by configure()
        except Exception as hold_exc:  # hold is simple enough never to get here
            self.record_fault("controller:hold", "update", hold_exc)
            self.estop("hold failed", source="controller:hold", event=SafetyEvent.FAULT)

    def enter_hold(
        self,
        reason: str,
        *,
        source: str = "loop",
        event: SafetyEvent = SafetyEvent.FAULT,
        level: SafetyLevel | None = None,
    ) -> None:
        """Replace the controller by ``hold``, continuing from the last command sent: a joint
        that was moving brakes to rest within its acceleration limit (no jump, no stall).
        A fault goes to ``[safety] fault_level`` instead when that is ``estop``."""
        to = self.safety.target(event, level)
        if to is None:
            return
        if to < SafetyLevel.HOLD:
            self.estop(reason, source=source, event=event)
            return
        log.warning("robot %s goes to hold: %s", self.robot.name, reason)
        self._event(event, source, reason)
        old = self.controller
        if old is not None and old is not self._hold:
            try:
                old.stop()
            except Exception as exc:
                self.record_fault(f"controller:{self.controller_type}", "stop", exc)
        cmd = self.robot.command
        # joints in velocity or effort mode had no meaningful position command: continue them
        # from where they are measured, at their commanded velocity (0 in effort mode)
        not_position = (cmd.mode != Mode.POSITION) & (cmd.mode != Mode.IMPEDANCE)
        if not_position.any():
            velocity = np.where((cmd.mode == Mode.VELOCITY) & np.isfinite(cmd.velocity), cmd.velocity, 0.0)
            self.limiter.follow_measured(not_position, velocity)
        self.limiter.hold_last()
        self.controller = self._hold
        self.controller_type = "hold"
        # the last command was sent one period ago: hold's motion starts there
        cast(Controller, self._hold).start((self.robot.clock.tick - self._k_start - 1) * self.period_s)

    def _hold_for_driver(self, name: str, reason: str) -> None:
        if self.level > SafetyLevel.HOLD:
            self.enter_hold(f"driver {name}: {reason}", source=f"driver:{name}")

    def resync_joints(self, rows: slice, mask: np.ndarray) -> None:
        """Joints ``mask`` of the driver rows ``rows`` were (re-)enabled where they stand: their
        command continues from the measured position at rest, so nothing jumps. Under ``hold``
        every joint's hold restarts from its current command (the others continue braking)."""
        cmd, measured = self.robot.command, self.robot.state.position
        n = self.robot.dof
        which = np.zeros(n, dtype=bool)
        which[rows] = mask
        which &= np.isfinite(measured)
        if not which.any():
            return
        np.copyto(cmd.position, measured, where=which)
        cmd.velocity[which] = 0.0
        self.limiter.follow_measured(which, np.zeros(n))
        if self.multirate is not None:  # the controller sees the change this tick, not its old command
            self.multirate.force()
        if self.controller is self._hold and self.state in (LoopState.ACTIVE, LoopState.RUNNING):
            cast(Controller, self._hold).start((self.robot.clock.tick - self._k_start) * self.period_s)

    def _check_feedback(self, k: int) -> None:
        """Some driver's feedback is older than its ``max_age`` ticks: flag it, hold, report once."""
        stale = [s for s in self._active if k - s.driver.view.fresh_tick > s.max_age]
        for slot in stale:
            view = slot.driver.view
            self.robot.state.fault[view.rows] |= np.uint32(Fault.STALE)
            if slot.name not in self._stale_drivers:
                self._stale_drivers.add(slot.name)
                self.record_fault(
                    f"driver:{slot.name}", "check", f"feedback is stale ({k - view.fresh_tick} ticks old)"
                )
        if stale:
            self.enter_hold("stale feedback from " + ", ".join(s.name for s in stale), source="feedback")
            self._warn.warning("stale", "feedback still stale from %s", ", ".join(s.name for s in stale))
        else:
            self._stale_drivers.clear()

    def _left_workspace(self, workspace: WorkspaceMonitor) -> None:
        """A site is outside its workspace: its configured level, the site and distance recorded.
        Not commanding (estop, disabled), there is nothing to stop; rearm() waits for the site."""
        if self.level < SafetyLevel.HOLD:
            return
        entry = workspace.entries[workspace.outside]
        source = f"workspace:{entry.site}"
        reason = (
            f"site {entry.site} is {workspace.distance * 1e3:.2f} mm outside its "
            f"{'box' if entry.box is not None else 'sphere'} (at {np.round(workspace.where, 4).tolist()} "
            f"in frame {entry.frame})"
        )
        if not self._outside:
            self._outside = True
            self.record_fault(source, "check", reason)
        self.enter_hold(reason, source=source, level=workspace.levels[workspace.outside])

    def _publisher_failed(self, publish: Callable, exc: BaseException) -> None:
        name = getattr(publish, "__qualname__", repr(publish))
        self.record_fault(f"publisher:{name}", "publish", exc)
        self._publishers[:] = [p for p in self._publishers if p is not publish]

    def _no_driver_left(self) -> None:
        self.record_fault("loop", "check", "every driver has failed: nothing left to command")
        self.estop("every driver has failed", source="loop", event=SafetyEvent.FAULT)
        self.request_stop("no driver left")

    # ------------------------------------------------------------ the tick

    async def run(self, duration: float | None = None, *, ticks: int | None = None) -> dict:
        """Tick until ``duration`` seconds (or ``ticks`` deadlines) passed, or a stop request.

        Returns the report (see :meth:`report`).
        """
        if self.state != LoopState.ACTIVE:
            raise LifecycleError(f"run() in state {self.state.value!r}; use activate() or 'async with'")
        if duration is not None:
            if not (duration > 0 and math.isfinite(duration * 1e9)):
                raise ValueError(f"duration must be a finite number of seconds more than 0 (got {duration})")
            ticks = max(1, round(duration * 1e9 / self.period_ns))
        self._stop = False
        self.stop_reason = ""
        for slot in self.slots:
            slot.read_ns = slot.write_ns = slot.max_read_ns = slot.max_write_ns = 0
        self.state = LoopState.RUNNING
        self.event_loop = type(asyncio.get_running_loop()).__module__.partition(".")[0]  # asyncio or uvloop
        self._run_finished.clear()
        self.realtime = RealtimeState()
        try:
            if self.source.kind == "virtual":
                # a virtual clock runs flat out: SCHED_FIFO would starve the machine (and be throttled)
                rt = self.config.realtime
                asked = [
                    name
                    for name, value in (
                        ("priority", rt.priority),
                        ("lock_memory", rt.lock_memory),
                        ("cpus", rt.cpus),
                        ("spin_guard_us", rt.spin_guard_us),
                    )
                    if value
                ]
                if asked:  # by design, not a fault: a note, not a warning
                    self.realtime.applied["not_applied"] = f"{', '.join(asked)} (virtual clock)"
            else:
                self.realtime = apply_realtime(self.config.realtime)
            if self._heap_frozen:
                freeze_young()  # what open() and earlier runs left: young generations only
            watchdog = StallWatchdog(self, self.config.loop.stall_timeout_ms / 1e3)
            if self.watchdog is not None:
                self.watchdog.arm()
                log.info(
                    "watchdog process %d armed: %g ms",
                    cast(subprocess.Popen, self.watchdog.proc).pid,
                    self.watchdog.watchdog_ms,
                )
            with watchdog:
                try:
                    await self._tick_loop(ticks)
                except asyncio.CancelledError:
                    if not watchdog.fired:
                        raise
                    cast(
                        asyncio.Task, asyncio.current_task()
                    ).uncancel()  # the watchdog's cancel ends the run, not the caller
        finally:
            if self.watchdog is not None:
                self.watchdog.disarm()
                self._check_watchdog_process()
            self.stats.end()
            self.ticker.close()
            restore_realtime(self.realtime)
            if self.state == LoopState.RUNNING:
                self.state = LoopState.ACTIVE
            self._run_finished.set()
        return self.report()

    def watchdog_trouble(self) -> str:
        """Why the watchdog process could not stop the robot now ("" when it could, or where
        none runs): dead, stopped, or not armed while the loop runs. Reads /proc: off the tick."""
        watchdog = self.watchdog
        if watchdog is None:
            return ""
        trouble = watchdog.trouble()
        # once it acted it disarms itself: that is the fault of the stall, reset_faults() re-arms
        if not trouble and self.state == LoopState.RUNNING and not (watchdog.armed or watchdog.fired_ns):
            trouble = "the watchdog process is not armed"
        return trouble

    def _watchdog_checked(self, trouble: str) -> None:
        """Off the tick, the watchdog process was seen unable to act (or able again): a watchdog
        that could not stop the robot is a fault that holds it; rearm() waits for it."""
        if trouble:
            self.record_fault("watchdog", "check", f"{trouble}: nothing would stop the robot in a stall")
            self.enter_hold(trouble, source="watchdog")

    def _check_watchdog_process(self) -> None:
        """The watchdog process acted on the hardware (the tick had stopped): estop here too."""
        watchdog = self.watchdog
        if watchdog is not None and watchdog.fired_ns and self.level > SafetyLevel.ESTOP:
            self.record_fault(
                "watchdog",
                "tick",
                f"the tick stopped for more than {watchdog.watchdog_ms:g} ms: "
                "the watchdog process ran the drivers' safe actions",
            )
            self.estop("the watchdog process acted", source="watchdog", event=SafetyEvent.WATCHDOG)

    def _after_gap(self, gap_ns: int) -> None:
        """This tick started ``gap_ns`` after the one before (the drivers have just been read):
        more than ``max_tick_gap_ns`` is a stall. Nothing computed across it is written: the
        robot holds where it is measured, at rest, with a fault naming the stall; the
        controller, replaced by ``hold``, never sees its time jump. Where the watchdog
        process acted meanwhile, the robot is e-stopped instead."""
        self._check_watchdog_process()
        if gap_ns <= self.max_tick_gap_ns:
            return
        cause = f"the tick stalled for {gap_ns / 1e6:.1f} ms (more than {self.max_tick_gap_ns / 1e6:g} ms)"
        self.record_fault("loop", "stall", cause)
        if self.level < SafetyLevel.HOLD:
            return  # nothing is commanded; rearm() starts from the measured position
        self.resync_joints(slice(None), np.ones(self.robot.dof, dtype=bool))
        self._last_update_k = self.robot.clock.tick - 1
        self.enter_hold(cause, source="loop")

    async def _tick_loop(self, ticks: int | None) -> None:
        self.stats.reset()
        robot, stats, ticker, limiter = self.robot, self.stats, self.ticker, self.limiter
        clock = robot.clock
        period_s, period_ns = self.period_s, self.period_ns
        mask = stats.mask
        lat_buf, work_buf = stats.lateness, stats.work
        ph_read, ph_check, ph_control, ph_limits, ph_write, ph_publish = stats.phases
        first_lateness = stats.first_lateness
        mono = time.monotonic_ns
        now_ns = self.source.now_ns
        publishers = self._publishers
        multirate = self.multirate
        heartbeat = self._heartbeat
        workspace = self.workspace
        feedforward = self.feedforward

        ticker.start(lead_ns=period_ns)
        self._missed_before = ticker.missed
        max_gap = self.max_tick_gap_ns
        last_woke = now_ns()  # the first tick comes one period from here
        stats.begin()
        k_start = self._k_start
        stop_k = None if ticks is None else ticker.k + ticks
        count = stats.count
        while not self._stop:
            k = ticker.poll() or await ticker.next()  # lockstep: no coroutine when nothing is awaited
            if stop_k is not None and k > stop_k:
                # a stall skipped past the run's last deadline: the deadlines after it are not
                # the run's, so they are not counted as missed, and tick k is not run
                ticker.missed -= k - stop_k - 1
                break
            woke = now_ns()
            t0 = mono()
            lateness = woke - ticker.deadline_ns
            clock.tick = k
            clock.now_ns = woke
            heartbeat[0] = k  # for the watchdog process: two stores, no system call
            heartbeat[1] = t0
            gap = woke - last_woke
            last_woke = woke

            # read and write are spelled out, not factored: a helper call per driver per
            # phase costs more than the lines it would save on this path
            for slot in self._active:
                if k % slot.every:  # a driver slower than the loop ([[driver]] every)
                    continue
                a = mono()
                try:
                    await slot.driver.read()
                except Exception as exc:
                    self._driver_failed(slot, "read", exc)
                d = mono() - a
                slot.read_ns += d
                if d > slot.max_read_ns:
                    slot.max_read_ns = d
            if gap > max_gap or heartbeat[3]:  # a stall, or the watchdog process acted: see why
                self._after_gap(gap)
            t1 = mono()

            for slot in self._active:
                if k - slot.driver.view.fresh_tick > slot.max_age:
                    self._check_feedback(k)
                    break
            else:
                if self._stale_drivers:
                    self._stale_drivers.clear()
            if not self._active:
                self._no_driver_left()
                break
            if workspace is not None:
                if not workspace.check():
                    self._left_workspace(workspace)
                elif self._outside:
                    self._outside = False
            t2 = mono()

            if self.level < SafetyLevel.HOLD:  # emergency stop: keep reading, command nothing
                t3 = t4 = t5 = mono()
            else:
                # hold, the HAL's own safety controller, runs on every tick whatever ``every``
                if multirate is None or multirate.due(k) or self.controller is self._hold:
                    try:
                        # never None while ticking (configure() set it); no cast call in the tick
                        self.controller.update((k - k_start) * period_s, (k - self._last_update_k) * period_s)  # type: ignore[union-attr]
                    except Exception as exc:
                        self._controller_failed("update", exc)
                    self._last_update_k = k
                    if multirate is not None:
                        multirate.capture(k)
                else:
                    multirate.fill(k)
                if feedforward is not None:
                    feedforward.apply()
                t3 = mono()

                if not limiter.apply():
                    if not self._refusing:  # once per episode, not once per tick
                        self._refusing = True
                        self._controller_failed("limits", "command is not finite (NaN or inf)")
                        limiter.apply()
                elif self._refusing:
                    self._refusing = False
                t4 = mono()

                for slot in self._active:
                    if k % slot.every:
                        continue
                    a = mono()
                    try:
                        await slot.driver.write()
                    except Exception as exc:
                        self._driver_failed(slot, "write", exc)
                    d = mono() - a
                    slot.write_ns += d
                    if d > slot.max_write_ns:
                        slot.max_write_ns = d
                t5 = mono()

            for publish in publishers:
                try:
                    publish(self)
                except Exception as exc:
                    self._publisher_failed(publish, exc)
            t6 = mono()

            i = count & mask
            work = t6 - t0
            lat_buf[i] = lateness
            work_buf[i] = work
            ph_read[i] = t1 - t0
            ph_check[i] = t2 - t1
            ph_control[i] = t3 - t2
            ph_limits[i] = t4 - t3
            ph_write[i] = t5 - t4
            ph_publish[i] = t6 - t5
            if count < 100:
                first_lateness.append(lateness)
                if count == 0:
                    stats.first_tick_ns = woke
            stats.last_tick_ns = woke
            if lateness > stats.max_lateness:
                stats.max_lateness = lateness
            if work > stats.max_work:
                stats.max_work = work
            if work > period_ns:
                stats.overruns += 1
            count += 1
            stats.count = count
            if stop_k is not None and k >= stop_k:
                break
        if not self.stop_reason:
            self.stop_reason = "stop requested" if self._stop else "duration reached"

    # ------------------------------------------------------------ report

    def report(self) -> dict:
        """Timing, faults, drivers and the controller's own metrics of the run so far."""
        stats = self.stats
        summary = stats.summary()
        n = stats.count
        span = (stats.last_tick_ns - stats.first_tick_ns) / 1e9
        achieved = (n - 1) / span if n > 1 and span > 0 else float("nan")
        target = 1e9 / self.period_ns
        controller = self.controller
        metrics: dict[str, Any] = {"type": self.controller_type}
        if self._given_controller is None and self.config.controller.type != self.controller_type:
            metrics["configured"] = self.config.controller.type
        if self.multirate is not None:
            metrics.update(
                every=self.multirate.every, extrapolate=self.multirate.extrapolate, updates=self.multirate.updates
            )
        if controller is not None:
            try:
                metrics.update(controller.metrics())
            except Exception as exc:
                metrics["metrics_error"] = f"{type(exc).__name__}: {exc}"
        drivers = {}
        for slot in self.slots:
            try:
                health = slot.driver.health()
            except Exception as exc:
                health = {"health_error": str(exc)}
            drivers[slot.name] = {
                "type": slot.type,
                "status": slot.status.value,
                "joints": len(slot.driver.view.joint_names),
                "read_us_mean": round(slot.read_ns / n / 1e3, 2) if n else None,
                "write_us_mean": round(slot.write_ns / n / 1e3, 2) if n else None,
                "read_us_max": round(slot.max_read_ns / 1e3, 2),
                "write_us_max": round(slot.max_write_ns / 1e3, 2),
                **health,
            }
        return {
            "robot": self.robot.name,
            "joints": self.robot.dof,
            "clock": self.source.kind,
            "event_loop": self.event_loop,
            **self._waits(),
            "overrun_policy": self.config.loop.overrun,
            "realtime": self.realtime.report() if self.realtime else {},
            "rate_hz_target": round(target, 3),
            "rate_hz_achieved": round(achieved, 3),
            "ticks": n,
            "missed_ticks": self.ticker.missed - self._missed_before,
            "duration_s": round(span, 4),
            **summary,
            "safety_level": self.level.name.lower(),
            "safety_worst": self.worst_level.name.lower(),
            "safety": [t.as_dict() for t in self.safety.transitions],
            "stop_reason": self.stop_reason,
            "commands_refused": self.limiter.refused,
            "faults": [f.as_dict() for f in self.faults],
            "drivers": drivers,
            "controller": metrics,
        }

    def _waits(self) -> dict:
        """How the timerfd's waits went: blocked on the timer, or round the event loop."""
        source = self.source
        if not isinstance(source, TimerfdTickSource):
            return {}
        return {"waits": {"on_timer": source.idle_waits, "through_loop": source.loop_waits}}


class StallWatchdog:
    """A thread that notices when the tick stops advancing (a driver awaiting forever, a
    blocking call) and then emergency-stops every driver and cancels the run.

    It only reads an integer per check: nothing is added to the tick. A stall of the whole
    process (the GIL held by C code, a frozen VM) needs the external watchdog of the safety
    layer; this one covers the event loop being stuck inside an ``await``.
    """

    def __init__(self, control: ControlLoop, timeout_s: float) -> None:
        self.control = control
        self.timeout_s = timeout_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task | None = None
        self.fired = False
        #: how often it looks (the tick counter, the watchdog process): a few times a timeout
        self.check_s = min(timeout_s / 4, 0.05) if timeout_s > 0 else 0.05

    def __enter__(self) -> StallWatchdog:
        if self.timeout_s > 0 or self.control.watchdog is not None:
            self._loop = asyncio.get_running_loop()
            self._task = asyncio.current_task()
            self._thread = threading.Thread(target=self._watch, name="aiohal-watchdog", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _watch(self) -> None:
        loop = cast(asyncio.AbstractEventLoop, self._loop)  # set by __enter__, before this thread starts
        stats = self.control.stats
        last, since = -1, time.monotonic()
        trouble = ""
        while not self._stop.wait(self.check_s):
            count = stats.count
            now = time.monotonic()
            if self.control.watchdog is not None:  # watched in turn: dead or stopped holds the robot
                seen = self.control.watchdog_trouble()
                if seen != trouble:
                    trouble = seen
                    loop.call_soon_threadsafe(self.control._watchdog_checked, trouble)
            if count != last:
                last, since = count, now
            elif self.timeout_s > 0 and now - since > self.timeout_s:
                self.fired = True
                # synchronous, from this thread: the loop may be stuck
                self.control.estop(
                    f"no tick for {self.timeout_s * 1e3:g} ms", source="watchdog", event=SafetyEvent.WATCHDOG
                )
                loop.call_soon_threadsafe(self._cancel)
                return

    def _cancel(self) -> None:
        self.control.record_fault("loop", "tick", f"no tick for {self.timeout_s * 1e3:g} ms: emergency stop")
        self.control.request_stop("stalled")
        if self._task is not None:
            self._task.cancel()
