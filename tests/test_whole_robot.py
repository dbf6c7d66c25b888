"""The whole robot (configs/walkman_whole_sim.toml): every kind of part in one config at 2 kHz,
checked, then run end to end through the CLI against the simulated EtherCAT segment (needs
root: skipped with the reason otherwise, a failure under CI=true)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import CONFIGS, ROOT, require_module, start_segment

CONFIG = CONFIGS / "walkman_whole_sim.toml"
LEGS = [f"{side}_{j}" for side in "lr" for j in ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")]
WAIST = ["waist_yaw", "waist_pitch", "waist_roll"]
SM_WATCHDOG_MS = 1000


def test_the_whole_robot_config_passes_check():
    proc = subprocess.run([sys.executable, "-m", "aiohal", "check", str(CONFIG)], capture_output=True, text=True,
                          timeout=60, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert "drivers: can_sensors (canopen, 0 joints), hand (nrt_hand, 1 joint), legs (ethercat, 15 joints)" in proc.stdout
    assert "at 2000 Hz" in proc.stdout


def whole_robot_text(ifname: str, record: str) -> str:
    """The shipped config on the segment's interface, recording to ``record``; the loop's stall
    and stale-feedback guards, the CAN sensors' staleness (40 ms: 4 s) and the slaves' SM
    watchdog widened (tested elsewhere): a stall of this shared host is not what is tested
    here (beside two CPU hogs the sensors once went 40 ms without a frame)."""
    text = CONFIG.read_text()
    changes = [
        ('interface = "ecm0"', f'interface = "{ifname}"'),
        ("rate_hz = 2000\n", "rate_hz = 2000\nmax_feedback_age = 10000\nstall_timeout_ms = 5000\n"),
        ("sync0 = true", f"sync0 = true\nsm_watchdog_ms = {SM_WATCHDOG_MS}\nreceive_timeout_us = 2000"),
        ('path = "/tmp/aiohal-walkman-whole.mcap"', f"path = {json.dumps(record)}"),
    ]
    for old, new in changes:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    assert text.count("stale_periods = 10") == 2
    text = text.replace("stale_periods = 10", "stale_periods = 1000")
    return text + "\n[safety]\nmax_tick_gap_ms = 5000\n"


# about 20 s: the segment's simulator starts, then the robot process and its hand, recorder and
# bridge processes, which run for 3 s; the recording is read back
@pytest.mark.root
def test_the_whole_robot_runs_with_every_part_producing_data(tmp_path):
    """A few seconds through the CLI: no working-counter error the driver could have avoided,
    no fault, and data from every part: the drives' positions moving, the CAN IMU reading
    gravity, the hand's state, the recording (read back) and the bridge's messages."""
    require_module("mcap")
    require_module("zenoh")
    segment = start_segment("drive*15", watchdog_ms=SM_WATCHDOG_MS)
    try:
        # the hardware does not stall: the simulated slaves answer at SCHED_FIFO beside a loaded host's work
        os.sched_setscheduler(segment.pid, os.SCHED_FIFO, os.sched_param(95))
        record, report_path = tmp_path / "whole.mcap", tmp_path / "report.json"
        config = tmp_path / CONFIG.name
        config.write_text(whole_robot_text(segment.ifname, str(record)))
        proc = subprocess.run([sys.executable, "-m", "aiohal", str(config), "--duration", "3", "--quiet",
                               "--log-format", "json", "--report-json", str(report_path)],
                              capture_output=True, text=True, timeout=120, cwd=ROOT)
        # a reply the simulator sent more than 2 ms after its frame came (the host stalled it)
        # is lost to the driver's 2 ms wait: none of the driver's doing
        stalled = segment.status()["counters"]["late_2000us"]
    finally:
        segment.stop()
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(report_path.read_text())
    assert report["faults"] == [] and report["safety_worst"] == "run", report["faults"]
    assert report["controller"]["every"] == 2 and report["controller"]["extrapolate"] is True
    assert report["rate_hz_target"] == 2000
    legs = report["drivers"]["legs"]
    assert legs["wkc_errors"] <= stalled, (legs["wkc_errors"], stalled)
    assert legs["cycles"] >= report["ticks"] - 1
    sensors = report["drivers"]["can_sensors"]["sensors"]
    for name in ("pelvis_imu", "l_ankle_ft"):
        assert sensors[name]["frames"] > 100 and not sensors[name]["stale"], sensors
    hand = report["drivers"]["hand"]
    assert hand["hand"] == "ok" and hand["pipe"]["received"] > 50, hand
    assert report["record"]["ticks"] > 0 and report["record"]["dropped_ticks"] == 0, report["record"]
    bridge = report["bridge"]["zenoh"]
    assert bridge["state_sent"] > 50 and bridge["state_lost"] == 0, bridge

    from aiohal.record import load

    rec = load(record)
    assert rec.joint_names[: len(LEGS) + len(WAIST)] == LEGS + WAIST
    q = rec["/joint_states"].position
    assert q.shape[0] == report["record"]["ticks"]
    moved = np.ptp(q[:, : len(LEGS) + len(WAIST)], axis=0)
    assert np.all(moved > 0.01), dict(zip(LEGS + WAIST, moved, strict=True))  # every drive followed the sine
    knee = rec.joint_names.index("l_knee")
    assert abs(q[0, knee] - 0.6) < 0.05  # the drive's zero is the joint's offset
    gravity = rec["/imu/pelvis_imu"]["linear_acceleration.z"]
    assert len(gravity) > 100 and abs(np.median(gravity) - 9.81) < 0.5
