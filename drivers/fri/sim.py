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

In command mode with the drives powered, a command that moves the set point by more than
``max_step`` in one cycle is an interpolation error: it is counted, the KRC brakes and drops
to monitor mode, as a real KRC does.

Fault injection: ``drop_answers`` (the probability that an answer is lost on the way), and
for a time: the drives powered off (``power_off``), the quality forced down
(``degrade_quality``), the KRL program restarting (``restart_krl``). With ``--control-stdin``
the process takes them as JSON lines on stdin (``{"do": "power_off", "for": 1.0}``,
``{"do": "quality", "for": 0.5, "quality": "UNACCEPTABLE"}``, ``{"do": "restart_krl", "for":
0.1}``) and answers ``{"do": "report"}`` with a ``{"report": ...}`` line on stdout.
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

from aiohal.lifetime import die_with_parent
from aiohal.robot import Mode
from aiohal.simulation.joints import add_dynamics_arguments, joint_model, servo_from_arguments

from .protocol import (
    CMD,
    CMD_ID,
    CMD_SIZE,
    CONTROL_OF_STRATEGY,
    JOINTS,
    MAX_STEP,
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
#: a step above ``max_step`` by less than this is float32 rounding of the set point's two halves
STEP_ROUNDING = 1e-6


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
    max_step: float = MAX_STEP  # rad per cycle in command mode: a larger step is an interpolation error
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
        self.msr["send_seq"] = 0xFFFF  # the first measurement carries sequence number 0
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
                "power_offs",
                "quality_drops",
                "krl_restarts",
            ),
            0,
        )
        self.largest_step = 0.0  # the largest set point step taken in command mode (rad)
        # fault injections: requested from any thread (their durations, s), then taken by the
        # cycle as until when (the cycle's clock)
        self._power_off: float | None = None
        self._power_off_until = 0.0
        self._degrade: tuple[float, Quality] | None = None
        self._quality_until = 0.0
        self._forced_quality = Quality.UNACCEPTABLE
        self._krl_restart: float | None = None
        self._krl_paused_until = 0.0
        self._now = 0.0
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

    # ------------------------------------------------------------ fault injection (any thread)

    def power_off(self, duration: float) -> None:
        """The drives off (brakes) for ``duration`` s; in command mode they come back powered."""
        self._power_off = duration

    def degrade_quality(self, duration: float, quality: Quality = Quality.UNACCEPTABLE) -> None:
        """The quality held at or below ``quality`` for ``duration`` s, whatever the answers."""
        self._degrade = (duration, quality)

    def restart_krl(self, pause: float) -> None:
        """The KRL program restarts: monitor mode, drives off, its handshake silent for ``pause`` s."""
        self._krl_restart = pause

    def report(self) -> dict:
        return {
            "counters": dict(self.counters),
            "state": self.state.name,
            "power": self.power,
            "quality": self.quality.name,
            "largest_step": self.largest_step,
            "setpoint": [float(x) for x in self.setpoint],
            "events": self.events[-20:],
        }

    def _inject(self, now: float) -> None:
        if self._power_off is not None:
            self._power_off_until = now + self._power_off
            self._power_off = None
            self.counters["power_offs"] += 1
        if self._degrade is not None:
            duration, self._forced_quality = self._degrade
            self._quality_until = now + duration
            self._degrade = None
            self.counters["quality_drops"] += 1
        if self._krl_restart is not None:
            self._krl_paused_until = now + self._krl_restart
            self._krl_restart = None
            self._to_monitor("KRL program restarted")
            self.counters["krl_restarts"] += 1
        if now < self._power_off_until:
            if self.power:
                self.power = 0
                self._brake()
                self.events.append("power off")
        elif self._power_off_until:
            self._power_off_until = 0.0
            if self.state == State.CMD:
                self.power = 0x7F
                self.events.append("power on")

    def _cycle(self, now: float) -> None:
        """End the last cycle (was it answered?), run the KRL program, move, send a measurement."""
        self._now = now
        self._inject(now)
        if self.packets:
            if not self.answered:
                self.window.append(None)
                self.miss_counter += 1
            self._grade()
        self._krl()
        self.model.step(self.options.cycle_s if self.packets else 0.0)
        self._fill_msr(now)
        self.answered = False
        data = self.msr.tobytes()
        self.sent_at = time.monotonic()  # the latency is the remote's: from the send, not from this cycle's start
        try:
            self.sock.sendto(data, self.remote)
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
        if self._now < self._quality_until:
            quality = min(quality, self._forced_quality)
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
        self._brake()
        self.events.append(f"MON: {why}")

    def _brake(self) -> None:
        """The brakes hold the joints where they stand: that is the set point from now on."""
        self.model.stop()
        self.setpoint = self.model.position.copy()
        self.krl_setpoint = self.setpoint.copy()

    def _krl(self) -> None:
        """The KRL program: strategy in MON, start on request at PERFECT, stop on request."""
        opts = self.options
        if self._now < self._krl_paused_until:
            return  # the program is not at its handshake yet
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
                step = float(np.max(np.abs(target - self.setpoint)))
                if step > opts.max_step + STEP_ROUNDING:
                    self.counters["interpolation_errors"] += 1
                    self.counters["drops_to_monitor"] += 1
                    self._to_monitor(f"interpolation error: a step of {step:.4f} rad (limit {opts.max_step})")
                    return
                self.largest_step = max(self.largest_step, step)
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
        status = 20 if self.state == State.CMD else 10
        msr["krl_int"][self.options.status_int - 1] = 0 if self._now < self._krl_paused_until else status


def take_commands(sim: KrcSimulator, lines, out) -> None:
    """Fault injections as JSON lines (``--control-stdin``); a bad line is answered with an error."""
    actions = {
        "power_off": lambda c: sim.power_off(float(c["for"])),
        "quality": lambda c: sim.degrade_quality(float(c["for"]), Quality[c.get("quality", "UNACCEPTABLE")]),
        "restart_krl": lambda c: sim.restart_krl(float(c["for"])),
    }
    for line in lines:
        try:
            command = json.loads(line)
            if command["do"] == "report":
                reply: dict = {"report": sim.report()}
            else:
                actions[command["do"]](command)
                reply = {"done": command["do"]}
        except (ValueError, KeyError, TypeError) as exc:
            reply = {"error": f"{type(exc).__name__}: {exc} in {line.strip()!r}"}
        print(json.dumps(reply), file=out, flush=True)


def parse_address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> None:
    die_with_parent(signal.SIGKILL)  # started by the fri driver: gone with it at once (nothing to tidy)
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
    p.add_argument(
        "--max-step", type=float, default=MAX_STEP, help="rad per cycle: a larger step is an interpolation error"
    )
    p.add_argument("--control-stdin", action="store_true", help="take fault injections as JSON lines on stdin")
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
        max_step=args.max_step,
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
    if args.control_stdin:
        threading.Thread(target=take_commands, args=(sim, sys.stdin, sys.stdout), daemon=True).start()
    try:
        sim.serve(args.duration)
    finally:
        print(json.dumps({"counters": sim.counters, "events": sim.events[-20:]}), file=sys.stderr, flush=True)
        sim.sock.close()


if __name__ == "__main__":
    main()
