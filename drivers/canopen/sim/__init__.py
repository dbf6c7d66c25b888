"""Simulated CANopen nodes on any python-can interface: CiA 402 drives (:mod:`.drive`) and a
DBC sensor gateway (:mod:`.sensors`). ``virtual`` runs them in the same process as the
master (tests, the one-command demo); ``udp_multicast`` or ``socketcan`` in another
(``python -m aiohal.drivers.canopen.sim``)."""

from __future__ import annotations

import can
import canopen

from .drive import DRIVE_EDS, SimDrive


class SimBus:
    """Simulated nodes on their own python-can bus and canopen network."""

    def __init__(self, interface: str, channel: str, drives: list[int], *, bitrate: int = 1_000_000,
                 **bus_options) -> None:
        self.bus = can.Bus(interface=interface, channel=channel, bitrate=bitrate, receive_own_messages=False,
                           **bus_options)
        self.network = canopen.Network(self.bus)
        self.network.connect()
        self.drives = {node_id: SimDrive(self.network, node_id) for node_id in drives}
        self.sensors = None

    def close(self) -> None:
        for drive in self.drives.values():
            drive.close()
        if self.sensors is not None:
            self.sensors.close()
        self.network.disconnect()


__all__ = ["DRIVE_EDS", "SimBus", "SimDrive"]
