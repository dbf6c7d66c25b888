"""The live view: the recorder's channels served over the Foxglove WebSocket protocol.

foxglove-sdk (extra ``foxglove``) runs the server in its own native threads; the recorder's
writer thread hands it the same encoded messages it writes to the file, every
``live_decimate``-th tick, so the tick does nothing more for it. A latched channel (``/robot``)
keeps its last message and sends it again whenever a client subscribes to it, as ROS 2's
transient-local topics do: a client that connects late still learns the joint names.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from ..errors import AiohalError, MissingDependencyError

log = logging.getLogger(__name__)


class FoxgloveServer:
    """A Foxglove WebSocket server on ``host:port`` (localhost by default; port 0: any free port)."""

    def __init__(self, port: int = 8765, host: str = "127.0.0.1", name: str = "aiohal") -> None:
        try:
            import foxglove
            from foxglove.websocket import ServerListener
        except ImportError as exc:
            raise MissingDependencyError(
                f"--foxglove needs foxglove-sdk: pip install 'aiohal[foxglove]' ({exc})"
            ) from None
        self._foxglove = foxglove
        self.context = foxglove.Context()
        #: channel id -> (channel, its last message, its log time)
        self._latched: dict[int, tuple[Any, bytes, int]] = {}
        self._lock = threading.Lock()  # the server's threads call on_subscribe
        resend = self._resend

        class Listener(ServerListener):
            def on_subscribe(self, client: Any, channel: Any) -> None:
                resend(client, channel)

        try:
            self.server = foxglove.start_server(
                name=name, host=host, port=port, context=self.context, server_listener=Listener()
            )
        except RuntimeError as exc:  # foxglove raises its errors as RuntimeError("FoxgloveError: ...")
            raise AiohalError(f"--foxglove {port}: the live view cannot listen on {host}:{port} ({exc})") from None
        self.host = host
        self.port = self.server.port

    def channel(self, topic: str, schema_name: str, schema_encoding: str, schema: bytes, message_encoding: str) -> Any:
        fg = self._foxglove
        return fg.Channel(
            topic,
            schema=fg.Schema(name=schema_name, encoding=schema_encoding, data=schema),
            message_encoding=message_encoding,
            context=self.context,
        )

    @staticmethod
    def log(channel: Any, data: bytes, log_time_ns: int) -> None:
        channel.log(data, log_time=log_time_ns)

    def latch(self, channel: Any, data: bytes, log_time_ns: int) -> None:
        """Send ``data`` now and to every client that subscribes to ``channel`` later."""
        with self._lock:
            self._latched[channel.id()] = (channel, data, log_time_ns)
        channel.log(data, log_time=log_time_ns)

    def _resend(self, client: Any, channel: Any) -> None:
        """A client subscribed: a latched channel's last message goes out again. The SDK sends
        it to every subscriber of the channel; a static message received twice changes nothing."""
        with self._lock:
            latched = self._latched.get(channel.id)
        if latched is not None:
            target, data, log_time = latched
            target.log(data, log_time=log_time)
            log.debug("live view: %s sent again for client %s", channel.topic, client.id)

    def close(self) -> None:
        self.server.stop()
