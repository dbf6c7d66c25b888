"""A simulated gripper that behaves like a slow, blocking device.

Each ``read`` blocks for a random I/O time (a serial or Modbus round trip), so the hand
service's loop runs at a slow, jittery rate, as a real NRT hand driver does. Fingers move
toward the grasp target at a speed-dependent rate and stop on an object when one is set.
"""

from __future__ import annotations

import random
import time

from .base import FAULT_NONE, HandBackend, HandError, HandStatus


class SimHand(HandBackend):
    def __init__(
        self,
        *,
        stroke_time_s: float = 0.7,
        object_at: float | None = None,
        io_time_s: tuple[float, float] = (0.001, 0.006),
        activation_s: float = 0.05,
        fail_open: bool = False,
        seed: int | None = None,
    ) -> None:
        """``object_at``: closing stops there with the object detected; ``io_time_s``: range of
        the random time each read blocks; ``fail_open``: activation fails (for tests)."""
        self.stroke_time_s = stroke_time_s
        self.object_at = object_at
        self.io_time_s = tuple(io_time_s)
        self.activation_s = activation_s
        self.fail_open = fail_open
        self._random = random.Random(seed)
        self._position = 0.0
        self._target = 0.0
        self._speed = 1.0
        self._force = 1.0
        self._last = time.monotonic()
        self._ready = False

    def open(self) -> None:
        if self.fail_open:
            raise HandError("activation failed (simulated)")
        time.sleep(self.activation_s)  # blocking, like a real activation sequence
        self._last = time.monotonic()
        self._ready = True

    def command(self, grasp: float, speed: float, force: float) -> None:
        self._advance()
        self._target, self._speed, self._force = grasp, max(speed, 1.0 / 6.0), force

    def _advance(self) -> None:
        now = time.monotonic()
        step = (now - self._last) * self._speed / self.stroke_time_s
        self._last = now
        target = self._target
        if self.object_at is not None and self._position <= self.object_at < target:
            target = self.object_at  # the fingers close on the object and stop there
        self._position += max(-step, min(step, target - self._position))

    def read(self) -> HandStatus:
        time.sleep(self._random.uniform(*self.io_time_s))
        self._advance()
        on_object = (
            self.object_at is not None and self._target > self.object_at and abs(self._position - self.object_at) < 1e-9
        )
        return HandStatus(
            position=self._position,
            effort=self._force if on_object else 0.0,
            object_detected=on_object,
            fault=FAULT_NONE,
            ready=self._ready,
        )
