"""The NRT side's process or thread: :class:`NrtPeer` runs a target function on an
:class:`~.ends.NrtEnd` and keeps the fast end; :func:`main` is the subprocess's entry point
(``python -m aiohal.pipe``)."""

from __future__ import annotations

import argparse
import asyncio
import inspect
import json
import os
import pkgutil
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any

from ..lifetime import child_env, die_with_parent
from .codec import PipeError
from .ends import FastEnd, NrtEnd, PeerGone, pipe_pair


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
    def start(
        cls, target: str, options: dict[str, Any] | None = None, *, mode: str = "subprocess", capacity: int = 32
    ) -> NrtPeer:
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
            peer._thread = threading.Thread(
                target=peer._run_thread,
                args=(fn, nrt, json.loads(options_json)),
                name=f"aiohal-nrt:{target}",
                daemon=True,
            )
            peer._thread.start()
            return peer
        fast, nrt = pipe_pair(capacity)
        try:
            fd = nrt.fileno()
            process = subprocess.Popen(
                [sys.executable, "-m", "aiohal.pipe", "--fd", str(fd), "--target", target, "--options", options_json],
                pass_fds=(fd,),
                stdin=subprocess.DEVNULL,
                env=child_env(),
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
        if process is None:  # neither a thread nor a subprocess: nothing to wait for
            return
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


def main(argv: list[str] | None = None) -> int:
    """``python -m aiohal.pipe --fd N --target mod:func --options JSON``: the child of an NrtPeer."""
    parser = argparse.ArgumentParser(
        prog="python -m aiohal.pipe", description="Run an NRT target on a pipe end inherited from the parent."
    )
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--target", required=True)
    parser.add_argument("--options", default="{}")
    args = parser.parse_args(argv)
    die_with_parent()  # a killed loop closes no pipe in time for a target that is not reading
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it closes the pipe to stop us
    end = NrtEnd(socket.socket(fileno=args.fd))
    try:
        _run_target(_load_target(args.target), end, json.loads(args.options))
    except Exception as exc:
        print(
            f"aiohal.pipe: target {args.target} failed: {type(exc).__name__}: {' '.join(str(exc).split())}",
            file=sys.stderr,
            flush=True,
        )
        return 1
    finally:
        end.close()
    return 0
