"""rmw_zenoh's names and wire formats, so that ROS 2 nodes running ``rmw_zenoh_cpp`` see the
bridge as one of theirs.

Matches rmw_zenoh_cpp 0.2.x, the release of ROS 2 Jazzy, from 0.2.4 on (the attachment in
zenoh's serializer format); the reference is ros2/rmw_zenoh's docs/design.md. What is here:

* a topic's or service's key expression, ``<domain>/<name without its leading />/<DDS type>/<RIHS01 hash>``;
* the liveliness tokens that put a node and its endpoints in the ROS 2 graph,
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]``,
  where every ``/`` inside a field is written ``%``;
* the QoS as the tokens encode it (fields equal to rmw_zenoh's default left empty);
* the attachment every publication, request and reply carries: sequence number and source
  time (int64, little-endian), then the GID's length (16) and the GID;
* an entity's GID, the XXH3-128 of its token (rmw_zenoh derives it so; ROS 2 tools show it).

Plain Python: zenoh is not imported here.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE = "NN", "MP", "MS", "SS"
#: rmw's enum values, as the tokens write them
_BEST_EFFORT, _TRANSIENT_LOCAL = 2, 1
#: the depth rmw_zenoh takes as its default (left empty in a token)
DEFAULT_DEPTH = 42

ATTACHMENT = struct.Struct("<qqB16s")
GID_SIZE = 16


@dataclass(frozen=True)
class Qos:
    """The QoS an endpoint declares (liveliness automatic, no deadline or lifespan)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10

    def token_text(self) -> str:
        """``reliability:durability:history,depth:deadline:lifespan:liveliness``, each field
        empty when it is rmw_zenoh's default (reliable, volatile, keep last 42, infinite)."""
        reliability = "" if self.reliable else str(_BEST_EFFORT)
        durability = str(_TRANSIENT_LOCAL) if self.transient_local else ""
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        return f"{reliability}:{durability}:,{depth}:,:,:,,"


#: ROS 2's default for topics (reliable, volatile, keep last 10), and for services
VOLATILE = Qos()
#: late joiners get the last message (rmw_zenoh: an advanced publisher with a cache of 1)
LATCHED = Qos(transient_local=True, depth=1)


def mangle(name: str) -> str:
    """A name as one chunk of a key expression: each ``/`` becomes ``%``."""
    return name.replace("/", "%")


def dds_type(ros_type: str) -> str:
    """``sensor_msgs/msg/JointState`` → ``sensor_msgs::msg::dds_::JointState_`` (services alike)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def data_key(domain_id: int, name: str, ros_type: str, type_hash: str) -> str:
    """The key expression a topic's messages (or a service's queries) travel on."""
    return f"{domain_id}/{name.strip('/')}/{dds_type(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class Node:
    """A ROS 2 node as rmw_zenoh names it: one per Zenoh session here (node id 0)."""

    domain_id: int
    zid: str  # the session's Zenoh id, as zenoh prints it
    namespace: str  # absolute, e.g. "/arm"
    name: str
    enclave: str = "/"

    def _head(self, entity_id: int, kind: str) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/0/{entity_id}/{kind}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(self.name)}"
        )

    def token(self) -> str:
        """The node's own liveliness token (entity id = node id)."""
        return self._head(0, NODE)

    def endpoint_token(self, entity_id: int, kind: str, name: str, ros_type: str, type_hash: str, qos: Qos) -> str:
        """The token of a publisher, subscription or service server of this node."""
        return (
            f"{self._head(entity_id, kind)}/{mangle(name)}/{mangle(dds_type(ros_type))}/{type_hash}/{qos.token_text()}"
        )

    def qualify(self, name: str) -> str:
        """A topic or service name made absolute in the node's namespace."""
        if name.startswith("/"):
            return name
        return f"{self.namespace.rstrip('/')}/{name}"


def gid(token: str) -> bytes:
    """The entity's GID: XXH3-128 of its liveliness token, low 64 bits first."""
    import xxhash  # with the zenoh extra

    return int(xxhash.xxh3_128_intdigest(token.encode())).to_bytes(GID_SIZE, "little")


def attachment(sequence_number: int, source_time_ns: int, source_gid: bytes) -> bytes:
    """The 33 bytes rmw_zenoh attaches to a publication, a request or a reply."""
    return ATTACHMENT.pack(sequence_number, source_time_ns, GID_SIZE, source_gid)


def read_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source time ns, GID) of an attachment; ``ValueError`` if malformed."""
    if len(data) != ATTACHMENT.size:
        raise ValueError(f"attachment of {len(data)} bytes, not {ATTACHMENT.size}")
    seq, stamp, size, source_gid = ATTACHMENT.unpack(data)
    if size != GID_SIZE:
        raise ValueError(f"attachment GID of {size} bytes, not {GID_SIZE}")
    return seq, stamp, source_gid
