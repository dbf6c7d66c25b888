"""Joint servo models for simulated bus devices (joint boards, a KUKA controller).

Two, with one interface (``command``, ``stop``, ``step``; ``position``, ``velocity``,
``effort``, ``mode`` arrays), chosen by a simulator's ``dynamics`` (:func:`joint_model`):

* ``"first_order"``, :class:`ServoModel`: no physics; each joint's position servo tracks a
  target that moves on with the commanded velocity, and the tracking error decays with a time
  constant. The step is exact for any time step (error × exp(-dt/τ)), so a simulator can
  advance whenever a datagram comes and stays stable however late it is. Every joint in one
  set of array operations.
* ``"servo"``, :class:`CascadeServoModel`: each joint behind the servo drive every simulated
  drive shares (:mod:`aiohal.simulation.servo`, compiled with numba, loaded only for this model).
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

import numpy as np

from aiohal.robot import Mode

if TYPE_CHECKING:
    from aiohal.simulation.servo import ServoParams


class ServoModel:
    """``n`` joints: ``position``, ``velocity``, ``effort`` measured; targets set by ``command``."""

    def __init__(self, n: int, time_constant: float = 0.005, initial: np.ndarray | None = None) -> None:
        self.n = n
        self.time_constant = time_constant
        self.position = np.zeros(n) if initial is None else np.array(initial, dtype=np.float64)
        self.velocity = np.zeros(n)
        self.effort = np.zeros(n)
        self.target = self.position.copy()  # where the servo wants the joint now
        self.target_velocity = np.zeros(n)
        self.command_effort = np.zeros(n)
        self.stiffness = np.zeros(n)
        self.damping = np.zeros(n)
        self.mode = np.zeros(n, dtype=np.uint8)  # Mode values; NONE holds where it stands
        self._previous = np.zeros(n)

    def command(self, rows: slice | np.ndarray, mode, position, velocity, effort, stiffness=0.0, damping=0.0) -> None:
        """New targets for ``rows``: a position target restarts from the commanded position."""
        self.mode[rows] = mode
        self.target[rows] = np.where(self._tracks(mode), position, self.position[rows])
        self.target_velocity[rows] = np.where(np.asarray(mode) == Mode.EFFORT, 0.0, velocity)
        self.command_effort[rows] = effort
        self.stiffness[rows] = stiffness
        self.damping[rows] = damping

    @staticmethod
    def _tracks(mode) -> np.ndarray:
        mode = np.asarray(mode)
        return (mode == Mode.POSITION) | (mode == Mode.IMPEDANCE)

    def stop(self, rows: slice | np.ndarray = slice(None)) -> None:
        """Brake where the joints stand (mode NONE)."""
        self.mode[rows] = Mode.NONE
        self.target[rows] = self.position[rows]
        self.target_velocity[rows] = 0.0

    def step(self, dt: float) -> None:
        """Advance every joint by ``dt`` seconds."""
        if dt <= 0.0:
            return
        moving = (self.mode != Mode.NONE) & (self.mode != Mode.EFFORT)
        np.copyto(self._previous, self.position)
        # the error to the target decays while the target moves on with the commanded velocity
        error = (self.position - self.target) * np.exp(-dt / self.time_constant)
        self.target += np.where(moving, self.target_velocity, 0.0) * dt
        velocity_mode = self.mode == Mode.VELOCITY
        self.position = np.where(velocity_mode, self.target, np.where(moving, self.target + error, self.position))
        self.target = np.where(moving, self.target, self.position)
        np.subtract(self.position, self._previous, out=self.velocity)
        self.velocity /= dt
        self.effort = (
            self.command_effort + self.stiffness * (self.target - self.position) - self.damping * self.velocity
        )


class CascadeServoModel:
    """``n`` joints behind simulated servo drives (:mod:`aiohal.simulation.servo`: LOLA's cascade with the
    motor, gear, friction and load), with :class:`ServoModel`'s interface.

    The command's mode picks the drive's loop, as a CiA 402 drive's mode does:

    * POSITION and IMPEDANCE: the whole cascade on the command's position, its velocity as
      velocity feed-forward and its effort as torque feed-forward. Impedance has no stiffness
      or damping of its own here: the drive's position loop stands in for the stiffness;
    * VELOCITY: the velocity and current loops on the command's velocity (effort as torque
      feed-forward);
    * EFFORT: the current loop alone on the command's effort;
    * NONE (and :meth:`stop`): the position loop holds the joint where it stood when it
      stopped, without feed-forward.

    Measured: position, velocity and the motor's torque at the joint (``effort``). A position
    target is reached at the end of the first :meth:`step` after the command: the drive ramps
    from the previous target to it over that step. A simulator that steps several times
    between commands thus ramps over the first step and holds the target over the others (the
    target arrives up to one command interval early); one that steps once per command (the
    KRC) ramps over the whole interval, as a drive interpolating over its bus cycle. A step is
    capped at ``max_step`` seconds: a simulator that was held up (a stall, a debugger) does
    not spend as long catching up; the joints lose the time beyond it.
    """

    max_step = 0.1  # s: FRI's longest cycle

    def __init__(self, n: int, params: ServoParams | list[ServoParams] | None = None, initial=None) -> None:
        from aiohal.simulation import servo as sv  # numba: only the simulators that run this model load it

        self._sv = sv
        self.n = n
        self.position = np.zeros(n) if initial is None else np.array(initial, dtype=np.float64)
        self.velocity = np.zeros(n)
        self.effort = np.zeros(n)
        self.mode = np.zeros(n, dtype=np.uint8)  # Mode values, as commanded
        self.bank = sv.ServoBank(params if params is not None else sv.ServoParams(), self.position)
        self._torque_per_amp = self.bank.params[:, sv.KT] * self.bank.params[:, sv.GEAR]
        self._holding = np.ones(n, dtype=bool)  # in NONE: the drive holds where the joint stopped
        self.bank.measure(self.position, self.velocity, self.effort)

    def command(self, rows: slice | np.ndarray, mode, position, velocity, effort, stiffness=0.0, damping=0.0) -> None:
        """New targets for ``rows`` (stiffness and damping: see the class's docstring)."""
        sv, s = self._sv, self.bank.state
        self.mode[rows] = mode
        mode = self.mode[rows]
        tracks = (mode == Mode.POSITION) | (mode == Mode.IMPEDANCE)
        speed = mode == Mode.VELOCITY
        torque = mode == Mode.EFFORT
        hold = ~(tracks | speed | torque)  # NONE, or a mode no loop takes
        here = self.position[rows]
        loop = np.where(speed, sv.VELOCITY_LOOP, np.where(torque, sv.CURRENT_LOOP, sv.POSITION_LOOP))
        stops = hold & ~self._holding[rows]
        # the position loop's ramp starts where the joint is when it comes back to it
        restart = ((loop == sv.POSITION_LOOP) & (s[rows, sv.LOOP] != sv.POSITION_LOOP)) | stops
        target = np.where(tracks, position, np.where(hold & ~stops, s[rows, sv.TARGET], here))
        restarting = np.flatnonzero(restart)
        if len(restarting):
            picked = np.arange(self.n)[rows][restarting]
            self.bank.restart(picked, self.position[picked])
        s[rows, sv.TARGET] = target
        s[rows, sv.VEL_FF] = np.where(tracks | speed, velocity, 0.0)
        s[rows, sv.CUR_FF] = np.where(hold, 0.0, effort) / self._torque_per_amp[rows]
        s[rows, sv.LOOP] = loop
        self._holding[rows] = hold

    def stop(self, rows: slice | np.ndarray = slice(None)) -> None:
        """Hold where the joints stand (mode NONE)."""
        sv, s = self._sv, self.bank.state
        self.mode[rows] = Mode.NONE
        self.bank.restart(rows, self.position[rows])
        s[rows, sv.TARGET] = self.position[rows]
        s[rows, sv.VEL_FF] = s[rows, sv.CUR_FF] = 0.0
        s[rows, sv.LOOP] = sv.POSITION_LOOP
        self._holding[rows] = True

    def step(self, dt: float) -> None:
        """Run the drives for ``dt`` seconds (at most ``max_step``; nothing for dt <= 0)."""
        if not dt > 0.0:
            return
        self.bank.step(min(dt, self.max_step))
        self.bank.measure(self.position, self.velocity, self.effort)


def add_dynamics_arguments(parser: argparse.ArgumentParser, time_constant: float) -> None:
    """A simulator's ``--dynamics``, ``--time-constant`` and ``--servo-json``."""
    parser.add_argument("--dynamics", choices=("first_order", "servo"), default="first_order", help="the joints' model")
    parser.add_argument(
        "--time-constant", type=float, default=time_constant, help="first_order: the tracking time constant (s)"
    )
    parser.add_argument(
        "--servo-json", default=None, help="servo: the drives' aiohal.simulation.servo.ServoParams as JSON"
    )


def servo_from_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> ServoParams | None:
    """The ``--servo-json`` parameters (None: the defaults); a wrong one is the parser's error
    (exit 2) naming the fields that are wrong."""
    if args.servo_json is None:
        return None
    if args.dynamics != "servo":
        parser.error("argument --servo-json: only with --dynamics servo")
    import pydantic

    from aiohal.simulation.servo import ServoParams

    try:
        return ServoParams.model_validate_json(args.servo_json)
    except pydantic.ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(x) for x in e['loc']) or 'the value'}: {e['msg'][:1].lower()}{e['msg'][1:]}"
            for e in exc.errors()
        )
        parser.error(f"argument --servo-json: {problems}")


def joint_model(
    dynamics: str, n: int, initial=None, time_constant: float = 0.005, servo: ServoParams | None = None
) -> ServoModel | CascadeServoModel:
    """The joints of a simulated bus device: ``"first_order"`` (:class:`ServoModel`) or
    ``"servo"`` (:class:`CascadeServoModel`)."""
    if dynamics == "first_order":
        return ServoModel(n, time_constant, initial)
    if dynamics == "servo":
        return CascadeServoModel(n, servo, initial)
    raise ValueError(f"dynamics must be 'first_order' or 'servo', not {dynamics!r}")
