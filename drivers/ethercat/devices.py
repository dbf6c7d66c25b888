"""Device classes on bus variables (LOLA): CiA 402 drives, IMUs and force/torque sensors.

Each class links the variables it needs by name at bring-up (errors name the slave and the
variable, types are checked) and then moves values between the process image and the
robot's records once per cycle. A per-slave :class:`~aiohal.busvar.RecordCodec` reads or
writes a slave's variables with one ``struct`` call: for the handful of drives of a robot
this is several times cheaper than numpy, whose fixed cost per call (a few µs for a cast of
7 values on this kind of machine) would be paid a dozen times per cycle.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from aiohal.busvar import ProcessImage, VariableTypeError
from aiohal.cia402 import CSP, CST, CSV, Cia402Drive, DriveEvent, DriveUnits, Target
from aiohal.robot import DeviceRecord, Fault, Mode

_CSP = int(CSP)  # a plain int: struct packs it without an enum lookup
#: joint command mode → CiA 402 mode of operation (impedance runs as CSP: the drive's own loop)
MODE_OF_OPERATION = {int(Mode.NONE): _CSP, int(Mode.POSITION): _CSP, int(Mode.IMPEDANCE): _CSP,
                     int(Mode.VELOCITY): int(CSV), int(Mode.EFFORT): int(CST)}
DRIVE_INPUTS = ("Statusword", "Position actual value", "Velocity actual value", "Torque actual value", "Error code")
DRIVE_INPUT_TYPES = ("u16", "i32", "i32", "i16", "u16")
DRIVE_OUTPUTS = ("Controlword", "Target position", "Target velocity", "Target torque", "Modes of operation")
DRIVE_OUTPUT_TYPES = ("u16", "i32", "i32", "i16", "i8")
_I32, _I16 = 1 << 31, 1 << 15


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
    """Every CiA 402 drive of one bus: state machines, bumpless enable, unit conversion."""

    def __init__(self, image: ProcessImage, specs: Sequence[DriveSpec], *, stuck_after: int,
                 target: Target = Target.ENABLED) -> None:
        self.specs = list(specs)
        self.inputs, self.outputs = [], []
        for s in specs:
            _check_types(image, s.slave, DRIVE_INPUTS, DRIVE_INPUT_TYPES)
            _check_types(image, s.slave, DRIVE_OUTPUTS, DRIVE_OUTPUT_TYPES)
            self.inputs.append(image.codec(s.slave, DRIVE_INPUTS))
            self.outputs.append(image.codec(s.slave, DRIVE_OUTPUTS, writable=True))
        self.rows = [s.row for s in specs]
        # per-drive constants as Python floats (a loop over a few drives)
        self.rad_per_count = [float(s.units.rad_per_count) for s in specs]
        self.counts_per_rad = [float(s.units.counts_per_rad) for s in specs]
        self.motor_rad_per_count = [2.0 * math.pi / float(s.units.counts_per_rev) for s in specs]
        self.nm_per_per_mille = [float(s.units.nm_per_per_mille) for s in specs]
        self.per_mille_per_nm = [float(s.units.per_mille_per_nm) for s in specs]
        self.offset = [s.position_offset for s in specs]
        self.machines = [Cia402Drive(s.slave, target=target, stuck_after=stuck_after) for s in specs]
        self._generation = 0  # bumped by every request: a pass of the machines that saw none may skip the next
        n = len(specs)
        self.hold = [True] * n  # target = actual: the drive does not follow the command (yet)
        self.controlwords = [0] * n
        self.statuswords = [0] * n
        self.error_codes = [0] * n
        self.raw_position = [0] * n  # the drive's int32 counts, as last read
        self.counts = [0] * n  # multi-turn counts (unwrapped)
        self._started = False
        self._last_status: list[int] = []
        self._steady = False  # every drive enabled, following, nothing pending
        # decode writes position, velocity, effort, motor position by row: into the robot's state
        # once bound, and into these private rows when not (or when cycled off the loop's thread)
        self._scratch = np.zeros((4, max(self.rows) + 1))
        self._scratch_rows = tuple(memoryview(r) for r in self._scratch)
        self._state_rows = self._scratch_rows
        # what the per-cycle loops need, bound once: (struct function, buffer, offset), row and constants
        self._decode_plan = tuple(((c.unpack_from, c.buf, c.offset), row, rad, motor_rad, nm, off)
                                  for c, row, rad, motor_rad, nm, off
                                  in zip(self.inputs, self.rows, self.rad_per_count, self.motor_rad_per_count,
                                         self.nm_per_per_mille, self.offset, strict=True))
        self._encode_plan = tuple(((c.pack_into, c.buf, c.offset), row, k, off, per_mille)
                                  for c, row, k, off, per_mille in zip(self.outputs, self.rows, self.counts_per_rad,
                                                                       self.offset, self.per_mille_per_nm, strict=True))
        self._cmd_views: tuple | None = None
        self._cmd_arrays: tuple = ()

    def __len__(self) -> int:
        return len(self.specs)

    # ------------------------------------------------------------ per cycle

    def bind_state(self, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray,
                   motor_position: np.ndarray) -> None:
        """The robot's state rows (rad, rad/s, N·m; motor side in rad) that :meth:`decode`
        writes, element by element through memoryviews: no list or array per cycle."""
        views = []
        for name, array in (("position", position), ("velocity", velocity), ("effort", effort),
                            ("motor_position", motor_position)):
            if array.ndim != 1 or array.dtype != np.float64 or not array.flags.c_contiguous or not array.flags.writeable:
                raise ValueError(f"state {name}: a writable contiguous 1-D float64 array is needed")
            if len(array) <= max(self.rows):
                raise ValueError(f"state {name} has {len(array)} joints, a drive writes row {max(self.rows)}")
            views.append(memoryview(array))
        self._state_rows = tuple(views)

    def decode(self, into_state: bool = True) -> None:
        """Unpack every drive's inputs; unwrap the positions; convert to SI units and write
        them into the bound state rows (``into_state=False``: into private rows, for a cycle
        made off the loop's thread, which must not touch the robot's state)."""
        P, V, E, M = self._state_rows if into_state else self._scratch_rows
        counts, raw_position, statuswords, error_codes = self.counts, self.raw_position, self.statuswords, self.error_codes
        started = self._started
        i = 0
        for (unpack, buf, offset), row, rad, motor_rad, nm, off in self._decode_plan:
            sw, raw, v, t, err = unpack(buf, offset)
            statuswords[i] = sw
            error_codes[i] = err
            c = counts[i] + ((raw - raw_position[i] + _I32) & 0xFFFFFFFF) - _I32 if started else raw
            counts[i] = c
            raw_position[i] = raw
            P[row] = c * rad + off
            M[row] = c * motor_rad
            V[row] = v * rad
            E[row] = t * nm
            i += 1
        self._started = True

    def update_machines(self, on_event: Callable[[int, DriveEvent], None]) -> None:
        """Run the state machines when a statusword changed or a drive is not steadily enabled;
        their controlwords and hold flags are used by :meth:`write`."""
        status = self.statuswords
        if self._steady and status == self._last_status:
            return
        self._last_status = list(status)
        generation = self._generation
        steady = True
        for i, machine in enumerate(self.machines):
            self.controlwords[i] = machine.update(status[i], self.error_codes[i])
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

    def write(self, cmd_position: np.ndarray, cmd_velocity: np.ndarray, cmd_effort: np.ndarray,
              cmd_feedforward: np.ndarray, cmd_mode: np.ndarray) -> None:
        """Commands → targets, modes and controlwords; a drive in ``hold`` gets target = actual.

        The command arrays are read element by element through memoryviews (made once for
        the same arrays): no temporary array or list per tick, and only the values the
        drive's mode uses."""
        arrays = (cmd_position, cmd_velocity, cmd_effort, cmd_feedforward, cmd_mode)
        views = self._cmd_views
        if views is None or any(a is not b for a, b in zip(arrays, self._cmd_arrays, strict=True)):
            views = tuple(_items(a) for a in arrays)
            if all(isinstance(v, memoryview) for v in views):  # live views: kept for the next ticks
                self._cmd_views, self._cmd_arrays = views, arrays
        cp, cv, ce, cf, cm = views
        modes, hold, controlwords, raw_position = MODE_OF_OPERATION, self.hold, self.controlwords, self.raw_position
        i = 0
        for (pack, buf, offset), row, k, off, per_mille in self._encode_plan:
            if hold[i]:
                pack(buf, offset, controlwords[i], raw_position[i], 0, 0, _CSP)
                i += 1
                continue
            mode = modes.get(cm[row], _CSP)
            target = ((round((cp[row] - off) * k) + _I32) & 0xFFFFFFFF) - _I32  # wraps as the drive counts
            if mode == _CSP:  # the drive reads the position target only
                pack(buf, offset, controlwords[i], target, 0, 0, _CSP)
            else:
                velocity = round(cv[row] * k)
                torque = round((ce[row] + cf[row]) * per_mille)
                pack(buf, offset, controlwords[i], target,
                     velocity if -_I32 <= velocity < _I32 else (_I32 - 1 if velocity > 0 else -_I32),
                     torque if -_I16 <= torque < _I16 else (_I16 - 1 if torque > 0 else -_I16), mode)
            i += 1

    def write_holding(self) -> None:
        """Every drive: its controlword, target = actual (before the first tick, and in a stop)."""
        for (pack, buf, offset), controlword, raw in zip((plan[0] for plan in self._encode_plan), self.controlwords,
                                                         self.raw_position):
            pack(buf, offset, controlword, raw, 0, 0, _CSP)

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
    """A force/torque slave → a ``force_torque`` record (N, N·m); status bit 0 valid, bit 1 overload."""

    GROUPS = (("wrench", 6),)

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


def _items(array: np.ndarray) -> memoryview | list:
    """Element access without a numpy call per element: a memoryview of a contiguous 1-D array
    (it sees later writes), else a snapshot list."""
    if array.ndim == 1 and array.flags.c_contiguous:
        return memoryview(array)
    return array.tolist()
