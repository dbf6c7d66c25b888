"""The EtherCAT device classes and struct codecs on a process image, without a bus (no root)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from conftest import require_module

require_module("numba")  # the drives' kernels (extra ethercat)
from hypothesis import given, settings
from hypothesis import strategies as st

from aiohal.drivers.ethercat.devices import DriveGroup, DriveSpec, ImuDevice
from aiohal.fieldbus.busvar import (
    PdoLayout,
    ProcessImage,
    ReadOnlyVariableError,
    UnknownVariableError,
    VariableTypeError,
    encode_mapping,
)
from aiohal.fieldbus.cia402 import CSP, CST, CSV, DriveUnits
from aiohal.robot import Fault, ImuGroup, JointCommand, JointState, Mode

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
    with pytest.raises(UnknownVariableError, match=r'"d0.Target velocity"'):
        DriveGroup(image, [DriveSpec("d0", "j0", 0, DriveUnits())], stuck_after=10)


def test_a_drive_variable_of_the_wrong_type_is_refused():
    names = {(0x6064, 0): ("Position actual value", "u32")}
    from aiohal.fieldbus.busvar import CIA402_NAMES
    image = ProcessImage([("d0", layout(names={**CIA402_NAMES, **names}))])
    with pytest.raises(VariableTypeError, match="maps it as i32"):
        DriveGroup(image, [DriveSpec("d0", "j0", 0, DriveUnits())], stuck_after=10)


def test_decode_unwraps_int32_positions_and_converts_units():
    units = DriveUnits(counts_per_rev=4096, gear_ratio=2.0, rated_torque=0.5)
    image, group = drives(2, units)
    set_inputs(image, 0, position=2**31 - 100, velocity=4096, torque=500)
    set_inputs(image, 1, position=-10)
    joints = JointState(2)
    group.bind_state(joints)
    state = joints.block
    group.decode(5, 500)
    before = state.copy()
    set_inputs(image, 0, position=-(2**31) + 100, velocity=4096, torque=500)  # wrapped: +200 counts
    set_inputs(image, 1, position=10)
    assert list(joints.updated_tick) == [5, 5] and list(joints.stamp_ns) == [500, 500]  # stamped by the decode
    group.decode(7, 700, into_state=False)  # a cycle off the loop's thread: unwrapped, the state not touched
    assert np.array_equal(state, before, equal_nan=True)  # (temperature is NaN: not reported)
    assert list(joints.updated_tick) == [5, 5] and list(joints.stamp_ns) == [500, 500]
    group.decode(9, 900)
    assert list(joints.updated_tick) == [9, 9] and list(joints.stamp_ns) == [900, 900]
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
    group.decode(5, 500)
    group.controlwords[:] = [0x0F, 0x0F, 0x06]
    group.hold[:] = [False, False, True]
    command = JointCommand(3)
    command.position[:] = [1.0, 0.0, 0.5]
    command.velocity[:] = [0.0, 2.0, 0.0]
    command.mode[:] = [Mode.POSITION, Mode.VELOCITY, Mode.EFFORT]
    group.write(command)
    k = 1000 / (2 * np.pi)
    assert outputs(image, 0) == (0x0F, round(1.0 * k), 0, 0, CSP)
    assert outputs(image, 1) == (0x0F, 0, round(2.0 * k), 0, CSV)
    assert outputs(image, 2) == (0x06, 1236, 0, 0, CSP)  # held: target = actual
    group.hold[:] = [False] * 3
    command.effort[2], command.feedforward[2] = 30.0, 20.0
    group.write(command)
    assert outputs(image, 2) == (0x06, round(0.5 * k), 0, 32767, CST)  # 50 N·m saturates the int16
    command.effort[2], command.feedforward[2] = -0.25, 0.05
    command.position[0] = np.nan  # never sent by the loop (its limits replace it): held, not garbage
    group.write(command)
    assert outputs(image, 2) == (0x06, round(0.5 * k), 0, -200, CST)  # effort + feed-forward, in ‰
    assert outputs(image, 0) == (0x0F, 1234, 0, 0, CSP)
    group.write_holding()  # every drive held, whatever its mode
    assert [outputs(image, i) for i in range(3)] == [(0x0F, 1234, 0, 0, CSP), (0x0F, 1235, 0, 0, CSP),
                                                      (0x06, 1236, 0, 0, CSP)]


def test_rows_out_of_order_map_each_drive_to_its_joint():
    image, group = drives(3, rows=[2, 0, 1])
    for i in range(3):
        set_inputs(image, i, position=1000 * (i + 1))
    joints = JointState(3)
    group.bind_state(joints)
    group.decode(5, 500)
    counts_per_rad = 131072 / (2 * np.pi)
    assert joints.position * counts_per_rad == pytest.approx([2000, 3000, 1000])


def test_bind_state_writes_the_drivers_rows_of_the_robots_state_and_refuses_too_few_joints():
    units = DriveUnits(counts_per_rev=1000)
    image, group = drives(2, units)
    set_inputs(image, 1, velocity=500)
    robot_state = JointState(5)
    group.bind_state(robot_state.view(slice(2, 4)))  # a driver's joints: a strided view of the robot's block
    group.decode(5, 500)
    assert robot_state.velocity[3] == pytest.approx(500 * 2 * np.pi / 1000)
    assert np.count_nonzero(robot_state.block[:4]) == 1
    assert list(robot_state.updated_tick) == [-1, -1, 5, 5, -1]  # only the driver's joints are stamped
    with pytest.raises(ValueError, match="the joint state has 1 joints, a drive writes row 1"):
        group.bind_state(JointState(1))


def test_imu_device_fills_its_record_and_faults_when_invalid_or_lost():
    from aiohal.drivers.ethercat.names import AIOHAL_VENDOR_ID, KNOWN_DEVICES, PRODUCT_IMU
    from aiohal.fieldbus.busvar import names_for
    tx = [(0x6000, s, 32) for s in range(1, 5)] + [(0x6010, s, 32) for s in range(1, 4)] + \
         [(0x6020, s, 32) for s in range(1, 4)] + [(0x6030, 0, 16)]
    imu_layout = PdoLayout.from_coe([], [0x1A00], {0x1A00: [encode_mapping(*e) for e in tx]},
                                    names_for(AIOHAL_VENDOR_ID, PRODUCT_IMU, known=KNOWN_DEVICES))
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


def test_force_torque_tare_holds_the_control_bit_for_a_few_cycles_then_clears_it():
    from aiohal.drivers.ethercat.devices import ForceTorqueDevice
    from aiohal.drivers.ethercat.names import AIOHAL_VENDOR_ID, KNOWN_DEVICES, PRODUCT_FT
    from aiohal.fieldbus.busvar import VariableTypeError, names_for
    from aiohal.robot import ForceTorqueGroup
    tx = [(0x6000, s, 32) for s in range(1, 7)] + [(0x6010, 0, 16)]
    ft_layout = PdoLayout.from_coe([0x1600], [0x1A00], {0x1600: [encode_mapping(0x7000, 0, 16)],
                                                         0x1A00: [encode_mapping(*e) for e in tx]},
                                   names_for(AIOHAL_VENDOR_ID, PRODUCT_FT, known=KNOWN_DEVICES))
    image = ProcessImage([("ft", ft_layout)])
    group = ForceTorqueGroup(["wrist"])
    variables = {"wrench": "Wrench", "status": "Status"}
    device = ForceTorqueDevice(image, "ft", group["wrist"], variables, control="Control")
    device.tare()
    control = []
    while device.tare_left:
        device.write_control()
        control.append(struct.unpack_from("<H", image.outputs, 0)[0])
    assert control == [1] * (ForceTorqueDevice.TARE_CYCLES - 1) + [0]
    without = ForceTorqueDevice(image, "ft", group["wrist"], variables)
    with pytest.raises(VariableTypeError, match='"ft" has no control output'):
        without.tare()


def test_write_reads_the_drivers_rows_of_the_robots_command_as_they_are_at_each_call():
    image, group = drives(2)
    group.decode(5, 500)
    group.hold[:] = [False, False]
    command = JointCommand(4)
    command.mode[:] = Mode.POSITION
    mine = command.view(slice(1, 3))  # a strided view, as a driver gets
    command.position[:] = [9.0, 0.1, 0.2, 9.0]
    group.write(mine)
    command.position[1:3] = [0.3, -0.4]  # the loop writes the same arrays in place each tick
    group.write(mine)
    k = 131072 / (2 * np.pi)
    assert outputs(image, 0)[1] == round(0.3 * k) and outputs(image, 1)[1] == round(-0.4 * k)
    read_only = JointCommand(4).readonly().view(slice(1, 3))  # the kernel only reads the command
    group.write(read_only)
    assert outputs(image, 0)[1] == 0
    with pytest.raises(ValueError, match="the joint command has 1 joints, a drive reads row 1"):
        group.write(JointCommand(1))  # the kernel does not check bounds: write does, once per command


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 0xFFFF), st.integers(-2**31, 2**31 - 1), st.integers(-2**31, 2**31 - 1),
                          st.integers(-2**15, 2**15 - 1), st.integers(0, 0xFFFF)), min_size=1, max_size=4),
       st.integers(-2**31, 2**31 - 1))
def test_decode_matches_the_bytes_and_unwraps_any_step_of_less_than_half_a_turn_of_the_counter(values, step):
    """The compiled decode against struct's reading of the same bytes; the counts move by the
    int32 difference between cycles, wrapped (steps of less than 2**31 counts are exact)."""
    units = DriveUnits(counts_per_rev=1 << 16, rated_torque=2.0)
    image, group = drives(len(values), units)
    joints = JointState(len(values))
    group.bind_state(joints)
    for i, (sw, pos, vel, tq, err) in enumerate(values):
        set_inputs(image, i, statusword=sw, position=pos, velocity=vel, torque=tq, error=err)
    group.decode(5, 500)
    assert group.statuswords.tolist() == [v[0] for v in values] and group.error_codes.tolist() == [v[4] for v in values]
    assert group.counts.tolist() == [v[1] for v in values]
    assert joints.velocity == pytest.approx([v[2] * 2 * np.pi / (1 << 16) for v in values])
    assert joints.effort == pytest.approx([v[3] / 1000 * 2.0 for v in values])
    for i, (sw, pos, vel, tq, err) in enumerate(values):
        wrapped = (pos + step + 2**31) % 2**32 - 2**31
        set_inputs(image, i, statusword=sw, position=wrapped, velocity=vel, torque=tq, error=err)
    group.decode(5, 500)
    expected = [v[1] + step for v in values]
    assert group.counts.tolist() == expected
    assert joints.position == pytest.approx([c * 2 * np.pi / (1 << 16) for c in expected])


@settings(max_examples=200, deadline=None)
@given(st.floats(-1e12, 1e12), st.floats(-1e12, 1e12), st.floats(-1e6, 1e6), st.sampled_from(list(Mode)))
def test_encode_wraps_the_position_and_clamps_velocity_and_torque_as_the_drive_types_allow(position, velocity,
                                                                                          effort, mode):
    units = DriveUnits(counts_per_rev=1 << 16, rated_torque=2.0)
    image, group = drives(1, units)
    group.decode(5, 500)
    group.hold[:] = [False]
    command = JointCommand(1)
    command.position[0], command.velocity[0], command.effort[0], command.mode[0] = position, velocity, effort, mode
    group.write(command)
    counts_per_rad = (1 << 16) / (2 * np.pi)
    cia = {Mode.VELOCITY: CSV, Mode.EFFORT: CST}.get(mode, CSP)
    target = (round(position * counts_per_rad) + 2**31) % 2**32 - 2**31
    speed = min(max(round(velocity * counts_per_rad), -2**31), 2**31 - 1) if cia != CSP else 0
    torque = min(max(round(effort * 500.0), -2**15), 2**15 - 1) if cia != CSP else 0
    assert outputs(image, 0) == (0, target, speed, torque, cia)


def test_the_kernels_are_called_directly_only_on_arrays_checked_first():
    image, group = drives(2)
    group.hold[:] = False
    plain = JointCommand(2)
    plain.position[:] = [0.5, 0.25]
    plain.mode[:] = Mode.POSITION
    group.write(plain)
    expected = [outputs(image, i) for i in range(2)]
    strided = JointCommand(4)
    strided.block = strided.block[:, ::2]  # 2 joints, every other column: the encode takes any layout
    strided.mode = strided.mode[::2]
    strided.block[0] = [0.5, 0.25]
    strided.mode[:] = Mode.POSITION
    group.write(JointCommand(2))  # zeros in between
    group.write(strided)
    assert [outputs(image, i) for i in range(2)] == expected and expected[0][1] != 0
    wrong = JointCommand(2)
    wrong.mode = wrong.mode.astype(np.int32)  # the kernel reads int8 modes
    with pytest.raises(TypeError, match="encode_drives, argument 5: a 1-d int32 array"):
        group.write(wrong)
    wrong.mode = np.zeros(2, dtype=np.int8)
    group.write(wrong)
    wrong.mode = np.zeros(2, dtype=np.uint8)  # replaced on a command already written: checked again
    with pytest.raises(TypeError, match="encode_drives, argument 5: a 1-d uint8 array"):
        group.write(wrong)
    wrong.mode = np.zeros(2, dtype=np.int8)
    wrong.block = np.zeros((6, 1))  # too few joints: the kernel would read past the end
    with pytest.raises(ValueError, match="the joint command has 1 joints"):
        group.write(wrong)
    state = JointState(2)
    unaligned = np.frombuffer(bytearray(state.block.nbytes + 1), offset=1).reshape(state.block.shape)
    state.block = unaligned  # passes bind_state's own checks (float64, 2-d, writable)
    assert unaligned.flags.writeable and not unaligned.flags.aligned
    with pytest.raises(TypeError, match="decode_drives, argument 4: not aligned"):
        group.bind_state(state)
