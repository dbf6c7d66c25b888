"""The Eclipse Zenoh bridge (``[bridge.zenoh]``, extra ``zenoh``): the robot on the network.

Key expressions, under ``<prefix>/<robot>/`` (prefix ``aiohal`` by default):

==================  ====  ==================================================================
``state``           out   binary, ``state_hz``: header (tick, now_ns, level, dof) + float64
                          rows position, velocity, effort, commanded position (:func:`decode_state`)
``report``          out   JSON every ``report_s``: joints, ticks, missed ticks, level, faults,
                          the bridge's counters
``safety``          out   JSON on every change of the safety level
``faults``          out   JSON, one message per new fault
``cmd/setpoint``    in    JSON ``{"position": {joint: value} | [values], "velocity": ...,
                          "t_ns": int}``, only with ``accept_setpoints`` (through the
                          shared-memory ring: needs ``[client] shm`` and the ``stream`` controller)
``cmd/<request>``   in    ``hold``, ``estop``, ``rearm``: only those named in ``accept_safety``
==================  ====  ==================================================================

The tick only copies a snapshot into a preallocated ring on the ticks that publish (one in
``rate / state_hz``) and compares the level and the fault count; the bridge's own thread
encodes and puts. A command on any other key under ``cmd/``, or one that fails validation
(malformed, unknown joint, not finite, out of range), is refused and counted, never applied.
Zenoh's own access control and authentication (``config_file``) decide who reaches the bridge
at all. ``zenoh`` is imported when the bridge starts, never by the tick core.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import math
import struct
import threading
import time
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ..files import read_regular_text
from ..logutil import RateLimitedLogger
from ..safety import SafetyLevel, SafetyRequestRefused
from .options import ZenohBridgeSection
from .port import LoopPort

if TYPE_CHECKING:
    from ..client import RobotClient

log = logging.getLogger(__name__)

STATE_HEADER = struct.Struct("<qqii")  # tick, now_ns, safety level, dof
STATE_ROWS = ("position", "velocity", "effort", "command_position")
SAFETY_REQUESTS = ("hold", "estop", "rearm")


def decode_state(payload: bytes) -> dict[str, Any]:
    """A ``state`` message as {tick, now_ns, level, position, velocity, effort, command_position}."""
    tick, now_ns, level, dof = STATE_HEADER.unpack_from(payload)
    rows = np.frombuffer(payload, np.float64, len(STATE_ROWS) * dof, STATE_HEADER.size).reshape(-1, dof)
    out: dict[str, Any] = {"tick": tick, "now_ns": now_ns, "level": SafetyLevel(level).name.lower()}
    out.update(zip(STATE_ROWS, rows, strict=True))
    return out


def zenoh_config(section: ZenohBridgeSection):
    """The session's config: the file if one is named, then the section's keys over it."""
    import zenoh

    if section.config_file:  # read here, a regular file only: zenoh's own reader would wait on a FIFO
        config = zenoh.Config.from_json5(read_regular_text(section.config_file, "bridge.zenoh.config_file"))
    else:
        config = zenoh.Config()
    config.insert_json5("mode", json.dumps(section.mode))
    if section.listen:
        config.insert_json5("listen/endpoints", json.dumps(section.listen))
    if section.connect:
        config.insert_json5("connect/endpoints", json.dumps(section.connect))
    config.insert_json5("scouting/multicast/enabled", json.dumps(section.multicast_scouting))
    return config


class ZenohBridge:
    """Made with the loop (nothing opened), started when the loop is active, closed with it."""

    def __init__(self, port: LoopPort, section: ZenohBridgeSection) -> None:
        self.port = port
        self.section = section
        robot = port.robot
        self.base = f"{section.prefix}/{robot.name}"
        self.dof = robot.dof
        rate = 1e9 / port.period_ns
        self.every = max(1, round(rate / section.state_hz))
        q = section.queue
        self._ticks = np.zeros((q, 3), dtype=np.int64)  # tick, now_ns, level
        self._rows = np.zeros((q, len(STATE_ROWS), robot.dof))
        self._head = 0  # snapshots written by the tick (the thread reads it; the GIL orders them)
        self._events: collections.deque = collections.deque()
        self.counters = {
            "state_sent": 0,
            "state_dropped": 0,
            "setpoints_accepted": 0,
            "requests_accepted": 0,
            "refused": 0,
        }
        self.refused_by_reason: dict[str, int] = collections.Counter()
        self._warn = RateLimitedLogger(log)
        self._session: Any = None  # a zenoh.Session (zenoh ships no types)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._client: RobotClient | None = None
        self._aio: asyncio.AbstractEventLoop | None = None
        self._lock = threading.Lock()  # the zenoh callbacks' counters and the shm client
        self.publish = self._make_publisher()

    # ------------------------------------------------------------ the tick's side

    def _make_publisher(self):
        port, robot = self.port, self.port.robot
        state_rows = memoryview(robot.state.block[:3]).cast("B")  # position, velocity, effort: adjacent
        command_position = memoryview(robot.command.position).cast("B")
        cut = 3 * robot.dof * 8
        rows = [
            (memoryview(self._rows[i]).cast("B")[:cut], memoryview(self._rows[i]).cast("B")[cut:])
            for i in range(self.section.queue)
        ]
        ticks = [memoryview(self._ticks[i]) for i in range(self.section.queue)]
        queue, every, clock, faults = self.section.queue, self.every, robot.clock, port.faults
        events = self._events
        due = [0]
        last = [int(port.level), len(faults)]

        def publish(_: object) -> None:
            level = port.level
            if level != last[0] or len(faults) != last[1]:
                events.append((int(level), len(faults), clock.tick))  # rare: allocation allowed
                last[0], last[1] = int(level), len(faults)
            k = clock.tick
            if k < due[0]:
                return
            # on the first tick at or after each multiple of ``every``: a skipped tick does not
            # shift the rate
            due[0] = (k // every + 1) * every
            i = self._head % queue
            s, cmd = rows[i]
            s[:] = state_rows
            cmd[:] = command_position
            t = ticks[i]
            t[0] = k
            t[1] = clock.now_ns
            t[2] = level
            self._head += 1

        return publish

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        import zenoh

        section = self.section
        self._aio = asyncio.get_running_loop()
        self._put = zenoh.SampleKind.PUT
        if section.accept_setpoints:
            from ..client import RobotClient

            self._client = RobotClient(self.port.robot.name, command=True)
        self._session = zenoh.open(zenoh_config(section))
        s = self._session
        self._pub_state = s.declare_publisher(f"{self.base}/state")
        self._pub_report = s.declare_publisher(f"{self.base}/report")
        self._pub_safety = s.declare_publisher(f"{self.base}/safety")
        self._pub_faults = s.declare_publisher(f"{self.base}/faults")
        # every key under cmd/ is heard, so that a command on a key not configured is counted
        self._sub = s.declare_subscriber(f"{self.base}/cmd/**", self._on_command)
        self._thread = threading.Thread(target=self._run, name=f"aiohal-zenoh-{self.port.robot.name}", daemon=True)
        self._thread.start()
        log.info(
            "zenoh bridge for %s: publishing under %s/, accepting %s",
            self.port.robot.name,
            self.base,
            ", ".join(self._accepted_keys()) or "no command",
        )

    def _accepted_keys(self) -> list[str]:
        keys = ["cmd/setpoint"] if self.section.accept_setpoints else []
        return keys + [f"cmd/{r}" for r in self.section.accept_safety]

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if self._session is not None:
            try:
                self._session.close()
            except Exception as exc:  # closing must not hide the loop's own shutdown
                log.warning("zenoh session close failed: %s", exc)
            self._session = None
        with self._lock:
            if self._client is not None:
                self._client.close()
                self._client = None

    # ------------------------------------------------------------ the bridge's thread

    def _run(self) -> None:
        section = self.section
        poll_s = min(0.005, 0.5 / section.state_hz)
        next_report = time.monotonic()
        tail = 0
        queue = section.queue
        header = STATE_HEADER
        while not self._stop.wait(poll_s):
            try:
                head = self._head
                if head - tail > queue:  # the thread fell behind: the oldest are overwritten
                    self.counters["state_dropped"] += head - tail - queue
                    tail = head - queue
                while tail < head:
                    i = tail % queue
                    tick, now, level = (int(x) for x in self._ticks[i])
                    self._pub_state.put(header.pack(tick, now, level, self.dof) + self._rows[i].tobytes())
                    tail += 1
                    self.counters["state_sent"] += 1
                while self._events:
                    self._publish_event(*self._events.popleft())
                if time.monotonic() >= next_report:
                    next_report += section.report_s
                    self._pub_report.put(json.dumps(self.report()))
            except Exception as exc:  # the network must never take the robot down
                self._warn.warning("put", "zenoh bridge: %s: %s", type(exc).__name__, exc)

    def _publish_event(self, level: int, n_faults: int, tick: int) -> None:
        self._pub_safety.put(json.dumps({"level": SafetyLevel(level).name.lower(), "tick": tick}))
        for fault in self.port.faults[self._faults_sent : n_faults]:
            self._pub_faults.put(json.dumps(fault.as_dict()))
        self._faults_sent = max(self._faults_sent, n_faults)

    _faults_sent = 0  # faults published so far

    def report(self) -> dict[str, Any]:
        """A light report (no percentiles: they would take the GIL from the tick for milliseconds)."""
        port = self.port
        return {
            "robot": port.robot.name,
            "joints": list(port.robot.joint_names),
            "tick": port.tick,
            "ticks": port.timing.count,
            "missed_ticks": port.missed_ticks,
            "level": port.level.name.lower(),
            "controller": port.controller_type,
            "faults": len(port.faults),
            "bridge": {
                **self.counters,
                "refused_by_reason": dict(self.refused_by_reason),
                "accepting": self._accepted_keys(),
            },
        }

    # ------------------------------------------------------------ commands (zenoh's threads)

    def _on_command(self, sample) -> None:
        key = str(sample.key_expr)
        name = key[len(self.base) + len("/cmd/") :]
        try:
            if sample.kind != self._put:  # a delete carries no command: it must not e-stop
                raise _Refused("not a put")
            payload = sample.payload.to_bytes()
            if name == "setpoint" and self.section.accept_setpoints:
                self._setpoint(payload)
            elif name in SAFETY_REQUESTS and name in self.section.accept_safety:
                self._safety(name)
            else:
                raise _Refused("key not configured")
        except _Refused as exc:
            self._refuse(str(exc), key)
        except Exception as exc:  # a client's error (busy ring, robot in hold) is still a refusal
            self._refuse(type(exc).__name__, key, str(exc))

    def _refuse(self, reason: str, key: str, detail: str = "") -> None:
        with self._lock:
            self.counters["refused"] += 1
            self.refused_by_reason[reason] += 1
        self._warn.warning(f"refused:{reason}", "zenoh bridge refused a command on %s: %s %s", key, reason, detail)

    def _setpoint(self, payload: bytes) -> None:
        try:
            msg = json.loads(payload)
        except (ValueError, UnicodeDecodeError):
            raise _Refused("malformed") from None
        if not isinstance(msg, dict) or "position" not in msg:
            raise _Refused("malformed")
        robot = self.port.robot
        position = self._vector(msg["position"], robot)
        velocity = None if msg.get("velocity") is None else self._vector(msg["velocity"], robot)
        if not np.all((position >= robot.position_min) & (position <= robot.position_max)):
            raise _Refused("out of range")
        t_ns = msg.get("t_ns", 0)
        if not isinstance(t_ns, int) or isinstance(t_ns, bool):
            raise _Refused("malformed")
        with self._lock:
            if self._client is None:
                raise _Refused("bridge closed")
            self._client.send(position, velocity=velocity, t_ns=t_ns)
            self.counters["setpoints_accepted"] += 1

    def _vector(self, value: Any, robot: Any) -> np.ndarray:
        names = robot.joint_names
        if isinstance(value, dict):
            unknown = [k for k in value if k not in names]
            if unknown:
                raise _Refused("unknown joint")
            if len(value) != len(names):
                raise _Refused("missing joint")
            value = [value[n] for n in names]
        if not isinstance(value, list) or len(value) != len(names):
            raise _Refused("malformed")
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise _Refused("malformed")
        if not all(math.isfinite(v) for v in value):
            raise _Refused("not finite")
        return np.array(value, dtype=np.float64)

    def _safety(self, name: str) -> None:
        port = self.port
        request = {
            "hold": lambda: port.hold("requested over zenoh"),
            "estop": lambda: port.estop("requested over zenoh", source="zenoh"),
            "rearm": lambda: port.rearm(source="zenoh"),
        }[name]

        def action() -> None:
            try:
                request()
            except SafetyRequestRefused as exc:  # the safety channel shows the level that stayed
                log.warning("robot %s: %s over zenoh refused: %s", port.robot.name, name, exc)

        log.warning("robot %s: %s requested over zenoh", port.robot.name, name)
        cast(asyncio.AbstractEventLoop, self._aio).call_soon_threadsafe(
            action
        )  # set by start()  # acted on between two ticks, in the loop's thread
        with self._lock:
            self.counters["requests_accepted"] += 1


class _Refused(Exception):
    """A command the bridge does not apply; the message is the reason counted."""
