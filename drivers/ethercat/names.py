"""Name tables of the EtherCAT devices this driver knows by identity (vendor ID, product code).

These are aiohal's simulated slaves (docs/ethercat.md); a real device that is not listed gets
the standard CiA 402 names when its device type says profile 402, and the configuration's
``names`` for the rest. The bus-variable machinery itself lives in :mod:`aiohal.fieldbus.busvar`.
"""

from __future__ import annotations

from aiohal.fieldbus.busvar import CIA402_NAMES, NameTable, object_entries

AIOHAL_VENDOR_ID = 0x000A1A1A
PRODUCT_DRIVE = 0x00000402
PRODUCT_IMU = 0x00001300
PRODUCT_FT = 0x00001600
PRODUCT_DIO = 0x00000808

IMU_NAMES: NameTable = {
    **object_entries(0x6000, "Orientation", "f32", 4),  # quaternion w, x, y, z
    **object_entries(0x6010, "Angular velocity", "f32", 3),  # rad/s
    **object_entries(0x6020, "Linear acceleration", "f32", 3),  # m/s²
    (0x6030, 0): ("Status", "u16"),  # bit 0 valid
}
FT_NAMES: NameTable = {
    (0x7000, 0): ("Control", "u16"),  # bit 0 tare
    **object_entries(0x6000, "Wrench", "f32", 6),  # Fx, Fy, Fz (N), Tx, Ty, Tz (N·m)
    (0x6010, 0): ("Status", "u16"),  # bit 0 valid, bit 1 overload
}
DIO_NAMES: NameTable = {
    **object_entries(0x7000, "Output", "bool", 8),
    **object_entries(0x6000, "Input", "bool", 8),
}
KNOWN_DEVICES: dict[tuple[int, int], NameTable] = {
    (AIOHAL_VENDOR_ID, PRODUCT_DRIVE): CIA402_NAMES,
    (AIOHAL_VENDOR_ID, PRODUCT_IMU): IMU_NAMES,
    (AIOHAL_VENDOR_ID, PRODUCT_FT): FT_NAMES,
    (AIOHAL_VENDOR_ID, PRODUCT_DIO): DIO_NAMES,
}
"""Name tables by (vendor ID, product code)."""
