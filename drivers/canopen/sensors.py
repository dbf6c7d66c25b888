"""CAN sensors whose frames a DBC file describes (LOLA's sensor gateway), decoded with cantools.

Each sensor fills one IMU or force/torque record from named signals ("Message.Signal"), in
the order of the record's fields. Each frame is decoded into the sensor's buffer as it
arrives (where the driver receives it: the loop's thread between ticks, or canopen's notifier
thread on a bus without a file descriptor); a frame of the wrong length, or one cantools cannot
decode, is counted and dropped; a status signal that says the values are not valid, as the
sensor's ``status_valid`` and ``status_bits`` read it, marks them invalid and they are not
taken. An IMU without orientation signals reads a quaternion of NaN (not measured). The tick copies a sensor's buffer into its record when a
frame came since the last tick, and marks it STALE when none came for ``stale_periods`` of its
period while the driver was reading, until frames come again.
"""

from __future__ import annotations

import logging
import math
import time
from functools import lru_cache
from pathlib import Path
from typing import Literal, cast

import cantools
import numpy as np
from pydantic import Field

from aiohal.files import read_regular_text
from aiohal.hal import FiniteFloat, Options
from aiohal.logutil import RateLimitedLogger
from aiohal.robot import DeviceRecord, DriverView, Fault

from .busload import frame_bits

log = logging.getLogger(__name__)

DATA = Path(__file__).resolve().parent / "data"
SENSORS_DBC = DATA / "aiohal_sensors.dbc"
FIELDS = {
    "imu": {"quaternion": 4, "angular_velocity": 3, "linear_acceleration": 3},
    "force_torque": {"force": 3, "torque": 3},
}
OPTIONAL = {"imu": {"quaternion"}}  # fields a sensor may leave out: NaN, not measured


class SensorOptions(Options):
    device: str = Field(description="The robot's imu or force_torque device this sensor fills.")
    period_ms: FiniteFloat = Field(gt=0, description="The sensor's own period (ms).")
    stale_periods: FiniteFloat = Field(3.0, ge=1, description="Stale after this many periods without a frame.")
    signals: dict[str, list[str]] = Field(
        description="Per field of the record (e.g. quaternion), its signals 'Message.Signal' in order. "
        "An IMU may leave out quaternion (no orientation): it then reads NaN, not measured."
    )
    status: str | None = Field(None, description="'Message.Signal' that says whether the values are valid.")
    status_valid: Literal["set", "clear"] = Field(
        "set",
        description="set: the values are valid when every bit of status_bits is set in the status signal; "
        "clear: when none is (a gateway whose status 0 means OK).",
    )
    status_bits: int = Field(
        1, ge=1, le=0xFFFFFFFF, description="The status signal's bits that status_valid reads (default: bit 0)."
    )


@lru_cache(maxsize=8)
def load_dbc(path: str, key: str = "options.dbc") -> cantools.database.can.Database:
    """The DBC at ``path``, read here (a regular file only: a FIFO or a device is refused)."""
    text = read_regular_text(path, key)
    return cast(cantools.database.can.Database, cantools.database.load_string(text, database_format="dbc"))


def _signal(db, name: str):
    """(message, signal name) of ``'Message.Signal'``; KeyError with a reason otherwise."""
    message_name, _, signal = name.partition(".")
    try:
        message = db.get_message_by_name(message_name)
    except KeyError:
        raise KeyError(f'no message "{message_name}" in the DBC') from None
    if signal not in [s.name for s in message.signals]:
        raise KeyError(f'message "{message_name}" has no signal "{signal}"')
    return message, signal


def sensor_issues(where: str, sensor: SensorOptions, kind: str | None, db) -> list[tuple[str, str]]:
    if kind not in FIELDS:
        return [(f"{where}.device", f'"{sensor.device}" is not an imu or force_torque device of this driver')]
    issues = []
    fields = FIELDS[kind]
    for field, names in sensor.signals.items():
        if field not in fields:
            issues.append((f"{where}.signals.{field}", f"not a field of an {kind} record ({', '.join(fields)})"))
            continue
        if len(names) != fields[field]:
            issues.append((f"{where}.signals.{field}", f"{fields[field]} signals expected, got {len(names)}"))
        for k, name in enumerate(names):
            try:
                _signal(db, name)
            except KeyError as exc:
                issues.append((f"{where}.signals.{field}[{k}]", exc.args[0]))
    for field in fields:
        if field not in sensor.signals and field not in OPTIONAL.get(kind, ()):
            issues.append((f"{where}.signals", f'no signals for "{field}"'))
    if sensor.status is not None:
        try:
            message, name = _signal(db, sensor.status)
        except KeyError as exc:
            issues.append((f"{where}.status", exc.args[0]))
        else:
            length = message.get_signal_by_name(name).length
            if sensor.status_bits >> length:
                issues.append(
                    (
                        f"{where}.status_bits",
                        f"0x{sensor.status_bits:X} has bits beyond the {length} of {sensor.status}",
                    )
                )
    return issues


class DbcSensor:
    """One sensor: its signals → columns of its record's row, a buffer filled as frames arrive."""

    def __init__(self, options: SensorOptions, record: DeviceRecord, kind: str, db) -> None:
        self.options = options
        self.record = record
        values = record.group.values
        if values is None:
            raise TypeError(f"a {kind} group whose fields are not one float64 block cannot take DBC signals")
        self.row = values[record.index]  # every field of the record, in column order
        columns = record.group.columns
        for field in OPTIONAL.get(kind, ()):
            if field not in options.signals:
                self.row[columns[field]] = math.nan  # not measured
        self.buffer = self.row.copy()
        self.columns: dict[int, list[tuple[str, int]]] = {}  # frame id -> [(signal, column)]
        for field, names in options.signals.items():
            start = columns[field].start
            for k, name in enumerate(names):
                message, signal = _signal(db, name)
                self.columns.setdefault(message.frame_id, []).append((signal, start + k))
        self.status = _signal(db, options.status) if options.status else None
        self.status_bits = options.status_bits
        self.status_wanted = options.status_bits if options.status_valid == "set" else 0
        self.stale_s = options.period_ms * options.stale_periods * 1e-3
        self.frames = 0
        self.invalid = 0
        self.seen = 0
        self.last_s = time.monotonic()
        self.stale = False
        self.stale_events = 0

    def take(self, frame_id: int, values: dict) -> None:
        """A decoded frame (as it arrives)."""
        status = self.status
        if (
            status is not None
            and status[0].frame_id == frame_id
            and int(values[status[1]]) & self.status_bits != self.status_wanted
        ):
            self.invalid += 1
            return
        buffer = self.buffer
        for signal, column in self.columns[frame_id]:
            buffer[column] = values[signal]
        self.frames += 1
        self.last_s = time.monotonic()


class SensorGateway:
    """Every DBC sensor of one bus."""

    def __init__(self, sensors: list[DbcSensor], db, name: str) -> None:
        self.sensors = sensors
        self.name = name
        self.malformed = 0
        self.bits = 0  # bits of the frames received whole, worst-case stuffing (the load achieved)
        self._warn = RateLimitedLogger(log)
        self._last_read_s = 0.0
        self._watch_gap_s = min((s.stale_s for s in sensors), default=1.0) / 2
        self.messages = {}
        for sensor in sensors:
            for frame_id in sensor.columns:
                self.messages[frame_id] = db.get_message_by_frame_id(frame_id)
            if sensor.status is not None:
                self.messages[sensor.status[0].frame_id] = sensor.status[0]
        self._bits = {frame_id: frame_bits(m.length) for frame_id, m in self.messages.items()}
        self.takers = {
            frame_id: [
                s
                for s in sensors
                if frame_id in s.columns or (s.status is not None and s.status[0].frame_id == frame_id)
            ]
            for frame_id in self.messages
        }

    def subscribe(self, network) -> None:
        for frame_id in self.messages:
            network.subscribe(frame_id, self.on_frame)

    def frame_sizes(self) -> list[tuple[int, float]]:
        """(data bytes, frames per second) of every frame the sensors send."""
        out = []
        for frame_id, message in self.messages.items():
            hz = max(1000.0 / s.options.period_ms for s in self.takers[frame_id])
            out.append((message.length, hz))
        return out

    def on_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        message = self.messages[can_id]
        if len(data) != message.length:
            self.malformed += 1
            self._warn.warning(
                f"dlc{can_id}",
                "canopen %s: %s of %d bytes, %d expected: dropped",
                self.name,
                message.name,
                len(data),
                message.length,
            )
            return
        try:
            values = message.decode(bytes(data), decode_choices=False)
        except Exception as exc:  # cantools raises its own DecodeError and others on bad data
            self.malformed += 1
            self._warn.warning(f"bad{can_id}", "canopen %s: %s not decoded (%s): dropped", self.name, message.name, exc)
            return
        self.bits += self._bits[can_id]
        for sensor in self.takers[can_id]:
            sensor.take(can_id, values)

    def read(self, tick: int, now_ns: int, view: DriverView) -> None:
        """Each sensor's new values into its record, or its staleness judged (the tick)."""
        now_s = time.monotonic()
        if now_s - self._last_read_s > self._watch_gap_s:
            # the master was not listening (before the first tick, a stall of this host): silence
            # counts only from now, not from the last frame seen before the gap
            for sensor in self.sensors:
                sensor.last_s = max(sensor.last_s, now_s)
        self._last_read_s = now_s
        for sensor in self.sensors:
            record = sensor.record
            if sensor.frames != sensor.seen:
                sensor.seen = sensor.frames
                np.copyto(sensor.row, sensor.buffer)
                record.mark_fresh(tick, now_ns)
                if sensor.stale:
                    sensor.stale = False
                    record.set_fault(0)
                    log.warning("canopen %s: sensor %s is back (no longer stale)", self.name, record.name)
            elif not sensor.stale and now_s - sensor.last_s > sensor.stale_s:
                sensor.stale = True
                sensor.stale_events += 1
                record.set_fault(Fault.STALE)
                view.fault(
                    f"sensor {record.name} is stale: no valid frame for {sensor.stale_s * 1e3:g} ms "
                    f"({sensor.options.stale_periods:g} periods)",
                    hold=False,
                )

    def health(self) -> dict:
        return {
            s.record.name: {"frames": s.frames, "invalid": s.invalid, "stale_events": s.stale_events, "stale": s.stale}
            for s in self.sensors
        } | {"malformed": self.malformed}
