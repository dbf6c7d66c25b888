"""The safety supervisor: keeps the robot at the level its state allows.

It owns what decides whether and how the robot moves: the safety machine and its record of
faults, the user's requests (estop, hold, reset_faults, rearm), the checks the tick calls at
fixed points (a stall between two ticks, stale feedback, a site outside its workspace), what
happens when a driver or the controller fails (isolated; the robot held or e-stopped), which
controller commands (the configured one, or ``hold``), and both watchdogs: the stall thread
(:mod:`.stall`) and the watchdog process (:mod:`.watchdog`), which it watches in turn.

The loop (:mod:`aiohal.core.loop`) keeps the lifecycle and the tick; the tick reads two attributes
of the supervisor, :attr:`Supervisor.level` and :attr:`Supervisor.controller`, and calls it
only when something is wrong.
"""

from __future__ import annotations

import logging
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, cast

import numpy as np

from ..core.lifecycle import DriverStatus
from ..hal import Controller
from ..logutil import RateLimitedLogger
from ..robot import DriverEvents, Fault, Mode
from .levels import FaultRecord, SafetyEvent, SafetyLevel, SafetyMachine, SafetyRequestRefused
from .watchdog import WORDS, WatchdogProcess

if TYPE_CHECKING:
    from ..config import Config
    from ..core.lifecycle import DriverSlot, LoopState
    from ..core.limits import CommandLimiter
    from ..core.target_extrapolation import TargetExtrapolator
    from ..core.tick_timing import TickStats
    from ..core.ticker import TickSource
    from ..robot import Robot
    from .workspace import WorkspaceMonitor

log = logging.getLogger("aiohal.core.loop")  # the robot's one voice in the log, as before the split


class Owner(Protocol):
    """What the supervisor uses of the loop it keeps safe (:class:`aiohal.core.loop.ControlLoop`)."""

    config: Config
    robot: Robot
    limiter: CommandLimiter
    extrapolator: TargetExtrapolator | None
    source: TickSource
    stats: TickStats
    period_ns: int
    period_s: float
    state: LoopState
    slots: list[DriverSlot]
    active: list[DriverSlot]  # the drivers read and written (not failed)
    k_start: int  # the controller's time counts from this tick
    last_update_k: int  # the tick the controller was last updated

    def request_stop(self, reason: str = ...) -> None: ...


class Supervisor:
    """The safety side of one :class:`~aiohal.core.loop.ControlLoop` (see the module)."""

    def __init__(self, loop: Owner) -> None:
        config = loop.config
        self.loop = loop
        self.robot = loop.robot
        self.limiter = loop.limiter
        #: the safety state machine; ``level`` mirrors its level for the tick
        self.machine = SafetyMachine(SafetyLevel[config.safety.fault_level.upper()])
        self.level = SafetyLevel.OFF
        #: the most severe level since activation: the report's "safety_worst"
        self.worst_level = SafetyLevel.OFF
        self.faults: list[FaultRecord] = []
        self._faults_reset_at = 0  # faults recorded before this index were cleared by reset_faults()
        #: who commands: the configured controller, or ``hold`` (set by :meth:`attach`)
        self.controller: Controller | None = None
        self.controller_type = config.controller.type
        self.hold_controller: Controller | None = None
        self._configured: tuple[Controller, str] | None = None  # what rearm() restarts
        #: the configured controller's type (the report names it when ``hold`` commands instead)
        self.configured_type = config.controller.type
        #: a tick that starts longer than this after the one before is a stall (hold, a fault)
        gap_ms = config.safety.max_tick_gap_ms
        if gap_ms is None:
            gap_ms = max(config.safety.watchdog_ms, 3 * loop.period_ns / 1e6)
        self.max_tick_gap_ns = round(gap_ms * 1e6)
        self.watchdog: WatchdogProcess | None = None
        #: the tick's heartbeat: two int64 stores per tick; shared with the watchdog process
        #: when one runs, else a private page nobody reads
        self.heartbeat = memoryview(bytearray(WORDS * 8)).cast("q")
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
        self.stale_drivers: set[str] = set()
        self.refusing = False  # the limiter refuses the controller's commands (once per episode)
        self._warn = RateLimitedLogger(log)

    def attach(self, controller: Controller, controller_type: str, hold: Controller) -> None:
        """The configured controller (what :meth:`rearm` restarts) and the HAL's ``hold``."""
        self.controller, self.controller_type = controller, controller_type
        self._configured = (controller, controller_type)
        self.configured_type = controller_type
        self.hold_controller = hold

    # ------------------------------------------------------------ levels and faults

    def event(self, event: SafetyEvent, source: str, cause: str, level: SafetyLevel | None = None) -> bool:
        """Fire ``event`` on the safety machine; the tick reads the level from ``self.level``."""
        changed = self.machine.fire(event, self.robot.clock.tick, source, cause, level)
        self.level = self.machine.level
        if self.level != SafetyLevel.OFF and (self.worst_level == SafetyLevel.OFF or self.level < self.worst_level):
            self.worst_level = self.level  # the lowest level reached while running, for the exit status
        return changed

    def record_fault(
        self, source: str, phase: str, exc: BaseException | str, *, condition: bool = False
    ) -> FaultRecord:
        """Record and log a fault; it appears in the report and makes the CLI exit 1.
        ``condition``: one a driver reported (logged as what it is, not as a failure)."""
        error = exc if isinstance(exc, str) else f"{type(exc).__name__}: {exc}"
        record = FaultRecord(source, phase, self.robot.clock.tick, error, condition)
        self.faults.append(record)
        log.error("%s", record)
        return record

    # ------------------------------------------------------------ the user's requests

    def estop(self, cause: str = "requested", *, source: str = "user", event: SafetyEvent = SafetyEvent.ESTOP) -> None:
        """Trigger every driver's emergency stop now (synchronous; safe to call twice, and from
        another thread or a signal handler). The drivers are still read; nothing is commanded
        until :meth:`reset_faults` and :meth:`rearm`."""
        for slot in self.loop.slots:
            try:
                slot.driver.estop()
            except Exception as exc:
                self.record_fault(f"driver:{slot.name}", "estop", exc)
        if self.level > SafetyLevel.OFF:
            self.event(event, source, cause, SafetyLevel.ESTOP if event is SafetyEvent.FAULT else None)

    def hold(self, cause: str = "requested") -> None:
        """A user's request: replace the controller by ``hold`` (braking to rest, no jump)."""
        if self.machine.target(SafetyEvent.HOLD) is None:
            raise SafetyRequestRefused(f"hold from {self.level.name.lower()}: only from run")
        self.enter_hold(cause, source="user", event=SafetyEvent.HOLD)

    def reset_faults(self, source: str = "user") -> list[str]:
        """Clear latched faults: every driver's own (:meth:`Driver.reset_faults`), the joints'
        fault bits and the record of faults since the last reset. After an emergency stop,
        every driver must release it (:meth:`Driver.release_estop`): the robot is then
        ``disabled``, read but not commanded, until :meth:`rearm`. A watchdog process that
        acted is armed again. Returns what a driver reported resetting (e.g. EtherCAT drive
        names). Raises :class:`SafetyRequestRefused` with the reason when it cannot."""
        loop = self.loop
        if loop.state not in ("active", "running"):
            raise SafetyRequestRefused(f"reset_faults() with the loop {loop.state}")
        if self.machine.target(SafetyEvent.RESET_FAULTS) is None:
            raise SafetyRequestRefused(f"reset_faults() from {self.level.name.lower()}")
        # the joints' fault bits first: a driver whose cause persists sets them again in its
        # reset_faults() (or on its next read), and rearm() is refused while one is set
        for slot in loop.active:
            self.robot.state.fault[slot.driver.view.rows] = 0
        reset: list[str] = []
        for slot in loop.active:
            try:
                names = slot.driver.reset_faults()
            except Exception as exc:
                self.record_fault(f"driver:{slot.name}", "reset_faults", exc)
                continue
            if isinstance(names, (list, tuple)):
                reset += [str(n) for n in names]
        if self.level == SafetyLevel.ESTOP:
            kept = []
            for slot in loop.active:
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
        watchdog = self.watchdog
        if watchdog is not None and loop.state == "running" and not watchdog.trouble():
            watchdog.arm()  # after it acted (it disarms itself then): watching again
        self.stale_drivers.clear()
        self.refusing = False
        cleared = len(self.faults) - self._faults_reset_at
        self._faults_reset_at = len(self.faults)
        self.event(SafetyEvent.RESET_FAULTS, source, f"{cleared} fault(s) cleared")
        log.info("robot %s: %d fault(s) cleared, level %s", self.robot.name, cleared, self.level.name.lower())
        return reset

    def active_faults(self) -> list[str]:
        """Why :meth:`rearm` would be refused now (empty: it would not)."""
        loop, reasons = self.loop, []
        failed = [s.name for s in loop.slots if s.status in (DriverStatus.FAILED, DriverStatus.ABANDONED)]
        if failed:
            reasons.append(f"driver(s) {', '.join(failed)} failed (isolated until the loop is started again)")
        if len(self.faults) > self._faults_reset_at:
            reasons.append(f"{len(self.faults) - self._faults_reset_at} fault(s) since the last reset_faults()")
        k, max_age = self.robot.clock.tick, loop.config.loop.max_feedback_age
        stale = [s.name for s in loop.active if k - s.driver.view.fresh_tick > max_age]
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
        loop = self.loop
        if loop.state not in ("active", "running"):
            raise SafetyRequestRefused(f"rearm() with the loop {loop.state}")
        if self.machine.target(SafetyEvent.REARM) is None:
            hint = ": reset_faults() first" if self.level == SafetyLevel.ESTOP else ""
            raise SafetyRequestRefused(f"rearm() from {self.level.name.lower()}{hint}")
        reasons = self.active_faults()
        if reasons:
            raise SafetyRequestRefused("rearm() refused: " + "; ".join(reasons))
        if self._configured is None:
            raise SafetyRequestRefused("rearm() before configure()")
        cmd, measured = self.robot.command, self.robot.state.position
        if self.level == SafetyLevel.DISABLED:
            cmd.rest_at(measured)
            self.limiter.reset(measured)
        controller, controller_type = self._configured
        self.controller, self.controller_type = controller, controller_type
        self.event(SafetyEvent.REARM, source, f"{controller_type} restarted from the measured state")
        log.info("robot %s re-armed: %s restarted from the measured state", self.robot.name, controller_type)
        k = self.robot.clock.tick
        loop.last_update_k = k
        if loop.extrapolator is not None:
            loop.extrapolator.force()
        try:
            controller.start((k - loop.k_start) * loop.period_s)
        except Exception as exc:
            self.controller_failed("start", exc)

    # ------------------------------------------------------------ holding

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
        to = self.machine.target(event, level)
        if to is None:
            return
        if to < SafetyLevel.HOLD:
            self.estop(reason, source=source, event=event)
            return
        log.warning("robot %s goes to hold: %s", self.robot.name, reason)
        self.event(event, source, reason)
        old = self.controller
        if old is not None and old is not self.hold_controller:
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
        hold = cast(Controller, self.hold_controller)  # set by attach(), before any level but off
        self.controller = hold
        self.controller_type = "hold"
        # the last command was sent one period ago: hold's motion starts there
        hold.start((self.robot.clock.tick - self.loop.k_start - 1) * self.loop.period_s)

    def events_of(self, name: str, rows: slice) -> DriverEvents:
        """What driver ``name``'s view sends here (:meth:`DriverView.fault`, ``resync``)."""
        return _DriverEvents(self, name, rows)

    def resync_joints(self, rows: slice, mask: np.ndarray) -> None:
        """Joints ``mask`` of the driver rows ``rows`` were (re-)enabled where they stand: their
        command continues from the measured position at rest, so nothing jumps. Under ``hold``
        every joint's hold restarts from its current command (the others continue braking)."""
        loop = self.loop
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
        if loop.extrapolator is not None:  # the controller sees the change this tick, not its old command
            loop.extrapolator.force()
        if self.controller is self.hold_controller and loop.state in ("active", "running"):
            cast(Controller, self.hold_controller).start((self.robot.clock.tick - loop.k_start) * loop.period_s)

    # ------------------------------------------------------------ what the tick reports

    def after_gap(self, gap_ns: int) -> None:
        """This tick started ``gap_ns`` after the one before (the drivers have just been read):
        more than ``max_tick_gap_ns`` is a stall. Nothing computed across it is written: the
        robot holds where it is measured, at rest, with a fault naming the stall; the
        controller, replaced by ``hold``, never sees its time jump. Where the watchdog
        process acted meanwhile, the robot is e-stopped instead."""
        self.check_watchdog_process()
        if gap_ns <= self.max_tick_gap_ns:
            return
        cause = f"the tick stalled for {gap_ns / 1e6:.1f} ms (more than {self.max_tick_gap_ns / 1e6:g} ms)"
        self.record_fault("loop", "stall", cause)
        if self.level < SafetyLevel.HOLD:
            return  # nothing is commanded; rearm() starts from the measured position
        self.resync_joints(slice(None), np.ones(self.robot.dof, dtype=bool))
        self.loop.last_update_k = self.robot.clock.tick - 1
        self.enter_hold(cause, source="loop")

    def check_feedback(self, k: int) -> None:
        """Some driver's feedback is older than its ``max_age`` ticks: flag it, hold, report once."""
        stale = [s for s in self.loop.active if k - s.driver.view.fresh_tick > s.max_age]
        for slot in stale:
            view = slot.driver.view
            self.robot.state.fault[view.rows] |= np.uint32(Fault.STALE)
            if slot.name not in self.stale_drivers:
                self.stale_drivers.add(slot.name)
                self.record_fault(
                    f"driver:{slot.name}", "check", f"feedback is stale ({k - view.fresh_tick} ticks old)"
                )
        if stale:
            self.enter_hold("stale feedback from " + ", ".join(s.name for s in stale), source="feedback")
            self._warn.warning("stale", "feedback still stale from %s", ", ".join(s.name for s in stale))
        else:
            self.stale_drivers.clear()

    def check_workspace(self, workspace: WorkspaceMonitor) -> None:
        """Each tick where workspace limits are configured: a site outside its shape takes the
        robot to its entry's level, the site and distance recorded once per excursion. Not
        commanding (estop, disabled), there is nothing to stop; rearm() waits for the site."""
        if workspace.check():
            self._outside = False
            return
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

    def command_refused(self) -> bool:
        """The limiter refused this tick's command (not finite). On the first tick of such an
        episode the controller fails (hold takes over and commands this tick): True, the
        command must be limited again."""
        if self.refusing:
            return False
        self.refusing = True
        self.controller_failed("limits", "command is not finite (NaN or inf)")
        return True

    def driver_failed(self, slot: DriverSlot, phase: str, exc: BaseException) -> None:
        """A driver raised: recorded, e-stopped, isolated (never read or written again), its
        joints faulted, the robot held."""
        self.record_fault(f"driver:{slot.name}", phase, exc)
        slot.status = DriverStatus.FAILED
        try:
            slot.driver.estop()
        except Exception as estop_exc:
            self.record_fault(f"driver:{slot.name}", "estop", estop_exc)
        self.robot.state.fault[slot.driver.view.rows] |= np.uint32(Fault.DRIVER)
        self.loop.active = [s for s in self.loop.active if s is not slot]
        self.enter_hold(f"driver {slot.name} failed in {phase}", source=f"driver:{slot.name}")

    def controller_failed(self, phase: str, exc: BaseException | str) -> None:
        """The controller raised or wrote a non-finite command: hold, and command this tick."""
        source = f"controller:{self.controller_type}"
        self.record_fault(source, phase, exc)
        self.enter_hold(f"controller {self.controller_type} failed in {phase}", source=source)
        if self.level < SafetyLevel.HOLD:
            return
        t = (self.robot.clock.tick - self.loop.k_start) * self.loop.period_s
        try:
            cast(Controller, self.hold_controller).update(t, self.loop.period_s)
        except Exception as hold_exc:  # hold is simple enough never to get here
            self.record_fault("controller:hold", "update", hold_exc)
            self.estop("hold failed", source="controller:hold", event=SafetyEvent.FAULT)

    def no_driver_left(self) -> None:
        self.record_fault("loop", "check", "every driver has failed: nothing left to command")
        self.estop("every driver has failed", source="loop", event=SafetyEvent.FAULT)
        self.loop.request_stop("no driver left")

    # ------------------------------------------------------------ the watchdog process

    def start_watchdog(self) -> None:
        """The watchdog process, when some driver declares a safe action and time is real."""
        loop, safety = self.loop, self.loop.config.safety
        actions = [(f"driver:{slot.name}", action) for slot in loop.slots for action in slot.driver.safe_actions()]
        if not (safety.watchdog and actions) or loop.source.kind == "virtual":
            return
        priority = safety.watchdog_priority
        if priority is None:  # above the loop's own, so that it runs when the loop does not
            loop_priority = loop.config.realtime.priority
            priority = min(99, loop_priority + 1) if loop_priority else 0
        watchdog = WatchdogProcess(actions, safety.watchdog_ms, priority)
        watchdog.start()
        self.watchdog = watchdog
        self.heartbeat = cast(memoryview, watchdog.heartbeat)  # mapped by start()

    def stop_watchdog(self) -> None:
        watchdog, self.watchdog = self.watchdog, None
        if watchdog is not None:
            self.heartbeat = memoryview(bytearray(WORDS * 8)).cast("q")
            watchdog.stop()

    def arm_watchdog(self) -> None:
        """A run starts: the watchdog process watches the heartbeat from now."""
        if self.watchdog is not None:
            self.watchdog.arm()
            log.info(
                "watchdog process %d armed: %g ms",
                cast(subprocess.Popen, self.watchdog.proc).pid,
                self.watchdog.watchdog_ms,
            )

    def disarm_watchdog(self) -> None:
        """A run ends: the heartbeat stops on purpose."""
        if self.watchdog is not None:
            self.watchdog.disarm()
            self.check_watchdog_process()

    def watchdog_trouble(self) -> str:
        """Why the watchdog process could not stop the robot now ("" when it could, or where
        none runs): dead, stopped, or not armed while the loop runs. Reads /proc: off the tick."""
        watchdog = self.watchdog
        if watchdog is None:
            return ""
        trouble = watchdog.trouble()
        # once it acted it disarms itself: that is the fault of the stall, reset_faults() re-arms
        if not trouble and self.loop.state == "running" and not (watchdog.armed or watchdog.fired_ns):
            trouble = "the watchdog process is not armed"
        return trouble

    def watchdog_checked(self, trouble: str) -> None:
        """Off the tick, the watchdog process was seen unable to act (or able again): a watchdog
        that could not stop the robot is a fault that holds it; rearm() waits for it."""
        if trouble:
            self.record_fault("watchdog", "check", f"{trouble}: nothing would stop the robot in a stall")
            self.enter_hold(trouble, source="watchdog")

    def check_watchdog_process(self) -> None:
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


class _DriverEvents(DriverEvents):
    """One driver's reports, to the supervisor: a fault is recorded with the driver's name
    and, when it asks, holds the robot; re-enabled joints continue where they stand."""

    def __init__(self, supervisor: Supervisor, name: str, rows: slice) -> None:
        self.supervisor = supervisor
        self.name = name
        self.source = f"driver:{name}"
        self.rows = rows

    def fault(self, phase: str, reason: str, hold: bool) -> None:
        supervisor = self.supervisor
        supervisor.record_fault(self.source, phase, reason, condition=True)
        if hold and supervisor.level > SafetyLevel.HOLD:
            supervisor.enter_hold(f"{self.name}: {reason}", source=self.source)

    def resync(self, mask: np.ndarray) -> None:
        self.supervisor.resync_joints(self.rows, mask)
