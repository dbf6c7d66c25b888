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


#: why a bridge with commands refuses to start (the error of the key ``bridge.zenoh.commands``)
UNCONTROLLED = (
    "commands are taken only where Zenoh controls who may send them: name a config_file with "
    "access_control (enabled, with rules and policies), user/password authentication "
    "(transport.auth.usrpwd.dictionary_file) or TLS with client certificates "
    "(transport.link.tls.enable_mtls, every listen endpoint tls/ or quic/); or, on a lab network, "
    "set allow_anyone = true"
)


class ZenohBridgeSection(Options):
    """``[bridge.zenoh]``: the robot as a ROS 2 node over rmw_zenoh (docs/ros2.md). It publishes
    only, unless commands are enabled by name; then it starts only where Zenoh controls who
    reaches it (``config_file``) or ``allow_anyone`` says a lab does without."""

    enabled: bool = Field(True, description="Start the bridge with the loop.")
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the ROS 2 graph the bridge joins.")
    namespace: str | None = Field(
        None,
        pattern=r"^(/[A-Za-z_][A-Za-z0-9_]*)+$",
        description='The node\'s namespace: its topics and services are under it (default "/<robot name>").',
    )
    node: str = Field("aiohal", pattern=r"^[A-Za-z_][A-Za-z0-9_]*$", description="The ROS 2 node's name.")
    state_hz: float = Field(100.0, gt=0, le=1000, description="Rate of joint_states messages.")
    report_s: float = Field(1.0, gt=0, description="Period of the diagnostics and tick timing messages (s).")
    mode: Literal["peer", "client"] = Field("peer", description="Zenoh session mode (client: through a router).")
    listen: list[str] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:0"],
        description="Endpoints to listen on (default: loopback, a port the system picks).",
    )
    connect: list[str] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"],
        description="Endpoints to connect to (default: the local Zenoh router, rmw_zenohd, as rmw_zenoh sessions do).",
    )
    multicast_scouting: bool = Field(False, description="Find peers on the LAN by UDP multicast.")
    config_file: str | None = Field(
        None,
        description="A Zenoh JSON5 config (access control, TLS, authentication); the keys above are applied over it.",
    )
    commands: list[Literal["setpoints", "estop", "hold", "reset_faults", "rearm"]] = Field(
        default_factory=list,
        description='What the bridge takes from the network: any of "setpoints" (the joint_trajectory topic), '
        '"estop", "hold", "reset_faults", "rearm" (services). None by default: it publishes only.',
    )
    allow_anyone: bool = Field(
        False,
        description="Take the commands without access control (a lab network only; a warning at every start).",
    )
    queue: int = Field(
        64, ge=4, le=1 << 16, description="State snapshots buffered between the tick and the bridge thread."
    )


class BridgeSection(Options):
    zenoh: ZenohBridgeSection | None = None
