"""Outputs in processes of their own: the loop's process keeps one thread while recording and
serving live, the output processes die with the loop, and the tick ring is read by a client."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")

from aiohal import ControlLoop, load_config
from aiohal.core.ticker import VirtualTickSource
from aiohal.outside.options import BridgeSection, ZenohBridgeSection
from aiohal.outside.recorder import Recorder
from aiohal.outside.tick_ring import TickReader
from aiohal.record import RecordSection, load

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "configs" / "mock_humanoid.toml"


def tasks() -> int:
    return len(os.listdir("/proc/self/task"))


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append(int(entry))
    return out


def alive(pid: int) -> bool:
    """Running (a zombie has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_recording_serving_live_and_bridging_start_no_thread_in_the_loops_process(tmp_path):
    """Threads of the loop's process while it records, serves Foxglove and bridges to Zenoh
    (/proc/self/task)."""
    pytest.importorskip("foxglove")
    seen: list[tuple[int, int]] = []

    pytest.importorskip("zenoh")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        zport = s.getsockname()[1]
    config = load_config(HUMANOID)
    config = dataclasses.replace(config, bridge=BridgeSection(
        zenoh=ZenohBridgeSection(listen=[f"tcp/127.0.0.1:{zport}"], connect=[])))

    # threads an earlier test of this worker left behind are not the loop's
    earlier = {t.name for t in threading.enumerate()} - {"MainThread"}

    async def main():
        control = ControlLoop(config, tick_source=VirtualTickSource())
        before = tasks()
        await control.activate()  # the Zenoh bridge starts
        bridge = control.doors.zenoh
        assert bridge is not None and control.faults == []
        recorder = Recorder(control.port, tmp_path / "run.mcap", RecordSection(), live_port=0)
        recorder.attach()
        control.add_publisher(
            lambda c: seen.append((tasks(), sorted(t.name for t in threading.enumerate())))
            if c.robot.clock.tick % 100 == 0
            else None
        )
        await control.run(ticks=400)
        await control.deactivate()
        return before, recorder.close(), bridge

    before, summary, bridge = asyncio.run(main())
    assert bridge.counters["state_sent"] >= 3  # joint_states at 100 Hz of 400 ticks
    assert summary["ticks"] == 401 and summary["dropped_ticks"] == 0
    # besides the tick's thread, only the loop's own stall watchdog (which runs without outputs
    # too) runs Python; no native thread comes and goes with the ticks (a library's native pool,
    # started once at import or first call, depends on the Python and the worker: not counted)
    ours = [sorted(set(s[1]) - earlier) for s in seen]
    assert len(seen) == 4 and all(o in (["MainThread", "aiohal-watchdog"], ["MainThread"]) for o in ours), (before, seen)
    assert any("aiohal-watchdog" in s[1] for s in seen)
    assert len({s[0] for s in seen}) == 1, (before, seen)


def test_output_processes_end_when_the_loop_is_killed(tmp_path):
    out = tmp_path / "run.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "aiohal", str(ROOT / "configs" / "mock_arm.toml"),
                             "--record", str(out), "--foxglove", "0", "--quiet"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 90
        kids: list[int] = []
        while len(kids) < 2 or not out.exists() or out.stat().st_size == 0:  # the recorder and the live view
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline, "the outputs did not start"
            time.sleep(0.1)
            kids = children(proc.pid)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        deadline = time.monotonic() + 30
        while any(alive(k) for k in kids):
            assert time.monotonic() < deadline, f"output processes {kids} outlived the loop"
            time.sleep(0.1)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    rec = load(out)  # what the writer had when the loop went is readable
    assert len(rec["/joint_states"]) > 0


def test_a_client_reads_every_tick_from_the_same_ring():
    rows: list[np.ndarray] = []

    async def main():
        control = ControlLoop(load_config(HUMANOID), tick_source=VirtualTickSource())
        await control.activate()
        recorder = Recorder(control.port, None, RecordSection(buffer_ticks=1024))
        recorder.attach()
        reader = TickReader(control.robot.name, pid=os.getpid())  # (tests in parallel run the same robot)
        snapshots = []
        control.add_publisher(lambda c: snapshots.append(c.robot.state.position.copy()))
        await control.run(ticks=300)
        for _ in range(100):
            got = reader.read(64)
            if not len(got):
                break
            rows.append(reader.field(got, reader.names.index("state"))[:, 0])
        lost = reader.lost
        reader.close()
        await control.deactivate()
        recorder.close()
        return snapshots, lost

    snapshots, lost = asyncio.run(main())
    positions = np.concatenate(rows)
    assert lost == 0 and len(positions) == 300
    assert np.array_equal(positions, np.array(snapshots))


def test_a_robot_client_reads_the_tick_ring_of_its_robot():
    """``RobotClient.ticks()``: the same ring, found through the robot's shared-memory door."""
    import uuid

    from helpers import arm_raw

    from aiohal.client import RobotClient
    from aiohal.config import parse_config

    raw = arm_raw(3)
    raw["robot"]["name"] = f"ring_{uuid.uuid4().hex[:6]}"
    raw["client"] = {"shm": True}

    async def main():
        control = ControlLoop(parse_config(raw), tick_source=VirtualTickSource())
        await control.activate()
        recorder = Recorder(control.port, None, RecordSection(buffer_ticks=256))
        recorder.attach()
        client = RobotClient(raw["robot"]["name"])
        reader = client.ticks()
        await control.run(ticks=50)
        meta = reader.meta(reader.read(256))
        reader.close()
        client.close()
        await control.deactivate()
        recorder.close()
        return meta

    meta = asyncio.run(main())
    assert list(meta[:, 1]) == list(range(1, 51))  # every tick of the run, from where it attached
