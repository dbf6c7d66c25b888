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


def _driver_reading(one_frame, checked, lost=(), known=None):
    """A driver (no bus opened) whose bus reads ``one_frame`` by SOEM's one-frame state read and
    slave by slave from ``checked`` ({position: (AL state, AL status code), or None: silent})."""
    import logging
    from types import SimpleNamespace

    from aiohal.drivers.ethercat.driver import EthercatDriver
    from aiohal.logutil import RateLimitedLogger

    asked = []

    def checked_states(positions, until_silent=False):
        found = {}
        for position in positions:
            asked.append(position)
            found[position] = checked[position]
            if found[position] is None and until_silent:
                break
        return found

    driver = object.__new__(EthercatDriver)
    driver.name, driver.lost, driver._states_generation, driver._expected = "bus", set(lost), 3, 9
    driver._known = list(known or [8] * len(one_frame))
    driver.al_checks = driver.al_checks_unanswered = driver.states_unanswered = driver.diagnoses = 0
    driver._al_found, driver._warn, driver._bad_run = None, RateLimitedLogger(logging.getLogger("test")), 10
    driver.bus = SimpleNamespace(states=lambda: list(one_frame), checked_states=checked_states, asked=asked)
    return driver


OP_ALL = [(8, 0)] * 3
OUT = [(8, 0), (0x14, 0x001A), (8, 0)]  # slave 1 in SAFEOP+ERROR, "synchronization error"
GARBAGE = [2, 0x1F, 0x13]  # what an unanswered one-frame read left (seen: 0xF+ERROR, BOOT, ...)


@pytest.mark.parametrize(
    ("one_frame", "checked", "wkc", "judged"),
    [
        ([8, 8, 8], {}, 5, OP_ALL),  # every slave in OP: the one-frame read, nothing more
        ([8, 0x14, 8], dict(enumerate(OUT)), 9, OUT),  # one out of OP: judged on each slave's own frame
        (GARBAGE, dict(enumerate(OP_ALL)), -1, OP_ALL),  # another frame's bytes: each slave says OP
        (GARBAGE, {0: None, 1: None, 2: None}, -1, None),  # nobody answered its own frame: not judged
        (GARBAGE, {0: (8, 0), 1: None, 2: None}, 6, [(8, 0), (0, 0), (0, 0)]),  # frames back: gone
        (GARBAGE, {0: (8, 0), 1: None, 2: None}, -1, OP_ALL),  # frames lost: what was known stays
    ],
)
def test_the_diagnosis_judges_each_slave_on_a_frame_of_its_own(one_frame, checked, wkc, judged):
    """SOEM's one-frame state read fills the states from its buffer whether or not its frame
    came back, and takes a reply that came back late to an earlier frame (a stalled host, a
    second master's frames on the wire) for the read that reuses its index: the bytes of
    another frame, the same read after read. A read showing a slave out of OP is judged on
    each slave's own checked frame; a slave silent on it is gone only when the cyclic frames
    come back (working counter >= 0), and a read nobody answered is not judged."""
    diagnosed = []
    driver = _driver_reading(one_frame, checked)
    driver._judge = lambda read, why: diagnosed.append(read)
    driver._diagnose(wkc)
    assert diagnosed == ([] if judged is None else [judged])
    assert driver.states_unanswered == (judged is None)
    assert driver.bus.asked == ([] if one_frame == [8, 8, 8] else [0, 1, 2])


@pytest.mark.parametrize(
    ("one_frame", "checked", "lost", "found", "asked", "unanswered"),
    [
        ([8, 8, 8], {}, (), None, [], 0),
        ([8, 0x14, 8], {1: (0x14, 0x1A)}, (), (3, OUT), [1], 0),  # read again on its own frame
        (GARBAGE, dict(enumerate(OP_ALL)), (), None, [0, 1, 2], 0),  # another frame's bytes
        (GARBAGE, {0: (8, 0), 1: None, 2: (8, 0)}, (), None, [0, 1], 1),  # silent: ends the check
        ([8, 0, 8], {}, (), None, [], 1),  # a one-frame read unanswered: not read slave by slave
        ([8, 0x14, 8], {}, (1,), None, [], 0),  # the lost one still out: its recovery's
        ([8, 0, 0x14], {2: (0x14, 0x1B)}, (1,), (3, [(8, 0), (0, 0), (0x14, 0x1B)]), [2], 0),  # a lost one reads NONE
        ([8, 8, 8], {}, (1,), (3, OP_ALL), [], 0),  # every slave in OP again: the lost one comes back
    ],
)
def test_the_al_check_reads_again_only_slaves_not_yet_lost(one_frame, checked, lost, found, asked, unanswered):
    """Off the tick, every 20 ms: a slave not yet lost that the one-frame read finds out of OP
    is read again on a frame of its own (a silent one ends the check: not judged); slaves
    already lost are their recovery's (one that reads NONE does not stop the check of the
    others), until every slave reads OP again."""
    driver = _driver_reading(one_frame, checked, lost, known=[8, 0, 8] if lost else None)
    driver._check_al_states()
    assert driver._al_found == found and driver.bus.asked == asked
    assert driver.al_checks_unanswered == unanswered


def test_a_checked_read_takes_each_slave_s_own_frame_and_names_the_silent_ones():
    """``Bus.checked_states``: FPRD of 0x0130..0x0135 per slave (AL status, then the AL
    status code at 0x0134); pysoem's WkcError is a silent slave; ``until_silent`` stops there."""
    import threading
    from types import SimpleNamespace

    from aiohal.drivers.ethercat.bus import Bus

    def slave(raw):
        def fprd(address, size, timeout_us):
            assert (address, size) == (0x0130, 6)
            if raw is None:
                raise RuntimeError("WkcError")
            return raw
        return SimpleNamespace(_fprd=fprd)

    bus = object.__new__(Bus)
    bus._states_lock = threading.Lock()
    bus.slaves = [slave(bytes([0x08, 0, 0, 0, 0, 0])), slave(None), slave(bytes([0x14, 0, 0xAA, 0xBB, 0x1B, 0]))]
    assert bus.checked_states([0, 1, 2]) == {0: (0x08, 0), 1: None, 2: (0x14, 0x001B)}
    assert bus.checked_states([2, 1, 0], until_silent=True) == {2: (0x14, 0x001B), 1: None}


def test_a_recovery_step_keeps_what_was_known_of_a_slave_silent_on_its_read():
    """The lost slaves only are read (one frame each); a silent one stays as it was known, one
    back in OP is recovered, one below SAFEOP is reported as needing a reconfiguration."""
    from types import SimpleNamespace

    driver = _driver_reading([8, 8, 8], {}, lost=(1, 2), known=[8, 0x14, 0x14])
    driver.infos = [SimpleNamespace(wkc=3, name=f"s{i}") for i in range(3)]
    driver.sensors, driver._reported, driver._unrecoverable, driver.recovered = [], {1, 2}, set(), 0
    driver.options = SimpleNamespace(recover_interval_s=1.0)
    faults = []
    driver.view = SimpleNamespace(fault=lambda message, hold: faults.append(message))
    reads = iter([{1: None, 2: (8, 0)}, {1: (0x01, 0)}])
    driver.bus.recover_steps = lambda positions: next(reads)
    driver._recover_lost()
    assert driver.lost == {1} and driver._known == [8, 0x14, 8] and driver.recovered == 1 and faults == []
    assert driver._expected == 9  # slave 1 in SAFEOP still counts
    driver._recover_lost()
    assert driver.lost == {1} and driver._unrecoverable == {1} and "reconfiguration" in faults[0]
    assert driver._expected == 6


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
