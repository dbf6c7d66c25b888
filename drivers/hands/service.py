"""The NRT side of a hand: a slow loop around a blocking backend, behind an ``aiohal.pipe``.

``serve`` is the target the ``nrt_hand`` driver starts with ``NrtPeer`` (in a subprocess by
default). At ``rate_hz`` it applies the newest grasp command, reads the hand and sends its
state back. Every backend call may block; a failing call becomes a fault code in the state
sent, and the backend is reopened after ``reopen_s``. It returns when the fast end is gone.
"""

from __future__ import annotations

import logging
import pkgutil
import time

from aiohal.logutil import RateLimitedLogger
from aiohal.pipe import NrtEnd, PeerGone

from .base import FAULT_BACKEND, HandBackend, HandError, HandStatus
from .messages import HandCommandMsg, HandStateMsg

log = logging.getLogger(__name__)
_warn = RateLimitedLogger(log)

NO_COMMAND = 0xFFFFFFFF  # ``command_seq`` before any command was applied (seq numbers start at 0)

BACKENDS = {
    "sim": "aiohal.drivers.hands.sim:SimHand",
    "robotiq": "aiohal.drivers.hands.robotiq:Robotiq2F85",
}


def make_backend(name: str, options: dict) -> HandBackend:
    """A backend by short name (``sim``, ``robotiq``) or ``package.module:Class``."""
    cls = pkgutil.resolve_name(BACKENDS.get(name, name))
    return cls(**options)


def serve(
    end: NrtEnd,
    backend: str = "sim",
    backend_options: dict | None = None,
    rate_hz: float = 100.0,
    reopen_s: float = 1.0,
    stall_after_s: float | None = None,
) -> None:
    """Run the hand until the fast end closes. ``stall_after_s`` (tests): stop answering then."""
    hand = make_backend(backend, backend_options or {})
    period = 1.0 / rate_hz
    started = time.monotonic()
    try:
        _loop(end, hand, period, reopen_s, None if stall_after_s is None else started + stall_after_s)
    except PeerGone:
        pass
    finally:
        try:
            hand.close()
        except Exception as exc:  # closing is best effort: the process is ending anyway
            log.warning("hand backend close failed: %s", exc)


def _loop(end: NrtEnd, hand: HandBackend, period: float, reopen_s: float, stall_at: float | None) -> None:
    command: HandCommandMsg | None = None
    applied_seq = NO_COMMAND
    opened, retry_at = False, time.monotonic()
    status = HandStatus()
    next_t = time.monotonic()
    while True:
        msg = end.receive_latest(timeout=max(next_t - time.monotonic(), 0.0))
        if isinstance(msg, HandCommandMsg):
            command = msg
        now = time.monotonic()
        if now < next_t:
            continue  # a command came early: keep it and wait for the period
        next_t = next_t + period if now - next_t < period else now + period
        if stall_at is not None and now >= stall_at:
            while True:  # answer nothing, but still notice when the fast end goes away
                end.receive(timeout=0.1)
        if now >= retry_at:
            try:
                if not opened:
                    hand.open()
                    opened = True
                if command is not None and command.seq != applied_seq:
                    hand.command(_unit(command.grasp), _unit(command.speed), _unit(command.force))
                    applied_seq = command.seq
                status = hand.read()
            except HandError as exc:
                # report the fault every period, but leave the hand alone for reopen_s; a hand
                # that was open is not re-activated (that would move it), only read again
                status = HandStatus(status.position, status.effort, False, exc.code, False)
                opened = opened and exc.code != FAULT_BACKEND
                retry_at = now + reopen_s
                _warn.warning("hand", "hand: %s", exc.reason)
        state = HandStateMsg(
            position=status.position,
            effort=status.effort,
            object_detected=status.object_detected,
            ready=status.ready,
            fault=status.fault,
            command_seq=applied_seq,
        )
        try:
            end.send(state, timeout=period)
        except TimeoutError:
            pass  # the fast side is not reading: this state is dropped, the next one is newer


def _unit(value: float) -> float:
    return min(max(value, 0.0), 1.0)
