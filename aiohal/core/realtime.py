"""Optional real-time settings for the thread that ticks: SCHED_FIFO, mlockall, CPU affinity,
timer slack. Each one that fails (no permission, not Linux) becomes one warning, never a crash.

On a shared VM without PREEMPT_RT, SCHED_FIFO is what removes most missed ticks (host-induced
stalls of 1-4 ms); see ../shared/reference/timing.md. Never combine it with a near-100 % spin:
RT throttling then freezes the task for 50 ms of every second (the spin guard is therefore
limited to half the period).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import threading
from dataclasses import dataclass, field
from typing import Annotated, Any

from pydantic import Field

from ..hal import Options

log = logging.getLogger(__name__)

PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30
MCL_CURRENT, MCL_FUTURE = 1, 2


class RealtimeSection(Options):
    priority: int | None = Field(
        None, ge=1, le=99, description="SCHED_FIFO priority of the ticking thread; none = normal scheduling."
    )
    lock_memory: bool = Field(False, description="mlockall(): no page faults on the tick (process-wide).")
    cpus: list[Annotated[int, Field(ge=0, le=4095)]] | None = Field(
        None, min_length=1, description="CPUs the ticking thread may run on."
    )
    timer_slack_ns: int | None = Field(
        1,
        ge=1,
        le=1_000_000_000,
        description="Timer slack of the ticking thread (Linux default 50 µs); none = leave it.",
    )
    spin_guard_us: float = Field(
        0.0, ge=0, description="Precision mode: wake this early and spin to the deadline (≤ half the period)."
    )


@dataclass
class RealtimeState:
    """What was applied, what failed, and how to undo the per-thread parts."""

    applied: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    _policy: tuple[int, int] | None = None
    _affinity: set[int] | None = None
    _slack: int | None = None

    def report(self) -> dict[str, Any]:
        return {**self.applied, "warnings": list(self.warnings)}


_libc: ctypes.CDLL | None = None


def _libc_call(name: str, *args: int) -> int:
    """Call a libc function; a negative result becomes OSError with errno."""
    global _libc
    if _libc is None:
        _libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    result = getattr(_libc, name)(*args)
    if result < 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))
    return result


def timer_slack_ns() -> int:
    """The calling thread's timer slack."""
    return _libc_call("prctl", PR_GET_TIMERSLACK, 0, 0, 0, 0)


def apply(settings: RealtimeSection) -> RealtimeState:
    """Apply the settings to the calling thread (and mlockall to the process)."""
    state = RealtimeState()

    def failed(what: str, exc: BaseException) -> None:
        message = f"could not {what}: {exc}; continuing without it"
        state.warnings.append(message)
        log.warning("%s", message)

    if settings.timer_slack_ns is not None:
        try:
            state._slack = timer_slack_ns()
            _libc_call("prctl", PR_SET_TIMERSLACK, settings.timer_slack_ns)
            state.applied["timer_slack_ns"] = settings.timer_slack_ns
        except (OSError, AttributeError, ValueError, OverflowError) as exc:
            failed(f"set the timer slack to {settings.timer_slack_ns} ns", exc)
    if settings.cpus:
        try:
            state._affinity = os.sched_getaffinity(0)
            os.sched_setaffinity(0, settings.cpus)
            state.applied["cpus"] = sorted(settings.cpus)
        except (OSError, AttributeError, ValueError, OverflowError) as exc:
            failed(f"pin the loop to CPUs {settings.cpus}", exc)
    if settings.lock_memory:
        try:
            _libc_call("mlockall", MCL_CURRENT | MCL_FUTURE)
            state.applied["memory_locked"] = True
        except (OSError, AttributeError, OverflowError) as exc:
            failed("lock memory (mlockall)", exc)
    if settings.priority is not None:
        try:
            state._policy = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(settings.priority))
            state.applied["sched_fifo_priority"] = settings.priority
        except (OSError, AttributeError) as exc:
            state._policy = None
            failed(f"set SCHED_FIFO priority {settings.priority}", exc)
    return state


def apply_for_clock(clock_kind: str, settings: RealtimeSection) -> RealtimeState:
    """:func:`apply`, except on a virtual clock: it runs flat out, and SCHED_FIFO would starve
    the machine (and be throttled); what was asked is noted, by design, not as a warning."""
    if clock_kind != "virtual":
        return apply(settings)
    state = RealtimeState()
    asked = [
        name
        for name, value in (
            ("priority", settings.priority),
            ("lock_memory", settings.lock_memory),
            ("cpus", settings.cpus),
            ("spin_guard_us", settings.spin_guard_us),
        )
        if value
    ]
    if asked:
        state.applied["not_applied"] = f"{', '.join(asked)} (virtual clock)"
    return state


def restore(state: RealtimeState) -> None:
    """Undo the per-thread settings (scheduling, affinity, slack); memory stays locked."""
    try:
        if state._policy is not None:
            policy, priority = state._policy
            os.sched_setscheduler(0, policy, os.sched_param(priority))
        if state._affinity is not None:
            os.sched_setaffinity(0, state._affinity)
        if state._slack is not None:
            _libc_call("prctl", PR_SET_TIMERSLACK, state._slack)
    except (OSError, AttributeError) as exc:
        log.warning("could not restore the thread's scheduling settings: %s", exc)


_freeze_lock = threading.Lock()
_freeze_holders = 0


def freeze_heap() -> None:
    """Collect everything once and freeze the survivors, so the run's collections scan only
    what the run allocates. Call it before any driver opens: a full collection holds the GIL
    for tens of milliseconds, which a driver's keep-alive thread must not wait out.

    Counted, because the freeze is process-wide: the heap thaws when the last holder leaves.
    """
    global _freeze_holders
    with _freeze_lock:
        gc.collect()
        gc.freeze()
        _freeze_holders += 1


def freeze_young() -> None:
    """Freeze what was allocated since :func:`freeze_heap` after a young-generation
    collection: cheap enough to run while drivers are open."""
    gc.collect(1)
    gc.freeze()


def thaw_heap() -> None:
    """Leave the freeze taken by :func:`freeze_heap`; the last holder unfreezes the heap."""
    global _freeze_holders
    with _freeze_lock:
        _freeze_holders = max(0, _freeze_holders - 1)
        if _freeze_holders == 0:
            gc.unfreeze()
