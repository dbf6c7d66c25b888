"""``fri``: the KUKA LWR 4+ through FRI 1.x (KRC 2lr), the remote PC's side (docs/fri.md).

The KRC sets the pace: it sends a measurement datagram every cycle (1-100 ms) and expects
one command back at once. The driver answers in its datagram endpoint's callback, the moment
the measurement arrives, from the latest command ``write()`` left (or, while the KRC is in
monitor mode, powered off, below ``min_quality`` or e-stopped, the KRC's own set point:
``cmdJntPos + cmdJntPosFriOffset``, so that nothing jumps). The loop thus runs at its own rate
(R-HAL ran it at 200 Hz, not real time) and never waits for the network: ``read()`` takes the
newest measurement, ``write()`` stores the command.

The KRC brakes on a set point step above its interpolation limit, so every answer moves the
KRC's set point by at most ``max_step``: each entry into command mode starts where the KRC
holds the arm, and a loop slower than the KRC has its targets interpolated over the KRC
cycles of one loop period. A backlog of measurements (the process stalled) is answered once,
the newest; a KRC that restarts (a new port on its host, or its sequence from the start,
after a silence, in monitor mode) is taken again.

Bring-up plays the KRL handshake through the user ints: the strategy (position 10, joint
impedance 30) in ``$FRI_FRM_INT[strategy_int]`` with its command flags while in monitor mode,
then the start request (10) in ``$FRI_FRM_INT[command_int]``, until the KRC reports command
mode (``$FRI_TO_INT[status_int]`` = 20, state CMD, drives powered). A drop to monitor mode,
drives off, drive errors or quality below ``min_quality`` during the run fault the joints and
hold the robot (commands are refused until then); no measurement for ``silent_ms`` fails the
driver. Only 916-byte datagrams with id 0x2006 from the KRC's address are taken; anything else
is counted and dropped.
"""

from __future__ import annotations

import asyncio
import logging
import select
import socket
import sys
import time
from typing import Any, Literal, cast

import numpy as np
from pydantic import Field

from aiohal.errors import AiohalError
from aiohal.hal import AnyOptions, Driver, FiniteFloat, JointValues, Options, unknown_joint_issues
from aiohal.logutil import RateLimitedLogger
from aiohal.robot import Fault, Mode
from aiohal.simulation import process as simprocess
from aiohal.simulation.joint_options import SimulatedJoints

from .protocol import (
    DEFAULT_PORT,
    FLAGS,
    JOINTS,
    MAX_STEP,
    MSR,
    MSR_ID,
    MSR_SIZE,
    STRATEGY,
    Control,
    FriError,
    Quality,
    State,
    check,
    new_cmd,
    seq16_newer,
)

log = logging.getLogger(__name__)
STATE_CMD = int(State.CMD)
#: A measurement the ordinary rules refuse (another port, an older sequence number) is a
#: restarted KRC when the KRC was silent for this many of its cycles and it is in monitor mode.
RESTART_SILENCE_CYCLES = 3


#: KRL's handshake at open is paced by the KRC: quality climbs over its first packets, then the
#: program answers the start request; at a 100 ms cycle it took about 100 cycles
HANDSHAKE_CYCLES = 200
#: the default silence that fails the driver: this many KRC cycles, and never less than
SILENT_CYCLES, MIN_SILENT_MS = 5, 100.0


class FriDriverError(AiohalError, OSError):
    """The KRC cannot be reached, refused command mode, or went silent."""


class KrlOptions(Options):
    strategy_int: int = Field(15, ge=1, le=16, description="$FRI_FRM_INT index carrying the strategy (10/20/30).")
    command_int: int = Field(16, ge=1, le=16, description="$FRI_FRM_INT index of the request: 10 start, 20 stop.")
    status_int: int = Field(16, ge=1, le=16, description="$FRI_TO_INT index of KRL's state: 10 monitor, 20 command.")
    start: int = 10
    stop: int = 20
    started: int = 20


class KrcSimulation(SimulatedJoints):
    cycle_ms: int = Field(5, ge=1, le=100, description="The simulated KRC's FRI cycle (friOpen's argument).")
    time_constant: FiniteFloat = Field(0.004, gt=0, description="first_order: the tracking time constant (s).")
    drop_answers: FiniteFloat = Field(
        0.0, ge=0, le=1, description="Probability that an answer is lost (fault injection)."
    )
    max_step: FiniteFloat = Field(MAX_STEP, gt=0, description="The simulated KRC's interpolation limit (rad/cycle).")
    priority: int | None = Field(70, ge=1, le=99, description="SCHED_FIFO priority of the KRC's process, when allowed.")


class FriOptions(Options):
    port: int = Field(DEFAULT_PORT, ge=0, le=0xFFFF, description="Local UDP port (FRISOCK; 0: the OS picks).")
    bind_address: str = Field("0.0.0.0", description="Local address.")
    krc_address: str | None = Field(
        None, description="Take measurements only from this host (default: the first sender's)."
    )
    control: Literal["position", "joint_impedance"] = Field("position", description="The KRC's control strategy.")
    stiffness: JointValues = Field(1000.0, ge=0, description="Joint impedance: N·m/rad where the command gives none.")
    damping: JointValues = Field(0.7, ge=0, description="Joint impedance: damping ratio where the command gives none.")
    max_step: FiniteFloat = Field(
        MAX_STEP, gt=0, description="Rad per KRC cycle: no answer moves the KRC's set point further (its limit)."
    )
    min_quality: Literal["bad", "ok", "perfect"] = Field(
        "bad",
        description="Below it, commands are refused and the robot holds (FRI: commanding is allowed from BAD up).",
    )
    krl: KrlOptions = Field(default_factory=KrlOptions)
    start: bool = Field(True, description="Request command mode at open (else stay in monitor mode: read only).")
    open_timeout_s: FiniteFloat = Field(
        10.0,
        gt=0,
        description=f"Each bring-up step (first measurement, monitor mode, command mode) within this, or "
        f"{HANDSHAKE_CYCLES} of the KRC's cycles if that is longer (KRL's handshake counts cycles).",
    )
    silent_ms: FiniteFloat | None = Field(
        None,
        gt=0,
        description=f"No measurement for this long fails the driver; default {SILENT_CYCLES} of the KRC's "
        f"cycles, at least {MIN_SILENT_MS:g} ms.",
    )
    simulate: bool = Field(False, description="Start `python -m aiohal.drivers.fri.sim` on loopback.")
    simulation: KrcSimulation = Field(default_factory=KrcSimulation)
    initial_position: JointValues = Field(0.0, description="With simulate: where the simulated arm starts.")


class _Endpoint(asyncio.DatagramProtocol):
    def __init__(self, driver: FriDriver) -> None:
        self.on_datagram = driver._on_datagram

    def datagram_received(self, data: bytes, addr) -> None:
        self.on_datagram(data, addr)


class FriDriver(Driver):
    Options = FriOptions
    options: FriOptions
    #: the KRC tracks a position target; its joint impedance strategy also takes the command's
    #: stiffness, damping and added torque (velocity and pure effort commands it has not)
    command_modes = frozenset({Mode.POSITION, Mode.IMPEDANCE})

    @classmethod
    def supported_modes(cls, options: AnyOptions) -> frozenset[Mode]:
        control = cast(FriOptions, options).control  # the config validated them as this driver's
        return cls.command_modes if control == "joint_impedance" else frozenset({Mode.POSITION})

    @classmethod
    def check_config(cls, options, joints, devices, robot):
        issues = []
        for key in ("stiffness", "damping", "initial_position"):
            issues += unknown_joint_issues(f"options.{key}", getattr(options, key), joints)
        if len(joints) != JOINTS:
            issues.append(("joints", f"an LWR 4+ has {JOINTS} joints; {len(joints)} given"))
        cycle_ms = options.simulation.cycle_ms
        if options.simulate and options.silent_ms is not None and options.silent_ms < 2 * cycle_ms:
            issues.append(
                (
                    "options.silent_ms",
                    f"{options.silent_ms:g} ms is less than two of the simulated KRC's "
                    f"{cycle_ms} ms cycles: leave it out for {SILENT_CYCLES} cycles",
                )
            )
        return issues

    def __init__(self, name, view, options) -> None:
        super().__init__(name, view, options)
        self.control = Control.POSITION if options.control == "position" else Control.JNT_IMP
        self.min_quality = int(Quality[options.min_quality.upper()])
        self.msr = np.zeros((), dtype=MSR)  # the newest measurement taken
        self._msr_bytes = self.msr.data.cast("B")
        self.cmd = new_cmd()  # the answer, sent from the callback
        self._cmd_bytes = self.cmd.data.cast("B")
        self.cmd["cmd_flags"] = FLAGS[self.control]
        krl = options.krl
        self.cmd["krl_int"][krl.strategy_int - 1] = STRATEGY[self.control]
        # the latest command from write(), as FRI's float32 fields
        self.target = np.zeros(JOINTS, dtype=np.float32)
        self.torque = np.zeros(JOINTS, dtype=np.float32)
        self.stiffness = view.per_joint(options.stiffness).astype(np.float32)
        self.damping = view.per_joint(options.damping).astype(np.float32)
        self._default_stiffness, self._default_damping = self.stiffness.copy(), self.damping.copy()
        self.cmd["jnt_stiffness"], self.cmd["jnt_damping"] = self.stiffness, self.damping  # also while mirroring
        self._msr_fields = {name: self.msr[name] for name in cast(tuple[str, ...], MSR.names)}  # a structured dtype
        self._cmd_fields = {name: self.cmd[name] for name in ("jnt_pos", "add_jnt_trq", "jnt_stiffness", "jnt_damping")}
        self._cmd_head = np.frombuffer(self._cmd_bytes, dtype="<u2", count=2)  # send_seq, refl_seq
        self.commanding = False  # answers carry our command (else the KRC's set point)
        self.estopped = False
        self.running = False  # command mode was reached at open
        self.krc: tuple[str, int] | None = None  # the KRC's address, once known: the only one taken
        self._krc_host: str | None = None  # options.krc_address, resolved
        self.sock: socket.socket | None = None
        self.transport: asyncio.DatagramTransport | None = None
        self.sim_process: asyncio.subprocess.Process | None = None
        self.sim_report: dict | None = None
        self._rx = bytearray(2048)
        self._readable = select.poll()  # the socket, once open: more datagrams waiting?
        self._new = False  # a measurement arrived since the last read
        self._last_seq: int | None = None
        self._last_msr_ns = 0
        self._silent_ns = float(MIN_SILENT_MS * 1e6)  # from the KRC's cycle at open
        self._previous_position = np.zeros(JOINTS)
        self._previous_stamp = 0.0
        self._fault = ""  # the KRC-side fault being held, "" when none
        # the answer path: the KRC's set point, one loop period's segment of targets in KRC
        # cycles (from the last answer to the latest target), scratch
        self.max_step = np.float32(options.max_step)
        self._setpoint = np.zeros(JOINTS, dtype=np.float32)
        self._segment_from = np.zeros(JOINTS, dtype=np.float32)
        self._segment_cycles = 1
        self._segment_done = 0
        self._step = np.zeros(JOINTS, dtype=np.float32)
        # the KRC was not commandable since the last read: answers hold its set point until
        # read() has re-synchronised the loop's commands where the arm stands
        self._entering = True
        self._all_joints = np.ones(JOINTS, dtype=bool)
        self._answer_ns = np.zeros(1 << 12, dtype=np.int64)
        self._warn = RateLimitedLogger(log)
        self.counters = dict.fromkeys(
            (
                "received",
                "sent",
                "stale",
                "lost",
                "duplicated",
                "reordered",
                "malformed",
                "unauthenticated",
                "refused",
                "rate_limited",
                "krc_restarts",
            ),
            0,
        )

    # ------------------------------------------------------------ the answer, at once

    def _on_datagram(self, data: bytes, addr) -> None:
        t0 = time.perf_counter_ns()
        if not self._take(data, addr):
            return
        # more queued behind it (this process stalled): they are newer, this one is stale;
        # answer only the newest. The event loop delivers a backlog one datagram per call
        # (asyncio: one per iteration, uvloop: up to 32), so the socket is drained here.
        if self._readable.poll(0):
            self.counters["stale"] += self._drain()  # each one taken makes the one before it stale
        self._answer(cast(int, self._last_seq))
        self._answer_ns[self.counters["received"] & (len(self._answer_ns) - 1)] = time.perf_counter_ns() - t0

    def _drain(self) -> int:
        """Take every datagram waiting in the socket; how many were taken as measurements."""
        sock, rx = cast(socket.socket, self.sock), self._rx
        taken = 0
        while True:
            try:
                size, addr = sock.recvfrom_into(rx)
            except OSError:  # BlockingIOError: nothing more
                return taken
            taken += self._take(memoryview(rx)[:size], addr)

    def _catch_up(self) -> None:
        """Measurements that wait in the socket because this process did not run (a stall longer
        than ``silent_ms``; the tick came before their callbacks) are not a silent KRC: take them
        and answer the newest, as the callback does."""
        if self.sock is not None and self._readable.poll(0):
            taken = self._drain()
            if taken:
                self.counters["stale"] += taken - 1
                self._answer(cast(int, self._last_seq))

    def _take(self, data, addr) -> bool:
        """Check one datagram and take it as the newest measurement; False: counted, dropped."""
        counters = self.counters
        krc = self.krc
        if krc is None:
            known_host = self._krc_host is None or addr[0] == self._krc_host
        else:
            known_host = addr == krc or addr[0] == krc[0]
        if not known_host:
            counters["unauthenticated"] += 1
            return False
        try:
            check(data, len(data), MSR_SIZE, MSR_ID)
        except FriError:
            counters["malformed"] += 1
            return False
        seq = int.from_bytes(data[0:2], "little")
        if krc is None:
            self.krc = addr  # the KRC's address: from now on the only one taken (or its restart)
        newer = 1 if self._last_seq is None or addr != self.krc else seq16_newer(seq, self._last_seq)
        if addr != self.krc or newer <= 0:
            if not self._restarted(data):
                counters["unauthenticated" if addr != self.krc else "duplicated" if newer == 0 else "reordered"] += 1
                return False
            counters["krc_restarts"] += 1
            self._warn.warning("restart", "fri: the KRC restarted (%s:%d, sequence %d)", addr[0], addr[1], seq)
            self.krc = addr
            self._previous_stamp = 0.0  # its clock restarted too
        else:
            counters["lost"] += newer - 1
        self._last_seq = seq
        self._msr_bytes[:] = data
        self._new = True
        self._last_msr_ns = time.monotonic_ns()
        counters["received"] += 1
        return True

    def _restarted(self, data) -> bool:
        """A restarted KRC: silent for some of its cycles, then in monitor mode (as any KRC starts)."""
        state = int.from_bytes(data[144:146], "little")
        cycle_ns = max(float(self.msr["desired_msr_sample_time"]), 1e-3) * 1e9
        silent_ns = time.monotonic_ns() - self._last_msr_ns
        return state == State.MON and silent_ns >= RESTART_SILENCE_CYCLES * cycle_ns

    def _answer(self, seq: int) -> None:
        # the fields as views made once: a structured array's field lookup costs more than its copy
        msr, cmd = self._msr_fields, self._cmd_fields
        head = self._cmd_head
        head[0] = (int(head[0]) + 1) & 0xFFFF  # send_seq
        head[1] = seq  # refl_seq
        position, setpoint = cmd["jnt_pos"], self._setpoint
        np.add(msr["cmd_jnt_pos"], msr["cmd_jnt_pos_fri_offset"], out=setpoint)  # where the KRC holds the arm
        commandable = (
            msr["state"] == STATE_CMD and msr["power"] != 0 and msr["error"] == 0 and msr["quality"] >= self.min_quality
        )
        if not commandable:
            self._entering = True
        if commandable and self.commanding and not self.estopped:
            if self._entering:  # back in command mode: stay where the KRC holds until the loop resyncs
                position[:] = setpoint
            else:
                self._toward_target(position, setpoint)
            cmd["add_jnt_trq"][:] = self.torque
            cmd["jnt_stiffness"][:] = self.stiffness
            cmd["jnt_damping"][:] = self.damping
        else:  # mirror the KRC's set point: nothing moves, nothing jumps when commanding starts
            position[:] = setpoint
            cmd["add_jnt_trq"][:] = 0.0
            if self.commanding:
                self.counters["refused"] += 1
        try:
            # open() set the transport before the KRC's first datagram; no test added per datagram
            self.transport.sendto(self._cmd_bytes, self.krc)  # type: ignore[union-attr]
            self.counters["sent"] += 1
        except OSError:
            pass

    def _toward_target(self, position: np.ndarray, setpoint: np.ndarray) -> None:
        """This KRC cycle's point of the segment to the target, at most ``max_step`` from the
        KRC's set point (so also from wherever it holds the arm when command mode returns)."""
        step = self._step
        done = self._segment_done = min(self._segment_done + 1, self._segment_cycles)
        if done == self._segment_cycles:
            np.subtract(self.target, setpoint, out=step)
        else:  # from + (target - from)·done/cycles, relative to the set point
            np.subtract(self.target, self._segment_from, out=step)
            step *= np.float32(done / self._segment_cycles)
            step += self._segment_from
            step -= setpoint
        limit = self.max_step
        if step.max() > limit or step.min() < -limit:
            np.clip(step, -limit, limit, out=step)
            self.counters["rate_limited"] += 1
        np.add(setpoint, step, out=position)

    # ------------------------------------------------------------ bring-up

    async def open(self) -> None:
        opts = self.options
        loop = asyncio.get_running_loop()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1" if opts.simulate else opts.bind_address, 0 if opts.simulate else opts.port))
        self.sock = sock  # the answer path drains a backlog from it
        self._readable.register(sock, select.POLLIN)
        self.transport, _ = await loop.create_datagram_endpoint(lambda: _Endpoint(self), sock=sock)
        if opts.simulate:
            port = await self._start_simulation(sock.getsockname())
            self.krc = ("127.0.0.1", port)
        elif opts.krc_address is not None:
            # an AF_INET address is (host, port), the host a str
            self._krc_host = cast(str, (await loop.getaddrinfo(opts.krc_address, None, family=socket.AF_INET))[0][4][0])
        await self._wait(lambda: self._new, "no measurement from the KRC")
        self._take_measurement()
        self._silent_ns = self.silent_ns()
        cycle_ms = self._krc_cycle_s() * 1e3
        if self._silent_ns < 2 * cycle_ms * 1e6:
            log.warning(
                "fri %s: silent_ms = %g is less than two of the KRC's %g ms cycles: one late measurement "
                "will fail the driver",
                self.name,
                self._silent_ns / 1e6,
                cycle_ms,
            )
        if opts.start:
            await self._wait(lambda: self.msr["state"] == State.MON, "the KRC is not in monitor mode")
            self.cmd["krl_int"][opts.krl.command_int - 1] = opts.krl.start
            await self._wait(
                lambda: (
                    self.msr["state"] == State.CMD
                    and self.msr["power"] != 0
                    and self.msr["krl_int"][opts.krl.status_int - 1] == opts.krl.started
                ),
                "the KRC did not reach command mode (quality, or the KRL program?)",
            )
            self.running = True
            self._take_measurement()
        np.copyto(self.target, self.view.state.position, casting="same_kind")

    async def _wait(self, condition, what: str) -> None:
        start = time.monotonic()
        while not condition():
            timeout_s = max(self.options.open_timeout_s, HANDSHAKE_CYCLES * self._krc_cycle_s())
            if time.monotonic() - start > timeout_s:
                raise FriDriverError(
                    f"{what} within {timeout_s:g} s "
                    f"(state {int(self.msr['state'])}, quality {int(self.msr['quality'])})"
                )
            await asyncio.sleep(0.005)

    def _krc_cycle_s(self) -> float:
        """The KRC's cycle as its measurements give it (0 before the first)."""
        return float(self.msr["desired_msr_sample_time"])

    def silent_ns(self) -> float:
        """How long without a measurement fails the driver: ``silent_ms``, or the default from
        the KRC's cycle."""
        if self.options.silent_ms is not None:
            return self.options.silent_ms * 1e6
        return max(MIN_SILENT_MS * 1e6, SILENT_CYCLES * self._krc_cycle_s() * 1e9)

    async def _start_simulation(self, remote: tuple[str, int]) -> int:
        sim = self.options.simulation
        initial = np.clip(
            self.view.per_joint(self.options.initial_position), self.view.position_min, self.view.position_max
        )
        krl = self.options.krl
        args = [
            sys.executable,
            "-m",
            "aiohal.drivers.fri.sim",
            "--remote",
            f"{remote[0]}:{remote[1]}",
            "--cycle-ms",
            str(sim.cycle_ms),
            "--initial=" + ",".join(repr(float(x)) for x in initial),
            "--strategy-int",
            str(krl.strategy_int),
            "--command-int",
            str(krl.command_int),
            "--status-int",
            str(krl.status_int),
            "--drop-answers",
            repr(sim.drop_answers),
            "--max-step",
            repr(sim.max_step),
            *sim.joint_arguments(),
        ]
        if sim.priority is not None:
            args += ["--priority", str(sim.priority)]
        try:
            self.sim_process, ready = await simprocess.start(args, 10.0)
            return int(ready["port"])
        except (simprocess.SimulatorStartError, KeyError, ValueError) as exc:
            raise FriDriverError(f"the KRC simulator did not start: {exc}") from exc

    # ------------------------------------------------------------ the tick

    def _take_measurement(self) -> None:
        """The newest measurement into the state rows (velocity from the KRC's time stamps)."""
        msr, state = self.msr, self.view.state
        stamp = float(msr["timestamp"])
        np.copyto(state.position, msr["msr_jnt_pos"])
        dt = stamp - self._previous_stamp
        if 0.0 < dt < 1.0 and self._previous_stamp:
            np.subtract(state.position, self._previous_position, out=state.velocity)
            state.velocity /= dt
        np.copyto(self._previous_position, state.position)
        self._previous_stamp = stamp
        np.copyto(state.effort, msr["msr_jnt_trq"])
        np.copyto(state.temperature, msr["temperature"])
        self._new = False

    async def read(self) -> None:
        view = self.view
        if not self._new and time.monotonic_ns() - self._last_msr_ns > self._silent_ns:
            self._catch_up()
            if not self._new:
                view.state.fault |= np.uint32(Fault.HARDWARE)
                raise FriDriverError(f"no measurement from the KRC for {self._silent_ns / 1e6:g} ms")
        if self._new:
            self._take_measurement()
            view.mark_fresh()
        if self.running:
            msr = self.msr
            if msr["state"] != State.CMD or msr["power"] == 0 or msr["error"] != 0 or msr["quality"] < self.min_quality:
                self._krc_fault()
            elif self._entering or self._fault:
                self._back_in_command_mode()

    def _back_in_command_mode(self) -> None:
        """The KRC is commandable again: the loop's commands continue from where the arm
        stands (``view.resync``), and the answers leave the KRC's set point toward them."""
        view = self.view
        if self._fault:
            log.warning(
                "fri %s: the KRC is back in command mode; commands continue from where the arm stands", self.name
            )
            self._fault = ""
            view.state.fault &= np.uint32(~Fault.HARDWARE & 0xFFFFFFFF)
        view.resync(self._all_joints)
        self._entering = False
        np.copyto(self.target, self._setpoint)  # until write(): the answers stay at the set point
        self._segment_cycles = self._segment_done = 1

    def _krc_fault(self) -> None:
        msr = self.msr
        reason = (
            f"KRC: state {State(int(msr['state'])).name}, quality {Quality(int(msr['quality'])).name}, "
            f"power 0x{int(msr['power']):02x}, error 0x{int(msr['error']):02x}"
        )
        if reason != self._fault:
            self._fault = reason
            self.view.state.fault |= np.uint32(Fault.HARDWARE)
            self.view.fault(reason)

    def reset_faults(self) -> None:
        """The KRC's own faults are not ours to reset (KRL and the KRC decide): while it
        cannot be commanded, its joints stay faulted and a re-arm waits for command mode."""
        if self._fault:
            self.view.state.fault |= np.uint32(Fault.HARDWARE)

    async def write(self) -> None:
        command = self.view.command
        # a segment from the last answer to this target, over the KRC cycles of one loop period
        np.copyto(self._segment_from, self._cmd_fields["jnt_pos"])
        np.copyto(self.target, command.position, casting="same_kind")
        cycle = float(self._msr_fields["desired_cmd_sample_time"])
        period = self.view.clock.period_ns * self.view.every * 1e-9
        self._segment_cycles = max(1, round(period / cycle)) if cycle > 0.0 else 1
        self._segment_done = 0
        if self.control == Control.JNT_IMP:
            impedance = command.mode == Mode.IMPEDANCE
            np.add(command.effort, command.feedforward, out=self.torque, casting="same_kind")
            np.copyto(
                self.stiffness, np.where(impedance, command.stiffness, self._default_stiffness), casting="same_kind"
            )
            np.copyto(self.damping, np.where(impedance, command.damping, self._default_damping), casting="same_kind")
        self.commanding = self.running

    @property
    def following(self) -> bool:
        """The KRC is in command mode and the loop's commands were resynchronised to it."""
        return self.running and not self._fault and not self._entering

    # ------------------------------------------------------------ stop

    def estop(self) -> None:
        """Answer with the KRC's own set point from now on and ask KRL to stop."""
        self.estopped = True
        self.cmd["krl_int"][self.options.krl.command_int - 1] = self.options.krl.stop

    async def close(self) -> None:
        krl = self.options.krl
        if self.transport is not None:
            self.commanding = False
            self.cmd["krl_int"][krl.command_int - 1] = krl.stop
            if self.running:
                deadline = time.monotonic() + 1.0
                while self.msr["state"] == State.CMD and time.monotonic() < deadline:
                    await asyncio.sleep(0.005)
            self.transport.close()
        if self.sim_process is not None:
            self.sim_report = await simprocess.stop(self.sim_process, "counters")

    def health(self) -> dict[str, Any]:
        msr = self.msr
        n = min(self.counters["received"], len(self._answer_ns))
        answer = np.sort(self._answer_ns[:n]) / 1e3 if n else None
        out: dict[str, Any] = {
            **self.counters,
            "answer_us_p50": None if answer is None else round(float(answer[n // 2]), 1),
            "answer_us_max": None if answer is None else round(float(answer[-1]), 1),
            "krc_state": State(int(msr["state"])).name
            if int(msr["state"]) in State._value2member_map_
            else int(msr["state"]),
            "krc_quality": Quality(int(msr["quality"])).name if int(msr["quality"]) <= 3 else int(msr["quality"]),
            "krc_cycle_ms": round(float(msr["desired_msr_sample_time"]) * 1e3, 3),
            "krc_answer_rate": round(float(msr["answer_rate"]), 4),
            "krc_latency_us": round(float(msr["latency"]) * 1e6, 1),
            "krc_miss_counter": int(msr["miss_counter"]),
        }
        if self.sim_report is not None:
            out["simulated_krc"] = self.sim_report["counters"]
        return out
