"""Where the CANopen driver receives: on a bus with a file descriptor (here a socket pair,
``can_pair``), the event loop's thread takes the frames between ticks once the drives are up,
and no thread of the driver runs beside the tick; the bring-up and the close keep canopen's
notifier thread; a bus whose reception keeps failing fails the driver."""

from __future__ import annotations

import itertools
import os
import threading

import can
import can.util
import numpy as np
import pytest

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.drivers.canopen import driver as canopen_driver

_channels = itertools.count()
JOINTS = ("j0", "j1")
IMU = {"device": "imu", "period_ms": 4.0, "stale_periods": 250, "status": "IMU_Gyro.Status", "signals": {
    "quaternion": ["IMU_Orientation.W", "IMU_Orientation.X", "IMU_Orientation.Y", "IMU_Orientation.Z"],
    "angular_velocity": ["IMU_Gyro.X", "IMU_Gyro.Y", "IMU_Gyro.Z"],
    "linear_acceleration": ["IMU_Accel.X", "IMU_Accel.Y", "IMU_Accel.Z"]}}


@pytest.fixture(autouse=True)
def pair_interface(monkeypatch):
    monkeypatch.setitem(can.interfaces.BACKENDS, "pair", ("can_pair", "PairBus"))
    monkeypatch.setattr(can.util, "VALID_INTERFACES", can.util.VALID_INTERFACES | {"pair"})  # checked by can.Bus


def raw_config(interface: str = "pair") -> dict:
    return {
        "robot": {"name": "can_pair_arm"},
        "loop": {"rate_hz": 250, "max_feedback_age": 50},
        "joints": {j: {"position": [-2.0, 2.0], "velocity": 2.0, "acceleration": 20.0, "effort": 50.0}
                   for j in JOINTS},
        "devices": {"imu": {"type": "imu"}},
        "driver": [{"type": "canopen", "name": "bus", "joints": list(JOINTS), "devices": ["imu"], "options": {
            "interface": interface, "channel": f"aiohal-pair-{os.getpid()}-{next(_channels)}", "simulate": True,
            "heartbeat_timeout_ms": 2000.0,  # the simulated nodes share a loaded host (default 200 ms)
            "nodes": [{"node_id": i + 1, "joint": j} for i, j in enumerate(JOINTS)], "sensors": [IMU]}}],
        "controller": {"type": "sine", "params": {"amplitude": 0.3, "frequency": 0.5}},
    }


def driver_threads(driver) -> list[str]:
    """The threads receiving on the driver's own bus (the simulator's end has its own)."""
    return [t.name for t in threading.enumerate() if driver.bus is not None and driver.bus.channel_info in t.name]


@pytest.mark.asyncio
async def test_on_a_bus_with_a_descriptor_the_loop_receives_and_no_driver_thread_runs():
    loop = ControlLoop(parse_config(raw_config()))
    async with loop:
        driver = loop.slots[0].driver
        assert driver.bus.channel_info.endswith("end B") and driver_threads(driver) == []
        during: list[list[str]] = []
        reached = [0.0]  # over the run: the last reading may follow a stall of the simulator

        def watch(lp):
            reached[0] = max(reached[0], float(np.max(np.abs(lp.robot.state.position))))
            if lp.robot.clock.tick % 50 == 0:
                during.append(driver_threads(driver))

        loop.add_publisher(watch)
        report = await loop.run(ticks=400)
        assert driver.drives.all_enabled()
        reach = reached[0]
        imu = loop.robot.imu["imu"]
    health = report["drivers"]["bus"]
    assert health["reception"] == "loop" and during and all(names == [] for names in during)
    assert report["faults"] == [] and health["rx_errors"] == 0 and health["malformed"] == 0
    assert health["rx_tpdos"] >= 2 * (report["ticks"] - health["late_cycles"])  # every TPDO taken
    assert reach > 0.05  # the drives follow the sine from the frames the loop received
    assert np.allclose(imu.linear_acceleration, (0, 0, 9.81), atol=0.01) and imu.fault == 0
    assert health["sensors"]["imu"]["frames"] > 0
    assert driver_threads(driver) == []  # the close's notifier is gone with the bus


@pytest.mark.asyncio
async def test_a_virtual_bus_has_no_descriptor_and_keeps_the_notifier_thread():
    async with ControlLoop(parse_config(raw_config("virtual"))) as loop:
        driver = loop.slots[0].driver
        assert len(driver_threads(driver)) == 2  # the simulator's and the driver's (same channel name)
        report = await loop.run(ticks=50)
    assert report["drivers"]["bus"]["reception"] == "thread" and report["faults"] == []


@pytest.mark.asyncio
async def test_a_bus_whose_reception_keeps_failing_fails_the_driver():
    loop = ControlLoop(parse_config(raw_config()))
    async with loop:
        driver = loop.slots[0].driver
        await loop.run(ticks=20)
        driver.bus.fail = "interface down"  # every receive now fails
        driver.sim.bus.send(can.Message(arbitration_id=0x700, data=b"\x05", is_extended_id=False))  # wake the reader
        loop.add_publisher(lambda lp: lp.request_stop("failed") if lp.faults else None)
        await loop.run(ticks=2000)
        assert driver.rx_errors >= canopen_driver.RX_FAILURES_LIMIT
        assert driver.health()["reception"] == "given up"  # not "thread": no thread took over
    assert [f.source for f in loop.faults][:1] == ["driver:bus"]
    assert "receiving failed" in loop.faults[0].error
