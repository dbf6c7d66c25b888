"""Opens and closes the loop's doors to other processes, as the config asks: the shared-memory
door (``[client] shm``) and the network bridges (``[bridge.*]``). They are made with the loop's
drivers, opened when it is active and closed with its drivers. The shared-memory door copies
its state at the end of the tick without blocking; the bridges read the tick ring from a
process of their own."""

from __future__ import annotations

import importlib.util
import logging
from typing import TYPE_CHECKING

from ..errors import MissingDependencyError
from .port import LoopPort

if TYPE_CHECKING:
    from ..config import Config
    from .shm_door import ShmDoor
    from .zenoh import ZenohBridge

log = logging.getLogger(__name__)


def check(config: Config) -> None:
    """Refuse before anything starts what a door would refuse when it opens (the CLI exits 2):
    a Zenoh config file that Zenoh cannot read, a bridge that would take commands from anyone."""
    section = config.bridge.zenoh
    if section is None or not section.enabled or not (section.commands or section.config_file):
        return
    if importlib.util.find_spec("zenoh") is None:
        raise MissingDependencyError("[bridge.zenoh] needs eclipse-zenoh: pip install 'aiohal[zenoh]'")
    from .zenoh_session import check_section

    check_section(section)


class Doorkeeper:
    def __init__(self, port: LoopPort) -> None:
        config = port.config
        self._port = port
        self.shm: ShmDoor | None = None
        self.zenoh: ZenohBridge | None = None
        #: the bridges' counters as they were when each closed (the run report comes after)
        self.closed: dict[str, dict] = {}
        if config.client.shm:
            from .shm_door import ShmDoor

            self.shm = ShmDoor(port, config.client.capacity)
            port.at_tick_end(self.shm.publish)
        zenoh_section = config.bridge.zenoh
        if zenoh_section is not None and zenoh_section.enabled:
            from .zenoh import ZenohBridge  # zenoh itself is imported when the bridge starts

            self.zenoh = ZenohBridge(port, zenoh_section)

    def activate(self) -> None:
        if self.zenoh is not None:
            try:
                self.zenoh.start()
            except Exception as exc:  # the network door failing must not keep the robot from its safe loop
                self._port.record_fault("bridge:zenoh", "open", exc)
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
            self.closed["zenoh"] = dict(self.zenoh.counters)
            self.zenoh = None

    def report(self) -> dict[str, dict]:
        """Each bridge's counters (sent, dropped, refused...): live while open, final once closed."""
        out = dict(self.closed)
        if self.zenoh is not None:
            out["zenoh"] = dict(self.zenoh.counters)
        return out
