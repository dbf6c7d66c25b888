"""CiA 402 drives on a bus's process data: state machines, bumpless enable, unit conversion.

Bus-independent: a :class:`DriveGroup` works on two byte buffers (the inputs the drives sent,
the outputs to send them) and each drive's byte offsets in them, whether the buffers are an
EtherCAT process image or the PDOs of CANopen nodes laid end to end. The per-cycle
conversions are compiled kernels (:mod:`.drive_kernels`); the state machines
(:mod:`.cia402`) stay in Python and run only when a statusword changed or a drive is not
steadily enabled.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from aiohal.core import compiled_entry
from aiohal.robot import JOINT_COMMAND_FIELDS, DriverView, Fault, JointCommand, JointState

from . import drive_kernels as kernels
from .busvar import ProcessImage, UnknownVariableError, VariableTypeError
from .cia402 import Cia402Drive, DriveEvent, DriveUnits, EventKind, State, Target

log = logging.getLogger(__name__)

DRIVE_INPUTS = ("Statusword", "Position actual value", "Velocity actual value", "Torque actual value", "Error code")
DRIVE_INPUT_TYPES = ("u16", "i32", "i32", "i16", "u16")
DRIVE_OUTPUTS = ("Controlword", "Target position", "Target velocity", "Target torque", "Modes of operation")
DRIVE_OUTPUT_TYPES = ("u16", "i32", "i32", "i16", "i8")
#: outputs a drive may map for feed-forward in CSP: the controller's target velocity and its
#: effort plus feed-forward are sent there, where the drive adds them to its own loops'
DRIVE_OFFSETS = ("Velocity offset", "Torque offset")  # 0x60B1, 0x60B2
DRIVE_OFFSET_TYPES = ("i32", "i16")
#: bytes of each variable, inputs, outputs then offsets
DRIVE_SIZES = tuple(int(t[1:]) // 8 for t in DRIVE_INPUT_TYPES + DRIVE_OUTPUT_TYPES + DRIVE_OFFSET_TYPES)
NOT_MAPPED = -1  # the offset of a feed-forward output the drive does not map: nothing is written


@dataclass(frozen=True)
class DriveSpec:
    """One drive: its slave name, the joint row it serves (in the driver's rows) and its units."""

    slave: str
    joint: str
    row: int
    units: DriveUnits
    position_offset: float = 0.0  # rad added to the drive's position (joint zero ≠ encoder zero)


def check_types(image: ProcessImage, slave: str, names: Sequence[str], types: Sequence[str]) -> None:
    for name, want in zip(names, types, strict=True):
        var = image.variable(f"{slave}.{name}")
        if var.type != want or var.shape != ():
            raise VariableTypeError(
                f'"{var.full_name}" is {var.type}{list(var.shape) or ""}, a CiA 402 drive maps it as {want}'
            )


class DriveGroup:
    """Every CiA 402 drive of one bus: state machines, bumpless enable, unit conversion.

    The per-cycle conversions (:meth:`decode`, :meth:`write`) are compiled kernels
    (:mod:`.drive_kernels`) over the buffers' bytes and the robot's arrays; the state machines stay
    in Python and run only when a statusword changed or a drive is not steadily enabled."""

    def __init__(
        self, image: ProcessImage, specs: Sequence[DriveSpec], *, stuck_after: int, target: Target = Target.ENABLED
    ) -> None:
        """On a process image whose slaves map every variable of :data:`DRIVE_INPUTS` and
        :data:`DRIVE_OUTPUTS` with its type (checked here, by name), and those of
        :data:`DRIVE_OFFSETS` they offer."""
        offsets = []
        for s in specs:
            check_types(image, s.slave, DRIVE_INPUTS, DRIVE_INPUT_TYPES)
            check_types(image, s.slave, DRIVE_OUTPUTS, DRIVE_OUTPUT_TYPES)
            extra = []
            for name, kind in zip(DRIVE_OFFSETS, DRIVE_OFFSET_TYPES, strict=True):
                try:
                    image.variable(f"{s.slave}.{name}")
                except UnknownVariableError:
                    extra.append(NOT_MAPPED)
                    continue
                check_types(image, s.slave, (name,), (kind,))
                extra += image.byte_offsets(s.slave, (name,), writable=True)
            offsets.append(
                image.byte_offsets(s.slave, DRIVE_INPUTS)
                + image.byte_offsets(s.slave, DRIVE_OUTPUTS, writable=True)
                + extra
            )
        self._setup(image.inputs, image.outputs, offsets, specs, stuck_after, target)

    @classmethod
    def on_buffers(
        cls,
        inputs: np.ndarray,
        outputs: np.ndarray,
        offsets: Sequence[Sequence[int]],
        specs: Sequence[DriveSpec],
        *,
        stuck_after: int,
        target: Target = Target.ENABLED,
    ) -> DriveGroup:
        """On plain ``uint8`` buffers: per drive, the byte offsets of the variables of
        :data:`DRIVE_INPUTS` in ``inputs`` then of :data:`DRIVE_OUTPUTS` in ``outputs``,
        optionally followed by those of :data:`DRIVE_OFFSETS` (``NOT_MAPPED`` where the drive
        has none; all of them when not given) (little-endian, of those types; the caller
        checked them). A variable a drive does not map may point at spare zero bytes past its
        buffer's data: it then reads 0, and what is written there is never sent."""
        required = len(DRIVE_INPUTS) + len(DRIVE_OUTPUTS)
        offsets = [list(o) + [NOT_MAPPED] * len(DRIVE_OFFSETS) if len(o) == required else list(o) for o in offsets]
        for i, o in enumerate(offsets):
            if len(o) != required + len(DRIVE_OFFSETS):
                raise ValueError(
                    f"drive {i}: {required} or {required + len(DRIVE_OFFSETS)} offsets expected, got {len(o)}"
                )
            for k, (offset, size) in enumerate(zip(o, DRIVE_SIZES, strict=True)):
                buf = inputs if k < len(DRIVE_INPUTS) else outputs
                if k >= required and offset == NOT_MAPPED:
                    continue
                if not 0 <= offset <= len(buf) - size:
                    raise ValueError(
                        f"drive {i}: offset {offset} of {(DRIVE_INPUTS + DRIVE_OUTPUTS + DRIVE_OFFSETS)[k]!r} is outside "
                        f"its buffer of {len(buf)} bytes"
                    )
        group = cls.__new__(cls)
        group._setup(inputs, outputs, offsets, specs, stuck_after, target)
        return group

    def _setup(
        self,
        inputs: np.ndarray,
        outputs: np.ndarray,
        offsets: Sequence[Sequence[int]],
        specs: Sequence[DriveSpec],
        stuck_after: int,
        target: Target,
    ) -> None:
        self.specs = list(specs)
        self._inputs, self._outputs = inputs, outputs
        self.rows = [s.row for s in specs]
        self._layout = np.array([[*list(o), s.row] for o, s in zip(offsets, specs, strict=True)], dtype=np.int64)
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
        self._decode = compiled_entry.compiled_for(
            kernels.decode_drives, (self._inputs, self._layout, self._constants, self.ints, state, ticks, stamps, 0, 0)
        )

    def _check_encode(self, block: np.ndarray, mode: np.ndarray) -> None:
        self._encode = compiled_entry.compiled_for(
            kernels.encode_drives, (self._outputs, self._layout, self._constants, self.ints, block, mode, False)
        )

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
                raise ValueError(f"the joint command has {block.shape[-1]} joints, a drive reads row {max(self.rows)}")
            if block.ndim != 2 or block.shape[0] < len(JOINT_COMMAND_FIELDS):
                raise ValueError(
                    f"the joint command block has shape {block.shape}, {len(JOINT_COMMAND_FIELDS)} rows are needed"
                )
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

    def reset_and_enable(self) -> list[str]:
        """Grant one fault reset to every drive in fault and enable again those that left
        Operation enabled unasked (parked by :func:`respond_to_event`); their names."""
        names = self.reset_faults()
        for machine in self.machines:
            if machine.target is Target.DISABLED:
                machine.target = Target.ENABLED
                names.append(machine.name)
        self.invalidate()
        return sorted(set(names))

    def all_enabled(self) -> bool:
        return all(m.enabled and not m.hold_target for m in self.machines)


def respond_to_event(
    drives: DriveGroup, i: int, event: DriveEvent, view: DriverView, mask: np.ndarray, who: str, detail: str = ""
) -> None:
    """What the HAL does on a drive's event, for every bus: a fault, a drive that left
    Operation enabled unasked (parked: enabling it again is the application's decision) or a
    stall faults its joint, is reported and holds the robot; a drive enabled again clears its
    joint's fault and its command continues from where it stands (``view.resync``).
    ``mask`` is the driver's scratch of one bool per joint; ``detail`` is added to a fault's
    reason (e.g. an EMCY's code); ``who`` starts the log lines ("ethercat arm")."""
    spec = drives.specs[i]
    row = spec.row
    fault = view.state.fault
    kind = event.kind
    machine = drives.machines[i]
    if kind is EventKind.FAULT_ENTERED:
        fault[row] |= Fault.HARDWARE
        reason = f"joint {spec.joint}: {event}{detail}"
        view.fault(reason)
    elif (
        kind is EventKind.LOST_ENABLED
        and event.state not in (State.FAULT_REACTION_ACTIVE, State.FAULT)
        and machine.target is Target.ENABLED
    ):
        machine.target = Target.DISABLED
        drives.invalidate()
        fault[row] |= Fault.HARDWARE
        reason = (
            f"joint {spec.joint}: drive {spec.slave!r} left Operation enabled ({event.state.label}); "
            "reset_faults() enables it again"
        )
        view.fault(reason)
    elif kind is EventKind.STUCK:
        fault[row] |= Fault.HARDWARE
        view.fault(f"joint {spec.joint}: {event}")
    elif kind is EventKind.BECAME_ENABLED:
        fault[row] &= ~np.uint32(Fault.HARDWARE)
        mask[:] = False
        mask[row] = True
        view.resync(mask)  # its command continues from where it stands
        log.warning("%s: joint %s enabled where it stands", who, spec.joint)
    else:
        log.info("%s: %s", who, event)
