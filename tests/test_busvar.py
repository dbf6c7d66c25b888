"""Bus variables: layouts from the PDO mapping the simulated devices of docs/ethercat.md report,
zero-copy views into the process image, strided views across slaves, and every link error."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from aiohal.drivers.ethercat.names import (
    AIOHAL_VENDOR_ID,
    KNOWN_DEVICES,
    PRODUCT_DIO,
    PRODUCT_DRIVE,
    PRODUCT_FT,
    PRODUCT_IMU,
)
from aiohal.errors import AiohalError
from aiohal.fieldbus.busvar import (
    CIA402_NAMES,
    BitsVar,
    BitVar,
    BusVarError,
    Gather,
    LayoutError,
    PdoLayout,
    ProcessImage,
    ReadOnlyVariableError,
    UnknownVariableError,
    VariableTypeError,
    canonical_type,
    decode_mapping,
    encode_mapping,
    names_for,
    normalise,
    parse_address,
    parse_names,
)

# What the simulated devices report over CoE (docs/ethercat.md): 0x1C12/0x1C13 and the mappings.
DRIVE_RX = [0x60400010, 0x607A0020, 0x60FF0020, 0x60710010, 0x60600008]
DRIVE_TX = [0x60410010, 0x60640020, 0x606C0020, 0x60770010, 0x60610008, 0x603F0010]
IMU_TX = ([encode_mapping(0x6000, s, 32) for s in range(1, 5)] + [encode_mapping(0x6010, s, 32) for s in range(1, 4)]
          + [encode_mapping(0x6020, s, 32) for s in range(1, 4)] + [0x60300010])
FT_RX = [0x70000010]
FT_TX = [encode_mapping(0x6000, s, 32) for s in range(1, 7)] + [0x60100010]


def drive_layout(**kw) -> PdoLayout:
    return PdoLayout.from_coe([0x1600], [0x1A00], {0x1600: DRIVE_RX, 0x1A00: DRIVE_TX},
                              names_for(AIOHAL_VENDOR_ID, PRODUCT_DRIVE, known=KNOWN_DEVICES, **kw))


def imu_layout() -> PdoLayout:
    return PdoLayout.from_coe([], [0x1A00], {0x1A00: IMU_TX}, names_for(AIOHAL_VENDOR_ID, PRODUCT_IMU, known=KNOWN_DEVICES))


def ft_layout() -> PdoLayout:
    return PdoLayout.from_coe([0x1600], [0x1A00], {0x1600: FT_RX, 0x1A00: FT_TX}, names_for(AIOHAL_VENDOR_ID, PRODUCT_FT, known=KNOWN_DEVICES))


def dio_layout() -> PdoLayout:
    """From the SII categories: no mailbox; the SII names are generic, the name table wins."""
    return PdoLayout.from_sii({0x1600: [(0x7000, s, 1, "Output") for s in range(1, 9)]},
                              {0x1A00: [(0x6000, s, 1, "Input") for s in range(1, 9)]},
                              names_for(AIOHAL_VENDOR_ID, PRODUCT_DIO, known=KNOWN_DEVICES))


def robot_image() -> ProcessImage:
    """A bus as a robot has it: drives with an IMU and an F/T sensor in between, and a DIO."""
    slaves = [("drive1", drive_layout()), ("drive2", drive_layout()), ("drive3", drive_layout()), ("imu", imu_layout()),
              ("drive4", drive_layout()), ("drive5", drive_layout()), ("ft", ft_layout()), ("drive6", drive_layout()),
              ("drive7", drive_layout()), ("dio", dio_layout())]
    return ProcessImage(slaves)


DRIVES = [f"drive{i}" for i in range(1, 8)]


# ---------------------------------------------------------------- layouts


@given(st.integers(0, 0xFFFF), st.integers(0, 0xFF), st.integers(0, 0xFF))
def test_mapping_entries_round_trip(index, subindex, bits):
    assert decode_mapping(encode_mapping(index, subindex, bits)) == (index, subindex, bits)


def test_drive_layout_is_what_the_document_says():
    layout = drive_layout()
    out = [(e.address, e.name, e.type, e.bit_offset // 8, e.pdo) for e in layout.outputs]
    assert out == [
        ("0x6040:00", "Controlword", "u16", 0, 0x1600),
        ("0x607A:00", "Target position", "i32", 2, 0x1600),
        ("0x60FF:00", "Target velocity", "i32", 6, 0x1600),
        ("0x6071:00", "Target torque", "i16", 10, 0x1600),
        ("0x6060:00", "Modes of operation", "i8", 12, 0x1600),
    ]
    inp = [(e.address, e.name, e.type, e.bit_offset // 8) for e in layout.inputs]
    assert inp == [
        ("0x6041:00", "Statusword", "u16", 0),
        ("0x6064:00", "Position actual value", "i32", 2),
        ("0x606C:00", "Velocity actual value", "i32", 6),
        ("0x6077:00", "Torque actual value", "i16", 10),
        ("0x6061:00", "Modes of operation display", "i8", 12),
        ("0x603F:00", "Error code", "u16", 13),
    ]
    assert (layout.output_bytes, layout.input_bytes) == (13, 15)
    assert "Target position" in layout.describe()


def test_sensor_layouts_are_what_the_document_says():
    imu, ft, dio = imu_layout(), ft_layout(), dio_layout()
    assert (imu.output_bytes, imu.input_bytes) == (0, 42)
    assert [e.name for e in imu.inputs][:5] == ["Orientation.1", "Orientation.2", "Orientation.3", "Orientation.4",
                                                 "Angular velocity.1"]
    assert imu.inputs[-1].name == "Status" and imu.inputs[-1].bit_offset == 40 * 8
    assert (ft.output_bytes, ft.input_bytes) == (2, 26)
    assert ft.outputs[0].name == "Control" and ft.inputs[5].name == "Wrench.6"
    assert (dio.output_bytes, dio.input_bytes) == (1, 1)
    assert [(e.name, e.type, e.bit_offset) for e in dio.outputs[:2]] == [("Output.1", "bool", 0), ("Output.2", "bool", 1)]


def test_sii_and_coe_give_the_same_layout():
    names = names_for(AIOHAL_VENDOR_ID, PRODUCT_DRIVE, known=KNOWN_DEVICES)
    sii = PdoLayout.from_sii({0x1600: [decode_mapping(v) for v in DRIVE_RX]},
                             {0x1A00: [(*decode_mapping(v), "ignored") for v in DRIVE_TX]}, names)
    assert sii == drive_layout()
    as_lists = PdoLayout.from_entries([[decode_mapping(v) for v in DRIVE_RX]], [[decode_mapping(v) for v in DRIVE_TX]])
    assert as_lists.signature == drive_layout().signature


def test_padding_entries_take_space_but_no_name():
    layout = PdoLayout.from_coe([0x1600], [0x1A00, 0x1A01], {
        0x1600: [0x60400010, 0x00000008, 0x60600008],  # 8 bits of padding between
        0x1A00: [0x60410010, 0x00000004, 0x00000004],
        0x1A01: [0x603F0010],
    })
    assert [(e.type, e.bit_offset) for e in layout.outputs] == [("u16", 0), ("pad", 16), ("i8", 24)]
    assert layout.outputs[1].is_padding and layout.outputs[1].name == ""
    assert layout.inputs[-1].bit_offset == 24 and layout.inputs[-1].pdo == 0x1A01
    image = ProcessImage({"d": layout})
    assert image.link("d.Modes of operation").ctypes.data == image.outputs.ctypes.data + 3
    assert image.link("d.Error code").ctypes.data == image.inputs.ctypes.data + 3
    assert not any(name.endswith(".") or "0x0000" in name for name in image.names())
    with pytest.raises(UnknownVariableError):
        image.link("d.0x0000:00")


def test_unknown_objects_are_named_by_address_or_sii_name():
    layout = PdoLayout.from_sii({0x1600: [(0x2000, 1, 16, "")]}, {0x1A00: [(0x2001, 0, 32, "Motor temperature"),
                                                                           (0x2002, 0, 4, "")]})
    assert [e.name for e in layout.outputs] == ["0x2000:01"]
    assert [(e.name, e.type) for e in layout.inputs] == [("Motor temperature", "u32"), ("0x2002:00", "bits")]


def test_name_overrides_from_config():
    names = names_for(AIOHAL_VENDOR_ID, PRODUCT_DRIVE, known=KNOWN_DEVICES, overrides={
        "0x6041:00": "Status", "0x2001": ["Motor temperature", "INT16"], (0x607A, 0): "Setpoint"})
    layout = PdoLayout.from_coe([0x1600], [0x1A00], {0x1600: DRIVE_RX, 0x1A00: [*DRIVE_TX, 536936464]}, names)
    assert layout.inputs[0].name == "Status" and layout.inputs[0].type == "u16"  # type kept from the table
    assert (layout.inputs[-1].name, layout.inputs[-1].type) == ("Motor temperature", "i16")
    assert layout.outputs[1].name == "Setpoint"
    image = ProcessImage({"drive1": layout})
    assert image.link("drive1.status").dtype == np.dtype("<u2")
    assert image.link("drive1.motor_temperature").dtype == np.dtype("<i2")


def test_name_table_choice_by_device():
    assert names_for(AIOHAL_VENDOR_ID, PRODUCT_IMU, known=KNOWN_DEVICES)[(0x6000, 1)] == ("Orientation.1", "f32")
    assert names_for(0x1234, 0x5678) == CIA402_NAMES  # unknown device: the standard drive objects
    assert names_for(0x1234, 0x5678, device_type=0x00020192) == CIA402_NAMES  # profile 402
    assert names_for(0x1234, 0x5678, device_type=0x00000191) == {}  # profile 401: not a drive


@pytest.mark.parametrize(("overrides", "message"), [
    ({"6041:00": "x"}, "expected an address"),
    ({"0x6041:00": ["x"]}, "expected a name or"),
    ({"0x6041:00": "  "}, "empty name"),
    ({"0x6041:00": ["x", "int17"]}, "unknown type"),
])
def test_bad_name_overrides(overrides, message):
    with pytest.raises(LayoutError, match=message):
        parse_names(overrides)


@pytest.mark.parametrize(("rx", "tx", "mappings", "message"), [
    ([0x1A00], [], {0x1A00: []}, "0x1C12:01 assigns 0x1A00, which is not an RxPDO"),
    ([], [0x1600], {0x1600: []}, "0x1C13:01 assigns 0x1600, which is not an TxPDO"),
    ([0x1600], [], {}, "its mapping was not given"),
    ([0x1600, 0x1600], [], {0x1600: []}, "assigns 0x1600 twice"),
    ([0x1600], [], {0x1600: [1 << 32]}, "not a u32 mapping entry"),
    ([0x1600], [], {0x1600: [0x60400000]}, "0 bits is not a valid"),
    ([0x1600], [], {0x1600: [0x60400020]}, "has 32 bits, but the name table says 'Controlword' is u16"),
])
def test_bad_mappings(rx, tx, mappings, message):
    with pytest.raises(LayoutError, match=message):
        PdoLayout.from_coe(rx, tx, mappings)


def test_type_names_and_normal_form():
    assert canonical_type("UINT16") == canonical_type("u16") == "u16"
    assert canonical_type("REAL32") == "f32" and canonical_type("BOOL") == "bool"
    assert normalise("  Target__ position ") == "target_position" == normalise("TARGET_POSITION")
    assert parse_address("0x607a") == (0x607A, 0) and parse_address("0x6000:0A") == (0x6000, 10)
    assert parse_address("Statusword") is None


# ---------------------------------------------------------------- views


def test_views_are_zero_copy_both_ways():
    image = robot_image()
    drive1 = image.slave("drive1")
    target = image.link("drive1.Target position", writable=True)
    assert target.shape == () and target.dtype == np.dtype("<i4") and target.flags.writeable
    assert np.shares_memory(target, image.outputs)
    target[...] = -123456
    assert bytes(drive1.outputs[2:6]) == struct.pack("<i", -123456)
    drive1.outputs[2:6] = np.frombuffer(struct.pack("<i", 42), np.uint8)
    assert int(target) == 42

    position = image.link("drive1.Position actual value")
    data = bytearray(15)
    struct.pack_into("<HiihbH", data, 0, 0x0237, -7, 99, -5, 8, 0x8611)
    drive1.load_inputs(bytes(data))
    assert int(position) == -7
    assert int(image.link("drive1.Error code")) == 0x8611
    assert int(image.link("drive1.modes of operation display")) == 8
    assert int(image.link("drive1.torque_actual_value")) == -5


def test_object_with_subindices_links_as_one_array():
    image = robot_image()
    q = image.link("imu.Orientation")
    assert q.shape == (4,) and q.dtype == np.dtype("<f4")
    raw = struct.pack("<10fH", 1.0, 0.1, 0.2, 0.3, 4, 5, 6, 7, 8, 9.81, 1)
    image.slave("imu").load_inputs(raw)
    np.testing.assert_allclose(q, [1.0, 0.1, 0.2, 0.3], rtol=1e-6)
    np.testing.assert_allclose(image.link("imu.linear_acceleration"), [7, 8, 9.81], rtol=1e-6)
    assert float(image.link("imu.Orientation.2")) == pytest.approx(0.1)
    assert int(image.link("imu.status")) == 1
    assert image.link("ft.Wrench").shape == (6,)


def test_normalised_names_and_addresses():
    image = robot_image()
    expected = image.link("drive1.Target position").ctypes.data
    for name in ["drive1.target_position", "DRIVE1.TARGET POSITION", "Drive1.target__position",
                 "drive1.0x607A:00", "drive1.0x607a", "drive1.0x607A:0"]:
        assert image.link(name).ctypes.data == expected, name
    assert image.variable("drive1.target_position").full_name == "drive1.Target position"


def test_strided_view_of_seven_drives():
    image = robot_image()
    status = image.link_many(DRIVES, "Statusword")
    assert isinstance(status, np.ndarray) and status.shape == (7,) and status.strides == (15,)
    assert not status.flags.writeable and np.shares_memory(status, image.inputs)
    for i, name in enumerate(DRIVES):
        image.slave(name).inputs[0:2] = np.frombuffer(struct.pack("<H", 0x0230 + i), np.uint8)
    assert status.tolist() == [0x0230 + i for i in range(7)]

    targets = image.link_many(DRIVES, "target_position", writable=True)
    assert targets.strides == (13,)
    targets[:] = np.arange(7) * 1000 - 3000
    for i, name in enumerate(DRIVES):
        assert struct.unpack("<i", image.slave(name).output_bytes()[2:6])[0] == i * 1000 - 3000
    control = image.link_many(DRIVES, "Controlword", np.uint16, writable=True)
    control[:] = 0x0F
    assert all(image.slave(name).output_bytes()[:2] == b"\x0f\x00" for name in DRIVES)


def test_identical_slaves_are_placed_together_whatever_the_bus_order():
    image = robot_image()
    offsets = [image.slave(name).input_offset for name in DRIVES]
    assert offsets == [i * 15 for i in range(7)]
    assert image.slave("imu").input_offset == 7 * 15
    assert image.slaves["imu"] is image.slave("imu")
    assert list(image.slaves) == ["drive1", "drive2", "drive3", "imu", "drive4", "drive5", "ft", "drive6", "drive7",
                                  "dio"]


def test_same_variable_of_sensors_as_a_two_dimensional_view():
    image = ProcessImage([("imu_a", imu_layout()), ("imu_b", imu_layout())])
    q = image.link_many(["imu_a", "imu_b"], "Orientation")
    assert q.shape == (2, 4) and q.strides == (42, 4)
    image.slave("imu_b").load_inputs(struct.pack("<10fH", 0.5, 0.5, 0.5, 0.5, *([0.0] * 6), 1))
    np.testing.assert_allclose(q[1], [0.5] * 4)


def test_gather_when_not_evenly_spaced():
    image = robot_image()
    order = ["drive3", "drive1", "drive7"]
    with pytest.raises(VariableTypeError, match="not evenly spaced"):
        image.link_many(order, "Target position", writable=True, gather=False)
    targets = image.link_many(order, "Target position", writable=True)
    assert isinstance(targets, Gather) and targets.shape == (3,) and len(targets) == 3
    targets[...] = [3, 1, 7]
    assert int(image.link("drive3.Target position")) == 3 and int(image.link("drive7.Target position")) == 7
    targets[1] = -1
    assert np.asarray(targets).tolist() == [3, -1, 7]
    assert targets[2] == 7
    image.slave("drive1").inputs[:2] = [0x37, 0x02]
    status = image.link_many(order, "Statusword")
    assert status.get().tolist() == [0, 0x0237, 0]
    with pytest.raises(ReadOnlyVariableError):
        status[...] = 0


def test_a_single_slave_list_is_a_view():
    image = robot_image()
    one = image.link_many(["drive4"], "Statusword")
    assert one.shape == (1,) and np.shares_memory(one, image.link("drive4.Statusword"))


# ---------------------------------------------------------------- read-only inputs


def test_inputs_are_read_only():
    image = robot_image()
    status = image.link("drive1.Statusword")
    assert not status.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        status[...] = 1
    with pytest.raises(ReadOnlyVariableError, match=r'"drive1.Statusword" is an input') as info:
        image.link("drive1.Statusword", writable=True)
    assert isinstance(info.value, AiohalError) and isinstance(info.value, TypeError)
    with pytest.raises(ReadOnlyVariableError):
        image.link_many(DRIVES, "Statusword", writable=True)
    with pytest.raises(ReadOnlyVariableError):
        image.link("dio.Input.1", writable=True)


def test_outputs_are_read_only_unless_asked():
    image = robot_image()
    control = image.link("drive1.Controlword")
    assert not control.flags.writeable
    assert image.link("drive1.Controlword", writable=True).flags.writeable


# ---------------------------------------------------------------- bit variables


def test_bit_variables():
    image = robot_image()
    dio = image.slave("dio")
    out3 = image.link("dio.Output.3", writable=True)
    assert isinstance(out3, BitVar) and out3.get() is False
    out3.set(True)
    assert dio.outputs[0] == 0b100 and bool(out3)
    image.link("dio.Output.8", writable=True).set(1)
    assert dio.outputs[0] == 0b1000_0100
    out3.set(False)
    assert dio.outputs[0] == 0b1000_0000

    dio.load_inputs(b"\x05")
    assert image.link("dio.Input.1").get() and not image.link("dio.Input.2").get()
    assert image.link("dio.input.3").get()
    with pytest.raises(ReadOnlyVariableError):
        image.link("dio.Output.1").set(True)  # linked without writable=True

    outputs = image.link("dio.Output", writable=True)
    assert isinstance(outputs, BitsVar) and outputs.bits == 8
    outputs.set(0b0101_1010)
    assert dio.output_bytes() == b"\x5a" and int(outputs) == 0x5A
    assert outputs[1] and not outputs[0]
    outputs[0] = True
    assert dio.outputs[0] == 0x5B
    with pytest.raises(ValueError):
        outputs.set(256)
    with pytest.raises(IndexError):
        outputs[8]
    assert image.link("dio.Input").get() == 5


def test_bit_field_that_spans_bytes():
    layout = PdoLayout.from_sii({0x1600: [(0x7000, 1, 3, ""), (0x7000, 2, 10, "Setpoint"), (0x7000, 3, 3, "")]}, {})
    image = ProcessImage({"io": layout})
    field = image.link("io.Setpoint", writable=True)
    assert isinstance(field, BitsVar)
    field.set(0x3FF)
    assert image.outputs.tolist() == [0b1111_1000, 0b0001_1111]
    assert field.get() == 0x3FF
    field.set(0)
    assert image.outputs.tolist() == [0, 0]


# ---------------------------------------------------------------- errors at link time


def test_unknown_names_with_hints():
    image = robot_image()
    cases = {
        "drive1.Statusword2": 'unknown variable "drive1.Statusword2" (did you mean "drive1.Statusword"?)',
        "drvie1.Statusword": 'unknown slave "drvie1" (did you mean "drive1"?)',
        "imu.orientatoin": 'unknown variable "imu.orientatoin" (did you mean "imu.Orientation"?)',
        "drive1": '"drive1": expected "<slave>.<variable>", e.g. "drive1.Statusword"',
        "nowhere.x": 'unknown slave "nowhere"',
    }
    for name, message in cases.items():
        with pytest.raises(UnknownVariableError) as info:
            image.link(name)
        assert str(info.value) == message
        assert isinstance(info.value, LookupError) and isinstance(info.value, AiohalError)
    with pytest.raises(UnknownVariableError, match=r"\(dio has: Output.1, Output.2, .*\.\.\.\)"):
        image.link("dio.zzzzzzzz")


def test_type_and_size_mismatch():
    image = robot_image()
    with pytest.raises(VariableTypeError) as info:
        image.link("drive1.Statusword", np.int16)
    assert str(info.value) == '"drive1.Statusword" is u16 (little-endian), not int16: type mismatch'
    with pytest.raises(VariableTypeError) as info:
        image.link("drive1.Statusword", np.uint32)
    assert str(info.value) == '"drive1.Statusword" is u16 (16 bits per element), uint32 has 32 bits: size mismatch'
    with pytest.raises(VariableTypeError, match="type mismatch"):
        image.link("drive1.Statusword", ">u2")
    with pytest.raises(VariableTypeError, match="not a numpy dtype"):
        image.link("drive1.Statusword", "nonsense")
    with pytest.raises(VariableTypeError, match="type mismatch"):
        image.link_many(DRIVES, "Position actual value", np.float32)
    assert image.link("drive1.Statusword", "<u2").dtype == np.uint16
    assert image.link("imu.Orientation", np.float32).shape == (4,)


def test_bit_variable_requested_as_array():
    image = robot_image()
    with pytest.raises(VariableTypeError) as info:
        image.link("dio.Output.2", np.uint8)
    assert str(info.value) == ('"dio.Output.2" is 1 bit(s) from bit 1 of a byte: not whole bytes on a byte boundary, '
                               "so it has no array view; link it without dtype for a bit accessor")
    with pytest.raises(VariableTypeError, match="bit variables cannot be linked across slaves"):
        ProcessImage([("a", dio_layout()), ("b", dio_layout())]).link_many(["a", "b"], "Input.1")


def test_link_many_errors():
    image = robot_image()
    with pytest.raises(UnknownVariableError, match="listed twice"):
        image.link_many(["drive1", "DRIVE1"], "Statusword")
    with pytest.raises(UnknownVariableError, match="non-empty list"):
        image.link_many([], "Statusword")
    with pytest.raises(UnknownVariableError, match="non-empty list"):
        image.link_many("drive1", "Statusword")
    with pytest.raises(UnknownVariableError, match=r'unknown variable "imu.Statusword"'):
        image.link_many(["drive1", "imu"], "Statusword")


def test_link_many_needs_one_type_shape_and_direction():
    wide = PdoLayout.from_sii({}, {0x1A00: [(0x6041, 0, 32, "")]}, names={(0x6041, 0): ("Statusword", "i32")})
    backwards = PdoLayout.from_sii({0x1600: [(0x6041, 0, 16, "")]}, {})
    flat = PdoLayout.from_sii({}, {0x1A00: [(0x6000, 0, 32, "")]}, names={(0x6000, 0): ("Orientation", "f32")})
    image = ProcessImage([("drive1", drive_layout()), ("wide", wide), ("backwards", backwards), ("imu", imu_layout()),
                          ("flat", flat)])
    with pytest.raises(VariableTypeError) as info:
        image.link_many(["drive1", "wide"], "Statusword")
    assert str(info.value) == '"wide.Statusword" is i32 (input), but "drive1.Statusword" is u16 (input)'
    with pytest.raises(VariableTypeError, match=r'"backwards.Statusword" is u16 \(output\)'):
        image.link_many(["drive1", "backwards"], "Statusword")
    with pytest.raises(VariableTypeError, match=r'"flat.Orientation" is f32 \(input\), but "imu.Orientation" is '
                                                r"f32\[4\] \(input\)"):
        image.link_many(["imu", "flat"], "Orientation")
    # same type, shape and direction: two slaves in image order are always one view, backwards a gather
    sensors = robot_image()
    assert isinstance(sensors.link_many(["imu", "ft"], "Status"), np.ndarray)
    backwards = sensors.link_many(["ft", "imu"], "Status")
    assert isinstance(backwards, Gather) and backwards.dtype == np.dtype("<u2")


def test_ambiguous_names_need_an_address():
    layout = PdoLayout.from_sii({}, {0x1A00: [(0x6000, 1, 16, "Value"), (0x6010, 1, 16, "Value")]}, names={})
    image = ProcessImage({"ai": layout})
    with pytest.raises(UnknownVariableError) as info:
        image.link("ai.value")
    assert str(info.value) == ('"ai.value" is ambiguous: it names 2 entries; use an address: '
                               '"ai.0x6000:01", "ai.0x6010:01"')
    assert image.link("ai.0x6010:01").ctypes.data == image.inputs.ctypes.data + 2


def test_group_with_gaps_cannot_be_one_array():
    layout = PdoLayout.from_sii({}, {0x1A00: [(0x6000, 1, 32, "Gain.1"), (0x6001, 0, 8, "Other"),
                                             (0x6000, 2, 32, "Gain.2")]}, names={})
    image = ProcessImage({"s": layout})
    with pytest.raises(VariableTypeError, match=r'link them one by one: "s.Gain.1", "s.Gain.2"'):
        image.link("s.Gain")
    assert image.link("s.Gain.2").dtype == np.dtype("<u4")


def test_image_construction_errors():
    with pytest.raises(LayoutError, match=r"without '.'"):
        ProcessImage({"a.b": drive_layout()})
    with pytest.raises(LayoutError, match="are the same name"):
        ProcessImage([("Drive 1", drive_layout()), ("drive_1", drive_layout())])
    with pytest.raises(LayoutError, match="expected a PdoLayout"):
        ProcessImage({"d": [1, 2]})


def test_process_image_size_checks_for_pysoem():
    image = robot_image()
    drive1 = image.slave("drive1")
    with pytest.raises(LayoutError, match="got 14 input bytes, its layout has 15"):
        drive1.load_inputs(bytes(14))
    drive1.check_sizes(13, 15)
    with pytest.raises(LayoutError, match="the master maps 12 output and 15 input bytes"):
        drive1.check_sizes(12, 15)
    assert len(drive1.output_bytes()) == 13
    assert len(image.outputs) == 7 * 13 + 2 + 1 and len(image.inputs) == 7 * 15 + 42 + 26 + 1


def test_every_error_is_an_aiohal_error():
    for cls in (LayoutError, UnknownVariableError, VariableTypeError, ReadOnlyVariableError):
        assert issubclass(cls, BusVarError) and issubclass(cls, AiohalError)
