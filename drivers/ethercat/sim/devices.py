"""Device models behind the simulated ESCs (layouts: docs/ethercat.md, "The simulated devices").

A device owns its object dictionary (CoE devices) and its process-data codecs. The ESC calls:

* :meth:`Device.compile_pdo` on PREOP -> SAFEOP (sizes the SyncManagers must have),
* :meth:`Device.exchange` after each frame that carried its process data (decode outputs when
  they are valid, step the model, encode inputs),
* :meth:`Device.outputs_lost` when it leaves OP (master request, SM watchdog, AL error),
* :meth:`Device.state_changed` on every AL state change.

Everything is deterministic: noise, when enabled, comes from a ``random.Random`` seeded per
device.
"""

from __future__ import annotations

import math
import random
from typing import Any

from aiohal.simulation import od as odm
from aiohal.simulation.od import RO, RW, RWP, Entry, ObjectDictionary, PdoCodec, SdoAbort

from .sii import (
    COE_COMPLETE_ACCESS,
    COE_PDO_ASSIGN,
    COE_PDO_CONFIG,
    COE_SDO,
    COE_SDO_INFO,
    FMMU_INPUTS,
    FMMU_MBX_STATE,
    FMMU_OUTPUTS,
    MBX_PROTO_COE,
    SM_INPUTS,
    SM_MBX_IN,
    SM_MBX_OUT,
    SM_OUTPUTS,
    SM_UNUSED,
    SiiDescription,
    SiiPdo,
    SiiPdoEntry,
    SiiSyncManager,
)

VENDOR_ID = 0x000A1A1A
MAILBOX = (0x1000, 128, 0x1080, 128)  # rx (master -> slave) offset/size, tx offset/size
SM2_ADDR = 0x1100
SM3_ADDR = 0x1180
GRAVITY = 9.80665

SIM_INFO = (
    "aiohal simulated EtherCAT slave. Not a product; not an ETG-registered vendor. "
    "Stdlib-only Python ESC model: registers, SII, AL, SyncManagers, FMMUs, CoE, DC. "
    "See docs/ethercat.md."
)


class PdoConfigError(Exception):
    """The PDO configuration cannot be used; ``side`` is 'out' or 'in'."""

    def __init__(self, side: str, message: str) -> None:
        super().__init__(message)
        self.side = side


class Device:
    """Base class: a CoE device with a mailbox, SM2 outputs at 0x1100 and SM3 inputs at 0x1180."""

    kind = "device"
    name = "AIOHAL-Device"
    product = 0
    revision = 1
    device_type = 0
    has_coe = True
    out_addr = SM2_ADDR
    in_addr = SM3_ADDR
    ds402_channels = 0
    rx_pdos: dict[int, list[tuple[int, int, int]]] = {}  # mapping index -> [(index, sub, bits)]
    tx_pdos: dict[int, list[tuple[int, int, int]]] = {}
    rx_assign: list[int] = []
    tx_assign: list[int] = []

    def __init__(self, serial: int = 0, seed: int = 0) -> None:
        self.serial = serial
        self.seed = seed
        self.rng = random.Random(seed)
        self.rx_codec: PdoCodec | None = None
        self.tx_codec: PdoCodec | None = None
        self.out_size = 0
        self.in_size = 0
        self._emergencies: list[tuple[int, int, bytes]] = []
        self.od: ObjectDictionary | None = ObjectDictionary() if self.has_coe else None
        self._od_defaults: list[tuple[Entry, Any]] = []
        if self.od is not None:
            self._common_objects(self.od)
            self.build(self.od)
            self._mapping_objects(self.od)
            self._od_defaults = [(e, e.value) for obj in self.od.objects.values() for e in obj.entries.values()]
        self.power_on()

    def reset_od(self) -> None:
        """Object dictionary values back to their defaults (power cycle)."""
        for e, value in self._od_defaults:
            e.value = value
        self.rx_codec = self.tx_codec = None
        self.out_size = self.in_size = 0

    # ------------------------------------------------------------ to override
    def build(self, od: ObjectDictionary) -> None:
        """Add the device-specific objects."""

    def power_on(self) -> None:
        """Reset the model to its power-on state (also called by a simulated power cycle)."""

    def step(self, now_ns: int, outputs_valid: bool) -> None:
        """Advance the model; outputs (if valid) are already decoded into the OD entries."""

    def outputs_lost(self, now_ns: int) -> None:
        """The slave left OP: outputs are no longer valid (safe state)."""

    def state_changed(self, old: int, new: int, now_ns: int) -> None:
        """AL state change (1 INIT, 2 PREOP, 3 BOOT, 4 SAFEOP, 8 OP)."""

    def configure(self, **kw: Any) -> dict:
        raise ValueError(f"{self.kind}: nothing to configure ({', '.join(kw)})")

    def status(self) -> dict:
        return {}

    # ------------------------------------------------------------ common parts
    @property
    def mailbox(self) -> tuple[int, int, int, int] | None:
        return MAILBOX if self.has_coe else None

    def _common_objects(self, od: ObjectDictionary) -> None:
        od.var(0x1000, "Device type", odm.UINT32, self.device_type)
        od.var(0x1008, "Device name", odm.VISIBLE_STRING, self.name)
        od.var(0x1009, "Hardware version", odm.VISIBLE_STRING, "1.0")
        od.var(0x100A, "Software version", odm.VISIBLE_STRING, "aiohal-sim 0.1")
        od.record(
            0x1018,
            "Identity",
            [
                ("Vendor ID", odm.UINT32, VENDOR_ID, RO),
                ("Product code", odm.UINT32, self.product, RO),
                ("Revision", odm.UINT32, self.revision, RO),
                ("Serial number", odm.UINT32, self.serial, RO),
            ],
        )
        od.array(0x1C00, "Sync manager type", odm.UINT8, [1, 2, 3, 4], 4)
        od.var(0x2000, "Simulator information", odm.VISIBLE_STRING, SIM_INFO)
        od.var(0x2001, "Scratch data", odm.OCTET_STRING, bytes(range(256)), RW)

    def _mapping_objects(self, od: ObjectDictionary) -> None:
        """PDO mapping objects (writable in PREOP) and the SM2/SM3 assignments."""
        for pdos, direction in ((self.rx_pdos, "rx"), (self.tx_pdos, "tx")):
            for index, items in pdos.items():
                words = [(i << 16) | (s << 8) | b for i, s, b in items]
                obj = od.array(
                    index, f"{'Rx' if direction == 'rx' else 'Tx'}PDO 0x{index:04X}", odm.UINT32, words, 16, access=RWP
                )
                obj.entries[0].on_write = self._check_mapping(index, direction)
        for assign_index, values, lo, hi in (
            (0x1C12, self.rx_assign, 0x1600, 0x17FF),
            (0x1C13, self.tx_assign, 0x1A00, 0x1BFF),
        ):
            obj = od.array(
                assign_index,
                "RxPDO assign" if assign_index == 0x1C12 else "TxPDO assign",
                odm.UINT16,
                values,
                4,
                access=RWP,
                low=0,
                high=0xFFFF,
            )
            for sub, e in obj.entries.items():
                if sub:
                    e.on_write = self._check_assign(lo, hi)

    def _check_mapping(self, index: int, direction: str):
        def check(entry: Entry, count: int) -> None:
            obj = self.od.objects[index]  # type: ignore[union-attr]
            old = obj.entries[0].value
            obj.entries[0].value = count
            try:
                odm.mapping_items(self.od, index, direction)  # type: ignore[arg-type]
            finally:
                obj.entries[0].value = old

        return check

    def _check_assign(self, lo: int, hi: int):
        def check(entry: Entry, value: int) -> None:
            if value and not (lo <= value <= hi and value in self.od.objects):  # type: ignore[union-attr]
                raise SdoAbort(odm.ABORT_VALUE_RANGE, f"no PDO 0x{value:04X}")

        return check

    # ------------------------------------------------------------ process data
    def compile_pdo(self) -> tuple[int, int]:
        """Compile the current mapping; returns (output bytes, input bytes)."""
        od = self.od
        assert od is not None
        try:
            self.rx_codec = odm.compile_assignment(od, 0x1C12, "rx")
        except SdoAbort as exc:
            raise PdoConfigError("out", str(exc)) from None
        try:
            self.tx_codec = odm.compile_assignment(od, 0x1C13, "tx")
        except SdoAbort as exc:
            raise PdoConfigError("in", str(exc)) from None
        self.out_size = self.rx_codec.size
        self.in_size = self.tx_codec.size
        return self.out_size, self.in_size

    def exchange(self, now_ns: int, mem: bytearray, outputs_valid: bool) -> None:
        rx = self.rx_codec
        if outputs_valid and rx is not None and rx.size:
            rx.decode(mem, self.out_addr)
        self.step(now_ns, outputs_valid)
        tx = self.tx_codec
        if tx is not None and tx.size:
            tx.encode(mem, self.in_addr)

    def emergency(self, code: int, register: int, data: bytes = b"") -> None:
        self._emergencies.append((code, register, data))

    def take_emergencies(self) -> list[tuple[int, int, bytes]]:
        out, self._emergencies = self._emergencies, []
        return out

    # ------------------------------------------------------------ SII
    def default_sizes(self) -> tuple[int, int]:
        def size(pdos, assign):
            return (sum(b for idx in assign for _, _, b in pdos[idx]) + 7) // 8

        return size(self.rx_pdos, self.rx_assign), size(self.tx_pdos, self.tx_assign)

    def sii_pdos(self, pdos, assign, sm) -> tuple[SiiPdo, ...]:
        out = []
        for index in assign:
            entries = []
            for i, s, b in pdos[index]:
                name, dtype = "", 0
                if self.od is not None and i:
                    e = self.od.entry(i, s)
                    name, dtype = e.name, e.dtype
                entries.append(SiiPdoEntry(i, s, b, dtype, name))
            out.append(SiiPdo(index, sm, tuple(entries), f"PDO 0x{index:04X}"))
        return tuple(out)

    def sii_description(self) -> SiiDescription:
        out_len, in_len = self.default_sizes()
        rx_off, rx_size, tx_off, tx_size = MAILBOX
        return SiiDescription(
            vendor=VENDOR_ID,
            product=self.product,
            revision=self.revision,
            serial=self.serial,
            name=self.name,
            order=self.name,
            mailbox=MAILBOX,
            mailbox_protocols=MBX_PROTO_COE,
            coe_details=COE_SDO | COE_SDO_INFO | COE_PDO_ASSIGN | COE_PDO_CONFIG | COE_COMPLETE_ACCESS,
            ds402_channels=self.ds402_channels,
            fmmus=(FMMU_OUTPUTS, FMMU_INPUTS, FMMU_MBX_STATE),
            sync_managers=(
                SiiSyncManager(rx_off, rx_size, 0x26, 1, SM_MBX_OUT),
                SiiSyncManager(tx_off, tx_size, 0x22, 1, SM_MBX_IN),
                SiiSyncManager(self.out_addr, out_len, 0x64, 1 if out_len else 0, SM_OUTPUTS),
                SiiSyncManager(self.in_addr, in_len, 0x20, 1 if in_len else 0, SM_INPUTS),
            ),
            txpdos=self.sii_pdos(self.tx_pdos, self.tx_assign, 3),
            rxpdos=self.sii_pdos(self.rx_pdos, self.rx_assign, 2),
        )


def _intval(value: Any) -> int:
    return int(value, 0) if isinstance(value, str) else int(value)


def _vec(value: Any, n: int, what: str) -> list[float]:
    v = [float(x) for x in value]
    if len(v) != n:
        raise ValueError(f"{what}: expected {n} numbers, got {len(v)}")
    return v


# ====================================================================== IMU


class Imu(Device):
    """Orientation, angular velocity and linear acceleration; at rest by default (gravity +z)."""

    kind = "imu"
    name = "AIOHAL-IMU"
    product = 0x00001300
    tx_pdos = {
        0x1A00: [
            (0x6000, 1, 32),
            (0x6000, 2, 32),
            (0x6000, 3, 32),
            (0x6000, 4, 32),
            (0x6010, 1, 32),
            (0x6010, 2, 32),
            (0x6010, 3, 32),
            (0x6020, 1, 32),
            (0x6020, 2, 32),
            (0x6020, 3, 32),
            (0x6030, 0, 16),
        ]
    }
    tx_assign = [0x1A00]

    def build(self, od: ObjectDictionary) -> None:
        f = odm.REAL32
        self.e_quat = od.record(0x6000, "Orientation", [(n, f, 0.0, RO) for n in "wxyz"], mappable="tx")
        self.e_gyro = od.record(0x6010, "Angular velocity", [(n, f, 0.0, RO) for n in "xyz"], mappable="tx")
        self.e_acc = od.record(0x6020, "Linear acceleration", [(n, f, 0.0, RO) for n in "xyz"], mappable="tx")
        self.e_status = od.var(0x6030, "Status", odm.UINT16, 0, mappable="tx")

    def power_on(self) -> None:
        self.quat = [1.0, 0.0, 0.0, 0.0]
        self.gyro = [0.0, 0.0, 0.0]
        self.acc = [0.0, 0.0, GRAVITY]
        self.noise = 0.0
        self.valid = True
        self.rng = random.Random(self.seed)
        self._publish(noise=False)

    def _publish(self, noise: bool = True) -> None:
        sigma = self.noise if noise else 0.0
        g = self.rng.gauss if sigma else None
        for e, v in zip(self.e_quat, self.quat, strict=True):
            e.value = v
        for e, v in zip(self.e_gyro, self.gyro, strict=True):
            e.value = v + (g(0.0, sigma) if g else 0.0)
        for e, v in zip(self.e_acc, self.acc, strict=True):
            e.value = v + (g(0.0, sigma) if g else 0.0)
        self.e_status.value = 1 if self.valid else 0

    def step(self, now_ns: int, outputs_valid: bool) -> None:
        self._publish()

    def configure(self, **kw: Any) -> dict:
        for key, value in kw.items():
            if key == "quat":
                q = _vec(value, 4, "quat")
                norm = math.sqrt(sum(x * x for x in q)) or 1.0
                self.quat = [x / norm for x in q]
            elif key == "gyro":
                self.gyro = _vec(value, 3, "gyro")
            elif key == "acc":
                self.acc = _vec(value, 3, "acc")
            elif key == "noise":
                self.noise = float(value)
            elif key == "valid":
                self.valid = bool(value)
            else:
                raise ValueError(f"imu: unknown setting {key!r}")
        self._publish(noise=False)
        return self.status()

    def status(self) -> dict:
        return {"quat": self.quat, "gyro": self.gyro, "acc": self.acc, "noise": self.noise}


# ====================================================================== force/torque


class ForceTorque(Device):
    """A 6-axis force/torque sensor reading a configurable wrench; control bit 0 tares."""

    kind = "ft"
    name = "AIOHAL-FT"
    product = 0x00001600
    rx_pdos = {0x1600: [(0x7000, 0, 16)]}
    tx_pdos = {0x1A00: [(0x6000, i, 32) for i in range(1, 7)] + [(0x6010, 0, 16)]}
    rx_assign = [0x1600]
    tx_assign = [0x1A00]

    def build(self, od: ObjectDictionary) -> None:
        self.e_control = od.var(0x7000, "Control", odm.UINT16, 0, RW, mappable="rx")
        self.e_wrench = od.record(
            0x6000, "Wrench", [(n, odm.REAL32, 0.0, RO) for n in ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")], mappable="tx"
        )
        self.e_status = od.var(0x6010, "Status", odm.UINT16, 0, mappable="tx")

    def power_on(self) -> None:
        self.wrench = [0.0] * 6
        self.offset = [0.0] * 6
        self.noise = 0.0
        self.force_limit = 500.0
        self.torque_limit = 50.0
        self.rng = random.Random(self.seed)
        self._last_control = 0
        self.tares = 0
        self._publish(noise=False)

    def _publish(self, noise: bool = True) -> None:
        sigma = self.noise if noise else 0.0
        for e, w, o in zip(self.e_wrench, self.wrench, self.offset, strict=True):
            e.value = w - o + (self.rng.gauss(0.0, sigma) if sigma else 0.0)
        over = any(abs(x) > self.force_limit for x in self.wrench[:3]) or any(
            abs(x) > self.torque_limit for x in self.wrench[3:]
        )
        self.e_status.value = 1 | (2 if over else 0)

    def step(self, now_ns: int, outputs_valid: bool) -> None:
        control = int(self.e_control.value) if outputs_valid else 0
        if control & 1 and not self._last_control & 1:
            self.offset = list(self.wrench)
            self.tares += 1
        self._last_control = control
        self._publish()

    def configure(self, **kw: Any) -> dict:
        for key, value in kw.items():
            if key == "wrench":
                self.wrench = _vec(value, 6, "wrench")
            elif key == "noise":
                self.noise = float(value)
            elif key == "force_limit":
                self.force_limit = float(value)
            elif key == "torque_limit":
                self.torque_limit = float(value)
            else:
                raise ValueError(f"ft: unknown setting {key!r}")
        self._publish(noise=False)
        return self.status()

    def status(self) -> dict:
        return {"wrench": self.wrench, "offset": self.offset, "tares": self.tares}


# ====================================================================== digital I/O


class DigitalIO(Device):
    """Mailbox-less I/O terminal, PDOs described in the SII only. Inputs read back the outputs
    (one cycle later, as wired in a loop) XOR a pattern. ``channels`` < 8 makes SOEM pack the
    terminal bitwise into the process image."""

    kind = "dio"
    has_coe = False
    out_addr = 0x1000
    in_addr = 0x1100

    def __init__(self, serial: int = 0, seed: int = 0, channels: int = 8) -> None:
        if not 1 <= channels <= 8:
            raise ValueError("dio: 1..8 channels")
        self.channels = channels
        self.name = f"AIOHAL-DIO{channels}"
        self.product = 0x00000800 | channels
        self.mask = (1 << channels) - 1
        self.rx_pdos = {0x1600: [(0x7000, i, 1) for i in range(1, channels + 1)]}
        self.tx_pdos = {0x1A00: [(0x6000, i, 1) for i in range(1, channels + 1)]}
        self.rx_assign = [0x1600]
        self.tx_assign = [0x1A00]
        super().__init__(serial, seed)

    def power_on(self) -> None:
        self.pattern = 0
        self.outputs = 0

    def compile_pdo(self) -> tuple[int, int]:
        self.out_size = self.in_size = 1
        return 1, 1

    def exchange(self, now_ns: int, mem: bytearray, outputs_valid: bool) -> None:
        if outputs_valid:
            self.outputs = mem[self.out_addr] & self.mask
        mem[self.in_addr] = (self.outputs ^ self.pattern) & self.mask

    def outputs_lost(self, now_ns: int) -> None:
        self.outputs = 0  # outputs switch off

    def configure(self, **kw: Any) -> dict:
        for key, value in kw.items():
            if key == "pattern":
                self.pattern = _intval(value) & self.mask
            else:
                raise ValueError(f"dio: unknown setting {key!r}")
        return self.status()

    def status(self) -> dict:
        return {"outputs": self.outputs, "pattern": self.pattern, "channels": self.channels}

    def sii_description(self) -> SiiDescription:
        bool_ = odm.BOOL
        rx = SiiPdo(
            0x1600,
            2,
            tuple(SiiPdoEntry(0x7000, i, 1, bool_, f"Output {i}") for i in range(1, self.channels + 1)),
            "Outputs",
        )
        tx = SiiPdo(
            0x1A00,
            3,
            tuple(SiiPdoEntry(0x6000, i, 1, bool_, f"Input {i}") for i in range(1, self.channels + 1)),
            "Inputs",
        )
        return SiiDescription(
            vendor=VENDOR_ID,
            product=self.product,
            revision=self.revision,
            serial=self.serial,
            name=self.name,
            order=self.name,
            fmmus=(FMMU_OUTPUTS, FMMU_INPUTS),
            sync_managers=(
                SiiSyncManager(0, 0, 0, 0, SM_UNUSED),
                SiiSyncManager(0, 0, 0, 0, SM_UNUSED),
                SiiSyncManager(self.out_addr, 1, 0x64, 1, SM_OUTPUTS),
                SiiSyncManager(self.in_addr, 1, 0x20, 1, SM_INPUTS),
            ),
            txpdos=(tx,),
            rxpdos=(rx,),
        )
