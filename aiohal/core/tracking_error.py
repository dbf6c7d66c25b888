"""LOLA's tracking error, the one definition the learning and every benchmark use: the
desired position θd(t) against the link position measured at the same instant t.

A reading that a driver hands over at tick k may have been measured before that tick: an
EtherCAT slave answers a frame with the inputs it latched in the cycle before. ``delay``
(ticks) says by how much; the error of tick k is then the target of tick k − delay (the
desired position at the instant the reading was taken) against the reading of tick k.
Comparing a target with a later reading instead would hide the time a target takes to reach
the joint, which is the lag the velocity feed-forward is there to make up for.
"""

from __future__ import annotations

import numpy as np


def tracking_error(desired: np.ndarray, measured: np.ndarray, delay: int = 0) -> np.ndarray:
    """θd − θ over ticks (axis 0): ``desired[k - delay] - measured[k]`` for k ≥ delay."""
    if delay < 0:
        raise ValueError("a reading cannot come before it was measured: delay >= 0")
    desired, measured = np.asarray(desired), np.asarray(measured)
    n = min(len(desired), len(measured))
    return desired[: n - delay] - measured[delay:n]


class TrackingError:
    """:func:`tracking_error` tick by tick, for ``n`` joints (no allocation per tick)."""

    def __init__(self, n: int, delay: int = 0) -> None:
        if delay < 0:
            raise ValueError("a reading cannot come before it was measured: delay >= 0")
        self.delay = delay
        self._desired = np.zeros((delay + 1, n))  # a ring of the last delay + 1 targets
        self._ticks = 0

    def update(self, desired: np.ndarray, measured: np.ndarray, out: np.ndarray) -> bool:
        """Record this tick's target; the error of this tick's reading into ``out``. False (and
        ``out`` untouched) while fewer than ``delay`` targets came before."""
        ring = self._desired
        ring[self._ticks % len(ring)] = desired
        self._ticks += 1
        if self._ticks <= self.delay:
            return False
        np.subtract(ring[self._ticks % len(ring)], measured, out=out)  # the oldest: tick k - delay
        return True
