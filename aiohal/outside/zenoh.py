"""The Eclipse Zenoh bridge (``[bridge.zenoh]``, extra ``zenoh``): the robot as a ROS 2 node that
nodes running rmw_zenoh see, list and echo (docs/ros2.md gives the mapping).

Node ``<namespace>/<node>`` (default ``/<robot>/aiohal``) publishes, in CDR with rmw_zenoh's
attachment: ``joint_states`` (``sensor_msgs/msg/JointState`` at ``state_hz``), ``/diagnostics``
(``diagnostic_msgs/msg/DiagnosticArray``: the robot's status every ``report_s`` and each new
fault), ``safety_level`` and ``robot`` (``aiohal_msgs``, transient-local: late joiners get the
last one), ``tick_timing`` (``aiohal_msgs/msg/TickTiming`` every ``report_s``). It takes nothing
unless ``commands`` names it: ``setpoints`` subscribes to ``joint_trajectory``
(``trajectory_msgs/msg/JointTrajectory``, into the stream controller's shared-memory ring);
``estop``, ``hold``, ``reset_faults``, ``rearm`` are ``std_srvs/srv/Trigger`` services answered
with the loop's reason when it refuses. Commands need access control in the session's config
(:mod:`.zenoh_session`).

The tick only copies a snapshot into a preallocated ring on the ticks that publish (one in
``rate / state_hz``) and compares the level and the fault count; the bridge's own thread
encodes and puts. A command that fails its checks is refused and counted, never applied.
``zenoh`` is imported when the bridge starts, never by the tick core.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import functools
import json
import logging
import threading
import time
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ..core.tick_timing import PHASES
from ..logutil import RateLimitedLogger
from ..ros2 import services
from ..safety import SafetyRequestRefused
from . import rmw_zenoh as rmw
from . import ros2_mapping as ros
from .options import ZenohBridgeSection
from .port import LoopPort
from .zenoh_session import check_access, session_config

if TYPE_CHECKING:
    from ..client import RobotClient

log = logging.getLogger(__name__)

#: how long a service waits for the loop to act on a request before it answers "no answer"
REQUEST_TIMEOUT_S = 2.0
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


class ZenohBridge:
    """Made with the loop (nothing opened), started when the loop is active, closed with it."""

    def __init__(self, port: LoopPort, section: ZenohBridgeSection) -> None:
        self.port = port
        self.section = section
        robot = port.robot
        self.namespace = section.namespace or f"/{robot.name}"
        self.dof = robot.dof
        rate = 1e9 / port.period_ns
        self.every = max(1, round(rate / section.state_hz))
        q = section.queue
        self._ticks = np.zeros((q, 3), dtype=np.int64)  # tick, now_ns, level
        self._rows = np.zeros((q, 3, robot.dof))  # position, velocity, effort
        self._head = 0  # snapshots written by the tick (the thread reads it; the GIL orders them)
        self._events: collections.deque = collections.deque()
        self.counters = {
            "state_sent": 0,
            "state_dropped": 0,
            "setpoints_accepted": 0,
            "requests_accepted": 0,
            "requests_refused_by_loop": 0,
            "refused": 0,
        }
        self.refused_by_reason: dict[str, int] = collections.Counter()
        self._warn = RateLimitedLogger(log)
        self._session: Any = None  # a zenoh.Session (zenoh ships no types)
        self._declared: list[Any] = []  # tokens, publishers, subscribers, queryables: undeclared at close
        self._topics: dict[str, _Topic] = {}
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._client: RobotClient | None = None
        self._aio: asyncio.AbstractEventLoop | None = None
        self._lock = threading.Lock()  # the zenoh callbacks' counters and the shm client
        self._wall_minus_loop = 0  # ROS time (the wall clock) minus the loop's clock, ns
        self._faults_sent = 0
        self.keys: dict[str, str] = {}  # endpoint name → its key expression (for logs and tests)
        self.tokens: list[str] = []  # the liveliness tokens declared
        self.publish = self._make_publisher()

    # ------------------------------------------------------------ the tick's side

    def _make_publisher(self):
        port, robot = self.port, self.port.robot
        state_rows = memoryview(robot.state.block[:3]).cast("B")  # position, velocity, effort: adjacent
        rows = [memoryview(self._rows[i]).cast("B") for i in range(self.section.queue)]
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
            rows[i][:] = state_rows
            t = ticks[i]
            t[0] = k
            t[1] = clock.now_ns
            t[2] = level
            self._head += 1

        return publish

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        import zenoh

        section, port = self.section, self.port
        config = session_config(section)
        means = check_access(section, config)
        if section.commands and means is None:  # allow_anyone: said at every start
            log.warning(
                "zenoh bridge for %s takes %s from anyone who reaches it (allow_anyone = true): a lab network only",
                port.robot.name,
                ", ".join(section.commands),
            )
        self._aio = asyncio.get_running_loop()
        self._wall_minus_loop = time.time_ns() - port.now_ns()
        if "setpoints" in section.commands:
            from ..client import RobotClient

            self._client = RobotClient(port.robot.name, command=True)
        self._put = zenoh.SampleKind.PUT
        self._session = zenoh.open(config)
        self.node = rmw.Node(section.domain_id, str(self._session.info.zid()), self.namespace, section.node)
        self._declare_token(self.node.token())
        self._entities = 0
        for endpoint in (ros.JOINT_STATES, ros.DIAGNOSTICS, ros.SAFETY, ros.TIMING, ros.ROBOT):
            self._topics[endpoint.name] = self._declare_publisher(endpoint)
        if "setpoints" in section.commands:
            key, _ = self._declare_endpoint(ros.TRAJECTORY, rmw.SUBSCRIPTION)
            self._declared.append(self._session.declare_subscriber(key, self._on_trajectory))
        for request in ros.REQUESTS:
            if request in section.commands:
                key, _ = self._declare_endpoint(ros.Endpoint(request, ros.TRIGGER), rmw.SERVICE)
                handler = functools.partial(self._on_request, request)
                self._declared.append(self._session.declare_queryable(key, handler, complete=True))
        rate_hz = 1e9 / port.period_ns
        self._topics[ros.ROBOT.name].put(ros.robot_description(port.robot, rate_hz, port.clock_kind))
        self._topics[ros.SAFETY.name].put(ros.safety_level(self._stamp(port.now_ns()), port.tick, int(port.level)))
        self._thread = threading.Thread(target=self._run, name=f"aiohal-zenoh-{port.robot.name}", daemon=True)
        self._thread.start()
        log.info(
            "zenoh bridge: ROS 2 node %s/%s on domain %d (rmw_zenoh), taking %s",
            self.namespace,
            section.node,
            section.domain_id,
            ", ".join(section.commands) or "no command",
        )

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
            "congestion_control": zenoh.CongestionControl.DROP,  # never block the bridge's thread
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

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if self._session is not None:
            try:
                for entity in reversed(self._declared):  # the tokens go: ROS 2 sees the node leave
                    entity.undeclare()
                self._session.close()
            except Exception as exc:  # closing must not hide the loop's own shutdown
                log.warning("zenoh session close failed: %s", exc)
            self._declared.clear()
            self._session = None
        with self._lock:
            if self._client is not None:
                self._client.close()
                self._client = None

    # ------------------------------------------------------------ the bridge's thread

    def _stamp(self, loop_ns: int) -> int:
        """A time of the loop's clock as ROS time (the wall clock), for headers."""
        return loop_ns + self._wall_minus_loop

    def _run(self) -> None:
        section = self.section
        poll_s = min(0.005, 0.5 / section.state_hz)
        next_report = time.monotonic()
        tail = 0
        queue = section.queue
        names = list(self.port.robot.joint_names)
        joint_states = self._topics[ros.JOINT_STATES.name]
        while not self._stop.wait(poll_s):
            try:
                head = self._head
                if head - tail > queue:  # the thread fell behind: the oldest are overwritten
                    self.counters["state_dropped"] += head - tail - queue
                    tail = head - queue
                while tail < head:
                    i = tail % queue
                    joint_states.put(ros.joint_state(names, self._stamp(int(self._ticks[i, 1])), self._rows[i]))
                    tail += 1
                    self.counters["state_sent"] += 1
                while self._events:
                    self._publish_event(*self._events.popleft())
                if time.monotonic() >= next_report:
                    next_report += section.report_s
                    self._publish_report()
            except Exception as exc:  # the network must never take the robot down
                self._warn.warning("put", "zenoh bridge: %s: %s", type(exc).__name__, exc)

    def _publish_event(self, level: int, n_faults: int, tick: int) -> None:
        now = self._stamp(self.port.now_ns())
        self._topics[ros.SAFETY.name].put(ros.safety_level(now, tick, level))
        if n_faults > self._faults_sent:
            self._publish_report(list(self.port.faults[self._faults_sent : n_faults]))

    def _publish_report(self, new_faults: list | None = None) -> None:
        port = self.port
        now = self._stamp(port.now_ns())
        if new_faults:
            self._faults_sent += len(new_faults)
        values = {k: v for k, v in self.report().items() if k not in ("joints", "bridge")}
        values.update(self.counters, refused_by_reason=json.dumps(dict(self.refused_by_reason)))
        diagnostics = ros.diagnostics(now, port.robot.name, port.level, values, new_faults or [])
        self._topics[ros.DIAGNOSTICS.name].put(diagnostics)
        timing = port.timing
        if not new_faults and timing.count >= 2:  # the last tick that has ended
            i = (timing.count - 2) & timing.mask
            phases = [int(timing.phases[p, i]) for p in range(len(PHASES))]
            self._topics[ros.TIMING.name].put(
                ros.tick_timing(now, timing.count - 2, int(timing.lateness[i]), int(timing.work[i]), phases)
            )

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
                "commands": self.section.commands,
            },
        }

    # ------------------------------------------------------------ commands (zenoh's threads)

    def _refuse(self, reason: str, what: str, detail: str = "") -> None:
        with self._lock:
            self.counters["refused"] += 1
            self.refused_by_reason[reason] += 1
        self._warn.warning(f"refused:{reason}", "zenoh bridge refused %s: %s %s", what, reason, detail)

    def _on_trajectory(self, sample) -> None:
        port = self.port
        try:
            if sample.kind != self._put:  # a delete carries no command
                raise ros.Refused("not a put")
            trajectory = ros.trajectory(sample.payload.to_bytes(), port.robot, port.now_ns(), self._wall_minus_loop)
            with self._lock:
                client = self._client
                if client is None:
                    raise ros.Refused("bridge closed")
                if len(trajectory.times_ns) > port.config.client.capacity - client.pending:
                    raise ros.Refused("ring full")
                client.send_trajectory(
                    trajectory.times_ns, trajectory.positions, trajectory.velocities, timeout_s=0.0, final=True
                )
                self.counters["setpoints_accepted"] += len(trajectory.times_ns)
        except ros.Refused as exc:
            self._refuse(str(exc), "a joint_trajectory")
        except Exception as exc:  # a client's error (robot in hold, no stream) is still a refusal
            self._refuse(type(exc).__name__, "a joint_trajectory", str(exc))

    def _on_request(self, name: str, query) -> None:
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
        success, message = self._ask_loop(name)
        response = services.serialize_response(ros.TRIGGER, success=success, message=message)
        query.reply(query.key_expr, response, attachment=rmw.attachment(sequence, time.time_ns(), client_gid))

    def _ask_loop(self, name: str) -> tuple[bool, str]:
        port = self.port

        def reset_faults() -> str:
            return f"cleared {len(port.reset_faults(source='zenoh'))} fault(s)"

        request = {
            "hold": lambda: port.hold("requested over ROS 2 (zenoh)"),
            "estop": lambda: port.estop("requested over ROS 2 (zenoh)", source="zenoh"),
            "reset_faults": reset_faults,
            "rearm": lambda: port.rearm(source="zenoh"),
        }[name]
        answer: concurrent.futures.Future = concurrent.futures.Future()

        def action() -> None:  # in the loop's thread
            try:
                done = request()
                answer.set_result((True, done or f"{name} done: safety level {port.level.name.lower()}"))
            except SafetyRequestRefused as exc:
                answer.set_result((False, str(exc)))
            except Exception as exc:
                answer.set_result((False, f"{type(exc).__name__}: {exc}"))

        log.warning("robot %s: %s requested over zenoh", port.robot.name, name)
        try:
            cast(asyncio.AbstractEventLoop, self._aio).call_soon_threadsafe(action)  # set by start()
            success, message = answer.result(timeout=REQUEST_TIMEOUT_S)
        except (RuntimeError, concurrent.futures.TimeoutError):  # the loop is closed or stuck
            success, message = False, f"the loop did not answer within {REQUEST_TIMEOUT_S:g} s"
        with self._lock:
            self.counters["requests_accepted" if success else "requests_refused_by_loop"] += 1
        if not success:
            log.warning("robot %s: %s over zenoh refused: %s", port.robot.name, name, message)
        return success, message
