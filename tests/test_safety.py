"""The safety state machine: its table, the user's requests, and a bumpless re-arm on the
mock and MuJoCo drivers (the EtherCAT driver's is in tests/test_ethercat_driver.py)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CONFIGS, require_module
from helpers import arm_raw, assert_bumpless, at, record, virtual_loop

from aiohal.config import load_config
from aiohal.core.loop import ControlLoop
from aiohal.core.ticker import VirtualTickSource
from aiohal.hal import Controller
from aiohal.safety import TRANSITIONS, SafetyEvent, SafetyLevel, SafetyMachine, SafetyRequestRefused

L, E = SafetyLevel, SafetyEvent


# ---------------------------------------------------------------- the table


def test_every_event_of_the_table_is_recorded_with_tick_source_and_cause():
    machine = SafetyMachine()
    steps = [(E.ACTIVATE, L.RUN), (E.HOLD, L.HOLD), (E.REARM, L.RUN), (E.FAULT, L.HOLD),
             (E.RESET_FAULTS, L.HOLD), (E.ESTOP, L.ESTOP), (E.RESET_FAULTS, L.DISABLED),
             (E.REARM, L.RUN), (E.WATCHDOG, L.ESTOP), (E.DEACTIVATE, L.OFF)]
    for tick, (event, level) in enumerate(steps):
        assert machine.fire(event, tick, "test", f"step {tick}")
        assert machine.level == level
    assert [(t.tick, t.event, t.after) for t in machine.transitions] == [
        (i, e.value, lv.name.lower()) for i, (e, lv) in enumerate(steps)]
    assert all(t.source == "test" and t.cause == f"step {t.tick}" for t in machine.transitions)


@pytest.mark.parametrize("level, event", [(L.OFF, E.REARM), (L.RUN, E.REARM), (L.ESTOP, E.REARM),
                                          (L.HOLD, E.HOLD), (L.ESTOP, E.HOLD), (L.OFF, E.FAULT),
                                          (L.ESTOP, E.FAULT), (L.RUN, E.ACTIVATE)])
def test_events_without_a_row_are_refused_and_change_nothing(level, event):
    assert (event, level) not in TRANSITIONS or event is E.FAULT
    machine = SafetyMachine()
    machine.level = level
    assert not machine.fire(event, 0, "test", "")
    assert machine.level == level and machine.transitions == []


def test_a_fault_only_lowers_the_level_to_its_own():
    machine = SafetyMachine(fault_level=L.ESTOP)
    machine.level = L.RUN
    assert machine.fire(E.FAULT, 1, "driver:x", "boom") and machine.level == L.ESTOP
    machine = SafetyMachine()
    machine.level = L.HOLD
    assert not machine.fire(E.FAULT, 1, "driver:x", "again")  # already there
    assert machine.fire(E.FAULT, 2, "loop", "nothing left", level=L.ESTOP) and machine.level == L.ESTOP


def test_levels_keep_their_order_higher_moves_more():
    assert L.OFF < L.ESTOP < L.DISABLED < L.HOLD < L.RUN


# ---------------------------------------------------------------- re-arm on the mock


class FailsOnce(Controller):
    """A sinusoid about the start position that raises once, at tick ``fail_at``."""

    fail_at = 300

    def start(self, t):
        self.t0, self.q0 = t, self.robot.state.position.copy()
        self.starts = getattr(self, "starts", 0) + 1

    def update(self, t, dt):
        if self.robot.clock.tick == self.fail_at:
            raise RuntimeError("bug")
        s = t - self.t0
        ramp = min(s / 0.2, 1.0)
        self.robot.command.position[:] = self.q0 + 0.3 * ramp * np.sin(2 * np.pi * 1.0 * s)


@pytest.mark.asyncio
async def test_rearm_after_a_controller_fault_returns_to_run_without_a_jump():
    raw = arm_raw(3)
    raw["driver"][0]["options"] = {"dynamics": "first_order", "time_constant": 0.01}
    loop = virtual_loop(raw, controller=FailsOnce())
    async with loop:
        sent, measured, own = record(loop)
        refused = []

        def too_early(lp):
            try:
                lp.rearm()
            except SafetyRequestRefused as exc:
                refused.append(str(exc))

        loop.add_publisher(at(600, too_early))
        loop.add_publisher(at(900, lambda lp: (lp.reset_faults(), lp.rearm())))
        report = await loop.run(ticks=1500)
    assert report["safety_level"] == "run" and loop.controller_type == "FailsOnce"
    assert loop.controller.starts == 2
    assert "1 fault(s) since the last reset_faults()" in refused[0]
    events = [(t["event"], t["source"], t["after"]) for t in report["safety"]]
    assert events == [("activate", "loop", "run"), ("fault", "controller:FailsOnce", "hold"),
                      ("reset_faults", "user", "hold"), ("rearm", "user", "run")]
    assert [t["tick"] for t in report["safety"]][1:] == [300, 900, 900]
    assert_bumpless(loop, sent, measured, own, 900)
    # and it moves again: the sinusoid's swing after the re-arm
    assert np.ptp(np.array([q for _, q in sent])[1000:, 0]) > 0.4


@pytest.mark.asyncio
async def test_estop_then_reset_leaves_the_robot_disabled_until_rearm():
    loop = virtual_loop(arm_raw(2), controller=FailsOnce())
    FailsOnce.fail_at = -1
    try:
        async with loop:
            sent, measured, own = record(loop)
            loop.add_publisher(at(250, lambda lp: lp.estop("operator")))
            levels = []
            loop.add_publisher(at(400, lambda lp: (lp.reset_faults(), levels.append(lp.level))))
            loop.add_publisher(at(600, lambda lp: lp.rearm()))
            report = await loop.run(ticks=1000)
            mock = loop.slots[0].driver
    finally:
        FailsOnce.fail_at = 300
    assert levels == [L.DISABLED] and report["safety_level"] == "run"
    assert [t["event"] for t in report["safety"]] == ["activate", "estop", "reset_faults", "rearm"]
    assert report["safety"][1]["cause"] == "operator" and report["safety"][1]["source"] == "user"
    assert mock.writes == 250 + 400  # nothing written while estopped or disabled
    assert_bumpless(loop, sent, measured, own, 600)


@pytest.mark.asyncio
async def test_rearm_is_refused_with_the_reason():
    raw = arm_raw(2)
    raw["driver"].append({"type": "mock", "name": "wrist", "joints": []})
    raw["driver"][0]["joints"] = ["j0"]
    raw["driver"][1]["joints"] = ["j1"]
    raw["driver"][1]["options"] = {"faults": {"read_error_at_tick": 50}}
    loop = virtual_loop(raw)
    async with loop:
        with pytest.raises(SafetyRequestRefused, match="from run"):
            loop.rearm()
        await loop.run(ticks=100)
        assert loop.level == L.HOLD
        with pytest.raises(SafetyRequestRefused, match="only from run"):
            loop.hold()
        loop.reset_faults()
        with pytest.raises(SafetyRequestRefused, match="wrist failed"):
            loop.rearm()
        loop.estop()
        with pytest.raises(SafetyRequestRefused, match="reset_faults\\(\\) first"):
            loop.rearm()
    assert loop.level == L.OFF
    with pytest.raises(SafetyRequestRefused, match="closed"):
        loop.reset_faults()


@pytest.mark.asyncio
async def test_fault_level_estop_sends_faults_to_the_emergency_stop():
    raw = arm_raw(1)
    raw["safety"] = {"fault_level": "estop"}
    loop = virtual_loop(raw, controller=FailsOnce())
    async with loop:
        report = await loop.run(ticks=400)
        mock = loop.slots[0].driver
    assert report["safety_level"] == "estop" and mock.estops == 1
    assert report["safety"][-1]["event"] == "fault" and report["safety"][-1]["after"] == "estop"


# ---------------------------------------------------------------- re-arm on MuJoCo


def mujoco_loop(**params) -> ControlLoop:
    require_module("mujoco")
    config = load_config(CONFIGS / "kuka_lwr_sim.toml").with_loop(clock="virtual")
    return ControlLoop(config, tick_source=VirtualTickSource(), controller=FailsOnce())


@pytest.mark.asyncio
async def test_rearm_on_mujoco_after_hold_and_after_an_estop_is_bumpless():
    loop = mujoco_loop()
    async with loop:
        sent, measured, own = record(loop)
        loop.add_publisher(at(800, lambda lp: (lp.reset_faults(), lp.rearm())))
        report = await loop.run(ticks=1200)
        assert report["safety_level"] == "run"
        assert_bumpless(loop, sent, measured, own, 800)
        # the arm goes limp in the emergency stop, falls, and is re-armed where it came to be
        k = loop.robot.clock.tick
        loop.add_publisher(at(k + 100, lambda lp: lp.estop()))
        loop.add_publisher(at(k + 400, lambda lp: (lp.reset_faults(), lp.rearm())))
        before = len(sent)
        report = await loop.run(ticks=800)
    assert report["safety_level"] == "run"
    fell = np.abs(np.array(measured[before + 399]) - np.array(measured[before + 99])).max()
    step = loop.robot.velocity_limit * loop.period_s
    assert fell > 1e-3  # it moved while limp: the re-arm starts from where it is
    own_after = [(k2, q) for k2, q in own if k2 > k + 400]
    assert (np.abs(own_after[0][1] - measured[before + 399]) <= step).all()
    after = np.array([q for _, q in sent[before + 400:]])
    assert (np.abs(np.diff(after, axis=0)) <= step + 1e-12).all()
    assert (np.abs(after[0] - measured[before + 399]) <= step + 1e-12).all()
