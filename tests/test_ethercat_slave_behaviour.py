"""The ``ethercat`` driver against slave behaviour the plain simulated line does not show:
a slow SAFEOP -> OP, a drive already in Fault at power-on, an I/O slave dropping to
SAFEOP + ERROR, a second master, slave-supplied bytes that do not fit.

Through real SOEM (pysoem) against the simulated segment over veth, like
``test_ethercat_driver.py`` (root; skipped with the reason otherwise, a failure under CI=true).
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest
from conftest import ROOT, start_segment
from test_ethercat_driver import (  # noqa: F401 (fixtures: this module's own segment of the same line)
    CONFIG,
    TicksRun,
    driver_of,
    frames_lost_allowed,
    one_drive_and,
    raw_config,
    segment,
    sim,
)

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.errors import DriverError

pytestmark = [pytest.mark.root, pytest.mark.asyncio_only("these test the simulated slaves, not the event loop")]


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
        if tick >= 500 and "future" not in seen:  # (a stall of the host skips ticks)
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


def _config_file(segment, tmp_path) -> str:
    text = CONFIG.read_text().replace('interface = "ecm0"', f'interface = "{segment.ifname}"')
    # this shared host stalls for longer than the loop's own feedback watchdogs at times
    text = text.replace("rate_hz = 1000\n", "rate_hz = 1000\nmax_feedback_age = 5000\nstall_timeout_ms = 5000\n", 1)
    text = text.replace("[[driver]]", "[safety]\nmax_tick_gap_ms = 5000\n\n[[driver]]", 1)
    # the frame timeouts of raw_config: on this loaded host frames come back late at times
    text = text.replace("sync0 = true", "sync0 = true\nreceive_timeout_us = 2000\nframe_timeout_us = 50000", 1)
    assert "max_feedback_age" in text and "frame_timeout_us" in text
    path = tmp_path / "ethercat_sim.toml"
    path.write_text(text)
    return str(path)


def _wait_all_op(segment, timeout_s=60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if all(s["state"] == "OP" for s in segment.status()["slaves"]):
            return True
        time.sleep(0.05)
    return False


def _second_master(config: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "aiohal", config, "--duration", "1"], capture_output=True,
                          text=True, timeout=120, cwd=ROOT, env={**os.environ, **env})


@pytest.mark.realtime  # two robot processes and the segment's simulator on two cores: run alone
@pytest.mark.parametrize("refused_by", ["lock", "op"])
def test_a_second_master_is_refused_and_the_first_keeps_running(segment, tmp_path, refused_by):
    """A second ``python -m aiohal`` on the interface: refused by the first one's lock on it,
    or (another master that is not aiohal here: a lock directory of its own) because the
    slaves are in OP; exit 1 before anything is written, and the first runs on undisturbed."""
    config = _config_file(segment, tmp_path)
    report_path = tmp_path / "first.json"
    # the first runs until it is told to stop: the second's start-up (imports, compiled kernels
    # on a cold cache) takes as long as the host makes it, and it must meet the first running
    first = subprocess.Popen([sys.executable, "-m", "aiohal", config, "--duration", "600", "--quiet",
                              "--report-json", str(report_path)], cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_all_op(segment), "the first master did not bring the bus up"
        counters_before = segment.status()["commands"]
        env = {"AIOHAL_LOCK_DIR": str(tmp_path)} if refused_by == "op" else {}
        second = _second_master(config, **env)
        counters_after = segment.status()["commands"]
        first_running = first.poll() is None
        first.send_signal(signal.SIGTERM)
        _, first_err = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            first.kill()
    assert first_running, first_err[-3000:]
    assert second.returncode == 1, second.stderr[-2000:]
    if refused_by == "lock":
        assert "is held by another aiohal process (pid " in second.stderr
    else:
        assert re.search(r"are in OP \(AL states ORed: 0x[0-9A-F]{2}\): another master is running this bus",
                         second.stderr), second.stderr[-2000:]
        assert "options.take_over = true" in second.stderr
    # nothing written by the second: no broadcast or addressed write beyond the first's own
    assert counters_after.get("BWR", 0) == counters_before.get("BWR", 0)
    assert counters_after.get("APWR", 0) == counters_before.get("APWR", 0)
    assert first.returncode == 0, first_err[-3000:]
    report = json.loads(report_path.read_text())
    bus = report["drivers"]["bus"]
    assert report["faults"] == [] and bus["drives_enabled"] == "7/7"
    # late frames only (the simulator not run in time by a loaded host): no wrong working counter
    assert bus["wkc_errors"] == bus["frames_lost"] <= frames_lost_allowed(segment, bus["cycles"], 20)


@pytest.mark.asyncio
async def test_a_drive_without_pdo_assignment_objects_is_mapped_from_its_sii(segment, caplog):
    """0x1C12/0x1C13 answered "object does not exist": SOEM maps the PDOs its SII describes,
    and the driver reads its layout from there too."""
    segment.control({"cmd": "hide_objects", "slave": 0, "indices": [0x1C12, 0x1C13]})
    with caplog.at_level("INFO", logger="aiohal.drivers.ethercat.bus"):
        async with ControlLoop(parse_config(raw_config(segment.ifname))) as loop:
            runs = TicksRun()
            loop.add_publisher(runs)
            report = await runs.run(loop, 300)
            layout = driver_of(loop).infos[0].layout
    assert "slave 0 (AIOHAL-Drive) has no PDO assignment object (0x1C12/0x1C13)" in caplog.text
    assert (layout.output_bits, layout.input_bits) == (13 * 8, 15 * 8)
    assert report["faults"] == [] and report["drivers"]["bus"]["drives_enabled"] == "7/7"


@pytest.mark.asyncio
async def test_a_configuration_error_is_not_retried_and_its_message_stays(segment, caplog):
    segment.control({"cmd": "dc", "slave": 3, "supported": False})
    loop = ControlLoop(parse_config(raw_config(segment.ifname)))  # the shipped sync0 = true
    with caplog.at_level("WARNING", logger="aiohal.drivers.ethercat.driver"), pytest.raises(DriverError) as err:
        await loop.activate()
    assert "slave 3 (AIOHAL-Drive) did not take SYNC0 at 1000000 ns" in str(err.value)
    assert "trying again" not in caplog.text
    assert segment.status()["counters"]["frames"] > 0 and not driver_of(loop).bus.is_open


def _driver_reading(one_frame, checked):
    """A driver (no bus opened) whose bus reads ``one_frame`` by SOEM's one-frame state read
    and ``checked`` slave by slave, each (AL state, AL status code), or None: nobody answered."""
    import logging

    from aiohal.drivers.ethercat.driver import EthercatDriver
    from aiohal.logutil import RateLimitedLogger

    driver = object.__new__(EthercatDriver)
    driver.name, driver.lost, driver._states_generation, driver._expected = "bus", set(), 3, 25
    driver.al_checks = driver.al_checks_unanswered = driver.states_unanswered = driver.diagnoses = 0
    driver._al_found, driver._warn, driver._bad_run = None, RateLimitedLogger(logging.getLogger("test")), 10
    driver.bus = type("Bus", (), {"states": staticmethod(lambda: list(one_frame)),
                                  "checked_states": staticmethod(lambda: checked)})()
    return driver


OP_ALL = [(8, 0)] * 3
OUT = [(8, 0), (0x14, 0x001A), (8, 0)]  # slave 1 in SAFEOP+ERROR, "synchronization error"


@pytest.mark.parametrize(
    ("one_frame", "checked", "judged"),
    [
        ([8, 8, 8], None, OP_ALL),  # every slave in OP: the one-frame read, nothing more
        ([8, 0x14, 8], OUT, OUT),  # one out of OP: read slave by slave, judged on that
        ([2, 0x1F, 0x13], OP_ALL, OP_ALL),  # another frame's bytes: each slave says OP
        ([2, 0x1F, 0x13], None, None),  # and no slave answered its own frame: not judged
        ([0, 0, 0], None, None),  # no answer in time (a busy host): not judged
    ],
)
def test_a_slave_out_of_op_is_judged_on_frames_of_its_own(one_frame, checked, judged):
    """SOEM's one-frame state read fills the states from its buffer whether or not its frame
    came back, and takes a reply that came back late to an earlier frame (a stalled host, a
    second master's frames on the wire) for the read that reuses its index: the bytes of
    another frame, the same read after read. A read showing a slave out of OP is judged on
    each slave's own checked frame, in the tick's diagnosis and in the AL check off the tick;
    a read nobody answered is not judged."""
    diagnosed = []
    driver = _driver_reading(one_frame, checked)
    driver._judge = lambda read, why: diagnosed.append(read)
    driver._diagnose(-1)
    assert diagnosed == ([] if judged is None else [judged])
    assert driver.states_unanswered == (judged is None and any(st != 8 for st in one_frame))

    driver = _driver_reading(one_frame, checked)
    driver._check_al_states()
    assert driver._al_found == (None if judged in (None, OP_ALL) else (3, judged))
    assert (driver.al_checks, driver.al_checks_unanswered) == (1, judged is None)


def test_a_slave_that_does_not_answer_is_not_judged_off_the_tick():
    """The AL check off the tick judges only a read every slave answered: a slave really gone
    shows in the working counter, which the tick's diagnosis reads."""
    driver = _driver_reading([8, 0x14, 8], [(8, 0), (0, 0), (8, 0)])
    driver._check_al_states()
    assert driver._al_found is None and driver.al_checks_unanswered == 1


def test_slaves_already_lost_are_not_read_one_by_one_on_each_check():
    """Off the tick, every 20 ms: a read whose slaves out of OP are all lost already finds
    nothing new (their recovery reads them each second); one new slave out is read slave by
    slave, and every slave back in OP is judged, so that the lost ones come back."""
    driver = _driver_reading([8, 0x14, 8], None)
    driver.lost = {1}
    driver.bus.checked_states = lambda: pytest.fail("read slave by slave for a slave already lost")
    driver._check_al_states()
    assert driver._al_found is None and driver.al_checks_unanswered == 0

    driver = _driver_reading([0x14, 0x14, 8], [(0x14, 0x1B), (0x14, 0x1A), (8, 0)])
    driver.lost = {1}
    driver._check_al_states()
    assert driver._al_found == (3, [(0x14, 0x1B), (0x14, 0x1A), (8, 0)])

    driver = _driver_reading([8, 8, 8], None)
    driver.lost = {1}
    driver._check_al_states()
    assert driver._al_found == (3, OP_ALL)


@pytest.mark.asyncio
async def test_slaves_left_in_op_are_refused_unless_the_config_takes_the_bus_over():
    """A master that stopped without taking its slaves out of OP (it crashed; their SM
    watchdogs are off): refused by default, brought up with options.take_over = true."""
    line = start_segment("drive", watchdog_ms=0)  # (skips without root or pysoem)
    import pysoem

    try:
        master = pysoem.Master()
        master.open(line.ifname)
        assert master.config_init() == 1
        master.config_map()
        assert master.state_check(pysoem.SAFEOP_STATE, 500_000) == pysoem.SAFEOP_STATE
        master.send_processdata()
        master.receive_processdata(20_000)
        master.state = pysoem.OP_STATE
        master.write_state()
        for _ in range(50):  # bounded: OP once an output cycle has arrived
            master.send_processdata()
            master.receive_processdata(20_000)
            if master.state_check(pysoem.OP_STATE, 5000) == pysoem.OP_STATE:
                break
        master.close()  # gone, its slave left in OP
        assert line.status()["slaves"][0]["state"] == "OP"
        loop = ControlLoop(parse_config(one_drive_and(line.ifname)))
        with pytest.raises(DriverError, match=r"are in OP .* another master is running this bus"):
            await loop.activate()
        assert line.status()["slaves"][0]["state"] == "OP"  # nothing written
        raw = one_drive_and(line.ifname)
        raw["driver"][0]["options"]["take_over"] = True
        async with ControlLoop(parse_config(raw)) as loop:
            report = await loop.run(ticks=200)
        assert report["faults"] == [] and report["drivers"]["bus"]["drives_enabled"] == "1/1"
    finally:
        line.stop()
