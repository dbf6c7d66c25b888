"""``sine``: every joint follows a sinusoid about its start position.

``amplitude``, ``frequency`` and ``phase`` are one number for all joints or a table per
joint name (joints not named get 0 amplitude). The motion starts at the measured position
and its amplitude ramps in smoothly over ``ramp`` seconds, so nothing jumps at start.
Reports the tracking error: the position measured at a tick against the command sent the
tick before (zero for a mirroring mock, the lag of the dynamics otherwise).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from aiohal.hal import Controller, JointValues, Options, unknown_joint_issues
from aiohal.robot import Mode


class SineParams(Options):
    amplitude: JointValues = Field(0.1, description="Amplitude (rad or m), scalar or per joint.")
    frequency: JointValues = Field(0.5, description="Frequency (Hz), scalar or per joint.")
    phase: JointValues = Field(0.0, description="Phase (rad), scalar or per joint.")
    ramp: float = Field(1.0, ge=0, description="Time over which the amplitude ramps in (s).")


class SineController(Controller):
    Params = SineParams

    @classmethod
    def check_config(cls, params, joints, robot):
        names = [j.name for j in joints]
        issues = []
        for key in ("amplitude", "frequency", "phase"):
            issues += unknown_joint_issues(f"params.{key}", getattr(params, key), names)
        if issues:
            return issues

        def value(field, name, default):
            v = getattr(params, field)
            return v.get(name, default) if isinstance(v, dict) else v

        too_fast: dict[str, list[str]] = {}
        too_wide: dict[str, list[str]] = {}
        for joint in joints:
            amplitude = abs(value("amplitude", joint.name, 0.0))
            frequency = value("frequency", joint.name, 0.5)
            where = f"params.amplitude.{joint.name}" if isinstance(params.amplitude, dict) else "params.amplitude"
            if frequency < 0:
                issues.append((f"params.frequency.{joint.name}" if isinstance(params.frequency, dict) else "params.frequency",
                               f"must be >= 0 (got {frequency})"))
            peak = 2.0 * math.pi * frequency * amplitude
            if peak > joint.velocity:
                too_fast.setdefault(where, []).append(f"{joint.name} ({peak:.3g} > {joint.velocity:.3g})")
            if 2 * amplitude > joint.position_max - joint.position_min:
                too_wide.setdefault(where, []).append(joint.name)
        # one line per key: a scalar amplitude that is too fast for 30 joints is one mistake
        for where, names in too_fast.items():
            issues.append((where, f"peak velocity 2π·f·A exceeds the velocity limit of {', '.join(names)}"))
        for where, names in too_wide.items():
            issues.append((where, f"swing 2·A is wider than the range of {', '.join(names)}"))
        return issues

    def configure(self, robot, params) -> None:
        super().configure(robot, params)
        n = robot.dof
        self.amplitude = robot.per_joint(params.amplitude, 0.0)
        self.omega = 2.0 * math.pi * robot.per_joint(params.frequency, 0.5)
        self.phase = robot.per_joint(params.phase, 0.0)
        self.sin_phase = np.sin(self.phase)
        self.amp_omega = self.amplitude * self.omega
        self._sin = np.empty(n)
        self._cos = np.empty(n)
        self._a = np.empty(n)
        self._aw = np.empty(n)
        self._err = np.empty(n)

    def start(self, t: float) -> None:
        self.t0 = t
        self.q0 = self.robot.state.position.copy()
        self.robot.command.mode[:] = Mode.POSITION
        self.sum_sq = 0.0
        self.max_err = 0.0
        self.samples = 0

    def update(self, t: float, dt: float) -> None:
        robot = self.robot
        cmd = robot.command
        err = self._err
        # tracking: what was commanded last tick against what is measured now
        np.subtract(robot.state.position, cmd.position, out=err)
        self.sum_sq += float(np.dot(err, err))
        e = max(float(err.max()), -float(err.min()))
        if e > self.max_err:
            self.max_err = e
        self.samples += robot.dof

        elapsed = t - self.t0
        sin, cos = self._sin, self._cos
        np.multiply(self.omega, elapsed, out=sin)
        sin += self.phase
        np.cos(sin, out=cos)
        np.sin(sin, out=sin)
        sin -= self.sin_phase  # sin(ωt+φ) - sin φ: zero at start
        ramp_t = self.params.ramp
        if elapsed >= ramp_t:
            # q = q0 + A·(sin(ωt+φ) - sin φ),  v = A·ω·cos(ωt+φ)
            np.multiply(sin, self.amplitude, out=cmd.position)
            cmd.position += self.q0
            np.multiply(cos, self.amp_omega, out=cmd.velocity)
            return
        # ramp in: amplitude scaled by r(t), a minimum-jerk 0 -> 1 over ramp_t
        x = elapsed / ramp_t
        r = x * x * x * (10.0 + x * (-15.0 + 6.0 * x))
        dr = 30.0 * x * x * (1.0 - x) * (1.0 - x) / ramp_t
        np.multiply(self.amplitude, r, out=self._a)
        np.multiply(self.amp_omega, r, out=self._aw)
        np.multiply(cos, self._aw, out=cmd.velocity)
        np.multiply(sin, self.amplitude, out=sin)
        np.multiply(sin, dr, out=cos)
        cmd.velocity += cos
        np.multiply(sin, r, out=cmd.position)
        cmd.position += self.q0

    def metrics(self) -> dict:
        rms = math.sqrt(self.sum_sq / self.samples) if getattr(self, "samples", 0) else float("nan")
        return {
            "tracking_rms": round(rms, 6),
            "tracking_max": round(self.max_err, 6) if self.samples else float("nan"),
        }
