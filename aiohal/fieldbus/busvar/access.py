"""Accessors of bus variables that cannot be numpy views: single bits, bit fields, and a
gather of one variable over many slaves."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

from .errors import ReadOnlyVariableError


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
        return int.from_bytes(self._buf[self._first : self._last].tobytes(), "little")

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
        self._buf[self._first : self._last] = np.frombuffer(raw.to_bytes(self._last - self._first, "little"), np.uint8)

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

    def __init__(
        self,
        name: str,
        buf: np.ndarray,
        byte_offsets: Sequence[int],
        dtype: np.dtype,
        element_shape: tuple[int, ...],
        writable: bool,
    ) -> None:
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

    def __array__(self, dtype: DTypeLike | None = None, copy: bool | None = None) -> np.ndarray:
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
