"""The simulated bus devices' joint models: the first-order servo tracks a moving target
without lag and is exact for any step; the cascade model gives each mode's command to the
shared servo drive (aiohal.simulation.servo) as the loop that mode asks for."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aiohal.robot import Mode
from aiohal.simulation.joints import CascadeServoModel, ServoModel, joint_model
from aiohal.simulation.servo import CURRENT_LOOP, LOOP, POSITION_LOOP, VELOCITY_LOOP, ReferenceServo, ServoParams


def test_a_ramp_is_tracked_without_lag_whatever_the_step():
    for dt in (0.0005, 0.005, 0.05):
        m = ServoModel(1, time_constant=0.005, initial=[0.0])
        m.command(slice(None), [Mode.POSITION], [0.0], [1.0], [0.0])
        for _ in range(int(0.2 / dt)):
            m.step(dt)
        assert abs(m.position[0] - 0.2) < 1e-9 and abs(m.velocity[0] - 1.0) < 1e-9


def test_a_step_decays_with_the_time_constant_and_none_mode_holds():
    m = ServoModel(2, time_constant=0.01, initial=[0.0, 0.5])
    m.command(np.array([True, False]), [Mode.POSITION], [1.0], [0.0], [0.0])
    m.step(0.01)
    assert np.isclose(m.position[0], 1.0 - np.exp(-1.0)) and m.position[1] == 0.5
    m.stop()
    before = m.position.copy()
    m.step(0.1)
    assert np.array_equal(m.position, before) and not m.velocity.any()


def test_velocity_mode_integrates_the_velocity():
    m = ServoModel(1, initial=[1.0])
    m.command(slice(None), [Mode.VELOCITY], [0.0], [-2.0], [0.0])
    m.step(0.25)
    assert np.isclose(m.position[0], 0.5)


# ---------------------------------------------------------------- the cascade model

PARAMS = ServoParams(coulomb=1.0, gravity_torque=10.0)


def _command(k: int) -> tuple[float, float, float]:
    """A moving command (position, velocity, effort) at step k."""
    t = k * 1e-3
    return 0.1 + 0.2 * math.sin(4.0 * t), 0.8 * math.cos(4.0 * t), 2.0 * math.sin(4.0 * t)


def _assert_same(model: CascadeServoModel, ref: ReferenceServo, row: int, k) -> None:
    assert model.position[row] == pytest.approx(ref.position, rel=1e-9, abs=1e-12), k
    assert model.velocity[row] == pytest.approx(ref.velocity, rel=1e-9, abs=1e-10), k
    assert model.effort[row] == pytest.approx(ref.torque, rel=1e-9, abs=1e-9), k


@pytest.mark.parametrize("mode, loop", [
    (Mode.POSITION, POSITION_LOOP),
    (Mode.IMPEDANCE, POSITION_LOOP),  # the drive's position loop stands in for the stiffness
    (Mode.VELOCITY, VELOCITY_LOOP),
    (Mode.EFFORT, CURRENT_LOOP),
])
def test_each_mode_runs_the_loop_it_asks_for_on_the_commands_fields(mode, loop):
    """Row 0 in ``mode`` is the plain drive given what that mode's loop takes; row 1, not
    commanded, holds where it started."""
    model = CascadeServoModel(2, PARAMS, [0.1, 0.3])
    ref = ReferenceServo(PARAMS, 0.1)
    held = ReferenceServo(PARAMS, 0.3)
    for k in range(300):
        q, v, e = _command(k)
        model.command(np.array([True, False]), mode, q, v, e, 500.0, 20.0)
        ref.command(q if loop == POSITION_LOOP else 0.0, v if loop != CURRENT_LOOP else 0.0, e, loop)
        model.step(1e-3)
        ref.step(1e-3)
        held.step(1e-3)
        _assert_same(model, ref, 0, k)
        _assert_same(model, held, 1, k)
    assert model.mode.tolist() == [mode, Mode.NONE]
    if loop == POSITION_LOOP:
        assert abs(model.position[0] - _command(299)[0]) < 0.01  # and it tracked


def test_mode_changes_restart_the_position_ramp_where_the_joint_is_and_none_holds():
    """Position, then velocity, then position again (the ramp from where the joint got to),
    then NONE: the drive's position loop holds the joint where it stood, without
    feed-forward, for as long as NONE lasts (and after stop())."""
    model = CascadeServoModel(1, PARAMS, [0.1])
    ref = ReferenceServo(PARAMS, 0.1)
    for k in range(500):
        q, v, e = _command(k)
        if k < 100 or 200 <= k < 300:
            if k == 200:
                ref.previous_target = ref.position
            model.command(slice(None), Mode.POSITION, q, v, e)
            ref.command(q, v, e, POSITION_LOOP)
        elif k < 200:
            model.command(slice(None), Mode.VELOCITY, q, 0.5, 0.0)
            ref.command(0.0, 0.5, 0.0, VELOCITY_LOOP)
        else:
            if k == 300:
                ref.previous_target = ref.target = ref.position
            model.command(slice(None), Mode.NONE, q, v, e)  # targets that NONE ignores
            ref.command(ref.target, 0.0, 0.0, POSITION_LOOP)
        model.step(1e-3)
        ref.step(1e-3)
        _assert_same(model, ref, 0, k)
    stood = ref.target
    assert abs(model.position[0] - stood) < 1e-3 and model.bank.state[0, LOOP] == POSITION_LOOP
    model.command(slice(None), Mode.POSITION, 0.4, 0.0, 0.0)  # the ramp from the held target
    ref.command(0.4, 0.0, 0.0, POSITION_LOOP)
    model.step(1e-3)
    ref.step(1e-3)
    _assert_same(model, ref, 0, "from NONE")
    model.stop()
    ref.previous_target = ref.target = ref.position
    ref.command(ref.target, 0.0, 0.0, POSITION_LOOP)
    for k in range(100):
        model.step(1e-3)
        ref.step(1e-3)
        _assert_same(model, ref, 0, k)
    assert model.mode[0] == Mode.NONE


def test_a_command_ramps_over_the_first_step_after_it_and_later_steps_hold():
    """Several steps between commands (a simulator that wakes more often than commands come):
    the target is reached at the end of the first step, as the plain drive stepped alike."""
    model = CascadeServoModel(1, PARAMS, [0.0])
    ref = ReferenceServo(PARAMS, 0.0)
    for k in range(100):
        q, v, e = _command(4 * k)
        model.command(slice(None), Mode.POSITION, q, v, e)
        ref.command(q, v, e)
        for dt in (5e-4, 2e-3, 1e-3, 5e-4):  # 4 ms per command, steps of any length
            model.step(dt)
            ref.step(dt)
            _assert_same(model, ref, 0, k)


def test_a_step_of_no_time_does_nothing_and_a_huge_one_is_capped():
    a = CascadeServoModel(1, PARAMS, [0.0])
    b = CascadeServoModel(1, PARAMS, [0.0])
    for model in (a, b):
        model.command(slice(None), Mode.VELOCITY, 0.0, 1.0, 0.0)
    before = a.bank.state.copy()
    for dt in (0.0, -1.0, math.nan):
        a.step(dt)
    assert np.array_equal(a.bank.state, before, equal_nan=True)
    a.step(30.0)
    b.step(CascadeServoModel.max_step)
    assert a.position[0] == b.position[0] > 0.05  # it moved for max_step, not 30 s


def test_joint_model_picks_the_dynamics():
    assert isinstance(joint_model("first_order", 2, None, 0.01), ServoModel)
    model = joint_model("servo", 2, np.array([0.1, 0.2]), servo=ServoParams(gear_ratio=50.0))
    assert isinstance(model, CascadeServoModel) and model.bank.params[0, 0] == 50.0
    np.testing.assert_allclose(model.position, [0.1, 0.2])
    with pytest.raises(ValueError, match="dynamics must be 'first_order' or 'servo', not 'rigid'"):
        joint_model("rigid", 1)
