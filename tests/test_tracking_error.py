"""LOLA's tracking error (aiohal.core.tracking_error): one definition, tick by tick and over a
run, and what it measures on the hip joint that another definition would hide."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from aiohal.core.tracking_error import TrackingError, tracking_error
from aiohal.simulation.servo import ServoBank, ServoParams

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "lola_hip_sim.toml"
HIP = ServoParams(**tomllib.loads(CONFIG.read_text())["driver"][0]["options"]["servo"])


@pytest.mark.parametrize("delay", [0, 1, 3])
def test_tick_by_tick_is_the_runs_definition(delay):
    rng = np.random.default_rng(delay)
    desired, measured = rng.normal(size=(40, 2)), rng.normal(size=(40, 2))
    tracker, out, errors = TrackingError(2, delay), np.zeros(2), []
    for k in range(40):
        if tracker.update(desired[k], measured[k], out):
            errors.append(out.copy())
    assert np.array_equal(np.array(errors), tracking_error(desired, measured, delay))
    assert len(errors) == 40 - delay


def test_a_reading_cannot_come_before_its_measurement():
    with pytest.raises(ValueError):
        tracking_error(np.zeros(3), np.zeros(3), -1)
    with pytest.raises(ValueError):
        TrackingError(1, -1)


def hip_run(period: float, seconds: float = 1.5, k_e: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The hip joint (the config's drive) on a 1 Hz, 0.3 rad sine with velocity and torque
    feed-forward: targets, readings and target velocities of each tick."""
    bank = ServoBank(HIP, np.array([0.1]))
    n = round(seconds / period)
    t = np.arange(n) * period
    ramp = np.minimum(t / 0.5, 1.0)
    q = 0.1 + 0.3 * ramp * np.sin(2 * math.pi * t)
    v = np.gradient(q, period)
    a = np.gradient(v, period)
    readings = np.zeros(n)
    position, velocity, effort = np.zeros(1), np.zeros(1), np.zeros(1)
    for k in range(n):
        bank.measure(position, velocity, effort)
        readings[k] = position[0]
        bank.command(q[k], (1 + k_e) * v[k], 3.0 * a[k] + 30.0 * math.sin(q[k]))
        bank.step(period)
    return q, readings, v


@pytest.mark.parametrize("period", [1e-3, 5e-4])
def test_the_error_holds_the_two_cycles_a_target_takes(period):
    """The drive takes a target at its next SYNC0 and ramps to it over the cycle after: at the
    same instant the joint is two cycles behind, v·2T. Against the reading one tick later
    (another definition) half of that lag disappears, and with it what k_e is for."""
    q, readings, v = hip_run(period)
    keep = slice(round(0.6 / period), None)
    lag = np.sqrt(np.mean(v[keep] ** 2))
    same_instant = np.sqrt(np.mean(tracking_error(q, readings)[keep] ** 2))
    one_tick_later = np.sqrt(np.mean((q[:-1] - readings[1:])[keep] ** 2))
    assert same_instant == pytest.approx(2 * period * lag, rel=0.12)
    assert one_tick_later == pytest.approx(period * lag, rel=0.25)


def test_the_gain_that_makes_up_for_two_cycles_lowers_the_error():
    """k_e = K_p·2T cancels the two cycles of lag in the position loop (K_p = 200, T = 1 ms)."""
    q, readings, _ = hip_run(1e-3)
    q_ff, readings_ff, _ = hip_run(1e-3, k_e=0.4)
    keep = slice(600, None)
    ref = np.sqrt(np.mean(tracking_error(q, readings)[keep] ** 2))
    learned = np.sqrt(np.mean(tracking_error(q_ff, readings_ff)[keep] ** 2))
    assert learned < 0.15 * ref
