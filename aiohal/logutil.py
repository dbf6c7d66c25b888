"""Rate-limited warnings for the hot path: at most one line per key per interval.

The library logs through stdlib ``logging`` only; the CLI decides how lines are rendered.
"""

from __future__ import annotations

import logging
import time


class RateLimitedLogger:
    def __init__(self, logger: logging.Logger, interval_s: float = 5.0) -> None:
        self.logger = logger
        self.interval_ns = int(interval_s * 1e9)
        self._last: dict[str, int] = {}
        self._suppressed: dict[str, int] = {}

    def log(self, level: int, key: str, msg: str, *args: object) -> bool:
        """Log unless ``key`` was logged within the interval; returns whether it was logged."""
        now = time.monotonic_ns()
        last = self._last.get(key)
        if last is not None and now - last < self.interval_ns:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        self._last[key] = now
        suppressed = self._suppressed.pop(key, 0)
        if suppressed:
            msg += " (%d similar suppressed)"
            args = (*args, suppressed)
        self.logger.log(level, msg, *args)
        return True

    def warning(self, key: str, msg: str, *args: object) -> bool:
        return self.log(logging.WARNING, key, msg, *args)
