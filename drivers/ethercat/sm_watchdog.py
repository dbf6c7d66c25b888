"""The slaves' process-data (SM) watchdog: a time in register units, programmed before OP and
read back after it.

An ESC counts the watchdog in units of its divider: register 0x0400 = d gives units of
(d + 2) x 40 ns (d = 2498, the ESC's power-on value, gives 100 µs; d = 0 is legal and gives
80 ns); register 0x0420 holds the time in those units, 16 bits. The watchdog watches the
SyncManagers whose control register has bit 6 set (the output SM). A slave whose outputs are
not written for that long leaves OP by itself (SAFEOP + AL status 0x001B) and its drive goes
to the state of its abort option (0x6007): the drives stop even when this process is frozen,
with no frame from anyone.

A time the slave's divider cannot hold (more than 0xFFFF units, or a unit so coarse that the
time is off by more than half of 100 µs) makes the bus program the divider to 2498, as
TwinCAT does from a device's ESI. That divider is also the PDI watchdog's (0x0410), whose time
scales with it; it is the slave's own application watchdog, the master has no other use for it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

DIVIDER, PD_TIME, SM_COUNT, SM_BASE = 0x0400, 0x0420, 0x0005, 0x0800
DEFAULT_DIVIDER = 2498  # 100 µs units: the ESC's power-on value
MAX_UNITS = 0xFFFF
SM_WATCHDOG_ENABLE = 0x40  # bit 6 of a SyncManager's control register
_TOLERANCE_NS = (DEFAULT_DIVIDER + 2) * 40 // 2 + 1  # half a default unit (+1 ns of float error)

Read = Callable[[int, int], bytes]
Write = Callable[[int, bytes], None]


def unit_ns(divider: int) -> int:
    """One watchdog unit at this divider register value."""
    return (divider + 2) * 40


def max_ms(divider: int = DEFAULT_DIVIDER) -> float:
    """The longest time 0x0420 holds at this divider (6553.5 ms at the default)."""
    return MAX_UNITS * unit_ns(divider) / 1e6


def units_for(ms: float, divider: int) -> int | None:
    """The 0x0420 value for ``ms`` at this divider, or None when it does not fit (out of
    1..0xFFFF units, or off by more than half of 100 µs)."""
    unit = unit_ns(divider)
    units = round(ms * 1e6 / unit)
    if not 1 <= units <= MAX_UNITS or abs(units * unit - ms * 1e6) > _TOLERANCE_NS:
        return None
    return units


@dataclass(frozen=True)
class Setting:
    """What a slave's watchdog registers hold."""

    divider: int  # 0x0400
    units: int  # 0x0420
    output_sms: tuple[tuple[int, int], ...]  # (SM number, control) of each active output SM

    @property
    def ms(self) -> float:
        return self.units * unit_ns(self.divider) / 1e6

    @property
    def watched(self) -> bool:
        """An output SM is there and every one has its watchdog enabled."""
        return bool(self.output_sms) and all(ctrl & SM_WATCHDOG_ENABLE for _, ctrl in self.output_sms)

    def describe(self) -> str:
        sms = ", ".join(
            f"SM{n} control 0x{ctrl:02X} (watchdog {'on' if ctrl & SM_WATCHDOG_ENABLE else 'off'})"
            for n, ctrl in self.output_sms
        )
        return f"divider 0x0400 = {self.divider}, time 0x0420 = {self.units} units ({self.ms:g} ms), " + (
            sms or "no active output SyncManager"
        )


def program(read: Read, write: Write, ms: float, where: str) -> Setting:
    """Write ``ms`` to a slave (in SAFEOP, before OP): 0x0420 in units of its divider, the
    divider set to 2498 first when the slave's cannot hold ``ms``. Each register is read back
    at once; :class:`ValueError` names the slave and what it kept."""
    divider = _u16(read(DIVIDER, 2))
    units = units_for(ms, divider)
    if units is None:
        write(DIVIDER, struct.pack("<H", DEFAULT_DIVIDER))
        kept = _u16(read(DIVIDER, 2))
        units = units_for(ms, kept)
        if units is None:
            raise ValueError(
                f"{where}: its watchdog divider 0x0400 = {divider} ({unit_ns(divider)} ns units, "
                f"at most {max_ms(divider):g} ms) cannot hold sm_watchdog_ms = {ms:g}, and it kept "
                f"{kept} when {DEFAULT_DIVIDER} (100 µs units) was written"
            )
        divider = kept
    write(PD_TIME, struct.pack("<H", units))
    setting = read_setting(read)
    if setting.units != units:
        raise ValueError(f"{where}: wrote {units} units ({ms:g} ms) to 0x0420, read back {setting.describe()}")
    return setting


def read_setting(read: Read) -> Setting:
    """The slave's divider, watchdog time and output SyncManagers, read now."""
    divider = _u16(read(DIVIDER, 2))
    units = _u16(read(PD_TIME, 2))
    count = min(read(SM_COUNT, 1)[0], 16)
    regs = read(SM_BASE, 8 * count) if count else b""
    outputs = []
    for n in range(len(regs) // 8):
        _start, length, ctrl, _status, activate, _pdi = struct.unpack_from("<HHBBBB", regs, 8 * n)
        # active, buffered (bits 0-1 = 00), written by the master (bits 2-3 = 01): process outputs
        if activate & 1 and length and ctrl & 0x03 == 0x00 and ctrl & 0x0C == 0x04:
            outputs.append((n, ctrl))
    return Setting(divider, units, tuple(outputs))


def check(setting: Setting, written: Setting, where: str) -> str | None:
    """Why a slave read back after OP does not watch its outputs as ``written``, or None."""
    if (setting.divider, setting.units) == (written.divider, written.units) and setting.watched:
        return None
    return (
        f"{where}: its SM watchdog is not armed for {written.ms:g} ms (divider {written.divider}, "
        f"{written.units} units written); read back after OP: {setting.describe()}"
    )


def _u16(data: bytes) -> int:
    if len(data) < 2:
        raise ValueError(f"a 2-byte register came back with {len(data)} byte(s)")
    return struct.unpack_from("<H", data)[0]
