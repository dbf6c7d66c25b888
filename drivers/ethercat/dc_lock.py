"""The loop's ticks locked to the EtherCAT reference clock (``options.dc_lock``).

Why: the host's clock and the reference clock run at rates some ppm apart, so ticks on host
deadlines slide along the slaves' SYNC0 cycle (50 ppm: a whole 1 ms cycle in 20 s) until their
frames cross SYNC0. Each cycle's frame brings back the reference clock's system time
(``master.dc_time``, from SOEM's FRMW); with the host time of that frame's send it maps host
time to reference time, which gives the reference's time at the tick's deadline. A PI on that
time's phase against the target (half a cycle before SYNC0) shifts the loop's deadlines, as
SOEM's examples adjust their sleep by the reference's time.

It wraps the tick's bound send and receive calls, so the tick pays for it only when it is on.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

KP = 0.02  # part of the phase error taken out at once (the frame's latency jitters it)
KI = 0.0002  # of its sum: takes out the rate difference (ppm) without a standing error
FOLLOW = 256  # the offset estimate rises by 1/FOLLOW of a larger sample's excess
RING = 4096


class DcLock:
    """A PI from the reference clock's phase at the tick's deadline to a shift of the deadlines."""

    def __init__(
        self,
        master: Any,
        send: Callable[[], Any],
        receive: Callable[[], int],
        clock: Any,
        target_ns: int,
    ) -> None:
        """``clock``: the robot's TickInfo (its ``ticker`` and ``period_ns``); ``target_ns``: the
        reference clock's time at a deadline, modulo the period."""
        self.master = master
        self._send_pd, self._receive_pd = send, receive
        self.clock = clock
        self.target_ns = target_ns
        self.integral = 0.0
        self.errors_ns = np.zeros(RING, dtype=np.int64)
        self.count = 0
        self._sent_ns = 0
        self._offset: float | None = None

    def send(self) -> Any:
        self._sent_ns = time.monotonic_ns()  # before: a preemption only adds to the latency
        return self._send_pd()

    def receive(self) -> int:
        wkc = self._receive_pd()
        ticker = self.clock.ticker
        if wkc > 0 and self._sent_ns and ticker is not None:
            self._step(ticker)
        return wkc

    def _step(self, ticker: Any) -> None:
        period = self.clock.period_ns
        # reference time - host time, from the frame: too large by its latency to the reference
        # clock, which jitters (the host, a simulator) but is never negative; the smallest seen,
        # let rise slowly (the clocks' rates differ by ppm)
        sample = self.master.dc_time - self._sent_ns
        offset = self._offset
        self._offset = offset = sample if offset is None or sample < offset else offset + (sample - offset) / FOLLOW
        reference_at_deadline = ticker.deadline_ns + offset
        error = round(reference_at_deadline - self.target_ns) % period
        if error >= period // 2:
            error -= period
        if self.count == 0:  # the first: one step to the target phase (the next period is shorter or longer)
            shift = -error
        else:
            integral = self.integral + error
            shift = -(KP * error + KI * integral)
            limit = period / 100  # a deadline moves by 1 % of a period per tick at most
            if -limit <= shift <= limit:
                self.integral = integral  # (not while the shift is clamped: no wind-up)
            else:
                shift = limit if shift > 0 else -limit
        ticker.shift(round(shift))
        self.errors_ns[self.count % RING] = error
        self.count += 1

    def recent_errors_ns(self) -> np.ndarray:
        """The phase errors of the last cycles (at most :data:`RING`)."""
        return self.errors_ns[: min(self.count, RING)]
