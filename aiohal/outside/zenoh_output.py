"""The Eclipse Zenoh bridge's process: the robot as a ROS 2 node that nodes running rmw_zenoh
see, list and echo (docs/ros2.md gives the mapping). Started by :mod:`.zenoh` with the loop.

Node ``<namespace>/<node>`` (default ``/<robot>/aiohal``) publishes, in CDR with rmw_zenoh's
attachment: ``joint_states`` (``sensor_msgs/msg/JointState`` at ``state_hz``, from the tick
ring), ``/diagnostics`` (``diagnostic_msgs/msg/DiagnosticArray``: the robot's status every
``report_s`` and each new fault), ``safety_level`` and ``robot`` (``aiohal_msgs``,
transient-local: late joiners get the last one), ``tick_timing`` (``aiohal_msgs/msg/TickTiming``
every ``report_s``). It takes nothing unless ``commands`` names it: ``setpoints`` subscribes to
``joint_trajectory`` (``trajectory_msgs/msg/JointTrajectory``, into the stream controller's
shared-memory ring, as any client); ``estop``, ``hold``, ``reset_faults``, ``rearm`` are
``std_srvs/srv/Trigger`` services, relayed to the loop, which acts between two ticks and
answers with its reason when it refuses. Commands need access control in the Zenoh config
(:mod:`.zenoh_session`). A command that fails its checks is refused and counted, never applied.
"""

from __future__ import annotations

import collections
import concurrent.futures
import functools
import itertools
import json
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from ..logutil import RateLimitedLogger
from ..ros2 import services
from ..safety import SafetyLevel
from . import rmw_zenoh as rmw
from . import ros2_mapping as ros
from . import tick_ring as R
from .zenoh import REQUEST_TIMEOUT_S
from .zenoh_session import session_config

if TYPE_CHECKING:
    from ..client import RobotClient

log = logging.getLogger(__name__)

#: rmw_zenoh's heartbeat for a reliable transient-local publisher (late sample recovery)
HEARTBEAT_S = 0.5


class _Topic:
    """A publisher with its GID and sequence number: each put carries rmw_zenoh's attachment."""

    def __init__(self, publisher: Any, gid: bytes) -> None:
        self.publisher = publisher
        self.gid = gid
        self.sequence = 0

    def put(self, payload: bytes) -> None:
        self.sequence += 1
        self.publisher.put(payload, attachment=rmw.attachment(self.sequence, time.time_ns(), self.gid))


class Commands:
    """What the bridge takes from the network (zenoh's threads call it): setpoints into the
    shared-memory ring through ``client``, safety requests to the loop through ``ask``
    (``name -> (success, message)``); every refusal counted by reason."""

    def __init__(self, robot: Any, capacity: int, wall_minus_loop: int, ask: Any, client: RobotClient | None) -> None:
        self.robot = robot
        self.capacity = capacity
        self.wall_minus_loop = wall_minus_loop
        self.ask = ask
        self.client = client
        self.counters: dict[str, int] = collections.Counter()
        self.refused_by_reason: dict[str, int] = collections.Counter()
        self._lock = threading.Lock()
        self._warn = RateLimitedLogger(log)
        import zenoh

        self._put = zenoh.SampleKind.PUT

    def _refuse(self, reason: str, what: str, detail: str = "") -> None:
        with self._lock:
            self.counters["refused"] += 1
            self.refused_by_reason[reason] += 1
        self._warn.warning(f"refused:{reason}", "zenoh bridge refused %s: %s %s", what, reason, detail)

    def on_trajectory(self, sample) -> None:
        try:
            if sample.kind != self._put:  # a delete carries no command
                raise ros.Refused("not a put")
            now = time.time_ns() - self.wall_minus_loop
            trajectory = ros.trajectory(sample.payload.to_bytes(), self.robot, now, self.wall_minus_loop)
            with self._lock:
                client = self.client
                if client is None:
                    raise ros.Refused("bridge closed")
                if len(trajectory.times_ns) > self.capacity - client.pending:
                    raise ros.Refused("ring full")
                client.send_trajectory(
                    trajectory.times_ns, trajectory.positions, trajectory.velocities, timeout_s=0.0, final=True
                )
                self.counters["setpoints_accepted"] += len(trajectory.times_ns)
        except ros.Refused as exc:
            self._refuse(str(exc), "a joint_trajectory")
        except Exception as exc:  # a client's error (robot in hold, no stream) is still a refusal
            self._refuse(type(exc).__name__, "a joint_trajectory", str(exc))

    def on_request(self, name: str, query) -> None:
        """A Trigger service call: acted on by the loop between two ticks; the answer carries
        the request's sequence number and client GID back, as rmw_zenoh's clients match them."""
        try:
            attachment = query.attachment
            if attachment is None:
                raise ros.Refused("no attachment")
            try:
                sequence, _, client_gid = rmw.read_attachment(attachment.to_bytes())
                services.deserialize_request(query.payload.to_bytes() if query.payload else b"", ros.TRIGGER)
            except Exception:
                raise ros.Refused("malformed") from None
        except ros.Refused as exc:
            self._refuse(str(exc), f"a {name} request")
            return
        success, message = self.ask(name)
        with self._lock:
            self.counters["requests_relayed"] += 1
        response = services.serialize_response(ros.TRIGGER, success=success, message=message)
        query.reply(query.key_expr, response, attachment=rmw.attachment(sequence, time.time_ns(), client_gid))

    def close(self) -> None:
        with self._lock:
            if self.client is not None:
                self.client.close()
                self.client = None


class ZenohOutput:
    """The bridge in its process: the session, the node's endpoints, the ring's rows out."""

    def __init__(self, spec: dict[str, Any], channel: Any) -> None:
        """``channel``: the process's socket to the loop (:class:`.output_main.Channel`)."""
        import zenoh

        section = self.section = spec["section"]
        robot = self.robot = spec["robot"]
        self.channel = channel
        self.namespace = spec["namespace"]
        self.every = int(spec["every"])
        self.period_ns = int(spec["period_ns"])
        self.clock = spec["clock"]
        self.wall_minus_loop = int(spec["wall_minus_loop"])
        self.IDLE_S = min(0.005, 0.5 / section.state_hz)
        self.names = list(robot.joint_names)
        self.ring = R.TickReader(robot.name, pid=spec["pid"], start=spec["start"], line=spec["line"])
        self._state = self.ring.names.index("state")
        self.counters: dict[str, int] = collections.Counter({"state_sent": 0, "state_lost": 0})
        self._due = 0
        self._level: int | None = None
        self._tick = 0
        self._last_timing: tuple[int, int, int, int, list[int]] | None = None
        self._health: Any = None
        self._loop_figures: dict[str, Any] = {}
        self._faults_sent = 0
        self._warn = RateLimitedLogger(log)
        self._answers: dict[int, concurrent.futures.Future] = {}
        self._ids = itertools.count(1)
        self._declared: list[Any] = []
        self._topics: dict[str, _Topic] = {}
        self.keys: dict[str, str] = {}
        self.tokens: list[str] = []
        client = None
        if "setpoints" in section.commands:
            from ..client import RobotClient

            client = RobotClient(robot.name, command=True)
        self.commands = Commands(robot, spec["capacity"], self.wall_minus_loop, self._ask_loop, client)
        try:
            self._session: Any = zenoh.open(session_config(section))  # zenoh ships no types
        except BaseException:
            self.commands.close()
            self.ring.close()
            raise
        self.node = rmw.Node(section.domain_id, str(self._session.info.zid()), self.namespace, section.node)
        self._declare_token(self.node.token())
        self._entities = 0
        for endpoint in (ros.JOINT_STATES, ros.DIAGNOSTICS, ros.SAFETY, ros.TIMING, ros.ROBOT):
            self._topics[endpoint.name] = self._declare_publisher(endpoint)
        if "setpoints" in section.commands:
            key, _ = self._declare_endpoint(ros.TRAJECTORY, rmw.SUBSCRIPTION)
            self._declared.append(self._session.declare_subscriber(key, self.commands.on_trajectory))
        for request in ros.REQUESTS:
            if request in section.commands:
                key, _ = self._declare_endpoint(ros.Endpoint(request, ros.TRIGGER), rmw.SERVICE)
                handler = functools.partial(self.commands.on_request, request)
                self._declared.append(self._session.declare_queryable(key, handler, complete=True))
        rate_hz = 1e9 / self.period_ns
        self._topics[ros.ROBOT.name].put(ros.robot_description(robot, rate_hz, self.clock))
        self._next_report = time.monotonic()

    def info(self) -> dict[str, Any]:
        return {"keys": self.keys, "tokens": self.tokens, "zid": str(self._session.info.zid())}

    # ------------------------------------------------------------ endpoints

    def _declare_token(self, token: str) -> None:
        self._declared.append(self._session.liveliness().declare_token(token))
        self.tokens.append(token)

    def _declare_endpoint(self, endpoint: ros.Endpoint, kind: str) -> tuple[str, bytes]:
        """The endpoint's liveliness token; its key expression and GID."""
        self._entities += 1
        name = self.node.qualify(endpoint.name)
        type_hash = endpoint.type_hash()
        token = self.node.endpoint_token(self._entities, kind, name, endpoint.ros_type, type_hash, endpoint.qos)
        self._declare_token(token)
        key = rmw.data_key(self.section.domain_id, name, endpoint.ros_type, type_hash)
        self.keys[endpoint.name] = key
        return key, rmw.gid(token)

    def _declare_publisher(self, endpoint: ros.Endpoint) -> _Topic:
        """As rmw_zenoh does: a transient-local publisher keeps its last messages in a cache that
        late subscribers query, is detectable, and sends heartbeats so that a lost last sample
        is recovered."""
        import zenoh
        import zenoh.ext

        key, gid = self._declare_endpoint(endpoint, rmw.PUBLISHER)
        options: dict[str, Any] = {
            "congestion_control": zenoh.CongestionControl.DROP,  # never block the bridge
            "reliability": zenoh.Reliability.RELIABLE,
        }
        if endpoint.qos.transient_local:
            publisher = zenoh.ext.declare_advanced_publisher(
                self._session,
                key,
                cache=zenoh.ext.CacheConfig(max_samples=endpoint.qos.depth),
                publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=HEARTBEAT_S),
                **options,
            )
        else:
            publisher = self._session.declare_publisher(key, **options)
        self._declared.append(publisher)
        return _Topic(publisher, gid)

    # ------------------------------------------------------------ the process's calls

    def _stamp(self, loop_ns: int) -> int:
        """A time of the loop's clock as ROS time (the wall clock), for headers."""
        return loop_ns + self.wall_minus_loop

    def step(self) -> bool:
        try:
            rows = self.ring.read(self.ring.slots)
            if len(rows):
                self._publish_rows(rows)
            if time.monotonic() >= self._next_report:
                self._next_report += self.section.report_s
                self._publish_report()
        except Exception as exc:  # the network must never take the bridge down
            self._warn.warning("put", "zenoh bridge: %s: %s", type(exc).__name__, exc)
        return True

    def _publish_rows(self, rows: np.ndarray) -> None:
        meta = self.ring.meta(rows)
        ticks, levels = meta[:, R.TICK], meta[:, R.LEVEL]
        timed = np.flatnonzero(meta[:, R.TIMING_VALID])
        if len(timed):
            m = meta[timed[-1]]
            self._last_timing = (
                int(m[R.PREV_TICK]),
                int(m[R.PREV_NOW]),
                int(m[R.TIMING]),
                int(m[R.TIMING + 1]),
                [int(v) for v in m[R.TIMING + 2 : R.TIMING + 8]],
            )
        previous = self._level if self._level is not None else int(levels[0]) - 1
        changed = np.flatnonzero(np.diff(levels, prepend=previous))
        for i in changed:
            self._topics[ros.SAFETY.name].put(
                ros.safety_level(self._stamp(int(meta[i, R.NOW])), int(ticks[i]), int(levels[i]))
            )
        self._level = int(levels[-1])
        self._tick = int(ticks[-1])
        # on the first tick at or after each multiple of ``every``: a skipped tick does not shift the rate
        state = None
        joint_states = self._topics[ros.JOINT_STATES.name]
        for i in np.flatnonzero(ticks >= self._due):
            k = int(ticks[i])
            if k < self._due:
                continue
            self._due = (k // self.every + 1) * self.every
            if state is None:
                state = self.ring.field(rows, self._state)
            joint_states.put(ros.joint_state(self.names, self._stamp(int(meta[i, R.NOW])), state[i, :3]))
            self.counters["state_sent"] += 1

    def message(self, message: tuple) -> None:
        what = message[0]
        if what == "answer":
            _, rid, success, text = message
            future = self._answers.pop(rid, None)
            if future is not None:
                future.set_result((success, text))
        elif what == "event":
            _, topic, _, body = message
            if topic == "/diagnostics":
                self._health = body
            elif topic == "/loop":
                self._loop_figures = body
            elif topic == "/faults":
                self._publish_report([body])

    def _ask_loop(self, name: str) -> tuple[bool, str]:
        """Relay a request to the loop and wait for its answer (zenoh's thread)."""
        rid = next(self._ids)
        future: concurrent.futures.Future = concurrent.futures.Future()
        self._answers[rid] = future
        self.channel.answer("request", (rid, name, time.monotonic()))
        try:
            return future.result(timeout=REQUEST_TIMEOUT_S)
        except concurrent.futures.TimeoutError:
            self._answers.pop(rid, None)
            return False, f"the loop did not answer within {REQUEST_TIMEOUT_S:g} s"

    def _publish_report(self, new_faults: list | None = None) -> None:
        now = time.time_ns()
        health = self._health
        level = SafetyLevel(self._level) if self._level is not None else SafetyLevel.OFF
        values = {
            "robot": self.robot.name,
            "tick": self._tick,
            "missed_ticks": self._loop_figures.get("missed_ticks", 0),
            "ticks": self._loop_figures.get("ticks", 0),
            "level": level.name.lower(),
            "controller": health.controller.get("type", "?") if health is not None else "?",
            **self.counters,
            **self.commands.counters,
            "refused_by_reason": json.dumps(dict(self.commands.refused_by_reason)),
        }
        self._topics[ros.DIAGNOSTICS.name].put(ros.diagnostics(now, self.robot.name, level, values, new_faults or []))
        if not new_faults and self._last_timing is not None:
            tick, _, lateness, work, phases = self._last_timing
            self._topics[ros.TIMING.name].put(ros.tick_timing(now, tick, lateness, work, phases))

    def finish(self, final: Any) -> dict[str, Any]:
        if final is not None:
            for event in final.get("events", []):
                self.message(event)
        self.counters["state_lost"] = self.ring.lost
        for future in self._answers.values():
            future.set_result((False, "the bridge is closing"))
        self._answers.clear()
        try:
            for entity in reversed(self._declared):  # the tokens go: ROS 2 sees the node leave
                entity.undeclare()
            self._session.close()
        except Exception as exc:
            log.warning("zenoh session close failed: %s", exc)
        self.commands.close()
        self.ring.close()
        return {
            "counters": {**self.counters, **self.commands.counters},
            "refused_by_reason": dict(self.commands.refused_by_reason),
        }
