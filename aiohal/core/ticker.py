"""Wake the control loop at absolute deadlines ``t0 + k·period`` (integer ns), never drifting.

Three wake sources share one small interface (``start``, ``wait``, ``poll``, ``now_ns``, ``close``):

* :class:`TimerfdTickSource` – Linux default: a periodic absolute timerfd on CLOCK_MONOTONIC
  registered with the running loop (``add_reader``); the kernel keeps the phase and counts
  expirations, so overruns are detected for free. Works the same on asyncio and uvloop.
  On asyncio's epoll loop, a wait with nothing else due blocks on the timer itself
  (:class:`IdleWait`) instead of going round the event loop.
  An optional guard wakes that much early and spins to the deadline (sub-µs jitter).
* :class:`SleepTickSource` – portable fallback: sleeps toward the deadline and re-checks,
  so it never wakes early (uvloop rounds ``call_later`` to ms and may fire early).
* :class:`VirtualTickSource` – a virtual clock for tests and lockstep simulation: each wait
  advances time by exactly one period, as fast as the CPU allows, deterministically.

:class:`Ticker` turns expirations into tick indices under an overrun policy:
``skip`` (default: keep the phase, count the missed ticks) or ``catch_up`` (run them late).
On the kernel's clock it places the deadlines between the kernel's own periodic ticks
(:func:`off_the_kernel_tick`).
"""

from __future__ import annotations

import abc
import asyncio
import ctypes
import ctypes.util
import math
import os
import select
import selectors
import sys
import time
from collections import deque
from typing import cast

CLOCK_MONOTONIC = 1
TFD_TIMER_ABSTIME = 1

#: Linux aligns its periodic scheduler tick to whole multiples of the tick's period (1e9 / HZ
#: ns) of CLOCK_MONOTONIC, and for HZ = 100, 250 and 1000 those fall on whole milliseconds.
KERNEL_TICK_GRID_NS = 1_000_000


def at_phase(t_ns: int, phase_ns: int, step_ns: int = KERNEL_TICK_GRID_NS) -> int:
    """The first time at or after ``t_ns`` that lies ``phase_ns`` past a multiple of ``step_ns``."""
    return t_ns + (phase_ns - t_ns) % step_ns


def off_the_kernel_tick(t_ns: int, period_ns: int) -> int:
    """The first time at or after ``t_ns`` from which deadlines every ``period_ns`` stay as
    far from whole milliseconds as the period allows: at least half of gcd(period, 1 ms) away
    (500 µs at 1 kHz, 250 µs at 2 kHz, 100 µs at 5 kHz; a period that shares no step with 1 ms
    sweeps every phase whatever its start, and its start is left as it is).

    Why: a deadline on the kernel's tick shares the CPU with the tick's interrupt. A 1 kHz
    loop in precision mode whose deadlines fall on whole milliseconds has every fourth tick
    late on a HZ = 250 kernel (``python -m benchmarks.tick_phase --fifo``; docs/performance.md,
    "Deadlines and the kernel's tick").
    """
    step = math.gcd(period_ns, KERNEL_TICK_GRID_NS)
    return at_phase(t_ns, step // 2, step)


class TickSource(abc.ABC):
    """Something that wakes the loop at deadlines ``t0 + k·period`` for k = 1, 2, …"""

    kind = "?"
    t0_ns = 0
    period_ns = 1
    #: deadlines are times of the kernel's CLOCK_MONOTONIC (False: a virtual time)
    on_kernel_clock = True

    def now_ns(self) -> int:
        return time.monotonic_ns()

    @abc.abstractmethod
    def start(self, t0_ns: int, period_ns: int, k0: int = 0) -> None:
        """Arm the source; the first deadline is ``t0_ns + (k0 + 1)·period_ns``.

        Call from inside the running event loop.
        """

    @abc.abstractmethod
    async def wait(self) -> int:
        """Wait for the next deadline; return how many deadlines passed since the last wait (>= 1)."""

    def poll(self) -> int:
        """What :meth:`wait` would return if the next deadline can be taken now without
        waiting or yielding to the loop, else 0 (and nothing changes). Lets a lockstep tick
        skip two coroutines; a source that always waits keeps this default."""
        return 0

    def shift(self, ns: int) -> None:
        """Move the deadlines after the current one by ``ns`` (a clock locked to another, e.g.
        an EtherCAT reference clock); a virtual clock keeps its own."""

    def close(self) -> None:
        pass


# ---------------------------------------------------------------- timerfd


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


_libc = None


def _timerfd_create_settime(first_ns: int, period_ns: int) -> int:
    """A non-blocking timerfd armed at absolute ``first_ns``, then every ``period_ns``."""
    if hasattr(os, "timerfd_create"):  # Python >= 3.13
        # the stubs of python_version = 3.11 lack the os.timerfd_* of 3.13
        fd = os.timerfd_create(time.CLOCK_MONOTONIC, flags=os.TFD_NONBLOCK | os.TFD_CLOEXEC)  # type: ignore[attr-defined]
    else:
        global _libc
        if _libc is None:
            _libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        fd = _libc.timerfd_create(CLOCK_MONOTONIC, os.O_NONBLOCK | os.O_CLOEXEC)
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_create: {os.strerror(err)}")
    try:
        _timerfd_settime(fd, first_ns, period_ns)
    except OSError:
        os.close(fd)
        raise
    return fd


def _timerfd_settime(fd: int, first_ns: int, period_ns: int) -> None:
    """Arm ``fd`` at absolute ``first_ns``, then every ``period_ns``."""
    if hasattr(os, "timerfd_settime_ns"):  # Python >= 3.13
        os.timerfd_settime_ns(fd, flags=os.TFD_TIMER_ABSTIME, initial=first_ns, interval=period_ns)  # type: ignore[attr-defined]
        return
    spec = _Itimerspec(
        _Timespec(period_ns // 1_000_000_000, period_ns % 1_000_000_000),
        _Timespec(first_ns // 1_000_000_000, first_ns % 1_000_000_000),
    )
    if _libc.timerfd_settime(fd, TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:  # type: ignore[union-attr]
        err = ctypes.get_errno()
        raise OSError(err, f"timerfd_settime: {os.strerror(err)}")


def timerfd_available() -> bool:
    return sys.platform.startswith("linux")


class TimerfdTickSource(TickSource):
    """Periodic absolute timerfd + ``loop.add_reader``; optional spin for the last ``guard_ns``."""

    kind = "timerfd"

    def __init__(self, guard_ns: int = 0, idle_wait: bool = True) -> None:
        """``idle_wait=False``: always wait through the event loop (see :class:`IdleWait`)."""
        self.guard_ns = guard_ns
        self.idle_wait = idle_wait
        self._fd = -1
        self._loop: asyncio.AbstractEventLoop | None = None
        self._idle: IdleWait | None = None
        self._expirations = 0
        self._waiter: asyncio.Future | None = None
        self._k = 0
        self.idle_waits = 0  # waits that blocked on the timer itself
        self.loop_waits = 0  # waits that went round the event loop

    def start(self, t0_ns: int, period_ns: int, k0: int = 0) -> None:
        if self.guard_ns * 2 > period_ns:
            raise ValueError(f"spin guard {self.guard_ns} ns is more than half the period {period_ns} ns")
        self.close()
        self.t0_ns, self.period_ns = t0_ns, period_ns
        self._k = k0
        self._expirations = 0
        self.idle_waits = self.loop_waits = 0
        self._loop = asyncio.get_running_loop()
        self._fd = _timerfd_create_settime(t0_ns + (k0 + 1) * period_ns - self.guard_ns, period_ns)
        self._idle = IdleWait.attach(self._loop, self._fd) if self.idle_wait else None
        if self._idle is None:  # with an IdleWait the loop watches the timer only while a wait is handed to it
            self._loop.add_reader(self._fd, self._on_readable)

    @property
    def waits_on_timer(self) -> bool:
        """True when waits with nothing else due block on the timer (asyncio's epoll loop)."""
        return self._idle is not None

    def _on_readable(self) -> None:
        try:
            data = os.read(self._fd, 8)
        except BlockingIOError:
            return
        self._expirations += int.from_bytes(data, sys.byteorder)
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def wait(self) -> int:
        if self._expirations == 0:
            idle = self._idle
            if idle is None:
                await self._through_loop()
            else:
                timer, loop_io = idle.wait()
                if timer:
                    self._on_readable()
                if self._expirations:
                    self.idle_waits += 1
                    if loop_io:  # I/O came with the timer (ticks that overrun find it expired): one iteration
                        await asyncio.sleep(0)
                else:  # the loop has something to run: it runs it, and wakes the tick on the timer
                    loop = cast(asyncio.AbstractEventLoop, self._loop)  # set by start()
                    loop.add_reader(self._fd, self._on_readable)
                    try:
                        await self._through_loop()
                    finally:
                        loop.remove_reader(self._fd)
        n = self._expirations
        self._expirations = 0
        self._k += n
        if self.guard_ns:
            deadline = self.t0_ns + self._k * self.period_ns
            mono = time.monotonic_ns
            while mono() < deadline:
                pass
        return n

    def shift(self, ns: int) -> None:
        self.t0_ns += ns
        if self._fd >= 0:
            _timerfd_settime(self._fd, self.t0_ns + (self._k + 1) * self.period_ns - self.guard_ns, self.period_ns)

    async def _through_loop(self) -> None:
        """Wait for the loop's reader callback on the timerfd (``_on_readable``)."""
        self.loop_waits += 1
        self._waiter = cast(asyncio.AbstractEventLoop, self._loop).create_future()  # set by start()
        try:
            await self._waiter
        finally:
            self._waiter = None

    def close(self) -> None:
        if self._idle is not None:
            self._idle.close()
            self._idle = None
        if self._fd >= 0:
            if self._loop is not None and not self._loop.is_closed():
                self._loop.remove_reader(self._fd)
            os.close(self._fd)
            self._fd = -1


class IdleWait:
    """Wait for the timer without a round trip through the event loop, when the loop has
    nothing to run before it.

    Through the loop, each tick costs two of its iterations (the timer's callback, then the
    task's wake-up), a future and a task switch: several times the CPU of a blocking wait
    (``python -m benchmarks.idle_wait``). When the loop has no callback ready and no timer due before the tick, this waits
    in one epoll on the timerfd and on the loop's own epoll: the timer resumes the tick at once;
    anything else (I/O, a thread's ``call_soon_threadsafe`` or a signal, both of which write
    the loop's self-pipe, or a loop timer falling due) hands the wait back to the loop, which
    runs it and wakes the tick as before. The loop watches the timerfd only during such a
    handed-back wait, so the loop's epoll is readable only for its own business: I/O that is
    pending when the timer fires (ticks that overrun find the timer already expired) shows in
    the same poll and gets one loop iteration right after the wait, so it runs just after the
    tick's wake instead of just before it.

    It reads asyncio's ready queue, timer heap and stop flag, private attributes that may
    change in any release, so it attaches only to asyncio's own epoll loop on the CPython
    versions it is tested on (``TESTED_PYTHONS``), and not in debug mode (there a task step
    that spans many ticks would be reported as a slow callback); on any other loop (uvloop)
    or Python every wait goes through the loop.
    With no ``asyncio.Runner`` and Python's default SIGINT handler, Ctrl-C raises
    KeyboardInterrupt inside the tick's task rather than in the loop's select.
    """

    __slots__ = ("_loop", "_fd", "_epoll")

    #: the longest a wait blocks without looking at the loop again (asyncio caps its own
    #: select timeout at a day; epoll refuses more than about 24.8 days)
    MAX_TIMEOUT_S = 86_400.0

    #: the Pythons whose event loop internals (``_selector``, ``_ready``, ``_scheduled``,
    #: ``_stopping``) CI has run this against: [first, last)
    TESTED_PYTHONS = ((3, 11), (3, 14))

    @classmethod
    def attach(cls, loop: asyncio.AbstractEventLoop, fd: int = -1) -> IdleWait | None:
        """For ``loop`` and the timerfd ``fd`` (-1: none, only :meth:`loop_has_work`), or None
        if ``loop`` is not asyncio's epoll loop, runs in debug mode or on an untested Python."""
        first, last = cls.TESTED_PYTHONS
        if not first <= sys.version_info[:2] < last or sys.implementation.name != "cpython":
            return None
        selector = getattr(loop, "_selector", None)
        if not isinstance(selector, selectors.EpollSelector) or loop.get_debug():
            return None
        if not isinstance(getattr(loop, "_ready", None), deque) or not isinstance(
            getattr(loop, "_scheduled", None), list
        ):
            return None
        return cls(loop, fd, selector.fileno())

    def __init__(self, loop: asyncio.AbstractEventLoop, fd: int, loop_fd: int) -> None:
        self._loop = loop
        self._fd = fd
        self._epoll = select.epoll(2)
        if fd >= 0:
            self._epoll.register(fd, select.EPOLLIN)
        self._epoll.register(loop_fd, select.EPOLLIN)  # readable when any of the loop's fds is

    def _due(self) -> float:
        """Seconds until the loop's next timer (``MAX_TIMEOUT_S`` if none), or 0 if the loop
        has something to run now (a ready callback, a due timer, a stop request). The loop's
        attributes are read each time: ``_run_once`` replaces its timer heap when it prunes
        cancelled timers."""
        loop = self._loop
        if loop._ready or loop._stopping:  # type: ignore[attr-defined]
            return 0.0
        scheduled = loop._scheduled  # type: ignore[attr-defined]
        if not scheduled:
            return self.MAX_TIMEOUT_S
        return min(max(0.0, scheduled[0].when() - loop.time()), self.MAX_TIMEOUT_S)

    def wait(self) -> tuple[bool, bool]:
        """Block until the timer fires or the loop has something to run, whichever comes
        first: (the timer fired, the loop has I/O). (False, _): the caller waits through the
        loop. Returns at once if the loop has something to run now."""
        timeout = self._due()
        if timeout <= 0.0:
            return False, True
        timer = loop_io = False
        fd = self._fd
        for ready_fd, _ in self._epoll.poll(timeout):
            if ready_fd == fd:
                timer = True
            else:
                loop_io = True
        return timer, loop_io

    def loop_has_work(self) -> bool:
        """Whether one iteration of the loop would run anything now (a ready callback, a due
        timer, a stop request, a ready fd); for an IdleWait without a timer. The virtual clock
        yields to the loop only then: an iteration that finds nothing costs a lockstep tick
        more than the tick's own bookkeeping."""
        return self._due() <= 0.0 or bool(self._epoll.poll(0))

    def close(self) -> None:
        self._epoll.close()


# ---------------------------------------------------------------- portable sleep


class SleepTickSource(TickSource):
    """``asyncio.sleep`` to the absolute deadline, re-checked so that it never wakes early.

    Lateness is 0–1 ms on the default loop (epoll rounds timeouts up to whole ms); prefer timerfd.
    """

    kind = "sleep"

    def start(self, t0_ns: int, period_ns: int, k0: int = 0) -> None:
        self.t0_ns, self.period_ns = t0_ns, period_ns
        self._k = k0

    async def wait(self) -> int:
        deadline = self.t0_ns + (self._k + 1) * self.period_ns
        now = time.monotonic_ns()
        while now < deadline:
            await asyncio.sleep((deadline - now) / 1e9)
            now = time.monotonic_ns()
        k = (now - self.t0_ns) // self.period_ns
        n = k - self._k
        self._k = k
        return n

    def shift(self, ns: int) -> None:
        self.t0_ns += ns


# ---------------------------------------------------------------- virtual clock


class VirtualTickSource(TickSource):
    """Virtual time: each wait advances exactly one period (or more after :meth:`stall`).

    It never sleeps: a lockstep simulation runs as fast as the CPU allows, deterministically.
    Every ``yield_every_ms`` of wall time it yields to the event loop, so other tasks (a stop
    request, a signal handler, a test) still run; yielding on every tick would cost a round
    trip through the event loop on each one. On asyncio's own loop it
    yields only when the loop has something to run (:meth:`IdleWait.loop_has_work`).
    """

    kind = "virtual"
    on_kernel_clock = False

    def __init__(self, start_ns: int = 0, yield_every_ms: float = 1.0, idle_wait: bool = True) -> None:
        """``idle_wait=False``: yield every ``yield_every_ms`` whether the loop has work or not."""
        self.idle_wait = idle_wait
        self._now = start_ns
        self._k = 0
        self._stall = 0
        self._yield_every_ns = int(yield_every_ms * 1e6)
        # one interval before the monotonic clock's origin: the first wait looks at the loop
        # however long the machine has been up (0 would count as recent on a fresh boot)
        self._last_yield = -self._yield_every_ns
        self._idle: IdleWait | None = None
        self.yields = 0  # waits that went round the event loop

    def now_ns(self) -> int:
        return self._now

    def start(self, t0_ns: int, period_ns: int, k0: int = 0) -> None:
        self.t0_ns, self.period_ns = t0_ns, period_ns
        self._k = k0
        self._now = max(self._now, t0_ns + k0 * period_ns)
        self.close()
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # started outside a loop (a test driving the source by hand)
            return
        self._idle = IdleWait.attach(loop) if self.idle_wait else None

    def close(self) -> None:
        if self._idle is not None:
            self._idle.close()
            self._idle = None

    def stall(self, periods: int) -> None:
        """Make the next wait return late by ``periods`` whole periods (overrun tests)."""
        self._stall += periods

    def advance(self, ns: int) -> None:
        """Move virtual time forward by ``ns`` now (a driver or test consuming time)."""
        self._now += ns

    def poll(self) -> int:
        if time.monotonic_ns() - self._last_yield >= self._yield_every_ns:
            return 0  # time to look at the event loop: wait() does that
        return self._advance()

    async def wait(self) -> int:
        wall = time.monotonic_ns()
        if wall - self._last_yield >= self._yield_every_ns:
            self._last_yield = wall
            if self._idle is None or self._idle.loop_has_work():
                self.yields += 1
                await asyncio.sleep(0)
        return self._advance()

    def _advance(self) -> int:
        """Take the next deadline (and those a stall skipped): virtual time moves to it."""
        n = 1 + self._stall
        self._stall = 0
        self._k += n
        self._now = max(self._now, self.t0_ns + self._k * self.period_ns)
        return n


def make_source(kind: str, guard_ns: int = 0, idle_wait: bool = True) -> TickSource:
    """A tick source by config name; ``auto`` is timerfd on Linux, sleep elsewhere."""
    if kind == "auto":
        kind = "timerfd" if timerfd_available() else "sleep"
    if kind == "timerfd":
        return TimerfdTickSource(guard_ns, idle_wait)
    if kind == "sleep":
        return SleepTickSource()
    if kind == "virtual":
        return VirtualTickSource(idle_wait=idle_wait)
    raise ValueError(f"unknown clock {kind!r}")


class Ticker:
    """Tick indices and deadlines from a source, under an overrun policy."""

    def __init__(self, source: TickSource, period_ns: int, overrun: str = "skip", phase_ns: int | None = None) -> None:
        """``phase_ns``: on the kernel's clock, start the deadlines that far past a whole
        millisecond (None: :func:`off_the_kernel_tick`)."""
        if overrun not in ("skip", "catch_up"):
            raise ValueError(f"unknown overrun policy {overrun!r}")
        if phase_ns is not None and not 0 <= phase_ns < KERNEL_TICK_GRID_NS:
            raise ValueError(f"phase {phase_ns} ns is not within one millisecond")
        self.source = source
        self.period_ns = period_ns
        self.phase_ns = phase_ns
        self.catch_up = overrun == "catch_up"
        self.k = 0
        self.t0_ns = 0
        self.deadline_ns = 0
        self.missed = 0  # deadlines not served (skip) or served late back-to-back (catch_up)
        self._pending = 0

    def start(self, lead_ns: int | None = None) -> None:
        """Arm the source; the next tick (k + 1) is due one period (plus ``lead_ns``) from now,
        on the kernel's clock up to 1 ms later: between the kernel's ticks
        (:func:`off_the_kernel_tick`), or at the phase given.

        Tick indices keep counting across restarts, so drivers see a monotonic tick.
        """
        now = self.source.now_ns()
        self.t0_ns = now + (lead_ns or 0) - self.k * self.period_ns
        if self.source.on_kernel_clock:
            if self.phase_ns is None:
                self.t0_ns = off_the_kernel_tick(self.t0_ns, self.period_ns)
            else:
                self.t0_ns = at_phase(self.t0_ns, self.phase_ns)
        self.deadline_ns = self.t0_ns + self.k * self.period_ns
        self._pending = 0
        self.source.start(self.t0_ns, self.period_ns, self.k)

    async def next(self) -> int:
        """Wait for the next tick to run; return its index k (deadline ``t0 + k·period``)."""
        return self.poll() or self._take(await self.source.wait())

    def poll(self) -> int:
        """The next tick's index if it can run now without waiting (a virtual clock between its
        looks at the event loop, or a tick caught up late), else 0: ``ticker.poll() or await
        ticker.next()`` takes the same ticks as ``await ticker.next()``, with no coroutine when
        nothing has to be waited for."""
        if self._pending:
            self._pending -= 1
            self.k += 1
            self.deadline_ns = self.t0_ns + self.k * self.period_ns
            return self.k
        n = self.source.poll()
        return self._take(n) if n else 0

    def _take(self, n: int) -> int:
        """Account for ``n`` deadlines passed (n - 1 of them missed) under the overrun policy."""
        if n > 1:
            self.missed += n - 1
        if self.catch_up:
            self._pending = n - 1
            self.k += 1
        else:
            self.k += n
        self.deadline_ns = self.t0_ns + self.k * self.period_ns
        return self.k

    def shift(self, ns: int) -> None:
        """Move every deadline after the current tick's by ``ns`` (see :meth:`TickSource.shift`)."""
        if self.source.on_kernel_clock:
            self.t0_ns += ns
            self.source.shift(ns)

    def close(self) -> None:
        self.source.close()
