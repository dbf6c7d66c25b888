"""The EtherCAT device classes and struct codecs on a process image, without a bus (no root)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from aiohal.busvar import (PdoLayout, ProcessImage, ReadOnlyVariableError, UnknownVariableError,
                           VariableTypeError, encode_mapping)
from aiohal.cia402 import CSP, CST, CSV, DriveUnits
from aiohal.drivers.ethercat.devices import DriveGroup, DriveSpec, ImuDevice
from aiohal.robot import Fault, ImuGroup, Mode

RX = [(0x6040, 16), (0x607A, 32), (0x60FF, 32), (0x6071, 16), (0x6060, 8)]
TX = [(0x6041, 16), (0x6064, 32), (0x606C, 32), (0x6077, 16), (0x6061, 8), (0x603F, 16)]
RX_COMPACT = [(0x6040, 16), (0x607A, 32)]


def layout(rx=RX, tx=TX, names=None) -> PdoLayout:
    return PdoLayout.from_coe([0x1600], [0x1A00], {0x1600: [encode_mapping(i, 0, b) for i, b in rx],
                                                   0x1A00: [encode_mapping(i, 0, b) for i, b in tx]}, names)


def drives(n=3, units=None, rows=None):
    image = ProcessImage([(f"d{i}", layout()) for i in range(n)])
    units = units or DriveUnits()
    rows = rows or list(range(n))
    group = DriveGroup(image, [DriveSpec(f"d{i}", f"j{i}", rows[i], units) for i in range(n)], stuck_after=100)
    return image, group


def set_inputs(image, i, statusword=0x0237, position=0, velocity=0, torque=0, error=0):
    base = image.slave(f"d{i}").input_offset
    struct.pack_into("<HiihbH", image.inputs, base, statusword, position, velocity, torque, 8, error)


def outputs(image, i):
    return struct.unpack_from("<Hiihb", image.outputs, image.slave(f"d{i}").output_offset)


def test_codec_reads_and_writes_in_the_order_given_whatever_the_byte_order():
    image = ProcessImage([("d0", layout())])
    set_inputs(image, 0, statusword=0x1234, position=-5, velocity=7, torque=-3, error=0x2310)
    codec = image.codec("d0", ["Error code", "Position actual value", "Statusword"])
    assert codec.unpack() == (0x2310, -5, 0x1234)
    out = image.codec("d0", ["Modes of operation", "Controlword"], writable=True)
    out.pack(9, 0x0F)
    assert outputs(image, 0)[0] == 0x0F and outputs(image, 0)[4] == 9
    out.pack_into(out.buf, out.offset, 10, 0x06)  # the per-cycle form, same order
    assert outputs(image, 0)[0] == 0x06 and outputs(image, 0)[4] == 10


def test_codec_link_errors():
    image = ProcessImage([("d0", layout())])
    with pytest.raises(ReadOnlyVariableError):
        image.codec("d0", ["Statusword"], writable=True)
    with pytest.raises(VariableTypeError, match="one direction"):
        image.codec("d0", ["Statusword", "Controlword"])
    with pytest.raises(UnknownVariableError, match="did you mean"):
        image.codec("d0", ["Statusword", "Positon actual value"])


def test_a_drive_mapping_without_a_needed_variable_is_named_at_link_time():
    image = ProcessImage([("d0", layout(rx=RX_COMPACT))])
    with pytest.raises(UnknownVariableError, match='"d0.Target velocity"'):
        DriveGroup(image, [DriveSpec("d0", "j0", 0, DriveUnits())], stuck_after=10)


def test_a_drive_variable_of_the_wrong_type_is_refused():
    names = {(0x6064, 0): ("Position actual value", "u32")}
    from aiohal.busvar import CIA402_NAMES
    image = ProcessImage([("d0", layout(names={**CIA402_NAMES, **names}))])
    with pytest.raises(VariableTypeError, match="maps it as i32"):
        DriveGroup(image, [DriveSpec("d0", "j0", 0, DriveUnits())], stuck_after=10)


def test_decode_unwraps_int32_positions_and_converts_units():
    units = DriveUnits(counts_per_rev=4096, gear_ratio=2.0, rated_torque=0.5)
    image, group = drives(2, units)
    set_inputs(image, 0, position=2**31 - 100, velocity=4096, torque=500)
    set_inputs(image, 1, position=-10)
    state = np.zeros((6, 2))
    group.bind_state(state[0], state[1], state[2], state[3])
    group.decode()
    before = state.copy()
    set_inputs(image, 0, position=-(2**31) + 100, velocity=4096, torque=500)  # wrapped: +200 counts
    set_inputs(image, 1, position=10)
    group.decode(into_state=False)  # a cycle off the loop's thread: unwrapped, the state not touched
    assert np.array_equal(state, before)
    group.decode()
    counts_per_rad = 4096 * 2 / (2 * np.pi)
    assert state[0, 0] == pytest.approx((2**31 + 100) / counts_per_rad)
    assert state[0, 1] == pytest.approx(10 / counts_per_rad)
    assert state[1, 0] == pytest.approx(4096 / counts_per_rad)  # rad/s at the joint
    assert state[2, 0] == pytest.approx(0.5 * 0.5 * 2.0)  # 500 ‰ of 0.5 N·m, through the 2:1 gear
    assert state[3, 0] == pytest.approx((2**31 + 100) / 4096 * 2 * np.pi)  # motor side


def test_write_holds_drives_not_following_and_maps_modes():
    units = DriveUnits(counts_per_rev=1000, rated_torque=1.0)
    image, group = drives(3, units)
    for i in range(3):
        set_inputs(image, i, position=1234 + i)
    group.decode()
    group.controlwords = [0x0F, 0x0F, 0x06]
    group.hold = [False, False, True]
    position = np.array([1.0, 0.0, 0.5])
    velocity = np.array([0.0, 2.0, 0.0])
    effort = np.array([0.0, 0.0, 0.0])
    mode = np.array([Mode.POSITION, Mode.VELOCITY, Mode.EFFORT], dtype=np.int8)
    group.write(position, velocity, effort, effort, mode)
    k = 1000 / (2 * np.pi)
    assert outputs(image, 0) == (0x0F, round(1.0 * k), 0, 0, CSP)
    assert outputs(image, 1) == (0x0F, 0, round(2.0 * k), 0, CSV)
    assert outputs(image, 2) == (0x06, 1236, 0, 0, CSP)  # held: target = actual
    group.hold = [False] * 3
    group.write(position, velocity, np.array([0.0, 0.0, 50.0]), np.zeros(3), mode)
    assert outputs(image, 2) == (0x06, round(0.5 * k), 0, 32767, CST)  # 50 N·m saturates the int16


def test_rows_out_of_order_map_each_drive_to_its_joint():
    image, group = drives(3, rows=[2, 0, 1])
    for i in range(3):
        set_inputs(image, i, position=1000 * (i + 1))
    state = np.zeros((6, 3))
    group.bind_state(state[0], state[1], state[2], state[3])
    group.decode()
    counts_per_rad = 131072 / (2 * np.pi)
    assert state[0] * counts_per_rad == pytest.approx([2000, 3000, 1000])


def test_bind_state_refuses_rows_decode_could_not_write_in_place():
    _, group = drives(2)
    block = np.zeros((6, 2))
    with pytest.raises(ValueError, match="state velocity: a writable contiguous"):
        group.bind_state(block[0], np.zeros((2, 4))[:, 0], block[2], block[3])
    with pytest.raises(ValueError, match="state effort has 1 joints"):
        group.bind_state(block[0], block[1], np.zeros(1), block[3])


def test_imu_device_fills_its_record_and_faults_when_invalid_or_lost():
    from aiohal.busvar import AIOHAL_VENDOR_ID, PRODUCT_IMU, names_for
    tx = [(0x6000, s, 32) for s in range(1, 5)] + [(0x6010, s, 32) for s in range(1, 4)] + \
         [(0x6020, s, 32) for s in range(1, 4)] + [(0x6030, 0, 16)]
    imu_layout = PdoLayout.from_coe([], [0x1A00], {0x1A00: [encode_mapping(*e) for e in tx]},
                                    names_for(AIOHAL_VENDOR_ID, PRODUCT_IMU))
    image = ProcessImage([("imu", imu_layout)])
    group = ImuGroup(["base"])
    device = ImuDevice(image, "imu", group["base"], {"quaternion": "Orientation", "angular_velocity": "Angular velocity",
                                                      "linear_acceleration": "Linear acceleration", "status": "Status"})
    struct.pack_into("<10fH", image.inputs, 0, 0.5, 0.5, 0.5, 0.5, 0.1, 0.2, 0.3, 0.0, 0.0, 9.81, 1)
    device.read(7, 123, lost=False)
    rec = group["base"]
    assert rec.quaternion == pytest.approx([0.5] * 4) and rec.linear_acceleration[2] == pytest.approx(9.81, abs=1e-5)
    assert rec.updated_tick == 7 and rec.fault == 0
    struct.pack_into("<H", image.inputs, 40, 0)  # status: not valid
    device.read(8, 124, lost=False)
    assert rec.fault == Fault.HARDWARE and rec.updated_tick == 7
    struct.pack_into("<H", image.inputs, 40, 1)  # valid again
    device.read(9, 125, lost=False)
    assert rec.fault == 0 and rec.updated_tick == 9
    device.read(10, 126, lost=True)  # the slave lost: faulted, nothing read
    assert rec.fault == Fault.HARDWARE and rec.updated_tick == 9


def test_write_sees_commands_written_in_place_between_ticks():
    image, group = drives(2)
    group.decode()
    group.hold = [False, False]
    command = np.zeros((6, 2))
    mode = np.full(2, Mode.POSITION, dtype=np.int8)
    command[0] = [0.1, 0.2]
    group.write(command[0], command[1], command[2], command[5], mode)
    command[0] = [0.3, -0.4]  # the loop writes the same arrays in place each tick
    group.write(command[0], command[1], command[2], command[5], mode)
    k = 131072 / (2 * np.pi)
    assert outputs(image, 0)[1] == round(0.3 * k) and outputs(image, 1)[1] == round(-0.4 * k)
    strided = np.zeros((2, 4))[:, 0]  # not contiguous: read afresh every time
    strided[:] = [0.5, 0.6]
    group.write(strided, command[1], command[2], command[5], mode)
    strided[:] = [0.7, 0.8]
    group.write(strided, command[1], command[2], command[5], mode)
    assert outputs(image, 0)[1] == round(0.7 * k) and outputs(image, 1)[1] == round(0.8 * k)
