"""Where each mapped object sits in one slave's process image: :class:`PdoLayout`, built from
the CoE PDO assignment and mapping objects or from the SII PDO categories; and
:class:`Variable`, what a name resolves to in it."""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from .errors import LayoutError
from .names import CIA402_NAMES, NUMPY_TYPES, TYPE_BITS, NameTable, _infer_type, address, canonical_type, decode_mapping


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
    def from_coe(
        cls,
        rx_assign: Sequence[int],
        tx_assign: Sequence[int],
        mappings: Mapping[int, Sequence[int]],
        names: NameTable | None = None,
    ) -> PdoLayout:
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
                lines.append(
                    f"{direction:3} {e.bit_offset // 8:4}.{e.bit_offset % 8} {e.address} {e.bits:3} {e.type:4} {e.name}"
                )
        return "\n".join(lines)


def _decode_pdos(
    assign: Sequence[int], mappings: Mapping[int, Sequence[int]], assign_index: int, allowed: range, kind: str
) -> dict[int, list[RawEntry]]:
    pdos: dict[int, list[RawEntry]] = {}
    for n, pdo in enumerate(assign, start=1):
        where = f"0x{assign_index:04X}:{n:02X}"
        if pdo not in allowed:
            raise LayoutError(
                f"{where} assigns 0x{pdo:04X}, which is not an {kind} mapping object "
                f"(0x{allowed.start:04X}-0x{allowed.stop - 1:04X})"
            )
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
            where = (
                f"{kind} 0x{pdo:04X} entry {address(index, subindex)}"
                if pdo
                else f"{kind} entry {address(index, subindex)}"
            )
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
        raise LayoutError(
            f"{where} has {bits} bits, but the name table says {name!r} is {type_} ({TYPE_BITS[type_]} bits)"
        )
    return name or sii_name or address(index, subindex), type_


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


def _kind(var: Variable) -> str:
    return f"{var.type}{list(var.shape) if var.shape else ''} ({var.direction})"
