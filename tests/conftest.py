"""Shared test set-up: every async test runs on asyncio and on uvloop (unless it is marked
``asyncio_only``, or ``AIOHAL_TEST_LOOPS`` names fewer loops); root-only tests."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"

#: An upper bound for "it returned instead of waiting for ever": far above any stall of a
#: loaded host (1.3 s seen in CI), far below a hang. How fast a call returns is the host's;
#: a test asserts that it returns, and the lower bounds the code itself guarantees.
NOT_HUNG_S = 30.0


#: The stall bound given to loops on a real clock in this process when their config leaves it
#: at its default (see :func:`_host_stalls_are_not_the_subject`).
TEST_PROCESS_TICK_GAP_NS = 5_000_000_000


def host_stalls_tolerated(text: str) -> str:
    """A config's text for a robot run in a process of its own whose subject is not the
    host's stalls: what :func:`_host_stalls_are_not_the_subject` gives loops in this process
    (a 5 s tick gap and watchdog process), and the stall thread's bound at 5 s. A loaded or
    even a quiet host running the parallel tests stops such a process for 20-30 ms at times,
    beyond the defaults (20 ms), and the robot holds."""
    assert "[safety]" not in text, "the config sets its own [safety]: say what the test needs there"
    text = text.replace("[loop]\n", "[loop]\nstall_timeout_ms = 5000\n", 1)
    assert "stall_timeout_ms = 5000" in text, "no [loop] table to bound the stall thread in"
    return text + "\n[safety]\nmax_tick_gap_ms = 5000\nwatchdog_ms = 5000\n"


@pytest.fixture(autouse=True)
def _host_stalls_are_not_the_subject(monkeypatch):
    """A loop ticking on a real clock inside the test process runs without SCHED_FIFO, and a
    loaded host (a user's CI, two CPU hogs) stops this process for 20-80 ms at times: with the
    default bound (20 ms) that is a stall, and the robot holds; the watchdog process, with the
    same default time (``[safety] watchdog_ms``), e-stops it. Tests about something else must
    not be decided by the host, so such a loop gets a 5 s bound and a 5 s watchdog process
    here. Tests about stalls set ``max_tick_gap_ms`` or ``watchdog_ms`` themselves, run on the
    virtual clock, or run the robot in a process of its own (tests/test_disturbances.py,
    tests/test_disturbance_matrix.py)."""
    from aiohal.safety import supervisor

    original_init = supervisor.Supervisor.__init__
    original_start = supervisor.Supervisor.start_watchdog
    watchdog_process = supervisor.WatchdogProcess

    def init(self, loop) -> None:
        original_init(self, loop)
        if loop.config.safety.max_tick_gap_ms is None and loop.source.kind != "virtual":
            self.max_tick_gap_ns = TEST_PROCESS_TICK_GAP_NS

    def start_watchdog(self) -> None:
        if "watchdog_ms" in self.loop.config.safety.model_fields_set:
            original_start(self)
            return
        with monkeypatch.context() as patch:
            patch.setattr(supervisor, "WatchdogProcess", lambda actions, _ms, priority: watchdog_process(
                actions, TEST_PROCESS_TICK_GAP_NS / 1e6, priority))
            original_start(self)

    monkeypatch.setattr(supervisor.Supervisor, "__init__", init)
    monkeypatch.setattr(supervisor.Supervisor, "start_watchdog", start_watchdog)


#: the start of the reason a realtime test skips with when the host could not meet its bound
HOST_UNFIT = "host unfit for this real-time bound"

#: the bare reference: sleeps to absolute 1 ms deadlines, at a given SCHED_FIFO priority, until
#: its stdin closes (or 10 min), then prints the worst lateness (ns) of its wakes
_REFERENCE = """
import os, select, sys, time
if int(sys.argv[1]):
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(sys.argv[1])))
period, worst = 1_000_000, 0
deadline = start = time.monotonic_ns()
print("ready", flush=True)
while not select.select([sys.stdin], [], [], 0)[0] and deadline - start < 600e9:
    deadline += period
    time.sleep(max(0, deadline - time.monotonic_ns()) / 1e9)
    now = time.monotonic_ns()
    worst = max(worst, now - deadline)
    deadline = max(deadline, now - now % period)  # after an overrun, from the current period on
print(worst, flush=True)
"""


class HostReference:
    """A bare reference measured beside a realtime test: a process of its own that only
    sleeps to absolute 1 ms deadlines, at the SCHED_FIFO priority of what the test times, and
    keeps its worst lateness. A bound on aiohal's time allows the host ``allowance_ms``; when
    the bare loop itself woke later than that during the test, the host could not have met
    the bound whatever aiohal does, and :meth:`require_fit` skips the test as run on an unfit
    host (the run's summary counts those skips)."""

    def __init__(self, allowance_ms: float, priority: int = 0) -> None:
        import subprocess
        import sys

        self.allowance_ms = allowance_ms
        self.priority = priority
        self.worst_ms: float | None = None
        self.proc = subprocess.Popen([sys.executable, "-I", "-c", _REFERENCE, str(priority)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        if self._line() != "ready":
            self.proc.kill()
            pytest.fail("the host reference did not start")

    def _line(self) -> str:
        import select

        ready, _, _ = select.select([self.proc.stdout], [], [], NOT_HUNG_S)
        return self.proc.stdout.readline().strip() if ready else ""

    def stop(self) -> float:
        """Ends the reference (once); its worst lateness in ms."""
        if self.worst_ms is None:
            self.proc.stdin.close()
            line = self._line()
            self.proc.kill()
            self.proc.wait(NOT_HUNG_S)
            self.worst_ms = int(line) / 1e6 if line else float("inf")
        return self.worst_ms

    def unfit_reason(self) -> str | None:
        """Ends the reference; why the host was unfit for the bound, or None if it was fit."""
        worst = self.stop()
        if worst <= self.allowance_ms:
            return None
        where = f"at SCHED_FIFO {self.priority}" if self.priority else "at normal priority"
        return (f"{HOST_UNFIT}: a bare sleep loop {where} woke {worst:.1f} ms late beside this test "
                f"(the bound allows the host {self.allowance_ms:g} ms)")

    def require_fit(self) -> None:
        reason = self.unfit_reason()
        if reason is not None:
            pytest.skip(reason)

    def __enter__(self) -> HostReference:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


@pytest.fixture(autouse=True)
def _host_reference(request):
    """A test marked ``host_reference(allowance_ms, priority=0)`` runs beside a bare reference
    (HostReference) from its set-up to its end: its peer grades every answer (FRI's KRC goes
    to command mode only on answers within a fifth of its cycle), so no bound of its own tells
    a stall of the host from the code's; a failure while the reference woke later than its
    allowance is reported as a skip, host unfit (pytest_runtest_makereport below)."""
    marker = request.node.get_closest_marker("host_reference")
    if marker is None:
        yield
        return
    allowance_ms, priority = marker.args[0], marker.args[1] if len(marker.args) > 1 else 0
    # (without root the answers keep their priority, and the reference can take no other)
    host = request.node.host_reference = HostReference(allowance_ms, priority if os.geteuid() == 0 else 0)
    try:
        yield
    finally:
        host.stop()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    host = getattr(item, "host_reference", None)
    if host is None or call.when != "call" or not report.failed:
        return
    reason = host.unfit_reason()
    if reason is not None:
        report.outcome = "skipped"
        report.longrepr = (str(item.path), item.location[1] or 0, f"Skipped: {reason}")


def pytest_terminal_summary(terminalreporter) -> None:
    unfit = [r for r in terminalreporter.stats.get("skipped", [])
             if isinstance(r.longrepr, tuple) and HOST_UNFIT in str(r.longrepr[-1])]
    terminalreporter.write_line(f"realtime tests skipped on a host unfit for their bounds: {len(unfit)}")


@pytest.fixture
def answers_at_fifo():
    """This test process's thread (and the threads it starts) at SCHED_FIFO 60 where allowed
    (root), as a robot's loop runs: for tests whose peer grades how soon it is answered (FRI's
    KRC goes to command mode only on answers within a fifth of its cycle), so that the driver is
    judged and not a loaded host's scheduling of this process. Elsewhere the priority stays."""
    if os.geteuid() != 0:
        yield
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
    try:
        yield
    finally:
        os.sched_setscheduler(0, policy, param)


def _loop_factories() -> dict:
    factories = {"asyncio": asyncio.new_event_loop}
    try:
        import uvloop
    except ImportError:  # uvloop is a core dependency on Linux; tolerate its absence elsewhere
        return factories
    factories["uvloop"] = uvloop.new_event_loop
    return factories


def _wanted_loops() -> list[str] | None:
    wanted = os.environ.get("AIOHAL_TEST_LOOPS")
    return [name.strip() for name in wanted.split(",") if name.strip()] if wanted else None


def pytest_configure(config) -> None:
    unknown = sorted(set(_wanted_loops() or ()) - set(_loop_factories()))
    if unknown:
        raise pytest.UsageError(f"AIOHAL_TEST_LOOPS names unknown loops {unknown}: choose from {sorted(_loop_factories())}")


def pytest_asyncio_loop_factories(config, item):
    """Both loops, except where a test is marked ``asyncio_only(why)`` (its code reaches the
    event loop only through calls whose uvloop path other tests cover: run twice, it would
    test the same thing twice) or ``AIOHAL_TEST_LOOPS`` (comma separated) narrows the run
    (.ci/run: the other Pythons, whose asyncio internals the ticker reads, on asyncio only)."""
    factories = _loop_factories()
    wanted = _wanted_loops()
    if wanted:
        factories = {name: factories[name] for name in wanted}
    if item.get_closest_marker("asyncio_only") is not None and "asyncio" in factories:
        factories = {"asyncio": factories["asyncio"]}
    return factories


def require_module(name: str):
    """Import an optional dependency or skip; under CI=true (where make test installs every
    extra the tests need) a missing one is a failure."""
    if os.environ.get("CI") == "true":
        import importlib

        return importlib.import_module(name)  # the named module itself, a dotted name's too
    return pytest.importorskip(name)


def require_root(reason: str) -> None:
    """Skip a test that needs root, except under CI=true where missing root is a failure."""
    if os.geteuid() == 0:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"needs root under CI: {reason}")
    pytest.skip(f"needs root: {reason}")


def start_segment(line: str, **options):
    """A started simulated EtherCAT segment (``aiohal.drivers.ethercat.sim.fixture``) for a
    module's tests; the caller stops it. Needs root and pysoem: skipped with the reason
    otherwise, a failure under CI=true."""
    require_root("a veth pair and a network namespace for the simulated EtherCAT segment")
    require_module("pysoem")
    from aiohal.drivers.ethercat.sim.fixture import (
        SimulatedSegment,
        SimulatorUnavailable,
    )

    try:
        segment = SimulatedSegment(line, **options)
        segment.start()
    except SimulatorUnavailable as exc:
        if os.environ.get("CI") == "true":
            pytest.fail(str(exc))
        pytest.skip(str(exc))
    return segment
