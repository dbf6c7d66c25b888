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

from .codec import HEADER, MAGIC, MAX_MESSAGE, VERSION, MalformedMessage, Message, MessageDefinitionError, PipeError
from .ends import COUNTERS, DRAIN_LIMIT, FastEnd, NrtEnd, PeerGone, PipeTimeout, pipe_pair
from .peer import NrtPeer, main

__all__ = [
    "COUNTERS",
    "DRAIN_LIMIT",
    "HEADER",
    "MAGIC",
    "MAX_MESSAGE",
    "VERSION",
    "FastEnd",
    "MalformedMessage",
    "Message",
    "MessageDefinitionError",
    "NrtEnd",
    "NrtPeer",
    "PeerGone",
    "PipeError",
    "PipeTimeout",
    "main",
    "pipe_pair",
]
