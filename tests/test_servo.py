"""The simulated joints' servo: it tracks a moving target without lag and is exact for any step."""

from __future__ import annotations

import numpy as np

from aiohal.fieldbus.servo import ServoModel
from aiohal.robot import Mode


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
