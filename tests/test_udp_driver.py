"""The udp driver against simulated boards (in a thread) and a hand-driven fake board: round
trips, every class of bad datagram counted and dropped, board faults, e-stop, a silent board
and forged datagrams. All traffic on 127.0.0.1, ports picked by the OS."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
import pytest_asyncio
from helpers import Reported
from udp_helpers import FakeBoard, driver_for, robot, tick, wait_for

from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.drivers.udp.driver import UdpDriver, UdpError, UdpOptions, board_layout
from aiohal.drivers.udp.protocol import COMMAND_RECORD, STATE_RECORD, BoardFault, Kind, encode
from aiohal.drivers.udp.sim import BoardSimulator
from aiohal.robot import Fault, Mode

#: the simulated boards answer on their own clock, in processes of their own: these run with
#: the realtime group, alone, not beside the parallel tests (a loaded host delays their replies)
pytestmark = pytest.mark.realtime

KEY_HEX = "00112233445566778899aabbccddeeff"
KEY = bytes.fromhex(KEY_HEX)


@pytest.fixture
def sim():
    started = []

    def make(layout, **kwargs):
        s = BoardSimulator(layout, **kwargs).start()
        started.append(s)
        return s

    yield make
    for s in started:
        s.stop()


async def exchange(driver, sim_, k):
    """One tick: write, wait until every board answered, read."""
    replies = sim_.counters()["replies"]
    await driver.write()
    await wait_for(lambda: sim_.counters()["replies"] >= replies + len(sim_.boards))
    await tick(driver, k)


@pytest.mark.asyncio
@pytest.mark.parametrize("keyed", [False, True])
async def test_commands_reach_the_boards_and_state_comes_back(sim, keyed):
    s = sim([2, 2, 1], initial=[0.1, 0.2, 0.3, 0.4, 0.5], key=KEY if keyed else None)
    rob = robot(5)
    d = driver_for(rob, s.addresses, 2, **({"key": KEY_HEX} if keyed else {}))
    # board 3 has one joint: layout from the boards' joint lists
    await d.open()
    try:
        np.testing.assert_allclose(rob.state.position, [0.1, 0.2, 0.3, 0.4, 0.5], atol=1e-6)  # read at open
        rob.command.mode[:] = Mode.POSITION
        rob.command.position[:] = [0.5, -0.5, 1.0, 0.0, -1.0]
        # the boards' servos run on their own clock (5 ms time constant): exchange until they
        # got there, at least 39 times (bounded)
        k, deadline = 0, time.monotonic() + 5.0
        while k < 39 or (np.abs(rob.state.position - rob.command.position).max() > 2e-3
                         and time.monotonic() < deadline):
            k += 1
            await exchange(d, s, k)
        np.testing.assert_allclose(rob.state.position, rob.command.position, atol=2e-3)
        h = d.health()
        assert h["sent"] == 3 * k + 3 and h["received"] == 3 * k + 3
        assert h["lost"] == h["late"] == h["malformed"] == h["unauthenticated"] == 0
        assert 0 < h["round_trip_us_p50"] <= h["round_trip_us_max"]
        assert rob.state.updated_tick.tolist() == [k] * 5 and d.view.fresh_tick == k
        assert s.counters()["commands"] == 3 * k
    finally:
        await d.close()


@pytest.mark.asyncio
async def test_estop_datagram_is_obeyed_at_once_and_latched(sim):
    s = sim([1], initial=[0.0])
    rob = robot(1)
    d = driver_for(rob, s.addresses, 1)
    await d.open()
    try:
        rob.command.mode[:] = Mode.POSITION
        rob.command.position[:] = 1.0
        await exchange(d, s, 1)
        d.estop()
        await wait_for(lambda: s.counters()["estops"] == 1)
        stopped_at = s.model.position[0]
        for k in range(2, 12):
            await exchange(d, s, k)
        assert s.model.position[0] == pytest.approx(stopped_at)  # commands after the e-stop move nothing
        assert d.rx_records["fault"][0] & BoardFault.ESTOP
        assert rob.state.fault[0] & Fault.HARDWARE
    finally:
        await d.close()


@pytest_asyncio.fixture
async def fake():
    board = FakeBoard(1, 2)
    rob = robot(2)
    d = driver_for(rob, [board.address], 2)
    import asyncio

    opening = asyncio.ensure_future(d.open())
    await wait_for(lambda: board.sock.getsockname() is not None)
    await asyncio.get_running_loop().run_in_executor(None, board.serve_resets)
    await opening
    yield board, rob, d
    await d.close()
    board.close()


async def _command(board, d, k):
    """The driver sends tick k's command; the fake board receives it: (its seq, driver address)."""
    await d.write()
    data, addr = board.receive()
    return int.from_bytes(data[16:20], "little"), addr


@pytest.mark.asyncio
async def test_every_class_of_bad_datagram_is_counted_and_dropped(fake):
    import socket

    board, rob, d = fake
    seq, addr = await _command(board, d, 1)
    board.reply(addr, seq, position=0.25)
    await tick(d, 1)
    assert rob.state.position.tolist() == [0.25, 0.25] and d.counters["received"] == 2  # open's reply and this one
    seq, addr = await _command(board, d, 2)
    good = encode(Kind.STATE, 1, board.seq + 1, seq, board.state(0.5))
    cases = {
        "malformed": [b"\x00" * 3, b"AHJB" + bytes(60), bytes(good[:-1]),
                      bytes(good[:10]) + b"\x07" + bytes(good[11:]),  # count changed: CRC and size
                      bytes(encode(Kind.COMMAND, 1, 99, seq, np.zeros(2, dtype=COMMAND_RECORD))),  # wrong kind
                      bytes(encode(Kind.STATE, 1, 99, seq, np.zeros(3, dtype=STATE_RECORD))),  # wrong count
                      bytes(encode(Kind.STATE, 1, 98, seq + 5, board.state(0.5)))],  # answers a command never sent
        "unauthenticated": [bytes(encode(Kind.STATE, 1, 97, seq, board.state(0.5), KEY)),  # a MAC nobody asked for
                            bytes(encode(Kind.STATE, 2, 96, seq, board.state(0.5)))],  # claims another board
    }
    for datagrams in cases.values():
        for data in datagrams:
            board.sock.sendto(data, addr)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))
    stranger.sendto(good, addr)  # a perfect datagram from an address that is not a board's
    stranger.close()
    before = dict(d.counters)
    await tick(d, 2)
    assert d.counters["malformed"] - before["malformed"] == len(cases["malformed"])
    assert d.counters["unauthenticated"] - before["unauthenticated"] == len(cases["unauthenticated"]) + 1
    assert rob.state.position.tolist() == [0.25, 0.25]  # nothing moved
    assert d.counters["lost"] == 1 and d.counters["received"] == before["received"]
    # duplicated, reordered, late: replies that are valid but not new
    seq3, addr = await _command(board, d, 3)
    first = board.reply(addr, seq3, position=0.75, seq=50)
    board.sock.sendto(first, addr)  # the same again
    board.reply(addr, seq3, position=0.9, seq=49)  # an older board seq, after a newer one
    await tick(d, 3)
    assert rob.state.position.tolist() == [0.75, 0.75]
    assert d.counters["duplicated"] == 1 and d.counters["reordered"] == 1
    _seq4, addr = await _command(board, d, 4)
    board.reply(addr, seq3, position=0.1, seq=51)  # answers the command before: late
    await tick(d, 4)
    assert d.counters["late"] == 1 and rob.state.position.tolist() == [0.75, 0.75]
    assert rob.state.updated_tick.tolist() == [3, 3]


@pytest.mark.asyncio
async def test_board_fault_bits_fault_the_joints_and_hold_the_robot(fake):
    board, rob, d = fake
    reported = Reported(d.view)
    d.view.attach(reported)
    seq, addr = await _command(board, d, 1)
    board.reply(addr, seq, fault=BoardFault.DRIVE)
    await tick(d, 1)
    assert (rob.state.fault & Fault.HARDWARE).all()
    assert len(reported.faults) == len(reported.holds) == 1 and "j0" in reported.reasons[0]
    seq, addr = await _command(board, d, 2)
    board.reply(addr, seq)
    await tick(d, 2)
    assert not (rob.state.fault & Fault.HARDWARE).any()


@pytest.mark.asyncio
async def test_a_silent_board_fails_the_driver_after_its_ticks(fake):
    _board, rob, d = fake
    limit = d.options.silent_ticks
    for k in range(1, limit + 1):  # it answered at open (tick 0); silent for 1..limit ticks is tolerated
        await d.write()
        await tick(d, k)
    assert not (rob.state.fault & Fault.HARDWARE).any()
    with pytest.raises(UdpError, match=r"board\(s\) \[1\] silent"):
        await d.write()
        await tick(d, limit + 1)
    assert (rob.state.fault & Fault.HARDWARE).all()


@pytest.mark.asyncio
async def test_forged_commands_move_no_joint_of_a_board(sim):
    """At the board: a command from an address that is not the master's, or with a wrong
    HMAC, is counted and moves nothing."""
    import socket

    master = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    master.bind(("127.0.0.1", 0))
    master.settimeout(2.0)
    s = sim([1], initial=[0.0], key=KEY, master=master.getsockname())
    target = s.addresses[0]
    cmd = np.zeros(1, dtype=COMMAND_RECORD)
    cmd["mode"], cmd["position"] = Mode.POSITION, 1.0
    forger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    forger.bind(("127.0.0.1", 0))
    try:
        forger.sendto(bytes(encode(Kind.COMMAND, 1, 1, 0, cmd, KEY)), target)  # right key, wrong address
        master.sendto(bytes(encode(Kind.COMMAND, 1, 2, 0, cmd, bytes(16))), target)  # right address, wrong key
        master.sendto(bytes(encode(Kind.COMMAND, 1, 3, 0, cmd)), target)  # no MAC
        await wait_for(lambda: s.counters()["unauthenticated"] == 3)
        master.sendto(bytes(encode(Kind.RESET, 1, 4, 0, None, KEY)), target)  # a genuine datagram, to sync on
        master.recvfrom(4096)
        assert s.model.position[0] == 0.0 and s.counters()["commands"] == 0
        master.sendto(bytes(encode(Kind.COMMAND, 1, 5, 0, cmd, KEY)), target)
        master.recvfrom(4096)
        assert s.counters()["commands"] == 1
    finally:
        forger.close()
        master.close()


def test_boards_must_cover_the_joints_in_order():
    joints = ["a", "b", "c"]
    opts = UdpOptions.model_validate({"boards": [{"id": 1, "joints": ["b"], "port": 1}, {"id": 2, "joints": ["a", "c"], "port": 2}]})
    _, problems = board_layout(opts, joints)
    assert problems and "board 1" in problems[0]
    opts = UdpOptions.model_validate({"boards": [{"id": 1, "joints": ["a", "b"], "port": 1}]})
    assert board_layout(opts, joints)[1] == ["joints ['c'] are on no board"]
    assert board_layout(UdpOptions(), joints)[1] == ["list the boards (or set simulate = true)"]
    assert board_layout(UdpOptions(simulate=True, joints_per_board=2), joints)[0] == [(1, 0, 2), (2, 2, 1)]
    with pytest.raises(ValueError, match="at least 16"):
        UdpOptions(key="00ff")


def _config(n: int, seconds_rate: int = 500, **options) -> dict:
    """``n`` simulated boards of one joint; their process at its SCHED_FIFO priority where
    allowed (the default): they stand for hardware, which answers on time on a loaded host."""
    return {
        "robot": {"name": "udp_loop"},
        "loop": {"rate_hz": seconds_rate, "max_feedback_age": 400},
        "joints": {f"j{i}": {"position": [-2.0, 2.0], "velocity": 2.0, "acceleration": 20.0, "effort": 50.0} for i in range(n)},
        "driver": [{"type": "udp", "name": "boards", "joints": ["*"], "options": {"simulate": True, **options}}],
        "controller": {"type": "sine", "params": {"amplitude": 0.2, "frequency": 1.0}},
    }


@pytest.mark.asyncio
async def test_a_loop_runs_on_simulated_boards_it_started_itself():
    loop = ControlLoop(parse_config(_config(4, key=KEY_HEX, silent_ticks=200)))  # the boards at their priority
    async with loop:
        report = await loop.run(duration=0.5)
    health = loop.report()["drivers"]["boards"]  # after close: with the simulated boards' own counters
    assert report["faults"] == [] and report["safety_level"] == "run"
    # most of the ticks run got each board's reply (a loaded host skips ticks: those sent nothing)
    assert health["received"] > 0.5 * report["ticks"] * 4 and health["unauthenticated"] == health["malformed"] == 0
    assert health["simulated_boards"]["commands"] > 0 and health["simulated_boards"]["unauthenticated"] == 0


@pytest.mark.asyncio
async def test_a_board_that_dies_sends_the_robot_to_its_safe_state():
    loop = ControlLoop(parse_config(_config(3, silent_ticks=25, simulation={"die_board": 2, "die_after_s": 0.1})))
    async with loop:
        report = await loop.run(duration=1.0)
    health = loop.report()["drivers"]["boards"]
    assert report["safety_level"] == "estop" and report["stop_reason"] == "no driver left"  # its only driver
    assert any("board(s) [2] silent" in f["error"] for f in report["faults"]), report["faults"]
    assert report["drivers"]["boards"]["status"] == "failed"
    assert health["simulated_boards"]["estops"] >= 3  # every board got the e-stop datagram


# a reply is taken when it answers the newest command, which a reply 5 ms late does only if
# the loop (normal priority) sent nothing for 3 ms more than its period: a host that stalls it so
@pytest.mark.host_reference(3.0)
@pytest.mark.asyncio
async def test_boards_that_answer_only_late_are_named_apart_from_silent_ones():
    """Every reply 5 ms late (2.5 ticks at 500 Hz) answers a command older than the last one
    sent: none is taken, so the driver fails, and its error says the boards answered late."""
    loop = ControlLoop(parse_config(_config(3, silent_ticks=25, simulation={"delay_ms": 5.0})))
    async with loop:
        report = await loop.run(duration=2.0)
    health = loop.report()["drivers"]["boards"]
    error = next(f["error"] for f in report["faults"] if f["source"] == "driver:boards")
    assert "board(s) [1, 2, 3] answered only late" in error and "silent" not in error, error
    assert health["late"] > 25 and health["status"] == "failed"
    # no reply taken on the tick: no round trip (open's RESET answers have no send time)
    assert health["round_trip_us_max"] is None, health


@pytest.mark.asyncio
async def test_a_stall_of_this_process_is_not_a_silent_board():
    """The boards answer commands: while this process did not run (here blocked for 0.3 s,
    150 ticks at 500 Hz, between a read and the write, when no reply is due) none were sent,
    and the boards are not silent."""
    from aiohal.controllers.hold import HoldController

    class StallsOnce(HoldController):
        def update(self, t: float, dt: float) -> None:
            if round(t * 500) == 100:
                time.sleep(0.3)
            super().update(t, dt)

    loop = ControlLoop(parse_config(_config(3, silent_ticks=25)),
                       controller=StallsOnce())
    async with loop:
        report = await loop.run(ticks=300)
    assert not any("silent" in f["error"] for f in report["faults"]), report["faults"]
    assert report["drivers"]["boards"]["status"] == "open" and loop.slots[0].driver.silent_boards == []


@pytest.mark.asyncio
async def test_servo_boards_track_a_ramp_and_velocity_feedforward_removes_its_lag():
    """``dynamics = "servo"`` through the driver and the boards' process it starts: a ramp at
    v lags behind the commands by v / K_p without velocity feed-forward (the P position loop
    makes its speed from that error) and hardly at all with it, the command's velocity being
    the board's velocity feed-forward. K_p = 50 1/s, not the default 150: the parameters
    reached the process. Each lag is the median over the second half of a 0.3 s ramp (the
    loop settles in 5 / K_p = 0.1 s); both also hold the board's own hold-off of one command,
    v times the time since it came, which the difference cancels."""
    v, gain = 0.5, 50.0
    rob = robot(1)
    opts = UdpOptions.model_validate({
        "simulate": True, "bind_address": "127.0.0.1", "silent_ticks": 1000,
        # the boards' process at its priority where allowed: it reports its counters on time
        "simulation": {"dynamics": "servo", "servo": {"position_gain": gain, "gravity_torque": 0.0}},
    })
    d = UdpDriver("boards", rob.driver_view(rob.joint_names), opts)
    await d.open()
    lags: dict[bool, list[float]] = {False: [], True: []}
    try:
        rob.command.mode[:] = Mode.POSITION
        t0 = time.monotonic()
        k, feedforward, phase_start = 0, False, 0.0
        # each phase at least 0.3 s and 20 samples (a stalled host takes longer, bounded by 10 s)
        while (t := time.monotonic() - t0) < 10.0 and k < 20_000:
            if t - phase_start >= 0.3 and len(lags[feedforward]) >= 20:
                if feedforward:
                    break
                feedforward, phase_start = True, t
            k += 1
            rob.command.position[:] = v * t
            rob.command.velocity[:] = v if feedforward else 0.0
            await d.write()
            await asyncio.sleep(0.002)
            await tick(d, k)
            if rob.state.updated_tick[0] == k and t - phase_start >= 0.15:  # the board's state when command k came
                lags[feedforward].append(v * t - float(rob.state.position[0]))
    finally:
        await d.close()
    assert len(lags[False]) >= 20 and len(lags[True]) >= 20, {ff: len(x) for ff, x in lags.items()}
    without, with_ff = float(np.median(lags[False])), float(np.median(lags[True]))
    print(f"ramp lag: {without * 1e3:.2f} mrad without velocity feed-forward, {with_ff * 1e3:.2f} mrad with it, "
          f"a command every {t / k * 1e3:.2f} ms")
    assert without - with_ff == pytest.approx(v / gain, rel=0.2), (without, with_ff)
    assert 0.0 < with_ff < 0.5 * without, (without, with_ff)  # what is left: the hold-off of one command
    assert d.health()["simulated_boards"]["commands"] >= k


@pytest.mark.asyncio
async def test_after_an_emergency_stop_the_boards_are_reset_and_the_robot_re_armed_without_a_jump():
    """estop: every board latches its stop; while the loop commands nothing the driver keeps
    the boards answering (braked where they stand); reset_faults() RESETs them, rearm()
    restarts the sine from the measured position."""
    from helpers import assert_rearmed_from_disabled, record

    loop = ControlLoop(parse_config(_config(3, silent_ticks=100)))
    async with loop:
        sent, measured, own = record(loop)
        await loop.run(duration=0.6)  # the sine moving
        loop.estop()
        report = await loop.run(duration=0.3)  # far longer than silent_ticks: the boards still answer
        assert report["safety_level"] == "estop" and report["drivers"]["boards"]["status"] != "failed"
        assert np.all(loop.robot.state.fault != 0)  # the boards report their latched stop
        loop.reset_faults()
        await loop.run(duration=0.1)  # the RESETs answered
        held = loop.robot.state.position.copy()
        rearm_tick = loop.robot.clock.tick
        loop.rearm()
        report = await loop.run(duration=1.0)
    health = loop.report()["drivers"]["boards"]
    assert report["safety_level"] == "run"
    assert [t["event"] for t in report["safety"]] == ["activate", "estop", "reset_faults", "rearm"]
    assert health["simulated_boards"]["estops"] >= 3
    assert_rearmed_from_disabled(loop, sent, measured, own, rearm_tick, held, 1e-3, moving_after=200)
