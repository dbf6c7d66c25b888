"""``sequence``: a list of steps, each a move to a pose or a grasp with a hand, done in order.

A move step goes from the pose commanded so far to ``pose`` (joints not named stay) along a
minimum-jerk path in ``duration`` seconds. A hand step addresses the hand through the joint
that carries it (``hand = "<joint>"``, XBot's joint-to-hand mapping), commands ``grasp``
with ``speed`` and ``force``, and holds the arm until the hand settles: it reached the grasp,
closed on an object, reports a fault, or ``timeout`` passed. The same steps drive a simulated
hand and a real one. The outcome of every hand step is in the report.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from pydantic import Field, model_validator

from aiohal.hal import Controller, Options, unknown_joint_issues
from aiohal.robot import Fault, Mode

SETTLED = 0.02  # a hand within this of its grasp target has arrived (0..1 units)
MIN_HAND_WAIT = 0.05  # s: let the slow hand report at least once after the command


class Step(Options):
    pose: dict[str, float] | None = Field(None, description="Target per joint name (move step).")
    duration: float | None = Field(None, gt=0, description="Time of the move (s).")
    hand: str | None = Field(None, description="The joint that carries the hand (hand step).")
    grasp: float = Field(1.0, ge=0, le=1, description="0 open .. 1 closed.")
    speed: float = Field(1.0, ge=0, le=1, description="Fraction of the hand's top speed.")
    force: float = Field(1.0, ge=0, le=1, description="Fraction of the hand's top force.")
    timeout: float = Field(3.0, gt=0, description="Longest wait for the hand to settle (s).")

    @model_validator(mode="after")
    def _one_kind(self) -> Step:
        if (self.pose is None) == (self.hand is None):
            raise ValueError("a step has either pose (with duration) or hand")
        if self.pose is not None and self.duration is None:
            raise ValueError("a pose step needs duration")
        return self


class SequenceParams(Options):
    steps: list[Step] = Field(min_length=1, description="Steps, done in order once.")


class SequenceController(Controller):
    Params = SequenceParams
    params: SequenceParams  # what configure() stores, typed as this controller's

    @classmethod
    def check_config(cls, params, joints, robot):
        names = {j.name: j for j in joints}
        issues = []
        for i, step in enumerate(params.steps):
            where = f"params.steps[{i}]"
            if step.pose is not None:
                issues += unknown_joint_issues(f"{where}.pose", step.pose, names)
                for name, target in step.pose.items():
                    joint = names.get(name)
                    if joint is not None and not joint.position_min <= target <= joint.position_max:
                        issues.append(
                            (
                                f"{where}.pose.{name}",
                                f"{target} is outside the joint's range [{joint.position_min}, {joint.position_max}]",
                            )
                        )
            elif step.hand not in names:
                issues.append((f"{where}.hand", f'unknown joint "{step.hand}"'))
        return issues

    def configure(self, robot, params) -> None:
        super().configure(robot, params)
        for step in params.steps:
            if step.hand is not None:
                robot.hand_for_joint(step.hand)  # KeyError with the reason if no hand is there

    def start(self, t: float) -> None:
        robot = self.robot
        robot.command.mode[:] = Mode.POSITION
        self.pose = robot.state.position.copy()  # the pose commanded between moves
        self.goals = [None if s.pose is None else robot.per_joint(s.pose, default=np.nan) for s in self.params.steps]
        self.index = -1
        self.outcomes: list[dict] = []
        self._next(t)

    def _next(self, t: float) -> None:
        self.index += 1
        self.t0 = t
        if self.index >= len(self.params.steps):
            return
        step = self.params.steps[self.index]
        if step.pose is not None:
            goal = cast(np.ndarray, self.goals[self.index])  # a pose step has its goal
            self.delta = np.where(np.isnan(goal), 0.0, goal - self.pose)
        else:
            self.hand = self.robot.hand_for_joint(cast(str, step.hand))  # a step without pose has hand
            self.hand.grasp[...] = step.grasp
            self.hand.speed[...] = step.speed
            self.hand.force[...] = step.force

    def update(self, t: float, dt: float) -> None:
        cmd = self.robot.command
        steps = self.params.steps
        if self.index >= len(steps):
            cmd.position[:] = self.pose
            cmd.velocity[:] = 0.0
            return
        step = steps[self.index]
        if step.pose is not None:
            T = cast(float, step.duration)  # a pose step has duration (Step._one_kind)
            tau = min((t - self.t0) / T, 1.0)
            s = tau * tau * tau * (10.0 + tau * (-15.0 + 6.0 * tau))
            ds = 30.0 * tau * tau * (1.0 - tau) * (1.0 - tau) / T
            np.multiply(self.delta, s, out=cmd.position)
            cmd.position += self.pose
            np.multiply(self.delta, ds, out=cmd.velocity)
            if tau >= 1.0:
                self.pose += self.delta
                self._next(t)
            return
        cmd.position[:] = self.pose
        cmd.velocity[:] = 0.0
        outcome = self._hand_outcome(step, t - self.t0)
        if outcome:
            hand = self.hand
            self.outcomes.append(
                {
                    "step": self.index,
                    "hand": hand.name,
                    "grasp": step.grasp,
                    "outcome": outcome,
                    "position": round(float(hand.position), 4),
                    "time_s": round(t - self.t0, 3),
                }
            )
            self._next(t)

    def _hand_outcome(self, step: Step, waited: float) -> str:
        hand = self.hand
        if hand.fault & Fault.HARDWARE:
            return "faulted"
        if waited >= step.timeout:
            return "timeout"
        if waited < MIN_HAND_WAIT:
            return ""
        position = float(hand.position)
        if bool(hand.object_detected) and step.grasp > position:
            return "object"
        if abs(position - step.grasp) < SETTLED:
            return "reached"
        return ""

    def metrics(self) -> dict:
        return {
            "steps_done": min(self.index, len(self.params.steps)),
            "steps": len(self.params.steps),
            "hand_steps": self.outcomes,
        }
