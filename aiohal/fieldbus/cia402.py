"""The CiA 402 drive state machine seen from the master: statusword in, controlword out.

Pure logic without I/O, shared by the EtherCAT and CANopen drivers. The drive runs the
real state machine (CiA 402 / IEC 61800-7-201); the master only observes it through the
statusword and asks for transitions through the controlword. :class:`Cia402Drive` does that
for one drive, once per bus cycle: it walks the transitions one step at a time toward the
requested target, sends at most one fault reset per request (a fault that persists is
reported, not hammered), says when the driver must hold the target position at the actual
one (bumpless enable), and notices when a transition makes no progress.

:class:`DriveUnits` converts between joint-side SI units and the drive's integer units (encoder
counts, per mille of rated torque), for one drive or, with array parameters, for all drives
of a bus at once.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum, IntEnum, IntFlag
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

# ---------------------------------------------------------------- statusword and controlword


class Statusword(IntFlag):
    """Bits of the statusword (0x6041). Bits 12-13 depend on the mode of operation."""

    READY_TO_SWITCH_ON = 1 << 0
    SWITCHED_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5  # active low: 0 while a quick stop is active
    SWITCH_ON_DISABLED = 1 << 6
    WARNING = 1 << 7
    REMOTE = 1 << 9
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT_ACTIVE = 1 << 11
    OPERATION_MODE_SPECIFIC_12 = 1 << 12  # CSP/CSV/CST: the drive follows the target value
    OPERATION_MODE_SPECIFIC_13 = 1 << 13  # CSP: following error


class Controlword(IntFlag):
    """Bits of the controlword (0x6040). Bits 4-6 depend on the mode of operation."""

    SWITCH_ON = 1 << 0
    ENABLE_VOLTAGE = 1 << 1
    QUICK_STOP = 1 << 2  # active low: 0 requests a quick stop
    ENABLE_OPERATION = 1 << 3
    FAULT_RESET = 1 << 7  # acts on the rising edge only
    HALT = 1 << 8


# Device control commands (the low byte of the controlword). Plain ints: two share a value.
SHUTDOWN = 0x06
SWITCH_ON = 0x07
ENABLE_OPERATION = 0x0F
DISABLE_VOLTAGE = 0x00
QUICK_STOP = 0x02
DISABLE_OPERATION = 0x07
FAULT_RESET = 0x80


class OperationMode(IntEnum):
    """Modes of operation (0x6060, displayed in 0x6061)."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


PP, PV, PT = OperationMode.PROFILE_POSITION, OperationMode.PROFILE_VELOCITY, OperationMode.PROFILE_TORQUE
CSP, CSV, CST = (
    OperationMode.CYCLIC_SYNC_POSITION,
    OperationMode.CYCLIC_SYNC_VELOCITY,
    OperationMode.CYCLIC_SYNC_TORQUE,
)


class State(IntEnum):
    """The drive's state as decoded from the statusword; UNKNOWN for a pattern the standard does not define."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7
    UNKNOWN = 8

    @property
    def label(self) -> str:
        """The state's name as the standard writes it ("Switch on disabled")."""
        return self.name.replace("_", " ").capitalize()


# (mask, value, state): the standard's patterns over bits 0-3, 5 and 6.
_PATTERNS = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)


def _decode_slow(statusword: int) -> State:
    for mask, value, state in _PATTERNS:
        if statusword & mask == value:
            return state
    return State.UNKNOWN


# The state depends on bits 0-6 only, so a 128-entry table decodes any statusword.
_STATE_OF_LOW7 = tuple(_decode_slow(sw) for sw in range(128))
_STATE_TABLE = np.array([int(s) for s in _STATE_OF_LOW7], dtype=np.uint8)


def decode_state(statusword: int) -> State:
    """The drive state a statusword reports."""
    return _STATE_OF_LOW7[int(statusword) & 0x7F]


def decode_states(statuswords: ArrayLike) -> np.ndarray:
    """The states of many drives at once, as ``uint8`` codes of :class:`State` (one table lookup)."""
    return _STATE_TABLE[np.bitwise_and(statuswords, 0x7F)]


# ---------------------------------------------------------------- the master's side of the state machine


class Target(Enum):
    """What the driver wants from a drive."""

    ENABLED = "enabled"  # Operation enabled: the drive follows its targets
    DISABLED = "disabled"  # Switch on disabled: power stage off (Disable voltage from any state)
    QUICK_STOP = "quick_stop"  # stop with the drive's quick stop ramp (0x6085, 0x605A)


class EventKind(Enum):
    STATE_CHANGED = "state_changed"
    BECAME_ENABLED = "became_enabled"
    LOST_ENABLED = "lost_enabled"  # left Operation enabled, for whatever reason
    QUICK_STOP_ACTIVE = "quick_stop_active"
    FAULT_ENTERED = "fault_entered"  # Fault reaction active or Fault, with the error code (0x603F)
    FAULT_RESET_SENT = "fault_reset_sent"
    FAULT_CLEARED = "fault_cleared"
    STUCK = "stuck"  # no progress toward the target for ``stuck_after`` cycles


@dataclass(frozen=True, slots=True)
class DriveEvent:
    """Something that happened in one cycle; ``str()`` is a log line."""

    kind: EventKind
    drive: str
    state: State
    previous: State | None = None
    error_code: int = 0
    cycles: int = 0
    target: Target | None = None

    def __str__(self) -> str:
        who = f"drive {self.drive!r}" if self.drive else "drive"
        match self.kind:
            case EventKind.STATE_CHANGED:
                prev = self.previous.label if self.previous is not None else "?"
                return f"{who}: {prev} -> {self.state.label}"
            case EventKind.FAULT_ENTERED:
                return f"{who}: fault, error code 0x{self.error_code:04X} ({self.state.label})"
            case EventKind.STUCK:
                target = self.target.value if self.target else "?"
                extra = ": the fault reset did not clear it" if self.state is State.FAULT else ""
                return f"{who}: no progress for {self.cycles} cycles in {self.state.label} (target {target}){extra}"
            case _:
                return f"{who}: {self.kind.value} ({self.state.label})"


_FAULTY = frozenset({State.FAULT_REACTION_ACTIVE, State.FAULT})

# States in which a target needs no further transition (a fault is reported, not "stuck").
_REACHED = {
    Target.ENABLED: frozenset({State.OPERATION_ENABLED}),
    Target.DISABLED: frozenset({State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED, State.FAULT}),
    Target.QUICK_STOP: frozenset(
        {State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED, State.QUICK_STOP_ACTIVE, State.FAULT}
    ),
}

# The next controlword per target and state, one standard transition at a time. Quick stop
# active is left through Disable voltage (transition 12), which every quick stop option code
# allows, and the walk up starts again from Switch on disabled.
_NEXT = {
    Target.ENABLED: {
        State.NOT_READY_TO_SWITCH_ON: DISABLE_VOLTAGE,  # the drive leaves it by itself
        State.SWITCH_ON_DISABLED: SHUTDOWN,  # 2
        State.READY_TO_SWITCH_ON: SWITCH_ON,  # 3
        State.SWITCHED_ON: ENABLE_OPERATION,  # 4
        State.OPERATION_ENABLED: ENABLE_OPERATION,
        State.QUICK_STOP_ACTIVE: DISABLE_VOLTAGE,  # 12
        State.FAULT_REACTION_ACTIVE: DISABLE_VOLTAGE,
        State.FAULT: DISABLE_VOLTAGE,
    },
    Target.DISABLED: dict.fromkeys(State, DISABLE_VOLTAGE),  # 7, 9, 10, 12
    Target.QUICK_STOP: {
        State.NOT_READY_TO_SWITCH_ON: DISABLE_VOLTAGE,
        State.SWITCH_ON_DISABLED: DISABLE_VOLTAGE,
        State.READY_TO_SWITCH_ON: QUICK_STOP,  # 7
        State.SWITCHED_ON: QUICK_STOP,  # 10
        State.OPERATION_ENABLED: QUICK_STOP,  # 11
        State.QUICK_STOP_ACTIVE: QUICK_STOP,  # held; the drive may go on to Switch on disabled
        State.FAULT_REACTION_ACTIVE: DISABLE_VOLTAGE,
        State.FAULT: DISABLE_VOLTAGE,
    },
}


# The same, as tuples indexed by the state's value (a tuple index is cheaper than hashing an Enum).
# None only for Unknown, which _next_controlword decides without the table
_NEXT_BY_STATE = {
    target: cast("tuple[int, ...]", tuple(table.get(state) for state in State)) for target, table in _NEXT.items()
}
_REACHED_BY_STATE = {target: tuple(state in states for state in State) for target, states in _REACHED.items()}
_IS_FAULTY = tuple(state in _FAULTY for state in State)


class Cia402Drive:
    """The master's half of one drive's state machine; call :meth:`update` once per bus cycle.

    ``update(statusword, error_code)`` returns the controlword to send (the device control
    bits; the driver may OR in mode-specific bits or Halt). After it:

    * ``events`` lists what happened in this cycle (consume it before the next update);
    * ``hold_target`` is True while the driver must write target = actual (position; zero
      velocity and torque targets): in every cycle before the drive is enabled and in the first
      cycle it reports Operation enabled. The controller takes over from the next cycle, which
      gives the driver one cycle to seed the controller's command from the actual position;
    * ``stuck`` is True once the drive made no progress toward the target for ``stuck_after``
      cycles (one ``STUCK`` event; the driver turns it into an error naming the state).

    Fault reset: one rising edge of bit 7, held ``reset_pulse_cycles`` cycles (so that one
    lost frame does not swallow it) or until the drive leaves Fault, then bit 7 stays 0. One
    reset is allowed per request: ``auto_reset`` grants one at construction (drives often
    power up with a stale fault), :meth:`reset_fault` grants another. A pending request
    expires when the drive is seen in Operation enabled, so a fault during operation waits for
    an explicit :meth:`reset_fault`, and recovery stays a decision of the application.
    """

    __slots__ = (
        "_idle",
        "_next",
        "_pulse_left",
        "_reached",
        "_reset_allowed",
        "_reset_watch",
        "_target",
        "controlword",
        "cycles_in_state",
        "error_code",
        "events",
        "hold_target",
        "name",
        "reset_pulse_cycles",
        "state",
        "statusword",
        "stuck",
        "stuck_after",
    )

    def __init__(
        self,
        name: str = "",
        *,
        target: Target = Target.DISABLED,
        stuck_after: int = 1000,
        reset_pulse_cycles: int = 3,
        auto_reset: bool = True,
    ) -> None:
        if stuck_after < 1 or reset_pulse_cycles < 1:
            raise ValueError("stuck_after and reset_pulse_cycles must be at least 1")
        self.name = name
        self.stuck_after = stuck_after
        self.reset_pulse_cycles = reset_pulse_cycles
        self.state = State.UNKNOWN  # until the first update
        self.statusword = 0
        self.controlword = DISABLE_VOLTAGE
        self.error_code = 0  # of the last fault
        self.cycles_in_state = 0  # completed cycles since the state last changed
        self.hold_target = True
        self.stuck = False
        self.events: list[DriveEvent] = []
        self._target = target
        self._next = _NEXT_BY_STATE[target]
        self._reached = _REACHED_BY_STATE[target]
        self._idle = 0  # cycles without progress: reset on a state change or a new request
        self._reset_allowed = auto_reset
        self._pulse_left = 0
        self._reset_watch = False  # a reset was sent and the drive is still in Fault

    # ------------------------------------------------------------ requests

    @property
    def target(self) -> Target:
        return self._target

    @target.setter
    def target(self, target: Target) -> None:
        if target is not self._target:
            self._target = target
            self._next = _NEXT_BY_STATE[target]
            self._reached = _REACHED_BY_STATE[target]
            self._restart_progress()

    def enable(self) -> None:
        self.target = Target.ENABLED

    def disable(self) -> None:
        self.target = Target.DISABLED

    def quick_stop(self) -> None:
        self.target = Target.QUICK_STOP

    def reset_fault(self) -> None:
        """Allow one more fault reset (one edge of bit 7 the next time the drive is in Fault)."""
        self._reset_allowed = True
        self._restart_progress()

    @property
    def enabled(self) -> bool:
        return self.state is State.OPERATION_ENABLED

    @property
    def faulted(self) -> bool:
        return self.state in _FAULTY

    @property
    def cycles_without_progress(self) -> int:
        """Cycles since the state last changed or the last request (what ``stuck_after`` counts)."""
        return self._idle

    @property
    def waiting_for_reset(self) -> bool:
        """In Fault with no reset left to send: only :meth:`reset_fault` moves it on."""
        return self.state is State.FAULT and not self._reset_allowed and not self._pulse_left

    @property
    def warning(self) -> bool:
        return bool(self.statusword & Statusword.WARNING)

    @property
    def target_reached(self) -> bool:
        return bool(self.statusword & Statusword.TARGET_REACHED)

    @property
    def internal_limit_active(self) -> bool:
        return bool(self.statusword & Statusword.INTERNAL_LIMIT_ACTIVE)

    @property
    def voltage_enabled(self) -> bool:
        return bool(self.statusword & Statusword.VOLTAGE_ENABLED)

    # ------------------------------------------------------------ the cycle

    def update(self, statusword: int, error_code: int = 0) -> int:
        """Take this cycle's statusword (and error code 0x603F); return the controlword to send."""
        if self.events:
            self.events.clear()
        statusword = int(statusword)  # a numpy scalar from a bus variable works too
        self.statusword = statusword
        state = _STATE_OF_LOW7[statusword & 0x7F]
        if state is not self.state:
            self._enter(state, int(error_code))
        else:
            self.cycles_in_state += 1
            self._idle += 1
        if _IS_FAULTY[state]:
            if error_code:
                self.error_code = int(error_code)
        elif state is State.OPERATION_ENABLED:
            self._reset_allowed = False  # a pending reset request expires
        if state is State.FAULT or state is State.UNKNOWN or self._pulse_left:
            controlword = self._next_controlword(state)
        else:
            controlword = self._next[state]
        if self._idle >= self.stuck_after and not self.stuck:
            self._check_progress(state)
        self.controlword = controlword
        self.hold_target = not (
            state is State.OPERATION_ENABLED and self._target is Target.ENABLED and self.cycles_in_state >= 1
        )
        return controlword

    def _enter(self, state: State, error_code: int) -> None:
        previous = self.state
        self.state = state
        self.cycles_in_state = 0
        self._restart_progress()
        self._event(EventKind.STATE_CHANGED, previous=previous)
        if state is State.OPERATION_ENABLED:
            self._event(EventKind.BECAME_ENABLED, previous=previous)
        elif previous is State.OPERATION_ENABLED:
            self._event(EventKind.LOST_ENABLED, previous=previous)
        if state is State.QUICK_STOP_ACTIVE:
            self._event(EventKind.QUICK_STOP_ACTIVE, previous=previous)
        if state in _FAULTY and previous not in _FAULTY:
            self.error_code = error_code
            self._event(EventKind.FAULT_ENTERED, previous=previous, error_code=error_code)
        elif previous in _FAULTY and state not in _FAULTY:
            self._reset_watch = False
            self._event(EventKind.FAULT_CLEARED, previous=previous, error_code=self.error_code)

    def _next_controlword(self, state: State) -> int:
        if state is State.FAULT and (self._pulse_left or self._reset_allowed):
            if not self._pulse_left:
                if self.controlword & FAULT_RESET:
                    return DISABLE_VOLTAGE  # bit 7 must be seen low before the edge
                self._reset_allowed = False
                self._pulse_left = self.reset_pulse_cycles
                self._reset_watch = True
                self._idle = 0
                self._event(EventKind.FAULT_RESET_SENT, error_code=self.error_code)
            self._pulse_left -= 1
            return FAULT_RESET
        self._pulse_left = 0  # the drive left Fault: end the pulse now
        if state is State.UNKNOWN:
            return self.controlword & ~FAULT_RESET  # no decision on a pattern we cannot read
        return self._next[state]

    def _check_progress(self, state: State) -> None:
        """Called once ``stuck_after`` cycles passed without progress: is that a stall?"""
        if state is State.FAULT:
            stalled = self._reset_watch  # a reset was sent and did not clear it; else: waiting for reset_fault()
        else:
            stalled = not self._reached[state]
        if stalled:
            self.stuck = True
            self._event(EventKind.STUCK, cycles=self._idle)

    def _restart_progress(self) -> None:
        self._idle = 0
        self.stuck = False

    def _event(self, kind: EventKind, *, previous: State | None = None, error_code: int = 0, cycles: int = 0) -> None:
        self.events.append(DriveEvent(kind, self.name, self.state, previous, error_code, cycles, self._target))

    def __repr__(self) -> str:
        return (
            f"Cia402Drive({self.name!r}, state={self.state.label}, target={self._target.value}, "
            f"controlword=0x{self.controlword:04X})"
        )


# ---------------------------------------------------------------- units

_TWO_PI = 2.0 * math.pi
_I16 = (-(1 << 15), (1 << 15) - 1)
_I32 = (-(1 << 31), (1 << 31) - 1)


class DriveUnits:
    """Joint-side SI units ↔ a drive's integer units, for one drive or an array of drives.

    ``counts_per_rev`` is encoder increments per motor revolution, ``gear_ratio`` motor
    revolutions per joint revolution, ``rated_torque`` the motor's rated torque in N·m (0x6076
    is in mN·m), ``torque_constant`` the motor's N·m/A (needed only for current conversions).
    Joint torque = motor torque × gear ratio (losses ignored). Each parameter may be an array
    (one value per drive; :meth:`stack` builds one from per-drive units): conversions then
    work element-wise on arrays of that shape.

    Positions wrap like the drive's int32 (modulo 2**32); use :class:`Int32Unwrapper` to read
    multi-turn positions across the wrap. Velocities (int32) and torques (int16 per mille)
    saturate. Every conversion takes ``out=`` (e.g. a bus variable's view) so that a tick
    allocates nothing once the shapes are known. Only finite values may reach the int
    conversions (the HAL's command limiter refuses NaN and infinities upstream).
    """

    def __init__(
        self,
        counts_per_rev: ArrayLike = 131072,
        gear_ratio: ArrayLike = 1.0,
        rated_torque: ArrayLike = 1.0,
        torque_constant: ArrayLike | None = None,
    ) -> None:
        self.counts_per_rev = np.asarray(counts_per_rev, dtype=np.float64)
        self.gear_ratio = np.asarray(gear_ratio, dtype=np.float64)
        self.rated_torque = np.asarray(rated_torque, dtype=np.float64)
        self.torque_constant = None if torque_constant is None else np.asarray(torque_constant, dtype=np.float64)
        for name in ("counts_per_rev", "gear_ratio", "rated_torque", "torque_constant"):
            value = getattr(self, name)
            if value is not None and not (np.all(np.isfinite(value)) and np.all(value > 0)):
                raise ValueError(f"{name} must be finite and positive, got {value}")
        self.counts_per_rad = self.counts_per_rev * self.gear_ratio / _TWO_PI
        self.rad_per_count = 1.0 / self.counts_per_rad
        self.per_mille_per_nm = 1000.0 / (self.rated_torque * self.gear_ratio)
        self.nm_per_per_mille = 1.0 / self.per_mille_per_nm
        if self.torque_constant is None:
            self.rated_current = None
        else:
            self.rated_current = self.rated_torque / self.torque_constant
        self._scratch: dict[tuple, np.ndarray] = {}

    @classmethod
    def from_objects(
        cls,
        encoder_increments: ArrayLike,
        motor_revolutions: ArrayLike = 1,
        shaft_revolutions: ArrayLike = 1,
        rated_torque_mnm: ArrayLike = 1000,
        torque_constant: ArrayLike | None = None,
    ) -> DriveUnits:
        """From the drive's objects: 0x608F:01, 0x6091:01/02 and 0x6076 (mN·m)."""
        motor = np.asarray(motor_revolutions, dtype=np.float64)
        shaft = np.asarray(shaft_revolutions, dtype=np.float64)
        return cls(
            encoder_increments, motor / shaft, np.asarray(rated_torque_mnm, dtype=np.float64) / 1000.0, torque_constant
        )

    @classmethod
    def stack(cls, units: Sequence[DriveUnits]) -> DriveUnits:
        """One object for many drives: parameter arrays of shape ``(len(units),)``."""
        if not units:
            raise ValueError("no drive units to stack")
        kts = [u.torque_constant for u in units if u.torque_constant is not None]
        kt = np.array([float(k) for k in kts]) if len(kts) == len(units) else None
        return cls(
            np.array([float(u.counts_per_rev) for u in units]),
            np.array([float(u.gear_ratio) for u in units]),
            np.array([float(u.rated_torque) for u in units]),
            kt,
        )

    # ------------------------------------------------------------ conversions

    def position_to_counts(self, rad: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Joint position (rad) → int32 counts, wrapped modulo 2**32 as the drive counts."""
        work = self._mul(rad, self.counts_per_rad)
        np.rint(work, out=work)
        wide = self._scratch_like(work, np.int64)
        np.copyto(wide, work, casting="unsafe")  # exact below 2**63 counts
        return self._to_int(wide, np.int32, out)  # int64 → int32 keeps the low 32 bits: the wrap

    def counts_to_position(self, counts: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Counts (int32, or int64 from :class:`Int32Unwrapper`) → joint position (rad)."""
        return np.multiply(counts, self.rad_per_count, out=out)

    def velocity_to_counts(self, rad_s: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Joint velocity (rad/s) → counts/s, int32, saturating."""
        work = self._mul(rad_s, self.counts_per_rad)
        return self._to_int(_saturate(work, _I32), np.int32, out)

    def counts_to_velocity(self, counts_s: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        return np.multiply(counts_s, self.rad_per_count, out=out)

    def torque_to_per_mille(self, nm: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Joint torque (N·m) → per mille of the motor's rated torque, int16, saturating."""
        work = self._mul(nm, self.per_mille_per_nm)
        return self._to_int(_saturate(work, _I16), np.int16, out)

    def per_mille_to_torque(self, per_mille: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        return np.multiply(per_mille, self.nm_per_per_mille, out=out)

    def current_to_per_mille(self, amps: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Motor current (A) → per mille of rated current (rated torque / torque constant), int16."""
        work = self._mul(amps, 1000.0 / self._rated_current())
        return self._to_int(_saturate(work, _I16), np.int16, out)

    def per_mille_to_current(self, per_mille: ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        return np.multiply(per_mille, self._rated_current() / 1000.0, out=out)

    # ------------------------------------------------------------ helpers

    def _rated_current(self) -> np.ndarray:
        if self.rated_current is None:
            raise ValueError("current conversions need a torque_constant (N·m/A)")
        return self.rated_current

    def _mul(self, values: ArrayLike, scale: np.ndarray) -> np.ndarray:
        """values × scale into a float64 scratch buffer reused across calls of the same shape."""
        shape = np.shape(values)
        work = self._scratch.get(shape)
        if work is None:
            work = self._scratch[shape] = np.empty(np.broadcast_shapes(shape, scale.shape))
        return np.multiply(values, scale, out=work)

    def _scratch_like(self, work: np.ndarray, dtype: type) -> np.ndarray:
        key = (dtype, work.shape)
        wide = self._scratch.get(key)
        if wide is None:
            wide = self._scratch[key] = np.empty(work.shape, dtype=dtype)
        return wide

    @staticmethod
    def _to_int(work: np.ndarray, dtype: type, out: np.ndarray | None) -> np.ndarray:
        if out is None:
            return work.astype(dtype)
        np.copyto(out, work, casting="unsafe")
        return out


def _saturate(work: np.ndarray, limits: tuple[int, int]) -> np.ndarray:
    """Round to integers and clamp into ``limits``, in place (np.clip is slower for small arrays)."""
    np.rint(work, out=work)
    np.maximum(work, limits[0], out=work)
    np.minimum(work, limits[1], out=work)
    return work


class Int32Unwrapper:
    """Multi-turn int64 counts from int32 positions that wrap, for one or many drives.

    The first update takes the raw value as is; later ones add the shortest signed step
    (modulo 2**32), so the result is right as long as a drive moves less than 2**31 counts
    between two updates.
    """

    __slots__ = ("_last", "_started", "_step", "value")

    def __init__(self, shape: int | tuple[int, ...] = ()) -> None:
        self.value = np.zeros(shape, dtype=np.int64)
        self._last = np.zeros(shape, dtype=np.int64)
        self._step = np.zeros(shape, dtype=np.int64)
        self._started = False

    def update(self, raw: ArrayLike) -> np.ndarray:
        """Take this cycle's raw int32 counts; return the unwrapped int64 counts (``value``, in place)."""
        if not self._started:
            np.copyto(self.value, raw, casting="unsafe")
            np.copyto(self._last, raw, casting="unsafe")
            self._started = True
            return self.value
        np.subtract(raw, self._last, out=self._step, casting="unsafe")
        np.add(self._step, 1 << 31, out=self._step)
        np.bitwise_and(self._step, 0xFFFFFFFF, out=self._step)
        np.subtract(self._step, 1 << 31, out=self._step)
        np.add(self.value, self._step, out=self.value)
        np.copyto(self._last, raw, casting="unsafe")
        return self.value

    def reset(self) -> None:
        self._started = False
