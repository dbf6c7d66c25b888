"""Calling a compiled (numba) kernel on the tick without numba's per-call dispatch.

numba's dispatcher types every argument on every call to choose a compiled version: for a
kernel of nine arguments that is most of the call (``python -m benchmarks.kernel_call``,
figures in docs/performance.md). A kernel with one explicit signature has one compiled
version, and :func:`compiled_for` returns its entry point. That entry point checks almost
nothing: an array of another dtype of the same item size is misread, a strided array in a
C-contiguous kernel reads the wrong memory, a read-only array is written, and an array of
more dimensions than the signature's can crash the process. So the only way to it is
:func:`compiled_for`, which checks the arrays it will be called on (dtype, dimensions,
layout, writable) as the dispatch would; its callers hold those arrays for their lifetime
(the robot's blocks are never reallocated) and check again whenever they are handed another.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np


def compiled_for(kernel: Any, args: Sequence[Any]) -> Callable[..., Any]:
    """The compiled version of ``kernel`` (which has exactly one explicit signature), to be
    called on the arrays of ``args``: they are checked here first (:func:`check`), and the
    caller passes those same arrays on every call, or calls this again for new ones."""
    if len(kernel.signatures) != 1:
        raise TypeError(
            f"{kernel.py_func.__qualname__}: one explicit signature is needed for a direct call, "
            f"it has {len(kernel.signatures)}"
        )
    check(kernel, args)
    return kernel.get_overload(kernel.signatures[0])


def check(kernel: Any, args: Sequence[Any]) -> None:
    """Raise TypeError unless every array in ``args`` fits the kernel's signature as numba's
    dispatch would require (dtype, dimensions, contiguity, writable where written); other
    arguments are converted by the entry point itself."""
    (signature,) = kernel.nopython_signatures
    if len(args) != len(signature.args):
        raise TypeError(f"{kernel.py_func.__qualname__} takes {len(signature.args)} arguments, got {len(args)}")
    for position, (arg, expected) in enumerate(zip(args, signature.args, strict=True)):
        if not hasattr(expected, "ndim"):  # a scalar
            continue
        why = _misfit(arg, expected)
        if why:
            raise TypeError(f"{kernel.py_func.__qualname__}, argument {position}: {why} (needs {expected})")


def _misfit(arg: Any, expected: Any) -> str:
    from numba.np.numpy_support import as_dtype

    if not isinstance(arg, np.ndarray):
        return f"{type(arg).__name__} is not a numpy array"
    if arg.dtype != as_dtype(expected.dtype) or arg.ndim != expected.ndim:
        return f"a {arg.ndim}-d {arg.dtype} array"
    if expected.layout == "C" and not arg.flags.c_contiguous:
        return "not C-contiguous"
    if expected.layout == "F" and not arg.flags.f_contiguous:
        return "not Fortran-contiguous"
    if expected.mutable and not arg.flags.writeable:
        return "read-only, and the kernel writes it"
    if not arg.flags.aligned:
        return "not aligned"
    return ""
