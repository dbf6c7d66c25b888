"""The ring buffer between the tick and the recorder's writer thread.

The tick's whole share of recording is one call of a compiled kernel (``record_tick``) that
copies the robot's arrays into the next slot: no allocation, no Python loop over joints or
arrays, no system call. One call with the arrays' addresses in a table instead of one numpy
copy per array, because on the tick's cold caches every call counts: six ``np.copyto`` cost
9-10 µs after a 0.5 ms sleep, the kernel 4 µs (``python -m benchmarks.record`` measures the
whole recorder against recording off).

Single producer (the tick), single consumer (the writer): the tick writes slot ``head`` only
while ``head - tail`` is below the ring's size and then advances ``head``; the writer reads
``[tail, head)`` and then advances ``tail``. When the writer is a whole ring behind, the tick
drops its copy and counts it (``dropped``): the tick never waits.
"""

from __future__ import annotations

import itertools

import numpy as np
from numba import carray, njit, types
from numba.extending import intrinsic

# meta columns at the start of a slot's row (int64)
TICK, NOW, LEVEL, COUNT, TIMING_VALID, PREV_TICK, PREV_NOW = range(7)
TIMING = 7  # lateness, work, then the 6 phases of the previous tick, in stats.PHASES order
META = TIMING + 8
META_BYTES = META * 8
# the shared state table (int64): the statistics' addresses, then the kernel's and the ring's counters
STATS_ROWS = 8  # addresses of lateness, work and the 6 phase rows
LAST_TICK, LAST_NOW, LAST_COUNT, HEAD, TAIL, DROPPED, MASK, STATS_MASK = range(STATS_ROWS, STATS_ROWS + 8)
STATE = STATS_ROWS + 8


@intrinsic
def _pointer(typingctx, address):
    """An integer address as a byte pointer, for ``carray``."""
    signature = types.CPointer(types.uint8)(types.int64)

    def codegen(context, builder, sig, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.uint8)))

    return signature, codegen


# not nogil: releasing the GIL for the call would let the writer thread take it mid-tick
@njit(
    types.void(
        types.uint8[:, ::1], types.int64[:, ::1], types.int64[::1], types.int64, types.int64, types.int64, types.int64
    ),
    cache=True,
)
def record_tick(data, sources, state, count, tick, now_ns, level):  # pragma: no cover
    """Copy one tick into the next free slot, or count a drop when the ring is full.

    ``sources`` rows are (address, bytes) of the arrays to copy; ``state`` the addresses of the
    loop's timing rows, then this kernel's and the ring's counters. The previous tick's timing
    is complete now (the loop stores it after the publishers), so it is copied with that
    tick's number when the previous tick was recorded too."""
    head = state[HEAD]
    if head - state[TAIL] > state[MASK]:
        state[DROPPED] += 1
        return
    row = data[head & state[MASK]]
    m = row[:META_BYTES].view(np.int64)
    m[TICK] = tick
    m[NOW] = now_ns
    m[LEVEL] = level
    m[COUNT] = count
    valid = count > 0 and state[LAST_COUNT] == count - 1
    m[TIMING_VALID] = valid
    m[PREV_TICK] = state[LAST_TICK]
    m[PREV_NOW] = state[LAST_NOW]
    if valid:
        j = (count - 1) & state[STATS_MASK]
        for r in range(STATS_ROWS):
            m[TIMING + r] = carray(_pointer(state[r] + 8 * j), 8).view(np.int64)[0]
    state[LAST_TICK] = tick
    state[LAST_NOW] = now_ns
    state[LAST_COUNT] = count
    offset = META_BYTES
    for i in range(sources.shape[0]):
        size = sources[i, 1]
        row[offset : offset + size] = carray(_pointer(sources[i, 0]), size)
        offset += size
    state[HEAD] = head + 1


class TickRing:
    """Preallocated slots of every recorded array, filled by the tick through ``record_tick``.

    ``arrays`` are the robot's arrays to copy (C-contiguous, never reallocated: the kernel holds
    their addresses, and this object holds the arrays so that they outlive it). ``columns[i]``
    is the byte range of ``arrays[i]`` in a slot's data row.
    """

    def __init__(self, arrays: list[np.ndarray], slots: int, stats_rows: list[np.ndarray], stats_mask: int) -> None:
        for a in [*arrays, *stats_rows]:
            if not a.flags.c_contiguous:
                raise ValueError("a recorded array must be C-contiguous")
        self.arrays = list(arrays)
        self.slots = 1 << max(6, (slots - 1).bit_length())
        self.mask = self.slots - 1
        sizes = [a.nbytes for a in arrays]
        starts = np.cumsum([META_BYTES, *sizes])
        self.columns = [slice(int(a), int(b)) for a, b in itertools.pairwise(starts)]
        # np.full touches every page now, not on the tick's first write to it
        self.data = np.full((self.slots, int(starts[-1])), 0, dtype=np.uint8)
        self.sources = np.array([[a.ctypes.data, a.nbytes] for a in arrays], dtype=np.int64).reshape(-1, 2)
        self._stats_rows = list(stats_rows)
        self.state = np.zeros(STATE, dtype=np.int64)
        self.state[:STATS_ROWS] = [r.ctypes.data for r in stats_rows]
        self.state[LAST_COUNT] = -2
        self.state[MASK] = self.mask
        self.state[STATS_MASK] = stats_mask

    # the counters live in ``state``, where the kernel reads and writes them
    head = property(lambda self: int(self.state[HEAD]), doc="slots written (the tick advances it)")
    dropped = property(lambda self: int(self.state[DROPPED]), doc="ticks not recorded: the ring was full")

    @property
    def tail(self) -> int:
        """Slots consumed (the writer advances it)."""
        return int(self.state[TAIL])

    @tail.setter
    def tail(self, value: int) -> None:
        self.state[TAIL] = value

    def meta(self, data: np.ndarray) -> np.ndarray:
        """The meta columns of rows ``data``, ``(n, META)`` int64."""
        return np.ascontiguousarray(data[:, :META_BYTES]).view(np.int64)

    def field(self, data: np.ndarray, index: int) -> np.ndarray:
        """Array ``index`` in rows ``data`` (a slice of :attr:`data`), shaped ``(n, *array.shape)``."""
        a = self.arrays[index]
        cols = data[:, self.columns[index]]
        return np.ascontiguousarray(cols).view(a.dtype).reshape(len(data), *a.shape)
