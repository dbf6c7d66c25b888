"""``stream``: follow time-stamped joint setpoints that another process writes into the
robot's shared-memory ring (``aiohal.client``; LOLA's planner-to-hardware FIFO).

Between two points the command is interpolated at the tick's time: linearly, or by a cubic
Hermite curve when both points carry velocities. A point stamped 0 is due at once. Past the
last point the command holds it; when no newer point arrives within ``dry_after_s`` the
controller raises, and the loop replaces it by ``hold`` and records the fault. A point flagged
final ends the stream instead: it is held at rest for as long as it takes, without a fault,
and the next point starts a new stream from there (no re-arm). Before the first point the
robot holds where it started, for as long as it takes.

A point that is not finite or lies outside a joint's range is refused and counted, never
applied. The ring's indices come from another process, so the tick trusts none of them: it
keeps the tail itself, takes at most the ring's capacity per tick, and a head behind the tail
or more than a capacity ahead of it is a corrupt ring, a fault (:class:`StreamCorrupt`) that
holds the robot. The stream is then detached: later points are ignored until the robot is
re-armed, when the controller starts again from the head as it then is. Needs
``[client] shm = true`` (the config check says so).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from aiohal.errors import AiohalError
from aiohal.hal import Controller, Options
from aiohal.outside import shm_door, shm_segment
from aiohal.robot import Mode

LATENCY_WINDOW = 1 << 16


class StreamUnderrun(AiohalError, RuntimeError):
    """The setpoint stream ran dry for longer than the controller may hold."""


class StreamCorrupt(AiohalError, RuntimeError):
    """The ring's head is out of range of the tail: a writer broke the ring's protocol."""


class StreamParams(Options):
    dry_after_s: float = Field(
        0.1,
        gt=0,
        description="After the last point's time, hold it this long "
        "waiting for the next, then fault (the loop goes to hold).",
    )


class _Point:
    """A point in the controller's hands: time, positions, velocities (preallocated)."""

    __slots__ = ("t", "q", "v", "has_v", "final")

    def __init__(self, n: int) -> None:
        self.t = 0
        self.q = np.zeros(n)
        self.v = np.zeros(n)
        self.has_v = False
        self.final = False


class StreamController(Controller):
    Params = StreamParams
    params: StreamParams  # what configure() stores, typed as this controller's

    def start(self, t: float) -> None:
        door = shm_door.door(self.robot.name)
        if door is None:
            raise shm_segment.ShmError("the stream controller reads the shared-memory ring: set [client] shm = true")
        seg = door.segment
        robot = self.robot
        n = robot.dof
        self._seg = seg
        self._head = seg.producer.data.cast("B").cast("q")
        self._cons = seg.consumer.data.cast("B").cast("q")
        self._capacity = seg.layout.capacity
        self._words = seg.slot_words
        self._pos = seg.slot_position
        self._vel = seg.slot_velocity
        self._a, self._b = _Point(n), _Point(n)
        self._has_b = False
        self._scratch = np.zeros(n)
        self._ok = np.zeros(n, dtype=bool)
        cmd = robot.command
        cmd.mode[:] = Mode.POSITION
        cmd.effort[:] = 0.0
        cmd.feedforward[:] = 0.0
        # until the first point: hold where the command is, at rest
        np.copyto(self._a.q, cmd.position)
        self._a.t = robot.clock.now_ns
        self._streaming = False
        self._dry_ns = int(self.params.dry_after_s * 1e9)
        self._period_ns = robot.clock.period_ns
        self._latency = np.zeros(LATENCY_WINDOW, dtype=np.int64)
        self._lat = self._latency.data
        self.applied = 0
        self.refused = 0
        self.underruns = 0
        self.finished = False  # the last stream ended with a final point and nothing followed
        self.streams_finished = 0
        self._cons[shm_segment.C_FINISHED] = 0
        # stale points from before this start are skipped: the consumer starts at the head
        # the tail is ours: kept here, never read back from the segment another process can write
        self._tail = int(self._head[shm_segment.P_HEAD])
        self._cons[shm_segment.C_TAIL] = self._tail
        self._cons[shm_segment.C_STREAMING] = 1
        cmd.velocity[:] = 0.0

    def _take(self, now: int) -> bool:
        """Move the oldest ring point (there is one) into ``_b``; False if it was refused."""
        cons = self._cons
        tail = self._tail
        i = tail % self._capacity
        words = self._words[i]
        b = self._b
        q = b.q
        np.copyto(q, self._pos[i])
        flags = int(words[shm_segment.SLOT_FLAGS])
        b.has_v = bool(flags & shm_segment.FLAG_VELOCITY)
        b.final = bool(flags & shm_segment.FLAG_FINAL)
        if b.has_v:
            np.copyto(b.v, self._vel[i])
        t = int(words[shm_segment.SLOT_T_NS])
        sent = int(words[shm_segment.SLOT_SENT_NS])
        self._tail = tail + 1
        cons[shm_segment.C_TAIL] = tail + 1  # the slot is ours now: the producer may reuse it
        robot = self.robot
        ok = self._ok
        np.isfinite(q, out=ok)
        good = ok.all()
        if good:
            np.greater_equal(q, robot.position_min, out=ok)
            good = ok.all()
            np.less_equal(q, robot.position_max, out=ok)
            good = good and ok.all()
        if good and b.has_v:
            np.isfinite(b.v, out=ok)
            good = ok.all()
        if not good:
            self.refused += 1
            cons[shm_segment.C_REFUSED] = self.refused
            return False
        b.t = now if t <= 0 else t
        if sent > 0:
            self._lat[self.applied & (LATENCY_WINDOW - 1)] = now - sent
        return True

    def update(self, t: float, dt: float) -> None:
        now = self.robot.clock.now_ns
        a = self._a
        # one read of the head per tick, checked before use: it bounds what this tick consumes
        head = int(self._head[shm_segment.P_HEAD])
        ahead = head - self._tail
        if not 0 <= ahead <= self._capacity:
            raise StreamCorrupt(
                f"the setpoint ring's head is {ahead} points ahead of the tail, outside 0..{self._capacity}: "
                "the stream is detached until the robot is re-armed"
            )
        # consume every point that is due: the newest due one becomes ``a``
        while True:
            if not self._has_b:
                while self._tail != head:
                    if self._take(now):  # else refused: try the next
                        self._has_b = True
                        break
                if not self._has_b:
                    break
                if not self._streaming:  # a stream's first point: the path starts where the command is
                    self._streaming = True
                    a.t = now
                    if self.finished:
                        self.finished = False
                        self._cons[shm_segment.C_FINISHED] = 0
            b = self._b
            if b.t > now:
                break
            self._a, self._b = b, a  # b is due: it becomes the start of the next segment
            a = b
            self._has_b = False
            self.applied += 1
            self._cons[shm_segment.C_APPLIED] = self.applied
            if a.final:
                self._finish(a)
        cmd = self.robot.command
        if self._has_b:
            self._interpolate(a, self._b, now, cmd)
            return
        # dry: hold the last point
        np.copyto(cmd.position, a.q)
        cmd.velocity.fill(0.0)
        if self._streaming and now - a.t > self._dry_ns:
            self.underruns += 1
            raise StreamUnderrun(
                f"no setpoint for {(now - a.t) / 1e9:.3f} s after the last one "
                f"(dry_after_s = {self.params.dry_after_s:g})"
            )

    def _finish(self, a: _Point) -> None:
        """The stream ended at ``a``: hold it at rest with no deadline; a new point restarts
        from here, starting at rest (a zero velocity for a Hermite segment)."""
        self._streaming = False
        self.finished = True
        self.streams_finished += 1
        self._cons[shm_segment.C_FINISHED] = 1
        a.v.fill(0.0)

    def _interpolate(self, a: _Point, b: _Point, now: int, cmd) -> None:
        span = (b.t - a.t) * 1e-9
        s = (now - a.t) * 1e-9 / span if span > 0 else 1.0
        pos, vel = cmd.position, cmd.velocity
        if not (a.has_v and b.has_v):
            np.subtract(b.q, a.q, out=vel)
            np.multiply(vel, s, out=pos)
            pos += a.q
            vel *= 1.0 / span if span > 0 else 0.0
            return
        # cubic Hermite on s in [0, 1] with tangents v·span
        s2, s3 = s * s, s * s * s
        h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
        d10, d01, d11 = 3 * s2 - 4 * s + 1, -6 * s2 + 6 * s, 3 * s2 - 2 * s  # dh/ds; dh00/ds = -d01
        tmp = self._scratch
        np.multiply(a.q, h00, out=pos)
        np.multiply(b.q, h01, out=tmp)
        pos += tmp
        np.multiply(a.v, h10 * span, out=tmp)
        pos += tmp
        np.multiply(b.v, h11 * span, out=tmp)
        pos += tmp
        # d/dt = (d/ds) / span
        np.subtract(b.q, a.q, out=vel)
        vel *= d01 / span
        np.multiply(a.v, d10, out=tmp)
        vel += tmp
        np.multiply(b.v, d11, out=tmp)
        vel += tmp

    def stop(self) -> None:
        cons = getattr(self, "_cons", None)
        if cons is not None:
            try:
                cons[shm_segment.C_STREAMING] = 0
            except ValueError:  # the segment is already gone
                pass
        # drop every view of the segment so that the door can unmap it
        self._head = self._cons = self._words = self._pos = self._vel = self._seg = None  # type: ignore[assignment]

    def latencies_ns(self, since: int = 0) -> np.ndarray:
        """Client write to the tick that took it, of the points applied since the ``since``-th
        (the last 65536 at most); stamps are CLOCK_MONOTONIC, so on a real clock only."""
        end = getattr(self, "applied", 0)
        start = max(since, end - LATENCY_WINDOW)
        idx = np.arange(start, end) & (LATENCY_WINDOW - 1)
        return self._latency[idx] if end else np.zeros(0, dtype=np.int64)

    def metrics(self) -> dict:
        out = {
            "points_applied": getattr(self, "applied", 0),
            "points_refused": getattr(self, "refused", 0),
            "underruns": getattr(self, "underruns", 0),
            "finished": getattr(self, "finished", False),
            "streams_finished": getattr(self, "streams_finished", 0),
        }
        n = min(getattr(self, "applied", 0), LATENCY_WINDOW)
        if n and self.robot.clock.kind != "virtual":
            lat = self._latency[:n] / 1e3
            out["latency_us_p50"] = round(float(np.percentile(lat, 50)), 1)
            out["latency_us_p99"] = round(float(np.percentile(lat, 99)), 1)
            out["latency_us_max"] = round(float(lat.max()), 1)
            out["latency_ticks_p99"] = round(float(np.percentile(lat, 99)) * 1e3 / self._period_ns, 3)
        return out
