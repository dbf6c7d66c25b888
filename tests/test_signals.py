"""SIGINT and SIGTERM stop a running robot safely: controller stopped, drivers closed, report."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import CONFIGS, NOT_HUNG_S, ROOT

from aiohal.cli import SIGNAL_ECHO_S

_STARTED: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def _reap_processes():
    """A test that fails half-way must not leave a robot process behind."""
    yield
    while _STARTED:
        proc = _STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def _start(tmp_path, *extra, config=CONFIGS / "mock_arm.toml", start_new_session=False):
    """The robot of ``config`` running in a process, once it logged that it runs."""
    report = tmp_path / "report.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "aiohal", str(config), "--log-format", "json",
         "--report-json", str(report), *extra],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=start_new_session,
    )
    _STARTED.append(proc)
    deadline = time.monotonic() + 30
    lines = []
    while time.monotonic() < deadline:  # bounded: wait for the loop to report it is running
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if json.loads(line)["event"].startswith("running"):
            return proc, report, lines
    proc.kill()
    pytest.fail(f"the robot did not start: {lines}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_stops_the_robot_safely(tmp_path, sig):
    proc, report_path, _ = _start(tmp_path)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "aiohal run report" in out
    assert "Traceback" not in err
    report = json.loads(report_path.read_text())
    assert report["stop_reason"] == sig.name
    assert report["ticks"] > 0
    assert report["drivers"]["arm"]["status"] == "closed"
    assert report["safety_level"] == "off"
    assert report["faults"] == []


def test_second_signal_forces_emergency_stop(tmp_path):
    # a driver whose close() never returns: the first signal stops the loop and waits for it,
    # the second one triggers every driver's emergency stop and ends the process
    cfg = tmp_path / "hang.toml"
    text = (CONFIGS / "mock_arm.toml").read_text().replace(
        'dynamics = "first_order"', 'dynamics = "first_order"\nfaults = { close_hangs = true }'
    )
    cfg.write_text(text)
    proc, report, _ = _start(tmp_path, config=cfg)
    proc.send_signal(signal.SIGINT)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # the first signal is handled before the second is sent
        line = proc.stderr.readline()
        if not line or "received: stopping" in line:
            break
    time.sleep(2 * SIGNAL_ECHO_S)  # closer together, the second would be the first's echo
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=30)
    data = json.loads(report.read_text())
    assert proc.returncode == 1  # the run ended with a fault: not every driver closed
    assert data["drivers"]["arm"]["estops"] >= 1
    assert data["drivers"]["arm"]["status"] in ("open", "abandoned")  # honest: close() never finished
    assert any("SIGINT received twice" in f["error"] for f in data["faults"])
    assert "Traceback" not in err


def test_a_close_that_hangs_is_abandoned_after_its_timeout(tmp_path):
    # one signal only: the loop stops, close() hangs, the timeout abandons it after estop
    cfg = tmp_path / "hang.toml"
    text = (CONFIGS / "mock_arm.toml").read_text().replace(
        'dynamics = "first_order"', 'dynamics = "first_order"\nfaults = { close_hangs = true }'
    ).replace("rate_hz = 1000", "rate_hz = 1000\nclose_timeout_ms = 300")
    cfg.write_text(text)
    report = tmp_path / "report.json"
    proc = subprocess.run(
        [sys.executable, "-m", "aiohal", str(cfg), "--duration", "0.2", "--report-json", str(report)],
        cwd=ROOT, capture_output=True, text=True, timeout=30,
    )
    data = json.loads(report.read_text())
    assert proc.returncode == 1
    assert data["drivers"]["arm"]["status"] == "abandoned"
    assert data["drivers"]["arm"]["estops"] == 1
    [fault] = data["faults"]
    assert fault["phase"] == "close" and "did not return within 0.3 s" in fault["error"]


def test_a_signal_to_the_process_and_its_group_at_once_stops_cleanly(tmp_path):
    """GNU ``timeout -s INT`` (and a terminal) signals the process, then its group: two SIGINTs
    microseconds apart are one request, not a double Ctrl-C."""
    proc, report, _ = _start(tmp_path, start_new_session=True)
    os.kill(proc.pid, signal.SIGINT)
    os.killpg(proc.pid, signal.SIGINT)
    _out, err = proc.communicate(timeout=30)
    data = json.loads(report.read_text())
    assert proc.returncode == 0, err
    assert data["stop_reason"] == "SIGINT" and data["faults"] == []
    assert data["drivers"]["arm"]["estops"] == 0 and data["safety_worst"] != "estop"
    assert "Traceback" not in err


@pytest.mark.parametrize("close_hangs", [False, "thread"], ids=["closes", "close-hangs-in-a-thread"])
def test_two_signals_further_apart_than_an_echo_are_an_emergency_stop(tmp_path, close_hangs):
    cfg = tmp_path / "arm.toml"
    text = (CONFIGS / "mock_arm.toml").read_text()
    if close_hangs:  # a close() whose worker thread never returns: the process must not wait for it
        text = text.replace('dynamics = "first_order"', 'dynamics = "first_order"\nfaults = { close_hangs = "thread" }')
        text = text.replace("rate_hz = 1000", "rate_hz = 1000\nclose_timeout_ms = 60000")  # longer than the test
    cfg.write_text(text)
    proc, report, _ = _start(tmp_path, config=cfg)
    proc.send_signal(signal.SIGINT)
    if close_hangs:
        # a second signal sent before the kernel delivered the first is merged with it (POSIX
        # signals do not queue): here it must be a second one, so it is sent once the first is seen
        _wait_for(proc, "SIGINT received: stopping")
    time.sleep(2 * SIGNAL_ECHO_S)  # closer together, the second would be the first's echo
    proc.send_signal(signal.SIGINT)
    second = time.monotonic()
    out, err = proc.communicate(timeout=NOT_HUNG_S + 5)
    exited_after = time.monotonic() - second
    assert "Traceback" not in err
    data = json.loads(report.read_text())
    if not close_hangs and data["drivers"]["arm"]["estops"] == 0:
        # the clean stop was over before the second signal came (or the kernel merged the two):
        # no emergency stop happened, and none is reported
        assert proc.returncode == 0, err
        assert "FAULT" not in out and data["safety_worst"] != "estop"
        return
    assert proc.returncode == 1, err  # an emergency stop is never a success
    assert data["drivers"]["arm"]["estops"] >= 1
    assert data["safety_worst"] == "estop"
    assert any("SIGINT received twice" in f["error"] for f in data["faults"])
    assert "FAULT        signal" in out and "EMERGENCY-STOPPED" in out
    # it waits neither for the close (60 s timeout) nor for its thread (never); 28-46 ms here
    assert exited_after < NOT_HUNG_S


@pytest.mark.parametrize("module", ["pydantic", "numpy", "aiohal.core.loop"])
def test_ctrl_c_while_starting_exits_130_without_a_traceback(module):
    # the SIGINT arrives exactly while `module` is being imported, as a Ctrl-C typed during start-up
    script = f"""
import os, runpy, signal, sys

# as a terminal starts it: a job started in the background by a non-interactive shell (a CI
# script's `&`) inherits SIGINT ignored, and Python then leaves it ignored
signal.signal(signal.SIGINT, signal.default_int_handler)

class CtrlC:
    def find_spec(self, name, path=None, target=None):
        if name == {module!r}:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None

sys.meta_path.insert(0, CtrlC())
sys.argv = ["aiohal", {str(CONFIGS / "mock_arm.toml")!r}, "--duration", "5", "--log-format", "json"]
runpy.run_module("aiohal", run_name="__main__", alter_sys=True)
"""
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert "aiohal run report" not in proc.stdout  # nothing ran


def _wait_for(proc, text: str, timeout_s: float = 30) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:  # bounded: the robot's log, line by line
        line = proc.stderr.readline()
        if not line:
            break
        if text in line:
            return line
    pytest.fail(f"no log line with {text!r}")


def test_safety_signals_hold_estop_and_rearm_a_running_robot(tmp_path):
    # SIGUSR1 holds, SIGUSR2 resets the faults and re-arms, SIGQUIT emergency-stops; SIGUSR2
    # again: the mock releases its stop, the robot is re-armed from where it stands
    proc, report_path, _ = _start(tmp_path)
    proc.send_signal(signal.SIGUSR1)
    _wait_for(proc, "goes to hold")
    # rearm() is refused while hold brakes: at most the fastest joint's velocity over its
    # acceleration limit (3.56 / 10 s in mock_arm.toml)
    time.sleep(0.5)
    for sig, seen in ((signal.SIGUSR2, "re-armed"), (signal.SIGQUIT, "SIGQUIT received"),
                      (signal.SIGUSR1, "SIGUSR1: hold from estop"), (signal.SIGUSR2, "re-armed")):
        proc.send_signal(sig)
        _wait_for(proc, seen)
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 1, err  # a run with an emergency stop is never a success, even re-armed
    report = json.loads(report_path.read_text())
    assert report["safety_worst"] == "estop" and report["safety_level"] == "off"
    steps = [(t["event"], t["source"], t["after"]) for t in report["safety"]]
    assert steps == [("activate", "loop", "run"), ("hold", "user", "hold"), ("reset_faults", "user", "hold"),
                     ("rearm", "user", "run"), ("estop", "user", "estop"), ("reset_faults", "user", "disabled"),
                     ("rearm", "user", "run"), ("deactivate", "loop", "off")]
    assert report["drivers"]["arm"]["estops"] >= 1
