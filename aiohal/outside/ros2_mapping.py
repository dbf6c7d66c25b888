"""What the Zenoh bridge says and hears in ROS 2 messages (docs/ros2.md): its topics with their
types and QoS, the messages built from the robot's arrays, and the commands it takes, checked
before anything reaches the robot. CDR, schemas and hashes come from :mod:`aiohal.ros2`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import ros2
from ..ros2 import services
from ..safety import SafetyLevel
from . import recorder_topics
from .recorder_topics import ERROR, OK, WARN
from .rmw_zenoh import LATCHED, VOLATILE, Qos

if TYPE_CHECKING:
    from ..robot import Robot
    from ..safety import FaultRecord


@dataclass(frozen=True)
class Endpoint:
    """A topic or service of the bridge: its name (relative: in the node's namespace), its type, its QoS."""

    name: str
    ros_type: str
    qos: Qos = VOLATILE

    def type_hash(self) -> str:
        if "/srv/" in self.ros_type:
            return services.service_hash(self.ros_type)
        return ros2.type_hash(self.ros_type)


JOINT_STATES = Endpoint("joint_states", "sensor_msgs/msg/JointState")
DIAGNOSTICS = Endpoint("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
SAFETY = Endpoint("safety_level", "aiohal_msgs/msg/SafetyLevel", LATCHED)
TIMING = Endpoint("tick_timing", "aiohal_msgs/msg/TickTiming")
ROBOT = Endpoint("robot", "aiohal_msgs/msg/Robot", LATCHED)
TRAJECTORY = Endpoint("joint_trajectory", "trajectory_msgs/msg/JointTrajectory")
#: the safety requests, each a std_srvs/srv/Trigger service of the same name
REQUESTS = ("estop", "hold", "reset_faults", "rearm")
TRIGGER = services.TRIGGER


def joint_state(names: list[str], stamp_ns: int, rows: np.ndarray) -> bytes:
    """``sensor_msgs/msg/JointState``: ``rows`` are position, velocity, effort."""
    msg = ros2.message_type(JOINT_STATES.ros_type)(
        header=ros2.header(stamp_ns), name=names, position=rows[0], velocity=rows[1], effort=rows[2]
    )
    return ros2.serialize(msg)


def safety_level(stamp_ns: int, tick: int, level: int) -> bytes:
    return ros2.serialize(ros2.message_type(SAFETY.ros_type)(header=ros2.header(stamp_ns), tick=tick, level=level))


def tick_timing(stamp_ns: int, tick: int, lateness_ns: int, work_ns: int, phases_ns: list[int]) -> bytes:
    """``aiohal_msgs/msg/TickTiming`` of one tick; ``phases_ns`` in the tick's phase order."""
    read, check, control, limits, write, publish = (int(p) for p in phases_ns)
    msg = ros2.message_type(TIMING.ros_type)(
        header=ros2.header(stamp_ns),
        tick=tick,
        lateness_ns=int(lateness_ns),
        work_ns=int(work_ns),
        read_ns=read,
        check_ns=check,
        control_ns=control,
        limits_ns=limits,
        write_ns=write,
        publish_ns=publish,
    )
    return ros2.serialize(msg)


def robot_description(robot: Robot, rate_hz: float, clock: str) -> bytes:
    """``aiohal_msgs/msg/Robot`` as the recording has it (inf: no limit), without the config text."""
    return ros2.serialize(recorder_topics.robot_message(robot, rate_hz, clock, ""))


def diagnostics(
    stamp_ns: int, robot: str, level: SafetyLevel, values: dict[str, Any], new_faults: list[FaultRecord]
) -> bytes:
    """``diagnostic_msgs/msg/DiagnosticArray``: the robot's status (OK in run, WARN in hold or
    disabled, ERROR in estop or off, or with a fault since the last report), then one ERROR
    status per new fault."""
    status_t = ros2.message_type("diagnostic_msgs/msg/DiagnosticStatus")
    key_value = ros2.message_type("diagnostic_msgs/msg/KeyValue")
    if new_faults or level <= SafetyLevel.ESTOP:
        severity = ERROR
    else:
        severity = OK if level == SafetyLevel.RUN else WARN
    statuses = [
        status_t(
            level=severity,
            name=f"aiohal: {robot}",
            message=f"safety level {level.name.lower()}",
            hardware_id=robot,
            values=[key_value(key=k, value=str(v)) for k, v in values.items()],
        )
    ]
    for fault in new_faults:
        statuses.append(
            status_t(
                level=ERROR,
                name=f"aiohal: {robot}: {fault.source}",
                message=str(fault),
                hardware_id=robot,
                values=[key_value(key=k, value=str(v)) for k, v in fault.as_dict().items()],
            )
        )
    msg = ros2.message_type(DIAGNOSTICS.ros_type)(header=ros2.header(stamp_ns), status=statuses)
    return ros2.serialize(msg)


class Refused(Exception):
    """A command the bridge does not apply; the message is the reason counted."""


@dataclass(frozen=True)
class Trajectory:
    """A JointTrajectory in the robot's joint order, its times on the loop's clock."""

    times_ns: list[int]
    positions: np.ndarray  # [points × dof]
    velocities: np.ndarray | None


def trajectory(payload: bytes, robot: Robot, now_ns: int, wall_minus_loop_ns: int) -> Trajectory:
    """Decode and check a ``trajectory_msgs/msg/JointTrajectory``: every joint named once, each
    point with every position (velocities: all or none), finite, within the position range, at
    non-decreasing times. A zero header stamp starts the points on receipt; another is ROS time
    (the wall clock) and is moved onto the loop's clock. Raises :class:`Refused`."""
    try:
        msg = ros2.deserialize(payload, TRAJECTORY.ros_type)
    except Exception:  # rosbags raises several kinds on a truncated or corrupt payload
        raise Refused("malformed") from None
    names = list(robot.joint_names)
    given = list(msg.joint_names)
    if any(n not in names for n in given):
        raise Refused("unknown joint")
    if len(set(given)) != len(given) or len(given) != len(names):
        raise Refused("missing joint")
    if not msg.points:
        raise Refused("no point")
    order = [given.index(n) for n in names]
    dof = len(names)
    positions = np.empty((len(msg.points), dof))
    has_velocity = len(msg.points[0].velocities) > 0
    velocities = np.empty((len(msg.points), dof)) if has_velocity else None
    stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
    start = now_ns if stamp == 0 else stamp - wall_minus_loop_ns
    times: list[int] = []
    for k, point in enumerate(msg.points):
        if len(point.positions) != dof or len(point.velocities) != (dof if has_velocity else 0):
            raise Refused("malformed")
        positions[k] = np.asarray(point.positions)[order]
        if velocities is not None:
            velocities[k] = np.asarray(point.velocities)[order]
        t = start + point.time_from_start.sec * 1_000_000_000 + point.time_from_start.nanosec
        if times and t < times[-1]:
            raise Refused("time goes back")
        times.append(t)
    if not np.isfinite(positions).all() or (velocities is not None and not np.isfinite(velocities).all()):
        raise Refused("not finite")
    if not ((positions >= robot.position_min) & (positions <= robot.position_max)).all():
        raise Refused("out of range")
    return Trajectory(times, positions, velocities)
