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

import numpy as np
from numba import carray, njit, types
from numba.extending import intrinsic

# meta columns of a slot (int64)
TICK, NOW, LEVEL, COUNT, TIMING_VALID, PREV_TICK, PREV_NOW = range(7)
TIMING = 7  # lateness, work, then the 6 phases of the previous tick, in stats.PHASES order
META = TIMING + 8
# the kernel's state, after the statistics' addresses in its ``stats`` table
STATS_ROWS = 8  # addresses of lateness, work and the 6 phase rows
LAST_TICK, LAST_NOW, LAST_COUNT = STATS_ROWS, STATS_ROWS + 1, STATS_ROWS + 2
STATS_TABLE = STATS_ROWS + 3


@intrinsic
def _pointer(typingctx, address):
    """An integer address as a byte pointer, for ``carray``."""
    signature = types.CPointer(types.uint8)(types.int64)

    def codegen(context, builder, sig, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.uint8)))

    return signature, codegen


@njit(types.void(types.int64[:, ::1], types.uint8[:, ::1], types.int64[:, ::1], types.int64[::1],
                 types.int64, types.int64, types.int64, types.int64, types.int64, types.int64),
      cache=True, nogil=True)
def record_tick(meta, data, sources, stats, slot, count, stats_mask, tick, now_ns, level):  # pragma: no cover
    """Copy one tick into ``slot``: ``sources`` rows are (address, bytes) of the arrays to copy,
    ``stats`` the addresses of the loop's timing rows and the kernel's own state. The previous
    tick's timing is complete now (the loop stores it after the publishers), so it is copied
    with that tick's number when the previous tick was recorded too."""
    m = meta[slot]
    m[TICK] = tick
    m[NOW] = now_ns
    m[LEVEL] = level
    m[COUNT] = count
    valid = count > 0 and stats[LAST_COUNT] == count - 1
    m[TIMING_VALID] = valid
    m[PREV_TICK] = stats[LAST_TICK]
    m[PREV_NOW] = stats[LAST_NOW]
    if valid:
        j = (count - 1) & stats_mask
        for row in range(STATS_ROWS):
            m[TIMING + row] = carray(_pointer(stats[row] + 8 * j), 8).view(np.int64)[0]
    stats[LAST_TICK] = tick
    stats[LAST_NOW] = now_ns
    stats[LAST_COUNT] = count
    row = data[slot]
    offset = 0
    for i in range(sources.shape[0]):
        size = sources[i, 1]
        row[offset: offset + size] = carray(_pointer(sources[i, 0]), size)
        offset += size


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
        starts = np.cumsum([0, *sizes])
        self.columns = [slice(int(a), int(b)) for a, b in zip(starts[:-1], starts[1:], strict=True)]
        # np.full touches every page now, not on the tick's first write to it
        self.meta = np.full((self.slots, META), 0, dtype=np.int64)
        self.data = np.full((self.slots, max(1, int(starts[-1]))), 0, dtype=np.uint8)
        self.sources = np.array([[a.ctypes.data, a.nbytes] for a in arrays], dtype=np.int64).reshape(-1, 2)
        self._stats_rows = list(stats_rows)
        self.stats = np.zeros(STATS_TABLE, dtype=np.int64)
        self.stats[:STATS_ROWS] = [r.ctypes.data for r in stats_rows]
        self.stats[LAST_COUNT] = -2
        self.stats_mask = stats_mask
        self.head = 0  # slots written (the tick advances it)
        self.tail = 0  # slots consumed (the writer advances it)
        self.dropped = 0  # ticks not recorded because the ring was full

    def field(self, data: np.ndarray, index: int) -> np.ndarray:
        """Array ``index`` in rows ``data`` (a slice of :attr:`data`), shaped ``(n, *array.shape)``."""
        a = self.arrays[index]
        cols = data[:, self.columns[index]]
        return np.ascontiguousarray(cols).view(a.dtype).reshape(len(data), *a.shape)

    def pending(self) -> list[slice]:
        """The written, unconsumed slots ``[tail, head)`` as at most two slices of the ring."""
        tail, head = self.tail, self.head
        if head == tail:
            return []
        a, b = tail & self.mask, head & self.mask
        if a < b:
            return [slice(a, b)]
        return [slice(a, self.slots), slice(0, b)] if b else [slice(a, self.slots)]
