"""Recording: exact read-back in lockstep (in ROS 2 messages, decoded by mcap-ros2-support),
a rosbag2 directory that rosbags reads, a SIGKILLed file, a writer that falls behind, the live
server seen by a WebSocket client (with the latched /robot), the summary."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2")

from conftest import NOT_HUNG_S
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_ros2._dynamic import generate_dynamic
from mcap_ros2.decoder import DecoderFactory

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
        snapshots(control)  # tick 0: what activation read, recorded by attach()
        control.add_publisher(snapshots)
        recorder = recorder_cls(control.port, tmp_path / "run.mcap", options)
        recorder.attach()
        report = await control.run(ticks=ticks)
        await control.deactivate()
        return control, snapshots, recorder, recorder.close(), report

    return asyncio.run(main())


def test_lockstep_recording_reads_back_exactly(tmp_path):
    control, snaps, _, summary, _ = run_recorded(tmp_path, 1500, RecordSection(buffer_ticks=4096))
    assert summary["dropped_ticks"] == 0 and summary["ticks"] == 1501  # ticks 0..1500
    names = list(control.robot.joint_names)
    # a decoder that is not the encoder: mcap's reader with mcap-ros2-support
    positions, ticks = [], []
    with open(tmp_path / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, msg in reader.iter_decoded_messages(topics=["/joint_states"]):
            assert schema.name == "sensor_msgs/msg/JointState" and schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr" and message.data[:4] == b"\x00\x01\x00\x00"
            assert msg.name == names
            ticks.append(message.sequence)
            positions.append(msg.position)
    assert ticks == [s["tick"] for s in snaps.rows]
    assert np.array_equal(np.array(positions), np.array([s["state"][0] for s in snaps.rows]))

    rec = load(tmp_path / "run.mcap")
    assert not rec.truncated
    state, extra = rec["/joint_states"], rec["/joint_states/extra"]
    command, command_extra = rec["/joint_commands"], rec["/joint_commands/extra"]
    for r, (series, name) in enumerate(((state, "position"), (state, "velocity"), (state, "effort"),
                                        (extra, "motor_position"), (extra, "motor_velocity"))):
        assert np.array_equal(series[name], np.array([s["state"][r] for s in snaps.rows]))
    for r, (series, name) in enumerate(((command, "position"), (command, "velocity"), (command, "effort"),
                                        (command_extra, "stiffness"), (command_extra, "damping"),
                                        (command_extra, "feedforward"))):
        assert np.array_equal(series[name], np.array([s["command"][r] for s in snaps.rows]))
    assert np.array_equal(command_extra.mode, np.array([s["mode"] for s in snaps.rows]))
    assert np.array_equal(extra.tick, ticks)
    imu = rec["/imu/pelvis_imu"]
    columns = [f"orientation.{c}" for c in "wxyz"] + [f"angular_velocity.{c}" for c in "xyz"] + [
        f"linear_acceleration.{c}" for c in "xyz"]
    assert np.array_equal(np.column_stack([imu[c] for c in columns]), np.array([s["imu"][0] for s in snaps.rows]))
    ft = rec["/force_torque/l_ankle_ft"]
    i = control.robot.force_torque.names.index("l_ankle_ft")
    columns = [f"wrench.{k}.{c}" for k in ("force", "torque") for c in "xyz"]
    assert np.array_equal(np.column_stack([ft[c] for c in columns]), np.array([s["ft"][i] for s in snaps.rows]))
    assert np.array_equal(rec["/hand/l_gripper"].grasp, np.array([s["grasp"][0] for s in snaps.rows]))
    assert np.array_equal(rec["/safety"].level, [s["level"] for s in snaps.rows])
    assert [e.event for e in rec["/safety/events"].messages] == ["activate", "deactivate"]
    # every tick's timing, the same figures as the loop's statistics
    timing = rec["/timing"]
    assert np.array_equal(timing.tick, ticks[1:])  # tick 0 ran no tick: no timing
    assert np.array_equal(timing.work_ns, control.stats.work[:1500])
    assert np.array_equal(timing.publish_ns, control.stats.phases[5, :1500])
    assert rec.joint_names == names
    robot = rec["/robot"].messages[0]
    assert robot.name == "mock_humanoid" and list(robot.joint_names) == names
    assert robot.position_max.tolist() == [j.position_max for j in control.robot.joints]
    assert "[robot]" in robot.description  # the config's text


def test_decimation_per_channel(tmp_path):
    _, snaps, _, _, _ = run_recorded(tmp_path, 400, RecordSection(decimate={"imu": 10, "joint_command": 4}))
    rec = load(tmp_path / "run.mcap")
    assert len(rec["/joint_states"]) == 401  # ticks 0..400
    assert list(rec["/imu/pelvis_imu"].tick) == [s["tick"] for s in snaps.rows if s["tick"] % 10 == 0]
    assert list(rec["/joint_commands"].tick) == [s["tick"] for s in snaps.rows if s["tick"] % 4 == 0]
    assert list(rec["/joint_commands/extra"].tick) == [s["tick"] for s in snaps.rows if s["tick"] % 4 == 0]


def test_a_stopped_writer_loses_its_oldest_ticks_counted_and_never_holds_the_tick(tmp_path):
    """The writer's process is SIGSTOPped for the whole run: the run ends (the tick never waits
    for it), and once it goes on it writes the ring's last ticks and counts the rest."""

    async def main():
        control = ControlLoop(load_config(HUMANOID), tick_source=VirtualTickSource())
        await control.activate()
        recorder = Recorder(control.port, tmp_path / "run.mcap", RecordSection(buffer_ticks=64))
        recorder.attach()
        os.kill(recorder.pid, signal.SIGSTOP)
        try:
            report = await asyncio.wait_for(control.run(ticks=500), 60)
        finally:
            os.kill(recorder.pid, signal.SIGCONT)
        await control.deactivate()
        return report, recorder.close()

    report, summary = asyncio.run(main())
    assert report["ticks"] == 500 and report["missed_ticks"] == 0
    assert summary["ticks"] + summary["dropped_ticks"] == 501  # ticks 0..500, each written or counted
    assert summary["dropped_ticks"] >= 501 - 64
    rec = load(tmp_path / "run.mcap")
    ticks = list(rec["/joint_states"].tick)
    # what it read before it stopped (tick 0, perhaps), then the newest the ring still held
    assert len(ticks) == summary["ticks"] and ticks[-40:] == list(range(461, 501)) and np.all(np.diff(ticks) > 0)


def test_a_killed_writer_costs_no_tick_and_its_loss_is_in_the_summary(tmp_path):
    async def main():
        control = ControlLoop(load_config(HUMANOID), tick_source=VirtualTickSource())
        await control.activate()
        recorder = Recorder(control.port, tmp_path / "run.mcap", RecordSection(buffer_ticks=64))
        recorder.attach()
        os.kill(recorder.pid, signal.SIGKILL)
        report = await asyncio.wait_for(control.run(ticks=300), 60)
        await control.deactivate()
        return report, recorder.close()

    report, summary = asyncio.run(main())
    assert report["ticks"] == 300, report
    assert not [f for f in report["faults"] if "record" in f["source"]], report["faults"]  # not the loop's fault
    assert summary["ticks"] + summary["dropped_ticks"] == 301, summary
    assert "SIGKILL" in summary["error"], summary


def flushed_ticks(path: Path) -> int:
    """The messages of the busiest channel (one a tick) the mcap library reads from ``path`` up
    to where the file ends now (a file being written, or cut by a kill)."""
    per_channel: dict[int, int] = {}
    if not path.exists():
        return 0
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f).records:
                if type(record).__name__ == "Message":
                    per_channel[record.channel_id] = per_channel.get(record.channel_id, 0) + 1
        except Exception as exc:
            assert type(exc).__module__.startswith("mcap"), exc
    return max(per_channel.values(), default=0)


def test_sigkilled_recording_holds_its_flushed_ticks(tmp_path):
    out = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "aiohal", str(ROOT / "configs" / "mock_arm.toml"),
                             "--record", str(out), "--quiet", "--log-format", "json"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        # the scenario: killed once the file holds 4 s of ticks (5 s into the run on a quiet host;
        # beside two CPU hogs the niced writer had flushed 88 ticks by then)
        deadline = time.monotonic() + 4 * NOT_HUNG_S
        while flushed_ticks(out) < 4 * 1000 + 100 and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read()
            time.sleep(0.5)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    assert flushed_ticks(out) >= 4000  # the mcap library reads it, up to where the file ends
    rec = load(out)
    assert rec.truncated
    state = rec["/joint_states"]
    assert state.tick[-1] - state.tick[0] >= 4000  # at least 4 s of ticks at 1 kHz
    assert np.all(np.diff(state.tick) > 0)


def test_live_server_seen_by_a_websocket_client(tmp_path):
    websockets = pytest.importorskip("websockets")
    pytest.importorskip("foxglove")

    async def subscribe(ws, topics: list[str]) -> dict[str, tuple[dict, bytes]]:
        """Subscribe to ``topics``; the first message of each (its channel and its CDR)."""
        channels: dict[str, dict] = {}
        while not all(t in channels for t in topics):
            msg = json.loads(await asyncio.wait_for(ws.recv(), NOT_HUNG_S))
            if msg["op"] == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
        subs = {i: channels[t] for i, t in enumerate(topics, start=7)}
        await ws.send(json.dumps({"op": "subscribe",
                                  "subscriptions": [{"id": i, "channelId": c["id"]} for i, c in subs.items()]}))
        got: dict[str, tuple[dict, bytes]] = {}
        for _ in range(10_000):
            if len(got) == len(topics):
                break
            frame = await asyncio.wait_for(ws.recv(), NOT_HUNG_S)  # the server's process is niced
            if isinstance(frame, bytes) and frame[0] == 0x01:  # message data
                sub_id, = struct.unpack_from("<I", frame, 1)
                channel = subs[sub_id]
                got.setdefault(channel["topic"], (channel, frame[13:]))
        return got

    async def main():
        control = ControlLoop(load_config(HUMANOID))  # the real clock: clients connect meanwhile
        await control.activate()
        recorder = Recorder(control.port, None, RecordSection(live_decimate=10), live_port=0)
        recorder.attach()  # /robot is sent now, before any client connects
        port = recorder.live_port
        # until both clients are served (stopped then): beside two CPU hogs the niced server
        # process took more than the 5 s this run once had
        run = asyncio.get_running_loop().create_task(control.run(duration=4 * NOT_HUNG_S))
        got = []
        try:
            for _ in range(2):  # each client joins late, and each gets /robot
                async with websockets.connect(f"ws://127.0.0.1:{port}",
                                              subprotocols=["foxglove.sdk.v1"]) as ws:
                    got.append(await subscribe(ws, ["/joint_states", "/robot"]))
        finally:
            control.request_stop()
            await run
            await control.deactivate()
            summary = recorder.close()
        return control, got, summary

    control, got, summary = asyncio.run(main())
    names = list(control.robot.joint_names)
    for client in got:
        for topic, msgtype in (("/joint_states", "sensor_msgs/msg/JointState"), ("/robot", "aiohal_msgs/msg/Robot")):
            channel, data = client[topic]
            assert channel["encoding"] == "cdr" and channel["schemaEncoding"] == "ros2msg"
            assert channel["schemaName"] == msgtype
            decoded = generate_dynamic(msgtype, channel["schema"])[msgtype](data)
            assert list(decoded.name if topic == "/joint_states" else decoded.joint_names) == names
    assert summary["live_messages"] > 0


def test_cli_record_and_info(tmp_path):
    out = tmp_path / "r.mcap"
    proc = subprocess.run([sys.executable, "-m", "aiohal", "configs/mock_arm.toml", "--clock", "virtual",
                           "--duration", "0.5", "--record", str(out), "--log-format", "json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "record       " in proc.stdout and " 0 dropped" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "aiohal", "info", str(out), "--json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["robot"] == "mock_arm" and summary["ticks"] == 501 and summary["missing_ticks"] == 0
    assert summary["channels"]["/joint_states"] == 501  # ticks 0 (activation) to 500


def test_cli_record_into_a_missing_folder_exits_2(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "aiohal", "configs/mock_arm.toml", "--duration", "0.1",
                           "--record", str(tmp_path / "nowhere" / "r.mcap")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "does not exist" in proc.stderr


def test_importing_the_loop_does_not_import_mcap():
    code = "import sys, aiohal.core.loop, aiohal.cli; print(sorted(m for m in sys.modules if m.split('.')[0] in ('mcap', 'matplotlib', 'rich', 'foxglove', 'rosbags')))"
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


def test_a_recording_whose_messages_do_not_decode_is_refused_by_name(tmp_path):
    """info, replay and plot on an MCAP whose JointState messages are garbage: exit 2 naming the
    topic and the type, no traceback."""
    from mcap.writer import Writer

    bad = tmp_path / "bad.mcap"
    with open(bad, "wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2")
        schema = writer.register_schema(name="sensor_msgs/msg/JointState", encoding="ros2msg", data=b"@@ not a msg")
        channel = writer.register_channel(topic="/joint_states", message_encoding="cdr", schema_id=schema)
        writer.add_message(channel_id=channel, log_time=1, data=b"\x00\x01\x00\x00bad", publish_time=1)
        writer.finish()
    for args in (["info"], ["replay", "--config", str(ROOT / "configs" / "mock_arm.toml")],
                 ["plot", "-o", str(tmp_path / "fig")]):
        proc = subprocess.run([sys.executable, "-m", "aiohal", args[0], str(bad), *args[1:]],
                              cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2, (args, proc.stderr)
        assert "/joint_states: its messages do not decode as sensor_msgs/msg/JointState" in proc.stderr
        assert "Traceback" not in proc.stderr
