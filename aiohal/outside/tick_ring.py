"""The tick ring: every tick's state in shared memory, the one door out of the loop's process.

The tick's whole share of every output is one call of a compiled kernel (``record_tick``) that
copies the robot's arrays into the next slot of a ring in a shared-memory segment
(``aiohal.<robot>.ticks``): no allocation, no Python loop over joints or arrays, no system
call. One call with the arrays' addresses in a table instead of one numpy copy per array,
because on the tick's cold caches every call counts (six ``np.copyto`` cost 9-10 µs after a
0.5 ms sleep, the kernel 4 µs).

One producer (the tick), any number of readers (the output processes, a client): the tick
never waits for a reader. It writes slot ``head`` whatever is there, each slot under its own
sequence word (0 while writing, then ``index + 1``), then advances ``head``. A reader keeps its
own position, copies rows and keeps those whose sequence word was the expected one both
before and after the copy; a reader a whole ring behind skips ahead and counts what it lost
(:class:`TickReader`). A slow reader loses its own rows, never another reader's, never a tick.
The stores' order is kept by a compiler fence in the kernel and by the x86-64 memory model
(docs/client.md says the same of the state door).
"""

from __future__ import annotations

import itertools
import json
import os
from multiprocessing import shared_memory
from typing import Any

import numpy as np
from numba import carray, njit, types
from numba.extending import intrinsic

from .shm_segment import MAGIC, SHM_DIR, ShmError, _untrack, pid_alive, segment_name

# meta columns at the start of a slot's row (int64); SEQ first: a reader's copy reads it first
SEQ, TICK, NOW, LEVEL, COUNT, TIMING_VALID, PREV_TICK, PREV_NOW = range(8)
TIMING = 8  # lateness, work, then the 6 phases of the previous tick, in stats.PHASES order
META = TIMING + 8
META_BYTES = META * 8
# the loop's own table (int64): the statistics' addresses, then the kernel's counters
STATS_ROWS = 8  # addresses of lateness, work and the 6 phase rows
LAST_TICK, LAST_NOW, LAST_COUNT, MASK, STATS_MASK = range(STATS_ROWS, STATS_ROWS + 5)
STATE = STATS_ROWS + 5

VERSION = 1
LINE = 64
# the segment's header line (int64), then the producer's line (HEAD), then one line per reader
H_MAGIC, H_VERSION, H_PID, H_STATUS, H_SLOTS, H_ROW_BYTES, H_META_LEN, H_DATA = range(8)
HEAD = 0
# a reader's line: where it is, what it kept and what it lost (the loop reads it when the reader is gone)
C_TAIL, C_KEPT, C_LOST, C_PID, C_START = range(5)
READERS = 8
STATUS_ACTIVE, STATUS_CLOSED = 1, 2


@intrinsic
def _pointer(typingctx, address):
    """An integer address as a byte pointer, for ``carray``."""
    signature = types.CPointer(types.uint8)(types.int64)

    def codegen(context, builder, sig, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.uint8)))

    return signature, codegen


@intrinsic
def _store_fence(typingctx):
    """Stores before it are not moved after stores behind it (on x86-64 a compiler fence only)."""

    def codegen(context, builder, sig, args):
        builder.fence("release")
        return context.get_dummy_value()

    return types.void(), codegen


@njit(
    types.void(
        types.uint8[:, ::1],
        types.int64[:, ::1],
        types.int64[::1],
        types.int64[::1],
        types.int64,
        types.int64,
        types.int64,
        types.int64,
    ),
    cache=True,
)
def record_tick(data, sources, state, producer, count, tick, now_ns, level):  # pragma: no cover
    """Copy one tick into the next slot, whatever it held.

    ``sources`` rows are (address, bytes) of the arrays to copy; ``state`` the addresses of the
    loop's timing rows, then this kernel's counters; ``producer`` the shared line whose first
    word is ``head``. The previous tick's timing is complete now (the loop stores it after the
    publishers), so it is copied with that tick's number when the previous tick was recorded too."""
    head = producer[HEAD]
    row = data[head & state[MASK]]
    m = row[:META_BYTES].view(np.int64)
    m[SEQ] = 0
    _store_fence()
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
    _store_fence()
    m[SEQ] = head + 1
    _store_fence()
    producer[HEAD] = head + 1


def ring_arrays(robot: Any) -> list[tuple[str, np.ndarray]]:
    """The robot's arrays every tick copies, by name: joint state and command blocks, fault
    bits, modes, then each device group's fault bits and values (or its field arrays)."""
    out = [
        ("state", robot.state.block),
        ("command", robot.command.block),
        ("state.fault", robot.state.fault),
        ("command.mode", robot.command.mode),
    ]
    for kind, group in robot.device_groups.items():
        if not len(group):
            continue
        out.append((f"{kind}.fault", group.fault))
        if group.values is not None:
            out.append((f"{kind}.values", group.values))
        else:
            out += [(f"{kind}.{f}", getattr(group, f)) for f in group.fields]
    return out


def ring_name(robot: str, pid: int) -> str:
    """The tick ring of ``robot`` served by process ``pid`` (two runs of one robot never share one)."""
    return f"{segment_name(robot)}.ticks.{pid}"


def find_ring(robot: str) -> str:
    """The name of the tick ring a live process serves for ``robot``: the one its state door
    names (``[client] shm``), else the only one; ShmError if there is none or several."""
    from .shm_segment import H_PID, RobotNotRunning, attach_segment

    try:
        door = attach_segment(robot)
    except (RobotNotRunning, ShmError):
        door = None
    if door is not None:
        pid = int(door.header[H_PID])
        door.release()
        return ring_name(robot, pid)
    prefix = segment_name(robot) + ".ticks."
    found = [
        p.name
        for p in sorted(SHM_DIR.glob(prefix + "*"))
        if p.name[len(prefix) :].isdigit() and pid_alive(int(p.name[len(prefix) :]))
    ]
    if len(found) != 1:
        raise ShmError(
            f"robot {robot!r}: "
            + (f"several processes serve a tick ring ({', '.join(found)}): name the pid" if found else "no tick ring")
        )
    return found[0]


def _round(n: int) -> int:
    return (n + LINE - 1) // LINE * LINE


class _Mapped:
    """Views of a tick segment's parts (either side)."""

    def __init__(self, shm: shared_memory.SharedMemory) -> None:
        self.shm = shm
        buf = shm.buf
        assert buf is not None
        self.header = np.frombuffer(buf, np.int64, 8, 0)
        self.producer = np.frombuffer(buf, np.int64, 8, LINE)
        self.readers = np.frombuffer(buf, np.int64, READERS * 8, 2 * LINE).reshape(READERS, 8)
        meta_at = (2 + READERS) * LINE
        self.layout: dict[str, Any] = json.loads(bytes(buf[meta_at : meta_at + int(self.header[H_META_LEN])]))
        slots, row_bytes = int(self.header[H_SLOTS]), int(self.header[H_ROW_BYTES])
        self.data = np.frombuffer(buf, np.uint8, slots * row_bytes, int(self.header[H_DATA])).reshape(slots, row_bytes)

    def release(self) -> None:
        self.header = self.producer = self.readers = self.data = None  # type: ignore[assignment]
        try:
            self.shm.close()
        except BufferError:  # a caller still holds a view; the mapping goes with the process
            pass


class TickRing:
    """The loop's side: makes the segment and gives the tick its publisher.

    ``arrays`` are the robot's arrays to copy, by name (C-contiguous, never reallocated: the
    kernel holds their addresses, and this object holds the arrays so that they outlive it).
    The segment also says each array's dtype, shape and byte range in a row, so that a reader
    needs nothing else to decode it.
    """

    def __init__(
        self,
        robot: str,
        arrays: list[tuple[str, np.ndarray]],
        slots: int,
        stats_rows: list[np.ndarray],
        stats_mask: int,
        period_ns: int,
    ) -> None:
        for _, a in arrays:
            if not a.flags.c_contiguous:
                raise ValueError("a recorded array must be C-contiguous")
        self.name = ring_name(robot, os.getpid())
        self.arrays = [a for _, a in arrays]
        self.slots = 1 << max(6, (slots - 1).bit_length())
        self.mask = self.slots - 1
        starts = np.cumsum([META_BYTES, *(a.nbytes for a in self.arrays)])
        row_bytes = _round(int(starts[-1]))
        columns = [
            {"name": n, "dtype": a.dtype.str, "shape": list(a.shape), "start": int(s), "stop": int(e)}
            for (n, a), (s, e) in zip(arrays, itertools.pairwise(starts), strict=True)
        ]
        blob = json.dumps({"robot": robot, "period_ns": period_ns, "columns": columns}).encode()
        data_at = _round((2 + READERS) * LINE + len(blob))
        size = data_at + self.slots * row_bytes
        try:
            try:
                shm = shared_memory.SharedMemory(self.name, create=True, size=size)
            except FileExistsError:
                _remove_stale(self.name)
                shm = shared_memory.SharedMemory(self.name, create=True, size=size)
        except OSError as exc:
            raise ShmError(f"robot {robot!r}: cannot make shared memory /dev/shm/{self.name}: {exc}") from None
        buf = shm.buf
        assert buf is not None
        buf[:size] = bytes(size)  # touch every page now, not on the tick's first write to it
        meta_at = (2 + READERS) * LINE
        buf[meta_at : meta_at + len(blob)] = blob
        h = np.frombuffer(buf, np.int64, 8, 0)
        h[H_VERSION], h[H_PID], h[H_STATUS] = VERSION, os.getpid(), STATUS_ACTIVE
        h[H_SLOTS], h[H_ROW_BYTES], h[H_META_LEN], h[H_DATA] = self.slots, row_bytes, len(blob), data_at
        h[H_MAGIC] = MAGIC  # last: a reader that sees the magic sees the shape
        del h
        self._mapped = _Mapped(shm)
        self.data = self._mapped.data
        self.producer = self._mapped.producer
        self.readers = self._mapped.readers
        self.sources = np.array([[a.ctypes.data, a.nbytes] for a in self.arrays], dtype=np.int64).reshape(-1, 2)
        self._stats_rows = list(stats_rows)
        self.state = np.zeros(STATE, dtype=np.int64)
        self.state[:STATS_ROWS] = [r.ctypes.data for r in stats_rows]
        self.state[LAST_COUNT] = -2
        self.state[MASK] = self.mask
        self.state[STATS_MASK] = stats_mask
        from ..core import compiled_entry

        self._kernel = compiled_entry.compiled_for(
            record_tick, (self.data, self.sources, self.state, self.producer, 0, 0, 0, 0)
        )
        self._next_reader = 0

    head = property(lambda self: int(self.producer[HEAD]), doc="slots written (the tick advances it)")

    def publisher(self, port: Any) -> Any:
        """The tick's part: one kernel call into the next slot."""
        kernel, stats, clock = self._kernel, port.timing, port.robot.clock
        data, sources, state, producer = self.data, self.sources, self.state, self.producer

        def record_tick(_: object) -> None:
            kernel(data, sources, state, producer, stats.count, clock.tick, clock.now_ns, port.level)

        return record_tick

    def claim_reader(self, start: int) -> int:
        """A reader line for an output process starting at row ``start``: it reports there where
        it is and what it lost."""
        if self._next_reader >= READERS:
            raise ShmError(f"{self.name}: at most {READERS} output processes")
        i = self._next_reader
        self._next_reader += 1
        self.readers[i] = 0
        self.readers[i, C_TAIL] = self.readers[i, C_START] = start
        return i

    def last_tick(self) -> tuple[int, int, int] | None:
        """(count, tick, now_ns) the kernel last recorded, or None."""
        if self.state[LAST_COUNT] < 0:
            return None
        return int(self.state[LAST_COUNT]), int(self.state[LAST_TICK]), int(self.state[LAST_NOW])

    def close(self) -> None:
        """Mark the segment closed (readers see it at once) and remove it."""
        m = self._mapped
        if m.header is None:
            return
        m.header[H_STATUS] = STATUS_CLOSED
        self.data = self.producer = self.readers = None  # type: ignore[assignment]
        self._kernel = None  # type: ignore[assignment]
        try:
            m.shm.unlink()
        except FileNotFoundError:
            pass
        m.release()


def _remove_stale(name: str) -> None:
    """A tick segment of a process that is gone is replaced; one still served is refused."""
    old = shared_memory.SharedMemory(name)
    try:
        h = np.frombuffer(old.buf, np.int64, 8, 0) if old.size >= 64 else None  # type: ignore[arg-type]
        if h is None or h[H_MAGIC] != MAGIC:
            del h
            raise ShmError(f"/dev/shm/{name} exists and is not an aiohal tick ring; it is left alone")
        pid, status = int(h[H_PID]), int(h[H_STATUS])
        del h
        if pid_alive(pid) and status != STATUS_CLOSED and pid != os.getpid():
            _untrack(old)
            raise ShmError(f"/dev/shm/{name} is served by process {pid}")
        old.unlink()
    finally:
        old.close()


class TickReader:
    """A reader of a tick ring, in any process: :meth:`read` gives the rows it has not seen.

    ``pid``: the loop's process (default: the one live process that serves ``robot``). It
    starts at the ring's head (or at ``start``), keeps its own position and counts the rows
    it lost (``lost``: the ring went round before it read them). With ``line``, it reports its
    position there, for the loop to see what an output process kept and lost.
    """

    def __init__(
        self, robot: str, *, pid: int | None = None, start: int | None = None, line: int | None = None
    ) -> None:
        name = find_ring(robot) if pid is None else ring_name(robot, pid)
        try:
            shm = shared_memory.SharedMemory(name)
        except FileNotFoundError:
            raise ShmError(f"robot {robot!r} publishes no tick ring (/dev/shm/{name})") from None
        h = np.frombuffer(shm.buf, np.int64, 8, 0) if shm.size >= 64 else None  # type: ignore[arg-type]
        if h is None or h[H_MAGIC] != MAGIC or h[H_VERSION] != VERSION:
            del h
            shm.close()
            raise ShmError(f"/dev/shm/{name} is not an aiohal tick ring of version {VERSION}")
        owner = int(h[H_PID])
        del h
        if owner != os.getpid():
            _untrack(shm)
        self._mapped = _Mapped(shm)
        self.data = self._mapped.data
        self.slots = len(self.data)
        self.mask = self.slots - 1
        layout = self._mapped.layout
        self.robot = layout["robot"]
        self.period_ns = int(layout["period_ns"])
        self.columns = [slice(c["start"], c["stop"]) for c in layout["columns"]]
        self.names = [c["name"] for c in layout["columns"]]
        self._types = [(np.dtype(c["dtype"]), tuple(c["shape"])) for c in layout["columns"]]
        self._line = None if line is None else self._mapped.readers[line]
        self.tail = int(self._mapped.producer[HEAD]) if start is None else start
        self.kept = 0
        self.lost = 0
        self._report()

    @property
    def head(self) -> int:
        return int(self._mapped.producer[HEAD])

    @property
    def closed(self) -> bool:
        h = self._mapped.header
        return h is None or int(h[H_STATUS]) == STATUS_CLOSED or not pid_alive(int(h[H_PID]))

    def read(self, limit: int = 64) -> np.ndarray:
        """Up to ``limit`` whole rows after the last one read (a copy, oldest first; possibly none)."""
        head = self.head
        slots = self.slots
        if head - self.tail > slots - slots // 8:  # the tick may be writing where we would read
            skip = head - (slots - slots // 4) - self.tail
            self.lost += skip
            self.tail += skip
        n = min(head - self.tail, limit, slots - (self.tail & self.mask))
        if n <= 0:
            return self.data[:0].copy()
        a = self.tail & self.mask
        rows = self.data[a : a + n].copy()
        expected = np.arange(self.tail + 1, self.tail + n + 1, dtype=np.int64)
        before = rows[:, :8].view(np.int64)[:, SEQ]
        after = self.data[a : a + n, :8].copy().view(np.int64)[:, SEQ]
        good = (before == expected) & (after == expected)
        self.tail += n
        if not good.all():
            rows = rows[good]
            self.lost += n - len(rows)
        self.kept += len(rows)
        self._report()
        return rows

    def _report(self) -> None:
        if self._line is not None:
            self._line[C_TAIL], self._line[C_KEPT], self._line[C_LOST], self._line[C_PID] = (
                self.tail,
                self.kept,
                self.lost,
                os.getpid(),
            )

    def meta(self, rows: np.ndarray) -> np.ndarray:
        """The meta columns of ``rows``, ``(n, META)`` int64."""
        return np.ascontiguousarray(rows[:, :META_BYTES]).view(np.int64)

    def field(self, rows: np.ndarray, index: int) -> np.ndarray:
        """Array ``index`` in ``rows``, shaped ``(n, *array.shape)``."""
        dtype, shape = self._types[index]
        return np.ascontiguousarray(rows[:, self.columns[index]]).view(dtype).reshape(len(rows), *shape)

    def close(self) -> None:
        self._line = None
        self.data = None  # type: ignore[assignment]
        self._mapped.release()


def reader_figures(ring: TickRing, line: int) -> dict[str, int]:
    """What the output process on reader ``line`` kept, as it last said, and the ticks written
    since it started that it did not keep (lost, or never read: it is gone or behind)."""
    r = ring.readers[line]
    kept = int(r[C_KEPT])
    return {"kept": kept, "not_kept": max(0, ring.head - int(r[C_START]) - kept)}
