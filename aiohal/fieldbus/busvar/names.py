"""Names and types of bus variables: the CiA 402 name table, name tables per device, the
normalised spelling of a name, CoE addresses and PDO mapping values."""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from .errors import LayoutError

TYPE_BITS = {
    "bool": 1,
    "i8": 8,
    "u8": 8,
    "i16": 16,
    "u16": 16,
    "i32": 32,
    "u32": 32,
    "i64": 64,
    "u64": 64,
    "f32": 32,
    "f64": 64,
}
NUMPY_TYPES = {name: np.dtype(f"<{name[0]}{TYPE_BITS[name] // 8}") for name in TYPE_BITS if name != "bool"}
# "bits": an unsigned bit field of any length; "pad": a gap (index 0) in a mapping.
_TYPE_ALIASES = {
    "boolean": "bool",
    "bit": "bool",
    "bit1": "bool",
    "int8": "i8",
    "sint": "i8",
    "integer8": "i8",
    "uint8": "u8",
    "usint": "u8",
    "unsigned8": "u8",
    "byte": "u8",
    "int16": "i16",
    "int": "i16",
    "integer16": "i16",
    "uint16": "u16",
    "uint": "u16",
    "unsigned16": "u16",
    "word": "u16",
    "int32": "i32",
    "dint": "i32",
    "integer32": "i32",
    "uint32": "u32",
    "udint": "u32",
    "unsigned32": "u32",
    "dword": "u32",
    "int64": "i64",
    "lint": "i64",
    "integer64": "i64",
    "uint64": "u64",
    "ulint": "u64",
    "unsigned64": "u64",
    "real32": "f32",
    "real": "f32",
    "float32": "f32",
    "float": "f32",
    "real64": "f64",
    "lreal": "f64",
    "float64": "f64",
    "double": "f64",
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
            raise LayoutError(f'name override {key!r}: expected an address like "0x6041:00"')
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


def names_for(
    vendor_id: int | None = None,
    product_code: int | None = None,
    *,
    device_type: int | None = None,
    overrides: Mapping[Any, Any] | None = None,
    known: Mapping[tuple[int, int], NameTable] | None = None,
) -> dict[tuple[int, int], tuple[str, str]]:
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
