"""The CiA 402 master-side state machine against a small model of a drive's own state machine,
and the unit conversions (hypothesis round trips, saturation, int32 wrap)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.fieldbus import cia402
from aiohal.fieldbus.cia402 import (
    DISABLE_VOLTAGE,
    ENABLE_OPERATION,
    FAULT_RESET,
    QUICK_STOP,
    SHUTDOWN,
    SWITCH_ON,
    Cia402Drive,
    DriveUnits,
    EventKind,
    Int32Unwrapper,
    State,
    Statusword,
    Target,
    decode_state,
    decode_states,
)

S = State
# A statusword per state as a drive reports it (bit 4 voltage enabled and bit 9 remote set where real drives set them).
STATUSWORD = {
    S.NOT_READY_TO_SWITCH_ON: 0x0000,
    S.SWITCH_ON_DISABLED: 0x0240,
    S.READY_TO_SWITCH_ON: 0x0231,
    S.SWITCHED_ON: 0x0233,
    S.OPERATION_ENABLED: 0x0237,
    S.QUICK_STOP_ACTIVE: 0x0217,
    S.FAULT_REACTION_ACTIVE: 0x021F,
    S.FAULT: 0x0218,
}


class ModelDrive:
    """The drive's side: the standard transitions, driven by the controlword it receives."""

    def __init__(self, state: State = S.SWITCH_ON_DISABLED, *, persistent_fault: bool = False,
                 quick_stop_to_disabled_after: int | None = None, deaf: bool = False) -> None:
        self.state = state
        self.error_code = 0x7500 if state is S.FAULT else 0
        self.persistent_fault = persistent_fault
        self.quick_stop_to_disabled_after = quick_stop_to_disabled_after
        self.deaf = deaf  # ignores every command (a drive that never makes progress)
        self.last_controlword = 0
        self.resets_seen = 0  # rising edges of bit 7
        self.cycles_in_quick_stop = 0
        self.actual = 1000  # position, counts
        self.target = 0
        self.target_when_enabled: int | None = None
        self.actual_when_enabled: int | None = None

    @property
    def statusword(self) -> int:
        return STATUSWORD[self.state]

    def inject_fault(self, code: int) -> None:
        self.state = S.FAULT_REACTION_ACTIVE
        self.error_code = code

    def receive(self, cw: int, target: int | None = None) -> None:
        edge = cw & 0x80 and not self.last_controlword & 0x80
        self.last_controlword = cw
        if target is not None:
            self.target = target
        if self.deaf:
            return
        st_ = self.state
        shutdown = cw & 0x87 == 0x06
        switch_on = cw & 0x8F == 0x07
        enable_op = cw & 0x8F == 0x0F
        disable_voltage = cw & 0x82 == 0x00
        quick_stop = cw & 0x86 == 0x02
        if st_ is S.FAULT_REACTION_ACTIVE:
            self.state = S.FAULT  # 14
        elif st_ is S.FAULT:
            if edge:
                self.resets_seen += 1
                if not self.persistent_fault:
                    self.state, self.error_code = S.SWITCH_ON_DISABLED, 0  # 15
        elif st_ is S.NOT_READY_TO_SWITCH_ON:
            self.state = S.SWITCH_ON_DISABLED  # 1
        elif st_ is S.SWITCH_ON_DISABLED:
            if shutdown:
                self.state = S.READY_TO_SWITCH_ON  # 2
        elif st_ is S.READY_TO_SWITCH_ON:
            if switch_on or enable_op:
                self.state = S.SWITCHED_ON  # 3
            elif disable_voltage or quick_stop:
                self.state = S.SWITCH_ON_DISABLED  # 7
        elif st_ is S.SWITCHED_ON:
            if enable_op:
                self.state = S.OPERATION_ENABLED  # 4
                self.target_when_enabled, self.actual_when_enabled = self.target, self.actual
            elif shutdown:
                self.state = S.READY_TO_SWITCH_ON  # 6
            elif disable_voltage or quick_stop:
                self.state = S.SWITCH_ON_DISABLED  # 10
        elif st_ is S.OPERATION_ENABLED:
            if switch_on:
                self.state = S.SWITCHED_ON  # 5
            elif shutdown:
                self.state = S.READY_TO_SWITCH_ON  # 8
            elif disable_voltage:
                self.state = S.SWITCH_ON_DISABLED  # 9
            elif quick_stop:
                self.state, self.cycles_in_quick_stop = S.QUICK_STOP_ACTIVE, 0  # 11
            else:
                self.actual = self.target  # follows its target
        elif st_ is S.QUICK_STOP_ACTIVE:
            self.cycles_in_quick_stop += 1
            after = self.quick_stop_to_disabled_after
            if disable_voltage or (after is not None and self.cycles_in_quick_stop >= after):
                self.state = S.SWITCH_ON_DISABLED  # 12
        if self.state in (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON):
            self.actual += 7  # unpowered, the joint sags: bumpless enable must follow it


def run(master: Cia402Drive, drive: ModelDrive, cycles: int) -> list[tuple[int, list]]:
    """Run up to ``cycles`` bus cycles; return (controlword, events) per cycle."""
    log = []
    for _ in range(cycles):
        cw = master.update(drive.statusword, drive.error_code)
        log.append((cw, list(master.events)))
        drive.receive(cw)
    return log


def kinds(log) -> list[EventKind]:
    return [e.kind for _, events in log for e in events]


def rising_edges(log) -> int:
    cws = [0] + [cw for cw, _ in log]
    return sum(1 for a, b in itertools.pairwise(cws) if b & 0x80 and not a & 0x80)


# ---------------------------------------------------------------- decoding


def reference_state(sw: int) -> State:
    """The standard's table, written out bit by bit (independently of the module's patterns)."""
    rtso, so, oe, f, qs, sod = (bool(sw >> b & 1) for b in (0, 1, 2, 3, 5, 6))
    if not (rtso or so or oe or f) and not sod:
        return S.NOT_READY_TO_SWITCH_ON
    if not (rtso or so or oe or f) and sod:
        return S.SWITCH_ON_DISABLED
    if sod or f:
        if f and not sod and rtso and so and oe:
            return S.FAULT_REACTION_ACTIVE
        if f and not sod and not (rtso or so or oe):
            return S.FAULT
        return S.UNKNOWN
    if qs and (rtso, so, oe) == (True, False, False):
        return S.READY_TO_SWITCH_ON
    if qs and (rtso, so, oe) == (True, True, False):
        return S.SWITCHED_ON
    if qs and (rtso, so, oe) == (True, True, True):
        return S.OPERATION_ENABLED
    if not qs and (rtso, so, oe) == (True, True, True):
        return S.QUICK_STOP_ACTIVE
    return S.UNKNOWN


def test_every_statusword_decodes_as_the_standard_says():
    every = np.arange(1 << 16, dtype=np.uint16)
    decoded = decode_states(every)
    assert decoded.dtype == np.uint8
    expected = np.array([reference_state(sw) for sw in range(1 << 16)], dtype=np.uint8)
    np.testing.assert_array_equal(decoded, expected)
    assert all(decode_state(sw) == expected[sw] for sw in range(0, 1 << 16, 97))


@pytest.mark.parametrize("state", list(STATUSWORD))
def test_each_state_decodes_whatever_the_other_bits(state):
    noise = Statusword.VOLTAGE_ENABLED | Statusword.WARNING | Statusword.REMOTE | Statusword.TARGET_REACHED \
        | Statusword.INTERNAL_LIMIT_ACTIVE | 0xF100
    assert decode_state(STATUSWORD[state]) is state
    assert decode_state(STATUSWORD[state] | noise) is state
    assert decode_state(STATUSWORD[state] & ~noise) is state
    assert State(int(decode_states(np.array([STATUSWORD[state]]))[0])) is state


def test_helper_bits_and_labels():
    d = Cia402Drive()
    d.update(STATUSWORD[S.OPERATION_ENABLED] | Statusword.TARGET_REACHED | Statusword.WARNING)
    assert d.target_reached and d.warning and d.voltage_enabled and not d.internal_limit_active
    d.update(STATUSWORD[S.OPERATION_ENABLED] | Statusword.INTERNAL_LIMIT_ACTIVE)
    assert d.internal_limit_active and not d.target_reached and not d.warning
    assert S.SWITCH_ON_DISABLED.label == "Switch on disabled"
    assert S.OPERATION_ENABLED.label == "Operation enabled"


def test_command_and_mode_constants():
    assert (SHUTDOWN, SWITCH_ON, ENABLE_OPERATION, DISABLE_VOLTAGE, QUICK_STOP) == (0x06, 0x07, 0x0F, 0x00, 0x02)
    assert cia402.DISABLE_OPERATION == 0x07 and FAULT_RESET == 0x80
    assert (cia402.CSP, cia402.CSV, cia402.CST, cia402.PP, cia402.PV, cia402.PT) == (8, 9, 10, 1, 3, 4)
    assert cia402.OperationMode(8) is cia402.OperationMode.CYCLIC_SYNC_POSITION


# ---------------------------------------------------------------- one step per state and target

NEXT = {
    Target.ENABLED: {
        S.NOT_READY_TO_SWITCH_ON: DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED: SHUTDOWN,
        S.READY_TO_SWITCH_ON: SWITCH_ON, S.SWITCHED_ON: ENABLE_OPERATION,
        S.OPERATION_ENABLED: ENABLE_OPERATION, S.QUICK_STOP_ACTIVE: DISABLE_VOLTAGE,
        S.FAULT_REACTION_ACTIVE: DISABLE_VOLTAGE, S.FAULT: DISABLE_VOLTAGE,
    },
    Target.DISABLED: dict.fromkeys(STATUSWORD, DISABLE_VOLTAGE),
    Target.QUICK_STOP: {
        S.NOT_READY_TO_SWITCH_ON: DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED: DISABLE_VOLTAGE,
        S.READY_TO_SWITCH_ON: QUICK_STOP, S.SWITCHED_ON: QUICK_STOP, S.OPERATION_ENABLED: QUICK_STOP,
        S.QUICK_STOP_ACTIVE: QUICK_STOP, S.FAULT_REACTION_ACTIVE: DISABLE_VOLTAGE, S.FAULT: DISABLE_VOLTAGE,
    },
}


@pytest.mark.parametrize("target", list(Target))
@pytest.mark.parametrize("state", list(STATUSWORD))
def test_next_controlword_for_every_state_and_target(state, target):
    d = Cia402Drive(target=target, auto_reset=False)
    assert d.update(STATUSWORD[state]) == NEXT[target][state]
    assert d.state is state


# The standard transitions the master asks for, each checked against the model drive.
TRANSITIONS = [
    # (number, from, target, to)
    (2, S.SWITCH_ON_DISABLED, Target.ENABLED, S.READY_TO_SWITCH_ON),
    (3, S.READY_TO_SWITCH_ON, Target.ENABLED, S.SWITCHED_ON),
    (4, S.SWITCHED_ON, Target.ENABLED, S.OPERATION_ENABLED),
    (7, S.READY_TO_SWITCH_ON, Target.DISABLED, S.SWITCH_ON_DISABLED),
    (7, S.READY_TO_SWITCH_ON, Target.QUICK_STOP, S.SWITCH_ON_DISABLED),
    (9, S.OPERATION_ENABLED, Target.DISABLED, S.SWITCH_ON_DISABLED),
    (10, S.SWITCHED_ON, Target.DISABLED, S.SWITCH_ON_DISABLED),
    (10, S.SWITCHED_ON, Target.QUICK_STOP, S.SWITCH_ON_DISABLED),
    (11, S.OPERATION_ENABLED, Target.QUICK_STOP, S.QUICK_STOP_ACTIVE),
    (12, S.QUICK_STOP_ACTIVE, Target.ENABLED, S.SWITCH_ON_DISABLED),
    (12, S.QUICK_STOP_ACTIVE, Target.DISABLED, S.SWITCH_ON_DISABLED),
    (15, S.FAULT, Target.DISABLED, S.SWITCH_ON_DISABLED),
]


@pytest.mark.parametrize(("number", "start", "target", "end"), TRANSITIONS)
def test_each_transition_in_one_cycle(number, start, target, end):
    model = ModelDrive(start)
    master = Cia402Drive(target=target, reset_pulse_cycles=1)
    run(master, model, 1)
    assert model.state is end, f"transition {number}"


def test_not_ready_leaves_by_itself_and_is_then_walked_up():
    model = ModelDrive(S.NOT_READY_TO_SWITCH_ON)
    master = Cia402Drive(target=Target.ENABLED)
    run(master, model, 5)
    assert master.state is S.OPERATION_ENABLED


def test_enable_walks_every_step_and_reports_it():
    model = ModelDrive(S.SWITCH_ON_DISABLED)
    master = Cia402Drive("j1", target=Target.ENABLED)
    log = run(master, model, 6)
    assert [cw for cw, _ in log] == [SHUTDOWN, SWITCH_ON, ENABLE_OPERATION, ENABLE_OPERATION, ENABLE_OPERATION,
                                     ENABLE_OPERATION]
    changes = [(e.previous, e.state) for _, events in log for e in events if e.kind is EventKind.STATE_CHANGED]
    assert changes == [(S.UNKNOWN, S.SWITCH_ON_DISABLED), (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON),
                       (S.READY_TO_SWITCH_ON, S.SWITCHED_ON), (S.SWITCHED_ON, S.OPERATION_ENABLED)]
    assert kinds(log).count(EventKind.BECAME_ENABLED) == 1
    assert master.enabled and not master.stuck
    assert str(log[1][1][0]) == "drive 'j1': Switch on disabled -> Ready to switch on"


def test_disable_from_enabled_and_lost_enabled_event():
    model = ModelDrive(S.SWITCH_ON_DISABLED)
    master = Cia402Drive(target=Target.ENABLED)
    run(master, model, 5)
    master.disable()
    log = run(master, model, 3)
    assert model.state is S.SWITCH_ON_DISABLED
    assert EventKind.LOST_ENABLED in kinds(log)
    assert all(cw == DISABLE_VOLTAGE for cw, _ in log)


def test_quick_stop_then_enable_again_goes_through_switch_on_disabled():
    model = ModelDrive(S.SWITCH_ON_DISABLED)
    master = Cia402Drive(target=Target.ENABLED)
    run(master, model, 5)
    master.quick_stop()
    log = run(master, model, 4)
    assert model.state is S.QUICK_STOP_ACTIVE and master.state is S.QUICK_STOP_ACTIVE
    assert EventKind.QUICK_STOP_ACTIVE in kinds(log) and EventKind.LOST_ENABLED in kinds(log)
    assert master.hold_target and not master.stuck
    master.enable()
    log = run(master, model, 6)
    visited = [e.state for _, events in log for e in events if e.kind is EventKind.STATE_CHANGED]
    assert visited[:4] == [S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED]


def test_quick_stop_that_ends_in_switch_on_disabled_is_reached():
    model = ModelDrive(S.OPERATION_ENABLED, quick_stop_to_disabled_after=3)
    master = Cia402Drive(target=Target.QUICK_STOP, stuck_after=5)
    run(master, model, 50)
    assert master.state is S.SWITCH_ON_DISABLED and not master.stuck


def test_unknown_statusword_keeps_the_last_command_without_reset_bit():
    master = Cia402Drive(target=Target.ENABLED)
    assert master.update(STATUSWORD[S.SWITCH_ON_DISABLED]) == SHUTDOWN
    assert master.update(0x0048) == SHUTDOWN  # fault bit with switch on disabled: no standard state
    assert master.state is S.UNKNOWN


# ---------------------------------------------------------------- fault handling


@pytest.mark.parametrize("pulse", [1, 3])
def test_fault_at_power_up_is_reset_once_then_enabled(pulse):
    model = ModelDrive(S.FAULT)
    master = Cia402Drive(target=Target.ENABLED, reset_pulse_cycles=pulse)
    log = run(master, model, 10)
    assert model.resets_seen == 1 and rising_edges(log) == 1
    assert master.state is S.OPERATION_ENABLED
    assert log[0][0] == FAULT_RESET
    ks = kinds(log)
    assert ks.index(EventKind.FAULT_ENTERED) < ks.index(EventKind.FAULT_RESET_SENT) < ks.index(EventKind.FAULT_CLEARED)
    entered = next(e for _, events in log for e in events if e.kind is EventKind.FAULT_ENTERED)
    assert entered.error_code == 0x7500 and "0x7500" in str(entered)


def test_pulse_ends_as_soon_as_the_drive_leaves_fault():
    model = ModelDrive(S.FAULT)
    master = Cia402Drive(target=Target.ENABLED, reset_pulse_cycles=50)
    log = run(master, model, 3)
    assert [cw for cw, _ in log] == [FAULT_RESET, SHUTDOWN, SWITCH_ON]


def test_persistent_fault_gets_one_edge_not_a_loop():
    model = ModelDrive(S.FAULT, persistent_fault=True)
    master = Cia402Drive("j3", target=Target.ENABLED, reset_pulse_cycles=2, stuck_after=100)
    log = run(master, model, 2000)
    assert rising_edges(log) == 1 and model.resets_seen == 1
    assert [cw for cw, _ in log[:3]] == [FAULT_RESET, FAULT_RESET, DISABLE_VOLTAGE]
    assert all(cw == DISABLE_VOLTAGE for cw, _ in log[2:])
    stuck = [e for _, events in log for e in events if e.kind is EventKind.STUCK]
    assert len(stuck) == 1 and stuck[0].state is S.FAULT and stuck[0].cycles == 100
    assert "did not clear" in str(stuck[0]) and "Fault" in str(stuck[0])
    assert master.waiting_for_reset and master.stuck

    master.reset_fault()  # an explicit request: exactly one more edge
    assert not master.stuck
    log = run(master, model, 500)
    assert rising_edges(log) == 1 and model.resets_seen == 2
    model.persistent_fault = False
    master.reset_fault()
    run(master, model, 10)
    assert model.resets_seen == 3 and master.state is S.OPERATION_ENABLED


def test_reset_request_during_the_pulse_waits_for_bit_7_low():
    model = ModelDrive(S.FAULT, persistent_fault=True)
    master = Cia402Drive(target=Target.ENABLED, reset_pulse_cycles=2)
    log = run(master, model, 1)
    master.reset_fault()
    log += run(master, model, 6)
    assert [cw for cw, _ in log[:6]] == [FAULT_RESET, FAULT_RESET, DISABLE_VOLTAGE, FAULT_RESET, FAULT_RESET,
                                         DISABLE_VOLTAGE]
    assert model.resets_seen == 2


def test_fault_during_operation_is_reported_and_waits_for_reset_fault():
    model = ModelDrive(S.SWITCH_ON_DISABLED)
    master = Cia402Drive(target=Target.ENABLED, stuck_after=50)
    run(master, model, 5)
    assert master.enabled
    model.inject_fault(0x8611)  # following error
    log = run(master, model, 1000)
    assert model.state is S.FAULT and rising_edges(log) == 0  # the power-up credit expired on enable
    ks = kinds(log)
    assert ks.count(EventKind.FAULT_ENTERED) == 1 and EventKind.LOST_ENABLED in ks
    assert EventKind.STUCK not in ks  # a fault waiting for the application is not "stuck"
    assert master.error_code == 0x8611 and master.faulted and master.waiting_for_reset
    assert master.hold_target
    master.reset_fault()
    log = run(master, model, 10)
    assert rising_edges(log) == 1 and master.enabled
    assert EventKind.FAULT_CLEARED in kinds(log)


def test_reset_request_while_enabled_expires():
    model = ModelDrive(S.SWITCH_ON_DISABLED)
    master = Cia402Drive(target=Target.ENABLED, auto_reset=False)
    run(master, model, 5)
    master.reset_fault()  # stale: nothing to reset
    run(master, model, 2)
    model.inject_fault(0x2310)
    log = run(master, model, 100)
    assert rising_edges(log) == 0 and master.waiting_for_reset


def test_no_auto_reset_when_disabled_by_construction():
    model = ModelDrive(S.FAULT)
    master = Cia402Drive(target=Target.ENABLED, auto_reset=False)
    log = run(master, model, 100)
    assert rising_edges(log) == 0 and master.waiting_for_reset


def test_fault_reset_with_target_disabled_lands_in_switch_on_disabled():
    model = ModelDrive(S.FAULT)
    master = Cia402Drive(target=Target.DISABLED)
    run(master, model, 10)
    assert master.state is S.SWITCH_ON_DISABLED and model.resets_seen == 1


# ---------------------------------------------------------------- progress


def test_stuck_is_reported_once_with_the_state():
    model = ModelDrive(S.SWITCH_ON_DISABLED, deaf=True)
    master = Cia402Drive("j2", target=Target.ENABLED, stuck_after=20)
    log = run(master, model, 19)
    assert EventKind.STUCK not in kinds(log) and not master.stuck
    log = run(master, model, 200)
    stuck = [e for _, events in log for e in events if e.kind is EventKind.STUCK]
    assert len(stuck) == 1 and master.stuck
    assert stuck[0].state is S.SWITCH_ON_DISABLED and stuck[0].cycles == 20 and stuck[0].target is Target.ENABLED
    assert str(stuck[0]) == "drive 'j2': no progress for 20 cycles in Switch on disabled (target enabled)"
    assert master.cycles_in_state == 218 and master.cycles_without_progress == 218


def test_a_new_request_restarts_the_progress_clock():
    model = ModelDrive(S.READY_TO_SWITCH_ON, deaf=True)
    master = Cia402Drive(target=Target.ENABLED, stuck_after=10)
    run(master, model, 10)  # the first cycle sees the state appear; 9 cycles without progress follow
    assert not master.stuck
    run(master, model, 1)
    assert master.stuck
    master.disable()
    assert not master.stuck
    run(master, model, 9)
    assert not master.stuck
    run(master, model, 1)
    assert master.stuck


def test_reached_targets_never_get_stuck():
    for start, target in [(S.OPERATION_ENABLED, Target.ENABLED), (S.SWITCH_ON_DISABLED, Target.DISABLED),
                          (S.QUICK_STOP_ACTIVE, Target.QUICK_STOP), (S.FAULT, Target.DISABLED)]:
        model = ModelDrive(start, deaf=True)
        master = Cia402Drive(target=target, stuck_after=5, auto_reset=False)
        log = run(master, model, 100)
        assert EventKind.STUCK not in kinds(log), (start, target)


def test_fault_reaction_that_never_ends_is_stuck():
    model = ModelDrive(S.FAULT_REACTION_ACTIVE, deaf=True)
    master = Cia402Drive(target=Target.ENABLED, stuck_after=10)
    log = run(master, model, 50)
    stuck = [e for _, events in log for e in events if e.kind is EventKind.STUCK]
    assert len(stuck) == 1 and stuck[0].state is S.FAULT_REACTION_ACTIVE


def test_construction_checks():
    with pytest.raises(ValueError):
        Cia402Drive(stuck_after=0)
    with pytest.raises(ValueError):
        Cia402Drive(reset_pulse_cycles=0)


# ---------------------------------------------------------------- bumpless enable


def test_bumpless_enable_target_equals_actual_until_handover():
    model = ModelDrive(S.SWITCH_ON_DISABLED)
    master = Cia402Drive(target=Target.ENABLED)
    commands = []  # what the controller would send, seeded from the actual position at handover
    controller_position = None
    holds = []
    for _ in range(8):
        actual = model.actual  # read this cycle
        cw = master.update(model.statusword, model.error_code)
        holds.append(master.hold_target)
        if master.hold_target:
            target = actual
            controller_position = actual  # the driver seeds the controller's command while holding
        else:
            controller_position += 1  # the controller moves on from there
            target = controller_position
            commands.append(target - actual)
        model.receive(cw, target)
    # held while walking up and in the first enabled cycle, then handed over
    assert holds == [True, True, True, True, False, False, False, False]
    assert model.target_when_enabled == model.actual_when_enabled
    assert all(abs(step) <= 1 for step in commands)  # no jump at the handover


def test_hold_target_while_not_asked_to_be_enabled():
    master = Cia402Drive(target=Target.QUICK_STOP)
    for _ in range(3):
        master.update(STATUSWORD[S.OPERATION_ENABLED])
        assert master.hold_target


# ---------------------------------------------------------------- units

CPR = st.sampled_from([4096, 10000, 131072, 1 << 20, 1 << 24])
GEAR = st.one_of(st.sampled_from([1.0, 50.0, 100.0, 160.0]), st.floats(0.5, 200.0))
INT32 = st.integers(-(1 << 31), (1 << 31) - 1)
INT16 = st.integers(-(1 << 15), (1 << 15) - 1)


@settings(max_examples=300, deadline=None)
@given(cpr=CPR, gear=GEAR, counts=INT32)
def test_counts_to_position_and_back_is_exact(cpr, gear, counts):
    u = DriveUnits(cpr, gear)
    assert int(u.position_to_counts(u.counts_to_position(counts))) == counts
    assert int(u.velocity_to_counts(u.counts_to_velocity(counts))) == counts


@settings(max_examples=300, deadline=None)
@given(cpr=CPR, gear=GEAR, fraction=st.floats(-1.0, 1.0))
def test_position_to_counts_and_back_within_half_a_count(cpr, gear, fraction):
    u = DriveUnits(cpr, gear)
    rad = fraction * ((1 << 31) - 2) / float(u.counts_per_rad)  # within the int32 range
    back = float(u.counts_to_position(u.position_to_counts(rad)))
    # half a count, and the rounding of a float this large (a position on a half count's boundary
    # came back half a count and 2e-11 rad away: cpr 4096, gear 1.25, fraction 0.25)
    bound = 0.5 * float(u.rad_per_count) * (1 + 1e-9) + 4 * math.ulp(rad)
    assert abs(back - rad) <= bound
    assert abs(float(u.counts_to_velocity(u.velocity_to_counts(rad))) - rad) <= bound


@settings(max_examples=200, deadline=None)
@given(cpr=CPR, gear=GEAR, turns=st.floats(-1e6, 1e6))
def test_positions_wrap_like_the_drive_and_velocities_saturate(cpr, gear, turns):
    u = DriveUnits(cpr, gear)
    rad = turns * 2 * math.pi
    exact = int(np.rint(rad * float(u.counts_per_rad)))
    wrapped = (exact + (1 << 31)) % (1 << 32) - (1 << 31)
    assert int(u.position_to_counts(rad)) == wrapped
    assert int(u.velocity_to_counts(rad)) == max(-(1 << 31), min((1 << 31) - 1, exact))


@settings(max_examples=300, deadline=None)
@given(per_mille=INT16, gear=GEAR, rated=st.floats(0.01, 100.0))
def test_torque_round_trip_and_saturation(per_mille, gear, rated):
    u = DriveUnits(131072, gear, rated)
    assert int(u.torque_to_per_mille(u.per_mille_to_torque(per_mille))) == per_mille
    assert float(u.per_mille_to_torque(1000)) == pytest.approx(rated * gear)
    huge = rated * gear * 1000.0
    assert int(u.torque_to_per_mille(huge)) == 32767
    assert int(u.torque_to_per_mille(-huge)) == -32768


def test_current_needs_a_torque_constant():
    u = DriveUnits(rated_torque=2.0, torque_constant=0.5)  # rated current 4 A
    assert int(u.current_to_per_mille(2.0)) == 500
    assert float(u.per_mille_to_current(250)) == pytest.approx(1.0)
    assert int(u.current_to_per_mille(1e6)) == 32767
    with pytest.raises(ValueError, match="torque_constant"):
        DriveUnits().current_to_per_mille(1.0)


def test_units_from_drive_objects():
    u = DriveUnits.from_objects(131072, motor_revolutions=100, shaft_revolutions=1, rated_torque_mnm=1500)
    assert float(u.gear_ratio) == 100 and float(u.rated_torque) == 1.5
    assert int(u.position_to_counts(2 * math.pi)) == 131072 * 100
    assert int(u.torque_to_per_mille(150.0)) == 1000


@pytest.mark.parametrize("kwargs", [{"counts_per_rev": 0}, {"gear_ratio": -1}, {"rated_torque": math.nan},
                                    {"torque_constant": 0}])
def test_units_refuse_nonsense(kwargs):
    with pytest.raises(ValueError):
        DriveUnits(**kwargs)


def test_stacked_units_convert_arrays_into_int_views():
    per_drive = [DriveUnits(131072, 100, 1.0), DriveUnits(4096, 50, 2.0), DriveUnits(1 << 20, 1, 0.5)]
    u = DriveUnits.stack(per_drive)
    rad = np.array([0.1, -0.2, 3.0])
    expected = [int(p.position_to_counts(r)) for p, r in zip(per_drive, rad, strict=True)]
    # an int32 view with a stride, as a bus variable across slaves is
    image = np.zeros(3 * 13, dtype=np.uint8)
    target = np.ndarray((3,), dtype="<i4", buffer=image, offset=2, strides=(13,))
    assert u.position_to_counts(rad, out=target) is target
    assert target.tolist() == expected
    assert image[2:6].view("<i4")[0] == expected[0]
    torque = np.ndarray((3,), dtype="<i2", buffer=image, offset=10, strides=(13,))
    u.torque_to_per_mille(np.array([50.0, 100.0, 0.25]), out=torque)
    assert torque.tolist() == [500, 1000, 500]
    out = np.empty(3)
    assert u.counts_to_position(target, out=out) is out
    np.testing.assert_allclose(out, rad, atol=1e-4)
    with pytest.raises(ValueError):
        DriveUnits.stack([])


@settings(max_examples=200, deadline=None)
@given(start=INT32, steps=st.lists(st.integers(-(1 << 31) + 1, (1 << 31) - 1), max_size=50))
def test_unwrapper_follows_positions_across_the_int32_wrap(start, steps):
    unwrap = Int32Unwrapper()
    position = start
    assert int(unwrap.update(np.int32(start))) == start
    for step in steps:
        position += step
        raw = np.int64((position + (1 << 31)) % (1 << 32) - (1 << 31)).astype(np.int32)
        assert int(unwrap.update(raw)) == position


def test_unwrapper_for_many_drives_in_place():
    unwrap = Int32Unwrapper(2)
    value = unwrap.update(np.array([(1 << 31) - 10, 0], dtype=np.int32))
    result = unwrap.update(np.array([-(1 << 31) + 5, -3], dtype=np.int32))
    assert result is value
    assert result.tolist() == [(1 << 31) + 5, -3]
    unwrap.reset()
    assert unwrap.update(np.array([7, 8], dtype=np.int32)).tolist() == [7, 8]
