"""The slaves' SYNC0 errors against the reference clock, over time: what an oscilloscope on
their SYNC0 pins would show, taken from the simulated clocks (control command ``dc_trace``).

A slave fires SYNC0 when its copy of the system time reaches the pulse's time, so its pulse
comes ``reference's system time - its own`` later than the reference's (to within its rate,
1 +- 1e-3). Sampled when the reference clock's time is propagated (the cyclic ARMW/FRMW), at
most once per ``every_ns`` of the segment's clock (0.5 ms: every cycle of a 1 kHz master whose
frames come a little early or late), the last ``MAX_SAMPLES`` kept.
"""

from __future__ import annotations

import random
from collections import deque
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .esc import Esc

MAX_SAMPLES = 100_000
MASK64 = (1 << 64) - 1


def drifts(count: int, spread_ppm: float, seed: int) -> list[float]:
    """Each slave's clock drift (ppm): the first at -spread/2, the last at +spread/2 (so the
    line spans ``spread_ppm``), the others drawn between them from ``seed``."""
    if count < 2 or not spread_ppm:
        return [0.0] * count
    rng = random.Random(seed * 7919 + 1)
    half = spread_ppm / 2
    return [-half] + [rng.uniform(-half, half) for _ in range(count - 2)] + [half]


class DcTrace:
    """Samples of every slave's SYNC0 error (ns) against the reference clock."""

    def __init__(self, every_ns: int = 500_000) -> None:
        self.every_ns = every_ns
        self.samples: deque[tuple[int, int, tuple[int | None, ...]]] = deque(maxlen=MAX_SAMPLES)
        self._next = 0

    def sample(self, now: int, reference: Esc, slaves: Sequence[Esc]) -> None:
        if now < self._next:
            return
        self._next = now + self.every_ns
        ref = reference.system_time(now)
        errors: list[int | None] = []
        for esc in slaves:
            if not esc.has_dc or esc.position < reference.position:
                errors.append(None)
                continue
            e = (ref - esc.system_time(now)) & MASK64
            errors.append(e - (1 << 64) if e >= 1 << 63 else e)
        self.samples.append((now, reference.position, tuple(errors)))

    def clear(self) -> None:
        self.samples.clear()
        self._next = 0

    def as_dict(self, since_ns: int = 0, step: int = 1) -> dict[str, Any]:
        """Samples at or after ``since_ns`` (segment clock), every ``step``-th; per slave, the
        largest error of all of them."""
        chosen = [s for s in self.samples if s[0] >= since_ns]
        n = len(chosen[0][2]) if chosen else 0
        worst: list[int | None] = [None] * n
        for _, _, errors in chosen:
            for i, e in enumerate(errors):
                if e is not None and (worst[i] is None or abs(e) > abs(worst[i])):  # type: ignore[arg-type]
                    worst[i] = e
        kept = chosen[:: max(1, step)]
        return {
            "t_ns": [s[0] for s in kept],
            "reference": [s[1] for s in kept],
            "errors_ns": [list(s[2]) for s in kept],
            "worst_ns": worst,
            "samples": len(chosen),
        }
