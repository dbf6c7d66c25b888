"""Workspace limits: a site leaving its box or sphere takes the robot to its configured level
on the tick it leaves, with the site and distance recorded (MuJoCo's kinematics, extra sim)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from conftest import CONFIGS, require_module

mujoco = require_module("mujoco")

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.core.ticker import VirtualTickSource
from aiohal.errors import ConfigError
from aiohal.safety import SafetyRequestRefused

CONFIG = CONFIGS / "kuka_lwr_sim.toml"
MODEL = str(CONFIGS / "models" / "kuka_lwr.xml")


def raw_config(workspace: list[dict]) -> dict:
    raw = tomllib.loads(CONFIG.read_text())
    raw["robot"]["model"] = MODEL
    raw["loop"]["clock"] = "virtual"
    raw["safety"] = {"workspace": workspace}
    return raw


def site_positions(q_rows: np.ndarray, joint_names, frame: str = "world") -> np.ndarray:
    """The ee site's position for each row of measured positions, computed here on a model of
    our own (the test's kinematics, not the loop's)."""
    model = mujoco.MjModel.from_xml_path(MODEL)
    data = mujoco.MjData(model)
    qadr = [model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in joint_names]
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "ee")
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, frame) if frame != "world" else 0
    out = np.empty((len(q_rows), 3))
    for i, q in enumerate(q_rows):
        data.qpos[qadr] = q
        mujoco.mj_kinematics(model, data)
        out[i] = data.xmat[body].reshape(3, 3).T @ (data.site_xpos[site] - data.xpos[body])
    return out


def start_position(frame: str = "world") -> np.ndarray:
    raw = raw_config([])
    names = list(raw["joints"])
    options = raw["driver"][0]["options"]
    if "initial_position" in options:
        initial = [options["initial_position"].get(n, 0.0) for n in names]
    else:  # the config starts from the model's keyframe
        model = mujoco.MjModel.from_xml_path(MODEL)
        qpos = model.key(options["keyframe"]).qpos
        initial = [qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)]] for n in names]
    return site_positions(np.array([initial]), names, frame)[0]


async def run(raw: dict, ticks: int = 3000):
    loop = ControlLoop(parse_config(raw), tick_source=VirtualTickSource())
    measured = []
    loop.add_publisher(lambda lp: measured.append((lp.robot.clock.tick, lp.robot.state.position.copy())))
    async with loop:
        report = await loop.run(ticks=ticks)
    return loop, report, measured


@pytest.mark.asyncio
async def test_leaving_a_sphere_holds_the_robot_on_that_tick_with_site_and_distance():
    center = start_position()
    loop, report, measured = await run(raw_config([{"site": "ee", "sphere": {"center": center.tolist(),
                                                                               "radius": 0.03}}]))
    assert report["safety_level"] == "hold"
    [fault] = report["faults"]
    assert fault["source"] == "workspace:ee" and "outside its sphere" in fault["error"]
    transition = report["safety"][-1]
    assert transition["event"] == "fault" and transition["after"] == "hold"
    # the first tick whose measured position puts the site outside, by the test's own kinematics
    ticks = np.array([k for k, _ in measured])
    where = site_positions(np.array([q for _, q in measured]), loop.robot.joint_names)
    out = np.linalg.norm(where - center, axis=1) > 0.03
    first_out = int(ticks[np.argmax(out)])
    assert transition["tick"] == fault["tick"] == first_out
    distance_mm = float(fault["error"].split(" mm")[0].split()[-1])
    expected = (np.linalg.norm(where[np.argmax(out)] - center) - 0.03) * 1e3
    assert distance_mm == pytest.approx(expected, abs=0.005)


@pytest.mark.asyncio
async def test_a_box_in_a_body_frame_can_send_the_robot_to_estop_and_rearm_waits_for_the_site():
    here = start_position("link1")
    box = {"min": (here - 0.02).tolist(), "max": (here + 0.02).tolist()}
    raw = raw_config([{"site": "ee", "frame": "link1", "box": box, "level": "estop"}])
    loop = ControlLoop(parse_config(raw), tick_source=VirtualTickSource())
    refused = []

    def try_rearm(lp):
        if lp.robot.clock.tick == 2000:
            lp.reset_faults()
            try:
                lp.rearm()
            except SafetyRequestRefused as exc:
                refused.append(str(exc))

    loop.add_publisher(try_rearm)
    async with loop:
        report = await loop.run(ticks=2500)
    assert [t["after"] for t in report["safety"]] == ["run", "estop", "disabled"]
    assert report["faults"][0]["source"] == "workspace:ee" and "in frame link1" in report["faults"][0]["error"]
    assert "site ee is outside its workspace" in refused[0]


@pytest.mark.asyncio
async def test_inside_the_workspace_nothing_happens():
    center = start_position()
    _, report, _ = await run(raw_config([{"site": "ee", "sphere": {"center": center.tolist(), "radius": 0.5}}]))
    assert report["safety_level"] == "run" and report["faults"] == []


@pytest.mark.parametrize("entry, key, message", [
    ({"site": "nose", "sphere": {"center": [0, 0, 0], "radius": 1}}, "safety.workspace[0].site", 'no site "nose"'),
    ({"site": "ee", "frame": "moon", "sphere": {"center": [0, 0, 0], "radius": 1}}, "safety.workspace[0].frame",
     'no body "moon"'),
    ({"site": "ee"}, "safety.workspace[0]", "exactly one of box or sphere"),
    ({"site": "ee", "box": {"min": [0, 0, 0], "max": [1, -1, 1]}}, "safety.workspace[0].box", "min must be below"),
    ({"site": "ee", "sphere": {"center": [float("nan"), 0, 0], "radius": 1}}, "safety.workspace[0].sphere.center[0]",
     "finite"),
    ({"site": "ee", "box": {"min": [0, 0, float("-inf")], "max": [1, 1, 1]}}, "safety.workspace[0].box.min[2]",
     "finite"),
])
def test_workspace_config_errors_name_the_key(entry, key, message):
    with pytest.raises(ConfigError) as info:
        parse_config(raw_config([entry]), base_dir=CONFIGS)
    assert any(i.path == key and message in i.message for i in info.value.issues), info.value.issues


def test_a_workspace_needs_the_model():
    raw = raw_config([{"site": "ee", "sphere": {"center": [0, 0, 0], "radius": 1}}])
    del raw["robot"]["model"]
    with pytest.raises(ConfigError, match=r"needs? the robot's model|need the robot's model"):
        parse_config(raw)
