"""``chirp``: a logarithmic sine sweep about the start position, to measure a joint's
closed-loop frequency response (LOLA's Fig. 10; ``benchmarks/lola_bandwidth.py``).

After ``settle`` seconds at the start position, each joint given an ``amplitude`` follows
``q*(t) = q0 + A·r(t)·sin φ(t)`` for ``duration`` seconds, with the instantaneous frequency
rising exponentially from ``f_start`` to ``f_end``::

    f(t) = f_start · (f_end / f_start)^(t / duration)
    φ(t) = 2π · f_start · duration / ln(f_end / f_start) · ((f_end / f_start)^(t / duration) − 1)

so every octave gets the same time (the same number of periods per decade at each frequency's
own scale, which a Bode plot on a log axis wants). ``r(t)`` fades the amplitude in over the
first and out over the last ``ramp`` seconds (minimum jerk), so neither end jumps; afterwards
the joints hold the start position. The target velocity is the exact derivative, sent as the
drives' velocity feed-forward unless ``velocity_feedforward = false`` (position only).
``f_end`` must stay below half the rate the controller runs at.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from aiohal.hal import Controller, JointValues, Options, unknown_joint_issues
from aiohal.robot import Mode


class ChirpParams(Options):
    amplitude: JointValues = Field(
        0.0002, description="Amplitude (rad), scalar or per joint (joints not named stay where they are)."
    )
    f_start: float = Field(10.0, gt=0, description="Frequency at the start of the sweep (Hz).")
    f_end: float = Field(500.0, gt=0, description="Frequency at the end of the sweep (Hz).")
    duration: float = Field(4.0, gt=0, description="Length of the sweep (s).")
    settle: float = Field(0.5, ge=0, description="Time at the start position before the sweep (s).")
    ramp: float = Field(0.05, ge=0, description="Fade-in and fade-out of the amplitude (s).")
    velocity_feedforward: bool = Field(
        True,
        description="Send the sweep's velocity as the target velocity (false: position only, zero target velocity).",
    )


def _fade(x: float) -> tuple[float, float]:
    """Minimum-jerk 0 → 1 on [0, 1] and its derivative in x."""
    if x >= 1.0:
        return 1.0, 0.0
    if x <= 0.0:
        return 0.0, 0.0
    return x**3 * (10.0 - 15.0 * x + 6.0 * x * x), 30.0 * x * x * (1.0 - x) ** 2


class ChirpController(Controller):
    Params = ChirpParams
    params: ChirpParams

    @classmethod
    def check_config(cls, params, joints, robot) -> list[tuple[str, str]]:
        issues = unknown_joint_issues("params.amplitude", params.amplitude, [j.name for j in joints])
        if params.f_end <= params.f_start:
            issues.append(("params.f_end", f"must be above f_start ({params.f_end:g} <= {params.f_start:g})"))
        if 2.0 * params.ramp > params.duration:
            issues.append(
                (
                    "params.ramp",
                    f"fade-in and fade-out ({2 * params.ramp:g} s) are longer than the sweep ({params.duration:g} s)",
                )
            )
        if issues:
            return issues
        too_fast: dict[str, list[str]] = {}
        for joint in joints:
            per_joint = isinstance(params.amplitude, dict)
            a = abs(params.amplitude.get(joint.name, 0.0) if per_joint else params.amplitude)
            # the fades add at most 15/8·A/ramp to the peak 2π·f·A
            peak = a * (2.0 * math.pi * params.f_end + (1.875 / params.ramp if params.ramp > 0 else 0.0))
            if peak > joint.velocity:
                where = f"params.amplitude.{joint.name}" if per_joint else "params.amplitude"
                too_fast.setdefault(where, []).append(f"{joint.name} ({peak:.3g} > {joint.velocity:.3g})")
        for where, names in too_fast.items():
            issues.append((where, f"peak velocity of the sweep exceeds the velocity limit of {', '.join(names)}"))
        return issues

    def configure(self, robot, params) -> None:
        super().configure(robot, params)
        self.amplitude = robot.per_joint(params.amplitude, 0.0)
        self.rate = math.log(params.f_end / params.f_start) / params.duration  # d ln f / dt

    def frequency(self, t: np.ndarray | float) -> np.ndarray | float:
        """Instantaneous frequency (Hz) at ``t`` s into the sweep."""
        return self.params.f_start * np.exp(self.rate * np.asarray(t))

    def phase(self, t: np.ndarray | float) -> np.ndarray | float:
        """φ(t), the integral of 2π·f from the sweep's start."""
        return 2.0 * math.pi * self.params.f_start / self.rate * np.expm1(self.rate * np.asarray(t))

    def reference(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Target position and velocity at the times ``t`` (s since start), joints last."""
        p = self.params
        t = np.asarray(t, dtype=np.float64)
        s = np.clip(t - p.settle, 0.0, p.duration)
        inside = (t >= p.settle) & (t <= p.settle + p.duration)
        fade = np.vectorize(_fade, otypes=[float, float])
        if p.ramp > 0:
            r_in, dr_in = fade(s / p.ramp)
            r_out, dr_out = fade((p.duration - s) / p.ramp)
            r, dr = r_in * r_out, (dr_in * r_out - r_in * dr_out) / p.ramp
        else:
            r, dr = np.ones_like(s), np.zeros_like(s)
        phi = self.phase(s)
        swing = np.where(inside, r * np.sin(phi), 0.0)[..., None]
        speed = np.where(inside, dr * np.sin(phi) + r * np.cos(phi) * 2.0 * math.pi * self.frequency(s), 0.0)[..., None]
        return self.q0 + self.amplitude * swing, self.amplitude * speed

    def start(self, t: float) -> None:
        self.t0 = t
        self.q0 = self.robot.state.position.copy()
        self.robot.command.mode[:] = Mode.POSITION

    def update(self, t: float, dt: float) -> None:
        p = self.params
        cmd = self.robot.command
        s = t - self.t0 - p.settle
        if s < 0.0 or s > p.duration:
            np.copyto(cmd.position, self.q0)
            cmd.velocity.fill(0.0)
            return
        if p.ramp > 0:
            r_in, dr_in = _fade(s / p.ramp)
            r_out, dr_out = _fade((p.duration - s) / p.ramp)
            r, dr = r_in * r_out, (dr_in * r_out - r_in * dr_out) / p.ramp
        else:
            r, dr = 1.0, 0.0
        f = p.f_start * math.exp(self.rate * s)
        phi = 2.0 * math.pi * p.f_start / self.rate * math.expm1(self.rate * s)
        sin, cos = math.sin(phi), math.cos(phi)
        np.multiply(self.amplitude, r * sin, out=cmd.position)
        cmd.position += self.q0
        if p.velocity_feedforward:
            np.multiply(self.amplitude, dr * sin + r * cos * 2.0 * math.pi * f, out=cmd.velocity)
        else:
            cmd.velocity.fill(0.0)

    def metrics(self) -> dict:
        return {"f_start_hz": self.params.f_start, "f_end_hz": self.params.f_end, "sweep_s": self.params.duration}
