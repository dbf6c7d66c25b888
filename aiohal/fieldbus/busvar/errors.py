"""The errors of bus variables: a package base and a builtin each, as elsewhere in aiohal."""

from __future__ import annotations

from ...errors import AiohalError


class BusVarError(AiohalError):
    """Base of the errors of bus variables."""


class LayoutError(BusVarError, ValueError):
    """A PDO mapping, name table or image that cannot be used (bring-up)."""


class UnknownVariableError(BusVarError, LookupError):
    """No such slave or variable, or a name that fits several variables."""


class VariableTypeError(BusVarError, TypeError):
    """A variable linked with a type, size or shape it does not have."""


class ReadOnlyVariableError(BusVarError, TypeError):
    """An input (slave → master) linked or written as writable."""
