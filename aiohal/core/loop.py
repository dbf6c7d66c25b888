"""The control loop: lifecycle and the tick.

One tick, in order::

    wake (absolute deadline k) -> read every driver -> check feedback -> controller.update
    (or, with ``[controller] every = n``, on the ticks between two updates: the last command
    with its position targets extrapolated, see :mod:`aiohal.core.target_extrapolation`)
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
import logging
import math
import time
from collections.abc import Callable
from typing import Any, cast

import numpy as np

from ..config import Config
from ..config import from_parts as config_from_parts
from ..errors import LifecycleError
from ..hal import Controller
from ..outside.doorkeeper import Doorkeeper
from ..outside.port import LoopPort
from ..robot import Mode
from ..safety import FaultRecord, SafetyEvent, SafetyLevel
from ..safety.stall import StallWatchdog
from ..safety.supervisor import Supervisor
from ..safety.watchdog import FIRED, STAMP, TICK, WatchdogProcess
from . import lifecycle
from .feedforward import VelocityFeedforward, gains_of
from .lifecycle import DriverSlot, LoopState
from .limits import CommandLimiter
from .realtime import RealtimeState, apply_for_clock, freeze_heap, freeze_young, thaw_heap
from .realtime import restore as restore_realtime
from .run_report import build as build_report
from .target_extrapolation import TargetExtrapolator
from .tick_timing import TickStats
from .ticker import Ticker, TickSource, make_source

assert (TICK, STAMP, FIRED) == (0, 1, 3)  # the tick stores heartbeat[0], [1] and reads [3]

log = logging.getLogger(__name__)


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
        self.extrapolator = (
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
        self.slots: list[DriverSlot] = []
        self.active: list[DriverSlot] = []
        self._given_controller = controller
        self._given_params = controller_params
        self._publishers: list[Callable[[ControlLoop], None]] = []
        self._stop = False
        self.stop_reason = ""
        self.state = LoopState.CREATED
        #: the controller's time counts from this tick; the tick it was last updated
        self.k_start = 0
        self.last_update_k = 0
        #: safety: levels, faults, requests, checks, which controller commands, the watchdogs
        self.supervisor = Supervisor(self)
        self._run_finished = asyncio.Event()
        self._missed_before = 0
        self._heap_frozen = False
        #: what everything outside the tick is given of this loop (aiohal.outside.port)
        self.port = LoopPort(self)
        self.doors: Doorkeeper | None = None
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
        lifecycle.check_given_controller(self.config, self._given_controller, self._given_params)
        self.slots = lifecycle.build_slots(self.config, self.robot, self.supervisor.events_of)
        controller, controller_type, hold = lifecycle.build_controllers(
            self.config, self.robot, self._given_controller, self._given_params
        )
        self.supervisor.attach(controller, controller_type, hold)
        self.doors = Doorkeeper(self.port)  # shared memory and bridges, as configured
        self.state = LoopState.CONFIGURED

    async def activate(self) -> None:
        """Open every driver, read once, start from the measured state, start the controller."""
        if self.state == LoopState.CREATED:
            self.configure()
        if self.state != LoopState.CONFIGURED:
            raise LifecycleError(f"activate() in state {self.state.value!r}")
        clock = self.robot.clock
        clock.kind = self.source.kind
        clock.ticker = self.ticker
        clock.tick = 0
        clock.now_ns = self.source.now_ns()
        if self.config.loop.gc == "freeze":
            freeze_heap()  # the one full collection, before any driver has a thread to feed
            self._heap_frozen = True
        try:
            await lifecycle.open_drivers(self.slots, self.record_fault)
            self.supervisor.start_watchdog()
        except BaseException:
            self.estop("bring-up failed", source="loop")
            await self._close_drivers()
            self.state = LoopState.CLOSED
            raise
        state = self.robot.state
        self.active = list(self.slots)
        cmd = self.robot.command
        cmd.rest_at(state.position)
        cmd.mode[cmd.mode == Mode.NONE] = Mode.POSITION
        self.limiter.reset(state.position)
        self.supervisor.event(SafetyEvent.ACTIVATE, "loop", "drivers open, controller started")
        self.state = LoopState.ACTIVE
        self.k_start = 0  # controller time counts from activation, across run() calls
        self.last_update_k = 0
        if self.extrapolator is not None:
            self.extrapolator.force()
        try:
            cast(Controller, self.controller).start(0.0)  # set by configure()
        except Exception as exc:
            self.supervisor.controller_failed("start", exc)
        cast(Doorkeeper, self.doors).activate()

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
        self.supervisor.event(SafetyEvent.DEACTIVATE, "loop", "drivers closed")
        self.state = LoopState.CLOSED

    async def _close_drivers(self) -> None:
        self.supervisor.stop_watchdog()
        await lifecycle.close_drivers(self.slots, self.config.loop.close_timeout_ms / 1e3, self.record_fault)
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

    # ------------------------------------------------------------ safety (aiohal.safety.supervisor)

    @property
    def level(self) -> SafetyLevel:
        """The safety level now (``off < estop < disabled < hold < run``)."""
        return self.supervisor.level

    @property
    def worst_level(self) -> SafetyLevel:
        return self.supervisor.worst_level

    @property
    def faults(self) -> list[FaultRecord]:
        return self.supervisor.faults

    @property
    def controller(self) -> Controller | None:
        """The controller commanding now: the configured one, or ``hold``."""
        return self.supervisor.controller

    @property
    def controller_type(self) -> str:
        return self.supervisor.controller_type

    @property
    def watchdog(self) -> WatchdogProcess | None:
        return self.supervisor.watchdog

    def estop(self, cause: str = "requested", *, source: str = "user", event: SafetyEvent = SafetyEvent.ESTOP) -> None:
        """Trigger every driver's emergency stop now (synchronous; safe to call twice, and from
        another thread or a signal handler). See :meth:`Supervisor.estop`."""
        self.supervisor.estop(cause, source=source, event=event)

    def hold(self, cause: str = "requested") -> None:
        """Replace the controller by ``hold`` (braking to rest, no jump); only from ``run``."""
        self.supervisor.hold(cause)

    def reset_faults(self, source: str = "user") -> list[str]:
        """Clear latched faults; after an emergency stop, release it (the robot is then
        ``disabled`` until :meth:`rearm`). See :meth:`Supervisor.reset_faults`."""
        return self.supervisor.reset_faults(source)

    def active_faults(self) -> list[str]:
        """Why :meth:`rearm` would be refused now (empty: it would not)."""
        return self.supervisor.active_faults()

    def rearm(self, source: str = "user") -> None:
        """Return to ``run`` without a jump when no fault is active. See :meth:`Supervisor.rearm`."""
        self.supervisor.rearm(source)

    def record_fault(self, source: str, phase: str, exc: BaseException | str) -> FaultRecord:
        """Record and log a fault; it appears in the report and makes the CLI exit 1."""
        return self.supervisor.record_fault(source, phase, exc)

    def resync_joints(self, rows: slice, mask: np.ndarray) -> None:
        """Joints re-enabled where they stand continue from there (``DriverView.resync``)."""
        self.supervisor.resync_joints(rows, mask)

    @property
    def max_tick_gap_ns(self) -> int:
        """A tick that starts longer than this after the one before is a stall."""
        return self.supervisor.max_tick_gap_ns

    def add_publisher(self, publish: Callable[[ControlLoop], None]) -> None:
        """Call ``publish(loop)`` at the end of every tick; it must not block."""
        self._publishers.append(publish)

    def remove_publisher(self, publish: Callable[[ControlLoop], None]) -> None:
        """Stop calling ``publish`` (from the next tick)."""
        self._publishers[:] = [p for p in self._publishers if p is not publish]

    @property
    def missed_ticks(self) -> int:
        """Deadlines missed in this run (or the last one)."""
        return self.ticker.missed - self._missed_before

    def _publisher_failed(self, publish: Callable, exc: BaseException) -> None:
        name = getattr(publish, "__qualname__", repr(publish))
        self.record_fault(f"publisher:{name}", "publish", exc)
        self.remove_publisher(publish)

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
            self.realtime = apply_for_clock(self.source.kind, self.config.realtime)
            if self._heap_frozen:
                freeze_young()  # what open() and earlier runs left: young generations only
            watchdog = StallWatchdog(self.supervisor, self.config.loop.stall_timeout_ms / 1e3)
            self.supervisor.arm_watchdog()
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
            self.supervisor.disarm_watchdog()
            self.stats.end()
            self.ticker.close()
            restore_realtime(self.realtime)
            if self.state == LoopState.RUNNING:
                self.state = LoopState.ACTIVE
            self._run_finished.set()
        return self.report()

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
        extrapolator = self.extrapolator
        supervisor = self.supervisor
        heartbeat = supervisor.heartbeat
        workspace = supervisor.workspace
        feedforward = self.feedforward

        ticker.start(lead_ns=period_ns)
        self._missed_before = ticker.missed
        max_gap = supervisor.max_tick_gap_ns
        last_woke = now_ns()  # the first tick comes one period from here
        stats.begin()
        k_start = self.k_start
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
            for slot in self.active:
                if k % slot.every:  # a driver slower than the loop ([[driver]] every)
                    continue
                a = mono()
                try:
                    await slot.driver.read()
                except Exception as exc:
                    supervisor.driver_failed(slot, "read", exc)
                d = mono() - a
                slot.read_ns += d
                if d > slot.max_read_ns:
                    slot.max_read_ns = d
            if gap > max_gap or heartbeat[3]:  # a stall, or the watchdog process acted: see why
                supervisor.after_gap(gap)
            t1 = mono()

            for slot in self.active:
                if k - slot.driver.view.fresh_tick > slot.max_age:
                    supervisor.check_feedback(k)
                    break
            else:
                if supervisor.stale_drivers:
                    supervisor.stale_drivers.clear()
            if not self.active:
                supervisor.no_driver_left()
                break
            if workspace is not None:
                supervisor.check_workspace(workspace)
            t2 = mono()

            if supervisor.level < SafetyLevel.HOLD:  # emergency stop: keep reading, command nothing
                t3 = t4 = t5 = mono()
            else:
                # hold, the HAL's own safety controller, runs on every tick whatever ``every``
                if extrapolator is None or extrapolator.due(k) or supervisor.controller is supervisor.hold_controller:
                    try:
                        # never None while ticking (configure() set it); no cast call in the tick
                        supervisor.controller.update((k - k_start) * period_s, (k - self.last_update_k) * period_s)  # type: ignore[union-attr]
                    except Exception as exc:
                        supervisor.controller_failed("update", exc)
                    self.last_update_k = k
                    if extrapolator is not None:
                        extrapolator.capture(k)
                else:
                    extrapolator.fill(k)
                if feedforward is not None:
                    feedforward.apply()
                t3 = mono()

                if not limiter.apply():
                    if supervisor.command_refused():  # once per episode: hold commands instead
                        limiter.apply()
                elif supervisor.refusing:
                    supervisor.refusing = False
                t4 = mono()

                for slot in self.active:
                    if k % slot.every:
                        continue
                    a = mono()
                    try:
                        await slot.driver.write()
                    except Exception as exc:
                        supervisor.driver_failed(slot, "write", exc)
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
        """Timing, faults, drivers and the controller's own metrics of the run so far
        (:func:`aiohal.core.run_report.build`)."""
        return build_report(self)
