"""The live view: the recorder's channels served over the Foxglove WebSocket protocol.

foxglove-sdk (extra ``foxglove``) runs the server in its own native threads; the recorder's
writer thread hands it the same encoded messages it writes to the file, every
``live_decimate``-th tick, so the tick does nothing more for it.
"""

from __future__ import annotations

from typing import Any

from ..errors import AiohalError, MissingDependencyError


class FoxgloveServer:
    """A Foxglove WebSocket server on ``host:port`` (localhost by default; port 0: any free port)."""

    def __init__(self, port: int = 8765, host: str = "127.0.0.1", name: str = "aiohal") -> None:
        try:
            import foxglove
        except ImportError as exc:
            raise MissingDependencyError(
                f"--foxglove needs foxglove-sdk: pip install 'aiohal[foxglove]' ({exc})"
            ) from None
        self._foxglove = foxglove
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
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

    def close(self) -> None:
        self.server.stop()
