"""Fixed-size ROS 2 messages in CDR: every field of a recorded channel at a constant offset.

A channel's message has the same sequence lengths on every tick (the joints and devices of a
robot do not change during a run), so its CDR encoding is a fixed byte layout: encoding a batch
of ticks is one array fill per field (numpy), and decoding a recording is one ``frombuffer``.
The schema is the ROS 2 ``.msg`` text that Foxglove and PlotJuggler parse (encoding
``ros2msg``, messages ``cdr``), without ROS installed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

#: little-endian plain CDR (XCDR1), the ROS 2 default
HEADER = bytes((0x00, 0x01, 0x00, 0x00))

ROS_TYPES: dict[np.dtype, str] = {
    np.dtype(np.float64): "float64",
    np.dtype(np.int64): "int64",
    np.dtype(np.uint32): "uint32",
    np.dtype(np.int8): "int8",
    np.dtype(np.uint8): "uint8",
    np.dtype(np.bool_): "bool",
}
DTYPES = {name: dtype for dtype, name in ROS_TYPES.items()}


def _align(pos: int, size: int) -> int:
    return (pos + size - 1) // size * size


class Layout:
    """A message type: ``fields`` are ``(name, dtype, count)``, count None for a scalar and an
    int for a sequence of that length (never 0: CDR readers disagree on aligning empty ones)."""

    def __init__(self, name: str, fields: Sequence[tuple[str, np.dtype | type, int | None]]) -> None:
        self.name = name
        self.fields: dict[str, tuple[np.dtype, int | None, int]] = {}  # name -> (dtype, count, offset)
        template = bytearray(HEADER)
        pos = 0  # CDR aligns relative to the body, after the 4-byte header
        for field, dtype, count in fields:
            dtype = np.dtype(dtype)
            if count is not None:
                if count < 1:
                    raise ValueError(f"{name}.{field}: a sequence needs at least one element")
                pos = _align(pos, 4)
                template += bytes(pos + 4 - len(template))
                template[4 + pos : 8 + pos] = np.uint32(count).tobytes()
                pos += 4
            pos = _align(pos, dtype.itemsize)
            self.fields[field] = (dtype, count, 4 + pos)
            pos += dtype.itemsize * (count or 1)
        self.size = 4 + pos
        template += bytes(self.size - len(template))
        self.template = np.frombuffer(bytes(template), dtype=np.uint8)

    @property
    def schema(self) -> str:
        """The ROS 2 message definition."""
        return (
            "\n".join(
                f"{ROS_TYPES[dtype]}{'[]' if count is not None else ''} {field}"
                for field, (dtype, count, _) in self.fields.items()
            )
            + "\n"
        )

    def encode(self, values: Mapping[str, np.ndarray], n: int) -> np.ndarray:
        """``n`` messages as an ``(n, size)`` byte array; ``values[field]`` has one row per message."""
        out = np.empty((n, self.size), dtype=np.uint8)
        out[:] = self.template
        for field, (dtype, count, offset) in self.fields.items():
            width = dtype.itemsize * (count or 1)
            column = np.ascontiguousarray(values[field], dtype=dtype).reshape(n, count or 1)
            out[:, offset : offset + width] = column.view(np.uint8)
        return out

    def decode(self, messages: np.ndarray) -> dict[str, np.ndarray]:
        """Fields of ``(n, size)`` encoded messages: ``(n,)`` for scalars, ``(n, count)`` for sequences."""
        out = {}
        for field, (dtype, count, offset) in self.fields.items():
            width = dtype.itemsize * (count or 1)
            column = np.ascontiguousarray(messages[:, offset : offset + width]).view(dtype)
            out[field] = column[:, 0] if count is None else column
        return out

    @classmethod
    def from_schema(cls, name: str, schema: str, message: bytes) -> Layout:
        """The layout of a recorded channel: field types from its schema, sequence lengths from
        one of its messages."""
        fields = []
        pos = 0
        body = memoryview(message)[4:]
        for line in schema.splitlines():
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            type_name, field = line.split()
            is_sequence = type_name.endswith("[]")
            dtype = DTYPES[type_name.removesuffix("[]")]
            count = None
            if is_sequence:
                pos = _align(pos, 4)
                count = int(np.frombuffer(body[pos : pos + 4], dtype=np.uint32)[0])
                pos += 4
            pos = _align(pos, dtype.itemsize) + dtype.itemsize * (count or 1)
            fields.append((field, dtype, count))
        return cls(name, fields)
