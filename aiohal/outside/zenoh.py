"""The Eclipse Zenoh bridge (``[bridge.zenoh]``, extra ``zenoh``), the loop's side: it starts
the bridge's process (:mod:`.zenoh_output`) reading the loop's tick ring, sends it the drivers'
health and the faults, and acts on the safety requests it relays (``estop``, ``hold``,
``reset_faults``, ``rearm``) between two ticks, answering each with the loop's reason when it
refuses. docs/ros2.md gives the ROS 2 mapping. Nothing of the bridge runs in the tick, and no
thread of it runs in the loop's process.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import os
from typing import Any

from ..safety import SafetyRequestExpired, SafetyRequestRefused
from .event_feed import EventFeed, join_feed, leave_feed
from .options import ZenohBridgeSection
from .output_process import OutputProcess
from .port import LoopPort
from .tick_door import TickDoor, close_door, open_door
from .zenoh_session import check_access, session_config

log = logging.getLogger(__name__)

#: how long the bridge's process may take to start (zenoh's import, the session)
START_TIMEOUT_S = 60.0
#: how often the bridge learns the drivers' health, new faults and safety changes
FEED_HZ = 10.0
#: how long the bridge's process waits for the loop's answer before it tells the caller "no answer"
REQUEST_TIMEOUT_S = 2.0
#: the oldest ``rearm`` or ``reset_faults`` the loop still acts on. A loop that was frozen reads
#: the requests queued meanwhile; one whose caller was told "no answer" must not move the robot
#: now. Half the bridge's wait leaves the answer time to get back; estop and hold act at any age.
ARMING_REQUEST_MAX_AGE_S = REQUEST_TIMEOUT_S / 2


class ZenohBridge:
    """Made with the loop (nothing opened), started when the loop is active, closed with it."""

    def __init__(self, port: LoopPort, section: ZenohBridgeSection) -> None:
        self.port = port
        self.section = section
        robot = port.robot
        self.namespace = section.namespace or f"/{robot.name}"
        rate = 1e9 / port.period_ns
        self.every = max(1, round(rate / section.state_hz))
        self.process: OutputProcess | None = None
        self.door: TickDoor | None = None
        self.feed: EventFeed | None = None
        self.keys: dict[str, str] = {}  # endpoint name → its key expression (for logs and tests)
        self.tokens: list[str] = []  # the liveliness tokens declared
        self.zid = ""
        #: the bridge process's figures (after close), and the loop's answers to its requests
        self.counters: dict[str, int] = collections.Counter()
        self.refused_by_reason: dict[str, int] = {}

    def start(self) -> None:
        section, port = self.section, self.port
        config = session_config(section)  # a config zenoh refuses is refused here, with its reason
        means = check_access(section, config)
        if section.commands and means is None:  # allow_anyone: said at every start
            log.warning(
                "zenoh bridge for %s takes %s from anyone who reaches it (allow_anyone = true): a lab network only",
                port.robot.name,
                ", ".join(section.commands),
            )
        self.door = door = open_door(port, port.config.record.buffer_ticks)
        start = door.start_index()
        spec = {
            "robot": port.robot,
            "section": section,
            "namespace": self.namespace,
            "every": self.every,
            "period_ns": port.period_ns,
            "clock": port.clock_kind,
            "wall_minus_loop": _wall_minus_loop(port),
            "capacity": port.config.client.capacity,
            "pid": os.getpid(),
            "start": start,
            "line": door.ring.claim_reader(start),
        }
        self.process = OutputProcess(
            "zenoh", spec, f"zenoh bridge of {port.robot.name}", avoid_cpus=port.config.realtime.cpus
        )
        try:
            info = self.process.wait_ready(START_TIMEOUT_S)
        except BaseException:
            self.close()
            raise
        self.keys, self.tokens, self.zid = info["keys"], info["tokens"], info["zid"]
        self.process.serve(asyncio.get_running_loop(), self._act)
        self.feed = join_feed(port, FEED_HZ, self.process)
        log.info(
            "zenoh bridge: ROS 2 node %s/%s on domain %d (rmw_zenoh), taking %s",
            self.namespace,
            section.node,
            section.domain_id,
            ", ".join(section.commands) or "no command",
        )

    def _act(self, name: str, sent_s: float) -> tuple[bool, str]:
        """A safety request the bridge relayed at ``sent_s`` (``time.monotonic()``), on the
        loop's thread between ticks."""
        port = self.port
        cause = "requested over ROS 2 (zenoh)"
        log.warning("robot %s: %s requested over zenoh", port.robot.name, name)
        act_by_ns = int((sent_s + ARMING_REQUEST_MAX_AGE_S) * 1e9)
        try:
            if name == "estop":
                port.estop(cause, source="zenoh")
            elif name == "hold":
                port.hold(cause)
            elif name == "reset_faults":
                cleared = port.reset_faults(source="zenoh", act_by_ns=act_by_ns)
            elif name == "rearm":
                port.rearm(source="zenoh", act_by_ns=act_by_ns)
            else:
                return False, f"unknown request {name!r}"
            success, message = True, f"{name} done: safety level {port.level.name.lower()}"
            if name == "reset_faults":
                message = f"cleared {len(cleared)} fault(s)"
        except SafetyRequestExpired as exc:
            self.counters["requests_expired"] += 1
            success, message = False, f"{exc}; its caller was told there was no answer"
        except SafetyRequestRefused as exc:
            success, message = False, str(exc)
        except Exception as exc:
            success, message = False, f"{type(exc).__name__}: {exc}"
        self.counters["requests_accepted" if success else "requests_refused_by_loop"] += 1
        if not success:
            log.warning("robot %s: %s over zenoh refused: %s", port.robot.name, name, message)
        return success, message

    def close(self) -> None:
        if self.feed is not None and self.process is not None:
            leave_feed(self.feed, self.process)
            self.feed = None
        if self.process is not None:
            summary = self.process.stop({}, 30.0)
            if summary is not None:
                for k, v in summary["counters"].items():
                    self.counters[k] += v
                self.refused_by_reason = summary["refused_by_reason"]
            else:
                log.warning("%s: %s", self.process.name, self.process.error)
            self.process = None
        if self.door is not None:
            close_door(self.door)
            self.door = None

    def report(self) -> dict[str, Any]:
        """The bridge's counters, as its process gave them at close, and the loop's answers."""
        return {
            "bridge": {
                **self.counters,
                "refused_by_reason": dict(self.refused_by_reason),
                "commands": self.section.commands,
            }
        }


def _wall_minus_loop(port: LoopPort) -> int:
    """ROS time (the wall clock) minus the loop's clock, ns."""
    import time

    return time.time_ns() - port.now_ns()
