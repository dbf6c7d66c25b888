"""Files named in a config or on the command line: a FIFO, a device or a huge file is refused
at once with the key that named it, never waited on nor read until memory runs out. Every
command runs in a subprocess with a timeout and a capped address space, so that a regression
fails instead of hanging the suite or the machine."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT

from aiohal.files import FileRefused, check_regular, read_regular, read_regular_text

CONFIGS = ROOT / "configs"
TIMEOUT = 30  # seconds: a hang fails the test instead of stalling the suite
CAPPED = (
    "import resource, sys, runpy; resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30)); "
    "sys.argv = ['aiohal', *sys.argv[1:]]; runpy.run_module('aiohal', run_name='__main__')"
)


@pytest.fixture
def fifo(tmp_path) -> Path:
    path = tmp_path / "fifo"
    os.mkfifo(path)
    return path


def run_capped(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", CAPPED, *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )


# ---------------------------------------------------------------- the helper


def test_a_regular_file_is_read_and_others_are_refused_at_once(tmp_path, fifo):
    good = tmp_path / "good.txt"
    good.write_text("héllo")
    assert read_regular_text(good, "k") == "héllo"
    check_regular(good)
    big = tmp_path / "big"
    big.write_bytes(b"x" * 101)
    assert read_regular(big, limit=101) == b"x" * 101
    start = time.monotonic()
    cases = [
        (fifo, "not a regular file (a FIFO)"),
        (Path("/dev/zero"), "not a regular file (a character device)"),
        (tmp_path, "not a regular file (a directory)"),
        (tmp_path / "absent", "file not found"),
    ]
    for path, reason in cases:
        with pytest.raises(FileRefused, match=rf"^some\.key: {re.escape(reason)}: "):
            read_regular(path, "some.key")
        with pytest.raises(FileRefused, match=rf"^{re.escape(reason)}: "):
            check_regular(path)
    with pytest.raises(FileRefused, match=r"^k: larger than 100 bytes: "):
        read_regular(big, "k", limit=100)
    (tmp_path / "latin").write_bytes(b"\xe9")
    with pytest.raises(FileRefused, match="not UTF-8 text"):
        read_regular_text(tmp_path / "latin", "k")
    assert time.monotonic() - start < 1.0


# ---------------------------------------------------------------- every file-valued key


def _canopen(tmp_path: Path, **replace: str) -> str:
    text = (CONFIGS / "canopen_arm_sim.toml").read_text()
    text = text.replace('model = "models/kuka_lwr.xml"', f'model = "{CONFIGS / "models" / "kuka_lwr.xml"}"')
    for old, new in replace.items():
        assert old in text
        text = text.replace(old, new)
    return text


def config_naming(key: str, path: Path, tmp_path: Path) -> Path:
    """A config whose ``key`` names ``path`` (everything else as a shipped config has it)."""
    mock = (CONFIGS / "mock_arm.toml").read_text()
    if key == "feedforward.gains":
        text = mock + f'\n[feedforward]\ngains = "{path}"\n'
    elif key == "bridge.zenoh.config_file":
        text = mock + f'\n[bridge.zenoh]\nconfig_file = "{path}"\n'
    elif key == "options.nodes[0].eds":
        text = _canopen(tmp_path, **{'{ node_id = 1, joint = "a1" }': f'{{ node_id = 1, joint = "a1", eds = "{path}" }}'})
    elif key == "options.dbc":
        text = _canopen(tmp_path, **{"bitrate = 1000000\n": f'bitrate = 1000000\ndbc = "{path}"\n'})
    elif key == "robot.model":
        text = _canopen(tmp_path)
        text = text.replace(f'model = "{CONFIGS / "models" / "kuka_lwr.xml"}"', f'model = "{path}"')
    else:
        raise AssertionError(key)
    out = tmp_path / "robot.toml"
    out.write_text(text)
    return out


KEYS = ["feedforward.gains", "bridge.zenoh.config_file", "options.nodes[0].eds", "options.dbc", "robot.model"]


@pytest.mark.parametrize("kind", ["fifo", "dev-zero"])
@pytest.mark.parametrize("key", KEYS)
def test_check_refuses_a_file_valued_key_that_is_not_a_regular_file(tmp_path, fifo, key, kind):
    if key.startswith("options.") or key == "robot.model":
        pytest.importorskip("canopen")
        pytest.importorskip("mujoco")
    path = fifo if kind == "fifo" else Path("/dev/zero")
    config = config_naming(key, path, tmp_path)
    proc = run_capped("check", config)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    named = [line for line in proc.stderr.splitlines() if key in line and "not a regular file" in line]
    assert named, proc.stderr[-2000:]
    assert str(path) in named[0]


@pytest.mark.parametrize("key", KEYS)
def test_a_regular_file_in_each_key_still_checks(tmp_path, key):
    if key.startswith("options.") or key == "robot.model":
        pytest.importorskip("canopen")
        pytest.importorskip("mujoco")
    data = CONFIGS.parent / "drivers" / "canopen" / "data"
    regular = {
        "feedforward.gains": tmp_path / "gains.toml",
        "bridge.zenoh.config_file": tmp_path / "zenoh.json5",
        "options.nodes[0].eds": data / "aiohal_drive.eds",
        "options.dbc": data / "aiohal_sensors.dbc",
        "robot.model": CONFIGS / "models" / "kuka_lwr.xml",
    }
    (tmp_path / "gains.toml").write_text("[k_e]\na1 = 0.1\n")
    (tmp_path / "zenoh.json5").write_text("{}\n")
    proc = run_capped("check", config_naming(key, regular[key], tmp_path))
    assert proc.returncode == 0, proc.stderr[-2000:]


@pytest.mark.parametrize("command", [["check"], ["run"], []])
def test_a_fifo_as_the_config_file_is_refused(fifo, command):
    proc = run_capped(*command, fifo)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert f"not a regular file (a FIFO): {fifo}" in proc.stderr


@pytest.mark.parametrize("command", ["info", "replay", "plot"])
@pytest.mark.parametrize("kind", ["fifo", "dev-zero"])
def test_a_recording_that_is_not_a_regular_file_is_refused(fifo, tmp_path, command, kind):
    if command == "plot":
        pytest.importorskip("matplotlib")
    pytest.importorskip("mcap")
    path = fifo if kind == "fifo" else Path("/dev/zero")
    extra = {"plot": ["-o", str(tmp_path)], "replay": ["--config", str(ROOT / "configs" / "kuka_lwr_mock.toml")]}
    extra = extra.get(command, [])
    proc = run_capped(command, path, *extra)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert "recording: not a regular file" in proc.stderr and str(path) in proc.stderr
