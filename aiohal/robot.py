"""The robot's joint model and its data: state and command as numpy arrays, one per quantity.

Every quantity of a kind lives in one 2-D block (rows = quantities, columns = joints), so a
driver's rows are plain slices written in place, and a whole snapshot is one ``copyto``.
Nothing here allocates once the robot is built.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING, Any

import numpy as np

log = logging.getLogger(__name__)


class StateRow(IntEnum):
    """Row of each measured quantity in the state block (``JointState.block``)."""

    POSITION = 0
    VELOCITY = 1
    EFFORT = 2
    MOTOR_POSITION = 3
    MOTOR_VELOCITY = 4
    TEMPERATURE = 5


class CommandRow(IntEnum):
    """Row of each commanded quantity in the command block (``JointCommand.block``).

    Compiled kernels take these rows, and the modes below, as constants when they are
    compiled, and numba's on-disk cache only notices changes to the kernel's own file: after
    changing a row or a mode, delete the ``__pycache__`` directories (the kernels' tests
    compare them with plain numpy on the current rows, and fail on a stale cache)."""

    POSITION = 0
    VELOCITY = 1
    EFFORT = 2
    STIFFNESS = 3
    DAMPING = 4
    FEEDFORWARD = 5


JOINT_STATE_FIELDS = tuple(row.name.lower() for row in StateRow)
JOINT_COMMAND_FIELDS = tuple(row.name.lower() for row in CommandRow)


class Mode(IntEnum):
    """Command mode of a joint; a driver applies the command fields its mode names."""

    NONE = 0
    POSITION = 1
    VELOCITY = 2
    EFFORT = 3
    IMPEDANCE = 4  # position + velocity targets with stiffness, damping and feed-forward effort


class Fault(IntEnum):
    """Bits of the per-row ``fault`` arrays."""

    DRIVER = 1 << 0  # the owning driver failed and was isolated
    STALE = 1 << 1  # feedback older than the configured age
    HARDWARE = 1 << 2  # the device itself reports a fault


@dataclass(frozen=True)
class JointSpec:
    """A joint and its limits (SI units: rad or m, per second, N·m or N)."""

    name: str
    index: int
    position_min: float = -np.inf
    position_max: float = np.inf
    velocity: float = np.inf
    acceleration: float = np.inf
    effort: float = np.inf


class TickInfo:
    """The current tick, shared by reference with drivers and controllers (updated by the loop)."""

    __slots__ = ("tick", "now_ns", "period_ns", "kind", "ticker")

    def __init__(self, period_ns: int) -> None:
        self.tick = -1
        self.now_ns = 0
        self.period_ns = period_ns
        self.kind = "?"  # the wake source: timerfd, sleep or virtual (a simulation steps in lockstep)
        #: the loop's :class:`~aiohal.core.ticker.Ticker` (its ``deadline_ns``, ``shift``), for a
        #: driver that locks the loop to a clock of its bus; None outside a loop
        self.ticker: Any = None


class _Rows:
    """Arrays of one kind of record; ``view`` returns the same type over a slice of its columns."""

    _fields: tuple[str, ...] = ()

    block: np.ndarray
    stamp_ns: np.ndarray
    updated_tick: np.ndarray
    fault: np.ndarray

    def __init__(self, n: int) -> None:
        self.block = np.zeros((len(self._fields), n))
        self.stamp_ns = np.zeros(n, dtype=np.int64)
        self.updated_tick = np.full(n, -1, dtype=np.int64)
        self.fault = np.zeros(n, dtype=np.uint32)
        self._bind_fields()

    def _bind_fields(self) -> None:
        for i, field in enumerate(self._fields):
            setattr(self, field, self.block[i])

    def _derived(self, transform):
        """The same record type with every array replaced by ``transform(name, array)``."""
        other = object.__new__(type(self))
        for name, value in vars(self).items():
            if not isinstance(value, np.ndarray):
                setattr(other, name, value)
            elif name not in self._fields:  # field rows are rebound from the new block
                setattr(other, name, transform(name, value))
        other._bind_fields()
        return other

    def view(self, rows: slice):
        return self._derived(lambda name, a: a[..., rows] if name == "block" else a[rows])

    def readonly(self):
        def frozen(name: str, a: np.ndarray) -> np.ndarray:
            ro = a.view()
            ro.flags.writeable = False
            return ro

        return self._derived(frozen)

    def mark_fresh(self, tick: int, stamp_ns: int) -> None:
        """Record that every row of this view was measured now (drivers call this after a read)."""
        self.updated_tick.fill(tick)  # (fill: a third cheaper than an indexed assignment, every tick)
        self.stamp_ns.fill(stamp_ns)

    def __len__(self) -> int:
        return self.block.shape[-1]


class JointState(_Rows):
    """Measured joint values. ``temperature`` is NaN where a driver does not report it."""

    _fields = JOINT_STATE_FIELDS
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    motor_position: np.ndarray
    motor_velocity: np.ndarray
    temperature: np.ndarray

    def __init__(self, n: int) -> None:
        super().__init__(n)
        self.temperature[:] = np.nan


class JointCommand(_Rows):
    """Joint commands; ``mode`` says which fields a driver applies."""

    _fields = JOINT_COMMAND_FIELDS
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray
    feedforward: np.ndarray
    mode: np.ndarray

    def __init__(self, n: int) -> None:
        super().__init__(n)
        self.mode = np.zeros(n, dtype=np.int8)

    def rest_at(self, position: np.ndarray) -> None:
        """Command ``position``, at rest, without effort: where a robot starts from (activation,
        a re-arm from ``disabled``), so that nothing jumps."""
        np.copyto(self.position, position)
        self.velocity[:] = 0.0
        self.effort[:] = 0.0
        self.feedforward[:] = 0.0


def per_joint(
    values: float | dict[str, float] | Sequence[float], names: Sequence[str], default: float = 0.0
) -> np.ndarray:
    """An array over ``names`` from a scalar, a {joint: value} map (others get ``default``) or a list."""
    if isinstance(values, dict):
        return np.array([float(values.get(name, default)) for name in names])
    if isinstance(values, (int, float)):
        return np.full(len(names), float(values))
    out = np.array(values, dtype=np.float64)
    if out.shape != (len(names),):
        raise ValueError(f"expected {len(names)} values, got {out.shape}")
    return out


# ---------------------------------------------------------------- devices besides joints


class DeviceRecord:
    """One device's values: numpy views into its group's arrays, written in place."""

    if TYPE_CHECKING:
        # a field of the group (``record.grasp``), set per record in __init__
        def __getattr__(self, field: str) -> np.ndarray: ...

    def __init__(self, group: DeviceGroup, index: int, name: str) -> None:
        self.name = name
        self.index = index
        self._group = group
        for field in group.fields:
            setattr(self, field, getattr(group, field)[index, ...])  # a view, 0-d for scalars

    @property
    def group(self) -> DeviceGroup:
        """The group whose row ``index`` this record is (a driver may fill rows at once)."""
        return self._group

    def mark_fresh(self, tick: int, stamp_ns: int) -> None:
        self._group.updated_tick[self.index] = tick
        self._group.stamp_ns[self.index] = stamp_ns

    @property
    def updated_tick(self) -> int:
        return int(self._group.updated_tick[self.index])

    @property
    def fault(self) -> int:
        return int(self._group.fault[self.index])

    def set_fault(self, bits: int) -> None:
        """Set this device's ``Fault`` bits (0 clears them); the driver owning it decides."""
        self._group.fault[self.index] = bits


class DeviceGroup:
    """All devices of one kind, as arrays with one row per device."""

    kind = ""
    fields: tuple[str, ...] = ()
    shapes: dict[str, tuple[tuple[int, ...], type]] = {}

    def __init__(self, names: Sequence[str]) -> None:
        self.names = tuple(names)
        n = len(self.names)
        #: When every field is a float64 vector (IMU, force/torque): one row of ``values`` per
        #: device, the fields its column ranges (``columns``), so that a driver can fill a
        #: device, or a run of them, with one call. None otherwise.
        self.values: np.ndarray | None = None
        self.columns: dict[str, slice] = {}
        if self.fields and all(len(shape) == 1 and dtype is np.float64 for shape, dtype in self.shapes.values()):
            start = 0
            for field in self.fields:
                width = self.shapes[field][0][0]
                self.columns[field] = slice(start, start + width)
                start += width
            self.values = np.zeros((n, start))
            for field, cols in self.columns.items():
                setattr(self, field, self.values[:, cols])
        else:
            for field in self.fields:
                shape, dtype = self.shapes[field]
                setattr(self, field, np.zeros((n, *shape), dtype=dtype))
        self.stamp_ns = np.zeros(n, dtype=np.int64)
        self.updated_tick = np.full(n, -1, dtype=np.int64)
        self.fault = np.zeros(n, dtype=np.uint32)
        self._init_values()
        self.records = {name: DeviceRecord(self, i, name) for i, name in enumerate(self.names)}

    def _init_values(self) -> None:
        pass

    def __getitem__(self, name: str) -> DeviceRecord:
        return self.records[name]

    def __len__(self) -> int:
        return len(self.names)


class ImuGroup(DeviceGroup):
    """Orientation as a unit quaternion (w, x, y, z), angular velocity (rad/s), acceleration (m/s²).
    A field of NaN is not measured (an IMU without orientation reads a quaternion of NaN)."""

    kind = "imu"
    fields = ("quaternion", "angular_velocity", "linear_acceleration")
    shapes = {
        "quaternion": ((4,), np.float64),
        "angular_velocity": ((3,), np.float64),
        "linear_acceleration": ((3,), np.float64),
    }
    # the arrays DeviceGroup.__init__ sets, one per field
    quaternion: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray

    def _init_values(self) -> None:
        self.quaternion[:, 0] = 1.0


class ForceTorqueGroup(DeviceGroup):
    """Force (N) and torque (N·m) in the sensor frame."""

    kind = "force_torque"
    fields = ("force", "torque")
    shapes = {"force": ((3,), np.float64), "torque": ((3,), np.float64)}
    force: np.ndarray
    torque: np.ndarray


class HandGroup(DeviceGroup):
    """Grippers: command ``grasp`` 0 (open) .. 1 (closed) with speed and force limits; measured state.

    As in XBot, a hand is addressed through the joint that carries it (``joint`` per hand).
    """

    kind = "hand"
    fields = ("grasp", "speed", "force", "position", "effort", "object_detected")
    shapes = {
        "grasp": ((), np.float64),
        "speed": ((), np.float64),
        "force": ((), np.float64),
        "position": ((), np.float64),
        "effort": ((), np.float64),
        "object_detected": ((), np.bool_),
    }
    grasp: np.ndarray
    speed: np.ndarray
    force: np.ndarray
    position: np.ndarray
    effort: np.ndarray
    object_detected: np.ndarray

    def __init__(self, names: Sequence[str], joints: Sequence[str | None] = ()) -> None:
        super().__init__(names)
        joints = list(joints) + [None] * (len(self.names) - len(joints))
        self.joint_of = dict(zip(self.names, joints, strict=True))

    def _init_values(self) -> None:
        self.speed[:] = 1.0
        self.force[:] = 1.0


DEVICE_GROUPS: dict[str, type[DeviceGroup]] = {cls.kind: cls for cls in (ImuGroup, ForceTorqueGroup, HandGroup)}


# ---------------------------------------------------------------- the robot and its views


class Robot:
    """The joint model and every array of state and command. Built once from the configuration."""

    def __init__(
        self,
        name: str,
        joints: Sequence[JointSpec],
        *,
        period_ns: int = 1_000_000,
        devices: Iterable[tuple[str, str, str | None]] = (),
        model_path: Any = None,
    ) -> None:
        self.name = name
        self.model_path = model_path  # the robot's model file (MJCF), if the config names one
        self.joints = tuple(joints)
        self.joint_names = tuple(j.name for j in self.joints)
        self._joint_index = {name: i for i, name in enumerate(self.joint_names)}
        n = len(self.joints)
        self.position_min = np.array([j.position_min for j in self.joints], dtype=np.float64)
        self.position_max = np.array([j.position_max for j in self.joints], dtype=np.float64)
        self.velocity_limit = np.array([j.velocity for j in self.joints], dtype=np.float64)
        self.acceleration_limit = np.array([j.acceleration for j in self.joints], dtype=np.float64)
        self.effort_limit = np.array([j.effort for j in self.joints], dtype=np.float64)
        self.state = JointState(n)
        self.command = JointCommand(n)
        self.clock = TickInfo(period_ns)
        by_kind: dict[str, list[tuple[str, str | None]]] = {kind: [] for kind in DEVICE_GROUPS}
        for dev_name, kind, joint in devices:
            by_kind[kind].append((dev_name, joint))
        self.imu = ImuGroup([d for d, _ in by_kind["imu"]])
        self.force_torque = ForceTorqueGroup([d for d, _ in by_kind["force_torque"]])
        self.hand = HandGroup([d for d, _ in by_kind["hand"]], [j for _, j in by_kind["hand"]])
        self.device_groups: dict[str, DeviceGroup] = {
            "imu": self.imu,
            "force_torque": self.force_torque,
            "hand": self.hand,
        }

    @property
    def dof(self) -> int:
        return len(self.joints)

    def joint_index(self, name: str) -> int:
        return self._joint_index[name]

    def indices(self, names: Iterable[str]) -> np.ndarray:
        return np.array([self._joint_index[n] for n in names], dtype=np.intp)

    def per_joint(self, values: float | dict[str, float] | Sequence[float], default: float = 0.0) -> np.ndarray:
        return per_joint(values, self.joint_names, default)

    def device(self, name: str) -> DeviceRecord:
        for group in self.device_groups.values():
            if name in group.records:
                return group.records[name]
        raise KeyError(name)

    def device_kind(self, name: str) -> str:
        for kind, group in self.device_groups.items():
            if name in group.records:
                return kind
        raise KeyError(name)

    def hand_for_joint(self, joint: str) -> DeviceRecord:
        """The hand carried by ``joint`` (XBot's joint-to-hand mapping)."""
        for hand, carrier in self.hand.joint_of.items():
            if carrier == joint:
                return self.hand.records[hand]
        raise KeyError(f"no hand is carried by joint {joint!r}")

    def joint_slice(self, names: Sequence[str]) -> slice:
        """The contiguous slice of ``names`` (config validation guarantees contiguity)."""
        if not names:
            return slice(0, 0)
        idx = self.indices(names)
        start = int(idx[0])
        if not np.array_equal(idx, np.arange(start, start + len(idx))):
            raise ValueError(f"joints {list(names)} are not a contiguous run of the robot's joints")
        return slice(start, start + len(idx))

    def driver_view(self, joints: Sequence[str], devices: Sequence[str] = ()) -> DriverView:
        return DriverView(self, self.joint_slice(joints), tuple(devices))

    def controller_view(self) -> RobotView:
        return RobotView(self)


class DriverEvents:
    """Where a driver's view sends what its driver reports: the loop attaches its safety
    supervisor's (:meth:`DriverView.attach`). This one, a view's own until then, only logs."""

    def fault(self, phase: str, reason: str, hold: bool) -> None:
        log.error("driver fault in %s (no loop attached%s): %s", phase, ", hold asked" if hold else "", reason)

    def resync(self, mask: np.ndarray) -> None:
        pass


class DriverView:
    """What one driver may touch: its joint rows (state writable, command read) and its devices."""

    def __init__(self, robot: Robot, rows: slice, devices: tuple[str, ...]) -> None:
        self.robot_name = robot.name
        self.model_path = robot.model_path
        self.rows = rows
        self.joint_names = robot.joint_names[rows]
        self.state = robot.state.view(rows)
        self.command = robot.command.view(rows)
        self.clock = robot.clock
        self.position_min = robot.position_min[rows]
        self.position_max = robot.position_max[rows]
        self.velocity_limit = robot.velocity_limit[rows]
        self.effort_limit = robot.effort_limit[rows]
        self.devices = {name: robot.device(name) for name in devices}
        self.device_kinds = {name: robot.device_kind(name) for name in devices}
        self.fresh_tick = -1
        """The last tick this driver's joints were all measured (``mark_fresh`` sets it)."""
        self.every = 1
        """The driver is read and written on every ``every``-th tick only (``[[driver]] every``)."""
        self._events = DriverEvents()

    def attach(self, events: DriverEvents) -> None:
        """The loop's side of :meth:`fault` and :meth:`resync` (set when the loop is built)."""
        self._events = events

    def fault(self, reason: str, *, hold: bool = True, phase: str = "read") -> None:
        """Report a condition of this driver's hardware, the one way a driver does: a drive
        faulted, a device lost, the KRC out of command mode. It is recorded once per call
        (logged, listed in the run report, the CLI exits 1, ``rearm()`` waits for
        ``reset_faults()``) and, with ``hold`` (the default), the robot is held so that
        nothing moves through it; ``hold=False`` for what the run survives (one sensor lost).
        Set the joints' or devices' fault bits too, while the condition lasts.

        A failure the driver cannot go on from is not reported: it raises from ``read()`` or
        ``write()`` (a :class:`~aiohal.errors.DriverError` names it best), and the loop
        isolates the driver, e-stops it and holds the robot."""
        self._events.fault(phase, reason, hold)

    def resync(self, mask: np.ndarray) -> None:
        """These of the driver's joints (a bool mask) were re-enabled where they stand: the
        loop makes their command continue from the measured position (bumpless)."""
        self._events.resync(mask)

    def per_joint(self, values: float | dict[str, float] | Sequence[float], default: float = 0.0) -> np.ndarray:
        """An array over this driver's joints (options given as a scalar or a {joint: value} map)."""
        return per_joint(values, self.joint_names, default)

    def devices_of(self, kind: str) -> list[DeviceRecord]:
        return [rec for name, rec in self.devices.items() if self.device_kinds[name] == kind]

    def device_runs(self) -> list[tuple[DeviceGroup, slice]]:
        """This driver's devices as runs of adjacent rows of their groups, ``(group, rows)``:
        a driver fills or stamps a run with one call instead of one per device."""
        by_group: dict[int, tuple[DeviceGroup, list[int]]] = {}
        for record in self.devices.values():
            by_group.setdefault(id(record.group), (record.group, []))[1].append(record.index)
        runs = []
        for group, indices in by_group.values():
            indices.sort()
            start: int | None = indices[0]
            for previous, row in zip(indices, [*indices[1:], None], strict=True):
                if row != previous + 1:  # the run ends at ``previous`` (None: the last row)
                    runs.append((group, slice(start, previous + 1)))
                    start = row
        return runs

    def mark_fresh(self, stamp_rows: bool = True) -> None:
        """Stamp all joints of this driver with the current tick (call after a successful read).

        The loop's stale-feedback check reads ``fresh_tick``; controllers see per-joint stamps.
        ``stamp_rows=False``: the driver already stamped every one of its rows itself (e.g. in
        a compiled decode), only the driver's tick is recorded.
        """
        clock = self.clock
        self.fresh_tick = clock.tick
        if stamp_rows:
            self.state.mark_fresh(clock.tick, clock.now_ns)

    @property
    def dof(self) -> int:
        return len(self.joint_names)


class RobotView:
    """What a controller sees: read-only state, writable command, limits and names."""

    def __init__(self, robot: Robot) -> None:
        self.name = robot.name
        self.model_path = robot.model_path
        self.joints = robot.joints
        self.joint_names = robot.joint_names
        self.dof = robot.dof
        self.state = robot.state.readonly()
        self.command = robot.command
        self.clock = robot.clock
        self.imu = robot.imu
        self.force_torque = robot.force_torque
        self.hand = robot.hand
        self.position_min = robot.position_min
        self.position_max = robot.position_max
        self.velocity_limit = robot.velocity_limit
        self.acceleration_limit = robot.acceleration_limit
        self.effort_limit = robot.effort_limit
        self._robot = robot

    def joint_index(self, name: str) -> int:
        return self._robot.joint_index(name)

    def indices(self, names: Iterable[str]) -> np.ndarray:
        return self._robot.indices(names)

    def per_joint(self, values, default: float = 0.0) -> np.ndarray:
        return self._robot.per_joint(values, default)

    def hand_for_joint(self, joint: str) -> DeviceRecord:
        return self._robot.hand_for_joint(joint)
