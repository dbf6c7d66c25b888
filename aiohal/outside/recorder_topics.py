"""What the recorder writes: each topic's ROS 2 message, and how its fields come from a tick.

Per-tick topics (one message per recorded tick) name a sample message (the run's constant
parts: joint names, frame ids, sequence lengths) and a function from ring rows to the
numbers of a batch of ticks, keyed by dotted field path. Rare topics (the robot, faults,
diagnostics, safety events) are built as messages when they happen. docs/recording.md lists
the topics and their types.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from .. import ros2
from ..core.tick_timing import PHASES
from ..record.options import Channel
from ..robot import CommandRow, StateRow
from . import tick_ring as R

#: (meta rows, data rows) -> numbers by field path, one row per tick
Fields = Callable[[np.ndarray, np.ndarray], dict[str, np.ndarray]]
#: (ring rows, device index, field) -> that field's values, one row per tick
FieldOf = Callable[[np.ndarray, int, str], np.ndarray]
AIOHAL = ros2.PACKAGE + "/msg/"
STAMP = ("header.stamp.sec", "header.stamp.nanosec")


@dataclass
class TickTopic:
    """A per-tick topic: its message type, sample and numbers, and the decimation key it follows."""

    topic: str
    key: Channel  # the [record] decimate key
    sample: Any  # the message with the run's constant parts
    fields: Fields
    timing: bool = False  # its rows are the previous tick's (timing is complete one tick later)

    @property
    def msgtype(self) -> str:
        return str(self.sample.__msgtype__)


def _msg(msgtype: str, /, **fields: Any) -> Any:
    return ros2.message_type(msgtype)(**fields)


def _vector3(name: str = "geometry_msgs/msg/Vector3") -> Any:
    return _msg(name, x=0.0, y=0.0, z=0.0)


def tick_topics(
    robot: Any, add_array: Callable[[np.ndarray], int], ring: Callable[[], R.TickReader]
) -> list[TickTopic]:
    """The run's per-tick topics. ``add_array`` names an array for the ring to copy and returns
    its index; ``ring()`` is the ring, built once every topic named its arrays."""
    n = robot.dof
    names = list(robot.joint_names)
    zeros = np.zeros(n)
    head = ros2.header(0)
    state, command = robot.state, robot.command
    i_state, i_cmd = add_array(state.block), add_array(command.block)

    def block_rows(index: int, rows: Mapping[str, int]) -> Fields:
        def fields(meta: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
            block = ring().field(data, index)
            return {f: block[:, r] for f, r in rows.items()}

        return fields

    def with_array(inner: Fields, path: str, index: int) -> Fields:
        def fields(meta: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
            return {**inner(meta, data), path: ring().field(data, index)}

        return fields

    def extra(
        topic: str, key: Channel, msgtype: str, block: int, rows: Mapping[str, int], last: str, array: np.ndarray
    ) -> TickTopic:
        """The joints' rows beyond JointState: ``rows`` of a block, then the array ``last``."""
        sample = _msg(
            AIOHAL + msgtype,
            header=head,
            tick=0,
            name=names,
            **dict.fromkeys(rows, zeros),
            **{last: np.zeros(n, dtype=array.dtype)},
        )
        return TickTopic(topic, key, sample, with_array(block_rows(block, rows), last, add_array(array)))

    joint_state = _msg(
        "sensor_msgs/msg/JointState", header=head, name=names, position=zeros, velocity=zeros, effort=zeros
    )
    S, C = StateRow, CommandRow
    return [
        TickTopic(
            "/joint_states",
            "joint_state",
            joint_state,
            block_rows(i_state, {"position": S.POSITION, "velocity": S.VELOCITY, "effort": S.EFFORT}),
        ),
        extra(
            "/joint_states/extra",
            "joint_state",
            "JointStateExtra",
            i_state,
            {"motor_position": S.MOTOR_POSITION, "motor_velocity": S.MOTOR_VELOCITY, "temperature": S.TEMPERATURE},
            "fault",
            state.fault,
        ),
        TickTopic(
            "/joint_commands",
            "joint_command",
            joint_state,
            block_rows(i_cmd, {"position": C.POSITION, "velocity": C.VELOCITY, "effort": C.EFFORT}),
        ),
        extra(
            "/joint_commands/extra",
            "joint_command",
            "JointCommandExtra",
            i_cmd,
            {"stiffness": C.STIFFNESS, "damping": C.DAMPING, "feedforward": C.FEEDFORWARD},
            "mode",
            command.mode,
        ),
        *_device_topics(robot, add_array, ring),
        _timing_topic(),
        TickTopic(
            "/safety",
            "safety",
            _msg(AIOHAL + "SafetyLevel", header=head, tick=0, level=0),
            lambda meta, data: {"level": meta[:, R.LEVEL]},
        ),
    ]


def _device_topics(
    robot: Any, add_array: Callable[[np.ndarray], int], ring: Callable[[], R.TickReader]
) -> list[TickTopic]:
    """``/imu/<name>`` (sensor_msgs/Imu), ``/force_torque/<name>`` (geometry_msgs/WrenchStamped),
    ``/hand/<name>`` (aiohal_msgs/Hand), and every device's fault bits on ``/device_faults``."""
    topics: list[TickTopic] = []
    fault_arrays: list[int] = []
    device_names: list[str] = []
    for kind, group in robot.device_groups.items():
        if not len(group):
            continue
        i_fault = add_array(group.fault)
        fault_arrays.append(i_fault)
        device_names += list(group.names)
        field_of = _field_reader(group, add_array, ring)
        for d, name in enumerate(group.names):
            if kind == "imu":
                sample, fields = _imu(name, d, field_of)
            elif kind == "force_torque":
                sample, fields = _wrench(name, d, field_of)
            else:
                sample, fields = _hand(name, d, field_of, group.fields, partial(_ring_field, ring, i_fault))
            topics.append(TickTopic(f"/{kind}/{name}", kind, sample, fields))
    if device_names:
        sample = _msg(
            AIOHAL + "DeviceFaults",
            header=ros2.header(0),
            tick=0,
            name=device_names,
            fault=np.zeros(len(device_names), dtype=np.uint32),
        )

        def all_faults(meta: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
            return {"fault": np.hstack([ring().field(data, i) for i in fault_arrays])}

        topics.append(TickTopic("/device_faults", "device_faults", sample, all_faults))
    return topics


def _ring_field(ring: Callable[[], R.TickReader], index: int, data: np.ndarray) -> np.ndarray:
    return ring().field(data, index)


def _field_reader(group: Any, add_array: Callable[[np.ndarray], int], ring: Callable[[], R.TickReader]) -> FieldOf:
    """How a device group's field is read from ring rows: columns of its value block, or its own array."""
    if group.values is not None:
        i_values = add_array(group.values)
        return lambda data, d, f: ring().field(data, i_values)[:, d, group.columns[f]]
    arrays = {f: add_array(getattr(group, f)) for f in group.fields}
    return lambda data, d, f: ring().field(data, arrays[f])[:, d]


def _imu(name: str, d: int, field_of: FieldOf) -> tuple[Any, Fields]:
    sample = _msg(
        "sensor_msgs/msg/Imu",
        header=ros2.header(0, name),
        orientation=_msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=_vector3(),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=_vector3(),
        linear_acceleration_covariance=np.zeros(9),
    )

    def fields(meta: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
        q = field_of(data, d, "quaternion")  # w, x, y, z
        w, a = field_of(data, d, "angular_velocity"), field_of(data, d, "linear_acceleration")
        out = {f"orientation.{c}": q[:, i] for i, c in enumerate("wxyz")}
        out.update({f"angular_velocity.{c}": w[:, i] for i, c in enumerate("xyz")})
        out.update({f"linear_acceleration.{c}": a[:, i] for i, c in enumerate("xyz")})
        return out

    return sample, fields


def _wrench(name: str, d: int, field_of: FieldOf) -> tuple[Any, Fields]:
    sample = _msg(
        "geometry_msgs/msg/WrenchStamped",
        header=ros2.header(0, name),
        wrench=_msg("geometry_msgs/msg/Wrench", force=_vector3(), torque=_vector3()),
    )

    def fields(meta: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
        f, t = field_of(data, d, "force"), field_of(data, d, "torque")
        out = {f"wrench.force.{c}": f[:, i] for i, c in enumerate("xyz")}
        out.update({f"wrench.torque.{c}": t[:, i] for i, c in enumerate("xyz")})
        return out

    return sample, fields


def _hand(
    name: str, d: int, field_of: FieldOf, names: Sequence[str], faults: Callable[[np.ndarray], np.ndarray]
) -> tuple[Any, Fields]:
    values = {f: (False if f == "object_detected" else 0.0) for f in names}
    sample = _msg(AIOHAL + "Hand", header=ros2.header(0, name), tick=0, **values, fault=0)

    def fields(meta: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
        out = {f: field_of(data, d, f) for f in names}
        out["fault"] = faults(data)[:, d]
        return out

    return sample, fields


def _timing_topic() -> TickTopic:
    sample = _msg(
        AIOHAL + "TickTiming",
        header=ros2.header(0),
        tick=0,
        lateness_ns=0,
        work_ns=0,
        **{f"{p}_ns": 0 for p in PHASES},
    )

    def fields(meta: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
        out = {"lateness_ns": meta[:, R.TIMING], "work_ns": meta[:, R.TIMING + 1]}
        for i, p in enumerate(PHASES):
            out[f"{p}_ns"] = meta[:, R.TIMING + 2 + i]
        return out

    return TickTopic("/timing", "timing", sample, fields, timing=True)


# ------------------------------------------------------------ rare topics

#: topic -> message type of the topics written when something happens
EVENT_TOPICS = {
    "/robot": AIOHAL + "Robot",
    "/faults": "diagnostic_msgs/msg/DiagnosticArray",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "/safety/events": AIOHAL + "SafetyEvent",
}
#: kept for late subscribers (transient local)
LATCHED = frozenset({"/robot"})
DEVICE_KINDS = ("imu", "force_torque", "hand")


def robot_message(robot: Any, rate_hz: float, clock: str, description: str) -> Any:
    """``/robot``: what does not change during the run (inf: no limit)."""
    specs = robot.joints

    def limit(field: str) -> np.ndarray:
        return np.array([getattr(j, field) for j in specs], dtype=np.float64)

    groups = robot.device_groups
    return _msg(
        AIOHAL + "Robot",
        name=robot.name,
        rate_hz=float(rate_hz),
        clock=clock,
        joint_names=list(robot.joint_names),
        position_min=limit("position_min"),
        position_max=limit("position_max"),
        velocity_max=limit("velocity"),
        acceleration_max=limit("acceleration"),
        effort_max=limit("effort"),
        **{f"{kind}_names": list(groups[kind].names) if kind in groups else [] for kind in DEVICE_KINDS},
        description=description,
    )


def _text(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(_jsonable(value))


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    return value


def _status(level: int, name: str, message: str, values: dict[str, Any], hardware_id: str = "") -> Any:
    pairs = [_msg("diagnostic_msgs/msg/KeyValue", key=str(k), value=_text(v)) for k, v in values.items()]
    return _msg(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=pairs,
    )


OK, WARN, ERROR = 0, 1, 2


def faults_message(stamp_ns: int, faults: Sequence[Any]) -> Any:
    """``/faults``: one ERROR status per fault (name: its source; values: tick, phase, and whether
    it is a condition its driver reported rather than a failure)."""
    return _msg(
        "diagnostic_msgs/msg/DiagnosticArray",
        header=ros2.header(stamp_ns),
        status=[
            _status(ERROR, f.source, f.error, {"tick": f.tick, "phase": f.phase, "condition": f.condition}, f.source)
            for f in faults
        ],
    )


def diagnostics_message(stamp_ns: int, health: Any) -> Any:
    """``/diagnostics``: the safety level, each driver's status and health, the controller's metrics."""
    status = [_status(OK, "safety", health.level.name.lower(), {"tick": health.tick})]
    for name, info in health.drivers.items():
        state = str(info.get("status", ""))
        level = OK if state == "open" else (ERROR if state in ("failed", "abandoned") else WARN)
        values = {k: v for k, v in info.items() if k != "status"}
        status.append(_status(level, f"driver:{name}", state, values, name))
    controller = dict(health.controller)
    status.append(_status(OK, "controller", str(controller.pop("type", "")), controller))
    return _msg("diagnostic_msgs/msg/DiagnosticArray", header=ros2.header(stamp_ns), status=status)


def safety_event_message(stamp_ns: int, transition: Any, levels: dict[str, int]) -> Any:
    """``/safety/events``: one change of safety level and why."""
    return _msg(
        AIOHAL + "SafetyEvent",
        header=ros2.header(stamp_ns),
        tick=transition.tick,
        event=transition.event,
        source=transition.source,
        cause=transition.cause,
        before=levels[transition.before],
        after=levels[transition.after],
    )
