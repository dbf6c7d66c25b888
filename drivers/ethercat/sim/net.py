"""Raw-socket runner: answer EtherCAT frames on one network interface, serve control commands.

The runner opens an ``AF_PACKET`` socket bound to EtherType 0x88A4 on exactly the interface it
is given (nothing else is ever opened), skips the frames it sent itself (``PACKET_OUTGOING``),
and answers every frame through :meth:`Segment.handle_frame`. Delayed replies (fault injection)
wait in a heap and go out when due, without holding up other frames. The control channel is a
UNIX stream socket at a filesystem path: unlike an abstract or TCP socket, a path works across
network namespaces. One request line (JSON) per connection, one answer line.
"""

from __future__ import annotations

import errno
import fcntl
import heapq
import os
import select
import socket
import struct
import sys
import time
import traceback
from typing import TextIO

from .control import apply_line
from .segment import Segment

ETH_P_ECAT = 0x88A4
PACKET_OUTGOING = 4
SIOCGIFFLAGS = 0x8913
SIOCSIFFLAGS = 0x8914
IFF_UP = 0x1
POLL_S = 0.005
# a wake-up later than the poll's timeout by more than this, or a step of the loop taking this
# long, means this process was not run (a stall of the host, which stalls the master as well):
# that time is not held against the slaves' watchdogs, as hardware slaves would not have
# stalled with it. Checked between every two steps of the loop, so that a stall anywhere in it
# is seen before the watchdogs are.
STALL_GRACE_NS = 50_000_000
MAX_FRAME = 2048
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; the kernel stamps each frame's arrival
TIMESPEC = struct.Struct("@qq")
ANCILLARY = socket.CMSG_SPACE(TIMESPEC.size)
MAX_REQUEST = 65536


def wait_for_interface(ifname: str, timeout_s: float) -> int:
    """The interface index, once ``ifname`` exists in this network namespace (bounded wait).

    Uses ``if_nametoindex`` (which looks at the caller's namespace), not /sys/class/net (which
    shows the namespace sysfs was mounted for)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return socket.if_nametoindex(ifname)
        except OSError:
            if time.monotonic() >= deadline:
                raise TimeoutError(f"interface {ifname!r} did not appear within {timeout_s} s") from None
        time.sleep(0.002)


def set_up(ifname: str) -> None:
    """Bring the interface up (SIOCSIFFLAGS); needs CAP_NET_ADMIN in its namespace."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        ifr = struct.pack("16sH14x", ifname.encode(), 0)
        flags = struct.unpack_from("16sH", fcntl.ioctl(s, SIOCGIFFLAGS, ifr))[1]
        if not flags & IFF_UP:
            fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack("16sH14x", ifname.encode(), flags | IFF_UP))


def disable_ipv6(ifname: str) -> bool:
    """Silence IPv6 autoconfiguration traffic on the interface (best effort)."""
    try:
        with open(f"/proc/sys/net/ipv6/conf/{ifname}/disable_ipv6", "w") as f:
            f.write("1")
        return True
    except OSError:
        return False


class Runner:
    def __init__(
        self,
        segment: Segment,
        ifname: str,
        control_path: str | None = None,
        out: TextIO = sys.stdout,
        parent_pid: int | None = None,
    ) -> None:
        self.parent_pid = parent_pid
        self.segment = segment
        self.ifname = ifname
        self.control_path = control_path
        self.out = out
        self.sock: socket.socket | None = None
        self.ctrl: socket.socket | None = None
        self._conns: dict[int, tuple[socket.socket, bytearray]] = {}
        self._delayed: list[tuple[int, int, bytes]] = []
        self._seq = 0
        self.running = False
        self.errors = 0

    def open(self) -> None:
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ECAT))
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            sock.bind((self.ifname, ETH_P_ECAT))
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self.sock = sock
        if self.control_path:
            try:
                os.unlink(self.control_path)
            except FileNotFoundError:
                pass
            ctrl = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            ctrl.bind(self.control_path)
            os.chmod(self.control_path, 0o600)
            ctrl.listen(8)
            ctrl.setblocking(False)
            self.ctrl = ctrl

    def close(self) -> None:
        for conn, _ in self._conns.values():
            conn.close()
        self._conns.clear()
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        if self.ctrl is not None:
            self.ctrl.close()
            self.ctrl = None
            if self.control_path:
                try:
                    os.unlink(self.control_path)
                except FileNotFoundError:
                    pass

    # ------------------------------------------------------------------ loop
    def serve(self, duration_s: float | None = None) -> None:
        assert self.sock is not None
        ep = select.epoll()
        raw_fd = self.sock.fileno()
        ep.register(raw_fd, select.EPOLLIN)
        ctrl_fd = -1
        if self.ctrl is not None:
            ctrl_fd = self.ctrl.fileno()
            ep.register(ctrl_fd, select.EPOLLIN)
        buf = bytearray(MAX_FRAME)
        view = memoryview(buf)
        recv = self.sock.recvmsg_into
        buffers = [buf]
        send = self.sock.send
        wall_ns = time.time_ns
        stamp = TIMESPEC.unpack_from
        handle = self.segment.handle_frame
        seg = self.segment

        def not_run(gap_ns: int) -> None:
            """A step of the loop took ``gap_ns`` more than it should: past the grace, a stall."""
            if gap_ns > STALL_GRACE_NS:
                seg.discount_stall(gap_ns)

        end = None if duration_s is None else time.monotonic() + duration_s
        self.running = True
        last = seg.clock()
        try:
            while self.running:
                timeout = max(0.0, min(POLL_S, (seg._next_poll - seg.clock()) / 1e9))
                if self._delayed:
                    due = (self._delayed[0][0] - seg.clock()) / 1e9
                    timeout = max(0.0, min(timeout, due))
                if end is not None:
                    left = end - time.monotonic()
                    if left <= 0:
                        break
                    timeout = min(timeout, left)
                events = ep.poll(timeout)
                mark = seg.clock()
                not_run(mark - last - round(timeout * 1e9))
                for fd, _ev in events:
                    if fd == raw_fd:
                        for _ in range(256):  # drain, bounded
                            try:
                                n, ancillary, _flags, addr = recv(buffers, ANCILLARY)
                            except BlockingIOError:
                                break
                            except OSError as exc:
                                if exc.errno in (errno.ENETDOWN, errno.ENXIO, errno.ENODEV):
                                    print(f"interface {self.ifname} is gone: {exc}", file=sys.stderr)
                                    self.running = False
                                    break
                                raise
                            if addr[2] == PACKET_OUTGOING:
                                continue
                            now = seg.clock()  # a stall since the poll (or the last frame) is not the master's
                            not_run(now - mark)
                            try:
                                reply = handle(bytes(view[:n]))
                            except Exception:  # a model bug must not kill the segment
                                self.errors += 1
                                if self.errors <= 5:
                                    traceback.print_exc()
                                continue
                            mark = seg.clock()
                            not_run(mark - now)  # stalled while handling it
                            if reply is None:
                                continue
                            if seg.last_delay_ns:
                                self._seq += 1
                                heapq.heappush(self._delayed, (seg.clock() + seg.last_delay_ns, self._seq, reply))
                            else:
                                try:
                                    send(reply)
                                except OSError as exc:
                                    if exc.errno not in (errno.ENOBUFS, errno.EAGAIN, errno.ENETDOWN):
                                        raise
                                if seg.last_logical and ancillary:
                                    level, kind, data = ancillary[0]
                                    if (
                                        level == socket.SOL_SOCKET
                                        and kind == SO_TIMESTAMPNS
                                        and len(data) >= TIMESPEC.size
                                    ):
                                        sec, nsec = stamp(data)
                                        seg.note_reply_latency(wall_ns() - sec * 1_000_000_000 - nsec)
                    elif fd == ctrl_fd:
                        self._accept(ep)
                    else:
                        self._serve_conn(ep, fd)
                now = seg.clock()
                not_run(now - mark)  # stalled after the last frame (or serving control)
                while self._delayed and self._delayed[0][0] <= now:
                    _, _, reply = heapq.heappop(self._delayed)
                    try:
                        send(reply)
                    except OSError:
                        pass
                if now >= seg._next_poll:
                    seg.poll(now)
                    if self.parent_pid is not None and os.getppid() != self.parent_pid:
                        break  # the process that started us is gone: do not outlive it
                last = seg.clock()
        finally:
            ep.close()

    def _accept(self, ep: select.epoll) -> None:
        assert self.ctrl is not None
        for _ in range(16):
            try:
                conn, _ = self.ctrl.accept()
            except BlockingIOError:
                return
            conn.setblocking(False)
            self._conns[conn.fileno()] = (conn, bytearray())
            ep.register(conn.fileno(), select.EPOLLIN)

    def _serve_conn(self, ep: select.epoll, fd: int) -> None:
        conn, pending = self._conns[fd]
        try:
            chunk = conn.recv(4096)
        except BlockingIOError:
            return
        except OSError:
            chunk = b""
        done = not chunk
        pending += chunk
        if b"\n" in pending or (done and pending):
            line = bytes(pending.split(b"\n", 1)[0])
            try:
                answer = apply_line(self.segment, line)
            except Exception as exc:  # a control request never takes the segment down
                answer = f'{{"ok": false, "error": "internal error: {type(exc).__name__}"}}\n'.encode()
            conn.setblocking(True)
            conn.settimeout(1.0)
            try:
                conn.sendall(answer)
            except OSError:
                pass
            done = True
        if done or len(pending) > MAX_REQUEST:
            ep.unregister(fd)
            conn.close()
            del self._conns[fd]
