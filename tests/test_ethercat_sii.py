"""The driver's SII reader (drivers/ethercat/sii.py) on the EEPROM images the simulator's
slaves carry: the layout of a slave without CoE, read as the driver reads it at bring-up."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.drivers.ethercat import sii
from aiohal.drivers.ethercat.names import DIO_NAMES
from aiohal.drivers.ethercat.sim.devices import DigitalIO
from aiohal.drivers.ethercat.sim.drive import Drive
from aiohal.drivers.ethercat.sim.sii import SiiDescription, SiiPdo, SiiPdoEntry, build_sii
from aiohal.fieldbus.busvar import LayoutError, PdoLayout, names_for


class Eeprom:
    """An EEPROM image read like pysoem's ``eeprom_read``: 4 bytes from a word address."""

    def __init__(self, image: bytes) -> None:
        self.image = image
        self.reads: list[int] = []

    def __call__(self, word: int) -> bytes:
        self.reads.append(word)
        return self.image[2 * word:2 * word + 4].ljust(4, b"\xff")


def test_a_digital_io_terminal_has_no_coe_and_its_pdos_come_from_its_sii():
    eeprom = Eeprom(build_sii(DigitalIO(channels=8).sii_description()))
    reader = sii.SiiReader(eeprom)
    assert not sii.has_coe(reader)
    rx, tx = sii.read_pdos(reader)
    assert rx == {0x1600: [(0x7000, i, 1, f"Output {i}") for i in range(1, 9)]}
    assert tx == {0x1A00: [(0x6000, i, 1, f"Input {i}") for i in range(1, 9)]}
    assert len(eeprom.reads) == len(set(eeprom.reads))  # each pair of words read once
    layout = PdoLayout.from_sii(rx, tx, DIO_NAMES)
    assert (layout.output_bytes, layout.input_bytes) == (1, 1)
    assert [e.name for e in layout.outputs][:2] == ["Output.1", "Output.2"]
    unknown = PdoLayout.from_sii(rx, tx, {})  # no name table: the SII's own names
    assert [e.name for e in unknown.inputs][:2] == ["Input 1", "Input 2"]


def test_a_drive_says_coe_so_its_mapping_is_read_over_coe():
    assert sii.has_coe(sii.SiiReader(Eeprom(build_sii(Drive().sii_description()))))


def test_unassigned_pdos_are_left_out_and_padding_is_kept():
    rxpdos = (SiiPdo(0x1600, 2, (SiiPdoEntry(0x7000, 1, 8, 5, "Setpoint"), SiiPdoEntry(0, 0, 8, 0, ""))),
              SiiPdo(0x1601, 0xFF, (SiiPdoEntry(0x7010, 1, 16, 6, "Spare"),), "not assigned"))
    txpdos = (SiiPdo(0x1A00, 3, (SiiPdoEntry(0x6000, 1, 16, 6, "Value"),), "Inputs"),)
    desc = SiiDescription(vendor=1, product=2, revision=3, serial=4, name="T", rxpdos=rxpdos, txpdos=txpdos)
    rx, tx = sii.read_pdos(sii.SiiReader(Eeprom(build_sii(desc))))
    assert rx == {0x1600: [(0x7000, 1, 8, "Setpoint"), (0, 0, 8, "")]}
    assert tx == {0x1A00: [(0x6000, 1, 16, "Value")]}
    layout = PdoLayout.from_sii(rx, tx, {})
    assert layout.output_bytes == 2 and layout.outputs[1].is_padding


def test_an_eeprom_without_an_end_of_categories_is_an_error_not_a_loop():
    blank = bytes(0x80) + bytes(4096)  # type 0, length 0, forever
    eeprom = Eeprom(blank)
    with pytest.raises(LayoutError, match="no end of the categories"):
        sii.read_pdos(sii.SiiReader(eeprom))
    assert len(eeprom.reads) <= sii.MAX_CATEGORIES + 1


def test_a_pdo_longer_than_its_category_and_a_short_read_are_errors():
    head = bytes(0x80)
    pdo = struct.pack("<HBBBBH", 0x1A00, 5, 3, 0, 0, 0) + struct.pack("<HBBBBH", 0x6000, 1, 0, 0, 8, 0)
    image = head + struct.pack("<HH", sii.CAT_TXPDO, len(pdo) // 2) + pdo + struct.pack("<H", sii.CAT_END)
    with pytest.raises(LayoutError, match="5 entries do not fit"):
        sii.read_pdos(sii.SiiReader(Eeprom(image)))
    with pytest.raises(LayoutError, match="2 bytes read"):
        sii.SiiReader(lambda word: b"\x00\x00").word(0x1C)


def _eeprom(categories: list[tuple[int, bytes]]) -> bytes:
    body = bytearray(0x80)  # the header words, then the categories from word 0x40
    for kind, data in categories:
        data += b"\0" * (len(data) % 2)
        body += struct.pack("<HH", kind, len(data) // 2) + data
    return bytes(body + struct.pack("<H", 0xFFFF) + b"\0\0")


@settings(max_examples=500, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([10, 30, 41, 50, 51]), st.binary(max_size=80)), max_size=5))
def test_whatever_pdo_categories_an_eeprom_holds_they_map_or_fail_with_a_layout_error(categories):
    image = _eeprom(categories)
    reader = sii.SiiReader(lambda word: image[2 * word:2 * word + 4] if 2 * word + 4 <= len(image) else b"\xff" * 4)
    try:
        rx, tx = sii.read_pdos(reader)
        PdoLayout.from_sii(rx, tx, names_for(0, 0, device_type=0))
    except LayoutError:
        pass
