"""The ROS 2 service types aiohal serves: ``std_srvs/srv/Trigger``, its request and response in
CDR, and the RIHS01 hash of the service, which rmw_zenoh puts in a service's key expression.

rosbags' Jazzy store holds messages only: a service is registered here, in a store of its own,
as rosidl describes it: the request, the response, the event (``service_msgs/ServiceEventInfo``
and at most one of each), and the service as a struct of the three. ROS 2 reads ``char`` in a
``.msg`` file as ``uint8``; rosbags keeps ``char`` in ``ServiceEventInfo.client_gid``, which
would change every service's hash, so this store takes that field as ``uint8``.
"""

from __future__ import annotations

import functools
from typing import Any

from .messages import typestore as message_typestore

#: the services' own types: (name, [(field, ros type)]) with the response's fields
TRIGGER = "std_srvs/srv/Trigger"
_RESPONSES = {TRIGGER: [("success", "bool"), ("message", "string")]}


@functools.cache
def typestore() -> Any:
    """A Jazzy store with the service types of :data:`_RESPONSES` registered."""
    from rosbags.interfaces import Nodetype
    from rosbags.typesys import Stores, get_typestore

    message_typestore()  # rosbags present, or the error that says which extra to install
    store = get_typestore(Stores.ROS2_JAZZY)
    consts, fields = store.fielddefs["service_msgs/msg/ServiceEventInfo"]
    store.fielddefs["service_msgs/msg/ServiceEventInfo"] = (
        consts,
        [
            (n, (Nodetype.ARRAY, ((Nodetype.BASE, ("uint8", 0)), 16))) if n == "client_gid" else (n, d)
            for n, d in fields
        ],
    )
    types: dict[str, Any] = {}
    for service, response in _RESPONSES.items():
        request_t, response_t, event_t = f"{service}_Request", f"{service}_Response", f"{service}_Event"
        types[request_t] = ([], [])
        types[response_t] = ([], [(n, (Nodetype.BASE, (t, 0))) for n, t in response])
        types[event_t] = (
            [],
            [
                ("info", (Nodetype.NAME, "service_msgs/msg/ServiceEventInfo")),
                ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, request_t), 1))),
                ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, response_t), 1))),
            ],
        )
        types[service] = (
            [],
            [
                ("request_message", (Nodetype.NAME, request_t)),
                ("response_message", (Nodetype.NAME, response_t)),
                ("event_message", (Nodetype.NAME, event_t)),
            ],
        )
    store.register(types)
    return store


def service_hash(service: str) -> str:
    """The RIHS01 hash of a service type (e.g. ``std_srvs/srv/Trigger``), as ROS 2 Jazzy computes it."""
    return str(typestore().hash_rihs01(service))


def deserialize_request(data: bytes | memoryview, service: str) -> Any:
    """A service's request from CDR (``ValueError``-like errors from rosbags if malformed)."""
    return typestore().deserialize_cdr(data, f"{service}_Request")


def serialize_response(service: str, **fields: Any) -> bytes:
    """A service's response in CDR, its fields given by name."""
    store = typestore()
    name = f"{service}_Response"
    return bytes(store.serialize_cdr(store.types[name](**fields), name))
