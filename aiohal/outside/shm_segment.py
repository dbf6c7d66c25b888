"""The shared-memory segment of a robot: its byte layout, made by the loop's door
(:mod:`.shm_door`) and mapped by another process's client (:mod:`aiohal.client`).

One ``multiprocessing.shared_memory`` segment per robot, named ``aiohal.<robot>``, holds:

- the latest state (joint state and command, faults, modes, IMU and force/torque values, the
  tick, its time and the safety level) under a **seqlock**: the tick makes the sequence odd,
  copies, makes it even; a reader copies between two reads of the sequence and retries when
  they differ or are odd. The tick never waits for a reader and makes no syscall for one (the
  pages are touched once when the segment is made);
- a **setpoint ring**: single producer (the client that holds the command lock), single
  consumer (the ``stream`` controller in the tick). Each side owns its index, on its own cache
  line; the producer fills a slot, then moves ``head``; the consumer reads, then moves
  ``tail``. Neither takes a lock;
- **safety requests** (hold, estop, reset faults, rearm): counters a client increments; the
  tick compares them with the last values it acted on (one read of each per tick), acts, and
  leaves an **answer** per kind (granted or refused, and the loop's reason) for the client. A
  reset or rearm carries the last moment the loop may act on it (the client's wait, on the
  host's monotonic clock): a loop that was frozen longer refuses it rather than move a robot
  whose client was told the request went unanswered.

The ordering the seqlock and the ring rely on (stores seen in program order by another core)
is the x86-64 memory model's; docs/client.md gives the byte layout and this caveat.
"""

from __future__ import annotations

import json
import logging
import os
import re
import stat
from multiprocessing import resource_tracker, shared_memory
from pathlib import Path
from typing import Any, cast

import numpy as np

from ..errors import AiohalError
from ..robot import JOINT_COMMAND_FIELDS, JOINT_STATE_FIELDS

log = logging.getLogger(__name__)

MAGIC = 0x314C4148_4F494100  # b"\x00AIOHAL1" read as a little-endian int64
VERSION = 3
LINE = 64  # bytes: each side's counters on a cache line of their own

# header line 0: identity and shape (written once, before STATUS becomes ACTIVE)
H_MAGIC, H_VERSION, H_PID, H_STATUS, H_DOF, H_PERIOD_NS, H_CAPACITY, H_META_LEN = range(8)
H_N_IMU, H_N_FT, H_CAN_REARM, H_SIZE = 8, 9, 10, 11
HEADER_WORDS = 16  # two lines
STATUS_STARTING, STATUS_ACTIVE, STATUS_CLOSED = 0, 1, 2
# the seqlock line: SEQ, then the scalars it guards
S_SEQ, S_TICK, S_NOW_NS, S_LEVEL = range(4)
# the request line: counters clients increment, and the counts the loop has acted on
R_HOLD, R_ESTOP, R_REARM, R_HOLD_DONE, R_ESTOP_DONE, R_REARM_DONE, R_RESET, R_RESET_DONE = range(8)
# the line after it: per request that can set the robot moving, the last CLOCK_MONOTONIC ns at
# which the loop may act on it (its client stops waiting a little after)
D_REARM_BY, D_RESET_BY = range(2)
# one answer block per request kind: the count it answers (0 while the loop writes it),
# refused (0 or 1), the reason's length in bytes, then the reason (UTF-8, cut to fit)
A_HOLD, A_ESTOP, A_REARM, A_RESET = range(4)
A_COUNT, A_REFUSED, A_LEN = range(3)
ANSWER_SIZE = 256
ANSWER_TEXT = ANSWER_SIZE - 3 * 8
# the ring's two lines: the producer's and the consumer's
P_HEAD = 0
C_TAIL, C_APPLIED, C_REFUSED, C_STREAMING, C_FINISHED = range(5)
# one ring slot: four int64 then position[n] and velocity[n]
SLOT_T_NS, SLOT_SENT_NS, SLOT_FLAGS = 0, 1, 2
SLOT_WORDS_HEAD = 4
FLAG_VELOCITY = 1  # the point carries velocities (cubic Hermite between two such points)
FLAG_FINAL = 2  # the stream ends here: hold this point at rest, no underrun

_NAME_OK = re.compile(r"^[A-Za-z0-9_.-]{1,200}$")


class ShmError(AiohalError, RuntimeError):
    """Base of the shared-memory door's errors."""


class RobotNotRunning(ShmError):
    """No live loop serves this robot's segment."""


class SegmentBusy(ShmError):
    """Another live process already serves a robot of this name."""


#: where Linux keeps POSIX shared memory
SHM_DIR = Path("/dev/shm")


def segment_name(robot: str) -> str:
    if not _NAME_OK.match(robot):
        raise ShmError(
            f"robot name {robot!r} cannot name a shared-memory segment (letters, digits, '_', '.', '-' only)"
        )
    return f"aiohal.{robot}"


def _round(n: int) -> int:
    return (n + LINE - 1) // LINE * LINE


def _buf(shm: shared_memory.SharedMemory) -> memoryview:
    """The mapping of an open segment (the stubs allow None, which only a closed one has)."""
    return cast(memoryview, shm.buf)


def pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, someone else's
        return True
    return True


class Layout:
    """Byte offsets of every part of a segment, from its shape (both sides compute the same)."""

    def __init__(self, dof: int, n_imu: int, n_ft: int, capacity: int, meta_len: int) -> None:
        self.dof, self.n_imu, self.n_ft, self.capacity, self.meta_len = dof, n_imu, n_ft, capacity, meta_len
        n_state, n_cmd = len(JOINT_STATE_FIELDS), len(JOINT_COMMAND_FIELDS)
        at = 0
        self.header = at
        at += HEADER_WORDS * 8
        self.seqlock = at
        at += LINE
        self.requests = at
        at += LINE
        self.act_by = at
        at += LINE
        self.producer = at
        at += LINE
        self.consumer = at
        at += LINE
        self.answers = at
        at += 4 * ANSWER_SIZE
        self.meta = at
        at += _round(meta_len)
        # the state payload the seqlock guards: each array on a line of its own
        self.state = at
        at += _round(n_state * dof * 8)
        self.command = at
        at += _round(n_cmd * dof * 8)
        self.fault = at
        at += _round(dof * 4)
        self.mode = at
        at += _round(dof)
        self.imu = at
        at += _round(n_imu * 10 * 8)
        self.ft = at
        at += _round(n_ft * 6 * 8)
        self.slot_words = SLOT_WORDS_HEAD + 2 * dof
        self.slot_size = _round(self.slot_words * 8)
        self.ring = at
        at += capacity * self.slot_size
        self.size = at


class Segment:
    """A mapped segment with numpy views of its parts (either side)."""

    def __init__(self, shm: shared_memory.SharedMemory, layout: Layout, owner: bool) -> None:
        self.shm, self.layout, self.owner = shm, layout, owner
        buf, L = _buf(shm), layout
        n = L.dof

        def words(offset: int, count: int) -> np.ndarray:
            return np.frombuffer(buf, np.int64, count, offset)

        self.header = words(L.header, HEADER_WORDS)
        self.seqlock = words(L.seqlock, 8)
        self.requests = words(L.requests, 8)
        self.act_by = words(L.act_by, 8)
        self.producer = words(L.producer, 8)
        self.consumer = words(L.consumer, 8)
        answers = np.frombuffer(buf, np.uint8, 4 * ANSWER_SIZE, L.answers).reshape(4, ANSWER_SIZE)
        #: per request kind: the answer's words and its reason's bytes
        self.answer_words = [answers[i, : 3 * 8].view(np.int64) for i in range(4)]
        self.answer_text = [answers[i, 3 * 8 :] for i in range(4)]
        self.state = np.frombuffer(buf, np.float64, len(JOINT_STATE_FIELDS) * n, L.state).reshape(-1, n)
        self.command = np.frombuffer(buf, np.float64, len(JOINT_COMMAND_FIELDS) * n, L.command).reshape(-1, n)
        self.fault = np.frombuffer(buf, np.uint32, n, L.fault)
        self.mode = np.frombuffer(buf, np.int8, n, L.mode)
        self.imu = np.frombuffer(buf, np.float64, L.n_imu * 10, L.imu).reshape(L.n_imu, 10)
        self.ft = np.frombuffer(buf, np.float64, L.n_ft * 6, L.ft).reshape(L.n_ft, 6)
        ring = np.frombuffer(buf, np.uint8, L.capacity * L.slot_size, L.ring).reshape(L.capacity, L.slot_size)
        #: per slot: the int64 head words, the positions and the velocities
        self.slot_words = [ring[i, : SLOT_WORDS_HEAD * 8].view(np.int64) for i in range(L.capacity)]
        self.slot_position = [
            ring[i, SLOT_WORDS_HEAD * 8 : (SLOT_WORDS_HEAD + n) * 8].view(np.float64) for i in range(L.capacity)
        ]
        self.slot_velocity = [
            ring[i, (SLOT_WORDS_HEAD + n) * 8 : (SLOT_WORDS_HEAD + 2 * n) * 8].view(np.float64)
            for i in range(L.capacity)
        ]

    @property
    def name(self) -> str:
        return self.shm.name

    def meta(self) -> dict[str, Any]:
        L = self.layout
        return json.loads(bytes(_buf(self.shm)[L.meta : L.meta + L.meta_len]).decode())

    def release(self) -> None:
        """Drop every view, then unmap (the views would keep the buffer exported)."""
        for attr in (
            "header",
            "seqlock",
            "requests",
            "act_by",
            "producer",
            "consumer",
            "answer_words",
            "answer_text",
            "state",
            "command",
            "fault",
            "mode",
            "imu",
            "ft",
            "slot_words",
            "slot_position",
            "slot_velocity",
        ):
            setattr(self, attr, None)
        try:
            self.shm.close()
        except BufferError:  # a caller still holds a view; the mapping goes with the process
            log.warning("shared memory %s still has views; left mapped", self.shm.name)


def create_segment(
    robot: str, meta: dict[str, Any], *, dof: int, n_imu: int, n_ft: int, capacity: int, period_ns: int, can_rearm: bool
) -> Segment:
    """Make the robot's segment; one left by a process that is gone is replaced."""
    name = segment_name(robot)
    blob = json.dumps(meta).encode()
    layout = Layout(dof, n_imu, n_ft, capacity, len(blob))
    try:
        try:
            shm = shared_memory.SharedMemory(name, create=True, size=layout.size)
        except FileExistsError:
            _remove_stale(name, robot)
            shm = shared_memory.SharedMemory(name, create=True, size=layout.size)
    except OSError as exc:
        raise ShmError(f"robot {robot!r}: cannot make shared memory /dev/shm/{name}: {exc.strerror or exc}") from None
    _buf(shm)[: layout.size] = bytes(layout.size)  # touch every page now, not in the tick
    _buf(shm)[layout.meta : layout.meta + len(blob)] = blob
    seg = Segment(shm, layout, owner=True)
    h = seg.header
    h[H_VERSION], h[H_PID], h[H_STATUS], h[H_DOF] = VERSION, os.getpid(), STATUS_STARTING, dof
    h[H_PERIOD_NS], h[H_CAPACITY], h[H_META_LEN] = period_ns, capacity, len(blob)
    h[H_N_IMU], h[H_N_FT], h[H_CAN_REARM], h[H_SIZE] = n_imu, n_ft, int(can_rearm), layout.size
    h[H_MAGIC] = MAGIC  # last: a reader that sees the magic sees the shape
    return seg


def _remove_stale(name: str, robot: str) -> None:
    """Remove a segment of this name that an aiohal process left when it ended; anything else
    at that name (a link, another program's file, a segment still served) is left alone."""
    path = SHM_DIR / name
    try:
        st = path.lstat()
    except FileNotFoundError:
        return  # gone meanwhile
    if not stat.S_ISREG(st.st_mode):
        raise ShmError(f"robot {robot!r}: {path} exists and is not a shared-memory segment (a link?); remove it")
    old = shared_memory.SharedMemory(name)
    try:
        words = np.frombuffer(_buf(old), np.int64, HEADER_WORDS) if old.size >= HEADER_WORDS * 8 else None
        if words is None or words[H_MAGIC] != MAGIC:
            del words
            raise ShmError(
                f"robot {robot!r}: {path} exists and is not an aiohal segment (or one whose making was "
                "cut short); it is left alone: remove it, or name the robot otherwise"
            )
        pid, status = int(words[H_PID]), int(words[H_STATUS])
        del words
        if pid_alive(pid) and status != STATUS_CLOSED:
            if pid != os.getpid():
                _untrack(old)
            raise SegmentBusy(f"robot {robot!r} is already served by process {pid} (shared memory /{name})")
        log.warning("replacing shared memory /%s left by process %d, which is gone", name, pid)
        old.unlink()
    finally:
        old.close()


def attach_segment(robot: str) -> Segment:
    """Map a running robot's segment (the client's side); RobotNotRunning if there is none."""
    name = segment_name(robot)
    try:
        shm = shared_memory.SharedMemory(name)
    except FileNotFoundError:
        raise RobotNotRunning(
            f"robot {robot!r} is not running: no shared memory /{name} (is the loop up with [client] shm = true?)"
        ) from None
    words = np.frombuffer(_buf(shm), np.int64, HEADER_WORDS) if shm.size >= HEADER_WORDS * 8 else None
    try:
        if words is None or words[H_MAGIC] != MAGIC:
            raise RobotNotRunning(f"robot {robot!r} is not running: /{name} is not ready or not an aiohal segment")
        if words[H_VERSION] != VERSION:
            raise ShmError(f"/{name} has layout version {int(words[H_VERSION])}, this client reads {VERSION}")
        pid, status = int(words[H_PID]), int(words[H_STATUS])
        if status == STATUS_CLOSED or not pid_alive(pid):
            raise RobotNotRunning(
                f"robot {robot!r} is not running: /{name} was left by process {pid}, "
                + ("which closed it" if status == STATUS_CLOSED else "which is gone")
            )
        layout = Layout(
            int(words[H_DOF]), int(words[H_N_IMU]), int(words[H_N_FT]), int(words[H_CAPACITY]), int(words[H_META_LEN])
        )
    except BaseException:
        del words
        shm.close()
        raise
    del words
    if pid != os.getpid():
        _untrack(shm)
    return Segment(shm, layout, owner=False)


def _untrack(shm: shared_memory.SharedMemory) -> None:
    """Python < 3.13 registers a segment it attaches to with this process's resource tracker,
    which would unlink it when this process ends: the robot's, not ours to remove."""
    try:
        # _name: the name as the tracker registered it (with its leading slash); not in the stubs
        resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
    except Exception:
        pass
