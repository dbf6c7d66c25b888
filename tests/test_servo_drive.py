"""The simulated servo drive (LOLA's cascade): the compiled kernel against the plain model,
and the physics doing what a servo drive does."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aiohal.simulation.servo import (
    CURRENT_LOOP,
    OFF,
    POSITION_LOOP,
    QL,
    VELOCITY_LOOP,
    Q,
    ReferenceServo,
    ServoBank,
    ServoParams,
    W,
)


def trajectory(k: int, period: float):
    t = k * period
    return 0.3 * math.sin(5.0 * t), 1.5 * math.cos(5.0 * t), -7.5 * math.sin(5.0 * t)


@pytest.mark.parametrize("params", [
    ServoParams(),
    ServoParams(position_gain=120.0, coulomb=8.0, gravity_torque=60.0, velocity_every=1, max_current=5.0),
    ServoParams(current_rate_hz=40_000.0, velocity_every=4, viscous=0.0, coulomb=0.0, load_inertia=0.0),
    ServoParams(stiffness_k1=6.7e4, stiffness_k2=1.1e5, stiffness_k3=1.2e5, stiffness_t1=29.0, stiffness_t2=108.0,
                gear_damping=50.0, motor_counts=131072, link_counts=524288, link_noise=2e-5,
                velocity_estimate=True, sync_latch=True, rotor_inertia=2e-4),
    ServoParams(stiffness_k1=4e4, gear_damping=200.0, link_counts=65536, velocity_estimate=True, link_feedback=True),
])
@pytest.mark.parametrize("period", [1e-3, 5e-4, 2.5e-3])
def test_the_compiled_servo_is_the_reference_model(params, period):
    starts = np.array([0.0, 0.2])
    bank = ServoBank(params, starts)
    references = [ReferenceServo(params, float(q)) for q in starts]
    for k in range(400):
        q, v, a = trajectory(k, period)
        targets = np.array([q, -q])
        velocity = np.array([v, -v])
        torque = np.array([2.2 * a, 40.0])  # the second joint also gets a torque it cannot hold
        bank.command(targets, velocity, torque)
        for j, ref in enumerate(references):
            ref.command(targets[j], velocity[j], torque[j])
            ref.step(period)
        bank.step(period)
    position, velocity_out, effort = np.zeros(2), np.zeros(2), np.zeros(2)
    bank.measure(position, velocity_out, effort)
    for j, ref in enumerate(references):
        assert position[j] == pytest.approx(ref.position, rel=1e-9, abs=1e-12)
        assert velocity_out[j] == pytest.approx(ref.velocity, rel=1e-9, abs=1e-10)
        assert effort[j] == pytest.approx(ref.torque, rel=1e-9, abs=1e-9)
        assert bank.state[j, QL] == pytest.approx(ref.link_angle, rel=1e-9, abs=1e-12)
    if params == ServoParams():
        assert abs(position[0] - trajectory(399, period)[0]) < 0.01  # and it did track


def test_a_position_step_settles_on_the_target_against_gravity():
    servo = ReferenceServo(ServoParams(), 0.0)
    servo.command(0.5, 0.0, 0.0)
    for _ in range(600):  # 0.6 s
        servo.step(1e-3)
    assert servo.position == pytest.approx(0.5, abs=1e-4)
    # the drive holds the leg's weight, 30 N·m · sin(0.5), up to the static friction's 3 N·m
    assert abs(servo.torque - 30.0 * math.sin(0.5)) <= 3.0 + 1e-6


def test_static_friction_holds_a_joint_the_drive_does_not_push():
    bank = ServoBank(ServoParams(gravity_torque=2.0, coulomb=3.0, position_gain=0.0, velocity_gain=0.0,
                                 current_gain=0.0), np.array([0.5]))
    for _ in range(100):
        bank.step(1e-3)
    assert bank.state[0, Q] / 100.0 == 0.5  # gravity (< Coulomb) does not move it


def test_the_current_limit_bounds_the_torque():
    servo = ReferenceServo(ServoParams(max_current=2.0), 0.0)
    servo.command(1.0, 0.0, 0.0)
    peak = 0.0
    for _ in range(50):
        servo.step(1e-3)
        peak = max(peak, abs(servo.torque))
    assert peak <= 2.0 * 0.1 * 100.0 * 1.02  # I_max · k_t · N, with the current loop's overshoot


def test_velocity_feedforward_removes_the_lag_of_a_ramp():
    """A ramp with velocity feed-forward: no steady error. Without it, the P position loop
    lags by v / K_p."""
    for ff, lag in ((1.0, 0.0), (0.0, 1.0 / 150.0)):
        servo = ReferenceServo(ServoParams(position_gain=150.0, gravity_torque=0.0), 0.0)
        for k in range(1, 401):
            servo.command(1.0 * k * 1e-3, ff * 1.0, 0.0)
            servo.step(1e-3)
        assert 0.4 - servo.position == pytest.approx(lag, abs=2e-5)


@pytest.mark.parametrize("period", [1e-3, 5e-4])
def test_the_compiled_servo_is_the_reference_model_in_every_loop(period):
    """Loops switched as a CiA 402 drive's mode and state switch them, with a push from outside."""
    params = ServoParams(coulomb=1.0, gravity_torque=10.0)
    bank = ServoBank(params, np.array([0.1]))
    ref = ReferenceServo(params, 0.1)
    schedule = [POSITION_LOOP, VELOCITY_LOOP, CURRENT_LOOP, OFF, VELOCITY_LOOP, POSITION_LOOP]
    for k in range(600):
        loop = schedule[k // 100]
        q, v, a = trajectory(k, period)
        push = 5.0 if 250 <= k < 450 else 0.0
        bank.command(q, v, 2.0 * a, loop)
        bank.set_external_torque(push)
        ref.command(q, v, 2.0 * a, loop)
        ref.external_torque = push
        ref.step(period)
        bank.step(period)
        assert bank.state[0, Q] / 100.0 == pytest.approx(ref.position, rel=1e-9, abs=1e-12), k
        assert bank.state[0, W] / 100.0 == pytest.approx(ref.velocity, rel=1e-9, abs=1e-10), k


def test_the_velocity_loop_holds_the_commanded_speed():
    servo = ReferenceServo(ServoParams(), 0.0)
    for _ in range(300):
        servo.command(0.0, 0.5, 0.0, VELOCITY_LOOP)  # the position target is ignored
        servo.step(1e-3)
    assert servo.velocity == pytest.approx(0.5, abs=1e-3)
    assert servo.position > 0.1


def test_the_current_loop_gives_the_commanded_torque_on_a_held_joint():
    """Against static friction the joint does not move: the torque is the command's."""
    servo = ReferenceServo(ServoParams(gravity_torque=0.0, coulomb=20.0), 0.0)
    for _ in range(50):
        servo.command(0.0, 0.0, 12.0, CURRENT_LOOP)
        servo.step(1e-3)
    assert servo.torque == pytest.approx(12.0, rel=1e-3)
    assert servo.position == 0.0


def test_with_the_power_stage_off_the_joint_coasts_to_rest():
    servo = ReferenceServo(ServoParams(gravity_torque=0.0), 0.0)
    for _ in range(200):
        servo.command(0.0, 1.0, 0.0, VELOCITY_LOOP)
        servo.step(1e-3)
    moving_at = servo.position
    for _ in range(2000):
        servo.command(0.0, 0.0, 0.0, OFF)
        servo.step(1e-3)
    assert servo.torque == 0.0 and servo.velocity == 0.0
    assert servo.position > moving_at  # it ran on before friction stopped it
