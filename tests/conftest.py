"""Shared test set-up: every async test runs on asyncio and on uvloop; root-only tests."""

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


@pytest.fixture(autouse=True)
def _host_stalls_are_not_the_subject(monkeypatch):
    """A loop ticking on a real clock inside the test process runs without SCHED_FIFO, and a
    loaded host (a user's CI, two CPU hogs) stops this process for 20-80 ms at times: with the
    default bound (20 ms) that is a stall, and the robot holds. Tests about something else
    must not be decided by the host, so such a loop gets a 5 s bound here. Tests about stalls
    set ``[safety] max_tick_gap_ms`` themselves, run on the virtual clock, or run the robot in
    a process of its own (tests/test_disturbances.py, tests/test_disturbance_matrix.py)."""
    from aiohal.safety import supervisor

    original = supervisor.Supervisor.__init__

    def init(self, loop) -> None:
        original(self, loop)
        if loop.config.safety.max_tick_gap_ms is None and loop.source.kind != "virtual":
            self.max_tick_gap_ns = TEST_PROCESS_TICK_GAP_NS

    monkeypatch.setattr(supervisor.Supervisor, "__init__", init)


def _loop_factories() -> dict:
    factories = {"asyncio": asyncio.new_event_loop}
    try:
        import uvloop
    except ImportError:  # uvloop is a core dependency on Linux; tolerate its absence elsewhere
        return factories
    factories["uvloop"] = uvloop.new_event_loop
    return factories


def pytest_asyncio_loop_factories(config, item):
    return _loop_factories()


def require_module(name: str):
    """Import an optional dependency or skip; under CI=true (where make test installs every
    extra the tests need) a missing one is a failure."""
    if os.environ.get("CI") == "true":
        return __import__(name)
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
