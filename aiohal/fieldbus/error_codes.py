"""What a CiA 301 / CiA 402 error code means: the code of a CANopen emergency (EMCY) and of a
drive's error code object 0x603F, and the bits of the error register 0x1001.

A code is looked up exactly first (the drive-specific codes of CiA 402), then by its group
(the high byte, CiA 301's classes), then by its class (the high nibble); a code of none of
them is the manufacturer's own.
"""

from __future__ import annotations

# the wording is aiohal's own, a short phrase per code
_EXACT = {
    0x0000: "no error (error reset)",
    0x2310: "continuous over-current",
    0x2320: "short circuit at the output",
    0x2330: "earth leakage",
    0x3110: "mains over-voltage",
    0x3120: "mains under-voltage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "device over-temperature",
    0x4310: "drive over-temperature",
    0x7121: "motor blocked",
    0x7305: "incremental encoder fault",
    0x8110: "CAN overrun: frames lost",
    0x8120: "CAN error passive",
    0x8130: "heartbeat or life guarding error",
    0x8140: "recovered from bus-off",
    0x8150: "CAN-ID collision",
    0x8210: "PDO not processed: wrong length",
    0x8220: "PDO longer than its mapping",
    0x8240: "SYNC of an unexpected length",
    0x8250: "RPDO timeout",
    0x8611: "following error",
    0x8612: "reference limit",
}
_GROUP = {  # high byte
    0x10: "generic error",
    0x21: "current on the device's input side",
    0x22: "current inside the device",
    0x23: "current on the device's output side",
    0x31: "mains voltage",
    0x32: "voltage inside the device",
    0x33: "output voltage",
    0x41: "ambient temperature",
    0x42: "device temperature",
    0x50: "device hardware",
    0x61: "internal software",
    0x62: "user software",
    0x63: "data set",
    0x70: "additional modules",
    0x81: "communication",
    0x82: "protocol error",
    0x90: "external error",
    0xF0: "additional functions",
    0xFF: "device specific",
}
_CLASS = {  # high nibble
    0x1: "generic error",
    0x2: "current",
    0x3: "voltage",
    0x4: "temperature",
    0x5: "device hardware",
    0x6: "device software",
    0x7: "additional modules",
    0x8: "monitoring",
    0x9: "external error",
}
_REGISTER_BITS = (
    "generic",
    "current",
    "voltage",
    "temperature",
    "communication",
    "device profile",
    "reserved",
    "manufacturer",
)


def describe_error_code(code: int) -> str:
    """The meaning of a CiA 301 / CiA 402 error code, e.g. 0x2310 'continuous over-current'."""
    text = _EXACT.get(code) or _GROUP.get(code >> 8) or _CLASS.get(code >> 12)
    return text or "manufacturer-specific"


def describe_error_register(register: int) -> str:
    """The error register's (0x1001) set bits by name, e.g. 0x03 'generic, current'."""
    return ", ".join(name for bit, name in enumerate(_REGISTER_BITS) if register >> bit & 1) or "none"
