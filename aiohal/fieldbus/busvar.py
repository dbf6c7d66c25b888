"""Bus variables (as in LOLA's EtherCAT layer): process data linked by name, as zero-copy views.

A :class:`PdoLayout` says where each mapped object sits in one slave's output image (RxPDO,
master → slave) and input image (TxPDO, slave → master). It is built at bring-up from what the
slave reports: the CoE PDO assignment (0x1C12/0x1C13) and mapping objects (0x16xx/0x1Axx),
or the SII TXPDO/RXPDO categories of a slave without a mailbox. Names come from a name table
keyed by (index, subindex): one for the standard CiA 402 objects here, one per device a bus driver
knows by identity (kept by that driver), overridable per device from the configuration.

A :class:`ProcessImage` holds one contiguous ``uint8`` buffer for the outputs of every slave and
one for the inputs; each slave has a slice of each. The driver copies a slave's slice to and
from the master once per cycle (pysoem hands out per-slave byte copies). ``link("drive1.Statusword")``
returns a numpy view into that buffer, so reading or writing a variable costs nothing beyond
the array access, and ``link_many(drives, "Statusword")`` returns the same variable of many
slaves as one strided array. Names, types, sizes and directions are checked once, at link
time, with errors that say what is wrong.

Naming rules (see also docs/ethercat.md):

* a variable is ``"<slave>.<name>"``; both parts are case-insensitive, and spaces and
  underscores are the same (``"drive1.target_position"`` is ``"drive1.Target position"``);
* the entry of subindex *n* of an object with subindices is ``"<object>.<n>"`` (decimal), e.g.
  ``"imu.Orientation.1"``; the object's name alone (``"imu.Orientation"``) links all its mapped
  subindices as one array (element i is subindex i+1) when they are numbered 1..n, contiguous
  and of one type;
* any entry can also be named by its address, ``"drive1.0x6041:00"`` (hex, as in CoE).
"""

from __future__ import annotations

import difflib
import itertools
import re
import struct
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

from ..errors import AiohalError

# ---------------------------------------------------------------- errors


class BusVarError(AiohalError):
    """Base of the errors of bus variables."""


class LayoutError(BusVarError, ValueError):
    """A PDO mapping, name table or image that cannot be used (bring-up)."""


class UnknownVariableError(BusVarError, LookupError):
    """No such slave or variable, or a name that fits several variables."""


class VariableTypeError(BusVarError, TypeError):
    """A variable linked with a type, size or shape it does not have."""


class ReadOnlyVariableError(BusVarError, TypeError):
    """An input (slave → master) linked or written as writable."""


# ---------------------------------------------------------------- types and names

TYPE_BITS = {"bool": 1, "i8": 8, "u8": 8, "i16": 16, "u16": 16, "i32": 32, "u32": 32,
             "i64": 64, "u64": 64, "f32": 32, "f64": 64}
NUMPY_TYPES = {name: np.dtype(f"<{name[0]}{TYPE_BITS[name] // 8}") for name in TYPE_BITS if name != "bool"}
# "bits": an unsigned bit field of any length; "pad": a gap (index 0) in a mapping.
_TYPE_ALIASES = {
    "boolean": "bool", "bit": "bool", "bit1": "bool",
    "int8": "i8", "sint": "i8", "integer8": "i8", "uint8": "u8", "usint": "u8", "unsigned8": "u8", "byte": "u8",
    "int16": "i16", "int": "i16", "integer16": "i16", "uint16": "u16", "uint": "u16", "unsigned16": "u16",
    "word": "u16", "int32": "i32", "dint": "i32", "integer32": "i32", "uint32": "u32", "udint": "u32",
    "unsigned32": "u32", "dword": "u32", "int64": "i64", "lint": "i64", "integer64": "i64",
    "uint64": "u64", "ulint": "u64", "unsigned64": "u64", "real32": "f32", "real": "f32",
    "float32": "f32", "float": "f32", "real64": "f64", "lreal": "f64", "float64": "f64", "double": "f64",
}

NameTable = Mapping[tuple[int, int], tuple[str, str]]
"""(index, subindex) → (name, type); an empty type means "from the bit length"."""


def canonical_type(name: str) -> str:
    """``"UINT16"``, ``"uint16"`` or ``"u16"`` → ``"u16"``; also ``"bits"`` and ``"pad"``."""
    key = name.strip().lower()
    key = _TYPE_ALIASES.get(key, key)
    if key not in TYPE_BITS and key not in ("bits", "pad"):
        raise LayoutError(f"unknown type {name!r} (known: {', '.join(TYPE_BITS)}, bits)")
    return key


def normalise(name: str) -> str:
    """The form names are compared in: case-folded, runs of spaces and underscores as one ``_``."""
    return re.sub(r"[\s_]+", "_", name.strip().casefold())


def address(index: int, subindex: int) -> str:
    """``0x6041:00``: an object entry as CoE tools write it."""
    return f"0x{index:04X}:{subindex:02X}"


_ADDRESS = re.compile(r"0x([0-9a-f]{1,4})(?::([0-9a-f]{1,2}))?")


def parse_address(text: str) -> tuple[int, int] | None:
    """``"0x6041:00"`` or ``"0x6041"`` (subindex 0) → (index, subindex); None if not an address."""
    match = _ADDRESS.fullmatch(text.strip().lower())
    if match is None:
        return None
    return int(match.group(1), 16), int(match.group(2) or "0", 16)


def decode_mapping(value: int) -> tuple[int, int, int]:
    """A mapping object's u32 entry → (index, subindex, bit length)."""
    return (value >> 16) & 0xFFFF, (value >> 8) & 0xFF, value & 0xFF


def encode_mapping(index: int, subindex: int, bits: int) -> int:
    return (index << 16) | (subindex << 8) | bits


def _infer_type(bits: int) -> str:
    return {1: "bool", 8: "u8", 16: "u16", 32: "u32", 64: "u64"}.get(bits, "bits")


def object_entries(index: int, name: str, type_: str, subindices: int) -> dict[tuple[int, int], tuple[str, str]]:
    """Name table rows of an object with subindices 1..n: ``"<name>.<n>"``."""
    return {(index, sub): (f"{name}.{sub}", type_) for sub in range(1, subindices + 1)}


CIA402_NAMES: dict[tuple[int, int], tuple[str, str]] = {
    (0x603F, 0): ("Error code", "u16"),
    (0x6040, 0): ("Controlword", "u16"),
    (0x6041, 0): ("Statusword", "u16"),
    (0x605A, 0): ("Quick stop option code", "i16"),
    (0x6060, 0): ("Modes of operation", "i8"),
    (0x6061, 0): ("Modes of operation display", "i8"),
    (0x6062, 0): ("Position demand value", "i32"),
    (0x6063, 0): ("Position actual internal value", "i32"),
    (0x6064, 0): ("Position actual value", "i32"),
    (0x606B, 0): ("Velocity demand value", "i32"),
    (0x606C, 0): ("Velocity actual value", "i32"),
    (0x6071, 0): ("Target torque", "i16"),
    (0x6072, 0): ("Max torque", "u16"),
    (0x6074, 0): ("Torque demand", "i16"),
    (0x6077, 0): ("Torque actual value", "i16"),
    (0x6078, 0): ("Current actual value", "i16"),
    (0x6079, 0): ("DC link circuit voltage", "u32"),
    (0x607A, 0): ("Target position", "i32"),
    (0x607F, 0): ("Max profile velocity", "u32"),
    (0x6081, 0): ("Profile velocity", "u32"),
    (0x60B0, 0): ("Position offset", "i32"),
    (0x60B1, 0): ("Velocity offset", "i32"),
    (0x60B2, 0): ("Torque offset", "i16"),
    (0x60B8, 0): ("Touch probe function", "u16"),
    (0x60B9, 0): ("Touch probe status", "u16"),
    (0x60BA, 0): ("Touch probe 1 positive value", "i32"),
    (0x60F4, 0): ("Following error actual value", "i32"),
    (0x60FD, 0): ("Digital inputs", "u32"),
    **object_entries(0x60FE, "Digital outputs", "u32", 2),  # 1 physical outputs, 2 bit mask
    (0x60FF, 0): ("Target velocity", "i32"),
}
"""The standard CiA 402 objects a drive commonly maps (axis 1)."""

def parse_names(overrides: Mapping[Any, Any]) -> dict[tuple[int, int], tuple[str, str]]:
    """A name table from the configuration's form: ``{"0x2000:01": "Motor temperature"}`` or
    ``{"0x2000:01": ["Motor temperature", "i16"]}`` (keys may also be (index, subindex))."""
    table: dict[tuple[int, int], tuple[str, str]] = {}
    for key, value in overrides.items():
        where = parse_address(key) if isinstance(key, str) else tuple(key) if isinstance(key, (tuple, list)) else None
        if where is None or len(where) != 2:
            raise LayoutError(f"name override {key!r}: expected an address like \"0x6041:00\"")
        if isinstance(value, str):
            name, type_ = value, ""
        elif isinstance(value, (tuple, list)) and len(value) == 2:
            name, type_ = value
        else:
            raise LayoutError(f"name override {key!r}: expected a name or [name, type], got {value!r}")
        if not str(name).strip():
            raise LayoutError(f"name override {key!r}: empty name")
        table[(int(where[0]), int(where[1]))] = (str(name).strip(), canonical_type(type_) if type_ else "")
    return table


def names_for(vendor_id: int | None = None, product_code: int | None = None, *, device_type: int | None = None,
              overrides: Mapping[Any, Any] | None = None,
              known: Mapping[tuple[int, int], NameTable] | None = None) -> dict[tuple[int, int], tuple[str, str]]:
    """The name table of a device: its own from ``known`` (tables by vendor ID and product code,
    which each bus driver keeps for the devices it knows), else the CiA 402 objects (when the
    device type 0x1000 is unknown or says profile 402), then the configuration's overrides on top."""
    table = (known or {}).get((vendor_id, product_code))  # type: ignore[arg-type]
    if table is None:
        table = CIA402_NAMES if device_type is None or device_type & 0xFFFF == 402 else {}
    merged = dict(table)
    for key, (name, type_) in parse_names(overrides or {}).items():
        merged[key] = (name, type_ or merged.get(key, ("", ""))[1])
    return merged


# ---------------------------------------------------------------- layouts


@dataclass(frozen=True)
class PdoEntry:
    """One mapped object entry and where it sits in its slave's output or input image."""

    index: int
    subindex: int
    bits: int
    name: str = ""  # the canonical name ("Statusword", "Orientation.1"); "" for padding
    type: str = ""  # "u16", "f32", "bool", "bits" (unsigned field), "pad"
    bit_offset: int = 0  # from the start of the slave's image
    pdo: int = 0  # the mapping object (0x1600, 0x1A00...); 0 when not known

    @property
    def address(self) -> str:
        return address(self.index, self.subindex)

    @property
    def is_padding(self) -> bool:
        return self.index == 0

    @property
    def byte_aligned(self) -> bool:
        """True when it can be a numpy view: whole bytes at a byte offset, of a numeric type."""
        return self.bit_offset % 8 == 0 and self.type in NUMPY_TYPES


RawEntry = tuple[int, int, int] | tuple[int, int, int, str]
"""(index, subindex, bits[, name]) as read from a mapping object or an SII PDO entry."""
PdoList = Mapping[int, Sequence[RawEntry]] | Sequence[Sequence[RawEntry]]
"""The PDOs of one direction, in order: {mapping index: entries} or a list of entry lists."""


@dataclass(frozen=True)
class PdoLayout:
    """One slave's process data: the RxPDO entries (outputs) and TxPDO entries (inputs), in order."""

    outputs: tuple[PdoEntry, ...] = ()
    inputs: tuple[PdoEntry, ...] = ()

    @property
    def output_bits(self) -> int:
        return sum(e.bits for e in self.outputs)

    @property
    def input_bits(self) -> int:
        return sum(e.bits for e in self.inputs)

    @property
    def output_bytes(self) -> int:
        return (self.output_bits + 7) // 8

    @property
    def input_bytes(self) -> int:
        return (self.input_bits + 7) // 8

    @property
    def signature(self) -> tuple[tuple[tuple[int, int, int], ...], ...]:
        """What the bus sees (objects and sizes, not names): equal for identically mapped slaves."""
        return tuple(tuple((e.index, e.subindex, e.bits) for e in entries) for entries in (self.outputs, self.inputs))

    @classmethod
    def from_entries(cls, rx: PdoList, tx: PdoList, names: NameTable | None = None) -> PdoLayout:
        """From the entries of each PDO, in order (the SII form, or any decoded mapping)."""
        names = CIA402_NAMES if names is None else names
        return cls(_place(rx, names, "RxPDO"), _place(tx, names, "TxPDO"))

    from_sii = from_entries

    @classmethod
    def from_coe(cls, rx_assign: Sequence[int], tx_assign: Sequence[int], mappings: Mapping[int, Sequence[int]],
                 names: NameTable | None = None) -> PdoLayout:
        """From the CoE PDO assignment as read by SDO: the u16 values of 0x1C12:01.. (RxPDOs) and
        0x1C13:01.. (TxPDOs), and each assigned mapping object's u32 values (subindex 1..n)."""
        rx = _decode_pdos(rx_assign, mappings, 0x1C12, range(0x1600, 0x1800), "RxPDO")
        tx = _decode_pdos(tx_assign, mappings, 0x1C13, range(0x1A00, 0x1C00), "TxPDO")
        return cls.from_entries(rx, tx, names)

    def describe(self) -> str:
        """A table for logs: direction, byte.bit offset, address, bits, type, name."""
        lines = []
        for direction, entries in (("out", self.outputs), ("in", self.inputs)):
            for e in entries:
                lines.append(f"{direction:3} {e.bit_offset // 8:4}.{e.bit_offset % 8} {e.address} "
                             f"{e.bits:3} {e.type:4} {e.name}")
        return "\n".join(lines)


def _decode_pdos(assign: Sequence[int], mappings: Mapping[int, Sequence[int]], assign_index: int,
                 allowed: range, kind: str) -> dict[int, list[RawEntry]]:
    pdos: dict[int, list[RawEntry]] = {}
    for n, pdo in enumerate(assign, start=1):
        where = f"0x{assign_index:04X}:{n:02X}"
        if pdo not in allowed:
            raise LayoutError(f"{where} assigns 0x{pdo:04X}, which is not an {kind} mapping object "
                              f"(0x{allowed.start:04X}-0x{allowed.stop - 1:04X})")
        if pdo in pdos:
            raise LayoutError(f"{where} assigns 0x{pdo:04X} twice")
        if pdo not in mappings:
            raise LayoutError(f"{where} assigns 0x{pdo:04X}, but its mapping was not given")
        entries: list[RawEntry] = []
        for sub, value in enumerate(mappings[pdo], start=1):
            if not 0 <= value <= 0xFFFFFFFF:
                raise LayoutError(f"0x{pdo:04X}:{sub:02X} = {value}: not a u32 mapping entry")
            index, subindex, bits = decode_mapping(value)
            entries.append((index, subindex, bits))
        pdos[pdo] = entries
    return pdos


def _place(pdos: PdoList, names: NameTable, kind: str) -> tuple[PdoEntry, ...]:
    """Name the entries and give each its bit offset, in mapping order."""
    items = pdos.items() if isinstance(pdos, Mapping) else ((0, entries) for entries in pdos)
    out: list[PdoEntry] = []
    offset = 0
    for pdo, entries in items:
        for raw in entries:
            index, subindex, bits = (int(v) for v in raw[:3])
            sii_name = str(raw[3]).strip() if len(raw) > 3 and raw[3] else ""
            where = f"{kind} 0x{pdo:04X} entry {address(index, subindex)}" if pdo else f"{kind} entry {address(index, subindex)}"
            if not 0 < bits <= 0xFF or not 0 <= index <= 0xFFFF or not 0 <= subindex <= 0xFF:
                raise LayoutError(f"{where}: {bits} bits is not a valid mapping entry")
            name, type_ = _name(index, subindex, bits, sii_name, names, where)
            out.append(PdoEntry(index, subindex, bits, name, type_, offset, pdo))
            offset += bits
    return tuple(out)


def _name(index: int, subindex: int, bits: int, sii_name: str, names: NameTable, where: str) -> tuple[str, str]:
    if index == 0:
        return "", "pad"
    name, type_ = names.get((index, subindex), ("", ""))
    type_ = canonical_type(type_) if type_ else _infer_type(bits)
    if TYPE_BITS.get(type_, bits) != bits:
        raise LayoutError(f"{where} has {bits} bits, but the name table says {name!r} is {type_} "
                          f"({TYPE_BITS[type_]} bits)")
    return name or sii_name or address(index, subindex), type_


# ---------------------------------------------------------------- accessors that are not views


class BitVar:
    """One bit of the process image (a digital I/O channel): ``get()`` / ``set()``."""

    __slots__ = ("_buf", "_byte", "_mask", "name", "writable")

    def __init__(self, name: str, buf: np.ndarray, bit_offset: int, writable: bool) -> None:
        self.name = name
        self.writable = writable
        self._buf = buf
        self._byte = bit_offset // 8
        self._mask = 1 << (bit_offset % 8)

    def get(self) -> bool:
        return bool(self._buf[self._byte] & self._mask)

    def set(self, value: bool) -> None:
        if not self.writable:
            raise ReadOnlyVariableError(f'"{self.name}" was linked read-only')
        if value:
            self._buf[self._byte] |= self._mask
        else:
            self._buf[self._byte] &= 0xFF ^ self._mask

    __bool__ = get

    def __repr__(self) -> str:
        return f"BitVar({self.name!r}, {self.get()})"


class BitsVar:
    """A run of bits read and written as one unsigned integer: a bit group (``"dio.Output"``,
    bit *k* = subindex *k* + 1) or an entry whose size is not whole bytes."""

    __slots__ = ("_buf", "_first", "_last", "_shift", "bits", "name", "writable")

    def __init__(self, name: str, buf: np.ndarray, bit_offset: int, bits: int, writable: bool) -> None:
        self.name = name
        self.bits = bits
        self.writable = writable
        self._buf = buf
        self._first = bit_offset // 8
        self._last = (bit_offset + bits + 7) // 8
        self._shift = bit_offset % 8

    def _raw(self) -> int:
        return int.from_bytes(self._buf[self._first:self._last].tobytes(), "little")

    def get(self) -> int:
        return (self._raw() >> self._shift) & ((1 << self.bits) - 1)

    def set(self, value: int) -> None:
        if not self.writable:
            raise ReadOnlyVariableError(f'"{self.name}" was linked read-only')
        value = int(value)
        if not 0 <= value < 1 << self.bits:
            raise ValueError(f'"{self.name}" holds {self.bits} bits, {value} does not fit')
        mask = ((1 << self.bits) - 1) << self._shift
        raw = (self._raw() & ~mask) | (value << self._shift)
        self._buf[self._first:self._last] = np.frombuffer(raw.to_bytes(self._last - self._first, "little"), np.uint8)

    def __getitem__(self, bit: int) -> bool:
        if not 0 <= bit < self.bits:
            raise IndexError(f'"{self.name}" has bits 0..{self.bits - 1}')
        return bool(self.get() >> bit & 1)

    def __setitem__(self, bit: int, value: bool) -> None:
        if not 0 <= bit < self.bits:
            raise IndexError(f'"{self.name}" has bits 0..{self.bits - 1}')
        self.set(self.get() | (1 << bit) if value else self.get() & ~(1 << bit))

    def __int__(self) -> int:
        return self.get()

    def __repr__(self) -> str:
        return f"BitsVar({self.name!r}, 0b{self.get():0{self.bits}b})"


class Gather:
    """The same variable of slaves that are not evenly spaced in the image: not a view, so a read
    copies out and a write scatters in (``g[...]`` reads, ``g[...] = values`` writes)."""

    __slots__ = ("_buf", "_index", "dtype", "name", "shape", "writable")

    def __init__(self, name: str, buf: np.ndarray, byte_offsets: Sequence[int], dtype: np.dtype,
                 element_shape: tuple[int, ...], writable: bool) -> None:
        self.name = name
        self.dtype = dtype
        self.shape = (len(byte_offsets), *element_shape)
        self.writable = writable
        self._buf = buf
        nbytes = dtype.itemsize * int(np.prod(element_shape, dtype=np.int64))
        self._index = np.asarray(byte_offsets, dtype=np.intp)[:, None] + np.arange(nbytes, dtype=np.intp)

    def get(self, out: np.ndarray | None = None) -> np.ndarray:
        values = self._buf[self._index].view(self.dtype).reshape(self.shape)
        if out is None:
            return values
        np.copyto(out, values)
        return out

    def set(self, values: ArrayLike) -> None:
        if not self.writable:
            raise ReadOnlyVariableError(f'"{self.name}" was linked read-only')
        packed = np.ascontiguousarray(np.broadcast_to(np.asarray(values, dtype=self.dtype), self.shape))
        self._buf[self._index] = packed.view(np.uint8).reshape(self._index.shape)

    def __array__(self, dtype: DTypeLike = None, copy: bool | None = None) -> np.ndarray:
        values = self.get()
        return values if dtype is None else values.astype(dtype)

    def __getitem__(self, key: Any) -> Any:
        return self.get()[key]

    def __setitem__(self, key: Any, values: ArrayLike) -> None:
        if key is Ellipsis or (isinstance(key, slice) and key == slice(None)):
            self.set(values)
            return
        current = self.get()
        current[key] = values
        self.set(current)

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        return f"Gather({self.name!r}, {self.get()!r})"


# ---------------------------------------------------------------- the process image


@dataclass(frozen=True)
class Variable:
    """What a name resolves to: one entry, or an object's subindices linked as one array."""

    slave: str
    name: str  # canonical, within the slave: "Statusword", "Orientation", "0x2000:01"
    direction: str  # "output" (RxPDO, master → slave) or "input" (TxPDO, slave → master)
    entries: tuple[PdoEntry, ...]
    bit_offset: int  # of the first entry, in the whole output or input buffer
    group: bool = False
    members: tuple[int, ...] = ()  # of a group: the subindex numbers of its names, in order

    @property
    def full_name(self) -> str:
        return f"{self.slave}.{self.name}"

    @property
    def type(self) -> str:
        types = {e.type for e in self.entries}
        return types.pop() if len(types) == 1 else "mixed"

    @property
    def bits(self) -> int:
        return sum(e.bits for e in self.entries)

    @property
    def contiguous(self) -> bool:
        """One run of bits; for a group also numbered 1..n, so that element i is ``"<name>.<i+1>"``."""
        if self.group and self.members != tuple(range(1, len(self.entries) + 1)):
            return False
        return all(b.bit_offset == a.bit_offset + a.bits for a, b in itertools.pairwise(self.entries))

    @property
    def byte_aligned(self) -> bool:
        return self.contiguous and all(e.byte_aligned for e in self.entries) and self.type != "mixed"

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self.entries),) if self.group else ()


_MEMBER = re.compile(r"(.+)\.(\d+)")


class SlaveImage:
    """One slave's part of the process image: its layout and its slices of the two buffers."""

    def __init__(self, name: str, layout: PdoLayout, output_offset: int, input_offset: int,
                 outputs: np.ndarray, inputs: np.ndarray) -> None:
        self.name = name
        self.layout = layout
        self.output_offset = output_offset  # bytes, in ProcessImage.outputs
        self.input_offset = input_offset
        self.outputs = outputs  # this slave's output bytes (a view)
        self.inputs = inputs  # this slave's input bytes (a view; the driver copies the master's into it)
        self._lookup: dict[str, list[Variable]] = {}  # normalised name or address → what it may mean
        self._display: dict[str, str] = {}  # normalised → canonical name
        self._index()

    def __repr__(self) -> str:
        return (f"SlaveImage({self.name!r}, outputs {self.output_offset}+{len(self.outputs)}, "
                f"inputs {self.input_offset}+{len(self.inputs)})")

    def load_inputs(self, data: bytes | bytearray | memoryview) -> None:
        """Copy the master's input bytes of this slave in (one memcpy); the size is checked."""
        if len(data) != len(self.inputs):
            raise LayoutError(f"slave {self.name!r}: got {len(data)} input bytes, its layout has {len(self.inputs)}")
        self.inputs[:] = np.frombuffer(data, dtype=np.uint8)

    def output_bytes(self) -> bytes:
        """This slave's outputs as bytes, for pysoem's ``slave.output = ...`` (which does not check sizes)."""
        return self.outputs.tobytes()

    def check_sizes(self, output_bytes: int, input_bytes: int) -> None:
        """Compare with the sizes the master gives the slave (e.g. ``len(slave.output)``) at bring-up."""
        if (output_bytes, input_bytes) != (len(self.outputs), len(self.inputs)):
            raise LayoutError(
                f"slave {self.name!r}: the master maps {output_bytes} output and {input_bytes} input bytes, "
                f"its PDO layout has {len(self.outputs)} and {len(self.inputs)}")

    def _index(self) -> None:
        """Every name (and address) of this slave → the variables it may mean."""
        groups: dict[tuple[str, str], list[tuple[int, PdoEntry]]] = {}
        for direction, entries, base in (("output", self.layout.outputs, self.output_offset),
                                         ("input", self.layout.inputs, self.input_offset)):
            for entry in entries:
                if entry.is_padding:
                    continue
                var = Variable(self.name, entry.name, direction, (entry,), base * 8 + entry.bit_offset)
                self._add(entry.name, var)
                if normalise(entry.address) != normalise(entry.name):
                    self._add(entry.address, var, display=False)
                member = _MEMBER.fullmatch(entry.name)
                if member:
                    groups.setdefault((direction, member.group(1)), []).append((int(member.group(2)), entry))
        for (direction, name), members in groups.items():
            if normalise(name) in self._lookup:
                continue  # a variable of that exact name exists: it wins
            members.sort(key=lambda m: m[0])
            entries = tuple(e for _, e in members)
            base = self.output_offset if direction == "output" else self.input_offset
            self._add(name, Variable(self.name, name, direction, entries, base * 8 + entries[0].bit_offset,
                                     group=True, members=tuple(n for n, _ in members)))

    def _add(self, name: str, var: Variable, display: bool = True) -> None:
        key = normalise(name)
        self._lookup.setdefault(key, []).append(var)
        if display:
            self._display.setdefault(key, name)

    def variable(self, name: str) -> Variable:
        where = parse_address(name)
        key = normalise(address(*where) if where else name)
        found = self._lookup.get(key)
        if not found:
            raise UnknownVariableError(f'unknown variable "{self.name}.{name}"{self._hint(key)}')
        if len(found) > 1:
            choices = ", ".join(f'"{self.name}.{v.entries[0].address}"' for v in found)
            raise UnknownVariableError(f'"{self.name}.{name}" is ambiguous: it names {len(found)} entries; '
                                       f"use an address: {choices}")
        return found[0]

    def _hint(self, key: str) -> str:
        close = difflib.get_close_matches(key, list(self._display), n=1)
        if close:
            return f' (did you mean "{self.name}.{self._display[close[0]]}"?)'
        known = list(self._display.values())
        if not known:
            return f" (slave {self.name!r} maps no process data)"
        listed = ", ".join(known[:12]) + (", ..." if len(known) > 12 else "")
        return f" ({self.name} has: {listed})"


class ProcessImage:
    """All slaves' process data in two ``uint8`` buffers (outputs, inputs), linked by name.

    Slaves with the same PDO layout (as the bus sees it) are placed next to each other in the
    buffers, whatever their bus order, so that the same variable of all of them is evenly
    spaced and :meth:`link_many` can return it as one strided view. The buffers are aiohal's
    own: the driver copies each slave's slice to and from the master every cycle
    (:meth:`SlaveImage.load_inputs`, :meth:`SlaveImage.output_bytes`).
    """

    def __init__(self, slaves: Mapping[str, PdoLayout] | Iterable[tuple[str, PdoLayout]]) -> None:
        items = list(slaves.items() if isinstance(slaves, Mapping) else slaves)
        seen: dict[str, str] = {}
        for name, layout in items:
            if not isinstance(name, str) or not name.strip() or "." in name:
                raise LayoutError(f"slave name {name!r}: expected a non-empty name without '.'")
            if normalise(name) in seen:
                raise LayoutError(f"slave names {seen[normalise(name)]!r} and {name!r} are the same name")
            if not isinstance(layout, PdoLayout):
                raise LayoutError(f"slave {name!r}: expected a PdoLayout, got {type(layout).__name__}")
            seen[normalise(name)] = name
        # placement: identical layouts together, in order of first appearance
        order: dict[Any, list[int]] = {}
        for i, (_, layout) in enumerate(items):
            order.setdefault(layout.signature, []).append(i)
        placed = [i for group in order.values() for i in group]
        offsets: dict[int, tuple[int, int]] = {}
        out_total = in_total = 0
        for i in placed:
            offsets[i] = (out_total, in_total)
            out_total += items[i][1].output_bytes
            in_total += items[i][1].input_bytes
        self.outputs = np.zeros(out_total, dtype=np.uint8)
        self.inputs = np.zeros(in_total, dtype=np.uint8)
        self.slaves: dict[str, SlaveImage] = {}
        self._by_key: dict[str, SlaveImage] = {}
        for i, (name, layout) in enumerate(items):
            out_off, in_off = offsets[i]
            slave = SlaveImage(name, layout, out_off, in_off,
                               self.outputs[out_off:out_off + layout.output_bytes],
                               self.inputs[in_off:in_off + layout.input_bytes])
            self.slaves[name] = slave
            self._by_key[normalise(name)] = slave

    # ------------------------------------------------------------ lookup

    def slave(self, name: str) -> SlaveImage:
        found = self._by_key.get(normalise(name))
        if found is None:
            close = difflib.get_close_matches(normalise(name), list(self._by_key), n=1)
            hint = f' (did you mean "{self._by_key[close[0]].name}"?)' if close else ""
            raise UnknownVariableError(f'unknown slave "{name}"{hint}')
        return found

    __getitem__ = slave

    def variable(self, name: str) -> Variable:
        """Resolve ``"<slave>.<variable>"`` without linking it."""
        slave, sep, var = name.partition(".")
        if not sep or not var:
            raise UnknownVariableError(f'"{name}": expected "<slave>.<variable>", e.g. "drive1.Statusword"')
        return self.slave(slave).variable(var)

    def names(self) -> list[str]:
        """Every linkable name, as ``"<slave>.<name>"`` (addresses not included)."""
        return [f"{s.name}.{n}" for s in self.slaves.values() for n in s._display.values()]

    # ------------------------------------------------------------ linking

    def link(self, name: str, dtype: DTypeLike = None, *, writable: bool = False) -> np.ndarray | BitVar | BitsVar:
        """A zero-copy view of one variable: 0-d for a single entry, shape (n,) for an object's
        subindices. Bit variables give a :class:`BitVar` / :class:`BitsVar` instead. Outputs are
        read-only unless ``writable``; inputs are always read-only. ``dtype``, when given, must
        be the variable's own (a check, not a conversion)."""
        var = self.variable(name)
        self._check_writable(var, writable)
        buf = self.outputs if var.direction == "output" else self.inputs
        if not var.contiguous or var.type == "mixed":
            members = ", ".join(f'"{var.slave}.{e.name}"' for e in var.entries)
            raise VariableTypeError(f'"{var.full_name}" cannot be linked as one variable: its subindices are '
                                    f"not contiguous, not numbered 1..n or not of one type; link them one by one: {members}")
        if not var.byte_aligned:
            if dtype is not None:
                raise VariableTypeError(
                    f'"{var.full_name}" is {var.bits} bit(s) from bit {var.bit_offset % 8} of a byte: not whole '
                    "bytes on a byte boundary, so it has no array view; link it without dtype for a bit accessor")
            if var.bits == 1:
                return BitVar(var.full_name, buf, var.bit_offset, writable)
            return BitsVar(var.full_name, buf, var.bit_offset, var.bits, writable)
        dt = self._check_dtype(var, dtype)
        view = np.ndarray(var.shape, dtype=dt, buffer=buf, offset=var.bit_offset // 8)
        view.flags.writeable = writable
        return view

    def link_many(self, slaves: Sequence[str], name: str, dtype: DTypeLike = None, *, writable: bool = False,
                  gather: bool = True) -> np.ndarray | Gather:
        """The same variable of several slaves as one array of shape (len(slaves), ...), in the
        order given: a strided zero-copy view when the slaves are evenly spaced in the image
        (identical layouts listed in image order always are), else a :class:`Gather` (or an
        error if ``gather`` is False)."""
        if isinstance(slaves, str) or not slaves:
            raise UnknownVariableError(f'link_many("{name}"): expected a non-empty list of slave names')
        variables = [self.variable(f"{s}.{name}") for s in slaves]
        first = variables[0]
        keys = [normalise(v.slave) for v in variables]
        if len(set(keys)) != len(keys):
            raise UnknownVariableError(f'link_many("{name}"): a slave is listed twice in {list(slaves)}')
        for var in variables:
            self._check_writable(var, writable)
            if not var.byte_aligned:
                raise VariableTypeError(f'"{var.full_name}" is not a byte-aligned numeric variable: bit variables '
                                        "cannot be linked across slaves; link each with link()")
            if (var.type, var.shape, var.direction) != (first.type, first.shape, first.direction):
                raise VariableTypeError(f'"{var.full_name}" is {_kind(var)}, but "{first.full_name}" is {_kind(first)}')
        dt = self._check_dtype(first, dtype)
        buf = self.outputs if first.direction == "output" else self.inputs
        offsets = [v.bit_offset // 8 for v in variables]
        element = first.shape
        element_strides = (dt.itemsize,) if element else ()
        if len(offsets) == 1:
            stride = dt.itemsize * max(1, int(np.prod(element)))
            evenly = True
        else:
            stride = offsets[1] - offsets[0]
            evenly = stride > 0 and all(b - a == stride for a, b in itertools.pairwise(offsets))
        if evenly:
            view = np.ndarray((len(offsets), *element), dtype=dt, buffer=buf, offset=offsets[0],
                              strides=(stride, *element_strides))
            view.flags.writeable = writable
            return view
        if not gather:
            raise VariableTypeError(f'"{name}" of {list(slaves)} is not evenly spaced in the image (byte offsets '
                                    f"{offsets}), so it has no single view; list the slaves in image order or allow gather")
        return Gather(f"{name} of {len(slaves)} slaves", buf, offsets, dt, element, writable)

    def codec(self, slave: str, names: Sequence[str], *, writable: bool = False) -> RecordCodec:
        """Several byte-aligned variables of one slave (all inputs or all outputs), read or
        written with one ``struct`` call: per value, far cheaper than a numpy call when a
        loop visits a few slaves (numpy's fixed cost per call dominates arrays of 7)."""
        variables = self._byte_variables(slave, names, writable)
        buf = self.outputs if variables[0].direction == "output" else self.inputs
        return RecordCodec(variables, buf)

    def byte_offsets(self, slave: str, names: Sequence[str], *, writable: bool = False) -> list[int]:
        """Where several byte-aligned variables of one slave (all inputs or all outputs) start
        in their buffer (``inputs`` or ``outputs``), checked as :meth:`codec` checks them: for
        code that reads or writes the image's bytes itself (compiled kernels)."""
        return [var.bit_offset // 8 for var in self._byte_variables(slave, names, writable)]

    def _byte_variables(self, slave: str, names: Sequence[str], writable: bool) -> list[Variable]:
        variables = [self.variable(f"{slave}.{name}") for name in names]
        for var in variables:
            self._check_writable(var, writable)
            if not var.byte_aligned or var.type not in STRUCT_CODES:
                raise VariableTypeError(f'"{var.full_name}" ({var.type}, {var.bits} bits) is not a byte-aligned '
                                        "number: no struct codec")
            if var.direction != variables[0].direction:
                raise VariableTypeError(f'"{var.full_name}" is an {var.direction}, "{variables[0].full_name}" an '
                                        f"{variables[0].direction}: a codec reads or writes one direction")
        if writable and variables[0].direction == "input":
            raise ReadOnlyVariableError(f'"{variables[0].full_name}" is an input (slave to master): it is read-only')
        return variables

    @staticmethod
    def _check_writable(var: Variable, writable: bool) -> None:
        if writable and var.direction == "input":
            raise ReadOnlyVariableError(f'"{var.full_name}" is an input (slave to master): it is read-only')

    @staticmethod
    def _check_dtype(var: Variable, dtype: DTypeLike) -> np.dtype:
        own = NUMPY_TYPES[var.type]
        if dtype is None:
            return own
        try:
            wanted = np.dtype(dtype)
        except TypeError as exc:
            raise VariableTypeError(f'"{var.full_name}": {dtype!r} is not a numpy dtype') from exc
        if wanted.itemsize != own.itemsize:
            raise VariableTypeError(f'"{var.full_name}" is {var.type} ({own.itemsize * 8} bits per element), '
                                    f"{wanted} has {wanted.itemsize * 8} bits: size mismatch")
        if wanted != own:
            raise VariableTypeError(f'"{var.full_name}" is {var.type} (little-endian), not {wanted}: type mismatch')
        return own


def _kind(var: Variable) -> str:
    return f"{var.type}{list(var.shape) if var.shape else ''} ({var.direction})"


STRUCT_CODES = {"i8": "b", "u8": "B", "i16": "h", "u16": "H", "i32": "i", "u32": "I", "i64": "q", "u64": "Q",
                "f32": "f", "f64": "d"}


class RecordCodec:
    """Byte-aligned variables of one slave as one little-endian ``struct`` over their bytes.

    ``unpack()`` returns the values in the order the variables were given (a group, e.g. an
    object's subindices, gives a tuple), ``pack(*values)`` takes them in that order. The
    buffer is the process image's (``inputs`` or ``outputs``): no copy of the image is made.
    """

    def __init__(self, variables: Sequence[Variable], buf: np.ndarray) -> None:
        self.names = tuple(v.full_name for v in variables)
        self.buf = buf
        by_offset = sorted(range(len(variables)), key=lambda i: variables[i].bit_offset)
        start = variables[by_offset[0]].bit_offset // 8
        fmt, at, slots = "<", start, [None] * len(variables)
        position = 0
        for i in by_offset:
            var = variables[i]
            offset = var.bit_offset // 8
            if offset < at:
                raise VariableTypeError(f'"{var.full_name}" overlaps another variable of the codec')
            fmt += "x" * (offset - at)
            count = len(var.entries)
            fmt += f"{count}{STRUCT_CODES[var.type]}" if var.group else STRUCT_CODES[var.type]
            slots[i] = slice(position, position + count) if var.group else position
            position += count
            at = offset + var.bits // 8
        self.offset = start
        self.struct = struct.Struct(fmt)
        in_order = tuple(slots) == tuple(range(len(slots)))  # scalars, in the bytes' order
        #: ``f(buf, offset) -> values`` and ``f(buf, offset, *values)``, values in the order the
        #: variables were given: ``struct``'s own functions when that is the bytes' order (the
        #: fast path of per-cycle loops)
        self.unpack_from: Callable[..., tuple] = self.struct.unpack_from if in_order else \
            _reordered_unpack(self.struct.unpack_from, tuple(slots))
        self.pack_into: Callable[..., None] = self.struct.pack_into if in_order else \
            _reordered_pack(self.struct.pack_into, tuple(slots), position)

    def unpack(self) -> tuple:
        return self.unpack_from(self.buf, self.offset)

    def pack(self, *values: Any) -> None:
        self.pack_into(self.buf, self.offset, *values)


def _reordered_unpack(unpack: Callable[..., tuple], slots: tuple) -> Callable[..., tuple]:
    def reordered(buf: Any, offset: int) -> tuple:
        raw = unpack(buf, offset)
        return tuple(raw[s] for s in slots)
    return reordered


def _reordered_pack(pack: Callable[..., None], slots: tuple, count: int) -> Callable[..., None]:
    def reordered(buf: Any, offset: int, *values: Any) -> None:
        raw: list[Any] = [0] * count
        for value, slot in zip(values, slots, strict=True):
            raw[slot] = value
        pack(buf, offset, *raw)
    return reordered
