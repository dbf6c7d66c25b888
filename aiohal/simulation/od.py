"""The object dictionary of simulated CiA 301 devices: data types, entries, objects, and PDO
image codecs; the EtherCAT slaves' CoE and the CANopen drive nodes use it alike.

An :class:`Entry` holds one value (``entry.value``); device models keep references to the entries
they drive, so a PDO exchange and an SDO access see the same value. A PDO mapping (objects
0x16xx / 0x1Axx plus the assignments 0x1C12 / 0x1C13) is compiled into a :class:`PdoCodec`
that decodes or encodes the whole process image with one ``struct`` call when every entry is
byte aligned, and with integer bit arithmetic otherwise.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

# CiA 301 data type codes: name -> (code, struct char or None, bit size or None for strings)
BOOL = 0x0001
INT8 = 0x0002
INT16 = 0x0003
INT32 = 0x0004
UINT8 = 0x0005
UINT16 = 0x0006
UINT32 = 0x0007
REAL32 = 0x0008
VISIBLE_STRING = 0x0009
OCTET_STRING = 0x000A
REAL64 = 0x0011
INT64 = 0x0015
UINT64 = 0x001B

_FMT = {
    BOOL: ("B", 1),
    INT8: ("b", 8),
    INT16: ("h", 16),
    INT32: ("i", 32),
    INT64: ("q", 64),
    UINT8: ("B", 8),
    UINT16: ("H", 16),
    UINT32: ("I", 32),
    UINT64: ("Q", 64),
    REAL32: ("f", 32),
    REAL64: ("d", 64),
}
_RANGE = {
    BOOL: (0, 1),
    INT8: (-(1 << 7), (1 << 7) - 1),
    INT16: (-(1 << 15), (1 << 15) - 1),
    INT32: (-(1 << 31), (1 << 31) - 1),
    INT64: (-(1 << 63), (1 << 63) - 1),
    UINT8: (0, 0xFF),
    UINT16: (0, 0xFFFF),
    UINT32: (0, 0xFFFFFFFF),
    UINT64: (0, (1 << 64) - 1),
}
SIGNED = {INT8, INT16, INT32, INT64}
FLOATS = {REAL32, REAL64}
STRINGS = {VISIBLE_STRING, OCTET_STRING}

# object codes
VAR = 7
ARRAY = 8
RECORD = 9

# SDO abort codes (ETG.1000.6 / CiA 301)
ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_SUB0_NOT_ZERO = 0x06010003
ABORT_CA_UNSUPPORTED = 0x06010004
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_HIGH = 0x06090031
ABORT_VALUE_LOW = 0x06090032
ABORT_GENERAL = 0x08000000
ABORT_STATE = 0x08000022


class SdoAbort(Exception):
    """Raised by the object dictionary; carries a CoE abort code."""

    def __init__(self, code: int, message: str = "") -> None:
        super().__init__(f"SDO abort 0x{code:08X} {message}".rstrip())
        self.code = code


def dtype_bits(dtype: int) -> int:
    return _FMT[dtype][1]


# access rights
RO = "ro"
RW = "rw"
RWP = "rwp"  # writable in PREOP only (PDO mapping and assignment)
WO = "wo"


class Entry:
    """One sub-index."""

    __slots__ = (
        "access",
        "dtype",
        "high",
        "index",
        "low",
        "mappable",
        "name",
        "on_write",
        "size",
        "sub",
        "value",
    )

    def __init__(
        self,
        index: int,
        sub: int,
        name: str,
        dtype: int,
        value: Any = 0,
        access: str = RO,
        mappable: str = "",
        size: int | None = None,
        on_write: Callable[[Entry, Any], None] | None = None,
        low: float | None = None,
        high: float | None = None,
    ) -> None:
        self.index = index
        self.sub = sub
        self.name = name
        self.dtype = dtype
        self.access = access
        self.mappable = mappable  # "", "rx" (outputs) or "tx" (inputs)
        self.on_write = on_write
        self.low = low
        self.high = high
        self.value: Any  # bytes for a string type, else a number
        if dtype in STRINGS:
            raw = value.encode("latin-1") if isinstance(value, str) else bytes(value)
            self.size = size if size is not None else len(raw)
            self.value = raw
        else:
            self.size = (_FMT[dtype][1] + 7) // 8
            self.value = value

    @property
    def bits(self) -> int:
        return self.size * 8 if self.dtype in STRINGS else _FMT[self.dtype][1]

    def to_bytes(self) -> bytes:
        if self.dtype in STRINGS:
            return bytes(self.value)
        fmt, bits = _FMT[self.dtype]
        v = self.value
        if bits == 1:
            v = 1 if v else 0
        return struct.pack("<" + fmt, v)

    def decode(self, data: bytes) -> Any:
        """Value for raw SDO data, checking length and range (raises SdoAbort)."""
        if self.dtype in STRINGS:
            if len(data) > self.size:
                raise SdoAbort(ABORT_LENGTH, f"{len(data)} bytes for a {self.size}-byte string")
            return bytes(data)
        if len(data) != self.size:
            raise SdoAbort(ABORT_LENGTH, f"{len(data)} bytes for a {self.size}-byte value")
        fmt, _ = _FMT[self.dtype]
        value = struct.unpack("<" + fmt, data)[0]
        if self.dtype == BOOL and value > 1:
            raise SdoAbort(ABORT_VALUE_RANGE)
        if self.low is not None and value < self.low:
            raise SdoAbort(ABORT_VALUE_LOW)
        if self.high is not None and value > self.high:
            raise SdoAbort(ABORT_VALUE_HIGH)
        return value

    def set(self, value: Any) -> None:
        """Set from a device model or the control channel: clamp integers to the type's range."""
        if self.dtype in STRINGS:
            self.value = value.encode("latin-1") if isinstance(value, str) else bytes(value)
        elif self.dtype in FLOATS:
            self.value = float(value)
        else:
            lo, hi = _RANGE[self.dtype]
            self.value = min(max(int(value), lo), hi)


@dataclass
class Obj:
    index: int
    name: str
    code: int  # VAR, ARRAY, RECORD
    entries: dict[int, Entry]

    def sub0_count(self) -> int:
        """Highest sub-index in use (sub 0's value for ARRAY/RECORD)."""
        if self.code == VAR:
            return 0
        return int(self.entries[0].value)

    def max_sub(self) -> int:
        return max(self.entries)


class ObjectDictionary:
    """Objects by index, with the helpers the SDO server and the devices need."""

    def __init__(self) -> None:
        self.objects: dict[int, Obj] = {}
        #: objects the SDO server says do not exist (a slave without them, e.g. one without
        #: 0x1C12/0x1C13 whose PDOs are in its SII only); the device model still uses them
        self.hidden: set[int] = set()
        self.state_getter: Callable[[], int] = lambda: 2  # AL state, set by the ESC

    # ---- building
    def var(
        self, index: int, name: str, dtype: int, value: Any = 0, access: str = RO, mappable: str = "", **kw: Any
    ) -> Entry:
        e = Entry(index, 0, name, dtype, value, access, mappable, **kw)
        self.objects[index] = Obj(index, name, VAR, {0: e})
        return e

    def record(
        self,
        index: int,
        name: str,
        subs: list[tuple[str, int, Any, str]],
        code: int = RECORD,
        mappable: str = "",
        sub0_access: str = RO,
    ) -> list[Entry]:
        """subs: (name, dtype, value, access) for sub 1..n; sub 0 = n (u8)."""
        entries = {0: Entry(index, 0, "Number of entries", UINT8, len(subs), sub0_access)}
        for i, (sname, dtype, value, access) in enumerate(subs, start=1):
            entries[i] = Entry(index, i, sname, dtype, value, access, mappable)
        self.objects[index] = Obj(index, name, code, entries)
        return [entries[i] for i in range(1, len(subs) + 1)]

    def array(
        self,
        index: int,
        name: str,
        dtype: int,
        values: list[Any],
        capacity: int,
        access: str = RO,
        sub0_access: str | None = None,
        **kw: Any,
    ) -> Obj:
        """An ARRAY with room for ``capacity`` entries, ``len(values)`` of them in use."""
        entries = {0: Entry(index, 0, "Number of entries", UINT8, len(values), sub0_access or access, high=capacity)}
        for i in range(1, capacity + 1):
            v = values[i - 1] if i <= len(values) else 0
            entries[i] = Entry(index, i, f"{name} {i}", dtype, v, access, **kw)
        obj = Obj(index, name, ARRAY, entries)
        self.objects[index] = obj
        return obj

    # ---- access
    def visible(self, index: int) -> Obj | None:
        """The object as the SDO server shows it (None: it does not exist)."""
        return None if index in self.hidden else self.objects.get(index)

    def entry(self, index: int, sub: int) -> Entry:
        obj = self.visible(index)
        if obj is None:
            raise SdoAbort(ABORT_NO_OBJECT)
        e = obj.entries.get(sub)
        if e is None:
            raise SdoAbort(ABORT_NO_SUBINDEX)
        return e

    def read(self, index: int, sub: int) -> bytes:
        e = self.entry(index, sub)
        if e.access == WO:
            raise SdoAbort(ABORT_WRITE_ONLY)
        return e.to_bytes()

    def check_writable(self, e: Entry) -> None:
        if e.access == RO:
            raise SdoAbort(ABORT_READ_ONLY)
        if e.access == RWP and self.state_getter() not in (1, 2, 3):
            raise SdoAbort(ABORT_STATE, "writable in PREOP only")

    def write(self, index: int, sub: int, data: bytes) -> None:
        e = self.entry(index, sub)
        self.check_writable(e)
        value = e.decode(data)
        if e.on_write is not None:
            e.on_write(e, value)  # may raise SdoAbort
        e.value = value

    def read_complete(self, index: int, sub: int) -> bytes:
        """Complete access upload starting at sub 0 or 1. Sub 0 (u8) is sent padded to 16 bits."""
        obj = self.visible(index)
        if obj is None:
            raise SdoAbort(ABORT_NO_OBJECT)
        if obj.code == VAR:
            if sub > 0:
                raise SdoAbort(ABORT_NO_SUBINDEX)
            return obj.entries[0].to_bytes()
        if sub > 1:
            raise SdoAbort(ABORT_CA_UNSUPPORTED)
        out = bytearray()
        if sub == 0:
            out += bytes([int(obj.entries[0].value) & 0xFF, 0])
        for i in range(1, obj.sub0_count() + 1):
            e = obj.entries.get(i)
            if e is None:
                continue
            out += e.to_bytes()
        return bytes(out)

    def write_complete(self, index: int, sub: int, data: bytes) -> None:
        """Complete access download starting at sub 0 (sub 0 value padded to 16 bits) or 1."""
        obj = self.visible(index)
        if obj is None:
            raise SdoAbort(ABORT_NO_OBJECT)
        if obj.code == VAR:
            if sub > 0:
                raise SdoAbort(ABORT_NO_SUBINDEX)
            self.write(index, 0, data)
            return
        if sub > 1:
            raise SdoAbort(ABORT_CA_UNSUPPORTED)
        pos = 0
        if sub == 0:
            if len(data) < 2:
                raise SdoAbort(ABORT_LENGTH)
            count = data[0]
            sub0 = obj.entries[0]
            self.check_writable(sub0)
            if sub0.high is not None and count > sub0.high:
                raise SdoAbort(ABORT_VALUE_HIGH)
            pos = 2
        else:
            count = obj.sub0_count()
        staged: list[tuple[Entry, Any]] = []
        for i in range(1, count + 1):
            e = obj.entries.get(i)
            if e is None:
                raise SdoAbort(ABORT_NO_SUBINDEX)
            self.check_writable(e)
            chunk = data[pos : pos + e.size]
            if len(chunk) != e.size:
                raise SdoAbort(ABORT_LENGTH, "complete access data too short")
            staged.append((e, e.decode(chunk)))
            pos += e.size
        if pos != len(data):
            raise SdoAbort(ABORT_LENGTH, "complete access data too long")
        if sub == 0:
            # entries first, then the count (the usual order for mapping objects)
            obj.entries[0].value = 0
        for e, v in staged:
            if e.on_write is not None:
                e.on_write(e, v)
            e.value = v
        if sub == 0:
            sub0 = obj.entries[0]
            if sub0.on_write is not None:
                sub0.on_write(sub0, count)
            sub0.value = count


# ---------------------------------------------------------------- PDO mapping and codecs


class PdoCodec:
    """Decode/encode a process image made of the given entries (``None`` = gap of n bits).

    A byte-aligned image (the usual one) is one ``struct`` call each way; any other goes bit by
    bit through one integer."""

    def __init__(self, items: list[tuple[Entry | None, int]]) -> None:
        self.items = items
        self.bits = sum(bits for _, bits in items)
        self.size = (self.bits + 7) // 8
        self.entries = [e for e, _ in items if e is not None]
        fmt = "<"
        aligned = True
        for e, bits in items:
            if e is None:
                if bits % 8:
                    aligned = False
                    break
                fmt += f"{bits // 8}x"
            elif e.dtype in STRINGS or e.bits != bits or bits % 8:
                aligned = False
                break
            else:
                fmt += _FMT[e.dtype][0]
        self._struct = struct.Struct(fmt) if aligned else None
        if self._struct is not None and self._struct.size != self.size:
            self._struct = None

    def decode(self, buf: Any, offset: int) -> None:
        st = self._struct
        if st is not None:
            for entry, v in zip(self.entries, st.unpack_from(buf, offset)):  # noqa: B905 (one field per entry)
                entry.value = v
            return
        raw = int.from_bytes(buf[offset : offset + self.size], "little")
        pos = 0
        for e, bits in self.items:
            if e is not None:
                v = (raw >> pos) & ((1 << bits) - 1)
                if e.dtype in FLOATS:
                    v = struct.unpack("<f" if bits == 32 else "<d", v.to_bytes(bits // 8, "little"))[0]
                elif e.dtype in SIGNED and v >> (bits - 1):
                    v -= 1 << bits
                e.value = v
            pos += bits

    def encode(self, buf: Any, offset: int) -> None:
        st = self._struct
        if st is not None:
            st.pack_into(buf, offset, *[e.value for e in self.entries])
            return
        raw = 0
        pos = 0
        for e, bits in self.items:
            if e is not None:
                if e.dtype in FLOATS:
                    v = int.from_bytes(e.to_bytes(), "little")
                elif e.dtype in STRINGS:
                    v = int.from_bytes(bytes(e.value)[: bits // 8], "little")
                else:
                    v = int(e.value)
                raw |= (v & ((1 << bits) - 1)) << pos
            pos += bits
        buf[offset : offset + self.size] = raw.to_bytes(self.size, "little")


def compile_assignment(od: ObjectDictionary, assign_index: int, direction: str) -> PdoCodec:
    """Codec for the PDOs assigned in 0x1C12 (direction 'rx') or 0x1C13 ('tx').

    Raises SdoAbort(ABORT_NOT_MAPPABLE) when a mapping names an object that does not exist or
    cannot be mapped in that direction.
    """
    assign = od.objects[assign_index]
    items: list[tuple[Entry | None, int]] = []
    for i in range(1, assign.sub0_count() + 1):
        pdo_index = int(assign.entries[i].value)
        items += mapping_items(od, pdo_index, direction)
    return PdoCodec(items)


def mapping_items(od: ObjectDictionary, pdo_index: int, direction: str) -> list[tuple[Entry | None, int]]:
    pdo = od.objects.get(pdo_index)
    if pdo is None:
        raise SdoAbort(ABORT_NOT_MAPPABLE, f"no PDO 0x{pdo_index:04X}")
    items: list[tuple[Entry | None, int]] = []
    for j in range(1, pdo.sub0_count() + 1):
        word = int(pdo.entries[j].value)
        index, sub, bits = word >> 16, (word >> 8) & 0xFF, word & 0xFF
        if index == 0:
            items.append((None, bits))  # gap
            continue
        try:
            e = od.entry(index, sub)
        except SdoAbort:
            raise SdoAbort(ABORT_NOT_MAPPABLE, f"0x{index:04X}:{sub:02X} does not exist") from None
        if e.mappable != direction or bits != e.bits:
            raise SdoAbort(ABORT_NOT_MAPPABLE, f"0x{index:04X}:{sub:02X} ({bits} bits)")
        items.append((e, bits))
    return items


def map_word(e: Entry) -> int:
    return (e.index << 16) | (e.sub << 8) | e.bits
