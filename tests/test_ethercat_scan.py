"""``python -m aiohal.drivers.ethercat.scan``: what is on a bus, and a config made from it.

The report and the config are checked from scanned slaves made here (no privilege needed);
the scan itself runs through real SOEM against the simulated segment over veth (root: skipped
with the reason otherwise, a failure under CI=true), and the config it prints then runs the bus.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib

import pytest
from conftest import ROOT, require_module, start_segment

from aiohal.config import parse_config
from aiohal.drivers.ethercat.names import FT_NAMES, IMU_NAMES
from aiohal.fieldbus.busvar import CIA402_NAMES, PdoLayout

require_module("pysoem")

from aiohal.drivers.ethercat.scan import (
    ScannedSlave,
    describe,
    main,
    suggest_kind,
    to_toml,
)

DRIVE_RX = [[(0x6040, 0, 16), (0x607A, 0, 32), (0x60FF, 0, 32), (0x6071, 0, 16), (0x6060, 0, 8)]]
DRIVE_TX = [[(0x6041, 0, 16), (0x6064, 0, 32), (0x606C, 0, 32), (0x6077, 0, 16), (0x603F, 0, 16)]]
IMU_TX = [[(0x6000, k, 32) for k in range(1, 5)] + [(0x6010, k, 32) for k in range(1, 4)]
          + [(0x6020, k, 32) for k in range(1, 4)] + [(0x6030, 0, 16)]]
FT_RX, FT_TX = [[(0x7000, 0, 16)]], [[(0x6000, k, 32) for k in range(1, 7)] + [(0x6010, 0, 16)]]
CIA402_DEVICE_TYPE = 0x00020192  # profile 402, servo drive

# what a robot config needs besides the driver: the scan cannot know it
ROBOT_PART = """
[robot]
name = "scanned"
[loop]
rate_hz = 1000
max_feedback_age = 5000
stall_timeout_ms = 5000
close_timeout_ms = 20000  # the bus's close beside two CPU hogs once took over the default 2 s
[safety]
max_tick_gap_ms = 5000  # a stall of a loaded host (tens of ms) is not what is tested
[joint_defaults]
position = [-2.5, 2.5]
velocity = 2.0
acceleration = 20.0
effort = 1.0
[controller]
type = "hold"
"""


def scanned(position, name, layout, device_type=None, vendor=0xA1A1A, product=0x402):
    return ScannedSlave(position, name, vendor, product, 1, 0x02, True, device_type, layout)


def line_of_every_kind() -> list[ScannedSlave]:
    return [
        scanned(0, "Drive", PdoLayout.from_entries(DRIVE_RX, DRIVE_TX, CIA402_NAMES), CIA402_DEVICE_TYPE),
        scanned(1, "Drive", PdoLayout.from_entries(DRIVE_RX, DRIVE_TX, CIA402_NAMES), CIA402_DEVICE_TYPE),
        scanned(2, "IMU", PdoLayout.from_entries([], IMU_TX, IMU_NAMES), product=0x1300),
        scanned(3, "FT", PdoLayout.from_entries(FT_RX, FT_TX, FT_NAMES), product=0x1600),
        scanned(4, "Coupler", PdoLayout(), product=0x44C2C52),
    ]


def test_each_slave_gets_the_kind_the_driver_could_run_it_as():
    assert [s.kind for s in line_of_every_kind()] == ["cia402", "cia402", "imu", "force_torque", "other"]
    # a drive whose PDOs lack one variable the drive class links is not offered as a drive
    short = PdoLayout.from_entries(DRIVE_RX, [DRIVE_TX[0][:-1]], CIA402_NAMES)
    assert suggest_kind(short) == "other"
    # three angular rates are not an IMU's four-value orientation
    assert suggest_kind(PdoLayout.from_entries([], [IMU_TX[0][1:]], IMU_NAMES)) == "other"


def test_the_report_lists_every_variable_and_says_why_a_402_device_is_no_drive():
    drive = line_of_every_kind()[0]
    short = scanned(1, "Elmo-like", PdoLayout.from_entries(DRIVE_RX, [DRIVE_TX[0][:-1]], CIA402_NAMES),
                    CIA402_DEVICE_TYPE)
    text = describe("ecm0", [drive, short])
    lines = text.splitlines()
    assert lines[0] == "ecm0: 2 slave(s)"
    assert "product 0x00000402" in lines[1] and "PREOP" in lines[1] and "kind cia402" in lines[1]
    assert "in     0.0 0x6041:00  16 u16  Statusword" in text
    assert "out   12.0 0x6060:00   8 i8   Modes of operation" in text
    assert 'not usable as a drive as mapped: unknown variable "Error code"' in text
    assert "remap it with rx_pdos / tx_pdos" in text
    packed = scanned(2, "DIO4", PdoLayout.from_entries([[(0x7000, k, 1) for k in range(1, 5)]], []), product=0x804)
    assert packed.kind == "other"
    assert "fewer than 8 bits of process data in a direction" in describe("ecm0", [packed])


def test_the_config_it_prints_passes_the_drivers_check():
    slaves = line_of_every_kind()
    text = to_toml("ecm0", slaves)
    config = parse_config(tomllib.loads(text + ROBOT_PART))
    (driver,) = config.drivers
    assert list(driver.joints) == ["joint1", "joint2"]
    assert [s.name for s in driver.options.slaves] == ["drive1", "drive2", "imu1", "ft1", "slave4"]
    assert [s.kind for s in driver.options.slaves] == ["cia402", "cia402", "imu", "force_torque", "other"]
    # the identities are in it, so bring-up refuses a bus that is not the one scanned
    assert [s.product_code for s in driver.options.slaves] == [0x402, 0x402, 0x1300, 0x1600, 0x44C2C52]
    assert {s.vendor_id for s in driver.options.slaves} == {0xA1A1A}
    assert [(name, kind) for name, kind, _ in config.devices] == [("imu1", "imu"), ("ft1", "force_torque")]


def test_an_interface_that_does_not_exist_exits_2_before_anything_is_opened(capsys):
    assert main(["aiohal-none0"]) == 2
    assert "'aiohal-none0' does not exist" in capsys.readouterr().err


# ---------------------------------------------------------------- through real SOEM


@pytest.fixture(scope="module")
def sim():
    segment = start_segment("drive*2,imu,ft,dio", watchdog_ms=1000)
    yield segment
    segment.stop()


def run_scan(ifname: str, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "aiohal.drivers.ethercat.scan", ifname, *flags],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)


def test_the_scan_finds_every_slave_and_moves_none(sim):
    sim.control({"cmd": "power_cycle"})
    sim.control({"cmd": "reset_counters"})
    proc = run_scan(sim.ifname, "--json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    found = json.loads(proc.stdout)["slaves"]
    assert [s["device_name"] for s in found] == ["AIOHAL-Drive", "AIOHAL-Drive", "AIOHAL-IMU", "AIOHAL-FT", "AIOHAL-DIO8"]
    assert [s["product_code"] for s in found] == [0x402, 0x402, 0x1300, 0x1600, 0x808]
    assert [s["kind"] for s in found] == ["cia402", "cia402", "imu", "force_torque", "other"]
    assert [s["coe"] for s in found] == [True, True, True, True, False]
    assert [s["state"] for s in found] == ["PREOP"] * 5
    drive_inputs = [(e["name"], e["type"], e["bit_offset"]) for e in found[0]["inputs"]]
    assert drive_inputs[:2] == [("Statusword", "u16", 0), ("Position actual value", "i32", 16)]
    assert [e["name"] for e in found[4]["outputs"]] == [f"Output.{k}" for k in range(1, 9)]  # from its SII
    status = sim.status()
    assert [s["state"] for s in status["slaves"]] == ["INIT"] * 5  # put back at the end
    assert not {"LRD", "LWR", "LRW"} & set(status["commands"])  # no process data was exchanged


def test_the_config_it_prints_runs_the_bus(sim, tmp_path):
    sim.control({"cmd": "power_cycle"})
    proc = run_scan(sim.ifname, "--toml")
    assert proc.returncode == 0, proc.stderr[-3000:]
    config = tmp_path / "scanned.toml"
    config.write_text(proc.stdout + ROBOT_PART)
    run = subprocess.run([sys.executable, "-m", "aiohal", str(config), "--duration", "1", "--report-json",
                          str(tmp_path / "report.json")], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["ticks"] > 0 and not report["faults"]
    assert report["drivers"]["bus"]["cycles"] >= report["ticks"]


# a joint another driver moves: a bus of I/O terminals is a part of a robot, not a robot
MOCK_JOINT = """
[joints.j1]
[[driver]]
type = "mock"
name = "arm"
joints = ["j1"]
"""


def test_a_bus_without_drives_says_what_to_add_and_runs_as_a_part_of_a_robot():
    dio = PdoLayout.from_entries([[(0x7000, k, 1) for k in range(1, 9)]], [[(0x6000, k, 1) for k in range(1, 9)]],
                                 {})
    slaves = [scanned(0, "AIOHAL-DIO8", dio, product=0x808), scanned(1, "AIOHAL-DIO8", dio, product=0x808)]
    text = to_toml("ecm0", slaves)
    assert "joints = []" in text and "# This bus has no cia402 drive" in text and "Add this [[driver]]" in text
    config = parse_config(tomllib.loads(text + ROBOT_PART + MOCK_JOINT))
    assert [d.type for d in config.drivers] == ["ethercat", "mock"] and config.drivers[0].joints == ()


def test_a_scanned_bus_of_io_terminals_runs_as_a_part_of_a_robot(tmp_path):
    segment = start_segment("dio*2", watchdog_ms=1000)
    try:
        proc = run_scan(segment.ifname, "--toml")
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "note: This bus has no cia402 drive" in proc.stderr  # what to add, said where it is seen
        config = tmp_path / "io.toml"
        config.write_text(proc.stdout + ROBOT_PART + MOCK_JOINT)
        check = subprocess.run([sys.executable, "-m", "aiohal", "check", str(config)], capture_output=True,
                               text=True, timeout=120, cwd=ROOT)
        assert check.returncode == 0, check.stderr[-3000:]
        run = subprocess.run([sys.executable, "-m", "aiohal", str(config), "--duration", "1", "--report-json",
                              str(tmp_path / "report.json")], capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert run.returncode == 0, run.stderr[-3000:]
        report = json.loads((tmp_path / "report.json").read_text())
        assert report["ticks"] > 0 and not report["faults"] and report["drivers"]["bus"]["slaves"] == 2
    finally:
        segment.stop()
