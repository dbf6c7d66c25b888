"""Disturbances: after a stall of the tick, the robot holds where it stands before anything
computed across the gap is written, with a fault naming the stall, and a re-arm resumes
without a step. On the virtual clock a stall is exact (the tick source is told to come late);
the frozen process on each simulated driver and the watchdog process are in
tests/test_disturbance_matrix.py."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import arm_raw, assert_bumpless, at, record, virtual_loop

from aiohal.safety import SafetyRequestRefused

SINE = {"type": "sine", "params": {"amplitude": 0.4, "frequency": 0.5, "ramp": 0.0}}


def sine_arm(**safety):
    raw = arm_raw(3, **SINE)
    raw["driver"][0]["options"] = {"dynamics": "first_order", "time_constant": 0.01}
    if safety:
        raw["safety"] = safety
    return raw


def stall_at(tick, periods):
    return at(tick, lambda lp: lp.source.stall(periods))


def controller_times(loop):
    """Every time the configured controller was updated with (a stall must not show in it)."""
    times = []
    update = loop.controller.update

    def spied(t, dt):
        times.append((loop.robot.clock.tick, t, dt))
        update(t, dt)

    loop.controller.update = spied
    return times


def assert_at_rest_where_measured(loop, sent, measured, after_tick):
    """Every command sent from ``after_tick`` on lies within one tick of the velocity limit of
    the position measured on the same tick."""
    step = loop.robot.velocity_limit * loop.period_s
    checked = 0
    for (k, q), m in zip(sent, measured, strict=True):
        if k >= after_tick:
            assert (np.abs(q - m) <= step + 1e-9).all(), (k, q, m)
            checked += 1
    assert checked > 0


@pytest.mark.asyncio
async def test_a_stall_holds_where_the_robot_stands_before_anything_is_written():
    loop = virtual_loop(sine_arm())
    async with loop:
        sent, measured, _ = record(loop)
        times = controller_times(loop)
        writes = []
        loop.add_publisher(lambda lp: writes.append(lp.slots[0].driver.writes))
        loop.add_publisher(stall_at(500, 2000))  # the tick after 500 comes 2 s late
        report = await loop.run(ticks=3000)
    resumed = 500 + 2001
    stall = [f for f in report["faults"] if f["source"] == "loop" and f["phase"] == "stall"]
    assert len(stall) == 1 and stall[0]["tick"] == resumed, report["faults"]
    assert "stalled for 2001.0 ms" in stall[0]["error"]
    assert report["safety_level"] == "hold" and report["safety"][-1]["tick"] == resumed
    # the controller never saw its time jump: it was not updated after the stall
    assert max(k for k, _, _ in times) == 500
    assert all(dt == pytest.approx(loop.period_s) for _, _, dt in times[1:])
    # every command from the resumed tick on is where the robot was measured, at rest
    assert_at_rest_where_measured(loop, sent, measured, resumed)
    # written once per tick run: ticks 1-500, then 2501-3000 (hold from the resumed tick on)
    assert writes[-1] == 500 + (3000 - resumed + 1)


@pytest.mark.asyncio
async def test_a_gap_within_the_bound_is_not_a_stall():
    loop = virtual_loop(sine_arm(max_tick_gap_ms=50))
    async with loop:
        loop.add_publisher(stall_at(200, 45))
        report = await loop.run(ticks=600)
    assert report["faults"] == [] and report["safety_level"] == "run"


@pytest.mark.asyncio
async def test_the_default_bound_is_the_watchdog_time():
    loop = virtual_loop(sine_arm(watchdog_ms=30))
    assert loop.max_tick_gap_ns == 30_000_000
    async with loop:
        loop.add_publisher(stall_at(200, 29))  # 30 ms between two ticks: allowed
        loop.add_publisher(stall_at(400, 30))  # 31 ms: a stall
        report = await loop.run(ticks=600)
    assert [(f["phase"], f["tick"]) for f in report["faults"]] == [("stall", 431)]


@pytest.mark.asyncio
async def test_rearm_after_a_stall_resumes_without_a_step():
    loop = virtual_loop(sine_arm())
    async with loop:
        sent, measured, own = record(loop)
        refused = []

        def rearm_too_early(lp):
            try:
                lp.rearm()
            except SafetyRequestRefused as exc:
                refused.append(str(exc))

        loop.add_publisher(stall_at(300, 1000))
        loop.add_publisher(at(1400, rearm_too_early))
        loop.add_publisher(at(1500, lambda lp: (lp.reset_faults(), lp.rearm())))
        report = await loop.run(ticks=2500)
    assert "1 fault(s) since the last reset_faults()" in refused[0]
    assert report["safety_level"] == "run"
    assert [t["event"] for t in report["safety"]] == ["activate", "fault", "reset_faults", "rearm"]
    assert_bumpless(loop, sent, measured, own, 1500, since=1302)
    assert np.ptp(np.array([q for k, q in sent if k > 1700])[:, 0]) > 0.3  # the sine runs again


@pytest.mark.asyncio
async def test_a_stall_while_held_restarts_hold_where_the_robot_stands():
    loop = virtual_loop(sine_arm())
    async with loop:
        sent, measured, _ = record(loop)
        loop.add_publisher(at(250, lambda lp: lp.hold("operator")))  # braking from full speed
        loop.add_publisher(stall_at(260, 500))
        report = await loop.run(ticks=1000)
    assert [f["phase"] for f in report["faults"]] == ["stall"] and report["safety_level"] == "hold"
    assert_at_rest_where_measured(loop, sent, measured, 761)


@pytest.mark.asyncio
async def test_a_stall_goes_to_the_emergency_stop_with_fault_level_estop():
    loop = virtual_loop(sine_arm(fault_level="estop"))
    async with loop:
        loop.add_publisher(stall_at(100, 100))
        report = await loop.run(ticks=400)
        mock = loop.slots[0].driver
    assert report["safety_level"] == "estop" and report["faults"][0]["phase"] == "stall"
    assert mock.writes == 100  # ticks 1-100: not one write after the stall
