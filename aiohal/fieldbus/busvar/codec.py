"""Records of bus variables read and written with one ``struct`` call in the order given,
whatever their order in the image."""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .errors import VariableTypeError
from .layout import Variable

STRUCT_CODES = {
    "i8": "b",
    "u8": "B",
    "i16": "h",
    "u16": "H",
    "i32": "i",
    "u32": "I",
    "i64": "q",
    "u64": "Q",
    "f32": "f",
    "f64": "d",
}


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
        slots: list[slice | int | None] = [None] * len(variables)  # each filled below
        fmt, at = "<", start
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
        self.unpack_from: Callable[..., tuple] = (
            self.struct.unpack_from if in_order else _reordered_unpack(self.struct.unpack_from, tuple(slots))
        )
        self.pack_into: Callable[..., None] = (
            self.struct.pack_into if in_order else _reordered_pack(self.struct.pack_into, tuple(slots), position)
        )

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
