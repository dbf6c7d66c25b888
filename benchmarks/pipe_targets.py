"""NRT targets for the pipe's benchmark and tests: echoes on raw datagrams, idle or busy.

    NrtPeer.start("benchmarks.pipe_targets:echo")
"""

from __future__ import annotations

import select
import time
from typing import Any

from aiohal.pipe.codec import _PREFIX, _SEQ, HEADER
from aiohal.pipe.ends import NrtEnd


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
