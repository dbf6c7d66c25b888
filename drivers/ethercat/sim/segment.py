"""A line of simulated slaves answering EtherCAT frames, plus fault injection.

:meth:`Segment.handle_frame` takes a whole Ethernet frame (EtherType 0x88A4) and returns the
frame as it would come back from the last slave (same length), or ``None`` when the frame is
lost. It does no I/O and takes the time from the segment's ``clock`` (``time.monotonic_ns`` by
default; tests pass a fake clock), so it can be tested without a network.

Datagram commands: NOP, APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW,
FRMW. Working counter: +1 per slave for a read, +1 for a write, +3 for a read-write; in LRW
+1 if a read FMMU and +2 if a write FMMU of the slave was hit (LWR: +1 per written slave);
ARMW/FRMW: +1 for the addressed slave's read and +1 per other slave's write. Auto-increment
addresses count up once per slave passed (also for broadcasts). Frames pass the slaves in bus
order; processing datagram by datagram is equivalent because a slave only sees its own memory.
"""

from __future__ import annotations

import random
import struct
import time
from collections.abc import Callable

from .dc_trace import DcTrace, drifts
from .devices import Device
from .esc import HOP_NS, MASK64, OP, SAFEOP, Esc
from .spec import parse_spec

ETHERTYPE = b"\x88\xa4"
DGRAM = struct.Struct("<BBHHHH")
U16 = struct.Struct("<H")
U64 = struct.Struct("<Q")

NOP, APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(15)
COMMANDS = (
    "NOP",
    "APRD",
    "APWR",
    "APRW",
    "FPRD",
    "FPWR",
    "FPRW",
    "BRD",
    "BWR",
    "BRW",
    "LRD",
    "LWR",
    "LRW",
    "ARMW",
    "FRMW",
)
POLL_NS = 1_000_000
#: process-data replies later than these (µs after the frame arrived) are counted, as ``late_<N>us``
LATE_REPLY_US = (200, 1000, 2000, 10_000, 50_000)


def _late_key(us: int) -> str:
    return f"late_{us}us"


class Faults:
    """Injected faults. Counts ("next N frames") decrement per affected frame."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self.drop_prob = 0.0
        self.drop_next = 0
        self.drop_after = False  # lose the frame after the slaves processed it
        self.delay_ns = 0
        self.delay_count = -1  # -1: every frame until cleared
        self.wkc_next = 0
        self.wkc_delta = -1
        self.wkc_all = False  # False: only frames with logical (process data) datagrams

    def as_dict(self) -> dict:
        return {
            "drop_prob": self.drop_prob,
            "drop_next": self.drop_next,
            "drop_where": "after" if self.drop_after else "before",
            "delay_ms": self.delay_ns / 1e6,
            "delay_count": self.delay_count,
            "wkc_next": self.wkc_next,
            "wkc_delta": self.wkc_delta,
            "wkc_scope": "all" if self.wkc_all else "pd",
        }


class Segment:
    def __init__(
        self,
        slaves: str | list[Device],
        *,
        clock: Callable[[], int] = time.monotonic_ns,
        watchdog_ms: float = 100.0,
        seed: int = 0,
        drift_ppm: float = 0.0,
    ) -> None:
        devices = parse_spec(slaves, seed) if isinstance(slaves, str) else list(slaves)
        self.clock = clock
        self.rng = random.Random(seed)
        self.slaves: list[Esc] = []
        self.dc_trace = DcTrace()
        self._frame_now: int | None = None  # the time of the frame being handled
        self.start_drifts = drifts(len(devices), drift_ppm, seed)  # (control command clear: back to these)
        for i, (dev, drift) in enumerate(zip(devices, self.start_drifts, strict=True)):
            esc = Esc(
                dev,
                clock=clock,
                watchdog_ms=watchdog_ms,
                boot_offset_ns=1_000_000_000 + 7_919_000 * i,
                drift_ppm=drift,
                frame_clock=self._frame_time,
            )
            esc.on_change = self._on_change
            self.slaves.append(esc)
        self.faults = Faults()
        self.break_at: int | None = None
        self.active: list[Esc] = []
        self.last_delay_ns = 0
        self.last_logical = False  # the last frame handled carried process data
        self._addr: dict[int, list[Esc]] = {}
        self._lmap: list[Esc] = []
        self._plans: dict[tuple[int, int, int], list[tuple]] = {}
        self._dirty_addr = True
        self._dirty_map = True
        self._next_poll = 0
        self._eeprom_busy: list[Esc] = []  # slaves whose EEPROM is armed or busy (control: eeprom_busy)
        self._touched: list[Esc] = []
        self.reset_counters()
        self._apply_topology()
        self._handlers = {
            NOP: self._nop,
            APRD: self._ap,
            APWR: self._ap,
            APRW: self._ap,
            FPRD: self._fp,
            FPWR: self._fp,
            FPRW: self._fp,
            BRD: self._broadcast,
            BWR: self._broadcast,
            BRW: self._broadcast,
            LRD: self._logical,
            LWR: self._logical,
            LRW: self._logical,
            ARMW: self._rmw,
            FRMW: self._rmw,
        }

    # ------------------------------------------------------------------ bookkeeping
    def reset_counters(self) -> None:
        self.counters = {
            "frames": 0,
            "replied": 0,
            "dropped": 0,
            "delayed": 0,
            "ignored": 0,
            "wkc_corrupted": 0,
            "watchdog_trips": 0,
            "datagrams": 0,
            "stalls_discounted": 0,
            **{_late_key(us): 0 for us in LATE_REPLY_US},
        }
        self.command_counts = [0] * 16

    def _on_change(self, what: str) -> None:
        if what == "address":
            self._dirty_addr = True
        else:
            self._dirty_map = True

    def _apply_topology(self) -> None:
        n = len(self.slaves) if self.break_at is None else self.break_at
        self.active = self.slaves[:n]
        for i, esc in enumerate(self.slaves):
            esc.set_topology(i, max(0, n - 1 - i) if i < n else 0)
        self._dirty_addr = True
        self._dirty_map = True

    def _compile(self) -> None:
        lmap = []
        for esc in self.active:
            esc.compile_fmmus()
            if esc.lwrites or esc.lreads:
                lmap.append(esc)
        self._lmap = lmap
        self._plans.clear()
        self._dirty_map = False

    def _addresses(self) -> dict[int, list[Esc]]:
        if self._dirty_addr:
            table: dict[int, list[Esc]] = {}
            for esc in self.active:
                table.setdefault(esc.station, []).append(esc)
                if esc.alias_enabled and esc.alias and esc.alias != esc.station:
                    table.setdefault(esc.alias, []).append(esc)
            self._addr = table
            self._dirty_addr = False
        return self._addr

    # ------------------------------------------------------------------ frames
    def _frame_time(self) -> int:
        now = self._frame_now
        return self.clock() if now is None else now

    def handle_frame(self, frame: bytes) -> bytes | None:
        """Process one Ethernet frame; the reply (same length) or None if it is lost."""
        self._frame_now = now = self.clock()
        try:
            return self._handle_frame(frame, now)
        finally:
            self._frame_now = None

    def _handle_frame(self, frame: bytes, now: int) -> bytes | None:
        c = self.counters
        c["frames"] += 1
        self.last_delay_ns = 0
        self.last_logical = False
        if now >= self._next_poll:
            self.poll(now)
        if self._eeprom_busy:
            self._eeprom_busy = [esc for esc in self._eeprom_busy if esc.eeprom_release(now)]
        if len(frame) < 28 or frame[12:14] != ETHERTYPE:
            c["ignored"] += 1
            return None
        f = self.faults
        drop = False
        if f.drop_next > 0:
            f.drop_next -= 1
            drop = True
        elif f.drop_prob and self.rng.random() < f.drop_prob:
            drop = True
        if drop and not f.drop_after:
            c["dropped"] += 1
            return None
        buf = bytearray(frame)
        head = U16.unpack_from(buf, 14)[0]
        if head >> 12 != 1:
            c["ignored"] += 1
            return None
        end = min(16 + (head & 0x7FF), len(buf))
        pos = 16
        wkc_positions = []
        logical = False
        handlers = self._handlers
        counts = self.command_counts
        while pos + 12 <= end:
            cmd, _idx, adp, ado, ln, _irq = DGRAM.unpack_from(buf, pos)
            n = ln & 0x7FF
            d = pos + 10
            wpos = d + n
            if wpos + 2 > end:
                break  # malformed: leave the rest untouched
            c["datagrams"] += 1
            handler = handlers.get(cmd)
            if handler is not None:
                counts[cmd] += 1
                if cmd >= LRD and cmd <= LRW:
                    logical = True
                wkc = U16.unpack_from(buf, wpos)[0]
                wkc, new_adp = handler(cmd, buf, d, n, adp, ado, wkc, now)
                U16.pack_into(buf, wpos, wkc & 0xFFFF)
                if new_adp != adp:
                    U16.pack_into(buf, pos + 2, new_adp & 0xFFFF)
            wkc_positions.append(wpos)
            if not ln & 0x8000:
                break
            pos = wpos + 2
        self.last_logical = logical  # a process-data frame (LRD/LWR/LRW): its reply's lateness is counted
        touched = self._touched
        if touched:
            for esc in touched:
                esc.touched = False
                esc.pd_cycle(now)
            touched.clear()
        if f.wkc_next > 0 and (logical or f.wkc_all):
            f.wkc_next -= 1
            c["wkc_corrupted"] += 1
            for wpos in wkc_positions:
                w = U16.unpack_from(buf, wpos)[0] + f.wkc_delta
                U16.pack_into(buf, wpos, min(max(w, 0), 0xFFFF))
        if drop:
            c["dropped"] += 1
            return None
        if f.delay_ns and f.delay_count != 0:
            self.last_delay_ns = f.delay_ns
            c["delayed"] += 1
            if f.delay_count > 0:
                f.delay_count -= 1
                if f.delay_count == 0:
                    f.delay_ns = 0
        buf[6] |= 0x02  # the first ESC marks the source MAC as locally administered
        c["replied"] += 1
        return bytes(buf)

    def poll(self, now: int | None = None) -> None:
        """Time-driven work (SM watchdogs); called by handle_frame and by the runner's timer."""
        if now is None:
            now = self.clock()
        for esc in self.slaves:
            if esc.al_state == OP and esc.check_watchdog(now):
                self.counters["watchdog_trips"] += 1
        # the next poll no later than the first watchdog deadline: a slave trips on time, not
        # up to a poll period late (the watchdog process's bound is measured against it)
        deadline = self.next_deadline()
        self._next_poll = now + POLL_NS if deadline is None else min(now + POLL_NS, deadline + 1)

    def note_reply_latency(self, ns: int) -> None:
        """A process-data reply went out ``ns`` after its frame reached this host's socket
        (kernel stamp). Hardware answers in microseconds; a late reply here is this process
        descheduled (a stall of the machine), and a master waiting less than that counted the
        frame lost. (A reply held up after it left, on its way back, is not seen here.)"""
        if ns > LATE_REPLY_US[0] * 1000:
            c = self.counters
            for us in LATE_REPLY_US:
                if ns > us * 1000:
                    c[_late_key(us)] += 1

    def discount_stall(self, ns: int) -> None:
        """The simulator was not run for ``ns`` (the host stalled it, and the master with it):
        the SM watchdogs do not count that time."""
        self.counters["stalls_discounted"] += 1
        for esc in self.slaves:
            if esc.last_output_ns is not None:
                esc.last_output_ns += ns

    def next_deadline(self) -> int | None:
        """Earliest watchdog deadline (ns, clock time) or None."""
        best = None
        for esc in self.slaves:
            t = esc.wd_deadline()
            if t is not None and (best is None or t < best):
                best = t
        return best

    # ------------------------------------------------------------------ commands
    @staticmethod
    def _nop(cmd, buf, d, n, adp, ado, wkc, now):
        return wkc, adp

    @staticmethod
    def _access(esc: Esc, cmd_kind: int, buf: bytearray, d: int, n: int, ado: int, wkc: int) -> int:
        """cmd_kind: 1 read, 2 write, 3 read-write."""
        if cmd_kind == 1:
            data = esc.read(ado, n)
            if data is not None:
                buf[d : d + n] = data
                wkc += 1
        elif cmd_kind == 2:
            if esc.write(ado, bytes(buf[d : d + n])):
                wkc += 1
        else:
            incoming = bytes(buf[d : d + n])
            data = esc.read(ado, n)
            if data is not None:
                buf[d : d + n] = data
                wkc += 1
            if esc.write(ado, incoming):
                wkc += 2
        return wkc

    def _ap(self, cmd, buf, d, n, adp, ado, wkc, now):
        active = self.active
        target = (-adp) & 0xFFFF
        if target < len(active):
            wkc = self._access(active[target], cmd - APRD + 1, buf, d, n, ado, wkc)
        return wkc, (adp + len(active)) & 0xFFFF

    def _fp(self, cmd, buf, d, n, adp, ado, wkc, now):
        for esc in self._addresses().get(adp, ()):
            wkc = self._access(esc, cmd - FPRD + 1, buf, d, n, ado, wkc)
        return wkc, adp

    def _broadcast(self, cmd, buf, d, n, adp, ado, wkc, now):
        active = self.active
        if cmd == BWR:
            data = bytes(buf[d : d + n])
            for esc in active:
                if esc.write(ado, data):
                    wkc += 1
        else:
            acc = int.from_bytes(buf[d : d + n], "little")
            incoming = bytes(buf[d : d + n])
            for esc in active:
                data = esc.read(ado, n)
                if data is not None:
                    acc |= int.from_bytes(data, "little")
                    wkc += 1
                if cmd == BRW:
                    if esc.write(ado, incoming):
                        wkc += 2
                    incoming = acc.to_bytes(n, "little")
            buf[d : d + n] = acc.to_bytes(n, "little")
        return wkc, (adp + len(active)) & 0xFFFF

    def _rmw(self, cmd, buf, d, n, adp, ado, wkc, now):
        active = self.active
        if cmd == ARMW:
            target = (-adp) & 0xFFFF
            readers = {id(active[target])} if target < len(active) else set()
            new_adp = (adp + len(active)) & 0xFFFF
        else:
            readers = {id(e) for e in self._addresses().get(adp, ())}
            new_adp = adp
        if ado == 0x0910 and n == 8:
            # the DC drift compensation datagram: the reference clock reads its system time
            # (as the frame passes it), the slaves after it take that time into their loops
            reference = None
            for esc in active:
                if id(esc) in readers:
                    reference = esc
                    if esc.has_dc:
                        U64.pack_into(buf, d, esc.system_time(now + HOP_NS * esc.position))
                else:
                    esc.system_time_written(now, U64.unpack_from(buf, d)[0])
                wkc += 1
            if reference is not None and reference.has_dc:
                self.dc_trace.sample(now, reference, active)
            return wkc, new_adp
        for esc in active:
            if id(esc) in readers:
                data = esc.read(ado, n)
                if data is not None:
                    buf[d : d + n] = data
                    wkc += 1
            elif esc.write(ado, bytes(buf[d : d + n])):
                wkc += 1
        return wkc, new_adp

    def _plan(self, cmd: int, lo: int, n: int) -> list[tuple]:
        """Precomputed work for one logical datagram shape (command, address, length):
        per slave hit, the byte copies to do, the working-counter increment, and the FMMUs that
        need the bit-granular or mailbox path. Valid until an FMMU, SM or AL state changes."""
        hi = lo + n
        do_w = cmd != LRD
        do_r = cmd != LWR
        wkc_w = 2 if cmd == LRW else 1
        plan = []
        for esc in self._lmap:
            wops: list[tuple[int, int, int, int, bool]] = []
            rops: list[tuple[int, int, int, int]] = []
            special: list[tuple[tuple, bool]] = []
            add = 0
            hit_w = hit_r = False
            for entries, write in ((esc.lwrites, True), (esc.lreads, False)):
                if (write and not do_w) or (not write and not do_r):
                    continue
                for e in entries:
                    ls, le, ps, sm_last, spec = e
                    if not (ls < hi and le > lo):
                        continue
                    if spec is not None:
                        if spec[0]:  # mailbox area: the access may be refused, decided per frame
                            special.append((e, write))
                            continue
                        # bit-granular: a hit only if the bit ranges overlap
                        if max(spec[1], lo * 8) > min(spec[2], hi * 8 - 1):
                            continue
                        special.append((e, write))
                    else:
                        a = max(ls, lo)
                        b = min(le, hi)
                        p = ps + a - ls
                        if write:
                            wops.append((p, p + b - a, a - lo, b - lo, p <= sm_last < p + b - a))
                        else:
                            rops.append((p, p + b - a, a - lo, b - lo))
                    if write:
                        hit_w = True
                    else:
                        hit_r = True
            if any(entry[4][0] for entry, _write in special):
                add = 0  # a mailbox area may refuse the access: computed per frame
                dynamic = True
            else:
                add = (wkc_w if hit_w else 0) + (1 if hit_r else 0)
                dynamic = False
            if wops or rops or special:
                plan.append((esc, esc.mem, tuple(wops), tuple(rops), add, tuple(special), dynamic))
        return plan

    def _logical(self, cmd, buf, d, n, adp, ado, wkc, now):
        if self._dirty_map:
            self._compile()
        lo = adp | (ado << 16)
        key = (cmd, lo, n)
        plan = self._plans.get(key)
        if plan is None:
            if len(self._plans) > 64:
                self._plans.clear()
            plan = self._plans[key] = self._plan(cmd, lo, n)
        touched = self._touched
        for esc, mem, wops, rops, add, special, dynamic in plan:
            for p, q, fa, fb, done in wops:
                mem[p:q] = buf[d + fa : d + fb]
                if done:
                    esc.outputs_written(now)
            for p, q, fa, fb in rops:
                buf[d + fa : d + fb] = mem[p:q]
            if special:
                if dynamic:
                    hw = hr = False
                    for e, write in special:
                        if esc.logical_special(e, write, buf, d, lo, n, now):
                            if write:
                                hw = True
                            else:
                                hr = True
                    hw = hw or bool(wops)
                    hr = hr or bool(rops)
                    add = ((2 if cmd == LRW else 1) if hw else 0) + (1 if hr else 0)
                else:
                    for e, write in special:
                        esc.logical_special(e, write, buf, d, lo, n, now)
            wkc += add
            if not esc.touched:
                esc.touched = True
                touched.append(esc)
        return wkc, adp

    # ------------------------------------------------------------------ fault injection
    def slave(self, k: int) -> Esc:
        if not 0 <= k < len(self.slaves):
            raise ValueError(f"no slave {k} (0..{len(self.slaves) - 1})")
        return self.slaves[k]

    def break_before(self, k: int | None) -> None:
        """Cable break in front of slave k: slave k and all after it stop answering (None:
        repaired). Frames come back from the last reachable slave."""
        if k is not None and not 0 <= k <= len(self.slaves):
            raise ValueError(f"break position {k} out of range 0..{len(self.slaves)}")
        self.break_at = k
        self._apply_topology()

    def al_error(self, k: int, code: int) -> None:
        self.slave(k).al_fault(code, self.clock())

    def drive_fault(self, k: int, code: int) -> None:
        self.slave(k).inject_drive_fault(code)

    def eeprom_busy(self, k: int, ms: float) -> None:
        """Slave k's next EEPROM read leaves its EEPROM busy for ``ms``."""
        esc = self.slave(k)
        esc.eeprom_busy_ns = int(ms * 1e6)
        self._eeprom_busy.append(esc)

    def eeprom_busy_off(self) -> None:
        for esc in self._eeprom_busy:
            esc.eeprom_busy_ns = 0
            esc.eeprom_release(esc.eeprom_busy_until or 0)
        self._eeprom_busy = []

    def power_cycle(self, k: int) -> None:
        esc = self.slave(k)
        esc.power_on()
        self._apply_topology()

    def status(self) -> dict:
        return {
            "counters": dict(self.counters),
            "commands": {COMMANDS[i]: n for i, n in enumerate(self.command_counts[:15]) if n},
            "faults": self.faults.as_dict(),
            "break_at": self.break_at,
            "slaves": [esc.summary() for esc in self.slaves],
        }

    def states(self) -> list[int]:
        return [esc.al_state | (0x10 if esc.al_error else 0) for esc in self.slaves]


__all__ = ["COMMANDS", "MASK64", "OP", "SAFEOP", "Faults", "Segment"]
