"""``aiohal replay``: a controller run in lockstep on a recording's measured state gives the
recorded commands bit for bit, and a changed parameter shows at the first tick it changes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import require_module

require_module("mcap")
require_module("rosbags")
require_module("mujoco")  # the circle's IK runs on the arm's MJCF model

from aiohal.record import load

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "kuka_lwr_mock.toml"


def aiohal(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "aiohal", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def record(config: Path, out: Path) -> None:
    proc = aiohal(str(config), "--duration", "1", "--record", str(out), "--quiet", "--log-format", "json")
    assert proc.returncode == 0, proc.stderr


def changed_config(tmp_path: Path, old: str, new: str) -> Path:
    text = CONFIG.read_text()
    assert old in text
    text = text.replace(old, new).replace('model = "models/', f'model = "{ROOT}/configs/models/')
    path = tmp_path / "changed.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def shipped_run(tmp_path_factory) -> Path:
    """One recording of the shipped config, read by every test here (each recording is a
    robot process: seconds of start-up)."""
    path = tmp_path_factory.mktemp("replay") / "run.mcap"
    record(CONFIG, path)
    return path


def test_replay_of_a_lockstep_circle_gives_the_recorded_commands_bit_for_bit(shipped_run):
    proc = aiohal("replay", str(shipped_run), "--config", str(CONFIG), "--json")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads(proc.stdout)
    assert result["ticks"] == 1001 and result["differing_ticks"] == 0 and result["first_differing_tick"] is None
    # and the text says so
    proc = aiohal("replay", str(shipped_run), "--config", str(CONFIG))
    assert proc.returncode == 0 and "0 ticks differ" in proc.stdout


def test_replay_with_a_changed_parameter_reports_the_first_tick_that_differs(tmp_path, shipped_run):
    changed = changed_config(tmp_path, "radius = 0.1\n", "radius = 0.1001\n")
    record(changed, tmp_path / "b.mcap")
    # the reference: where the two runs' recorded commands first part (before it both runs saw
    # the same states, so the replay on run a's states must part there too)
    a, b = load(shipped_run)["/joint_commands"], load(tmp_path / "b.mcap")["/joint_commands"]
    assert np.array_equal(a.tick, b.tick)
    parted = np.flatnonzero((a.position != b.position).any(axis=1) | (a.velocity != b.velocity).any(axis=1))
    assert len(parted)
    proc = aiohal("replay", str(shipped_run), "--config", str(changed), "--json")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    result = json.loads(proc.stdout)
    assert result["first_differing_tick"] == int(a.tick[parted[0]])
    assert result["differing_ticks"] > 0
    first = result["differences"][0]
    assert first["field"] in ("position", "velocity") and first["recorded"] != first["replayed"]


def test_replay_refuses_another_rate_and_a_missing_file(tmp_path, shipped_run):
    other = changed_config(tmp_path, "rate_hz = 1000\n", "rate_hz = 500\n")
    proc = aiohal("replay", str(shipped_run), "--config", str(other))
    assert proc.returncode == 2 and "loop.rate_hz" in proc.stderr and "1000" in proc.stderr
    proc = aiohal("replay", str(tmp_path / "nothing.mcap"), "--config", str(CONFIG))
    assert proc.returncode == 2 and "nothing.mcap" in proc.stderr
