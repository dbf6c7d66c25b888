"""Simulated CANopen nodes on any python-can interface: CiA 402 drives (:mod:`.drive`) and a
DBC sensor gateway (:mod:`.sensors`). ``virtual`` runs them in the same process as the
master (tests, the one-command demo); ``udp_multicast`` or ``socketcan`` in another
(``python -m aiohal.drivers.canopen.sim``)."""

from __future__ import annotations

import can
import canopen

from .drive import DRIVE_EDS, SimDrive
from .sensors import SimSensorGateway


class SimBus:
    """Simulated nodes on their own python-can bus and canopen network."""

    def __init__(
        self,
        interface: str,
        channel: str,
        drives: list[int],
        *,
        bitrate: int = 1_000_000,
        sensors: dict[str, float] | None = None,
        rpdo_transmission_type: int | None = None,
        imu_orientation: bool = True,
        status_ok: int = 1,
        **bus_options,
    ) -> None:
        """``sensors``: the gateway's period per kind (``{"imu": 0.004, "force_torque": 0.004}``), or None.
        ``rpdo_transmission_type``: the drives' RPDOs' at start (e.g. 255, event-driven);
        ``imu_orientation``, ``status_ok``: the gateway's (:class:`.SimSensorGateway`)."""
        self.bus = can.Bus(
            interface=interface, channel=channel, bitrate=bitrate, receive_own_messages=False, **bus_options
        )
        self.network = canopen.Network(self.bus)
        self.network.NOTIFIER_CYCLE = 0.05  # its thread's receive timeout: how long closing waits for it
        self.network.connect()
        self.drives = {
            node_id: SimDrive(self.network, node_id, rpdo_transmission_type=rpdo_transmission_type)
            for node_id in drives
        }
        self.sensors = None
        if sensors is not None:
            self.sensors = SimSensorGateway(
                self.network,
                imu_period_s=sensors.get("imu", 0.002),
                ft_period_s=sensors.get("force_torque", 0.002),
                orientation=imu_orientation,
                status_ok=status_ok,
            )

    def bus_off(self) -> None:
        """What a controller that went bus-off reports: a socketcan error frame of class 0x40."""
        self.bus.send(can.Message(arbitration_id=0x40, is_error_frame=True, data=bytes(8), is_extended_id=False))

    def close(self) -> None:
        for drive in self.drives.values():
            drive.close()
        if self.sensors is not None:
            self.sensors.close()
        self.network.disconnect()


__all__ = ["DRIVE_EDS", "SimBus", "SimDrive", "SimSensorGateway"]
