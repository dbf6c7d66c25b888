"""Batch CDR for messages whose byte layout is fixed for a run, found from rosbags' own output.

A recorded channel's messages have the same strings and sequence lengths on every tick (the
joints and devices of a run do not change), so every number sits at the same byte offset in
every message. :class:`FixedLayout` serializes a sample message with rosbags (the template)
and finds where each number lies by serializing the sample with that field set to two byte
patterns: the bytes that differ are the field's. Encoding a batch of ticks is then one numpy
fill per field, decoding one ``frombuffer`` per field. The bytes are rosbags' bytes (a test
checks every recorded channel against :func:`aiohal.ros2.serialize`, the plain path), without
building and serializing a message object per tick.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .messages import serialize, typestore

#: ROS 2 number types as numpy dtypes (CDR is little-endian here); most share numpy's names
DTYPES: dict[str, np.dtype] = {
    name: np.dtype(name)
    for name in ("bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32", "float64")
} | {"byte": np.dtype(np.uint8), "char": np.dtype(np.uint8)}


def number_fields(sample: Any, prefix: str = "") -> dict[str, tuple[np.dtype, int | None]]:
    """Every number of ``sample`` by dotted path (``header.stamp.sec``, ``position``): its dtype
    and count (None for a scalar, the length for an array or a sequence). Nested messages are
    followed; a sequence of messages cannot have a fixed layout (ValueError)."""
    from rosbags.interfaces import Nodetype

    _, fields = typestore().fielddefs[sample.__msgtype__]
    out: dict[str, tuple[np.dtype, int | None]] = {}
    for name, (kind, detail) in fields:
        path = prefix + name
        value = getattr(sample, name)
        if kind == Nodetype.BASE:
            if detail[0] in DTYPES:
                out[path] = (DTYPES[detail[0]], None)
        elif kind == Nodetype.NAME:
            out.update(number_fields(value, path + "."))
        else:  # ARRAY or SEQUENCE
            (inner_kind, inner), _ = detail
            if inner_kind == Nodetype.BASE and inner[0] in DTYPES:
                out[path] = (DTYPES[inner[0]], len(value))
            elif inner_kind != Nodetype.BASE and len(value):
                raise ValueError(f"{sample.__msgtype__}.{path}: a sequence of messages has no fixed layout")
    return out


def with_values(msg: Any, values: Mapping[str, Any]) -> Any:
    """A copy of ``msg`` with the fields at the dotted paths of ``values`` replaced."""
    direct: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for path, value in values.items():
        head, _, rest = path.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = value.item() if isinstance(value, np.generic) else value
    for head, inner in nested.items():
        direct[head] = with_values(getattr(msg, head), inner)
    return dataclasses.replace(msg, **direct)


def _pattern(dtype: np.dtype, count: int | None, byte: int) -> Any:
    """A value whose every byte is ``byte`` (bool: False or True)."""
    n = count or 1
    if dtype == np.bool_:
        array = np.full(n, byte == 2, dtype=np.bool_)
    else:
        array = np.frombuffer(bytes([byte]) * (dtype.itemsize * n), dtype=dtype).copy()
    return array if count is not None else array[0]


class FixedLayout:
    """The byte layout of ``sample``'s type for messages like it: the same strings and the same
    sequence lengths. ``fields``: the dotted paths a batch gives (default every number);
    the others keep the sample's values."""

    def __init__(self, sample: Any, fields: Sequence[str] | None = None) -> None:
        self.name: str = sample.__msgtype__
        numbers = number_fields(sample)
        if fields is None:
            fields = list(numbers)
        template = serialize(sample)
        self.size = len(template)
        self.template = np.frombuffer(template, dtype=np.uint8)
        #: path -> (dtype, count, byte offset)
        self.fields: dict[str, tuple[np.dtype, int | None, int]] = {}
        for path in fields:
            if path not in numbers:
                raise KeyError(f"{self.name} has no number field {path!r}")
            dtype, count = numbers[path]
            a, b = (
                np.frombuffer(serialize(with_values(sample, {path: _pattern(dtype, count, byte)})), dtype=np.uint8)
                for byte in (1, 2)
            )
            width = dtype.itemsize * (count or 1)
            changed = np.flatnonzero(a != b) if len(a) == len(b) == self.size else np.array([], dtype=np.int64)
            if len(changed) != width or changed[-1] - changed[0] + 1 != width:
                raise ValueError(f"{self.name}.{path}: not at a fixed place in the message")
            self.fields[path] = (dtype, count, int(changed[0]))
        self._constant = np.ones(self.size, dtype=bool)
        for dtype, count, offset in self.fields.values():
            self._constant[offset : offset + dtype.itemsize * (count or 1)] = False

    def encode(self, values: Mapping[str, np.ndarray], n: int) -> np.ndarray:
        """``n`` messages as an ``(n, size)`` byte array; ``values[path]`` has one row per message."""
        out = np.empty((n, self.size), dtype=np.uint8)
        out[:] = self.template
        for path, (dtype, count, offset) in self.fields.items():
            width = dtype.itemsize * (count or 1)
            column = np.ascontiguousarray(values[path], dtype=dtype).reshape(n, count or 1)
            out[:, offset : offset + width] = column.view(np.uint8)
        return out

    def matches(self, messages: np.ndarray) -> bool:
        """Whether every row of ``(n, size)`` messages has this layout: its bytes other than the
        numbers (strings, lengths, padding) are the template's."""
        return bool(
            np.array_equal(
                messages[:, self._constant],
                np.broadcast_to(self.template[self._constant], (len(messages), int(self._constant.sum()))),
            )
        )

    def decode(self, messages: np.ndarray) -> dict[str, np.ndarray]:
        """Fields of ``(n, size)`` messages: ``(n,)`` for scalars, ``(n, count)`` for sequences."""
        out = {}
        for path, (dtype, count, offset) in self.fields.items():
            width = dtype.itemsize * (count or 1)
            column = np.ascontiguousarray(messages[:, offset : offset + width]).view(dtype)
            out[path] = column[:, 0] if count is None else column
        return out
