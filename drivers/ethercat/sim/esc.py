"""One simulated EtherCAT slave controller (ESC): registers, SII interface, AL state machine,
SyncManagers, FMMUs, distributed-clock registers and the process-data watchdog.

Memory is one ``bytearray``: registers at 0x0000-0x0FFF, process RAM from 0x1000 (8 KiB).
Register writes go through a write mask (read-only bits stay) and then through hooks that give
the write its effect (AL control, EEPROM command, SM/FMMU configuration, DC latch, ...).
Register numbers and bit meanings follow the ESC datasheets / ETG.1000.4; values the simulator
chooses are marked as such.

Logical (LRD/LWR/LRW) access does not come through :meth:`Esc.read`/:meth:`Esc.write`: the
segment uses the FMMU tables compiled here (:attr:`Esc.lwrites`, :attr:`Esc.lreads`) for
speed, and calls back into the ESC only for bit-granular FMMUs, mailbox areas and the end of an
output SyncManager buffer.
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Callable
from typing import Any

from .coe import CoeServer
from .dc import DcClock
from .devices import Device, PdoConfigError
from .sii import build_sii

MEM_SIZE = 0x3000
REG_END = 0x1000

INIT, PREOP, BOOT, SAFEOP, OP = 1, 2, 3, 4, 8
STATE_NAMES = {INIT: "INIT", PREOP: "PREOP", BOOT: "BOOT", SAFEOP: "SAFEOP", OP: "OP"}

# AL status codes
AL_OK = 0x0000
AL_UNSPECIFIED = 0x0001
AL_INVALID_TRANSITION = 0x0011
AL_UNKNOWN_STATE = 0x0012
AL_BOOT_NOT_SUPPORTED = 0x0013
AL_INVALID_MBX_BOOT = 0x0015
AL_INVALID_MBX = 0x0016
AL_INVALID_SM = 0x0017
AL_SM_WATCHDOG = 0x001B
AL_INVALID_OUTPUTS = 0x001D
AL_INVALID_INPUTS = 0x001E

_VALID = {
    (INIT, PREOP),
    (INIT, BOOT),
    (PREOP, SAFEOP),
    (SAFEOP, OP),
    (OP, SAFEOP),
    (OP, PREOP),
    (OP, INIT),
    (SAFEOP, PREOP),
    (SAFEOP, INIT),
    (PREOP, INIT),
    (BOOT, INIT),
}

ESC_TYPE = 0x11  # an ET1100-like ESC (simulator's choice)
FEATURES = 0x000C  # DC supported, 64-bit DC; bit 0 = 0: FMMUs are bit oriented
FEATURES_DC = 0x000C
EEPROM_BUSY = 0x8000  # bit 15 of the EEPROM control/status register (0x0502)
DC_START, DC_END = 0x0900, 0x0A00  # the distributed clock's registers (absent without DC)
PORT_DESCRIPTOR = 0x0F  # ports 0 and 1: MII; ports 2 and 3: not implemented
WD_DIVIDER = 2498  # 100 us watchdog units
WD_START, WD_END = 0x0400, 0x0444  # the watchdog unit's registers (absent without one)
SM_START, SM_END = 0x0800, 0x0880  # 16 SyncManagers of 8 bytes
SM_WD_TRIGGER = 0x40  # bit 6 of an SM control register: its writes trigger the SM watchdog
HOP_NS = 400  # simulated forwarding delay per slave and direction
MASK64 = (1 << 64) - 1

U16 = struct.Struct("<H")
U32 = struct.Struct("<I")
U64 = struct.Struct("<Q")
FMMU = struct.Struct("<IHBBHBBB")
SM = struct.Struct("<HHBBBB")


def _write_mask() -> bytes:
    m = bytearray(b"\xff" * REG_END)

    def ro(a: int, b: int) -> None:
        m[a:b] = bytes(b - a)

    ro(0x0000, 0x0010)  # identification
    ro(0x0012, 0x0014)  # station alias (from SII, PDI writable only)
    ro(0x0110, 0x0112)  # DL status
    ro(0x0130, 0x0140)  # AL status, AL status code
    ro(0x0140, 0x0200)  # PDI control and configuration
    ro(0x0210, 0x0224)  # event requests
    ro(0x0440, 0x0442)  # watchdog status
    m[0x0501] = 0x00  # PDI EEPROM access state
    m[0x0502] = 0x01  # EEPROM control: write enable only
    m[0x0503] = 0x07  # command bits
    for n in range(16):
        m[0x0805 + 8 * n] = 0x00  # SM status
        m[0x0807 + 8 * n] = 0x00  # SM PDI control
    ro(0x0900, 0x0920)  # receive times (a write latches), system time, receive time of the PU
    ro(0x092C, 0x0930)  # system time difference
    ro(0x098E, 0x0990)  # SYNC status
    ro(0x0998, 0x09A0)  # next SYNC1 pulse
    ro(0x09B0, 0x0A00)  # latch unit status and times
    ro(0x0E00, 0x0F00)  # power-on values / product id
    return bytes(m)


WMASK = _write_mask()


class Esc:
    """A slave: an ESC with its device behind the PDI."""

    def __init__(
        self,
        device: Device,
        *,
        clock: Callable[[], int],
        watchdog_ms: float = 100.0,
        boot_offset_ns: int = 0,
        drift_ppm: float = 0.0,
        frame_clock: Callable[[], int] | None = None,
    ) -> None:
        self.device = device
        self.clock = clock
        #: the distributed clock's time source: the time of the frame being handled (as the
        #: frame passes every slave within microseconds on hardware, not as this process walks
        #: them), else the clock
        self.dc_clock = frame_clock or clock
        self.watchdog_ms = watchdog_ms
        self.boot_offset_ns = boot_offset_ns
        #: how much faster this slave's crystal runs than the host's clock (kept over power cycles)
        self.drift_ppm = drift_ppm
        #: False: the time control loop compares the propagated time but corrects nothing
        self.dc_compensation = True
        self.sii_original = build_sii(device.sii_description())
        self.sii = bytearray(self.sii_original)
        mbx = device.mailbox
        self.coe = CoeServer(device.od, mbx[1], mbx[3]) if device.od is not None and mbx else None
        if device.od is not None:
            device.od.state_getter = lambda: self.al_state
        self.position = 0  # in the active segment (set by the segment)
        self.downstream = 0  # active slaves after this one
        self.on_change: Callable[[str], None] = lambda what: None
        self.stats = {
            "eeprom_reads": 0,
            "eeprom_writes": 0,
            "mailbox_in": 0,
            "mailbox_out": 0,
            "wd_trips": 0,
            "al_errors": 0,
            "pd_cycles": 0,
        }
        #: False: an ESC without a distributed clock (its features say so, its DC registers
        #: read 0 and ignore writes); set through the control command ``dc``
        self.has_dc = True
        #: SAFEOP -> OP takes this long (a slave whose application starts slowly, e.g. a drive
        #: that checks its motor first); set through the control command ``op_delay``
        self.op_delay_ns = 0
        #: the watchdog divider at power-on (0x0400; 2498: 100 us units); whether the ESC has
        #: an SM watchdog at all (False: 0x0400-0x0443 read 0 and ignore writes, as in an ESC
        #: configured without one); whether its SyncManagers take the watchdog trigger bit
        #: (False: bit 6 of every SM control register reads 0, the time is kept but never
        #: runs); set through the control command ``watchdog``
        self.wd_divider_power_on = WD_DIVIDER
        self.wd_implemented = True
        self.wd_sm_trigger = True
        self.power_on()

    # ================================================================ power-on reset
    def power_on(self) -> None:
        mem = self.mem = bytearray(MEM_SIZE)
        mem[0] = ESC_TYPE
        mem[1] = 0x02
        U16.pack_into(mem, 2, 0x0001)
        mem[4] = 8  # FMMUs
        mem[5] = 8  # SyncManagers
        mem[6] = (MEM_SIZE - REG_END) // 1024  # process RAM in KiB
        mem[7] = PORT_DESCRIPTOR
        U16.pack_into(mem, 0x0008, FEATURES if self.has_dc else FEATURES & ~FEATURES_DC)
        self.alias = U16.unpack_from(self.sii, 8)[0]
        U16.pack_into(mem, 0x0012, self.alias)
        mem[0x0140:0x0142] = self.sii[0:2]
        mem[0x0150:0x0152] = self.sii[2:4]
        if self.wd_implemented:
            div = self.wd_divider_power_on
            U16.pack_into(mem, 0x0400, div)
            U16.pack_into(mem, 0x0410, 1000)
            U16.pack_into(mem, 0x0420, max(0, min(0xFFFF, round(self.watchdog_ms * 1e6 / ((div + 2) * 40)))))
            U16.pack_into(mem, 0x0440, 1)
        U16.pack_into(mem, 0x0502, 0x0040)  # 8-byte reads supported
        #: armed by the control command ``eeprom_busy``: the next read leaves the EEPROM busy
        #: this long (as a slow or stalled EEPROM would), and the master's wait times out
        self.eeprom_busy_ns = 0
        self.eeprom_busy_until: int | None = None
        if self.has_dc:
            U16.pack_into(mem, 0x0930, 0x1000)
            mem[0x0934] = 0x04
        self.station = 0
        self.alias_enabled = False
        self.al_state = INIT
        self.al_error = False
        self.al_code = 0
        self.dc = DcClock(self.dc_clock(), self.boot_offset_ns, self.drift_ppm)
        self.dc.compensating = self.dc_compensation
        self.sync0_start = 0
        self._set_al_status()
        # mailbox
        self.mbx_rx: tuple[int, int, int] | None = None  # (start, end, sm index), master -> slave
        self.mbx_tx: tuple[int, int, int] | None = None  # slave -> master
        self.mbx_in_full = False
        self.mbx_out_full = False
        self.mbx_queue: deque[bytes] = deque()
        self.mbx_last: bytes | None = None
        self._mbx_pending: bytes | None = None
        self._repeat_toggle = 0
        if self.coe is not None:
            self.coe.reset()
        # process data
        self.pd_out: tuple[int, int] | None = None  # SM2 buffer (start, end) when usable
        self.lwrites: list[tuple] = []
        self.lreads: list[tuple] = []
        self.last_output_ns: int | None = None
        self.outputs_fresh = False
        self.op_pending = False
        self.op_due: int | None = None  # with op_delay_ns: OP not before this (clock time)
        self.touched = False
        self.wd_ns = 0
        self._wd_enabled = False
        self.last_trip: dict[str, int] | None = None
        self._watchdog_params()
        self.sii[:] = self.sii_original
        self.device.reset_od()
        self.device.power_on()
        self._sm_changed()

    # ================================================================ helpers
    def local_time(self, now: int) -> int:
        return self.dc.local(now)

    def system_time(self, now: int) -> int:
        return self.dc.system(now)

    def system_time_written(self, now: int, value: int, bits: int = 64) -> None:
        """The system time arrived (ARMW/FRMW of the reference clock's, or a write): one step
        of the time control loop, at this slave's place in the line."""
        if self.has_dc:
            diff = self.dc.received(now + HOP_NS * self.position, value, bits)
            U32.pack_into(self.mem, 0x092C, diff)

    def _set_al_status(self) -> None:
        U16.pack_into(self.mem, 0x0130, self.al_state | (0x10 if self.al_error else 0))
        U16.pack_into(self.mem, 0x0134, self.al_code)

    def set_topology(self, position: int, downstream: int) -> None:
        """Place the slave in the (possibly broken) line: DL status shows which ports are open."""
        self.position = position
        self.downstream = downstream
        if downstream:
            dl = 0x0031 | (0b01_01_10_10 << 8)  # port 0 and 1: link, open, communication
        else:
            dl = 0x0011 | (0b01_01_01_10 << 8)  # port 1 closed (loop), end of the line
        U16.pack_into(self.mem, 0x0110, dl)

    # ================================================================ physical access
    def read(self, ado: int, n: int) -> bytes | None:
        """Read n bytes at ado (FPRD/APRD/BRD...). None: access refused (no working counter)."""
        end = ado + n
        if ado < REG_END:
            if end > REG_END:
                a = self.read(ado, REG_END - ado)
                b = self.read(REG_END, end - REG_END)
                return None if a is None or b is None else a + b
            if ado < 0x0918 and end > 0x0910 and self.has_dc:
                U64.pack_into(self.mem, 0x0910, self.system_time(self.dc_clock() + HOP_NS * self.position))
            if ado < 0x0998 and end > 0x0990:
                self._refresh_next_sync0()
            return bytes(self.mem[ado:end])
        tx = self.mbx_tx
        if tx is not None and ado < tx[1] and end > tx[0]:
            if not self.mbx_out_full:
                return None
            data = bytes(self.mem[ado:end])
            if ado < tx[1] <= end:
                self._mbx_out_read_done()
            return data
        if end > MEM_SIZE:
            return bytes(self.mem[ado:MEM_SIZE]) + bytes(end - max(ado, MEM_SIZE))
        return bytes(self.mem[ado:end])

    def write(self, ado: int, data: bytes) -> bool:
        """Write (FPWR/APWR/BWR...). False: refused (no working counter)."""
        n = len(data)
        end = ado + n
        if ado < REG_END:
            if end > REG_END:
                k = REG_END - ado
                a = self.write(ado, data[:k])
                b = self.write(REG_END, data[k:])
                return a or b
            self._write_regs(ado, data)
            if ado <= 0x0910 and end >= 0x0914:  # a write of the system time: the loop compares it
                k = 0x0910 - ado
                wide = end >= 0x0918
                self.system_time_written(
                    self.dc_clock(), int.from_bytes(data[k : k + (8 if wide else 4)], "little"), 64 if wide else 32
                )
            return True
        rx = self.mbx_rx
        if rx is not None and ado < rx[1] and end > rx[0]:
            if self.mbx_in_full:
                return False
            self.mem[ado:end] = data
            if ado < rx[1] <= end:
                self._mailbox_received()
            return True
        tx = self.mbx_tx
        if tx is not None and ado < tx[1] and end > tx[0]:
            return False  # the send mailbox is written by the slave only
        if end > MEM_SIZE:
            data = data[: max(0, MEM_SIZE - ado)]
            end = ado + len(data)
        self.mem[ado:end] = data
        out = self.pd_out
        if out is not None and ado < out[1] <= end:
            self.outputs_written(self.clock())
        return True

    def _write_regs(self, ado: int, data: bytes) -> None:
        mem = self.mem
        end = ado + len(data)
        for absent, lo_reg, hi_reg in (
            (not self.has_dc, DC_START, DC_END),
            (not self.wd_implemented, WD_START, WD_END),
        ):
            if absent and ado < hi_reg and end > lo_reg:  # no such unit: only the rest is written
                for lo, hi in ((ado, min(end, lo_reg)), (max(ado, hi_reg), end)):
                    if lo < hi:
                        self._write_regs(lo, data[lo - ado : hi - ado])
                return
        mask = WMASK[ado:end]
        if mask.count(0xFF) == len(mask):
            mem[ado:end] = data
        else:
            for i, m in enumerate(mask):
                if m:
                    a = ado + i
                    mem[a] = (mem[a] & ~m) | (data[i] & m)
        if not self.wd_sm_trigger and ado < SM_END and end > SM_START:
            for n in range(16):
                mem[SM_START + 4 + 8 * n] &= ~SM_WD_TRIGGER & 0xFF
        for lo, hi, hook in _HOOKS:
            if lo < end and hi > ado:
                hook(self, ado, end)

    # ================================================================ register hooks
    def _h_station(self, a: int, b: int) -> None:
        self.station = U16.unpack_from(self.mem, 0x0010)[0]
        self.on_change("address")

    def _h_dl_control(self, a: int, b: int) -> None:
        self.alias_enabled = bool(self.mem[0x0103] & 0x01)
        self.on_change("address")

    def _h_al_control(self, a: int, b: int) -> None:
        self.al_request(U16.unpack_from(self.mem, 0x0120)[0])

    def _h_clear(self, a: int, b: int) -> None:
        for lo, hi in ((0x0300, 0x0314), (0x0442, 0x0444)):
            if lo < b and hi > a:
                s, e = max(lo, a), min(hi, b)
                self.mem[s:e] = bytes(e - s)

    def _h_watchdog(self, a: int, b: int) -> None:
        self._watchdog_params()

    def _watchdog_params(self) -> None:
        div = U16.unpack_from(self.mem, 0x0400)[0]
        units = U16.unpack_from(self.mem, 0x0420)[0]
        self.wd_ns = units * (div + 2) * 40

    def _h_eeprom(self, a: int, b: int) -> None:
        mem = self.mem
        if self.eeprom_busy_until is not None:  # busy: a command written now is not taken
            U16.pack_into(mem, 0x0502, EEPROM_BUSY | 0x0040)
            return
        ctl = U16.unpack_from(mem, 0x0502)[0]
        cmd = (ctl >> 8) & 0x07
        if cmd == 1 and self.eeprom_busy_ns:
            self.eeprom_busy_until = self.clock() + self.eeprom_busy_ns
            self.eeprom_busy_ns = 0
            U16.pack_into(mem, 0x0502, EEPROM_BUSY | 0x0040)
            return
        status = 0x0040
        addr = U32.unpack_from(mem, 0x0504)[0] & 0xFFFF
        if cmd == 1:  # read 8 bytes (4 words)
            chunk = bytes(self.sii[2 * addr : 2 * addr + 8])
            mem[0x0508:0x0510] = chunk + b"\xff" * (8 - len(chunk))
            self.stats["eeprom_reads"] += 1
        elif cmd == 2:
            if ctl & 0x0001:
                need = 2 * addr + 2
                if need > len(self.sii):
                    self.sii += b"\xff" * (need - len(self.sii))
                self.sii[2 * addr : 2 * addr + 2] = mem[0x0508:0x050A]
                self.stats["eeprom_writes"] += 1
            else:
                status |= 0x4000  # write enable error
        elif cmd in (3, 4):  # reload the ESC configuration area
            self.alias = U16.unpack_from(self.sii, 8)[0]
            U16.pack_into(mem, 0x0012, self.alias)
        elif cmd != 0:
            status |= 0x2000  # invalid command
        U16.pack_into(mem, 0x0502, status)

    def eeprom_release(self, now: int) -> bool:
        """End a busy period once its time has come; True while one is armed or lasts."""
        if self.eeprom_busy_until is None:
            return self.eeprom_busy_ns > 0
        if now < self.eeprom_busy_until:
            return True
        self.eeprom_busy_until = None
        U16.pack_into(self.mem, 0x0502, 0x0040)  # the read was never done: the data register is unchanged
        return False

    def _h_fmmu(self, a: int, b: int) -> None:
        self.on_change("fmmu")

    def _h_sm(self, a: int, b: int) -> None:
        # repeat request: bit 1 of the activate register of the send-mailbox SM
        tx = self.mbx_tx
        if tx is not None:
            act_reg = 0x0806 + 8 * tx[2]
            if a <= act_reg < b:
                toggle = (self.mem[act_reg] >> 1) & 1
                if toggle != self._repeat_toggle:
                    self._repeat_toggle = toggle
                    self._mbx_repeat(tx, toggle)
        self._sm_changed()

    def _h_latch(self, a: int, b: int) -> None:
        now = self.dc_clock()
        t0 = self.local_time(now + HOP_NS * self.position)
        mem = self.mem
        U32.pack_into(mem, 0x0900, t0 & 0xFFFFFFFF)
        t1 = t0 + 2 * HOP_NS * self.downstream if self.downstream else 0
        U32.pack_into(mem, 0x0904, t1 & 0xFFFFFFFF)
        U32.pack_into(mem, 0x0908, 0)
        U32.pack_into(mem, 0x090C, 0)
        U64.pack_into(mem, 0x0918, t0 & MASK64)

    def _h_dc_offset(self, a: int, b: int) -> None:
        self.dc.set_offset(self.dc_clock() + HOP_NS * self.position, U64.unpack_from(self.mem, 0x0920)[0])

    def _h_dc_delay(self, a: int, b: int) -> None:
        self.dc.delay = U32.unpack_from(self.mem, 0x0928)[0]

    def _h_dc_loop(self, a: int, b: int) -> None:
        self.dc.depth = self.mem[0x0934]
        if a < 0x0932 and b > 0x0930:  # a write of the speed counter start restarts the loop
            self.dc.set_speed_start(self.dc_clock() + HOP_NS * self.position, U16.unpack_from(self.mem, 0x0930)[0])
            U32.pack_into(self.mem, 0x092C, 0)

    def _h_sync0_start(self, a: int, b: int) -> None:
        self.sync0_start = U64.unpack_from(self.mem, 0x0990)[0]

    def _refresh_next_sync0(self) -> None:
        mem = self.mem
        cycle = U32.unpack_from(mem, 0x09A0)[0]
        start = self.sync0_start
        if mem[0x0981] & 0x03 == 0x03 and cycle:
            now = self.system_time(self.dc_clock() + HOP_NS * self.position)
            if now > start:
                start += -(-(now - start) // cycle) * cycle
        U64.pack_into(mem, 0x0990, start & MASK64)

    # ================================================================ SyncManagers
    def sm(self, n: int) -> tuple[int, int, int, int, int, int]:
        """(start, length, control, status, activate, pdi control) of SM n."""
        return SM.unpack_from(self.mem, 0x0800 + 8 * n)

    def _sm_changed(self) -> None:
        mbx_rx = mbx_tx = None
        for n in range(8):
            start, length, ctrl, _status, act, _pdi = self.sm(n)
            if not act & 1 or not length or ctrl & 0x03 != 0x02:
                continue
            if ctrl & 0x0C == 0x04 and mbx_rx is None:
                mbx_rx = (start, start + length, n)
            elif ctrl & 0x0C == 0x00 and mbx_tx is None:
                mbx_tx = (start, start + length, n)
        if self.device.mailbox is None:
            mbx_rx = mbx_tx = None  # no mailbox behind the PDI
        if mbx_rx != self.mbx_rx or mbx_tx != self.mbx_tx:
            self.mbx_rx, self.mbx_tx = mbx_rx, mbx_tx
            self._mailbox_reset()
        self._pd_sm_update()
        self.on_change("sm")

    def _pd_sm_update(self) -> None:
        """Output SM (SM2) buffer end detection and watchdog enable, for states >= SAFEOP."""
        start, length, ctrl, _s, act, _p = self.sm(2)
        usable = self.al_state in (SAFEOP, OP) and act & 1 and length and ctrl & 0x03 == 0
        self.pd_out = (start, start + length) if usable and ctrl & 0x0C == 0x04 else None
        self._wd_enabled = bool(self.pd_out is not None and ctrl & 0x40)
        for n in range(2, 8):
            pdi = 0x0807 + 8 * n
            _st, ln, c, _s2, a2, _p2 = self.sm(n)
            if a2 & 1 and ln and c & 0x03 == 0:
                self.mem[pdi] = 0 if self.al_state in (SAFEOP, OP) else 1  # PDI deactivated

    def _gate(self, pstart: int, pend: int) -> str:
        """How an FMMU may access [pstart, pend): 'ok', 'deny' or 'slow' (mailbox area)."""
        if pend > MEM_SIZE:
            return "deny"
        result = "ok"
        for n in range(8):
            start, length, ctrl, _st, act, _pdi = self.sm(n)
            if not act & 1 or not length or pstart >= start + length or pend <= start:
                continue
            if ctrl & 0x03 == 0x02:
                return "slow"
            if self.al_state not in (SAFEOP, OP):
                return "deny"
        return result

    # ================================================================ FMMUs
    def compile_fmmus(self) -> None:
        """Build the tables used by logical commands. Entry: (log start, log end, phys start,
        SM2 last byte or -1, special) where special is None (byte copy) or a tuple describing a
        bit-granular or mailbox FMMU handled by :meth:`logical_special`."""
        writes: list[tuple] = []
        reads: list[tuple] = []
        out = self.pd_out
        for n in range(8):
            lstart, llen, lsb, leb, pstart, psb, ftype, act = FMMU.unpack_from(self.mem, 0x0600 + 16 * n)
            if not act & 1 or not llen or not ftype & 0x03:
                continue
            gate = self._gate(pstart, pstart + llen)
            if gate == "deny":
                continue
            lend = lstart + llen
            sm_last = out[1] - 1 if out is not None and pstart <= out[1] - 1 < pstart + llen else -1
            special = None
            if gate == "slow" or lsb or leb != 7 or psb:
                special = (gate == "slow", lstart * 8 + lsb, (lend - 1) * 8 + leb, pstart * 8 + psb)
            entry = (lstart, lend, pstart, sm_last, special)
            if ftype & 0x02:
                writes.append(entry)
            if ftype & 0x01:
                reads.append(entry)
        self.lwrites = writes
        self.lreads = reads

    def logical_special(
        self, entry: tuple, write: bool, buf: bytearray, off: int, laddr: int, dlen: int, now: int
    ) -> bool:
        """Bit-granular or mailbox FMMU access; returns whether the FMMU was hit."""
        slow, l0, l1, p0 = entry[4]
        d0 = laddr * 8
        d1 = (laddr + dlen) * 8 - 1
        a = max(l0, d0)
        b = min(l1, d1)
        if a > b:
            return False
        nb = b - a + 1
        mask = (1 << nb) - 1
        fa = a // 8 - laddr
        fb = b // 8 - laddr
        pa = p0 + (a - l0)
        pb = pa + nb - 1
        mem = self.mem
        if slow:  # whole bytes through the mailbox-aware path
            if write:
                return self.write(pa // 8, bytes(buf[off + fa : off + fb + 1]))
            data = self.read(pa // 8, fb - fa + 1)
            if data is None:
                return False
            buf[off + fa : off + fb + 1] = data
            return True
        if write:
            val = (int.from_bytes(buf[off + fa : off + fb + 1], "little") >> (a % 8)) & mask
            shift = pa % 8
            cur = int.from_bytes(mem[pa // 8 : pb // 8 + 1], "little")
            cur = (cur & ~(mask << shift)) | (val << shift)
            mem[pa // 8 : pb // 8 + 1] = cur.to_bytes(pb // 8 - pa // 8 + 1, "little")
            if entry[3] >= 0 and pa // 8 <= entry[3] <= pb // 8:
                self.outputs_written(now)
        else:
            val = (int.from_bytes(mem[pa // 8 : pb // 8 + 1], "little") >> (pa % 8)) & mask
            shift = a % 8
            cur = int.from_bytes(buf[off + fa : off + fb + 1], "little")
            cur = (cur & ~(mask << shift)) | (val << shift)
            buf[off + fa : off + fb + 1] = cur.to_bytes(fb - fa + 1, "little")
        return True

    # ================================================================ process data
    def outputs_written(self, now: int) -> None:
        """The master completed a write of the output SM buffer."""
        self.last_output_ns = now
        self.outputs_fresh = True
        if not self.mem[0x0440] & 1 and self.wd_implemented:
            self.mem[0x0440] |= 1
        if self.op_pending and (self.op_due is None or now >= self.op_due):
            self._set_state(OP, now)

    def pd_cycle(self, now: int) -> None:
        """After a frame that carried this slave's process data: the device consumes outputs
        (valid only in OP) and produces inputs for the next frame."""
        if self.op_pending and not self.device.out_size and now >= (self.op_due or 0):
            self._set_state(OP, now)  # a slave without outputs, at the end of its op_delay
        st = self.al_state
        if st in (OP, SAFEOP):
            valid = st == OP and self.outputs_fresh
            self.outputs_fresh = False
            self.device.exchange(now, self.mem, valid)
            self.stats["pd_cycles"] += 1
            if self.device._emergencies:
                self._flush_emergencies()

    def check_watchdog(self, now: int) -> bool:
        """SM watchdog: in OP, outputs older than the watchdog time -> SAFEOP + error 0x001B."""
        if (
            self.al_state == OP
            and self._wd_enabled
            and self.wd_ns
            and self.last_output_ns is not None
            and now - self.last_output_ns > self.wd_ns
        ):
            self.mem[0x0440] &= 0xFE
            if self.mem[0x0442] < 0xFF:
                self.mem[0x0442] += 1
            self.stats["wd_trips"] += 1
            # what the slave measured: its last valid outputs, and when it gave up on them
            self.last_trip = {"last_output_ns": self.last_output_ns, "tripped_ns": now}
            self.al_fault(AL_SM_WATCHDOG, now)
            return True
        return False

    def wd_deadline(self) -> int | None:
        if self.al_state == OP and self._wd_enabled and self.wd_ns and self.last_output_ns is not None:
            return self.last_output_ns + self.wd_ns
        return None

    # ================================================================ AL state machine
    def al_request(self, value: int) -> None:
        now = self.clock()
        req = value & 0x0F
        ack = value & 0x10
        if self.al_error and not ack:
            return  # an error must be acknowledged before any other request
        if req == OP and self.op_pending:
            return  # the same request again: the transition under way goes on
        self.op_pending = False
        if ack and self.al_error:
            self.al_error = False
            self.al_code = AL_OK
            self._set_al_status()
        cur = self.al_state
        if req == cur:
            return
        if req not in STATE_NAMES:
            self._al_refuse(AL_UNKNOWN_STATE)
            return
        if (cur, req) not in _VALID:
            self._al_refuse(AL_INVALID_TRANSITION)
            return
        if req == PREOP and cur == INIT:
            code = self._check_mailbox(0x0018)
            if code:
                self._al_refuse(code)
                return
        elif req == BOOT:
            code = self._check_mailbox(0x0014)
            if code:
                self._al_refuse(AL_INVALID_MBX_BOOT)
                return
        elif req == SAFEOP and cur == PREOP:
            code = self._check_process_data()
            if code:
                self._al_refuse(code)
                return
        elif req == OP and self.op_delay_ns:
            self.op_pending = True  # OP once the delay is over (and valid outputs arrived)
            self.op_due = now + self.op_delay_ns
            return
        elif req == OP and self.device.out_size and not self._outputs_recent(now):
            self.op_pending = True  # go to OP once valid outputs arrive
            self.op_due = None
            return
        self._set_state(req, now)

    def _outputs_recent(self, now: int) -> bool:
        if self.last_output_ns is None:
            return False
        return not self.wd_ns or now - self.last_output_ns <= self.wd_ns

    def _al_refuse(self, code: int) -> None:
        self.al_error = True
        self.al_code = code
        self.stats["al_errors"] += 1
        self._set_al_status()

    def al_fault(self, code: int, now: int | None = None) -> None:
        """An error raised by the slave itself (watchdog, injected): SAFEOP (if higher) + error."""
        if now is None:
            now = self.clock()
        self.al_error = True
        self.al_code = code & 0xFFFF
        self.stats["al_errors"] += 1
        if self.al_state == OP:
            self._set_state(SAFEOP, now)
        else:
            self._set_al_status()

    def _set_state(self, new: int, now: int) -> None:
        old = self.al_state
        self.al_state = new
        self.op_pending = False
        self.op_due = None
        if old == OP and new != OP:
            self.device.outputs_lost(now)
        if new in (INIT, BOOT):
            self._mailbox_reset()
        elif new == PREOP and old == INIT and self.coe is not None:
            self.coe.reset()  # a new mailbox session (counters); a message written in INIT stays
        if new == SAFEOP and old == PREOP:
            self.last_output_ns = None
            self.outputs_fresh = False
        if new == OP:
            self.last_output_ns = now
        self._set_al_status()
        self._pd_sm_update()
        self.device.state_changed(old, new, now)
        if new == SAFEOP and old == PREOP:
            self.device.exchange(now, self.mem, False)  # valid inputs from the start of SAFEOP
        if new in (PREOP, SAFEOP, OP) and self._mbx_pending is not None:
            msg, self._mbx_pending = self._mbx_pending, None
            self._mailbox_process(msg)
        self._flush_emergencies()
        self.on_change("al")

    def _check_mailbox(self, word: int) -> int:
        if self.device.mailbox is None:
            return AL_OK
        rx_off, rx_size, tx_off, tx_size = struct.unpack_from("<HHHH", self.sii, 2 * word)
        s0 = self.sm(0)
        s1 = self.sm(1)
        ok0 = s0[0] == rx_off and s0[1] == rx_size and s0[2] & 0x0F == 0x06 and s0[4] & 1
        ok1 = s1[0] == tx_off and s1[1] == tx_size and s1[2] & 0x0F == 0x02 and s1[4] & 1
        return AL_OK if ok0 and ok1 else AL_INVALID_MBX

    def _check_process_data(self) -> int:
        dev = self.device
        try:
            out_size, in_size = dev.compile_pdo()
        except PdoConfigError as exc:
            return AL_INVALID_OUTPUTS if exc.side == "out" else AL_INVALID_INPUTS
        for n, size, addr, direction, code in (
            (2, out_size, dev.out_addr, 0x04, AL_INVALID_OUTPUTS),
            (3, in_size, dev.in_addr, 0x00, AL_INVALID_INPUTS),
        ):
            start, length, ctrl, _st, act, _pdi = self.sm(n)
            enabled = bool(act & 1) and length > 0
            if size == 0:
                if enabled:
                    return code
                continue
            if not enabled or length != size or start != addr or ctrl & 0x0F != direction:
                return code
        return AL_OK

    # ================================================================ mailbox
    def _mailbox_reset(self) -> None:
        self.mbx_in_full = False
        self.mbx_out_full = False
        self.mbx_queue.clear()
        self.mbx_last = None
        self._mbx_pending = None
        if self.coe is not None:
            self.coe.reset()
        for sm in (self.mbx_rx, self.mbx_tx):
            if sm is not None:
                self.mem[0x0805 + 8 * sm[2]] &= ~0x08
        if self.mbx_tx is not None:
            self._repeat_toggle = (self.mem[0x0806 + 8 * self.mbx_tx[2]] >> 1) & 1
            self.mem[0x0807 + 8 * self.mbx_tx[2]] = (self.mem[0x0807 + 8 * self.mbx_tx[2]] & ~0x02) | (
                self._repeat_toggle << 1
            )

    def _mailbox_received(self) -> None:
        rx = self.mbx_rx
        assert rx is not None
        msg = bytes(self.mem[rx[0] : rx[1]])
        self.stats["mailbox_in"] += 1
        if self.al_state in (PREOP, SAFEOP, OP, BOOT):
            self._mailbox_process(msg)
        else:
            self.mbx_in_full = True  # INIT: the application reads it after PREOP is reached
            self.mem[0x0805 + 8 * rx[2]] |= 0x08
            self._mbx_pending = msg

    def _mailbox_process(self, msg: bytes) -> None:
        rx = self.mbx_rx
        self.mbx_in_full = False
        if rx is not None:
            self.mem[0x0805 + 8 * rx[2]] &= ~0x08
        if self.coe is None:
            return
        if self.al_state == BOOT:
            replies = [self.coe.mailbox_error(0x0002)]  # only FoE in BOOT, and FoE is not there
        else:
            replies = self.coe.handle(msg)
        for r in replies:
            if r:
                self.mbx_queue.append(r)
        self._mbx_pump()

    def _mbx_pump(self) -> None:
        tx = self.mbx_tx
        if tx is None or self.mbx_out_full or not self.mbx_queue:
            return
        msg = self.mbx_queue.popleft()
        self._mbx_put(tx, msg)

    def _mbx_put(self, tx: tuple[int, int, int], msg: bytes) -> None:
        size = tx[1] - tx[0]
        self.mem[tx[0] : tx[1]] = msg[:size].ljust(size, b"\0")
        self.mbx_last = msg
        self.mbx_out_full = True
        self.mem[0x0805 + 8 * tx[2]] |= 0x08
        self.stats["mailbox_out"] += 1

    def _mbx_out_read_done(self) -> None:
        tx = self.mbx_tx
        self.mbx_out_full = False
        if tx is not None:
            self.mem[0x0805 + 8 * tx[2]] &= ~0x08
        self._mbx_pump()

    def _mbx_repeat(self, tx: tuple[int, int, int], toggle: int) -> None:
        if self.mbx_last is not None:
            if self.mbx_out_full:
                pass  # the message is still there; the master reads it again
            else:
                self._mbx_put(tx, self.mbx_last)
        pdi = 0x0807 + 8 * tx[2]
        self.mem[pdi] = (self.mem[pdi] & ~0x02) | (toggle << 1)

    def _flush_emergencies(self) -> None:
        ems = self.device.take_emergencies()
        if not ems or self.coe is None or self.al_state not in (PREOP, SAFEOP, OP):
            return
        for code, reg, data in ems:
            self.mbx_queue.append(self.coe.emergency(code, reg, data))
        self._mbx_pump()

    # ================================================================ faults and status
    def inject_drive_fault(self, code: int) -> None:
        inject = getattr(self.device, "inject_fault", None)
        if inject is None:
            raise ValueError(f"slave {self.position} ({self.device.kind}) is not a drive")
        inject(code)

    def summary(self) -> dict[str, Any]:
        return {
            "position": self.position,
            "kind": self.device.kind,
            "name": self.device.name,
            "station": self.station,
            "state": STATE_NAMES.get(self.al_state, str(self.al_state)),
            "error": self.al_error,
            "al_status_code": self.al_code,
            "op_pending": self.op_pending,
            "device": self.device.status(),
            "stats": dict(self.stats),
            "watchdog_ms": self.wd_ns / 1e6,
            "watchdog_divider": U16.unpack_from(self.mem, 0x0400)[0],
            "watchdog_units": U16.unpack_from(self.mem, 0x0420)[0],
            "watchdog_armed": self._wd_enabled and self.wd_ns > 0,
            "watchdog_trip": self.last_trip,
            "coe": dict(self.coe.stats) if self.coe is not None else None,
            "dc": self.has_dc,
            "drift_ppm": self.drift_ppm,
            "dc_compensation": self.dc_compensation,
            "dc_loop": self.dc.summary(),
            "sync0": {"active": self.mem[0x0981] & 0x03 == 0x03, "cycle_ns": U32.unpack_from(self.mem, 0x09A0)[0]},
        }


_HOOKS: list[tuple[int, int, Any]] = [
    (0x0010, 0x0012, Esc._h_station),
    (0x0100, 0x0104, Esc._h_dl_control),
    (0x0120, 0x0122, Esc._h_al_control),
    (0x0300, 0x0314, Esc._h_clear),
    (0x0400, 0x0402, Esc._h_watchdog),
    (0x0420, 0x0422, Esc._h_watchdog),
    (0x0442, 0x0444, Esc._h_clear),
    (0x0502, 0x0504, Esc._h_eeprom),
    (0x0600, 0x0700, Esc._h_fmmu),
    (0x0800, 0x0880, Esc._h_sm),
    (0x0900, 0x0904, Esc._h_latch),
    (0x0920, 0x0928, Esc._h_dc_offset),
    (0x0928, 0x092C, Esc._h_dc_delay),
    (0x0930, 0x0936, Esc._h_dc_loop),
    (0x0990, 0x0998, Esc._h_sync0_start),
]
