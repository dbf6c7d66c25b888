"""The simulated CiA 402 drive (:mod:`aiohal.simulation.cia402_drive`) as an EtherCAT slave:
its identity, its PDO mappings and assignment (RxPDO 0x1602 carries the velocity and torque
offsets, for the controller's feed-forward), the AL states it follows.
"""

from __future__ import annotations

from typing import Any, cast

from aiohal.simulation.cia402_drive import DriveModel
from aiohal.simulation.od import ObjectDictionary, PdoCodec

from .devices import Device


class Drive(Device):
    """The simulated CiA 402 drive as an EtherCAT slave: its identity and PDOs; the drive
    itself is the :class:`~aiohal.simulation.cia402_drive.DriveModel` in ``model``."""

    kind = "drive"
    name = "AIOHAL-Drive"
    product = 0x00000402
    device_type = 0x00020192  # CiA 402, servo drive
    ds402_channels = 1
    rx_pdos = {
        0x1600: [(0x6040, 0, 16), (0x607A, 0, 32), (0x60FF, 0, 32), (0x6071, 0, 16), (0x6060, 0, 8)],
        0x1601: [(0x6040, 0, 16), (0x607A, 0, 32)],
        # CSP with the controller's feed-forward: velocity and torque offset
        0x1602: [
            (0x6040, 0, 16),
            (0x607A, 0, 32),
            (0x60FF, 0, 32),
            (0x6071, 0, 16),
            (0x6060, 0, 8),
            (0x60B1, 0, 32),
            (0x60B2, 0, 16),
        ],
    }
    tx_pdos = {
        0x1A00: [(0x6041, 0, 16), (0x6064, 0, 32), (0x606C, 0, 32), (0x6077, 0, 16), (0x6061, 0, 8), (0x603F, 0, 16)],
        0x1A01: [(0x6041, 0, 16), (0x6064, 0, 32)],
    }
    rx_assign = [0x1600]
    tx_assign = [0x1A00]

    def build(self, od: ObjectDictionary) -> None:
        self.model = DriveModel(od, self.emergency)

    def power_on(self) -> None:
        self.model.power_on()

    def compile_pdo(self) -> tuple[int, int]:
        sizes = super().compile_pdo()
        self.model.outputs_mapped(cast(PdoCodec, self.rx_codec).entries)  # super().compile_pdo() has just compiled it
        return sizes

    def step(self, now_ns: int, outputs_valid: bool) -> None:
        self.model.step(now_ns, outputs_valid)

    def outputs_lost(self, now_ns: int) -> None:
        self.model.outputs_lost(now_ns)

    def state_changed(self, old: int, new: int, now_ns: int) -> None:
        if new >= 2:  # PREOP: the self-test is done
            self.model.self_test_done()

    def inject_fault(self, code: int) -> None:
        """An internal drive fault (e.g. 0x2310 over-current): fault reaction, then Fault."""
        self.model.inject_fault(code)

    def configure(self, **kw: Any) -> dict:
        return self.model.configure(**kw)

    def status(self) -> dict:
        return self.model.status()
