"""A message pipe between the fast loop and a non-real-time (NRT) endpoint, like XDDP in XBot.

A slow NRT driver (a gripper at 50-100 Hz doing blocking I/O) runs on its own, in a thread or,
by default, a subprocess with its own interpreter and GIL; the fast loop reads and writes
without ever blocking. The mechanism is an ``AF_UNIX`` ``SOCK_SEQPACKET`` socketpair: message
boundaries are kept, order and delivery are guaranteed, and when the peer dies the kernel
closes its descriptor, so the survivor sees EOF (or EPIPE) at once. The fast end only makes
non-blocking calls (``MSG_DONTWAIT``); the NRT end blocks with timeouts, or awaits.

Messages are fixed little-endian layouts of at most :data:`MAX_MESSAGE` bytes: a 16-byte
header (magic ``b"AH"``, version, type, seq, stamp_ns) and the fields of a :class:`Message`
subclass, registered by its ``TYPE``. Every send stamps the header with the sender's own
sequence number (u32, one per send attempt, so a message dropped on a full pipe shows as a gap
``lost`` at the receiver) and ``time.monotonic_ns()`` (one clock system-wide, comparable across
processes).

Run on the NRT side of a subprocess peer (see :class:`NrtPeer`)::

    python -m aiohal.pipe --fd N --target package.module:function --options JSON

See docs/pipe.md for the choice of mechanism, capacity and the measured figures.
"""

from __future__ import annotations

import argparse
import array
import asyncio
import errno
import fcntl
import functools
import inspect
import json
import os
import pkgutil
import select
import signal
import socket
import struct
import subprocess
import sys
import termios
import threading
import time
from collections.abc import Iterator
from typing import Any, Callable, ClassVar

from .errors import AiohalError

MAX_MESSAGE = 256  # bytes, header included
HEADER = struct.Struct("<2sBBIQ")  # magic, version, type, seq, stamp_ns
MAGIC = b"AH"
VERSION = 1
_PREFIX = MAGIC + bytes([VERSION])
_SEQ = struct.Struct("<I")  # the seq field, at offset 4 of the header
_SEQ_MASK = 0xFFFFFFFF
_HALF_SEQ = 1 << 31

_CODES = {code: 0 for code in "bBhHiIlLqQ"} | {code: 0.0 for code in "efd"} | {"?": False}
_RESERVED = frozenset({"seq", "stamp_ns", "TYPE", "FIELDS"})

COUNTERS = ("sent", "dropped_full", "received", "superseded", "malformed", "lost", "out_of_order")
DRAIN_LIMIT = 64  # datagrams read per receive call at least: bounded time, more than a full pipe holds

_DONTWAIT = socket.MSG_DONTWAIT
_SEND_FLAGS = socket.MSG_DONTWAIT | socket.MSG_NOSIGNAL  # EPIPE as an error, never SIGPIPE
_GONE_ERRNOS = frozenset({errno.EPIPE, errno.ECONNRESET, errno.ECONNREFUSED, errno.ENOTCONN})
_HUP = select.POLLHUP | getattr(select, "POLLRDHUP", 0)


# ---------------------------------------------------------------- errors


class PipeError(AiohalError):
    """Base of the pipe's errors."""


class MalformedMessage(PipeError, ValueError):
    """Bytes that are not a message of a registered type (or field values that cannot be encoded)."""


class MessageDefinitionError(PipeError, TypeError):
    """A :class:`Message` subclass whose TYPE or FIELDS cannot be registered."""


class PeerGone(PipeError, ConnectionError):
    """The other end closed, or its process or thread died."""


class PipeTimeout(PipeError, TimeoutError):
    """A blocking NRT call ran out of time (the fast side is not reading)."""


# ---------------------------------------------------------------- messages

_REGISTRY: dict[int, type[Message]] = {}


class Message:
    """A typed message with a fixed little-endian layout; subclass with ``TYPE`` and ``FIELDS``.

    ``TYPE`` (1..255) must be unique in the process; ``FIELDS`` is a tuple of (name, struct code)
    pairs, one scalar each (``?bBhHiIlLqQefd``). Instances take the fields as keywords (missing
    ones are zero) and carry the header's ``seq`` and ``stamp_ns`` (set by the sender's send()).
    Equality compares the type and the field values, not the header.
    """

    TYPE: ClassVar[int]
    FIELDS: ClassVar[tuple[tuple[str, str], ...]] = ()
    _names: ClassVar[tuple[str, ...]] = ()
    _defaults: ClassVar[dict[str, Any]] = {}
    _struct: ClassVar[struct.Struct]

    seq: int
    stamp_ns: int

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        name = f"{cls.__module__}.{cls.__qualname__}"
        type_id = cls.__dict__.get("TYPE")
        if type(type_id) is not int or not 1 <= type_id <= 255:
            raise MessageDefinitionError(f"{name}: TYPE must be an int in 1..255 in the class body, not {type_id!r}")
        try:
            fields = tuple((str(n), str(c)) for n, c in cls.FIELDS)
        except (TypeError, ValueError):
            raise MessageDefinitionError(f"{name}: FIELDS must be (name, struct code) pairs") from None
        names = [n for n, _ in fields]
        for field, code in fields:
            if not field.isidentifier() or field.startswith("_") or field in _RESERVED:
                raise MessageDefinitionError(f"{name}: field name {field!r} is not allowed")
            if code not in _CODES:
                raise MessageDefinitionError(f"{name}.{field}: struct code {code!r} is not one of {''.join(_CODES)}")
        if len(set(names)) != len(names):
            raise MessageDefinitionError(f"{name}: duplicate field names in {names}")
        layout = struct.Struct(HEADER.format + "".join(c for _, c in fields))
        if layout.size > MAX_MESSAGE:
            raise MessageDefinitionError(f"{name}: {layout.size} bytes with the header, more than MAX_MESSAGE = {MAX_MESSAGE}")
        other = _REGISTRY.get(type_id)
        # the same class defined again (a module reloaded) replaces itself; any other is a clash
        if other is not None and (other.__module__, other.__qualname__) != (cls.__module__, cls.__qualname__):
            raise MessageDefinitionError(
                f"{name}: TYPE {type_id} is already {other.__module__}.{other.__qualname__}")
        cls.FIELDS = fields
        cls._names = tuple(names)
        cls._defaults = {n: _CODES[c] for n, c in fields}
        cls._struct = layout
        _REGISTRY[type_id] = cls

    def __init__(self, **fields: Any) -> None:
        unknown = fields.keys() - self._defaults.keys()
        if unknown:
            raise TypeError(f"{type(self).__name__} has no field(s) {', '.join(sorted(unknown))}")
        self.seq = 0
        self.stamp_ns = 0
        self.__dict__.update(self._defaults)
        self.__dict__.update(fields)

    def encode(self) -> bytes:
        try:
            return self._struct.pack(MAGIC, VERSION, self.TYPE, self.seq, self.stamp_ns,
                                     *[getattr(self, n) for n in self._names])
        except (struct.error, OverflowError) as exc:  # a value out of its field's range or of the wrong kind
            raise MalformedMessage(f"cannot encode {self!r}: {exc}") from None

    @staticmethod
    def decode(data: bytes | bytearray | memoryview) -> Message:
        """The message in ``data`` (one whole datagram); raises :class:`MalformedMessage`."""
        cls = _check(data)
        if isinstance(cls, str):
            raise MalformedMessage(cls)
        return cls._unpack(data)

    @classmethod
    def _unpack(cls, data: bytes | bytearray | memoryview) -> Message:
        _, _, _, seq, stamp_ns, *values = cls._struct.unpack(data)
        msg = cls.__new__(cls)
        fields = msg.__dict__
        fields["seq"] = seq
        fields["stamp_ns"] = stamp_ns
        fields.update(zip(cls._names, values))
        return msg

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(getattr(self, n) == getattr(other, n) for n in self._names)

    __hash__ = None  # type: ignore[assignment]  # mutable

    def __repr__(self) -> str:
        fields = ", ".join(f"{n}={getattr(self, n, '?')!r}" for n in self._names)
        return f"{type(self).__name__}(seq={self.seq}, stamp_ns={self.stamp_ns}{', ' if fields else ''}{fields})"


def _check(data: bytes | bytearray | memoryview) -> type[Message] | str:
    """The registered class whose layout ``data`` has exactly, or why not (a string)."""
    n = len(data)
    if n < HEADER.size:
        return f"{n} bytes, shorter than the {HEADER.size}-byte header"
    magic, version, type_id, _, _ = HEADER.unpack_from(data)
    if magic != MAGIC:
        return f"bad magic {bytes(magic)!r}"
    if version != VERSION:
        return f"version {version}, expected {VERSION}"
    cls = _REGISTRY.get(type_id)
    if cls is None:
        return f"unknown message type {type_id}"
    if n != cls._struct.size:
        return f"{n} bytes for {cls.__name__}, expected {cls._struct.size}"
    return cls


# ---------------------------------------------------------------- the two ends


@functools.cache
def _truesize() -> int:
    """Bytes the kernel charges to the send buffer for the smallest message (skb truesize).

    AF_UNIX counts whole socket buffers, not payload: 768 B for any datagram of up to 192 B and
    1280 B for 193-256 B on Linux 6.x. Measured once per process with SIOCOUTQ.
    """
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    with a, b:
        a.send(bytes(HEADER.size))
        out = array.array("i", [0])
        fcntl.ioctl(a.fileno(), termios.TIOCOUTQ, out)  # SIOCOUTQ: the send buffer's charge
        return out[0]


class _End:
    """What both ends share: the socket, the counters, header stamping and seq tracking."""

    def __init__(self, sock: socket.socket) -> None:
        sock.setblocking(False)
        self._sock = sock
        self._fd = sock.fileno()
        self._poll = select.poll()
        self._poll.register(self._fd, select.POLLIN | _HUP)
        self._closed = False
        self._send_seq = 0
        self._expect_seq = 0
        # a send succeeds while the kernel's charge is below SO_SNDBUF, so ceil(sndbuf / truesize) fit
        self.capacity = -(-sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF) // _truesize())
        self.drain_limit = max(DRAIN_LIMIT, self.capacity)
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self.last_receive_ns = 0  # monotonic ns of the last valid message (0 = none yet)
        self.peer_alive = True  # False once EOF or EPIPE was seen (or this end was closed)

    def fileno(self) -> int:
        return self._fd

    def close(self) -> None:
        """Close this end (idempotent): the other end sees EOF."""
        self.peer_alive = False
        if not self._closed:
            self._closed = True
            self._sock.close()

    def _take_seq(self) -> int:
        seq = self._send_seq
        self._send_seq = (seq + 1) & _SEQ_MASK
        return seq

    def _stamp(self, msg: Message) -> bytes:
        msg.seq = self._take_seq()
        msg.stamp_ns = time.monotonic_ns()
        return msg.encode()

    def _recv_datagram(self) -> bytes | None:
        """One pending datagram, or None; raises :class:`PeerGone` at EOF. One syscall (two
        after a reset), never blocks."""
        try:
            data = self._sock.recv(MAX_MESSAGE + 1, _DONTWAIT)  # + 1: an oversized datagram shows as such
        except BlockingIOError:
            return None
        except OSError as exc:
            if exc.errno not in _GONE_ERRNOS:
                raise
            # ECONNRESET: the peer died with our messages unread. Linux reports it once, before
            # the datagrams the peer had sent us: those are still read, EOF comes after them
            try:
                data = self._sock.recv(MAX_MESSAGE + 1, _DONTWAIT)
            except OSError as again:
                raise PeerGone("the other end of the pipe is gone") from again
        if not data and self._hung_up():  # EOF, not an empty datagram (which is malformed)
            raise PeerGone("the other end of the pipe closed")
        return data

    def _hung_up(self) -> bool:
        return any(events & _HUP for _, events in self._poll.poll(0))

    def _accept(self, data: bytes) -> type[Message] | None:
        """Count one datagram; its class if it is a valid message, else None (malformed)."""
        counters = self.counters
        if len(data) >= HEADER.size and data.startswith(_PREFIX):
            self._track(_SEQ.unpack_from(data, 4)[0])
        cls = _check(data)
        if isinstance(cls, str):
            counters["malformed"] += 1
            return None
        counters["received"] += 1
        return cls

    def _track(self, seq: int) -> None:
        """Gaps in the peer's seq are messages it could not send (pipe full) or that never came."""
        gap = (seq - self._expect_seq) & _SEQ_MASK
        if gap >= _HALF_SEQ:
            self.counters["out_of_order"] += 1
            return
        self.counters["lost"] += gap
        self._expect_seq = (seq + 1) & _SEQ_MASK

    def _pending(self, limit: int) -> Iterator[tuple[bytes, type[Message]]]:
        """The valid datagrams pending, oldest first, reading at most ``limit``; malformed ones
        are counted and skipped. EOF ends it and clears ``peer_alive``."""
        for _ in range(limit):
            try:
                data = self._recv_datagram()
            except PeerGone:
                self.peer_alive = False
                return
            if data is None:
                return
            cls = self._accept(data)
            if cls is not None:
                yield data, cls

    def _drain(self, limit: int) -> tuple[tuple[bytes, type[Message]] | None, int]:
        """Read up to ``limit`` pending datagrams: the newest valid one and how many were valid.
        Only the newest is decoded (by the caller)."""
        newest, valid = None, 0
        for newest in self._pending(limit):
            valid += 1
        return newest, valid

    def _decoded(self, data: bytes, cls: type[Message]) -> Message:
        self.last_receive_ns = time.monotonic_ns()
        return cls._unpack(data)


class FastEnd(_End):
    """The loop's end. Never blocks: every call is one or a few non-blocking syscalls.

    Nothing is raised for a full pipe, a dead peer or a bad datagram: they are counted in
    :attr:`counters` and :attr:`peer_alive`, so the tick goes on whatever the NRT side does.
    """

    def send(self, msg: Message) -> bool:
        """Stamp and send ``msg``; False if the pipe is full (counted) or the peer is gone."""
        if not self.peer_alive:
            return False
        data = self._stamp(msg)
        try:
            self._sock.send(data, _SEND_FLAGS)
        except BlockingIOError:
            self.counters["dropped_full"] += 1
            return False
        except OSError as exc:
            if exc.errno not in _GONE_ERRNOS:
                raise
            self.peer_alive = False
            return False
        self.counters["sent"] += 1
        return True

    def receive_latest(self) -> Message | None:
        """Drain what is pending (at most :attr:`drain_limit`); the newest valid message, or None."""
        if self._closed:
            return None
        newest, valid = self._drain(self.drain_limit)
        if newest is None:
            return None
        self.counters["superseded"] += valid - 1
        return self._decoded(*newest)

    def receive_all(self, limit: int = DRAIN_LIMIT) -> list[Message]:
        """Every valid message pending (at most ``limit`` datagrams read), oldest first."""
        if self._closed:
            return []
        return [self._decoded(data, cls) for data, cls in self._pending(limit)]


class NrtEnd(_End):
    """The NRT side's end: blocking calls with timeouts, or awaitables for asyncio code.

    A malformed datagram is counted and skipped; the fast end gone raises :class:`PeerGone`.
    """

    def _check_open(self) -> None:
        if self._closed:
            raise PipeError("this end of the pipe is closed")

    def _wait(self, events: int, deadline: float | None) -> bool:
        """Wait until the socket is ready for ``events`` (or hung up); False at the deadline."""
        self._poll.modify(self._fd, events | _HUP)
        timeout = None if deadline is None else max(0.0, (deadline - time.monotonic()) * 1e3)
        return bool(self._poll.poll(timeout))

    def _try_send(self, data: bytes | bytearray) -> bool:
        """One non-blocking send: False if the pipe is full; :class:`PeerGone` if the fast end is gone."""
        try:
            self._sock.send(data, _SEND_FLAGS)
        except BlockingIOError:
            return False
        except OSError as exc:
            if exc.errno in _GONE_ERRNOS:
                raise PeerGone("the fast end of the pipe is gone") from exc
            raise
        self.counters["sent"] += 1
        return True

    def _send_datagram(self, data: bytes | bytearray, deadline: float | None) -> None:
        # POLLOUT comes once the fast side has read 3/4 of the queue (unix_writable), not at once
        while not self._try_send(data):
            if not self._wait(select.POLLOUT, deadline):
                self.counters["dropped_full"] += 1
                raise PipeTimeout("the pipe stayed full: the fast side is not reading")

    def _take_one(self) -> Message | None:
        """The next valid pending message, malformed ones skipped; None if none is pending."""
        while (data := self._recv_datagram()) is not None:
            cls = self._accept(data)
            if cls is not None:
                return self._decoded(data, cls)
        return None

    def send(self, msg: Message, timeout: float | None = None) -> None:
        """Stamp and send ``msg``, waiting while the pipe is full (:class:`PipeTimeout` after ``timeout`` s)."""
        self._check_open()
        data = self._stamp(msg)
        self._send_datagram(data, None if timeout is None else time.monotonic() + timeout)

    def receive(self, timeout: float | None = None) -> Message | None:
        """The next valid message, waiting up to ``timeout`` s (None: for ever); None on timeout."""
        self._check_open()
        deadline = None if timeout is None else time.monotonic() + timeout
        while (msg := self._take_one()) is None:
            if not self._wait(select.POLLIN, deadline):
                return None
        return msg

    def receive_latest(self, timeout: float | None = None) -> Message | None:
        """Wait up to ``timeout`` s for a message, then drain the rest; the newest, or None."""
        first = self.receive(timeout)
        if first is None:
            return None
        newest, valid = self._drain(self.drain_limit)
        if newest is None:
            return first
        self.counters["superseded"] += valid
        return self._decoded(*newest)

    async def areceive(self) -> Message:
        """The next valid message, awaiting readability on the running loop; PeerGone at EOF."""
        self._check_open()
        while (msg := self._take_one()) is None:
            await self._ready(writable=False)
        return msg

    async def asend(self, msg: Message) -> None:
        """Stamp and send ``msg``, awaiting room while the pipe is full (cancel to give up)."""
        self._check_open()
        data = self._stamp(msg)
        while not self._try_send(data):
            await self._ready(writable=True)

    async def _ready(self, writable: bool) -> None:
        loop = asyncio.get_running_loop()
        ready = loop.create_future()

        def wake() -> None:
            if not ready.done():
                ready.set_result(None)

        if writable:
            loop.add_writer(self._fd, wake)
        else:
            loop.add_reader(self._fd, wake)
        try:
            await ready
        finally:
            if writable:
                loop.remove_writer(self._fd)
            else:
                loop.remove_reader(self._fd)


def pipe_pair(capacity: int = 32) -> tuple[FastEnd, NrtEnd]:
    """A connected pair of ends; about ``capacity`` messages fit in each direction.

    AF_UNIX charges each datagram's kernel buffer (truesize, 768 B for messages of up to 192 B
    on Linux 6.x) to the *sender's* SO_SNDBUF until the reader takes it; SO_RCVBUF plays no part.
    SO_SNDBUF is set on both sockets so that exactly ``capacity`` such messages fit (larger ones
    take 1280 B: about 60 % as many fit). The kernel's minimum buffer holds 6. The ends'
    ``capacity`` attribute says what the kernel granted.
    """
    if capacity < 1:
        raise ValueError(f"capacity must be at least 1, not {capacity}")
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for sock in (a, b):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, capacity * _truesize() // 2)  # the kernel doubles it
    return FastEnd(a), NrtEnd(b)


# ---------------------------------------------------------------- the NRT peer


def _load_target(target: str) -> Callable[..., Any]:
    """The function named by ``"package.module:function"``."""
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"target {target!r} is not 'package.module:function'")
    return pkgutil.resolve_name(target)


def _run_target(fn: Callable[..., Any], end: NrtEnd, options: dict[str, Any]) -> None:
    """Call ``fn(end, **options)`` (awaited on a fresh event loop if it is async).

    The calling thread first drops a real-time policy it may have inherited from the fast
    loop's thread (SCHED_FIFO a busy NRT side would starve the machine with). :class:`PeerGone`
    escaping the target is a clean end: the fast side closed the pipe.
    """
    if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    try:
        result = fn(end, **options)
        if inspect.iscoroutine(result):
            asyncio.run(result)
    except PeerGone:
        pass


class NrtPeer:
    """Runs ``target(nrt_end, **options)`` on the NRT side: in a subprocess (the default: its own
    interpreter and GIL, so its Python work cannot delay the tick) or in a daemon thread.

    The fast side holds :attr:`fast`. Closing it (:meth:`stop`) is the shutdown signal: the
    target sees :class:`PeerGone` and returns. A peer that dies is seen on the fast end at once
    (EOF): ``fast.peer_alive`` becomes False on its next receive or send.
    """

    def __init__(self, fast: FastEnd, mode: str, process: subprocess.Popen | None = None) -> None:
        self.fast = fast
        self.mode = mode
        self.error: str | None = None  # thread mode: the target's exception as text
        self._process = process
        self._thread: threading.Thread | None = None
        self._thread_exitcode: int | None = None

    @classmethod
    def start(cls, target: str, options: dict[str, Any] | None = None, *, mode: str = "subprocess",
              capacity: int = 32) -> NrtPeer:
        """Start ``target`` ("package.module:function") with JSON-serialisable ``options``.

        Thread mode imports the target here (errors raise now); a subprocess imports it itself
        and exits with status 1 and a line on stderr if that fails or the target raises.
        """
        if mode not in ("subprocess", "thread"):
            raise ValueError(f"unknown NRT peer mode {mode!r} (subprocess, thread)")
        options_json = json.dumps(options or {})  # the same contract in both modes
        if mode == "thread":
            fn = _load_target(target)
            fast, nrt = pipe_pair(capacity)
            peer = cls(fast, mode)
            peer._thread = threading.Thread(target=peer._run_thread, args=(fn, nrt, json.loads(options_json)),
                                            name=f"aiohal-nrt:{target}", daemon=True)
            peer._thread.start()
            return peer
        fast, nrt = pipe_pair(capacity)
        try:
            fd = nrt.fileno()
            process = subprocess.Popen(
                [sys.executable, "-m", "aiohal.pipe", "--fd", str(fd), "--target", target, "--options", options_json],
                pass_fds=(fd,), stdin=subprocess.DEVNULL,
            )
        except BaseException:
            fast.close()
            raise
        finally:
            nrt.close()  # the child holds the only copy now: its death is EOF here
        return cls(fast, mode, process)

    def _run_thread(self, fn: Callable[..., Any], end: NrtEnd, options: dict[str, Any]) -> None:
        try:
            _run_target(fn, end, options)
            self._thread_exitcode = 0
        except BaseException as exc:  # kept for the fast side, which cannot see this thread's stack
            self.error = f"{type(exc).__name__}: {exc}"
            self._thread_exitcode = 1
        finally:
            end.close()  # EOF on the fast end

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    @property
    def exitcode(self) -> int | None:
        """Subprocess: its return code (negative: killed by that signal). Thread: 0, or 1 if it raised."""
        if self._process is not None:
            return self._process.poll()
        return self._thread_exitcode

    def alive(self) -> bool:
        """Whether the process or thread still runs (non-blocking)."""
        if self._process is not None:
            return self._process.poll() is None
        return self._thread is not None and self._thread.is_alive()

    def kill(self) -> None:
        """SIGKILL the subprocess (tests, emergencies). A thread cannot be killed: :class:`PipeError`."""
        if self._process is None:
            raise PipeError("an NRT thread cannot be killed; stop() closes its pipe and waits")
        if self._process.poll() is None:
            self._process.kill()

    def stop(self, timeout: float = 1.0) -> None:
        """Close the fast end and wait up to ``timeout`` s for the target to return.

        Then a subprocess gets SIGTERM, and SIGKILL, each with ``timeout`` s more (so at most
        about 3 × ``timeout`` in all); a thread that does not return is left running (a daemon).
        Idempotent.
        """
        self.fast.close()
        if self._thread is not None:
            self._thread.join(timeout)
            return
        process = self._process
        for escalate in (None, process.terminate, process.kill):
            if process.poll() is not None:
                return
            if escalate is not None:
                escalate()
            try:
                process.wait(timeout)
                return
            except subprocess.TimeoutExpired:
                pass


# ---------------------------------------------------------------- built-in targets (tests, benchmarks)


def _echo_pending(end: NrtEnd) -> None:
    """Send back every pending datagram that has an aiohal header, with this end's own seq.

    Raw datagrams: any message type is echoed, registered in this process or not, and its
    ``stamp_ns`` is kept, so the fast side reads the round trip from the echo itself.
    """
    while (data := end._recv_datagram()) is not None:
        if len(data) >= HEADER.size and data.startswith(_PREFIX):
            reply = bytearray(data)
            _SEQ.pack_into(reply, 4, end._take_seq())
            end._send_datagram(reply, None)


def echo(end: NrtEnd, **_: Any) -> None:
    """Echo every message back unchanged except its seq, until the fast end closes."""
    while True:
        _echo_pending(end)
        end._wait(select.POLLIN, None)


def busy_echo(end: NrtEnd, busy_fraction: float = 1.0, slice_ms: float = 1.0, **_: Any) -> None:
    """Echo while burning pure-Python CPU: ``slice_ms`` of a tight loop between non-blocking polls.

    With ``busy_fraction`` 1 the NRT side's interpreter never rests (its GIL is always wanted);
    below 1 it sleeps so that the loop takes that fraction of the time.
    """
    burn_ns = int(slice_ms * 1e6)
    rest_s = slice_ms / 1e3 * (1.0 - busy_fraction) / busy_fraction if busy_fraction < 1.0 else 0.0
    mono = time.monotonic_ns
    while True:
        _echo_pending(end)
        until = mono() + burn_ns
        while mono() < until:
            pass
        if rest_s:
            time.sleep(rest_s)


# ---------------------------------------------------------------- subprocess entry point


def main(argv: list[str] | None = None) -> int:
    """``python -m aiohal.pipe --fd N --target mod:func --options JSON``: the child of an NrtPeer."""
    parser = argparse.ArgumentParser(prog="python -m aiohal.pipe",
                                     description="Run an NRT target on a pipe end inherited from the parent.")
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--target", required=True)
    parser.add_argument("--options", default="{}")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it closes the pipe to stop us
    end = NrtEnd(socket.socket(fileno=args.fd))
    try:
        _run_target(_load_target(args.target), end, json.loads(args.options))
    except Exception as exc:
        print(f"aiohal.pipe: target {args.target} failed: {type(exc).__name__}: {' '.join(str(exc).split())}",
              file=sys.stderr, flush=True)
        return 1
    finally:
        end.close()
    return 0


if __name__ == "__main__":
    # Through the package's module, not this __main__ copy: one message registry with the target.
    from aiohal.pipe import main as _main

    sys.exit(_main())
