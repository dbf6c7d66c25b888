"""A robot process to disturb: ``python -m aiohal`` on a config, with a recording and a JSON
report, its log lines read as they come, and the checks every disturbance shares (nothing
commanded away from where the robot stands after the resume; a re-arm without a step)."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from conftest import ROOT


class RobotProcess:
    """``python -m aiohal CONFIG`` in a process group of its own, as a shell starts a job (a
    signal to the group reaches nothing else; the group is not orphaned, so SIGTSTP stops it
    as Ctrl-Z would), until SIGTERM. Every log line is kept in ``lines``."""

    def __init__(self, config: Path, tmp_path: Path, *extra: str) -> None:
        self.record = tmp_path / "run.mcap"
        self.report_path = tmp_path / "report.json"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "aiohal", str(config), "--log-format", "json", "--record", str(self.record),
             "--report-json", str(self.report_path), *extra],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, process_group=0)
        self.lines: list[str] = []
        self._new: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:  # ends with the process
            self._new.put(line)

    def wait_for(self, text: str, timeout_s: float = 60.0) -> str:
        """The first log event (new since the last call) that contains ``text``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self._new.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                break
            self.lines.append(line)
            try:
                event = json.loads(line).get("event", "")
            except ValueError:
                event = line
            if text in event:
                return event
        self.kill()
        raise AssertionError(f"no log event with {text!r} within {timeout_s:g} s:\n" + "".join(self.lines[-30:]))

    def drain(self) -> None:
        """Take the log lines written so far."""
        while not self._new.empty():
            self.lines.append(self._new.get())

    def ensure_running(self) -> None:
        """Re-arm when something (a host stall before the disturbance under test) took the
        robot out of run since it last was re-armed, so that the test starts from run."""
        self.drain()
        since = max((i for i, line in enumerate(self.lines) if "re-armed" in line), default=-1)
        if any('"level": "error"' in line for line in self.lines[since + 1 :]):
            self.rearm()

    def wait_for_stall(self, min_ms: float, timeout_s: float = 30.0) -> str:
        """The log event of a stall of at least ``min_ms`` (a host's shorter ones are skipped)."""
        deadline = time.monotonic() + timeout_s
        while True:
            event = self.wait_for("stalled for", max(0.1, deadline - time.monotonic()))
            if stall_ms(event) >= min_ms:
                return event

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def freeze(self, seconds: float) -> tuple[int, int]:
        """SIGSTOP, ``seconds``, SIGCONT: the CLOCK_MONOTONIC times of both."""
        stopped = time.monotonic_ns()
        self.proc.send_signal(signal.SIGSTOP)
        time.sleep(seconds)  # the disturbance itself: how long the process stays frozen
        resumed = time.monotonic_ns()
        self.proc.send_signal(signal.SIGCONT)
        return stopped, resumed

    def rearm(self, attempts: int = 20) -> None:
        """SIGUSR2 (reset_faults, then rearm) until the robot is re-armed; a refusal names why
        (a drive still coming back, hold still braking), so it is tried again, bounded."""
        for _ in range(attempts):
            self.signal(signal.SIGUSR2)
            self.wait_for("SIGUSR2 received", 20)
            for _ in range(20):  # the request's outcome: re-armed, or an error naming the refusal
                event = self.wait_for("", 20)
                if "re-armed" in event or event.startswith("SIGUSR2:"):
                    break
            if "re-armed" in event:
                return
            time.sleep(0.2)  # let the drivers come back before asking again
        raise AssertionError("the robot was never re-armed:\n" + "".join(self.lines[-30:]))

    def stop(self, timeout_s: float = 60.0) -> dict:
        """SIGTERM; the report once the process has left."""
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout_s)
        finally:
            self.kill()
        self._reader.join(5)
        self.drain()
        return json.loads(self.report_path.read_text())

    def kill(self) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.proc.wait(10)


def stall_ms(text: str) -> float:
    """The gap a stall fault or log line names ("the tick stalled for 1001.5 ms ...")."""
    return float(text.split("stalled for ")[1].split(" ms")[0])


def commanded_ticks(recording) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per recorded tick where the robot was commanded (hold or run): the tick, the command
    and the measured position."""
    from aiohal.record.reader import LEVELS

    cmd, state, safety = recording["/joint_commands"], recording["/joint_states"], recording["/safety"]
    ticks = np.intersect1d(np.intersect1d(cmd["tick"], state["tick"]), safety["tick"])
    pick = lambda series: np.searchsorted(series["tick"], ticks)  # noqa: E731
    level = safety["level"][pick(safety)]
    moving = level >= LEVELS.index("hold")
    return ticks[moving], cmd["position"][pick(cmd)][moving], state["position"][pick(state)][moving]


def check_resume(report: dict, recording, period_s: float, velocity_limit: np.ndarray, resumed_tick: int):
    """After the resume, until the re-arm: the first command sent lies within one tick at the
    velocity limit of the position measured on its tick, and every later one within one such
    step of it (held there, whatever the servo's own error under load). After the re-arm no
    step is larger than that."""
    ticks, command, measured = commanded_ticks(recording)
    rearm = [t["tick"] for t in report["safety"] if t["event"] == "rearm" and t["tick"] >= resumed_tick]
    assert rearm, report["safety"]
    step = velocity_limit * period_s
    held = (ticks >= resumed_tick) & (ticks <= rearm[0])  # none when e-stopped: nothing was sent
    first = np.flatnonzero(ticks >= resumed_tick)[0]
    assert (np.abs(command[first] - measured[first]) <= step + 1e-9).all(), (
        ticks[first], command[first], measured[first])
    far = np.abs(command[held] - command[first]) > step + 1e-9  # held: no motion
    assert not far.any(), f"held commands moved away at ticks {ticks[held][far.any(axis=1)][:10]}"
    after = ticks >= rearm[0]
    steps = np.abs(np.diff(command[after], axis=0)) > np.diff(ticks[after])[:, None] * step + 1e-9
    assert not steps.any(), f"steps after the re-arm at ticks {ticks[after][1:][steps.any(axis=1)][:10]}"
    return int(held.sum()), int(after.sum())

