"""An output in a process of its own: started with the loop, stopped with it, dying with it.

The loop's process keeps one thread running Python, the tick's: whatever an output costs in
Python (encoding, compression, a network library, drawing) runs in a child process that reads
the tick ring (:mod:`.tick_ring`). Between the two, a socket pair of datagrams (``SOCK_SEQPACKET``):
the loop sends what is not in the ring (health, faults, safety changes) and never waits (a
full socket drops the message and counts it); the child answers ``ready`` once it runs and its
summary when asked to stop. The child runs in a session of its own (a Ctrl-C on the terminal
is the loop's to handle), dies with the loop through ``PR_SET_PDEATHSIG`` and by watching the
socket's end (:mod:`.output_main`).
"""

from __future__ import annotations

import asyncio
import logging
import os
import pickle
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Collection
from typing import Any

log = logging.getLogger(__name__)

#: bytes a message may take (a robot's description with its config's text fits)
MAX_MESSAGE = 1 << 20


class OutputRefused(RuntimeError):
    """The output's process could not start; ``reason`` says why in its own words."""

    def __init__(self, name: str, reason: str) -> None:
        super().__init__(f"{name}: {reason}")
        self.reason = reason


class OutputProcess:
    """One output's child process, from the loop's side.

    ``kind`` names the output (:mod:`.output_main` knows them), ``spec`` what it needs (pickled:
    the robot, the options). Start it from the loop's thread: the parent-death signal follows
    the thread that started the child.
    """

    def __init__(self, kind: str, spec: dict[str, Any], name: str, avoid_cpus: Collection[int] | None = None) -> None:
        self.kind = kind
        self.name = name
        self.sent = 0
        self.dropped_messages = 0
        self.answer: dict[str, Any] | None = None
        self.error: str | None = None
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        for s in (ours, theirs):
            s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, MAX_MESSAGE)
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "aiohal.outside.output_main", str(theirs.fileno()), str(os.getpid())],
                pass_fds=[theirs.fileno()],
                stdin=subprocess.DEVNULL,
                start_new_session=True,
                env=env,
            )
        finally:
            theirs.close()
        self._keep_off(avoid_cpus)
        self._sock = ours
        self._loop: asyncio.AbstractEventLoop | None = None
        ours.sendall(pickle.dumps(("start", kind, spec), protocol=pickle.HIGHEST_PROTOCOL))
        ours.setblocking(False)

    def _keep_off(self, cpus: Collection[int] | None) -> None:
        """Off the CPUs the tick is pinned to (``[realtime] cpus``), where there are others: the
        tick's caches stay its own."""
        if not cpus:
            return
        try:
            others = os.sched_getaffinity(0) - set(cpus)
            if others:
                os.sched_setaffinity(self.process.pid, others)
        except OSError as exc:
            log.warning("%s: not kept off CPUs %s: %s", self.name, sorted(cpus), exc)

    @property
    def pid(self) -> int:
        return self.process.pid

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def wait_ready(self, timeout_s: float) -> dict[str, Any]:
        """Block until the child says it runs (its ``ready`` info); OutputRefused with its reason if
        it failed or is silent for ``timeout_s``."""
        message = self._receive(timeout_s)
        if message is None:
            raise OutputRefused(self.name, f"no answer within {timeout_s:g} s ({self._exit_text()})")
        what, body = message
        if what != "ready":
            raise OutputRefused(self.name, str(body))
        return body

    def send(self, message: Any) -> bool:
        """Hand the child a message without waiting: False (counted) if it could not go now."""
        return self.send_bytes(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))

    def send_bytes(self, data: bytes) -> bool:
        """:meth:`send` of a message pickled already (one pickling for every output)."""
        try:
            self._sock.send(data)
        except OSError:  # full (BlockingIOError), or the child is gone
            self.dropped_messages += 1
            return False
        self.sent += 1
        return True

    def serve(self, loop: asyncio.AbstractEventLoop, act: Callable[[str, float], tuple[bool, str]]) -> None:
        """Answer the child's requests on ``loop`` (the loop's thread, between ticks): each
        ``("request", (id, name, sent))`` is acted on by ``act(name, sent) -> (success, message)``
        and answered ``("answer", id, success, message)``. ``sent`` is the child's
        ``time.monotonic()`` (one clock for every process of the host): from it ``act`` knows
        when the caller stops waiting, and refuses a request read later (a loop that was frozen)."""
        self._loop = loop

        def readable() -> None:
            for _ in range(64):  # bounded: what is there now
                try:
                    data = self._sock.recv(MAX_MESSAGE)
                except (BlockingIOError, InterruptedError):
                    return
                except OSError:
                    data = b""
                if not data:
                    loop.remove_reader(self._sock.fileno())
                    self._loop = None
                    return
                what, body = pickle.loads(data)
                if what == "request":
                    rid, name, sent = body
                    success, message = act(name, sent)
                    self.send(("answer", rid, success, message))

        loop.add_reader(self._sock.fileno(), readable)

    def stop(self, final: Any, timeout_s: float) -> dict[str, Any] | None:
        """Ask the child to finish (``final`` is its last message) and wait for its summary; a
        child that does not answer within ``timeout_s`` is killed. None when it gave no summary."""
        summary = None
        if self._loop is not None:
            self._loop.remove_reader(self._sock.fileno())
            self._loop = None
        if self.alive:
            self._sock.setblocking(True)
            try:
                self._sock.sendall(pickle.dumps(("stop", final), protocol=pickle.HIGHEST_PROTOCOL))
                message = self._receive(timeout_s)
                if message is not None and message[0] == "summary":
                    summary = message[1]
                elif message is not None:
                    self.error = str(message[1])
            except OSError:  # the child is going: its exit says why, below
                pass
        self._sock.close()
        try:
            self.process.wait(timeout=max(1.0, timeout_s / 4))
        except subprocess.TimeoutExpired:
            log.warning("%s: did not end; killed", self.name)
            self.process.kill()
            self.process.wait(timeout=10)
        if summary is None and self.error is None:
            self.error = f"the output process ended without a summary ({self._exit_text()})"
        return summary

    def kill(self) -> None:
        """End the child now (the loop is going away without a summary)."""
        if self._loop is not None:
            self._loop.remove_reader(self._sock.fileno())
            self._loop = None
        if self.alive:
            self.process.kill()
        self.process.wait(timeout=10)
        self._sock.close()

    def _receive(self, timeout_s: float) -> tuple[str, Any] | None:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            ready, _, _ = select.select([self._sock], [], [], min(left, 0.5))
            if ready:
                try:
                    data = self._sock.recv(MAX_MESSAGE)
                except BlockingIOError:
                    continue
                if not data:
                    return None  # the child is gone
                return pickle.loads(data)
            if not self.alive:
                return None

    def _exit_text(self) -> str:
        code = self.process.poll()
        if code is None:
            return "still running"
        if code < 0:
            return f"killed by {signal.Signals(-code).name}"
        return f"exit status {code}"
