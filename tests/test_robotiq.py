"""The Robotiq 2F-85 backend against the simulated gripper, all on 127.0.0.1.

Motion is checked on a manual clock handed to the simulator where timing matters (speed,
faults, stopping): the test moves time, so the positions are exact. Elsewhere the simulator
runs on wall time and the tests poll for a condition with a deadline.
"""

from __future__ import annotations

import asyncio
import importlib
import select
import socket
import subprocess
import sys
import time

import pytest
from conftest import NOT_HUNG_S, require_module

require_module("pymodbus")

from pymodbus.client import ModbusTcpClient

from aiohal.drivers.hands.base import (
    FAULT_COMMUNICATION,
    FAULT_NONE,
    FAULT_NOT_READY,
    VENDOR_FAULT_BASE,
    HandError,
)
from aiohal.drivers.hands.robotiq import (
    RawStatus,
    Robotiq2F85,
    decode_status,
    encode_command,
    fault_code,
)
from aiohal.drivers.hands.robotiq_sim import RobotiqSimServer, running_in_thread
from aiohal.errors import MissingDependencyError

HOST = "127.0.0.1"
TIMEOUT_S = 2.5  # per request; generous: a stall of the host (1.3 s seen) must not fail a healthy link
WAIT_S = 5.0  # for a condition polled on wall time (above TIMEOUT_S)
POLL_S = 0.005
ONE_STEP = 1 / 255  # one position unit of the gripper


class ManualClock:
    """The simulator's clock, moved by the test."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def sim():
    with running_in_thread(host=HOST, port=0, activation_time_s=0.05) as server:
        yield server


@pytest.fixture
def clock():
    return ManualClock()


@pytest.fixture
def clocked_sim(clock):
    """A simulator on the manual clock; activation completes at once."""
    with running_in_thread(host=HOST, port=0, activation_time_s=0.0, clock=clock) as server:
        yield server


@pytest.fixture
def make_hand():
    hands = []

    def make(server, cls=Robotiq2F85, **options):
        options.setdefault("timeout_s", TIMEOUT_S)
        hand = cls(HOST, server.port, **options)
        hands.append(hand)
        return hand

    yield make
    for hand in hands:
        hand.close()


def wait_for(read, predicate, timeout_s=WAIT_S):
    """Poll ``read()`` until ``predicate`` holds; fail with the last value at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = read()
        if predicate(value):
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"not met within {timeout_s} s, last: {value}")
        time.sleep(POLL_S)


# -- register layout and mapping -------------------------------------------------------------


def test_register_layout_on_the_wire(clocked_sim, clock):
    """A plain Modbus client sees the documented byte layout (high byte first)."""
    client = ModbusTcpClient(HOST, port=clocked_sim.port, timeout=TIMEOUT_S, retries=0)
    try:
        assert not client.write_registers(0x03E8, [0x0100, 0, 0], device_id=9).isError()
        # rACT+rGTO, rPR=128, rSP=255, rFR=0x40
        assert not client.write_registers(0x03E8, [0x0900, 0x0080, 0xFF40], device_id=9).isError()
        clock.advance(0.7)
        status = client.read_input_registers(0x07D0, count=3, device_id=9)
        # gACT|gGTO|gSTA=3|gOBJ=3 = 0xF9; no fault, gPR=128; gPO=128, no current
        assert status.registers == [0xF900, 0x0080, 0x8000]
        echo = client.read_holding_registers(0x03E8, count=3, device_id=9)
        assert echo.registers == [0x0900, 0x0080, 0xFF40]
        assert client.write_registers(0x07D0, [0, 0, 0], device_id=9).isError()  # read-only
    finally:
        client.close()
    assert encode_command(0x09, 0x80, 0xFF, 0x40) == [0x0900, 0x0080, 0xFF40]
    assert decode_status([0xF900, 0x5A80, 0x801E]) == RawStatus(
        gact=1, ggto=1, gsta=3, gobj=3, gflt=0xA, kflt=0x5, gpr=0x80, gpo=0x80, gcu=0x1E
    )


@pytest.mark.parametrize(
    ("gflt", "expected"),
    [(0x0, FAULT_NONE), (0x5, FAULT_NOT_READY), (0x7, FAULT_NOT_READY), (0xE, VENDOR_FAULT_BASE + 0xE)],
)
def test_fault_code_mapping(gflt, expected):
    assert fault_code(gflt) == expected


def test_invalid_options_are_refused():
    with pytest.raises(ValueError, match="framing"):
        Robotiq2F85(HOST, framing="ascii")
    with pytest.raises(ValueError, match="timeout_s"):
        Robotiq2F85(HOST, timeout_s=0)


def test_missing_pymodbus_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pymodbus", None)
    monkeypatch.delitem(sys.modules, "aiohal.drivers.hands.robotiq")
    with pytest.raises(MissingDependencyError, match=r"aiohal\[modbus\]"):
        importlib.import_module("aiohal.drivers.hands.robotiq")


# -- activation and motion -------------------------------------------------------------------


def test_open_activates_the_gripper(sim, make_hand):
    hand = make_hand(sim)
    assert hand.read().ready is False  # reading needs no activation
    hand.open()
    status = hand.read()
    assert status.ready is True
    assert status.fault == FAULT_NONE
    assert hand.read_raw().gact == 1


def test_activation_that_never_completes_times_out(make_hand):
    with running_in_thread(host=HOST, port=0, activation_time_s=60.0) as slow:
        hand = make_hand(slow, activation_timeout_s=0.2)
        start = time.monotonic()
        with pytest.raises(HandError) as info:
            hand.open()
        assert 0.2 <= time.monotonic() - start < NOT_HUNG_S  # waited its timeout, then gave up
        assert info.value.code == FAULT_NOT_READY
        assert "did not complete within 0.2 s" in info.value.reason


def test_fingers_reach_the_grasp_target(sim, make_hand):
    hand = make_hand(sim)
    hand.open()
    hand.command(0.5, 1.0, 0.3)
    wait_for(hand.read_raw, lambda raw: raw.gobj == 3)  # at the requested position
    status = hand.read()
    assert status.position == pytest.approx(0.5, abs=ONE_STEP)
    assert status.object_detected is False
    assert status.effort == 0.0


def test_an_object_stops_the_fingers(sim, make_hand):
    sim.set_object(0.6)
    hand = make_hand(sim)
    hand.open()
    hand.command(1.0, 1.0, 0.5)
    status = wait_for(hand.read, lambda s: s.object_detected)
    assert status.position == pytest.approx(0.6, abs=ONE_STEP)
    assert status.effort == pytest.approx(0.5, abs=0.02)  # current follows the force request
    sim.set_object(None)  # the object slips out: the fingers close on
    status = wait_for(hand.read, lambda s: s.position == 1.0)
    assert status.object_detected is False


def test_speed_scales_the_motion(clocked_sim, clock, make_hand):
    hand = make_hand(clocked_sim)
    hand.open()

    def closed_after(speed: float, seconds: float) -> float:
        hand.command(0.0, 1.0, 0.0)
        clock.advance(1.0)
        assert hand.read().position == 0.0
        hand.command(1.0, speed, 0.0)
        clock.advance(seconds)
        return hand.read().position

    assert closed_after(1.0, 0.35) == pytest.approx(0.5, abs=ONE_STEP)  # full stroke in 0.7 s
    assert closed_after(0.5, 0.35) == pytest.approx(0.25, abs=ONE_STEP)
    assert closed_after(0.0, 0.35) == pytest.approx(0.5 / 6, abs=ONE_STEP)  # slowest: 1/6
    assert closed_after(1.0, 0.7) == 1.0


def test_close_stops_the_fingers(clocked_sim, clock, make_hand):
    hand = make_hand(clocked_sim)
    hand.open()
    hand.command(1.0, 1.0, 0.0)
    clock.advance(0.35)
    hand.close()
    clock.advance(0.35)
    assert clocked_sim.gripper.position == pytest.approx(0.5, abs=ONE_STEP)


# -- faults ------------------------------------------------------------------------------------


def test_an_injected_fault_is_reported_and_stops_the_fingers(clocked_sim, clock, make_hand):
    hand = make_hand(clocked_sim)
    hand.open()
    hand.command(1.0, 1.0, 0.0)
    clock.advance(0.35)
    clocked_sim.inject_fault(0xE)  # overcurrent
    status = hand.read()
    assert status.fault == VENDOR_FAULT_BASE + 0xE
    clock.advance(0.35)
    assert hand.read().position == status.position
    clocked_sim.clear_fault()
    clock.advance(0.35)
    status = hand.read()
    assert status.fault == FAULT_NONE
    assert status.position == 1.0


def test_go_to_without_the_activation_bit_is_refused(sim, make_hand):
    client = ModbusTcpClient(HOST, port=sim.port, timeout=TIMEOUT_S, retries=0)
    try:
        assert not client.write_registers(0x03E8, [0x0800, 0x00FF, 0xFFFF], device_id=9).isError()
    finally:
        client.close()
    hand = make_hand(sim)
    status = hand.read()
    assert status.fault == FAULT_NOT_READY
    assert status.ready is False
    assert hand.read_raw().gflt == 0x7
    hand.open()  # the reset clears it
    assert hand.read().fault == FAULT_NONE


def test_go_to_during_activation_is_delayed(clock, make_hand):
    # the manual clock: a stall of the host between the go-to and the read must not complete
    # the activation (a CI run read a 50 ms activation as done)
    with running_in_thread(host=HOST, port=0, activation_time_s=0.05, clock=clock) as sim:
        hand = make_hand(sim)
        hand.command(1.0, 1.0, 0.0)  # no open(): rACT rises with this go-to
        status = hand.read()
        assert status.fault == FAULT_NOT_READY
        assert hand.read_raw().gflt == 0x5
        clock.advance(0.06)
        assert hand.read().ready and hand.read().fault == FAULT_NONE  # then it moves
        clock.advance(1.0)
        assert hand.read().position == 1.0


def test_a_modbus_exception_is_a_clear_error(sim, make_hand):
    class MisaddressedRobotiq(Robotiq2F85):
        STATUS_ADDRESS = 0x0BB8

    hand = make_hand(sim, cls=MisaddressedRobotiq)
    with pytest.raises(HandError) as info:
        hand.read()
    assert info.value.code == FAULT_COMMUNICATION
    assert "input registers 0x0BB8" in info.value.reason
    assert "Modbus exception 2 (ILLEGAL_ADDRESS)" in info.value.reason


# -- the link ----------------------------------------------------------------------------------


def test_a_lost_connection_raises_then_reconnects(sim, make_hand):
    hand = make_hand(sim)
    hand.open()
    port = sim.port
    sim.stop()
    start = time.monotonic()
    with pytest.raises(HandError) as info:
        hand.read()
    assert time.monotonic() - start < NOT_HUNG_S
    assert info.value.code == FAULT_COMMUNICATION
    assert "connection lost" in info.value.reason
    with pytest.raises(HandError) as info:
        hand.command(0.5, 1.0, 0.0)
    assert info.value.code == FAULT_COMMUNICATION

    sim.start()
    assert sim.port == port
    assert hand.read().ready is True  # same gripper, still activated


def test_a_dropped_link_is_reconnected_by_read(sim, make_hand):
    hand = make_hand(sim)
    hand.open()
    sim.drop_connections()
    assert hand.read().ready is True


def test_a_silent_peer_times_out():
    """A peer that accepts the connection but never answers: bounded by timeout_s."""
    with socket.create_server((HOST, 0)) as silent:
        hand = Robotiq2F85(HOST, silent.getsockname()[1], timeout_s=0.2)
        try:
            start = time.monotonic()
            with pytest.raises(HandError) as info:
                hand.read()
            elapsed = time.monotonic() - start
        finally:
            hand.close()  # the failed request dropped the link: no stop is sent
    assert 0.15 <= elapsed < NOT_HUNG_S  # the 0.2 s timeout (less a coarse clock), then it gave up
    assert info.value.code == FAULT_COMMUNICATION
    assert "no valid response within 0.2 s" in info.value.reason


def test_rtu_framing_over_tcp(make_hand):
    with running_in_thread(host=HOST, port=0, activation_time_s=0.05, framing="rtu") as rtu_sim:
        hand = make_hand(rtu_sim, framing="rtu")
        hand.open()
        hand.command(0.5, 1.0, 0.0)
        wait_for(hand.read_raw, lambda raw: raw.gobj == 3)
        assert hand.read().position == pytest.approx(0.5, abs=ONE_STEP)
        hand.close()


# -- the server's own API ----------------------------------------------------------------------


@pytest.mark.asyncio
async def test_server_runs_in_the_current_loop():
    async with RobotiqSimServer(host=HOST, port=0, activation_time_s=0.05) as server:
        assert server.port > 0
        hand = Robotiq2F85(HOST, server.port, timeout_s=TIMEOUT_S)
        try:
            await asyncio.wait_for(asyncio.to_thread(hand.open), WAIT_S)
            status = await asyncio.wait_for(asyncio.to_thread(hand.read), WAIT_S)
            assert status.ready is True
            server.inject_fault(0xC)
            status = await asyncio.wait_for(asyncio.to_thread(hand.read), WAIT_S)
            assert status.fault == VENDOR_FAULT_BASE + 0xC
            port = server.port
            await server.stop()
            await server.start()  # serves the same port and gripper again
            assert server.port == port
            status = await asyncio.wait_for(asyncio.to_thread(hand.read), WAIT_S)
            assert status.fault == VENDOR_FAULT_BASE + 0xC
        finally:
            await asyncio.wait_for(asyncio.to_thread(hand.close), WAIT_S)


def test_command_line_demo_serves_a_gripper(make_hand):
    process = subprocess.Popen(
        [sys.executable, "-m", "aiohal.drivers.hands.robotiq_sim", "--port", "0", "--object", "0.4"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        ready, _, _ = select.select([process.stdout], [], [], 10.0)
        assert ready, "the simulator printed nothing within 10 s"
        line = process.stdout.readline()
        port = int(line.split(":")[1].split()[0])
        hand = Robotiq2F85(HOST, port, timeout_s=TIMEOUT_S)
        try:
            hand.open()
            hand.command(1.0, 1.0, 1.0)
            status = wait_for(hand.read, lambda s: s.object_detected)
            assert status.position == pytest.approx(0.4, abs=ONE_STEP)
        finally:
            hand.close()
    finally:
        process.terminate()
        process.wait(timeout=10)
