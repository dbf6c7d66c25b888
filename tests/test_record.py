"""Recording: exact read-back in lockstep, a SIGKILLed file, a writer that falls behind, the
live server seen by a WebSocket client, the replay summary."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")

from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from aiohal import ControlLoop, load_config
from aiohal.core.ticker import VirtualTickSource
from aiohal.outside.recorder import Recorder
from aiohal.record import RecordSection, load

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "configs" / "mock_humanoid.toml"


class Snapshots:
    """A publisher keeping a copy of what the loop had on every tick (the test's reference)."""

    def __init__(self) -> None:
        self.rows: list[dict] = []

    def __call__(self, control: ControlLoop) -> None:
        robot = control.robot
        self.rows.append({"tick": robot.clock.tick, "state": robot.state.block.copy(),
                          "command": robot.command.block.copy(), "mode": robot.command.mode.copy(),
                          "imu": robot.imu.values.copy(), "ft": robot.force_torque.values.copy(),
                          "grasp": robot.hand.grasp.copy(), "level": int(control.level)})


def run_recorded(tmp_path: Path, ticks: int, options: RecordSection, recorder_cls=Recorder):
    async def main():
        control = ControlLoop(load_config(HUMANOID), tick_source=VirtualTickSource())
        await control.activate()
        snapshots = Snapshots()
        control.add_publisher(snapshots)
        recorder = recorder_cls(control.port, tmp_path / "run.mcap", options)
        recorder.attach()
        report = await control.run(ticks=ticks)
        await control.deactivate()
        return control, snapshots, recorder, recorder.close(), report

    return asyncio.run(main())


def test_lockstep_recording_reads_back_exactly(tmp_path):
    control, snaps, _, summary, _ = run_recorded(tmp_path, 1500, RecordSection(buffer_ticks=4096))
    assert summary["dropped_ticks"] == 0 and summary["ticks"] == 1500
    n = control.robot.dof
    # the mcap library's own reader, and the CDR layout decoded by hand: tick (int64) after the
    # 4-byte header, then a uint32 length and the float64 positions at body offset 16
    positions, ticks = [], []
    with open(tmp_path / "run.mcap", "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(topics=["/joint_state"]):
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            data = message.data
            assert data[:4] == b"\x00\x01\x00\x00"
            ticks.append(struct.unpack_from("<q", data, 4)[0])
            assert struct.unpack_from("<I", data, 12)[0] == n
            positions.append(np.frombuffer(data, dtype="<f8", count=n, offset=20))
    assert ticks == [s["tick"] for s in snaps.rows]
    assert np.array_equal(np.array(positions), np.array([s["state"][0] for s in snaps.rows]))

    rec = load(tmp_path / "run.mcap")
    assert not rec.truncated
    state, command = rec["/joint_state"], rec["/joint_command"]
    for r, name in enumerate(("position", "velocity", "effort", "motor_position", "motor_velocity")):
        assert np.array_equal(state[name], np.array([s["state"][r] for s in snaps.rows]))
    for r, name in enumerate(("position", "velocity", "effort", "stiffness", "damping", "feedforward")):
        assert np.array_equal(command[name], np.array([s["command"][r] for s in snaps.rows]))
    assert np.array_equal(command.mode, np.array([s["mode"] for s in snaps.rows]))
    imu = rec["/imu/pelvis_imu"]
    assert np.array_equal(np.hstack([imu.quaternion, imu.angular_velocity, imu.linear_acceleration]),
                          np.array([s["imu"][0] for s in snaps.rows]))
    ft = rec["/force_torque/l_ankle_ft"]
    i = control.robot.force_torque.names.index("l_ankle_ft")
    assert np.array_equal(np.hstack([ft.force, ft.torque]), np.array([s["ft"][i] for s in snaps.rows]))
    assert np.array_equal(rec["/hand/l_gripper"].grasp, np.array([s["grasp"][0] for s in snaps.rows]))
    assert np.array_equal(rec["/safety"].level, [s["level"] for s in snaps.rows])
    # every tick's timing, the same figures as the loop's statistics
    timing = rec["/timing"]
    assert np.array_equal(timing.tick, ticks)
    assert np.array_equal(timing.work_ns, control.stats.work[:1500])
    assert np.array_equal(timing.publish_ns, control.stats.phases[5, :1500])
    assert rec.joint_names == list(control.robot.joint_names)


def test_decimation_per_channel(tmp_path):
    _, snaps, _, _, _ = run_recorded(tmp_path, 400, RecordSection(decimate={"imu": 10, "joint_command": 4}))
    rec = load(tmp_path / "run.mcap")
    assert len(rec["/joint_state"]) == 400
    assert list(rec["/imu/pelvis_imu"].tick) == [s["tick"] for s in snaps.rows if s["tick"] % 10 == 0]
    assert list(rec["/joint_command"].tick) == [s["tick"] for s in snaps.rows if s["tick"] % 4 == 0]


class StuckWriter(Recorder):
    """A writer that does nothing until released: the ring fills up."""

    release = threading.Event()

    def _write_loop(self) -> None:
        self.release.wait(60)
        super()._write_loop()


def test_writer_behind_drops_and_counts_and_never_holds_the_tick(tmp_path):
    StuckWriter.release.clear()
    try:
        # the run can only end while the writer is stuck if the tick never waits for it

        async def main():
            control = ControlLoop(load_config(HUMANOID), tick_source=VirtualTickSource())
            await control.activate()
            recorder = StuckWriter(control.port, tmp_path / "run.mcap", RecordSection(buffer_ticks=64))
            recorder.attach()
            report = await asyncio.wait_for(control.run(ticks=500), 60)
            assert recorder.ring.dropped == 500 - 64 and recorder.ticks_written == 0
            StuckWriter.release.set()
            await control.deactivate()
            return report, recorder.close()

        report, summary = asyncio.run(main())
    finally:
        StuckWriter.release.set()
    assert report["ticks"] == 500
    assert summary["dropped_ticks"] == 436 and summary["ticks"] == 64
    rec = load(tmp_path / "run.mcap")
    assert list(rec["/joint_state"].tick) == list(range(1, 65))  # the first 64, the rest counted


def test_sigkilled_recording_holds_its_flushed_ticks(tmp_path):
    out = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "aiohal", str(ROOT / "configs" / "mock_arm.toml"),
                             "--record", str(out), "--quiet", "--log-format", "json"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not (out.exists() and out.stat().st_size > 0) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read()
            time.sleep(0.05)
        time.sleep(5.0)  # the scenario: killed 5 s into the run
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    ticks = []
    with open(out, "rb") as f:  # the mcap library reads it, up to where the file ends
        try:
            for record in StreamReader(f).records:
                if type(record).__name__ == "Message":
                    ticks.append(record.sequence)
        except Exception as exc:
            assert type(exc).__module__.startswith("mcap"), exc
    rec = load(out)
    assert rec.truncated
    state = rec["/joint_state"]
    assert state.tick[-1] - state.tick[0] >= 4000  # at least 4 s of ticks at 1 kHz
    assert np.all(np.diff(state.tick) > 0)


def test_live_server_seen_by_a_websocket_client(tmp_path):
    websockets = pytest.importorskip("websockets")
    pytest.importorskip("foxglove")
    from aiohal.outside.foxglove_server import FoxgloveServer

    async def main():
        live = FoxgloveServer(port=0)
        control = ControlLoop(load_config(HUMANOID))  # the real clock: a client connects meanwhile
        await control.activate()
        recorder = Recorder(control.port, None, RecordSection(live_decimate=10), live=live)
        recorder.attach()
        run = asyncio.get_running_loop().create_task(control.run(duration=5.0))
        got = {}
        try:
            async with websockets.connect(f"ws://127.0.0.1:{live.port}", subprotocols=["foxglove.sdk.v1"]) as ws:
                channels = {}
                while "/joint_state" not in channels:
                    msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
                    if msg["op"] == "advertise":
                        channels.update({c["topic"]: c for c in msg["channels"]})
                state = channels["/joint_state"]
                assert state["encoding"] == "cdr" and state["schemaEncoding"] == "ros2msg"
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": state["id"]}]}))
                while "data" not in got:
                    frame = await asyncio.wait_for(ws.recv(), 5)
                    if isinstance(frame, bytes) and frame[0] == 0x01:  # message data
                        sub_id, = struct.unpack_from("<I", frame, 1)
                        got["data"] = frame[13:]
                        got["sub"] = sub_id
        finally:
            control.request_stop()
            await run
            await control.deactivate()
            summary = recorder.close()
            live.close()
        return control, got, summary

    control, got, summary = asyncio.run(main())
    assert got["sub"] == 7
    tick = struct.unpack_from("<q", got["data"], 4)[0]
    assert tick % 10 == 0 and 0 < tick <= control.robot.clock.tick
    assert struct.unpack_from("<I", got["data"], 12)[0] == control.robot.dof
    assert summary["live_messages"] > 0


def test_cli_record_and_replay(tmp_path):
    out = tmp_path / "r.mcap"
    proc = subprocess.run([sys.executable, "-m", "aiohal", "configs/mock_arm.toml", "--clock", "virtual",
                           "--duration", "0.5", "--record", str(out), "--log-format", "json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "record       " in proc.stdout and " 0 dropped" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "aiohal", "replay", str(out), "--json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["robot"] == "mock_arm" and summary["ticks"] == 500 and summary["missing_ticks"] == 0
    assert summary["channels"]["/joint_state"] == 500


def test_cli_record_into_a_missing_folder_exits_2(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "aiohal", "configs/mock_arm.toml", "--duration", "0.1",
                           "--record", str(tmp_path / "nowhere" / "r.mcap")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "does not exist" in proc.stderr


def test_importing_the_loop_does_not_import_mcap():
    code = "import sys, aiohal.core.loop, aiohal.cli; print(sorted(m for m in sys.modules if m.split('.')[0] in ('mcap', 'matplotlib', 'rich', 'foxglove')))"
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.stdout.strip() == "[]", proc.stderr


def test_plot_writes_its_pngs(tmp_path):
    pytest.importorskip("matplotlib")
    run_recorded(tmp_path, 300, RecordSection())
    proc = subprocess.run([sys.executable, "-m", "aiohal", "plot", str(tmp_path / "run.mcap"), "-o",
                           str(tmp_path / "fig"), "--joints", "l_*"], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    for name in ("joints.png", "timing.png", "safety.png"):
        data = (tmp_path / "fig" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_plot_refuses_outputs_it_would_destroy_before_drawing(tmp_path):
    """A symlink where a figure goes is refused (its target is left as it was), and so is an
    output "folder" that is a file or a device."""
    pytest.importorskip("matplotlib")
    run_recorded(tmp_path, 100, RecordSection())
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    (tmp_path / "fig").mkdir()
    (tmp_path / "fig" / "timing.png").symlink_to(target)
    plain_file = tmp_path / "a_file"
    plain_file.write_text("not a folder")
    for out, message in ((tmp_path / "fig", "symbolic link"), (plain_file, "not a folder"),
                         (Path("/dev/null"), "not a folder")):
        proc = subprocess.run([sys.executable, "-m", "aiohal", "plot", str(tmp_path / "run.mcap"), "-o", str(out)],
                              cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and message in proc.stderr, (out, proc.stderr)
        assert "Traceback" not in proc.stderr
    assert target.read_text() == "keep me" and plain_file.read_text() == "not a folder"
    assert not (tmp_path / "fig" / "joints.png").exists()  # refused before any figure was drawn


def test_record_never_replaces_a_file_the_config_names(tmp_path):
    """``--record`` on the config's own MJCF model (or the config itself) exits 2 before the
    robot starts, and the file is unchanged."""
    import shutil

    shutil.copytree(ROOT / "configs", tmp_path / "configs")
    config = tmp_path / "configs" / "walkman_sim.toml"
    model = tmp_path / "configs" / "models" / "walkman.xml"
    before = model.read_bytes()
    for victim in (model, config):
        proc = subprocess.run([sys.executable, "-m", "aiohal", str(config), "--duration", "0.1", "--record",
                               str(victim)], cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert "the config or a file it names" in proc.stderr
    assert model.read_bytes() == before


def test_a_live_view_port_in_use_exits_2_before_the_robot_starts(tmp_path):
    pytest.importorskip("foxglove")
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = subprocess.run([sys.executable, "-m", "aiohal", "configs/mock_arm.toml", "--clock", "virtual",
                               "--duration", "0.1", "--foxglove", str(port)],
                              cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert f"--foxglove {port}: the live view cannot listen" in proc.stderr and "Traceback" not in proc.stderr
    assert "starting robot" in proc.stderr and "running" not in proc.stderr  # built, never activated
