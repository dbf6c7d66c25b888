"""hold, homing and sine on the mock robot (virtual clock: exact and fast)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import arm_raw, virtual_loop


def robot_raw(controller, n=3, acceleration=50.0, **options):
    raw = arm_raw(n, **controller)
    limits = {"position": [-3.0, 3.0], "velocity": 5.0}
    if acceleration is not None:
        limits["acceleration"] = acceleration
    raw["joints"] = {f"j{i}": dict(limits) for i in range(n)}
    raw["driver"][0]["options"] = {"initial_position": {"j0": 0.2, "j1": -0.3, "j2": 1.0}, **options}
    return raw


@pytest.mark.asyncio
async def test_hold_keeps_the_start_position():
    loop = virtual_loop(robot_raw({"type": "hold"}, dynamics="first_order"))
    async with loop:
        report = await loop.run(ticks=500)
    assert np.allclose(loop.robot.state.position, [0.2, -0.3, 1.0])
    assert np.allclose(loop.robot.command.position, [0.2, -0.3, 1.0])
    assert report["controller"] == {"type": "hold", "braking_s": 0.0}


@pytest.mark.asyncio
async def test_homing_follows_minimum_jerk_and_arrives_on_time():
    params = {"pose": {"j0": 1.2, "j2": -1.0}, "duration": 1.0}
    loop = virtual_loop(robot_raw({"type": "homing", "params": params}))
    commanded = []
    loop.add_publisher(lambda lp: commanded.append(lp.robot.command.position.copy()))
    async with loop:
        report = await loop.run(ticks=1200)
    q = np.array(commanded)
    t = np.arange(1, 1201) * 1e-3
    tau = np.clip(t / 1.0, 0, 1)
    s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
    assert np.allclose(q[:, 0], 0.2 + (1.2 - 0.2) * s, atol=1e-12)
    assert np.allclose(q[:, 2], 1.0 + (-1.0 - 1.0) * s, atol=1e-12)
    assert np.allclose(q[:, 1], -0.3)  # not in the pose: holds
    # symmetric bell-shaped velocity, peak 1.875·Δ/T at mid-time
    v = np.diff(q[:, 0]) / 1e-3
    assert v.max() == pytest.approx(1.875 * 1.0 / 1.0, rel=1e-3)
    assert abs(int(np.argmax(v)) - 499) <= 1
    assert report["controller"]["reached"] is True
    assert report["controller"]["final_error_max"] < 1e-9


@pytest.mark.asyncio
async def test_sine_amplitude_frequency_phase_per_joint():
    params = {"amplitude": {"j0": 0.5, "j1": 0.2}, "frequency": {"j0": 1.0, "j1": 2.0}, "phase": {"j1": math.pi / 2}, "ramp": 0.0}
    loop = virtual_loop(robot_raw({"type": "sine", "params": params}, acceleration=None))
    commanded = []
    loop.add_publisher(lambda lp: commanded.append(lp.robot.command.block[:2].copy()))
    async with loop:
        report = await loop.run(ticks=2000)
    q = np.array([c[0] for c in commanded])
    v = np.array([c[1] for c in commanded])
    t = np.arange(1, 2001) * 1e-3
    assert np.allclose(q[:, 0], 0.2 + 0.5 * np.sin(2 * np.pi * t), atol=1e-9)
    assert np.allclose(q[:, 1], -0.3 + 0.2 * (np.sin(4 * np.pi * t + np.pi / 2) - 1.0), atol=1e-9)
    assert np.allclose(q[:, 2], 1.0)  # amplitude 0 for joints not named
    assert np.allclose(v[:, 0], 0.5 * 2 * np.pi * np.cos(2 * np.pi * t), atol=1e-9)
    # mirror dynamics: each tick measures exactly what the tick before commanded
    assert report["controller"]["tracking_max"] == 0.0


@pytest.mark.asyncio
async def test_sine_ramps_in_without_a_jump():
    params = {"amplitude": 0.4, "frequency": 1.0, "phase": 1.0, "ramp": 0.5}
    loop = virtual_loop(robot_raw({"type": "sine", "params": params}))
    commanded = []
    loop.add_publisher(lambda lp: commanded.append(lp.robot.command.position[0]))
    async with loop:
        await loop.run(ticks=1500)
    q = np.array([0.2, 0.2, *commanded])  # at rest at the measured position before the start
    # bounded acceleration everywhere: A·ω² plus the ramp's terms stay below 60 rad/s²,
    # i.e. 6e-5 rad per tick²; a jump at the start would be orders of magnitude above
    accel = np.abs(np.diff(q, 2))
    assert accel.max() < 6e-5
    assert np.abs(np.diff(q))[:10].max() < 1e-6
    assert q[2] - 0.2 == pytest.approx(0.0, abs=1e-8)


@pytest.mark.asyncio
async def test_sine_tracking_error_reflects_the_dynamics():
    params = {"amplitude": 0.3, "frequency": 1.0, "ramp": 0.2}
    fast = virtual_loop(robot_raw({"type": "sine", "params": params}, dynamics="first_order", time_constant=0.002))
    slow = virtual_loop(robot_raw({"type": "sine", "params": params}, dynamics="first_order", time_constant=0.05))
    async with fast:
        r_fast = await fast.run(ticks=2000)
    async with slow:
        r_slow = await slow.run(ticks=2000)
    assert r_slow["controller"]["tracking_rms"] > 5 * r_fast["controller"]["tracking_rms"] > 0
