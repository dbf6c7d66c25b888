"""``mock``: a robot with no hardware, for CI and for trying controllers (like ros2_control's
GenericSystem).

Commands are mirrored into state, or followed through first-order dynamics; velocity
commands integrate into position. IMUs read gravity at rest, force/torque sensors a
configured wrench, hands move toward their grasp command. Faults can be injected: errors in
open/read/write at a given tick, lost feedback, delayed feedback and a slow (blocking) read.
"""

from __future__ import annotations

import asyncio
import errno
import math
import socket
import threading
import time
from typing import Literal, cast

import numpy as np
from pydantic import Field

from aiohal import kernel_call
from aiohal.hal import Driver, JointValues, Options, unknown_joint_issues
from aiohal.robot import HandGroup, StateRow
from aiohal.safety.watchdog import SendDatagram
from aiohal.simulation.servo import ServoParams

ESTOP_PAYLOAD = b"ESTOP"


#: the state rows the simulated joints move (the others keep what the driver last wrote)
MOVED_ROWS = (StateRow.POSITION, StateRow.VELOCITY, StateRow.EFFORT)


class MockFaults(Options):
    open_error: bool = Field(False, description="Fail in open().")
    read_error_at_tick: int | None = Field(None, ge=0, description="Raise in read() at this tick.")
    write_error_at_tick: int | None = Field(None, ge=0, description="Raise in write() at this tick.")
    feedback_lost_at_tick: int | None = Field(None, ge=0, description="Stop updating state from this tick.")
    feedback_lost_for: int = Field(0, ge=0, description="Ticks without feedback; 0 = for good.")
    estop_error: bool = Field(False, description="Raise in estop() (to test isolation).")
    close_hangs: bool | Literal["thread"] = Field(
        False,
        description='close() never returns (to test a forced stop); "thread": it waits for ever on a '
        "worker thread, as a blocking call in asyncio.to_thread would, which the process cannot join.",
    )


class MockOptions(Options):
    dynamics: Literal["mirror", "first_order", "servo"] = Field(
        "mirror",
        description="mirror: state = command; first_order: state follows with time_constant; "
        "servo: each joint behind a simulated servo drive (options.servo).",
    )
    servo: ServoParams = Field(default_factory=ServoParams, description="The drives and joints of dynamics = servo.")
    time_constant: float = Field(0.02, gt=0, description="First-order time constant (s).")
    initial_position: JointValues = Field(0.0, description="Start position, scalar or per joint.")
    feedback_delay_ticks: int = Field(0, ge=0, le=1000, description="State shows the robot N ticks ago.")
    read_latency_us: float = Field(0.0, ge=0, le=100_000, description="Busy time inside read() (a slow bus).")
    force: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="Force read by F/T sensors (N).")
    torque: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="Torque read by F/T sensors (N·m).")
    hand_speed: float = Field(2.0, gt=0, description="Hand closing speed at speed=1 (grasp units/s).")
    faults: MockFaults = Field(default_factory=MockFaults)
    estop_datagram: str | None = Field(
        None,
        pattern=r"^[^:]+:\d{1,5}$",
        description="'host:port': the simulated board's e-stop datagram goes there, from estop() and, when "
        "the tick stops, from the watchdog process.",
    )


class MockDriver(Driver):
    Options = MockOptions
    device_kinds = frozenset({"imu", "force_torque", "hand"})
    options: MockOptions

    @classmethod
    def check_config(cls, options, joints, devices, robot):
        return unknown_joint_issues("options.initial_position", options.initial_position, joints)

    def __init__(self, name, view, options) -> None:
        super().__init__(name, view, options)
        # counted from here: estop() and health() may come before open() or after it failed
        self.reads = 0
        self.writes = 0
        self.estops = 0
        self.feedback_lost = 0
        self.closed = False
        self.stopped = False

    async def open(self) -> None:
        opts = self.options
        if opts.faults.open_error:
            raise OSError(errno.ENODEV, "injected open error")
        view = self.view
        start = view.per_joint(opts.initial_position)
        np.clip(start, view.position_min, view.position_max, out=start)
        faults = opts.faults
        # without delay or lost feedback the simulated joints *are* the state rows: no copy
        self._direct = opts.feedback_delay_ticks == 0 and faults.feedback_lost_at_tick is None
        state = view.state
        self.sim = state.block if self._direct else np.zeros_like(state.block)  # rows as in the state block
        self.position, self.velocity, self.effort = (self.sim[row] for row in MOVED_ROWS)
        self.position[:] = start
        self.velocity[:] = 0.0
        self.effort[:] = 0.0
        self._faulty = (
            faults.read_error_at_tick is not None or faults.write_error_at_tick is not None or opts.read_latency_us > 0
        )
        self._first_order = opts.dynamics == "first_order"
        self._dt = 0.0
        self._alpha = 1.0
        self._inv_dt = 0.0
        delay = opts.feedback_delay_ticks
        self._history = np.zeros((delay + 1, *self.sim.shape))  # ring of past states, oldest next
        self._history[:, StateRow.POSITION, :] = start
        self._slot = 0
        self._last_tick = view.clock.tick
        for imu in view.devices_of("imu"):
            imu.quaternion[:] = (1.0, 0.0, 0.0, 0.0)
            imu.linear_acceleration[:] = (0.0, 0.0, 9.81)  # at rest, the accelerometer reads +g up
        for ft in view.devices_of("force_torque"):
            ft.force[:] = opts.force
            ft.torque[:] = opts.torque
        self._bind_step()
        self._servo = None
        if opts.dynamics == "servo":
            from .mock_servo import MockServo

            self._servo = MockServo(view, opts.servo, self.sim)
        # the devices, a run of adjacent rows at a time: the stamps of each run, and the hands'
        # rows (grasp, speed, force, position, effort) with scratch rows for their step
        runs = view.device_runs()
        self._device_stamps = [(group.updated_tick[rows], group.stamp_ns[rows]) for group, rows in runs]
        self._hand_runs = []
        for group, rows in runs:
            if group.kind == "hand":
                hand = cast(HandGroup, group)  # "hand" is HandGroup's kind and no other group's
                hands = rows.stop - rows.start
                self._hand_runs.append(
                    (
                        hand.grasp[rows],
                        hand.speed[rows],
                        hand.force[rows],
                        hand.position[rows],
                        hand.effort[rows],
                        np.zeros(hands),
                        np.zeros(hands),
                        np.zeros(hands, dtype=bool),
                    )
                )

    def _set_dt(self, dt: float) -> None:
        """The step's factors for a time step of ``dt`` (a new one after a missed tick)."""
        self._dt = dt
        self._inv_dt = 1.0 / dt
        self._alpha = 1.0 - math.exp(-dt / self.options.time_constant) if self._first_order else 1.0

    def _bind_step(self) -> None:
        """The compiled joint step (``mock_kernels``), called without numba's dispatch: its
        arrays are taken and checked here, once; the robot's blocks are never reallocated."""
        from . import mock_kernels

        state, command = self.view.state, self.view.command
        self._step_args = (command.block, command.mode, self.sim)
        self._stamp_args = (state.updated_tick, state.stamp_ns)
        self._step_joints = kernel_call.compiled_for(
            mock_kernels.step_joints, (*self._step_args, 0.0, False, 1.0, 0.0, False, *self._stamp_args, 0, 0)
        )

    async def read(self) -> None:
        view = self.view
        clock = view.clock
        tick = clock.tick
        if self._faulty:
            self._inject_read_faults(tick)
        stamped = False
        if tick > self._last_tick and not self.stopped:
            # advance the simulated joints toward the command; when they are the state's rows
            # (no delay, no loss), the compiled step stamps them too
            dt = (tick - self._last_tick) * clock.period_ns * 1e-9
            if dt != self._dt:
                self._set_dt(dt)
            stamped = self._direct
            if self._servo is not None:
                self._servo.step(dt)
                stamped = False
            else:
                self._step_joints(
                    *self._step_args,
                    dt,
                    self._first_order,
                    self._alpha,
                    self._inv_dt,
                    stamped,
                    *self._stamp_args,
                    tick,
                    clock.now_ns,
                )
        self._last_tick = tick
        self.reads += 1
        if not self._direct and not self._publish_state(tick):
            return
        if stamped:
            view.fresh_tick = tick
        else:
            view.mark_fresh()
        if self._device_stamps:
            self._read_devices(tick, clock.now_ns)

    def _inject_read_faults(self, tick: int) -> None:
        opts = self.options
        at = opts.faults.read_error_at_tick
        if at is not None and tick >= at:
            raise OSError(errno.EIO, f"injected read error at tick {tick}")
        if opts.read_latency_us:
            until = time.monotonic_ns() + int(opts.read_latency_us * 1e3)
            while time.monotonic_ns() < until:
                pass

    def _publish_state(self, tick: int) -> bool:
        """Copy the simulated joints into the state rows, delayed or lost; False if lost."""
        opts = self.options
        faults = opts.faults
        lost_at = faults.feedback_lost_at_tick
        if (
            lost_at is not None
            and tick >= lost_at
            and (not faults.feedback_lost_for or tick < lost_at + faults.feedback_lost_for)
        ):
            self.feedback_lost += 1
            return False
        shown = self.sim
        if opts.feedback_delay_ticks:
            history = self._history
            np.copyto(history[self._slot], self.sim)
            self._slot = (self._slot + 1) % len(history)
            shown = history[self._slot]
        measured = self.view.state.block
        for row in MOVED_ROWS:
            np.copyto(measured[row], shown[row])
        return True

    def _read_devices(self, tick: int, now: int) -> None:
        """IMUs and F/T sensors keep the values set at open (gravity, the configured wrench);
        each hand moves toward its grasp by at most ``hand_speed × speed`` per second and
        pushes with its force while not fully open; every device is stamped with this read."""
        period_s = self.view.clock.period_ns * 1e-9
        for grasp, speed, force, position, effort, step, moved, closed in self._hand_runs:
            np.greater(position, 0.0, out=closed)
            effort.fill(0.0)
            np.copyto(effort, force, where=closed)
            np.multiply(speed, self.options.hand_speed * period_s, out=step)
            np.subtract(grasp, position, out=moved)
            np.minimum(moved, step, out=moved)
            np.negative(step, out=step)
            np.maximum(moved, step, out=moved)
            position += moved
        for ticks, stamps in self._device_stamps:
            ticks.fill(tick)
            stamps.fill(now)

    async def write(self) -> None:
        if self._faulty:
            at = self.options.faults.write_error_at_tick
            tick = self.view.clock.tick
            if at is not None and tick >= at:
                raise OSError(errno.EIO, f"injected write error at tick {tick}")
        if self._servo is not None:
            self._servo.write()
        self.writes += 1

    def estop(self) -> None:
        self.estops += 1
        self.stopped = True  # the simulated joints freeze, as braked drives would
        for action in self.safe_actions():
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
                sock.sendto(action.payload, (action.host, action.port))
        if self.options.faults.estop_error:
            raise RuntimeError("injected estop error")

    def release_estop(self) -> bool:
        """The simulated brakes let go; the joints move again when commanded."""
        self.stopped = False
        self._last_tick = self.view.clock.tick  # no catching up on the time spent stopped
        return True

    def safe_actions(self) -> list:
        if self.options.estop_datagram is None:
            return []
        host, port = self.options.estop_datagram.rsplit(":", 1)
        return [SendDatagram(host, int(port), ESTOP_PAYLOAD + b" " + self.name.encode())]

    async def close(self) -> None:
        hangs = self.options.faults.close_hangs
        if hangs == "thread":
            await asyncio.to_thread(threading.Event().wait)  # never set
        elif hangs:
            await asyncio.get_running_loop().create_future()  # never resolved
        self.closed = True

    def health(self) -> dict:
        return {
            "reads": self.reads,
            "writes": self.writes,
            "estops": self.estops,
            "feedback_lost_ticks": self.feedback_lost,
        }
