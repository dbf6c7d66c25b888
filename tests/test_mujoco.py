"""The MuJoCo driver and the circle controller: R-HAL's experiment on four simulated robots.

Every run here is lockstep on the virtual clock: the simulation is the clock, deterministic,
faster than real time.
"""

from __future__ import annotations

import re
import tomllib

import numpy as np
import pytest
from conftest import CONFIGS, require_module

mujoco = require_module("mujoco")

from aiohal.config import load_config, parse_config
from aiohal.core.loop import ControlLoop
from aiohal.core.ticker import VirtualTickSource
from aiohal.errors import ConfigError

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


@pytest.mark.parametrize("joints, left_out", [
    (["a5", "a1", "a3", "a2", "a6", "a4"], ["e1"]),  # out of order: the IK gathers and scatters its rows
    (["a2", "e1", "a3", "a4", "a5", "a6"], ["a1"]),  # a run not from row 0: a view of q*'s rows
])
@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_circle_moves_only_its_joints(joints, left_out):
    """``params.joints`` a subset of the robot's: the joints left out keep their start command."""
    raw = tomllib.loads((CONFIGS / "kuka_lwr_sim.toml").read_text())
    raw["controller"]["params"]["joints"] = joints
    loop = lockstep(parse_config(raw, base_dir=CONFIGS))
    async with loop:
        fixed = loop.robot.indices(left_out)
        start = loop.robot.state.position.copy()
        report = await loop.run(duration=3.0)
        command = loop.robot.command.position.copy()
        moved = np.abs(command - loop.controller.q_cmd)
    assert report["faults"] == [] and report["controller"]["rms_error_m"] < 0.002
    assert (command[fixed] == start[fixed]).all() and moved.max() == 0.0  # the command is q*
    assert np.abs(np.delete(command - start, fixed)).max() > 0.05  # the others traced the circle


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


FLOATING = """
<mujoco model="floating_pendulum">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.0005" gravity="0 0 0"/>
  <worldbody>
    <body name="base" pos="0 0 1">
      <freejoint name="root"/>
      <geom type="box" size="0.1 0.1 0.1" mass="1000" contype="0" conaffinity="0"/>
      <site name="imu"/>
      <body name="link" pos="0 0 0">
        <joint name="hinge" type="hinge" axis="0 0 1" range="-3 3" damping="0"/>
        <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.02" mass="1" contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor name="hinge" joint="hinge" ctrlrange="-10 10"/></actuator>
  <sensor>
    <framequat name="imu_quat" objtype="site" objname="imu"/>
    <gyro name="imu_gyro" site="imu"/>
    <accelerometer name="imu_accel" site="imu"/>
  </sensor>
</mujoco>
"""


def floating_config(tmp_path, controller):
    (tmp_path / "floating.xml").write_text(FLOATING)
    raw = {
        "robot": {"name": "floating", "model": "floating.xml"},
        "loop": {"rate_hz": 1000, "clock": "virtual"},
        "joints": {"hinge": {"position": [-3, 3], "velocity": 50.0, "effort": 10.0}},
        "devices": {"base_imu": {"type": "imu"}},
        "driver": [{"type": "mujoco", "name": "sim", "joints": ["hinge"], "devices": ["base_imu"],
                    "options": {"kp": 50.0, "kd": 2.0, "gravity_compensation": False,
                                "sensors": {"base_imu": {"quaternion": "imu_quat", "angular_velocity": "imu_gyro",
                                                         "linear_acceleration": "imu_accel"}}}}],
    }
    return ControlLoop(parse_config(raw, base_dir=tmp_path), tick_source=VirtualTickSource(), controller=controller)


def fixed(mode, **values):
    from aiohal.hal import Controller
    from aiohal.robot import Mode

    class Fixed(Controller):
        def update(self, t, dt):
            cmd = self.robot.command
            cmd.mode[:] = getattr(Mode, mode)
            for key, value in values.items():
                getattr(cmd, key)[:] = value

    return Fixed()


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_floating_base_substeps_and_effort_mode(tmp_path):
    loop = floating_config(tmp_path, fixed("EFFORT", effort=0.5))
    async with loop:
        report = await loop.run(ticks=200)
    sim = report["drivers"]["sim"]
    assert sim["sim_steps"] == 2 * 200  # 0.5 ms model timestep, 1 ms tick: two substeps
    assert sim["sim_time_s"] == pytest.approx(0.2)
    # a constant torque accelerates the link; the heavy free base barely turns the other way
    assert loop.robot.state.velocity[0] > 0.5
    assert loop.robot.state.effort[0] == pytest.approx(0.5)
    assert np.linalg.norm(loop.robot.imu["base_imu"].angular_velocity) > 0  # reaction on the free base


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_velocity_and_impedance_modes(tmp_path):
    loop = floating_config(tmp_path, fixed("VELOCITY", velocity=1.0))
    async with loop:
        await loop.run(ticks=500)
    assert loop.robot.state.velocity[0] == pytest.approx(1.0, rel=0.05)

    loop = floating_config(tmp_path, fixed("IMPEDANCE", position=0.3, stiffness=20.0, damping=3.0))
    async with loop:
        await loop.run(ticks=3000)
    assert loop.robot.state.position[0] == pytest.approx(0.3, abs=1e-3)


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_every_device_field_reads_its_own_sensor_when_another_driver_owns_a_device_between():
    """The driver fills its devices with one gather per run of adjacent rows: a force/torque
    device of another driver between two of its own splits its run, and each field still
    reads the sensor it is named after (or mapped to in ``sensors``)."""
    from aiohal.drivers.mujoco import SENSOR_FIELDS
    from aiohal.mjcf import sensor_slice

    raw = tomllib.loads((CONFIGS / "walkman_sim.toml").read_text())
    raw["controller"] = {"type": "hold"}
    sim_joints = list(raw["joints"])
    raw["joints"]["extra"] = {"velocity": 1.0}
    devices = raw.pop("devices")
    raw["devices"] = {}
    for name, spec in devices.items():  # the mock's F/T between the sim's l_wrist_ft and r_wrist_ft
        raw["devices"][name] = spec
        if name == "l_wrist_ft":
            raw["devices"]["extra_ft"] = {"type": "force_torque"}
    (sim,) = raw["driver"]
    sim["joints"] = sim_joints
    raw["driver"].append({"type": "mock", "name": "aux", "joints": ["extra"], "devices": ["extra_ft"],
                          "options": {"force": [1.0, 2.0, 3.0], "torque": [4.0, 5.0, 6.0]}})
    loop = await hold_still(parse_config(raw, base_dir=CONFIGS), ticks=50)
    driver, robot = loop.slots[0].driver, loop.robot
    assert [len(run[1]) for run in driver._sensor_runs] == [1, 1, 3]  # IMU; l_wrist; r_wrist, l_ankle, r_ankle
    names = {"pelvis_imu": {"quaternion": "imu_quat", "angular_velocity": "imu_gyro", "linear_acceleration": "imu_accel"}}
    for device in devices:
        record = robot.device(device)
        kind = robot.device_kind(device)
        for field, (suffix, _dim) in SENSOR_FIELDS[kind].items():
            sensor = names.get(device, {}).get(field, f"{device}_{suffix}")
            expected = driver.data.sensordata[sensor_slice(driver.model, sensor)]
            np.testing.assert_array_equal(getattr(record, field), expected, err_msg=f"{device}.{field}")
        assert record.updated_tick == robot.clock.tick
    extra = robot.device("extra_ft")
    assert list(extra.force) == [1.0, 2.0, 3.0] and list(extra.torque) == [4.0, 5.0, 6.0]
    assert np.linalg.norm(robot.device("l_ankle_ft").force) > 10.0  # a leg's weight: real sensor values


@pytest.mark.parametrize("rate", [2000, 1500, 300])
@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_any_rate_runs_the_model_in_step_with_the_ticks(rate):
    # 1 ms model timestep: 0.5, 0.667 and 3.33 ms periods are not whole numbers of it, so the
    # driver shortens the timestep to fill each period with whole substeps
    config = load_config(CONFIGS / "kuka_lwr_sim.toml").with_loop(rate_hz=rate)
    loop = lockstep(config)
    async with loop:
        report = await loop.run(ticks=100)
        sim = loop.slots[0].driver
        assert sim.model.opt.timestep <= 0.001
        assert sim.substeps * sim.model.opt.timestep == pytest.approx(loop.period_s, rel=1e-12)
    assert report["faults"] == []
    assert report["drivers"]["sim"]["sim_time_s"] == pytest.approx(100 * loop.period_s, abs=2e-6)


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_a_driver_whose_open_failed_closes_without_a_second_error(tmp_path):
    from aiohal.drivers.mujoco import MujocoDriver

    config = load_config(CONFIGS / "kuka_lwr_sim.toml")
    dc = config.drivers[0]
    driver = MujocoDriver(dc.name, config.build_robot().driver_view(dc.joints), dc.options)
    driver.estop()
    await driver.close()  # open() never ran (or failed before its first line)
    assert driver.health()["sim_steps"] == 0


def test_a_missing_robot_model_is_reported_once_at_the_key_that_names_it(tmp_path):
    raw = tomllib.loads((CONFIGS / "kuka_lwr_sim.toml").read_text())
    raw["robot"]["model"] = "models/nothere.xml"
    with pytest.raises(ConfigError) as info:
        parse_config(raw, base_dir=CONFIGS)
    assert [str(i) for i in info.value.issues] == [f"robot.model: file not found: {CONFIGS / 'models/nothere.xml'}"]


# ---------------------------------------------------------------- the circle says when it cannot do its job


def kuka_raw(**params):
    raw = tomllib.loads((CONFIGS / "kuka_lwr_sim.toml").read_text())
    raw["controller"]["params"].update(params)
    return raw


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_a_circle_out_of_reach_is_an_error_at_start_naming_the_site_and_distance():
    loop = lockstep(parse_config(kuka_raw(radius=2.0), base_dir=CONFIGS))
    async with loop:
        report = await loop.run(ticks=50)
    [fault] = report["faults"]
    assert fault["source"] == "controller:circle" and fault["phase"] == "start"
    assert re.fullmatch(r'ValueError: site "ee": the circle comes \d\.\d{3} m from joint "a1", '
                        r"farther than the chain reaches \(1\.068 m\)", fault["error"]), fault["error"]
    assert report["safety_worst"] == "hold"  # the robot held its pose instead


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_a_singular_start_pose_is_a_warning_naming_the_site():
    raw = kuka_raw()
    del raw["driver"][0]["options"]["keyframe"]  # every joint at 0: the arm stands straight up
    model = mujoco.MjModel.from_xml_path(str(CONFIGS / "models/kuka_lwr.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    top = data.site("ee").xpos
    raw["controller"]["params"]["center"] = [float(top[0]), float(top[1]), float(top[2]) - 0.15]  # within reach
    loop = lockstep(parse_config(raw, base_dir=CONFIGS))
    async with loop:
        warning = loop.controller.start_warning
    assert warning.startswith('site "ee": the start pose is singular in the yz plane (smallest singular value ')
    assert "start from another pose (initial_position or keyframe)" in warning


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_a_tracking_error_over_its_bound_faults_and_holds():
    loop = lockstep(parse_config(kuka_raw(max_error_m=1e-5), base_dir=CONFIGS))
    async with loop:
        report = await loop.run(ticks=2000)  # the 1 s ramp, then the bound applies
    [fault] = report["faults"]
    assert fault["phase"] == "update" and fault["tick"] > 1000
    assert re.fullmatch(r"RuntimeError: tracking error 0\.\d{3} m exceeds max_error_m 1e-05 m", fault["error"])
    assert report["controller"]["type"] == "hold"


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_an_absolute_center_draws_the_same_circle_as_its_offset():
    config = load_config(CONFIGS / "kuka_lwr_sim.toml")
    loop = lockstep(config)
    async with loop:
        start = loop.controller.x_start.copy()
        by_offset = await loop.run(ticks=3000)
        centre = loop.controller.center.copy()
    np.testing.assert_allclose(centre, start + np.array([0.0, -0.1, 0.0]))  # the default offset: -radius along y
    loop = lockstep(parse_config(kuka_raw(center=centre.tolist()), base_dir=CONFIGS))
    async with loop:
        by_center = await loop.run(ticks=3000)
    assert by_center["controller"] == by_offset["controller"]


def test_center_and_offset_together_are_refused():
    with pytest.raises(ConfigError) as info:
        parse_config(kuka_raw(center=[0.0, 0.0, 1.0], offset=[0.0, 0.1, 0.0]), base_dir=CONFIGS)
    assert [str(i) for i in info.value.issues] == ["controller.params: give center or offset, not both"]


@pytest.mark.asyncio(loop_factories=["asyncio"])
async def test_a_keyframe_start_is_the_models_pose():
    config = load_config(CONFIGS / "kuka_lwr_sim.toml")
    assert config.drivers[0].options.keyframe == "home"
    loop = lockstep(config)
    async with loop:
        np.testing.assert_allclose(loop.robot.state.position, [0, 0.5, 0, -1.2, 0, 0.8, 0])
    raw = kuka_raw()
    raw["driver"][0]["options"]["initial_position"] = {"a1": 0.25}  # on top of the keyframe
    loop = lockstep(parse_config(raw, base_dir=CONFIGS))
    async with loop:
        np.testing.assert_allclose(loop.robot.state.position, [0.25, 0.5, 0, -1.2, 0, 0.8, 0])
    raw["driver"][0]["options"]["keyframe"] = "hom"
    with pytest.raises(ConfigError) as info:
        parse_config(raw, base_dir=CONFIGS)
    assert [str(i) for i in info.value.issues] == [
        'driver[0].options.keyframe: no keyframe "hom" in the model kuka_lwr.xml (did you mean "home"?)']


def test_mujoco_warnings_go_to_the_log_not_to_a_file_in_the_current_folder(tmp_path, monkeypatch, caplog):
    from aiohal import mjcf
    from aiohal.logutil import RateLimitedLogger
    from aiohal.mjcf import load_model

    monkeypatch.setattr(mjcf, "_warnings", RateLimitedLogger(mjcf.log))  # none logged yet by this test's limiter
    model_file = tmp_path / "one.xml"
    model_file.write_text('<mujoco><worldbody><body><joint/><geom size="0.1"/></body></worldbody></mujoco>')
    monkeypatch.chdir(tmp_path)
    model = load_model(model_file)
    data = mujoco.MjData(model)
    with caplog.at_level("WARNING", logger="aiohal.mjcf"):
        for _ in range(3):  # unstable every step: logged once (rate limited)
            data.qvel[0] = float("nan")
            mujoco.mj_step(model, data)
    assert data.warning[mujoco.mjtWarning.mjWARN_BADQVEL].number >= 1
    lines = [r.getMessage() for r in caplog.records if r.name == "aiohal.mjcf"]
    assert len(lines) == 1 and "MuJoCo: Nan, Inf or huge value in QVEL" in lines[0], lines
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
