"""In-process measurement of :meth:`Segment.handle_frame` (no network, no root).

A tiny master (:class:`MiniMaster`) brings the segment to OP with the datagrams a master would
send (station addresses, mailbox and process-data SyncManagers, FMMUs laid out as SOEM's
``config_map`` does, AL states), then times frames made of one LRW over the whole process image
plus the DC ``FRMW 0x0910`` datagram, as SOEM sends them every cycle.
"""

from __future__ import annotations

import struct
import time
from typing import Any

from .drive import Drive
from .segment import APRD, APWR, BRD, BWR, FPRD, FPWR, FRMW, LRW, Segment

HEADER = bytes.fromhex("ffffffffffff010101010101") + b"\x88\xa4"


def frame(*datagrams: tuple[int, int, int, int, bytes]) -> bytes:
    """Ethernet frame from (cmd, idx, adp, ado, data) datagrams."""
    body = b""
    for i, (cmd, idx, adp, ado, data) in enumerate(datagrams):
        more = 0x8000 if i < len(datagrams) - 1 else 0
        body += struct.pack("<BBHHHH", cmd, idx, adp, ado, len(data) | more, 0) + data + b"\0\0"
    return HEADER + struct.pack("<H", len(body) | 0x1000) + body


def parse(reply: bytes) -> list[tuple[int, bytes, int]]:
    """(cmd, data, wkc) per datagram of a reply frame."""
    out = []
    pos = 16
    while True:
        cmd, _idx, _adp, _ado, ln, _irq = struct.unpack_from("<BBHHHH", reply, pos)
        n = ln & 0x7FF
        data = reply[pos + 10 : pos + 10 + n]
        wkc = struct.unpack_from("<H", reply, pos + 10 + n)[0]
        out.append((cmd, data, wkc))
        if not ln & 0x8000:
            return out
        pos += 12 + n


def soem_map(layout: list[tuple[int, Any, int, int]]) -> tuple[list[tuple[int, int, bytes]], dict, int, int]:
    """SOEM's legacy ``config_map`` for slaves ``(station, device, out_bits, in_bits)`` in bus
    order: the outputs of all slaves first, then the inputs, slaves of fewer than 8 bits
    bit-packed. Returns the FMMU register writes ``(station, register, data)``, the logical bit
    offset of each ``(station, "out" | "in")``, the output bytes and the IO map bytes."""
    writes: list[tuple[int, int, bytes]] = []
    offsets: dict[tuple[int, str], int] = {}
    fmmus = {station: 0 for station, *_ in layout}
    pos = out_total = 0
    for key in ("out", "in"):
        for station, dev, out_bits, in_bits in layout:
            bits = out_bits if key == "out" else in_bits
            if not bits:
                continue
            if bits >= 8 and pos % 8:
                pos += 8 - pos % 8
            start, sbit = divmod(pos, 8)
            span = bits if bits < 8 else (bits + 7) // 8 * 8
            end, ebit = divmod(pos + span - 1, 8)
            offsets[(station, key)] = pos
            phys, ftype = (dev.out_addr, 2) if key == "out" else (dev.in_addr, 1)
            writes.append(
                (
                    station,
                    0x0600 + 16 * fmmus[station],
                    struct.pack("<IHBBHBBB", start, end - start + 1, sbit, ebit, phys, 0, ftype, 1) + bytes(3),
                )
            )
            fmmus[station] += 1
            pos += span
        if key == "out":
            out_total = (pos + 7) // 8
            pos = out_total * 8
    return writes, offsets, out_total, (pos + 7) // 8


class MiniMaster:
    def __init__(self, segment: Segment) -> None:
        self.seg = segment

    def dg(self, cmd: int, adp: int, ado: int, data: bytes) -> tuple[bytes, int]:
        reply = self.seg.handle_frame(frame((cmd, 1, adp, ado, data)))
        if reply is None:
            return b"", 0
        _, out, wkc = parse(reply)[0]
        return out, wkc

    def bring_up(self, station0: int = 0x1001) -> dict[str, Any]:
        seg = self.seg
        self.dg(BWR, 0, 0x0120, struct.pack("<H", 0x11))
        _, count = self.dg(BRD, 0, 0x0000, b"\0\0")
        stations = []
        for i in range(count):
            station = station0 + i
            self.dg(APWR, (-i) & 0xFFFF, 0x0010, struct.pack("<H", station))
            stations.append(station)
        layout = []
        for i, station in enumerate(stations):
            esc = seg.active[i]
            dev = esc.device
            if dev.mailbox:
                rx_off, rx_size, tx_off, tx_size = dev.mailbox
                self.dg(
                    FPWR,
                    station,
                    0x0800,
                    struct.pack("<HHBBBB", rx_off, rx_size, 0x26, 0, 1, 0)
                    + struct.pack("<HHBBBB", tx_off, tx_size, 0x22, 0, 1, 0),
                )
            self.dg(FPWR, station, 0x0120, struct.pack("<H", 0x02))
            out_bytes, in_bytes = dev.default_sizes()
            out_bits = sum(b for idx in dev.rx_assign for _, _, b in dev.rx_pdos[idx])
            in_bits = sum(b for idx in dev.tx_assign for _, _, b in dev.tx_pdos[idx])
            layout.append((station, dev, out_bits, in_bits))
            if out_bytes:
                self.dg(FPWR, station, 0x0810, struct.pack("<HHBBBB", dev.out_addr, out_bytes, 0x64, 0, 1, 0))
            if in_bytes:
                self.dg(FPWR, station, 0x0818, struct.pack("<HHBBBB", dev.in_addr, in_bytes, 0x20, 0, 1, 0))
        writes, bit_offsets, out_total, size = soem_map(layout)
        for station, register, data in writes:
            self.dg(FPWR, station, register, data)
        self.offsets = {key: bits // 8 for key, bits in bit_offsets.items()}  # (station, "out"/"in") -> logical byte
        self.layout = layout
        for station, *_ in layout:
            self.dg(FPWR, station, 0x0120, struct.pack("<H", 0x04))
        self.lrw(bytes(size))
        self.dg(BWR, 0, 0x0120, struct.pack("<H", 0x08))
        states, _ = self.dg(BRD, 0, 0x0130, b"\0\0")
        return {"slaves": count, "iomap": size, "outputs": out_total, "state": struct.unpack("<H", states)[0]}

    def lrw(self, data: bytes, dc_station: int | None = None) -> tuple[bytes, int]:
        dgs = [(LRW, 2, 0, 0, data)]
        if dc_station is not None:
            dgs.append((FRMW, 2, dc_station, 0x0910, bytes(8)))
        reply = self.seg.handle_frame(frame(*dgs))
        if reply is None:
            return b"", 0
        _, out, wkc = parse(reply)[0]
        return out, wkc


def measure(segment: Segment, frames: int = 2000) -> dict[str, Any]:
    """Bring ``segment`` to OP in-process and time ``frames`` LRW+FRMW frames."""
    m = MiniMaster(segment)
    info = m.bring_up()
    size = info["iomap"]
    first = segment.active[0].station if segment.active else 0
    # enable every drive in CSP with a fixed target, so that the timed frames do real work
    data = bytearray(size)
    drives = [(st, m.offsets[(st, "out")]) for st, dev, *_ in m.layout if dev.kind == "drive"]
    for cw in (0x06, 0x0F):
        for _st, off in drives:
            struct.pack_into("<HiihB", data, off, cw, 5000, 0, 0, 8)
        m.lrw(bytes(data), first)
    enabled = sum(
        1 for esc in segment.active if isinstance(esc.device, Drive) and esc.device.model.state == "operation_enabled"
    )
    fr = frame((LRW, 2, 0, 0, bytes(data)), (FRMW, 2, first, 0x0910, bytes(8)))
    handle = segment.handle_frame
    reply = handle(fr)
    _, _, wkc = parse(reply)[0] if reply else (0, b"", 0)
    for _ in range(min(200, frames)):  # warm-up
        handle(fr)
    batches = []
    per_batch = max(1, frames // 5)
    for _ in range(5):  # the machine may be shared: report the best and the median batch
        t0 = time.perf_counter_ns()
        for _ in range(per_batch):
            handle(fr)
        batches.append((time.perf_counter_ns() - t0) / per_batch / 1000)
    batches.sort()
    return {
        "slaves": len(segment.slaves),
        "iomap_bytes": size,
        "frame_bytes": len(fr),
        "state": info["state"],
        "wkc": wkc,
        "frames": per_batch * 5,
        "drives_enabled": enabled,
        "us_per_frame": round(batches[0], 2),
        "us_per_frame_median": round(batches[2], 2),
    }


__all__ = ["APRD", "FPRD", "MiniMaster", "frame", "measure", "parse"]
