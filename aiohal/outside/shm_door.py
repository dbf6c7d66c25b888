"""The loop's side of the shared-memory door (``[client] shm``): it makes the robot's segment
(:mod:`.shm_segment`), publishes the state into it at the end of every tick, answers the safety
requests a client leaves there, and hands the setpoint ring to the ``stream`` controller."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from ..robot import JOINT_COMMAND_FIELDS, JOINT_STATE_FIELDS
from ..safety import SafetyRequestExpired, SafetyRequestRefused
from .port import LoopPort
from .shm_segment import (
    A_COUNT,
    A_ESTOP,
    A_HOLD,
    A_LEN,
    A_REARM,
    A_REFUSED,
    A_RESET,
    ANSWER_TEXT,
    D_REARM_BY,
    D_RESET_BY,
    H_STATUS,
    R_ESTOP,
    R_ESTOP_DONE,
    R_HOLD,
    R_HOLD_DONE,
    R_REARM,
    R_REARM_DONE,
    R_RESET,
    R_RESET_DONE,
    S_LEVEL,
    S_NOW_NS,
    S_SEQ,
    S_TICK,
    STATUS_ACTIVE,
    STATUS_CLOSED,
    create_segment,
)

log = logging.getLogger(__name__)


class ShmDoor:
    """The loop's side: makes the segment, publishes state at the end of every tick, acts on
    safety requests, and hands the setpoint ring to the ``stream`` controller."""

    def __init__(self, port: LoopPort, capacity: int) -> None:
        robot = port.robot
        self.port = port
        self.robot_name = robot.name
        meta = {
            "robot": robot.name,
            "joints": list(robot.joint_names),
            "position_min": robot.position_min.tolist(),
            "position_max": robot.position_max.tolist(),
            "velocity": robot.velocity_limit.tolist(),
            "state_rows": list(JOINT_STATE_FIELDS),
            "command_rows": list(JOINT_COMMAND_FIELDS),
            "imu": list(robot.imu.names),
            "force_torque": list(robot.force_torque.names),
        }
        self.segment = create_segment(
            robot.name,
            _finite_json(meta),
            dof=robot.dof,
            n_imu=len(robot.imu),
            n_ft=len(robot.force_torque),
            capacity=capacity,
            period_ns=port.period_ns,
            can_rearm=True,
        )
        self.requests_acted = 0
        self.requests_expired = 0  # resets and rearms read too late to answer their client
        self.publish = self._make_publisher()
        _DOORS[robot.name] = self

    def activate(self) -> None:
        self.segment.header[H_STATUS] = STATUS_ACTIVE

    def _make_publisher(self):
        """The per-tick closure: byte copies between memoryviews (cheapest on cold caches),
        sequence stores as single aligned int64 stores, no allocation of arrays, no syscall."""
        seg, robot, port = self.segment, self.port.robot, self.port
        seq = memoryview(seg.seqlock).cast("B").cast("q")
        req = memoryview(seg.requests).cast("B").cast("q")
        pairs = [
            (memoryview(dst).cast("B"), memoryview(src).cast("B"))
            for dst, src in (
                (seg.state, robot.state.block),
                (seg.command, robot.command.block),
                (seg.fault, robot.state.fault),
                (seg.mode, robot.command.mode),
                (seg.imu, robot.imu.values),
                (seg.ft, robot.force_torque.values),
            )
            if src is not None and src.size
        ]
        (d_state, s_state), (d_cmd, s_cmd), (d_fault, s_fault), (d_mode, s_mode) = pairs[:4]
        devices = pairs[4:]
        # released at close: a memoryview left over the segment would keep it mapped
        self._views = [seq, req, *(v for pair in pairs for v in pair)]
        clock = robot.clock
        counter = [0]  # the sequence, kept here: the tick never reads it back from the segment
        seen = [0, 0, 0, 0]  # per answer kind (A_HOLD, A_ESTOP, A_REARM, A_RESET)

        def publish(_: object) -> None:
            s = counter[0] + 1
            seq[S_SEQ] = s  # odd: writing
            seq[S_TICK] = clock.tick
            seq[S_NOW_NS] = clock.now_ns
            seq[S_LEVEL] = port.level
            d_state[:] = s_state
            d_cmd[:] = s_cmd
            d_fault[:] = s_fault
            d_mode[:] = s_mode
            for d, src in devices:
                d[:] = src
            seq[S_SEQ] = s + 1  # even: consistent
            counter[0] = s + 1
            if (
                req[R_HOLD] != seen[A_HOLD]
                or req[R_ESTOP] != seen[A_ESTOP]
                or req[R_REARM] != seen[A_REARM]
                or req[R_RESET] != seen[A_RESET]
            ):
                self._act(req, seen)

        return publish

    def _act(self, req: memoryview, seen: list[int]) -> None:
        """A client asked for a safety change (rare: off the per-tick path). Each request gets
        an answer (granted, or refused with the loop's reason) before its acted-on count moves,
        so a client that sees the count reads the answer; the next tick's snapshot shows the
        new level. The most protective request goes first."""
        port, cause = self.port, "requested by a shared-memory client"
        actions = (
            (A_ESTOP, R_ESTOP, R_ESTOP_DONE, "estop", lambda: port.estop(cause, source="client")),
            (A_HOLD, R_HOLD, R_HOLD_DONE, "hold", lambda: port.hold(cause)),
            (
                A_RESET,
                R_RESET,
                R_RESET_DONE,
                "reset_faults",
                lambda: port.reset_faults(source="client", act_by_ns=self._act_by(D_RESET_BY)),
            ),
            (
                A_REARM,
                R_REARM,
                R_REARM_DONE,
                "rearm",
                lambda: port.rearm(source="client", act_by_ns=self._act_by(D_REARM_BY)),
            ),
        )
        for kind, ask, done, what, action in actions:
            count = req[ask]
            if count == seen[kind]:
                continue
            seen[kind] = count
            (log.warning if kind == A_ESTOP else log.info)(
                "robot %s: %s requested by a shared-memory client", self.robot_name, what
            )
            refused, reason = False, ""
            try:
                action()
            except SafetyRequestExpired as exc:
                self.requests_expired += 1
                refused, reason = True, str(exc)
            except SafetyRequestRefused as exc:
                refused, reason = True, str(exc)
            except Exception as exc:  # whatever goes wrong with a request must not end the tick
                refused, reason = True, f"{type(exc).__name__}: {exc}"
                log.exception("robot %s: a shared-memory client's %s failed", self.robot_name, what)
            if refused:
                log.warning("robot %s: a shared-memory client's %s refused: %s", self.robot_name, what, reason)
            self._answer(kind, count, refused, reason)
            req[done] = count
        self.requests_acted += 1

    def _act_by(self, line: int) -> int:
        """The moment the client stops waiting for this request's answer (it writes it first)."""
        return int(self.segment.act_by[line])

    def _answer(self, kind: int, count: int, refused: bool, reason: str) -> None:
        """Write one answer under its count: 0 while writing, so a reader never keeps a torn one."""
        words, text = self.segment.answer_words[kind], self.segment.answer_text[kind]
        data = reason.encode()[:ANSWER_TEXT]
        words[A_COUNT] = 0
        words[A_REFUSED] = int(refused)
        words[A_LEN] = len(data)
        text[: len(data)] = np.frombuffer(data, np.uint8)
        words[A_COUNT] = count

    def close(self) -> None:
        """Mark the segment closed (attached clients see it at once) and remove it."""
        if _DOORS.get(self.robot_name) is self:
            del _DOORS[self.robot_name]
        seg = self.segment
        if seg.header is None:
            return
        seg.header[H_STATUS] = STATUS_CLOSED
        self.publish = None
        for view in self._views:
            view.release()
        self._views = []
        try:
            seg.shm.unlink()
        except FileNotFoundError:
            pass
        seg.release()


_DOORS: dict[str, ShmDoor] = {}


def door(robot: str) -> ShmDoor | None:
    """The open door of a robot in this process (the ``stream`` controller finds its ring here)."""
    return _DOORS.get(robot)


def _finite_json(meta: dict[str, Any]) -> dict[str, Any]:
    """JSON has no inf: an absent limit is written as null."""

    def fix(v: Any) -> Any:
        if isinstance(v, float) and not np.isfinite(v):
            return None
        if isinstance(v, list):
            return [fix(x) for x in v]
        return v

    return {k: fix(v) for k, v in meta.items()}
