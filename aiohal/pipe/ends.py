"""The two ends of a pipe: :class:`FastEnd` for the fast loop, which never blocks, and
:class:`NrtEnd` for the NRT side, which blocks with timeouts or awaits; :func:`pipe_pair`
makes a connected pair (an ``AF_UNIX`` ``SOCK_SEQPACKET`` socketpair)."""

from __future__ import annotations

import array
import asyncio
import errno
import fcntl
import functools
import select
import socket
import termios
import time
from collections.abc import Iterator

from .codec import _HALF_SEQ, _PREFIX, _SEQ, _SEQ_MASK, HEADER, MAX_MESSAGE, Message, PipeError, _check

COUNTERS = ("sent", "dropped_full", "received", "superseded", "malformed", "lost", "out_of_order")
DRAIN_LIMIT = 64  # datagrams read per receive call at least: bounded time, more than a full pipe holds

_DONTWAIT = socket.MSG_DONTWAIT
_SEND_FLAGS = socket.MSG_DONTWAIT | socket.MSG_NOSIGNAL  # EPIPE as an error, never SIGPIPE
_GONE_ERRNOS = frozenset({errno.EPIPE, errno.ECONNRESET, errno.ECONNREFUSED, errno.ENOTCONN})
_HUP = select.POLLHUP | getattr(select, "POLLRDHUP", 0)


class PeerGone(PipeError, ConnectionError):
    """The other end closed, or its process or thread died."""


class PipeTimeout(PipeError, TimeoutError):
    """A blocking NRT call ran out of time (the fast side is not reading)."""


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
        for newest in self._pending(limit):  # noqa: B007 - the loop leaves the newest in ``newest``
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
