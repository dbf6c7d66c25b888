"""A robot built in code: the same validated Config as from TOML, the same errors."""

from __future__ import annotations

import math

import pytest
from helpers import arm_raw

from aiohal import ConfigError, ControlLoop, JointSpec, plugins
from aiohal.config import from_parts, parse_config
from aiohal.controllers.sine import SineController, SineParams
from aiohal.drivers.mock import MockDriver


def test_the_same_config_as_from_the_file():
    raw = arm_raw(type="sine", params={"amplitude": 0.2})
    from_file = parse_config(raw)
    built = from_parts(robot=raw["robot"], loop=raw["loop"], joints=raw["joints"], drivers=raw["driver"],
                       controller="sine", params={"amplitude": 0.2})
    assert built == from_file
    shorthand = from_parts(robot="test_arm", joints=raw["joints"], drivers=[("mock", {"name": "arm", "joints": ["j*"]})],
                           controller=SineController, params=SineParams(amplitude=0.2), rate_hz=1000, clock="virtual")
    assert shorthand.joints == from_file.joints and shorthand.loop == from_file.loop
    assert shorthand.drivers == from_file.drivers
    assert shorthand.controller.params == from_file.controller.params
    assert shorthand.controller.cls is SineController and shorthand.controller.type == "SineController"


def test_joints_as_joint_specs():
    specs = [JointSpec("q1", 0, -1.0, 1.0, 2.0, 10.0, 5.0), JointSpec("q2", 1, velocity=3.0)]
    config = from_parts(joints=specs, drivers=[(MockDriver, {"joints": ["q1", "q2"]})])
    assert config.joints == tuple(specs)
    assert config.joints[1].position_min == -math.inf and config.drivers[0].cls is MockDriver
    assert config.controller.type == "hold"


def test_errors_name_the_key_as_for_a_file():
    raw = arm_raw()
    raw["driver"][0]["joints"] = ["j0", "j9"]
    raw["joints"]["j1"]["velocity"] = -1.0
    with pytest.raises(ConfigError) as from_file:
        parse_config(raw)
    with pytest.raises(ConfigError) as built:
        from_parts(robot=raw["robot"], loop=raw["loop"], joints=raw["joints"], drivers=raw["driver"])
    assert built.value.issues == from_file.value.issues
    assert [str(i) for i in built.value.issues] == [
        "joints.j1.velocity: input should be greater than 0 (got -1.0)",
        'driver[0].joints: unknown joint "j9" (did you mean "j0"?)',
        "joints.j1: no driver owns this joint",
        "joints.j2: no driver owns this joint",
    ]


def test_a_class_that_is_no_plugin_is_an_error_at_its_type():
    with pytest.raises(ConfigError) as info:
        from_parts(joints={"q": {"velocity": 1.0}}, drivers=[(SineController, {"joints": ["q"]})])
    [issue] = info.value.issues
    assert issue.path == "driver[0].type" and "not a subclass of aiohal.Driver" in issue.message


def test_params_go_with_a_name_or_class_not_with_a_table():
    with pytest.raises(TypeError, match="params"):
        from_parts(joints={"q": {"velocity": 1.0}}, drivers=[("mock", {"joints": ["q"]})],
                   controller={"type": "sine"}, params={"amplitude": 0.1})


@pytest.mark.asyncio
async def test_a_controller_instance_gets_its_validated_params():
    controller = SineController()
    with pytest.raises(ConfigError) as info:  # checked as a configured sine's params are
        ControlLoop.from_parts(joints={"q": {"position": [-1, 1], "velocity": 1.0}}, drivers=[("mock", {"joints": ["q"]})],
                               controller=controller, params={"amplitude": 0.5, "frequency": 1.0})
    assert [str(i) for i in info.value.issues] == [
        "controller.params.amplitude: peak velocity 2π·f·A exceeds the velocity limit of q (3.14 > 1)"]
    loop = ControlLoop.from_parts(joints={"q": {"position": [-1, 1], "velocity": 1.0}}, drivers=[("mock", {"joints": ["q"]})],
                                  controller=controller, params={"amplitude": 0.1}, clock="virtual")
    async with loop:
        report = await loop.run(ticks=10)
    assert loop.controller is controller and controller.params.amplitude == 0.1
    assert report["ticks"] == 10 and report["controller"]["type"] == "SineController"


def test_register_a_class_or_a_target():
    try:
        plugins.register("driver", "mine", MockDriver)
        assert plugins.load("driver", "mine") is MockDriver
        plugins.register("driver", "mine", "aiohal.drivers.mock:MockDriver")  # replaced, imported when used
        assert plugins.available("driver")["mine"].source == "registered"
        assert plugins.load("driver", "mine") is MockDriver
        with pytest.raises(plugins.PluginError, match='driver "mock" is built in'):
            plugins.register("driver", "mock", MockDriver)
        with pytest.raises(plugins.PluginError, match=r"not a subclass of aiohal.Driver"):
            plugins.register("driver", "wrong", SineController)
    finally:
        plugins.unregister("driver", "mine")
    assert "mine" not in plugins.available("driver") and "wrong" not in plugins.available("driver")
