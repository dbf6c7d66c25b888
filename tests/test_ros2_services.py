"""aiohal.ros2.services: the Trigger service's hashes equal ROS 2 Jazzy's, its CDR round-trips."""

from __future__ import annotations

from conftest import require_module

require_module("rosbags")

from aiohal.ros2 import services


def test_trigger_hashes_are_the_ones_ros2_jazzy_computes():
    # the hashes rosidl generates for std_srvs (Jazzy), as ROS 2 tools print them
    store = services.typestore()
    assert services.service_hash("std_srvs/srv/Trigger") == (
        "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
    )
    assert store.hash_rihs01("std_srvs/srv/Trigger_Request") == (
        "RIHS01_d010825374ce8918e72bfd826c82603e60f45419e932ea976f807b74a863a199"
    )
    assert store.hash_rihs01("std_srvs/srv/Trigger_Event") == (
        "RIHS01_ec4a1d26b0575e61906890342aba9523a2360e9845857c5590fa6e23bc39e1c2"
    )


def test_trigger_request_and_response_in_cdr():
    # an empty request is one placeholder byte after the encapsulation header
    request = services.deserialize_request(b"\x00\x01\x00\x00\x00", services.TRIGGER)
    assert request.__msgtype__ == "std_srvs/srv/Trigger_Request"
    data = services.serialize_response(services.TRIGGER, success=False, message="refused")
    back = services.typestore().deserialize_cdr(data, "std_srvs/srv/Trigger_Response")
    assert (back.success, back.message) == (False, "refused")
