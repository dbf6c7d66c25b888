"""Helper processes end with the aiohal process that started them, even when it is killed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT

from aiohal.lifetime import PARENT_ENV

TIMEOUT = 30  # seconds: every wait below is bounded by this or less

UDP_ROBOT = """
[robot]
name = "lifetime_udp"

[loop]
rate_hz = 250
max_feedback_age = 400

[joints.j0]
position = [-2.0, 2.0]
velocity = 2.0
acceleration = 20.0

[joints.j1]
position = [-2.0, 2.0]
velocity = 2.0
acceleration = 20.0

[[driver]]
type = "udp"
name = "boards"
joints = ["*"]

[driver.options]
simulate = true
simulation = { priority = 1 }  # the lowest SCHED_FIFO priority, where allowed

[controller]
type = "hold"
"""


def _alive(pid: int) -> bool:
    """Running: a zombie (dead, not yet reaped by whoever adopted it) counts as gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat.rpartition(")")[2].split()[0] not in ("Z", "X")


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except FileNotFoundError:
            continue
    return out


def _main_ran(pid: int) -> bool:
    """The helper's main has run past its start (where it asks to die with its parent): it has
    set its own signal dispositions, SIGTERM caught (the simulators) or SIGINT ignored (the peer)."""
    try:
        fields = dict(line.split(":\t", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    except FileNotFoundError:
        return False
    bit = lambda sig: 1 << (sig - 1)  # noqa: E731
    return bool(int(fields["SigCgt"], 16) & bit(signal.SIGTERM) or int(fields["SigIgn"], 16) & bit(signal.SIGINT))


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except FileNotFoundError:
        return ""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
@pytest.mark.parametrize(
    "config, helper",
    [
        (None, "udp.sim"),  # UDP_ROBOT
        (ROOT / "configs" / "kuka_fri_sim.toml", "fri.sim"),
        (ROOT / "configs" / "kuka_lwr_hand_sim.toml", "aiohal.pipe"),  # the hand's peer
    ],
    ids=["udp-simulator", "fri-simulator", "nrt-hand-peer"],
)
def test_a_helper_dies_within_a_second_of_a_sigkill_of_the_robot(tmp_path, config, helper):
    if config is None:
        config = tmp_path / "udp.toml"
        config.write_text(UDP_ROBOT)
    else:
        pytest.importorskip("mujoco")
    robot = subprocess.Popen(
        [sys.executable, "-m", "aiohal", str(config), "--duration", "60", "--quiet"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    sim = None
    try:
        deadline = time.monotonic() + TIMEOUT
        while sim is None and time.monotonic() < deadline and robot.poll() is None:
            sim = next((c for c in _children(robot.pid) if helper in _cmdline(c)), None)
            time.sleep(0.05)
        assert sim is not None, f"no {helper} started: {robot.stderr.read().decode()[-2000:] if robot.poll() is not None else ''}"
        while not _main_ran(sim) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.2)
        assert _main_ran(sim) and _alive(sim) and robot.poll() is None
        robot.send_signal(signal.SIGKILL)
        robot.wait(TIMEOUT)
        gone_by = time.monotonic() + 1.0
        while _alive(sim) and time.monotonic() < gone_by:
            time.sleep(0.01)
        assert not _alive(sim), f"{helper} outlived the robot process by a second"
    finally:
        if robot.poll() is None:
            robot.kill()
            robot.wait(TIMEOUT)
        if sim is not None and _alive(sim):
            os.kill(sim, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_helper_whose_parent_is_already_gone_exits_at_once():
    """The parent may end between the child's start and its prctl: the child sees another
    parent than the one it was given, and exits instead of running on."""
    code = "from aiohal.lifetime import die_with_parent; die_with_parent(); import time; time.sleep(30)"
    env = {**os.environ, PARENT_ENV: "1" if os.getpid() != 1 else "2"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=TIMEOUT)
    assert proc.returncode == 1
    assert "that started this one is gone" in proc.stderr


def test_a_helper_started_by_hand_is_left_alone():
    code = "from aiohal.lifetime import die_with_parent; die_with_parent(); print('ran')"
    env = {k: v for k, v in os.environ.items() if k != PARENT_ENV}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=TIMEOUT)
    assert proc.returncode == 0 and proc.stdout.strip() == "ran"
