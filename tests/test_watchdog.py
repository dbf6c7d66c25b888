"""The watchdog process: it acts on the hardware when the whole control process stops
(a frozen process, SIGSTOP, is in tests/test_fault_matrix.py).

The simulated hardware is this test process: the mock driver's board listens on a UDP port
of loopback, as a UDP motor board would, and takes the time its e-stop datagram arrives. The
robot runs from the command line in a process of its own, which the test freezes (SIGSTOP)
or kills (SIGKILL). Root only for SCHED_FIFO (of the robot, its watchdog and the listener);
without it the bounds are not what the code guarantees, so the test needs root.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time

import pytest
from conftest import CONFIGS, ROOT, HostReference, require_root

from aiohal.safety.watchdog import ARMED, STAMP, SendDatagram, WatchdogProcess

WATCHDOG_MS = 20.0
SLACK_MS = 5.0


class Board:
    """A UDP board on loopback: notes the CLOCK_MONOTONIC time of every datagram, in a
    SCHED_FIFO thread so that its own wake-up is not what is measured."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.received: list[tuple[int, bytes]] = []
        self.arrived = threading.Event()
        self._stop = False
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(95))
        except OSError:
            pass
        while not self._stop:
            try:
                data = self.sock.recv(64)
            except TimeoutError:
                continue
            self.received.append((time.monotonic_ns(), data))
            self.arrived.set()

    def close(self) -> None:
        self._stop = True
        self._thread.join(2)
        self.sock.close()


@pytest.fixture
def board():
    b = Board()
    yield b
    b.close()


def robot_config(tmp_path, port: int, watchdog_ms: float = WATCHDOG_MS) -> str:
    text = (CONFIGS / "mock_arm.toml").read_text().replace(
        'dynamics = "first_order"', f'dynamics = "first_order"\nestop_datagram = "127.0.0.1:{port}"')
    assert "estop_datagram" in text
    text += f"\n[safety]\nwatchdog_ms = {watchdog_ms}\nwatchdog_priority = 90\n"
    path = tmp_path / "robot.toml"
    path.write_text(text)
    return str(path)


def start_robot(tmp_path, board):
    report = tmp_path / "report.json"
    proc = subprocess.Popen([sys.executable, "-m", "aiohal", robot_config(tmp_path, board.port), "--log-format",
                             "json", "--report-json", str(report)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # bounded: until the watchdog is armed
        line = proc.stderr.readline()
        if not line:
            break
        event = json.loads(line)["event"]
        if event.startswith("watchdog process"):
            return proc, report, int(event.split()[2])
    proc.kill()
    pytest.fail(f"the robot did not arm its watchdog: {proc.communicate(timeout=10)[1][-2000:]}")


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is gone for our purpose
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.realtime
def test_the_watchdog_process_acts_and_exits_when_its_parent_is_killed(tmp_path, board):
    require_root("SCHED_FIFO for the robot, its watchdog process and the simulated board")
    proc, _, watchdog_pid = start_robot(tmp_path, board)
    host = HostReference(SLACK_MS, priority=90)  # the watchdog process's priority
    try:
        assert alive(watchdog_pid)
        killed = time.monotonic_ns()
        proc.kill()
        proc.wait(10)
        assert board.arrived.wait(2.0)
        host.require_fit()
        assert (board.received[0][0] - killed) / 1e6 <= WATCHDOG_MS + SLACK_MS
        deadline = time.monotonic() + 5
        while alive(watchdog_pid) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not alive(watchdog_pid)
    finally:
        host.stop()
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def test_the_watchdog_process_does_not_act_on_a_fresh_heartbeat_and_exits_when_asked(board):
    # a long timeout: this test's own heartbeat loop may be stalled by a loaded host, which is
    # not what it tests (the frozen-process tests measure the 20 ms case)
    watchdog = WatchdogProcess([("driver:x", SendDatagram("127.0.0.1", board.port, b"stop"))], 500.0)
    watchdog.start()
    try:
        hb = watchdog.heartbeat
        watchdog.arm()
        end = time.monotonic() + 0.2
        while time.monotonic() < end:  # a heartbeat every ms, from this process
            hb[STAMP] = time.monotonic_ns()
            time.sleep(0.001)
        assert board.received == [] and watchdog.fired_ns == 0
        watchdog.disarm()
        assert not board.arrived.wait(0.1)  # disarmed: a stale heartbeat is no stall
        watchdog.arm()
        assert board.arrived.wait(2.0)
        deadline = time.monotonic() + 2.0  # it marks the page once its actions are sent
        while watchdog.fired_ns == 0 and time.monotonic() < deadline:
            time.sleep(0.001)
        assert watchdog.fired_ns > 0 and hb[ARMED] == 0
        proc = watchdog.proc
    finally:
        watchdog.stop()
    assert proc.returncode == 0


def test_a_wrong_action_fails_at_start_not_in_the_emergency():
    watchdog = WatchdogProcess([("driver:x", SendDatagram("no.such.host.invalid", 9, b""))], 20.0)
    with pytest.raises(RuntimeError, match="did not start"):
        watchdog.start()
    with pytest.raises(TypeError, match="not a watchdog action"):
        WatchdogProcess([("driver:x", "send bytes somewhere")], 20.0)
