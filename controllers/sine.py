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

from aiohal import kernel_call
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
        from . import sine_kernels  # noqa: F401  compiled or loaded from numba's cache now, before drivers open
        self.amplitude = robot.per_joint(params.amplitude, 0.0)
        self.omega = 2.0 * math.pi * robot.per_joint(params.frequency, 0.5)
        self.phase = robot.per_joint(params.phase, 0.0)
        self.sin_phase = np.sin(self.phase)

    def start(self, t: float) -> None:
        robot = self.robot
        self.t0 = t
        self.q0 = robot.state.position.copy()
        robot.command.mode[:] = Mode.POSITION
        self._error = np.zeros(3)  # sum of squares, largest magnitude, samples
        self._tick = _tick_function(self)

    def update(self, t: float, dt: float) -> None:
        self._tick(t, dt)

    def metrics(self) -> dict:
        sum_sq, largest, samples = getattr(self, "_error", (0.0, 0.0, 0.0))
        if not samples:
            return {"tracking_rms_rad_or_m": float("nan"), "tracking_max_rad_or_m": float("nan")}
        return {"tracking_rms_rad_or_m": round(math.sqrt(sum_sq / samples), 6), "tracking_max_rad_or_m": round(float(largest), 6)}


def _tick_function(c: SineController):
    """``update(t, dt)`` of a started controller: one call of the compiled tick, with the
    arrays bound once here (the robot's blocks are never reallocated) and checked, because the
    direct call checks nothing itself (``aiohal.kernel_call``)."""
    from . import sine_kernels

    robot = c.robot
    arrays = (robot.state.position, robot.command.block, c.q0, c.amplitude, c.omega, c.phase, c.sin_phase)
    t0, ramp, error = c.t0, c.params.ramp, c._error
    kernel_call.check(sine_kernels.sine_tick, (*arrays, 0.0, ramp, error))
    kernel = kernel_call.direct(sine_kernels.sine_tick)
    measured, command, q0, amplitude, omega, phase, sin_phase = arrays

    def update(t: float, dt: float) -> None:
        kernel(measured, command, q0, amplitude, omega, phase, sin_phase, t - t0, ramp, error)

    return update
