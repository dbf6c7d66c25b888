"""Device classes on bus variables (LOLA): CiA 402 drives, IMUs and force/torque sensors.

Each class links the variables it needs by name at bring-up (errors name the slave and the
variable, types are checked) and then moves values between the process image and the
robot's records once per cycle: the drives through :mod:`aiohal.fieldbus.drives`, the
sensors, one or two per bus, with one ``struct`` call each (:class:`~aiohal.fieldbus.busvar.RecordCodec`).
"""

from __future__ import annotations

from typing import cast

from aiohal.fieldbus.busvar import ProcessImage, RecordCodec, VariableTypeError
from aiohal.fieldbus.drives import (  # noqa: F401 (the drives, re-exported where the driver and its tests find them)
    DRIVE_INPUT_TYPES,
    DRIVE_INPUTS,
    DRIVE_OUTPUT_TYPES,
    DRIVE_OUTPUTS,
    DriveGroup,
    DriveSpec,
)
from aiohal.robot import DeviceRecord, Fault


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

    def __init__(
        self,
        image: ProcessImage,
        slave: str,
        record: DeviceRecord,
        variables: dict[str, str],
        control: str | None = None,
    ) -> None:
        super().__init__(image, slave, record, variables)
        self.control = image.codec(slave, [control], writable=True) if control else None
        self.tare_left = 0  # cycles the control bit stays set

    def tare(self) -> None:
        if self.control is None:
            raise VariableTypeError(
                f'"{self.slave}" has no control output to tare with (its slave\'s variables.control names one)'
            )
        self.tare_left = self.TARE_CYCLES

    def write_control(self) -> None:
        """One cycle of a pending tare (the loop's write)."""
        self.tare_left -= 1
        cast(RecordCodec, self.control).pack(1 if self.tare_left > 0 else 0)  # tare() checked it

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
        raise VariableTypeError(
            f'"{var.full_name}" must be {n} contiguous values, it is {var.type}{list(var.shape) or ""}'
        )
