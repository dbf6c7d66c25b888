"""The doors' config sections: ``[client]`` (shared memory) and ``[bridge.zenoh]``. Kept apart
from the doors, so that validating a config opens nothing and imports no network library
(the bridge imports zenoh only when it starts; tests/test_layers.py)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from ..hal import Options


class ClientSection(Options):
    """``[client]``: the shared-memory door for processes on this machine (docs/client.md)."""

    shm: bool = Field(
        False,
        description="Publish state and take setpoints through shared memory "
        "(segment aiohal.<robot>); needed by the stream controller.",
    )
    capacity: int = Field(1024, ge=2, le=1 << 20, description="Setpoints the ring holds.")


class ZenohBridgeSection(Options):
    """``[bridge.zenoh]``: state, report, faults and safety changes published under
    ``<prefix>/<robot>/...``; setpoints and safety requests taken on the keys named here only
    (docs/client.md)."""

    enabled: bool = Field(True, description="Start the bridge with the loop.")
    prefix: str = Field("aiohal", min_length=1, description="First part of every key expression.")
    state_hz: float = Field(100.0, gt=0, le=1000, description="Rate of state messages.")
    report_s: float = Field(1.0, gt=0, description="Period of the report message (s).")
    mode: Literal["peer", "client"] = Field("peer", description="Zenoh session mode (client: through a router).")
    listen: list[str] = Field(default_factory=list, description='Endpoints to listen on, e.g. "tcp/127.0.0.1:7447".')
    connect: list[str] = Field(default_factory=list, description="Endpoints (peers or a router) to connect to.")
    multicast_scouting: bool = Field(True, description="Find peers on the LAN by UDP multicast.")
    config_file: str | None = Field(
        None,
        description="A Zenoh JSON5 config (access control, TLS, authentication); the keys above are applied over it.",
    )
    accept_setpoints: bool = Field(False, description="Take joint setpoints on <prefix>/<robot>/cmd/setpoint.")
    accept_safety: list[Literal["hold", "estop", "rearm"]] = Field(
        default_factory=list,
        description='Safety requests taken on <prefix>/<robot>/cmd/<name>: any of "hold", "estop", "rearm".',
    )
    queue: int = Field(
        64, ge=4, le=1 << 16, description="State snapshots buffered between the tick and the bridge thread."
    )


class BridgeSection(Options):
    zenoh: ZenohBridgeSection | None = None
