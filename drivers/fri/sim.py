"""A KUKA KRC 2lr on FRI 1.x, simulated: ``python -m aiohal.drivers.fri.sim --remote HOST:PORT``.

Every cycle (1-100 ms) it sends a measurement datagram to the remote and expects the command
that answers it within the cycle. It keeps FRI's statistics over the last 100 packets
(answer rate, latency, jitter, miss rate) and grades the quality from them: it starts BAD and
ramps up as good answers fill the window; answers later than ``perfect_latency`` or
``ok_latency`` of a cycle, or missing, bring it down. A KRL program is played through the
user ints: the strategy is taken from ``$FRI_FRM_INT[strategy_int]`` while in monitor mode;
``$FRI_FRM_INT[command_int]`` = 10 starts command mode once the quality is PERFECT (the
command must match the set point, else an interpolation error keeps it in monitor mode), 20
stops it; ``$FRI_TO_INT[status_int]`` reports 10 (monitor) or 20 (command). In command mode
with the drives powered the joints follow the command (``aiohal.simulation.joints``:
``--dynamics first_order``, no physics, or ``servo``, each joint behind a simulated servo
drive taking the command's slope as velocity feed-forward and, in joint impedance, its added
torque as torque feed-forward); when the quality falls to ``drop_quality`` the KRC drops to monitor mode, powers the
drives off and the joints stop (brakes). These thresholds are this simulator's choices: KUKA
does not publish its own.

Fault injection: ``drop_answers`` (the probability that an answer is lost on the way).
The first line on stdout is ``{"port": N}`` once bound.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import random
import select
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from aiohal.robot import Mode
from aiohal.simulation.joints import add_dynamics_arguments, joint_model, servo_from_arguments

from .protocol import (
    CMD,
    CMD_ID,
    CMD_SIZE,
    CONTROL_OF_STRATEGY,
    JOINTS,
    Control,
    Flags,
    FriError,
    Quality,
    State,
    check,
    new_msr,
    seq16_newer,
)

if TYPE_CHECKING:
    from aiohal.simulation.servo import ServoParams

WINDOW = 100  # packets in FRI's statistics


@dataclass
class KrcOptions:
    cycle_s: float = 0.005
    strategy_int: int = 15  # KRL indices, 1-based, as in the KRL program
    command_int: int = 16
    status_int: int = 16
    perfect_latency: float = 0.2  # fraction of the cycle
    ok_latency: float = 0.5
    drop_quality: Quality = Quality.UNACCEPTABLE  # in CMD at or below this: back to MON, drives off
    ramp_packets: int = 20  # quality is capped while the window fills: BAD, then OK, then graded
    time_constant: float = 0.004  # dynamics "first_order"
    dynamics: str = "first_order"  # or "servo" (aiohal.simulation.joints.joint_model)
    servo: ServoParams | None = None  # dynamics "servo": the drives (None: aiohal.simulation.servo's defaults)
    drop_answers: float = 0.0
    seed: int = 0


class KrcSimulator:
    def __init__(
        self,
        remote: tuple[str, int],
        options: KrcOptions | None = None,
        initial=None,
        host: str = "127.0.0.1",
        port: int = 0,
    ) -> None:
        self.options = opts = options or KrcOptions()
        self.remote = remote
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.sock.setblocking(False)
        start = np.zeros(JOINTS) if initial is None else initial
        self.model = joint_model(opts.dynamics, JOINTS, start, opts.time_constant, opts.servo)
        self.msr = new_msr()
        self.msr["desired_msr_sample_time"] = self.msr["desired_cmd_sample_time"] = opts.cycle_s
        self.msr["safety_limits"] = 1.0
        self.msr["temperature"] = 35.0
        self.state = State.MON
        self.quality = Quality.BAD
        self.control = Control.POSITION
        self.power = 0
        self.setpoint = self.model.position.copy()  # the whole set point (held in MON)
        self.krl_setpoint = self.setpoint.copy()  # the KRL interpolator's share
        self.window: collections.deque[float | None] = collections.deque(maxlen=WINDOW)  # latency, None = missed
        self.packets = 0
        self.miss_counter = 0
        self.cmd = np.zeros((), dtype=CMD)
        self.answered = True
        self.sent_at = 0.0
        self.random = random.Random(opts.seed)
        self.counters = dict.fromkeys(
            (
                "sent",
                "answers",
                "late",
                "malformed",
                "unauthenticated",
                "interpolation_errors",
                "drops_to_monitor",
                "starts",
                "stops",
            ),
            0,
        )
        self.events: list[str] = []
        self._rx = bytearray(2048)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cmd_flags = 0

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    # ------------------------------------------------------------ running

    def serve(self, duration: float | None = None) -> None:
        period = self.options.cycle_s
        start = time.monotonic()
        next_at = start
        while not self._stop.is_set() and (duration is None or time.monotonic() - start < duration):
            now = time.monotonic()
            if now >= next_at:
                self._cycle(now)
                next_at += period
                if next_at < now:  # fell behind (a stall): keep the phase, skip the missed cycles
                    next_at += math.ceil((now - next_at) / period) * period
            ready, _, _ = select.select([self.sock], [], [], max(0.0, next_at - time.monotonic()))
            if ready:
                self._drain(time.monotonic())

    def start(self) -> KrcSimulator:
        self._thread = threading.Thread(target=self.serve, name="krc-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.sock.close()

    def _cycle(self, now: float) -> None:
        """End the last cycle (was it answered?), run the KRL program, move, send a measurement."""
        if self.packets:
            if not self.answered:
                self.window.append(None)
                self.miss_counter += 1
            self._grade()
        self._krl()
        self.model.step(self.options.cycle_s if self.packets else 0.0)
        self._fill_msr(now)
        self.answered = False
        self.sent_at = now
        try:
            self.sock.sendto(self.msr.tobytes(), self.remote)
            self.counters["sent"] += 1
        except OSError:
            pass
        self.packets += 1

    def _drain(self, now: float) -> None:
        while True:
            try:
                size, addr = self.sock.recvfrom_into(self._rx)
            except (BlockingIOError, InterruptedError):
                return
            if addr != self.remote:
                self.counters["unauthenticated"] += 1
                continue
            try:
                check(self._rx, size, CMD_SIZE, CMD_ID)
            except FriError:
                self.counters["malformed"] += 1
                continue
            if self.options.drop_answers and self.random.random() < self.options.drop_answers:
                continue
            cmd = np.frombuffer(self._rx, dtype=CMD, count=1)[0]
            if self.answered or seq16_newer(int(cmd["refl_seq"]), int(self.msr["send_seq"])) != 0:
                self.counters["late"] += 1  # answers an earlier measurement: a miss for the quality
                continue
            self.answered = True
            self.counters["answers"] += 1
            self.window.append(now - self.sent_at)
            self.cmd = cmd.copy()

    # ------------------------------------------------------------ the KRC's side

    def _grade(self) -> None:
        opts, window = self.options, self.window
        latencies = [x for x in window if x is not None]
        rate = len(latencies) / len(window) if window else 0.0
        latency = sum(latencies) / len(latencies) if latencies else opts.cycle_s
        cycle = opts.cycle_s
        if rate >= 0.99 and latency <= opts.perfect_latency * cycle:
            quality = Quality.PERFECT
        elif rate >= 0.95 and latency <= opts.ok_latency * cycle:
            quality = Quality.OK
        elif rate >= 0.8 and latency <= cycle:
            quality = Quality.BAD
        else:
            quality = Quality.UNACCEPTABLE
        if self.packets < opts.ramp_packets:
            quality = min(quality, Quality.BAD if self.packets < opts.ramp_packets // 2 else Quality.OK)
        self.quality = quality
        msr = self.msr
        msr["answer_rate"] = rate
        msr["latency"] = latency
        msr["jitter"] = float(np.std(latencies)) if len(latencies) > 1 else 0.0
        msr["miss_rate"] = 1.0 - rate
        msr["miss_counter"] = self.miss_counter
        if self.state == State.CMD and quality <= opts.drop_quality:
            self._to_monitor(f"quality {quality.name}")
            self.counters["drops_to_monitor"] += 1

    def _to_monitor(self, why: str) -> None:
        self.state = State.MON
        self.power = 0
        self.model.stop()  # brakes
        self.setpoint = self.model.position.copy()
        self.krl_setpoint = self.setpoint.copy()
        self.events.append(f"MON: {why}")

    def _krl(self) -> None:
        """The KRL program: strategy in MON, start on request at PERFECT, stop on request."""
        opts = self.options
        frm = self.cmd["krl_int"]
        request = int(frm[opts.command_int - 1])
        if self.state == State.MON:
            strategy = CONTROL_OF_STRATEGY.get(int(frm[opts.strategy_int - 1]))
            if strategy is not None:
                self.control = strategy
            self._cmd_flags = int(self.cmd["cmd_flags"])
            if request == 10 and self.quality == Quality.PERFECT and self.answered_last():
                if np.max(np.abs(self.cmd["jnt_pos"] - self.setpoint)) > 1e-3:
                    self.counters["interpolation_errors"] += 1
                    self.events.append("interpolation error: the command does not match the set point")
                else:
                    self.state = State.CMD
                    self.power = 0x7F
                    self.krl_setpoint = self.setpoint.copy()
                    self.counters["starts"] += 1
                    self.events.append("CMD")
        elif self.state == State.CMD:
            if request == 20:
                self._to_monitor("stop requested")
                self.counters["stops"] += 1
            elif self.power and int(self.cmd["cmd_flags"]) & Flags.JNTPOS:
                target = self.cmd["jnt_pos"].astype(np.float64)
                velocity = (target - self.setpoint) / opts.cycle_s
                stiffness = self.cmd["jnt_stiffness"] if self.control == Control.JNT_IMP else 0.0
                self.model.command(
                    slice(None),
                    Mode.POSITION,
                    target,
                    velocity,
                    self.cmd["add_jnt_trq"] if self.control == Control.JNT_IMP else 0.0,
                    stiffness,
                    0.0,
                )
                self.setpoint = target

    def answered_last(self) -> bool:
        return bool(self.window) and self.window[-1] is not None

    def _fill_msr(self, now: float) -> None:
        msr = self.msr
        msr["send_seq"] = (int(msr["send_seq"]) + 1) & 0xFFFF
        msr["refl_seq"] = self.cmd["send_seq"]
        msr["timestamp"] = now
        msr["state"], msr["quality"], msr["power"], msr["control"] = self.state, self.quality, self.power, self.control
        msr["msr_jnt_pos"] = self.model.position
        msr["msr_jnt_trq"] = self.model.effort
        # the set point: the KRL interpolator's, plus FRI's share as the offset (0 in MON)
        msr["cmd_jnt_pos"] = self.krl_setpoint
        msr["cmd_jnt_pos_fri_offset"] = self.setpoint - self.krl_setpoint
        msr["krl_int"][self.options.status_int - 1] = 20 if self.state == State.CMD else 10


def parse_address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m aiohal.drivers.fri.sim", description=__doc__.splitlines()[0])
    p.add_argument("--remote", required=True, help="HOST:PORT of the remote PC (the driver)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--cycle-ms", type=int, default=5, help="1..100 ms (friOpen's argument)")
    p.add_argument("--initial", default=None, help="7 start positions, comma separated (rad)")
    p.add_argument("--strategy-int", type=int, default=15)
    p.add_argument("--command-int", type=int, default=16)
    p.add_argument("--status-int", type=int, default=16)
    p.add_argument("--drop-answers", type=float, default=0.0)
    add_dynamics_arguments(p, time_constant=0.004)
    p.add_argument("--priority", type=int, default=None, help="SCHED_FIFO priority, when allowed")
    p.add_argument("--duration", type=float, default=None)
    args = p.parse_args(argv)
    if not 1 <= args.cycle_ms <= 100:
        p.error("--cycle-ms must be 1..100")
    servo = servo_from_arguments(p, args)
    opts = KrcOptions(
        cycle_s=args.cycle_ms / 1e3,
        strategy_int=args.strategy_int,
        command_int=args.command_int,
        status_int=args.status_int,
        drop_answers=args.drop_answers,
        time_constant=args.time_constant,
        dynamics=args.dynamics,
        servo=servo,
    )
    initial = np.array([float(x) for x in args.initial.split(",")]) if args.initial else None
    sim = KrcSimulator(parse_address(args.remote), opts, initial, args.host, args.port)
    if args.priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
        except OSError as exc:
            print(f"SCHED_FIFO not applied: {exc}", file=sys.stderr)
    signal.signal(signal.SIGTERM, lambda *_: sim._stop.set())
    signal.signal(signal.SIGINT, lambda *_: sim._stop.set())
    print(json.dumps({"port": sim.port}), flush=True)
    try:
        sim.serve(args.duration)
    finally:
        print(json.dumps({"counters": sim.counters, "events": sim.events[-20:]}), file=sys.stderr, flush=True)
        sim.sock.close()


if __name__ == "__main__":
    main()
