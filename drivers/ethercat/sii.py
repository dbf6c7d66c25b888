"""A slave's PDOs from its SII EEPROM: the layout of a slave without CoE.

A slave with no mailbox (a digital I/O terminal, most simple Beckhoff EL terminals) has no
object dictionary to ask for its PDO assignment; its PDOs are described in the SII categories
TXPDO (50) and RXPDO (51), which is also where SOEM takes them from when it maps such a slave.
Facts used (ETG.2010), all little endian, addresses in 16-bit words:

* word 0x1C: the mailbox protocols the slave supports (bit 2, 0x0004: CoE);
* from word 0x40: categories, each a type word, a length word (in words) and its data, ended
  by the type 0xFFFF;
* STRINGS (10): a count byte, then per string a length byte and its characters; string
  numbers in other categories count from 1 (0 = none);
* TXPDO / RXPDO: per PDO an 8-byte header (index u16, entry count u8, SyncManager u8, DC sync
  u8, name string u8, flags u16), then per entry 8 bytes (index u16, subindex u8, name string
  u8, data type u8, bit length u8, flags u16). A PDO whose SyncManager number is not a
  SyncManager (0xFF and the like) is not assigned, so not mapped.

``read_words(word)`` is the slave's EEPROM read (pysoem's ``eeprom_read``: 4 bytes, the word
and the next one).
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from aiohal.fieldbus.busvar import LayoutError, RawEntry

MAILBOX_PROTOCOLS_WORD = 0x1C
MBX_COE = 0x0004
FIRST_CATEGORY_WORD = 0x40
CAT_STRINGS, CAT_TXPDO, CAT_RXPDO, CAT_END = 10, 50, 51, 0xFFFF
MAX_SYNC_MANAGERS = 16  # an ESC has at most 16
#: a walk that goes on longer than this reads a corrupt or blank EEPROM (64 Kibit is 4096 words)
MAX_WORD = 0x8000
MAX_CATEGORIES = 256

ReadWords = Callable[[int], bytes]


class SiiReader:
    """Words of one slave's EEPROM, read two at a time and kept (each read is a few frames)."""

    def __init__(self, read_words: ReadWords) -> None:
        self._read = read_words
        self._cache: dict[int, bytes] = {}

    def words(self, start: int, count: int) -> bytes:
        out = bytearray()
        for word in range(start, start + count):
            pair = word & ~1
            if pair not in self._cache:
                data = bytes(self._read(pair))
                if len(data) < 4:
                    raise LayoutError(f"SII word 0x{pair:04X}: {len(data)} bytes read, 4 expected")
                self._cache[pair] = data[:4]
            half = (word - pair) * 2
            out += self._cache[pair][half : half + 2]
        return bytes(out)

    def word(self, address: int) -> int:
        return struct.unpack("<H", self.words(address, 1))[0]


def has_coe(reader: SiiReader) -> bool:
    """The slave says it speaks CoE through its mailbox."""
    return bool(reader.word(MAILBOX_PROTOCOLS_WORD) & MBX_COE)


def categories(reader: SiiReader, wanted: set[int]) -> dict[int, bytes]:
    """The data of the ``wanted`` categories (the first of each type); the others are skipped
    over by their length, unread."""
    found: dict[int, bytes] = {}
    word = FIRST_CATEGORY_WORD
    for _ in range(MAX_CATEGORIES):
        if word + 2 > MAX_WORD:
            break
        kind, length = struct.unpack("<HH", reader.words(word, 2))
        if kind == CAT_END:
            return found
        if kind in wanted and kind not in found:
            found[kind] = reader.words(word + 2, length)
        word += 2 + length
    raise LayoutError(f"SII: no end of the categories before word 0x{word:04X} (a blank or corrupt EEPROM?)")


def parse_strings(data: bytes) -> list[str]:
    if not data:
        return []
    out, pos = [], 1
    for _ in range(data[0]):
        if pos >= len(data):
            break
        n = data[pos]
        out.append(data[pos + 1 : pos + 1 + n].decode("latin-1"))
        pos += 1 + n
    return out


def parse_pdos(data: bytes, strings: list[str], kind: str) -> dict[int, list[RawEntry]]:
    """One TXPDO or RXPDO category → {PDO index: [(index, subindex, bits, name)]}, the PDOs
    assigned to a SyncManager only, in their order."""

    def name(i: int) -> str:
        return strings[i - 1] if 0 < i <= len(strings) else ""

    pdos: dict[int, list[RawEntry]] = {}
    pos = 0
    while pos + 8 <= len(data):
        index, count, sm, _dc, _name, _flags = struct.unpack_from("<HBBBBH", data, pos)
        pos += 8
        if pos + 8 * count > len(data):
            raise LayoutError(f"SII {kind} 0x{index:04X}: {count} entries do not fit in the category")
        entries = [struct.unpack_from("<HBBBBH", data, pos + 8 * k) for k in range(count)]
        pos += 8 * count
        if sm >= MAX_SYNC_MANAGERS:
            continue  # not assigned
        if index in pdos:
            raise LayoutError(f"SII {kind} 0x{index:04X} is described twice")
        pdos[index] = [(e_index, e_sub, e_bits, name(e_name)) for e_index, e_sub, e_name, _type, e_bits, _f in entries]
    return pdos


def read_pdos(reader: SiiReader) -> tuple[dict[int, list[RawEntry]], dict[int, list[RawEntry]]]:
    """(RxPDOs, TxPDOs) of the slave, named from its strings."""
    found = categories(reader, {CAT_STRINGS, CAT_TXPDO, CAT_RXPDO})
    strings = parse_strings(found.get(CAT_STRINGS, b""))
    return (
        parse_pdos(found.get(CAT_RXPDO, b""), strings, "RxPDO"),
        parse_pdos(found.get(CAT_TXPDO, b""), strings, "TxPDO"),
    )
