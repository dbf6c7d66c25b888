"""The watchdog process: makes the hardware safe when the whole control process stops.

The stall watchdog of :mod:`aiohal.core.loop` is a thread: it covers an event loop stuck in an
``await``, not a process frozen whole (SIGSTOP, the GIL held by a stuck extension, a debugger,
swapped out). This one is a separate OS process, as in LOLA. The tick stores its index and
its CLOCK_MONOTONIC time into a shared page (two item stores, no system call); when that time
is older than ``watchdog_ms`` while the loop is running, the process runs the safe action
each driver declared (:meth:`aiohal.Driver.safe_actions`), marks the page as fired and waits
for the next run. It exits when asked, and with its parent: a parent that dies while running
gets the safe actions first.

Actions are plain data, built before the process starts (sockets are opened then, so that a
wrong address fails the loop's activation, not the emergency):

* :class:`SendDatagram`: a UDP datagram (a board's e-stop message), from a socket of its
  own or from the driver's (passed to the process, so that a board that takes datagrams only
  from its master's address takes this one);
* :class:`SendFrame`: a raw Ethernet frame on an interface (a fieldbus stop frame; root);
* :class:`SendCanFrame`: a classic CAN frame on a SocketCAN interface (an NMT stop);
* :class:`WriteFile`: bytes written to a file (a GPIO's ``value`` for a motor power relay).

Its own oversleeping (a stall of the whole machine, which also stalls the control process)
is not held against the heartbeat: after waking more than half of ``watchdog_ms`` late it
measures staleness from its own wake-up. The module imports only the standard library: the
process runs it as a script (``python -I``), in tens of milliseconds.

It is out of reach of the terminal: it runs in a session of its own (no Ctrl-C, Ctrl-\\ or
Ctrl-Z of the loop's terminal reaches it) and ignores SIGINT, SIGQUIT, SIGTSTP and SIGHUP sent
to it. The loop watches it in turn (:meth:`WatchdogProcess.trouble`): a dead, stopped or
disarmed watchdog holds the robot.
"""

from __future__ import annotations

import json
import mmap
import os
import select
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

# the shared page: int64 words
TICK, STAMP, ARMED, FIRED, COMMAND, ACTED = range(6)
#: what the terminal sends a foreground process group; the watchdog process ignores them all
TERMINAL_SIGNALS = ("SIGINT", "SIGQUIT", "SIGTSTP", "SIGHUP")
WORDS = 8
EXIT = 1


@dataclass(frozen=True)
class SendDatagram:
    """Send ``payload`` to ``host``:``port`` over UDP; from the socket ``fd`` of the control
    process when given (its source address is then the driver's own)."""

    host: str
    port: int
    payload: bytes
    fd: int | None = None


@dataclass(frozen=True)
class SendFrame:
    """Send ``frame`` (a whole Ethernet frame) on ``interface``; needs CAP_NET_RAW."""

    interface: str
    frame: bytes


CAN_EFF_FLAG = 0x80000000  # linux/can.h: a 29-bit identifier
CAN_FRAME = struct.Struct("=IB3x8s")  # struct can_frame: id, length, pad, reserved, len8_dlc, data


def can_frame(can_id: int, data: bytes, extended: bool = False) -> bytes:
    """The 16 bytes of a ``struct can_frame`` as a CAN_RAW socket sends them."""
    if len(data) > 8:
        raise ValueError(f"a classic CAN frame carries at most 8 bytes, not {len(data)}")
    if not 0 <= can_id < (1 << 29 if extended else 1 << 11):
        raise ValueError(f"CAN id 0x{can_id:X} does not fit {'29' if extended else '11'} bits")
    return CAN_FRAME.pack(can_id | (CAN_EFF_FLAG if extended else 0), len(data), bytes(data))


@dataclass(frozen=True)
class SendCanFrame:
    """Send ``frame`` (:func:`can_frame`'s bytes) on the SocketCAN ``interface`` (e.g. can0)."""

    interface: str
    frame: bytes


@dataclass(frozen=True)
class WriteFile:
    """Write ``data`` to ``path`` (e.g. ``/sys/class/gpio/gpio17/value``, ``b"0"``)."""

    path: str
    data: bytes


ACTIONS = (SendDatagram, SendFrame, SendCanFrame, WriteFile)


def _encode(owner: str, action: object) -> dict:
    fields = {k: (v.hex() if isinstance(v, bytes) else v) for k, v in vars(action).items()}
    return {"owner": owner, "kind": type(action).__name__, **fields}


class WatchdogProcess:
    """The parent's handle: the shared page, and the process watching it."""

    def __init__(self, actions: list[tuple[str, object]], watchdog_ms: float, priority: int = 0) -> None:
        for owner, action in actions:
            if not isinstance(action, ACTIONS):
                raise TypeError(f"{owner}: {action!r} is not a watchdog action")
        self.actions = actions
        self.watchdog_ms = watchdog_ms
        self.priority = priority
        self.proc: subprocess.Popen | None = None
        self._mm: mmap.mmap | None = None
        self.heartbeat: memoryview | None = None

    def start(self, timeout_s: float = 10.0) -> None:
        fd = os.memfd_create("aiohal-heartbeat")
        try:
            os.ftruncate(fd, WORDS * 8)
            self._mm = mmap.mmap(fd, WORDS * 8)
            self.heartbeat = memoryview(self._mm).cast("q")
            spec = {
                "parent": os.getpid(),
                "fd": fd,
                "watchdog_ns": round(self.watchdog_ms * 1e6),
                "priority": self.priority,
                "actions": [_encode(o, a) for o, a in self.actions],
            }
            shared = tuple(a.fd for _, a in self.actions if isinstance(a, SendDatagram) and a.fd is not None)
            self.proc = subprocess.Popen(
                [sys.executable, "-I", __file__],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                pass_fds=(fd, *shared),
                text=True,
                start_new_session=True,  # setsid: the loop's terminal and process group do not reach it
            )
        finally:
            os.close(fd)
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(spec) + "\n")
        self.proc.stdin.close()
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        line = self.proc.stdout.readline().strip() if ready else "no answer"
        if line != "ready":
            self.stop()
            raise RuntimeError(f"the watchdog process did not start: {line}")

    def arm(self) -> None:
        """The loop starts ticking: watch the heartbeat from now."""
        hb = self.heartbeat
        if hb is None:
            raise RuntimeError("arm() before start()")
        hb[FIRED] = 0
        hb[STAMP] = time.monotonic_ns()
        hb[ARMED] = 1

    def disarm(self) -> None:
        if self.heartbeat is not None:
            self.heartbeat[ARMED] = 0

    @property
    def armed(self) -> bool:
        return self.heartbeat is not None and self.heartbeat[ARMED] == 1

    def trouble(self) -> str:
        """Why this watchdog cannot stop the robot now ("" when it can): the process is dead
        or stopped (SIGSTOP, a debugger). Reads /proc: call it off the tick."""
        proc = self.proc
        if proc is None:
            return "the watchdog process is not running"
        code = proc.poll()
        if code is not None:
            return f"the watchdog process {proc.pid} is dead (exit status {code})"
        state = process_state(proc.pid)
        if state in ("T", "t"):
            return f"the watchdog process {proc.pid} is stopped"
        if state in ("Z", "X"):
            return f"the watchdog process {proc.pid} is dead"
        return ""

    @property
    def fired_ns(self) -> int:
        """CLOCK_MONOTONIC time at which the process acted (0: it has not)."""
        return self.heartbeat[FIRED] if self.heartbeat is not None else 0

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is not None:
            if self.heartbeat is not None:
                self.heartbeat[ARMED] = 0
                self.heartbeat[COMMAND] = EXIT
            try:
                proc.wait(2.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(2.0)
            if proc.stdout is not None:
                proc.stdout.close()
        if self.heartbeat is not None:
            self.heartbeat.release()
            self.heartbeat = None
        if self._mm is not None:
            self._mm.close()
            self._mm = None


def process_state(pid: int) -> str:
    """The one-letter state of a process (R, S, D, T, t, Z, ...) from /proc; "" if unknown."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read(4096)
    except OSError:
        return ""
    # "pid (comm) S ...": comm may hold spaces and parentheses, the state follows the last ")"
    return stat[stat.rfind(b")") + 2 :][:1].decode("ascii", "replace")


def _ignore_terminal_signals() -> None:
    import signal

    for name in TERMINAL_SIGNALS:
        signal.signal(getattr(signal, name), signal.SIG_IGN)


# ---------------------------------------------------------------- the process itself


def _prepare(action: dict) -> Callable[[], object]:
    """A function that runs the action now (its socket or file opened beforehand)."""
    kind = action["kind"]
    if kind == "SendDatagram":
        payload, to = bytes.fromhex(action["payload"]), (action["host"], int(action["port"]))
        if action.get("fd") is not None:  # the driver's socket: its address, never read here
            shared = socket.socket(fileno=action["fd"])
            return lambda: shared.sendto(payload, to)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.connect(to)
        return lambda: sock.send(payload)
    if kind == "SendCanFrame":
        can = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        can.bind((action["interface"],))
        can_bytes = bytes.fromhex(action["frame"])
        return lambda: can.send(can_bytes)
    if kind == "SendFrame":
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW)
        sock.bind((action["interface"], 0))
        frame = bytes.fromhex(action["frame"])
        return lambda: sock.send(frame)
    if kind == "WriteFile":
        path, data = action["path"], bytes.fromhex(action["data"])
        fd = os.open(path, os.O_WRONLY)

        def write() -> None:
            os.pwrite(fd, data, 0)

        return write
    raise ValueError(f"unknown action {kind!r}")


def _act(run: list[tuple[str, Callable[[], object]]]) -> None:
    for owner, action in run:
        try:
            action()
        except OSError as exc:
            print(f"watchdog: the safe action of {owner} failed: {exc}", file=sys.stderr, flush=True)


def main() -> int:
    _ignore_terminal_signals()
    spec = json.loads(sys.stdin.readline())
    parent = spec["parent"]
    mm = mmap.mmap(spec["fd"], WORDS * 8)
    hb = memoryview(mm).cast("q")
    os.close(spec["fd"])
    try:
        run = [(a["owner"], _prepare(a)) for a in spec["actions"]]
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", flush=True)
        return 1
    if spec["priority"]:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(spec["priority"]))
        except OSError as exc:
            print(f"watchdog: SCHED_FIFO refused ({exc}); normal scheduling", file=sys.stderr, flush=True)
    limit = spec["watchdog_ns"]
    period_ns = max(100_000, min(1_000_000, limit // 4))
    grace = limit // 2
    print("ready", flush=True)
    clock, sleep = time.monotonic_ns, time.sleep
    woke = clock()
    since = woke  # staleness is measured from here or the heartbeat, whichever is later
    while True:
        sleep(period_ns / 1e9)
        now = clock()
        if now - woke > period_ns + grace:
            since = now  # this process was not run either: a stall of the machine
        woke = now
        if hb[COMMAND] == EXIT:
            return 0
        armed = hb[ARMED] == 1
        if os.getppid() != parent:  # the parent is gone: it ticks no more
            if armed:
                _act(run)
                hb[FIRED] = clock()
            return 0
        if armed and now - max(hb[STAMP], since) > limit:
            _act(run)
            hb[ACTED] = clock()
            hb[FIRED] = now
            hb[ARMED] = 0


if __name__ == "__main__":
    sys.exit(main())
