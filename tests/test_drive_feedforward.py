"""The joint command's feed-forward reaches a CiA 402 drive in CSP as its velocity and torque
offsets (0x60B1, 0x60B2), and the simulated EtherCAT drive applies them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aiohal.drivers.ethercat.sim.drive import Drive
from aiohal.fieldbus.cia402 import DriveUnits
from aiohal.fieldbus.drives import DriveGroup, DriveSpec
from aiohal.robot import JointCommand, JointState, Mode
from aiohal.simulation.cia402_drive import DriveModel

COUNTS_PER_RAD = 131072 / (2 * math.pi)
# byte offsets in RxPDO 0x1602 (controlword, target position, target velocity, target torque,
# mode, velocity offset, torque offset) and TxPDO 0x1A00 (statusword, position, velocity,
# torque, mode display, error code)
RX = [0, 2, 6, 10, 12, 13, 17]
TX = [0, 2, 6, 10, 13]
PERIOD_NS = 1_000_000


class FeedforwardDrive(Drive):
    rx_assign = [0x1602]


def bus(drive_cls=FeedforwardDrive, offsets=RX):
    """A drive and a DriveGroup over one buffer, as a bus would exchange it."""
    drive = drive_cls()
    out_size, in_size = drive.compile_pdo()
    drive.out_addr, drive.in_addr = 0, out_size
    drive.state_changed(0, 8, 0)  # OP: the self-test is done
    image = np.zeros(out_size + in_size + 8, dtype=np.uint8)
    outputs, inputs = image[:out_size + 8], image[out_size:]
    group = DriveGroup.on_buffers(inputs, outputs, [TX + offsets], [DriveSpec("drive1", "j", 0, DriveUnits())],
                                  stuck_after=1000)
    state, command = JointState(1), JointCommand(1)
    group.bind_state(state)
    return drive, image, group, state, command


def cycle(drive, image, group, command, k):
    group.decode(k, k * PERIOD_NS)
    group.update_machines(lambda i, event: None)
    group.write(command)
    drive.exchange(k * PERIOD_NS, image, True)


def enable(drive, image, group, command):
    command.mode[:] = Mode.POSITION
    for k in range(1, 20):
        cycle(drive, image, group, command, k)
    assert group.all_enabled()
    return k


def test_velocity_and_torque_feedforward_arrive_as_0x60b1_and_0x60b2_in_csp():
    drive, image, group, state, command = bus()
    k = enable(drive, image, group, command)
    command.position[:] = state.position
    command.velocity[:] = 0.25
    command.effort[:] = 0.1
    command.feedforward[:] = 0.2
    cycle(drive, image, group, command, k + 1)
    assert drive.model.e_mode.value == 8  # CSP
    assert drive.model.e_vel_offset.value == round(0.25 * COUNTS_PER_RAD)  # counts/s, as 0x60FF
    assert drive.model.e_torque_offset.value == 300  # per mille of the 1 N·m rated torque
    assert drive.model.e_target_vel.value == 0 and drive.model.e_target_torque.value == 0  # CSP: the targets stay 0


def test_a_drive_without_the_offsets_still_gets_its_csp_target():
    drive, image, group, state, command = bus(Drive, [*RX[:5], -1, -1])  # RxPDO 0x1600: no offsets
    k = enable(drive, image, group, command)
    command.position[:] = state.position + 0.01
    command.velocity[:] = 0.25
    cycle(drive, image, group, command, k + 1)
    assert drive.model.e_target_pos.value == round((state.position[0] + 0.01) * COUNTS_PER_RAD)
    assert drive.model.e_vel_offset.value == 0


def test_the_simulated_drive_applies_the_torque_offset():
    """The drive's CSP loop is a PD on its inertia (it compensates its own load model): a
    torque offset is added to its output, so at rest the PD stands off by offset / (J·ω²)."""
    offsets = {}
    for ff in (0.0, 0.2):
        drive, image, group, state, command = bus()
        k = enable(drive, image, group, command)
        hold = float(state.position[0])
        command.position[:] = hold
        command.feedforward[:] = ff
        for j in range(k + 1, k + 400):
            cycle(drive, image, group, command, j)
        offsets[ff] = state.position[0] - hold
    stiffness = DriveModel.inertia * (2 * math.pi * DriveModel.csp_hz) ** 2  # N·m/rad
    assert abs(offsets[0.0]) < 1e-4
    assert offsets[0.2] == pytest.approx(0.2 / stiffness, rel=0.05)


def test_the_simulated_drive_takes_0x60b1_as_its_velocity_feedforward():
    """A ramp: with the target velocity as 0x60B1 the drive follows without the lag of
    deriving it from its targets' slope."""
    lags = {}
    for drive_cls, offsets in ((FeedforwardDrive, RX), (Drive, [*RX[:5], -1, -1])):
        drive, image, group, state, command = bus(drive_cls, offsets)
        k = enable(drive, image, group, command)
        start = float(state.position[0])
        command.velocity[:] = 1.0
        for j in range(1, 300):
            command.position[:] = start + j * 1e-3
            cycle(drive, image, group, command, k + j)
        lags[drive_cls] = start + 299e-3 - state.position[0]
    assert abs(lags[FeedforwardDrive]) < 2e-3 and abs(lags[Drive]) < 2e-3
    assert lags[FeedforwardDrive] == pytest.approx(lags[Drive], abs=2e-3)
