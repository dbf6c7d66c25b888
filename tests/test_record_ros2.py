"""Recordings in ROS 2 terms: the batch encoder writes rosbags' bytes for every channel, a
WALK-MAN run decodes as sensor_msgs/JointState with 33 names per tick, and a rosbag2 directory
is read by rosbags (a reader that is not the writer)."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import require_module

require_module("mcap")
require_module("rosbags")
require_module("mcap_ros2")

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader as BagReader

from aiohal import ControlLoop, load_config, ros2
from aiohal.core.ticker import VirtualTickSource
from aiohal.outside.recorder import Recorder
from aiohal.outside.recorder_writer import RecorderWriter
from aiohal.record import RecordSection, load

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "configs" / "mock_humanoid.toml"


def test_batch_encoder_writes_the_bytes_of_rosbags_for_every_channel(tmp_path):
    async def main():
        control = ControlLoop(load_config(HUMANOID), tick_source=VirtualTickSource())
        await control.activate()
        recorder = Recorder(control.port, tmp_path / "run.mcap", RecordSection())
        recorder.attach()
        await control.run(ticks=200)
        await control.deactivate()
        # the writer's encoder, in this process, on the same ring
        writer = RecorderWriter({"robot": control.robot, "path": None, "options": RecordSection(),
                                 "period_ns": control.period_ns, "clock": "virtual", "config_text": "",
                                 "offset_ns": 0, "now_ns": 0, "start": recorder.ring.head, "pid": os.getpid(),
                                 "line": recorder.ring.claim_reader(recorder.ring.head)})
        recorder.close()
        return writer

    recorder = asyncio.run(main())
    rng = np.random.default_rng(7)
    kinds = set()
    for ch in recorder.channels:
        kinds.add(ch.topic.msgtype)
        n = 5
        values = {}
        for path, (dtype, count, _) in ch.layout.fields.items():
            shape = (n,) if count is None else (n, count)
            if dtype.kind == "f":
                values[path] = rng.normal(size=shape).astype(dtype)
            elif dtype.kind == "b":
                values[path] = rng.integers(0, 2, size=shape).astype(bool)
            else:
                info = np.iinfo(dtype)
                values[path] = rng.integers(info.min, info.max, size=shape, dtype=dtype, endpoint=True)
        batch = list(recorder._encode(ch, values, n))
        recorder.plain = True
        plain = list(recorder._encode(ch, values, n))
        recorder.plain = False
        assert batch == plain, ch.topic.topic
    recorder.ring.close()
    assert {"sensor_msgs/msg/JointState", "sensor_msgs/msg/Imu", "geometry_msgs/msg/WrenchStamped",
            "aiohal_msgs/msg/Hand", "aiohal_msgs/msg/TickTiming", "aiohal_msgs/msg/SafetyLevel",
            "aiohal_msgs/msg/JointStateExtra", "aiohal_msgs/msg/JointCommandExtra",
            "aiohal_msgs/msg/DeviceFaults"} <= kinds
    # and what was written re-serializes to itself through rosbags
    rec = load(tmp_path / "run.mcap")
    for series in rec.series.values():
        for raw in series.raw[:3]:
            assert ros2.serialize(ros2.deserialize(raw, series.schema)) == raw, series.topic


def test_walkman_recording_decodes_as_joint_state_with_33_names_on_every_tick(tmp_path):
    require_module("mujoco")
    out = tmp_path / "walkman.mcap"
    proc = subprocess.run([sys.executable, "-m", "aiohal", "configs/walkman_sim.toml", "--clock", "virtual",
                           "--duration", "0.5", "--record", str(out), "--quiet", "--log-format", "json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    names = [j.name for j in load_config(ROOT / "configs" / "walkman_sim.toml").joints]
    assert len(names) == 33
    ticks = []
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, _, message, msg in reader.iter_decoded_messages(topics=["/joint_states"]):
            assert schema.name == "sensor_msgs/msg/JointState"
            assert list(msg.name) == names and len(msg.position) == 33
            ticks.append(message.sequence)
    assert ticks == list(range(501))  # tick 0: the state read at activation


def test_rosbag2_directory_is_read_by_rosbags(tmp_path):
    bag = tmp_path / "run_bag"
    proc = subprocess.run([sys.executable, "-m", "aiohal", "configs/mock_arm.toml", "--clock", "virtual",
                           "--duration", "0.3", "--record", str(bag), "--quiet", "--log-format", "json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert (bag / "metadata.yaml").is_file() and (bag / "run_bag_0.mcap").is_file()
    names = [j.name for j in load_config(ROOT / "configs" / "mock_arm.toml").joints]
    store = ros2.typestore()
    with BagReader(bag) as reader:
        types = {c.topic: (c.msgtype, c.digest) for c in reader.connections}
        assert types["/joint_states"] == ("sensor_msgs/msg/JointState", ros2.type_hash("sensor_msgs/msg/JointState"))
        robot = next(c for c in reader.connections if c.topic == "/robot")
        assert robot.ext.offered_qos_profiles[0].durability.name == "TRANSIENT_LOCAL"
        states = [c for c in reader.connections if c.topic == "/joint_states"]
        decoded = [store.deserialize_cdr(raw, c.msgtype) for c, _, raw in reader.messages(connections=states)]
        assert reader.message_count == sum(c.msgcount for c in reader.connections)
    assert len(decoded) == 301 and all(list(m.name) == names for m in decoded)
    info = subprocess.run([sys.executable, "-m", "aiohal", "info", str(bag), "--json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["ticks"] == 301


def test_record_into_an_existing_directory_exits_2(tmp_path):
    (tmp_path / "bag").mkdir()
    proc = subprocess.run([sys.executable, "-m", "aiohal", "configs/mock_arm.toml", "--duration", "0.1",
                           "--record", str(tmp_path / "bag")], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "exists" in proc.stderr and "--record" in proc.stderr


@pytest.mark.parametrize("topic", ["/robot", "/faults", "/diagnostics", "/safety/events"])
def test_event_topics_have_standard_or_aiohal_types(topic):
    from aiohal.outside.recorder_topics import EVENT_TOPICS

    assert ros2.type_hash(EVENT_TOPICS[topic]).startswith("RIHS01_")
