"""SII (slave information interface) EEPROM images, built from a device description.

Layout (ETG.1000.6 / ETG.2010), all little endian, addressed in 16-bit words:

* words 0x00-0x07: ESC configuration area (PDI control, PDI configuration, sync impulse length,
  extended PDI configuration, configured station alias, two reserved words, and a CRC-8 over
  words 0-6 in the low byte of word 7);
* words 0x08-0x0F: vendor id, product code, revision, serial number (u32 each);
* words 0x14-0x17: bootstrap mailbox (receive offset/size, send offset/size);
* words 0x18-0x1B: standard mailbox (receive = master to slave, then send);
* word 0x1C: supported mailbox protocols (0x0004 = CoE);
* word 0x3E: EEPROM size in KiBit minus one; word 0x3F: SII version;
* from word 0x40: categories, each a type word, a length word (in words) and data, ended by
  the type 0xFFFF.

Categories written here: STRINGS (10), GENERAL (30), FMMU (40), SYNCM (41), TXPDO (50),
RXPDO (51).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

CAT_STRINGS = 10
CAT_GENERAL = 30
CAT_FMMU = 40
CAT_SYNCM = 41
CAT_TXPDO = 50
CAT_RXPDO = 51
CAT_END = 0xFFFF

MBX_PROTO_COE = 0x0004

# GENERAL category, byte 5 (CoE details)
COE_SDO = 0x01
COE_SDO_INFO = 0x02
COE_PDO_ASSIGN = 0x04
COE_PDO_CONFIG = 0x08
COE_UPLOAD_AT_STARTUP = 0x10
COE_COMPLETE_ACCESS = 0x20

# FMMU category usage codes
FMMU_UNUSED = 0
FMMU_OUTPUTS = 1
FMMU_INPUTS = 2
FMMU_MBX_STATE = 3

# SYNCM category type byte
SM_UNUSED = 0
SM_MBX_OUT = 1  # master -> slave (receive mailbox)
SM_MBX_IN = 2  # slave -> master (send mailbox)
SM_OUTPUTS = 3
SM_INPUTS = 4


def crc8(data: bytes) -> int:
    """CRC-8 of the SII configuration area: polynomial x^8 + x^2 + x + 1, initial value 0xFF,
    no reflection, no final XOR."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


@dataclass(frozen=True)
class SiiSyncManager:
    start: int
    length: int
    control: int
    enable: int
    kind: int  # SM_* type byte


@dataclass(frozen=True)
class SiiPdoEntry:
    index: int
    subindex: int
    bits: int
    dtype: int = 0  # CoE data type code (0 for gaps)
    name: str = ""


@dataclass(frozen=True)
class SiiPdo:
    index: int
    sm: int
    entries: tuple[SiiPdoEntry, ...]
    name: str = ""


@dataclass
class SiiDescription:
    """Everything that goes into one slave's EEPROM image."""

    vendor: int
    product: int
    revision: int
    serial: int
    name: str
    group: str = "aiohal"
    order: str = ""
    alias: int = 0
    pdi_control: int = 0x0008  # SPI, a usual value; SOEM only stores it
    pdi_config: int = 0x0000
    mailbox: tuple[int, int, int, int] | None = None  # rx offset, rx size, tx offset, tx size
    mailbox_protocols: int = 0
    coe_details: int = 0
    flags: int = 0
    ebus_current_ma: int = 0
    ds402_channels: int = 0
    fmmus: tuple[int, ...] = (FMMU_OUTPUTS, FMMU_INPUTS)
    sync_managers: tuple[SiiSyncManager, ...] = ()
    txpdos: tuple[SiiPdo, ...] = ()
    rxpdos: tuple[SiiPdo, ...] = ()
    eeprom_kbit: int = 4  # 4 KiBit = 512 bytes would be small; grown to fit below
    _strings: list[str] = field(default_factory=list, repr=False)

    def string_index(self, text: str) -> int:
        """Index (1-based) of ``text`` in the STRINGS category, adding it if new; 0 for ''."""
        if not text:
            return 0
        if text not in self._strings:
            self._strings.append(text)
        return self._strings.index(text) + 1


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", kind, len(data) // 2) + data


def build_sii(desc: SiiDescription) -> bytes:
    """The EEPROM image (bytes, even length) for ``desc``."""
    # String 1 must be the device name: SOEM takes string 1 as the slave name.
    desc._strings.clear()
    name_idx = desc.string_index(desc.name)
    group_idx = desc.string_index(desc.group)
    order_idx = desc.string_index(desc.order or desc.name)

    def pdo_bytes(pdos: tuple[SiiPdo, ...]) -> bytes:
        out = b""
        for pdo in pdos:
            out += struct.pack("<HBBBBH", pdo.index, len(pdo.entries), pdo.sm, 0, desc.string_index(pdo.name), 0)
            for e in pdo.entries:
                out += struct.pack("<HBBBBH", e.index, e.subindex, desc.string_index(e.name), e.dtype, e.bits, 0)
        return out

    tx = pdo_bytes(desc.txpdos)
    rx = pdo_bytes(desc.rxpdos)

    general = struct.pack(
        "<BBBBBBBBBBBBhBBHH",
        group_idx,  # group
        0,  # image
        order_idx,  # order
        name_idx,  # name
        0,  # reserved
        desc.coe_details,
        0,  # FoE details
        0,  # EoE details
        0,  # SoE channels
        desc.ds402_channels,
        0,  # sysman class
        desc.flags,
        desc.ebus_current_ma,
        group_idx,
        0,  # reserved
        0x0011,  # physical ports: port 0 and 1 MII
        0x0000,  # physical memory address
    )
    general += bytes(32 - len(general))

    fmmu = bytes(desc.fmmus)
    syncm = b"".join(
        struct.pack("<HHBBBB", sm.start, sm.length, sm.control, 0, sm.enable, sm.kind) for sm in desc.sync_managers
    )

    strings = bytes([len(desc._strings)])
    for s in desc._strings:
        raw = s.encode("latin-1")[:255]
        strings += bytes([len(raw)]) + raw

    cats = _category(CAT_STRINGS, strings) + _category(CAT_GENERAL, general)
    if fmmu:
        cats += _category(CAT_FMMU, fmmu)
    if syncm:
        cats += _category(CAT_SYNCM, syncm)
    if tx:
        cats += _category(CAT_TXPDO, tx)
    if rx:
        cats += _category(CAT_RXPDO, rx)
    cats += struct.pack("<H", CAT_END)

    head = bytearray(0x80)
    struct.pack_into("<HHHHH", head, 0, desc.pdi_control, desc.pdi_config, 0, 0, desc.alias)
    head[14] = crc8(bytes(head[:14]))
    struct.pack_into("<IIII", head, 0x10, desc.vendor, desc.product, desc.revision, desc.serial)
    if desc.mailbox:
        rx_off, rx_size, tx_off, tx_size = desc.mailbox
        # bootstrap mailbox: same buffers as the standard mailbox
        struct.pack_into("<HHHH", head, 0x28, rx_off, rx_size, tx_off, tx_size)
        struct.pack_into("<HHHHH", head, 0x30, rx_off, rx_size, tx_off, tx_size, desc.mailbox_protocols)
    image = bytes(head) + cats
    kbit = desc.eeprom_kbit
    while kbit * 128 < len(image):
        kbit *= 2
    struct.pack_into("<HH", head, 0x7C, kbit - 1, 1)
    image = bytes(head) + cats
    return image + b"\xff" * (kbit * 128 - len(image))
