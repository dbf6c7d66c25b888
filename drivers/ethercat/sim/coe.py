"""Mailbox protocol and CoE (CANopen over EtherCAT) server of one simulated slave.

Mailbox header (6 bytes): length of the data that follows (u16), station address (u16),
channel/priority (u8), type (low nibble; 3 = CoE) | counter << 4.
CoE header (u16): number (9 bits) | service << 12 (1 emergency, 2 SDO request, 3 SDO response,
8 SDO information).
SDO part: command byte, index (u16), sub-index (u8), then 4 bytes (expedited data or complete
size) and the data of a normal transfer.

What is served: expedited, normal and segmented upload and download, complete access (sub-index
0 travels as 16 bits, as SOEM expects for PDO assignment and mapping objects), aborts, SDO
information (object list, object description, entry description) and emergencies.

Aborts go out with CoE service 2 (SDO request), not 3: SOEM only reports an SdoError for that
form (measured; see the reference notes).
"""

from __future__ import annotations

import struct
from typing import Any

from aiohal.simulation.od import (
    ABORT_COMMAND,
    ABORT_GENERAL,
    ABORT_LENGTH,
    ABORT_NO_OBJECT,
    ABORT_TOGGLE,
    ARRAY,
    RECORD,
    RO,
    RW,
    RWP,
    WO,
    ObjectDictionary,
    SdoAbort,
)

MBX_ERR = 0x00
MBX_COE = 0x03

COE_EMERGENCY = 1
COE_SDO_REQ = 2
COE_SDO_RES = 3
COE_SDO_INFO = 8

# mailbox error details (ETG.1000.4)
MBXERR_SYNTAX = 0x0001
MBXERR_UNSUPPORTED_PROTOCOL = 0x0002
MBXERR_SERVICE_NOT_SUPPORTED = 0x0004
MBXERR_INVALID_HEADER = 0x0005
MBXERR_SIZE_TOO_SHORT = 0x0006
MBXERR_INVALID_SIZE = 0x0008

MBX_HEADER = struct.Struct("<HHBB")
SDO_HEAD = struct.Struct("<HBHB")  # CoE header, command, index, sub-index

# SDO information object access bits: read in PREOP/SAFEOP/OP (bits 0-2), write (bits 3-5)
_ACCESS_BITS = {RO: 0x0007, RW: 0x003F, RWP: 0x000F, WO: 0x0038}


class CoeServer:
    """Turns one received mailbox message into zero or more reply messages (bytes, header
    included). The owning ESC puts replies into its send mailbox, one at a time."""

    def __init__(self, od: ObjectDictionary, rx_size: int, tx_size: int) -> None:
        self.od = od
        self.rx_size = rx_size
        self.tx_size = tx_size
        self.counter = 0  # counter of the last message this slave sent (1..7)
        self.last_rx_counter = 0
        self.stats = {
            "sdo_upload": 0,
            "sdo_download": 0,
            "sdo_abort": 0,
            "segments": 0,
            "sdo_info": 0,
            "emergency": 0,
            "mailbox_error": 0,
            "duplicates": 0,
        }
        self._upload: dict[str, Any] | None = None
        self._download: dict[str, Any] | None = None

    def reset(self) -> None:
        """Mailbox (re)initialised: INIT state or new mailbox SyncManager configuration."""
        self.counter = 0
        self.last_rx_counter = 0
        self._upload = None
        self._download = None

    # ------------------------------------------------------------------ framing helpers
    def _next_counter(self) -> int:
        self.counter = self.counter % 7 + 1
        return self.counter

    def _message(self, mtype: int, payload: bytes) -> bytes:
        return MBX_HEADER.pack(len(payload), 0, 0, mtype | (self._next_counter() << 4)) + payload

    def mailbox_error(self, detail: int) -> bytes:
        self.stats["mailbox_error"] += 1
        return self._message(MBX_ERR, struct.pack("<HH", 0x0001, detail))

    def emergency(self, code: int, register: int, data: bytes = b"") -> bytes:
        self.stats["emergency"] += 1
        payload = struct.pack("<HHB", COE_EMERGENCY << 12, code, register) + data[:5].ljust(5, b"\0")
        return self._message(MBX_COE, payload)

    def _sdo(self, service: int, command: int, index: int, sub: int, rest: bytes) -> bytes:
        payload = SDO_HEAD.pack(service << 12, command, index, sub) + rest
        if len(payload) < 10:
            payload += bytes(10 - len(payload))
        return self._message(MBX_COE, payload)

    def _abort(self, index: int, sub: int, code: int) -> bytes:
        self.stats["sdo_abort"] += 1
        self._upload = None
        self._download = None
        return self._sdo(COE_SDO_REQ, 0x80, index, sub, struct.pack("<I", code))

    # ------------------------------------------------------------------ entry point
    def handle(self, msg: bytes) -> list[bytes]:
        if len(msg) < 6:
            return [self.mailbox_error(MBXERR_SIZE_TOO_SHORT)]
        length, _address, _channel, type_cnt = MBX_HEADER.unpack_from(msg)
        mtype = type_cnt & 0x0F
        cnt = (type_cnt >> 4) & 0x07
        if length < 2 or 6 + length > len(msg):
            return [self.mailbox_error(MBXERR_INVALID_SIZE)]
        if cnt and cnt == self.last_rx_counter:
            # a repeated message (same counter as the previous one): already handled
            self.stats["duplicates"] += 1
            return []
        self.last_rx_counter = cnt
        if mtype != MBX_COE:
            return [self.mailbox_error(MBXERR_UNSUPPORTED_PROTOCOL)]
        body = msg[6 : 6 + length]
        service = struct.unpack_from("<H", body)[0] >> 12
        if service == COE_SDO_REQ:
            if length < 10:
                return [self.mailbox_error(MBXERR_SIZE_TOO_SHORT)]
            return [self._sdo_request(body, length)]
        if service == COE_SDO_INFO:
            return self._sdo_info(body)
        return [self.mailbox_error(MBXERR_SERVICE_NOT_SUPPORTED)]

    # ------------------------------------------------------------------ SDO
    def _sdo_request(self, body: bytes, length: int) -> bytes:
        _coe, cmd, index, sub = SDO_HEAD.unpack_from(body)
        ccs = cmd >> 5
        try:
            if ccs == 1:
                return self._download_init(cmd, index, sub, body, length)
            if ccs == 0:
                return self._download_segment(cmd, body, length)
            if ccs == 2:
                return self._upload_init(cmd, index, sub)
            if ccs == 3:
                return self._upload_segment(cmd)
            if ccs == 4:  # abort from the master: drop any transfer, no answer expected
                self._upload = None
                self._download = None
                return b""
            raise SdoAbort(ABORT_COMMAND)
        except SdoAbort as exc:
            if ccs in (0, 3):
                t = self._upload or self._download or {"index": index, "sub": sub}
                index, sub = t["index"], t["sub"]
            return self._abort(index, sub, exc.code)

    def _upload_init(self, cmd: int, index: int, sub: int) -> bytes:
        self._upload = None
        self._download = None
        ca = bool(cmd & 0x10)
        data = self.od.read_complete(index, sub) if ca else self.od.read(index, sub)
        self.stats["sdo_upload"] += 1
        n = len(data)
        if 0 < n <= 4:
            return self._sdo(COE_SDO_RES, 0x43 | ((4 - n) << 2), index, sub, data.ljust(4, b"\0"))
        room = self.tx_size - 16
        if n <= room:
            return self._sdo(COE_SDO_RES, 0x41, index, sub, struct.pack("<I", n) + data)
        self._upload = {"index": index, "sub": sub, "data": data, "pos": room, "toggle": 0}
        return self._sdo(COE_SDO_RES, 0x41, index, sub, struct.pack("<I", n) + data[:room])

    def _upload_segment(self, cmd: int) -> bytes:
        t = self._upload
        if t is None:
            raise SdoAbort(ABORT_COMMAND, "no upload in progress")
        toggle = cmd & 0x10
        if toggle != t["toggle"]:
            raise SdoAbort(ABORT_TOGGLE)
        room = self.tx_size - 9
        chunk = t["data"][t["pos"] : t["pos"] + room]
        t["pos"] += len(chunk)
        last = t["pos"] >= len(t["data"])
        self.stats["segments"] += 1
        t["toggle"] ^= 0x10
        if last:
            self._upload = None
        res = toggle | (1 if last else 0)
        if len(chunk) < 7:
            res |= (7 - len(chunk)) << 1
            chunk = chunk.ljust(7, b"\0")
        payload = struct.pack("<HB", COE_SDO_RES << 12, res) + chunk
        return self._message(MBX_COE, payload)

    def _download_init(self, cmd: int, index: int, sub: int, body: bytes, length: int) -> bytes:
        self._upload = None
        self._download = None
        ca = bool(cmd & 0x10)
        if cmd & 0x02:  # expedited
            if cmd & 0x01:
                n = 4 - ((cmd >> 2) & 0x03)
            else:
                n = self.od.entry(index, sub if not ca else 0).size
                n = min(max(n, 1), 4)
            data = body[6 : 6 + n]
            self._store(index, sub, ca, data)
            return self._sdo(COE_SDO_RES, 0x60, index, sub, b"")
        present = length - 10
        if cmd & 0x01:
            total = struct.unpack_from("<I", body, 6)[0]
        else:
            total = present
        if total <= present:
            self._store(index, sub, ca, body[10 : 10 + total])
            return self._sdo(COE_SDO_RES, 0x60, index, sub, b"")
        # segmented download: check the target first, so that errors come early
        if not ca:
            e = self.od.entry(index, sub)
            self.od.check_writable(e)
        elif self.od.visible(index) is None:
            raise SdoAbort(ABORT_NO_OBJECT)
        self._download = {
            "index": index,
            "sub": sub,
            "ca": ca,
            "total": total,
            "buf": bytearray(body[10 : 10 + present]),
            "toggle": 0,
        }
        return self._sdo(COE_SDO_RES, 0x60, index, sub, b"")

    def _download_segment(self, cmd: int, body: bytes, length: int) -> bytes:
        t = self._download
        if t is None:
            raise SdoAbort(ABORT_COMMAND, "no download in progress")
        toggle = cmd & 0x10
        if toggle != t["toggle"]:
            raise SdoAbort(ABORT_TOGGLE)
        n = length - 3
        if n == 7:
            n -= (cmd >> 1) & 0x07
        t["buf"] += body[3 : 3 + n]
        t["toggle"] ^= 0x10
        self.stats["segments"] += 1
        if len(t["buf"]) > t["total"]:
            raise SdoAbort(ABORT_LENGTH, "more data than announced")
        if cmd & 0x01:  # last segment
            self._download = None
            if len(t["buf"]) != t["total"]:
                raise SdoAbort(ABORT_LENGTH, "less data than announced")
            self._store(t["index"], t["sub"], t["ca"], bytes(t["buf"]))
        payload = struct.pack("<HB", COE_SDO_RES << 12, 0x20 | toggle) + bytes(7)
        return self._message(MBX_COE, payload)

    def _store(self, index: int, sub: int, ca: bool, data: bytes) -> None:
        if ca:
            self.od.write_complete(index, sub, data)
        else:
            self.od.write(index, sub, data)
        self.stats["sdo_download"] += 1

    # ------------------------------------------------------------------ SDO information
    def _sdo_info(self, body: bytes) -> list[bytes]:
        """OD list (opcode 1), object description (3) and entry description (5); answers are
        fragmented over several mailbox messages when they do not fit in one."""
        self.stats["sdo_info"] += 1
        if len(body) < 6:
            return [self.mailbox_error(MBXERR_SIZE_TOO_SHORT)]
        opcode = body[2] & 0x7F
        try:
            if opcode == 0x01:
                list_type = struct.unpack_from("<H", body, 6)[0] if len(body) >= 8 else 1
                indices = sorted(self.od.objects)
                if list_type == 0:
                    n = len(indices)
                    data = struct.pack("<H6H", 0, n, n, 0, 0, 0, 0)
                else:
                    if list_type not in (1, 2, 3, 4, 5):
                        raise SdoAbort(ABORT_GENERAL)
                    data = struct.pack("<H", list_type) + b"".join(struct.pack("<H", i) for i in indices)
                return self._info_fragments(0x02, data)
            if opcode == 0x03:
                index = struct.unpack_from("<H", body, 6)[0]
                obj = self.od.visible(index)
                if obj is None:
                    raise SdoAbort(ABORT_NO_OBJECT)
                first = obj.entries.get(1, obj.entries[0]) if obj.code in (ARRAY, RECORD) else obj.entries[0]
                max_sub = obj.max_sub()
                data = struct.pack("<HHBB", index, first.dtype, max_sub, obj.code) + obj.name.encode("latin-1")
                return self._info_fragments(0x04, data)
            if opcode == 0x05:
                index, sub, _request = struct.unpack_from("<HBB", body, 6)
                e = self.od.entry(index, sub)
                access = _ACCESS_BITS.get(e.access, 0x0007)
                if e.mappable == "rx":
                    access |= 0x0040  # mappable in an RxPDO
                elif e.mappable == "tx":
                    access |= 0x0080  # mappable in a TxPDO
                data = struct.pack("<HBBHHH", index, sub, 0x00, e.dtype, e.bits, access)
                data += e.name.encode("latin-1")
                return self._info_fragments(0x06, data)
            raise SdoAbort(ABORT_COMMAND)
        except SdoAbort as exc:
            payload = struct.pack("<HBBH", COE_SDO_INFO << 12, 0x07, 0, 0) + struct.pack("<I", exc.code)
            return [self._message(MBX_COE, payload)]

    def _info_fragments(self, opcode: int, data: bytes) -> list[bytes]:
        room = self.tx_size - 6 - 6
        chunks = [data[i : i + room] for i in range(0, len(data), room)] or [b""]
        out = []
        for k, chunk in enumerate(chunks):
            left = len(chunks) - 1 - k
            op = opcode | (0x80 if left else 0)
            out.append(self._message(MBX_COE, struct.pack("<HBBH", COE_SDO_INFO << 12, op, 0, left) + chunk))
        return out
