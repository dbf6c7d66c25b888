"""The stall thread: notices when the tick stops advancing while the process still runs (a
driver awaiting forever, a blocking call), and watches the watchdog process off the tick."""

from __future__ import annotations

import asyncio
import threading
import time
from typing import TYPE_CHECKING, Any, cast

from .levels import SafetyEvent

if TYPE_CHECKING:
    from .supervisor import Supervisor


class StallWatchdog:
    """A thread that notices when the tick stops advancing (a driver awaiting forever, a
    blocking call) and then emergency-stops every driver and cancels the run.

    It only reads an integer per check: nothing is added to the tick. A stall of the whole
    process (the GIL held by C code, a frozen VM) needs the external watchdog of the safety
    layer; this one covers the event loop being stuck inside an ``await``. Where a watchdog
    process runs, it also checks that process every ``check_s`` (see
    :meth:`Supervisor.watchdog_trouble`).
    """

    def __init__(self, supervisor: Supervisor, timeout_s: float) -> None:
        self.supervisor = supervisor
        self.timeout_s = timeout_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task | None = None
        self.fired = False
        #: how often it looks (the tick counter, the watchdog process): a few times a timeout
        self.check_s = min(timeout_s / 4, 0.05) if timeout_s > 0 else 0.05

    def __enter__(self) -> StallWatchdog:
        if self.timeout_s > 0 or self.supervisor.watchdog is not None:
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
        supervisor = self.supervisor
        stats = supervisor.loop.stats
        last, since = -1, time.monotonic()
        trouble = ""
        while not self._stop.wait(self.check_s):
            count = stats.count
            now = time.monotonic()
            if supervisor.watchdog is not None:  # watched in turn: dead or stopped holds the robot
                seen = supervisor.watchdog_trouble()
                if seen != trouble:
                    trouble = seen
                    loop.call_soon_threadsafe(supervisor.watchdog_checked, trouble)
            if count != last:
                last, since = count, now
            elif self.timeout_s > 0 and now - since > self.timeout_s:
                self.fired = True
                # synchronous, from this thread: the loop may be stuck
                supervisor.estop(
                    f"no tick for {self.timeout_s * 1e3:g} ms", source="watchdog", event=SafetyEvent.WATCHDOG
                )
                loop.call_soon_threadsafe(self._cancel)
                return

    def _cancel(self) -> None:
        self.supervisor.record_fault("loop", "tick", f"no tick for {self.timeout_s * 1e3:g} ms: emergency stop")
        self.supervisor.loop.request_stop("stalled")
        if self._task is not None:
            self._task.cancel()
