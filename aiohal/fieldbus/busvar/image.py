"""The process image: one contiguous buffer per direction for all slaves, each slave a slice,
and variables linked by name as numpy views into it."""

from __future__ import annotations

import difflib
import itertools
import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

from .access import BitsVar, BitVar, Gather
from .codec import STRUCT_CODES, RecordCodec
from .errors import LayoutError, ReadOnlyVariableError, UnknownVariableError, VariableTypeError
from .layout import PdoEntry, PdoLayout, Variable, _kind
from .names import NUMPY_TYPES, address, normalise, parse_address

_MEMBER = re.compile(r"(.+)\.(\d+)")


class SlaveImage:
    """One slave's part of the process image: its layout and its slices of the two buffers."""

    def __init__(
        self,
        name: str,
        layout: PdoLayout,
        output_offset: int,
        input_offset: int,
        outputs: np.ndarray,
        inputs: np.ndarray,
    ) -> None:
        self.name = name
        self.layout = layout
        self.output_offset = output_offset  # bytes, in ProcessImage.outputs
        self.input_offset = input_offset
        self.outputs = outputs  # this slave's output bytes (a view)
        self.inputs = inputs  # this slave's input bytes (a view; the driver copies the master's into it)
        self._lookup: dict[str, list[Variable]] = {}  # normalised name or address → what it may mean
        self._display: dict[str, str] = {}  # normalised → canonical name
        self._index()

    def __repr__(self) -> str:
        return (
            f"SlaveImage({self.name!r}, outputs {self.output_offset}+{len(self.outputs)}, "
            f"inputs {self.input_offset}+{len(self.inputs)})"
        )

    def load_inputs(self, data: bytes | bytearray | memoryview) -> None:
        """Copy the master's input bytes of this slave in (one memcpy); the size is checked."""
        if len(data) != len(self.inputs):
            raise LayoutError(f"slave {self.name!r}: got {len(data)} input bytes, its layout has {len(self.inputs)}")
        self.inputs[:] = np.frombuffer(data, dtype=np.uint8)

    def output_bytes(self) -> bytes:
        """This slave's outputs as bytes, for pysoem's ``slave.output = ...`` (which does not check sizes)."""
        return self.outputs.tobytes()

    def check_sizes(self, output_bytes: int, input_bytes: int) -> None:
        """Compare with the sizes the master gives the slave (e.g. ``len(slave.output)``) at bring-up."""
        if (output_bytes, input_bytes) != (len(self.outputs), len(self.inputs)):
            raise LayoutError(
                f"slave {self.name!r}: the master maps {output_bytes} output and {input_bytes} input bytes, "
                f"its PDO layout has {len(self.outputs)} and {len(self.inputs)}"
            )

    def _index(self) -> None:
        """Every name (and address) of this slave → the variables it may mean."""
        groups: dict[tuple[str, str], list[tuple[int, PdoEntry]]] = {}
        for direction, entries, base in (
            ("output", self.layout.outputs, self.output_offset),
            ("input", self.layout.inputs, self.input_offset),
        ):
            for entry in entries:
                if entry.is_padding:
                    continue
                var = Variable(self.name, entry.name, direction, (entry,), base * 8 + entry.bit_offset)
                self._add(entry.name, var)
                if normalise(entry.address) != normalise(entry.name):
                    self._add(entry.address, var, display=False)
                member = _MEMBER.fullmatch(entry.name)
                if member:
                    groups.setdefault((direction, member.group(1)), []).append((int(member.group(2)), entry))
        for (direction, name), members in groups.items():
            if normalise(name) in self._lookup:
                continue  # a variable of that exact name exists: it wins
            members.sort(key=lambda m: m[0])
            entries = tuple(e for _, e in members)
            base = self.output_offset if direction == "output" else self.input_offset
            self._add(
                name,
                Variable(
                    self.name,
                    name,
                    direction,
                    entries,
                    base * 8 + entries[0].bit_offset,
                    group=True,
                    members=tuple(n for n, _ in members),
                ),
            )

    def _add(self, name: str, var: Variable, display: bool = True) -> None:
        key = normalise(name)
        self._lookup.setdefault(key, []).append(var)
        if display:
            self._display.setdefault(key, name)

    def variable(self, name: str) -> Variable:
        where = parse_address(name)
        key = normalise(address(*where) if where else name)
        found = self._lookup.get(key)
        if not found:
            raise UnknownVariableError(f'unknown variable "{self.name}.{name}"{self._hint(key)}')
        if len(found) > 1:
            choices = ", ".join(f'"{self.name}.{v.entries[0].address}"' for v in found)
            raise UnknownVariableError(
                f'"{self.name}.{name}" is ambiguous: it names {len(found)} entries; use an address: {choices}'
            )
        return found[0]

    def _hint(self, key: str) -> str:
        close = difflib.get_close_matches(key, list(self._display), n=1)
        if close:
            return f' (did you mean "{self.name}.{self._display[close[0]]}"?)'
        known = list(self._display.values())
        if not known:
            return f" (slave {self.name!r} maps no process data)"
        listed = ", ".join(known[:12]) + (", ..." if len(known) > 12 else "")
        return f" ({self.name} has: {listed})"


class ProcessImage:
    """All slaves' process data in two ``uint8`` buffers (outputs, inputs), linked by name.

    Slaves with the same PDO layout (as the bus sees it) are placed next to each other in the
    buffers, whatever their bus order, so that the same variable of all of them is evenly
    spaced and :meth:`link_many` can return it as one strided view. The buffers are aiohal's
    own: the driver copies each slave's slice to and from the master every cycle
    (:meth:`SlaveImage.load_inputs`, :meth:`SlaveImage.output_bytes`).
    """

    def __init__(self, slaves: Mapping[str, PdoLayout] | Iterable[tuple[str, PdoLayout]]) -> None:
        items = list(slaves.items() if isinstance(slaves, Mapping) else slaves)
        seen: dict[str, str] = {}
        for name, layout in items:
            if not isinstance(name, str) or not name.strip() or "." in name:
                raise LayoutError(f"slave name {name!r}: expected a non-empty name without '.'")
            if normalise(name) in seen:
                raise LayoutError(f"slave names {seen[normalise(name)]!r} and {name!r} are the same name")
            if not isinstance(layout, PdoLayout):
                raise LayoutError(f"slave {name!r}: expected a PdoLayout, got {type(layout).__name__}")
            seen[normalise(name)] = name
        # placement: identical layouts together, in order of first appearance
        order: dict[Any, list[int]] = {}
        for i, (_, layout) in enumerate(items):
            order.setdefault(layout.signature, []).append(i)
        placed = [i for group in order.values() for i in group]
        offsets: dict[int, tuple[int, int]] = {}
        out_total = in_total = 0
        for i in placed:
            offsets[i] = (out_total, in_total)
            out_total += items[i][1].output_bytes
            in_total += items[i][1].input_bytes
        self.outputs = np.zeros(out_total, dtype=np.uint8)
        self.inputs = np.zeros(in_total, dtype=np.uint8)
        self.slaves: dict[str, SlaveImage] = {}
        self._by_key: dict[str, SlaveImage] = {}
        for i, (name, layout) in enumerate(items):
            out_off, in_off = offsets[i]
            slave = SlaveImage(
                name,
                layout,
                out_off,
                in_off,
                self.outputs[out_off : out_off + layout.output_bytes],
                self.inputs[in_off : in_off + layout.input_bytes],
            )
            self.slaves[name] = slave
            self._by_key[normalise(name)] = slave

    # ------------------------------------------------------------ lookup

    def slave(self, name: str) -> SlaveImage:
        found = self._by_key.get(normalise(name))
        if found is None:
            close = difflib.get_close_matches(normalise(name), list(self._by_key), n=1)
            hint = f' (did you mean "{self._by_key[close[0]].name}"?)' if close else ""
            raise UnknownVariableError(f'unknown slave "{name}"{hint}')
        return found

    __getitem__ = slave

    def variable(self, name: str) -> Variable:
        """Resolve ``"<slave>.<variable>"`` without linking it."""
        slave, sep, var = name.partition(".")
        if not sep or not var:
            raise UnknownVariableError(f'"{name}": expected "<slave>.<variable>", e.g. "drive1.Statusword"')
        return self.slave(slave).variable(var)

    def names(self) -> list[str]:
        """Every linkable name, as ``"<slave>.<name>"`` (addresses not included)."""
        return [f"{s.name}.{n}" for s in self.slaves.values() for n in s._display.values()]

    # ------------------------------------------------------------ linking

    def link(
        self, name: str, dtype: DTypeLike | None = None, *, writable: bool = False
    ) -> np.ndarray | BitVar | BitsVar:
        """A zero-copy view of one variable: 0-d for a single entry, shape (n,) for an object's
        subindices. Bit variables give a :class:`BitVar` / :class:`BitsVar` instead. Outputs are
        read-only unless ``writable``; inputs are always read-only. ``dtype``, when given, must
        be the variable's own (a check, not a conversion)."""
        var = self.variable(name)
        self._check_writable(var, writable)
        buf = self.outputs if var.direction == "output" else self.inputs
        if not var.contiguous or var.type == "mixed":
            members = ", ".join(f'"{var.slave}.{e.name}"' for e in var.entries)
            raise VariableTypeError(
                f'"{var.full_name}" cannot be linked as one variable: its subindices are '
                f"not contiguous, not numbered 1..n or not of one type; link them one by one: {members}"
            )
        if not var.byte_aligned:
            if dtype is not None:
                raise VariableTypeError(
                    f'"{var.full_name}" is {var.bits} bit(s) from bit {var.bit_offset % 8} of a byte: not whole '
                    "bytes on a byte boundary, so it has no array view; link it without dtype for a bit accessor"
                )
            if var.bits == 1:
                return BitVar(var.full_name, buf, var.bit_offset, writable)
            return BitsVar(var.full_name, buf, var.bit_offset, var.bits, writable)
        dt = self._check_dtype(var, dtype)
        view = np.ndarray(var.shape, dtype=dt, buffer=buf, offset=var.bit_offset // 8)
        view.flags.writeable = writable
        return view

    def link_many(
        self,
        slaves: Sequence[str],
        name: str,
        dtype: DTypeLike | None = None,
        *,
        writable: bool = False,
        gather: bool = True,
    ) -> np.ndarray | Gather:
        """The same variable of several slaves as one array of shape (len(slaves), ...), in the
        order given: a strided zero-copy view when the slaves are evenly spaced in the image
        (identical layouts listed in image order always are), else a :class:`Gather` (or an
        error if ``gather`` is False)."""
        if isinstance(slaves, str) or not slaves:
            raise UnknownVariableError(f'link_many("{name}"): expected a non-empty list of slave names')
        variables = [self.variable(f"{s}.{name}") for s in slaves]
        first = variables[0]
        keys = [normalise(v.slave) for v in variables]
        if len(set(keys)) != len(keys):
            raise UnknownVariableError(f'link_many("{name}"): a slave is listed twice in {list(slaves)}')
        for var in variables:
            self._check_writable(var, writable)
            if not var.byte_aligned:
                raise VariableTypeError(
                    f'"{var.full_name}" is not a byte-aligned numeric variable: bit variables '
                    "cannot be linked across slaves; link each with link()"
                )
            if (var.type, var.shape, var.direction) != (first.type, first.shape, first.direction):
                raise VariableTypeError(f'"{var.full_name}" is {_kind(var)}, but "{first.full_name}" is {_kind(first)}')
        dt = self._check_dtype(first, dtype)
        buf = self.outputs if first.direction == "output" else self.inputs
        offsets = [v.bit_offset // 8 for v in variables]
        element = first.shape
        element_strides = (dt.itemsize,) if element else ()
        if len(offsets) == 1:
            stride = dt.itemsize * max(1, int(np.prod(element)))
            evenly = True
        else:
            stride = offsets[1] - offsets[0]
            evenly = stride > 0 and all(b - a == stride for a, b in itertools.pairwise(offsets))
        if evenly:
            view = np.ndarray(
                (len(offsets), *element), dtype=dt, buffer=buf, offset=offsets[0], strides=(stride, *element_strides)
            )
            view.flags.writeable = writable
            return view
        if not gather:
            raise VariableTypeError(
                f'"{name}" of {list(slaves)} is not evenly spaced in the image (byte offsets '
                f"{offsets}), so it has no single view; list the slaves in image order or allow gather"
            )
        return Gather(f"{name} of {len(slaves)} slaves", buf, offsets, dt, element, writable)

    def codec(self, slave: str, names: Sequence[str], *, writable: bool = False) -> RecordCodec:
        """Several byte-aligned variables of one slave (all inputs or all outputs), read or
        written with one ``struct`` call: per value, far cheaper than a numpy call when a
        loop visits a few slaves (numpy's fixed cost per call dominates arrays of 7)."""
        variables = self._byte_variables(slave, names, writable)
        buf = self.outputs if variables[0].direction == "output" else self.inputs
        return RecordCodec(variables, buf)

    def byte_offsets(self, slave: str, names: Sequence[str], *, writable: bool = False) -> list[int]:
        """Where several byte-aligned variables of one slave (all inputs or all outputs) start
        in their buffer (``inputs`` or ``outputs``), checked as :meth:`codec` checks them: for
        code that reads or writes the image's bytes itself (compiled kernels)."""
        return [var.bit_offset // 8 for var in self._byte_variables(slave, names, writable)]

    def _byte_variables(self, slave: str, names: Sequence[str], writable: bool) -> list[Variable]:
        variables = [self.variable(f"{slave}.{name}") for name in names]
        for var in variables:
            self._check_writable(var, writable)
            if not var.byte_aligned or var.type not in STRUCT_CODES:
                raise VariableTypeError(
                    f'"{var.full_name}" ({var.type}, {var.bits} bits) is not a byte-aligned number: no struct codec'
                )
            if var.direction != variables[0].direction:
                raise VariableTypeError(
                    f'"{var.full_name}" is an {var.direction}, "{variables[0].full_name}" an '
                    f"{variables[0].direction}: a codec reads or writes one direction"
                )
        if writable and variables[0].direction == "input":
            raise ReadOnlyVariableError(f'"{variables[0].full_name}" is an input (slave to master): it is read-only')
        return variables

    @staticmethod
    def _check_writable(var: Variable, writable: bool) -> None:
        if writable and var.direction == "input":
            raise ReadOnlyVariableError(f'"{var.full_name}" is an input (slave to master): it is read-only')

    @staticmethod
    def _check_dtype(var: Variable, dtype: DTypeLike | None) -> np.dtype:
        own = NUMPY_TYPES[var.type]
        if dtype is None:
            return own
        try:
            wanted = np.dtype(dtype)
        except TypeError as exc:
            raise VariableTypeError(f'"{var.full_name}": {dtype!r} is not a numpy dtype') from exc
        if wanted.itemsize != own.itemsize:
            raise VariableTypeError(
                f'"{var.full_name}" is {var.type} ({own.itemsize * 8} bits per element), '
                f"{wanted} has {wanted.itemsize * 8} bits: size mismatch"
            )
        if wanted != own:
            raise VariableTypeError(f'"{var.full_name}" is {var.type} (little-endian), not {wanted}: type mismatch')
        return own
