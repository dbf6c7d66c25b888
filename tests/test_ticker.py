"""The tick sources and the Ticker: exact on the virtual clock, bounded drift on the real one."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import socket
import sys
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from aiohal.core.ticker import (
    KERNEL_TICK_GRID_NS,
    IdleWait,
    SleepTickSource,
    Ticker,
    TimerfdTickSource,
    VirtualTickSource,
    make_source,
    off_the_kernel_tick,
    timerfd_available,
)

PERIOD = 1_000_000  # 1 kHz


@pytest.mark.asyncio
async def test_virtual_clock_ticks_are_exact():
    source = VirtualTickSource(start_ns=5_000)
    ticker = Ticker(source, PERIOD)
    ticker.start()
    seen = []
    for _ in range(1000):
        k = await ticker.next()
        seen.append((k, source.now_ns(), ticker.deadline_ns))
    assert [k for k, _, _ in seen] == list(range(1, 1001))
    # virtual time is exactly the deadline of each tick: t0 + k·period
    assert all(now == 5_000 + k * PERIOD == deadline for k, now, deadline in seen)
    assert ticker.missed == 0


@pytest.mark.asyncio
async def test_skip_policy_keeps_phase_and_counts_missed():
    source = VirtualTickSource()
    ticker = Ticker(source, PERIOD, "skip")
    ticker.start()
    assert await ticker.next() == 1
    source.stall(3)  # the next wake comes 3 periods late
    assert await ticker.next() == 5  # ticks 2, 3, 4 skipped, phase kept
    assert ticker.deadline_ns == ticker.t0_ns + 5 * PERIOD
    assert source.now_ns() == ticker.deadline_ns
    assert ticker.missed == 3
    assert await ticker.next() == 6


@pytest.mark.asyncio
async def test_catch_up_policy_runs_missed_ticks_late():
    source = VirtualTickSource()
    ticker = Ticker(source, PERIOD, "catch_up")
    ticker.start()
    await ticker.next()
    source.stall(2)
    ks = [await ticker.next() for _ in range(4)]
    assert ks == [2, 3, 4, 5]
    assert ticker.missed == 2
    # ticks 2 and 3 ran late (their deadlines passed), 4 ran at its deadline, 5 one period on
    assert source.now_ns() == ticker.t0_ns + 5 * PERIOD


def _from_whole_ms(t_ns: int) -> int:
    """How far ``t_ns`` lies from the nearest whole millisecond, ns."""
    r = t_ns % KERNEL_TICK_GRID_NS
    return min(r, KERNEL_TICK_GRID_NS - r)


@given(t=st.integers(0, 2**62), period=st.integers(10_000, 100_000_000), k=st.integers(0, 10_000))
def test_deadlines_off_the_kernel_tick_keep_half_the_shared_step_from_whole_milliseconds(t, period, k):
    step = math.gcd(period, KERNEL_TICK_GRID_NS)
    t0 = off_the_kernel_tick(t, period)
    assert t <= t0 < t + step  # never before the asked start, never a whole step after it
    assert _from_whole_ms(t0 + k * period) >= step // 2  # every deadline, as far as the period allows


def test_the_kernel_tick_phase_of_common_rates():
    def phases(period, count):  # µs past a whole ms of the first deadlines
        t0 = off_the_kernel_tick(123_456_789, period)
        return sorted({(t0 + k * period) % KERNEL_TICK_GRID_NS // 1000 for k in range(count)})

    assert phases(1_000_000, 10) == [500]  # 1 kHz
    assert phases(500_000, 10) == [250, 750]  # 2 kHz
    assert phases(200_000, 10) == [100, 300, 500, 700, 900]  # 5 kHz
    assert phases(4_000_000, 10) == [500]  # 250 Hz
    assert off_the_kernel_tick(123_456_789, 999_999) == 123_456_789  # sweeps every phase: left as it is


@pytest.mark.asyncio
async def test_real_clock_deadlines_sit_between_kernel_ticks_and_virtual_ones_where_asked():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    for source in (TimerfdTickSource(), SleepTickSource()):
        ticker = Ticker(source, PERIOD)
        before = time.monotonic_ns()
        ticker.start(lead_ns=PERIOD)
        try:
            assert ticker.t0_ns % KERNEL_TICK_GRID_NS == 500_000
            first = ticker.t0_ns + PERIOD
            assert before + 2 * PERIOD <= first < time.monotonic_ns() + 3 * PERIOD
            k = await ticker.next()
            assert _from_whole_ms(ticker.deadline_ns) == 500_000 and ticker.deadline_ns == ticker.t0_ns + k * PERIOD
        finally:
            ticker.close()
    virtual = VirtualTickSource(start_ns=123_456)
    ticker = Ticker(virtual, PERIOD)
    ticker.start(lead_ns=PERIOD)
    assert ticker.t0_ns == 123_456 + PERIOD  # virtual time has no kernel tick: lockstep runs unchanged


@pytest.mark.asyncio
async def test_a_phase_given_places_the_deadlines_and_one_outside_a_millisecond_is_refused():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    for period, phase in ((PERIOD, 250_000), (PERIOD, 0), (500_000, 100_000)):
        ticker = Ticker(TimerfdTickSource(), period, phase_ns=phase)
        ticker.start(lead_ns=period)
        try:
            assert ticker.t0_ns % KERNEL_TICK_GRID_NS == phase
            k = await ticker.next()
            assert ticker.deadline_ns % period == phase % period and ticker.deadline_ns == ticker.t0_ns + k * period
        finally:
            ticker.close()
    virtual = Ticker(VirtualTickSource(start_ns=7), PERIOD, phase_ns=250_000)
    virtual.start(lead_ns=PERIOD)
    assert virtual.t0_ns == 7 + PERIOD  # virtual time has no kernel tick to keep away from
    for bad in (-1, KERNEL_TICK_GRID_NS):
        with pytest.raises(ValueError, match="within one millisecond"):
            Ticker(VirtualTickSource(), PERIOD, phase_ns=bad)


def test_unknown_policy_and_source_are_refused():
    with pytest.raises(ValueError):
        Ticker(VirtualTickSource(), PERIOD, "whenever")
    with pytest.raises(ValueError):
        make_source("sundial")


@pytest.mark.asyncio
async def test_timerfd_guard_above_half_period_is_refused():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    source = TimerfdTickSource(guard_ns=600_000)
    with pytest.raises(ValueError, match="half the period"):
        source.start(time.monotonic_ns(), PERIOD)


async def _run_real(source, seconds: float, period_ns: int = PERIOD):
    ticker = Ticker(source, period_ns)
    ticker.start(lead_ns=period_ns)
    n = int(seconds * 1e9 / period_ns)
    lateness = []
    deadlines = []  # (k, deadline) of every tick served
    try:
        while ticker.k < n:
            await ticker.next()
            lateness.append(time.monotonic_ns() - ticker.deadline_ns)
            deadlines.append((ticker.k, ticker.deadline_ns))
    finally:
        ticker.close()
    ticker.served = deadlines
    return ticker, lateness


def assert_absolute_deadlines(ticker) -> None:
    """No drift by construction: tick k's deadline is t0 + k·period, whatever each wake cost
    (how late the host wakes a tick is the host's; where the deadlines lie is the ticker's)."""
    assert ticker.served, "no tick ran"
    assert all(deadline == ticker.t0_ns + k * ticker.period_ns for k, deadline in ticker.served)


@pytest.mark.asyncio
@pytest.mark.realtime
async def test_timerfd_has_bounded_drift_over_two_seconds():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    ticker, lateness = await _run_real(TimerfdTickSource(), 2.0)
    # every deadline up to the last one was either served or counted as missed
    assert ticker.k >= 2000 and len(lateness) + ticker.missed == ticker.k
    assert min(lateness) >= 0, "a tick woke before its deadline"
    assert_absolute_deadlines(ticker)


@pytest.mark.asyncio
@pytest.mark.realtime
async def test_sleep_source_never_wakes_early_and_does_not_drift():
    ticker, lateness = await _run_real(SleepTickSource(), 1.0)
    assert min(lateness) >= 0, "the portable source woke before a deadline"
    assert ticker.k >= 1000 and len(lateness) + ticker.missed == ticker.k
    assert_absolute_deadlines(ticker)


@pytest.mark.asyncio
@pytest.mark.realtime
async def test_timerfd_detects_a_stall_as_missed_ticks():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    ticker = Ticker(TimerfdTickSource(), PERIOD)
    ticker.start()
    try:
        await ticker.next()
        before = ticker.k
        time.sleep(0.0105)  # block the loop for 10.5 periods
        k = await ticker.next()
    finally:
        ticker.close()
    assert k - before >= 10
    assert ticker.missed >= 9


@pytest.mark.asyncio
async def test_timerfd_source_works_on_this_loop():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    source = TimerfdTickSource()
    source.start(time.monotonic_ns(), PERIOD)
    try:
        n = await asyncio.wait_for(source.wait(), timeout=1.0)
    finally:
        source.close()
    assert n >= 1
    assert source._fd == -1


@pytest.mark.skipif(sys.version_info >= (3, 13), reason="ctypes path is for Python < 3.13")
def test_ctypes_timerfd_reports_errors():
    from aiohal.core import ticker as t

    # an invalid period makes timerfd_settime fail with EINVAL, raised as OSError
    with pytest.raises(OSError):
        t._timerfd_create_settime(time.monotonic_ns(), -5)


@pytest.mark.asyncio
@pytest.mark.realtime
async def test_precision_mode_spins_to_the_deadline_and_never_early():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    ticker, lateness = await _run_real(TimerfdTickSource(guard_ns=200_000), 0.3)
    # what the spin guarantees: never early, however early the timer fired (how late the host
    # wakes a tick is the host's: 73 ms at the 10th percentile was seen on a loaded CI machine)
    assert min(lateness) >= 0
    assert_absolute_deadlines(ticker)


# ---------------------------------------------------------------- waiting on the timer itself


def _on_asyncio_epoll_loop() -> bool:
    """On asyncio's epoll loop, on a Python whose loop internals IdleWait was tested against."""
    loop = asyncio.get_running_loop()
    first, last = IdleWait.TESTED_PYTHONS
    return (
        first <= sys.version_info[:2] < last
        and isinstance(loop, asyncio.SelectorEventLoop)
        and type(loop._selector).__name__ == "EpollSelector"
    )


@contextlib.contextmanager
def _socket_read_by_the_loop(on_data):
    """A socket pair whose reading end the running loop watches: ``on_data()`` runs after each
    datagram is consumed. Yields the writing end."""
    loop = asyncio.get_running_loop()
    r, w = socket.socketpair()
    r.setblocking(False)

    def on_readable():
        r.recv(16)
        on_data()

    loop.add_reader(r.fileno(), on_readable)
    try:
        yield w
    finally:
        loop.remove_reader(r.fileno())
        r.close()
        w.close()


@pytest.mark.asyncio
async def test_an_idle_wait_blocks_on_the_timer_on_asyncio_and_goes_round_the_loop_elsewhere():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    source = TimerfdTickSource()
    ticker = Ticker(source, PERIOD)
    ticker.start()
    try:
        ks = [await ticker.next() for _ in range(20)]
        on_timer = source.waits_on_timer
    finally:
        ticker.close()
    assert all(b > a for a, b in itertools.pairwise(ks))  # every wait returned a later deadline
    assert on_timer == _on_asyncio_epoll_loop()
    assert not source.waits_on_timer  # closed
    if on_timer:
        assert source.idle_waits > 0
    else:
        assert source.idle_waits == 0 and source.loop_waits > 0


@pytest.mark.asyncio
async def test_on_an_untested_python_every_wait_goes_round_the_loop(monkeypatch):
    """The loop's private attributes may change in any release: outside the tested versions
    IdleWait does not attach, and the ticks still come, through the loop."""
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    loop = asyncio.get_running_loop()
    if _on_asyncio_epoll_loop():
        idle = IdleWait.attach(loop)
        assert idle is not None
        idle.close()
    here = sys.version_info[:2]
    monkeypatch.setattr(IdleWait, "TESTED_PYTHONS", ((here[0], here[1] + 1), (here[0], here[1] + 2)))
    assert IdleWait.attach(loop) is None
    source = TimerfdTickSource()
    ticker = Ticker(source, PERIOD)
    ticker.start()
    try:
        ks = [await ticker.next() for _ in range(5)]
        on_timer = source.waits_on_timer
    finally:
        ticker.close()
    assert all(b > a for a, b in itertools.pairwise(ks))
    assert not on_timer and source.idle_waits == 0 and source.loop_waits > 0


@pytest.mark.asyncio
async def test_idle_wait_can_be_turned_off():
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    source = TimerfdTickSource(idle_wait=False)
    ticker = Ticker(source, PERIOD)
    ticker.start()
    try:
        for _ in range(5):
            await ticker.next()
        assert not source.waits_on_timer
    finally:
        ticker.close()
    assert source.idle_waits == 0 and source.loop_waits >= 1


@pytest.mark.asyncio
async def test_loop_timers_run_while_the_ticks_wait_on_the_timer():
    """A task sleeping 2 ms at a time finishes ten sleeps while the ticks run; the ticks stop as
    soon as it is done, long before their cap of 2000 (2 s)."""
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    done = asyncio.Event()

    async def sleeper():
        for _ in range(10):
            await asyncio.sleep(0.002)
        done.set()

    source = TimerfdTickSource()
    ticker = Ticker(source, PERIOD)
    task = asyncio.create_task(sleeper())
    ticker.start()
    ticks = 0
    try:
        while not done.is_set() and ticks < 2000:
            await ticker.next()
            ticks += 1
    finally:
        ticker.close()
        task.cancel()
    assert done.is_set(), f"the sleeping task did not finish in {ticks} ticks"
    assert ticks < 1000


@pytest.mark.asyncio
async def test_io_and_other_threads_reach_the_loop_while_the_ticks_wait_on_the_timer():
    """A thread writes a socket the loop reads, then calls ``call_soon_threadsafe``, while the
    ticks run: each callback runs within two ticks (waits returned, not deadlines: a stall of
    the host skips deadlines) of the thread doing it. The socket alone can reach the loop only
    through its epoll, which the wait on the timer watches."""
    import threading

    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    loop = asyncio.get_running_loop()
    ticker = Ticker(TimerfdTickSource(), PERIOD)
    waits = 0
    seen: dict[str, int] = {}
    sent_at: dict[str, int] = {}
    go, io_seen = threading.Event(), threading.Event()

    def on_data():
        seen["io"] = waits
        io_seen.set()

    with _socket_read_by_the_loop(on_data) as w:

        def from_thread():
            go.wait(5.0)
            w.send(b"x")
            sent_at["io"] = waits
            if io_seen.wait(5.0):
                loop.call_soon_threadsafe(lambda: seen.setdefault("call", waits))
                sent_at["call"] = waits

        thread = threading.Thread(target=from_thread)
        thread.start()
        ticker.start()
        try:
            while len(seen) < 2 and waits < 2000:
                await ticker.next()
                waits += 1
                if waits == 5:
                    go.set()
        finally:
            go.set()
            io_seen.set()
            ticker.close()
            thread.join(5.0)
    assert set(seen) == {"io", "call"}, f"after {waits} waits only {seen} ran"
    assert seen["io"] - sent_at["io"] <= 2
    assert seen["call"] - sent_at["call"] <= 2


@pytest.mark.asyncio
async def test_io_reaches_the_loop_when_every_tick_overruns():
    """Ticks that take longer than the period find the timer already expired at every wait;
    a socket written at tick 10 is still read within three ticks."""
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    ticker = Ticker(TimerfdTickSource(), PERIOD)
    seen: list[int] = []
    ticks = 0
    with _socket_read_by_the_loop(lambda: seen.append(ticks)) as w:
        ticker.start()
        try:
            while not seen and ticks < 200:
                await ticker.next()
                ticks += 1
                time.sleep(0.0015)  # 1.5 periods of work
                if ticks == 10:
                    w.send(b"x")
        finally:
            ticker.close()
    assert seen and seen[0] - 10 <= 3, f"read at tick {seen[0] if seen else None}"


@pytest.mark.asyncio
async def test_a_timer_set_after_the_loop_pruned_its_timer_heap_still_runs():
    """``_run_once`` replaces its heap when most of it is cancelled timers; a wait on the timer
    must look at the new one."""
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    loop = asyncio.get_running_loop()
    ticker = Ticker(TimerfdTickSource(), PERIOD)
    ticker.start()
    fired = asyncio.Event()
    far = []
    waits = 0
    try:
        for _ in range(3):
            await ticker.next()
        far = [loop.call_later(60.0, lambda: None) for _ in range(200)]
        for handle in far[:150]:
            handle.cancel()
        await asyncio.sleep(0)  # one loop iteration: the heap is rebuilt without the cancelled timers
        loop.call_later(0.005, fired.set)
        while not fired.is_set() and waits < 500:
            await ticker.next()
            waits += 1
    finally:
        ticker.close()
        for handle in far:
            handle.cancel()
    assert fired.is_set(), f"a 5 ms timer had not run after {waits} ticks"


@pytest.mark.asyncio
async def test_a_timer_weeks_away_does_not_break_the_wait():
    """epoll refuses timeouts above about 24.8 days; asyncio caps its own at a day."""
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    loop = asyncio.get_running_loop()
    handle = loop.call_later(30 * 86_400, lambda: None)
    ticker = Ticker(TimerfdTickSource(), PERIOD)
    ticker.start()
    try:
        ks = [await ticker.next() for _ in range(10)]
    finally:
        ticker.close()
        handle.cancel()
    assert all(b > a for a, b in itertools.pairwise(ks))


@pytest.mark.asyncio
async def test_the_virtual_clock_yields_only_when_the_loop_has_something_to_run():
    """Checked on every wait (``yield_every_ms=0``): with nothing else in the loop, asyncio's
    loop is never entered; a task that keeps itself ready runs to its end between ticks. On
    other loops every check yields."""
    source = VirtualTickSource(yield_every_ms=0)
    ticker = Ticker(source, PERIOD)
    ticker.start()
    for _ in range(50):
        await ticker.next()
    idle_yields = source.yields

    hops = 0

    async def hopper():
        nonlocal hops
        for _ in range(20):
            hops += 1
            await asyncio.sleep(0)

    task = asyncio.create_task(hopper())
    for _ in range(50):
        await ticker.next()
    ticker.close()
    assert task.done() and hops == 20
    if _on_asyncio_epoll_loop():
        assert idle_yields == 0
        assert 20 <= source.yields <= 30  # one per hop, give or take the task's start and end
    else:
        assert idle_yields == 50 and source.yields == 100


@pytest.mark.asyncio
async def test_no_wait_on_the_timer_in_debug_mode():
    """asyncio's debug mode reports a task step longer than 0.1 s as slow: a step that spans
    many ticks would be, so there every wait goes round the loop."""
    if not timerfd_available():
        pytest.skip("timerfd is Linux only")
    loop = asyncio.get_running_loop()
    was = loop.get_debug()
    loop.set_debug(True)
    source = TimerfdTickSource()
    ticker = Ticker(source, PERIOD)
    try:
        ticker.start()
        for _ in range(3):
            await ticker.next()
        on_timer = source.waits_on_timer
    finally:
        ticker.close()
        loop.set_debug(was)
    assert not on_timer and source.idle_waits == 0


@pytest.mark.asyncio
async def test_the_virtual_clock_without_idle_wait_yields_on_every_check():
    source = VirtualTickSource(yield_every_ms=0, idle_wait=False)
    ticker = Ticker(source, PERIOD)
    ticker.start()
    for _ in range(30):
        await ticker.next()
    ticker.close()
    assert source.yields == 30


@pytest.mark.asyncio
@pytest.mark.parametrize("policy", ["skip", "catch_up"])
async def test_ticks_taken_by_poll_are_those_a_wait_would_take(policy):
    """The loop ticks with ``ticker.poll() or await ticker.next()``. A virtual clock that looks
    at the event loop on every tick lets poll take none of its ticks (but those a catch-up runs
    late); one that never looks lets poll take all but the first. Both give the same indices,
    deadlines, virtual times and missed counts, stalls included."""
    runs = {}
    for yield_every_ms in (0.0, 1e6):
        source = VirtualTickSource(yield_every_ms=yield_every_ms)
        ticker = Ticker(source, PERIOD, policy)
        ticker.start()
        seen, taken_by_poll = [], 0
        for i in range(40):
            if i in (5, 17):
                source.stall(3)
            k = ticker.poll()
            taken_by_poll += bool(k)
            k = k or await ticker.next()
            seen.append((k, ticker.deadline_ns, source.now_ns(), ticker.missed))
        runs[yield_every_ms] = seen, taken_by_poll
    (waited, none_polled), (polled, all_polled) = runs[0.0], runs[1e6]
    # the ticks a catch-up runs late are taken at once, on either clock
    assert none_polled == (6 if policy == "catch_up" else 0)
    assert all_polled == 39  # the first tick is the source's first look at the loop
    assert polled == waited
    assert waited[-1][3] == 6  # two stalls of 3 periods


@pytest.mark.asyncio
async def test_poll_leaves_a_look_at_the_loop_and_a_real_wait_to_next():
    source = VirtualTickSource(yield_every_ms=0)  # a look at the loop is due on every tick
    ticker = Ticker(source, PERIOD)
    ticker.start()
    assert ticker.poll() == 0 and ticker.k == 0 and source.now_ns() == ticker.t0_ns
    assert await ticker.next() == 1
    if timerfd_available():
        timer = Ticker(TimerfdTickSource(), PERIOD)
        timer.start()
        try:
            assert timer.poll() == 0 and timer.k == 0  # a deadline is waited for, never polled
            # the next deadline, or a later one if the host stalled us past it (skipped, counted)
            assert await timer.next() == 1 + timer.missed
        finally:
            timer.close()
