"""The MuJoCo driver and the circle controller: R-HAL's experiment on four simulated robots.

Every run here is lockstep on the virtual clock: the simulation is the clock, deterministic,
faster than real time.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from conftest import CONFIGS, require_module

mujoco = require_module("mujoco")

from aiohal.config import load_config, parse_config  # noqa: E402
from aiohal.errors import ConfigError  # noqa: E402
from aiohal.loop import ControlLoop  # noqa: E402
from aiohal.ticker import VirtualTickSource  # noqa: E402

ROBOTS = ["kuka_lwr_sim", "centauro_upper_sim", "coman_sim", "walkman_sim"]


def lockstep(config):
    return ControlLoop(config.with_loop(clock="virtual"), tick_source=VirtualTickSource())


def fit_circle(points: np.ndarray) -> tuple[float, np.ndarray, float]:
    """Radius, plane normal and RMS distance of 3-D points from their best-fit circle."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre)
    q = (points - centre) @ vt[:2].T  # coordinates in the best-fit plane
    a = np.c_[2 * q, np.ones(len(q))]
    sol = np.linalg.lstsq(a, (q**2).sum(axis=1), rcond=None)[0]
    radius = float(np.sqrt(sol[2] + sol[0] ** 2 + sol[1] ** 2))
    residual = np.hypot(q[:, 0] - sol[0], q[:, 1] - sol[1]) - radius
    return radius, vt[2], float(np.sqrt(np.mean(residual**2)))


async def run_circle(name: str, seconds: float = 5.0):
    config = load_config(CONFIGS / f"{name}.toml")
    loop = lockstep(config)
    params = config.controller.params
    paths: list[np.ndarray] = []
    async with loop:
        sim = loop.slots[0].driver
        site_ids = [mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_SITE, s) for s in params.sites]
        loop.add_publisher(lambda lp: paths.append(sim.data.site_xpos[site_ids].copy()))
        report = await loop.run(duration=seconds)
    return config, report, np.array(paths)


@pytest.mark.parametrize("name", ROBOTS)
@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_one_controller_traces_the_circle_on_every_robot(name):
    config, report, paths = await run_circle(name)
    params = config.controller.params
    assert report["ticks"] == 5000 and report["faults"] == []
    assert report["drivers"]["sim"]["time_mode"] == "lockstep"
    assert report["drivers"]["sim"]["sim_time_s"] == pytest.approx(5.0)
    ramp_ticks = int(params.ramp * 1000) + 1
    for i, site in enumerate(params.sites):
        radius, normal, spread = fit_circle(paths[ramp_ticks:, i])
        assert radius == pytest.approx(params.radius, rel=0.05), site
        assert spread < 0.002, site  # the points lie on a circle, not just near one
        axis = {"xy": 2, "yz": 0, "xz": 1}[params.plane]
        assert abs(normal[axis]) > 0.99, site  # in the configured plane
    assert report["controller"]["rms_error_m"] < 0.002
    assert report["controller"]["samples"] == (5000 - ramp_ticks + 1) * len(params.sites)


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_lockstep_is_deterministic():
    _, r1, p1 = await run_circle("kuka_lwr_sim", 1.5)
    _, r2, p2 = await run_circle("kuka_lwr_sim", 1.5)
    assert np.array_equal(p1, p2)
    assert r1["controller"] == r2["controller"]


async def hold_still(config, ticks=500, payload_kg=0.0, body=None):
    raw = config
    loop = lockstep(raw)
    async with loop:
        sim = loop.slots[0].driver
        if payload_kg:
            bid = mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_BODY, body)
            sim.model.body_mass[bid] += payload_kg
        await loop.run(ticks=ticks)
    return loop


def hold_config(name):
    raw = tomllib.loads((CONFIGS / f"{name}.toml").read_text())
    raw["controller"] = {"type": "hold"}
    return parse_config(raw, base_dir=CONFIGS)


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_imu_reads_gravity_at_rest():
    loop = await hold_still(hold_config("kuka_lwr_sim"))
    imu = loop.robot.imu["base_imu"]
    assert np.allclose(imu.linear_acceleration, [0.0, 0.0, 9.81], atol=1e-6)
    assert np.allclose(imu.angular_velocity, 0.0, atol=1e-9)
    assert np.allclose(np.abs(imu.quaternion), [1.0, 0.0, 0.0, 0.0], atol=1e-9)
    assert imu.updated_tick == loop.robot.clock.tick


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_force_torque_sensor_weighs_a_known_payload():
    config = hold_config("kuka_lwr_sim")
    model = mujoco.MjModel.from_xml_path(str(config.robot.model))
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "wrist_ft")
    body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.site_bodyid[site])
    empty = await hold_still(config)
    loaded = await hold_still(config, payload_kg=2.0, body=body)
    f0 = empty.robot.force_torque["wrist_ft"].force.copy()
    f1 = loaded.robot.force_torque["wrist_ft"].force.copy()
    assert np.linalg.norm(f1 - f0) == pytest.approx(2.0 * 9.81, rel=0.02)
    # and the unloaded reading is the weight of what hangs below the sensor
    hanging = model.body_subtreemass[model.site_bodyid[site]]
    assert np.linalg.norm(f0) == pytest.approx(hanging * 9.81, rel=0.05)


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_position_hold_keeps_the_start_pose():
    config = hold_config("kuka_lwr_sim")
    loop = await hold_still(config, ticks=2000)
    start = np.clip(loop.robot.command.position, -10, 10)
    assert np.abs(loop.robot.state.position - start).max() < 1e-3


def test_unknown_joint_or_site_is_a_config_error():
    raw = tomllib.loads((CONFIGS / "kuka_lwr_sim.toml").read_text())
    raw["joints"]["a8"] = raw["joints"].pop("a6")
    raw["controller"]["params"]["sites"] = ["ee", "tool0"]
    with pytest.raises(ConfigError) as info:
        parse_config(raw, base_dir=CONFIGS)
    messages = [str(i) for i in info.value.issues]
    assert 'driver[0].joints: joint "a8" is not in the model kuka_lwr.xml' in messages
    assert 'controller.params.sites[1]: site "tool0" is not in the model kuka_lwr.xml' in messages


def test_missing_sensor_for_a_device_is_a_config_error():
    raw = tomllib.loads((CONFIGS / "kuka_lwr_sim.toml").read_text())
    raw["devices"]["elbow_ft"] = {"type": "force_torque"}
    raw["driver"][0]["devices"].append("elbow_ft")
    with pytest.raises(ConfigError) as info:
        parse_config(raw, base_dir=CONFIGS)
    assert [str(i) for i in info.value.issues] == [
        'driver[0].options.sensors.elbow_ft: force_torque "elbow_ft" needs sensor "elbow_ft_force" with 3 values (missing)',
        'driver[0].options.sensors.elbow_ft: force_torque "elbow_ft" needs sensor "elbow_ft_torque" with 3 values (missing)',
    ]


@pytest.mark.asyncio(loop_factories=["asyncio"])
@pytest.mark.parametrize("step", ["inline", "thread"])
async def test_real_time_keeps_one_step_per_tick(step):
    raw = tomllib.loads((CONFIGS / "kuka_lwr_sim.toml").read_text())
    raw["driver"][0]["options"]["step"] = step
    raw["realtime"] = {}
    config = parse_config(raw, base_dir=CONFIGS).with_loop(clock="timerfd")
    loop = ControlLoop(config)
    async with loop:
        await loop.run(ticks=300)
    report = loop.report()  # after close: a threaded step still in flight has finished
    sim = report["drivers"]["sim"]
    assert sim["time_mode"] == "realtime" and sim["step"] == step
    # the physics kept pace: one step per tick, started at activation
    assert sim["sim_steps"] == report["ticks"]
    assert sim["sim_time_s"] == pytest.approx(report["ticks"] * 1e-3)
