"""The entry point of an output process (:mod:`.output_process`): it dies with the loop.

``python -m aiohal.outside.output_main FD PARENT_PID``: FD is the socket to the loop. The
process asks the kernel for SIGTERM when its parent ends (``PR_SET_PDEATHSIG``), and also ends
when the socket reaches its end; either way the output finishes what it has (a recording
closes its file) within a bounded time, then the process exits.
"""

from __future__ import annotations

import ctypes
import logging
import os
import pickle
import select
import signal
import socket
import sys
import time
from typing import Any

log = logging.getLogger("aiohal.outside.output")

PR_SET_PDEATHSIG = 1
#: after the loop is gone, how long an output may take to finish before the process exits anyway
FINISH_S = 10.0
MAX_MESSAGE = 1 << 20


def die_with_parent(parent: int) -> None:
    """SIGTERM when the parent ends; exit now if it already has."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the socket's end still stops us
        pass
    if os.getppid() != parent:
        sys.exit(0)


class Channel:
    """The child's side of the socket: messages in, answers out."""

    def __init__(self, fd: int) -> None:
        self.sock = socket.socket(fileno=fd)
        self.closed = False

    def receive(self, timeout_s: float) -> Any:
        """The next message, or None (none within ``timeout_s``, or the loop is gone: ``closed``)."""
        if self.closed:
            return None
        ready, _, _ = select.select([self.sock], [], [], timeout_s)
        if not ready:
            return None
        try:
            data = self.sock.recv(MAX_MESSAGE)
        except OSError:
            data = b""
        if not data:
            self.closed = True
            return None
        return pickle.loads(data)

    def answer(self, what: str, body: Any) -> None:
        """Send a message to the loop (from any thread: each is one datagram)."""
        try:
            self.sock.sendall(pickle.dumps((what, body), protocol=pickle.HIGHEST_PROTOCOL))
        except OSError:
            self.closed = True


def make_output(kind: str, spec: dict[str, Any], channel: Channel) -> Any:
    """The output object: ``step() -> bool`` (True: nothing was left to do), ``message(m)``,
    ``finish(final) -> summary``, ``info() -> dict``."""
    if kind == "recorder":
        from .recorder_writer import RecorderWriter

        return RecorderWriter(spec)
    if kind == "status":
        from .terminal_status import StatusOutput

        return StatusOutput(spec)
    if kind == "zenoh":
        from .zenoh_output import ZenohOutput

        return ZenohOutput(spec, channel)
    raise ValueError(f"unknown output {kind!r}")


def run(channel: Channel) -> int:
    stop = [False]
    signal.signal(signal.SIGTERM, lambda *_: stop.__setitem__(0, True))
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the loop stops us
    first = channel.receive(60.0)
    if first is None or first[0] != "start":
        return 1
    _, kind, spec = first
    try:
        output = make_output(kind, spec, channel)
    except Exception as exc:
        from ..errors import AiohalError

        channel.answer("error", str(exc) if isinstance(exc, AiohalError) else f"{type(exc).__name__}: {exc}")
        return 1
    channel.answer("ready", output.info())
    final: Any = None
    while not stop[0]:
        idle = output.step()
        message = channel.receive(output.IDLE_S if idle else 0.0)
        while message is not None:
            if message[0] == "stop":
                final = message
                break
            output.message(message)
            message = channel.receive(0.0)
        if final is not None or channel.closed:
            break
    if final is None:  # the loop is gone: finish within a bound, whatever is left
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        signal.alarm(int(FINISH_S))
    summary = output.finish(None if final is None else final[1])
    channel.answer("summary", summary)
    return 0


def main() -> None:
    fd, parent = int(sys.argv[1]), int(sys.argv[2])
    die_with_parent(parent)
    try:
        os.nice(5)  # behind the tick when both want a core
    except OSError:
        pass
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s[%(process)d]: %(message)s")
    started = time.monotonic()
    code = run(Channel(fd))
    log.debug("output process done after %.1f s", time.monotonic() - started)
    sys.exit(code)


if __name__ == "__main__":
    main()
