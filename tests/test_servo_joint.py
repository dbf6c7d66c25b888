"""The servo drive's richer joint: the gear's elasticity, the encoders, the drive's velocity
estimate, the measurement's noise and the drive's SYNC0 latch, each doing what it does (and
each test failing with that part taken out of the model)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aiohal.simulation.servo import (
    W_MEAS,
    ReferenceServo,
    ServoBank,
    ServoParams,
    W,
    gear_torque,
)

CSG_32 = {
    "stiffness_k1": 6.7e4,
    "stiffness_k2": 1.1e5,
    "stiffness_k3": 1.2e5,
    "stiffness_t1": 29.0,
    "stiffness_t2": 108.0,
}


def test_the_gear_curve_has_the_catalogues_three_segments():
    k = CSG_32
    args = (k["stiffness_k1"], k["stiffness_k2"], k["stiffness_k3"], k["stiffness_t1"], k["stiffness_t2"])
    phi1 = 29.0 / 6.7e4
    phi2 = phi1 + (108.0 - 29.0) / 1.1e5
    assert gear_torque(phi1, *args) == pytest.approx(29.0)
    assert gear_torque(phi2, *args) == pytest.approx(108.0)
    assert gear_torque(phi2 + 1e-4, *args) == pytest.approx(108.0 + 12.0)
    assert gear_torque(-phi1 / 2, *args) == pytest.approx(-14.5)
    assert gear_torque(1e-3, 5e4, 0.0, 0.0, 0.0, 0.0) == pytest.approx(50.0)  # one stiffness throughout


def test_the_link_sags_under_its_weight_by_the_gears_twist():
    """The position loop on the motor encoder holds the motor at the target; the link hangs
    below it by the twist that carries the leg's weight through the gear."""
    target = 0.5
    servo = ReferenceServo(ServoParams(**CSG_32, gear_damping=50.0, coulomb=0.0, rotor_inertia=2e-4), target)
    servo.command(target, 0.0, 30.0 * math.sin(target))
    for _ in range(800):
        servo.step(1e-3)
    weight = 30.0 * math.sin(servo.link_angle)
    assert servo.motor_angle / 100.0 == pytest.approx(target, abs=2e-6)
    assert target - servo.position == pytest.approx(weight / 6.7e4, rel=0.02)  # T < T1: the K1 segment
    assert target - servo.position > 2e-4


def test_the_reported_position_is_the_link_encoders_reading():
    counts = 524288
    servo = ReferenceServo(ServoParams(link_counts=counts), 0.0)
    readings = []
    for k in range(200):
        servo.command(0.3 * math.sin(k * 1e-2), 0.0, 0.0)
        servo.step(1e-3)
        readings.append(servo.position)
    steps = np.array(readings) / (2 * math.pi / counts)
    assert np.allclose(steps, np.round(steps), atol=1e-6)
    assert len(set(np.round(steps))) > 100  # and it moved


def speeds_seen(params: ServoParams, acceleration: float, cycles: int) -> tuple[np.ndarray, np.ndarray]:
    """The motor's speed and what the velocity loop saw of it, at the end of each cycle, while
    the current loop alone accelerates the joint evenly (no friction, no gravity)."""
    bank = ServoBank(params, np.zeros(1))
    torque = acceleration * (params.rotor_inertia * 100.0**2 + params.load_inertia)
    true, seen = np.zeros(cycles), np.zeros(cycles)
    for k in range(cycles):
        bank.command(0.0, 0.0, torque, loop=2)  # CURRENT_LOOP
        bank.step(1e-3)
        true[k], seen[k] = bank.state[0, W], bank.state[0, W_MEAS]
    return true, seen


PLAIN = {"coulomb": 0.0, "viscous": 0.0, "gravity_torque": 0.0, "velocity_filter_hz": 1e9}


def test_the_velocity_estimate_is_the_encoders_difference():
    """Unfiltered, the estimate is a whole number of motor encoder counts per velocity period
    (100 µs), and it lags the speed: by half the period less half a mechanics step (the rotor's
    speed is held over each 50 µs step), 25 µs."""
    counts = 131072
    true, seen = speeds_seen(ServoParams(**PLAIN, motor_counts=counts, velocity_estimate=True), 20.0, 50)
    per_count = 2 * math.pi / counts / 1e-4
    assert np.allclose(seen / per_count, np.round(seen / per_count), atol=1e-6)
    true, seen = speeds_seen(ServoParams(**PLAIN, velocity_estimate=True), 20.0, 50)
    motor_acceleration = 20.0 * 100.0
    lag = (true - seen)[10:] / motor_acceleration
    assert lag == pytest.approx(np.full(len(lag), 0.25e-4), rel=0.02)


def test_the_link_noise_has_its_standard_deviation_and_is_reproducible():
    params = ServoParams(link_noise=2e-5, coulomb=5.0, gravity_torque=0.0)
    runs = []
    for _ in range(2):
        bank = ServoBank(params, np.zeros(1))
        position, velocity, effort = np.zeros(1), np.zeros(1), np.zeros(1)
        readings = np.zeros(2000)
        for k in range(len(readings)):
            bank.step(1e-3)
            bank.measure(position, velocity, effort)
            readings[k] = position[0]
        runs.append(readings)
    assert np.std(runs[0]) == pytest.approx(2e-5, rel=0.08)
    assert abs(np.mean(runs[0])) < 3e-6
    assert np.array_equal(runs[0], runs[1])


@pytest.mark.parametrize("latch", [False, True])
def test_a_latched_target_moves_the_joint_one_cycle_later(latch):
    """A position step sent at a cycle: without the latch the drive ramps to it over that
    cycle, with it over the next."""
    servo = ReferenceServo(ServoParams(gravity_torque=0.0, coulomb=0.0, sync_latch=latch), 0.0)
    servo.step(1e-3)
    servo.command(1e-3, 0.0, 0.0)
    servo.step(1e-3)
    first = servo.position
    servo.step(1e-3)
    if latch:
        assert abs(first) < 1e-9 < servo.position
    else:
        assert first > 1e-5
