"""The disturbance matrix: the robot's process, run from the command line on each simulated
driver, is frozen (SIGSTOP) for a second and resumed; its watchdog process is killed, stopped,
and made to act twice. Each row checks, from the run's recording and report, that nothing was
commanded away from where the robot stood after the resume, that the robot was held or
e-stopped with a fault naming the disturbance, and that the operator's re-arm (SIGUSR2)
resumed without a step. EtherCAT's rows are in tests/test_ethercat_disturbances.py, the KRC's
own disturbances in tests/test_fri_disturbances.py."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest
from conftest import CONFIGS, HostReference, require_root
from disturb import RobotProcess, check_resume, stall_ms
from test_watchdog import Board, alive, robot_config

from aiohal.config import load_config
from aiohal.record.reader import load

FREEZE_S = 1.0

# (config, what the freeze takes the robot to): drivers whose safe action the watchdog process
# runs are e-stopped by it (and so by the loop when it resumes); the others are held
FREEZES = {
    "mock": ("mock_arm.toml", "hold"),
    "mujoco": ("kuka_lwr_sim.toml", "hold"),
    "canopen": ("canopen_arm_sim.toml", "hold"),
    "udp": ("coman_udp_sim.toml", "estop"),
    "fri": ("kuka_fri_sim.toml", "hold"),
}
# COMAN's 29 boards of one joint at 1 kHz take a slow 2-vCPU guest most of a core on each
# side (bare asyncio sending and taking the same datagrams: 808 µs a tick, benchmarks.udp),
# so that their replies come late and the driver fails before any freeze: the freeze is the
# subject here, on four boards of eight joints (tests/test_udp_driver.py covers the boards)
EDITS = {"coman_udp_sim.toml": ("joints_per_board = 1 ", "joints_per_board = 8 ")}


def frozen_config(name: str, tmp_path) -> Path:
    """A shipped config, copied, whose stalls are those of a frozen process: the bound (and
    the watchdog process's time) at 200 ms, above a loaded host's own stalls of the robot's
    process, far below the freeze."""
    text = (CONFIGS / name).read_text().replace('model = "models/', f'model = "{CONFIGS}/models/')
    # the loop's stall watchdog (a thread of the frozen process) is not the subject: on the
    # resume it may run before the tick and end the run (no tick for its 500 ms)
    text = text.replace("[loop]\n", "[loop]\nstall_timeout_ms = 5000\n", 1)
    assert "stall_timeout_ms = 5000" in text
    if name in EDITS:
        old, new = EDITS[name]
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / name
    path.write_text(text + "\n[safety]\nmax_tick_gap_ms = 200\nwatchdog_ms = 200\n")
    return path


def running(robot: RobotProcess, seconds: float = 1.0) -> None:
    """Until it runs, then ``seconds`` of motion."""
    robot.wait_for("running")
    time.sleep(seconds)  # let the controller move the robot: the freeze catches it moving


@pytest.fixture
def board():
    b = Board()
    yield b
    b.close()


@pytest.mark.realtime  # a robot process frozen and resumed, its simulators on their own clock: run alone
@pytest.mark.parametrize("driver", [
    # the KRC takes commands again only once it grades the answers PERFECT (as tests/test_fri.py),
    # answered by a robot process at normal priority (the config asks for none)
    pytest.param(name, marks=pytest.mark.host_reference(1.0)) if name == "fri" else name for name in FREEZES
])
def test_a_frozen_robot_process_holds_where_it_stands_and_rearms_without_a_step(tmp_path, driver):
    name, level = FREEZES[driver]
    path = frozen_config(name, tmp_path)
    config = load_config(path)
    robot = RobotProcess(path, tmp_path)
    try:
        running(robot)
        robot.ensure_running()
        robot.freeze(FREEZE_S)
        robot.wait_for_stall(FREEZE_S * 1e3 * 0.9)
        time.sleep(0.3)  # held (or e-stopped) for a moment before the operator re-arms
        robot.rearm()
        time.sleep(0.5)  # moving again
        report = robot.stop()
    finally:
        robot.kill()
    # the freeze's stall (a loaded host may have stalled the tick beyond the bound before it)
    stall = [f for f in report["faults"] if f["phase"] == "stall" and stall_ms(f["error"]) >= FREEZE_S * 900]
    assert len(stall) == 1 and stall[0]["source"] == "loop", report["faults"]
    gap_ms = stall_ms(stall[0]["error"])
    # from the stalled tick on; and the watchdog process's e-stop, which the loop may notice off
    # the tick on the resume, before the stalled tick, with the number of the last tick before
    since = stall[0]["tick"] - gap_ms * 1e6 / config.period_ns - 1
    after = [(t["event"], t["after"]) for t in report["safety"]
             if t["tick"] >= stall[0]["tick"] or (t["tick"] >= since and t["source"] == "watchdog")]
    if level == "hold":
        assert after[0] == ("fault", "hold"), report["safety"]
    else:  # the watchdog's e-stop, noticed on the resume: first, or right after the stall's hold
        # (both come on the resume; once, on Python 3.13, the hold was recorded first)
        first = after[1] if after[0] == ("fault", "hold") else after[0]
        assert first == ("watchdog", "estop"), report["safety"]
    assert after[-2:] == [("rearm", "run"), ("deactivate", "off")], report["safety"]
    robot_model = config.build_robot()
    held, moved = check_resume(report, load(robot.record), config.period_ns / 1e9, robot_model.velocity_limit,
                               stall[0]["tick"])
    print(f"{driver}: stalled {gap_ms:.0f} ms, {held} ticks held at the measured position, {moved} after the re-arm")
    assert moved > 50


# ---------------------------------------------------------------- the watchdog process


def watched_robot(tmp_path, board, watchdog_ms: float = 20.0) -> tuple[RobotProcess, int]:
    """The mock arm whose board takes the e-stop datagram; its watchdog process's pid."""
    robot = RobotProcess(robot_config(tmp_path, board.port, watchdog_ms), tmp_path)
    event = robot.wait_for("watchdog process")  # "watchdog process <pid> armed": it runs
    return robot, int(event.split()[2])


def estops_between(board, start_ns: int, end_ns: int) -> int:
    return sum(start_ns <= t <= end_ns for t, _ in board.received)


def test_a_killed_watchdog_holds_the_robot_and_refuses_rearm(tmp_path, board):
    # the watchdog's absence is the subject, not its time: a loaded host's stall of the robot
    # beyond 20 ms would have it e-stop first
    robot, watchdog = watched_robot(tmp_path, board, watchdog_ms=500.0)
    try:
        time.sleep(0.5)
        import os

        os.kill(watchdog, signal.SIGKILL)
        robot.wait_for("is dead", 10)
        robot.signal(signal.SIGUSR2)
        refused = robot.wait_for("rearm() refused", 10)
        assert f"the watchdog process {watchdog} is dead" in refused
        report = robot.stop()
    finally:
        robot.kill()
    assert robot.proc.returncode == 1
    assert report["safety_worst"] == "hold"
    assert any(f["source"] == "watchdog" and "dead" in f["error"] for f in report["faults"])
    events = [(t["event"], t["source"]) for t in report["safety"]]
    assert ("fault", "watchdog") in events and ("rearm", "user") not in events, events


def test_a_stopped_watchdog_holds_the_robot_until_it_runs_again(tmp_path, board):
    # the watchdog's absence is the subject, not its time: a loaded host's stall of the robot
    # beyond 20 ms would have it e-stop first
    robot, watchdog = watched_robot(tmp_path, board, watchdog_ms=500.0)
    try:
        time.sleep(0.5)
        import os

        os.kill(watchdog, signal.SIGSTOP)
        robot.wait_for("is stopped", 10)
        robot.signal(signal.SIGUSR2)
        assert "is stopped" in robot.wait_for("rearm() refused", 10)
        os.kill(watchdog, signal.SIGCONT)
        robot.rearm()
        report = robot.stop()
    finally:
        robot.kill()
    events = [(t["event"], t["source"], t["after"]) for t in report["safety"]]
    assert ("fault", "watchdog", "hold") in events and events[-2:] == [
        ("rearm", "user", "run"), ("deactivate", "loop", "off")]


@pytest.mark.realtime
def test_terminal_signals_to_the_robots_group_do_not_reach_the_watchdog(tmp_path, board):
    """Ctrl-\\ (SIGQUIT to the foreground group) e-stops the robot and leaves its watchdog
    running and armed again after the re-arm; Ctrl-Z (SIGTSTP) stops the robot, not the
    watchdog, which then acts."""
    import os

    require_root("the e-stop datagram's time is judged with SCHED_FIFO on the robot, its watchdog and the board")
    robot, watchdog = watched_robot(tmp_path, board)
    try:
        time.sleep(0.5)
        robot.ensure_running()
        os.killpg(robot.proc.pid, signal.SIGQUIT)
        robot.wait_for("SIGQUIT received")
        robot.rearm()
        assert alive(watchdog)
        before = len(board.received)
        with HostReference(5.0, priority=90) as host:  # the watchdog process's priority
            stopped = time.monotonic_ns()
            os.killpg(robot.proc.pid, signal.SIGTSTP)  # the robot stops; its watchdog does not
            deadline = time.monotonic() + 5
            while len(board.received) == before and time.monotonic() < deadline:  # bounded
                time.sleep(0.002)
        assert len(board.received) > before, "the watchdog process did not act while the robot was stopped"
        took_ms = (board.received[before][0] - stopped) / 1e6
        os.killpg(robot.proc.pid, signal.SIGCONT)
        robot.wait_for("the watchdog process ran", 10)
        report = robot.stop()
    finally:
        robot.kill()
    print(f"e-stop datagram {took_ms:.2f} ms after SIGTSTP")
    assert alive(watchdog) is False  # it left with the robot
    host.require_fit()
    assert took_ms <= 20.0 + 5.0
    events = [(t["event"], t["source"]) for t in report["safety"]]
    assert events[-5:] == [("estop", "user"), ("reset_faults", "user"), ("rearm", "user"), ("watchdog", "watchdog"),
                           ("deactivate", "loop")]


def test_the_watchdog_acts_again_after_a_rearm(tmp_path, board):
    robot, _ = watched_robot(tmp_path, board)
    acted = []
    try:
        for _ in range(2):
            time.sleep(0.3)
            robot.ensure_running()
            stopped, resumed = robot.freeze(0.3)
            robot.wait_for_stall(250)
            acted.append(estops_between(board, stopped, resumed))
            robot.rearm()
        time.sleep(0.3)
        report = robot.stop()
    finally:
        robot.kill()
    assert all(n >= 1 for n in acted), f"e-stop datagrams during each freeze: {acted}"
    # a fault of the watchdog per freeze, and one again after the rearm: at a stall the loop saw
    # too. The watchdog process can also see a stall of its own (beside two CPU hogs: before the
    # second tick, or at tick 300 while the loop saw none, that fault then covering the first
    # freeze), so the faults are judged from its first one on: a later one at a loop stall.
    stalls = [f["tick"] for f in report["faults"] if f["phase"] == "stall"]
    watchdog_faults = [f["tick"] for f in report["faults"] if f["source"] == "watchdog"]
    after_start = [t for t in watchdog_faults if t > 1]
    assert len(after_start) >= 2, report["faults"]
    assert any(t in after_start for t in stalls if t > after_start[0]), report["faults"]
    events = [t["event"] for t in report["safety"]]
    assert events.count("watchdog") == len(watchdog_faults) and events[-3:] == ["reset_faults", "rearm", "deactivate"]
