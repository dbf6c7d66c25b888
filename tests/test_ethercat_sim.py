"""The simulated EtherCAT segment, through raw frames only (no root, no network).

Frames are built here with ``struct``; a fake clock makes every time-dependent behaviour (DC,
watchdog, drive dynamics) deterministic.
"""

from __future__ import annotations

import itertools
import json
import random
import struct
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.drivers.ethercat.sim import control
from aiohal.drivers.ethercat.sim.bench import soem_map
from aiohal.drivers.ethercat.sim.segment import Segment
from aiohal.drivers.ethercat.sim.sii import crc8
from aiohal.simulation.od import (
    ABORT_NO_OBJECT,
    BOOL,
    INT16,
    INT32,
    REAL32,
    UINT8,
    Entry,
    PdoCodec,
    SdoAbort,
)

NOP, APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(15)
INIT, PREOP, BOOT, SAFEOP, OP = 1, 2, 3, 4, 8
ACK = 0x10
VENDOR = 0x000A1A1A
ETH = bytes.fromhex("ffffffffffff" "010101010101") + b"\x88\xa4"


# ====================================================================== frame helpers


def frame(*datagrams: tuple) -> bytes:
    """(cmd, adp, ado, data) or (cmd, adp, ado, data, wkc) tuples -> Ethernet frame."""
    body = b""
    for i, dg in enumerate(datagrams):
        cmd, adp, ado, data = dg[:4]
        wkc = dg[4] if len(dg) > 4 else 0
        more = 0x8000 if i < len(datagrams) - 1 else 0
        body += struct.pack("<BBHHHH", cmd, 0x40 + i, adp, ado, len(data) | more, 0) + data
        body += struct.pack("<H", wkc)
    return ETH + struct.pack("<H", len(body) | 0x1000) + body


def parse(reply: bytes) -> list[tuple[int, int, int, bytes, int]]:
    """(cmd, adp, ado, data, wkc) per datagram."""
    out = []
    pos = 16
    while True:
        cmd, _idx, adp, ado, ln, _irq = struct.unpack_from("<BBHHHH", reply, pos)
        n = ln & 0x7FF
        out.append((cmd, adp, ado, reply[pos + 10:pos + 10 + n],
                    struct.unpack_from("<H", reply, pos + 10 + n)[0]))
        if not ln & 0x8000:
            return out
        pos += 12 + n


def u16(v: int) -> bytes:
    return struct.pack("<H", v)


class Clock:
    def __init__(self) -> None:
        self.t = 5_000_000_000_000

    def __call__(self) -> int:
        return self.t

    def advance(self, ms: float) -> None:
        self.t += int(ms * 1_000_000)


class SdoAbortSeen(Exception):
    def __init__(self, code: int, service: int) -> None:
        super().__init__(f"abort 0x{code:08X} (service {service})")
        self.code = code
        self.service = service


class Bus:
    """A test master on a Segment with a fake clock."""

    def __init__(self, spec: str, watchdog_ms: float = 100.0, seed: int = 0, drift_ppm: float = 0.0) -> None:
        self.clock = Clock()
        self.seg = Segment(spec, clock=self.clock, watchdog_ms=watchdog_ms, seed=seed, drift_ppm=drift_ppm)
        self.cnt = itertools.cycle(range(1, 8))
        self.offsets: dict[tuple[int, str], int] = {}
        self.iomap = 0
        self.emergencies: list[bytes] = []

    # ---- single datagrams
    def dg(self, cmd: int, adp: int, ado: int, data: bytes) -> tuple[bytes, int]:
        reply = self.seg.handle_frame(frame((cmd, adp, ado, data)))
        assert reply is not None
        _, _, _, out, wkc = parse(reply)[0]
        return out, wkc

    def brd(self, ado, n):
        return self.dg(BRD, 0, ado, bytes(n))

    def bwr(self, ado, data):
        return self.dg(BWR, 0, ado, data)[1]

    def aprd(self, pos, ado, n):
        return self.dg(APRD, (-pos) & 0xFFFF, ado, bytes(n))

    def apwr(self, pos, ado, data):
        return self.dg(APWR, (-pos) & 0xFFFF, ado, data)[1]

    def fprd(self, st_, ado, n):
        return self.dg(FPRD, st_, ado, bytes(n))

    def fpwr(self, st_, ado, data):
        return self.dg(FPWR, st_, ado, data)[1]

    def al(self, st_):
        data, _ = self.fprd(st_, 0x0130, 6)
        state, _res, code = struct.unpack("<HHH", data)
        return state, code

    def request(self, st_, state):
        return self.fpwr(st_, 0x0120, u16(state))

    # ---- EEPROM
    def eeprom(self, st_, word):
        assert self.fpwr(st_, 0x0502, struct.pack("<HI", 0x0100, word)) == 1
        status, _ = self.fprd(st_, 0x0502, 2)
        assert not struct.unpack("<H", status)[0] & 0x8000
        return self.fprd(st_, 0x0508, 8)[0]

    def sii(self, st_, nbytes=1024):
        out = b""
        for w in range(0, nbytes // 2, 4):
            out += self.eeprom(st_, w)
        return out

    # ---- mailbox
    def mbx_send(self, st_, payload, mtype=3, cnt=None):
        status, _ = self.fprd(st_, 0x0805, 1)
        assert not status[0] & 0x08, "receive mailbox full"
        cnt = next(self.cnt) if cnt is None else cnt
        msg = struct.pack("<HHBB", len(payload), 0, 0, mtype | (cnt << 4)) + payload
        return self.fpwr(st_, 0x1000, msg.ljust(128, b"\0"))

    def mbx_recv(self, st_, skip_emergencies=False):
        while True:
            status, wkc = self.fprd(st_, 0x080D, 1)
            if not status[0] & 0x08:
                return None
            data, wkc = self.fprd(st_, 0x1080, 128)
            assert wkc == 1
            length = struct.unpack_from("<H", data)[0]
            msg = data[:6 + length]
            if skip_emergencies and msg[5] & 0x0F == 3 and struct.unpack_from("<H", msg, 6)[0] >> 12 == 1:
                self.emergencies.append(msg)  # as SOEM does: handled, then the answer is read
                continue
            return msg

    def sdo_upload(self, st_, index, sub, ca=False):
        self.mbx_recv(st_, skip_emergencies=True)  # empty the send mailbox first, as SOEM does
        assert self.mbx_send(st_, struct.pack("<HBHB", 2 << 12, 0x50 if ca else 0x40, index, sub) + bytes(4)) == 1
        r = self.mbx_recv(st_, skip_emergencies=True)
        assert r is not None and r[5] & 0x0F == 3
        service = struct.unpack_from("<H", r, 6)[0] >> 12
        cmd = r[8]
        if cmd == 0x80:
            raise SdoAbortSeen(struct.unpack_from("<I", r, 12)[0], service)
        assert service == 3
        assert struct.unpack_from("<H", r, 9)[0] == index
        if cmd & 0x02:
            return r[12:12 + 4 - ((cmd >> 2) & 3)]
        size = struct.unpack_from("<I", r, 12)[0]
        data = r[16:]
        toggle = 0
        while len(data) < size:
            assert self.mbx_send(st_, struct.pack("<HB", 2 << 12, 0x60 | toggle) + bytes(7)) == 1
            s = self.mbx_recv(st_)
            length = struct.unpack_from("<H", s)[0]
            scmd = s[8]
            if scmd == 0x80:
                raise SdoAbortSeen(struct.unpack_from("<I", s, 12)[0], struct.unpack_from("<H", s, 6)[0] >> 12)
            assert scmd & 0xE0 == 0 and scmd & 0x10 == toggle
            n = length - 3
            if n == 7:
                n -= (scmd >> 1) & 7
            data += s[9:9 + n]
            toggle ^= 0x10
            if scmd & 1:
                break
        assert len(data) == size
        return data

    def sdo_download(self, st_, index, sub, value: bytes, ca=False, segment_toggle_error=False):
        if len(value) <= 4 and not ca:
            cmd = 0x23 | ((4 - len(value)) << 2)
            payload = struct.pack("<HBHB", 2 << 12, cmd, index, sub) + value.ljust(4, b"\0")
            assert self.mbx_send(st_, payload) == 1
            return self._sdo_answer(st_, 0x60)
        first = value[:128 - 16]
        payload = struct.pack("<HBHBI", 2 << 12, 0x31 if ca else 0x21, index, sub, len(value)) + first
        assert self.mbx_send(st_, payload) == 1
        self._sdo_answer(st_, 0x60)
        rest = value[len(first):]
        toggle = 0x10 if segment_toggle_error else 0
        while rest:
            chunk, rest = rest[:128 - 9], rest[128 - 9:]
            last = 0 if rest else 1
            if len(chunk) < 7:
                cmd = toggle | last | ((7 - len(chunk)) << 1)
                chunk = chunk.ljust(7, b"\0")
            else:
                cmd = toggle | last
            assert self.mbx_send(st_, struct.pack("<HB", 2 << 12, cmd) + chunk) == 1
            self._sdo_answer(st_, 0x20 | toggle, mask=0xF0)
            toggle ^= 0x10
        return None

    def _sdo_answer(self, st_, expect, mask=0xFF):
        r = self.mbx_recv(st_, skip_emergencies=True)
        assert r is not None
        service = struct.unpack_from("<H", r, 6)[0] >> 12
        if r[8] == 0x80:
            raise SdoAbortSeen(struct.unpack_from("<I", r, 12)[0], service)
        assert service == 3 and r[8] & mask == expect
        return r

    # ---- bring-up (the documented layouts)
    def init_all(self):
        assert self.bwr(0x0120, u16(INIT | ACK)) == len(self.seg.active)
        _, n = self.brd(0x0000, 2)
        for i in range(n):
            assert self.apwr(i, 0x0010, u16(0x1001 + i)) == 1
        return n

    def to_preop(self, st_, mailbox=True):
        if mailbox:
            sm = struct.pack("<HHBBBB", 0x1000, 128, 0x26, 0, 1, 0) + struct.pack("<HHBBBB", 0x1080, 128, 0x22, 0, 1, 0)
            assert self.fpwr(st_, 0x0800, sm) == 1
        self.request(st_, PREOP)
        return self.al(st_)

    def map_all(self):
        """SM2/SM3 and FMMUs for every slave: outputs first, then inputs (SOEM's legacy map),
        bit-packed for < 8 bits; then SAFEOP."""
        layout = []
        for i, esc in enumerate(self.seg.active):
            dev = esc.device
            st_ = 0x1001 + i
            o_bits = sum(b for idx in dev.rx_assign for _, _, b in dev.rx_pdos[idx])
            i_bits = sum(b for idx in dev.tx_assign for _, _, b in dev.tx_pdos[idx])
            layout.append((st_, dev, o_bits, i_bits))
            if o_bits:
                self.fpwr(st_, 0x0810, struct.pack("<HHBBBB", dev.out_addr, (o_bits + 7) // 8, 0x64, 0, 1, 0))
            if i_bits:
                self.fpwr(st_, 0x0818, struct.pack("<HHBBBB", dev.in_addr, (i_bits + 7) // 8, 0x20, 0, 1, 0))
        writes, self.offsets, _, self.iomap = soem_map(layout)
        for st_, register, data in writes:
            self.fpwr(st_, register, data)
        for st_, *_ in layout:
            self.request(st_, SAFEOP)
        return layout

    def up(self, to=OP):
        n = self.init_all()
        for i in range(n):
            self.to_preop(0x1001 + i, mailbox=self.seg.active[i].device.mailbox is not None)
        if to == PREOP:
            return
        self.map_all()
        if to == SAFEOP:
            return
        self.lrw(bytes(self.iomap))
        assert self.bwr(0x0120, u16(OP)) == n
        assert self.brd(0x0130, 2)[0] == u16(OP)

    def lrw(self, data, cmd=LRW, addr=0, extra=()):
        reply = self.seg.handle_frame(frame((cmd, addr & 0xFFFF, addr >> 16, data), *extra))
        assert reply is not None
        return parse(reply)

    def out_at(self, st_):
        return self.offsets[(st_, "out")] // 8

    def in_at(self, st_):
        return self.offsets[(st_, "in")] // 8


# ====================================================================== registers and addressing


def test_count_station_addresses_and_addressing_modes():
    bus = Bus("drive,imu,dio")
    seg = bus.seg
    _, wkc = bus.brd(0x0000, 2)
    assert wkc == 3
    reply = parse(seg.handle_frame(frame((BRD, 0, 0x0000, b"\0\0"))))[0]
    assert reply[1] == 3  # ADP counts up once per slave
    for i in range(3):
        data, wkc = bus.aprd(i, 0x0000, 1)
        assert wkc == 1 and data == b"\x11"
        assert bus.apwr(i, 0x0010, u16(0x1001 + i)) == 1
    assert bus.aprd(3, 0x0000, 1)[1] == 0  # nobody at position 3
    reply = parse(seg.handle_frame(frame((APRD, 0xFFFF, 0x0010, b"\0\0"))))[0]
    assert reply[1] == 2 and reply[3] == u16(0x1002) and reply[4] == 1
    for i in range(3):
        data, wkc = bus.fprd(0x1001 + i, 0x0010, 2)
        assert (data, wkc) == (u16(0x1001 + i), 1)
    assert bus.fprd(0x2000, 0x0010, 2)[1] == 0
    # FPRW: the frame gets the old value, the register the new one; +1 read +2 write
    reply = parse(seg.handle_frame(frame((FPRW, 0x1002, 0x0200, u16(0x1234)))))[0]
    assert reply[3] == u16(0) and reply[4] == 3
    assert bus.fprd(0x1002, 0x0200, 2)[0] == u16(0x1234)
    reply = parse(seg.handle_frame(frame((APRW, 0xFFFF, 0x0200, u16(0x5678)))))[0]
    assert reply[3] == u16(0x1234) and reply[4] == 3
    # BWR reaches everybody, BRD ORs
    assert bus.bwr(0x0204, u16(0x0001)) == 3
    bus.apwr(2, 0x0204, u16(0x0100))
    data, wkc = bus.brd(0x0204, 2)
    assert data == u16(0x0101) and wkc == 3
    # BRW: +3 per slave
    reply = parse(seg.handle_frame(frame((BRW, 0, 0x0206, u16(0x0003)))))[0]
    assert reply[4] == 9
    # NOP leaves the working counter alone
    reply = parse(seg.handle_frame(frame((NOP, 0, 0x0000, b"\0\0", 5))))[0]
    assert reply[4] == 5


def test_identification_and_read_only_registers():
    bus = Bus("drive")
    bus.init_all()
    data, _ = bus.fprd(0x1001, 0x0000, 10)
    esc_type, _rev, _build, n_fmmu, n_sm, _ram, ports, features = struct.unpack("<BBHBBBBH", data)
    assert (n_fmmu, n_sm, ports) == (8, 8, 0x0F)
    assert features & 0x0004 and features & 0x0008  # DC, 64-bit DC
    assert bus.fpwr(0x1001, 0x0000, b"\x99") == 1  # the write "succeeds"...
    assert bus.fprd(0x1001, 0x0000, 1)[0] == bytes([esc_type])  # ...but changes nothing
    assert bus.fpwr(0x1001, 0x0130, u16(0x0008)) == 1
    assert bus.al(0x1001) == (INIT, 0)
    assert bus.fprd(0x1001, 0x0140, 1)[0] == b"\x08"  # PDI control from SII word 0
    dl = struct.unpack("<H", bus.fprd(0x1001, 0x0110, 2)[0])[0]
    assert dl & 0x0300 == 0x0200  # port 0 open with communication
    assert dl & 0x0C00 == 0x0400  # port 1 closed: end of the line
    # error counters are cleared by a write
    bus.seg.slaves[0].mem[0x0300] = 5
    bus.fpwr(0x1001, 0x0300, b"\x77")
    assert bus.fprd(0x1001, 0x0300, 1)[0] == b"\0"


def test_topology_bits_for_a_line():
    bus = Bus("drive,drive,dio")
    bus.init_all()
    dls = [struct.unpack("<H", bus.fprd(0x1001 + i, 0x0110, 2)[0])[0] for i in range(3)]
    assert dls == [0x5A31, 0x5A31, 0x5611]


# ====================================================================== SII / EEPROM


def test_eeprom_header_words_and_checksum():
    bus = Bus("drive")
    bus.init_all()
    status = struct.unpack("<H", bus.fprd(0x1001, 0x0502, 2)[0])[0]
    assert status & 0x0040  # 8-byte reads
    head = b"".join(bus.eeprom(0x1001, w) for w in range(0, 0x40, 4))
    assert head[14] == crc8(head[:14])
    vendor, product, revision, serial = struct.unpack_from("<IIII", head, 0x10)
    assert (vendor, product, revision, serial) == (VENDOR, 0x402, 1, 1)
    rx_off, rx_size, tx_off, tx_size, proto = struct.unpack_from("<HHHHH", head, 0x30)
    assert (rx_off, rx_size, tx_off, tx_size, proto) == (0x1000, 128, 0x1080, 128, 0x0004)
    # a 4-byte read window (what SOEM's readeeprom2 uses) gets the first 4 of the 8 bytes
    bus.fpwr(0x1001, 0x0502, struct.pack("<HI", 0x0100, 0x08))
    assert bus.fprd(0x1001, 0x0508, 4)[0] == struct.pack("<I", VENDOR)
    # beyond the image: erased EEPROM
    assert bus.eeprom(0x1001, 0x7FF0) == b"\xff" * 8


def _categories(image: bytes) -> dict[int, bytes]:
    cats = {}
    pos = 0x80
    while True:
        kind, words = struct.unpack_from("<HH", image, pos)
        if kind == 0xFFFF:
            return cats
        cats[kind] = image[pos + 4:pos + 4 + 2 * words]
        pos += 4 + 2 * words


def _strings(data: bytes) -> list[str]:
    out, pos = [], 1
    for _ in range(data[0]):
        ln = data[pos]
        out.append(data[pos + 1:pos + 1 + ln].decode())
        pos += 1 + ln
    return out


def _pdos(data: bytes) -> list[tuple[int, int, list[tuple[int, int, int]]]]:
    out, pos = [], 0
    while pos < len(data):
        index, n, sm, _sync, _name, _flags = struct.unpack_from("<HBBBBH", data, pos)
        pos += 8
        entries = []
        for _ in range(n):
            ei, es, _en, _dt, bits, _f = struct.unpack_from("<HBBBBH", data, pos)
            entries.append((ei, es, bits))
            pos += 8
        out.append((index, sm, entries))
    return out


def test_eeprom_categories_describe_the_documented_devices():
    bus = Bus("drive,dio")
    bus.init_all()
    image = bus.sii(0x1001)
    cats = _categories(image)
    assert set(cats) >= {10, 30, 40, 41, 50, 51}
    assert _strings(cats[10])[0] == "AIOHAL-Drive"  # string 1 = the slave name in SOEM
    general = cats[30]
    assert general[5] & 0x01 and general[5] & 0x20  # SDO and complete access
    assert general[11] & 0x02 == 0  # LRW allowed
    assert cats[40][:2] == bytes([1, 2])  # FMMU0 outputs, FMMU1 inputs
    sms = [struct.unpack_from("<HHBBBB", cats[41], 8 * i) for i in range(4)]
    assert sms[0][:3] == (0x1000, 128, 0x26) and sms[1][:3] == (0x1080, 128, 0x22)
    assert sms[2][:3] == (0x1100, 13, 0x64) and sms[3][:3] == (0x1180, 15, 0x20)
    assert [k for k, _s, _e in _pdos(cats[51])] == [0x1600]
    assert _pdos(cats[51])[0][2] == [(0x6040, 0, 16), (0x607A, 0, 32), (0x60FF, 0, 32), (0x6071, 0, 16), (0x6060, 0, 8)]
    assert _pdos(cats[50])[0][2] == [(0x6041, 0, 16), (0x6064, 0, 32), (0x606C, 0, 32), (0x6077, 0, 16),
                                     (0x6061, 0, 8), (0x603F, 0, 16)]
    dio = _categories(bus.sii(0x1002))
    assert _strings(dio[10])[0] == "AIOHAL-DIO8"
    tx = _pdos(dio[50])
    assert tx == [(0x1A00, 3, [(0x6000, i, 1) for i in range(1, 9)])]
    assert _pdos(dio[51]) == [(0x1600, 2, [(0x7000, i, 1) for i in range(1, 9)])]
    head = bus.eeprom(0x1002, 0x18)
    assert head[:4] == b"\0\0\0\0"  # no mailbox


def test_eeprom_write_needs_write_enable():
    bus = Bus("imu")
    bus.init_all()
    bus.fpwr(0x1001, 0x0508, u16(0xBEEF))
    bus.fpwr(0x1001, 0x0502, struct.pack("<HI", 0x0200, 0x0050))
    status = struct.unpack("<H", bus.fprd(0x1001, 0x0502, 2)[0])[0]
    assert status & 0x4000  # write enable error
    bus.fpwr(0x1001, 0x0502, u16(0x0000))  # NOP clears the error
    assert not struct.unpack("<H", bus.fprd(0x1001, 0x0502, 2)[0])[0] & 0x7800
    bus.fpwr(0x1001, 0x0508, u16(0xBEEF))
    bus.fpwr(0x1001, 0x0502, struct.pack("<HI", 0x0201, 0x0050))
    assert bus.eeprom(0x1001, 0x0050)[:2] == u16(0xBEEF)


def test_an_armed_eeprom_read_leaves_the_eeprom_busy_for_its_time_and_is_never_done():
    """Fault injection ``eeprom_busy``: what SOEM meets when an EEPROM read does not finish
    within its wait (its split read then returns whatever the data register held)."""
    from aiohal.drivers.ethercat.sim.control import apply

    bus = Bus("drive,drive")
    bus.init_all()
    assert apply(bus.seg, {"cmd": "eeprom_busy", "slave": 1, "ms": 30}) == {"ok": True}

    def status(st_):
        return struct.unpack("<H", bus.fprd(st_, 0x0502, 2)[0])[0]

    before = bus.fprd(0x1002, 0x0508, 8)[0]
    bus.fpwr(0x1002, 0x0502, struct.pack("<HI", 0x0100, 0x08))  # the vendor id's words
    assert status(0x1002) & 0x8000
    assert bus.fprd(0x1002, 0x0508, 8)[0] == before  # not read
    bus.fpwr(0x1002, 0x0502, struct.pack("<HI", 0x0100, 0x0A))  # a command while busy is not taken
    bus.clock.advance(29)
    assert status(0x1002) & 0x8000
    assert bus.eeprom(0x1001, 0x08)[:4] == struct.pack("<I", VENDOR)  # the other slave is not affected
    bus.clock.advance(1)
    assert not status(0x1002) & 0x8000
    assert bus.fprd(0x1002, 0x0508, 8)[0] == before
    assert bus.eeprom(0x1002, 0x08)[:4] == struct.pack("<I", VENDOR)  # once: the next read is done
    assert apply(bus.seg, {"cmd": "eeprom_busy", "slave": 1, "ms": 0})["ok"] is False


# ====================================================================== AL state machine


def test_al_transitions_errors_and_acknowledge():
    bus = Bus("drive")
    bus.init_all()
    st_ = 0x1001
    bus.request(st_, SAFEOP)
    assert bus.al(st_) == (INIT | 0x10, 0x0011)  # invalid transition
    bus.request(st_, PREOP)
    assert bus.al(st_) == (INIT | 0x10, 0x0011)  # ignored until acknowledged
    bus.request(st_, INIT | ACK)
    assert bus.al(st_) == (INIT, 0)
    bus.request(st_, PREOP)  # no mailbox SyncManagers configured
    assert bus.al(st_) == (INIT | 0x10, 0x0016)
    bus.request(st_, INIT | ACK)
    assert bus.to_preop(st_) == (PREOP, 0)
    bus.request(st_, OP)
    assert bus.al(st_) == (PREOP | 0x10, 0x0011)
    bus.request(st_, 0x0006 | ACK)
    assert bus.al(st_) == (PREOP | 0x10, 0x0012)  # unknown state
    bus.request(st_, PREOP | ACK)
    assert bus.al(st_) == (PREOP, 0)
    bus.request(st_, SAFEOP)  # SM2/SM3 not configured
    assert bus.al(st_) == (PREOP | 0x10, 0x001D)
    bus.request(st_, PREOP | ACK)
    bus.fpwr(st_, 0x0810, struct.pack("<HHBBBB", 0x1100, 12, 0x64, 0, 1, 0))  # one byte short
    bus.fpwr(st_, 0x0818, struct.pack("<HHBBBB", 0x1180, 15, 0x20, 0, 1, 0))
    bus.request(st_, SAFEOP)
    assert bus.al(st_) == (PREOP | 0x10, 0x001D)
    bus.request(st_, PREOP | ACK)
    bus.fpwr(st_, 0x0810, struct.pack("<HHBBBB", 0x1100, 13, 0x64, 0, 1, 0))
    bus.fpwr(st_, 0x0818, struct.pack("<HHBBBB", 0x1180, 16, 0x20, 0, 1, 0))
    bus.request(st_, SAFEOP)
    assert bus.al(st_) == (PREOP | 0x10, 0x001E)
    bus.request(st_, PREOP | ACK)
    bus.fpwr(st_, 0x0818, struct.pack("<HHBBBB", 0x1180, 15, 0x20, 0, 1, 0))
    bus.request(st_, SAFEOP)
    assert bus.al(st_) == (SAFEOP, 0)
    # OP waits for valid outputs (SM2 written), then goes by itself
    bus.request(st_, OP)
    assert bus.al(st_) == (SAFEOP, 0)
    bus.fpwr(st_, 0x1100, bytes(13))
    assert bus.al(st_) == (OP, 0)
    for target in (SAFEOP, PREOP, INIT):
        bus.request(st_, target)
        assert bus.al(st_) == (target, 0)
    bus.request(st_, BOOT)
    assert bus.al(st_) == (BOOT, 0)
    bus.request(st_, PREOP)
    assert bus.al(st_) == (BOOT | 0x10, 0x0011)
    bus.request(st_, INIT | ACK)
    assert bus.al(st_) == (INIT, 0)


def test_brd_of_al_status_ors_states_and_error_flags():
    bus = Bus("drive,dio")
    bus.up(to=PREOP)
    bus.request(0x1002, SAFEOP | ACK)  # the DIO has no SM2/SM3 yet
    data, wkc = bus.brd(0x0130, 2)
    assert wkc == 2 and struct.unpack("<H", data)[0] == (PREOP | 0x10)
    # SOEM then asks every slave in one frame with several datagrams
    reply = bus.seg.handle_frame(frame((FPRD, 0x1001, 0x0130, bytes(6)), (FPRD, 0x1002, 0x0130, bytes(6))))
    dgs = parse(reply)
    assert [struct.unpack("<HHH", d[3])[0::2] for d in dgs] == [(PREOP, 0), (PREOP | 0x10, 0x001D)]
    assert [d[4] for d in dgs] == [1, 1]


# ====================================================================== mailbox and CoE


@pytest.fixture()
def preop_drive():
    bus = Bus("drive,imu")
    bus.up(to=PREOP)
    return bus


def test_sdo_expedited_normal_and_segmented_upload(preop_drive):
    bus = preop_drive
    assert bus.sdo_upload(0x1001, 0x1000, 0) == struct.pack("<I", 0x00020192)
    assert bus.sdo_upload(0x1001, 0x6072, 0) == u16(1000)
    assert bus.sdo_upload(0x1001, 0x1008, 0) == b"AIOHAL-Drive"
    assert bus.sdo_upload(0x1002, 0x1008, 0) == b"AIOHAL-IMU"
    assert struct.unpack("<I", bus.sdo_upload(0x1001, 0x1018, 1))[0] == VENDOR
    info = bus.sdo_upload(0x1001, 0x2000, 0)  # longer than one mailbox: segmented
    assert len(info) > 128 and info.startswith(b"aiohal simulated")
    assert bus.sdo_upload(0x1001, 0x2001, 0) == bytes(range(256))


def test_sdo_download_expedited_normal_segmented(preop_drive):
    bus = preop_drive
    bus.sdo_download(0x1001, 0x6072, 0, u16(800))
    assert bus.sdo_upload(0x1001, 0x6072, 0) == u16(800)
    bus.sdo_download(0x1001, 0x6060, 0, b"\x09")
    assert bus.sdo_upload(0x1001, 0x6060, 0) == b"\x09"
    bus.sdo_download(0x1001, 0x6085, 0, struct.pack("<I", 123456))  # 4 bytes, expedited
    assert bus.sdo_upload(0x1001, 0x6085, 0) == struct.pack("<I", 123456)
    payload = bytes((7 * i) & 0xFF for i in range(256))
    bus.sdo_download(0x1001, 0x2001, 0, payload)  # > one mailbox: segmented download
    assert bus.sdo_upload(0x1001, 0x2001, 0) == payload
    bus.sdo_download(0x1001, 0x2001, 0, bytes(40))  # normal, one mailbox
    assert bus.sdo_upload(0x1001, 0x2001, 0) == bytes(40)
    with pytest.raises(SdoAbortSeen) as exc:
        bus.sdo_download(0x1001, 0x2001, 0, bytes(200), segment_toggle_error=True)
    assert exc.value.code == 0x05030000


def test_sdo_aborts_use_service_2(preop_drive):
    bus = preop_drive
    cases = [
        (lambda: bus.sdo_upload(0x1001, 0x5555, 0), 0x06020000),
        (lambda: bus.sdo_upload(0x1001, 0x1018, 9), 0x06090011),
        (lambda: bus.sdo_download(0x1001, 0x1000, 0, struct.pack("<I", 1)), 0x06010002),
        (lambda: bus.sdo_download(0x1001, 0x6072, 0, struct.pack("<I", 1)), 0x06070010),
        (lambda: bus.sdo_download(0x1001, 0x6060, 0, b"\x05"), 0x06090030),  # mode not supported
    ]
    for call, code in cases:
        with pytest.raises(SdoAbortSeen) as exc:
            call()
        assert exc.value.code == code
        assert exc.value.service == 2  # what SOEM needs to report an SdoError


def test_complete_access_read_and_remap(preop_drive):
    bus = preop_drive
    # sub 0 is sent as 16 bits, as SOEM's PDO assign/mapping structures expect
    assert bus.sdo_upload(0x1001, 0x1C00, 0, ca=True) == bytes([4, 0, 1, 2, 3, 4])
    assert bus.sdo_upload(0x1001, 0x1C12, 0, ca=True) == bytes([1, 0]) + u16(0x1600)
    mapping = bus.sdo_upload(0x1001, 0x1600, 0, ca=True)
    assert mapping[:2] == bytes([5, 0])
    assert struct.unpack_from("<5I", mapping, 2) == (0x60400010, 0x607A0020, 0x60FF0020, 0x60710010, 0x60600008)
    ident = bus.sdo_upload(0x1001, 0x1018, 1, ca=True)  # from sub 1: no sub 0
    assert struct.unpack("<4I", ident) == (VENDOR, 0x402, 1, 1)
    assert bus.sdo_upload(0x1002, 0x1C12, 0, ca=True) == bytes([0, 0])  # the IMU has no outputs
    # remap through complete access: assign the compact RxPDO 0x1601 (6 bytes)
    bus.sdo_download(0x1001, 0x1C12, 0, bytes([1, 0]) + u16(0x1601), ca=True)
    assert bus.sdo_upload(0x1001, 0x1C12, 1) == u16(0x1601)
    # the classic way: sub 0 = 0, entries, sub 0 = n
    bus.sdo_download(0x1001, 0x1A01, 0, b"\0")
    bus.sdo_download(0x1001, 0x1A01, 1, struct.pack("<I", 0x60410010))
    bus.sdo_download(0x1001, 0x1A01, 2, struct.pack("<I", 0x60640020))
    bus.sdo_download(0x1001, 0x1A01, 3, struct.pack("<I", 0x60F40020))
    bus.sdo_download(0x1001, 0x1A01, 0, b"\x03")
    bus.sdo_download(0x1001, 0x1C13, 1, u16(0x1A01))
    # a mapping naming a missing or wrongly directed object is refused
    bus.sdo_download(0x1001, 0x1601, 0, b"\0")
    bus.sdo_download(0x1001, 0x1601, 3, struct.pack("<I", 0x60410010))  # statusword in an RxPDO
    with pytest.raises(SdoAbortSeen) as exc:
        bus.sdo_download(0x1001, 0x1601, 0, b"\x03")
    assert exc.value.code == 0x06040041
    bus.sdo_download(0x1001, 0x1601, 0, b"\x02")
    with pytest.raises(SdoAbortSeen):
        bus.sdo_download(0x1001, 0x1C12, 1, u16(0x1234))
    # SAFEOP needs SM2 = 6 bytes and SM3 = 10 bytes now
    st_ = 0x1001
    bus.fpwr(st_, 0x0810, struct.pack("<HHBBBB", 0x1100, 13, 0x64, 0, 1, 0))
    bus.fpwr(st_, 0x0818, struct.pack("<HHBBBB", 0x1180, 10, 0x20, 0, 1, 0))
    bus.request(st_, SAFEOP)
    assert bus.al(st_) == (PREOP | 0x10, 0x001D)
    bus.request(st_, PREOP | ACK)
    bus.fpwr(st_, 0x0810, struct.pack("<HHBBBB", 0x1100, 6, 0x64, 0, 1, 0))
    bus.request(st_, SAFEOP)
    assert bus.al(st_) == (SAFEOP, 0)
    # mapping objects are writable in PREOP only
    with pytest.raises(SdoAbortSeen) as exc:
        bus.sdo_download(0x1001, 0x1C12, 0, b"\x01")
    assert exc.value.code == 0x08000022
    # CA writes are checked like single writes
    with pytest.raises(SdoAbortSeen) as exc:
        bus.sdo_download(0x1001, 0x1018, 0, bytes([4, 0]) + bytes(16), ca=True)
    assert exc.value.code == 0x06010002


def test_mailbox_counter_repeat_and_empty_reads(preop_drive):
    bus = preop_drive
    st_ = 0x1001
    assert bus.fprd(st_, 0x1080, 128)[1] == 0  # empty send mailbox: no working counter
    req = struct.pack("<HBHB", 2 << 12, 0x40, 0x1000, 0) + bytes(4)
    bus.mbx_send(st_, req, cnt=3)
    assert bus.mbx_recv(st_) is not None
    bus.mbx_send(st_, req, cnt=3)  # same counter again: a retry, already answered
    assert bus.mbx_recv(st_) is None
    bus.mbx_send(st_, req, cnt=4)
    first = bus.mbx_recv(st_)
    # repeat request: toggle SM1 activate bit 1, the slave puts the last answer back
    act = bus.fprd(st_, 0x080E, 1)[0][0]
    bus.fpwr(st_, 0x080E, bytes([act ^ 0x02]))
    assert bus.fprd(st_, 0x080F, 1)[0][0] & 0x02 == (act ^ 0x02) & 0x02
    assert bus.mbx_recv(st_) == first
    # unsupported mailbox type: mailbox error (type 0), detail 0x0002
    bus.mbx_send(st_, b"\0" * 10, mtype=4)
    err = bus.mbx_recv(st_)
    assert err[5] & 0x0F == 0 and struct.unpack_from("<HH", err, 6) == (1, 2)


def test_mailbox_written_in_init_is_answered_after_preop():
    bus = Bus("drive")
    bus.init_all()
    st_ = 0x1001
    sm = struct.pack("<HHBBBB", 0x1000, 128, 0x26, 0, 1, 0) + struct.pack("<HHBBBB", 0x1080, 128, 0x22, 0, 1, 0)
    bus.fpwr(st_, 0x0800, sm)
    bus.mbx_send(st_, struct.pack("<HBHB", 2 << 12, 0x40, 0x1000, 0) + bytes(4))
    assert bus.fprd(st_, 0x0805, 1)[0][0] & 0x08  # full until the application runs
    assert bus.fpwr(st_, 0x1000, bytes(128)) == 0  # a full mailbox refuses writes
    bus.request(st_, PREOP)
    assert bus.al(st_) == (PREOP, 0)
    reply = bus.mbx_recv(st_)
    assert reply is not None and reply[12:16] == struct.pack("<I", 0x00020192)


def test_sdo_information(preop_drive):
    bus = preop_drive
    st_ = 0x1001
    bus.mbx_send(st_, struct.pack("<HBBHH", 8 << 12, 0x01, 0, 0, 1))
    indices = []
    while True:
        r = bus.mbx_recv(st_)
        op, frags = r[8], struct.unpack_from("<H", r, 10)[0]
        assert op & 0x7F == 0x02
        length = struct.unpack_from("<H", r)[0]
        body = r[12:6 + length]
        if not indices:
            body = body[2:]
        indices += [struct.unpack_from("<H", body, i)[0] for i in range(0, len(body), 2)]
        if not frags:
            break
    assert {0x1000, 0x1018, 0x1C12, 0x6040, 0x6041, 0x607A} <= set(indices)
    bus.mbx_send(st_, struct.pack("<HBBHH", 8 << 12, 0x03, 0, 0, 0x6041))
    r = bus.mbx_recv(st_)
    index, dtype, max_sub, code = struct.unpack_from("<HHBB", r, 12)
    length = struct.unpack_from("<H", r)[0]
    assert (index, dtype, max_sub, code) == (0x6041, 0x0006, 0, 7)
    assert r[18:6 + length] == b"Statusword"
    bus.mbx_send(st_, struct.pack("<HBBHHBB", 8 << 12, 0x05, 0, 0, 0x607A, 0, 7))
    r = bus.mbx_recv(st_)
    index, sub, _vi, dtype, bits, access = struct.unpack_from("<HBBHHH", r, 12)
    assert (index, sub, dtype, bits) == (0x607A, 0, 0x0004, 32) and access & 0x0040
    bus.mbx_send(st_, struct.pack("<HBBHH", 8 << 12, 0x03, 0, 0, 0x5555))
    r = bus.mbx_recv(st_)
    assert r[8] & 0x7F == 0x07 and struct.unpack_from("<I", r, 12)[0] == 0x06020000


# ====================================================================== process data


def test_lrw_byte_granular_wkc_and_one_cycle_lag():
    bus = Bus("drive,imu,ft,dio")
    bus.up()
    assert bus.iomap == 13 + 2 + 1 + 15 + 42 + 26 + 1
    out = bytearray(bus.iomap)
    struct.pack_into("<B", out, bus.out_at(0x1004), 0xA5)
    dgs = bus.lrw(bytes(out))
    assert dgs[0][4] == 3 + 1 + 3 + 3  # drive, imu (inputs only), ft, dio
    # the DIO reads back last cycle's outputs: not yet
    assert dgs[0][3][bus.in_at(0x1004)] == 0
    dgs = bus.lrw(bytes(out))
    data = dgs[0][3]
    assert data[bus.in_at(0x1004)] == 0xA5
    imu = struct.unpack_from("<4f3f3fH", data, bus.in_at(0x1002))
    assert imu[:4] == (1.0, 0.0, 0.0, 0.0) and abs(imu[9] - 9.80665) < 1e-5 and imu[10] == 1
    # LRD and LWR: +1 per slave hit
    assert bus.lrw(bytes(out), cmd=LRD)[0][4] == 4
    assert bus.lrw(bytes(out), cmd=LWR)[0][4] == 3
    # pattern XOR on the DIO through the control channel
    assert control.apply(bus.seg, {"cmd": "device", "slave": 3, "pattern": "0x0F"})["ok"]
    bus.lrw(bytes(out))
    assert bus.lrw(bytes(out))[0][3][bus.in_at(0x1004)] == 0xA5 ^ 0x0F


def test_lrw_overlapping_map_reads_after_writes():
    """config_overlap_map: a slave's inputs replace its outputs at the same logical bytes."""
    bus = Bus("dio,dio")
    bus.init_all()
    for i in range(2):
        st_ = 0x1001 + i
        bus.to_preop(st_, mailbox=False)
        bus.fpwr(st_, 0x0810, struct.pack("<HHBBBB", 0x1000, 1, 0x64, 0, 1, 0))
        bus.fpwr(st_, 0x0818, struct.pack("<HHBBBB", 0x1100, 1, 0x20, 0, 1, 0))
        bus.fpwr(st_, 0x0600, struct.pack("<IHBBHBBB", i, 1, 0, 7, 0x1000, 0, 2, 1) + bytes(3))
        bus.fpwr(st_, 0x0610, struct.pack("<IHBBHBBB", i, 1, 0, 7, 0x1100, 0, 1, 1) + bytes(3))
        bus.request(st_, SAFEOP)
        bus.request(st_, OP)
    dgs = bus.lrw(b"\x11\x22")
    assert dgs[0][4] == 6
    assert bus.brd(0x0130, 2)[0] == u16(OP)
    assert bus.lrw(b"\x33\x44")[0][3] == b"\x11\x22"


def test_lrw_bit_granular_fmmus_pack_two_terminals_in_one_byte():
    bus = Bus("dio4,dio4,drive")
    bus.up()
    assert bus.offsets[(0x1001, "out")] == 0 and bus.offsets[(0x1002, "out")] == 4
    fm = bus.fprd(0x1002, 0x0600, 16)[0]
    lstart, llen, lsb, leb = struct.unpack_from("<IHBB", fm)
    assert (lstart, llen, lsb, leb) == (0, 1, 4, 7)
    out = bytearray(bus.iomap)
    out[0] = 0x9A  # terminal 1: 0xA, terminal 2: 0x9
    bus.lrw(bytes(out))
    assert bus.seg.slaves[0].mem[0x1000] == 0x0A and bus.seg.slaves[1].mem[0x1000] == 0x09
    data = bus.lrw(bytes(out))[0][3]
    inb = bus.in_at(0x1001)
    assert bus.offsets[(0x1002, "in")] == bus.offsets[(0x1001, "in")] + 4
    assert data[inb] == 0x9A  # both nibbles read back, in place
    # bits outside a bit FMMU stay as the master sent them
    before = bytearray(out)
    before[inb] = 0x00
    reply = bus.lrw(bytes(before), cmd=LRD)[0]
    assert reply[3][inb] == 0x9A and reply[4] == 3
    # LWR of only the first nibble's byte range still hits both terminals
    assert bus.lrw(bytes(out[:1]), cmd=LWR)[0][4] == 2


def test_segmented_lrw_and_output_buffer_completion():
    bus = Bus("drive,imu")
    bus.up()
    assert bus.iomap == 13 + 15 + 42
    esc = bus.seg.slaves[0]
    # two logical datagrams in one frame, the split inside the IMU's inputs
    reply = bus.seg.handle_frame(frame((LRW, 0, 0, bytes(35)), (LRW, 35, 0, bytes(35))))
    assert [d[4] for d in parse(reply)] == [3 + 1, 1]
    # split inside the drive's outputs: the SM2 buffer completes with its last byte only
    last = esc.last_output_ns
    bus.clock.advance(1)
    reply = bus.seg.handle_frame(frame((LRW, 0, 0, bytes(6))))
    assert parse(reply)[0][4] == 2 and esc.last_output_ns == last
    reply = bus.seg.handle_frame(frame((LRW, 6, 0, bytes(64))))
    assert parse(reply)[0][4] == 2 + 1 + 1 and esc.last_output_ns == bus.clock.t


# ====================================================================== watchdog


def test_sm_watchdog_trips_to_safeop_and_disables_the_drive():
    bus = Bus("drive,imu")
    bus.up()
    enable_drive(bus, 0x1001)
    assert bus.seg.slaves[0].device.model.state == "operation_enabled"
    bus.clock.advance(60)
    bus.seg.poll()
    assert bus.al(0x1001) == (OP, 0)
    bus.clock.advance(60)
    bus.seg.poll()
    assert bus.al(0x1001) == (SAFEOP | 0x10, 0x001B)
    assert bus.al(0x1002) == (OP, 0)  # no outputs, no SM watchdog
    assert bus.seg.slaves[0].device.model.state == "switch_on_disabled"
    assert bus.fprd(0x1001, 0x0440, 2)[0] == u16(0)
    assert bus.fprd(0x1001, 0x0442, 1)[0] == b"\x01"
    assert bus.seg.counters["watchdog_trips"] == 1
    # outputs in SAFEOP are not applied; recovery: acknowledge, outputs, OP
    bus.request(0x1001, SAFEOP | ACK)
    assert bus.al(0x1001) == (SAFEOP, 0)
    out = bytearray(bus.iomap)
    struct.pack_into("<HiihB", out, bus.out_at(0x1001), 0x0F, 0, 0, 0, 8)
    bus.lrw(bytes(out))
    bus.request(0x1001, OP)
    assert bus.al(0x1001) == (OP, 0)
    # the watchdog time is a register (pysoem's set_watchdog): 0 switches it off
    bus.fpwr(0x1001, 0x0420, u16(0))
    bus.clock.advance(500)
    bus.seg.poll()
    assert bus.al(0x1001) == (OP, 0)


def test_watchdog_also_trips_during_a_frame_gap():
    bus = Bus("drive", watchdog_ms=20)
    bus.up()
    bus.clock.advance(30)
    bus.brd(0x0130, 2)  # any frame polls the watchdog
    assert bus.al(0x1001) == (SAFEOP | 0x10, 0x001B)


def test_a_stall_of_the_simulator_itself_is_not_held_against_the_watchdog():
    """The runner reports the time it was not run (the host stalled it and the master with
    it): hardware slaves would not have stalled, so their watchdogs do not count it."""
    bus = Bus("drive", watchdog_ms=100)
    bus.up()
    bus.clock.advance(500)  # the host stalled both sides for 500 ms
    bus.seg.discount_stall(500_000_000)
    bus.seg.poll()
    assert bus.al(0x1001) == (OP, 0) and bus.seg.counters["stalls_discounted"] == 1
    bus.clock.advance(120)  # then the master really stops sending
    bus.seg.poll()
    assert bus.al(0x1001) == (SAFEOP | 0x10, 0x001B)


# ====================================================================== drive


def drive_cycle(bus, st_, cw, mode=8, pos=0, vel=0, torque=0, ms=1.0, cycles=1):
    out = bytearray(bus.iomap)
    struct.pack_into("<HiihB", out, bus.out_at(st_), cw, pos, vel, torque, mode)
    data = b""
    for _ in range(cycles):
        bus.clock.advance(ms)
        data = bus.lrw(bytes(out))[0][3]
    return struct.unpack_from("<HiihbH", data, bus.in_at(st_))


def enable_drive(bus, st_, mode=8, pos=0):
    drive_cycle(bus, st_, 0x06, mode, pos)
    drive_cycle(bus, st_, 0x07, mode, pos)
    sw = drive_cycle(bus, st_, 0x0F, mode, pos, cycles=2)[0]
    assert sw & 0x6F == 0x27
    return sw


def test_drive_state_machine_through_controlword():
    bus = Bus("drive")
    bus.up()
    st_ = 0x1001
    sw = drive_cycle(bus, st_, 0x00, cycles=2)[0]
    assert sw & 0x4F == 0x40  # switch on disabled
    assert drive_cycle(bus, st_, 0x06, cycles=2)[0] & 0x6F == 0x21  # ready to switch on
    assert drive_cycle(bus, st_, 0x07, cycles=2)[0] & 0x6F == 0x23  # switched on
    sw = drive_cycle(bus, st_, 0x0F, cycles=2)[0]
    assert sw & 0x6F == 0x27 and sw & 0x1000  # operation enabled, following the target
    assert drive_cycle(bus, st_, 0x07, cycles=2)[0] & 0x6F == 0x23  # disable operation
    assert drive_cycle(bus, st_, 0x0F, cycles=2)[0] & 0x6F == 0x27
    assert drive_cycle(bus, st_, 0x0B, cycles=2)[0] & 0x4F == 0x40  # quick stop at rest -> SOD
    assert drive_cycle(bus, st_, 0x06, cycles=2)[0] & 0x6F == 0x21
    assert drive_cycle(bus, st_, 0x0F, cycles=2)[0] & 0x6F == 0x27  # switch on + enable at once
    assert drive_cycle(bus, st_, 0x00, cycles=2)[0] & 0x4F == 0x40  # disable voltage
    dev = bus.seg.slaves[0].device.model
    assert dev.state == "switch_on_disabled"


def test_drive_quick_stop_ramps_down_then_disables():
    bus = Bus("drive")
    bus.up()
    st_ = 0x1001
    enable_drive(bus, st_, mode=9)
    _sw, _p, vel, *_ = drive_cycle(bus, st_, 0x0F, mode=9, vel=200_000, cycles=100)
    assert abs(vel - 200_000) < 2_000
    # inputs come one cycle late (the slave processes outputs after the frame has passed)
    sw, _p, vel, *_ = drive_cycle(bus, st_, 0x0B, mode=9, vel=200_000, cycles=2)
    assert sw & 0x6F == 0x07 and 0 < vel < 200_000  # quick stop active, decelerating
    for _ in range(200):
        sw, _p, vel, *_ = drive_cycle(bus, st_, 0x0B, mode=9, vel=200_000)
        if sw & 0x4F == 0x40:
            break
    assert sw & 0x4F == 0x40 and vel == 0


def test_drive_csp_tracks_a_ramp_and_a_step():
    bus = Bus("drive")
    bus.up()
    st_ = 0x1001
    enable_drive(bus, st_)
    target = 0
    err = []
    for k in range(600):  # 0.6 s at 1 kHz: a 100 000 counts/s ramp
        target = 100 * k
        _sw, pos, vel, _tq, mode, code = drive_cycle(bus, st_, 0x0F, 8, target)
        if k > 200:
            err.append(abs(target - pos))
    assert mode == 8 and code == 0
    assert max(err) < 300  # feed-forward: small lag on a ramp
    assert abs(vel - 100_000) < 3_000
    for _ in range(300):  # a step of 5000 counts, then hold
        sw, pos, vel, *_ = drive_cycle(bus, st_, 0x0F, 8, 65_000)
    assert abs(pos - 65_000) <= 5 and abs(vel) < 500
    assert sw & 0x0400  # target reached


def test_drive_csv_and_cst():
    bus = Bus("drive")
    bus.up()
    st_ = 0x1001
    enable_drive(bus, st_, mode=9)
    for _ in range(100):
        _sw, _pos, vel, _tq, mode, _c = drive_cycle(bus, st_, 0x0F, 9, vel=-50_000)
    assert mode == 9 and abs(vel + 50_000) < 500
    drive_cycle(bus, st_, 0x0F, 10, torque=0, cycles=300)  # let friction stop it
    _sw, p0, v0, tq, mode, _c = drive_cycle(bus, st_, 0x0F, 10, torque=100, cycles=2)
    assert mode == 10 and tq == 100
    _sw, p1, v1, *_ = drive_cycle(bus, st_, 0x0F, 10, torque=100, cycles=20)
    assert v1 > v0 and p1 > p0  # positive torque accelerates forward
    _sw, _p, v2, *_ = drive_cycle(bus, st_, 0x0F, 10, torque=-100, cycles=40)
    assert v2 < v1


def test_drive_fault_injection_and_reset_on_bit7_edge():
    bus = Bus("drive")
    bus.up()
    st_ = 0x1001
    enable_drive(bus, st_)
    assert control.apply(bus.seg, {"cmd": "drive_fault", "slave": 0, "code": "0x2310"})["ok"]
    sw, *_rest, code = drive_cycle(bus, st_, 0x0F, cycles=2)  # inputs are one cycle late
    assert sw & 0x4F == 0x0F  # fault reaction active
    sw, *_rest, code = drive_cycle(bus, st_, 0x0F)
    assert sw & 0x4F == 0x08 and code == 0x2310
    assert bus.sdo_upload(st_, 0x603F, 0) == u16(0x2310)
    assert bus.sdo_upload(st_, 0x1001, 0)[0] & 0x03 == 0x03  # generic + current
    # the emergency (CoE service 1) was queued before the SDO answer
    assert bus.seg.slaves[0].coe.stats["emergency"] == 1 and len(bus.emergencies) == 1
    assert drive_cycle(bus, st_, 0x8F, cycles=2)[0] & 0x4F == 0x40  # rising edge of bit 7
    sw, *_rest, code = drive_cycle(bus, st_, 0x80, cycles=3)
    assert sw & 0x4F == 0x40 and code == 0  # holding bit 7 high does nothing more


def test_emergency_arrives_through_the_mailbox():
    bus = Bus("drive")
    bus.up()
    st_ = 0x1001
    enable_drive(bus, st_)
    bus.seg.drive_fault(0, 0x3210)
    drive_cycle(bus, st_, 0x0F)
    msg = bus.mbx_recv(st_)
    assert msg[5] & 0x0F == 3 and struct.unpack_from("<H", msg, 6)[0] >> 12 == 1
    code, reg = struct.unpack_from("<HB", msg, 8)
    assert code == 0x3210 and reg & 0x04


# ====================================================================== other devices


def test_ft_tare_and_imu_settings():
    bus = Bus("imu,ft")
    bus.up()
    seg = bus.seg
    control.apply(seg, {"cmd": "device", "slave": 1, "wrench": [1, 2, 30, 0.1, 0.2, 0.3]})
    control.apply(seg, {"cmd": "device", "slave": 0, "acc": [0, 0, 1], "quat": [2, 0, 0, 0]})
    out = bytearray(bus.iomap)
    bus.lrw(bytes(out))
    data = bus.lrw(bytes(out))[0][3]
    ft = struct.unpack_from("<6fH", data, bus.in_at(0x1002))
    assert abs(ft[2] - 30) < 1e-5 and ft[6] == 1
    imu = struct.unpack_from("<4f3f3f", data, bus.in_at(0x1001))
    assert imu[0] == 1.0 and imu[9] == 1.0
    struct.pack_into("<H", out, bus.out_at(0x1002), 1)  # tare
    bus.lrw(bytes(out))
    data = bus.lrw(bytes(out))[0][3]
    ft = struct.unpack_from("<6fH", data, bus.in_at(0x1002))
    assert max(abs(x) for x in ft[:6]) < 1e-6
    control.apply(seg, {"cmd": "device", "slave": 1, "wrench": [900, 0, 0, 0, 0, 0]})
    bus.lrw(bytes(out))
    assert struct.unpack_from("<H", bus.lrw(bytes(out))[0][3], bus.in_at(0x1002) + 24)[0] == 3  # overload
    # noise is off by default (exact values above) and deterministic (seeded) when on
    def noisy(seed):
        b = Bus("imu,ft", seed=seed)
        b.up()
        control.apply(b.seg, {"cmd": "device", "slave": 0, "noise": 0.05})
        frames = [b.lrw(bytes(b.iomap))[0][3] for _ in range(3)]
        return [f[b.in_at(0x1001):b.in_at(0x1001) + 42] for f in frames]
    a1, a2 = noisy(1), noisy(1)
    assert a1 == a2 and a1[1] != a1[2] and noisy(2) != a1


# ====================================================================== DC


def test_dc_latch_offset_system_time_and_frmw():
    bus = Bus("drive,drive,imu")
    bus.init_all()
    assert bus.bwr(0x0900, bytes(4)) == 3
    t = [struct.unpack("<IIII", bus.fprd(0x1001 + i, 0x0900, 16)[0]) for i in range(3)]
    for i in range(2):
        assert t[i][1] > t[i][0]  # port 1 sees the frame come back later
    assert t[2][1] == 0  # last slave: port 1 closed
    # round trip through the slaves behind decreases along the line
    assert t[0][1] - t[0][0] > t[1][1] - t[1][0]
    rx64 = struct.unpack("<Q", bus.fprd(0x1001, 0x0918, 8)[0])[0]
    master_time = 800_000_000_000_000_000
    bus.fpwr(0x1001, 0x0920, struct.pack("<q", master_time - rx64))
    sys1 = struct.unpack("<Q", bus.fprd(0x1001, 0x0910, 8)[0])[0]
    assert sys1 == master_time
    bus.clock.advance(2.5)
    sys2 = struct.unpack("<Q", bus.fprd(0x1001, 0x0910, 8)[0])[0]
    assert sys2 - sys1 == 2_500_000
    # the cyclic FRMW: the reference clock's time comes back; others add to the counter
    reply = parse(bus.seg.handle_frame(frame((FRMW, 0x1001, 0x0910, bytes(8)))))[0]
    assert struct.unpack("<Q", reply[3])[0] == sys2 and reply[4] == 3
    # stored SYNC0 registers, next pulse computed when active
    bus.fpwr(0x1001, 0x09A0, struct.pack("<I", 1_000_000))
    bus.fpwr(0x1001, 0x0990, struct.pack("<Q", sys2 + 100_000))
    bus.fpwr(0x1001, 0x0981, b"\x03")
    bus.clock.advance(10.2)
    nxt = struct.unpack("<Q", bus.fprd(0x1001, 0x0990, 8)[0])[0]
    assert nxt == sys2 + 100_000 + 11 * 1_000_000


def test_a_slave_without_dc_says_so_and_ignores_its_dc_registers_until_cleared():
    bus = Bus("drive,drive")
    assert control.apply(bus.seg, {"cmd": "dc", "slave": 1, "supported": False})["ok"]
    assert not control.apply(bus.seg, {"cmd": "dc", "slave": 1, "supported": "no"})["ok"]
    bus.init_all()
    features = [struct.unpack("<H", bus.fprd(0x1001 + i, 0x0008, 2)[0])[0] for i in range(2)]
    assert features[0] & 0x000C == 0x000C and features[1] & 0x000C == 0  # no DC, no 64-bit DC
    assert bus.bwr(0x0900, bytes(4)) == 2  # the latch: both count the datagram, one latches
    assert struct.unpack("<I", bus.fprd(0x1001, 0x0900, 4)[0])[0] != 0
    assert bus.fprd(0x1002, 0x0900, 16)[0] == bytes(16)
    for i in range(2):  # SYNC0 as SOEM's dc_sync writes it
        bus.fpwr(0x1001 + i, 0x09A0, struct.pack("<I", 1_000_000))
        bus.fpwr(0x1001 + i, 0x0981, b"\x03")
    assert [bus.fprd(0x1001 + i, 0x0981, 1)[0] for i in range(2)] == [b"\x03", b"\x00"]
    assert [s["sync0"]["active"] for s in bus.seg.status()["slaves"]] == [True, False]
    control.apply(bus.seg, {"cmd": "clear"})  # DC back (the slave power-cycled)
    assert [s["dc"] for s in bus.seg.status()["slaves"]] == [True, True]
    assert struct.unpack("<H", bus.seg.slave(1).read(0x0008, 2))[0] & 0x000C == 0x000C


# ====================================================================== faults


def test_fault_drop_delay_and_wrong_wkc():
    bus = Bus("drive")
    bus.up()
    seg = bus.seg
    f = frame((LRW, 0, 0, bytes(bus.iomap)))
    control.apply(seg, {"cmd": "drop", "count": 2})
    assert seg.handle_frame(f) is None and seg.handle_frame(f) is None
    assert seg.handle_frame(f) is not None
    assert seg.counters["dropped"] == 2
    # probability, deterministic through the seed
    control.apply(seg, {"cmd": "drop", "prob": 0.25})
    lost = sum(seg.handle_frame(f) is None for _ in range(400))
    assert 60 < lost < 140
    control.apply(seg, {"cmd": "clear"})
    # dropped after processing: the slaves saw it
    before = seg.slaves[0].stats["mailbox_in"]
    control.apply(seg, {"cmd": "drop", "count": 1, "where": "after"})
    msg = struct.pack("<HHBB", 10, 0, 0, 3 | (5 << 4)) + struct.pack("<HBHB", 2 << 12, 0x40, 0x1000, 0) + bytes(4)
    assert seg.handle_frame(frame((FPWR, 0x1001, 0x1000, msg.ljust(128, b"\0")))) is None
    assert seg.slaves[0].stats["mailbox_in"] == before + 1
    assert bus.mbx_recv(0x1001) is not None
    # delay: the runner holds the reply back
    control.apply(seg, {"cmd": "delay", "ms": 5, "count": 2})
    seg.handle_frame(f)
    assert seg.last_delay_ns == 5_000_000
    seg.handle_frame(f)
    seg.handle_frame(f)
    assert seg.last_delay_ns == 0 and seg.counters["delayed"] == 2
    # wrong working counter on the next 2 process-data frames only
    control.apply(seg, {"cmd": "wkc", "count": 2})
    assert bus.brd(0x0130, 2)[1] == 1  # not a process-data frame
    assert parse(seg.handle_frame(f))[0][4] == 2
    assert parse(seg.handle_frame(f))[0][4] == 2
    assert parse(seg.handle_frame(f))[0][4] == 3
    control.apply(seg, {"cmd": "wkc", "count": 1, "delta": 5, "scope": "all"})
    assert bus.brd(0x0130, 2)[1] == 6


def test_fault_cable_break_al_error_power_cycle():
    bus = Bus("drive,drive,imu")
    bus.up()
    seg = bus.seg
    out = bytes(bus.iomap)
    assert bus.lrw(out)[0][4] == 3 + 3 + 1
    assert control.apply(seg, {"cmd": "break", "slave": 1})["ok"]
    assert bus.lrw(out)[0][4] == 3
    assert bus.brd(0x0000, 2)[1] == 1
    assert bus.fprd(0x1002, 0x0130, 2)[1] == 0
    assert struct.unpack("<H", bus.fprd(0x1001, 0x0110, 2)[0])[0] & 0x0C00 == 0x0400  # port 1 closed now
    reply = parse(seg.handle_frame(frame((APRD, 0, 0, b"\0\0"))))[0]
    assert reply[1] == 1
    # the unreachable drive's watchdog runs out meanwhile (the others get their frames)
    for _ in range(15):
        bus.clock.advance(10)
        bus.lrw(out)
    control.apply(seg, {"cmd": "repair"})
    assert bus.al(0x1002) == (SAFEOP | 0x10, 0x001B)
    assert bus.al(0x1001) == (OP, 0)
    assert bus.al(0x1003) == (OP, 0)  # inputs only: no watchdog
    # AL error on demand
    assert control.apply(seg, {"cmd": "al_error", "slave": 2, "code": "0x0020"})["ok"]
    assert bus.al(0x1003) == (SAFEOP | 0x10, 0x0020)
    # power cycle: station address and state gone
    control.apply(seg, {"cmd": "power_cycle", "slave": 0})
    assert bus.fprd(0x1001, 0x0130, 2)[1] == 0
    assert bus.aprd(0, 0x0130, 2)[0] == u16(INIT)


def test_control_commands_and_status():
    bus = Bus("drive,dio")
    seg = bus.seg
    bus.up()
    bus.lrw(bytes(bus.iomap))
    status = control.apply(seg, {"cmd": "status"})
    assert status["ok"] and status["counters"]["frames"] > 0
    assert status["commands"]["LRW"] >= 2 and status["commands"]["BWR"] >= 1
    assert [s["state"] for s in status["slaves"]] == ["OP", "OP"]
    assert status["slaves"][0]["device"]["state"] == "switch_on_disabled"
    json.dumps(status)
    bad = [{"cmd": "nope"}, {"cmd": "drive_fault", "slave": 1}, {"cmd": "break", "slave": 9},
           {"cmd": "drop", "prob": 2}, {"cmd": "device", "slave": 1, "color": 3}, {"cmd": "al_error"}]
    for c in bad:
        answer = control.apply(seg, c)
        assert not answer["ok"] and answer["error"]
    assert json.loads(control.apply_line(seg, b'{"cmd": "ping"}'))["pong"]
    assert not json.loads(control.apply_line(seg, b"[1]"))["ok"]
    assert not json.loads(control.apply_line(seg, b"{nope"))["ok"]
    control.apply(seg, {"cmd": "reset_counters"})
    assert seg.counters["frames"] == 0


# ====================================================================== frames


def test_multi_datagram_frame_and_reply_shape():
    bus = Bus("drive,imu")
    bus.init_all()
    f = frame((FPRD, 0x1001, 0x0010, b"\0\0"), (FPWR, 0x1002, 0x0200, u16(7)), (BRD, 0, 0x0130, b"\0\0"),
              (NOP, 0, 0, b"\0"))
    f_padded = f + bytes(60 - len(f)) if len(f) < 60 else f
    reply = bus.seg.handle_frame(f_padded)
    assert len(reply) == len(f_padded)
    assert reply[6] & 0x02  # locally administered source MAC
    dgs = parse(reply)
    assert [d[4] for d in dgs] == [1, 1, 2, 0]
    assert dgs[0][3] == u16(0x1001)
    assert bus.seg.handle_frame(b"\x00" * 12 + b"\x08\x00" + bytes(46)) is None  # IPv4: not ours
    assert bus.seg.handle_frame(f[:20]) is None  # truncated
    broken = bytearray(f)
    struct.pack_into("<H", broken, 14 + 2 + 6, 0x7FF)  # a datagram longer than the frame
    assert bus.seg.handle_frame(bytes(broken)) is not None


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=0, max_size=200), st.integers(0, 14))
def test_handle_frame_never_raises_on_garbage(payload, cmd):
    seg = Segment("drive,dio", clock=Clock())
    raw = ETH + payload
    reply = seg.handle_frame(raw)
    assert reply is None or len(reply) == len(raw)
    dg = frame((cmd, 0, 0x0100 + (len(payload) % 0x500), payload[:64]))
    reply = seg.handle_frame(dg)
    assert reply is None or len(reply) == len(dg)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([BOOL, UINT8, INT16, INT32, REAL32]), st.integers(0, 2**31 - 1)),
                min_size=1, max_size=8))
def test_pdo_codec_round_trip(fields):
    entries = []
    items = []
    for i, (dtype, raw) in enumerate(fields):
        e = Entry(0x6000, i + 1, f"e{i}", dtype, 0)
        if dtype == BOOL:
            e.value = raw & 1
        elif dtype == UINT8:
            e.value = raw & 0xFF
        elif dtype == INT16:
            e.value = (raw & 0xFFFF) - 0x8000
        elif dtype == INT32:
            e.value = raw - 2**30
        else:
            e.value = float(raw % 1000) / 4
        entries.append(e)
        items.append((e, e.bits))
    codec = PdoCodec(items)
    buf = bytearray(codec.size + 3)
    codec.encode(buf, 1)
    want = [e.value for e in entries]
    for e in entries:
        e.value = 0
    codec.decode(buf, 1)
    assert [e.value for e in entries] == want


# ====================================================================== SOEM bring-up replay


def _sdo_u(bus, st_, index, sub, ca=False):
    return bus.sdo_upload(st_, index, sub, ca)


def test_replay_soem_bring_up_sequence_to_op():
    """The datagram sequence pysoem 1.1.13 sends for config_init + config_map + config_dc +
    OP (reference notes, section 4.2), for an I/O terminal and a CoE drive, rebuilt here."""
    bus = Bus("dio,drive")
    seg = bus.seg
    z = bytes(64)
    # --- config_init: detect
    assert bus.bwr(0x0103, b"\0") == 2
    assert bus.bwr(0x0120, u16(INIT | ACK)) == 2
    assert bus.bwr(0x0120, u16(INIT | ACK)) == 2
    _, count = bus.brd(0x0000, 2)
    assert count == 2
    # --- set slaves to default
    for ado, data in ((0x0101, b"\0"), (0x0200, u16(4)), (0x0300, z[:8]), (0x0600, z[:48]), (0x0800, z[:32]),
                      (0x0981, b"\0"), (0x0910, z[:4]), (0x0930, u16(0x1000)), (0x0934, u16(0x0C00)),
                      (0x0103, b"\0"), (0x0120, u16(INIT | ACK)), (0x0500, b"\x02"), (0x0500, b"\0")):
        assert bus.bwr(ado, data) == 2
    stations = []
    for slave in range(1, count + 1):
        adp = (1 - slave) & 0xFFFF
        assert bus.dg(APRD, adp, 0x0140, b"\0\0")[1] == 1
        assert bus.dg(APWR, adp, 0x0010, u16(0x1000 + slave))[1] == 1
        assert bus.dg(APWR, adp, 0x0100, u16(1 if slave == 1 else 0))[1] == 1
        data, _ = bus.dg(APRD, adp, 0x0010, b"\0\0")
        station = struct.unpack("<H", data)[0]
        stations.append(station)
        assert bus.fprd(station, 0x0012, 2)[1] == 1
        estat = struct.unpack("<H", bus.fprd(station, 0x0502, 2)[0])[0]
        assert estat & 0x0040
    # SOEM reads each header item in parallel (request to all, then collect)
    eep = {s: {} for s in stations}
    for word in (0x08, 0x0E, 0x0A, 0x0C, 0x18, 0x1A, 0x1C):
        for s in stations:
            bus.fpwr(s, 0x0502, struct.pack("<HI", 0x0100, word))
        for s in stations:
            assert not struct.unpack("<H", bus.fprd(s, 0x0502, 2)[0])[0] & 0x8000
            eep[s][word] = struct.unpack("<I", bus.fprd(s, 0x0508, 4)[0])[0]
    dio, drv = stations
    assert (eep[dio][0x08], eep[dio][0x0A]) == (VENDOR, 0x808) and eep[dio][0x18] == 0
    assert (eep[drv][0x08], eep[drv][0x0A], eep[drv][0x0C]) == (VENDOR, 0x402, 1)
    mbx_l = eep[drv][0x18] >> 16
    assert (eep[drv][0x18] & 0xFFFF, mbx_l) == (0x1000, 128) and eep[drv][0x1C] & 0x0004
    sii = {s: bus.sii(s) for s in stations}
    for s in stations:
        assert struct.unpack("<H", bus.fprd(s, 0x0008, 2)[0])[0] & 0x04  # DC
        topo = struct.unpack("<H", bus.fprd(s, 0x0110, 2)[0])[0]
        assert topo & 0x0300 == 0x0200
        bus.fprd(s, 0x0007, 2)
        assert bus.al(s) == (INIT, 0)
    cats = {s: _categories(sii[s]) for s in stations}
    assert cats[drv][30][5] & 0x20  # complete access: SOEM maps with CA first
    bus.fpwr(drv, 0x0800, struct.pack("<HHBBBB", 0x1000, 128, 0x26, 0, 1, 0) + struct.pack("<HHBBBB", 0x1080, 128, 0x22, 0, 1, 0))
    for s in stations:
        bus.fpwr(s, 0x0500, b"\x01")
        bus.fpwr(s, 0x0120, u16(PREOP | ACK))
    # --- config_map: PREOP check, CoE mapping with complete access
    for s in stations:
        assert bus.al(s) == (PREOP, 0)
    for s in stations:
        bus.fpwr(s, 0x0500, b"\x02")
        bus.fpwr(s, 0x0500, b"\x00")
    sm_types = _sdo_u(bus, drv, 0x1C00, 0, ca=True)
    assert sm_types[0] == 4 and list(sm_types[2:]) == [1, 2, 3, 4]
    bits = {}
    for sm, assign in ((2, 0x1C12), (3, 0x1C13)):
        a = _sdo_u(bus, drv, assign, 0, ca=True)
        total = 0
        for k in range(a[0]):
            pdo = struct.unpack_from("<H", a, 2 + 2 * k)[0]
            m = _sdo_u(bus, drv, pdo, 0, ca=True)
            total += sum(struct.unpack_from("<I", m, 2 + 4 * j)[0] & 0xFF for j in range(m[0]))
        bits[sm] = total
    assert bits == {2: 13 * 8, 3: 15 * 8}
    # SII mapping for the mailbox-less terminal: TXPDO for inputs, RXPDO for outputs
    dio_in = sum(b for _i, sm, es in _pdos(cats[dio][50]) for _x, _y, b in es)
    dio_out = sum(b for _i, sm, es in _pdos(cats[dio][51]) for _x, _y, b in es)
    assert (dio_out, dio_in) == (8, 8)
    # SM programming (non-mailbox slave: from its SII SM category; SM2/SM3 for everyone)
    dio_sms = [struct.unpack_from("<HHBBBB", cats[dio][41], 8 * i) for i in range(4)]
    for n, (start, _length, ctrl, _st, enable, _kind) in enumerate(dio_sms):
        if start:
            bus.fpwr(dio, 0x0800 + 8 * n, struct.pack("<HHBBBB", start, (dio_out if n == 2 else dio_in) // 8, ctrl, 0, enable, 0))
    bus.fpwr(drv, 0x0810, struct.pack("<HHBBBB", 0x1100, bits[2] // 8, 0x64, 0, 1, 0))
    bus.fpwr(drv, 0x0818, struct.pack("<HHBBBB", 0x1180, bits[3] // 8, 0x20, 0, 1, 0))
    # FMMUs: outputs (dio 1 B at 0, drive 13 B at 1), inputs (dio at 14, drive 15 B at 15)
    bus.fpwr(dio, 0x0600, struct.pack("<IHBBHBBB", 0, 1, 0, 7, 0x1000, 0, 2, 1) + bytes(3))
    bus.fpwr(drv, 0x0600, struct.pack("<IHBBHBBB", 1, 13, 0, 7, 0x1100, 0, 2, 1) + bytes(3))
    bus.fpwr(dio, 0x0610, struct.pack("<IHBBHBBB", 14, 1, 0, 7, 0x1100, 0, 1, 1) + bytes(3))
    bus.fpwr(drv, 0x0610, struct.pack("<IHBBHBBB", 15, 15, 0, 7, 0x1180, 0, 1, 1) + bytes(3))
    for s in stations:
        bus.fpwr(s, 0x0500, b"\x01")
        bus.fpwr(s, 0x0120, u16(SAFEOP))
    data, wkc = bus.brd(0x0130, 2)
    assert struct.unpack("<H", data)[0] == SAFEOP and wkc == 2
    # --- config_dc
    assert bus.bwr(0x0900, bytes(4)) == 2
    t_dio = struct.unpack("<I", bus.fprd(dio, 0x0900, 4)[0])[0]
    rx = struct.unpack("<Q", bus.fprd(dio, 0x0918, 8)[0])[0]
    assert rx & 0xFFFFFFFF == t_dio
    bus.fpwr(dio, 0x0920, struct.pack("<Q", (10**18 - rx) & (2**64 - 1)))
    for ado in (0x0904, 0x0908, 0x090C):
        bus.fprd(dio, ado, 4)
    rx2 = struct.unpack("<Q", bus.fprd(drv, 0x0918, 8)[0])[0]
    bus.fpwr(drv, 0x0920, struct.pack("<Q", (10**18 - rx2) & (2**64 - 1)))
    bus.fpwr(drv, 0x0928, struct.pack("<I", 400))
    # --- one process-data cycle (LRW + FRMW), then OP
    out = bytearray(30)
    out[0] = 0x5A
    dgs = bus.lrw(bytes(out), extra=((FRMW, dio, 0x0910, bytes(8)),))
    assert dgs[0][4] == 6  # expected_wkc = 2 * outputsWKC + inputsWKC = 2*2 + 2
    assert struct.unpack("<Q", dgs[1][3])[0] >= 10**18
    assert bus.bwr(0x0120, u16(OP)) == 2
    data, wkc = bus.brd(0x0130, 2)
    assert struct.unpack("<H", data)[0] == OP
    bus.lrw(bytes(out), extra=((FRMW, dio, 0x0910, bytes(8)),))
    dgs = bus.lrw(bytes(out), extra=((FRMW, dio, 0x0910, bytes(8)),))
    assert dgs[0][4] == 6 and dgs[0][3][14] == 0x5A  # the terminal's loop-back, a cycle late
    assert [esc.al_state for esc in seg.slaves] == [OP, OP]


# ====================================================================== spec, CLI, fixture checks


def test_slave_spec_parsing():
    from aiohal.drivers.ethercat.sim.spec import parse_spec

    devs = parse_spec("drive*3, imu,ft,dio,dio4")
    assert [d.kind for d in devs] == ["drive"] * 3 + ["imu", "ft", "dio", "dio"]
    assert [d.serial for d in devs] == list(range(1, 8))
    assert devs[-1].name == "AIOHAL-DIO4" and devs[-2].name == "AIOHAL-DIO8"
    for bad in ("", "robot", "drive*0", "imu3", "dio9", "drive**2"):
        with pytest.raises(ValueError):
            parse_spec(bad)


def test_cli_bench_and_errors(capsys):
    from aiohal.drivers.ethercat.sim.__main__ import main

    assert main(["--slaves", "drive*2,imu,dio4", "--bench", "50"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["state"] == OP and result["wkc"] == 3 + 3 + 1 + 3 and result["drives_enabled"] == 2
    assert result["us_per_frame"] > 0
    assert main(["--slaves", "robot"]) == 2
    assert main(["--slaves", "drive", "--inject", '{"cmd": "nope"}']) == 2
    assert main(["--slaves", "drive"]) == 2  # --ifname missing
    # every drive behind the shared servo model: brought up and enabled the same way
    assert main(["--slaves", "drive*2,imu", "--dynamics", "servo", "--bench", "50"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["state"] == OP and result["drives_enabled"] == 2
    assert main(["--slaves", "drive", "--dynamics", "servo", "--servo-json", '{"gear_ratio": -1}', "--bench", "5"]) == 2
    assert "drive: servo: " in capsys.readouterr().err


def test_fixture_explains_what_is_missing(monkeypatch):
    from aiohal.drivers.ethercat.sim import fixture

    monkeypatch.setattr(fixture.os, "geteuid", lambda: 1000)
    with pytest.raises(fixture.SimulatorUnavailable, match="root"):
        fixture.check_environment()
    with pytest.raises(fixture.SimulatorUnavailable):
        fixture.SimulatedSegment("drive").start()
    monkeypatch.setattr(fixture.os, "geteuid", lambda: 0)
    monkeypatch.setattr(fixture.shutil, "which", lambda tool: None if tool == "unshare" else "/usr/sbin/ip")
    with pytest.raises(fixture.SimulatorUnavailable, match="unshare"):
        fixture.check_environment()


def test_the_control_channel_answers_any_input_with_an_error_and_carries_on():
    seg = Bus("drive,dio").seg
    # the JSON parser's recursion runs out (Python 3.11, 3.12) or it finds the input truncated (3.13)
    nested = json.loads(control.apply_line(seg, b"[" * 6000))
    assert not nested["ok"] and nested["error"].startswith(("bad request: RecursionError", "bad request: JSONDecodeError"))
    deep = json.loads(control.apply_line(seg, b'{"cmd": "device", "slave": 0, "load": ' + b"[" * 3000 + b"]" * 3000
                                         + b"}"))
    assert not deep["ok"]
    assert json.loads(control.apply_line(seg, b'{"cmd": "ping"}'))["pong"]


_json = st.recursive(st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats() | st.text(max_size=8),
                     lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
                     max_leaves=8)
_commands = ["ping", "status", "drop", "delay", "wkc", "break", "repair", "al_error", "drive_fault", "device",
             "dc", "eeprom_busy", "power_cycle", "clear", "reset_counters", "op_delay", "hide_objects", "nope"]


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(_commands), st.dictionaries(
    st.sampled_from(["slave", "code", "ms", "count", "prob", "where", "delta", "scope", "supported", "indices",
                     "load", "fault", "power_on_fault", "position", "pattern", "quat"]), _json, max_size=4))
def test_every_control_command_answers_whatever_its_fields(cmd, fields):
    seg = _FUZZ_BUS.seg
    answer = control.apply(seg, {"cmd": cmd, **fields})
    assert isinstance(answer["ok"], bool)
    json.loads(control.apply_line(seg, json.dumps({"cmd": cmd, **fields}, allow_nan=True)))
    control.apply(seg, {"cmd": "clear"})
    control.apply(seg, {"cmd": "power_cycle"})


_FUZZ_BUS = Bus("drive,imu,ft,dio")


def test_an_interface_name_longer_than_linux_allows_is_refused_at_once():
    proc = subprocess.run([sys.executable, "-m", "aiohal.drivers.ethercat.sim", "--ifname", "a" * 16, "--wait-s", "30"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "is not a Linux interface name (1..15 bytes" in proc.stderr


def test_safeop_to_op_takes_the_configured_delay_and_a_repeated_request_does_not_restart_it():
    bus = Bus("drive,imu")
    assert control.apply(bus.seg, {"cmd": "op_delay", "ms": 30})["ok"]
    bus.up(to=SAFEOP)
    bus.lrw(bytes(bus.iomap))
    bus.bwr(0x0120, u16(OP))
    for _ in range(5):  # 25 ms of cycles and repeated requests: still SAFEOP
        bus.clock.advance(5)
        bus.lrw(bytes(bus.iomap))
        bus.bwr(0x0120, u16(OP))
        assert bus.brd(0x0130, 2)[0] == u16(SAFEOP)
    bus.clock.advance(6)
    bus.lrw(bytes(bus.iomap))  # the drive with outputs and the IMU without: both at the next cycle
    assert [bus.al(0x1001 + i) for i in range(2)] == [(OP, 0), (OP, 0)]
    control.apply(bus.seg, {"cmd": "clear"})
    assert all(esc.op_delay_ns == 0 for esc in bus.seg.slaves)


def test_a_drive_with_a_power_on_fault_is_in_fault_from_its_first_exchange_at_every_power_cycle():
    bus = Bus("drive")
    assert control.apply(bus.seg, {"cmd": "device", "slave": 0, "power_on_fault": "0x7500"})["ok"]
    control.apply(bus.seg, {"cmd": "power_cycle"})
    bus.up(to=SAFEOP)
    for _ in range(3):
        bus.clock.advance(1)
        bus.lrw(bytes(bus.iomap))
    drive = bus.seg.slaves[0].device.status()
    assert drive["state"] == "fault" and drive["error_code"] == 0x7500
    control.apply(bus.seg, {"cmd": "clear"})
    control.apply(bus.seg, {"cmd": "power_cycle"})
    assert bus.seg.slaves[0].device.model.power_on_fault is None


def test_hidden_objects_are_answered_as_missing_and_clear_shows_them_again():
    bus = Bus("drive")
    od = bus.seg.slaves[0].device.od
    assert control.apply(bus.seg, {"cmd": "hide_objects", "slave": 0, "indices": ["0x1C12", 0x1C13]})["ok"]
    with pytest.raises(SdoAbort) as missing:
        od.read(0x1C12, 0)
    assert missing.value.code == ABORT_NO_OBJECT and od.read(0x1C00, 0)  # the others are there
    control.apply(bus.seg, {"cmd": "clear"})
    assert od.read(0x1C12, 0) == b"\x01"


def _config_dc(bus: Bus, stations: list[int], master_time: int) -> None:
    """What SOEM's config_dc does: latch, offsets from each slave's receive time, propagation
    delays from the port receive times (half the round trip's difference to the reference's)."""
    bus.bwr(0x0900, bytes(4))
    ports = [struct.unpack("<II", bus.fprd(st_, 0x0900, 8)[0]) for st_ in stations]
    for st_, (t0, t1) in zip(stations, ports, strict=True):
        rx = struct.unpack("<Q", bus.fprd(st_, 0x0918, 8)[0])[0]
        bus.fpwr(st_, 0x0920, struct.pack("<Q", (master_time - rx) & (2**64 - 1)))
        ref_trip = ports[0][1] - ports[0][0]
        trip = t1 - t0 if t1 else 0
        bus.fpwr(st_, 0x0928, struct.pack("<I", (ref_trip - trip) // 2))


def _propagate(bus: Bus, ms: float, count: int, rng: random.Random) -> None:
    """The cyclic FRMW of the reference clock's time, every ``ms`` give or take 30 %."""
    for _ in range(count):
        bus.clock.advance(ms * rng.uniform(0.7, 1.3))
        bus.seg.handle_frame(frame((FRMW, 0x1001, 0x0910, bytes(8))))


@pytest.mark.parametrize("compensation", [True, False])
def test_dc_drift_compensation_locks_clocks_100_ppm_apart(compensation):
    bus = Bus("drive*4", seed=3, drift_ppm=100)
    drifts = [s["drift_ppm"] for s in bus.seg.status()["slaves"]]
    assert drifts[0] == -50 and drifts[-1] == 50 and len(set(drifts)) == 4
    bus.init_all()
    assert control.apply(bus.seg, {"cmd": "dc", "compensation": compensation})["ok"]
    stations = [0x1001 + i for i in range(4)]
    _config_dc(bus, stations, 800_000_000_000_000_000)
    delays = [struct.unpack("<I", bus.fprd(st_, 0x0928, 4)[0])[0] for st_ in stations]
    assert delays[0] == 0 and delays[1] > 0 and delays == sorted(delays)
    rng = random.Random(1)
    _propagate(bus, 0.1, 3000, rng)  # static drift compensation
    locked = bus.clock()
    _propagate(bus, 1.0, 2000, rng)  # cyclic operation, 2 s
    trace = control.apply(bus.seg, {"cmd": "dc_trace", "since_ns": locked})
    worst = max(abs(w) for w in trace["worst_ns"])
    assert trace["samples"] >= 1900 and trace["worst_ns"][0] == 0
    if compensation:
        assert worst < 1000  # LOLA's +-1 us
    else:  # the slaves 100 ppm from the reference drift 100 us per second
        assert worst > 100_000


def test_the_system_time_difference_register_says_which_way_the_slave_is_off():
    bus = Bus("drive,drive")
    bus.init_all()
    t = struct.unpack("<Q", bus.fprd(0x1002, 0x0910, 8)[0])[0]
    bus.fpwr(0x1002, 0x0934, b"\x00")  # no averaging
    bus.fpwr(0x1002, 0x0910, struct.pack("<Q", t + 5000))  # the written time is ahead: the slave is behind
    diff = struct.unpack("<I", bus.fprd(0x1002, 0x092C, 4)[0])[0]
    assert diff >> 31 == 1 and 4000 < diff & 0x7FFF_FFFF <= 5000
    bus.fpwr(0x1002, 0x0930, u16(0x1000))  # a write of the speed counter start restarts the loop
    assert bus.fprd(0x1002, 0x092C, 4)[0] == bytes(4)
