"""CAN sensors decoded from a DBC file with cantools: values into the robot's IMU and F/T
records, stale when the frames stop and back when they return, malformed frames counted and
dropped (fuzzed), and config errors that name the signal."""

from __future__ import annotations

import itertools
import logging
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.drivers.canopen.sensors import SENSORS_DBC, DbcSensor, SensorGateway, SensorOptions, load_dbc
from aiohal.drivers.canopen.sim import SimBus
from aiohal.errors import ConfigError
from aiohal.robot import Fault, Robot

_channels = itertools.count()

# 1 s before stale: beside two CPU hogs the simulated gateway's thread went 100 ms without a
# frame (the staleness row sets its own)
IMU = {"device": "imu", "period_ms": 4.0, "stale_periods": 250, "status": "IMU_Gyro.Status", "signals": {
    "quaternion": ["IMU_Orientation.W", "IMU_Orientation.X", "IMU_Orientation.Y", "IMU_Orientation.Z"],
    "angular_velocity": ["IMU_Gyro.X", "IMU_Gyro.Y", "IMU_Gyro.Z"],
    "linear_acceleration": ["IMU_Accel.X", "IMU_Accel.Y", "IMU_Accel.Z"]}}
FT = {"device": "ft", "period_ms": 4.0, "stale_periods": 250, "status": "FT_Force.Status", "signals": {
    "force": ["FT_Force.X", "FT_Force.Y", "FT_Force.Z"], "torque": ["FT_Torque.X", "FT_Torque.Y", "FT_Torque.Z"]}}


def raw_config(sensors: list[dict], channel: str | None = None, **options) -> dict:
    channel = channel or f"aiohal-sensors-{os.getpid()}-{next(_channels)}"
    return {
        "robot": {"name": "gateway"},
        "loop": {"rate_hz": 250},
        "joints": {"j0": {"position": [-1.0, 1.0], "velocity": 1.0}},
        "devices": {"imu": {"type": "imu"}, "ft": {"type": "force_torque"}},
        "driver": [
            {"type": "mock", "name": "arm", "joints": ["j0"]},
            {"type": "canopen", "name": "can", "joints": [], "devices": ["imu", "ft"], "options": {
                "interface": "virtual", "channel": channel,
                "simulate": True, "sensors": sensors, **options}}],
        "controller": {"type": "hold"},
    }


def driver_of(loop):
    return loop.slots[1].driver


@pytest.mark.asyncio
async def test_sensor_frames_fill_the_imu_and_ft_records():
    async with ControlLoop(parse_config(raw_config([IMU, FT]))) as loop:
        report = await loop.run(ticks=100)
        imu, ft = loop.robot.imu["imu"], loop.robot.force_torque["ft"]
        # within one LSB of the DBC's scaling of what the gateway sent
        assert np.allclose(imu.quaternion, (1, 0, 0, 0), atol=5e-5)
        assert np.allclose(imu.linear_acceleration, (0, 0, 9.81), atol=0.01)
        assert np.allclose(ft.force, (1.0, -2.0, 15.0), atol=0.05)
        assert np.allclose(ft.torque, (0.1, -0.05, 0.02), atol=0.001)
        # updated into the run's second half: a loaded host lags the gateway's thread by tens of ms
        assert imu.fault == 0 and ft.fault == 0 and imu.updated_tick > 50
    sensors = report["drivers"]["can"]["sensors"]
    assert sensors["imu"]["frames"] > 0 and sensors["malformed"] == 0 and report["faults"] == []


@pytest.mark.asyncio
async def test_a_sensor_whose_frames_stop_is_stale_and_comes_back():
    async with ControlLoop(parse_config(raw_config([{**IMU, "stale_periods": 3}, FT]))) as loop:
        driver = driver_of(loop)
        await loop.run(ticks=20)
        gateway = driver.sim.sensors
        gateway.stopped = True
        imu = loop.robot.imu["imu"]
        wanted = {"stale": True}

        def stop_when(lp):
            if bool(imu.fault & Fault.STALE) == wanted["stale"]:
                lp.request_stop("seen")

        loop.add_publisher(stop_when)
        await loop.run(ticks=500)
        assert imu.fault & Fault.STALE
        gateway.stopped = False
        wanted["stale"] = False
        report = await loop.run(ticks=500)
        assert imu.fault == 0
    faults = [f["error"] for f in report["faults"]]
    assert any("sensor imu is stale: no valid frame for 12 ms (3 periods)" in f for f in faults)
    assert report["drivers"]["can"]["sensors"]["imu"]["stale_events"] >= 1


@pytest.mark.asyncio
async def test_sensor_frames_of_the_wrong_length_are_counted_and_dropped():
    async with ControlLoop(parse_config(raw_config([IMU, FT]))) as loop:
        driver = driver_of(loop)
        driver.sim.sensors.wrong_dlc = True
        loop.add_publisher(lambda lp: lp.request_stop("seen") if driver.gateway.malformed >= 10 else None)
        await loop.run(ticks=500)
        assert driver.gateway.malformed >= 10


def test_a_signal_that_is_not_in_the_dbc_is_named():
    bad = {**FT, "signals": {"force": ["FT_Force.X", "FT_Force.Q", "FT_Forse.Z"], "torque": ["FT_Torque.X"]}}
    with pytest.raises(ConfigError) as err:
        parse_config(raw_config([IMU, bad]))
    text = str(err.value)
    assert 'options.sensors[1].signals.force[1]: message "FT_Force" has no signal "Q"' in text
    assert 'options.sensors[1].signals.force[2]: no message "FT_Forse" in the DBC' in text
    assert "options.sensors[1].signals.torque: 3 signals expected, got 1" in text


def _gateway():
    robot = Robot("r", [], devices=[("imu", "imu", None), ("ft", "force_torque", None)])
    db = load_dbc(str(SENSORS_DBC))
    sensors = [DbcSensor(SensorOptions(**IMU), robot.imu["imu"], "imu", db),
               DbcSensor(SensorOptions(**FT), robot.force_torque["ft"], "force_torque", db)]
    return SensorGateway(sensors, db, "fuzz")


@settings(max_examples=300, deadline=None)
@given(frame=st.sampled_from([272, 273, 274, 288, 289]), data=st.binary(min_size=0, max_size=8))
def test_the_decoder_takes_any_bytes_without_raising(frame, data):
    gateway = _gateway()
    message = gateway.messages[frame]
    gateway.on_frame(frame, bytearray(data), 0.0)
    if len(data) != message.length:
        assert gateway.malformed == 1 and all(s.frames == 0 for s in gateway.sensors)
    else:
        assert gateway.malformed == 0
        taken = sum(s.frames + s.invalid for s in gateway.sensors)
        assert taken >= 1
        assert all(np.all(np.isfinite(s.buffer)) for s in gateway.sensors)


NO_ORIENTATION = {**IMU, "signals": {k: v for k, v in IMU["signals"].items() if k != "quaternion"}}


@pytest.mark.asyncio
async def test_an_imu_without_orientation_reads_a_quaternion_of_nan_and_its_other_fields():
    async with ControlLoop(parse_config(raw_config([NO_ORIENTATION, FT]))) as loop:
        report = await loop.run(ticks=100)
        imu = loop.robot.imu["imu"]
        assert np.all(np.isnan(imu.quaternion))  # not measured
        assert np.allclose(imu.linear_acceleration, (0, 0, 9.81), atol=0.01)
        assert np.allclose(imu.angular_velocity, 0.0) and imu.fault == 0 and imu.updated_tick > 50  # as above
    assert report["faults"] == [] and report["drivers"]["can"]["sensors"]["imu"]["frames"] > 0


def test_only_the_orientation_of_an_imu_may_be_left_out():
    bad = {**IMU, "signals": {"quaternion": IMU["signals"]["quaternion"]}}
    with pytest.raises(ConfigError) as err:
        parse_config(raw_config([bad, FT]))
    text = str(err.value)
    assert 'no signals for "angular_velocity"' in text and 'no signals for "linear_acceleration"' in text
    assert "quaternion" not in text


@pytest.mark.asyncio
async def test_a_status_whose_zero_means_ok_takes_the_frames_and_drops_those_it_marks_invalid():
    """A gateway whose Status 0 means OK (here, the simulated one so configured), read with
    status_valid = "clear": its frames are taken; a frame whose status is 1 is not."""
    ch = f"aiohal-sensors-{os.getpid()}-{next(_channels)}"
    sim = SimBus("virtual", ch, [], sensors={"imu": 0.004, "force_torque": 0.004}, status_ok=0)
    try:
        sensors = [{**IMU, "status_valid": "clear"}, {**FT, "status_valid": "clear", "status_bits": 0xFF}]
        raw = raw_config(sensors, channel=ch, simulate=False)
        async with ControlLoop(parse_config(raw)) as loop:
            driver = driver_of(loop)
            await loop.run(ticks=50)
            imu = driver.gateway.sensors[0]
            assert imu.frames > 0 and imu.invalid == 0 and loop.robot.imu["imu"].fault == 0
            assert np.allclose(loop.robot.force_torque["ft"].force, (1.0, -2.0, 15.0), atol=0.05)
            sim.sensors.invalid = True  # Status 1: not valid
            loop.add_publisher(lambda lp: lp.request_stop("seen") if imu.invalid >= 5 else None)
            await loop.run(ticks=500)
            assert imu.invalid >= 5
    finally:
        sim.close()


def test_status_bits_beyond_the_status_signal_are_refused():
    with pytest.raises(ConfigError, match=r"options.sensors\[0\].status_bits: 0x100 has bits beyond the 8 of "
                                          r"IMU_Gyro.Status"):
        parse_config(raw_config([{**IMU, "status_bits": 0x100}, FT]))


@pytest.mark.asyncio
async def test_a_stale_sensor_is_logged_as_stale_naming_it(caplog):
    async with ControlLoop(parse_config(raw_config([{**IMU, "stale_periods": 3}, FT]))) as loop:
        driver = driver_of(loop)
        await loop.run(ticks=20)
        driver.sim.sensors.stopped = True
        imu = loop.robot.imu["imu"]
        loop.add_publisher(lambda lp: lp.request_stop("seen") if imu.fault & Fault.STALE else None)
        await loop.run(ticks=500)
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert any(line.startswith("driver:can at tick ") and line.endswith(
        ": sensor imu is stale: no valid frame for 12 ms (3 periods)") for line in lines), lines
    assert not any("failed in" in line for line in lines), lines
