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


@pytest.mark.asyncio
async def test_a_sensor_dropped_to_safeop_error_is_faulted_with_its_al_status_within_100_ms(segment):
    """In SAFEOP its SyncManagers still work, so the working counter stays right: only the
    periodic AL state check sees it."""
    seen: dict = {}

    def drop_ft(loop):
        driver = driver_of(loop)

        def run():
            segment.control({"cmd": "al_error", "slave": 8, "code": 0x001B})  # SM watchdog
            seen["done"] = driver.cycles

        seen["future"] = asyncio.get_running_loop().run_in_executor(None, run)

    def watch(loop):
        tick = loop.robot.clock.tick
        if tick == 500:
            drop_ft(loop)
        if "done" in seen and "faulted" not in seen and loop.robot.device("wrist_ft").fault:
            seen["faulted"] = driver_of(loop).cycles
        if "faulted" in seen and driver_of(loop).cycles > seen["faulted"] + 50:
            loop.request_stop("seen")

    raw = raw_config(segment.ifname, recover_interval_s=60)  # it stays lost for the assertions
    async with ControlLoop(parse_config(raw)) as loop:
        loop.add_publisher(watch)
        report = await loop.run(ticks=8000)
        await seen["future"]
        bus = report["drivers"]["bus"]
    assert loop.stop_reason == "seen", loop.stop_reason
    # the check runs every 20 bus cycles (1 kHz): faulted within 100 of the slave's drop
    assert seen["faulted"] - seen["done"] < 100, seen
    lost = [f for f in report["faults"] if "ft" in f["error"] and "lost" in f["error"]]
    assert len(lost) == 1 and "SAFEOP+ERROR, AL status 0x001B (Sync manager watchdog)" in lost[0]["error"]
    assert bus["wkc_errors"] == bus["frames_lost"]  # the working counter never showed it
    assert report["safety_level"] == "run" and bus["lost"] == ["ft"]
