"""The simulated CiA 402 drive with ``dynamics = "servo"``: the shared servo model
(:mod:`aiohal.simulation.servo`) behind the drive's objects, in the drive's motor-side units."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_drive_feedforward import RX, TX, FeedforwardDrive, cycle

from aiohal.drivers.ethercat.sim.drive import Drive
from aiohal.fieldbus.cia402 import DriveUnits
from aiohal.fieldbus.drives import DriveGroup, DriveSpec
from aiohal.robot import JointCommand, JointState, Mode
from aiohal.simulation.servo import ReferenceServo, ServoParams

GEAR = 100.0
COUNTS_PER_MOTOR_RAD = 131072 / (2 * math.pi)
# max_current: the 10 A that 0x6072 (1000 per mille of a 1 N·m motor at 0.1 N·m/A) allows
PARAMS = {"gear_ratio": GEAR, "coulomb": 1.0, "gravity_torque": 20.0, "max_current": 10.0}


def servo_bus(drive_cls=FeedforwardDrive, offsets=RX, start_counts=0):
    """A drive with the cascade (a 100:1 joint) and a DriveGroup in the matching units."""
    drive = drive_cls()
    drive.configure(dynamics="servo", servo=PARAMS, position=start_counts)
    out_size, in_size = drive.compile_pdo()
    drive.out_addr, drive.in_addr = 0, out_size
    drive.state_changed(0, 8, 0)
    image = np.zeros(out_size + in_size + 8, dtype=np.uint8)
    outputs, inputs = image[:out_size + 8], image[out_size:]
    units = DriveUnits(gear_ratio=GEAR, rated_torque=1.0)
    group = DriveGroup.on_buffers(inputs, outputs, [TX + offsets], [DriveSpec("drive1", "j", 0, units)],
                                  stuck_after=1000)
    state, command = JointState(1), JointCommand(1)
    group.bind_state(state)
    return drive, image, group, state, command


def enable(drive, image, group, state, command, mode=Mode.POSITION):
    command.mode[:] = mode
    for k in range(1, 20):
        command.position[:] = state.position
        cycle(drive, image, group, command, k)
    assert group.all_enabled()
    return k


def test_the_drive_runs_the_shared_servo_model_on_what_it_received():
    """Every cycle, the drive's joint is where the plain model puts it when given the targets
    the drive decoded from its objects (0x607A, 0x60B1, 0x60B2)."""
    drive, image, group, state, command = servo_bus()  # at 0 rad, where gravity does not pull
    k0 = enable(drive, image, group, state, command)
    assert drive.model.pos == 0.0
    start = 0.0
    reference = ReferenceServo(ServoParams(**PARAMS), 0.0)
    for k in range(1, 400):
        t = k * 1e-3
        command.position[:] = start + 0.3 * math.sin(6.0 * t)
        command.velocity[:] = 1.8 * math.cos(6.0 * t)
        command.feedforward[:] = -10.8 * math.sin(6.0 * t)
        cycle(drive, image, group, command, k0 + k)
        reference.command(drive.model.e_target_pos.value / COUNTS_PER_MOTOR_RAD / GEAR,
                          drive.model.e_vel_offset.value / COUNTS_PER_MOTOR_RAD / GEAR,
                          drive.model.e_torque_offset.value / 1000.0 * GEAR)
        reference.step(1e-3)
        assert drive.model.pos / COUNTS_PER_MOTOR_RAD / GEAR == pytest.approx(reference.position, rel=1e-9), k
    assert abs(state.position[0] - (start + 0.3 * math.sin(6.0 * 0.398))) < 0.01  # and it tracked


@pytest.mark.parametrize("velocity_ff", [0.0, 1.0])
def test_0x60b1_is_the_cascades_velocity_feedforward(velocity_ff):
    """A 1 rad/s ramp: the P position loop lags by v / K_p without the velocity offset, and
    not at all with it."""
    drive, image, group, state, command = servo_bus(start_counts=0)
    k0 = enable(drive, image, group, state, command)
    start = float(state.position[0])
    command.velocity[:] = velocity_ff
    for k in range(1, 400):
        command.position[:] = start + k * 1e-3
        cycle(drive, image, group, command, k0 + k)
    lag = start + 398e-3 - state.position[0]  # the target sent at tick k is reached at k + 1
    expected = (1.0 - velocity_ff) / ServoParams().position_gain
    assert lag == pytest.approx(expected, abs=2e-4)


def test_cst_gives_the_commanded_joint_torque():
    """Target torque in per mille of the motor's rated torque, through the gear: a joint held
    against a stop (static friction above the command) shows the commanded torque."""
    drive, image, group, state, command = servo_bus()
    drive.configure(servo={**PARAMS, "coulomb": 50.0})
    k0 = enable(drive, image, group, state, command, Mode.EFFORT)
    command.effort[:] = 12.0
    for k in range(1, 50):
        cycle(drive, image, group, command, k0 + k)
    assert drive.model.mode == 10
    assert state.effort[0] == pytest.approx(12.0, rel=0.01)  # 0x6077 through the units
    assert state.position[0] == 0.0


def test_a_disabled_drive_turns_its_power_stage_off():
    drive, image, group, state, command = servo_bus()
    k0 = enable(drive, image, group, state, command)
    command.position[:] = 0.1
    for k in range(1, 200):
        cycle(drive, image, group, command, k0 + k)
    assert abs(state.effort[0]) > 1.0  # holding the leg against gravity
    drive.configure(fault="0x2310")
    for k in range(200, 210):
        cycle(drive, image, group, command, k0 + k)
    assert drive.model.state == "fault" and drive.model.torque == 0.0


@pytest.mark.parametrize("bad, message", [
    ({"dynamics": "rigid"}, "dynamics must be 'motor' or 'servo'"),
    ({"servo": {"gear_ratio": -1}}, "drive: servo: "),
    ({"servo": 3}, "drive: servo must be a table"),
])
def test_a_bad_dynamics_setting_is_refused_with_its_reason(bad, message):
    with pytest.raises(ValueError, match=message):
        Drive().configure(**bad)
