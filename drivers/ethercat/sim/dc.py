"""One ESC's distributed clock: a local clock with its own drift, and the time control loop
that locks the local copy of the system time to the reference clock's.

Why a model of its own: the SYNC0 pulses of two slaves are as far apart as their copies of the
system time, so the error the master fights (drift between crystals) and what the ESC does
about it (drift compensation from the propagated time) have to be simulated, not shared.

Time is the segment's clock (host ns: ``time.monotonic_ns``, or a test's fake clock). The local
clock runs at ``(1 + drift) * (1 + speed)`` of it, ``speed`` being the loop's correction; the
system time is the local time plus the offset (0x0920). Errors are in this model's time, so
they do not depend on when the host ran the simulator.

The time control loop runs on every write of the system time (0x0910: the master's ARMW/FRMW
carrying the reference clock's time, or any write): ``ΔT = (local time + offset) - (written
time + delay 0x0928)``, averaged over about 2^depth writes (0x0934, bits 0-3), goes to 0x092C
(bit 31: the local copy is behind). Then, as the ESC does with its 9/11 ns steps, the local copy
is slewed by a part of -ΔT (at most :data:`MAX_SLEW` of the elapsed time), and the speed is
corrected by the integral of ΔT, slower for a larger speed counter start (0x0930). A write of
0x0930 restarts the loop. The gains are this simulator's, not a datasheet's.
"""

from __future__ import annotations

PHASE_GAIN = 0.25  # part of the filtered difference slewed away after each write
MAX_SLEW = 1e-3  # phase correction: at most 1 us per ms
MAX_SPEED = 1e-3  # the speed correction's range (+-1000 ppm)
SPEED_SCALE_NS = 1 << 16  # integral gain = 1 / (speed counter start * this), per ns of difference
SPEED_COUNTER_START = 0x1000  # 0x0930 at power-on


class DcClock:
    """A local clock with a drift, its offset and delay, and the ESC's time control loop."""

    def __init__(self, now: int, boot_ns: int, drift_ppm: float = 0.0) -> None:
        self.drift = drift_ppm * 1e-6
        self.offset = 0  # 0x0920 (u64, added modulo 2^64)
        self.delay = 0  # 0x0928
        self.depth = 4  # 0x0934 bits 0-3
        self.speed_start = SPEED_COUNTER_START
        self._h0 = now  # anchor: host time, local time there
        self._l0 = float(boot_ns)
        self.compensating = True  # False: writes of 0x0910 are compared but change nothing
        self.restart()

    def restart(self) -> None:
        """The loop from scratch (a write of 0x0930): no speed correction, no filtered difference."""
        self.speed = 0.0
        self.diff = 0.0  # filtered ΔT (ns)
        self._pending = 0.0  # phase correction still to slew (ns)
        self._samples = 0

    # ------------------------------------------------------------ reading the clock
    def _rate(self) -> float:
        return (1.0 + self.drift) * (1.0 + self.speed)

    def _slewed(self, dt: int) -> float:
        if dt <= 0:  # (a time before the last anchor: a slave further along the line)
            return 0.0
        p = self._pending
        most = MAX_SLEW * dt
        return p if -most <= p <= most else (most if p > 0 else -most)

    def local_f(self, now: int) -> float:
        dt = now - self._h0
        return self._l0 + dt * self._rate() + self._slewed(dt)

    def local(self, now: int) -> int:
        return int(self.local_f(now))

    def system(self, now: int) -> int:
        return (self.local(now) + self.offset) & ((1 << 64) - 1)

    def system_f(self, now: int) -> float:
        """The system time without the modulo (for differences between clocks)."""
        return self.local_f(now) + self.offset

    def _anchor(self, now: int) -> None:
        dt = now - self._h0
        self._l0 += dt * self._rate() + self._slewed(dt)
        self._pending -= self._slewed(dt)
        self._h0 = now

    # ------------------------------------------------------------ the time control loop
    def received(self, now: int, value: int, bits: int = 64) -> int:
        """The system time ``value`` was written at ``now`` (host time of this slave); the
        filtered difference as the ESC shows it in 0x092C."""
        self._anchor(now)
        mod = 1 << bits
        dt = (self.system(now) - value - self.delay) % mod
        if dt >= mod // 2:
            dt -= mod
        depth = self.depth & 0x0F
        self.diff = float(dt) if self._samples == 0 or depth == 0 else self.diff + (dt - self.diff) / (1 << depth)
        self._samples += 1
        if self.compensating:
            self._pending = -PHASE_GAIN * self.diff
            ki = 1.0 / (max(self.speed_start, 1) * SPEED_SCALE_NS)
            self.speed = min(MAX_SPEED, max(-MAX_SPEED, self.speed - ki * self.diff))
        return register_difference(self.diff)

    def set_offset(self, now: int, offset: int) -> None:
        self._anchor(now)
        self.offset = offset

    def set_drift(self, now: int, drift_ppm: float) -> None:
        self._anchor(now)
        self.drift = drift_ppm * 1e-6

    def set_speed_start(self, now: int, value: int) -> None:
        self._anchor(now)
        self.speed_start = value
        self.restart()

    def summary(self) -> dict[str, float]:
        return {"speed_ppm": self.speed * 1e6, "difference_ns": self.diff, "writes": self._samples}


def register_difference(diff: float) -> int:
    """0x092C: the magnitude in bits 0-30, bit 31 set when the local copy is behind."""
    mag = min(int(abs(diff)), 0x7FFF_FFFF)
    return mag | (0x8000_0000 if diff < 0 else 0)
