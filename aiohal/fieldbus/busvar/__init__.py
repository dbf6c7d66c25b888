"""Bus variables (as in LOLA's EtherCAT layer): process data linked by name, as zero-copy views.

A :class:`PdoLayout` says where each mapped object sits in one slave's output image (RxPDO,
master → slave) and input image (TxPDO, slave → master). It is built at bring-up from what the
slave reports: the CoE PDO assignment (0x1C12/0x1C13) and mapping objects (0x16xx/0x1Axx),
or the SII TXPDO/RXPDO categories of a slave without a mailbox. Names come from a name table
keyed by (index, subindex): one for the standard CiA 402 objects here, one per device a bus driver
knows by identity (kept by that driver), overridable per device from the configuration.

A :class:`ProcessImage` holds one contiguous ``uint8`` buffer for the outputs of every slave and
one for the inputs; each slave has a slice of each. The driver copies a slave's slice to and
from the master once per cycle (pysoem hands out per-slave byte copies). ``link("drive1.Statusword")``
returns a numpy view into that buffer, so reading or writing a variable costs nothing beyond
the array access, and ``link_many(drives, "Statusword")`` returns the same variable of many
slaves as one strided array. Names, types, sizes and directions are checked once, at link
time, with errors that say what is wrong.

Naming rules (see also docs/ethercat.md):

* a variable is ``"<slave>.<name>"``; both parts are case-insensitive, and spaces and
  underscores are the same (``"drive1.target_position"`` is ``"drive1.Target position"``);
* the entry of subindex *n* of an object with subindices is ``"<object>.<n>"`` (decimal), e.g.
  ``"imu.Orientation.1"``; the object's name alone (``"imu.Orientation"``) links all its mapped
  subindices as one array (element i is subindex i+1) when they are numbered 1..n, contiguous
  and of one type;
* any entry can also be named by its address, ``"drive1.0x6041:00"`` (hex, as in CoE).

The package's modules, one job each: ``names`` (types, name tables, addresses), ``layout``
(:class:`PdoLayout`), ``image`` (:class:`ProcessImage` and its variables), ``access`` (bit and
gather accessors), ``codec`` (:class:`RecordCodec`), ``errors``; everything is importable from
``aiohal.fieldbus.busvar`` itself.
"""

from __future__ import annotations

from .access import BitsVar, BitVar, Gather
from .codec import STRUCT_CODES, RecordCodec
from .errors import BusVarError, LayoutError, ReadOnlyVariableError, UnknownVariableError, VariableTypeError
from .image import ProcessImage, SlaveImage
from .layout import PdoEntry, PdoLayout, PdoList, RawEntry, Variable
from .names import (
    CIA402_NAMES,
    NUMPY_TYPES,
    TYPE_BITS,
    NameTable,
    address,
    canonical_type,
    decode_mapping,
    encode_mapping,
    names_for,
    normalise,
    object_entries,
    parse_address,
    parse_names,
)

__all__ = [
    "CIA402_NAMES",
    "NUMPY_TYPES",
    "STRUCT_CODES",
    "TYPE_BITS",
    "BitVar",
    "BitsVar",
    "BusVarError",
    "Gather",
    "LayoutError",
    "NameTable",
    "PdoEntry",
    "PdoLayout",
    "PdoList",
    "ProcessImage",
    "RawEntry",
    "ReadOnlyVariableError",
    "RecordCodec",
    "SlaveImage",
    "UnknownVariableError",
    "Variable",
    "VariableTypeError",
    "address",
    "canonical_type",
    "decode_mapping",
    "encode_mapping",
    "names_for",
    "normalise",
    "object_entries",
    "parse_address",
    "parse_names",
]
