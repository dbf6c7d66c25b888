"""The pipe's messages: a fixed little-endian layout of at most :data:`MAX_MESSAGE` bytes, a
16-byte header (magic ``b"AH"``, version, type, seq, stamp_ns) and the fields of a
:class:`Message` subclass, registered by its ``TYPE``; and the errors of the pipe."""

from __future__ import annotations

import struct
from typing import Any, ClassVar

from ..errors import AiohalError

MAX_MESSAGE = 256  # bytes, header included
HEADER = struct.Struct("<2sBBIQ")  # magic, version, type, seq, stamp_ns
MAGIC = b"AH"
VERSION = 1
_PREFIX = MAGIC + bytes([VERSION])
_SEQ = struct.Struct("<I")  # the seq field, at offset 4 of the header
_SEQ_MASK = 0xFFFFFFFF
_HALF_SEQ = 1 << 31

_CODES = {code: 0 for code in "bBhHiIlLqQ"} | {code: 0.0 for code in "efd"} | {"?": False}
_RESERVED = frozenset({"seq", "stamp_ns", "TYPE", "FIELDS"})


class PipeError(AiohalError):
    """Base of the pipe's errors."""


class MalformedMessage(PipeError, ValueError):
    """Bytes that are not a message of a registered type (or field values that cannot be encoded)."""


class MessageDefinitionError(PipeError, TypeError):
    """A :class:`Message` subclass whose TYPE or FIELDS cannot be registered."""


# ---------------------------------------------------------------- messages

_REGISTRY: dict[int, type[Message]] = {}


class Message:
    """A typed message with a fixed little-endian layout; subclass with ``TYPE`` and ``FIELDS``.

    ``TYPE`` (1..255) must be unique in the process; ``FIELDS`` is a tuple of (name, struct code)
    pairs, one scalar each (``?bBhHiIlLqQefd``). Instances take the fields as keywords (missing
    ones are zero) and carry the header's ``seq`` and ``stamp_ns`` (set by the sender's send()).
    Equality compares the type and the field values, not the header.
    """

    TYPE: ClassVar[int]
    FIELDS: ClassVar[tuple[tuple[str, str], ...]] = ()
    _names: ClassVar[tuple[str, ...]] = ()
    _defaults: ClassVar[dict[str, Any]] = {}
    _struct: ClassVar[struct.Struct]

    seq: int
    stamp_ns: int

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        name = f"{cls.__module__}.{cls.__qualname__}"
        type_id = cls.__dict__.get("TYPE")
        if type(type_id) is not int or not 1 <= type_id <= 255:
            raise MessageDefinitionError(f"{name}: TYPE must be an int in 1..255 in the class body, not {type_id!r}")
        try:
            fields = tuple((str(n), str(c)) for n, c in cls.FIELDS)
        except (TypeError, ValueError):
            raise MessageDefinitionError(f"{name}: FIELDS must be (name, struct code) pairs") from None
        names = [n for n, _ in fields]
        for field, code in fields:
            if not field.isidentifier() or field.startswith("_") or field in _RESERVED:
                raise MessageDefinitionError(f"{name}: field name {field!r} is not allowed")
            if code not in _CODES:
                raise MessageDefinitionError(f"{name}.{field}: struct code {code!r} is not one of {''.join(_CODES)}")
        if len(set(names)) != len(names):
            raise MessageDefinitionError(f"{name}: duplicate field names in {names}")
        layout = struct.Struct(HEADER.format + "".join(c for _, c in fields))
        if layout.size > MAX_MESSAGE:
            raise MessageDefinitionError(
                f"{name}: {layout.size} bytes with the header, more than MAX_MESSAGE = {MAX_MESSAGE}"
            )
        other = _REGISTRY.get(type_id)
        # the same class defined again (a module reloaded) replaces itself; any other is a clash
        if other is not None and (other.__module__, other.__qualname__) != (cls.__module__, cls.__qualname__):
            raise MessageDefinitionError(f"{name}: TYPE {type_id} is already {other.__module__}.{other.__qualname__}")
        cls.FIELDS = fields
        cls._names = tuple(names)
        cls._defaults = {n: _CODES[c] for n, c in fields}
        cls._struct = layout
        _REGISTRY[type_id] = cls

    def __init__(self, **fields: Any) -> None:
        unknown = fields.keys() - self._defaults.keys()
        if unknown:
            raise TypeError(f"{type(self).__name__} has no field(s) {', '.join(sorted(unknown))}")
        self.seq = 0
        self.stamp_ns = 0
        self.__dict__.update(self._defaults)
        self.__dict__.update(fields)

    def encode(self) -> bytes:
        try:
            return self._struct.pack(
                MAGIC, VERSION, self.TYPE, self.seq, self.stamp_ns, *[getattr(self, n) for n in self._names]
            )
        except (struct.error, OverflowError) as exc:  # a value out of its field's range or of the wrong kind
            raise MalformedMessage(f"cannot encode {self!r}: {exc}") from None

    @staticmethod
    def decode(data: bytes | bytearray | memoryview) -> Message:
        """The message in ``data`` (one whole datagram); raises :class:`MalformedMessage`."""
        cls = _check(data)
        if isinstance(cls, str):
            raise MalformedMessage(cls)
        return cls._unpack(data)

    @classmethod
    def _unpack(cls, data: bytes | bytearray | memoryview) -> Message:
        _, _, _, seq, stamp_ns, *values = cls._struct.unpack(data)
        msg = cls.__new__(cls)
        fields = msg.__dict__
        fields["seq"] = seq
        fields["stamp_ns"] = stamp_ns
        fields.update(zip(cls._names, values, strict=True))
        return msg

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(getattr(self, n) == getattr(other, n) for n in self._names)

    __hash__ = None  # type: ignore[assignment]  # mutable

    def __repr__(self) -> str:
        fields = ", ".join(f"{n}={getattr(self, n, '?')!r}" for n in self._names)
        return f"{type(self).__name__}(seq={self.seq}, stamp_ns={self.stamp_ns}{', ' if fields else ''}{fields})"


def _check(data: bytes | bytearray | memoryview) -> type[Message] | str:
    """The registered class whose layout ``data`` has exactly, or why not (a string)."""
    n = len(data)
    if n < HEADER.size:
        return f"{n} bytes, shorter than the {HEADER.size}-byte header"
    magic, version, type_id, _, _ = HEADER.unpack_from(data)
    if magic != MAGIC:
        return f"bad magic {bytes(magic)!r}"
    if version != VERSION:
        return f"version {version}, expected {VERSION}"
    cls = _REGISTRY.get(type_id)
    if cls is None:
        return f"unknown message type {type_id}"
    if n != cls._struct.size:
        return f"{n} bytes for {cls.__name__}, expected {cls._struct.size}"
    return cls
