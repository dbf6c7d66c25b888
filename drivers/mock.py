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
from typing import Literal

import numpy as np
from pydantic import Field

from aiohal.hal import Driver, JointValues, Options, unknown_joint_issues
from aiohal.robot import Mode
from aiohal.safety.watchdog import SendDatagram
from aiohal.simulation.servo import ServoParams

ESTOP_PAYLOAD = b"ESTOP"

#: the modes as ints: numpy compares an array with an IntEnum member about ten times slower
#: (5-6 µs against 0.6 on Python 3.11, numpy 2.4)
VELOCITY, EFFORT = int(Mode.VELOCITY), int(Mode.EFFORT)


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
        start = np.clip(view.per_joint(opts.initial_position), view.position_min, view.position_max)
        self.sim = np.zeros((3, view.dof))  # the simulated joints: position, velocity, effort
        self.sim[0] = start
        self._history = np.zeros((opts.feedback_delay_ticks + 1, 3, view.dof))  # past states, oldest next
        self._history[:, 0] = start
        self._slot = 0
        self._last_tick = view.clock.tick
        for imu in view.devices_of("imu"):
            imu.quaternion[:] = (1.0, 0.0, 0.0, 0.0)
            imu.linear_acceleration[:] = (0.0, 0.0, 9.81)  # at rest, the accelerometer reads +g up
        for ft in view.devices_of("force_torque"):
            ft.force[:] = opts.force
            ft.torque[:] = opts.torque
        self._servo = None
        if opts.dynamics == "servo":
            from .mock_servo import MockServo

            self._servo = MockServo(view, opts.servo, self.sim)

    async def read(self) -> None:
        view = self.view
        tick = view.clock.tick
        self._inject_read_faults(tick)
        if tick > self._last_tick and not self.stopped:
            dt = (tick - self._last_tick) * view.clock.period_ns * 1e-9
            if self._servo is not None:
                self._servo.step(dt)
            else:
                self._step(dt)
        self._last_tick = tick
        self.reads += 1
        if self._feedback_lost(tick):
            self.feedback_lost += 1
            return
        # the state shows the simulated joints as they were feedback_delay_ticks ago
        self._history[self._slot] = self.sim
        self._slot = (self._slot + 1) % len(self._history)
        shown = self._history[self._slot]
        state = view.state
        state.position[:] = shown[0]
        state.velocity[:] = shown[1]
        state.effort[:] = shown[2]
        view.mark_fresh()
        self._read_devices(tick, view.clock.now_ns)

    def _step(self, dt: float) -> None:
        """Move each joint toward its target: the position command, or where the commanded
        velocity takes it in velocity mode, or where it is in effort mode; all the way (mirror)
        or by the first-order filter's share of it."""
        command = self.view.command
        position = self.sim[0]
        target = np.where(command.mode == VELOCITY, position + command.velocity * dt, command.position)
        target = np.where(command.mode == EFFORT, position, target)
        motion = target - position
        if self.options.dynamics == "first_order":
            motion *= 1.0 - math.exp(-dt / self.options.time_constant)
        self.sim[0] = position + motion
        self.sim[1] = motion / dt
        self.sim[2] = command.effort + command.feedforward

    def _inject_read_faults(self, tick: int) -> None:
        opts = self.options
        at = opts.faults.read_error_at_tick
        if at is not None and tick >= at:
            raise OSError(errno.EIO, f"injected read error at tick {tick}")
        if opts.read_latency_us:
            until = time.monotonic_ns() + int(opts.read_latency_us * 1e3)
            while time.monotonic_ns() < until:
                pass

    def _feedback_lost(self, tick: int) -> bool:
        faults = self.options.faults
        lost_at = faults.feedback_lost_at_tick
        if lost_at is None or tick < lost_at:
            return False
        return not faults.feedback_lost_for or tick < lost_at + faults.feedback_lost_for

    def _read_devices(self, tick: int, now: int) -> None:
        """IMUs and F/T sensors keep the values set at open (gravity, the configured wrench);
        each hand moves toward its grasp by at most ``hand_speed × speed`` per second and
        pushes with its force while not fully open; every device is stamped with this read."""
        period_s = self.view.clock.period_ns * 1e-9
        for hand in self.view.devices_of("hand"):
            hand.effort[...] = hand.force if hand.position > 0.0 else 0.0
            step = self.options.hand_speed * float(hand.speed) * period_s
            hand.position[...] += min(max(float(hand.grasp - hand.position), -step), step)
        for device in self.view.devices.values():
            device.mark_fresh(tick, now)

    async def write(self) -> None:
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
