"""A python-can bus over one end of a socket pair: a bus with a file descriptor, as socketcan
has, without a CAN interface on the host (no vcan here, no root). The first bus opened on a
channel takes one end and the second the other; frames are 4 bytes of id (bit 31: extended,
bit 30: error frame), a length byte and up to 8 data bytes. Registered for a test with
``monkeypatch.setitem(can.interfaces.BACKENDS, "pair", ("can_pair", "PairBus"))``."""

from __future__ import annotations

import select
import socket
import struct
import time

import can

HEAD = struct.Struct("<IB")
EXTENDED, ERROR = 1 << 31, 1 << 30

_waiting: dict[str, socket.socket] = {}  # channel -> the end the second bus takes


class PairBus(can.BusABC):
    def __init__(self, channel: str, **kwargs) -> None:
        super().__init__(channel=channel, **kwargs)
        if channel in _waiting:
            self.sock, self.channel_info = _waiting.pop(channel), f"pair {channel} end B"
        else:
            self.sock, _waiting[channel] = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            self.channel_info = f"pair {channel} end A"
        self.sock.setblocking(False)
        self.fail: str | None = None  # set by a test: every receive raises this

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        word = msg.arbitration_id | (EXTENDED if msg.is_extended_id else 0) | (ERROR if msg.is_error_frame else 0)
        try:
            self.sock.send(HEAD.pack(word, msg.dlc) + bytes(msg.data))
        except (BlockingIOError, ConnectionResetError, BrokenPipeError):  # the other end does not read,
            pass  # or is gone: on a CAN bus the frames are lost there
        except OSError as exc:
            raise can.CanOperationError(f"pair send: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.fail is not None:
            raise can.CanOperationError(self.fail)
        if timeout != 0.0 and not select.select([self.sock], [], [], timeout)[0]:
            return None, False
        try:
            data = self.sock.recv(HEAD.size + 8)
        except (BlockingIOError, ConnectionResetError):
            data = None
        if not data:  # nothing, or the other end is gone: silence, as on a bus without nodes
            time.sleep(min(timeout or 0.0, 0.01))
            return None, False
        word, dlc = HEAD.unpack_from(data)
        msg = can.Message(timestamp=time.time(), arbitration_id=word & 0x1FFFFFFF, is_extended_id=bool(word & EXTENDED),
                          is_error_frame=bool(word & ERROR), dlc=dlc, data=data[HEAD.size:])
        return msg, False

    def fileno(self) -> int:
        return self.sock.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self.sock.close()
