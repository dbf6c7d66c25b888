"""Simulated joint boards on UDP: ``python -m aiohal.drivers.udp.sim --boards 29``.

Each board has its own socket (its own port, as boards have their own addresses), answers
every command with its joints' state at once, obeys an e-stop datagram at once (latched until
RESET) and stops its joints when no command came for its watchdog time. The joints are one
model of ``aiohal.simulation.joints``, advanced whenever the simulator wakes: ``--dynamics
first_order`` (the position error decays with ``--time-constant``) or ``servo`` (each joint
behind a simulated servo drive, LOLA's cascade, its parameters as ``--servo-json``).

Fault injection (per reply, from a seeded generator): ``drop`` a reply, ``delay_ms`` every
reply, ``reorder`` (hold a reply back and send it after the next), ``garbage`` (send random
bytes besides), ``die_board`` (that board goes silent after ``die_after_s``).

The first line on stdout is ``{"ports": [...], "boards": [...]}`` once every socket is bound
(port 0 lets the OS pick), so a driver or a test can start it and then talk to it.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import random
import selectors
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from aiohal.lifetime import die_with_parent
from aiohal.simulation.joints import add_dynamics_arguments, joint_model, servo_from_arguments

from .protocol import (
    COMMAND_RECORD,
    FLAG_MAC,
    HEADER,
    HEADER_SIZE,
    MAGIC,
    STATE_RECORD,
    VERSION,
    ZERO_MAC,
    BoardFault,
    Kind,
    ProtocolError,
    check,
    seal_parts,
    seq_newer,
)

if TYPE_CHECKING:
    from aiohal.simulation.servo import ServoParams

RECV_SIZE = 2048


@dataclass
class SimFaults:
    drop: float = 0.0  # probability that a reply is not sent
    delay_ms: float = 0.0  # every reply leaves this late
    reorder: float = 0.0  # probability that a reply is held and sent after the next one
    garbage: float = 0.0  # probability that random bytes are sent besides a reply
    die_board: int | None = None  # this board goes silent ...
    die_after_s: float = 0.0  # ... this long after the first command
    seed: int = 0


@dataclass
class SimBoard:
    id: int
    rows: slice
    sock: socket.socket
    head: bytearray  # the reply's header
    body: memoryview  # the reply's records: this board's rows of the simulator's ``states``
    command: memoryview  # this board's rows of the simulator's ``commands``
    seq: int = 0  # the last state seq sent
    last_command: int | None = None  # the seq of the last command applied
    last_command_at: float = 0.0
    estopped: bool = False
    watchdog: bool = False
    dead: bool = False
    faulted: bool = False  # fault bits were set in its records
    held: tuple[bytes, bytes] | None = None  # a reply held back to be reordered
    estops_at: list[tuple[float, float]] = field(default_factory=list)  # (arrival, last command's), monotonic s
    counters: dict[str, int] = field(
        default_factory=lambda: dict.fromkeys(
            ("commands", "replies", "estops", "resets", "malformed", "unauthenticated", "stale", "dropped", "garbage"),
            0,
        )
    )


class BoardSimulator:
    """``layout``: joints per board (board ids 1..N unless ``ids``); ``initial``: start positions;
    ``dynamics`` and ``servo`` (an ``aiohal.simulation.servo.ServoParams``): see ``joint_model``."""

    def __init__(
        self,
        layout: list[int],
        *,
        ids: list[int] | None = None,
        host: str = "127.0.0.1",
        ports: list[int] | None = None,
        master: tuple[str, int] | None = None,
        key: bytes | None = None,
        initial: list[float] | None = None,
        time_constant: float = 0.005,
        dynamics: str = "first_order",
        servo: ServoParams | None = None,
        watchdog_ms: float = 100.0,
        temperature: float = 35.0,
        servo_period_s: float = 0.0005,
        faults: SimFaults | None = None,
    ) -> None:
        n = sum(layout)
        positions = np.asarray(initial, dtype=np.float64) if initial else None
        self.model = joint_model(dynamics, n, positions, time_constant, servo)
        self.master = master
        self.key = key
        self.watchdog_s = watchdog_ms / 1e3
        self.temperature = temperature
        self.faults = faults or SimFaults()
        self.random = random.Random(self.faults.seed)
        self.selector = selectors.DefaultSelector()
        self.boards: list[SimBoard] = []
        self._delayed: list[
            tuple[float, int, SimBoard, tuple[bytes, bytes], tuple]
        ] = []  # heap of (due, n, board, bytes, addr)
        self._n_delayed = 0
        self._rx = bytearray(RECV_SIZE)
        self.commands = np.zeros(n, dtype=COMMAND_RECORD)  # the last command of every joint
        self.states = np.zeros(n, dtype=STATE_RECORD)  # every board's reply records, in joint order
        self._commanded = np.zeros(n, dtype=bool)  # joints whose board got a command in this wake
        self.servo_period_s = servo_period_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._first_command_at: float | None = None
        self._t_last = time.monotonic()
        start = 0
        ids = ids or list(range(1, len(layout) + 1))
        ports = ports or [0] * len(layout)
        for board_id, count, port in zip(ids, layout, ports, strict=True):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind((host, port))
            sock.setblocking(False)
            rows = slice(start, start + count)
            board = SimBoard(
                board_id,
                rows,
                sock,
                bytearray(HEADER_SIZE),
                self.states[rows].data.cast("B"),
                self.commands[rows].data.cast("B"),
            )
            self.boards.append(board)
            self.selector.register(sock, selectors.EVENT_READ, board)
            start += count
        self._measure()

    @property
    def addresses(self) -> list[tuple[str, int]]:
        return [b.sock.getsockname() for b in self.boards]

    def board(self, board_id: int) -> SimBoard:
        return next(b for b in self.boards if b.id == board_id)

    # ------------------------------------------------------------ serving

    def serve(self, duration: float | None = None) -> None:
        """Answer datagrams until ``stop()`` (or for ``duration`` seconds).

        The servo runs at its own rate (``servo_period_s``): a board answers every command at
        once with its latest measurement, as a board samples its encoders in its own loop."""
        end = None if duration is None else time.monotonic() + duration
        period = self.servo_period_s
        while not self._stop.is_set() and (end is None or time.monotonic() < end):
            timeout = period
            if self._delayed:
                timeout = max(0.0, min(timeout, self._delayed[0][0] - time.monotonic()))
            events = self.selector.select(timeout)
            now = time.monotonic()
            if now - self._t_last >= period:
                self._servo_step(now)
            for key, _ in events:
                self._drain(key.data, now)
            self._check_watchdogs(now)
            self._send_delayed(now)

    def start(self) -> BoardSimulator:
        """Serve in a daemon thread (for tests); ``stop()`` ends it."""
        self._thread = threading.Thread(target=self.serve, name="udp-board-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for board in self.boards:
            self.selector.unregister(board.sock)
            board.sock.close()
        self.selector.close()

    def _drain(self, board: SimBoard, now: float) -> None:
        rx = self._rx
        while True:
            try:
                size, addr = board.sock.recvfrom_into(rx)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if board.dead or self._dies(board, now):
                continue
            self._on_datagram(board, size, addr, now)

    def _dies(self, board: SimBoard, now: float) -> bool:
        f = self.faults
        if f.die_board != board.id or self._first_command_at is None:
            return False
        if now - self._first_command_at >= f.die_after_s:
            board.dead = True
        return board.dead

    def _on_datagram(self, board: SimBoard, size: int, addr: tuple, now: float) -> None:
        counters = board.counters
        try:
            head = check(self._rx, size, self.key)
        except ProtocolError as exc:
            counters[exc.reason] += 1
            return
        if self.master is not None and addr != self.master:
            counters["unauthenticated"] += 1
            return
        if head.board != board.id or head.kind == Kind.STATE:
            counters["malformed"] += 1
            return
        rows = board.rows
        if head.kind == Kind.ESTOP:  # obeyed at once, whatever its sequence number
            counters["estops"] += 1
            board.estops_at.append((now, board.last_command_at))
            board.estopped = True
            self._commanded[rows] = False  # a command not applied yet never will be
            self.model.stop(rows)
        elif head.kind == Kind.RESET:
            counters["resets"] += 1
            board.estopped = board.watchdog = False
            self._commanded[rows] = False
            self.model.stop(rows)
        else:
            if head.count != rows.stop - rows.start:
                counters["malformed"] += 1
                return
            if board.last_command is not None and seq_newer(head.seq, board.last_command) <= 0:
                counters["stale"] += 1  # a duplicate or an older command: never applied
                return
            counters["commands"] += 1
            board.last_command = head.seq
            board.last_command_at = now
            board.watchdog = False
            if self._first_command_at is None:
                self._first_command_at = now
            if not board.estopped:
                board.command[:] = memoryview(self._rx)[HEADER_SIZE:size]
                self._commanded[rows] = True
        self._reply(board, head.seq, addr, now)

    def _servo_step(self, now: float) -> None:
        """Every board's servo: the commands since the last step applied, the joints moved
        on to ``now``, every state record refilled."""
        model, cmd, mask = self.model, self.commands, self._commanded
        model.step(now - self._t_last)
        self._t_last = now
        if mask.any():
            model.command(
                mask,
                cmd["mode"][mask],
                cmd["position"][mask],
                cmd["velocity"][mask],
                cmd["effort"][mask],
                cmd["stiffness"][mask],
                cmd["damping"][mask],
            )
            mask[:] = False
        self._measure()

    def _measure(self) -> None:
        """Every state record refilled from the joints: after each servo step, and once at
        construction so that a board asked before its first step answers where it stands."""
        model, states = self.model, self.states
        states["position"] = model.position
        states["velocity"] = model.velocity
        states["effort"] = model.effort
        states["temperature"] = self.temperature
        states["mode"] = model.mode

    def _reply(self, board: SimBoard, ack: int, addr: tuple, now: float) -> None:
        bits = (BoardFault.ESTOP if board.estopped else 0) | (BoardFault.WATCHDOG if board.watchdog else 0)
        if bits or board.faulted:
            self.states["fault"][board.rows] = bits
            board.faulted = bool(bits)
        board.seq = (board.seq + 1) & 0xFFFFFFFF
        HEADER.pack_into(
            board.head,
            0,
            MAGIC,
            0,
            VERSION,
            Kind.STATE,
            board.rows.stop - board.rows.start,
            FLAG_MAC if self.key is not None else 0,
            board.id,
            0,
            board.seq,
            ack,
            ZERO_MAC,
        )
        seal_parts(board.head, board.body, self.key)
        self._send(board, (bytes(board.head), bytes(board.body)), addr, now)

    def _send(self, board: SimBoard, data: tuple[bytes, bytes], addr: tuple, now: float) -> None:
        f, rnd = self.faults, self.random
        if f.garbage and rnd.random() < f.garbage:
            board.sock.sendto(rnd.randbytes(rnd.randrange(1, 200)), addr)
            board.counters["garbage"] += 1
        if f.drop and rnd.random() < f.drop:
            board.counters["dropped"] += 1
            return
        if f.reorder and board.held is None and rnd.random() < f.reorder:
            board.held = data  # goes out after the next reply
            return
        for out in (data, board.held) if board.held is not None else (data,):
            if f.delay_ms:
                self._n_delayed += 1
                heapq.heappush(self._delayed, (now + f.delay_ms / 1e3, self._n_delayed, board, out, addr))
            else:
                self._sendto(board, out, addr)
        board.held = None

    def _sendto(self, board: SimBoard, data: tuple[bytes, bytes], addr: tuple) -> None:
        try:
            board.sock.sendmsg(data, (), 0, addr)
            board.counters["replies"] += 1
        except OSError:  # the master's port is gone (it closed): nobody to answer
            pass

    def _send_delayed(self, now: float) -> None:
        while self._delayed and self._delayed[0][0] <= now:
            _due, _n, board, data, addr = heapq.heappop(self._delayed)
            self._sendto(board, data, addr)

    def _check_watchdogs(self, now: float) -> None:
        for board in self.boards:
            if board.last_command is not None and not board.watchdog and now - board.last_command_at > self.watchdog_s:
                board.watchdog = True
                self.model.stop(board.rows)

    def counters(self) -> dict[str, int]:
        total: dict[str, int] = {}
        for board in self.boards:
            for name, value in board.counters.items():
                total[name] = total.get(name, 0) + value
        return total


def parse_address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> None:
    die_with_parent(signal.SIGKILL)  # started by the udp driver: gone with it at once (nothing to tidy)
    p = argparse.ArgumentParser(prog="python -m aiohal.drivers.udp.sim", description=__doc__.splitlines()[0])
    p.add_argument("--boards", type=int, default=1, help="number of boards (ids 1..N)")
    p.add_argument("--joints-per-board", type=int, default=1)
    p.add_argument("--layout", default=None, help="joints per board, comma separated (overrides the two above)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0, help="first board's port, the others follow (0: the OS picks each)")
    p.add_argument("--master", default=None, help="host:port: answer commands only from there")
    p.add_argument("--key", default=None, help="shared HMAC key, hex")
    p.add_argument("--initial", default=None, help="start positions, comma separated (rad)")
    add_dynamics_arguments(p, time_constant=0.005)
    p.add_argument("--watchdog-ms", type=float, default=100.0)
    p.add_argument("--drop", type=float, default=0.0)
    p.add_argument("--delay-ms", type=float, default=0.0)
    p.add_argument("--reorder", type=float, default=0.0)
    p.add_argument("--garbage", type=float, default=0.0)
    p.add_argument("--die-board", type=int, default=None)
    p.add_argument("--die-after-s", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--priority",
        type=int,
        default=None,
        help="SCHED_FIFO priority, when allowed (boards are hardware: they keep up)",
    )
    p.add_argument("--duration", type=float, default=None, help="serve this long (default: until SIGTERM)")
    args = p.parse_args(argv)
    servo = servo_from_arguments(p, args)
    layout = [int(x) for x in args.layout.split(",")] if args.layout else [args.joints_per_board] * args.boards
    ports = [0] * len(layout) if args.port == 0 else [args.port + i for i in range(len(layout))]
    sim = BoardSimulator(
        layout,
        host=args.host,
        ports=ports,
        master=parse_address(args.master) if args.master else None,
        key=bytes.fromhex(args.key) if args.key else None,
        initial=[float(x) for x in args.initial.split(",")] if args.initial else None,
        time_constant=args.time_constant,
        dynamics=args.dynamics,
        servo=servo,
        watchdog_ms=args.watchdog_ms,
        faults=SimFaults(
            args.drop, args.delay_ms, args.reorder, args.garbage, args.die_board, args.die_after_s, args.seed
        ),
    )
    if args.priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
        except (PermissionError, OSError) as exc:
            print(f"SCHED_FIFO not applied: {exc}", file=sys.stderr)
    signal.signal(signal.SIGTERM, lambda *_: sim._stop.set())
    signal.signal(signal.SIGINT, lambda *_: sim._stop.set())
    print(json.dumps({"ports": [port for _, port in sim.addresses], "boards": [b.id for b in sim.boards]}), flush=True)
    try:
        sim.serve(args.duration)
    finally:
        print(json.dumps({"counters": sim.counters()}), file=sys.stderr, flush=True)
        sim.stop()


if __name__ == "__main__":
    main()
