"""Device classes on bus variables (LOLA): CiA 402 drives, IMUs and force/torque sensors.

Each class links the variables it needs by name at bring-up (errors name the slave and the
variable, types are checked) and then moves values between the process image and the
robot's records once per cycle: the drives through compiled kernels (:mod:`.kernels`), the
sensors, one or two per bus, with one ``struct`` call each (:class:`~aiohal.fieldbus.busvar.RecordCodec`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from aiohal import kernel_call
from aiohal.fieldbus.busvar import ProcessImage, VariableTypeError
from aiohal.fieldbus.cia402 import Cia402Drive, DriveEvent, DriveUnits, Target
from aiohal.robot import (
    JOINT_COMMAND_FIELDS,
    DeviceRecord,
    Fault,
    JointCommand,
    JointState,
)

from . import kernels

DRIVE_INPUTS = ("Statusword", "Position actual value", "Velocity actual value", "Torque actual value", "Error code")
DRIVE_INPUT_TYPES = ("u16", "i32", "i32", "i16", "u16")
DRIVE_OUTPUTS = ("Controlword", "Target position", "Target velocity", "Target torque", "Modes of operation")
DRIVE_OUTPUT_TYPES = ("u16", "i32", "i32", "i16", "i8")


@dataclass(frozen=True)
class DriveSpec:
    """One drive: its slave name, the joint row it serves (in the driver's rows) and its units."""

    slave: str
    joint: str
    row: int
    units: DriveUnits
    position_offset: float = 0.0  # rad added to the drive's position (joint zero ≠ encoder zero)


def _check_types(image: ProcessImage, slave: str, names: Sequence[str], types: Sequence[str]) -> None:
    for name, want in zip(names, types, strict=True):
        var = image.variable(f"{slave}.{name}")
        if var.type != want or var.shape != ():
            raise VariableTypeError(f'"{var.full_name}" is {var.type}{list(var.shape) or ""}, a CiA 402 drive '
                                    f"maps it as {want}")


class DriveGroup:
    """Every CiA 402 drive of one bus: state machines, bumpless enable, unit conversion.

    The per-cycle conversions (:meth:`decode`, :meth:`write`) are compiled kernels
    (:mod:`.kernels`) over the image's bytes and the robot's arrays; the state machines stay
    in Python and run only when a statusword changed or a drive is not steadily enabled."""

    def __init__(self, image: ProcessImage, specs: Sequence[DriveSpec], *, stuck_after: int,
                 target: Target = Target.ENABLED) -> None:
        self.specs = list(specs)
        for s in specs:
            _check_types(image, s.slave, DRIVE_INPUTS, DRIVE_INPUT_TYPES)
            _check_types(image, s.slave, DRIVE_OUTPUTS, DRIVE_OUTPUT_TYPES)
        self._inputs, self._outputs = image.inputs, image.outputs
        self.rows = [s.row for s in specs]
        self._layout = np.array([image.byte_offsets(s.slave, DRIVE_INPUTS)
                                 + image.byte_offsets(s.slave, DRIVE_OUTPUTS, writable=True) + [s.row]
                                 for s in specs], dtype=np.int64)
        constants = np.zeros((len(specs), 6))
        for i, s in enumerate(specs):
            u = s.units
            constants[i, kernels.RAD_PER_COUNT] = u.rad_per_count
            constants[i, kernels.MOTOR_RAD_PER_COUNT] = 2.0 * math.pi / u.counts_per_rev
            constants[i, kernels.NM_PER_PER_MILLE] = u.nm_per_per_mille
            constants[i, kernels.POSITION_OFFSET] = s.position_offset
            constants[i, kernels.COUNTS_PER_RAD] = u.counts_per_rad
            constants[i, kernels.PER_MILLE_PER_NM] = u.per_mille_per_nm
        self._constants = constants
        self.machines = [Cia402Drive(s.slave, target=target, stuck_after=stuck_after) for s in specs]
        self._generation = 0  # bumped by every request: a pass of the machines that saw none may skip the next
        #: per drive, columns named in kernels: statusword, error code, raw int32 position,
        #: unwrapped counts, controlword, hold (target = actual: not following the command yet)
        self.ints = np.zeros((len(specs), 7), dtype=np.int64)
        self.ints[:, kernels.HOLD] = 1
        self.statuswords = self.ints[:, kernels.STATUSWORD]
        self.error_codes = self.ints[:, kernels.ERROR_CODE]
        self.raw_position = self.ints[:, kernels.RAW_POSITION]
        self.counts = self.ints[:, kernels.COUNTS]
        self.controlwords = self.ints[:, kernels.CONTROLWORD]
        self.hold = self.ints[:, kernels.HOLD]
        self._changed = True  # a statusword or error code changed since the machines last ran
        self._steady = False  # every drive enabled, following, nothing pending
        # decode writes position, velocity, effort, motor position by row: into the robot's state
        # once bound, and into these private rows when not (or when cycled off the loop's thread)
        self._scratch = np.zeros((4, max(self.rows) + 1))
        self._state = self._scratch
        self._scratch_stamps = np.zeros((2, max(self.rows) + 1), dtype=np.int64)  # updated_tick, stamp_ns
        self._ticks, self._stamps = self._scratch_stamps
        self._no_command = np.zeros((len(JOINT_COMMAND_FIELDS), max(self.rows) + 1))
        self._no_mode = np.zeros(max(self.rows) + 1, dtype=np.int8)
        self._checked_block: np.ndarray | None = None  # the command arrays checked for the encode kernel
        self._checked_mode: np.ndarray | None = None
        # the kernels are called directly (numba's dispatch would be most of the call): every
        # array they are given is checked first, here, in bind_state and for each new command
        self._check_decode(self._scratch, *self._scratch_stamps)
        self._check_encode(self._no_command, self._no_mode)
        self.write_holding()

    def _check_decode(self, state: np.ndarray, ticks: np.ndarray, stamps: np.ndarray) -> None:
        self._decode = kernel_call.compiled_for(
            kernels.decode_drives, (self._inputs, self._layout, self._constants, self.ints, state, ticks, stamps, 0, 0))

    def _check_encode(self, block: np.ndarray, mode: np.ndarray) -> None:
        self._encode = kernel_call.compiled_for(
            kernels.encode_drives, (self._outputs, self._layout, self._constants, self.ints, block, mode, False))

    def __len__(self) -> int:
        return len(self.specs)

    # ------------------------------------------------------------ per cycle

    def bind_state(self, state: JointState) -> None:
        """The robot's joint state (the driver's rows) that :meth:`decode` writes: position,
        velocity, effort (rad, rad/s, N·m) and motor position (rad), and each row's stamps."""
        block = state.block
        if block.dtype != np.float64 or block.ndim != 2 or not block.flags.writeable or block.shape[0] < 4:
            raise ValueError("the joint state: a writable float64 block of at least 4 rows is needed")
        if block.shape[1] <= max(self.rows):
            raise ValueError(f"the joint state has {block.shape[1]} joints, a drive writes row {max(self.rows)}")
        for stamps in (state.updated_tick, state.stamp_ns):
            if stamps.dtype != np.int64 or stamps.shape != block.shape[1:] or not stamps.flags.writeable:
                raise ValueError("the joint state: writable int64 stamps, one per joint, are needed")
        self._check_decode(block, state.updated_tick, state.stamp_ns)
        self._state = block
        self._ticks, self._stamps = state.updated_tick, state.stamp_ns

    def decode(self, tick: int, now_ns: int, into_state: bool = True) -> None:
        """Unpack every drive's inputs; unwrap the positions; convert to SI units and write
        them into the bound state, each drive's joint stamped measured at ``tick`` /
        ``now_ns`` (``into_state=False``: into private rows, for a cycle made off the loop's
        thread, which must not touch the robot's state)."""
        if into_state:
            state, ticks, stamps = self._state, self._ticks, self._stamps
        else:
            state, (ticks, stamps) = self._scratch, self._scratch_stamps
        if self._decode(self._inputs, self._layout, self._constants, self.ints, state, ticks, stamps, tick, now_ns):
            self._changed = True

    def update_machines(self, on_event: Callable[[int, DriveEvent], None]) -> None:
        """Run the state machines when a statusword changed or a drive is not steadily enabled;
        their controlwords and hold flags are used by :meth:`write`."""
        if self._steady and not self._changed:
            return
        self._changed = False
        generation = self._generation
        status, errors = self.statuswords.tolist(), self.error_codes.tolist()
        steady = True
        for i, machine in enumerate(self.machines):
            self.controlwords[i] = machine.update(status[i], errors[i])
            self.hold[i] = machine.hold_target
            for event in machine.events:
                on_event(i, event)
            if machine.hold_target or machine.target is not Target.ENABLED or machine.controlword & 0x80:
                steady = False
        self._steady = steady and generation == self._generation  # a request from another thread meanwhile

    def invalidate(self) -> None:
        """Run the machines next cycle whatever the statuswords (after a request)."""
        self._generation += 1
        self._steady = False

    def write(self, command: JointCommand) -> None:
        """Commands → targets, modes and controlwords; a drive in ``hold`` gets target = actual,
        and only the values the drive's mode uses are sent (the others are 0)."""
        block, mode = command.block, command.mode
        if block is not self._checked_block or mode is not self._checked_mode:  # the kernel checks nothing
            if block.shape[-1] <= max(self.rows) or mode.shape[-1] <= max(self.rows):
                raise ValueError(f"the joint command has {block.shape[-1]} joints, a drive reads row "
                                 f"{max(self.rows)}")
            if block.ndim != 2 or block.shape[0] < len(JOINT_COMMAND_FIELDS):
                raise ValueError(f"the joint command block has shape {block.shape}, "
                                 f"{len(JOINT_COMMAND_FIELDS)} rows are needed")
            self._check_encode(block, mode)
            self._checked_block, self._checked_mode = block, mode
        self._encode(self._outputs, self._layout, self._constants, self.ints, block, mode, False)

    def write_holding(self) -> None:
        """Every drive: its controlword, target = actual (before the first tick, and in a stop)."""
        self._encode(self._outputs, self._layout, self._constants, self.ints, self._no_command, self._no_mode, True)

    def request(self, target: Target) -> None:
        for machine in self.machines:
            machine.target = target
        self.invalidate()

    def reset_faults(self) -> list[str]:
        """Grant one fault reset to every drive in fault; their names."""
        reset = []
        for machine in self.machines:
            if machine.faulted:
                machine.reset_fault()
                reset.append(machine.name)
        self.invalidate()
        return reset

    def all_enabled(self) -> bool:
        return all(m.enabled and not m.hold_target for m in self.machines)


class SensorDevice:
    """A sensor slave → one device record: its variables (by the keys of ``GROUPS``, with the
    number of values each must have) and an optional status read with one codec."""

    GROUPS: tuple[tuple[str, int], ...] = ()

    def __init__(self, image: ProcessImage, slave: str, record: DeviceRecord, variables: dict[str, str]) -> None:
        self.slave = slave
        self.record = record
        names = [variables[key] for key, _ in self.GROUPS]
        for name, (_, n) in zip(names, self.GROUPS, strict=True):
            _check_group(image, slave, name, n)
        self.has_status = bool(variables.get("status"))
        self.codec = image.codec(slave, names + ([variables["status"]] if self.has_status else []))

    def read(self, tick: int, now_ns: int, lost: bool) -> None:
        rec = self.record
        if lost:
            rec.set_fault(Fault.HARDWARE)
            return
        values = self.codec.unpack()
        status = values[-1] if self.has_status else 1
        if self.fill(values, status):
            rec.mark_fresh(tick, now_ns)
        rec.set_fault(0 if self.valid(status) else Fault.HARDWARE)

    def fill(self, values: tuple, status: int) -> bool:
        """Copy the values into the record; False if they were not taken (not fresh)."""
        raise NotImplementedError

    @staticmethod
    def valid(status: int) -> bool:
        return bool(status & 1)


class ImuDevice(SensorDevice):
    """An IMU slave → an ``imu`` record (quaternion w, x, y, z; rad/s; m/s²); status bit 0 = valid."""

    GROUPS = (("quaternion", 4), ("angular_velocity", 3), ("linear_acceleration", 3))

    def fill(self, values: tuple, status: int) -> bool:
        if not self.valid(status):  # an invalid orientation is not copied
            return False
        rec = self.record
        rec.quaternion[:] = values[0]
        rec.angular_velocity[:] = values[1]
        rec.linear_acceleration[:] = values[2]
        return True


class ForceTorqueDevice(SensorDevice):
    """A force/torque slave → a ``force_torque`` record (N, N·m); status bit 0 valid, bit 1 overload.

    With a ``control`` output variable, :meth:`tare` zeroes the sensor: control is 1 for
    ``TARE_CYCLES`` cycles, then 0 (sensors tare on the rising edge; a few cycles so that a
    lost frame does not lose the request)."""

    GROUPS = (("wrench", 6),)
    TARE_CYCLES = 10

    def __init__(self, image: ProcessImage, slave: str, record: DeviceRecord, variables: dict[str, str],
                 control: str | None = None) -> None:
        super().__init__(image, slave, record, variables)
        self.control = image.codec(slave, [control], writable=True) if control else None
        self.tare_left = 0  # cycles the control bit stays set

    def tare(self) -> None:
        if self.control is None:
            raise VariableTypeError(f'"{self.slave}" has no control output to tare with '
                                    "(its slave's variables.control names one)")
        self.tare_left = self.TARE_CYCLES

    def write_control(self) -> None:
        """One cycle of a pending tare (the loop's write)."""
        self.tare_left -= 1
        self.control.pack(1 if self.tare_left > 0 else 0)

    def fill(self, values: tuple, status: int) -> bool:
        wrench = values[0]
        self.record.force[:] = wrench[:3]
        self.record.torque[:] = wrench[3:]
        return True

    @staticmethod
    def valid(status: int) -> bool:
        return bool(status & 1) and not status & 2


def _check_group(image: ProcessImage, slave: str, name: str, n: int) -> None:
    var = image.variable(f"{slave}.{name}")
    if var.shape != (n,) or not var.byte_aligned:
        raise VariableTypeError(f'"{var.full_name}" must be {n} contiguous values, it is '
                                f"{var.type}{list(var.shape) or ''}")
