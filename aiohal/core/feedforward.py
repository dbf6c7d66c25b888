"""Learned velocity feed-forward (LOLA, section V): the HAL scales each joint's target velocity.

A drive in cyclic synchronous position mode gets the target position and, as feed-forward,
the target velocity. What the joint does lags the target by the bus and interpolation delay
(a target sent at tick k is reached at tick k + 1) and by the servo loops; a velocity
feed-forward a little larger than the target velocity makes up for it:
``k_vel,ff = 1 + k_e`` per joint. The HAL applies it, once per tick after the controller (or
the extrapolation of a slower controller) and before the limits, to the joints commanded in
position or impedance mode: no controller needs to know.

``k_e`` is learned by LOLA's policy (:class:`GainLearner`): start at 0, measure the RMS
tracking error (:mod:`aiohal.core.tracking_error`: the target against the link position
measured at the same instant) over a window,
raise ``k_e`` of every joint by one step, measure again, and keep raising while the error
decreases; the last gain that lowered it is the result. ``python -m aiohal.learn_feedforward
CONFIG --out gains.toml`` runs the configured controller with the learner and writes the
gains; ``[feedforward] gains = "gains.toml"`` in a config applies them.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, Field, ValidationInfo

from ..files import read_regular_text
from ..hal import JointValues, Options
from ..robot import JointCommand, JointState, Mode
from .tracking_error import TrackingError

#: a gains file has one line per joint
MAX_GAINS_BYTES = 1 << 20
#: k_e per joint: below -1 the feed-forward pushes against the motion; LOLA learned 1.0, and
#: a gain ten times that multiplies the target velocity by 11 (a typo, not a tuning)
K_E_RANGE = (-1.0, 10.0)


def _relative(value: Path | None, info: ValidationInfo) -> Path | None:
    base = (info.context or {}).get("base_dir")
    if value is not None and base is not None and not value.is_absolute():
        return (Path(base) / value).resolve()
    return value


class FeedforwardSection(Options):
    """``[feedforward]``: learned velocity feed-forward gains, and how to learn them."""

    gains: Annotated[Path | None, AfterValidator(_relative)] = Field(
        None, description="A gains file written by `python -m aiohal.learn_feedforward` (relative to this config)."
    )
    k_e: JointValues | None = Field(
        None, description="k_e given here, scalar or per joint (k_vel,ff = 1 + k_e); added to the file's, if both."
    )
    step: float = Field(0.1, gt=0, le=1, description="Learning: the raise of k_e per window.")
    window_s: float = Field(1.2, gt=0, description="Learning: the window of each RMS (one period of the motion).")
    settle_s: float = Field(1.2, ge=0, description="Learning: time before the first window (the ramp-in).")
    max_steps: int = Field(20, ge=1, le=1000, description="Learning: most raises.")
    measurement_delay_ticks: int = Field(
        0,
        ge=0,
        le=100,
        description="Learning: the ticks between measuring a position and reading it (EtherCAT: 1), "
        "so that a reading is compared with the target of the instant it was measured.",
    )

    @property
    def active(self) -> bool:
        return self.gains is not None or self.k_e is not None


def read_gains(path: Path, key: str = "feedforward.gains") -> dict[str, float]:
    """A gains file: ``[k_e]`` with one ``joint = value`` per joint (a regular file only)."""
    data = tomllib.loads(read_regular_text(path, key, limit=MAX_GAINS_BYTES))
    table = data.get("k_e")
    if not isinstance(table, dict) or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in table.values()):
        raise ValueError(f"{path}: a table [k_e] of finite numbers per joint is needed")
    return {str(k): float(v) for k, v in table.items()}


def write_gains(path: Path, gains: dict[str, float], comment: str = "") -> None:
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += ['# k_vel,ff = 1 + k_e per joint; load it with [feedforward] gains = "<this file>"', "[k_e]"]
    lines += [f"{name} = {value:.6g}" for name, value in gains.items()]
    Path(path).write_text("\n".join(lines) + "\n")


def section_issues(section: FeedforwardSection, joint_names: list[str]) -> list[tuple[str, str]]:
    """What is wrong with a ``[feedforward]`` section: an unreadable file, unknown joints."""
    issues = []
    if section.gains is not None:
        try:
            for name in read_gains(section.gains, key=""):  # the issue names the key
                if name not in joint_names:
                    issues.append(("feedforward.gains", f"{section.gains}: unknown joint {name!r}"))
        except (OSError, ValueError, tomllib.TOMLDecodeError) as exc:
            issues.append(("feedforward.gains", str(exc)))
    if isinstance(section.k_e, dict):
        issues += [(f"feedforward.k_e.{name}", "unknown joint") for name in section.k_e if name not in joint_names]
    if not issues:
        low, high = K_E_RANGE
        key = "feedforward.k_e" if section.k_e is not None else "feedforward.gains"
        for name, value in zip(joint_names, gains_of(section, joint_names), strict=True):
            if not low <= value <= high:
                issues.append(
                    (
                        key,
                        f"k_e of {name} is {value:g} (file and inline summed): it must be within "
                        f"[{low:g}, {high:g}] (k_vel,ff = 1 + k_e; LOLA learned 1.0)",
                    )
                )
    return issues


def gains_of(section: FeedforwardSection, joint_names: list[str]) -> np.ndarray:
    """k_e per joint from the section (file plus inline)."""
    k_e = np.zeros(len(joint_names))
    if section.gains is not None:
        for name, value in read_gains(section.gains).items():
            k_e[joint_names.index(name)] += value
    if isinstance(section.k_e, dict):
        for name, value in section.k_e.items():
            k_e[joint_names.index(name)] += value
    elif section.k_e is not None:
        k_e += section.k_e
    return k_e


class VelocityFeedforward:
    """Scales the target velocity of the joints in position or impedance mode by 1 + k_e."""

    def __init__(self, command: JointCommand, k_e: np.ndarray) -> None:
        self.command = command
        self.k_e = np.array(k_e, dtype=np.float64)
        self._factor = 1.0 + self.k_e
        n = len(self.k_e)
        self._moving = np.zeros(n, dtype=bool)
        self._impedance = np.zeros(n, dtype=bool)

    def set_gains(self, k_e: np.ndarray | float) -> None:
        self.k_e[:] = k_e
        np.add(self.k_e, 1.0, out=self._factor)

    def apply(self) -> None:
        """Once per tick, after the controller and before the limits (no allocation)."""
        cmd = self.command
        np.equal(cmd.mode, Mode.POSITION, out=self._moving)
        np.equal(cmd.mode, Mode.IMPEDANCE, out=self._impedance)
        np.logical_or(self._moving, self._impedance, out=self._moving)
        np.multiply(cmd.velocity, self._factor, out=cmd.velocity, where=self._moving)


class GainLearner:
    """LOLA's policy over windows of RMS tracking error: raise every joint's k_e by ``step``
    while the error decreases. ``costs`` lists (k_e, RMS) per window, in order."""

    def __init__(self, step: float = 0.1, max_steps: int = 20) -> None:
        self.step = step
        self.max_steps = max_steps
        self.k_e = 0.0  # what is applied now
        self.best: tuple[float, float] | None = None  # (k_e, RMS) of the lowest window so far
        self.costs: list[tuple[float, float]] = []
        self.repeated = 0  # windows measured again (a missed deadline in them)
        self.done = False

    def window(self, rms: float) -> float:
        """The RMS of the window run with the current k_e; returns the k_e for the next."""
        if self.done:
            return self.k_e
        self.costs.append((self.k_e, rms))
        if self.best is None or rms < self.best[1]:
            self.best = (self.k_e, rms)
            if len(self.costs) <= self.max_steps:
                self.k_e = round(self.k_e + self.step, 12)
                return self.k_e
        self.done = True  # the error went up (or the steps ran out): keep the best
        self.k_e = self.best[0]
        return self.k_e


class LearningFeedforward(VelocityFeedforward):
    """The feed-forward applied while :class:`GainLearner` learns it, in the tick: the error
    of each tick (:class:`TrackingError`: the target against the position measured at its
    instant, ``delay`` ticks before it is read) is summed over windows of ``window`` ticks,
    after ``settle`` ticks.

    With the robot's ``clock``, a window in which a deadline was missed is measured again
    (at most ``MAX_REPEATS`` times in a row): on a real clock a missed tick puts a spike of
    error into the window that says nothing about k_e, and the policy stops at the first
    window that is worse than the one before."""

    MAX_REPEATS = 3

    def __init__(
        self,
        command: JointCommand,
        state: JointState,
        learner: GainLearner,
        window: int,
        settle: int,
        clock: Any = None,
        delay: int = 0,
    ) -> None:
        super().__init__(command, np.zeros(len(command)))
        self.tracking = TrackingError(len(command), delay)
        self.state = state
        self.learner = learner
        self.window = window
        self.settle = settle
        self.clock = clock  # its ``tick``: a tick that is not the one after the last was missed
        self.ticks = 0
        self._sum = 0.0
        self._count = 0
        self._error = np.zeros(len(command))
        self._last_tick: int | None = None
        self._spoiled = False
        self._repeats = 0

    def apply(self) -> None:
        super().apply()
        self.ticks += 1
        if self.clock is not None:
            tick = self.clock.tick
            if self._last_tick is not None and tick != self._last_tick + 1:
                self._spoiled = True
            self._last_tick = tick
        measured = self.tracking.update(self.command.position, self.state.position, self._error)
        if self.ticks <= self.settle or self.learner.done or not measured:
            self._spoiled = False  # (the first window starts clean)
            return
        self._sum += float(np.dot(self._error, self._error))
        self._count += len(self._error)
        if self._count >= self.window * len(self._error):
            rms = math.sqrt(self._sum / self._count)
            self._sum, self._count = 0.0, 0
            if self._spoiled and self._repeats < self.MAX_REPEATS:
                self._repeats += 1
                self.learner.repeated += 1
            else:
                self._repeats = 0
                self.set_gains(self.learner.window(rms))
            self._spoiled = False
