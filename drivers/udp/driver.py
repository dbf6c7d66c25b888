"""``udp``: Ethernet joint boards, one UDP datagram per board per tick each way (docs/udp.md).

``write`` sends every board its command datagram (the commands of all boards sit in one
array of records, so filling them is a few array copies; each board's datagram is its header
and its run of records, sent with ``sendmsg`` from the driver's one non-blocking socket).
``read`` drains the socket without waiting: the boards answered between the ticks, and the
kernel kept their datagrams. A reply is taken when it comes from the board's configured
address, is well formed (size, magic, CRC, version, kind, records), carries the right HMAC
when a key is configured, is newer than the board's last one and answers the last command
sent; anything else is counted by class and dropped. A board that has not answered for
``silent_ticks`` ticks fails the driver: the loop emergency-stops it (an ESTOP datagram to
every board) and holds the robot.

With ``simulate = true`` the driver starts ``python -m aiohal.drivers.udp.sim`` itself, on
loopback with ports the OS picks, so a demo config is one command; ``simulation.dynamics``
picks its joints' model (``"servo"``: LOLA's cascade, ``simulation.servo``).
"""

from __future__ import annotations

import asyncio
import fnmatch
import ipaddress
import logging
import socket
import struct
import sys
import time
from typing import Any, cast

import numpy as np
from pydantic import Field, field_validator

from aiohal.errors import AiohalError
from aiohal.hal import Driver, FiniteFloat, JointValues, Options, unknown_joint_issues
from aiohal.logutil import RateLimitedLogger
from aiohal.robot import Fault, Mode
from aiohal.safety.watchdog import SendDatagram
from aiohal.simulation import process as simprocess
from aiohal.simulation.joint_options import SimulatedJoints

from .protocol import (
    COMMAND_RECORD,
    FLAG_MAC,
    HEADER,
    HEADER_SIZE,
    MAGIC,
    MAX_JOINTS,
    STATE_RECORD,
    VERSION,
    ZERO_MAC,
    Kind,
    ProtocolError,
    check,
    encode,
    seal_parts,
    seq_newer,
)

log = logging.getLogger(__name__)

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux: kernel receive time of each datagram
TIMESPEC = struct.Struct("@qq")
ANC_SIZE = socket.CMSG_SPACE(TIMESPEC.size)
SEQ_ACK = struct.Struct("<II")
RTT_RING = 1 << 14  # round trips kept for the report
SEND_RING = 1 << 10  # send times of the last commands, by sequence number


class UdpError(AiohalError, OSError):
    """A board that cannot be reached or went silent."""


class BoardOptions(Options):
    id: int = Field(ge=0, le=0xFFFF, description="The board's id (in every datagram's header).")
    joints: list[str] = Field(min_length=1, description="Its joints, names or glob patterns, in the driver's order.")
    address: str = Field("127.0.0.1", min_length=1, description="The board's IPv4 address (or a name it resolves to).")
    port: int = Field(ge=1, le=0xFFFF, description="The board's UDP port.")

    @field_validator("address")
    @classmethod
    def _ipv4(cls, value: str) -> str:
        try:
            version = ipaddress.ip_address(value).version
        except ValueError:
            return value  # a host name, resolved to IPv4 at open
        if version != 4:
            raise ValueError(
                f"{value} is an IPv6 address: the boards are reached over IPv4 (AF_INET); give its IPv4 address"
            )
        return value


class SimulationOptions(SimulatedJoints):
    drop: FiniteFloat = Field(0.0, ge=0, le=1, description="Probability that a board drops a reply.")
    delay_ms: FiniteFloat = Field(0.0, ge=0, description="Every reply leaves this late.")
    reorder: FiniteFloat = Field(
        0.0, ge=0, le=1, description="Probability that a reply is held and sent after the next."
    )
    garbage: FiniteFloat = Field(0.0, ge=0, le=1, description="Probability that random bytes are sent besides a reply.")
    die_board: int | None = Field(None, description="This board goes silent ...")
    die_after_s: FiniteFloat = Field(0.0, ge=0, description="... this long after the first command.")
    seed: int = 0
    priority: int | None = Field(
        70, ge=1, le=99, description="SCHED_FIFO priority of the boards' process, when allowed."
    )


class UdpOptions(Options):
    boards: list[BoardOptions] = Field(default_factory=list, description="The boards (needed unless simulate).")
    simulate: bool = Field(False, description="Start simulated boards on loopback (boards: from joints_per_board).")
    joints_per_board: int = Field(
        1, ge=1, le=MAX_JOINTS, description="With simulate and no boards listed: boards 1..N in joint order."
    )
    simulation: SimulationOptions = Field(default_factory=SimulationOptions)
    initial_position: JointValues = Field(0.0, description="With simulate: where the simulated joints start.")
    bind_address: str = Field("0.0.0.0", description="Local address of the driver's socket.")
    bind_port: int = Field(0, ge=0, le=0xFFFF, description="Local port (0: the OS picks).")
    key: str | None = Field(
        None, description="Shared HMAC key, hex, at least 16 bytes: every datagram is authenticated."
    )
    silent_ticks: int = Field(20, ge=1, description="A board silent this many ticks fails the driver (safe state).")
    open_timeout_s: FiniteFloat = Field(2.0, gt=0, description="Every board must answer within this at open.")

    @field_validator("key")
    @classmethod
    def _key_is_hex(cls, value: str | None) -> str | None:
        if value is None:
            return value
        try:
            raw = bytes.fromhex(value)
        except ValueError:
            raise ValueError("the key must be hex digits") from None
        if len(raw) < 16:
            raise ValueError(f"the key has {len(raw)} bytes; at least 16 are needed")
        return value


def board_layout(options: UdpOptions, joints: list[str]) -> tuple[list[tuple[int, int, int]], list[str]]:
    """The boards as (id, first row, joint count) over ``joints``, and the problems found."""
    if not options.boards:
        if not options.simulate:
            return [], ["list the boards (or set simulate = true)"]
        k = options.joints_per_board
        return [(i // k + 1, i, min(k, len(joints) - i)) for i in range(0, len(joints), k)], []
    layout: list[tuple[int, int, int]] = []
    problems: list[str] = []
    row, ids = 0, set()
    places: dict[tuple[str, int], int] = {}
    for b in options.boards:
        names = [j for pattern in b.joints for j in joints if fnmatch.fnmatchcase(j, pattern)]
        if b.id in ids:
            problems.append(f"board {b.id}: the id is used twice")
        ids.add(b.id)
        where = (b.address, b.port)
        if where in places:  # the replies are told apart by their source address
            problems.append(
                f"board {b.id}: {b.address}:{b.port} is board {places[where]}'s too; each board needs "
                "its own address and port"
            )
        places.setdefault(where, b.id)
        if names != joints[row : row + len(names)] or not names:
            problems.append(
                f"board {b.id}: its joints {names} are not the next run of the driver's joints "
                f"(expected from {joints[row] if row < len(joints) else 'none left'!r})"
            )
            return layout, problems
        if len(names) > MAX_JOINTS:
            problems.append(f"board {b.id}: {len(names)} joints, at most {MAX_JOINTS} per board")
        layout.append((b.id, row, len(names)))
        row += len(names)
    if row != len(joints):
        problems.append(f"joints {joints[row:]} are on no board")
    return layout, problems


class UdpDriver(Driver):
    Options = UdpOptions
    options: UdpOptions

    @classmethod
    def check_config(cls, options, joints, devices, robot):
        issues = unknown_joint_issues("options.initial_position", options.initial_position, joints)
        _, problems = board_layout(options, list(joints))
        return issues + [("options.boards", p) for p in problems]

    def __init__(self, name, view, options) -> None:
        super().__init__(name, view, options)
        layout, problems = board_layout(options, list(view.joint_names))
        if problems:
            raise ValueError("; ".join(problems))
        self.key = bytes.fromhex(options.key) if options.key else None
        n, nb = view.dof, len(layout)
        self.board_ids = [board_id for board_id, _, _ in layout]
        self.board_rows = [slice(start, start + count) for _, start, count in layout]
        self.addresses: list[tuple[str, int]] = []  # resolved at open
        self._by_address: dict[tuple[str, int], int] = {}
        # every board's command and state records, in joint order, and their fields as views
        self.tx_records = np.zeros(n, dtype=COMMAND_RECORD)
        self.rx_records = np.zeros(n, dtype=STATE_RECORD)
        self.rx_records["temperature"] = np.nan
        # structured dtypes: their names are a tuple
        self._tx = {f: self.tx_records[f] for f in cast(tuple[str, ...], COMMAND_RECORD.names)}
        self._rx = {f: self.rx_records[f] for f in cast(tuple[str, ...], STATE_RECORD.names)}
        tx_bytes, rx_bytes = self.tx_records.data.cast("B"), self.rx_records.data.cast("B")
        self._tx_bodies = [
            tx_bytes[r.start * COMMAND_RECORD.itemsize : r.stop * COMMAND_RECORD.itemsize] for r in self.board_rows
        ]
        self._rx_bodies = [
            rx_bytes[r.start * STATE_RECORD.itemsize : r.stop * STATE_RECORD.itemsize] for r in self.board_rows
        ]
        self._heads = [bytearray(HEADER_SIZE) for _ in layout]
        self._head_views = [memoryview(h) for h in self._heads]
        self._rx_buf = bytearray(
            HEADER_SIZE + MAX_JOINTS * STATE_RECORD.itemsize + 64
        )  # room to see an oversize datagram
        self._rx_view = memoryview(self._rx_buf)
        self._rx_bufs = [self._rx_view]
        self.joint_board = np.repeat(np.arange(nb), [r.stop - r.start for r in self.board_rows])
        self.board_tick = np.full(nb, -1, dtype=np.int64)  # the tick each board last answered
        self.board_late_tick = np.full(nb, -1, dtype=np.int64)  # ... or last answered an older command
        self.board_stamp = np.zeros(nb, dtype=np.int64)
        self._board_seq = [0] * nb  # the last state seq taken from each board
        self._board_seen = [False] * nb
        self._ack = [0] * nb  # what the next command acknowledges
        self._seq = 0  # the last command seq sent
        self._outstanding = False  # a command was sent since the last read
        self._tx_ns = np.zeros(SEND_RING, dtype=np.int64)
        self._rtt_ns = np.zeros(RTT_RING, dtype=np.int64)
        self._rtt_count = 0
        self._first_read = True
        self._written = True  # write() sent this tick's commands (the first read: open's RESET did)
        self._fault_latched = False
        self.sock: socket.socket | None = None
        self.sim_process: asyncio.subprocess.Process | None = None
        self.sim_counters: dict[str, int] | None = None
        self.estopped = False
        self.counters = dict.fromkeys(
            (
                "sent",
                "received",
                "lost",
                "late",
                "duplicated",
                "reordered",
                "malformed",
                "unauthenticated",
                "send_errors",
            ),
            0,
        )
        self.silent_boards: list[int] = []
        self._last_read_tick = 0  # the tick of the last read() (a gap in them is a stall)
        self._warn = RateLimitedLogger(log)

    # ------------------------------------------------------------ bring-up

    async def open(self) -> None:
        opts = self.options
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.bind(("127.0.0.1" if opts.simulate else opts.bind_address, opts.bind_port))
        self.sock = sock
        if opts.simulate:
            ports = await self._start_simulation()
            self.addresses = [("127.0.0.1", port) for port in ports]
        else:
            loop = asyncio.get_running_loop()
            # an AF_INET address is (host, port), the host a str
            self.addresses = [
                (
                    cast(
                        str,
                        (await loop.getaddrinfo(b.address, b.port, family=socket.AF_INET, type=socket.SOCK_DGRAM))[0][
                            4
                        ][0],
                    ),
                    b.port,
                )
                for b in opts.boards
            ]
        self._by_address = {addr: i for i, addr in enumerate(self.addresses)}
        for i, head in enumerate(self._heads):
            count = self.board_rows[i].stop - self.board_rows[i].start
            HEADER.pack_into(
                head,
                0,
                MAGIC,
                0,
                VERSION,
                Kind.COMMAND,
                count,
                FLAG_MAC if self.key else 0,
                self.board_ids[i],
                0,
                0,
                0,
                ZERO_MAC,
            )
        await self._reset_boards()

    async def _start_simulation(self) -> list[int]:
        opts, sim = self.options, self.options.simulation
        host, port = cast(socket.socket, self.sock).getsockname()  # open() made it
        initial = self.view.per_joint(opts.initial_position)
        np.clip(initial, self.view.position_min, self.view.position_max, out=initial)
        args = [
            sys.executable,
            "-m",
            "aiohal.drivers.udp.sim",
            "--layout",
            ",".join(str(r.stop - r.start) for r in self.board_rows),
            "--master",
            f"{host}:{port}",
            "--initial=" + ",".join(repr(float(x)) for x in initial),
            *sim.joint_arguments(),
            "--drop",
            repr(sim.drop),
            "--delay-ms",
            repr(sim.delay_ms),
            "--reorder",
            repr(sim.reorder),
            "--garbage",
            repr(sim.garbage),
            "--seed",
            str(sim.seed),
        ]
        if sim.priority is not None:
            args += ["--priority", str(sim.priority)]
        if sim.die_board is not None:
            args += ["--die-board", str(sim.die_board), "--die-after-s", repr(sim.die_after_s)]
        if self.key:
            args += ["--key", self.key.hex()]
        try:
            self.sim_process, ready = await simprocess.start(args, opts.open_timeout_s * 5)
            ports = ready["ports"]
        except (simprocess.SimulatorStartError, KeyError) as exc:
            raise UdpError(f"the simulated boards did not start: {exc}") from exc
        if len(ports) != len(self.board_rows):
            raise UdpError(f"the simulated boards reported {len(ports)} ports for {len(self.board_rows)} boards")
        return ports

    async def _reset_boards(self) -> None:
        """RESET every board (clears a latched e-stop) until each has answered: its state is
        the start state. Off the tick: waits, bounded by ``open_timeout_s``."""
        deadline = time.monotonic() + self.options.open_timeout_s
        answered = [False] * len(self.board_ids)
        while not all(answered):
            for i, done in enumerate(answered):
                if not done:
                    self._seq = (self._seq + 1) & 0xFFFFFFFF
                    self._send_control(i, Kind.RESET)
            until = time.monotonic() + 0.05
            while time.monotonic() < until and not all(answered):
                await asyncio.sleep(0.002)
                for i in self._drain(-1, 0, accept_any_ack=True):
                    answered[i] = True
            if time.monotonic() > deadline and not all(answered):
                silent = [self.board_ids[i] for i, ok in enumerate(answered) if not ok]
                raise UdpError(f"board(s) {silent} did not answer within {self.options.open_timeout_s:g} s")
        self._publish_state()

    def _send_control(self, board: int, kind: Kind) -> None:
        """An ESTOP or RESET datagram to one board (allocates: not for the tick)."""
        data = encode(kind, self.board_ids[board], self._seq, self._ack[board], key=self.key)
        try:
            cast(socket.socket, self.sock).sendto(data, self.addresses[board])  # open() made it
            self.counters["sent"] += 1
        except OSError:
            self.counters["send_errors"] += 1

    # ------------------------------------------------------------ the tick

    def _drain(self, tick: int, now_ns: int, accept_any_ack: bool = False) -> list[int]:
        """Take every datagram waiting on the socket; the boards whose reply was taken."""
        sock, counters, by_address = self.sock, self.counters, self._by_address
        rx_bufs, rx_view, key, seq = self._rx_bufs, self._rx_view, self.key, self._seq
        taken: list[int] = []
        while True:
            try:
                # open() made the socket; no test added to the tick
                size, anc, _flags, addr = sock.recvmsg_into(rx_bufs, ANC_SIZE)  # type: ignore[union-attr]
            except (BlockingIOError, InterruptedError):
                return taken
            b = by_address.get(addr)
            if b is None:
                counters["unauthenticated"] += 1  # not a configured board
                continue
            try:
                head = check(rx_view, size, key)
            except ProtocolError as exc:
                counters[exc.reason] += 1
                continue
            rows = self.board_rows[b]
            if head.kind != Kind.STATE or head.count != rows.stop - rows.start:
                counters["malformed"] += 1
                continue
            if head.board != self.board_ids[b]:
                counters["unauthenticated"] += 1  # a configured address claiming another board
                continue
            if self._board_seen[b]:
                newer = seq_newer(head.seq, self._board_seq[b])
                if newer <= 0:
                    counters["duplicated" if newer == 0 else "reordered"] += 1
                    continue
            answers = seq_newer(head.ack, seq)
            if answers > 0:
                counters["malformed"] += 1  # acknowledges a command never sent
                continue
            if answers < 0 and not accept_any_ack:
                counters["late"] += 1
                self.board_late_tick[b] = tick
                self._board_seq[b] = head.seq
                self._board_seen[b] = True
                continue
            self._board_seq[b] = head.seq
            self._board_seen[b] = True
            self._ack[b] = head.seq
            self._rx_bodies[b][:] = rx_view[HEADER_SIZE:size]
            self.board_tick[b] = tick
            self.board_stamp[b] = now_ns
            counters["received"] += 1
            if anc and not accept_any_ack:  # open's RESET datagrams have no send time
                sec, nsec = TIMESPEC.unpack_from(anc[0][2])
                self._rtt_ns[self._rtt_count & (RTT_RING - 1)] = (
                    sec * 1_000_000_000 + nsec - self._tx_ns[head.ack & (SEND_RING - 1)]
                )
                self._rtt_count += 1
            taken.append(b)

    def _publish_state(self) -> None:
        state, rx = self.view.state, self._rx
        np.copyto(state.position, rx["position"])
        np.copyto(state.velocity, rx["velocity"])
        np.copyto(state.effort, rx["effort"])
        np.copyto(state.temperature, rx["temperature"])

    async def read(self) -> None:
        view = self.view
        clock = view.clock
        tick, now_ns = clock.tick, clock.now_ns
        if self._first_read:  # the state read at open counts as the tick before the first
            self._first_read = False
            self.board_tick.fill(tick - 1)
        elif tick - self._last_read_tick > self.options.silent_ticks // 2:
            # ticks went by without a read (this process frozen, a host stall): the boards
            # answer commands, and none were sent; each gets a whole silent_ticks from here
            np.maximum(self.board_tick, tick - 1, out=self.board_tick)
        self._last_read_tick = tick
        taken = self._drain(tick, now_ns)
        if self._outstanding:
            self.counters["lost"] += len(self.board_ids) - len(taken)
            self._outstanding = False
        if not self._written:
            # the loop commands nothing (emergency stop, disabled): the boards still get a
            # datagram each tick, every joint braked where it stands (mode NONE), so that they
            # keep answering and their watchdog does not trip
            self.tx_records["mode"] = Mode.NONE
            self._send_commands()
        self._written = False
        state = view.state
        if taken:
            self._publish_state()
            np.take(self.board_tick, self.joint_board, out=state.updated_tick)
            np.take(self.board_stamp, self.joint_board, out=state.stamp_ns)
            faults = self._rx["fault"]
            if faults.any() or self._fault_latched:
                self._board_faults(faults)
        oldest = int(self.board_tick.min())
        view.fresh_tick = oldest
        if tick - oldest > self.options.silent_ticks:
            self._board_silent(tick)

    def _board_faults(self, faults: np.ndarray) -> None:
        """Board fault bits -> the joints' HARDWARE bit; a new fault holds the robot."""
        bad = faults != 0
        fault = self.view.state.fault
        hardware = np.uint32(Fault.HARDWARE)
        fault[bad] |= hardware
        fault[~bad] &= ~hardware
        if bad.any() and not self._fault_latched:
            joints = [self.view.joint_names[i] for i in np.flatnonzero(bad)]
            reason = f"board fault bits on joint(s) {', '.join(joints)}"
            self.view.fault(reason)
        self._fault_latched = bool(bad.any())

    def _board_silent(self, tick: int) -> None:
        """Fail the driver: the boards that did not answer within ``silent_ticks``, those that
        still answered, but only after the next command, named apart (a board or host too slow
        for the rate is not a dead board)."""
        silent = np.flatnonzero(tick - self.board_tick > self.options.silent_ticks)
        self.silent_boards = [self.board_ids[i] for i in silent]
        for i in silent:
            self.view.state.fault[self.board_rows[i]] |= np.uint32(Fault.HARDWARE)
        # late: its late answers kept coming through the second half of the silence; a board
        # whose last answer before dying came late (a stalled host) is silent, not slow
        recent = tick - self.options.silent_ticks // 2
        late = [self.board_ids[i] for i in silent if self.board_late_tick[i] > max(self.board_tick[i], recent)]
        quiet = [board for board in self.silent_boards if board not in late]
        reasons = []
        if quiet:
            reasons.append(f"board(s) {quiet} silent for more than {self.options.silent_ticks} ticks")
        if late:
            reasons.append(
                f"board(s) {late} answered only late (after the next command) for more than "
                f"{self.options.silent_ticks} ticks: the boards, the network or this host cannot keep the rate"
            )
        raise UdpError("; ".join(reasons))

    async def write(self) -> None:
        command, tx = self.view.command, self._tx
        np.copyto(tx["mode"], command.mode, casting="unsafe")
        np.copyto(tx["position"], command.position, casting="same_kind")
        np.copyto(tx["velocity"], command.velocity, casting="same_kind")
        np.add(command.effort, command.feedforward, out=tx["effort"], casting="same_kind")
        np.copyto(tx["stiffness"], command.stiffness, casting="same_kind")
        np.copyto(tx["damping"], command.damping, casting="same_kind")
        self._send_commands()
        self._written = True

    def _send_commands(self) -> None:
        """Every board its datagram: its header (seq, ack, CRC, MAC) and its run of records."""
        seq = self._seq = (self._seq + 1) & 0xFFFFFFFF
        self._tx_ns[seq & (SEND_RING - 1)] = time.time_ns()
        sock, key, acks, bodies, addresses, counters = (
            self.sock,
            self.key,
            self._ack,
            self._tx_bodies,
            self.addresses,
            self.counters,
        )
        pack = SEQ_ACK.pack_into
        sent = 0
        for i, head in enumerate(self._head_views):
            pack(head, 16, seq, acks[i])
            body = bodies[i]
            seal_parts(head, body, key)
            try:
                sock.sendmsg((head, body), (), 0, addresses[i])  # type: ignore[union-attr]  # open() made it
                sent += 1
            except OSError:
                counters["send_errors"] += 1
        counters["sent"] += sent
        self._outstanding = True

    # ------------------------------------------------------------ stop

    def estop(self) -> None:
        """An ESTOP datagram to every board (they obey it at once); synchronous, idempotent."""
        self.estopped = True
        if self.sock is None or self.sock.fileno() < 0:
            return
        for i in range(len(self.addresses)):
            self._seq = (self._seq + 1) & 0xFFFFFFFF
            self._send_control(i, Kind.ESTOP)

    def release_estop(self) -> bool:
        """Leave the emergency stop: a RESET to every board (it clears the latched stop and its
        faults); the joints stay braked where they stand until the loop, re-armed, commands
        them. A RESET that is lost leaves that board's fault bits set: ``rearm()`` says so."""
        if self.sock is None or self.sock.fileno() < 0:
            return False
        self.estopped = False
        for i in range(len(self.addresses)):
            self._seq = (self._seq + 1) & 0xFFFFFFFF
            self._send_control(i, Kind.RESET)
        return True

    def safe_actions(self) -> list:
        """The ESTOP datagram of every board, as :meth:`estop` sends it (with the MAC when a
        key is configured), sent from this driver's socket by the watchdog process: a board
        that takes datagrams only from its master's address takes it. Its ``seq`` is fixed
        when the watchdog starts: a board obeys an ESTOP whatever its ``seq`` (docs/udp.md),
        and a replayed one can only stop the robot."""
        if self.sock is None or self.sock.fileno() < 0:
            return []
        fd = self.sock.fileno()
        return [
            SendDatagram(
                host, port, bytes(encode(Kind.ESTOP, self.board_ids[i], self._seq, self._ack[i], key=self.key)), fd=fd
            )
            for i, (host, port) in enumerate(self.addresses)
        ]

    async def close(self) -> None:
        if self.sock is not None and self.sock.fileno() >= 0:
            if not self.estopped:  # leave the joints braked where they stand
                self.tx_records["mode"] = Mode.NONE
                self._send_commands()
            self.sock.close()
        if self.sim_process is not None:
            stopped = await simprocess.stop(self.sim_process, "counters")
            if stopped is not None:
                self.sim_counters = stopped["counters"]

    def health(self) -> dict[str, Any]:
        n = min(self._rtt_count, RTT_RING)
        rtt = np.sort(self._rtt_ns[:n]) / 1e3 if n else None
        out: dict[str, Any] = {
            "boards": len(self.board_ids),
            **self.counters,
            "round_trip_us_p50": None if rtt is None else round(float(rtt[n // 2]), 1),
            "round_trip_us_p99": None if rtt is None else round(float(rtt[min(n - 1, int(n * 0.99))]), 1),
            "round_trip_us_max": None if rtt is None else round(float(rtt[-1]), 1),
            "authenticated": self.key is not None,
        }
        if self.silent_boards:
            out["silent_boards"] = self.silent_boards
        if self.sim_counters is not None:
            out["simulated_boards"] = self.sim_counters
        return out
