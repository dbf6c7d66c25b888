"""``homing``: move to a configured pose along a minimum-jerk path in a configured time.

Joints not named in ``pose`` hold where they start. The path starts and ends at rest with
zero acceleration, so it is smooth for any drive.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from aiohal.hal import Controller, Options, unknown_joint_issues
from aiohal.robot import Mode


class HomingParams(Options):
    pose: dict[str, float] = Field(description="Target position per joint name (rad or m).")
    duration: float = Field(gt=0, description="Time to reach the pose (s).")


class HomingController(Controller):
    Params = HomingParams
    params: HomingParams  # what configure() stores, typed as this controller's

    @classmethod
    def check_config(cls, params, joints, robot):
        issues = unknown_joint_issues("params.pose", params.pose, (j.name for j in joints))
        for joint in joints:
            target = params.pose.get(joint.name)
            if target is not None and not joint.position_min <= target <= joint.position_max:
                issues.append(
                    (
                        f"params.pose.{joint.name}",
                        f"{target} is outside the joint's range [{joint.position_min}, {joint.position_max}]",
                    )
                )
        return issues

    def start(self, t: float) -> None:
        robot = self.robot
        self.t0 = t
        self.q0 = robot.state.position.copy()
        self.goal = robot.per_joint(self.params.pose, default=np.nan)
        keep = np.isnan(self.goal)
        self.goal[keep] = self.q0[keep]
        self.delta = self.goal - self.q0
        self.done = False
        self.finished_at: float | None = None
        robot.command.mode[:] = Mode.POSITION

    def update(self, t: float, dt: float) -> None:
        cmd = self.robot.command
        T = self.params.duration
        tau = min(max((t - self.t0) / T, 0.0), 1.0)
        s = tau * tau * tau * (10.0 + tau * (-15.0 + 6.0 * tau))
        ds = 30.0 * tau * tau * (1.0 - tau) * (1.0 - tau) / T
        np.multiply(self.delta, s, out=cmd.position)
        cmd.position += self.q0
        np.multiply(self.delta, ds, out=cmd.velocity)
        if tau >= 1.0 and not self.done:
            self.done = True
            self.finished_at = t

    def metrics(self) -> dict:
        error = np.abs(self.robot.state.position - self.goal)
        return {
            "reached": bool(self.done),
            "final_error_max": round(float(error.max(initial=0.0)), 6),
            "duration_s": self.params.duration,
        }
