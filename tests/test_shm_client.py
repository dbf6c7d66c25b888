"""The shared-memory door: consistent reads under a fast writer, the setpoint ring's order,
wrap and underrun, the stream controller's interpolation, safety requests, and clear errors."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from conftest import NOT_HUNG_S, ROOT
from helpers import arm_raw, virtual_loop

from aiohal.client import (
    BufferFull,
    CommandBusy,
    CommandRequired,
    JointMismatch,
    NotStreaming,
    RequestRefused,
    RequestTimeout,
    RobotClient,
    RobotNotRunning,
)
from aiohal.config import parse_config
from aiohal.core.loop import ControlLoop
from aiohal.errors import AiohalError, ConfigError
from aiohal.outside import shm_segment
from aiohal.safety import SafetyLevel, SafetyRequestRefused

JOINTS = ["j0", "j1", "j2"]


def unique(prefix: str = "shm") -> str:
    return f"{prefix}_{uuid.uuid4().hex[:8]}"


def stream_raw(name: str, *, capacity: int = 16, dry: float = 0.1, clock: str = "virtual") -> dict:
    raw = arm_raw(3, type="stream", params={"dry_after_s": dry})
    raw["robot"]["name"] = name
    raw["loop"]["clock"] = clock
    raw["client"] = {"shm": True, "capacity": capacity}
    for joint in raw["joints"].values():  # limits that leave the streamed points as they are
        joint.update(velocity=100.0, acceleration=1e6)
    # the mock mirrors the command, so the measured state shows what the controller sent
    return raw


# ---------------------------------------------------------------- seqlock


def test_no_torn_read_under_a_fast_writer():
    name, dof = unique("torn"), 64
    writer = subprocess.Popen([sys.executable, str(ROOT / "tests" / "shm_writer.py"), name, str(dof), str(NOT_HUNG_S)],
                              cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert writer.stdout.readline().strip() == "ready"
        client = RobotClient(name)
        snapshots, ticks, unguarded_torn = 0, set(), 0
        # 1.5 s, and on until the writer was seen at 100 ticks (a loaded host runs it less often)
        end, deadline = time.monotonic() + 1.5, time.monotonic() + NOT_HUNG_S
        seg = client._seg
        raw_state, raw_cmd = np.empty((6, dof)), np.empty((6, dof))
        state = None
        while (time.monotonic() < end or len(ticks) <= 100) and time.monotonic() < deadline and snapshots < 200_000:
            state = client.read(state)
            k = state.tick
            # every array of one snapshot was written at the same tick
            assert (state.state == k).all() and (state.command == k).all(), f"torn snapshot at tick {k}"
            assert (state.fault == (k & 0xFFFF)).all() and state.now_ns == k
            ticks.add(k)
            snapshots += 1
            # the same copies without the sequence check, to show that the writer overlaps readers
            np.copyto(raw_state, seg.state)
            np.copyto(raw_cmd, seg.command)
            unguarded_torn += raw_state[0, 0] != raw_cmd[-1, -1]
        client.close()
        assert len(ticks) > 100, "the writer did not run while the reader read"
        print(f"{snapshots} consistent snapshots of {len(ticks)} ticks; {unguarded_torn} torn without the seqlock")
    finally:
        writer.stdin.close()  # it stops
        writer.wait(timeout=30)
    assert writer.returncode == 0


# ---------------------------------------------------------------- ring and stream controller


@pytest.mark.asyncio
async def test_points_are_applied_in_order_through_a_wrapping_ring():
    name = unique()
    loop = virtual_loop(stream_raw(name, capacity=4, dry=1.0))
    async with loop:
        with RobotClient(name, joints=JOINTS, command=True) as client:
            await loop.run(ticks=2)
            # point k (1..20) at T0 + (k-1)·3 ms, value 0.01·k: in order, the command is one line
            t0 = client.read().now_ns + 3_000_000
            k, full, checked = 1, 0, 0
            while k <= 20 or client.pending:
                while k <= 20:
                    try:
                        client.send([0.01 * k] * 3, t_ns=t0 + (k - 1) * 3_000_000)
                    except BufferFull:
                        full += 1
                        break
                    k += 1
                assert client.pending <= 4
                await loop.run(ticks=2)
                s = client.read()
                if t0 <= s.now_ns <= t0 + 19 * 3_000_000:
                    expected = 0.01 * (1 + (s.now_ns - t0) / 3e6)
                    np.testing.assert_allclose(s.command_position, expected, atol=1e-12)
                    checked += 1
            assert full >= 10 and checked >= 15  # the ring was full often; 20 points through 4 slots
            await loop.run(ticks=10)
            np.testing.assert_allclose(client.read().command_position, 0.2, atol=1e-12)
            assert client.applied == 20 and client.refused == 0 and client.pending == 0
        assert loop.level == SafetyLevel.RUN and not loop.faults


@pytest.mark.asyncio
async def test_linear_interpolation_between_points():
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=1.0))
    async with loop:
        with RobotClient(name, command=True) as client:
            await loop.run(ticks=1)
            t0 = client.read().now_ns
            client.send([0.0, 0.0, 0.0], t_ns=t0 + 1_000_000)
            client.send([0.1, -0.1, 0.05], t_ns=t0 + 101_000_000)
            await loop.run(ticks=51)  # 50 ms into the 100 ms segment
            s = client.read()
            frac = (s.now_ns - (t0 + 1_000_000)) / 100e6
            assert 0.4 < frac < 0.6
            np.testing.assert_allclose(s.command_position, frac * np.array([0.1, -0.1, 0.05]), atol=1e-12)
            np.testing.assert_allclose(s.command_velocity, [1.0, -1.0, 0.5], atol=1e-9)


@pytest.mark.asyncio
async def test_hermite_interpolation_with_velocities():
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=1.0))
    async with loop:
        with RobotClient(name, command=True) as client:
            await loop.run(ticks=1)
            t0 = client.read().now_ns + 1_000_000
            T = 0.2
            qa, va, qb, vb = np.array([0.0, 0.1, 0.2]), np.array([0.5, 0.0, -0.5]), np.array([0.1, 0.3, 0.0]), np.zeros(3)
            client.send(qa, velocity=va, t_ns=t0)
            client.send(qb, velocity=vb, t_ns=t0 + int(T * 1e9))
            await loop.run(ticks=71)
            s = client.read()
            u = (s.now_ns - t0) / 1e9 / T
            h = np.array([2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2])
            expected = h[0] * qa + h[1] * T * va + h[2] * qb + h[3] * T * vb
            dh = np.array([6 * u**2 - 6 * u, 3 * u**2 - 4 * u + 1, -6 * u**2 + 6 * u, 3 * u**2 - 2 * u])
            expected_v = (dh[0] * qa + dh[2] * qb) / T + dh[1] * va + dh[3] * vb
            np.testing.assert_allclose(s.command_position, expected, atol=1e-12)
            np.testing.assert_allclose(s.command_velocity, expected_v, atol=1e-9)
            await loop.run(ticks=200)  # past the last point: it is held exactly
            np.testing.assert_allclose(client.read().command_position, qb, atol=1e-12)


@pytest.mark.asyncio
async def test_underrun_holds_the_last_point_then_faults_to_hold():
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=0.05))
    async with loop:
        with RobotClient(name, command=True) as client:
            await loop.run(ticks=1)
            client.send([0.02, 0.0, -0.02])
            await loop.run(ticks=40)  # dry for 40 ms < 50 ms: holding, still running
            s = client.read()
            assert s.level == SafetyLevel.RUN and not loop.faults
            np.testing.assert_allclose(s.command_position, [0.02, 0.0, -0.02])
            await loop.run(ticks=20)
            assert loop.level == SafetyLevel.HOLD
            assert [f.source for f in loop.faults] == ["controller:stream"]
            assert "StreamUnderrun" in loop.faults[0].error
            np.testing.assert_allclose(client.read().command_position, [0.02, 0.0, -0.02])
            with pytest.raises(NotStreaming):
                client.send([0.0] * 3)


@pytest.mark.asyncio
async def test_a_point_the_tick_finds_invalid_is_refused_and_counted():
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=1.0))
    async with loop:
        with RobotClient(name, command=True) as client:
            await loop.run(ticks=1)
            with pytest.raises(ValueError, match=r"not finite for.*j1"):
                client.send([0.0, np.nan, 0.0])
            with pytest.raises(ValueError, match=r"out of range for.*j2"):
                client.send([0.0, 0.0, 5.0])
            with pytest.raises(ValueError, match="expected 3 values"):
                client.send([0.0, 0.0])
            with pytest.raises(JointMismatch, match="unknown joint"):
                client.send({"j0": 0.0, "j1": 0.0, "j9": 0.0})
            assert client.pending == 0  # nothing was queued
            # a writer that skips the client's checks: the tick refuses the point
            seg = client._seg
            head = int(seg.producer[shm_segment.P_HEAD])
            seg.slot_position[head % 16][:] = [0.0, np.inf, 0.0]
            seg.slot_words[head % 16][:] = 0
            seg.producer[shm_segment.P_HEAD] = head + 1
            client.send({"j0": 0.01, "j1": 0.02, "j2": 0.03})
            await loop.run(ticks=3)
            assert client.refused == 1 and client.applied == 1
            np.testing.assert_allclose(client.read().position, [0.01, 0.02, 0.03])
        assert loop.level == SafetyLevel.RUN


@contextlib.contextmanager
def interrupted_after(seconds: float):
    """Raise TimeoutError in the main thread after ``seconds``: a tick that never returns is
    interrupted between two bytecodes, so the test fails instead of hanging."""

    def alarm(signum, frame):
        raise TimeoutError(f"still inside after {seconds} s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@pytest.mark.asyncio
@pytest.mark.parametrize("jump", [10**15, -(10**15), 17, -1])
async def test_a_ring_head_out_of_range_holds_the_robot_and_detaches_the_stream(jump):
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=1.0))
    async with loop:
        with RobotClient(name, command=True) as client:
            await loop.run(ticks=1)
            client.send([0.01, 0.0, 0.0])
            await loop.run(ticks=2)
            client._seg.producer[shm_segment.P_HEAD] += jump  # a writer that breaks the protocol
            with interrupted_after(10.0):
                await loop.run(ticks=50)  # returns: the tick is bounded
            assert loop.robot.clock.tick == 53
            assert loop.level == SafetyLevel.HOLD
            assert [f.source for f in loop.faults] == ["controller:stream"]
            assert "StreamCorrupt" in loop.faults[0].error
            np.testing.assert_allclose(client.read().command_position, [0.01, 0.0, 0.0])
            with pytest.raises(NotStreaming):  # detached: nothing more is taken
                client.send([0.02, 0.0, 0.0])
            # re-armed, the controller starts again from the head as it is now
            await ticking(loop, client.reset_faults, 10.0)
            await ticking(loop, client.rearm, 10.0)
            assert loop.level == SafetyLevel.RUN
            client.send([0.03, 0.0, 0.0], final=True)
            await loop.run(ticks=3)
            np.testing.assert_allclose(client.read().command_position, [0.03, 0.0, 0.0])
            assert loop.level == SafetyLevel.RUN


# ---------------------------------------------------------------- safety requests


async def ticking(loop, fn, *args, max_ticks: int = 20_000, timeout_s: float = 60.0):
    """Run the client's blocking call ``fn(*args)`` in a thread while the virtual loop ticks,
    one tick at a time, until the call returns; bounded in ticks and in time. Returns what the
    call returned, or raises what it raised."""
    call = asyncio.ensure_future(asyncio.to_thread(fn, *args))
    deadline = time.monotonic() + timeout_s
    for _ in range(max_ticks):
        if call.done() or time.monotonic() > deadline:
            break
        await loop.run(ticks=1)
        await asyncio.sleep(0)  # lets the thread's result reach the event loop
    if not call.done():  # let the thread end (its own wait is bounded) before failing
        await asyncio.wait_for(call, timeout_s)
    return call.result()


def ticks_until(loop, level: SafetyLevel, max_ticks: int):
    async def go():
        for _ in range(max_ticks):
            if loop.level == level:
                return
            await loop.run(ticks=1)
        assert loop.level == level, f"still {loop.level.name} after {max_ticks} ticks"

    return go()


@pytest.mark.asyncio
@pytest.mark.parametrize("request_name, level", [("hold", SafetyLevel.HOLD), ("estop", SafetyLevel.ESTOP)])
async def test_safety_request_from_a_client(request_name, level):
    """On the real clock: any client may ask for hold or estop; re-arming takes the command lock."""
    name = unique()
    loop = ControlLoop(parse_config(stream_raw(name, dry=10.0, clock="sleep")))
    async with loop:
        run = asyncio.create_task(loop.run(duration=30.0))
        try:
            client = RobotClient(name)
            await asyncio.to_thread(client.wait_tick, 0, 10.0)
            await asyncio.to_thread(getattr(client, request_name), 10.0)
            assert loop.level == level
            tick = client.read().tick
            await asyncio.to_thread(client.wait_tick, tick + 2, 10.0)
            assert client.read().level == level
            with RobotClient(name, command=True) as commander:
                if level == SafetyLevel.ESTOP:
                    with pytest.raises(RequestRefused, match="reset_faults"):
                        await asyncio.to_thread(commander.rearm, 10.0)
                    await asyncio.to_thread(commander.reset_faults, 10.0)
                    assert client.read().level == SafetyLevel.DISABLED
                await asyncio.to_thread(commander.rearm, 10.0)
                assert client.read().level == SafetyLevel.RUN
            client.close()
        finally:
            loop.request_stop()
            await run
    assert loop.faults == []


@pytest.mark.asyncio
async def test_client_resets_faults_and_rearms_after_an_underrun():
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=0.05))
    async with loop:
        with RobotClient(name, joints=JOINTS, command=True) as client:
            await loop.run(ticks=1)
            client.send([0.02, 0.0, -0.02])
            await ticks_until(loop, SafetyLevel.HOLD, 200)
            assert "StreamUnderrun" in loop.faults[0].error
            # the loop's own refusal, asked in this process, and the client's: the same reason
            with pytest.raises(SafetyRequestRefused) as direct:
                loop.rearm()
            with pytest.raises(RequestRefused) as refused:
                await ticking(loop, client.rearm, 10.0)
            assert refused.value.request == "rearm" and refused.value.reason == str(direct.value)
            assert "fault(s) since the last reset_faults()" in refused.value.reason
            assert isinstance(refused.value, AiohalError) and isinstance(refused.value, RuntimeError)
            assert not isinstance(refused.value, RequestTimeout)
            assert loop.level == SafetyLevel.HOLD

            await ticking(loop, client.reset_faults, 10.0)
            assert loop.level == SafetyLevel.HOLD  # faults cleared; still holding until re-armed
            await ticking(loop, client.rearm, 10.0)
            assert loop.level == SafetyLevel.RUN and client.read().level == SafetyLevel.RUN
            # the stream runs again from where the robot stands
            client.send([0.03, 0.01, -0.01], final=True)
            await loop.run(ticks=3)
            np.testing.assert_allclose(client.read().command_position, [0.03, 0.01, -0.01])
            await loop.run(ticks=200)
            assert loop.level == SafetyLevel.RUN
        sources = [(t["event"], t["source"]) for t in loop.report()["safety"]]
        assert ("reset_faults", "client") in sources and ("rearm", "client") in sources


@pytest.mark.asyncio
async def test_client_resets_faults_and_rearms_after_an_estop():
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=1.0))
    async with loop:
        with RobotClient(name, command=True) as client:
            await loop.run(ticks=1)
            with pytest.raises(RequestRefused, match=r"reset_faults\(\) from run") as refused:
                await ticking(loop, client.reset_faults, 10.0)  # nothing to reset while running
            assert refused.value.request == "reset_faults"
            await ticking(loop, client.estop, 10.0)
            assert loop.level == SafetyLevel.ESTOP
            with pytest.raises(RequestRefused) as refused:
                await ticking(loop, client.rearm, 10.0)
            assert refused.value.reason == "rearm() from estop: reset_faults() first"
            with pytest.raises(NotStreaming):
                client.send([0.0] * 3)
            await ticking(loop, client.reset_faults, 10.0)
            assert loop.level == SafetyLevel.DISABLED and client.read().level == SafetyLevel.DISABLED
            await ticking(loop, client.rearm, 10.0)
            assert loop.level == SafetyLevel.RUN
            client.send([0.01, 0.02, 0.03], final=True)
            await loop.run(ticks=3)
            np.testing.assert_allclose(client.read().command_position, [0.01, 0.02, 0.03])
        assert loop.level == SafetyLevel.RUN and loop.faults == []


@pytest.mark.asyncio
async def test_a_client_without_command_permission_is_refused():
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=1.0))
    async with loop:
        await loop.run(ticks=1)
        loop.estop()
        await loop.run(ticks=1)
        with RobotClient(name) as reader:
            for call in (reader.reset_faults, reader.rearm, lambda: reader.send([0.0] * 3)):
                with pytest.raises(CommandRequired, match=r"command=True") as refused:
                    call()
                assert isinstance(refused.value, PermissionError)
            # refused before anything was asked of the loop
            assert reader._seg.requests[shm_segment.R_RESET] == 0 and reader._seg.requests[shm_segment.R_REARM] == 0
            await loop.run(ticks=3)
            assert loop.level == SafetyLevel.ESTOP


@pytest.mark.asyncio
async def test_a_request_the_loop_does_not_answer_times_out():
    name = unique()
    loop = virtual_loop(stream_raw(name))
    async with loop:
        await loop.run(ticks=1)
        with RobotClient(name, command=True) as client:
            # the virtual clock does not tick unless the test runs it: nobody answers
            with pytest.raises(RequestTimeout, match="did not act") as timed_out:
                client.reset_faults(wait_s=0.2)
            assert isinstance(timed_out.value, TimeoutError) and not isinstance(timed_out.value, RequestRefused)


@pytest.mark.asyncio
async def test_a_reset_or_rearm_read_after_its_client_gave_up_is_refused():
    """A loop that does not run while a client asks it to reset or re-arm (frozen, stopped)
    must not act on that request when it runs again: its client was told it went unanswered."""
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=1.0))
    async with loop:
        door = loop.doors.shm
        with RobotClient(name, command=True) as client:
            await loop.run(ticks=1)
            await ticking(loop, client.estop, 10.0)
            # the virtual clock does not tick unless the test runs it: the loop is frozen
            with pytest.raises(RequestTimeout):
                client.reset_faults(wait_s=0.2)
            await loop.run(ticks=3)
            assert loop.level == SafetyLevel.ESTOP and door.requests_expired == 1
            await ticking(loop, client.reset_faults, 10.0)  # asked again while the loop runs: done
            assert loop.level == SafetyLevel.DISABLED
            with pytest.raises(RequestTimeout):
                client.rearm(wait_s=0.2)
            await loop.run(ticks=3)
            assert loop.level == SafetyLevel.DISABLED and door.requests_expired == 2
            answer = client._seg.answer_text[shm_segment.A_REARM].tobytes().decode(errors="replace")
            assert "too late to answer its caller" in answer
            await ticking(loop, client.rearm, 10.0)
            assert loop.level == SafetyLevel.RUN
        events = [t["event"] for t in loop.report()["safety"]]
        assert events.count("reset_faults") == 1 and events.count("rearm") == 1, events


# ---------------------------------------------------------------- the end of a stream


@pytest.mark.asyncio
async def test_a_finished_trajectory_holds_its_last_point_and_a_new_one_follows():
    name = unique()
    loop = virtual_loop(stream_raw(name, dry=0.05))
    async with loop:
        with RobotClient(name, command=True) as client:
            await loop.run(ticks=1)
            t0 = client.read().now_ns + 5_000_000
            last = np.array([0.1, -0.05, 0.02])
            positions = np.array([[0.0, 0.0, 0.0], [0.05, -0.02, 0.01], last])
            velocities = np.array([[0.0, 0.0, 0.0], [1.0, -0.5, 0.2], [0.0, 0.0, 0.0]])
            client.send_trajectory([t0, t0 + 20_000_000, t0 + 40_000_000], positions, velocities, final=True)
            await loop.run(ticks=50)  # past the last point (45 ms)
            assert client.finished and client.applied == 3
            await loop.run(ticks=500)  # ten times dry_after_s: no underrun
            s = client.read()
            assert s.level == SafetyLevel.RUN and loop.faults == []
            np.testing.assert_allclose(s.command_position, last, atol=1e-12)
            np.testing.assert_allclose(s.command_velocity, 0.0)
            report = loop.report()
            assert report["faults"] == [] and report["safety_level"] == "run"
            metrics = report["controller"]
            assert metrics["type"] == "stream" and metrics["finished"] is True
            assert metrics["streams_finished"] == 1 and metrics["underruns"] == 0

            # a new stream, without a re-arm: it starts from the held point, not mid-segment
            target = np.array([0.2, -0.05, 0.02])
            client.send(target, t_ns=client.read().now_ns + 100_000_000)
            await loop.run(ticks=2)
            assert not client.finished
            first = client.read().command_position.copy()
            assert 0.1 < first[0] < 0.1 + 0.1 * 0.05  # a few ticks into a 100 ms segment
            # this stream has no final point: it runs dry, a fault as before
            await ticks_until(loop, SafetyLevel.HOLD, 400)
            assert [f.source for f in loop.faults] == ["controller:stream"]
            assert "StreamUnderrun" in loop.faults[0].error
            np.testing.assert_allclose(client.read().command_position, target, atol=1e-12)
            assert loop.report()["controller"]["type"] == "hold"


# ---------------------------------------------------------------- errors


def test_not_running_is_a_clear_error():
    with pytest.raises(RobotNotRunning, match=r"no shared memory /aiohal.nobody_here"):
        RobotClient("nobody_here")
    with pytest.raises(shm_segment.ShmError, match="cannot name a shared-memory segment"):
        RobotClient("a/b")


def test_stream_without_the_door_is_a_config_error():
    raw = arm_raw(3, type="stream")
    with pytest.raises(ConfigError, match=r"controller.type: the stream controller .* \[client\] shm = true"):
        parse_config(raw)


@pytest.mark.asyncio
async def test_joint_mismatch_command_lock_and_closed_robot():
    name = unique()
    loop = virtual_loop(stream_raw(name))
    async with loop:
        with pytest.raises(JointMismatch, match=r"not named by the client: \['j2'\]"):
            RobotClient(name, joints=["j0", "j1"])
        with pytest.raises(JointMismatch, match="another order"):
            RobotClient(name, joints=["j1", "j0", "j2"])
        first = RobotClient(name, command=True)
        with pytest.raises(CommandBusy):
            RobotClient(name, command=True)
        reader = RobotClient(name)  # reading needs no lock
        with pytest.raises(shm_segment.ShmError, match="command=True"):
            reader.send([0.0] * 3)
        first.close()
        RobotClient(name, command=True).close()  # released with the first client
    with pytest.raises(RobotNotRunning, match="has stopped"):
        reader.read()
    reader.close()
    with pytest.raises(RobotNotRunning):
        RobotClient(name)


_KILLED_OWNER = """
import sys, os, signal
from multiprocessing import resource_tracker
from aiohal.outside.shm_segment import create_segment
seg = create_segment(sys.argv[1], {"joints": []}, dof=1, n_imu=0, n_ft=0, capacity=2, period_ns=1, can_rearm=False)
seg.header[1 + 2] = 1  # STATUS_ACTIVE
resource_tracker.unregister(seg.shm._name, "shared_memory")  # as after a kill of the whole group
print("made", flush=True)
os.kill(os.getpid(), signal.SIGKILL)
"""


@pytest.mark.asyncio
async def test_a_segment_left_by_a_killed_process_is_replaced():
    name = unique("stale")
    proc = subprocess.run([sys.executable, "-c", _KILLED_OWNER, name], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.stdout.strip() == "made" and proc.returncode == -signal.SIGKILL
    assert os.path.exists(f"/dev/shm/aiohal.{name}")
    with pytest.raises(RobotNotRunning, match="which is gone"):
        RobotClient(name)
    loop = virtual_loop(stream_raw(name))
    async with loop:  # replaces it
        with RobotClient(name, joints=JOINTS) as client:
            await loop.run(ticks=3)
            assert client.read().tick == 3
    assert not os.path.exists(f"/dev/shm/aiohal.{name}")


@pytest.mark.parametrize("squatter", ["symlink", "foreign-file"])
def test_what_is_not_an_aiohal_segment_at_its_name_is_refused_and_left_alone(tmp_path, squatter):
    """A link at /dev/shm/aiohal.<robot> (shm_open would fail with ELOOP) or another program's
    file there: the loop refuses to configure, names the path, and deletes nothing."""
    name = unique(squatter.replace("-", "_"))
    path = Path(f"/dev/shm/aiohal.{name}")
    target = tmp_path / "precious"
    target.write_bytes(b"not aiohal's" * 100)
    if squatter == "symlink":
        path.symlink_to(target)
    else:
        path.write_bytes(target.read_bytes())
    try:
        loop = virtual_loop(stream_raw(name))
        with pytest.raises(shm_segment.ShmError, match=rf"/dev/shm/aiohal\.{name} exists and is not"):
            loop.configure()
        assert path.is_symlink() if squatter == "symlink" else path.read_bytes() == target.read_bytes()
        assert target.read_bytes() == b"not aiohal's" * 100
    finally:
        path.unlink()


@pytest.mark.asyncio
async def test_a_second_live_loop_with_the_same_name_is_refused():
    name = unique()
    async with virtual_loop(stream_raw(name)):
        with pytest.raises(shm_segment.SegmentBusy, match=f"already served by process {os.getpid()}"):
            virtual_loop(stream_raw(name)).configure()
        code = ("import sys; from aiohal.outside.shm_segment import create_segment; create_segment(sys.argv[1], {}, dof=1, n_imu=0, "
                "n_ft=0, capacity=2, period_ns=1, can_rearm=False)")
        proc = subprocess.run([sys.executable, "-c", code, name], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert proc.returncode == 1 and f"SegmentBusy: robot '{name}' is already served by process" in proc.stderr


# ---------------------------------------------------------------- a planner in another process


@pytest.mark.asyncio
async def test_planner_example_streams_from_another_process():
    name = unique("planner")
    raw = stream_raw(name, dry=0.5, clock="auto")
    loop = ControlLoop(parse_config(raw))  # the real clock: the planner runs in wall time
    async with loop:
        run = asyncio.create_task(loop.run(duration=20.0))
        try:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, str(ROOT / "examples" / "shm_planner.py"), name, "--duration", "1.0",
                "--amplitude", "0.1", cwd=ROOT, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
            out, err = await asyncio.wait_for(proc.communicate(), 30)
            assert proc.returncode == 0, err.decode()
            assert loop.level == SafetyLevel.HOLD
        finally:
            loop.request_stop()
            await run
    summary = json.loads(out)
    assert summary["points_sent"] == 101 and summary["points_applied"] == 101 and summary["points_refused"] == 0
    assert summary["level"] == "hold" and loop.faults == []
    # the last point of sin(2π·0.5·t) at t = 1 s is back at the start pose
    np.testing.assert_allclose(summary["final_command"], [0.0, 0.0, 0.0], atol=1e-6)
