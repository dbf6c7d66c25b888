"""The loop's one tick ring, shared by every output: the first that opens it makes it and puts
its publisher on the tick; the last that lets go removes both.

Between ``activate()`` and ``run()`` the door writes tick 0 (the state the activation read,
where the controller started) once, for the first reader that starts then; every reader that
starts before the run reads from there (:meth:`TickDoor.start_index`).
"""

from __future__ import annotations

from . import tick_ring as R
from .port import LoopPort


def make_ring(port: LoopPort, buffer_ticks: int) -> R.TickRing:
    """A tick ring of the loop's robot holding ``buffer_ticks`` ticks (rounded up to a power of 2)."""
    stats = port.timing
    return R.TickRing(
        port.robot.name,
        R.ring_arrays(port.robot),
        buffer_ticks,
        [stats.lateness, stats.work, *stats.phases],
        stats.mask,
        port.period_ns,
    )


class TickDoor:
    """The ring and its publisher (the tick's whole share of every output)."""

    def __init__(self, port: LoopPort, buffer_ticks: int) -> None:
        self.port = port
        self.ring = make_ring(port, buffer_ticks)
        self.publish = self.ring.publisher(port)
        self.users = 0
        self._tick0: int | None = None

    def start_index(self) -> int:
        """Where a reader starting now begins: before the run, tick 0's row (written by the
        first reader that asks once the loop is active: the state the activation read);
        else the next row."""
        port = self.port
        if port.active and port.tick == 0:
            if self._tick0 is None:
                self._tick0 = self.ring.head
                self.publish(None)
            return self._tick0
        return self.ring.head


def open_door(port: LoopPort, buffer_ticks: int) -> TickDoor:
    """The loop's tick door (made with ``buffer_ticks`` slots by its first user); every caller
    calls :func:`close_door` once when done."""
    door = port.tick_door
    if door is None:
        door = port.tick_door = TickDoor(port, buffer_ticks)
        port.at_tick_end(door.publish)
    door.users += 1
    return door


def close_door(door: TickDoor) -> None:
    """One user less; the last takes the publisher off the tick and removes the ring."""
    door.users -= 1
    if door.users > 0:
        return
    port = door.port
    port.stop_calling(door.publish)
    door.publish = None  # it holds views of the ring's memory
    if port.tick_door is door:
        port.tick_door = None
    door.ring.close()
