"""Attach to a running robot from another process on the same machine: read its state, stream
setpoints to its ``stream`` controller, ask for hold or emergency stop, reset faults and re-arm.

Plain synchronous Python (no asyncio, no event loop)::

    from aiohal.client import RobotClient

    with RobotClient("mock_arm", joints=["a1", "a2"], command=True) as robot:
        state = robot.read()                     # a consistent snapshot
        robot.send(state.position + 0.1, t_ns=state.now_ns + 500_000_000, final=True)
        ...                                      # after an underrun or an emergency stop:
        robot.reset_faults()                     # RequestRefused says why when it cannot
        robot.rearm()

Time stamps are the loop's clock (``State.now_ns``; CLOCK_MONOTONIC on a real clock, the same
as ``time.monotonic_ns()`` here); ``t_ns=0`` means "as soon as possible". Layout and
guarantees: docs/client.md.
"""

from __future__ import annotations

import fcntl
import math
import os
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from .outside import shm_segment
from .outside.shm_segment import RobotNotRunning, ShmError
from .robot import JOINT_COMMAND_FIELDS, JOINT_STATE_FIELDS
from .safety import SafetyLevel

if TYPE_CHECKING:
    from .outside.tick_ring import TickReader

__all__ = [
    "BufferFull",
    "CommandBusy",
    "CommandRequired",
    "JointMismatch",
    "NotStreaming",
    "RequestRefused",
    "RequestTimeout",
    "RobotClient",
    "RobotNotRunning",
    "ShmError",
    "State",
]


class JointMismatch(ShmError, ValueError):
    """The client's joint names are not the robot's."""


class CommandBusy(ShmError):
    """Another process already holds this robot's setpoint ring."""


class NotStreaming(ShmError):
    """No ``stream`` controller consumes setpoints (another controller, hold or emergency stop)."""


class BufferFull(ShmError):
    """The setpoint ring stayed full for the whole timeout."""


class CommandRequired(ShmError, PermissionError):
    """Setpoints, resetting faults and re-arming need a client opened with ``command=True``."""


class RequestRefused(ShmError):
    """The loop refused a safety request; ``reason`` is the loop's own (e.g. a fault not reset)."""

    def __init__(self, robot: str, request: str, reason: str) -> None:
        self.request = request
        self.reason = reason
        super().__init__(f"robot {robot!r} refused {request}: {reason}")


class RequestTimeout(ShmError, TimeoutError):
    """The loop did not answer a safety request in time (it may still act on it later)."""


class State:
    """One consistent snapshot: the tick, its time, the safety level and every array."""

    def __init__(self, dof: int, n_imu: int, n_ft: int) -> None:
        self.tick = -1
        self.now_ns = 0
        self.level = SafetyLevel.OFF
        self.state = np.zeros((len(JOINT_STATE_FIELDS), dof))
        self.command = np.zeros((len(JOINT_COMMAND_FIELDS), dof))
        self.fault = np.zeros(dof, dtype=np.uint32)
        self.mode = np.zeros(dof, dtype=np.int8)
        self.imu = np.zeros((n_imu, 10))
        self.force_torque = np.zeros((n_ft, 6))
        for i, name in enumerate(JOINT_STATE_FIELDS):
            setattr(self, name, self.state[i])
        for i, name in enumerate(JOINT_COMMAND_FIELDS):
            setattr(self, f"command_{name}", self.command[i])

    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    command_position: np.ndarray
    command_velocity: np.ndarray


class RobotClient:
    """A process's handle on a running robot (see the module's docstring)."""

    def __init__(self, robot: str, *, joints: Sequence[str] | None = None, command: bool = False) -> None:
        """``joints``: the names this client was written for, in order; a robot with other
        joints raises :class:`JointMismatch`. ``command``: take the setpoint ring (one process
        at a time; :class:`CommandBusy` otherwise)."""
        self.robot = robot
        self._seg = shm_segment.attach_segment(robot)
        self._lock_fd: int | None = None
        try:
            meta = self._seg.meta()
            self.joint_names: tuple[str, ...] = tuple(meta["joints"])
            if joints is not None and tuple(joints) != self.joint_names:
                raise JointMismatch(_mismatch(robot, list(joints), list(self.joint_names)))
            inf = math.inf
            self.position_min = np.array([-inf if v is None else v for v in meta["position_min"]])
            self.position_max = np.array([inf if v is None else v for v in meta["position_max"]])
            self.imu_names = tuple(meta["imu"])
            self.force_torque_names = tuple(meta["force_torque"])
            if command:
                self._lock_fd = _lock(self._seg.name, robot)
        except BaseException:
            self.close()
            raise
        seg = self._seg
        self.dof = len(self.joint_names)
        self.period_ns = int(seg.header[shm_segment.H_PERIOD_NS])
        self._capacity = seg.layout.capacity
        self._index = {name: i for i, name in enumerate(self.joint_names)}
        self._q = np.zeros(self.dof)
        self._v = np.zeros(self.dof)
        self._ok = np.zeros(self.dof, dtype=bool)

    # ------------------------------------------------------------ state

    def read(self, out: State | None = None, *, timeout_s: float = 0.1) -> State:
        """The latest state, consistent (never half of one tick and half of the next)."""
        seg = self._seg
        self._check_open()
        out = out or State(self.dof, len(self.imu_names), len(self.force_torque_names))
        seq = seg.seqlock
        deadline = None
        while True:
            s1 = int(seq[shm_segment.S_SEQ])
            if not s1 & 1:
                tick, now, level = (
                    int(seq[shm_segment.S_TICK]),
                    int(seq[shm_segment.S_NOW_NS]),
                    int(seq[shm_segment.S_LEVEL]),
                )
                np.copyto(out.state, seg.state)
                np.copyto(out.command, seg.command)
                np.copyto(out.fault, seg.fault)
                np.copyto(out.mode, seg.mode)
                np.copyto(out.imu, seg.imu)
                np.copyto(out.force_torque, seg.ft)
                if int(seq[shm_segment.S_SEQ]) == s1:
                    out.tick, out.now_ns, out.level = tick, now, SafetyLevel(level)
                    return out
            # the tick is writing: it takes microseconds, so spin, within a bound
            now_wall = time.monotonic()
            if deadline is None:
                deadline = now_wall + timeout_s
            elif now_wall > deadline:
                self._check_alive()
                raise ShmError(f"robot {self.robot!r}: no consistent state within {timeout_s:g} s")

    def ticks(self, *, start: int | None = None) -> TickReader:
        """A reader of every tick the loop publishes (the tick ring the recorder and the other
        outputs read): while an output runs, or ShmError. It starts at the newest row (or at
        ``start``); close it when done."""
        from .outside.tick_ring import TickReader

        return TickReader(self.robot, pid=int(self._seg.header[shm_segment.H_PID]), start=start)

    def wait_tick(self, after: int = -1, timeout_s: float = 1.0) -> int:
        """Wait until the robot published a tick later than ``after``; returns it."""
        deadline = time.monotonic() + timeout_s
        seq = self._seg.seqlock
        while True:
            self._check_open()
            tick = int(seq[shm_segment.S_TICK])
            if tick > after and int(seq[shm_segment.S_SEQ]) > 0:
                return tick
            if time.monotonic() > deadline:
                self._check_alive()
                raise RobotNotRunning(f"robot {self.robot!r} published no tick within {timeout_s:g} s")
            time.sleep(self.period_ns / 4e9)

    @property
    def level(self) -> SafetyLevel:
        return SafetyLevel(int(self._seg.seqlock[shm_segment.S_LEVEL]))

    # ------------------------------------------------------------ setpoints

    def send(
        self,
        position: Sequence[float] | Mapping[str, float] | np.ndarray,
        *,
        t_ns: int = 0,
        velocity: Sequence[float] | Mapping[str, float] | np.ndarray | None = None,
        timeout_s: float = 0.0,
        final: bool = False,
    ) -> None:
        """Queue one setpoint for time ``t_ns`` (0: as soon as possible). Every joint is given,
        as an array in the robot's order or a {name: value} map. ``final``: the stream ends at
        this point; the controller holds it at rest, without the underrun fault, until a new
        point comes. Raises ValueError for a value that is not finite or out of range (nothing
        is queued), :class:`NotStreaming` when no stream controller consumes,
        :class:`BufferFull` when the ring stays full."""
        self._require_command("send setpoints")
        self._check_open()
        q = self._vector(position, self._q, "position")
        ok = self._ok
        np.isfinite(q, out=ok)
        if not ok.all():
            raise ValueError(f"position is not finite for {self._names(~ok)}")
        bad = (q < self.position_min) | (q > self.position_max)
        if bad.any():
            raise ValueError(f"position out of range for {self._names(bad)}")
        flags = 0
        if velocity is not None:
            v = self._vector(velocity, self._v, "velocity")
            np.isfinite(v, out=ok)
            if not ok.all():
                raise ValueError(f"velocity is not finite for {self._names(~ok)}")
            flags = shm_segment.FLAG_VELOCITY
        if final:
            flags |= shm_segment.FLAG_FINAL
        seg = self._seg
        if not seg.consumer[shm_segment.C_STREAMING] or self.level < SafetyLevel.RUN:
            raise NotStreaming(
                f"robot {self.robot!r} takes no setpoints: no stream controller is running "
                f"(safety level {self.level.name.lower()})"
            )
        head = int(seg.producer[shm_segment.P_HEAD])
        if head - int(seg.consumer[shm_segment.C_TAIL]) >= self._capacity:
            deadline = time.monotonic() + timeout_s
            while head - int(seg.consumer[shm_segment.C_TAIL]) >= self._capacity:
                if time.monotonic() >= deadline:
                    raise BufferFull(f"robot {self.robot!r}: the setpoint ring ({self._capacity} points) is full")
                time.sleep(self.period_ns / 4e9)
        i = head % self._capacity
        np.copyto(seg.slot_position[i], q)
        if velocity is not None:
            np.copyto(seg.slot_velocity[i], self._v)
        words = seg.slot_words[i]
        words[shm_segment.SLOT_T_NS] = t_ns
        words[shm_segment.SLOT_FLAGS] = flags
        words[shm_segment.SLOT_SENT_NS] = time.monotonic_ns()
        seg.producer[shm_segment.P_HEAD] = head + 1  # last: the slot is complete before the tick can see it

    def send_trajectory(
        self,
        times_ns: Sequence[int],
        positions: np.ndarray,
        velocities: np.ndarray | None = None,
        timeout_s: float = 1.0,
        final: bool = False,
    ) -> None:
        """Queue a trajectory, one point per row, waiting for room up to ``timeout_s`` per point;
        ``final``: the stream ends at the last row (see :meth:`send`)."""
        last = len(times_ns) - 1
        for k, t in enumerate(times_ns):
            self.send(
                positions[k],
                t_ns=int(t),
                velocity=None if velocities is None else velocities[k],
                timeout_s=timeout_s,
                final=final and k == last,
            )

    @property
    def pending(self) -> int:
        """Points queued and not yet taken by the controller."""
        return int(self._seg.producer[shm_segment.P_HEAD]) - int(self._seg.consumer[shm_segment.C_TAIL])

    @property
    def applied(self) -> int:
        return int(self._seg.consumer[shm_segment.C_APPLIED])

    @property
    def refused(self) -> int:
        return int(self._seg.consumer[shm_segment.C_REFUSED])

    @property
    def finished(self) -> bool:
        """The stream reached a final point and holds it; no newer point was taken since."""
        return bool(self._seg.consumer[shm_segment.C_FINISHED])

    # ------------------------------------------------------------ safety requests

    def hold(self, wait_s: float = 1.0) -> None:
        """Ask the loop to replace its controller by ``hold``; waits until it has. Any client
        may ask; a robot already below ``run`` stays where it is (the level says so)."""
        self._request(shm_segment.R_HOLD, shm_segment.R_HOLD_DONE, shm_segment.A_HOLD, wait_s)

    def estop(self, wait_s: float = 1.0) -> None:
        """Ask the loop to trigger every driver's emergency stop; waits until it has. Any
        client may ask."""
        self._request(shm_segment.R_ESTOP, shm_segment.R_ESTOP_DONE, shm_segment.A_ESTOP, wait_s)

    def reset_faults(self, wait_s: float = 1.0) -> None:
        """Ask the loop to clear its latched faults (after an emergency stop: to release it,
        leaving the robot ``disabled``); :meth:`rearm` then lets it move. Needs
        ``command=True``; :class:`RequestRefused` carries the loop's reason when it cannot."""
        self._require_command("reset faults")
        self._check_rearm("reset faults")
        answer = self._request(
            shm_segment.R_RESET, shm_segment.R_RESET_DONE, shm_segment.A_RESET, wait_s, shm_segment.D_RESET_BY
        )
        self._refused_raises("reset_faults", answer)

    def rearm(self, wait_s: float = 1.0) -> None:
        """Ask the loop to return to ``run`` from hold or disabled (the controller restarts
        from where the robot stands). Needs ``command=True``; :class:`RequestRefused`
        carries the loop's reason when it cannot (a fault not reset, hold still braking)."""
        self._require_command("re-arm")
        self._check_rearm("re-arm")
        answer = self._request(
            shm_segment.R_REARM, shm_segment.R_REARM_DONE, shm_segment.A_REARM, wait_s, shm_segment.D_REARM_BY
        )
        self._refused_raises("rearm", answer)

    def _require_command(self, what: str) -> None:
        if self._lock_fd is None:
            raise CommandRequired(
                f"robot {self.robot!r}: to {what} a client takes the setpoint ring: RobotClient(..., command=True)"
            )

    def _check_rearm(self, what: str) -> None:
        self._check_open()
        if not self._seg.header[shm_segment.H_CAN_REARM]:
            raise ShmError(f"robot {self.robot!r}: this loop cannot {what} on request")

    def _refused_raises(self, request: str, answer: tuple[bool, str]) -> None:
        refused, reason = answer
        if refused:
            raise RequestRefused(self.robot, request, reason or "no reason given")

    def _request(self, ask: int, done: int, kind: int, wait_s: float, act_by: int | None = None) -> tuple[bool, str]:
        """Increment the request's counter, wait for the loop to act and return its answer
        (refused, reason); :class:`RequestTimeout` when it does not act within ``wait_s``.
        ``act_by``: the word where a request that sets the robot moving says until when the
        loop may act on it, a margin before this call stops waiting (never acted on later)."""
        self._check_open()
        seg = self._seg  # no view of it in a local: an error's traceback would keep it mapped
        now_ns = time.monotonic_ns()
        if act_by is not None:  # stored before the counter: the loop reads it after seeing the counter move
            seg.act_by[act_by] = now_ns + int(wait_s * 1e9) - _act_margin_ns(wait_s)
        # several clients may ask at once: the loop acts on any change of the counter (and the
        # latest act-by, which a merged request shares)
        target = int(seg.requests[ask]) + 1
        seg.requests[ask] = target
        deadline = now_ns / 1e9 + wait_s
        while int(seg.requests[done]) < target:
            if time.monotonic() > deadline and int(seg.requests[done]) >= target:
                break  # acted on as the wait ended: the answer counts
            self._wait_a_little(deadline, wait_s)
        answer = self._read_answer(kind, target, deadline, wait_s)
        # the tick acted after it published: the next tick's snapshot shows the new level
        self.wait_tick(int(self._seg.seqlock[shm_segment.S_TICK]), max(0.0, deadline - time.monotonic()) + 0.1)
        return answer

    def _read_answer(self, kind: int, target: int, deadline: float, wait_s: float) -> tuple[bool, str]:
        """The answer to our request or a later one of the same kind (they merge). The loop
        writes it under its count (0 while writing): a copy between two equal counts is whole."""
        seg = self._seg
        while True:
            count = int(seg.answer_words[kind][shm_segment.A_COUNT])
            refused = bool(seg.answer_words[kind][shm_segment.A_REFUSED])
            n = min(
                max(int(seg.answer_words[kind][shm_segment.A_LEN]), 0), shm_segment.ANSWER_TEXT
            )  # bounded: from outside
            reason = bytes(seg.answer_text[kind][:n]).decode(errors="replace")
            if count >= target and int(seg.answer_words[kind][shm_segment.A_COUNT]) == count:
                return refused, reason
            self._wait_a_little(deadline, wait_s)

    def _wait_a_little(self, deadline: float, wait_s: float) -> None:
        if time.monotonic() > deadline:
            self._check_alive()
            raise RequestTimeout(f"robot {self.robot!r} did not act on the request within {wait_s:g} s")
        time.sleep(self.period_ns / 4e9)

    # ------------------------------------------------------------ plumbing

    def _vector(self, values, out: np.ndarray, what: str) -> np.ndarray:
        if isinstance(values, Mapping):
            unknown = [k for k in values if k not in self._index]
            if unknown:
                raise JointMismatch(f"{what}: unknown joint(s) {unknown} of robot {self.robot!r}")
            missing = [n for n in self.joint_names if n not in values]
            if missing:
                raise ValueError(f"{what}: every joint needs a value; missing {missing}")
            for name, value in values.items():
                out[self._index[name]] = value
            return out
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape != (self.dof,):
            raise ValueError(
                f"{what}: expected {self.dof} values (joints {list(self.joint_names)}), got shape {arr.shape}"
            )
        np.copyto(out, arr)
        return out

    def _names(self, mask: np.ndarray) -> list[str]:
        return [n for n, m in zip(self.joint_names, mask, strict=True) if m]

    def _check_open(self) -> None:
        if self._seg is None or self._seg.header is None:
            raise ShmError("the client is closed")
        if self._seg.header[shm_segment.H_STATUS] == shm_segment.STATUS_CLOSED:
            raise RobotNotRunning(f"robot {self.robot!r} has stopped (its loop closed the shared memory)")

    def _check_alive(self) -> None:
        self._check_open()
        pid = int(self._seg.header[shm_segment.H_PID])
        if not shm_segment.pid_alive(pid):
            raise RobotNotRunning(f"robot {self.robot!r} is not running: its process {pid} is gone")

    def close(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the command lock
            self._lock_fd = None
        if self._seg is not None:
            self._seg.release()
            # closed: _check_open() says so to whoever asks next
            self._seg = None  # type: ignore[assignment]

    def __enter__(self) -> RobotClient:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _act_margin_ns(wait_s: float) -> int:
    """How long before a client stops waiting the loop must have acted on its reset or rearm:
    the loop writes its answer right after it acts, so a tenth of a second (less for short
    waits) leaves room for a client thread the host is slow to wake."""
    return int(min(0.1, wait_s / 4) * 1e9)


def _lock(name: str, robot: str) -> int:
    """The command lock: an advisory lock on the segment's file, released by the kernel when
    the process ends, so a killed planner never leaves the ring taken."""
    fd = os.open(f"/dev/shm/{name}", os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise CommandBusy(f"robot {robot!r}: another process holds the setpoint ring") from None
    return fd


def _mismatch(robot: str, mine: list[str], theirs: list[str]) -> str:
    extra = [n for n in mine if n not in theirs]
    missing = [n for n in theirs if n not in mine]
    parts = [f"robot {robot!r} has joints {theirs}, the client expects {mine}"]
    if extra:
        parts.append(f"unknown to the robot: {extra}")
    if missing:
        parts.append(f"not named by the client: {missing}")
    if not extra and not missing:
        parts.append("same names in another order")
    return "; ".join(parts)
