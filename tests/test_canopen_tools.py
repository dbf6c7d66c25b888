"""The CANopen scan (identity, NMT state, PDO mapping as the driver would use it, a config
that checks) and the simulated nodes' command line, on python-can's virtual interface."""

from __future__ import annotations

import itertools
import os
import threading
import time
import tomllib

import can
import canopen
import numpy as np
import pytest
from conftest import CONFIGS

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.drivers.canopen import scan
from aiohal.drivers.canopen.sim import SimBus
from aiohal.drivers.canopen.sim.__main__ import main as sim_main
from aiohal.drivers.canopen.sim.__main__ import node_ids, rpdo_type

_channels = itertools.count()


def channel() -> str:
    return f"aiohal-tools-{os.getpid()}-{next(_channels)}"


def connected(ch: str) -> canopen.Network:
    network = canopen.Network(can.Bus(interface="virtual", channel=ch, receive_own_messages=False))
    network.NOTIFIER_CYCLE = 0.05
    return network.connect()


def test_scan_lists_the_nodes_and_prints_a_config_that_checks():
    ch = channel()
    sim = SimBus("virtual", ch, [3, 5])
    sim.drives[3].node.nmt.start_heartbeat(20)
    network = connected(ch)
    try:
        nodes = scan.scan(network, listen_s=0.3)
    finally:
        network.disconnect()
        sim.close()
    assert [n.node_id for n in nodes] == [3, 5]
    three = nodes[0]
    assert three.is_drive and three.vendor_id == 0x000A1A1A and three.product_code == 0x402 and three.serial == 3
    assert three.nmt_state == "PRE-OPERATIONAL" and nodes[1].nmt_state is None
    assert [p.cob_id for p in three.tpdos] == [0x183, 0x283] and three.tpdos[0].enabled and not three.tpdos[1].enabled
    assert three.tpdos[0].entries == [(0x6041, 0, 16), (0x6064, 0, 32), (0x6077, 0, 16)]
    used, missing = three.drive_mapping()
    assert used == ["Statusword", "Position actual value", "Torque actual value", "Controlword", "Target position",
                    "Modes of operation"] and missing == []
    text = scan.describe(nodes)
    assert "node 3: CiA 402 drive, vendor 0x000A1A1A" in text and "NMT unknown (no heartbeat heard)" in text
    toml = tomllib.loads(scan.to_toml(nodes, "socketcan", "can0", 1_000_000))
    raw = {"joints": {j: {"velocity": 1.0} for j in toml["driver"][0]["joints"]}, **toml}
    config = parse_config(raw)  # the printed config is valid as it stands
    assert [n.node_id for n in config.drivers[0].options.nodes] == [3, 5]


@pytest.mark.asyncio
async def test_the_simulator_command_line_serves_a_driver_until_stopped():
    ch = channel()
    stop, ready = threading.Event(), threading.Event()
    runner = threading.Thread(target=sim_main, args=(["--interface", "virtual", "--channel", ch, "--drives", "1-2"],
                                                     stop, ready))
    runner.start()
    try:
        assert ready.wait(10)
        raw = {
            "loop": {"rate_hz": 250, "max_feedback_age": 50},
            "joints": {"j0": {"velocity": 1.0}, "j1": {"velocity": 1.0}},
            "driver": [{"type": "canopen", "name": "bus", "joints": ["j0", "j1"], "options": {
                "interface": "virtual", "channel": ch,
                "nodes": [{"node_id": 1, "joint": "j0"}, {"node_id": 2, "joint": "j1"}]}}],
        }
        async with ControlLoop(parse_config(raw)) as loop:
            report = await loop.run(ticks=100)
        assert report["drivers"]["bus"]["drives_enabled"] == "2/2" and report["faults"] == []
    finally:
        stop.set()
        runner.join(5)
    assert not runner.is_alive()


def test_the_simulator_command_line_refuses_bad_servo_parameters(capsys):
    args = ["--interface", "virtual", "--channel", channel(), "--drives", "1", "--dynamics", "servo"]
    assert sim_main([*args, "--servo-json", '{"gear_ratio": 0}'], threading.Event(), None) == 2
    err = capsys.readouterr().err
    assert "drive: servo: " in err and "gear_ratio" in err


def test_node_ids_are_parsed_and_checked():
    assert node_ids("1-3,7") == [1, 2, 3, 7]
    for bad in ("0", "1-200", "a", "1,1"):
        with pytest.raises(Exception, match="node ids"):
            node_ids(bad)


@pytest.mark.asyncio
async def test_the_driver_runs_nodes_configured_as_their_makers_ship_them():
    """Drives whose RPDOs are event-driven (255), an IMU without orientation and a status whose
    0 means OK: the simulator's command line so configured, the driver as it is."""
    ch = channel()
    stop, ready = threading.Event(), threading.Event()
    argv = ["--interface", "virtual", "--channel", ch, "--drives", "1-2", "--rpdo-type", "255",
            "--sensors", "--no-orientation", "--status-ok", "0"]
    runner = threading.Thread(target=sim_main, args=(argv, stop, ready))
    runner.start()
    try:
        assert ready.wait(10)
        # stale after 200 ms: the frames' timing on a loaded host is not this test's subject
        imu = {"device": "imu", "period_ms": 4.0, "stale_periods": 50, "status": "IMU_Gyro.Status",
               "status_valid": "clear",
               "signals": {"angular_velocity": ["IMU_Gyro.X", "IMU_Gyro.Y", "IMU_Gyro.Z"],
                           "linear_acceleration": ["IMU_Accel.X", "IMU_Accel.Y", "IMU_Accel.Z"]}}
        raw = {
            "loop": {"rate_hz": 250, "max_feedback_age": 50},
            "joints": {"j0": {"velocity": 2.0}, "j1": {"velocity": 2.0}},
            "devices": {"imu": {"type": "imu"}},
            "driver": [{"type": "canopen", "name": "bus", "joints": ["j0", "j1"], "devices": ["imu"], "options": {
                "interface": "virtual", "channel": ch, "sensors": [imu],
                "nodes": [{"node_id": 1, "joint": "j0"}, {"node_id": 2, "joint": "j1"}]}}],
            "controller": {"type": "sine", "params": {"amplitude": 0.2, "frequency": 1.0}},
        }
        async with ControlLoop(parse_config(raw)) as loop:
            driver = loop.slots[0].driver
            assert [node.rpdo[1].trans_type for node in driver.remotes] == [255, 255]
            reach = [0.0]
            loop.add_publisher(lambda lp: reach.append(float(np.max(np.abs(lp.robot.state.position)))))
            report = await loop.run(ticks=250)
            imu_record = loop.robot.imu["imu"]
            assert max(reach) > 0.1  # the drives followed the sine
            assert np.all(np.isnan(imu_record.quaternion)) and imu_record.linear_acceleration[2] == pytest.approx(9.81)
        health = report["drivers"]["bus"]
        assert report["faults"] == [] and health["drives_enabled"] == "2/2"
        assert health["sensors"]["imu"]["frames"] > 0 and health["sensors"]["imu"]["invalid"] == 0
    finally:
        stop.set()
        runner.join(5)
    assert not runner.is_alive()


def test_an_event_driven_rpdo_is_applied_on_receipt_a_synchronous_one_on_sync():
    ch = channel()
    sim = SimBus("virtual", ch, [1, 2], rpdo_transmission_type=255)
    sim.drives[2].node.sdo[0x1400][2].raw = 1
    network = connected(ch)
    try:
        for node_id in (1, 2):
            network.send_message(0, bytes((0x01, node_id)))  # NMT start: the PDOs compiled
        # RPDO1: controlword 0x0006, target position 5000, mode 8
        for node_id in (1, 2):
            network.send_message(0x200 + node_id, bytes((6, 0)) + (5000).to_bytes(4, "little") + bytes((8,)))
        deadline = time.monotonic() + 5
        while sim.drives[1].model.e_target_pos.value != 5000 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert sim.drives[1].model.e_target_pos.value == 5000  # no SYNC yet
        assert sim.drives[2].model.e_target_pos.value == 0 and sim.drives[2].pending
        network.send_message(0x80, b"")
        while sim.drives[2].model.e_target_pos.value != 5000 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert sim.drives[2].model.e_target_pos.value == 5000
    finally:
        network.disconnect()
        sim.close()


def test_rpdo_types_are_parsed_and_checked():
    assert [rpdo_type(t) for t in ("0", "240", "254", "255")] == [0, 240, 254, 255]
    for bad in ("241", "253", "-1", "x"):
        with pytest.raises(Exception, match=r"transmission type is 0\.\.240, 254 or 255"):
            rpdo_type(bad)


@pytest.mark.parametrize("content, reason", [
    (b"[FileInfo]\nFileName=x\n[1000]\nParameterName=Dev\n[unclosed\n", "not a readable EDS/DCF (ParsingError"),
    (b"\xff\xfe\x00binary", "not UTF-8 text"),
])
def test_a_malformed_eds_is_a_config_error_naming_the_key_and_the_file(tmp_path, content, reason):
    from aiohal.errors import ConfigError

    eds = tmp_path / "drive.eds"
    eds.write_bytes(content)
    raw = tomllib.loads((CONFIGS / "canopen_arm_sim.toml").read_text())
    raw["driver"][0]["options"]["simulate"] = False
    raw["driver"][0]["options"]["nodes"][0]["eds"] = str(eds)
    with pytest.raises(ConfigError) as info:
        parse_config(raw, base_dir=CONFIGS)
    lines = [str(issue) for issue in info.value.issues]
    assert any(line.startswith("driver[0].options.nodes[0].eds: ") and str(eds) in line and reason in line
               for line in lines), lines
