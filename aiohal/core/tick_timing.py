"""Always-on tick statistics: preallocated ring buffers, summarised only when asked.

Recording a tick is a handful of integer stores into numpy arrays (no allocation); percentiles
are computed over the last ``window`` ticks, maxima and counts over the whole run.
"""

from __future__ import annotations

import resource
import time

import numpy as np

PHASES = ("read", "check", "control", "limits", "write", "publish")


def _pow2(n: int) -> int:
    return 1 << max(10, (n - 1).bit_length())


def percentiles_us(samples_ns: np.ndarray) -> dict[str, float]:
    if samples_ns.size == 0:
        return {key: float("nan") for key in ("min", "p50", "p99", "p999", "max")}
    p50, p99, p999 = np.percentile(samples_ns, (50, 99, 99.9)) / 1e3
    return {
        "min": round(float(samples_ns.min()) / 1e3, 2),
        "p50": round(float(p50), 2),
        "p99": round(float(p99), 2),
        "p999": round(float(p999), 2),
        "max": round(float(samples_ns.max()) / 1e3, 2),
    }


class TickStats:
    """Lateness, work time and per-phase time of every tick (ns)."""

    def __init__(self, window: int = 1 << 19) -> None:
        size = _pow2(window)
        self.mask = size - 1
        # np.full writes every page now: a lazily mapped page (np.zeros) faults on its first
        # write, and 8 buffers faulting in the same tick every 512 ticks cost a missed tick
        self.lateness = np.full(size, 0, dtype=np.int64)
        self.work = np.full(size, 0, dtype=np.int64)
        # rows: one per phase of the tick, in PHASES order
        self.phases = np.full((len(PHASES), size), 0, dtype=np.int64)
        self.reset()

    def reset(self) -> None:
        """Forget every tick recorded (the buffers are reused, not reallocated)."""
        self.count = 0
        self.max_lateness = 0
        self.max_work = 0
        self.overruns = 0  # ticks whose work took longer than the period
        self.first_lateness: list[int] = []  # the first ticks, to measure drift against
        self.started_wall_ns = 0
        self.stopped_wall_ns = 0
        self.first_tick_ns = 0
        self.last_tick_ns = 0
        self._ru0: resource.struct_rusage | None = None
        self._ru1: resource.struct_rusage | None = None

    def begin(self) -> None:
        self._ru0 = resource.getrusage(resource.RUSAGE_SELF)
        self.started_wall_ns = time.monotonic_ns()

    def end(self) -> None:
        self._ru1 = resource.getrusage(resource.RUSAGE_SELF)
        self.stopped_wall_ns = time.monotonic_ns()

    def _window(self, arr: np.ndarray) -> np.ndarray:
        return arr[..., : min(self.count, self.mask + 1)]

    def cpu_percent(self) -> float:
        if self._ru0 is None:
            return float("nan")
        ru1 = self._ru1 or resource.getrusage(resource.RUSAGE_SELF)
        wall = ((self.stopped_wall_ns or time.monotonic_ns()) - self.started_wall_ns) / 1e9
        used = (ru1.ru_utime - self._ru0.ru_utime) + (ru1.ru_stime - self._ru0.ru_stime)
        return round(100.0 * used / wall, 2) if wall > 0 else float("nan")

    def drift_ns(self) -> float:
        """How much lateness grew over the run: median of the last 100 ticks minus the first 100.

        A loop on absolute deadlines keeps this near zero whatever its wake latency; a loop that
        sleeps one period per tick accumulates its overhead here.
        """
        if self.count == 0:
            return 0.0
        n = min(100, self.count)
        head = np.median(self.first_lateness[:n])
        last = (self.count - 1 - np.arange(n)) & self.mask
        return float(np.median(self.lateness[last]) - head)

    def summary(self) -> dict:
        lat = self._window(self.lateness)
        work = self._window(self.work)
        phases = self._window(self.phases)
        return {
            "lateness_us": percentiles_us(lat),
            "work_us": percentiles_us(work),
            "phases_us": {
                name: {k: v for k, v in percentiles_us(phases[i]).items() if k in ("p50", "p99", "max")}
                for i, name in enumerate(PHASES)
            },
            "lateness_max_run_us": round(self.max_lateness / 1e3, 2),
            "work_max_run_us": round(self.max_work / 1e3, 2),
            "overruns": self.overruns,
            "drift_us": round(self.drift_ns() / 1e3, 2),
            "cpu_percent": self.cpu_percent(),
            "window_ticks": int(lat.size),
        }
