"""The joints' model of a simulated bus device started as a subprocess (the UDP boards, the
KRC): the options a driver's ``simulation`` table takes, and the simulator's command line
for them (``--dynamics``, ``--time-constant``, ``--servo-json``; see
:mod:`aiohal.simulation.joints`)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from aiohal.hal import FiniteFloat, Options
from aiohal.simulation.servo import ServoParams


class SimulatedJoints(Options):
    dynamics: Literal["first_order", "servo"] = Field(
        "first_order",
        description="first_order: the position error decays with time_constant; "
        "servo: each joint behind a simulated servo drive (servo).",
    )
    time_constant: FiniteFloat = Field(0.005, gt=0, description="first_order: the tracking time constant (s).")
    servo: ServoParams = Field(default_factory=ServoParams, description="The drives and joints of dynamics = servo.")

    def joint_arguments(self) -> list[str]:
        """The simulator's arguments for these options."""
        args = ["--dynamics", self.dynamics, "--time-constant", repr(self.time_constant)]
        if self.dynamics == "servo":
            args += ["--servo-json", self.servo.model_dump_json()]
        return args
