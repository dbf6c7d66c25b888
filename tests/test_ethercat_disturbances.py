"""EtherCAT drives stop by themselves when the master stops: every slave's SM watchdog is set
by default, read back after OP, and a slave that does not arm it is refused.

The register tests drive a simulated segment directly (no root). The end-to-end tests run real
SOEM (pysoem) against the simulated segment over veth: they need root and are skipped with the
reason otherwise, a failure under CI=true. The last one is the disturbance matrix's EtherCAT row
(tests/test_disturbance_matrix.py): the robot process frozen for 2 s. Trip times are the simulated slaves' own stamps
(their last outputs, their trip, their drive's safe state), never this process's clock.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
import tomllib

import numpy as np
import pytest
from conftest import CONFIGS, ROOT, require_module, start_segment
from test_ethercat_sim import OP, SAFEOP, enable_drive
from test_ethercat_sim import Bus as SimBus

from aiohal.drivers.ethercat import sm_watchdog
from aiohal.drivers.ethercat.sm_watchdog import max_ms, unit_ns, units_for

DEFAULT_MS = 50.0  # options.sm_watchdog_ms when the config does not say
DRIVE = 0x1001  # the first slave's station address on the register-level bus


def registers(bus: SimBus, station: int = DRIVE):
    def read(address: int, size: int) -> bytes:
        return bus.fprd(station, address, size)[0]

    def write(address: int, data: bytes) -> None:
        assert bus.fpwr(station, address, data) == 1

    return read, write


def slave_with(spec: str, **esc) -> SimBus:
    """A register-level bus whose first slave's ESC has the given watchdog settings."""
    bus = SimBus(spec)
    for key, value in esc.items():
        setattr(bus.seg.slaves[0], key, value)
    bus.seg.power_cycle(0)
    return bus


def trip_after(bus: SimBus, ms: float) -> bool:
    """The slave, fed its outputs now, then none for ``ms``: whether it left OP."""
    bus.lrw(bytes(bus.iomap))
    bus.clock.advance(ms)
    bus.seg.poll()
    return bus.al(DRIVE) == (SAFEOP | 0x10, 0x001B)


# ---------------------------------------------------------------- registers (no root)


def test_units_come_from_the_divider_and_a_value_out_of_range_does_not_fit():
    assert unit_ns(2498) == 100_000 and unit_ns(0) == 80
    assert units_for(50, 2498) == 500
    assert units_for(50, 0) is None  # 625000 units of 80 ns: the old code wrote 0xFFFF (5.2 ms)
    assert units_for(5, 0) == 62_500
    assert max_ms() == 6553.5 and units_for(6553.5, 2498) == 0xFFFF and units_for(6553.6, 2498) is None
    assert units_for(50, 0xFFFF) is None  # units of 2.62 ms: 19 of them are 49.8 ms


def test_a_divider_that_cannot_hold_the_time_is_set_and_the_slave_trips_on_time():
    bus = slave_with("drive", wd_divider_power_on=0)  # 80 ns units: at most 5.2 ms
    bus.up(to=SAFEOP)
    read, write = registers(bus)
    setting = sm_watchdog.program(read, write, DEFAULT_MS, "slave 0")
    assert (setting.divider, setting.units, setting.ms) == (2498, 500, 50.0)
    assert setting.output_sms == ((2, 0x64),) and setting.watched
    bus.lrw(bytes(bus.iomap))
    assert bus.bwr(0x0120, b"\x08\x00") == 1 and bus.al(DRIVE) == (OP, 0)
    enable_drive(bus, DRIVE)
    assert not trip_after(bus, 49.9)
    assert trip_after(bus, 50.1)
    assert bus.seg.slaves[0].device.model.state == "switch_on_disabled"  # its abort option (0x6007 = 2)


def test_a_time_the_divider_holds_keeps_the_divider_and_the_simulator_honours_it():
    bus = slave_with("drive", wd_divider_power_on=0)
    bus.up(to=SAFEOP)
    read, write = registers(bus)
    setting = sm_watchdog.program(read, write, 5.0, "slave 0")
    assert (setting.divider, setting.units) == (0, 62_500)
    bus.lrw(bytes(bus.iomap))
    bus.bwr(0x0120, b"\x08\x00")
    assert not trip_after(bus, 4.9)
    assert trip_after(bus, 5.1)


def test_a_slave_without_a_watchdog_is_refused_naming_its_divider_and_the_value():
    bus = slave_with("drive", wd_implemented=False)
    bus.up(to=SAFEOP)
    read, write = registers(bus)
    with pytest.raises(ValueError) as err:
        sm_watchdog.program(read, write, DEFAULT_MS, "slave 0 (AIOHAL-Drive)")
    assert str(err.value) == (
        "slave 0 (AIOHAL-Drive): its watchdog divider 0x0400 = 0 (80 ns units, at most 5.2428 ms) cannot "
        "hold sm_watchdog_ms = 50, and it kept 0 when 2498 (100 µs units) was written"
    )


def test_an_output_sm_that_does_not_trigger_the_watchdog_is_found_after_op():
    bus = slave_with("drive", wd_sm_trigger=False)
    bus.up(to=SAFEOP)
    read, write = registers(bus)
    written = sm_watchdog.program(read, write, DEFAULT_MS, "slave 0")  # the time is taken...
    bus.lrw(bytes(bus.iomap))
    bus.bwr(0x0120, b"\x08\x00")
    after = sm_watchdog.read_setting(read)
    assert (after.divider, after.units) == (2498, 500) and not after.watched
    assert sm_watchdog.check(after, written, "slave 0") == (
        "slave 0: its SM watchdog is not armed for 50 ms (divider 2498, 500 units written); read back "
        "after OP: divider 0x0400 = 2498, time 0x0420 = 500 units (50 ms), SM2 control 0x24 (watchdog off)"
    )
    assert not trip_after(bus, 500)  # ...and never runs


# ---------------------------------------------------------------- configuration (no root)


def run_check(tmp_path, **options) -> subprocess.CompletedProcess:
    require_module("pysoem")  # (check imports the driver)
    raw = (CONFIGS / "ethercat_sim.toml").read_text()
    lines = "".join(f"{key} = {value}\n" for key, value in options.items())
    path = tmp_path / "robot.toml"
    path.write_text(raw.replace("[driver.options]\n", "[driver.options]\n" + lines))
    return subprocess.run(
        [sys.executable, "-m", "aiohal", "check", str(path)], cwd=ROOT, capture_output=True, text=True, timeout=60
    )


def test_a_watchdog_time_beyond_the_registers_is_refused_at_check_naming_the_key(tmp_path):
    proc = run_check(tmp_path, sm_watchdog_ms=6553.6)
    assert proc.returncode == 2, proc
    assert "driver[0].options.sm_watchdog_ms: 6553.6 ms does not fit the watchdog registers: at most 6553.5 ms" in (
        proc.stderr
    )
    assert run_check(tmp_path, sm_watchdog_ms=6553.5).returncode == 0  # the registers' largest


def test_the_default_watchdog_time_must_outlast_the_keepalive_gaps(tmp_path):
    assert run_check(tmp_path).returncode == 0
    proc = run_check(tmp_path, keepalive_after_ms=40)
    assert proc.returncode == 2, proc
    assert "driver[0].options.sm_watchdog_ms: 50 ms (the default) would trip between runs" in proc.stderr
    assert run_check(tmp_path, keepalive_after_ms=40, sm_watchdog_ms=0).returncode == 0  # off: nothing to outlast


# ---------------------------------------------------------------- end to end (root)

LINE = "drive*7,imu,ft"  # as configs/ethercat_sim.toml
WITH_OUTPUTS = [f"drive{i}" for i in range(1, 8)] + ["ft"]  # the IMU has inputs only
SLACK_MS = 2.0  # a trip later than the watchdog time by more than this is a late stop...
SLACK_NO_RT_MS = 25.0  # ...when the simulator runs SCHED_FIFO; without it, a busy host wakes it late
FREEZE_S = 2.0  # the robot process's freeze in the disturbance matrix's row
ATTEMPTS = 3  # a run whose drives tripped before the freeze (a stall of this host) is run again


@pytest.fixture(scope="module")
def sim():
    # the slaves' own watchdog is off at power-on: only what the driver writes can stop them
    segment = start_segment(LINE, watchdog_ms=0)
    try:
        os.sched_setscheduler(segment.pid, os.SCHED_FIFO, os.sched_param(95))  # the hardware does not stall
        segment.slack_ms = SLACK_MS
    except OSError:  # no real-time scheduling here: a busy host wakes the simulator late
        segment.slack_ms = SLACK_NO_RT_MS
    yield segment
    segment.stop()


@pytest.fixture
def segment(sim):
    sim.control({"cmd": "clear"})
    sim.control({"cmd": "power_cycle"})
    sim.control({"cmd": "reset_counters"})
    return sim


def _raw(ifname: str, **options) -> dict:
    from test_ethercat_driver import raw_config

    return raw_config(ifname, **options)


@pytest.mark.root
@pytest.mark.asyncio
@pytest.mark.parametrize("divider", [2498, 0], ids=["divider-100us", "divider-80ns"])
async def test_the_watchdog_time_is_written_to_every_slave_with_outputs_and_read_back(segment, divider):
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop

    segment.control({"cmd": "watchdog", "divider": divider})  # the slaves' divider at power-on
    # 1 s, not the default: a stall of this process alone must not trip the slaves mid-test
    async with ControlLoop(parse_config(_raw(segment.ifname, sm_watchdog_ms=1000))) as loop:
        driver = loop.slots[0].driver
        assert driver.drives.all_enabled()
        assert driver.sm_watchdogs == dict.fromkeys(WITH_OUTPUTS, 1000.0)
        assert driver.health()["sm_watchdog_ms"] == [1000.0]
        slaves = segment.status()["slaves"]
    for s in slaves:
        armed = s["kind"] != "imu"
        assert s["watchdog_armed"] == armed, s
        # a divider of 0 cannot hold 1 s (at most 5.2 ms): the driver set it to 2498
        assert (s["watchdog_divider"], s["watchdog_units"]) == ((2498, 10_000) if armed else (divider, 0)), s


@pytest.mark.root
@pytest.mark.asyncio
@pytest.mark.parametrize(
    "esc, read_back",
    [
        ({"implemented": False}, "its watchdog divider 0x0400 = 0 (80 ns units, at most 5.2428 ms) cannot hold"),
        ({"sm_trigger": False}, "read back after OP: divider 0x0400 = 2498, time 0x0420 = 500 units (50 ms), SM2 "),
    ],
    ids=["no-watchdog-unit", "sm-without-trigger"],
)
async def test_a_slave_that_does_not_arm_its_watchdog_is_refused_unless_it_is_turned_off(
    segment, caplog, esc, read_back
):
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop
    from aiohal.errors import DriverError

    segment.control({"cmd": "watchdog", "slave": 2, **esc})
    raw = _raw(segment.ifname)
    del raw["driver"][0]["options"]["sm_watchdog_ms"]  # the default
    loop = ControlLoop(parse_config(raw))
    with caplog.at_level("WARNING", logger="aiohal.drivers.ethercat.driver"), pytest.raises(DriverError) as err:
        await loop.activate()
    assert "slave 2 (AIOHAL-Drive): " in str(err.value) and read_back in str(err.value), str(err.value)
    assert "options.sm_watchdog_ms = 0" in str(err.value)
    assert "trying again" not in caplog.text  # a configuration error: not retried
    assert not loop.slots[0].driver.bus.is_open
    # the report of the failed bring-up gives the working counter the slaves were mapped for
    refused_wkc = loop.report()["drivers"]["bus"]["expected_wkc"]
    caplog.clear()
    # turned off explicitly: the same slave is brought up, and a warning names what is unwatched
    with caplog.at_level("WARNING", logger="aiohal.drivers.ethercat.driver"):
        async with ControlLoop(parse_config(_raw(segment.ifname, sm_watchdog_ms=0))) as loop:
            assert loop.slots[0].driver.drives.all_enabled()
            assert loop.slots[0].driver.sm_watchdogs == {}
            assert loop.report()["drivers"]["bus"]["expected_wkc"] == refused_wkc > 0
    assert "sm_watchdog_ms = 0: the SM watchdogs of slave(s) 0 (drive1), 1 (drive2), 2 (drive3)" in caplog.text


def robot_config(tmp_path, ifname: str) -> os.PathLike:
    """configs/ethercat_sim.toml on this segment, the SM watchdog left at its default; the loop's
    own stale-feedback and stall checks wide (this shared host stalls at times)."""
    text = (CONFIGS / "ethercat_sim.toml").read_text()
    assert "sm_watchdog_ms" not in text
    text = text.replace(
        'interface = "ecm0"', f'interface = "{ifname}"\nreceive_timeout_us = 2000\nframe_timeout_us = 50000'
    )
    text = text.replace("rate_hz = 1000\n", "rate_hz = 1000\nmax_feedback_age = 5000\nstall_timeout_ms = 5000\n")
    # a stall of this host (tens of ms) is not the freeze under test (seconds)
    text = text.replace("[[driver]]", "[safety]\nmax_tick_gap_ms = 500\n\n[[driver]]", 1)
    path = tmp_path / "robot.toml"
    path.write_text(text)
    assert tomllib.loads(text)["driver"][0]["options"]["interface"] == ifname
    return path


def start_robot(path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "aiohal", str(path), "--duration", "60", "--quiet", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_enabled(segment, proc: subprocess.Popen, timeout_s: float = 60.0) -> list[dict]:
    """The drives, once all are enabled (bounded)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        drives = [s for s in segment.status()["slaves"] if s["kind"] == "drive"]
        if all(d["device"]["state"] == "operation_enabled" for d in drives):
            return drives
        select.select([], [], [], 0.05)
    proc.kill()
    pytest.fail(f"the robot did not enable its drives: {proc.communicate(timeout=30)[1][-3000:]}")


def wait_tripped(segment, timeout_s: float = 10.0) -> list[dict]:
    """The drives' slaves once every one has tripped (bounded: an armed watchdog trips)."""
    deadline = time.monotonic() + timeout_s
    while True:
        drives = [s for s in segment.status()["slaves"] if s["kind"] == "drive"]
        if all(d["watchdog_trip"] for d in drives) or time.monotonic() >= deadline:
            return drives
        select.select([], [], [], 0.01)


@pytest.mark.root
def test_every_drive_reaches_its_safe_state_within_the_watchdog_time_of_a_frozen_process(segment, tmp_path):
    path = robot_config(tmp_path, segment.ifname)
    for attempt in range(ATTEMPTS):
        segment.control({"cmd": "power_cycle"})
        proc = start_robot(path)
        try:
            drives = wait_enabled(segment, proc)
            # the default, written by the driver (the slaves' own is off)
            assert {(d["watchdog_ms"], d["watchdog_armed"]) for d in drives} == {(DEFAULT_MS, True)}
            frozen_ns = time.monotonic_ns()
            proc.send_signal(signal.SIGSTOP)
            drives = wait_tripped(segment)
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait(30)
        early = [d["name"] for d in drives if d["watchdog_trip"] and d["watchdog_trip"]["tripped_ns"] < frozen_ns]
        if not early:
            break
        print(f"attempt {attempt + 1}: {early} tripped before the freeze (this host stalled the robot)")
    assert not early, "every attempt was stalled before the freeze"
    trips = []
    for d in drives:
        trip, device = d["watchdog_trip"], d["device"]
        assert trip is not None, d  # the drives kept going (no watchdog armed)
        assert d["state"] == "SAFEOP" and d["error"] and d["al_status_code"] == 0x001B, d
        assert device["state"] != "operation_enabled", device
        # the slave's own stamps: its last outputs, its trip, its drive's safe state
        trips.append((trip["tripped_ns"] - trip["last_output_ns"]) / 1e6)
        assert device["outputs_lost_ns"] == trip["tripped_ns"]
    print(
        f"SM watchdog {DEFAULT_MS:g} ms: drives safe {min(trips):.3f} .. {max(trips):.3f} ms after their last "
        f"outputs ({', '.join(f'{t:.3f}' for t in trips)})"
    )
    assert all(DEFAULT_MS <= t <= DEFAULT_MS + segment.slack_ms for t in trips), trips


@pytest.mark.root
def test_a_frozen_robot_process_holds_where_it_stands_and_its_drives_stopped_by_themselves(segment, tmp_path):
    """The disturbance matrix's EtherCAT row: the CLI running ``sine`` is frozen for 2 s. The
    slaves' SM watchdogs stop the drives meanwhile; the resumed tick finds the stall and holds
    the robot where it is measured, with no command step."""
    from disturb import RobotProcess, commanded_ticks, stall_ms

    from aiohal.config import load_config
    from aiohal.record.reader import load

    path = robot_config(tmp_path, segment.ifname)
    config = load_config(path)
    robot = RobotProcess(path, tmp_path)
    try:
        robot.wait_for("running")
        time.sleep(1.0)  # the sine moves the arm: the freeze catches it moving
        stopped_ns, resumed_ns = robot.freeze(FREEZE_S)
        robot.wait_for_stall(FREEZE_S * 900)
        time.sleep(0.3)  # held for a moment after the resume
        report = robot.stop()
    finally:
        robot.kill()
    drives = [s for s in segment.status()["slaves"] if s["kind"] == "drive"]
    stall = [f for f in report["faults"] if f["phase"] == "stall" and stall_ms(f["error"]) >= FREEZE_S * 900]
    assert len(stall) == 1 and stall[0]["source"] == "loop", report["faults"]
    after = [(t["event"], t["after"]) for t in report["safety"] if t["tick"] >= stall[0]["tick"]]
    assert after[0] == ("fault", "hold"), report["safety"]
    # from the recording: the first command after the resume is where the arm was measured on
    # that tick (within one tick at the velocity limit), and no later one moves away from it
    ticks, command, measured = commanded_ticks(load(robot.record))
    step = config.build_robot().velocity_limit * config.period_ns / 1e9
    # (none when the driver's failure, found by its own thread on the resume, e-stops the robot
    # before a held tick was recorded: nothing is then sent at all)
    resumed = np.flatnonzero(ticks >= stall[0]["tick"])
    if resumed.size:
        first = resumed[0]
        assert (np.abs(command[first] - measured[first]) <= step + 1e-9).all(), (command[first], measured[first])
        moved = np.abs(command[resumed] - command[first]) > step + 1e-9
        assert not moved.any(), (
            f"commands moved away after the resume at ticks {ticks[resumed][moved.any(axis=1)][:10]}"
        )
    # the drives stopped by themselves during the freeze, each within its SM watchdog time
    trips = []
    for d in drives:
        trip = d["watchdog_trip"]
        assert trip is not None and stopped_ns <= trip["tripped_ns"] <= resumed_ns, (d, stopped_ns, resumed_ns)
        trips.append((trip["tripped_ns"] - trip["last_output_ns"]) / 1e6)
    # the resumed driver then finds its drives' slaves out of OP, tripped by their watchdogs
    tripped = [f for f in report["faults"] if f["source"] == "driver:bus" and "out of OP" in f["error"]]
    assert tripped and tripped[0]["error"].count("AL status 0x001B (Sync manager watchdog)") == 8, report["faults"]
    print(
        f"ethercat: stalled {stall_ms(stall[0]['error']):.0f} ms, {resumed.size} ticks held; drives safe "
        f"{min(trips):.3f} .. {max(trips):.3f} ms after their last outputs; safety {after}"
    )
    assert all(DEFAULT_MS <= t <= DEFAULT_MS + segment.slack_ms for t in trips), trips
