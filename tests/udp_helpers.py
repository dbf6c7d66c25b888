"""Builders for the UDP driver tests: a robot view, a driver on given boards, a fake board."""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np

from aiohal.drivers.udp.driver import UdpDriver, UdpOptions
from aiohal.drivers.udp.protocol import STATE_RECORD, Kind, encode
from aiohal.robot import JointSpec, Robot


def robot(n: int) -> Robot:
    return Robot("udp_test", [JointSpec(f"j{i}", i, -3.0, 3.0, 5.0, 50.0, 50.0) for i in range(n)])


def driver_for(rob: Robot, addresses: list[tuple[str, int]], per_board: int, **options) -> UdpDriver:
    names = list(rob.joint_names)
    boards = [{"id": i + 1, "joints": names[i * per_board:(i + 1) * per_board], "address": host, "port": port}
              for i, (host, port) in enumerate(addresses)]
    opts = UdpOptions.model_validate({"boards": boards, "bind_address": "127.0.0.1", "open_timeout_s": 2.0, **options})
    return UdpDriver("boards", rob.driver_view(names), opts)


async def wait_for(condition, timeout: float = 2.0) -> None:
    """Until ``condition()`` holds; AssertionError after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.001)


async def tick(driver: UdpDriver, k: int) -> None:
    clock = driver.view.clock
    clock.tick, clock.now_ns = k, time.monotonic_ns()
    await driver.read()


class FakeBoard:
    """A socket playing one board: the test writes each datagram it sends by hand."""

    def __init__(self, board_id: int = 1, joints: int = 2) -> None:
        self.id, self.joints = board_id, joints
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)
        self.seq = 0

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def receive(self) -> tuple[bytes, tuple]:
        return self.sock.recvfrom(4096)

    def serve_resets(self, driver_address: tuple[str, int] | None = None) -> None:
        """Answer the RESET the driver sends at open."""
        data, addr = self.receive()
        assert data[9] == Kind.RESET
        self.reply(addr, ack=int.from_bytes(data[16:20], "little"))

    def state(self, position: float = 0.0, fault: int = 0) -> np.ndarray:
        rec = np.zeros(self.joints, dtype=STATE_RECORD)
        rec["position"] = position
        rec["fault"] = fault
        return rec

    def reply(self, addr, ack: int, position: float = 0.0, seq: int | None = None, key: bytes | None = None,
              fault: int = 0, board: int | None = None) -> bytes:
        if seq is None:
            self.seq += 1
            seq = self.seq
        data = bytes(encode(Kind.STATE, self.id if board is None else board, seq, ack, self.state(position, fault), key))
        self.sock.sendto(data, addr)
        return data

    def close(self) -> None:
        self.sock.close()
