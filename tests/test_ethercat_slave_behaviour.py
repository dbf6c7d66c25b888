"""The ``ethercat`` driver against slave behaviour the plain simulated line does not show:
a slow SAFEOP -> OP, a drive already in Fault at power-on, an I/O slave dropping to
SAFEOP + ERROR, a second master, slave-supplied bytes that do not fit.

Through real SOEM (pysoem) against the simulated segment over veth, like
``test_ethercat_driver.py`` (root; skipped with the reason otherwise, a failure under CI=true).
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time

import pytest
from conftest import ROOT, start_segment
from test_ethercat_driver import CONFIG, TicksRun, driver_of, raw_config

from aiohal.config import parse_config
from aiohal.loop import ControlLoop

pytestmark = pytest.mark.root

LINE = "drive*7,imu,ft"


@pytest.fixture(scope="module")
def sim():
    segment = start_segment(LINE, watchdog_ms=1000)
    yield segment
    segment.stop()


@pytest.fixture
def segment(sim):
    sim.control({"cmd": "clear"})
    sim.control({"cmd": "power_cycle"})
    sim.control({"cmd": "reset_counters"})
    yield sim
    sim.control({"cmd": "clear"})


@pytest.mark.asyncio
async def test_a_drive_in_fault_at_power_on_is_reset_and_enabled_after_a_slow_safeop_to_op(segment):
    """The one automatic fault reset must go out in OP: a slave ignores outputs before."""
    segment.control({"cmd": "device", "slave": 2, "power_on_fault": 0x7500})
    segment.control({"cmd": "power_cycle", "slave": 2})
    segment.control({"cmd": "op_delay", "ms": 1500})
    started = time.monotonic()
    async with ControlLoop(parse_config(raw_config(segment.ifname))) as loop:
        took = time.monotonic() - started
        runs = TicksRun()
        loop.add_publisher(runs)
        report = await runs.run(loop, 200)
        status = await asyncio.to_thread(segment.status)
    assert took >= 1.5  # the delay was there
    drive3 = status["slaves"][2]["device"]
    assert drive3["state"] == "operation_enabled" and drive3["faults"] == 1
    assert report["faults"] == [] and report["drivers"]["bus"]["drives_enabled"] == "7/7"
