"""Drivers declare the command modes they apply; a controller commanding another is refused
before anything starts, with the driver named (ros2_control's command interfaces)."""

from __future__ import annotations

from typing import Literal

import pytest
from helpers import arm_raw
from pydantic import Field

from aiohal import ConfigError, Controller, Mode, Options
from aiohal.config import from_parts, parse_config
from aiohal.core.loop import ControlLoop
from aiohal.plugins import load

LWR = {f"a{i}": {"position": [-2.9, 2.9], "velocity": 1.9} for i in range(1, 8)}


class VelocityController(Controller):
    command_modes = frozenset({Mode.VELOCITY})

    def update(self, t, dt):
        self.robot.command.velocity[:] = 0.0


class ImpedanceController(Controller):
    command_modes = frozenset({Mode.POSITION, Mode.IMPEDANCE})

    def update(self, t, dt):
        pass


class ModeParams(Options):
    mode: Literal["position", "velocity", "effort"] = Field("position")


class ModeController(Controller):
    """Commands the mode its ``mode`` parameter names."""

    Params = ModeParams

    @classmethod
    def commanded_modes(cls, params):
        return frozenset({Mode[params.mode.upper()]})

    def update(self, t, dt):
        pass


def fri_config(controller, params=None, control="position"):
    return from_parts(joints=LWR, drivers=[("fri", {"name": "lwr", "joints": ["a*"], "options": {"control": control}})],
                      controller=controller, params=params)


def messages(info) -> list[str]:
    return [str(issue) for issue in info.value.issues]


def test_the_shipped_drivers_declare_what_they_apply():
    every = {Mode.POSITION, Mode.VELOCITY, Mode.EFFORT, Mode.IMPEDANCE}
    for name in ("mock", "udp"):
        assert load("driver", name).command_modes == every
    fri = load("driver", "fri")
    assert fri.supported_modes(fri.Options(control="position")) == {Mode.POSITION}
    assert fri.supported_modes(fri.Options(control="joint_impedance")) == {Mode.POSITION, Mode.IMPEDANCE}
    assert load("driver", "nrt_hand").command_modes == {Mode.POSITION}
    for name in ("hold", "homing", "sine", "sequence", "stream"):
        assert load("controller", name).command_modes == {Mode.POSITION}


def test_a_mode_the_driver_cannot_apply_is_refused_at_the_controller_type():
    with pytest.raises(ConfigError) as info:
        fri_config(VelocityController)
    assert messages(info) == [
        'controller.type: commands velocity, which driver "lwr" (fri) cannot apply (it takes position)'
    ]


def test_the_driver_options_decide_its_modes():
    with pytest.raises(ConfigError) as info:
        fri_config(ImpedanceController)
    assert messages(info) == [
        'controller.type: commands impedance, which driver "lwr" (fri) cannot apply (it takes position)'
    ]
    config = fri_config(ImpedanceController, control="joint_impedance")
    assert config.controller.cls is ImpedanceController


def test_a_mode_chosen_by_a_parameter_is_reported_there():
    fri_config(ModeController, {"mode": "position"})
    with pytest.raises(ConfigError) as info:
        fri_config(ModeController, {"mode": "effort"})
    assert messages(info) == [
        'controller.params.mode: commands effort, which driver "lwr" (fri) cannot apply (it takes position)'
    ]


def test_every_driver_that_cannot_is_named():
    raw = {"joints": {**LWR, "b1": {"velocity": 1.0}},
           "driver": [{"type": "fri", "joints": ["a*"]}, {"type": "mock", "joints": ["b1"]}],
           "controller": {"type": "hold"}}
    parse_config(raw)  # hold commands position, which both apply
    with pytest.raises(ConfigError) as info:
        from_parts(joints=raw["joints"], drivers=raw["driver"], controller=VelocityController)
    assert messages(info) == [
        'controller.type: commands velocity, which driver "fri" (fri) cannot apply (it takes position)'
    ]


def test_the_mock_applies_every_mode():
    config = from_parts(joints=arm_raw()["joints"], drivers=[("mock", {"joints": ["j*"]})], controller=ModeController,
                        params={"mode": "effort"})
    assert config.controller.params.mode == "effort"


@pytest.mark.asyncio
async def test_a_controller_instance_is_checked_before_any_driver_is_built():
    loop = ControlLoop(fri_config("hold"), controller=VelocityController())
    with pytest.raises(ConfigError) as info:
        await loop.activate()
    assert messages(info) == [
        'controller.type: commands velocity, which driver "lwr" (fri) cannot apply (it takes position)'
    ]
    assert loop.slots == []  # no driver was built, let alone opened
