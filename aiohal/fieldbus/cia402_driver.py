"""What a driver of CiA 402 drives does alike on every bus, off the tick.

Enabling the drives where they stand, fault reset, the emergency stop and its release, the
stop at shutdown, the wait for the drives at bring-up, the response to their events and
their part of ``health()``: one implementation for the EtherCAT and CANopen drivers. Each
driver keeps what its bus does differently (how a cycle is exchanged, SDO, NMT, bring-up)
and gives this class its hooks: :meth:`~Cia402Driver._bus_ready`,
:meth:`~Cia402Driver._send_holding`, :meth:`~Cia402Driver._cycle_holding`,
:meth:`~Cia402Driver._bringup_wait` and :meth:`~Cia402Driver._not_enabled_error`. The tick's ``read()`` and ``write()`` stay the
driver's own: nothing here runs on every cycle.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, ClassVar

import numpy as np

from aiohal.hal import Driver

from .cia402 import Cia402Drive, DriveEvent, EventKind, State, Target
from .drives import DriveGroup, respond_to_event

log = logging.getLogger(__name__)


class Cia402Driver(Driver):
    """A driver whose joints are CiA 402 drives (a :class:`~aiohal.fieldbus.drives.DriveGroup`)."""

    bus_name: ClassVar[str] = "cia402"  # "ethercat", "canopen": the logs' prefix

    drives: DriveGroup | None  # None on a bus without drives (sensors only), or before bring-up
    drive_faults: int  # faults the drives entered during the run
    _lock: threading.Lock  # one thread at a time on the bus's cycle and the drives' state
    _estop_requested: bool  # estop() was called: bring-up enables nothing
    _estop_sent: bool  # the quick stop is out (or left to the next cycle): estop() is done
    _enabled_at_close: int | None  # drives enabled as the run left them (health after close)
    _drive_mask: np.ndarray  # the joints respond_to_event has faulted

    def _init_drive_state(self) -> None:
        """Where the drives' part starts from: no drives yet, no stop asked (each bring-up)."""
        self.drives = None
        self.drive_faults = 0
        self._lock = threading.Lock()
        self._estop_requested = False
        self._estop_sent = False
        self._enabled_at_close = None
        self._drive_mask = np.zeros(self.view.dof, dtype=bool)

    @property
    def _label(self) -> str:
        return f"{self.bus_name} {self.name}"

    # ------------------------------------------------------------ the bus's hooks

    def _bus_ready(self) -> bool:
        """The bus is open and can carry a cycle now."""
        raise NotImplementedError

    def _send_holding(self) -> None:
        """Send one cycle now, without waiting for its answer, every drive held where it
        stands with the controlword it has; the lock is held."""
        raise NotImplementedError

    def _cycle_holding(self) -> None:
        """One whole cycle (outputs out, inputs in, the machines updated), every drive held
        where it stands; the lock is held. Blocking: bring-up and shutdown only."""
        raise NotImplementedError

    def _bringup_wait(self) -> None:
        """One step of the wait for the drives at bring-up: cycle the bus, or let the thread
        that does run; raises what ends the bring-up."""
        raise NotImplementedError

    def _not_enabled_error(self, timeout_s: float) -> Exception:
        """What the bring-up raises when the drives were not enabled in time (or an
        emergency stop came first); :meth:`_not_enabled` says which drives and why."""
        raise NotImplementedError

    # ------------------------------------------------------------ application API

    def enable_drives(self) -> None:
        """Enable every drive (a bus opened without enabling them); each starts where it stands."""
        if self.drives is not None and not self._estop_requested:
            with self._lock:
                self.drives.request(Target.ENABLED)

    def reset_faults(self) -> list[str]:
        """Grant one fault reset to every faulted drive and enable again those that left
        Operation enabled unasked; each is enabled where it stands. The names of those drives."""
        if self.drives is None or self._estop_requested:
            return []
        with self._lock:
            return self.drives.reset_and_enable()

    def release_estop(self) -> bool:
        """Leave the emergency stop: every drive (quick-stopped, then disabled by its ramp) gets
        a fault reset where it needs one and is enabled again where it stands, held there by
        the cycles until the loop, re-armed, commands it."""
        if self.drives is None or not self._bus_ready():
            return False
        with self._lock:
            self._estop_requested = False
            self._estop_sent = False
            self.drives.reset_faults()
            self.drives.request(Target.ENABLED)
        log.info("%s: emergency stop released; drives enabled where they stand", self._label)
        return True

    # ------------------------------------------------------------ safety and shutdown

    def estop(self) -> None:
        """Quick stop every drive: one cycle of controlwords 0x02 sent at once when the bus is
        free within 2 ms; otherwise the next cycle, the tick's or another thread's, carries
        it. Never blocks longer, never raises."""
        self._estop_requested = True  # a bring-up under way stops and enables nothing
        drives = self.drives
        if drives is None or self._estop_sent or not self._bus_ready():
            return
        self._estop_sent = True
        drives.request(Target.QUICK_STOP)
        if not self._lock.acquire(timeout=0.002):
            return
        try:
            drives.controlwords[:] = 0x02  # Quick stop (the machines take over next cycle)
            self._send_holding()
        except Exception as exc:  # never raise from estop
            log.error("%s: sending the quick stop failed: %s", self._label, exc)
        finally:
            self._lock.release()

    def _wait_enabled(self, timeout_s: float) -> None:
        """Bring-up: return once every drive is enabled; raise if one is not within
        ``timeout_s`` or an emergency stop comes first."""
        drives = self.drives
        assert drives is not None  # bring-up waits only when the bus has drives
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self._estop_requested:
            self._bringup_wait()
            if drives.all_enabled():
                return
        raise self._not_enabled_error(timeout_s)

    def _not_enabled(self) -> str:
        """The drives that are not enabled, with their state (and error code in Fault)."""
        if self.drives is None:
            return ""
        return ", ".join(_describe(m) for m in self.drives.machines if not m.enabled)

    def _stop_drives(self, budget_s: float, period_s: float) -> None:
        """Shutdown: quick stop every drive and wait for its ramp, then disable it, all
        within ``budget_s``, cycling the bus every ``period_s``."""
        drives = self.drives
        assert drives is not None  # stopped only when the bus has drives
        deadline = time.monotonic() + budget_s
        for target, done in ((Target.QUICK_STOP, _stopped), (Target.DISABLED, _disabled)):
            drives.request(target)
            while time.monotonic() < deadline:
                with self._lock:
                    self._cycle_holding()
                if all(done(m) for m in drives.machines):
                    break
                time.sleep(period_s)

    def _remember_enabled(self) -> None:
        """At close, before the shutdown disables them: how the run left the drives."""
        if self.drives is not None:
            self._enabled_at_close = sum(m.enabled for m in self.drives.machines)

    def _respond(self, i: int, event: DriveEvent, detail: str = "") -> None:
        """A drive's event in the run: counted when it is a fault, then the joint faulted,
        held or resynchronised as :func:`~aiohal.fieldbus.drives.respond_to_event` says."""
        drives = self.drives
        assert drives is not None  # only drives raise events
        if event.kind is EventKind.FAULT_ENTERED:
            self.drive_faults += 1
        respond_to_event(drives, i, event, self.view, self._drive_mask, self._label, detail)

    def _drives_health(self) -> dict[str, Any]:
        """The drives' part of ``health()``: how many are enabled (as the run left them, once
        closed) and the faults they entered."""
        if self.drives is None:
            return {}
        enabled = self._enabled_at_close
        if enabled is None:
            enabled = sum(m.enabled for m in self.drives.machines)
        return {"drives_enabled": f"{enabled}/{len(self.drives)}", "drive_faults": self.drive_faults}


def _stopped(machine: Cia402Drive) -> bool:
    return machine.state not in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)


def _disabled(machine: Cia402Drive) -> bool:
    return machine.state in (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT)


def _describe(machine: Cia402Drive) -> str:
    error = f" (error 0x{machine.error_code:04X})" if machine.faulted else ""
    return f"{machine.name} {machine.state.label}{error}"
