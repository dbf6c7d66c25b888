"""A simulated CAN sensor gateway: an IMU and a force/torque sensor, their frames encoded with
cantools from aiohal's DBC (``drivers/canopen/data/aiohal_sensors.dbc``), each sensor at its
own period (checked on every SYNC). At rest: the IMU reads gravity, the F/T sensor a
configured wrench. As gateways ship: ``orientation=False`` (an IMU that sends no orientation
frame), ``status_ok=0`` (a status signal whose 0 means OK, 1 an error; default 1 = valid).
Fault injection: :attr:`stopped` (no frame: the master sees it go stale), :attr:`wrong_dlc`
(frames one byte short) and :attr:`invalid` (the status says the values are not valid)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import cast

import canopen
import cantools

from ..sensors import SENSORS_DBC

SYNC_COB_ID = 0x80


@dataclass
class _Schedule:
    """Sensor frames sent together at their own period."""

    period: float  # s
    due: float  # time.monotonic() of the next send
    messages: list[tuple[cantools.database.can.Message, dict[str, float]]]  # (frame, payload values)


class SimSensorGateway:
    def __init__(
        self,
        network: canopen.Network,
        *,
        imu_period_s: float = 0.002,
        ft_period_s: float = 0.002,
        wrench: tuple[float, ...] = (1.0, -2.0, 15.0, 0.1, -0.05, 0.02),
        orientation: bool = True,
        status_ok: int = 1,
    ) -> None:
        self.network = network
        # a .dbc file loads as a CAN database (a .cdd would give a diagnostics one)
        db = cast(cantools.database.can.Database, cantools.database.load_file(str(SENSORS_DBC)))
        self.counter = 0
        self.stopped = False
        self.wrong_dlc = False
        self.invalid = False
        self.status_ok = status_ok
        fx, fy, fz, tx, ty, tz = wrench
        imu = [
            (db.get_message_by_name("IMU_Gyro"), {"X": 0.0, "Y": 0.0, "Z": 0.0}),
            (db.get_message_by_name("IMU_Accel"), {"X": 0.0, "Y": 0.0, "Z": 9.81}),
        ]
        if orientation:
            imu.insert(0, (db.get_message_by_name("IMU_Orientation"), {"W": 1.0, "X": 0.0, "Y": 0.0, "Z": 0.0}))
        self.groups = [
            _Schedule(imu_period_s, 0.0, imu),
            _Schedule(
                ft_period_s,
                0.0,
                [
                    (db.get_message_by_name("FT_Force"), {"X": fx, "Y": fy, "Z": fz}),
                    (db.get_message_by_name("FT_Torque"), {"X": tx, "Y": ty, "Z": tz}),
                ],
            ),
        ]
        self.frames = 0
        network.subscribe(SYNC_COB_ID, self._on_sync)

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.stopped:
            return
        now = time.monotonic()
        for group in self.groups:
            period, due, messages = group.period, group.due, group.messages
            if now < due:
                continue
            group.due = due + period if now - due < period else now + period  # its own period, whatever the SYNC rate
            self.counter = (self.counter + 1) & 0xFF
            status = self.status_ok ^ 1 if self.invalid else self.status_ok
            for message, values in messages:
                names = [s.name for s in message.signals]
                if "Counter" in names:
                    values = {**values, "Counter": self.counter}
                if "Status" in names:
                    values = {**values, "Status": status}
                payload = message.encode(values, strict=False, padding=True)
                if self.wrong_dlc:
                    payload = payload[:-1]
                self.network.send_message(message.frame_id, payload)
                self.frames += 1

    def close(self) -> None:
        self.stopped = True
