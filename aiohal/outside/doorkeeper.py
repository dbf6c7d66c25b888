"""The loop's doors to other processes: the shared-memory door (``[client] shm``) and the
network bridges (``[bridge.*]``). Made with the loop's drivers, opened when it is active,
closed with its drivers; each publishes from the end of the tick without blocking."""

from __future__ import annotations

import logging
from typing import Any

log = logging.getLogger(__name__)


class Doors:
    def __init__(self, control: Any) -> None:
        config = control.config
        self._control = control
        self.shm = None
        self.zenoh = None
        if config.client.shm:
            from .shm import ShmDoor

            self.shm = ShmDoor(control, config.client.capacity)
            control.add_publisher(self.shm.publish)
        zenoh_section = config.bridge.zenoh
        if zenoh_section is not None and zenoh_section.enabled:
            from .zenoh import ZenohBridge  # zenoh itself is imported when the bridge starts

            self.zenoh = ZenohBridge(control, zenoh_section)
            control.add_publisher(self.zenoh.publish)

    def activate(self) -> None:
        if self.zenoh is not None:
            try:
                self.zenoh.start()
            except Exception as exc:  # the network door failing must not keep the robot from its safe loop
                self._control.record_fault("bridge:zenoh", "open", exc)
                self.zenoh.close()
                self.zenoh = None
        if self.shm is not None:
            self.shm.activate()

    def close(self) -> None:
        if self.shm is not None:
            self.shm.close()
            self.shm = None
        if self.zenoh is not None:
            self.zenoh.close()
            self.zenoh = None
