"""A controller of your own: move an end-effector site by an offset (docs/writing-a-controller.md).

The kinematics come from the robot's MJCF model through MuJoCo (site position and Jacobian),
so the same class moves the site of any robot whose model has it. Each tick, damped least
squares turns the site's velocity toward its goal into joint velocities, integrated into the
commanded configuration. Needs the ``sim`` extra (MuJoCo).

    python examples/reach_controller.py
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import mujoco
import numpy as np
from pydantic import Field

from aiohal import Controller, ControlLoop, Mode, Options
from aiohal.mjcf import joint_addresses, load_model, model_names


class ReachParams(Options):
    site: str = Field(description="The site of the model to move.")
    offset: tuple[float, float, float] = Field(description="Where the site goes, from where it starts (m, world axes).")
    speed: float = Field(0.1, gt=0, description="Largest speed of the site (m/s).")
    gain: float = Field(10.0, gt=0, description="Site velocity per metre left to go (1/s).")
    damping: float = Field(0.02, gt=0, description="Damped least squares λ (m).")


class ReachController(Controller):
    Params = ReachParams
    params: ReachParams  # what configure() stores, typed as this controller's

    @classmethod
    def check_config(cls, params, joints, robot):
        if robot.model is None:
            return [("/robot.model", "the reach controller needs the robot's MJCF model")]
        if params.site not in model_names(str(robot.model)).sites:
            return [("params.site", f'no site "{params.site}" in {robot.model.name}')]
        return []

    def configure(self, robot, params) -> None:
        super().configure(robot, params)
        # everything update() uses is made here, once
        self.model = load_model(robot.model_path)
        self.data = mujoco.MjData(self.model)
        self.qpos, self.dofs = joint_addresses(self.model, list(robot.joint_names))
        self.site_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, params.site)
        self.site = self.data.site_xpos[self.site_id]  # a view: mj_kinematics updates it in place
        self.jacobian = np.zeros((3, self.model.nv))
        self.regularise = params.damping**2 * np.eye(3)
        self.q = np.zeros(robot.dof)  # the commanded configuration
        self.goal = np.zeros(3)

    def start(self, t: float) -> None:
        # bumpless: from the last command, which the loop set to the measured position (at
        # activation, or after a disabled robot is re-armed) or which hold left
        np.copyto(self.q, self.robot.command.position)
        self.goal[:] = self.site_at(self.q) + self.params.offset
        self.robot.command.mode[:] = Mode.POSITION

    def site_at(self, q: np.ndarray) -> np.ndarray:
        self.data.qpos[self.qpos] = q
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)  # what mj_jacSite needs besides
        return self.site

    def update(self, t: float, dt: float) -> None:
        robot, params = self.robot, self.params
        to_go = self.goal - self.site_at(self.q)
        velocity = params.gain * to_go
        norm = np.linalg.norm(velocity)
        if norm > params.speed:
            velocity *= params.speed / norm
        mujoco.mj_jacSite(self.model, self.data, self.jacobian, None, self.site_id)
        J = self.jacobian[:, self.dofs]
        dq = J.T @ np.linalg.solve(J @ J.T + self.regularise, velocity)
        np.clip(dq, -robot.velocity_limit, robot.velocity_limit, out=dq)
        self.q += dq * dt
        np.clip(self.q, robot.position_min, robot.position_max, out=self.q)
        np.copyto(robot.command.position, self.q)
        np.copyto(robot.command.velocity, dq)

    def metrics(self) -> dict:
        measured = self.site_at(self.robot.state.position)
        return {"distance_m": round(float(np.linalg.norm(self.goal - measured)), 6)}


MODEL = Path(__file__).resolve().parent.parent / "configs" / "models" / "kuka_lwr.xml"
LIMITS = {"position": [-2.0, 2.0], "velocity": 1.5, "acceleration": 10.0}


def build() -> ControlLoop:
    return ControlLoop.from_parts(
        robot={"name": "lwr", "model": str(MODEL)},
        joints={name: LIMITS for name in ("a1", "a2", "e1", "a3", "a4", "a5", "a6")},
        drivers=[("mock", {"joints": ["*"], "options": {"initial_position": {"a2": 0.5, "a3": -1.2, "a5": 0.6}}})],
        controller=ReachController,
        params={"site": "ee", "offset": (0.0, 0.1, -0.05)},
        rate_hz=1000,
        clock="virtual",
    )


async def main() -> dict:
    async with build() as loop:
        report = await loop.run(duration=3.0)
    print("controller:", report["controller"])
    return report


if __name__ == "__main__":
    asyncio.run(main())
