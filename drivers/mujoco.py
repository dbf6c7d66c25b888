"""``mujoco``: a robot simulated in MuJoCo behind the HAL (extra ``sim``).

The configured joints are MJCF joints of the same name (or renamed with ``joint_map``), each
driven by the motor actuator attached to it. The driver closes the joint loop itself, once per
tick, as a drive would: ``tau = kp·(q* - q) + kd·(v* - v) + effort* + feed-forward`` plus
gravity and Coriolis compensation (``qfrc_bias``) when asked, clipped to the actuator range.
Position mode uses the configured gains, velocity mode only kd, effort mode none, impedance
mode the command's own stiffness and damping. Both the joint read and this torque law are one
compiled call each per tick (``mujoco_kernels``).

Time: each tick advances the physics by exactly one tick period (in substeps of the model
timestep). On the virtual clock this is lockstep: the simulation is the clock and runs as fast
as the CPU allows, deterministically. On a real clock (timerfd) it is real time, paced by the
ticker. ``step = "inline"`` (default) steps inside ``write()``; ``step = "thread"`` steps in a
worker thread between ticks (``mj_step`` releases the GIL), which takes the step off the tick
but adds two thread hand-offs per tick: lower lateness, for more CPU and, on a machine of two
CPUs, a few more missed ticks.

IMUs read ``framequat``/``gyro``/``accelerometer`` sensors, force/torque devices ``force``/
``torque`` sensors, named ``<device>_quat``, ``<device>_gyro``, ``<device>_accel``,
``<device>_force``, ``<device>_torque`` unless ``sensors`` says otherwise.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Literal, cast

import mujoco
import numpy as np
from pydantic import Field

from aiohal.config import ConfigPath
from aiohal.core import compiled_entry
from aiohal.hal import Driver, JointValues, Options, did_you_mean, unknown_joint_issues
from aiohal.mjcf import actuator_for_joints, joint_addresses, load_model, model_names, sensor_slice

log = logging.getLogger(__name__)

SENSOR_FIELDS = {
    "imu": {"quaternion": ("quat", 4), "angular_velocity": ("gyro", 3), "linear_acceleration": ("accel", 3)},
    "force_torque": {"force": ("force", 3), "torque": ("torque", 3)},
}


class MujocoOptions(Options):
    model: ConfigPath | None = Field(None, description="MJCF file; default: [robot] model.")
    step: Literal["inline", "thread"] = Field(
        "inline", description="Where mj_step runs: inside write() or in a worker thread between ticks."
    )
    kp: JointValues = Field(300.0, description="Position gain (N·m/rad), scalar or per joint.")
    kd: JointValues = Field(20.0, description="Velocity gain (N·m·s/rad), scalar or per joint.")
    gravity_compensation: bool = Field(True, description="Add qfrc_bias (gravity, Coriolis) to the torque.")
    initial_position: JointValues = Field(0.0, description="Start position, scalar or per joint.")
    keyframe: str | None = Field(
        None,
        description='Start from this keyframe of the model (e.g. "home"); '
        "initial_position, if given too, then sets the joints it names.",
    )
    joint_map: dict[str, str] = Field(default_factory=dict, description="Config joint -> MJCF joint name.")
    sensors: dict[str, dict[str, str]] = Field(
        default_factory=dict, description="Device -> {field: MJCF sensor name}, to override the naming rule."
    )
    viewer: bool = Field(False, description="Open MuJoCo's passive viewer (needs a display).")


def _sensor_name(options: MujocoOptions, device: str, field: str, suffix: str) -> str:
    return options.sensors.get(device, {}).get(field, f"{device}_{suffix}")


def _keyframes(path: str) -> list[str]:
    model = load_model(path)
    return [model.key(i).name for i in range(model.nkey)]


def fit_timestep(model, period_s: float) -> int:
    """Substeps per tick; when the tick period is not a whole number of the model's timesteps,
    the timestep is shortened (never lengthened: that could make the model unstable) so that
    a whole number of them fills the period, and the simulation keeps time with the ticks."""
    timestep = model.opt.timestep
    steps = period_s / timestep
    substeps = max(1, round(steps))
    if abs(steps - substeps) > 1e-6:
        substeps = math.ceil(steps)
        model.opt.timestep = period_s / substeps
        log.info(
            "tick period %g ms is not a whole number of model timesteps (%g ms): %d substep(s) of %g ms",
            period_s * 1e3,
            timestep * 1e3,
            substeps,
            model.opt.timestep * 1e3,
        )
    return substeps


class MujocoDriver(Driver):
    Options = MujocoOptions
    device_kinds = frozenset({"imu", "force_torque"})
    options: MujocoOptions

    @classmethod
    def check_config(cls, options, joints, devices, robot):
        issues = unknown_joint_issues("options.initial_position", options.initial_position, joints)
        issues += unknown_joint_issues("options.kp", options.kp, joints)
        issues += unknown_joint_issues("options.kd", options.kd, joints)
        issues += unknown_joint_issues("options.joint_map", options.joint_map, joints)
        path = options.model or robot.model
        where = "options.model" if options.model else "/robot.model"  # the key that named the file
        if path is None:
            return [*issues, ("options.model", "no model: set options.model or [robot] model")]
        if not os.path.exists(path):
            return [*issues, (where, f"file not found: {path}")]
        try:
            names = model_names(str(path))
        except ValueError as exc:
            return [*issues, (where, str(exc))]
        if options.keyframe is not None:
            keys = _keyframes(str(path))
            if options.keyframe not in keys:
                hint = did_you_mean(options.keyframe, keys)
                issues.append(
                    (
                        "options.keyframe",
                        f'no keyframe "{options.keyframe}" in the model '
                        f"{os.path.basename(path)}{hint or ' (it has: ' + (', '.join(keys) or 'none') + ')'}",
                    )
                )
        for joint in joints:
            mjcf = options.joint_map.get(joint, joint)
            if mjcf not in names.joints:
                issues.append(
                    (
                        f"options.joint_map.{joint}" if joint in options.joint_map else "joints",
                        f'joint "{mjcf}" is not in the model {os.path.basename(path)}',
                    )
                )
            elif mjcf not in names.actuated_joints:
                issues.append(("joints", f'joint "{mjcf}" has no actuator in the model {os.path.basename(path)}'))
        for device, kind in devices.items():
            for field, (suffix, dim) in SENSOR_FIELDS.get(kind, {}).items():
                sensor = _sensor_name(options, device, field, suffix)
                if names.sensors.get(sensor) != dim:
                    found = "missing" if sensor not in names.sensors else f"has {names.sensors[sensor]} values"
                    issues.append(
                        (
                            f"options.sensors.{device}",
                            f'{kind} "{device}" needs sensor "{sensor}" with {dim} values ({found})',
                        )
                    )
        return issues

    def __init__(self, name, view, options) -> None:
        super().__init__(name, view, options)
        # what estop(), close() and health() look at, whether open() ran, failed half-way or not at all
        self.data: mujoco.MjData | None = None
        self.actuators = np.zeros(0, dtype=np.intp)
        self.time_mode: str | None = None  # lockstep or realtime, once open
        self.steps = 0
        self.step_ns = 0
        self._estopped = False
        self._pending: asyncio.Future | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._viewer = None

    async def open(self) -> None:
        opts, view = self.options, self.view
        path = opts.model or view.model_path
        self.model = await asyncio.to_thread(load_model, path)
        self.data = mujoco.MjData(self.model)
        names = [opts.joint_map.get(j, j) for j in view.joint_names]
        self.qpos_adr, self.dof_adr = joint_addresses(self.model, names)
        self.actuators = actuator_for_joints(self.model, names)
        self.substeps = fit_timestep(self.model, view.clock.period_ns * 1e-9)
        n = view.dof
        lo = self.model.actuator_ctrlrange[self.actuators, 0]
        hi = self.model.actuator_ctrlrange[self.actuators, 1]
        limited = self.model.actuator_ctrllimited[self.actuators].astype(bool)
        # rows as drivers/mujoco_kernels.py names them: kp, kd, lower and upper torque bound
        self._table = np.array(
            [
                view.per_joint(opts.kp),
                view.per_joint(opts.kd),
                np.where(limited, lo, -np.inf),
                np.where(limited, hi, np.inf),
            ]
        )
        self._index = np.array([self.qpos_adr, self.dof_adr, self.actuators], dtype=np.intp)  # qpos, dof, actuator
        self.tau = np.zeros(n)
        if opts.keyframe is not None:  # the whole model's pose (a floating base's too), then the overrides
            mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key(opts.keyframe).id)
            start = self.data.qpos[self.qpos_adr].copy()
            if "initial_position" in opts.model_fields_set:
                given = opts.initial_position
                named = given if isinstance(given, dict) else dict.fromkeys(view.joint_names, given)
                for i, joint in enumerate(view.joint_names):
                    if joint in named:
                        start[i] = named[joint]
        else:
            start = view.per_joint(opts.initial_position)
        start = np.clip(start, view.position_min, view.position_max)
        self.data.qpos[self.qpos_adr] = start
        mujoco.mj_forward(self.model, self.data)
        self._bind_kernels()
        self.time_mode = "lockstep" if view.clock.kind == "virtual" else "realtime"
        threaded = opts.step == "thread"
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="mujoco-step") if threaded else None
        self._viewer = self._open_viewer() if opts.viewer else None

    def _bind_kernels(self) -> None:
        """The compiled read and torque law, called without numba's dispatch (it would cost more
        than the work; ``aiohal.core.compiled_entry``): every array they get is taken and checked here, once. MjData's arrays
        and the robot's blocks are never reallocated while the driver is open."""
        from . import mujoco_kernels as kernels

        data, state, command = self.data, self.view.state, self.view.command
        if data is None:
            raise RuntimeError("the kernels are bound to the MjData made in __init__")
        self._read_args = (data.qpos, data.qvel, self._index, self.tau, state.block, state.updated_tick, state.stamp_ns)
        self._read_joints = compiled_entry.compiled_for(kernels.read_joints, (*self._read_args, 0, 0))
        self._torque_args = (
            command.block,
            command.mode,
            state.block,
            self._table,
            self._index,
            data.qfrc_bias,
            self.options.gravity_compensation,
            self.tau,
            data.ctrl,
        )
        self._drive_torque = compiled_entry.compiled_for(kernels.drive_torque, self._torque_args)
        self._sensor_runs = [(data.sensordata, *run) for run in self._gather_plan()]
        self._read_sensors: Callable[..., Any] = kernels.read_sensors  # (no run: never called)
        for run in self._sensor_runs:
            self._read_sensors = compiled_entry.compiled_for(kernels.read_sensors, (*run, 0, 0))

    def _gather_plan(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """How read() fills the devices: for each run of this driver's devices in adjacent rows
        of a group's ``values``, (the sensordata address of each of their values, those rows,
        their ``updated_tick``, their ``stamp_ns``): one compiled call per run, however many
        sensors (WALK-MAN: 2 runs instead of 11 copies and 10 stamps)."""
        opts, view = self.options, self.view
        addresses_of: dict[tuple[int, int], np.ndarray] = {}  # (id(group), row) -> addresses
        for device, record in view.devices.items():
            group = record.group
            fields = SENSOR_FIELDS[view.device_kinds[device]]
            if group.values is None:
                raise RuntimeError(f"{device}: a {group.kind} record is not one float64 row; no sensor fills it")
            addresses = np.full(group.values.shape[1], -1, dtype=np.intp)
            for field, (suffix, _dim) in fields.items():
                sl = sensor_slice(self.model, _sensor_name(opts, device, field, suffix))
                addresses[group.columns[field]] = np.arange(sl.start, sl.stop)
            # the compiled read does not check its indices: every column must have a sensor value
            if not ((addresses >= 0) & (addresses < self.model.nsensordata)).all():
                raise RuntimeError(f"{device}: a column of its {view.device_kinds[device]} record has no sensor value")
            addresses_of[id(group), record.index] = addresses
        runs = []
        for group, rows in view.device_runs():
            index = np.array([addresses_of[id(group), row] for row in range(rows.start, rows.stop)], dtype=np.intp)
            values = cast(np.ndarray, group.values)  # checked in the loop above
            runs.append((index, values[rows], group.updated_tick[rows], group.stamp_ns[rows]))
        return runs

    def _open_viewer(self):
        if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
            log.warning("viewer requested but there is no display; running without it")
            return None
        import mujoco.viewer

        return mujoco.viewer.launch_passive(self.model, self.data)

    def _step(self) -> None:
        t0 = time.monotonic_ns()
        mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        self.step_ns += time.monotonic_ns() - t0
        self.steps += self.substeps

    async def read(self) -> None:
        # spelled out, with write(): a helper frame per call costs more than its lines on the
        # tick's cold caches (see controllers/circle_fast.py)
        if self._pending is not None:
            pending, self._pending = self._pending, None
            await pending  # the step of the last tick, done in the worker thread
        view = self.view
        clock = view.clock
        tick, now_ns = clock.tick, clock.now_ns
        self._read_joints(*self._read_args, tick, now_ns)
        view.fresh_tick = tick  # the kernel stamped every row itself
        read_sensors = self._read_sensors
        for run in self._sensor_runs:
            read_sensors(*run, tick, now_ns)
        if self._viewer is not None and tick % 16 == 0:
            self._viewer.sync()

    async def write(self) -> None:
        if self._estopped:
            self.tau[:] = 0.0
            self.data.ctrl[self.actuators] = 0.0  # type: ignore[union-attr]  # made in __init__; no test in write()
        else:
            self._drive_torque(*self._torque_args)
        if self._executor is None:
            self._step()
        else:
            self._pending = asyncio.get_running_loop().run_in_executor(self._executor, self._step)

    def estop(self) -> None:
        # drives off: no torque from now on, the simulated robot goes limp
        self._estopped = True
        if self.data is not None:
            self.data.ctrl[self.actuators] = 0.0

    def release_estop(self) -> bool:
        """Drives on again; the loop re-arms them from where the limp robot came to be."""
        self._estopped = False
        return True

    async def close(self) -> None:
        if self._pending is not None:
            await self._pending
            self._pending = None
        if self._executor is not None:
            self._executor.shutdown(wait=True)
        if self._viewer is not None:
            self._viewer.close()

    def health(self) -> dict:
        steps = self.steps
        return {
            "time_mode": self.time_mode,
            "step": self.options.step,
            "sim_time_s": round(float(self.data.time), 6) if self.data is not None else 0.0,
            "sim_steps": steps,
            "sim_steps_per_s": round(steps / (self.step_ns * 1e-9)) if self.step_ns else None,
        }
