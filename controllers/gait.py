"""``gait``: a periodic joint trajectory like a walking robot's hip, with its feed-forward.

The motion is a Fourier series in the gait's phase, ``f(t) = Σ_h A_h sin(h·ω·t + φ_h)``
(ω = 2π / period), the same for every joint up to a per-joint ``scale`` and ``offset``:
``q*(t) = offset + scale · f(t)``. The defaults are a hip flexion at LOLA's 2.7 km/h: a stride
of 1.2 s (two steps of 0.45 m), about 40° of swing, flexed most late in swing and extended most
before toe-off (a fundamental and a second harmonic, the shape of human hip flexion in gait).

Each tick the controller commands the target position, the target velocity q̇* (which the
drives take as velocity feed-forward) and a torque feed-forward from a rigid model of the
joint: ``inertia · q̈* + gravity_torque · sin q*`` (what the drives take as current
feed-forward). It starts where the joints stand and blends into the motion over ``ramp``
seconds with a smooth step, differentiated with it, so nothing jumps.

``reference(t)`` gives the same trajectory vectorised, for analysis; the report gives the
RMS of target against measured position at the same tick, after ``ramp`` + one period.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from aiohal.hal import Controller, JointValues, Options, unknown_joint_issues
from aiohal.robot import Mode


class GaitParams(Options):
    period: float = Field(1.2, gt=0, description="Gait period, one stride (s).")
    harmonics: list[tuple[float, float]] = Field(
        [(0.35, 0.0), (0.06, 0.9)],
        min_length=1,
        description="(amplitude rad, phase rad) of harmonic 1, 2, ... of the gait frequency.",
    )
    offset: JointValues = Field(0.1, description="Mean position (rad), scalar or per joint.")
    scale: JointValues = Field(1.0, description="Factor on the series, scalar or per joint.")
    ramp: float = Field(1.0, ge=0, description="Blend-in time from the start position (s).")
    inertia: JointValues = Field(
        2.2,
        ge=0,
        description="Model: inertia at the joint incl. the rotor's "
        "through the gear (kg·m²), for the torque feed-forward.",
    )
    gravity_torque: JointValues = Field(
        30.0, description="Model: m·g·l of the load (N·m): gravity torque gravity_torque · sin q."
    )
    torque_feedforward: bool = Field(True, description="Send the model's torque as feed-forward.")


def _smoothstep(x: float) -> tuple[float, float, float]:
    """The quintic 0 → 1 on [0, 1] and its first two derivatives (in x)."""
    if x >= 1.0:
        return 1.0, 0.0, 0.0
    if x <= 0.0:
        return 0.0, 0.0, 0.0
    return (x**3 * (10 - 15 * x + 6 * x * x), 30 * x * x * (1 - x) ** 2, 60 * x * (1 - x) * (1 - 2 * x))


class GaitController(Controller):
    Params = GaitParams
    params: GaitParams

    @classmethod
    def check_config(cls, params, joints, robot):
        names = [j.name for j in joints]
        issues = []
        for key in ("offset", "scale", "inertia", "gravity_torque"):
            issues += unknown_joint_issues(f"params.{key}", getattr(params, key), names)
        return issues

    def configure(self, robot, params) -> None:
        super().configure(robot, params)
        self.offset = robot.per_joint(params.offset, 0.0)
        self.scale = robot.per_joint(params.scale, 1.0)
        self.inertia = robot.per_joint(params.inertia, 0.0)
        self.gravity = robot.per_joint(params.gravity_torque, 0.0)
        self.omega = 2.0 * math.pi / params.period
        self._harmonics = [(a, h * self.omega, phi) for h, (a, phi) in enumerate(params.harmonics, start=1)]
        n = robot.dof
        self._goal = np.zeros(n)  # q* of the full motion
        self._tmp = np.zeros(n)

    def series(self, t: float) -> tuple[float, float, float]:
        """f(t), f'(t), f''(t)."""
        f = df = ddf = 0.0
        for a, w, phi in self._harmonics:
            s, c = math.sin(w * t + phi), math.cos(w * t + phi)
            f += a * s
            df += a * w * c
            ddf -= a * w * w * s
        return f, df, ddf

    def reference(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Target position and velocity at the times ``t`` (s since start), joints last."""
        t = np.asarray(t, dtype=np.float64)[..., None]
        f = sum(a * np.sin(w * t + phi) for a, w, phi in self._harmonics)
        df = sum(a * w * np.cos(w * t + phi) for a, w, phi in self._harmonics)
        goal = self.offset + self.scale * f
        if self.params.ramp > 0:
            x = np.clip(t / self.params.ramp, 0.0, 1.0)
            s = x**3 * (10 - 15 * x + 6 * x * x)
            ds = 30 * x * x * (1 - x) ** 2 / self.params.ramp
            return self.q0 + s * (goal - self.q0), ds * (goal - self.q0) + s * self.scale * df
        return goal, self.scale * df

    def start(self, t: float) -> None:
        robot = self.robot
        self.t0 = t
        self.q0 = robot.state.position.copy()
        robot.command.mode[:] = Mode.POSITION
        self._measure_from = self.params.ramp + self.params.period
        self._sum = 0.0
        self._samples = 0

    def update(self, t: float, dt: float) -> None:
        t -= self.t0
        cmd, state = self.robot.command, self.robot.state
        f, df, ddf = self.series(t)
        ramp = self.params.ramp
        s, ds, dds = _smoothstep(t / ramp) if ramp > 0 else (1.0, 0.0, 0.0)
        if ramp > 0:
            ds, dds = ds / ramp, dds / ramp / ramp
        goal, tmp = self._goal, self._tmp
        np.multiply(self.scale, f, out=goal)
        goal += self.offset
        # q* = q0 + s (goal - q0): position, velocity and acceleration by the product rule
        np.subtract(goal, self.q0, out=tmp)
        np.multiply(tmp, s, out=cmd.position)
        cmd.position += self.q0
        np.multiply(tmp, ds, out=cmd.velocity)
        cmd.velocity += self.scale * (s * df)
        if self.params.torque_feedforward:
            acc = cmd.feedforward  # the acceleration first, then the torque in place
            np.multiply(tmp, dds, out=acc)
            acc += self.scale * (2.0 * ds * df + s * ddf)
            acc *= self.inertia
            np.sin(cmd.position, out=tmp)
            tmp *= self.gravity
            acc += tmp
        if t >= self._measure_from:
            np.subtract(cmd.position, state.position, out=tmp)
            self._sum += float(np.dot(tmp, tmp))
            self._samples += len(tmp)

    def metrics(self) -> dict:
        samples = getattr(self, "_samples", 0)
        rms = math.sqrt(self._sum / samples) if samples else float("nan")
        return {"tracking_rms_rad": round(rms, 8)}
