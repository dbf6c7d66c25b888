"""``replay``: the measured state of a recorded run, tick by tick, for ``aiohal replay``.

Each read gives the joints and devices what the recording holds for the loop's tick (the
state read at activation is the recording's tick 0), so a controller run in lockstep on it
sees what the recorded controller saw. Nothing is commanded: ``write()`` only counts. The
recording is loaded whole in ``open()``, never on the tick.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from aiohal.errors import DriverError
from aiohal.hal import Driver, Options

#: joint state rows and the recorded (topic, field) they come from
STATE_ROWS = (
    ("position", "/joint_states", "position"),
    ("velocity", "/joint_states", "velocity"),
    ("effort", "/joint_states", "effort"),
    ("motor_position", "/joint_states/extra", "motor_position"),
    ("motor_velocity", "/joint_states/extra", "motor_velocity"),
    ("temperature", "/joint_states/extra", "temperature"),
)
#: a device kind's measured fields and the recorded fields (dotted paths) that fill them
DEVICE_FIELDS: dict[str, dict[str, tuple[str, ...]]] = {
    "imu": {
        "quaternion": tuple(f"orientation.{c}" for c in "wxyz"),
        "angular_velocity": tuple(f"angular_velocity.{c}" for c in "xyz"),
        "linear_acceleration": tuple(f"linear_acceleration.{c}" for c in "xyz"),
    },
    "force_torque": {
        "force": tuple(f"wrench.force.{c}" for c in "xyz"),
        "torque": tuple(f"wrench.torque.{c}" for c in "xyz"),
    },
    "hand": {"position": ("position",), "effort": ("effort",), "object_detected": ("object_detected",)},
}


class ReplayOptions(Options):
    recording: Path = Field(description="The recording (an MCAP file or a rosbag2 directory) to replay.")


class ReplayDriver(Driver):
    """The joints and devices of a recording, as they were measured on each tick."""

    Options = ReplayOptions
    options: ReplayOptions
    device_kinds = frozenset(DEVICE_FIELDS)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.ticks = np.zeros(0, dtype=np.int64)
        self._state: dict[str, np.ndarray] = {}  # row name -> (recorded ticks, dof)
        self._devices: list[tuple[Any, str, np.ndarray]] = []  # (record, field, (recorded ticks, width))
        self.reads = 0
        self.writes = 0
        self.missing = 0  # ticks the recording does not hold (its values kept)

    async def open(self) -> None:
        from aiohal.record import load

        try:
            rec = load(self.options.recording)
        except (OSError, ValueError, ImportError) as exc:
            raise DriverError(self.name, "open", f"cannot read the recording: {exc}") from None
        if "/joint_states" not in rec:
            raise DriverError(self.name, "open", "the recording has no /joint_states")
        states = rec["/joint_states"]
        self.ticks = np.asarray(states.tick, dtype=np.int64)
        recorded = list(rec.joint_names) or list(states.messages[0].name)
        missing = [j for j in self.view.joint_names if j not in recorded]
        if missing:
            raise DriverError(self.name, "open", f"joints not in the recording: {', '.join(missing)}")
        columns = [recorded.index(j) for j in self.view.joint_names]
        for row, topic, field in STATE_ROWS:
            series = rec.series.get(topic)
            if series is not None and len(series) == len(self.ticks):
                self._state[row] = np.ascontiguousarray(series[field][:, columns])
        for name, record in self.view.devices.items():
            kind = self.view.device_kinds[name]
            series = rec.series.get(f"/{kind}/{name}")
            if series is None or len(series) != len(self.ticks):
                raise DriverError(self.name, "open", f"device {name}: /{kind}/{name} not recorded on every tick")
            for field, paths in DEVICE_FIELDS[kind].items():
                self._devices.append((record, field, np.column_stack([series[p] for p in paths])))
        await self.read()

    async def read(self) -> None:
        view = self.view
        tick = view.clock.tick
        i = int(np.searchsorted(self.ticks, tick))
        self.reads += 1
        if i >= len(self.ticks) or self.ticks[i] != tick:
            self.missing += 1
            return
        state = view.state
        for row, values in self._state.items():
            getattr(state, row)[:] = values[i]
        for record, field, values in self._devices:
            target = getattr(record, field)
            target[...] = values[i].reshape(target.shape)
        for record in view.devices.values():
            record.mark_fresh(tick, view.clock.now_ns)
        view.mark_fresh()

    async def write(self) -> None:
        self.writes += 1

    def health(self) -> dict[str, Any]:
        return {"reads": self.reads, "writes": self.writes, "missing_ticks": self.missing}
