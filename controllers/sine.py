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
    params: SineParams  # what configure() stores, typed as this controller's

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
                issues.append(
                    (
                        f"params.frequency.{joint.name}" if isinstance(params.frequency, dict) else "params.frequency",
                        f"must be >= 0 (got {frequency})",
                    )
                )
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
        self.amplitude = robot.per_joint(params.amplitude, 0.0)
        self.omega = 2.0 * math.pi * robot.per_joint(params.frequency, 0.5)
        self.phase = robot.per_joint(params.phase, 0.0)
        self.sin_phase = np.sin(self.phase)
        self.peak_velocity = self.amplitude * self.omega
        n = robot.dof
        self._error = np.zeros(n)
        self._angle = np.zeros(n)
        self._swing = np.zeros(n)

    def start(self, t: float) -> None:
        robot = self.robot
        self.t0 = t
        self.q0 = robot.state.position.copy()
        robot.command.mode[:] = Mode.POSITION
        self._sum_sq, self._largest, self._samples = 0.0, 0.0, 0

    def update(self, t: float, dt: float) -> None:
        """Command ``q0 + r·A·(sin(ωt+φ) − sin φ)`` and its derivative, where ``r`` ramps the
        amplitude in from 0 to 1 over ``ramp`` seconds (minimum jerk); first, the tracking
        error of the position commanded the tick before."""
        command = self.robot.command
        error, angle, swing = self._error, self._angle, self._swing
        np.subtract(self.robot.state.position, command.position, out=error)
        self._sum_sq += float(np.dot(error, error))
        np.abs(error, out=error)
        self._largest = max(self._largest, float(error.max(initial=0.0)))
        self._samples += len(error)

        elapsed = t - self.t0
        np.multiply(self.omega, elapsed, out=angle)
        angle += self.phase
        np.sin(angle, out=swing)
        swing -= self.sin_phase
        swing *= self.amplitude
        np.cos(angle, out=command.velocity)
        command.velocity *= self.peak_velocity
        ramp = self.params.ramp
        if elapsed < ramp:
            x = elapsed / ramp
            r = x * x * x * (10.0 + x * (-15.0 + 6.0 * x))
            dr = 30.0 * x * x * (1.0 - x) * (1.0 - x) / ramp
            command.velocity *= r
            np.multiply(swing, dr, out=angle)
            command.velocity += angle
            swing *= r
        np.add(swing, self.q0, out=command.position)

    def metrics(self) -> dict:
        """Tracking error over the run, in the joints' own units (rad, or m for a prismatic joint)."""
        sum_sq, largest, samples = (
            getattr(self, "_sum_sq", 0.0),
            getattr(self, "_largest", 0.0),
            getattr(self, "_samples", 0),
        )
        if not samples:
            return {"tracking_rms": float("nan"), "tracking_max": float("nan")}
        return {
            "tracking_rms": round(math.sqrt(sum_sq / samples), 6),
            "tracking_max": round(float(largest), 6),
        }
